"""Where a draft head's drafts fail, per token of a policy call: what bounds lossless drafting.

On greedy rollouts of a policy (held-out seeds), for each generated token k of a call (a0.x ... a1.gripper) and each
draft head given, teacher-forced (the head sees the right earlier tokens, as in a chain whose drafts were right):

* ``head top-1 / top-4``: the target's greedy token is the head's first choice / among its 4 first (what a chain /
  an EAGLE-2 tree level of width 4 can accept);
* ``chain``: the head drafting from the root after the prefill (its own features from the second draft on, as it
  drafts): its draft of token k is right;
* ``copy``: the robot's previous action at that dimension is the token (the action prior's draft);
* ``target p(top-1)``: the median probability the target gives its own greedy token: a flat distribution means
  greedy's choice is a near-tie that a cheaper model rarely reproduces.

    python examples/benchmarks/head_bound.py --policy policies/mt10_vla3 \\
        --draft-heads policies/mt10_vla3_draft policies/mt10_vla3_draft_v2 --tasks MT10 --seeds 400011 --steps 150
    python examples/benchmarks/head_bound.py --tiny     # seconds: what CI runs (an untrained head, asserts nothing)
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from hf_specvla import ActionNormalizer, DraftHead
from hf_specvla.metaworld.env import TASK_INSTRUCTIONS
from hf_specvla.metaworld.evaluation import record_observations
from hf_specvla.policies import VLAPolicy, VLAPolicyConfig
from hf_specvla.training.draft_head import (
    build_distillation_dataset,
    collate_distillation,
    dataset_hidden_layers,
    unrolled_features,
)
from hf_specvla.training.policy_draft import policy_prompts

POSITION_NAMES = ("x", "y", "z", "grip")


def frames_of(policy: VLAPolicy, tasks: list[str], seeds: list[int], steps: int, tiny: bool) -> list[dict]:
    """The policy's greedy rollouts' frames (each with its previous action), or random frames for ``--tiny``."""
    if not tiny:
        return [frame for episode in record_observations(policy, tasks, seeds, steps) for frame in episode]
    rng = np.random.default_rng(0)
    frames, previous = [], None
    for _ in range(6):
        image = rng.integers(0, 256, (policy.config.image_size,) * 2 + (3,), dtype=np.uint8)
        state = rng.uniform(-1, 1, policy.config.state_dim)
        frames.append({"image": image, "instruction": TASK_INSTRUCTIONS["reach-v3"], "state": state,
                       "previous_action": previous})  # fmt: skip
        previous = list(policy.action_token_ids(rng.uniform(-1, 1, (1, 4)))[0])
    return frames


@torch.no_grad()
def head_rows(policy: VLAPolicy, head: DraftHead, frames: list[dict]) -> list[dict]:
    """One row per generated token k >= 1 (the prefill makes token 0): the rates above."""
    tokens = policy.config.action_tokens
    dataset = build_distillation_dataset(policy.model, policy_prompts(policy, frames, 32), tokens,
                                         policy.action_tokenizer, progress=False, action_dim=policy.config.action_dim,
                                         hidden_state_layers=head.config.hidden_state_layers)  # fmt: skip
    batch = collate_distillation(list(dataset))
    handles = head.target_handles(policy.model)
    width, layers = head.config.hidden_size, head.config.hidden_state_layers
    top = dataset_hidden_layers(layers).index(-1)
    hidden = batch["hidden"]
    features = unrolled_features(head, handles, batch, hidden[:, :-1, : len(layers) * width], tokens - 1)
    target_logits = handles.lm_head(hidden[:, 1:, top * width : (top + 1) * width])  # [B, T, V]: token p + 2
    target_ids, target_top = target_logits.argmax(-1), target_logits.softmax(-1).max(-1).values
    first = batch["first_position"][:, 0]  # one prompt length per batch of frames: rows may differ
    rows_index = torch.arange(len(first))
    has_previous = (batch["previous_action"] >= 0).all(1)
    rows = []
    for k in range(1, tokens):
        p = first - 2 + k  # the input that predicts generated token k, teacher-forced
        right = target_ids[rows_index, p]
        logits = handles.lm_head(features[0][rows_index, p])
        rank = (logits > logits.gather(1, right[:, None])).sum(1)
        root = first - 1  # the root after the prefill; its step k - 1 drafts token k
        chain = handles.lm_head(features[k - 1][rows_index, root]).argmax(-1) == target_ids[rows_index, root + k - 1]
        copy = batch["previous_action"][:, k % policy.config.action_dim] == right
        rows.append({
            "token": f"a{k // policy.config.action_dim}.{POSITION_NAMES[k % policy.config.action_dim]}",
            "head_top1": (rank < 1).float().mean().item(), "head_top4": (rank < 4).float().mean().item(),
            "chain": chain.float().mean().item(),
            "copy": copy[has_previous].float().mean().item() if bool(has_previous.any()) else None,
            "target_top1_probability": target_top[rows_index, p].median().item(),
        })  # fmt: skip
    return rows


def tiny_policy() -> VLAPolicy:
    unit = ActionNormalizer(-np.ones(4), np.ones(4))
    config = VLAPolicyConfig(text_layers=2, text_hidden_size=12, chunk_length=2)
    return VLAPolicy.build(list(TASK_INSTRUCTIONS.values()), unit, unit, config, seed=0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", default="policies/mt10_vla3", help="a policy folder")
    parser.add_argument("--draft-heads", nargs="+", default=["policies/mt10_vla3_draft"], help="DraftHead folders")
    parser.add_argument("--tasks", nargs="+", default=["MT10"], help="suites and/or task names")
    parser.add_argument("--seeds", nargs="+", type=int, default=[400011], help="rollout seeds (held out of training)")
    parser.add_argument("--steps", type=int, default=150, help="policy calls kept per rollout")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--output", default=None, help="write the rows as JSON here")
    parser.add_argument("--tiny", action="store_true", help="a tiny random policy and head (CI: runs, asserts nothing)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    policy = tiny_policy() if args.tiny else VLAPolicy.from_pretrained(args.policy)
    frames = frames_of(policy, args.tasks, args.seeds, args.steps, args.tiny)
    heads = {
        "untrained v2": DraftHead.from_target(policy.model, policy.action_tokenizer, 4, previous_action_input=True)
    }
    if not args.tiny:
        heads = {folder: DraftHead.from_pretrained(folder) for folder in args.draft_heads}
    results = {}
    print(f"\n{len(frames)} frames ({', '.join(args.tasks)}; seeds {args.seeds}; {args.steps} calls per rollout)\n")
    print("| head | token | head top-1 | head top-4 | chain from the prefill | copy previous | target p(top-1) |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for name, head in heads.items():
        results[name] = head_rows(policy, head.eval(), frames)
        for row in results[name]:
            copy = "-" if row["copy"] is None else f"{row['copy']:.0%}"
            print(f"| {name} | {row['token']} | {row['head_top1']:.0%} | {row['head_top4']:.0%} | {row['chain']:.0%} | "
                  f"{copy} | {row['target_top1_probability']:.2f} |")  # fmt: skip
    if args.output:
        Path(args.output).write_text(json.dumps({"settings": vars(args), "frames": len(frames), "heads": results},
                                                indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
