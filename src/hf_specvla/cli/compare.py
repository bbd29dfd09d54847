"""``hf-specvla compare``: a paired side-by-side of decoding methods on the same seeds (every method runs a seed
before the next): success with 95% intervals, speed-up, forwards per action, bin deviation; a table, JSON and plots
(resumable)."""

from __future__ import annotations

import logging

from ..metaworld.comparison.methods import DRAFTER_CHOICES, METHOD_KEYS, PRESETS, CompareConfig
from .common import (
    NON_NEGATIVE,
    POSITIVE,
    add_device_arguments,
    add_tree_arguments,
    check_draft_head_flag,
    check_output_dir_flag,
    load_draft_head_for,
    load_policy,
    positive_number,
    read_policy_config,
    resolve_placement,
    usage_errors,
)

logger = logging.getLogger(__name__)

NAME = "compare"
HELP = "paired side-by-side of decoding methods on the same seeds (resumable)"
EXAMPLES = """
    # Paired side-by-side of decoding methods (same seeds; every method runs a seed before the next): success with
    # 95% intervals, speed-up, forwards per action, bin deviation; a table, JSON and plots (resumable)
    hf-specvla compare --policy policies/mt10_vla3 --draft-head policies/mt10_vla3_draft_v2 --tasks MT10 \\
        --episodes 20 --methods greedy head tree tree:r=4 prior prior:r=2 prior:r=4 prior:r=8 prior+tree:r=4 \\
        --workers 2 --output-dir runs/compare_mt10
    hf-specvla compare --policy policies/mt10_vla --tasks reach --episodes 2 --methods greedy prior prior:r=4 \\
        --output-dir runs/compare_smoke
    # Jacobi drafts (the target's own guesses past a rejection) against transformers' compiled greedy
    hf-specvla compare --policy policies/mt10_vla3 --tasks reach --episodes 1 \\
        --methods greedy greedy:compile prior+jacobi prior+jacobi:compile --output-dir runs/compare_jacobi_smoke
    # More seeds into a folder timed with 1 worker, now with 2: refused (timings would mix) unless the timing restarts
    # (the finished episodes kept; only episodes timed from now on enter the speed columns)
    hf-specvla compare --policy policies/mt10_vla --tasks reach --episodes 4 --methods greedy prior prior:r=4 \\
        --workers 2 --restart-timing --output-dir runs/compare_smoke
    # The presets (exact: the fastest setting identical to greedy; fast: the relaxed one, r=4 on x y z with gate=0.5
    # chosen on policy v2, confirm=1 added on policy v3) and a relaxed rule spelled out: r per dimension (strict
    # gripper), at most 1 relaxed token per action, a confidence gate
    hf-specvla compare --policy policies/mt10_vla3 --tasks reach --episodes 1 \\
        --methods greedy exact fast prior+jacobi:r=4/4/4/0,m=1,gate=0.5 --output-dir runs/compare_rules_smoke
    # Rules that scale with the motion: within 10% of greedy's motion in bins (x y z), at most 0.04 units, the gripper
    # confirmed after a relaxed token; the deviation reported apart for motions >= 0.25 units and smaller ones
    hf-specvla compare --policy policies/mt10_vla3 --tasks reach --episodes 1 --methods greedy \\
        prior+jacobi:rho=0.1/0.1/0.1/0,dev=0.04/0.04/0.04/0,confirm=1 --motion-threshold 0.25 \\
        --output-dir runs/compare_motion_smoke
    # On the CPU in float32 (default: auto, a GPU in bfloat16 when torch sees one; the folder records both, and a
    # continued run on another device or dtype is refused)
    hf-specvla compare --policy policies/mt10_vla --tasks reach --episodes 1 --methods greedy prior \\
        --device cpu --dtype float32 --output-dir runs/compare_cpu
"""


def add_arguments(parser) -> None:
    parser.add_argument("--policy", required=True, help="a policy folder (train-vla output)")
    parser.add_argument("--draft-head", default=None, help="the DraftHead folder the head / tree methods use")
    parser.add_argument(
        "--methods",
        nargs="+",
        default=list(CompareConfig.methods),
        help="<drafters>[:<option>,...][:compile], drafters one of "
        + ", ".join(DRAFTER_CHOICES)
        + "; options: "
        + "; ".join(f"{k}= {v}" for k, v in METHOD_KEYS.items())
        + "; or a preset: "
        + ", ".join(PRESETS)
        + "; or oracle[:compile], the bound (greedy's "
        "own tokens, decoded off the clock, drafted: one target forward a call). Greedy always "
        "runs: the baseline; :compile = static cache + compiled verification, greedy:compile = "
        "transformers' compiled greedy",
    )
    parser.add_argument("--tasks", nargs="+", default=["MT10"], help="suites and/or task names")
    parser.add_argument("--episodes", type=POSITIVE, default=CompareConfig.episodes_per_task, help="seeds per task")
    parser.add_argument("--seed-start", type=NON_NEGATIVE, default=CompareConfig.seed_start, help="first seed")
    parser.add_argument(
        "--max-episode-steps", type=POSITIVE, default=CompareConfig.max_episode_steps, help="step limit"
    )
    parser.add_argument(
        "--workers",
        type=POSITIVE,
        default=CompareConfig.workers,
        help="processes the seeds are split between (timings compared within a worker)",
    )
    parser.add_argument("--threads", type=POSITIVE, default=CompareConfig.threads, help="torch CPU threads per worker")
    add_device_arguments(parser)
    parser.add_argument("--seed", type=int, default=CompareConfig.order_seed, help="seeds the method order per seed")
    parser.add_argument(
        "--motion-threshold",
        type=positive_number,
        default=CompareConfig.motion_threshold,
        help="the size of greedy's action (|value|, policy's units) from which a motion is large, for "
        "the deviation by phase of relaxed methods",
    )
    add_tree_arguments(parser)
    parser.add_argument("--output-dir", required=True, help="logs, summary.json, compare.md, plots (resumes)")
    parser.add_argument(
        "--overwrite-output-dir", action="store_true", help="move a folder holding another run aside, start over"
    )
    parser.add_argument(
        "--restart-timing",
        action="store_true",
        help="continue a folder timed under other conditions (workers, threads, machine): its finished "
        "episodes are kept, only episodes timed from now on enter the speed columns",
    )


def run(args, parser) -> int:
    check_output_dir_flag(args.output_dir, parser)
    action_dim = read_policy_config(args.policy, parser).action_dim  # the presets resolve to the policy's layout
    with usage_errors(parser, errors=(ValueError,)):
        config = CompareConfig(
            args.tasks,
            args.episodes,
            args.methods,
            args.seed_start,
            args.max_episode_steps,
            args.workers,
            args.threads,
            args.seed,
            args.tree_top_k,
            args.tree_depth,
            args.tree_total_tokens,
            draft_head_given=args.draft_head is not None,
            action_dim=action_dim,
            motion_threshold=args.motion_threshold,
        )
        config.check_draft_head_given(args.draft_head is not None)
    if args.draft_head and not config.draft_head_methods():
        logger.warning(
            "--draft-head %s is not used: none of the methods %s drafts with a head (head, tree, "
            "prior+head, prior+tree); it is ignored",
            args.draft_head,
            config.methods,
        )
        args.draft_head = None
    check_draft_head_flag(args.draft_head, parser)
    # the runner imports the policy's torch and transformers (seconds): after the flags' cheap checks
    from ..metaworld.comparison import format_comparison, run_comparison
    from ..metaworld.comparison.runner import WorkerDiedError, check_timing

    if not args.overwrite_output_dir:  # a folder timed otherwise is refused before anything loads
        with usage_errors(parser, errors=(FileExistsError,)):
            check_timing(args.output_dir, config, args.restart_timing)
    placement = resolve_placement(args, parser)  # before the policy loads and the folder is claimed
    policy = load_policy(args.policy, parser)
    draft_head = load_draft_head_for(policy, args.draft_head, parser) if args.draft_head else None
    placement.place_policy(policy, draft_head)  # after the head's check: it compares the weights as saved
    try:
        with usage_errors(parser, errors=(FileExistsError, ValueError)):
            summary = run_comparison(
                policy,
                config,
                args.output_dir,
                draft_head,
                args.policy,
                args.draft_head,
                overwrite=args.overwrite_output_dir,
                restart_timing=args.restart_timing,
            )
    except WorkerDiedError as error:  # a killed worker: the folder is consistent, the same command resumes it
        logger.error("%s", error)
        return 1
    print(format_comparison(summary))
    print(f"table, JSON and plots in {args.output_dir}")
    return 0
