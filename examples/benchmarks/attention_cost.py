"""What shape-invariant (eager) attention costs against sdpa, per dtype: the price of
``enable_speculation(model, exact_reduced_precision=True)``, which switches a bf16 / fp16 target to eager attention so
that r=0 speculative decoding keeps greedy decoding's tokens at near-ties.

    python examples/benchmarks/attention_cost.py --policy policies/mt10_vla3 --tasks MT10 --steps 6 --repeats 2
    python examples/benchmarks/attention_cost.py --tiny   # a random 2-layer policy, seconds (plumbing, no speed)

Observations come from fp32 greedy rollouts of the policy; then every variant (dtype x attention) decodes each
observation with plain greedy decoding and with ``prior+jacobi`` (its own episode memory), interleaved, and the
median milliseconds per call are compared.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from hf_specvla.run_folder import write_json_atomic

ATTENTIONS = ("sdpa", "eager")
DTYPES = ("float32", "bfloat16")


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--policy", help="a VLAPolicy folder")
    source.add_argument("--tiny", action="store_true", help="a random 2-layer policy instead (seconds)")
    parser.add_argument("--tasks", nargs="+", default=["MT10"], help="suites and/or task names (default: MT10)")
    parser.add_argument("--steps", type=int, default=6, help="policy calls per episode (default: 6)")
    parser.add_argument("--repeats", type=int, default=2, help="interleaved passes over the calls (default: 2)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default: 1)")
    parser.add_argument("--output", default=None, help="also write the figures as JSON here")
    args = parser.parse_args(argv)
    if min(args.steps, args.repeats, args.threads) < 1:
        parser.error(f"--steps, --repeats and --threads must be >= 1, got {args.steps}, {args.repeats}, {args.threads}")
    if args.tiny:
        args.tasks, args.steps, args.repeats = ["reach-v3"], 2, 1
    return args


def load_policy(args):
    from hf_specvla.policies import VLAPolicy

    if not args.tiny:
        return VLAPolicy.from_pretrained(args.policy)
    from hf_specvla import ActionNormalizer
    from hf_specvla.policies import VLAPolicyConfig

    config = VLAPolicyConfig(image_size=32, patch_size=16, vision_hidden_size=32, vision_layers=1,
                             text_hidden_size=64, text_layers=2, text_heads=4)  # fmt: skip
    actions = ActionNormalizer(q01=[-1.0] * 4, q99=[1.0] * 4)
    states = ActionNormalizer(q01=[-0.5, 0.3, 0.0, 0.0], q99=[0.5, 1.0, 0.4, 1.0])
    return VLAPolicy.build(["reach the goal"], actions, states, config, seed=3)


def main(argv=None) -> dict:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    import copy

    from hf_specvla.metaworld.evaluation import record_observations
    from hf_specvla.metaworld.seeds import BENCH_SEED_START
    from hf_specvla.speculative import JacobiDrafter, enable_speculation

    source = load_policy(args)
    episodes = record_observations(source, args.tasks, [BENCH_SEED_START], args.steps)  # fp32 greedy
    variants = {}
    for dtype in DTYPES:
        for attention in ATTENTIONS:
            policy = copy.deepcopy(source)
            enable_speculation(policy.model, exact_reduced_precision=False)  # this script chooses the attention
            policy.model.to(getattr(torch, dtype)).set_attn_implementation(attention)
            variants[(dtype, attention)] = policy
    methods = {"greedy": {}, "prior+jacobi": {"action_prior": True, "assistant_model": JacobiDrafter()}}
    times = {(variant, method): [] for variant in variants for method in methods}
    for _ in range(args.repeats):
        for episode in episodes:
            memory = {key: [] for key in times}  # each variant and method keeps its own episode memory
            for obs in episode:
                for variant, policy in variants.items():
                    for method, kwargs in methods.items():
                        policy.previous_action_ids = memory[(variant, method)]
                        start = time.perf_counter()
                        policy.predict_action(obs["image"], obs["instruction"], obs["state"], **kwargs)
                        times[(variant, method)].append(time.perf_counter() - start)
                        memory[(variant, method)] = policy.previous_action_ids
    rows = []
    for dtype in DTYPES:
        for method in methods:
            sdpa, eager = (statistics.median(times[((dtype, a), method)]) * 1000 for a in ATTENTIONS)
            rows.append({"dtype": dtype, "method": method, "sdpa_ms": sdpa, "eager_ms": eager,
                         "eager_over_sdpa": eager / sdpa})  # fmt: skip
    calls = len(times[next(iter(times))])
    print(f"median ms per call over {calls} calls, interleaved, {args.threads} thread(s)")
    print("| dtype | method | sdpa | eager | eager / sdpa |")
    print("|---|---|---:|---:|---:|")
    for row in rows:
        print(f"| {row['dtype']} | {row['method']} | {row['sdpa_ms']:.2f} | {row['eager_ms']:.2f} | "
              f"{row['eager_over_sdpa']:.2f} |")  # fmt: skip
    result = {"calls": calls, "threads": args.threads, "rows": rows}
    if args.output:
        write_json_atomic(args.output, result)
    return result


if __name__ == "__main__":
    main()
