"""``hf-specvla rollouts``: greedy on-policy rollouts of a policy saved episode by episode (frames, previous actions,
the policy's own greedy action tokens as labels), what ``train-draft --rollouts`` trains a draft head on; resumable,
split between worker processes, the same arrays however it was run."""

from __future__ import annotations

from ..training.rollouts import RolloutConfig
from .common import NON_NEGATIVE, POSITIVE, check_output_dir_flag, load_policy, read_policy_config, usage_errors

NAME = "rollouts"
HELP = "save a policy's greedy rollouts (frames + its own action tokens) for draft-head training (resumable)"
EXAMPLES = """
    # On-policy rollouts for a draft head: 100 greedy episodes per task, seeds from 400000 (train-draft's)
    hf-specvla rollouts --policy policies/mt10_vla3 --tasks MT10 --episodes-per-task 100 --workers 2 \\
        --output-dir runs/rollouts_v3
    hf-specvla rollouts --policy policies/mt10_vla3 --tasks reach --episodes-per-task 2 --max-steps 10 \\
        --method greedy --output-dir runs/rollouts_reach_smoke
    # then: a draft head trained on them (the last --validation-episodes of each task held out)
    hf-specvla train-draft --policy policies/mt10_vla3 --tasks reach --rollouts runs/rollouts_reach_smoke \\
        --max-steps 20 --output-dir runs/reach_draft_from_rollouts
"""


def add_arguments(parser) -> None:
    defaults = RolloutConfig
    parser.add_argument("--policy", required=True, help="the policy folder (train-vla output)")
    parser.add_argument("--output-dir", required=True, help="episodes/<task>/<seed>.npz, run.json, manifest.json")
    parser.add_argument("--tasks", nargs="+", default=[defaults.tasks], help="suites and/or task names")
    parser.add_argument(
        "--episodes-per-task",
        type=POSITIVE,
        default=defaults.episodes_per_task,
        help="greedy episodes per task (seeds --seed-start, +1, ...)",
    )
    parser.add_argument(
        "--seed-start",
        type=NON_NEGATIVE,
        default=defaults.seed_start,
        help="first seed (train-draft's --rollout-seed-start)",
    )
    parser.add_argument(
        "--max-steps",
        type=POSITIVE,
        default=defaults.max_steps,
        help="policy calls kept per episode (train-draft's --rollout-max-steps)",
    )
    parser.add_argument(
        "--method",
        default=defaults.method,
        help="how the greedy tokens are decoded: a lossless method without a draft head (greedy, "
        "prior+jacobi, exact): the same tokens, faster",
    )
    parser.add_argument(
        "--workers", type=POSITIVE, default=defaults.workers, help="worker processes (each loads the policy)"
    )
    parser.add_argument("--threads", type=POSITIVE, default=defaults.threads, help="torch CPU threads per worker")
    parser.add_argument(
        "--max-episodes", type=POSITIVE, default=None, help="stop after this many new episodes (a collection in parts)"
    )
    parser.add_argument("--resume", action="store_true", help="continue the collection in --output-dir")
    parser.add_argument(
        "--overwrite-output-dir", action="store_true", help="move the folder's previous contents aside, start over"
    )


def run(args, parser) -> int:
    from ..training.rollouts import check_rollouts_folder, collect_rollouts

    check_output_dir_flag(args.output_dir, parser)
    with usage_errors(parser, errors=(ValueError,)):
        config = RolloutConfig(
            args.tasks,
            args.episodes_per_task,
            args.seed_start,
            args.max_steps,
            args.method,
            args.workers,
            args.threads,
            args.max_episodes,
        )
    policy_config = read_policy_config(args.policy, parser)  # a missing policy named before anything loads
    with usage_errors(parser, "--method", (ValueError,)):
        config.decoding_method(policy_config.action_dim)
    with usage_errors(parser, errors=(FileExistsError, FileNotFoundError)):
        check_rollouts_folder(args.output_dir, None, args.resume, args.overwrite_output_dir)
    policy = load_policy(args.policy, parser)
    with usage_errors(parser, errors=(FileExistsError, FileNotFoundError)):
        manifest = collect_rollouts(policy, config, args.output_dir, args.resume, args.overwrite_output_dir)
    episodes = manifest["episodes"]
    success = sum(e["success"] for e in episodes) / max(len(episodes), 1)
    frames = sum(e["frames"] for e in episodes)
    state = "complete" if manifest["complete"] else "not complete: the same command with --resume continues it"
    print(
        f"{len(episodes)} episodes in {args.output_dir} ({manifest['new_episodes']} new in "
        f"{manifest['seconds']:.0f} s), {frames} frames, success {success:.0%}; {state}"
    )
    return 0
