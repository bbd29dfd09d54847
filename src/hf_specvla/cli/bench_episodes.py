"""``hf-specvla bench-episodes``: replay recorded episodes (so the previous actions are real) and time greedy
against the action prior, the draft head's chain and its EAGLE-2 tree, interleaved at every step, with where the
time goes (vision, prefill, later forwards, drafting, the rest)."""

from __future__ import annotations

from ..metaworld.seeds import BENCH_SEED_START
from .benchmark import load_pipeline
from .common import (
    NON_NEGATIVE,
    POSITIVE,
    add_device_arguments,
    add_tree_arguments,
    check_bin_tolerances,
    check_draft_head_flag,
    check_tasks,
    load_draft_head,
    load_draft_head_for,
    load_policy,
    resolve_placement,
    usage_errors,
)

NAME = "bench-episodes"
HELP = "replay recorded episodes: greedy (eager and compiled) vs prior / head / tree drafts"
EXAMPLES = """
    # Replay recorded episodes (previous actions are real): greedy vs action prior vs draft head chain / tree
    hf-specvla bench-episodes --policy policies/mt10_vla --tasks MT10 --episodes 1 --steps 40 --threads 1
    hf-specvla bench-episodes --pipeline-dir policies/toy_dot --episodes 16 --threads 1
    # Eager rows only (no compilation)
    hf-specvla bench-episodes --pipeline-dir policies/toy_dot --episodes 4 --threads 1 --no-compile
    # On the CPU in float32 (default: auto, a GPU in bfloat16 when torch sees one)
    hf-specvla bench-episodes --pipeline-dir policies/toy_dot --episodes 2 --no-compile --device cpu --dtype float32
"""


def add_arguments(parser) -> None:
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--policy", help="a policy folder: record its greedy Meta-World rollouts, then replay them")
    source.add_argument(
        "--pipeline-dir", help="a toy pipeline (policies/toy_dot, or `demo --train`'s): replay moving-dot episodes"
    )
    parser.add_argument("--tasks", nargs="+", default=["MT10"], help="with --policy: suites and/or task names")
    parser.add_argument("--episodes", type=POSITIVE, default=1, help="episodes per task (toy: episodes in all)")
    parser.add_argument(
        "--steps", type=POSITIVE, default=40, help="with --policy: steps recorded per episode (at most)"
    )
    parser.add_argument(
        "--seed-start", type=NON_NEGATIVE, default=BENCH_SEED_START, help="with --policy: first rollout seed"
    )
    parser.add_argument(
        "--bin-tolerances", type=NON_NEGATIVE, nargs="+", default=[0, 1, 2, 4, 8], help="r for the prior"
    )
    parser.add_argument(
        "--draft-head", default=None, help="a DraftHead folder (default: an untrained head, seeded; toy: its own)"
    )
    parser.add_argument(
        "--chain-length", type=POSITIVE, default=None, help="draft-head chain length k (default: tokens per call - 1)"
    )
    add_tree_arguments(parser)
    parser.add_argument(
        "--no-compile",
        dest="compile",
        action="store_false",
        help="skip the compiled rows (transformers' greedy:compile and every method :compile, on a "
        "static cache; they compile on first use, off the clock)",
    )
    parser.add_argument("--repeats", type=POSITIVE, default=1, help="timed passes over the episodes")
    parser.add_argument("--threads", type=POSITIVE, default=None, help="torch CPU threads (default: torch's)")
    add_device_arguments(parser)
    parser.add_argument("--seed", type=int, default=0, help="random seed (method order, untrained head)")


def _check_bin_tolerances(args, n_bins: int, parser) -> None:
    check_bin_tolerances(
        args.bin_tolerances, n_bins, f"--bin-tolerances {' '.join(map(str, args.bin_tolerances))}", parser
    )


def _policy_episodes(args, parser, placement):
    """(act, action_dim, episodes, target, draft_head, head_name) for ``--policy``: its greedy rollouts recorded, the
    policy and head on ``placement``."""
    import torch

    from ..benchmarks.speed import policy_actor
    from ..metaworld.evaluation import record_observations
    from ..speculative import DraftHead

    policy = load_policy(args.policy, parser)
    _check_bin_tolerances(args, policy.action_tokenizer.n_bins, parser)  # before the rollouts are recorded
    if args.draft_head:
        draft_head, head_name = load_draft_head_for(policy, args.draft_head, parser), args.draft_head
    else:
        torch.manual_seed(args.seed)
        draft_head = DraftHead.from_target(policy.model, policy.action_tokenizer, policy.config.action_dim).eval()
        head_name = f"an untrained DraftHead (seed {args.seed})"
    placement.place_policy(policy, draft_head)  # after the head's check: it compares the weights as saved
    seeds = [args.seed_start + i for i in range(args.episodes)]
    episodes = record_observations(policy, args.tasks, seeds, args.steps)
    return policy_actor(policy), policy.config.action_tokens, episodes, policy.model, draft_head, head_name


def _toy_episodes(args, parser, placement):
    """The same for ``--pipeline-dir``: moving-dot episodes of a saved toy pipeline."""
    from ..benchmarks.speed import toy_actor, toy_episodes
    from ..benchmarks.toy import ACTION_DIM

    pipeline = load_pipeline(args.pipeline_dir, parser)
    _check_bin_tolerances(args, pipeline.action_tokenizer.n_bins, parser)
    draft_head = load_draft_head(args.draft_head, parser) if args.draft_head else pipeline.draft_head
    head_name = args.draft_head or f"{pipeline.output_dir}/draft_head"
    placement.move(pipeline.target, pipeline.draft_head, draft_head)
    return toy_actor(pipeline), ACTION_DIM, toy_episodes(args.episodes), pipeline.target, draft_head, head_name


def run(args, parser) -> int:
    import torch

    from ..benchmarks.speed import ForwardClock, episode_methods, format_episode_report, run_episode_benchmark
    from ..speculative import DraftTreeConfig

    check_tasks(args.tasks, parser)
    tree_settings = {
        k: v
        for k, v in (("top_k", args.tree_top_k), ("depth", args.tree_depth), ("total_tokens", args.tree_total_tokens))
        if v is not None
    }
    with usage_errors(parser, errors=(ValueError,)):
        tree = DraftTreeConfig(**tree_settings)
    check_draft_head_flag(args.draft_head, parser)
    placement = resolve_placement(args, parser)  # before anything loads
    source = _policy_episodes if args.policy is not None else _toy_episodes
    act, action_dim, episodes, target, draft_head, head_name = source(args, parser, placement)
    compiled_on = target.device.type if args.compile else None
    methods = episode_methods(draft_head, args.bin_tolerances, tree, args.chain_length or action_dim - 1, compiled_on)
    results = run_episode_benchmark(
        act, episodes, methods, action_dim, repeats=args.repeats, seed=args.seed, clock=ForwardClock(target)
    )
    steps = sum(len(e) for e in episodes)
    print(
        f"\n{len(episodes)} episodes, {steps} steps x {args.repeats} repeats, {action_dim} action tokens per action, "
        f"{torch.get_num_threads()} CPU threads, on {placement}; draft head: {head_name}; tree: {tree}; methods "
        f"interleaved in a fresh random order at every step:\n"
    )
    print(format_episode_report(results))
    return 0
