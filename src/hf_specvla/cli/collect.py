"""``hf-specvla collect``: scripted-expert Meta-World demonstrations (Parquet, resumable), or DAgger data where a
policy drives and the expert labels every state it reaches."""

from __future__ import annotations

from ..metaworld.env import CAMERAS, EnvConfig
from ..metaworld.seeds import COLLECT_SEED_START
from .common import (
    NON_NEGATIVE,
    POSITIVE,
    check_output_dir_flag,
    check_tasks,
    load_policy,
    read_policy_config,
    usage_errors,
)

NAME = "collect"
HELP = "record scripted-expert Meta-World demonstrations (Parquet; resumable)"
EXAMPLES = """
    # Meta-World expert demonstrations (resumable)
    hf-specvla collect --tasks MT10 --episodes 50 --output-dir runs/mt10_demos

    # DAgger: the policy drives (a quarter of the steps run the expert), the expert labels every state it reaches
    hf-specvla collect --policy policies/mt10_vla --expert-mix 0.25 --episodes 30 --seed-start 20000 \\
        --max-episode-steps 250 --output-dir runs/mt10_dagger
"""


def add_arguments(parser) -> None:
    parser.add_argument("--tasks", nargs="+", default=["MT10"], help="suites (MT10, MT50) and/or task names")
    parser.add_argument(
        "--episodes",
        type=POSITIVE,
        default=50,
        help="successful episodes per task (with --policy: episodes, failed ones kept)",
    )
    parser.add_argument("--output-dir", required=True, help="dataset folder (resumes if it exists)")
    parser.add_argument(
        "--image-size",
        type=int,
        default=None,
        help=f"image side (px) (default: the --policy's, else {EnvConfig.image_size})",
    )
    parser.add_argument(
        "--camera",
        default=None,
        choices=CAMERAS,
        help=f"camera to render from (default: the --policy's, else {EnvConfig.camera})",
    )
    parser.add_argument("--seed-start", type=NON_NEGATIVE, default=COLLECT_SEED_START, help="first seed tried per task")
    parser.add_argument(
        "--action-noise",
        type=float,
        default=0.0,
        help="std of Gaussian noise added to the executed expert action (recorded actions stay "
        "clean): recovery data for behaviour cloning (DART)",
    )
    parser.add_argument(
        "--hand-start-noise",
        type=float,
        default=EnvConfig.hand_start_noise,
        help="metres: uniform per-axis offset of the hand's start position, drawn from the seed "
        "(varied starts keep a cloned policy from copying the state's drift)",
    )
    parser.add_argument("--max-episode-steps", type=int, default=EnvConfig.max_episode_steps, help="step limit")
    parser.add_argument(
        "--policy", default=None, help="DAgger: this policy folder drives, the expert labels the states it reaches"
    )
    parser.add_argument(
        "--expert-mix",
        type=float,
        default=None,
        help="with --policy: probability that a step runs the expert instead (default 0)",
    )
    parser.add_argument("--threads", type=POSITIVE, default=None, help="torch CPU threads (with --policy)")


def run(args, parser) -> int:
    from ..metaworld.demonstrations import (
        check_action_noise,
        check_dataset_folder,
        check_expert_mix,
        collect_demonstrations,
    )

    check_output_dir_flag(args.output_dir, parser)
    check_tasks(args.tasks, parser)
    if args.policy is None and args.expert_mix is not None:
        parser.error("--expert-mix needs --policy (it mixes expert steps into the policy's rollouts)")
    with usage_errors(parser, "--action-noise", (ValueError,)):
        check_action_noise(args.action_noise)
    if args.expert_mix is not None:
        with usage_errors(parser, "--expert-mix", (ValueError,)):
            check_expert_mix(args.expert_mix)
    policy_config = read_policy_config(args.policy, parser) if args.policy is not None else None
    # the image settings default to the driving policy's (it can only read what it was trained on)
    if args.image_size is not None:
        image_size = args.image_size
    else:
        image_size = policy_config.image_size if policy_config else EnvConfig.image_size
    camera = args.camera or (policy_config.camera if policy_config else EnvConfig.camera)
    with usage_errors(parser, errors=(ValueError,)):
        env_config = EnvConfig(image_size, camera, args.max_episode_steps, args.hand_start_noise)
        if policy_config is not None:
            env_config.check_renders_for(policy_config)
    policy = load_policy(args.policy, parser) if args.policy is not None else None
    with usage_errors(parser, "--output-dir", (ValueError,)):  # a dataset of other settings: before any episode
        check_dataset_folder(args.output_dir, env_config, args.action_noise, policy, args.expert_mix or 0.0)
    summary = collect_demonstrations(
        args.output_dir,
        args.tasks,
        args.episodes,
        env_config,
        args.seed_start,
        action_noise=args.action_noise,
        policy=policy,
        expert_mix=args.expert_mix or 0.0,
    )
    print(
        f"{summary.episodes_written} episodes written, {summary.episodes_present} in {args.output_dir}, "
        f"{summary.expert_failures} expert failures skipped"
    )
    if policy is not None:
        driver = "the policy"
        if args.expert_mix:
            driver += f" (the expert at {args.expert_mix:.0%} of the steps)"
        print(f"{driver} solved {summary.driven_successes} of the {summary.episodes_written} episodes it drove")
    return 0
