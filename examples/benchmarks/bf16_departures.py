"""How often r=0 speculative decoding departs from plain greedy decoding in reduced precision, per drafter, and at
what margins: the CPU test bed of the bf16 question (on a GPU in bf16, a multi-token verification forward rounds
differently from a one-token decode step, so near-tied argmaxes can flip).

    python examples/benchmarks/bf16_departures.py --policy policies/mt10_vla3 \\
        --draft-head policies/mt10_vla3_draft_v2 --tasks MT10 --episodes 1 --steps 20 --threads 1
    python examples/benchmarks/bf16_departures.py --policy policies/mt10_vla3 --draft-head policies/mt10_vla3_draft_v2 \
        --tasks MT10 --episodes 1 --steps 20 --threads 1 --exact-reduced-precision off   # sdpa attention
    python examples/benchmarks/bf16_departures.py --policy policies/mt10_vla3 --dtype float32   # the control: 0
    python examples/benchmarks/bf16_departures.py --policy policies/mt10_vla3 --reference greedy:compile \
        --methods prior+jacobi:compile   # against transformers' compiled greedy

Observations come from fp32 greedy rollouts of the policy (so they are real); then, in the chosen dtype, at every
observation plain greedy decoding and every method decode from the same episode memory (greedy's previous actions),
and each method's action tokens are compared with greedy's. A departure's margin is greedy's top-1 minus top-2
logit at the first token where they part. ``--exact-reduced-precision`` is ``enable_speculation``'s option (on: in
reduced precision the policy runs eager attention, for greedy and speculation alike; off: it keeps sdpa);
``--reference`` the greedy decoding the methods are compared with (eager greedy, or transformers' compiled greedy).
"""

from __future__ import annotations

import argparse
import statistics

import torch

from hf_specvla.run_folder import write_json_atomic

DEFAULT_METHODS = ("prior", "jacobi", "prior+jacobi", "tree", "prior+tree", "prior+jacobi:compile")
MARGIN_THRESHOLDS = (0.0625, 0.125, 0.25, 0.5)


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", required=True, help="a VLAPolicy folder")
    parser.add_argument("--draft-head", default=None, help="a DraftHead folder (for head / tree methods)")
    parser.add_argument("--tasks", nargs="+", default=["MT10"], help="suites and/or task names")
    parser.add_argument("--episodes", type=int, default=1, help="seeds per task (from 300000)")
    parser.add_argument("--steps", type=int, default=20, help="policy calls per episode")
    parser.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS), help="r=0 methods (compare's names)")
    parser.add_argument("--dtype", default="bfloat16", choices=("bfloat16", "float16", "float32"))
    parser.add_argument("--exact-reduced-precision", default="on", choices=("on", "off"),
                        help="enable_speculation's option: on = eager attention in bf16, off = keep sdpa")  # fmt: skip
    parser.add_argument("--reference", default="greedy", choices=("greedy", "greedy:compile"),
                        help="the greedy decoding every method is compared with")  # fmt: skip
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--output", default=None, help="also write the figures as JSON here")
    args = parser.parse_args(argv)
    if min(args.episodes, args.steps, args.threads) < 1:
        parser.error("--episodes, --steps and --threads must be >= 1")
    from hf_specvla.metaworld.comparison.methods import DecodingMethod

    try:
        args.methods = [DecodingMethod.parse(m, draft_head_given=args.draft_head is not None) for m in args.methods]
    except ValueError as error:
        parser.error(str(error))
    relaxed = [m.name for m in args.methods if not m.lossless]
    if relaxed:
        parser.error(f"departures are measured for r=0 methods; {relaxed} relax acceptance")
    if any(m.uses_draft_head for m in args.methods) and args.draft_head is None:
        parser.error("head / tree methods need --draft-head")
    return args


def margins(scores: tuple[torch.Tensor, ...]) -> list[float]:
    """Per generated token, the top-1 minus top-2 score (greedy's ``output_scores``)."""
    values = []
    for step in scores:
        top = step[0].float().topk(2).values
        values.append(float(top[0] - top[1]))
    return values


def main(argv=None) -> dict:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    from hf_specvla.metaworld.comparison.methods import DecodingMethod
    from hf_specvla.metaworld.evaluation import record_observations
    from hf_specvla.metaworld.seeds import BENCH_SEED_START
    from hf_specvla.policies import VLAPolicy
    from hf_specvla.speculative import DraftHead, enable_speculation

    policy = VLAPolicy.from_pretrained(args.policy)
    enable_speculation(policy.model, exact_reduced_precision=args.exact_reduced_precision == "on")
    seeds = [BENCH_SEED_START + i for i in range(args.episodes)]
    episodes = record_observations(policy, args.tasks, seeds, args.steps)  # fp32 greedy: real observations
    dtype = getattr(torch, args.dtype)
    policy.model.to(dtype)
    head = DraftHead.from_pretrained(args.draft_head).to(dtype).eval() if args.draft_head else None
    device = policy.model.device.type
    kwargs = {m.name: m.generate_kwargs(head, device, action_dim=policy.config.action_dim) for m in args.methods}
    reference = DecodingMethod.parse(args.reference).generate_kwargs(None, device)
    forwards = {m.name: 0 for m in args.methods}
    departed = {m.name: [] for m in args.methods}  # per call: None (same) or greedy's margin where they part
    all_margins: list[float] = []  # greedy's margin at every token: what a near-tie fallback would re-decide
    for episode in episodes:
        history: list[list[int]] = []
        for obs in episode:
            policy.previous_action_ids = list(history)
            _, greedy = policy.predict_action(obs["image"], obs["instruction"], obs["state"], return_output=True,
                                              output_scores=True, **reference)  # fmt: skip
            tokens = policy.config.action_tokens
            greedy_ids = greedy.sequences[0, -tokens:].tolist()
            greedy_margins = margins(greedy.scores)
            all_margins += greedy_margins
            for method in args.methods:
                policy.previous_action_ids = list(history)
                _, out = policy.predict_action(obs["image"], obs["instruction"], obs["state"], return_output=True,
                                               **kwargs[method.name])  # fmt: skip
                ids = out.sequences[0, -tokens:].tolist()
                first = next((i for i, (a, b) in enumerate(zip(ids, greedy_ids)) if a != b), None)
                departed[method.name].append(None if first is None else greedy_margins[first])
                stats = getattr(out, "speculation", None)  # None for plain greedy (and a prior's first step)
                forwards[method.name] += tokens if stats is None else stats.num_batch_forwards
            dim = policy.config.action_dim
            history = [*history, *(greedy_ids[i : i + dim] for i in range(0, tokens, dim))][-policy.HISTORY_LENGTH :]
    rows = []
    for name, calls in departed.items():
        parted = [m for m in calls if m is not None]
        rows.append({"method": name, "calls": len(calls), "departed": len(parted),
                     "margin_median": statistics.median(parted) if parted else None,
                     "margin_max": max(parted) if parted else None,
                     "target_forwards_per_call": forwards[name] / len(calls)})  # fmt: skip
    attention = policy.model.config._attn_implementation
    print(f"{args.dtype}, {attention} attention, {sum(len(e) for e in episodes)} calls, r=0, each method from the "
          f"reference's episode memory")  # fmt: skip
    print(f"| method | calls departed from {args.reference} | margin where they part (median / max) | "
          f"target fwd/call |")  # fmt: skip
    print("|---|---:|---|---:|")
    for row in rows:
        margin = "-" if not row["departed"] else f"{row['margin_median']:.3f} / {row['margin_max']:.3f}"
        share = f"{row['departed']}/{row['calls']} ({row['departed'] / row['calls']:.1%})"
        print(f"| {row['method']} | {share} | {margin} | {row['target_forwards_per_call']:.2f} |")
    below = {delta: sum(m < delta for m in all_margins) / len(all_margins) for delta in MARGIN_THRESHOLDS}
    print("greedy's tokens with a top-1 - top-2 margin below d (a fallback at margin d would re-decide them): "
          + ", ".join(f"d={d:g}: {share:.1%}" for d, share in below.items()))  # fmt: skip
    result = {"dtype": args.dtype, "attn_implementation": attention, "reference": args.reference, "rows": rows,
              "share_of_tokens_below_margin": below}  # fmt: skip
    if args.output:
        write_json_atomic(args.output, result)
    return result


if __name__ == "__main__":
    main()
