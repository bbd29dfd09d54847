"""``hf-specvla benchmark``: re-time a toy pipeline a previous ``demo`` saved (strict chains and relaxed r)."""

from __future__ import annotations

from .common import NON_NEGATIVE, POSITIVE, check_bin_tolerances, usage_errors

NAME = "benchmark"
HELP = "benchmark a pipeline saved by `demo`"
EXAMPLES = """
    # Re-run only the benchmark on a pipeline a previous demo saved
    hf-specvla benchmark --pipeline-dir policies/toy_dot --chain-lengths 2 4 6 --bin-tolerances 1 2 4
    # Eager rows only (no compilation)
    hf-specvla benchmark --pipeline-dir policies/toy_dot --no-compile
"""


def add_benchmark_arguments(parser) -> None:
    """The timing options ``demo`` and ``benchmark`` share."""
    parser.add_argument("--chain-lengths", type=POSITIVE, nargs="+", default=[2, 4, 6], help="strict chains k to time")
    parser.add_argument(
        "--bin-tolerances", type=NON_NEGATIVE, nargs="+", default=[1, 2, 4], help="relaxed r to time (k=6)"
    )
    parser.add_argument("--prompts", type=POSITIVE, default=48, help="held-out toy scenes to decode (of 256)")
    parser.add_argument("--repeats", type=POSITIVE, default=3, help="timed passes over the prompts")
    parser.add_argument("--threads", type=POSITIVE, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--seed", type=int, default=0, help="random seed")
    parser.add_argument(
        "--no-compile",
        dest="compile",
        action="store_false",
        help="skip the compiled rows (transformers' greedy:compile and the chains :compile, on a "
        "static cache; they compile on first use, off the clock)",
    )


def add_arguments(parser) -> None:
    parser.add_argument(
        "--pipeline-dir",
        required=True,
        help="a toy pipeline: policies/toy_dot (shipped) or one `hf-specvla demo --train` saved",
    )
    add_benchmark_arguments(parser)


def load_pipeline(pipeline_dir: str, parser):
    """The toy pipeline a previous `demo` saved in ``pipeline_dir``; a usage error when there is none."""
    from ..benchmarks.toy import load_toy_pipeline

    with usage_errors(parser, "--pipeline-dir", (FileNotFoundError,)):
        return load_toy_pipeline(pipeline_dir)


def time_pipeline(pipeline, args) -> tuple[list, str]:
    """The strict / relaxed table on held-out toy scenes, methods interleaved: (the results, the table with its
    heading)."""
    import torch

    from ..benchmarks.speed import format_report, run_benchmark, speculative_methods
    from ..benchmarks.toy import ACTION_DIM, early_exit_assistant, split_scenes, toy_inputs

    scenes = split_scenes()[1]  # never seen by the target's or the draft head's training
    step = max(1, len(scenes) // args.prompts)
    device = pipeline.target.device  # demo --device
    prompts = [
        {name: value.to(device) for name, value in toy_inputs([s], pipeline.tokenizer).items()}
        for s in scenes[step // 2 :: step][: args.prompts]
    ]
    compiled_on = pipeline.target.device.type if args.compile else None
    # transformers' own assisted generation beside ours, with a 1-layer early exit of the target as its small model
    assistant = early_exit_assistant(pipeline.target)
    methods = speculative_methods(
        pipeline.draft_head, args.chain_lengths, args.bin_tolerances, compiled_on=compiled_on, assistant_model=assistant
    )
    results = run_benchmark(
        pipeline.target, prompts, methods, ACTION_DIM, pipeline.action_tokenizer, repeats=args.repeats, seed=args.seed
    )
    heading = (
        f"{len(prompts)} held-out prompts x {args.repeats} repeats, {ACTION_DIM} action tokens each, "
        f"{torch.get_num_threads()} CPU threads, methods interleaved in random order:"
    )
    return results, f"{heading}\n\n{format_report(results)}"


def run(args, parser) -> int:
    pipeline = load_pipeline(args.pipeline_dir, parser)
    given = f"--bin-tolerances {' '.join(map(str, args.bin_tolerances))}"
    check_bin_tolerances(args.bin_tolerances, pipeline.action_tokenizer.n_bins, given, parser)  # before any timing
    _, report = time_pipeline(pipeline, args)
    print(f"\n{report}")
    return 0
