"""Does a Meta-World policy read its image, or copy its proprio state? (causal confusion / "copycat" check)

    python examples/copycat_check.py --policy policies/mt10_vla --data runs/mt10_demos_hs
    python examples/copycat_check.py --policy runs/mt10_vla --data runs/mt10_demos --tasks reach push --pairs 5

For pairs of demonstrations of the same task (seeds a, b) at the same step, it predicts the action from
(image a, state a), (image b, state a) and (image a, state b), and reports per task the mean change of the xyz
action (in [-1, 1] units) when only the image is swapped and when only the state is swapped, next to how much
the two experts' actions differ. A policy that reads the goal from the image moves with the image; a copycat
moves only with the state. Only reads the dataset and the policy (no simulator).
"""

import argparse
import itertools
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from hf_specvla.metaworld.demonstrations import collected_seeds, dataset_info, decode_png, episode_path
from hf_specvla.metaworld.env import resolve_tasks
from hf_specvla.policies import VLAPolicy


def load_episode(path):
    table = pq.read_table(path).to_pydict()
    images = [decode_png(png) for png in table["image"]]
    return images, np.asarray(table["state"], np.float32), np.asarray(table["action"]), table["instruction"][0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", required=True, help="a policy folder")
    parser.add_argument("--data", required=True, help="a dataset folder written by `hf-specvla collect`")
    parser.add_argument("--tasks", nargs="+", default=["MT10"], help="suites or task names")
    parser.add_argument("--pairs", type=int, default=3, help="episode pairs per task")
    parser.add_argument("--steps", type=int, nargs="+", default=[0, 5, 15], help="steps compared in each pair")
    args = parser.parse_args()

    policy = VLAPolicy.from_pretrained(args.policy)
    if dataset_info(args.data)["camera"] != policy.config.camera:
        parser.error(f"{args.data} was rendered from another camera than the policy's {policy.config.camera!r}")

    def act(image, instruction, state):
        actions = policy.predict_action(image, instruction, state if policy.config.use_state else None)
        return policy.action_steps(actions)[0][:3]  # a chunked policy: the chunk's first action

    print("| task | image swapped | state swapped | experts differ |\n|---|---:|---:|---:|")
    for task in resolve_tasks(args.tasks):
        seeds = collected_seeds(Path(args.data), task)[: 2 * args.pairs]
        episodes = [load_episode(episode_path(Path(args.data), task, seed)) for seed in seeds]
        image_change, state_change, expert_change = [], [], []
        for a, b in itertools.islice(zip(episodes[::2], episodes[1::2]), args.pairs):
            for step in args.steps:
                if step >= min(len(a[0]), len(b[0])):
                    continue
                base = act(a[0][step], a[3], a[1][step])
                image_change.append(np.abs(act(b[0][step], a[3], a[1][step]) - base).mean())
                state_change.append(np.abs(act(a[0][step], a[3], b[1][step]) - base).mean())
                expert_change.append(np.abs(a[2][step][:3] - b[2][step][:3]).mean())
        if expert_change:
            print(
                f"| {task} | {np.mean(image_change):.2f} | {np.mean(state_change):.2f} | {np.mean(expert_change):.2f} |"
            )


if __name__ == "__main__":
    main()
