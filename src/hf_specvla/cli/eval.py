"""``hf-specvla eval``: roll a policy out on Meta-World's held-out seeds and report per-task success, with any
decoding method (``--method`` takes `compare`'s names; the older flags build the same method), resumable."""

from __future__ import annotations

import logging
from dataclasses import replace

from ..metaworld.env import EnvConfig
from ..metaworld.seeds import EVAL_SEED_START
from .common import (
    NON_NEGATIVE,
    POSITIVE,
    add_device_arguments,
    check_bin_tolerances,
    check_draft_head_flag,
    check_output_dir_flag,
    check_tasks,
    load_draft_head_for,
    load_policy,
    read_policy_config,
    resolve_placement,
    usage_errors,
)

logger = logging.getLogger(__name__)

NAME = "eval"
HELP = "roll a policy out on Meta-World and report per-task success (resumable)"
EXAMPLES = """
    # Evaluation on held-out seeds; with a video; with speculative decoding (a method as `compare` names it)
    hf-specvla eval --policy policies/mt10_vla --tasks MT10 --episodes 20 --output-dir runs/eval_greedy
    hf-specvla eval --policy policies/mt10_vla --tasks reach push --episodes 5 --video runs/reach.gif \\
        --output-dir runs/eval_reach_push
    hf-specvla eval --policy policies/mt10_vla3 --draft-head policies/mt10_vla3_draft_v2 --method prior+tree:r=4 \\
        --tasks reach --episodes 2 --output-dir runs/eval_prior_tree
    hf-specvla eval --policy policies/mt10_vla --draft-head runs/draft --bin-tolerance 2 --output-dir runs/eval_spec
    hf-specvla eval --policy policies/mt10_vla --action-prior --bin-tolerance 2 --output-dir runs/eval_prior
    hf-specvla eval --policy policies/mt10_vla --tasks MT10 --episodes 2 --num-envs 10 --output-dir runs/eval_batched
    # Where the policy runs and in what precision (default: auto, a GPU in bfloat16 when torch sees one); a folder
    # records both, and continuing it on another device or dtype is refused
    hf-specvla eval --policy policies/mt10_vla --tasks reach --episodes 1 --device cpu --dtype float32 \\
        --output-dir runs/eval_cpu
"""


def add_arguments(parser) -> None:
    parser.add_argument("--policy", required=True, help="a policy folder (train-vla output)")
    parser.add_argument("--tasks", nargs="+", default=["MT10"], help="suites and/or task names")
    parser.add_argument("--episodes", type=POSITIVE, default=20, help="episodes per task")
    parser.add_argument("--output-dir", required=True, help="episodes.jsonl + summary.json go here (resumes)")
    parser.add_argument("--seed-start", type=NON_NEGATIVE, default=EVAL_SEED_START, help="first evaluation seed")
    parser.add_argument("--max-episode-steps", type=int, default=EnvConfig.max_episode_steps, help="step limit")
    parser.add_argument("--video", default=None, help="save the first episode as .gif / .mp4")
    parser.add_argument(
        "--overwrite-output-dir", action="store_true", help="move a folder holding another run aside, start over"
    )
    parser.add_argument(
        "--method",
        default=None,
        help="a decoding method as `compare` names it (e.g. prior+tree:r=4, head:k=3, "
        "prior+jacobi:r=4/4/4/0,m=1:compile) or a preset (exact, fast), instead of "
        "--action-prior / --draft-tree / --num-draft-tokens / --bin-tolerance",
    )
    parser.add_argument("--draft-head", default=None, help="speculative decoding with this DraftHead folder")
    parser.add_argument(
        "--bin-tolerance", type=NON_NEGATIVE, nargs="+", default=None, help="relaxed acceptance r (or one per dim)"
    )
    parser.add_argument("--num-draft-tokens", type=POSITIVE, default=None, help="chain length k (default: the head's)")
    parser.add_argument("--draft-tree", action="store_true", help="the draft head drafts an EAGLE-2 tree, not a chain")
    parser.add_argument(
        "--action-prior",
        action="store_true",
        help="draft each action from the episode's previous actions (verified inside the prefill)",
    )
    parser.add_argument("--threads", type=POSITIVE, default=None, help="torch CPU threads")
    add_device_arguments(parser)
    parser.add_argument(
        "--num-envs",
        type=POSITIVE,
        default=1,
        help="episodes run in lockstep, one batched policy call per step for all of them (same "
        "results, less wall time)",
    )


def decoding_method(args, parser, action_dim: int | None = None):
    """The [`DecodingMethod`] that ``--method`` or the older flags name, checked before anything loads; with
    ``action_dim`` (the policy's), presets resolve to its layout and per-dimension tolerances must fit it."""
    from ..metaworld.comparison.methods import DecodingMethod, check_tolerance_dims

    if args.method is not None:
        flags = [
            flag
            for flag, given in (
                ("--action-prior", args.action_prior),
                ("--draft-tree", args.draft_tree),
                ("--num-draft-tokens", args.num_draft_tokens is not None),
                ("--bin-tolerance", args.bin_tolerance is not None),
            )
            if given
        ]
        if flags:
            parser.error(f"--method {args.method} already says how to decode; drop {' / '.join(flags)}")
        with usage_errors(parser, "--method", (ValueError,)):
            method = DecodingMethod.parse(args.method, bool(args.draft_head), action_dim)
        if method.uses_draft_head and not args.draft_head:
            parser.error(f"--method {method.name} drafts with the draft head: give --draft-head")
        return method
    if args.bin_tolerance is not None and not (args.draft_head or args.action_prior):
        parser.error("--bin-tolerance needs --draft-head and/or --action-prior (something to draft with)")
    if (args.num_draft_tokens is not None or args.draft_tree) and not args.draft_head:
        parser.error("--num-draft-tokens / --draft-tree need --draft-head")
    if args.num_draft_tokens is not None and args.draft_tree:
        parser.error("--num-draft-tokens sets a chain; --draft-tree drafts a tree: give one of them")
    parts = ["prior"] * args.action_prior + (["tree" if args.draft_tree else "head"] if args.draft_head else [])
    tolerance = args.bin_tolerance or [0]
    tolerance = tolerance[0] if len(tolerance) == 1 else tuple(tolerance)
    if action_dim is not None and args.bin_tolerance is not None:
        with usage_errors(parser, errors=(ValueError,)):
            check_tolerance_dims(tolerance, action_dim, f"--bin-tolerance {' '.join(map(str, args.bin_tolerance))}")
    return DecodingMethod("+".join(parts) or "greedy", tolerance, args.num_draft_tokens)


def _check_tolerances(policy, method, args, parser) -> None:
    """The method's acceptance rule built for ``policy``'s actions (the engine's checks), before the folder is
    claimed."""
    from ..metaworld.comparison.runner import check_method_rule

    tolerances = args.bin_tolerance or method.tolerances() or [0]
    given = f"--method {method.name}" if args.method else f"--bin-tolerance {' '.join(map(str, tolerances))}"
    check_bin_tolerances(tolerances, policy.action_tokenizer.n_bins, given, parser)
    with usage_errors(parser, errors=(ValueError, TypeError)):
        check_method_rule(method, policy)


def run(args, parser) -> int:
    import json

    check_output_dir_flag(args.output_dir, parser)
    check_tasks(args.tasks, parser)
    decoding_method(args, parser)  # the flags' own mistakes first, whatever the policy
    check_draft_head_flag(args.draft_head, parser)
    if args.video is not None:
        from ..metaworld.evaluation import check_video_path

        with usage_errors(parser, "--video", (ValueError,)):
            check_video_path(args.video)
    policy_config = read_policy_config(args.policy, parser)  # cheap: no weights loaded yet
    method = decoding_method(args, parser, policy_config.action_dim)
    if args.method is not None and method.name != args.method.strip():
        logger.info("--method %s = %s", args.method.strip(), method.name)
    with usage_errors(parser, errors=(ValueError,)):
        env_config = EnvConfig(policy_config.image_size, policy_config.camera, args.max_episode_steps)
    placement = resolve_placement(args, parser)  # imports torch: after the cheap checks, before the policy loads
    from ..metaworld.evaluation import evaluate, format_summary

    policy = load_policy(args.policy, parser)
    _check_tolerances(policy, method, args, parser)
    if args.draft_head and not method.uses_draft_head:
        logger.warning("--method %s drafts without a head: --draft-head %s is not used", method.name, args.draft_head)
    draft_head = load_draft_head_for(policy, args.draft_head, parser) if method.uses_draft_head else None
    placement.place_policy(policy, draft_head)  # after the head's check: it compares the weights as saved
    plan = method.plan(draft_head, policy.model.device.type, action_dim=policy.config.action_dim)
    if args.bin_tolerance is not None:  # as given (one r, or one per action dimension), as eval folders record it
        tolerance = args.bin_tolerance[0] if len(args.bin_tolerance) == 1 else args.bin_tolerance
        plan = replace(plan, acceptance={**plan.acceptance, "bin_tolerance": tolerance})
    with usage_errors(parser, errors=(FileExistsError,)):
        summary = evaluate(
            policy,
            args.tasks,
            args.episodes,
            args.output_dir,
            env_config,
            args.seed_start,
            video_path=args.video,
            overwrite=args.overwrite_output_dir,
            num_envs=args.num_envs,
            decoding=plan,
        )
    print(format_summary(summary))
    calls = "one batched call decides the actions" if args.num_envs > 1 else "one call decides the action"
    chunk = f" of the next {policy.config.chunk_length} steps" if policy.config.chunk_length > 1 else ""
    print(f"ms/call: the median wall time of a policy call ({calls}{chunk} of {args.num_envs} environment(s))")
    print(json.dumps(summary["overall"]))
    return 0
