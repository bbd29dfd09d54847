"""One-shot benchmark of speculative decoding on OpenVLA-7B against the greedy baselines a user has (issues 54, 66).

OpenVLA-7B through the port (``hf_specvla.openvla``) with openvla/openvla-7b's shapes, built in code (no file
needed; ``--config`` reads a config.json instead, ``--checkpoint`` loads a local checkpoint folder), random weights
(times only), bf16 on CUDA. Per batch size, in one process, interleaved (every round runs every method once, in a
fresh random order; medians over the rounds):

* ``greedy``: ``generate`` with plain greedy decoding (eager);
* ``greedy:compile``: transformers' compiled greedy (static cache + ``CompileConfig``: CUDA graphs on a GPU), whose
  prefill runs eagerly;
* ``none:compile``: the engine's own greedy decoding (no drafts: one token a verification), compiled, its prefill
  too: the greedy a GPU user would try with the prefill compiled and CUDA-graphed;
* ``drafts p=<p>``: the call's own greedy tokens (compiled greedy's when speculation is compiled: in bf16 a static
  cache and compiled kernels round near-ties unlike eager decoding) drafted with each token right with probability p
  (the others replaced by a wrong action token), verified inside the prefill, compiled (the prefill too): what
  ``exact``'s previous-action drafts cost when they are right that often;
* ``head chain``: an (untrained, unless ``--draft-head``) draft head's chain, compiled.

Every method is reported against the fastest of the three greedy baselines at its batch size (``vs fastest
greedy``, naming it). Per (method, batch size): ms per call, ms per action (a call decodes one action per row),
target forwards per call, ms per target forward, host syncs per round (``Tensor.item / tolist / ...`` counted by a
``TorchFunctionMode`` in one extra call of the same method, uncompiled: a compiled call's syncs are hidden in its
graphs), and how many tokens differ from eager greedy's and from compiled greedy's (fp32: none may, the script fails;
bf16: reported, as kernels round differently: a static cache and CUDA graphs are another rounding than eager
decoding).

One-shot safe: ``--budget-s`` covers everything after the model is built (warm-ups and compiles included); each
batch size gets an equal share of what is left when it starts, a method whose warm-up would not fit is skipped and
listed, a method that raises (in its warm-up or a timed round) is listed with its error and left out, and the JSON
is rewritten after every batch size (``"complete": false`` until the end). The random weights are seeded (the same
model every run).

    python examples/benchmarks/gpu_openvla.py --json gpu.json                  # OpenVLA-7B shapes, B 1 and 4
    python examples/benchmarks/gpu_openvla.py --batch-sizes 1 4 8 16 --budget-s 1500 --json gpu.json
    python examples/benchmarks/gpu_openvla.py --tiny      # a tiny random OpenVLA on the CPU (~1 min: what CI runs)
"""

from __future__ import annotations

import argparse
import json
import logging
import random
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import torch
import transformers

from hf_specvla import DraftHead, DraftHeadDrafter
from hf_specvla.openvla import OpenVLAConfig, OpenVLAForActionPrediction, VisionTowerSpec, register_vision_tower
from hf_specvla.speculative import NoDrafter, compiled_decoding_kwargs, enable_speculation
from hf_specvla.speculative.syncs import HostSyncCounter

logger = logging.getLogger("gpu_openvla")

#: "In: What action should the robot take to pick up the red block?\nOut:" (Llama-2 tokenizer)
PROMPT_IDS = [1, 512, 29901, 1724, 3158, 881, 278, 19964, 2125, 304, 5839, 701, 278, 2654, 2908, 29973, 13, 3744, 29901]
ACTION_DIM = 7
#: every call decodes one action per row, greedily
#: action statistics of the random models (the times do not depend on them)
PLACEHOLDER_STATS = {"bridge_orig": {"action": {"q01": [-1.0] * ACTION_DIM, "q99": [1.0] * ACTION_DIM}}}
#: the part of a batch size's share of the budget that warm-ups may start in (the rest times them)
WARM_UP_SHARE = 0.7
#: the methods every batch size warms up and times whatever the budget says (the speed-ups are over the fastest)
BASELINES = ("greedy", "greedy:compile", "none:compile")
#: rounds timed whatever the budget says, once the warm-ups are done (a round costs far less than a compile)
MIN_ROUNDS = 3
COMMON = dict(max_new_tokens=ACTION_DIM, min_new_tokens=ACTION_DIM, do_sample=False, return_dict_in_generate=True)


def openvla_7b_config() -> OpenVLAConfig:
    """openvla/openvla-7b's shapes without its files: config.json differs from the port's defaults (the Prismatic
    ``dinosiglip-vit-so-224px`` towers, the Llama-2-7B decoder) only in its padded vocabulary and its statistics; the
    statistics here are placeholders (the times do not depend on them)."""
    return OpenVLAConfig(norm_stats=PLACEHOLDER_STATS, text_config={"vocab_size": 32064, "pad_token_id": 32000})


def tiny_config() -> OpenVLAConfig:
    """A random OpenVLA small enough for a CPU test: tiny towers, 2 Llama layers of 64, the real vocabulary."""
    register_vision_tower("bench-tiny-dino", VisionTowerSpec(32, 3, 2, 64, class_token=True, num_register_tokens=4,
                          no_embed_class=True, layer_scale=True), exist_ok=True)  # fmt: skip
    register_vision_tower("bench-tiny-siglip", VisionTowerSpec(24, 3, 2, 40, attention_pool=True), exist_ok=True)
    text = dict(hidden_size=64, intermediate_size=128, num_hidden_layers=2, num_attention_heads=4, vocab_size=32064,
                pad_token_id=32000)  # fmt: skip
    return OpenVLAConfig(norm_stats=PLACEHOLDER_STATS, timm_model_ids=["bench-tiny-dino", "bench-tiny-siglip"],
                         image_sizes=[28, 28], text_config=text)  # fmt: skip


def build_model(args, device: torch.device, dtype: torch.dtype) -> OpenVLAForActionPrediction:
    if args.checkpoint:
        return OpenVLAForActionPrediction.from_pretrained(args.checkpoint, dtype=dtype).to(device).eval()
    if args.tiny:
        config = tiny_config()
    else:
        config = OpenVLAConfig.from_pretrained(args.config) if args.config else openvla_7b_config()
    config.text_config._attn_implementation = "sdpa"
    torch.manual_seed(0)  # the same random weights every run (their near-ties decide the forwards a call takes)
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


class Method(NamedTuple):
    """One way to decode: ``run()`` times a call; ``run_uncompiled()`` is the same call without compilation (for
    counting host syncs, which compiled graphs hide); ``graphs`` names what its warm-up compiles ("" for nothing
    beyond its own call): methods with the same name share those graphs, so only the first at a batch size pays."""

    run: Callable[[], object]
    run_uncompiled: Callable[[], object]
    graphs: str = ""


def baseline_methods(model, inputs: dict, device) -> dict[str, Method]:
    """name -> [`Method`] of the baselines (``BASELINES``): eager greedy, transformers' compiled greedy and the
    engine's compiled greedy (no drafts, its prefill compiled)."""
    return {
        "greedy": method(model, inputs, False),
        "greedy:compile": method(model, inputs, True, device=device),
        "none:compile": method(model, inputs, True, "engine greedy", device, assistant_model=NoDrafter()),
    }


def head_drafter(model, args) -> DraftHeadDrafter:
    """The head chain's drafter: ``--draft-head`` or an untrained head. Built once, before anything compiles:
    building a model of a new class grows a registry of transformers' that compiled graphs guard on
    (``_CAN_RECORD_REGISTRY``), so a head built after compiled greedy's warm-up recompiles its graph at its next call
    (6.5-8.6 s on an H200)."""
    if args.draft_head:
        head = DraftHead.from_pretrained(args.draft_head)
    else:
        head = DraftHead.from_target(model, model.action_tokenizer, ACTION_DIM)
    return DraftHeadDrafter(head.to(device=model.device, dtype=model.dtype).eval(), num_draft_tokens=ACTION_DIM - 1)


def speculative_methods(
    model, inputs: dict, reference_ids: torch.Tensor, chain: DraftHeadDrafter, args, device
) -> dict[str, Method]:  # fmt: skip
    """name -> [`Method`] of the speculative calls, in the order their warm-ups run (the most telling drafts first):
    drafts made from ``reference_ids`` ``[B, ACTION_DIM]`` (the greedy tokens the method is compared with)."""
    generator = torch.Generator().manual_seed(0)
    compile_it = not args.eager_speculation
    table = {}
    for p in sorted(args.right_probabilities, reverse=True):
        drafts = wrong_where(reference_ids[:, :-1], p, generator)
        table[f"drafts p={p:g}"] = method(model, inputs, compile_it, "verification", device, draft_ids=drafts)
    table["head chain"] = method(model, inputs, compile_it, "verification + head", device, assistant_model=chain)
    return table


def method(model, inputs: dict, compile_it: bool, graphs: str = "", device=None, **kwargs) -> Method:
    """``generate`` over ``inputs`` with ``kwargs``, compiled (static cache + ``CompileConfig``) or not."""

    def run(**extra):
        def call():
            with torch.no_grad():
                return model.generate(**inputs, **COMMON, **kwargs, **extra)

        return call

    if not compile_it:
        return Method(run(), run())
    return Method(run(**compiled_decoding_kwargs(device.type)), run(), graphs)


def forwards_of(output, tokens: int) -> int:
    speculation = getattr(output, "speculation", None)
    return tokens if speculation is None else speculation.num_batch_forwards


def new_tokens(output, prompt_length: int) -> torch.Tensor:
    """``[B, ACTION_DIM]`` the action tokens a call decoded."""
    return output.sequences[:, prompt_length : prompt_length + ACTION_DIM]


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default=None,
                        help="a config.json or its folder (default: openvla-7b's shapes, built in code)")  # fmt: skip
    parser.add_argument("--checkpoint", default=None, help="a local OpenVLA checkpoint folder (real weights)")
    parser.add_argument("--draft-head", default=None, help="a DraftHead folder for the head chain (default: untrained)")
    parser.add_argument("--batch-sizes", nargs="+", type=int, default=None,
                        help="robots per call (default: 1 4; with --tiny 1 2)")  # fmt: skip
    parser.add_argument("--right-probabilities", nargs="+", type=float, default=[0.5, 0.7, 0.9, 1.0],
                        help="per-token probability that a prefill draft is right")  # fmt: skip
    parser.add_argument("--rounds", type=int, default=20, help="timed rounds per batch size (after the warm-up)")
    parser.add_argument("--budget-s", type=float, default=420.0,
                        help="seconds for all after the model is built, warm-ups and compiles included")  # fmt: skip
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument("--json", default=None, help="also write the results here (after every batch size)")
    parser.add_argument("--eager-speculation", action="store_true",
                        help="speculative methods uncompiled (greedy:compile stays compiled)")  # fmt: skip
    parser.add_argument("--tiny", action="store_true", help="a tiny random OpenVLA on the CPU, 2 rounds, B 1 and 2")
    args = parser.parse_args()
    for p in args.right_probabilities:
        if not 0.0 <= p <= 1.0:
            parser.error(f"--right-probabilities are probabilities in [0, 1], got {p}")
    for b in args.batch_sizes or []:
        if b < 1:
            parser.error(f"--batch-sizes are robots per call (>= 1), got {b}")
    if args.rounds < 1:
        parser.error(f"--rounds must be >= 1, got {args.rounds}")
    if not 0 < args.budget_s < float("inf"):
        parser.error(f"--budget-s must be a positive number of seconds, got {args.budget_s}")
    if args.config and args.checkpoint:
        parser.error("give --config (random weights of that shape) or --checkpoint (a saved model), not both")
    if args.tiny:
        args.device, args.rounds = "cpu", 2
    args.batch_sizes = args.batch_sizes or ([1, 2] if args.tiny else [1, 4])
    return args


def timed(fn, device: torch.device) -> tuple[object, float]:
    """``fn()``'s result and its wall-clock seconds on ``device`` (synchronised before and after on CUDA)."""
    if device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    out = fn()
    if device.type == "cuda":
        torch.cuda.synchronize()
    return out, time.perf_counter() - start


class BatchSizeRun:
    """One batch size's share of the budget: warm-ups (compiles), tokens against greedy's, syncs, timed rounds.

    A method whose warm-up would not fit before ``warm_ups_end`` is skipped; one that raises (in its warm-up or a
    timed round) is listed with its error and left out, so that one method breaking on a device loses no other's
    figures.
    """

    def __init__(
        self, model, chain: DraftHeadDrafter, args, batch_size: int, warm_up_s: dict[str, float], warm_ups_end: float
    ):  # fmt: skip
        self.model, self.chain, self.args, self.batch_size = model, chain, args, batch_size
        self.warm_up_s = warm_up_s  # the longest warm-up of each method so far, across batch sizes
        self.warm_ups_end = warm_ups_end
        self.inputs = prompt(model, batch_size, model.device, model.dtype)
        self.prompt_length = self.inputs["input_ids"].shape[1]
        with torch.no_grad():
            self.greedy_ids = new_tokens(model.generate(**self.inputs, **COMMON), self.prompt_length)
        self.compiled_ids = None  # compiled greedy's tokens, once it has run
        self.ran: dict[str, Method] = {}
        self.skipped: list[str] = []
        self.graphs_compiled: set[str] = set()  # the `Method.graphs` warmed up at this batch size
        self.failed: dict[str, str] = {}
        self.forwards, self.syncs, self.departures, self.departures_compiled = {}, {}, {}, {}

    def warm_up_all(self) -> str:
        """Warms up the baselines, then the speculative methods; returns whose tokens the drafts were made from."""
        device = self.model.device
        for name, method in baseline_methods(self.model, self.inputs, device).items():
            self.warm_up(name, method)
        # drafts from the tokens of the greedy a method is compared with: compiled greedy's for compiled speculation
        # (in bf16 a static cache and compiled kernels round near-ties unlike eager decoding)
        compiled_speculation = not self.args.eager_speculation and self.compiled_ids is not None
        reference_ids = self.compiled_ids if compiled_speculation else self.greedy_ids
        speculative = speculative_methods(self.model, self.inputs, reference_ids, self.chain, self.args, device)
        for name, method in speculative.items():
            self.warm_up(name, method)
        return "greedy:compile" if compiled_speculation else "greedy"

    def warm_up(self, name: str, method: Method) -> None:
        """The method's first call (its compiles), its tokens against greedy's, the syncs of an uncompiled call."""
        # a method met before: its own warm-up; one whose graphs another method compiled at this batch size: none;
        # else the longest speculative warm-up so far, so that a ~200-300 s compile does not start with less left
        speculative = [seconds for other, seconds in self.warm_up_s.items() if other not in BASELINES]
        compiled_here = method.graphs and method.graphs in self.graphs_compiled
        expected_s = self.warm_up_s.get(name, 0.0 if compiled_here else max(speculative, default=0.0))
        if name not in BASELINES and time.perf_counter() + expected_s > self.warm_ups_end:
            self.skipped.append(name)
            return
        try:
            output, seconds = timed(method.run, self.model.device)
            with HostSyncCounter() as counter:
                method.run_uncompiled()
        except Exception as error:  # one-shot: a method that breaks on this device must not lose the others
            self.failed[name] = f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}"
            logger.exception("B=%d %s failed; left out", self.batch_size, name)
            return
        self.warm_up_s[name] = max(self.warm_up_s.get(name, 0.0), seconds)
        self.forwards[name] = forwards_of(output, ACTION_DIM)
        tokens = new_tokens(output, self.prompt_length)
        self.compiled_ids = tokens if name == "greedy:compile" else self.compiled_ids
        differ = int((tokens != self.greedy_ids).sum())
        compiled = None if self.compiled_ids is None else int((tokens != self.compiled_ids).sum())
        if differ and self.model.dtype == torch.float32:
            raise AssertionError(f"{name} at B={self.batch_size} decoded {differ} tokens unlike greedy's in fp32")
        self.departures[name], self.departures_compiled[name] = differ, compiled
        self.syncs[name] = counter.count
        self.ran[name] = method
        self.graphs_compiled.add(method.graphs)
        print(f"B={self.batch_size} {name}: warm-up {seconds:.1f} s, {self.forwards[name]} forwards, tokens unlike "
              f"greedy's {differ} (compiled greedy's {compiled}), {counter.count} syncs uncompiled",
              flush=True)  # fmt: skip

    def time_rounds(self, share_end: float) -> tuple[dict[str, list[float]], int]:
        """Interleaved rounds (every method once, in a fresh random order) until ``--rounds`` or ``share_end`` (at
        least ``MIN_ROUNDS``); returns each method's ms per call and the rounds run."""
        times = {name: [] for name in self.ran}
        order, rng, rounds_run, round_s = list(self.ran), random.Random(self.batch_size), 0, 0.0
        while rounds_run < self.args.rounds and (
            rounds_run < MIN_ROUNDS or time.perf_counter() + round_s < share_end
        ):  # fmt: skip
            round_started = time.perf_counter()
            rng.shuffle(order)
            for name in [name for name in order if name not in self.failed]:
                try:
                    times[name].append(1000 * timed(self.ran[name].run, self.model.device)[1])
                except Exception as error:  # e.g. a graph that breaks on a later replay: keep what it timed
                    self.failed[name] = f"{type(error).__name__} in round {rounds_run + 1}: {str(error)[:200]}"
                    logger.exception("B=%d %s failed in a timed round; left out", self.batch_size, name)
            rounds_run += 1
            round_s = time.perf_counter() - round_started
        return times, rounds_run

    def rows(self, times: dict[str, list[float]]) -> list[dict]:
        rows = []
        for name, values in times.items():
            ms = statistics.median(values) if values else None  # warmed up, but no round was timed
            rows.append({"method": name, "batch_size": self.batch_size, "ms_per_call": ms,
                         "ms_per_action": ms and ms / self.batch_size,
                         "target_forwards_per_call": self.forwards[name],
                         "ms_per_forward": ms and ms / self.forwards[name],
                         "syncs_per_round": self.syncs[name] / self.forwards[name],
                         "tokens_unlike_greedy": self.departures[name],
                         "tokens_unlike_greedy_compiled": self.departures_compiled[name],
                         "tokens": self.batch_size * ACTION_DIM,
                         "warm_up_s": self.warm_up_s[name], "samples_ms": values})  # fmt: skip
        return rows


def main() -> None:
    args = parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    dtype = torch.bfloat16 if device.type == "cuda" else torch.float32
    model = enable_speculation(build_model(args, device, dtype))
    chain = head_drafter(model, args)
    started = time.perf_counter()
    deadline = started + args.budget_s
    report = {"settings": vars(args), "device": str(device), "dtype": str(dtype), "complete": False,
              "device_name": torch.cuda.get_device_name() if device.type == "cuda" else "cpu",
              "torch": torch.__version__, "transformers": transformers.__version__,
              "batches": [], "rows": []}  # fmt: skip
    warm_up_s: dict[str, float] = {}
    for index, batch_size in enumerate(args.batch_sizes):
        share_start = time.perf_counter()
        share_end = share_start + (deadline - share_start) / (len(args.batch_sizes) - index)
        warm_ups_end = share_start + WARM_UP_SHARE * (share_end - share_start)
        run = BatchSizeRun(model, chain, args, batch_size, warm_up_s, warm_ups_end)
        drafts_from = run.warm_up_all()
        times, rounds_run = run.time_rounds(share_end)
        report["rows"].extend(run.rows(times))
        report["batches"].append({"batch_size": batch_size, "rounds_run": rounds_run, "skipped": run.skipped,
                                  "failed": run.failed, "drafts_from": drafts_from})  # fmt: skip
        report["elapsed_s"] = time.perf_counter() - started
        if args.json:  # after every batch size: a call cut short keeps what it measured
            Path(args.json).write_text(json.dumps(report, indent=2))
    report["complete"] = True
    report["fastest_greedy"] = {str(size): name for size, (name, _) in fastest_greedy(report["rows"]).items()}
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))
    print_table(report)


def fastest_greedy(rows: list[dict]) -> dict[int, tuple[str, float]]:
    """batch size -> (the fastest of the greedy baselines, its ms per call): what every method is compared with."""
    fastest: dict[int, tuple[str, float]] = {}
    for row in rows:
        ms, size = row["ms_per_call"], row["batch_size"]
        if row["method"] in BASELINES and ms is not None and (size not in fastest or ms < fastest[size][1]):
            fastest[size] = (row["method"], ms)
    return fastest


def print_table(report: dict) -> None:
    print(f"\n{report['device']} ({report['device_name']}), {report['dtype']}, torch {report['torch']}, "
          f"transformers {report['transformers']}, {report['elapsed_s']:.0f} s; medians:\n")  # fmt: skip
    for batch in report["batches"]:
        skipped = f", skipped (budget): {', '.join(batch['skipped'])}" if batch["skipped"] else ""
        failed = "".join(f"; {name} failed ({error})" for name, error in batch["failed"].items())
        print(f"B={batch['batch_size']}: {batch['rounds_run']} rounds, drafts from {batch['drafts_from']}'s tokens"
              f"{skipped}{failed}")  # fmt: skip
    print("\n| method | B | ms / call | ms / action | target fwd / call | ms / fwd | syncs / round (uncompiled) | "
          "tokens unlike greedy (eager / compiled) | vs fastest greedy |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    rows = report["rows"]
    fastest = fastest_greedy(rows)
    for size, (name, ms) in sorted(fastest.items()):
        print(f"B={size}: the fastest greedy is {name} ({ms:.1f} ms a call)")
    baseline = {size: ms for size, (_, ms) in fastest.items()}

    def number(value, suffix="") -> str:
        return "not timed" if value is None else f"{value:.{2 if suffix else 1}f}{suffix}"

    for row in rows:
        ms, base = row["ms_per_call"], baseline.get(row["batch_size"])
        versus = base / ms if ms and base else None
        print(f"| {row['method']} | {row['batch_size']} | {number(ms)} | {number(row['ms_per_action'])} | "
              f"{row['target_forwards_per_call']} | {number(row['ms_per_forward'])} | "
              f"{row['syncs_per_round']:.1f} | {row['tokens_unlike_greedy']} / "
              f"{row['tokens_unlike_greedy_compiled']} of {row['tokens']} | "
              f"{number(versus, 'x')} |")  # fmt: skip


if __name__ == "__main__":
    main()
