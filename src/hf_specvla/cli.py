"""``hf-specvla``: the command line.

Examples:

    # The main job: build and train a toy OpenVLA-style target and a draft head on the spot, then benchmark
    # plain greedy vs speculative decoding (strict and relaxed). About 2 minutes on 2 CPU cores.
    hf-specvla demo

    # The same, with a bigger (slower, more VLA-like) target, more timing repeats, kept in ./runs/toy-medium
    hf-specvla demo --size medium --repeats 5 --output-dir runs/toy-medium

    # Re-run only the benchmark on a pipeline a previous demo saved
    hf-specvla benchmark --pipeline-dir runs/toy --chain-lengths 2 4 6 --bin-tolerances 1 2 4

    # Replay recorded episodes (previous actions are real): greedy vs action prior vs draft head chain / tree
    hf-specvla bench-episodes --policy policies/mt10_vla --tasks MT10 --episodes 1 --steps 40 --threads 1
    hf-specvla bench-episodes --pipeline-dir runs/toy --episodes 16 --threads 1

    # Meta-World: expert demonstrations (resumable), behaviour cloning, evaluation on held-out seeds
    hf-specvla collect --tasks MT10 --episodes 50 --output-dir runs/mt10_demos
    hf-specvla train-vla --data runs/mt10_demos --output-dir runs/mt10_vla --max-steps 6000
    hf-specvla eval --policy policies/mt10_vla --tasks MT10 --episodes 20 --output-dir runs/eval_greedy
    hf-specvla eval --policy policies/mt10_vla --tasks reach push --episodes 5 --video runs/reach.gif \\
        --output-dir runs/eval_reach_push
    hf-specvla eval --policy policies/mt10_vla --draft-head runs/draft --bin-tolerance 2 --output-dir runs/eval_spec
    hf-specvla eval --policy policies/mt10_vla --action-prior --bin-tolerance 2 --output-dir runs/eval_prior
    hf-specvla eval --policy policies/mt10_vla2 --draft-head policies/mt10_vla2_draft --method prior+tree:r=4 \
        --tasks reach --episodes 2 --output-dir runs/eval_prior_tree
    hf-specvla eval --policy policies/mt10_vla --tasks MT10 --episodes 2 --num-envs 10 --output-dir runs/eval_batched

    # A draft head for a policy: self-distillation on its own rollouts (+ demonstrations), validated by the engine
    hf-specvla train-draft --policy policies/mt10_vla --tasks MT10 --max-steps 3000 --output-dir runs/mt10_draft
    hf-specvla train-draft --policy policies/mt10_vla --tasks reach --rollout-episodes 2 --max-steps 20 \\
        --output-dir runs/reach_draft_smoke

    # Paired side-by-side of decoding methods (same seeds; every method runs a seed before the next): success with
    # 95% intervals, speed-up, forwards per action, bin deviation; a table, JSON and plots (resumable)
    hf-specvla compare --policy policies/mt10_vla --draft-head policies/mt10_vla_draft --tasks MT10 --episodes 20 \\
        --methods greedy head tree tree:r=4 prior prior:r=2 prior:r=4 prior:r=8 prior+tree:r=4 --workers 2 \\
        --output-dir runs/compare_mt10
    hf-specvla compare --policy policies/mt10_vla --tasks reach --episodes 2 --methods greedy prior prior:r=4 \\
        --output-dir runs/compare_smoke

    # DAgger: the policy drives (a quarter of the steps run the expert), the expert labels every state it reaches
    hf-specvla collect --policy policies/mt10_vla --expert-mix 0.25 --episodes 30 --seed-start 20000 \\
        --max-episode-steps 250 --output-dir runs/mt10_dagger
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import torch

from .comparison import DRAFTER_CHOICES, CompareConfig
from .envs.metaworld import CAMERAS, EnvConfig
from .envs.seeds import BENCH_SEED_START, EVAL_SEED_START
from .policy import VLAPolicyConfig
from .policy_draft import POLICY_DRAFT_DEFAULTS, DraftDataConfig
from .training import DraftTrainingConfig
from .vla_training import VLATrainingConfig

EXAMPLES = __doc__.split("Examples:", 1)[1]

SIZES = {
    "small": dict(
        hidden_size=128, num_hidden_layers=4, num_attention_heads=4, num_key_value_heads=2, intermediate_size=256
    ),
    "medium": dict(
        hidden_size=256, num_hidden_layers=8, num_attention_heads=8, num_key_value_heads=4, intermediate_size=688
    ),
}


def _at_least(minimum: int):
    """argparse ``type``: an int >= ``minimum``, else a usage error naming the value (exit code 2)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        return value

    parse.__name__ = f"int >= {minimum}"  # what argparse names in its error
    return parse


POSITIVE, NON_NEGATIVE = _at_least(1), _at_least(0)


class _HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Keeps the examples' line breaks and shows every option's default."""


def _subcommand(commands, name: str, help: str) -> argparse.ArgumentParser:
    return commands.add_parser(name, help=help, epilog="examples:" + EXAMPLES, formatter_class=_HelpFormatter)


def _add_benchmark_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--chain-lengths", type=POSITIVE, nargs="+", default=[2, 4, 6], help="strict chains k to time")
    parser.add_argument(
        "--bin-tolerances", type=NON_NEGATIVE, nargs="+", default=[1, 2, 4], help="relaxed r to time (k=6)"
    )
    parser.add_argument("--prompts", type=POSITIVE, default=48, help="held-out toy scenes to decode (of 256)")
    parser.add_argument("--repeats", type=POSITIVE, default=3, help="timed passes over the prompts")
    parser.add_argument("--threads", type=POSITIVE, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--seed", type=int, default=0, help="random seed")


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


def _add_training_run_arguments(parser: argparse.ArgumentParser, seed: int) -> None:
    """--resume, --overwrite-output-dir, --seed, --threads: shared by the trainers."""
    parser.add_argument("--resume", action="store_true", help="continue from the newest checkpoint in --output-dir")
    parser.add_argument(
        "--overwrite-output-dir", action="store_true", help="move the folder's previous run aside, train from scratch"
    )
    parser.add_argument("--seed", type=int, default=seed, help="random seed")
    parser.add_argument("--threads", type=POSITIVE, default=None, help="torch CPU threads (default: torch's)")


def _check_training_folder(output_dir: Path, resume: bool, overwrite: bool, parser) -> None:
    """The common folder mistakes as usage errors before any data is loaded (the full check of the folder's
    run.json runs once the data's fingerprint is known)."""
    from .checkpointing import check_output_dir

    try:
        check_output_dir(output_dir, None, resume, overwrite)
    except (FileExistsError, FileNotFoundError) as error:
        parser.error(str(error))


def _check_draft_head_flag(draft_head: str | None, parser) -> None:
    """``--draft-head`` must be a saved draft head (or a hub id): a usage error before anything is loaded."""
    from .speculative import check_draft_head_folder

    if draft_head is None:
        return
    try:
        check_draft_head_folder(draft_head)
    except (FileNotFoundError, ValueError) as error:
        parser.error(f"--draft-head: {error}")


def _load_draft_head_for(policy, draft_head: str, parser):
    """The ``--draft-head`` for ``policy``; a usage error when it was made for another model."""
    from .speculative import DraftHead

    head = DraftHead.from_pretrained(draft_head).eval()
    try:
        policy.check_draft_head(head)
    except ValueError as error:
        parser.error(f"--draft-head {draft_head}: {error}")
    return head


def _load_pipeline(pipeline_dir: str, parser):
    """The toy pipeline a previous `demo` saved in ``pipeline_dir``; a usage error when there is none."""
    from .toy import load_toy_pipeline

    try:
        return load_toy_pipeline(pipeline_dir)
    except FileNotFoundError as error:
        parser.error(f"--pipeline-dir: {error}")


def _demo_episodes(pipeline, args) -> None:
    """The demo's second table: moving-dot episodes, so that the action prior has previous actions to draft."""
    from .benchmark import episode_methods, format_episode_report, run_episode_benchmark, toy_actor, toy_episodes
    from .speculative import DraftTreeConfig
    from .toy import ACTION_DIM

    tolerances = [0, *args.bin_tolerances[:1]]
    methods = episode_methods(pipeline.draft_head, tolerances, DraftTreeConfig(), chain_length=ACTION_DIM - 1)
    episodes = toy_episodes(args.episodes)
    results = run_episode_benchmark(toy_actor(pipeline), episodes, methods, ACTION_DIM, seed=args.seed)
    print(
        f"\n{len(episodes)} moving-dot episodes ({sum(map(len, episodes))} steps): drafts from the previous actions "
        f"(prior), the draft head (chain / EAGLE-2 tree) or both, interleaved at every step:\n"
    )
    print(format_episode_report(results))


def _bench_episodes(args, parser) -> int:
    from .benchmark import episode_methods, format_episode_report, run_episode_benchmark
    from .speculative import DraftHead, DraftTreeConfig

    tree_settings = {k: v for k, v in (("top_k", args.tree_top_k), ("depth", args.tree_depth),
                                       ("total_tokens", args.tree_total_tokens)) if v is not None}  # fmt: skip
    try:
        tree = DraftTreeConfig(**tree_settings)
    except ValueError as error:
        parser.error(str(error))
    _check_draft_head_flag(args.draft_head, parser)
    if args.policy is not None:
        from .benchmark import policy_actor
        from .evaluation import record_observations
        from .policy import VLAPolicy

        policy = VLAPolicy.from_pretrained(args.policy)
        if args.draft_head:
            draft_head = _load_draft_head_for(policy, args.draft_head, parser)
        seeds = [args.seed_start + i for i in range(args.episodes)]
        episodes = record_observations(policy, args.tasks, seeds, args.steps)
        act, action_dim, head_name = policy_actor(policy), policy.config.action_tokens, args.draft_head
        if not args.draft_head:
            torch.manual_seed(args.seed)
            draft_head = DraftHead.from_target(policy.model, policy.action_tokenizer, policy.config.action_dim).eval()
            head_name = f"an untrained DraftHead (seed {args.seed})"
    else:
        from .benchmark import toy_actor, toy_episodes
        from .toy import ACTION_DIM

        pipeline = _load_pipeline(args.pipeline_dir, parser)
        draft_head = DraftHead.from_pretrained(args.draft_head).eval() if args.draft_head else pipeline.draft_head
        act, action_dim, episodes = toy_actor(pipeline), ACTION_DIM, toy_episodes(args.episodes)
        head_name = args.draft_head or f"{pipeline.output_dir}/draft_head"
    methods = episode_methods(draft_head, args.bin_tolerances, tree, args.chain_length or action_dim - 1)
    from .benchmark import ForwardClock

    target = policy.model if args.policy is not None else pipeline.target
    results = run_episode_benchmark(act, episodes, methods, action_dim, repeats=args.repeats, seed=args.seed,
                                    clock=ForwardClock(target))  # fmt: skip
    steps = sum(len(e) for e in episodes)
    print(
        f"\n{len(episodes)} episodes, {steps} steps x {args.repeats} repeats, {action_dim} action tokens per action, "
        f"{torch.get_num_threads()} CPU threads; draft head: {head_name}; tree: {tree}; methods interleaved in a "
        f"fresh random order at every step:\n"
    )
    print(format_episode_report(results))
    return 0


def _collect(args, parser) -> int:
    from .demonstrations import collect_demonstrations

    policy = None
    if args.policy is not None:
        from .policy import VLAPolicy

        policy = VLAPolicy.from_pretrained(args.policy)
    elif args.expert_mix is not None:
        parser.error("--expert-mix needs --policy (it mixes expert steps into the policy's rollouts)")
    # the image settings default to the driving policy's (it can only read what it was trained on)
    image_size = args.image_size or (policy.config.image_size if policy else EnvConfig.image_size)
    camera = args.camera or (policy.config.camera if policy else EnvConfig.camera)
    env_config = EnvConfig(image_size, camera, args.max_episode_steps, args.hand_start_noise)
    summary = collect_demonstrations(
        args.output_dir, args.tasks, args.episodes, env_config, args.seed_start, action_noise=args.action_noise,
        policy=policy, expert_mix=args.expert_mix or 0.0,
    )  # fmt: skip
    print(f"{summary.episodes_written} episodes written, {summary.episodes_present} in {args.output_dir}, "
          f"{summary.expert_failures} expert failures skipped")  # fmt: skip
    if policy is not None:
        print(f"the policy solved {summary.driven_successes} of the {summary.episodes_written} episodes it drove")
    return 0


def _train_vla(args, parser) -> int:
    from .demonstrations import dataset_info, dataset_stats, load_demonstrations
    from .envs.metaworld import SCENE_STATE_DIM, TASK_INSTRUCTIONS
    from .policy import VLAPolicy
    from .vla_training import train_vla

    if args.scene_loss_weight is not None and not args.scene_targets:
        parser.error("--scene-loss-weight needs --scene-targets (it weighs the scene-state tokens' loss)")
    _check_training_folder(Path(args.output_dir), args.resume, args.overwrite_output_dir, parser)
    weight = {} if args.scene_loss_weight is None else {"scene_loss_weight": args.scene_loss_weight}
    config = VLATrainingConfig(
        args.output_dir, max_steps=args.max_steps, batch_size=args.batch_size, learning_rate=args.learning_rate,
        eval_every=args.eval_every, save_every=args.save_every, resume=args.resume,
        overwrite_output_dir=args.overwrite_output_dir, seed=args.seed, **weight,
    )  # fmt: skip
    stats = dataset_stats(args.data)
    scene_stats = stats.scene_normalizer() if args.scene_targets else None  # before the slow load: fails fast
    action_stats, state_stats = stats.action, stats.state
    info = dataset_info(args.data)
    try:
        policy_config = VLAPolicyConfig(
            image_size=info["image_size"], camera=info["camera"], patch_size=args.patch_size,
            use_state=not args.no_state, vision_hidden_size=args.vision_hidden_size, vision_layers=args.vision_layers,
            text_hidden_size=args.text_hidden_size, text_layers=args.text_layers, chunk_length=args.chunk_length,
            scene_state_dim=SCENE_STATE_DIM if args.scene_targets else 0,
        )  # fmt: skip
    except ValueError as error:
        parser.error(str(error))
    source = None
    if args.init_from is not None:
        try:
            source = VLAPolicy.from_pretrained(args.init_from)
        except FileNotFoundError as error:
            parser.error(f"--init-from: {error}")
        if source.config.text_layers > policy_config.text_layers:
            parser.error(f"--init-from {args.init_from} has {source.config.text_layers} decoder layers: "
                         f"--text-layers must be at least that, got {args.text_layers}")  # fmt: skip
        # the source's tokens mean its bins: keep its normalisation
        action_stats, state_stats = source.action_normalizer, source.state_normalizer
        if args.scene_targets and source.scene_normalizer is not None:
            scene_stats = source.scene_normalizer
    demos = load_demonstrations(args.data, args.tasks)
    policy = VLAPolicy.build(
        list(TASK_INSTRUCTIONS.values()), action_stats, state_stats, policy_config, args.seed, scene_stats
    )
    metrics = train_vla(policy, demos, config, init_from=source)
    print(f"policy saved to {args.output_dir}: {metrics}")
    return 0


def _train_draft(args, parser) -> int:
    import shlex

    from .demonstrations import dataset_info
    from .policy import VLAPolicy
    from .policy_draft import DraftDataConfig, train_policy_draft_head
    from .training import DraftTrainingConfig

    _check_training_folder(Path(args.output_dir), args.resume, args.overwrite_output_dir, parser)
    try:
        data_config = DraftDataConfig(
            args.tasks, args.rollout_episodes, args.rollout_max_steps, args.rollout_seed_start,
            args.validation_episodes, args.validation_frames, args.demo_frames_per_task, seed=args.seed,
        )  # fmt: skip
        training_config = DraftTrainingConfig(
            args.output_dir, max_steps=args.max_steps, batch_size=args.batch_size, learning_rate=args.learning_rate,
            warmup_steps=args.warmup_steps, lr_schedule=args.lr_schedule, save_every=args.save_every,
            eval_every=args.eval_every, resume=args.resume, overwrite_output_dir=args.overwrite_output_dir,
            seed=args.seed,
        )  # fmt: skip
        for root in args.data or []:
            dataset_info(root)
    except (ValueError, FileNotFoundError) as error:
        parser.error(str(error))
    try:
        policy = VLAPolicy.from_pretrained(args.policy)
    except FileNotFoundError as error:
        parser.error(f"--policy: {error}")
    command = shlex.join(["hf-specvla", *args.argv])
    try:
        head = train_policy_draft_head(policy, training_config, data_config, args.data or [], args.num_draft_tokens,
                                       command=command)  # fmt: skip
    except FileExistsError as error:
        parser.error(str(error))
    print(f"draft head saved to {args.output_dir} ({head.num_parameters():,} parameters); see its README.md")
    return 0


def _compare(args, parser) -> int:
    from .comparison import CompareConfig, format_comparison, run_comparison
    from .policy import VLAPolicy
    from .speculative import DraftHead

    try:
        config = CompareConfig(args.tasks, args.episodes, args.methods, args.seed_start, args.max_episode_steps,
                               args.workers, args.threads, args.seed)  # fmt: skip
    except ValueError as error:
        parser.error(str(error))
    needs_head = [m.name for m in config.decoding_methods() if m.uses_draft_head]
    if needs_head and not args.draft_head:
        parser.error(f"methods {needs_head} draft with a draft head: pass --draft-head <folder>")
    if args.draft_head and not needs_head:
        logging.getLogger(__name__).warning("--draft-head %s is not used: none of the methods %s drafts with a head "
                                            "(head, tree, prior+head, prior+tree); it is ignored", args.draft_head,
                                            config.methods)  # fmt: skip
        args.draft_head = None
    _check_draft_head_flag(args.draft_head, parser)
    try:
        policy = VLAPolicy.from_pretrained(args.policy)
    except FileNotFoundError as error:
        parser.error(f"--policy: {error}")
    draft_head = DraftHead.from_pretrained(args.draft_head).eval() if args.draft_head else None
    try:
        summary = run_comparison(policy, config, args.output_dir, draft_head, args.policy, args.draft_head,
                                 overwrite=args.overwrite_output_dir)  # fmt: skip
    except (FileExistsError, ValueError) as error:
        parser.error(str(error))
    print(format_comparison(summary))
    print(f"table, JSON and plots in {args.output_dir}")
    return 0


def _eval_method(args, parser):
    """``eval --method``: the [`DecodingMethod`] it names (checked before anything loads), or None."""
    if args.method is None:
        return None
    from .comparison import DecodingMethod

    flags = [flag for flag, given in (("--action-prior", args.action_prior), ("--draft-tree", args.draft_tree),
             ("--num-draft-tokens", args.num_draft_tokens is not None),
             ("--bin-tolerance", args.bin_tolerance is not None)) if given]  # fmt: skip
    if flags:
        parser.error(f"--method {args.method} already says how to decode; drop {' / '.join(flags)}")
    try:
        method = DecodingMethod.parse(args.method)
    except ValueError as error:
        parser.error(f"--method: {error}")
    if method.uses_draft_head and not args.draft_head:
        parser.error(f"--method {method.name} drafts with the draft head: give --draft-head")
    return method


def _eval(args, parser) -> int:
    import json

    from .evaluation import evaluate, format_summary
    from .policy import VLAPolicy
    from .speculative import DraftHeadDrafter, DraftTreeConfig

    method = _eval_method(args, parser)
    if (args.bin_tolerance is not None) and not (args.draft_head or args.action_prior):
        parser.error("--bin-tolerance needs --draft-head and/or --action-prior (something to draft with)")
    if (args.num_draft_tokens is not None or args.draft_tree) and not args.draft_head:
        parser.error("--num-draft-tokens / --draft-tree need --draft-head")
    if args.num_draft_tokens is not None and args.draft_tree:
        parser.error("--num-draft-tokens sets a chain; --draft-tree drafts a tree: give one of them")
    _check_draft_head_flag(args.draft_head, parser)
    if args.video is not None:
        from .evaluation import check_video_path

        try:
            check_video_path(args.video)
        except ValueError as error:
            parser.error(f"--video: {error}")
    policy = VLAPolicy.from_pretrained(args.policy)
    generate_kwargs = {}
    if method is not None:
        widest = policy.action_tokenizer.n_bins - 1
        if method.bin_tolerance > widest:
            parser.error(f"--method {method.name}: the policy's {widest + 1} bins are at most {widest} apart; use "
                         f"r=0..{widest}")  # fmt: skip
        draft_head = _load_draft_head_for(policy, args.draft_head, parser) if method.uses_draft_head else None
        if args.draft_head and not method.uses_draft_head:
            logging.getLogger(__name__).warning("--method %s drafts without a head: --draft-head %s is not used",
                                                method.name,
                           args.draft_head)  # fmt: skip
        generate_kwargs = method.generate_kwargs(draft_head)
    elif args.draft_head:
        draft_head = _load_draft_head_for(policy, args.draft_head, parser)
        if args.draft_tree:
            generate_kwargs["assistant_model"] = DraftHeadDrafter(draft_head, tree=DraftTreeConfig())
        else:
            generate_kwargs["assistant_model"] = draft_head
            if args.num_draft_tokens is not None:
                generate_kwargs["num_draft_tokens"] = args.num_draft_tokens
    if args.action_prior:
        generate_kwargs["action_prior"] = True
    if args.bin_tolerance is not None:
        tolerance = args.bin_tolerance
        widest = policy.action_tokenizer.n_bins - 1
        if max(tolerance) > widest:
            parser.error(f"--bin-tolerance {' '.join(map(str, tolerance))}: the policy's {widest + 1} bins are at most "
                         f"{widest} apart (r={widest} already accepts any action token); use 0..{widest}")  # fmt: skip
        generate_kwargs["bin_tolerance"] = tolerance[0] if len(tolerance) == 1 else tolerance
    env_config = EnvConfig(policy.config.image_size, policy.config.camera, args.max_episode_steps)
    try:
        summary = evaluate(policy, args.tasks, args.episodes, args.output_dir, env_config, args.seed_start,
                           generate_kwargs, args.video, overwrite=args.overwrite_output_dir,
                           num_envs=args.num_envs)  # fmt: skip
    except FileExistsError as error:
        parser.error(str(error))
    print(format_summary(summary))
    calls = "one batched call decides the actions" if args.num_envs > 1 else "one call decides the action"
    chunk = f" of the next {policy.config.chunk_length} steps" if policy.config.chunk_length > 1 else ""
    print(f"ms/call: the median wall time of a policy call ({calls}{chunk} of {args.num_envs} environment(s))")
    print(json.dumps(summary["overall"]))
    return 0


def configure_logging(verbose: bool = False) -> None:
    """hf_specvla's own messages at INFO (DEBUG with ``-v``), each on its own line even while a progress bar is
    drawn; other libraries' INFO (OpenGL, accelerate, ...) and transformers' weight-loading bars are left out."""
    from transformers.utils import logging as transformers_logging

    from .progress import ProgressAwareHandler

    handler = ProgressAwareHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    for existing in [h for h in root.handlers if isinstance(h, ProgressAwareHandler)]:  # main() called again
        root.removeHandler(existing)
    root.addHandler(handler)
    root.setLevel(logging.WARNING)
    logging.getLogger("hf_specvla").setLevel(logging.DEBUG if verbose else logging.INFO)
    transformers_logging.disable_progress_bar()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="hf-specvla",
        description="Draft-head speculative decoding with relaxed action acceptance for VLA models.",
        epilog="examples:" + EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    commands = parser.add_subparsers(dest="command", required=True)

    demo = _subcommand(commands, "demo", "train a toy VLA target + draft head on the spot and benchmark them")
    demo.add_argument(
        "--output-dir", default="runs/toy", help="where target and draft head are kept (reused: same settings)"
    )
    demo.add_argument("--size", choices=sorted(SIZES), default="small", help="toy target size")
    demo.add_argument("--target-steps", type=int, default=300, help="toy target training steps")
    demo.add_argument("--draft-steps", type=int, default=800, help="draft head training steps")
    demo.add_argument(
        "--overwrite-output-dir", action="store_true", help="move a pipeline built with other settings aside"
    )
    demo.add_argument(
        "--episodes", type=NON_NEGATIVE, default=16, help="moving-dot episodes to replay (0: skip that table)"
    )
    _add_benchmark_arguments(demo)

    bench = _subcommand(commands, "benchmark", "benchmark a pipeline saved by `demo`")
    bench.add_argument("--pipeline-dir", required=True, help="a folder written by `hf-specvla demo`")
    _add_benchmark_arguments(bench)

    episodes = _subcommand(commands, "bench-episodes", "replay recorded episodes: greedy vs prior / head / tree drafts")
    source = episodes.add_mutually_exclusive_group(required=True)
    source.add_argument("--policy", help="a policy folder: record its greedy Meta-World rollouts, then replay them")
    source.add_argument("--pipeline-dir", help="a toy pipeline saved by `hf-specvla demo`: replay moving-dot episodes")
    episodes.add_argument("--tasks", nargs="+", default=["MT10"], help="with --policy: suites and/or task names")
    episodes.add_argument("--episodes", type=POSITIVE, default=1, help="episodes per task (toy: episodes in all)")
    episodes.add_argument(
        "--steps", type=POSITIVE, default=40, help="with --policy: steps recorded per episode (at most)"
    )
    episodes.add_argument(
        "--seed-start", type=NON_NEGATIVE, default=BENCH_SEED_START, help="with --policy: first rollout seed"
    )
    episodes.add_argument(
        "--bin-tolerances", type=NON_NEGATIVE, nargs="+", default=[0, 1, 2, 4, 8], help="r for the prior"
    )
    episodes.add_argument("--draft-head", default=None,
                          help="a DraftHead folder (default: an untrained head, seeded; toy: its own)")  # fmt: skip
    episodes.add_argument("--chain-length", type=POSITIVE, default=None,
                          help="draft-head chain length k (default: tokens per call - 1)")  # fmt: skip
    episodes.add_argument(
        "--tree-top-k", type=POSITIVE, default=None, help="EAGLE-2 tree top_k (default: DraftTreeConfig's)"
    )
    episodes.add_argument(
        "--tree-depth", type=POSITIVE, default=None, help="EAGLE-2 tree depth (default: DraftTreeConfig's)"
    )
    episodes.add_argument("--tree-total-tokens", type=POSITIVE, default=None, help="EAGLE-2 tree nodes kept")
    episodes.add_argument("--repeats", type=POSITIVE, default=1, help="timed passes over the episodes")
    episodes.add_argument("--threads", type=POSITIVE, default=None, help="torch CPU threads (default: torch's)")
    episodes.add_argument("--seed", type=int, default=0, help="random seed (method order, untrained head)")

    collect = _subcommand(commands, "collect", "record scripted-expert Meta-World demonstrations (Parquet; resumable)")
    collect.add_argument("--tasks", nargs="+", default=["MT10"], help="suites (MT10, MT50) and/or task names")
    collect.add_argument("--episodes", type=POSITIVE, default=50,
                         help="successful episodes per task (with --policy: episodes, failed ones kept)")  # fmt: skip
    collect.add_argument("--output-dir", required=True, help="dataset folder (resumes if it exists)")
    collect.add_argument("--image-size", type=int, default=None,
                         help=f"image side (px) (default: the --policy's, else {EnvConfig.image_size})")  # fmt: skip
    collect.add_argument("--camera", default=None, choices=CAMERAS,
                         help=f"camera to render from (default: the --policy's, else {EnvConfig.camera})")  # fmt: skip
    collect.add_argument("--seed-start", type=NON_NEGATIVE, default=0, help="first seed tried per task")
    collect.add_argument("--action-noise", type=float, default=0.0,
                         help="std of Gaussian noise added to the executed expert action (recorded actions stay "
                              "clean): recovery data for behaviour cloning (DART)")  # fmt: skip
    collect.add_argument("--hand-start-noise", type=float, default=EnvConfig.hand_start_noise,
                         help="metres: uniform per-axis offset of the hand's start position, drawn from the seed "
                              "(varied starts keep a cloned policy from copying the state's drift)")  # fmt: skip
    collect.add_argument("--max-episode-steps", type=int, default=EnvConfig.max_episode_steps, help="step limit")
    collect.add_argument("--policy", default=None,
                         help="DAgger: this policy folder drives, the expert labels the states it reaches")  # fmt: skip
    collect.add_argument("--expert-mix", type=float, default=None,
                         help="with --policy: probability that a step runs the expert instead (default 0)")  # fmt: skip
    collect.add_argument("--threads", type=POSITIVE, default=None, help="torch CPU threads (with --policy)")

    train = _subcommand(commands, "train-vla", "behaviour-clone an OpenVLA-style policy on demonstrations (resumable)")
    train.add_argument("--data", required=True, nargs="+",
                       help="folders written by `hf-specvla collect` (same image size and camera)")  # fmt: skip
    train.add_argument("--output-dir", required=True, help="the policy folder (and checkpoints)")
    train.add_argument("--tasks", nargs="+", default=None, help="train on these tasks only (default: all in --data)")
    train.add_argument("--max-steps", type=int, default=VLATrainingConfig.max_steps, help="optimizer steps")
    train.add_argument("--batch-size", type=int, default=VLATrainingConfig.batch_size, help="frames per step")
    train.add_argument("--learning-rate", type=float, default=VLATrainingConfig.learning_rate, help="peak AdamW lr")
    train.add_argument("--eval-every", type=int, default=VLATrainingConfig.eval_every, help="steps between validations")
    train.add_argument("--save-every", type=int, default=VLATrainingConfig.save_every, help="steps between checkpoints")
    train.add_argument("--patch-size", type=int, default=VLAPolicyConfig.patch_size,
                       help="ViT patch size (px): the image becomes (image size / patch size)^2 tokens")  # fmt: skip
    train.add_argument("--vision-hidden-size", type=int, default=VLAPolicyConfig.vision_hidden_size,
                       help="width of the vision encoder")  # fmt: skip
    train.add_argument("--vision-layers", type=int, default=VLAPolicyConfig.vision_layers,
                       help="transformer layers of the vision encoder")  # fmt: skip
    train.add_argument("--text-layers", type=POSITIVE, default=VLAPolicyConfig.text_layers,
                       help="decoder layers (its depth sets the cost of a decode step)")  # fmt: skip
    train.add_argument("--text-hidden-size", type=POSITIVE, default=VLAPolicyConfig.text_hidden_size,
                       help="decoder width")  # fmt: skip
    train.add_argument("--chunk-length", type=POSITIVE, default=VLAPolicyConfig.chunk_length,
                       help="actions predicted per call (an action chunk of H x action_dim tokens)")  # fmt: skip
    train.add_argument("--init-from", default=None,
                       help="start from this trained policy (same widths; its decoder layers spread over a "
                            "deeper one, new layers start as the identity; its statistics are kept)")  # fmt: skip
    train.add_argument("--no-state", action="store_true", help="do not give the proprio state to the model")
    train.add_argument("--scene-targets", action="store_true",
                       help="also learn to predict the object and goal positions (the data's scene_state column) "
                            "after the action tokens: an auxiliary target for the vision encoder; acting is "
                            "unchanged")  # fmt: skip
    train.add_argument("--scene-loss-weight", type=float, default=None,
                       help="weight of the scene-state loss against the action tokens' (with --scene-targets; "
                            f"default {VLATrainingConfig.scene_loss_weight})")  # fmt: skip
    _add_training_run_arguments(train, VLATrainingConfig.seed)

    draft = _subcommand(commands, "train-draft",
                        "train a draft head for a policy: self-distillation on its rollouts (resumable)")  # fmt: skip
    draft.add_argument("--policy", required=True, help="the policy folder (train-vla output)")
    draft.add_argument("--output-dir", required=True, help="the draft head folder (and checkpoints)")
    draft.add_argument("--tasks", nargs="+", default=["MT10"], help="suites and/or task names")
    draft.add_argument("--data", nargs="+", default=None,
                       help="also distil on frames of these `collect` folders (default: rollouts only)")  # fmt: skip
    draft.add_argument("--demo-frames-per-task", type=NON_NEGATIVE, default=DraftDataConfig.demo_frames_per_task,
                       help="with --data: frames sampled per task")  # fmt: skip
    draft.add_argument("--rollout-episodes", type=POSITIVE, default=DraftDataConfig.rollout_episodes,
                       help="greedy on-policy episodes per task (the last --validation-episodes held out)")  # fmt: skip
    draft.add_argument("--rollout-max-steps", type=POSITIVE, default=DraftDataConfig.rollout_max_steps,
                       help="steps kept per rollout")  # fmt: skip
    draft.add_argument("--rollout-seed-start", type=NON_NEGATIVE, default=DraftDataConfig.rollout_seed_start,
                       help="first rollout seed")  # fmt: skip
    draft.add_argument("--validation-episodes", type=POSITIVE, default=DraftDataConfig.validation_episodes,
                       help="held-out rollouts per task")  # fmt: skip
    draft.add_argument("--validation-frames", type=POSITIVE, default=DraftDataConfig.validation_frames,
                       help="held-out frames the engine validates on (evenly spread)")  # fmt: skip
    draft.add_argument("--num-draft-tokens", type=POSITIVE, default=None,
                       help="the head's default chain length k (default: tokens per call - 1)")  # fmt: skip
    draft.add_argument("--max-steps", type=POSITIVE, default=POLICY_DRAFT_DEFAULTS["max_steps"], help="optimizer steps")
    draft.add_argument("--batch-size", type=POSITIVE, default=POLICY_DRAFT_DEFAULTS["batch_size"],
                       help="sequences per step")  # fmt: skip
    draft.add_argument("--learning-rate", type=float, default=POLICY_DRAFT_DEFAULTS["learning_rate"],
                       help="peak AdamW learning rate")  # fmt: skip
    draft.add_argument("--lr-schedule", choices=("constant", "cosine"), default=POLICY_DRAFT_DEFAULTS["lr_schedule"],
                       help="after warm-up")  # fmt: skip
    draft.add_argument("--warmup-steps", type=NON_NEGATIVE, default=POLICY_DRAFT_DEFAULTS["warmup_steps"],
                       help="linear warm-up steps")  # fmt: skip
    draft.add_argument("--eval-every", type=NON_NEGATIVE, default=POLICY_DRAFT_DEFAULTS["eval_every"],
                       help="steps between validations (0: only at the end)")  # fmt: skip
    draft.add_argument("--save-every", type=NON_NEGATIVE, default=POLICY_DRAFT_DEFAULTS["save_every"],
                       help="steps between checkpoints (0: only the final head)")  # fmt: skip
    _add_training_run_arguments(draft, DraftTrainingConfig.seed)

    compare = _subcommand(commands, "compare",
                          "paired side-by-side of decoding methods on the same seeds (resumable)")  # fmt: skip
    compare.add_argument("--policy", required=True, help="a policy folder (train-vla output)")
    compare.add_argument("--draft-head", default=None, help="the DraftHead folder the head / tree methods use")
    compare.add_argument("--methods", nargs="+", default=list(CompareConfig.methods),
                         help="<drafters>[:r=<int>][,k=<int>], drafters one of " + ", ".join(DRAFTER_CHOICES)
                              + " (greedy always runs: the baseline)")  # fmt: skip
    compare.add_argument("--tasks", nargs="+", default=["MT10"], help="suites and/or task names")
    compare.add_argument("--episodes", type=POSITIVE, default=CompareConfig.episodes_per_task, help="seeds per task")
    compare.add_argument("--seed-start", type=NON_NEGATIVE, default=CompareConfig.seed_start, help="first seed")
    compare.add_argument("--max-episode-steps", type=POSITIVE, default=CompareConfig.max_episode_steps,
                         help="step limit")  # fmt: skip
    compare.add_argument("--workers", type=POSITIVE, default=CompareConfig.workers,
                         help="processes the seeds are split between (timings compared within a worker)")  # fmt: skip
    compare.add_argument("--threads", type=POSITIVE, default=CompareConfig.threads, help="torch CPU threads per worker")
    compare.add_argument("--seed", type=int, default=CompareConfig.order_seed, help="seeds the method order per seed")
    compare.add_argument("--output-dir", required=True, help="logs, summary.json, compare.md, plots (resumes)")
    compare.add_argument(
        "--overwrite-output-dir", action="store_true", help="move a folder holding another run aside, start over"
    )

    ev = _subcommand(commands, "eval", "roll a policy out on Meta-World and report per-task success (resumable)")
    ev.add_argument("--policy", required=True, help="a policy folder (train-vla output)")
    ev.add_argument("--tasks", nargs="+", default=["MT10"], help="suites and/or task names")
    ev.add_argument("--episodes", type=POSITIVE, default=20, help="episodes per task")
    ev.add_argument("--output-dir", required=True, help="episodes.jsonl + summary.json go here (resumes)")
    ev.add_argument("--seed-start", type=NON_NEGATIVE, default=EVAL_SEED_START, help="first evaluation seed")
    ev.add_argument("--max-episode-steps", type=int, default=EnvConfig.max_episode_steps, help="step limit")
    ev.add_argument("--video", default=None, help="save the first episode as .gif / .mp4")
    ev.add_argument(
        "--overwrite-output-dir", action="store_true", help="move a folder holding another run aside, start over"
    )
    ev.add_argument("--draft-head", default=None, help="speculative decoding with this DraftHead folder")
    ev.add_argument(
        "--bin-tolerance", type=NON_NEGATIVE, nargs="+", default=None, help="relaxed acceptance r (or one per dim)"
    )
    ev.add_argument("--num-draft-tokens", type=POSITIVE, default=None, help="chain length k (default: the head's)")
    ev.add_argument("--draft-tree", action="store_true", help="the draft head drafts an EAGLE-2 tree, not a chain")
    ev.add_argument("--method", default=None,
                    help="a decoding method as `compare` names it (e.g. prior+tree:r=4, head:k=3), instead of "
                         "--action-prior / --draft-tree / --num-draft-tokens / --bin-tolerance")  # fmt: skip
    ev.add_argument(
        "--action-prior",
        action="store_true",
        help="draft each action from the episode's previous actions (verified inside the prefill)",
    )
    ev.add_argument("--threads", type=POSITIVE, default=None, help="torch CPU threads")
    ev.add_argument(
        "--num-envs",
        type=POSITIVE,
        default=1,
        help="episodes run in lockstep, one batched policy call per step for all of them (same results, less wall "
        "time)",
    )

    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser.parse_args(argv)
    args.argv = argv
    configure_logging(args.verbose)
    if getattr(args, "threads", None) is not None:
        torch.set_num_threads(args.threads)

    if args.command == "collect":
        return _collect(args, collect)
    if args.command == "train-vla":
        return _train_vla(args, train)
    if args.command == "eval":
        return _eval(args, ev)
    if args.command == "train-draft":
        return _train_draft(args, draft)
    if args.command == "compare":
        return _compare(args, compare)
    if args.command == "bench-episodes":
        return _bench_episodes(args, episodes)

    from .toy import ToyTargetSize, build_toy_pipeline

    if args.command == "demo":
        size = ToyTargetSize(**SIZES[args.size])
        try:
            pipeline = build_toy_pipeline(args.output_dir, size, args.target_steps, args.draft_steps, seed=args.seed,
                                          overwrite=args.overwrite_output_dir)  # fmt: skip
        except FileExistsError as error:
            demo.error(str(error))
    else:
        pipeline = _load_pipeline(args.pipeline_dir, bench)
    _benchmark(pipeline, args)
    if args.command == "demo" and args.episodes:
        _demo_episodes(pipeline, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
