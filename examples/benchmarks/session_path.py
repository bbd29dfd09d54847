"""What a policy's decoder session saves (issue 75 item 4): one Meta-World policy's calls through ``model.generate``
against the same calls through the policy's ``DecoderSession`` (``generate``'s set-up done once per shape), greedy
and speculative, so that a speed-up from skipping set-up is not mistaken for one from speculation.

Greedy episodes are rolled out first (``--tasks`` x ``--episodes`` from ``--seed-start``, off the clock), keeping every
call's observation and the episode's previous actions; then each observation is decoded by every path below, the
paths in a fresh random order per observation (one process, ``--threads`` threads, every path compiled):

* ``greedy:compile``: transformers' compiled greedy decoding (``generate``), the baseline;
* ``none:compile session``: greedy decoding through hf_specvla's engine and the policy's session (``NoDrafter``: one
  token a verification): what the session's path alone saves;
* ``exact generate``: ``exact`` (the previous action drafted, Jacobi guesses, compiled) through ``model.generate``;
* ``exact session``: the same through the policy's session (what ``predict_action`` runs by default).

Per path: the median ms per call, the ratio of greedy:compile's total time to its total time over the same calls
(the compare's "total decode time"), target forwards per call, and calls whose action tokens differ from greedy's.

    python examples/benchmarks/session_path.py --json runs/session_path.json
    python examples/benchmarks/session_path.py --policy policies/mt10_vla3 --tasks reach-v3 push-v3 --episodes 2
    python examples/benchmarks/session_path.py --tiny      # a random tiny policy, a few calls: what CI runs
"""

from __future__ import annotations

import argparse
import json
import random
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from hf_specvla.metaworld.env import TASK_INSTRUCTIONS, EnvConfig, MetaWorldEnv
from hf_specvla.metaworld.rollout import rollout
from hf_specvla.policies import VLAPolicy
from hf_specvla.policies.decoding_methods import DecodingMethod

#: path name -> (method, through the policy's decoder session)
PATHS = {
    "greedy:compile": ("greedy:compile", False),
    "none:compile session": ("none:compile", True),
    "exact generate": ("exact", False),
    "exact session": ("exact", True),
}


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n")[-1],
                                     formatter_class=argparse.RawTextHelpFormatter)  # fmt: skip
    parser.add_argument("--policy", default="policies/mt10_vla3", help="a policy folder (default: %(default)s)")
    parser.add_argument(
        "--tasks",
        nargs="+",
        default=["reach-v3", "push-v3", "drawer-open-v3", "window-close-v3"],
        choices=sorted(TASK_INSTRUCTIONS),
        metavar="TASK",
        help="Meta-World tasks (default: 4)",
    )
    parser.add_argument("--episodes", type=int, default=1, help="episodes a task (default: %(default)s)")
    parser.add_argument("--seed-start", type=int, default=100000, help="the first seed (default: %(default)s)")
    parser.add_argument("--max-episode-steps", type=int, default=150, help="steps an episode at most (default: 150)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default: %(default)s)")
    parser.add_argument("--json", type=Path, help="write the table's rows here")
    parser.add_argument("--tiny", action="store_true", help="a random tiny policy, 1 task, 6 steps (seconds)")
    args = parser.parse_args(argv)
    for name in ("episodes", "max_episode_steps", "threads"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.json is not None and args.json.exists():
        parser.error(f"--json {args.json} exists: nothing a run wrote is overwritten; pass a new path")
    return args


def tiny_policy() -> VLAPolicy:
    from hf_specvla.actions.tokenizer import ActionNormalizer
    from hf_specvla.policies import VLAPolicyConfig

    unit = ActionNormalizer(-np.ones(4), np.ones(4))
    config = VLAPolicyConfig(text_layers=2, text_hidden_size=48, vision_layers=1, vision_hidden_size=32)
    return VLAPolicy.build(list(TASK_INSTRUCTIONS.values()), unit, unit, config, seed=0)


def greedy_calls(policy: VLAPolicy, tasks, episodes: int, seed_start: int, max_steps: int) -> list[dict]:
    """Every call of greedy episodes: its observation and the episode's previous actions (token ids) before it."""
    calls: list[dict] = []
    for task in tasks:
        env = MetaWorldEnv(task, EnvConfig(policy.config.image_size, policy.config.camera, max_steps))
        for seed in range(seed_start, seed_start + episodes):
            policy.reset()

            def decide(rows, observations):
                obs = observations[0]
                calls.append({"obs": obs, "history": [list(a) for a in policy.previous_action_ids]})
                return [policy.action_steps(policy.predict_action(obs["image"], obs["instruction"], obs["state"]))]

            rollout([env], [seed], decide)
        env.close()
    return calls


def run(args: argparse.Namespace) -> list[dict]:
    torch.set_num_threads(args.threads)
    policy = tiny_policy() if args.tiny else VLAPolicy.from_pretrained(args.policy)
    tasks, episodes, steps = args.tasks, args.episodes, args.max_episode_steps
    if args.tiny:
        tasks, episodes, steps = tasks[:1], 1, 6
    calls = greedy_calls(policy, tasks, episodes, args.seed_start, steps)
    device, dim = policy.model.device.type, policy.config.action_dim
    plans = {path: DecodingMethod.parse(method).plan(None, device, None, dim) for path, (method, _) in PATHS.items()}
    tokens = policy.config.action_tokens

    def decode(path: str, call: dict) -> tuple[float, list[int], int]:
        policy.decoder_sessions = PATHS[path][1]
        policy.previous_action_ids = [list(a) for a in call["history"]]
        obs = call["obs"]
        start = time.perf_counter()
        _, output = policy.predict_action(obs["image"], obs["instruction"], obs["state"], return_output=True,
                                          decoding=plans[path])  # fmt: skip
        seconds = time.perf_counter() - start
        stats = getattr(output, "speculation", None)
        return seconds, output.sequences[0, -tokens:].tolist(), tokens if stats is None else stats.num_target_forwards

    warm_up = [c for task in dict.fromkeys(c["obs"]["instruction"] for c in calls)
               for c in [d for d in calls if d["obs"]["instruction"] == task][:3]]  # fmt: skip
    for path in PATHS:  # compiled off the clock: every path's graphs, on each task's first calls (its prompt shape)
        for call in warm_up:
            decode(path, call)
    times = {path: [] for path in PATHS}
    forwards = {path: 0 for path in PATHS}
    differ = {path: 0 for path in PATHS}
    order = list(PATHS)
    for call in calls:
        random.shuffle(order)
        results = {path: decode(path, call) for path in order}
        for path, (seconds, ids, count) in results.items():
            times[path].append(seconds)
            forwards[path] += count
            differ[path] += ids != results["greedy:compile"][1]
    baseline = sum(times["greedy:compile"])
    return [
        {"path": path, "calls": len(calls), "median_ms": round(1000 * statistics.median(times[path]), 2),
         "vs_greedy_compile_total": round(baseline / sum(times[path]), 3),
         "target_forwards_per_call": round(forwards[path] / len(calls), 2), "calls_unlike_greedy": differ[path]}
        for path in PATHS
    ]  # fmt: skip


def main(argv=None) -> None:
    args = parse_args(argv)
    rows = run(args)
    print("| path | calls | ms a call (median) | vs greedy:compile (total) | target fwd / call | unlike greedy |")
    print("|---|---:|---:|---:|---:|---:|")
    for row in rows:
        print(f"| {row['path']} | {row['calls']} | {row['median_ms']} | {row['vs_greedy_compile_total']:.3f}x | "
              f"{row['target_forwards_per_call']} | {row['calls_unlike_greedy']} |")  # fmt: skip
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
