"""``hf-specvla``: the command line.

Examples:

    # The main job: build and train a toy OpenVLA-style target and a draft head on the spot, then benchmark
    # plain greedy vs speculative decoding (strict and relaxed). About 2 minutes on 2 CPU cores.
    hf-specvla demo

    # The same, with a bigger (slower, more VLA-like) target, more timing repeats, kept in ./runs/toy-medium
    hf-specvla demo --size medium --repeats 5 --output-dir runs/toy-medium

    # Re-run only the benchmark on a pipeline a previous demo saved
    hf-specvla benchmark --pipeline-dir runs/toy --chain-lengths 2 4 6 --bin-tolerances 1 2 4
"""

from __future__ import annotations

import argparse
import logging
import sys

import torch

EXAMPLES = __doc__.split("Examples:", 1)[1]

SIZES = {
    "small": dict(
        hidden_size=128, num_hidden_layers=4, num_attention_heads=4, num_key_value_heads=2, intermediate_size=256
    ),
    "medium": dict(
        hidden_size=256, num_hidden_layers=8, num_attention_heads=8, num_key_value_heads=4, intermediate_size=688
    ),
}


def _add_benchmark_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--chain-lengths", type=int, nargs="+", default=[2, 4, 6], help="strict chains k to time")
    parser.add_argument("--bin-tolerances", type=int, nargs="+", default=[1, 2, 4], help="relaxed r to time (k=6)")
    parser.add_argument("--prompts", type=int, default=48, help="held-out toy scenes to decode (of 256)")
    parser.add_argument("--repeats", type=int, default=3, help="timed passes over the prompts")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--seed", type=int, default=0)


def _benchmark(pipeline, args) -> None:
    from .benchmark import format_report, run_benchmark, speculative_methods
    from .toy import ACTION_DIM, split_scenes, toy_inputs

    scenes = split_scenes()[1]  # never seen by the target's or the draft head's training
    step = max(1, len(scenes) // args.prompts)
    prompts = [toy_inputs([s], pipeline.tokenizer) for s in scenes[step // 2 :: step][: args.prompts]]
    methods = speculative_methods(pipeline.draft_head, args.chain_lengths, args.bin_tolerances)
    results = run_benchmark(
        pipeline.target, prompts, methods, ACTION_DIM, pipeline.action_tokenizer, repeats=args.repeats, seed=args.seed
    )
    print(
        f"\n{len(prompts)} prompts x {args.repeats} repeats, {ACTION_DIM} action tokens each, "
        f"{torch.get_num_threads()} CPU threads, methods interleaved in random order:\n"
    )
    print(format_report(results))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="hf-specvla",
        description="Draft-head speculative decoding with relaxed action acceptance for VLA models.",
        epilog="examples:" + EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    commands = parser.add_subparsers(dest="command", required=True)

    demo = commands.add_parser(
        "demo", help="train a toy VLA target + draft head on the spot and benchmark them",
        epilog="examples:" + EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    demo.add_argument(
        "--output-dir", default="runs/toy", help="where target and draft head are kept (reused if present)"
    )
    demo.add_argument("--size", choices=sorted(SIZES), default="small", help="toy target size")
    demo.add_argument("--target-steps", type=int, default=300)
    demo.add_argument("--draft-steps", type=int, default=800)
    _add_benchmark_arguments(demo)

    bench = commands.add_parser(
        "benchmark", help="benchmark a pipeline saved by `demo`",
        epilog="examples:" + EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    bench.add_argument("--pipeline-dir", required=True, help="a folder written by `hf-specvla demo`")
    _add_benchmark_arguments(bench)

    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s"
    )
    if args.threads:
        torch.set_num_threads(args.threads)

    from pathlib import Path

    from .toy import ToyTargetSize, build_toy_pipeline

    if args.command == "demo":
        pipeline = build_toy_pipeline(
            args.output_dir, ToyTargetSize(**SIZES[args.size]), args.target_steps, args.draft_steps, seed=args.seed
        )
    else:
        root = Path(args.pipeline_dir)
        if not (root / "target" / "config.json").exists() or not (root / "draft_head" / "config.json").exists():
            parser.error(f"--pipeline-dir {str(root)!r} has no target/ and draft_head/ saved by `hf-specvla demo`")
        pipeline = build_toy_pipeline(str(root))
    _benchmark(pipeline, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
