"""``hf-specvla train-vla``: behaviour-clone an OpenVLA-style policy on `collect` folders (resumable)."""

from __future__ import annotations

from ..policies.configuration_vla import VLAPolicyConfig
from ..training.configuration import VLATrainingConfig
from .common import (
    POSITIVE,
    add_training_run_arguments,
    check_output_dir_flag,
    check_tasks,
    check_training_folder,
    load_policy,
    usage_errors,
)

NAME = "train-vla"
HELP = "behaviour-clone an OpenVLA-style policy on demonstrations (resumable)"
EXAMPLES = """
    # Behaviour cloning on demonstrations (resumable: run it again with --resume)
    hf-specvla train-vla --data runs/mt10_demos --output-dir runs/mt10_vla --max-steps 6000
"""


def add_arguments(parser) -> None:
    parser.add_argument(
        "--data", required=True, nargs="+", help="folders written by `hf-specvla collect` (same image size and camera)"
    )
    parser.add_argument("--output-dir", required=True, help="the policy folder (and checkpoints)")
    parser.add_argument("--tasks", nargs="+", default=None, help="train on these tasks only (default: all in --data)")
    parser.add_argument("--max-steps", type=int, default=VLATrainingConfig.max_steps, help="optimizer steps")
    parser.add_argument("--batch-size", type=int, default=VLATrainingConfig.batch_size, help="frames per step")
    parser.add_argument("--learning-rate", type=float, default=VLATrainingConfig.learning_rate, help="peak AdamW lr")
    parser.add_argument(
        "--eval-every", type=int, default=VLATrainingConfig.eval_every, help="steps between validations"
    )
    parser.add_argument(
        "--save-every", type=int, default=VLATrainingConfig.save_every, help="steps between checkpoints"
    )
    parser.add_argument(
        "--patch-size",
        type=int,
        default=VLAPolicyConfig.patch_size,
        help="ViT patch size (px): the image becomes (image size / patch size)^2 tokens",
    )
    parser.add_argument(
        "--vision-hidden-size", type=int, default=VLAPolicyConfig.vision_hidden_size, help="width of the vision encoder"
    )
    parser.add_argument(
        "--vision-layers",
        type=int,
        default=VLAPolicyConfig.vision_layers,
        help="transformer layers of the vision encoder",
    )
    parser.add_argument(
        "--text-layers",
        type=POSITIVE,
        default=VLAPolicyConfig.text_layers,
        help="decoder layers (its depth sets the cost of a decode step)",
    )
    parser.add_argument(
        "--text-hidden-size", type=POSITIVE, default=VLAPolicyConfig.text_hidden_size, help="decoder width"
    )
    parser.add_argument(
        "--chunk-length",
        type=POSITIVE,
        default=VLAPolicyConfig.chunk_length,
        help="actions predicted per call (an action chunk of H x action_dim tokens)",
    )
    parser.add_argument(
        "--init-from",
        default=None,
        help="start from this trained policy (same widths; its decoder layers spread over a "
        "deeper one, new layers start as the identity; its statistics are kept)",
    )
    parser.add_argument("--no-state", action="store_true", help="do not give the proprio state to the model")
    parser.add_argument(
        "--scene-targets",
        action="store_true",
        help="also learn to predict the object and goal positions (the data's scene_state column) "
        "after the action tokens: an auxiliary target for the vision encoder; acting is "
        "unchanged",
    )
    parser.add_argument(
        "--scene-loss-weight",
        type=float,
        default=None,
        help="weight of the scene-state loss against the action tokens' (with --scene-targets; "
        f"default {VLATrainingConfig.scene_loss_weight})",
    )
    parser.add_argument(
        "--scene-readout-weight",
        type=float,
        default=None,
        help="also train a linear readout of the object and goal positions from the decoder where the "
        "first action token is decoded, with this loss weight (with --scene-targets; training "
        "only: the policy folder holds no readout, acting is unchanged; default "
        f"{VLATrainingConfig.scene_readout_weight}: none)",
    )
    parser.add_argument(
        "--freeze-vision",
        action="store_true",
        help="do not train the vision tower (e.g. one pretrained on scenes: "
        "examples/metaworld/localization_probe.py --save-policy, with --init-from)",
    )
    add_training_run_arguments(parser, VLATrainingConfig.seed)


def _configs(args, parser, info: dict) -> tuple[VLATrainingConfig, VLAPolicyConfig]:
    from ..metaworld.env import SCENE_STATE_DIM

    weight = {} if args.scene_loss_weight is None else {"scene_loss_weight": args.scene_loss_weight}
    if args.scene_readout_weight is not None:
        weight["scene_readout_weight"] = args.scene_readout_weight
    with usage_errors(parser, errors=(ValueError,)):
        config = VLATrainingConfig(
            args.output_dir,
            max_steps=args.max_steps,
            batch_size=args.batch_size,
            learning_rate=args.learning_rate,
            eval_every=args.eval_every,
            save_every=args.save_every,
            resume=args.resume,
            overwrite_output_dir=args.overwrite_output_dir,
            seed=args.seed,
            freeze_vision=args.freeze_vision,
            **weight,
        )
        policy_config = VLAPolicyConfig(
            image_size=info["image_size"],
            camera=info["camera"],
            patch_size=args.patch_size,
            use_state=not args.no_state,
            vision_hidden_size=args.vision_hidden_size,
            vision_layers=args.vision_layers,
            text_hidden_size=args.text_hidden_size,
            text_layers=args.text_layers,
            chunk_length=args.chunk_length,
            scene_state_dim=SCENE_STATE_DIM if args.scene_targets else 0,
        )
    return config, policy_config


def run(args, parser) -> int:
    from ..metaworld.demonstrations import dataset_info, dataset_stats, load_demonstrations
    from ..metaworld.env import TASK_INSTRUCTIONS
    from ..policies import VLAPolicy
    from ..training.behaviour_cloning import check_demonstrations, train_vla

    check_output_dir_flag(args.output_dir, parser)
    if args.scene_loss_weight is not None and not args.scene_targets:
        parser.error("--scene-loss-weight needs --scene-targets (it weighs the scene-state tokens' loss)")
    if args.scene_readout_weight is not None and not args.scene_targets:
        parser.error(
            "--scene-readout-weight needs --scene-targets (the readout learns the data's scene_state column "
            "in the policy's scene-state statistics)"
        )
    if args.tasks is not None:
        check_tasks(args.tasks, parser)
    check_training_folder(args.output_dir, args.resume, args.overwrite_output_dir, parser)
    with usage_errors(parser, "--data", (FileNotFoundError, ValueError)):  # not a collect folder, mixed folders
        stats, info = dataset_stats(args.data), dataset_info(args.data)
        scene_stats = stats.scene_normalizer() if args.scene_targets else None  # before the slow load: fails fast
    action_stats, state_stats = stats.action, stats.state
    config, policy_config = _configs(args, parser, info)
    source = None
    if args.init_from is not None:
        source = load_policy(args.init_from, parser, "--init-from")
        if source.config.text_layers > policy_config.text_layers:
            parser.error(
                f"--init-from {args.init_from} has {source.config.text_layers} decoder layers: "
                f"--text-layers must be at least that, got {args.text_layers}"
            )
        # the source's tokens mean its bins: keep its normalisation
        action_stats, state_stats = source.action_normalizer, source.state_normalizer
        if args.scene_targets and source.scene_normalizer is not None:
            scene_stats = source.scene_normalizer
    demos = load_demonstrations(args.data, args.tasks)
    with usage_errors(parser, errors=(ValueError,)):  # too few frames for a batch: before the policy is built
        check_demonstrations(demos, config, policy_config)
    policy = VLAPolicy.build(
        list(TASK_INSTRUCTIONS.values()), action_stats, state_stats, policy_config, args.seed, scene_stats
    )
    metrics = train_vla(policy, demos, config, init_from=source)
    print(f"policy saved to {args.output_dir}: {metrics}")
    return 0
