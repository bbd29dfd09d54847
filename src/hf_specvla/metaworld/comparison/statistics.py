"""A comparison's statistics: success with paired bootstrap intervals against greedy, speed-up, forwards per call
and per action, tokens per forward, bin deviation; the markdown table and the plots."""

from __future__ import annotations

import statistics
from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np

from .methods import COMPILED_GREEDY, GREEDY, DecodingMethod

BOOTSTRAP_RESAMPLES = 10_000
PLOTS = ("speedup_vs_r.png", "success_vs_r.png", "accept_lengths.png")


# ----------------------------------------------------------------------------- statistics
def paired_difference(
    method_success: list[bool], greedy_success: list[bool], resamples: int = BOOTSTRAP_RESAMPLES, seed: int = 0
) -> dict:
    """Success difference (method - greedy) over paired episodes, with a 95% percentile-bootstrap interval
    (pairs resampled with replacement) and the discordant counts.

    Returns:
        ``difference``, ``ci_low``, ``ci_high``, ``pairs``, ``greedy_only`` (greedy succeeded, the method failed),
        ``method_only`` (the reverse).
    """
    if len(method_success) != len(greedy_success) or not method_success:
        raise ValueError(
            f"paired outcomes must be two equally long, non-empty lists, got {len(method_success)} and "
            f"{len(greedy_success)}"
        )
    method = np.asarray(method_success, dtype=float)
    greedy = np.asarray(greedy_success, dtype=float)
    differences = method - greedy
    rng = np.random.default_rng(seed)
    means = differences[rng.integers(0, len(differences), (resamples, len(differences)))].mean(axis=1)
    low, high = np.percentile(means, [2.5, 97.5])
    return {
        "difference": float(differences.mean()), "ci_low": float(low), "ci_high": float(high),
        "pairs": len(differences), "greedy_only": int(((greedy == 1) & (method == 0)).sum()),
        "method_only": int(((method == 1) & (greedy == 0)).sum()),
    }  # fmt: skip


def summarize_comparison(records: list[dict], methods: list[str]) -> dict:
    """Per-method figures (see module docstring) from episode records; ``methods[0]`` must be greedy."""
    if not methods or methods[0] != GREEDY.name:
        raise ValueError(f"the first method must be greedy (the baseline), got {methods[:1]}")
    by_method: dict[str, dict[tuple[str, int], dict]] = {m: {} for m in methods}
    for record in records:
        if record["method"] in by_method:
            by_method[record["method"]][(record["task"], record["seed"])] = record
    greedy = by_method[GREEDY.name]
    compiled_greedy = by_method.get(COMPILED_GREEDY.name, {})
    summary: dict = {"methods": {}}
    for name in methods:
        episodes = by_method[name]
        if not episodes:
            continue
        method = DecodingMethod.parse(name)
        paired = sorted(key for key in episodes if key in greedy)
        latencies = [x for r in episodes.values() for x in r["latencies_ms"]]
        ratios = [
            statistics.median(greedy[key]["latencies_ms"]) / statistics.median(episodes[key]["latencies_ms"])
            for key in paired
        ]
        compiled_paired = [key for key in episodes if key in compiled_greedy]
        compiled_ratios = [
            statistics.median(compiled_greedy[key]["latencies_ms"]) / statistics.median(episodes[key]["latencies_ms"])
            for key in compiled_paired
        ]
        accept_counts: Counter = Counter()
        for record in episodes.values():
            accept_counts.update({int(k): v for k, v in record["accept_length_counts"].items()})
        forwards = sum(r["target_forwards"] for r in episodes.values())
        actions = sum(r["length"] for r in episodes.values())
        distance_count = sum(r["bin_distance_count"] for r in episodes.values())
        tasks = sorted({task for task, _ in episodes})
        row = {
            "drafters": method.drafters,
            "bin_tolerance": method.widest_tolerance,  # the largest r (per dimension or chunk step)
            # the method but its r: the curves of the plots (prior+jacobi, prior+jacobi:m=1, ...)
            "family": replace(method, bin_tolerance=0, later_tolerance=None).name,
            "episodes": len(episodes),
            "success_rate": statistics.mean(r["success"] for r in episodes.values()),
            "task_success_rates": {
                t: statistics.mean(r["success"] for (task, _), r in episodes.items() if task == t) for t in tasks
            },
            "mean_episode_length": statistics.mean(r["length"] for r in episodes.values()),
            "median_ms_per_call": statistics.median(latencies),  # one call decides one action, or one chunk
            "speedup": statistics.median(ratios) if ratios else None,
            # against transformers' compiled greedy decoding, when the comparison ran it (greedy:compile)
            "speedup_vs_greedy_compile": statistics.median(compiled_ratios) if compiled_ratios else None,
            "target_forwards_per_action": forwards / actions,  # per env step
            "target_forwards_per_call": forwards / len(latencies),
            "tokens_per_target_forward": sum(r["new_tokens"] for r in episodes.values()) / forwards,
            "accept_length_counts": {str(k): v for k, v in sorted(accept_counts.items())},
            "mean_bin_deviation": (
                sum(r["bin_distance_sum"] for r in episodes.values()) / distance_count if distance_count else 0.0
            ),  # fmt: skip
            "max_bin_deviation": max(r["bin_distance_max"] for r in episodes.values()),
            # the executed action's distance from greedy's on the same observation, per action dimension
            **_deviation_per_dim(list(episodes.values())),
            "identical_to_greedy": sum(episodes[k]["actions_digest"] == greedy[k]["actions_digest"] for k in paired),
        }
        if paired:
            row["vs_greedy"] = paired_difference(
                [episodes[k]["success"] for k in paired], [greedy[k]["success"] for k in paired]
            )
        summary["methods"][name] = row
    return summary


def _deviation_per_dim(records: list[dict]) -> dict:
    """Mean and max bin deviation per action dimension over relaxed episodes' records (logs written before the
    per-dimension fields existed give none)."""
    records = [r for r in records if "bin_distance_sum_per_dim" in r]
    count = sum(r["bin_distance_count"] for r in records)
    if not count:
        return {}
    dims = len(records[0]["bin_distance_sum_per_dim"])
    per_dim = count / dims  # every dimension has the same number of tokens
    return {
        "mean_bin_deviation_per_dim": [sum(r["bin_distance_sum_per_dim"][d] for r in records) / per_dim
                                       for d in range(dims)],
        "max_bin_deviation_per_dim": [max(r["bin_distance_max_per_dim"][d] for r in records) for d in range(dims)],
    }  # fmt: skip


def format_comparison(summary: dict) -> str:
    """The markdown table of a comparison summary."""
    lines = [
        "| method | episodes | success | vs greedy (95% CI) | greedy-only / method-only | mean length "
        "| median ms/call | speed-up | vs greedy:compile | target fwd/call | tokens/target fwd | bin dev. mean / max "
        "| deviation per dim. (mean) | identical to greedy |",
        "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---|---|---:|",
    ]
    for name, row in summary["methods"].items():
        paired = row.get("vs_greedy")
        if paired is None:
            versus, discordant = "-", "-"
        else:
            versus = f"{paired['difference']:+.1%} [{paired['ci_low']:+.1%}, {paired['ci_high']:+.1%}]"
            discordant = f"{paired['greedy_only']} / {paired['method_only']}"
        speedup = "-" if row["speedup"] is None else f"{row['speedup']:.2f}x"
        compiled = row.get("speedup_vs_greedy_compile")
        versus_compiled = "-" if compiled is None else f"{compiled:.2f}x"
        deviation = "-" if not row["bin_tolerance"] else f"{row['mean_bin_deviation']:.2f} / {row['max_bin_deviation']}"
        identical = f"{row['identical_to_greedy']}/{paired['pairs'] if paired else 0}"
        per_dim = row.get("mean_bin_deviation_per_dim")
        per_dim = "-" if not row["bin_tolerance"] or not per_dim else " / ".join(f"{d:.2f}" for d in per_dim)
        lines.append(
            f"| {name} | {row['episodes']} | {row['success_rate']:.1%} | {versus} | {discordant} "
            f"| {row['mean_episode_length']:.0f} | {row['median_ms_per_call']:.2f} | {speedup} | {versus_compiled} "
            f"| {row['target_forwards_per_call']:.2f} | {row['tokens_per_target_forward']:.2f} | {deviation} "
            f"| {per_dim} | {identical} |"
        )
    return "\n".join(lines)


# ----------------------------------------------------------------------------- plots
def _finish_plot(plt, figure, axis, baseline: float, ylabel: str, title: str, path: Path) -> None:
    """Greedy's level as a grey line, labels, legend; saves and closes the figure."""
    axis.axhline(baseline, color="grey", linewidth=0.8)
    axis.set(xlabel="bin tolerance r", ylabel=ylabel, title=title)
    axis.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def plot_comparison(summary: dict, output_dir: str | Path) -> list[Path]:
    """Writes the PNG plots of [`PLOTS`]: speed-up vs r and success difference vs r (95% CI) per drafter family,
    and each method's histogram of tokens per target forward."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    output_dir = Path(output_dir)
    rows = summary["methods"]
    families: dict[str, list[tuple[int, dict]]] = {}
    for row in rows.values():
        families.setdefault(row.get("family", row["drafters"]), []).append((row["bin_tolerance"], row))
    paths = [output_dir / name for name in PLOTS]

    figure, axis = plt.subplots(figsize=(6, 4))
    for family, points in families.items():
        points = sorted((r, row["speedup"]) for r, row in points if row["speedup"] is not None)
        axis.plot([p[0] for p in points], [p[1] for p in points], marker="o", label=family)
    _finish_plot(plt, figure, axis, 1.0, "speed-up vs greedy (per action)", "Speed-up", paths[0])

    figure, axis = plt.subplots(figsize=(6, 4))
    for offset, (family, points) in enumerate(families.items()):
        points = sorted((r, row["vs_greedy"]) for r, row in points if "vs_greedy" in row)
        x = [p[0] + 0.08 * offset for p in points]
        y = [100 * p[1]["difference"] for p in points]
        errors = [[100 * (p[1]["difference"] - p[1]["ci_low"]) for p in points],
                  [100 * (p[1]["ci_high"] - p[1]["difference"]) for p in points]]  # fmt: skip
        axis.errorbar(x, y, yerr=errors, marker="o", capsize=3, label=family)
    _finish_plot(plt, figure, axis, 0.0, "success - greedy's (points, 95% CI)", "Success, paired", paths[1])

    columns = min(3, len(rows))
    lines = -(-len(rows) // columns)
    figure, axes = plt.subplots(lines, columns, figsize=(3.2 * columns, 2.4 * lines), squeeze=False)
    for axis, (name, row) in zip(axes.flat, rows.items()):
        counts = {int(k): v for k, v in row["accept_length_counts"].items()}
        total = sum(counts.values())
        axis.bar(list(counts), [v / total for v in counts.values()])
        axis.set_title(name, fontsize=9)
        axis.set_xlabel("tokens per target forward", fontsize=8)
    for axis in list(axes.flat)[len(rows) :]:
        axis.set_visible(False)
    figure.tight_layout()
    figure.savefig(paths[2], dpi=120)
    plt.close(figure)
    return paths
