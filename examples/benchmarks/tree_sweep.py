"""EAGLE-2 tree settings against the chain on the toy target's moving-dot episodes (head only, one thread): the
table "EAGLE-2 tree settings on the toy" in docs/benchmarks.md. Needs `hf-specvla demo --output-dir runs/toy`.

    python examples/benchmarks/tree_sweep.py runs/toy
"""

import sys

import torch

from hf_specvla import DraftHeadDrafter, DraftTreeConfig
from hf_specvla.benchmarks.speed import (
    EpisodeMethod,
    format_episode_report,
    run_episode_benchmark,
    toy_actor,
    toy_episodes,
)
from hf_specvla.benchmarks.toy import ACTION_DIM, load_toy_pipeline

torch.set_num_threads(1)
pipeline = load_toy_pipeline(sys.argv[1])
head = pipeline.draft_head
methods = [EpisodeMethod("greedy"), EpisodeMethod("chain k=6", dict(assistant_model=DraftHeadDrafter(head, 6)))]
for top_k, total in ((2, 12), (2, 16), (3, 16), (3, 24), (4, 24), (4, 32), (8, 50)):
    tree = DraftTreeConfig(top_k=top_k, depth=6, total_tokens=total)
    methods.append(
        EpisodeMethod(f"tree top_k={top_k} total={total}", dict(assistant_model=DraftHeadDrafter(head, tree=tree)))
    )
print(format_episode_report(run_episode_benchmark(toy_actor(pipeline), toy_episodes(12), methods, ACTION_DIM)))
