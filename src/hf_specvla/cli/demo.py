"""``hf-specvla demo``: the main job. Build and train a toy OpenVLA-style target and its draft head on the spot
(nothing downloaded), then time plain greedy against speculative decoding: strict and relaxed chains on held-out
scenes, and drafts from previous actions / the head / both on moving-dot episodes."""

from __future__ import annotations

from .benchmark import add_benchmark_arguments, time_pipeline
from .common import NON_NEGATIVE, check_output_dir_flag, usage_errors

NAME = "demo"
HELP = "train a toy VLA target + draft head on the spot and benchmark them"
EXAMPLES = """
    # The main job: build and train a toy OpenVLA-style target and a draft head on the spot, then benchmark
    # plain greedy (eager and compiled) vs speculative decoding (strict and relaxed). About 5 minutes on 2 CPU cores,
    # half of it compiling the compiled rows (--no-compile skips them).
    hf-specvla demo

    # The same, with a bigger (slower, more VLA-like) target, more timing repeats, kept in ./runs/toy-medium
    hf-specvla demo --size medium --repeats 5 --output-dir runs/toy-medium
"""

SIZES = {
    "small": dict(
        hidden_size=128, num_hidden_layers=4, num_attention_heads=4, num_key_value_heads=2, intermediate_size=256
    ),
    "medium": dict(
        hidden_size=256, num_hidden_layers=8, num_attention_heads=8, num_key_value_heads=4, intermediate_size=688
    ),
}


def add_arguments(parser) -> None:
    parser.add_argument(
        "--output-dir", default="runs/toy", help="where target and draft head are kept (reused: same settings)"
    )
    parser.add_argument("--size", choices=sorted(SIZES), default="small", help="toy target size")
    parser.add_argument("--target-steps", type=int, default=300, help="toy target training steps")
    parser.add_argument("--draft-steps", type=int, default=800, help="draft head training steps")
    parser.add_argument(
        "--overwrite-output-dir", action="store_true", help="move a pipeline built with other settings aside"
    )
    parser.add_argument(
        "--episodes", type=NON_NEGATIVE, default=16, help="moving-dot episodes to replay (0: skip that table)"
    )
    add_benchmark_arguments(parser)


def time_episodes(pipeline, args) -> None:
    """The demo's second table: moving-dot episodes, so that the action prior has previous actions to draft."""
    from ..benchmarks.speed import (
        episode_methods,
        format_episode_report,
        run_episode_benchmark,
        toy_actor,
        toy_episodes,
    )
    from ..benchmarks.toy import ACTION_DIM
    from ..speculative import DraftTreeConfig

    tolerances = [0, *args.bin_tolerances[:1]]
    compiled_on = pipeline.target.device.type if args.compile else None
    methods = episode_methods(pipeline.draft_head, tolerances, DraftTreeConfig(), ACTION_DIM - 1, compiled_on)
    episodes = toy_episodes(args.episodes)
    results = run_episode_benchmark(toy_actor(pipeline), episodes, methods, ACTION_DIM, seed=args.seed)
    print(
        f"\n{len(episodes)} moving-dot episodes ({sum(map(len, episodes))} steps): drafts from the previous actions "
        f"(prior), the draft head (chain / EAGLE-2 tree) or both, interleaved at every step:\n"
    )
    print(format_episode_report(results))


def run(args, parser) -> int:
    from ..benchmarks.toy import ToyTargetSize, build_toy_pipeline

    check_output_dir_flag(args.output_dir, parser)
    with usage_errors(parser, errors=(FileExistsError,)):
        size = ToyTargetSize(**SIZES[args.size])
        pipeline = build_toy_pipeline(args.output_dir, size, args.target_steps, args.draft_steps, seed=args.seed,
                                      overwrite=args.overwrite_output_dir)  # fmt: skip
    time_pipeline(pipeline, args)
    if args.episodes:
        time_episodes(pipeline, args)
    return 0
