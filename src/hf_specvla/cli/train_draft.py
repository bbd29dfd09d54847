"""``hf-specvla train-draft``: a draft head for a policy, self-distilled on the policy's own rollouts (and
optionally demonstration frames), validated by the engine, saved with a model card (resumable)."""

from __future__ import annotations

from ..progress import is_secondary_process
from ..training.configuration import (
    HEAD_VERSIONS,
    DraftDataConfig,
    PolicyDraftTrainingConfig,
    check_draft_chain,
    default_unroll_steps,
)
from .common import (
    NON_NEGATIVE,
    POSITIVE,
    add_training_run_arguments,
    check_output_dir_flag,
    check_training_folder,
    load_policy,
    read_policy_config,
    usage_errors,
)

NAME = "train-draft"
HELP = "train a draft head for a policy: self-distillation on its rollouts (resumable)"
EXAMPLES = """
    # A draft head for a policy: self-distillation on its own rollouts (+ demonstrations), validated by the engine
    hf-specvla train-draft --policy policies/mt10_vla --tasks MT10 --max-steps 3000 --output-dir runs/mt10_draft
    hf-specvla train-draft --policy policies/mt10_vla --tasks reach --rollout-episodes 2 --max-steps 20 \\
        --output-dir runs/reach_draft_smoke
    # Head v2: a low, a middle and the top layer of the policy, its previous action, trained on its own drafts
    hf-specvla train-draft --policy policies/mt10_vla --tasks reach --rollout-episodes 2 --max-steps 20 \\
        --head v2 --output-dir runs/reach_draft_v2_smoke
    # On rollouts collected beforehand (hf-specvla rollouts): its episodes, the last --validation-episodes held out
    hf-specvla rollouts --policy policies/mt10_vla --tasks reach --episodes-per-task 3 --max-steps 10 \\
        --output-dir runs/reach_rollouts_smoke
    hf-specvla train-draft --policy policies/mt10_vla --tasks reach --rollouts runs/reach_rollouts_smoke \\
        --max-steps 20 --output-dir runs/reach_draft_rollouts_smoke
"""


def add_arguments(parser) -> None:
    parser.add_argument("--policy", required=True, help="the policy folder (train-vla output)")
    parser.add_argument("--output-dir", required=True, help="the draft head folder (and checkpoints)")
    parser.add_argument("--tasks", nargs="+", default=["MT10"], help="suites and/or task names")
    parser.add_argument(
        "--data",
        nargs="+",
        default=None,
        help="also distil on frames of these `collect` folders (default: rollouts only)",
    )
    parser.add_argument(
        "--demo-frames-per-task",
        type=NON_NEGATIVE,
        default=None,
        help=f"with --data: frames sampled per task (default: {DraftDataConfig.demo_frames_per_task})",
    )
    parser.add_argument(
        "--rollouts",
        default=None,
        help="read the on-policy frames from this `hf-specvla rollouts` folder of the policy "
        "instead of rolling it out here",
    )
    parser.add_argument(
        "--rollout-episodes",
        type=POSITIVE,
        default=None,
        help=f"greedy on-policy episodes per task, the last --validation-episodes held out (default: "
        f"{DraftDataConfig.rollout_episodes}); with --rollouts, every finished one",
    )
    parser.add_argument(
        "--rollout-max-steps",
        type=POSITIVE,
        default=None,
        help=f"steps kept per rollout (default: {DraftDataConfig.rollout_max_steps}); with --rollouts, the folder's",
    )
    parser.add_argument(
        "--rollout-seed-start",
        type=NON_NEGATIVE,
        default=None,
        help=f"first rollout seed (default: {DraftDataConfig.rollout_seed_start}); with --rollouts, the folder's",
    )
    parser.add_argument(
        "--validation-episodes",
        type=POSITIVE,
        default=DraftDataConfig.validation_episodes,
        help="held-out rollouts per task",
    )
    parser.add_argument(
        "--validation-frames",
        type=POSITIVE,
        default=DraftDataConfig.validation_frames,
        help="held-out frames the engine validates on (evenly spread)",
    )
    parser.add_argument(
        "--num-draft-tokens",
        type=POSITIVE,
        default=None,
        help="the head's default chain length k (default: tokens per call - 1)",
    )
    parser.add_argument(
        "--head",
        choices=HEAD_VERSIONS,
        default=HEAD_VERSIONS[0],
        help="v1: the policy's last hidden state; v2: a low, a middle and the top layer and the "
        "robot's previous action (EAGLE-3 + the last action)",
    )
    parser.add_argument(
        "--prefill-image-features",
        action="store_true",
        help="with --head v3: its drafts before the prefill read the encoded camera frame too (paid "
        "on the demo's toy target, not on policy v3)",
    )
    parser.add_argument(
        "--unroll-steps",
        type=POSITIVE,
        default=None,
        help="draft steps trained per example on the head's own features (training-time test; "
        "default: 1 for v1, the chain length for v2 and v3)",
    )
    defaults = PolicyDraftTrainingConfig
    parser.add_argument("--max-steps", type=POSITIVE, default=defaults.max_steps, help="optimizer steps")
    parser.add_argument("--batch-size", type=POSITIVE, default=defaults.batch_size, help="sequences per step")
    parser.add_argument("--learning-rate", type=float, default=defaults.learning_rate, help="peak AdamW learning rate")
    parser.add_argument(
        "--feature-loss-weight",
        type=float,
        default=defaults.feature_loss_weight,
        help="weight of the SmoothL1 loss on the features (EAGLE-1/2; EAGLE-3 uses 0)",
    )
    parser.add_argument(
        "--token-loss-weight",
        type=float,
        default=defaults.token_loss_weight,
        help="weight of the soft cross-entropy on the tokens",
    )
    parser.add_argument(
        "--lr-schedule", choices=("constant", "cosine"), default=defaults.lr_schedule, help="after warm-up"
    )
    parser.add_argument("--warmup-steps", type=NON_NEGATIVE, default=defaults.warmup_steps, help="linear warm-up steps")
    parser.add_argument(
        "--eval-every",
        type=NON_NEGATIVE,
        default=defaults.eval_every,
        help="steps between validations (0: only at the end)",
    )
    parser.add_argument(
        "--save-every",
        type=NON_NEGATIVE,
        default=defaults.save_every,
        help="steps between checkpoints (0: only the final head)",
    )
    add_training_run_arguments(parser, defaults.seed)


def run(args, parser) -> int:
    import shlex

    check_output_dir_flag(args.output_dir, parser)
    if args.prefill_image_features and args.head != "v3":
        parser.error(
            f"--prefill-image-features is read by a head v3's drafts before the prefill; got --head "
            f"{args.head}: add --head v3"
        )
    if args.demo_frames_per_task is not None and not args.data:
        parser.error("--demo-frames-per-task samples frames of the --data folders: give --data (or drop the flag)")
    check_training_folder(args.output_dir, args.resume, args.overwrite_output_dir, parser)
    # the chain and its training depth from the policy's layout (its config: no weights loaded yet)
    tokens_per_call = read_policy_config(args.policy, parser).action_tokens
    num_draft_tokens = args.num_draft_tokens or tokens_per_call - 1
    unroll_steps = args.unroll_steps or default_unroll_steps(args.head, num_draft_tokens)
    flags = {"--head": args.head, "--num-draft-tokens": args.num_draft_tokens, "--unroll-steps": args.unroll_steps}
    given = " ".join(f"{flag} {value}" for flag, value in flags.items() if value is not None)
    with usage_errors(parser, f"{given} for a policy of {tokens_per_call} tokens a call", (ValueError,)):
        check_draft_chain(num_draft_tokens, tokens_per_call, unroll_steps, args.head == "v3")
    with usage_errors(parser, errors=(ValueError, FileNotFoundError)):
        episodes, max_steps, seed_start = rollout_defaults(args)
        demo_frames = args.demo_frames_per_task
        demo_frames = DraftDataConfig.demo_frames_per_task if demo_frames is None else demo_frames
        data_config = DraftDataConfig(
            args.tasks,
            episodes,
            max_steps,
            seed_start,
            args.validation_episodes,
            args.validation_frames,
            demo_frames,
            seed=args.seed,
        )
        training_config = PolicyDraftTrainingConfig(
            args.output_dir,
            max_steps=args.max_steps,
            batch_size=args.batch_size,
            learning_rate=args.learning_rate,
            warmup_steps=args.warmup_steps,
            lr_schedule=args.lr_schedule,
            save_every=args.save_every,
            feature_loss_weight=args.feature_loss_weight,
            token_loss_weight=args.token_loss_weight,
            eval_every=args.eval_every,
            resume=args.resume,
            overwrite_output_dir=args.overwrite_output_dir,
            seed=args.seed,
            unroll_steps=unroll_steps,
        )
        if args.data:  # imports torch (seconds): only where there are demonstrations to check
            from ..metaworld.demonstrations import dataset_info

            for root in args.data:
                dataset_info(root)
    policy = load_policy(args.policy, parser)
    if args.rollouts is not None:  # another policy's rollouts, too few: refused before the training starts
        from ..training.rollouts import check_rollouts_for

        with usage_errors(parser, "--rollouts", (ValueError, FileNotFoundError)):
            check_rollouts_for(args.rollouts, policy, data_config)
    from ..training.policy_draft import train_policy_draft_head

    command = shlex.join(["hf-specvla", *args.argv])
    with usage_errors(parser, errors=(FileExistsError,)):
        head = train_policy_draft_head(
            policy,
            training_config,
            data_config,
            args.data or [],
            args.num_draft_tokens,
            command=command,
            head_version=args.head,
            rollouts=args.rollouts,
            image_features=args.prefill_image_features,
        )
    if not is_secondary_process():
        print(f"draft head saved to {args.output_dir} ({head.num_parameters():,} parameters); see its README.md")
    return 0


def rollout_defaults(args) -> tuple[int, int, int]:
    """--rollout-episodes, --rollout-max-steps, --rollout-seed-start as given, else ``DraftDataConfig``'s or, with
    --rollouts, the folder's (every episode finished for each task, its step cut, its first seed).

    Raises:
        FileNotFoundError: --rollouts names no rollouts folder.
    """
    defaults = DraftDataConfig
    episodes, max_steps, seed_start = args.rollout_episodes, args.rollout_max_steps, args.rollout_seed_start
    if args.rollouts is None:
        return (
            episodes or defaults.rollout_episodes,
            max_steps or defaults.rollout_max_steps,
            defaults.rollout_seed_start if seed_start is None else seed_start,
        )
    from ..metaworld.env import resolve_tasks
    from ..training.rollouts import finished_episodes_per_task, read_rollouts_record

    settings = read_rollouts_record(args.rollouts)
    seed_start = settings["seed_start"] if seed_start is None else seed_start
    episodes = episodes or finished_episodes_per_task(args.rollouts, resolve_tasks(args.tasks), seed_start)
    return episodes, max_steps or settings["max_steps"], seed_start
