"""One-shot benchmark of speculative decoding on OpenVLA-7B against the greedy baselines a user has (issue 54).

OpenVLA-7B through the port (``hf_specvla.openvla``), built from the real ``openvla/openvla-7b`` config with random
weights (times only; ``--checkpoint`` loads a local checkpoint folder instead), in bf16 on CUDA. In one process,
interleaved (every round runs every (method, batch size) once, in a fresh random order; medians over the rounds):

* ``greedy``: ``generate`` with plain greedy decoding (eager);
* ``greedy:compile``: transformers' compiled greedy (static cache + ``CompileConfig``);
* ``drafts p=<p>``: the call's own greedy tokens drafted with each token right with probability p (the others
  replaced by a wrong action token), verified inside the prefill, compiled: what ``exact``'s previous-action drafts
  cost when they are right that often;
* ``head chain``: an (untrained, unless ``--draft-head``) draft head's chain, compiled.

Per (method, batch size): ms per call, ms per action (a call decodes one action per row), target forwards per call,
ms per target forward, and host syncs per round (``Tensor.item / tolist / cpu / numpy / __bool__ / __int__ /
__float__ / __index__`` counted by a ``TorchFunctionMode`` in one extra, untimed call). Whatever does not fit in
``--budget-s`` (rounds after the warm-up) is skipped, and the output says how many rounds ran.

    python examples/benchmarks/gpu_openvla.py --config ../shared/openvla-reference/hub-openvla-7b --json out.json
    python examples/benchmarks/gpu_openvla.py --tiny      # a tiny random OpenVLA on the CPU (~1 min: what CI runs)
"""

from __future__ import annotations

import argparse
import json
import random
import statistics
import time
from pathlib import Path

import torch

from hf_specvla import DraftHead, DraftHeadDrafter
from hf_specvla.openvla import OpenVLAConfig, OpenVLAForActionPrediction, VisionTowerSpec, register_vision_tower
from hf_specvla.speculative import compiled_decoding_kwargs, enable_speculation
from hf_specvla.speculative.syncs import HostSyncCounter

#: "In: What action should the robot take to pick up the red block?\nOut:" (Llama-2 tokenizer)
PROMPT_IDS = [1, 512, 29901, 1724, 3158, 881, 278, 19964, 2125, 304, 5839, 701, 278, 2654, 2908, 29973, 13, 3744, 29901]
ACTION_DIM = 7


def tiny_config() -> OpenVLAConfig:
    """A random OpenVLA small enough for a CPU test: tiny towers, 2 Llama layers of 64, the real vocabulary."""
    register_vision_tower("bench-tiny-dino", VisionTowerSpec(32, 3, 2, 64, class_token=True, num_register_tokens=4,
                          no_embed_class=True, layer_scale=True), exist_ok=True)  # fmt: skip
    register_vision_tower("bench-tiny-siglip", VisionTowerSpec(24, 3, 2, 40, attention_pool=True), exist_ok=True)
    stats = {"bridge_orig": {"action": {"q01": [-1.0] * ACTION_DIM, "q99": [1.0] * ACTION_DIM}}}
    text = dict(hidden_size=64, intermediate_size=128, num_hidden_layers=2, num_attention_heads=4, vocab_size=32064,
                pad_token_id=32000)  # fmt: skip
    return OpenVLAConfig(norm_stats=stats, timm_model_ids=["bench-tiny-dino", "bench-tiny-siglip"],
                         image_sizes=[28, 28], text_config=text)  # fmt: skip


def build_model(args, device: torch.device, dtype: torch.dtype) -> OpenVLAForActionPrediction:
    if args.checkpoint:
        return OpenVLAForActionPrediction.from_pretrained(args.checkpoint, dtype=dtype).to(device).eval()
    config = tiny_config() if args.tiny else OpenVLAConfig.from_pretrained(args.config)
    config.text_config._attn_implementation = "sdpa"
    with torch.device(device):
        torch.set_default_dtype(dtype)
        model = OpenVLAForActionPrediction(config).eval()
        torch.set_default_dtype(torch.float32)
    with torch.no_grad():  # random weights: make greedy decoding emit action tokens, as a trained OpenVLA does
        model.get_output_embeddings().weight[31744:32000] *= 4
    return model


def prompt(model: OpenVLAForActionPrediction, batch_size: int, device, dtype) -> dict:
    """OpenVLA's prompt (+ 29871, image tokens in place) for ``batch_size`` robots, random images."""
    ids = torch.tensor([PROMPT_IDS] * batch_size, device=device)
    input_ids, mask = model.add_image_tokens(*model.end_prompt(ids, torch.ones_like(ids)))
    size = model.config.image_sizes[0]
    generator = torch.Generator().manual_seed(batch_size)
    pixel_values = torch.randn(batch_size, 6, size, size, generator=generator).to(device=device, dtype=dtype)
    return {"input_ids": input_ids, "attention_mask": mask, "pixel_values": pixel_values}


def wrong_where(drafts: torch.Tensor, p: float, generator: torch.Generator) -> torch.Tensor:
    """``drafts`` with each token kept with probability ``p``, else moved to another action token."""
    keep = torch.rand(drafts.shape, generator=generator) < p
    moved = 31744 + (drafts.cpu() - 31744 + 1 + torch.randint(0, 254, drafts.shape, generator=generator)) % 256
    return torch.where(keep, drafts.cpu(), moved).to(drafts.device)


def methods(model, inputs: dict, args, device) -> dict:
    """name -> a function running one call (returns generate's output)."""
    compiled = compiled_decoding_kwargs(device.type)
    common = dict(max_new_tokens=ACTION_DIM, min_new_tokens=ACTION_DIM, do_sample=False, return_dict_in_generate=True)
    with torch.no_grad():
        greedy_ids = model.generate(**inputs, **common).sequences[:, inputs["input_ids"].shape[1] : -1]
    generator = torch.Generator().manual_seed(0)
    if args.draft_head:
        head = DraftHead.from_pretrained(args.draft_head)
    else:
        head = DraftHead.from_target(model, model.action_tokenizer, ACTION_DIM)
    chain = DraftHeadDrafter(head.to(device=device, dtype=model.dtype).eval(), num_draft_tokens=ACTION_DIM - 1)

    def call(**kwargs):
        def run():
            with torch.no_grad():
                return model.generate(**inputs, **common, **kwargs)

        return run

    table = {"greedy": call(), "greedy:compile": call(**compiled)}
    for p in args.right_probabilities:
        table[f"drafts p={p:g}"] = call(draft_ids=wrong_where(greedy_ids, p, generator), **compiled)
    table["head chain"] = call(assistant_model=chain, **compiled)
    return table


def forwards_of(output, tokens: int) -> int:
    speculation = getattr(output, "speculation", None)
    return tokens if speculation is None else speculation.num_batch_forwards


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="../shared/openvla-reference/hub-openvla-7b",
                        help="openvla-7b's folder or config.json (random weights of that shape)")  # fmt: skip
    parser.add_argument("--checkpoint", default=None, help="a local OpenVLA checkpoint folder (real weights)")
    parser.add_argument("--draft-head", default=None, help="a DraftHead folder for the head chain (default: untrained)")
    parser.add_argument("--batch-sizes", nargs="+", type=int, default=None,
                        help="robots per call (default: 1 4 8 16; with --tiny 1 2)")  # fmt: skip
    parser.add_argument("--right-probabilities", nargs="+", type=float, default=[0.5, 0.7, 0.9, 1.0],
                        help="per-token probability that a prefill draft is right")  # fmt: skip
    parser.add_argument("--rounds", type=int, default=20, help="timed rounds (after one warm-up round)")
    parser.add_argument("--budget-s", type=float, default=480.0, help="stop starting rounds past this many seconds")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument("--json", default=None, help="also write the results here")
    parser.add_argument("--tiny", action="store_true", help="a tiny random OpenVLA on the CPU, 2 rounds, B 1 and 2")
    args = parser.parse_args()
    for p in args.right_probabilities:
        if not 0.0 <= p <= 1.0:
            parser.error(f"--right-probabilities are probabilities in [0, 1], got {p}")
    if args.tiny:
        args.device, args.rounds = "cpu", 2
    args.batch_sizes = args.batch_sizes or ([1, 2] if args.tiny else [1, 4, 8, 16])
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    dtype = torch.bfloat16 if device.type == "cuda" else torch.float32
    started = time.perf_counter()
    model = enable_speculation(build_model(args, device, dtype))

    def synchronize():
        if device.type == "cuda":
            torch.cuda.synchronize()

    runs = {(name, b): fn for b in args.batch_sizes
            for name, fn in methods(model, prompt(model, b, device, dtype), args, device).items()}  # fmt: skip
    times = {key: [] for key in runs}
    forwards, syncs = {}, {}
    for key, run in runs.items():  # warm-up (compiles), then the syncs of one call, untimed
        forwards[key] = forwards_of(run(), ACTION_DIM)
        with HostSyncCounter() as counter:
            run()
        syncs[key] = counter.count
    order, rng, rounds_run = list(runs), random.Random(0), 0
    round_s = 0.0
    for _ in range(args.rounds):
        if time.perf_counter() - started + round_s > args.budget_s:
            break
        round_started = time.perf_counter()
        rng.shuffle(order)
        for key in order:
            synchronize()
            start = time.perf_counter()
            runs[key]()
            synchronize()
            times[key].append(1000 * (time.perf_counter() - start))
        rounds_run += 1
        round_s = time.perf_counter() - round_started
    rows = []
    for (name, b), values in times.items():
        if not values:
            continue
        ms = statistics.median(values)
        rows.append({"method": name, "batch_size": b, "ms_per_call": ms, "ms_per_action": ms / b,
                     "target_forwards_per_call": forwards[(name, b)],
                     "ms_per_forward": ms / forwards[(name, b)],
                     "syncs_per_round": syncs[(name, b)] / forwards[(name, b)]})  # fmt: skip
    print(f"\n{device} ({torch.cuda.get_device_name() if device.type == 'cuda' else 'cpu'}), {dtype}, "
          f"{rounds_run} of {args.rounds} rounds in {time.perf_counter() - started:.0f} s, medians:\n")  # fmt: skip
    print("| method | B | ms / call | ms / action | target fwd / call | ms / fwd | syncs / round | vs greedy:compile |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    baseline = {row["batch_size"]: row["ms_per_call"] for row in rows if row["method"] == "greedy:compile"}
    for row in rows:
        versus = baseline.get(row["batch_size"], float("nan")) / row["ms_per_call"]
        print(f"| {row['method']} | {row['batch_size']} | {row['ms_per_call']:.1f} | {row['ms_per_action']:.1f} | "
              f"{row['target_forwards_per_call']} | {row['ms_per_forward']:.1f} | {row['syncs_per_round']:.1f} | "
              f"{versus:.2f}x |")  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps({"settings": vars(args), "device": str(device), "dtype": str(dtype),
                                               "rounds_run": rounds_run, "rows": rows}, indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
