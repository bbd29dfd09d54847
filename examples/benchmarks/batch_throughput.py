"""Actions per second of batched greedy vs batched speculative decoding, batch sizes 1, 4, 8, 16 (interleaved, in
one process): the table "Batched decoding" in docs/benchmarks.md.

B episodes are replayed in lockstep: each step, one call decodes the next action of all B episodes. On the
shipped Meta-World policy the episodes are recorded greedy rollouts (MT10, 2 seeds per task); on the toy target
they are the toy's moving-dot episodes. Every method keeps its own per-row action memory (the prior's drafts).
Methods run in a freshly shuffled order at every step, so machine-load drift hits them alike.

    python examples/benchmarks/batch_throughput.py --policy policies/mt10_vla3 --draft-head policies/mt10_vla3_draft_v2
    python examples/benchmarks/batch_throughput.py --toy runs/batch/toy_pipeline --steps 8
    python examples/benchmarks/batch_throughput.py --policy policies/mt10_vla3 \
        --draft-head policies/mt10_vla3_draft_v2 --steps 12 --methods greedy:compile prior+jacobi
    python examples/benchmarks/batch_throughput.py --policy policies/mt10_vla3 \
        --draft-head policies/mt10_vla3_draft_v2 --steps 12 \
        --methods greedy:compile prior+jacobi prior+jacobi:compile prior+jacobi:cap=2:compile --max-drafts-per-row 2
    python examples/benchmarks/batch_throughput.py --policy policies/mt10_vla3 \
        --draft-head policies/mt10_vla3_draft_v2 --steps 8 \
        --methods prior head prior:cap=1 prior:cap=2 head:cap=1 head:cap=2 --max-drafts-per-row 1 2
"""

from __future__ import annotations

import argparse
import json
import random
import statistics
import time

import numpy as np
import torch

from hf_specvla import ActionLayout, DraftHead, JacobiDrafter
from hf_specvla.speculative import as_drafter
from hf_specvla.speculative.compiled import compiled_decoding_kwargs
from hf_specvla.speculative.drafters import with_action_priors
from hf_specvla.speculative.generation import SPECULATION_KWARGS

#: bounds, not methods: "oracle" drafts this step's greedy action itself (the best any drafter can do: one target
#: forward per action, every row), "one-token" is greedy decoding stopped after ONE token (the prefill alone: no
#: decoder that runs the target can be faster)
BOUNDS = ("oracle", "one-token")


def methods(draft_head, bin_tolerance: int, caps: list[int] = (), only: list[str] | None = None) -> dict[str, dict]:
    """name -> generate kwargs ("oracle" gets its draft_ids at each step); ``caps``: also prior, prior+jacobi and head
    with at most that many drafts per row and forward (``max_drafts_per_row``); ``only``: these methods (and greedy).
    ``:compile``: on a static cache through transformers' compiled model call (greedy: transformers' own compiled
    decoding; the others: compiled batched verification)."""
    compiled = compiled_decoding_kwargs("cpu")
    relaxed = {"action_prior": True, "bin_tolerance": bin_tolerance}
    capped = {}
    for cap in caps:
        capped[f"prior:cap={cap}"] = {"action_prior": True, "max_drafts_per_row": cap}
        capped[f"prior+jacobi:cap={cap}"] = {"action_prior": True, "assistant_model": JacobiDrafter(),
                                             "max_drafts_per_row": cap}  # fmt: skip
        capped[f"head:cap={cap}"] = {"assistant_model": draft_head, "max_drafts_per_row": cap}
        capped[f"prior+jacobi:cap={cap}:compile"] = {**capped[f"prior+jacobi:cap={cap}"], **compiled}
    every = {
        "greedy": {},
        "greedy:compile": compiled,  # transformers' compiled greedy (static cache), batched
        "oracle": {},
        "one-token": {"max_new_tokens": 1, "min_new_tokens": 1},
        "prior": {"action_prior": True},
        f"prior:r={bin_tolerance}": relaxed,
        "prior+jacobi": {"action_prior": True, "assistant_model": JacobiDrafter()},
        "prior+jacobi:compile": {"action_prior": True, "assistant_model": JacobiDrafter(), **compiled},
        f"prior+jacobi:r={bin_tolerance}:compile": {**relaxed, "assistant_model": JacobiDrafter(), **compiled},
        "head": {"assistant_model": draft_head},
        f"head:r={bin_tolerance}": {"assistant_model": draft_head, "bin_tolerance": bin_tolerance},
        "head:compile": {"assistant_model": draft_head, **compiled},
        **capped,
    }
    return every if only is None else {name: every[name] for name in every if name == "greedy" or name in only}


def policy_target(args):
    from hf_specvla.metaworld.evaluation import record_observations
    from hf_specvla.policies import VLAPolicy

    policy = VLAPolicy.from_pretrained(args.policy)
    draft_head = DraftHead.from_pretrained(args.draft_head).eval()
    episodes = record_observations(policy, "MT10", [100_000, 100_001], max_steps=args.steps)

    def act(rows, memories, settings):
        observations = [episodes[e][t] for e, t in rows]
        kwargs = dict(settings)
        _, output = policy.predict_action(
            np.stack([o["image"] for o in observations]), [o["instruction"] for o in observations],
            np.stack([o["state"] for o in observations]), return_output=True, previous_action_ids=memories, **kwargs,
        )  # fmt: skip
        return output

    return act, episodes, draft_head, policy.config.action_tokens  # tokens per call (a chunk's, when chunked)


def toy_target(args):
    from hf_specvla.benchmarks.speed import toy_episodes
    from hf_specvla.benchmarks.toy import ACTION_DIM, build_toy_pipeline, toy_inputs

    pipeline = build_toy_pipeline(args.toy, progress=False)
    episodes = [e[: args.steps] for e in toy_episodes(16)]
    layout = ActionLayout(pipeline.action_tokenizer, ACTION_DIM)

    def act(rows, memories, settings):
        kwargs = dict(settings)
        prior = kwargs.pop("action_prior", False)
        head = as_drafter(kwargs.pop("assistant_model", None), None)
        drafter = with_action_priors(head, memories, layout) if prior else head
        if drafter is None:  # nothing to draft from: plain greedy
            kwargs = {k: v for k, v in kwargs.items() if k not in SPECULATION_KWARGS}
        else:
            kwargs.update(assistant_model=drafter, action_layout=layout)
        generate_kwargs = dict(max_new_tokens=ACTION_DIM, min_new_tokens=ACTION_DIM, do_sample=False,
                               return_dict_in_generate=True)  # fmt: skip
        generate_kwargs.update(kwargs)
        inputs = toy_inputs([episodes[e][t] for e, t in rows], pipeline.tokenizer)
        output = pipeline.target.generate(**inputs, **generate_kwargs)
        for memory, ids in zip(memories, output.sequences[:, -ACTION_DIM:].tolist()):
            memory[:] = [*memory, ids][-2:]
        return output

    return act, episodes, pipeline.draft_head, ACTION_DIM


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", help="a policy folder (with --draft-head)")
    parser.add_argument("--draft-head", help="the policy's draft head folder")
    parser.add_argument("--toy", help="a toy pipeline folder (built there if missing)")
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 4, 8, 16])
    parser.add_argument("--steps", type=int, default=24, help="steps replayed per episode")
    parser.add_argument("--bin-tolerance", type=int, default=4, help="the relaxed r")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--max-drafts-per-row", type=int, nargs="*", default=[],
                        help="also prior and head with at most this many drafts per row (e.g. 1 2)")  # fmt: skip
    parser.add_argument("--methods", nargs="+", default=None, help="only these methods (and greedy)")
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args()
    if any(cap < 0 for cap in args.max_drafts_per_row):
        parser.error(f"--max-drafts-per-row takes ints >= 0, got {args.max_drafts_per_row}")
    known = methods(None, args.bin_tolerance, args.max_drafts_per_row)
    unknown = sorted(set(args.methods or []) - set(known))
    if unknown:
        parser.error(f"--methods: unknown {unknown}; choose from {sorted(known)}")
    if (args.policy is None) == (args.toy is None) or (args.policy and not args.draft_head):
        parser.error("give --policy with --draft-head, or --toy")
    torch.set_num_threads(args.threads)
    random.seed(0)
    act, episodes, draft_head, action_dim = policy_target(args) if args.policy else toy_target(args)
    table = []
    for batch_size in args.batch_sizes:
        chosen = [e for e in range(len(episodes)) if len(episodes[e]) >= args.steps][:batch_size]
        if len(chosen) < batch_size:
            raise SystemExit(f"only {len(chosen)} episodes have {args.steps} steps; lower --steps or the batch size")
        settings = methods(draft_head, args.bin_tolerance, args.max_drafts_per_row, args.methods)
        memories = {name: [[] for _ in chosen] for name in settings}
        seconds = {name: [] for name in settings}
        row_forwards = {name: 0 for name in settings}
        batch_forwards = {name: 0 for name in settings}
        for name in settings:  # compiled methods compile their graphs for this B outside the timed steps
            if name.endswith(":compile"):
                act([(e, 0) for e in chosen], [[] for _ in chosen], settings[name])
        for step in range(args.steps):
            if "oracle" in settings:  # an untimed greedy call: the oracle's drafts
                greedy_ids = act([(e, step) for e in chosen], [[] for _ in chosen], {}).sequences[:, -action_dim:]
                settings["oracle"] = {"draft_ids": greedy_ids}
            order = list(settings)
            random.shuffle(order)
            for name in order:
                start = time.perf_counter()
                output = act([(e, step) for e in chosen], memories[name], settings[name])
                seconds[name].append(time.perf_counter() - start)
                stats = getattr(output, "speculation", None)
                tokens = 1 if name == "one-token" else action_dim
                row_forwards[name] += stats.num_target_forwards if stats else tokens * batch_size
                batch_forwards[name] += stats.num_batch_forwards if stats else tokens
        greedy_median = statistics.median(seconds["greedy"])
        compiled_median = statistics.median(seconds["greedy:compile"]) if "greedy:compile" in seconds else None
        for name in settings:
            median = statistics.median(seconds[name])
            table.append({
                "batch_size": batch_size, "method": name, "bound": name in BOUNDS,
                "median_ms_per_call": 1000 * median,
                "actions_per_second": batch_size / median, "vs_greedy": greedy_median / median,
                "vs_compiled_greedy": None if compiled_median is None else compiled_median / median,
                "target_forwards_per_action": row_forwards[name] / (batch_size * args.steps),
                "batch_forwards_per_step": batch_forwards[name] / args.steps,
                # a call's median time over its mean batch forwards: what one batch forward costs, loop included
                "ms_per_batch_forward": 1000 * median * args.steps / batch_forwards[name],
            })  # fmt: skip
            row = table[-1]
            print(f"B={batch_size:2d} {name:10s} {row['median_ms_per_call']:7.1f} ms/call "
                  f"{row['actions_per_second']:7.1f} actions/s {row['vs_greedy']:.2f}x "
                  f"{row['target_forwards_per_action']:.2f} fwd/action {row['batch_forwards_per_step']:.2f} "
                  f"batch fwd/step", flush=True)  # fmt: skip
    print("\n| B | method | ms per call (median) | actions/s | vs batched greedy | vs batched compiled greedy | "
          "target fwd/action | batch fwd/step | ms per batch fwd |")  # fmt: skip
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    for row in table:
        method = f"({row['method']}: bound)" if row["bound"] else row["method"]
        versus = "-" if row["vs_compiled_greedy"] is None else f"{row['vs_compiled_greedy']:.2f}x"
        print(f"| {row['batch_size']} | {method} | {row['median_ms_per_call']:.1f} | "
              f"{row['actions_per_second']:.0f} | {row['vs_greedy']:.2f}x | {versus} | "
              f"{row['target_forwards_per_action']:.2f} | {row['batch_forwards_per_step']:.2f} | "
              f"{row['ms_per_batch_forward']:.1f} |")  # fmt: skip
    if args.json:
        with open(args.json, "w") as file:
            json.dump({"args": vars(args), "rows": table}, file, indent=2)


if __name__ == "__main__":
    main()
