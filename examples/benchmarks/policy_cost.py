"""The cost structure of a Meta-World policy shape: is its decoder deep enough for a draft head to pay?

For each decoder shape (``LAYERSxWIDTH``), a random policy of the shipped policy's layout (64 px image, 16 image
tokens, the proprio state in the prompt, ``--chunk-length`` actions per call) and an untrained one-layer
``DraftHead.from_target``; on one CPU thread, each measurement repeated ``--repeats`` times, the measurements
interleaved in a fresh random order every round, medians reported:

* ``decode``: one target decode step (1 token against the prompt's KV cache);
* ``head step``: one level of the head's chain *as the engine runs it* (``DraftHeadDrafter`` session: head
  forward, scorer, top-k, masks), from proposals of depth k and 1: ``(t(k) - t(1)) / (k - 1)``; ``--heads v1 v2``
  times head v1 (the last hidden state) and head v2 (layers 2, middle and last fused, the previous action as input);
* ``prompt``: the prompt's forward with the image (the prefill); ``+16 drafted``: the same with 16 drafted
  tokens appended (what verifying drafts inside the prefill costs); ``+ v2 features``: the prompt's forward that
  also returns head v2's three hidden states, concatenated (what EAGLE-3 features cost the prefill);
* ``greedy call``: ``predict_action`` with plain greedy decoding (``chunk_length x 4`` tokens).

The ratios that decide (issue 22): ``head step / decode`` (at most ~10%) and ``+16 drafted / prompt`` (at most
~1.15x), with ``greedy call`` at most ~150 ms.

    python examples/benchmarks/policy_cost.py --decoders 3x192 8x192 12x192 16x192 --chunk-length 2
    python examples/benchmarks/policy_cost.py --decoders 16x192 --heads v1 v2
    python examples/benchmarks/policy_cost.py --tiny        # seconds: what CI runs (no timing is asserted)
"""

from __future__ import annotations

import argparse
import json
import random
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from transformers.cache_utils import DynamicCache

from hf_specvla import ActionNormalizer, DraftHead, DraftHeadDrafter
from hf_specvla.metaworld.env import TASK_INSTRUCTIONS
from hf_specvla.policies import VLAPolicy, VLAPolicyConfig
from hf_specvla.speculative import CACHE_KEY, read_hidden_states
from hf_specvla.speculative.cache import truncate_cache
from hf_specvla.speculative.drafter import Commit, DraftContext, DraftRound
from hf_specvla.training import head_v2_settings


def parse_decoder(text: str) -> tuple[int, int]:
    try:
        layers, width = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"a decoder is LAYERSxWIDTH, e.g. 12x192, got {text!r}") from None
    if layers < 1 or width < 6 or width % 6:
        raise argparse.ArgumentTypeError(f"layers >= 1 and a width that is a multiple of 6 (6 heads), got {text!r}")
    return layers, width


def random_policy(layers: int, width: int, chunk_length: int, seed: int) -> VLAPolicy:
    unit = ActionNormalizer(-np.ones(4), np.ones(4))
    config = VLAPolicyConfig(text_layers=layers, text_hidden_size=width, chunk_length=chunk_length)
    return VLAPolicy.build(list(TASK_INSTRUCTIONS.values()), unit, unit, config, seed)


def measurements(policy: VLAPolicy, draft_head: DraftHead, drafted: int, chain_depth: int) -> dict:
    """name -> a function timed by the caller (each leaves every cache as it found it)."""
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)
    instruction, state = TASK_INSTRUCTIONS["push-v3"], np.array([0.0, 0.6, 0.2, 0.5])
    model = policy.model
    input_ids = torch.tensor([policy.prompt_ids(instruction, state)])
    pixel_values = policy.preprocess_images(image)
    action_ids = torch.tensor(policy.action_token_ids(np.zeros((1, drafted // 4 + 1, 4))).reshape(1, -1)[:, :drafted])
    with torch.no_grad():
        cache = DynamicCache()
        prefill = model(input_ids=input_ids, pixel_values=pixel_values, **{CACHE_KEY: cache}, use_cache=True,
                        output_hidden_states=True)  # fmt: skip
    prompt_length = input_ids.shape[1]
    layers = draft_head.config.hidden_state_layers
    hidden = read_hidden_states(prefill.hidden_states, layers)  # [1, S, n H]: what a Commit carries
    context = DraftContext(model, policy.action_layout, [policy.tokenizer.eos_token_id], None)
    drafter = DraftHeadDrafter(draft_head, num_draft_tokens=chain_depth).with_previous_action(action_ids[0, :4])
    session = drafter.start(context)
    with torch.no_grad():  # the prefill's round: a head v2 learns where the generated tokens start
        session.propose(DraftRound(input_ids, 0, chain_depth, True, torch.tensor([[prompt_length - 1]])))
    next_ids = torch.cat([input_ids[:, 1:], action_ids[:, :1]], dim=1)
    session.observe(Commit(next_ids, torch.arange(prompt_length)[None], hidden, prompt_length))
    sequence = torch.cat([input_ids, action_ids[:, :1]], dim=1)
    root = torch.tensor([[prompt_length]])

    @torch.no_grad()
    def decode():
        model(input_ids=action_ids[:, :1], **{CACHE_KEY: cache}, use_cache=True)
        truncate_cache(cache, prompt_length)

    def propose(depth: int):
        @torch.no_grad()
        def run():
            session.propose(DraftRound(sequence, 1, depth, False, root))

        return run

    @torch.no_grad()
    def prompt():
        model(input_ids=input_ids, pixel_values=pixel_values)

    @torch.no_grad()
    def prompt_features():
        states = model(input_ids=input_ids, pixel_values=pixel_values, output_hidden_states=True).hidden_states
        read_hidden_states(states, head_v2_settings(model)["feature_layers"])

    @torch.no_grad()
    def prompt_drafted():
        model(input_ids=torch.cat([input_ids, action_ids], dim=1), pixel_values=pixel_values)

    def greedy_call():
        policy.predict_action(image, instruction, state)

    propose(1)()  # the catch-up over the prompt happens once, outside the clock
    return {"decode": decode, "propose 1": propose(1), f"propose {chain_depth}": propose(chain_depth),
            "prompt": prompt, f"+{drafted} drafted": prompt_drafted, "greedy call": greedy_call,
            "+ v2 features": prompt_features}  # fmt: skip


def measure(functions: dict, repeats: int, seed: int) -> dict[str, float]:
    """Median ms of each function, interleaved in a fresh random order every round (one warm-up round)."""
    order, times = list(functions), {name: [] for name in functions}
    rng = random.Random(seed)
    for round_index in range(repeats + 1):
        rng.shuffle(order)
        for name in order:
            start = time.perf_counter()
            functions[name]()
            if round_index:
                times[name].append(1000 * (time.perf_counter() - start))
    return {name: statistics.median(values) for name, values in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--decoders", nargs="+", type=parse_decoder, default=[(3, 192), (12, 192)],
                        help="decoder shapes LAYERSxWIDTH")  # fmt: skip
    parser.add_argument("--chunk-length", type=int, default=2, help="actions per policy call")
    parser.add_argument("--heads", nargs="+", choices=("v1", "v2"), default=["v1"], help="draft-head versions timed")
    parser.add_argument("--drafted", type=int, default=16, help="drafted tokens appended to the prompt's forward")
    parser.add_argument("--chain-depth", type=int, default=5, help="depth k of the chain proposal timed")
    parser.add_argument("--repeats", type=int, default=30, help="timed rounds")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--output", default=None, help="write the results as JSON here")
    parser.add_argument("--tiny", action="store_true", help="two tiny decoders, 2 rounds (CI: runs, asserts nothing)")
    args = parser.parse_args()
    if args.tiny:
        args.decoders, args.repeats, args.chain_depth, args.heads = [(1, 12), (2, 12)], 2, 2, ["v1", "v2"]
    torch.set_num_threads(args.threads)
    rows = []
    for (layers, width), head in [(decoder, head) for decoder in args.decoders for head in args.heads]:
        policy = random_policy(layers, width, args.chunk_length, seed=0)
        settings = head_v2_settings(policy.model) if head == "v2" else {}
        draft_head = DraftHead.from_target(policy.model, policy.action_tokenizer, 4, **settings).eval()
        median = measure(measurements(policy, draft_head, args.drafted, args.chain_depth), args.repeats, seed=0)
        head_step = (median[f"propose {args.chain_depth}"] - median["propose 1"]) / (args.chain_depth - 1)
        rows.append({
            "decoder": f"{layers}x{width}", "head": head, "decode_ms": median["decode"], "head_step_ms": head_step,
            "head_step_over_decode": head_step / median["decode"], "prompt_ms": median["prompt"],
            "drafted_over_prompt": median[f"+{args.drafted} drafted"] / median["prompt"],
            "features_over_prompt": median["+ v2 features"] / median["prompt"],
            "greedy_call_ms": median["greedy call"], "first_level_ms": median["propose 1"],
        })  # fmt: skip
    print(f"\n{args.repeats} interleaved rounds, {args.threads} thread(s), chunk_length {args.chunk_length} "
          f"({4 * args.chunk_length} tokens per call), medians:\n")  # fmt: skip
    print(f"| decoder | head | decode step | head step | head / decode | prompt forward | + {args.drafted} drafted | "
          "+ v2 features | greedy call |")  # fmt: skip
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for row in rows:
        print(f"| {row['decoder']} | {row['head']} | {row['decode_ms']:.2f} ms | {row['head_step_ms']:.2f} ms | "
              f"{100 * row['head_step_over_decode']:.0f}% | {row['prompt_ms']:.2f} ms | "
              f"{row['drafted_over_prompt']:.2f}x | {row['features_over_prompt']:.2f}x | "
              f"{row['greedy_call_ms']:.1f} ms |")  # fmt: skip
    if args.output:
        Path(args.output).write_text(json.dumps({"settings": vars(args) | {"decoders": [r["decoder"] for r in rows]},
                                                 "rows": rows}, indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
