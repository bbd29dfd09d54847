"""``hf-specvla demo``: the main job. Build and train a toy OpenVLA-style target and its draft head on the spot (no
model or data downloaded), then time plain greedy against speculative decoding: strict and relaxed chains on held-out
scenes, and drafts from previous actions / the head / both on moving-dot episodes. It ends with a verdict (the rows a
newcomer needs, read from the measurements: [`format_verdict`]); the full tables go to ``<output-dir>/demo_report.md``.
"""

from __future__ import annotations

from pathlib import Path

from .benchmark import add_benchmark_arguments, time_pipeline
from .common import NON_NEGATIVE, check_output_dir_flag, usage_errors

NAME = "demo"
HELP = "train a toy VLA target + draft head on the spot and benchmark them"
EXAMPLES = """
    # The main job: build and train a toy OpenVLA-style target and a draft head on the spot, then benchmark
    # plain greedy (eager and compiled) vs speculative decoding (strict and relaxed), ending with a verdict; the full
    # tables go to runs/toy/demo_report.md. ~17 minutes on one CPU thread, training included (the target ~5 min,
    # its draft head ~6: 4800 steps), 2 min of it compiling the compiled rows (--no-compile skips them).
    hf-specvla demo

    # A quick look at a pipeline already trained in runs/toy: few prompts, two episodes, one relaxed r, no compiled rows
    hf-specvla demo --prompts 4 --repeats 1 --episodes 2 --chain-lengths 4 --bin-tolerances 1 --no-compile

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
    parser.add_argument("--target-steps", type=int, default=1500, help="toy target training steps")
    parser.add_argument("--draft-steps", type=int, default=4800, help="draft head training steps")
    parser.add_argument(
        "--overwrite-output-dir", action="store_true", help="move a pipeline built with other settings aside"
    )
    parser.add_argument(
        "--episodes", type=NON_NEGATIVE, default=16, help="moving-dot episodes to replay (0: skip that table)"
    )
    add_benchmark_arguments(parser)


#: the file in the run's folder that holds the demo's full tables
REPORT_FILE = "demo_report.md"


def time_episodes(pipeline, args) -> tuple[list, str]:
    """The demo's second table: moving-dot episodes, so that the action prior has previous actions to draft: (the
    results, the tables with their heading: speed, where the time goes, Jacobi guesses, accepted drafts by position)."""
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
    heading = (
        f"{len(episodes)} moving-dot episodes ({sum(map(len, episodes))} steps): drafts from the previous actions "
        f"(prior), the draft head (chain / EAGLE-2 tree) or both, interleaved at every step:"
    )
    return results, f"{heading}\n\n{format_episode_report(results)}"


def write_report(output_dir: str, sections: list[str], verdict: str, argv: list[str]) -> Path:
    """Writes the full tables and the verdict to ``output_dir/demo_report.md`` (replaced whole: a crash leaves the
    previous report), holding the folder's lock (see ``hf_specvla.run_folder``). Returns the file's path."""
    import os

    from ..run_folder import lock_folder

    command = " ".join(["hf-specvla", *argv])
    text = "\n\n".join([f"# `{command}`", *sections, "## Verdict", verdict]) + "\n"
    with lock_folder(output_dir) as run:
        temporary = run.bound / f".{REPORT_FILE}.tmp"
        temporary.write_text(text)
        os.replace(temporary, run.bound / REPORT_FILE)
    return Path(output_dir) / REPORT_FILE


def _count(number: int, noun: str) -> str:
    return f"{number} {noun}{'' if number == 1 else 's'}"


def run(args, parser) -> int:
    import torch

    from ..benchmarks.speed import format_verdict
    from ..benchmarks.toy import ACTION_DIM, ToyTargetSize, build_toy_pipeline

    check_output_dir_flag(args.output_dir, parser)
    with usage_errors(parser, errors=(FileExistsError,)):
        size = ToyTargetSize(**SIZES[args.size])
        pipeline = build_toy_pipeline(args.output_dir, size, args.target_steps, args.draft_steps, seed=args.seed,
                                      overwrite=args.overwrite_output_dir)  # fmt: skip
    results, scenes = time_pipeline(pipeline, args)
    sections = [f"## Held-out scenes\n\n{scenes}"]
    measured = f"{_count(len(results[0].latencies), 'action')} on held-out scenes"
    if args.episodes:
        results, episodes = time_episodes(pipeline, args)  # the verdict reads these: the previous action drafts
        sections.append(f"## Moving-dot episodes\n\n{episodes}")
        measured = f"{_count(len(results[0].latencies), 'action')} of {_count(args.episodes, 'moving-dot episode')}"
    verdict = format_verdict(results, ACTION_DIM)
    report = write_report(args.output_dir, sections, verdict, getattr(args, "argv", ["demo"]))
    print(
        f"\nVerdict ({measured}, {_count(torch.get_num_threads(), 'CPU thread')}; a toy target: the README has a "
        f"real policy's figures):\n\n{verdict}\n\nThe full tables (every method, Jacobi guesses, accepted drafts "
        f"by token position): {report}"
    )
    return 0
