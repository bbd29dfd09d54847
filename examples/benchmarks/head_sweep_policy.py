"""Draft-head chain lengths and EAGLE-2 tree sizes on a Meta-World policy's recorded rollouts (one thread,
interleaved, r=0): which drafting pays best for that policy and head.

    python examples/benchmarks/head_sweep_policy.py --policy policies/mt10_vla3 --draft-head policies/mt10_vla3_draft_v2

Prints the episode-benchmark table (speed-up, target forwards per call, tokens per target forward) and where the
time goes per setting.
"""

from __future__ import annotations

import argparse

import torch

from hf_specvla import DraftHead, DraftHeadDrafter, DraftTreeConfig
from hf_specvla.benchmarks.speed import (
    EpisodeMethod,
    ForwardClock,
    format_episode_report,
    policy_actor,
    run_episode_benchmark,
)
from hf_specvla.metaworld.evaluation import record_observations
from hf_specvla.metaworld.seeds import BENCH_SEED_START
from hf_specvla.policies import VLAPolicy

TREES = ((2, 4, 8), (3, 4, 12), (4, 6, 24))  # (top_k, depth, total_tokens)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", required=True)
    parser.add_argument("--draft-head", required=True)
    parser.add_argument("--tasks", nargs="+", default=["MT10"])
    parser.add_argument("--steps", type=int, default=20, help="recorded calls per task")
    parser.add_argument("--chain-lengths", type=int, nargs="+", default=[2, 3, 4, 5, 7])
    args = parser.parse_args(argv)
    if args.steps < 1 or min(args.chain_lengths) < 1:
        parser.error("--steps and --chain-lengths must be >= 1")
    torch.set_num_threads(1)
    policy = VLAPolicy.from_pretrained(args.policy)
    head = DraftHead.from_pretrained(args.draft_head).eval()
    policy.check_draft_head(head)
    methods = [EpisodeMethod("greedy")]
    methods += [
        EpisodeMethod(f"chain k={k}", dict(assistant_model=DraftHeadDrafter(head, k))) for k in args.chain_lengths
    ]
    for top_k, depth, total in TREES:
        tree = DraftTreeConfig(top_k=top_k, depth=depth, total_tokens=total)
        methods.append(
            EpisodeMethod(f"tree {top_k}/{depth}/{total}", dict(assistant_model=DraftHeadDrafter(head, tree=tree)))
        )
    episodes = record_observations(policy, args.tasks, [BENCH_SEED_START], args.steps)
    results = run_episode_benchmark(policy_actor(policy), episodes, methods, policy.config.action_tokens,
                                    clock=ForwardClock(policy.model))  # fmt: skip
    print(format_episode_report(results))


if __name__ == "__main__":
    main()
