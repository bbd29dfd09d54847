"""The engine's own time between forwards (issue 66): on a tiny Llama whose forwards cost almost nothing, what a
compiled speculative call and round cost the host against transformers' compiled greedy decoding.

One process, one thread, interleaved (every round runs every method once, in a fresh random order; medians over the
rounds), every method compiled (static cache + ``CompileConfig``, inductor's default mode on the CPU):

* ``greedy:compile N``: transformers' compiled greedy for N = 1, 2 and 8 new tokens;
* ``drafts right``: the call's 8 greedy tokens drafted (7, the 8th is the bonus) and verified inside the prefill:
  one target forward, the least a speculative call can do;
* ``jacobi``: the target's own guesses (``JacobiDrafter``) on a random model: about one token a round, so the
  call is a prefill and a round per further token;
* ``head chain`` / ``head tree``: an untrained draft head's chain and EAGLE-2 tree (rarely accepted: rounds);
* ``drafts right B=4`` / ``jacobi B=4``: the same for a batch of 4 prompts;
* ``drafts right session`` / ``jacobi session`` / ``none session``: the same calls through a ``DecoderSession``
  (``generate``'s set-up done once, what a policy's calls run), ``none``: greedy through the engine, no drafts.

Per method: ms per call, target forwards per call (a round is one target forward), ms per round (the call over its
forwards), where a speculative call's time goes (the loop's own clock: transformers' generate around the loop, the
target forwards, drafting, the rest of the loop), and two marginal costs against the targets of issue 66: a
round's host time beyond the first forward, ``(jacobi - drafts right) / (jacobi's forwards - 1)``, against a compiled
greedy step, ``(greedy 8 - greedy 1) / 7``; and a right-drafts call against a 2-token compiled greedy call.

    python examples/benchmarks/host_overhead.py --json host.json
    python examples/benchmarks/host_overhead.py --small          # 4 methods, 3 rounds (the test's mode, ~2 min)
"""

from __future__ import annotations

import argparse
import json
import random
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch
import transformers
from transformers import LlamaConfig, LlamaForCausalLM

from hf_specvla import ActionTokenizer, DraftHead, DraftHeadDrafter, DraftTreeConfig, JacobiDrafter
from hf_specvla.speculative import DecoderSession, compiled_decoding_kwargs, enable_speculation

VOCAB = 512
NEW_TOKENS = 8
PROMPT = [1, 5, 17, 42, 99, 7, 23, 64]
#: where a speculative call's time goes (medians, ms): transformers' generate around the loop (its set-up: the
#: generation config, the static cache, logits processors), the target's forwards (the compiled call included), the
#: drafters, and the rest of the loop (trees, acceptance, commits, bookkeeping)
PARTS = ("generate_outside_loop", "target_forwards", "drafting", "loop_other")


def tiny_llama() -> LlamaForCausalLM:
    """A random 2-layer Llama of width 64: its forwards cost ~nothing, so a call's time is the host's."""
    torch.manual_seed(0)
    config = LlamaConfig(vocab_size=VOCAB, hidden_size=64, intermediate_size=128, num_hidden_layers=2,
                         num_attention_heads=4, num_key_value_heads=2, max_position_embeddings=256, bos_token_id=1,
                         eos_token_id=2, pad_token_id=0)  # fmt: skip
    return enable_speculation(LlamaForCausalLM(config).eval())


def methods(model: LlamaForCausalLM, small: bool) -> dict[str, Callable[[], object]]:
    """name -> a function running one call (returns generate's output), in the order they are warmed up."""
    compiled = compiled_decoding_kwargs("cpu")
    prompts = {1: torch.tensor([PROMPT]), 4: torch.tensor([PROMPT[:1] + [t + i for t in PROMPT[1:]] for i in range(4)])}
    common = dict(do_sample=False, return_dict_in_generate=True, **compiled)

    def call(batch: int = 1, new_tokens: int = NEW_TOKENS, **kwargs) -> Callable[[], object]:
        def run():
            with torch.no_grad():
                return model.generate(input_ids=prompts[batch], max_new_tokens=new_tokens, min_new_tokens=new_tokens,
                                      **common, **kwargs)  # fmt: skip

        return run

    def right_drafts(batch: int) -> torch.Tensor:
        """``[batch, NEW_TOKENS - 1]`` the first greedy tokens: all right, the last one is the bonus."""
        with torch.no_grad():
            greedy = model.generate(input_ids=prompts[batch], max_new_tokens=NEW_TOKENS, min_new_tokens=NEW_TOKENS,
                                    do_sample=False)  # fmt: skip
        return greedy[:, prompts[batch].shape[1] : -1]

    table = {"greedy:compile 1": call(new_tokens=1), "greedy:compile 2": call(new_tokens=2),
             "greedy:compile 8": call(), "drafts right": call(draft_ids=right_drafts(1)),
             "jacobi": call(assistant_model=JacobiDrafter())}  # fmt: skip
    if small:
        return table
    # the same calls through a decoder session (generate's set-up done once: what a policy's calls run)
    session = DecoderSession.of(model, max_new_tokens=NEW_TOKENS, min_new_tokens=NEW_TOKENS, **common)
    drafts = right_drafts(1)
    table["drafts right session"] = lambda: session.generate(prompts[1], draft_ids=drafts)
    table["jacobi session"] = lambda: session.generate(prompts[1], assistant_model=JacobiDrafter())
    table["none session"] = lambda: session.generate(prompts[1])  # greedy through the engine
    torch.manual_seed(2)
    head = DraftHead.from_target(model, ActionTokenizer(VOCAB), action_dim=7, draft_action_tokens_only=False).eval()
    table["head chain"] = call(assistant_model=DraftHeadDrafter(head))
    table["head tree"] = call(assistant_model=DraftHeadDrafter(head, tree=DraftTreeConfig(top_k=2, depth=3,
                                                                                          total_tokens=6)))  # fmt: skip
    table["drafts right B=4"] = call(batch=4, draft_ids=right_drafts(4))
    table["jacobi B=4"] = call(batch=4, assistant_model=JacobiDrafter())
    return table


def forwards_of(output, new_tokens: int) -> int:
    speculation = getattr(output, "speculation", None)
    return new_tokens if speculation is None else speculation.num_batch_forwards


def summarize(rows: dict[str, dict]) -> dict[str, float | None]:
    """The two comparisons of issue 66's targets, from the rows' medians (the round's None when Jacobi took one
    round)."""

    def ms(name: str) -> float:
        return rows[name]["ms_per_call"]

    greedy_step = (ms("greedy:compile 8") - ms("greedy:compile 1")) / (NEW_TOKENS - 1)
    jacobi_rounds = rows["jacobi"]["target_forwards_per_call"]
    round_ms = (ms("jacobi") - ms("drafts right")) / (jacobi_rounds - 1) if jacobi_rounds > 1 else None
    return {"greedy_step_ms": greedy_step, "speculative_round_ms": round_ms,
            "round_over_greedy_step": round_ms / greedy_step if round_ms is not None else None,
            "right_drafts_call_over_greedy_2": ms("drafts right") / ms("greedy:compile 2"),
            **({"right_drafts_session_call_over_greedy_2": ms("drafts right session") / ms("greedy:compile 2"),
                "none_session_call_over_greedy_8": ms("none session") / ms("greedy:compile 8")}
               if "drafts right session" in rows else {})}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=40, help="timed rounds (after one warm-up)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    parser.add_argument("--json", default=None, help="also write the results here")
    parser.add_argument("--small", action="store_true", help="greedy, right drafts and Jacobi only, 3 rounds")
    args = parser.parse_args()
    if args.rounds < 1:
        parser.error(f"--rounds must be >= 1, got {args.rounds}")
    if args.threads < 1:
        parser.error(f"--threads must be >= 1, got {args.threads}")
    if args.small:
        args.rounds = min(args.rounds, 3)
    torch.set_num_threads(args.threads)
    model = tiny_llama()
    table = methods(model, args.small)
    forwards, warm_up_s = {}, {}
    for name, run in table.items():  # warm-up: every graph compiled before any timing
        start = time.perf_counter()
        forwards[name] = forwards_of(run(), int(name.split()[-1]) if name.startswith("greedy") else NEW_TOKENS)
        warm_up_s[name] = time.perf_counter() - start
    times = {name: [] for name in table}
    parts = {name: {part: [] for part in PARTS} for name in table}  # the loop's own clock, speculative calls
    order, rng = list(table), random.Random(0)
    for _ in range(args.rounds):
        rng.shuffle(order)
        for name in order:
            start = time.perf_counter()
            output = table[name]()
            elapsed = time.perf_counter() - start
            times[name].append(1000 * elapsed)
            stats = getattr(output, "speculation", None)
            if stats is not None:
                loop = stats.total_seconds
                values = {"generate_outside_loop": elapsed - loop, "target_forwards": stats.target_seconds,
                          "drafting": stats.draft_seconds,
                          "loop_other": loop - stats.target_seconds - stats.draft_seconds}  # fmt: skip
                for part, seconds in values.items():
                    parts[name][part].append(1000 * seconds)
    rows = {}
    for name, values in times.items():
        ms = statistics.median(values)
        rows[name] = {"method": name, "ms_per_call": ms, "target_forwards_per_call": forwards[name],
                      "ms_per_round": ms / forwards[name], "warm_up_s": warm_up_s[name],
                      "parts_ms": {part: statistics.median(v) for part, v in parts[name].items() if v},
                      "samples_ms": values}  # fmt: skip
    summary = summarize(rows)
    print(f"\ntiny Llama (2 x 64), {args.threads} thread(s), torch {torch.__version__}, transformers "
          f"{transformers.__version__}, {args.rounds} interleaved rounds, medians:\n")  # fmt: skip
    print("| method | ms / call | target fwd / call | ms / round | generate outside the loop | target forwards | "
          "drafting | the loop's other |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for row in rows.values():
        split = " | ".join(f"{row['parts_ms'][part]:.2f}" if part in row["parts_ms"] else "" for part in PARTS)
        print(f"| {row['method']} | {row['ms_per_call']:.2f} | {row['target_forwards_per_call']} | "
              f"{row['ms_per_round']:.2f} | {split} |")  # fmt: skip
    round_ms, ratio = summary["speculative_round_ms"], summary["round_over_greedy_step"]
    round_text = "n/a (no call took more than one round)" if round_ms is None else f"{round_ms:.2f} ms ({ratio:.2f}x)"
    print(f"\na compiled greedy step: {summary['greedy_step_ms']:.2f} ms; a speculative round beyond the first "
          f"forward: {round_text}; a right-drafts call over a 2-token greedy call: "
          f"{summary['right_drafts_call_over_greedy_2']:.2f}x")  # fmt: skip
    if "right_drafts_session_call_over_greedy_2" in summary:
        print(
            f"through a decoder session: a right-drafts call over a 2-token greedy call "
            f"{summary['right_drafts_session_call_over_greedy_2']:.2f}x; greedy through the engine over "
            f"transformers' compiled greedy, 8 tokens: {summary['none_session_call_over_greedy_8']:.2f}x"
        )
    if args.json:
        Path(args.json).write_text(json.dumps({"settings": vars(args), "torch": torch.__version__,
                                               "transformers": transformers.__version__, "summary": summary,
                                               "rows": list(rows.values())}, indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
