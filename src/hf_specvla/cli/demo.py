"""``hf-specvla demo``: the main job. Load the shipped toy OpenVLA-style target and its draft head
(``policies/toy_dot``: nothing downloaded, nothing trained; ``--train`` builds and trains them on the spot instead),
then time plain greedy against speculative decoding: strict and relaxed chains on held-out scenes, and drafts from
previous actions / the head / both on moving-dot episodes. It ends with a verdict (the rows a newcomer needs, read
from the measurements: [`format_verdict`]); the full tables go to ``<output-dir>/demo_report.md``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .benchmark import add_benchmark_arguments, time_pipeline
from .common import NON_NEGATIVE, POSITIVE, add_device_arguments, check_output_dir_flag, resolve_placement, usage_errors

NAME = "demo"
HELP = "benchmark the shipped toy VLA target + draft head (or train them on the spot: --train)"
EXAMPLES = """
    # The main job: time the shipped toy OpenVLA-style target and its draft head (policies/toy_dot) on moving-dot
    # episodes: greedy (eager and compiled), `exact`, `exact` + the head and a relaxed r, ending with a verdict; the
    # tables go to runs/demo/demo_report.md. Run from the checkout; most of its minutes compile the compiled rows.
    hf-specvla demo

    # Every table: also held-out scenes (chains, transformers' assisted generation) and every drafter on the episodes
    hf-specvla demo --all-tables

    # A quick look: two episodes, one relaxed r, no compiled rows
    hf-specvla demo --episodes 2 --bin-tolerances 1 --no-compile

    # On the CPU in float32 (default: auto, a GPU in bfloat16 when torch sees one), in a folder of its own
    hf-specvla demo --episodes 2 --bin-tolerances 1 --no-compile --device cpu --dtype float32 --output-dir runs/demo_cpu

    # The whole pipeline: train the toy target and distil its draft head on the spot (~15 min on one CPU thread),
    # kept in runs/toy, then time them
    hf-specvla demo --train

    # The same with a bigger (slower, more VLA-like) target, more timing repeats, kept in ./runs/toy-medium
    hf-specvla demo --train --size medium --repeats 5 --output-dir runs/toy-medium
"""

SIZES = {
    "small": dict(
        hidden_size=128, num_hidden_layers=4, num_attention_heads=4, num_key_value_heads=2, intermediate_size=256
    ),
    "medium": dict(
        hidden_size=256, num_hidden_layers=8, num_attention_heads=8, num_key_value_heads=4, intermediate_size=688
    ),
}


#: ``--output-dir``'s default: the report of the shipped pipeline's timing; a trained pipeline and its report
OUTPUT_DIRS = {"shipped": "runs/demo", "train": "runs/toy"}
#: the training flags' defaults (``toy.TOY_TARGET_STEPS`` / ``TOY_HEAD_STEPS``, tested): they apply with --train only
TRAINING_DEFAULTS = dict(size="small", target_steps=1500, draft_steps=4800)


def add_arguments(parser) -> None:
    parser.add_argument(
        "--train",
        action="store_true",
        help="build and train the toy target and its draft head on the spot (~15 min on one CPU thread) instead of "
        "timing the shipped ones (policies/toy_dot)",
    )
    parser.add_argument(
        "--output-dir",
        default=None,
        help=f"the report's folder (default {OUTPUT_DIRS['shipped']}); with --train also the trained target and "
        f"head (default {OUTPUT_DIRS['train']}; reused when trained with the same settings)",
    )
    parser.add_argument(
        "--size",
        choices=sorted(SIZES),
        default=argparse.SUPPRESS,
        help=f"toy target size, with --train (default {TRAINING_DEFAULTS['size']})",
    )
    parser.add_argument(
        "--target-steps",
        type=POSITIVE,
        default=argparse.SUPPRESS,
        help=f"toy target training steps, with --train (default {TRAINING_DEFAULTS['target_steps']})",
    )
    parser.add_argument(
        "--draft-steps",
        type=POSITIVE,
        default=argparse.SUPPRESS,
        help=f"draft head training steps, with --train (default {TRAINING_DEFAULTS['draft_steps']})",
    )
    parser.add_argument(
        "--overwrite-output-dir", action="store_true", help="move a folder holding another run's results aside"
    )
    parser.add_argument(
        "--episodes",
        type=NON_NEGATIVE,
        default=16,
        help="moving-dot episodes to replay (0: time the held-out scenes for the verdict instead)",
    )
    parser.add_argument(
        "--all-tables",
        action="store_true",
        help="also the held-out scenes table (chains of --chain-lengths, transformers' assisted generation) and "
        "every drafter on the episodes, not only the verdict's rows (many more graphs to compile)",
    )
    add_benchmark_arguments(parser)
    add_device_arguments(parser)


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
    if not args.all_tables:  # the verdict's rows alone: only their graphs are compiled
        methods = [method for method in methods if method.name in verdict_methods(tolerances[1], args.compile)]
    episodes = toy_episodes(args.episodes)
    results = run_episode_benchmark(toy_actor(pipeline), episodes, methods, ACTION_DIM, seed=args.seed)
    heading = (
        f"{len(episodes)} moving-dot episodes ({sum(map(len, episodes))} steps): drafts from the previous actions "
        f"(prior), the draft head (chain / EAGLE-2 tree) or both, interleaved at every step:"
    )
    return results, f"{heading}\n\n{format_episode_report(results)}"


def verdict_methods(relaxed: int, compiled: bool) -> set[str]:
    """The episode rows the verdict reads (``speed.VERDICT_ROLES``): greedy, eager and compiled, `exact`, `exact` with
    the draft head, and `exact` at the relaxed ``r`` (compiled when ``compiled``; eager greedy always: the baseline
    the others' actions are compared with)."""
    suffix = ":compile" if compiled else ""
    names = {
        "greedy",
        f"prior+jacobi r=0{suffix}",
        f"prior+jacobi+tree r=0{suffix}",
        f"prior+jacobi r={relaxed}{suffix}",
    }
    return names | ({"greedy:compile"} if compiled else set())


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


def training_settings(args, parser) -> dict:
    """``--size`` / ``--target-steps`` / ``--draft-steps`` with their defaults filled in; a usage error when one is
    given without ``--train`` (the shipped pipeline is timed as it is)."""
    given = [f"--{name.replace('_', '-')}" for name in TRAINING_DEFAULTS if hasattr(args, name)]
    if given and not args.train:
        parser.error(f"{', '.join(given)}: only with --train (the shipped toy pipeline is timed as it was trained)")
    return {name: getattr(args, name, default) for name, default in TRAINING_DEFAULTS.items()}


def load_or_train(args, parser):
    """The pipeline to time, on ``--device`` in ``--dtype``: the shipped one (its report in ``--output-dir``, a folder
    of its own), or with ``--train`` the one built and trained in ``--output-dir`` (trained as ``build_toy_pipeline``
    trains, then moved)."""
    from ..benchmarks.toy import ToyTargetSize, build_toy_pipeline, load_toy_pipeline, shipped_toy_dir
    from ..run_folder import RunRecord, claim_run_folder, fingerprint

    settings = training_settings(args, parser)
    args.output_dir = args.output_dir or OUTPUT_DIRS["train" if args.train else "shipped"]
    check_output_dir_flag(args.output_dir, parser)
    placement = resolve_placement(args, parser)  # before anything is trained or written
    if args.train:
        with usage_errors(parser, errors=(FileExistsError,)):
            size = ToyTargetSize(**SIZES[settings["size"]])
            pipeline = build_toy_pipeline(
                args.output_dir,
                size,
                settings["target_steps"],
                settings["draft_steps"],
                seed=args.seed,
                overwrite=args.overwrite_output_dir,
            )
        placement.move(pipeline.target, pipeline.draft_head)
        return pipeline
    shipped = shipped_toy_dir()
    if shipped is None:
        parser.error(
            "the shipped toy pipeline (policies/toy_dot) is not under this folder or this checkout: run "
            "from the hf_specvla checkout, or add --train to build one here (~15 min on one CPU thread)"
        )
    pipeline = load_toy_pipeline(str(shipped))  # a few MB: its weights identify the report's folder
    record = RunRecord("demo", {"target": fingerprint(pipeline.target), "draft_head": fingerprint(pipeline.draft_head)})
    with usage_errors(parser, errors=(FileExistsError,)):  # the report's folder follows the folder rule
        with claim_run_folder(args.output_dir, record, args.overwrite_output_dir):
            pass
    placement.move(pipeline.target, pipeline.draft_head)  # after the record: it names the weights as shipped
    return pipeline


def run(args, parser) -> int:
    import torch

    from ..benchmarks.speed import format_verdict
    from ..benchmarks.toy import ACTION_DIM
    from ..policies.devices import dtype_name

    pipeline = load_or_train(args, parser)
    placement = f"{pipeline.target.device.type} in {dtype_name(pipeline.target.dtype)}"
    sections = []
    if args.all_tables or not args.episodes:  # the held-out scenes: the verdict's rows when there are no episodes
        results, scenes = time_pipeline(pipeline, args)
        sections.append(f"## Held-out scenes\n\n{scenes}")
        measured = f"{_count(len(results[0].latencies), 'action')} on held-out scenes"
    if args.episodes:
        results, episodes = time_episodes(pipeline, args)  # the verdict reads these: the previous action drafts
        sections.append(f"## Moving-dot episodes\n\n{episodes}")
        measured = f"{_count(len(results[0].latencies), 'action')} of {_count(args.episodes, 'moving-dot episode')}"
    verdict = format_verdict(results, ACTION_DIM)
    report = write_report(args.output_dir, sections, verdict, getattr(args, "argv", ["demo"]))
    threads = _count(torch.get_num_threads(), "CPU thread")
    print(
        f"\nVerdict ({measured}, {threads}, on {placement}; a toy target: the README has a real policy's figures):"
        f"\n\n{verdict}\n\nThe full tables (every method, Jacobi guesses, accepted drafts by token position): {report}"
    )
    return 0
