"""Speed benchmark: plain greedy vs speculative decoding, in one process, interleaved.

For every repeat and prompt, the methods run in a freshly shuffled order, so drift in machine load hits them
alike. Reported per method: median per-action latency, speed-up = median(greedy) / median(method), mean accept
length (tokens per target forward), where the time goes (target forwards / draft forwards / the rest), and how
far the actions moved from greedy's (mean and max bin distance; 0 for lossless methods).
"""

from __future__ import annotations

import random
import statistics
import time
from dataclasses import dataclass, field

import torch
from tqdm.auto import tqdm

from .action_tokenizer import ActionTokenizer
from .speculative import SpeculationStats


@dataclass
class Method:
    """One decoding configuration: a name and the extra ``generate`` keyword arguments it uses."""

    name: str
    generate_kwargs: dict = field(default_factory=dict)


@dataclass
class MethodResult:
    name: str
    latencies: list[float] = field(default_factory=list)
    stats: SpeculationStats | None = None
    bin_distances: list[int] = field(default_factory=list)

    @property
    def median_latency(self) -> float:
        return statistics.median(self.latencies)


def speculative_methods(draft_head, chain_lengths=(2, 4, 6), bin_tolerances=(1, 2, 4), relaxed_chain=6) -> list[Method]:
    """Greedy, strict chains of several lengths k, and relaxed acceptance at several r (chain ``relaxed_chain``)."""
    methods = [Method("greedy")]
    for k in chain_lengths:
        methods.append(Method(f"spec k={k} r=0", dict(assistant_model=draft_head, num_draft_tokens=k)))
    for r in bin_tolerances:
        kwargs = dict(assistant_model=draft_head, num_draft_tokens=relaxed_chain, bin_tolerance=r)
        methods.append(Method(f"spec k={relaxed_chain} r={r}", kwargs))
    return methods


@torch.no_grad()
def run_benchmark(
    target,
    prompts: list[dict],
    methods: list[Method],
    max_new_tokens: int,
    action_tokenizer: ActionTokenizer,
    repeats: int = 3,
    warmup: int = 2,
    seed: int = 0,
    progress: bool = True,
) -> list[MethodResult]:
    """Times every method on every prompt ``repeats`` times, interleaved. The first method is the baseline."""
    results = {m.name: MethodResult(m.name) for m in methods}
    base = dict(max_new_tokens=max_new_tokens, min_new_tokens=max_new_tokens, do_sample=False)
    for method in methods:  # warm-up: allocator, lazy init
        for prompt in prompts[:warmup]:
            target.generate(**prompt, **base, **method.generate_kwargs)
    rng = random.Random(seed)
    order = list(methods)
    for _ in tqdm(range(repeats), desc="benchmark", disable=not progress):
        for prompt in prompts:
            rng.shuffle(order)
            outputs = {}
            for method in order:
                start = time.perf_counter()
                out = target.generate(**prompt, **base, **method.generate_kwargs, return_dict_in_generate=True)
                results[method.name].latencies.append(time.perf_counter() - start)
                outputs[method.name] = out.sequences[:, -max_new_tokens:]
                spec = getattr(out, "speculation", None)
                if spec is not None:
                    prev = results[method.name].stats
                    results[method.name].stats = spec if prev is None else prev.merge(spec)
            reference = outputs[methods[0].name]
            for name, tokens in outputs.items():
                distance = action_tokenizer.bin_distance(tokens, reference)
                results[name].bin_distances.extend(distance.flatten().tolist())
    return [results[m.name] for m in methods]


def format_report(results: list[MethodResult]) -> str:
    """Markdown table of [`run_benchmark`] results; the first row is the baseline."""
    baseline = results[0].median_latency
    lines = [
        "| method | median ms/action | speed-up | mean accept length | target / draft / other time | "
        "bin distance to greedy (mean / max) |",
        "|---|---:|---:|---:|---|---|",
    ]
    for result in results:
        stats = result.stats
        if stats is None:
            accept, split = "1.00", "100% / 0% / 0%"
        else:
            total = stats.total_seconds or 1.0
            target_share, draft_share = stats.target_seconds / total, stats.draft_seconds / total
            accept = f"{stats.mean_accept_length:.2f}"
            split = f"{target_share:.0%} / {draft_share:.0%} / {1 - target_share - draft_share:.0%}"
        distances = result.bin_distances or [0]
        lines.append(
            f"| {result.name} | {1000 * result.median_latency:.2f} | {baseline / result.median_latency:.2f}x | "
            f"{accept} | {split} | {statistics.mean(distances):.2f} / {max(distances)} |"
        )
    return "\n".join(lines)
