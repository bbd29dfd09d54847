"""A comparison's statistics: success with paired bootstrap intervals against greedy, speed-up, forwards per call
and per action, tokens per forward, bin deviation; the markdown table and the plots.

Two speed-ups, both paired (a seed's methods run side by side in one worker):

* ``speedup_total`` (the headline; labelled "mean per call", its key kept for the files written before): greedy's
  mean ms per call over the paired episodes divided by the method's (for a lossless method, whose episodes make
  the same calls as greedy's, exactly the ratio of total decode times; for a method that makes more calls, higher
  than that ratio: ``figures.total_time_speedup`` computes the total-time ratio, sum over sum), with a 95% paired
  bootstrap interval over episodes ([`paired_speedup`]);
* ``speedup``: the median over episodes of (greedy's median ms per call / the method's), the figure reported before
  ``speedup_total`` existed: robust to a slow call, blind to how slow calls add up.

Each against eager greedy and, when the comparison ran it, transformers' compiled greedy (``greedy:compile``). The
summary keeps every timed episode's ms per call (``per_call_ms``, 0.01 ms, [`per_call_latencies`] reads them back),
so that any other statistic can be computed later."""

from __future__ import annotations

import statistics
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from .methods import COMPILED_GREEDY, GREEDY, CompareConfig, DecodingMethod

DEFAULT_MOTION_THRESHOLD = CompareConfig.motion_threshold

BOOTSTRAP_RESAMPLES = 10_000
#: resamples of the speed-up's paired bootstrap (a ratio of sums: each resample costs a gather over episodes)
SPEEDUP_RESAMPLES = 2_000
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
        "difference": float(differences.mean()),
        "ci_low": float(low),
        "ci_high": float(high),
        "pairs": len(differences),
        "greedy_only": int(((greedy == 1) & (method == 0)).sum()),
        "method_only": int(((method == 1) & (greedy == 0)).sum()),
    }


def paired_speedup(
    baseline_ms: Sequence[Sequence[float]],
    method_ms: Sequence[Sequence[float]],
    resamples: int = SPEEDUP_RESAMPLES,
    seed: int = 0,
) -> dict:
    """Speed-up of a method over a baseline from their paired episodes' per-call times: the baseline's mean ms per
    call over all the episodes divided by the method's (= the ratio of total decode times when both made the same
    calls), with a 95% percentile-bootstrap interval (the episode pairs resampled with replacement, ``seed`` fixed).

    Args:
        baseline_ms: per episode, the baseline's ms per call (episode i is paired with ``method_ms[i]``).
        method_ms: per episode, the method's ms per call (its number of calls may differ: a relaxed method's
            episode can end elsewhere).
    Returns:
        ``speedup``, ``ci_low``, ``ci_high``, ``pairs``.
    Raises:
        ValueError: the lists differ in length, are empty, or an episode has no calls.
    """
    if len(baseline_ms) != len(method_ms) or not baseline_ms:
        raise ValueError(
            f"paired timings must be two equally long, non-empty lists of episodes, got "
            f"{len(baseline_ms)} and {len(method_ms)}"
        )
    if any(len(episode) == 0 for episode in [*baseline_ms, *method_ms]):
        raise ValueError("every paired episode needs at least one timed call, got an episode with none")
    # per episode: total ms and number of calls, [pairs]
    base_total = np.array([np.sum(e, dtype=np.float64) for e in baseline_ms])
    base_calls = np.array([len(e) for e in baseline_ms], dtype=np.float64)
    method_total = np.array([np.sum(e, dtype=np.float64) for e in method_ms])
    method_calls = np.array([len(e) for e in method_ms], dtype=np.float64)

    def ratio(index):  # index: [..., pairs] episode indices -> the speed-up of those episodes, [...]
        base = base_total[index].sum(-1) / base_calls[index].sum(-1)
        return base / (method_total[index].sum(-1) / method_calls[index].sum(-1))

    pairs = len(base_total)
    rng = np.random.default_rng(seed)
    samples = ratio(rng.integers(0, pairs, (resamples, pairs)))  # [resamples]
    low, high = np.percentile(samples, [2.5, 97.5])
    return {"speedup": float(ratio(np.arange(pairs))), "ci_low": float(low), "ci_high": float(high), "pairs": pairs}


def format_per_call_ms(latencies_ms: Sequence[float]) -> str:
    """One episode's ms per call as compact text, 0.01 ms: ``"107.23 98.11 12.50"``."""
    return " ".join(f"{x:.2f}" for x in latencies_ms)


def per_call_latencies(summary: dict) -> dict[str, dict[tuple[str, int], list[float]]]:
    """A summary's ``per_call_ms`` read back: method -> (task, seed) -> ms per call (the episodes its speed figures
    are of), e.g. ``paired_speedup`` on them recomputes ``speedup_total`` (to the 0.01 ms rounding)."""
    latencies: dict[str, dict[tuple[str, int], list[float]]] = {}
    for method, episodes in summary.get("per_call_ms", {}).items():
        latencies[method] = {}
        for key, text in episodes.items():
            task, _, seed = key.rpartition(":")
            latencies[method][task, int(seed)] = [float(x) for x in text.split()]
    return latencies


def _speedups(baseline: dict, episodes: dict, timed_keys: set) -> tuple[float | None, dict | None]:
    """(median of per-episode median ratios, [`paired_speedup`]) of ``episodes`` over ``baseline`` on the pairs
    both timed under the folder's conditions; (None, None) without such pairs."""
    paired = sorted(key for key in episodes if key in baseline and key in timed_keys and baseline[key]["_timed"])
    paired = [key for key in paired if episodes[key]["latencies_ms"] and baseline[key]["latencies_ms"]]
    if not paired:
        return None, None
    ratios = [
        statistics.median(baseline[k]["latencies_ms"]) / statistics.median(episodes[k]["latencies_ms"]) for k in paired
    ]
    total = paired_speedup([baseline[k]["latencies_ms"] for k in paired], [episodes[k]["latencies_ms"] for k in paired])
    return statistics.median(ratios), total


def summarize_comparison(
    records: list[dict],
    methods: list[str],
    timed: Callable[[dict], bool] | None = None,
    motion_threshold: float = DEFAULT_MOTION_THRESHOLD,
) -> dict:
    """Per-method figures (see module docstring) from episode records; ``methods[0]`` must be greedy.

    Args:
        timed: whether a record's wall times enter the speed figures (timed under the folder's conditions); the
            others count for every other figure. Default: all do.
        motion_threshold: the size of greedy's action (policy's units) from which a motion is large, for
            [`deviation_by_phase`].
    """
    if not methods or methods[0] != GREEDY.name:
        raise ValueError(f"the first method must be greedy (the baseline), got {methods[:1]}")
    by_method: dict[str, dict[tuple[str, int], dict]] = {m: {} for m in methods}
    for record in records:
        if record["method"] in by_method:
            record = {**record, "_timed": True if timed is None else bool(timed(record))}
            by_method[record["method"]][(record["task"], record["seed"])] = record
    greedy = by_method[GREEDY.name]
    compiled_greedy = by_method.get(COMPILED_GREEDY.name, {})
    summary: dict = {"methods": {}, "per_call_ms": {}}
    for name in methods:
        episodes = by_method[name]
        if not episodes:
            continue
        method = DecodingMethod.parse(name, oracle=True)
        paired = sorted(key for key in episodes if key in greedy)
        timed_keys = {key for key, r in episodes.items() if r["_timed"]}
        latencies = [x for key in sorted(timed_keys) for x in episodes[key]["latencies_ms"]]
        calls = sum(len(r["latencies_ms"]) for r in episodes.values())
        speedup, speedup_total = _speedups(greedy, episodes, timed_keys)
        compiled_speedup, compiled_total = _speedups(compiled_greedy, episodes, timed_keys)
        summary["per_call_ms"][name] = {
            f"{task}:{seed}": format_per_call_ms(episodes[task, seed]["latencies_ms"])
            for task, seed in sorted(timed_keys)
        }
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
            "relaxed": not method.lossless,
            # the method but its r: the curves of the plots (prior+jacobi, prior+jacobi:m=1, ...)
            "family": replace(method, bin_tolerance=0, later_tolerance=None).name,
            "episodes": len(episodes),
            "success_rate": statistics.mean(r["success"] for r in episodes.values()),
            "task_success_rates": {
                t: statistics.mean(r["success"] for (task, _), r in episodes.items() if task == t) for t in tasks
            },
            "mean_episode_length": statistics.mean(r["length"] for r in episodes.values()),
            # speed: only episodes timed under the folder's conditions (and paired with a timed baseline episode)
            "timed_episodes": len(timed_keys),
            # one call decides one action, or one chunk
            "median_ms_per_call": statistics.median(latencies) if latencies else None,
            # greedy's mean ms per call / the method's (total decode time per call), 95% paired bootstrap interval
            "speedup_total": speedup_total,
            # the median over episodes of (greedy's median ms per call / the method's)
            "speedup": speedup,
            # the same two against transformers' compiled greedy decoding, when the comparison ran it (greedy:compile)
            "speedup_total_vs_greedy_compile": compiled_total,
            "speedup_vs_greedy_compile": compiled_speedup,
            "target_forwards_per_action": forwards / actions,  # per env step
            "target_forwards_per_call": forwards / calls,
            "tokens_per_target_forward": sum(r["new_tokens"] for r in episodes.values()) / forwards,
            "accept_length_counts": {str(k): v for k, v in sorted(accept_counts.items())},
            "mean_bin_deviation": (
                sum(r["bin_distance_sum"] for r in episodes.values()) / distance_count if distance_count else 0.0
            ),
            "max_bin_deviation": max(r["bin_distance_max"] for r in episodes.values()),
            # the executed action's distance from greedy's on the same observation, per action dimension
            **_deviation_per_dim(list(episodes.values())),
            # the same split by the size of greedy's action (where relaxation acts: transport or fine motions)
            "deviation_by_phase": deviation_by_phase(list(episodes.values()), motion_threshold),
            # per token position of a call: the share of calls whose token there was an accepted draft
            **_acceptance_by_position(list(episodes.values())),
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
        "mean_bin_deviation_per_dim": [
            sum(r["bin_distance_sum_per_dim"][d] for r in records) / per_dim for d in range(dims)
        ],
        "max_bin_deviation_per_dim": [max(r["bin_distance_max_per_dim"][d] for r in records) for d in range(dims)],
    }


def deviation_by_phase(records: list[dict], threshold: float = DEFAULT_MOTION_THRESHOLD) -> dict:
    """The deviation from greedy's action on the same observation, per action dimension, split by the size of greedy's
    action there: ``large`` where ``|greedy's value| >= threshold`` (policy's units), ``small`` elsewhere. Per phase:
    ``tokens_per_dim``, ``mean_bins_per_dim``, ``mean_units_per_dim`` (bins x the dimension's bin width),
    ``max_bins_per_dim`` and ``changed_per_dim`` (the share of tokens that differ from greedy's). Logs written before
    the per-token fields existed give none."""
    records = [r for r in records if r.get("reference_magnitudes")]
    if not records:
        return {}
    dims = len(records[0]["bin_widths"])
    phases: dict = {}
    for phase in ("large", "small"):
        tokens, total, changed, largest = [0] * dims, [0] * dims, [0] * dims, [0] * dims
        for record in records:
            for i, (distance, size) in enumerate(zip(record["bin_distances"], record["reference_magnitudes"])):
                if (size >= threshold) == (phase == "large"):
                    d = i % dims
                    tokens[d] += 1
                    total[d] += distance
                    changed[d] += distance > 0
                    largest[d] = max(largest[d], distance)
        widths = records[0]["bin_widths"]
        phases[phase] = {
            "tokens_per_dim": tokens,
            "mean_bins_per_dim": [t / n if n else 0.0 for t, n in zip(total, tokens)],
            "mean_units_per_dim": [t * w / n if n else 0.0 for t, w, n in zip(total, widths, tokens)],
            "max_bins_per_dim": largest,
            "changed_per_dim": [c / n if n else 0.0 for c, n in zip(changed, tokens)],
        }
    return {"threshold": threshold, **phases}


def format_deviation_by_phase(summary: dict) -> str:
    """A markdown table: per relaxed method and phase, the mean bin deviation per dimension and the share changed."""
    rows = [
        (name, row["deviation_by_phase"]) for name, row in summary["methods"].items() if row.get("deviation_by_phase")
    ]
    if not rows:
        return ""
    threshold = rows[0][1]["threshold"]
    lines = [
        f"Deviation from greedy's action on the same observation, by the size of greedy's action (large: |value| >= "
        f"{threshold:g} in the policy's units): mean bins per dimension (share of tokens changed), tokens",
        "",
        "| method | phase | mean bins per dim. (changed) | mean units per dim. | tokens |",
        "|---|---|---|---|---:|",
    ]
    for name, phases in rows:
        for phase in ("large", "small"):
            figures = phases[phase]
            per_dim = " / ".join(
                f"{m:.2f} ({c:.0%})" for m, c in zip(figures["mean_bins_per_dim"], figures["changed_per_dim"])
            )
            units = " / ".join(f"{u:.4f}" for u in figures["mean_units_per_dim"])
            lines.append(f"| {name} | {phase} | {per_dim} | {units} | {sum(figures['tokens_per_dim'])} |")
    return "\n".join(lines)


def _acceptance_by_position(records: list[dict]) -> dict:
    """The share of calls whose token at each position of the call was a drafted token the target accepted (the
    rest are the target's own tokens: after a rejection, or the bonus token that ends every forward); logs written
    before the field existed give none."""
    records = [r for r in records if "accepted_by_position" in r]
    calls = sum(len(r["latencies_ms"]) for r in records)
    if not calls:
        return {}
    positions = len(records[0]["accepted_by_position"])
    return {
        "accepted_by_position": [sum(r["accepted_by_position"][p] for r in records) / calls for p in range(positions)]
    }


def format_acceptance_by_position(summary: dict) -> str:
    """Markdown table: per method, the share of calls that took an accepted draft at each token position of a call
    (columns named by action and dimension, ``a0.x``, ``a0.gripper``, ``a1.x``, ..., for a known action layout;
    ``t0``, ``t1``, ... without the summary's ``action_dim``); empty when no method recorded it."""
    from ...policies.decoding_methods import ACTION_LAYOUTS

    rows = {
        name: row["accepted_by_position"] for name, row in summary["methods"].items() if row.get("accepted_by_position")
    }
    if not rows:
        return ""
    positions = len(next(iter(rows.values())))
    action_dim = summary.get("action_dim") or positions
    names = ACTION_LAYOUTS.get(action_dim, tuple(f"d{d}" for d in range(action_dim)))
    if "action_dim" not in summary:
        names = tuple(f"t{p}" for p in range(positions))
    header = [
        f"a{p // action_dim}.{names[p % action_dim]}" if "action_dim" in summary else names[p] for p in range(positions)
    ]
    lines = ["| method | " + " | ".join(header) + " |", "|---|" + "---:|" * positions]
    lines += [f"| {name} | " + " | ".join(f"{share:.0%}" for share in shares) + " |" for name, shares in rows.items()]
    return "\n".join(lines)


def _format_speedup(total: dict | None, episodes: int) -> str:
    """``1.85x [1.79, 1.91]``, and the pairs it is of when fewer than the method's episodes were timed alike."""
    if total is None:
        return "-"
    pairs = f" ({total['pairs']} pairs)" if total["pairs"] < episodes else ""
    return f"{total['speedup']:.2f}x [{total['ci_low']:.2f}, {total['ci_high']:.2f}]{pairs}"


def _format_ratio(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}x"


SPEEDUP_NOTE = (
    "Speed-up, mean per call: greedy's mean ms per call over the paired episodes divided by the method's (the ratio "
    "of total decode times only when both make the same calls), 95% paired bootstrap interval over episodes; median of "
    "ratios: the median over episodes of greedy's median ms per call / the method's (the figure reported before)."
)


def format_comparison(summary: dict) -> str:
    """The markdown table of a comparison summary, then a note on the speed-ups and the timing conditions."""
    lines = [
        "| method | episodes | success | vs greedy (95% CI) | greedy-only / method-only | mean length "
        "| median ms/call | speed-up, mean per call (95% CI) | speed-up, median of ratios "
        "| vs greedy:compile, mean per call (95% CI) | vs greedy:compile, median of ratios | target fwd/call "
        "| tokens/target fwd | bin dev. mean / max | deviation per dim. (mean) | identical to greedy |",
        "|---|---:|---:|---|---:|---:|---:|---|---:|---|---:|---:|---:|---|---|---:|",
    ]
    for name, row in summary["methods"].items():
        paired = row.get("vs_greedy")
        if paired is None:
            versus, discordant = "-", "-"
        else:
            versus = f"{paired['difference']:+.1%} [{paired['ci_low']:+.1%}, {paired['ci_high']:+.1%}]"
            discordant = f"{paired['greedy_only']} / {paired['method_only']}"
        speeds = " | ".join(
            [
                _format_speedup(row.get("speedup_total"), row["episodes"]),
                _format_ratio(row.get("speedup")),
                _format_speedup(row.get("speedup_total_vs_greedy_compile"), row["episodes"]),
                _format_ratio(row.get("speedup_vs_greedy_compile")),
            ]
        )
        median_ms = "-" if row.get("median_ms_per_call") is None else f"{row['median_ms_per_call']:.2f}"
        relaxed = row.get("relaxed", bool(row["bin_tolerance"]))
        deviation = "-" if not relaxed else f"{row['mean_bin_deviation']:.2f} / {row['max_bin_deviation']}"
        identical = f"{row['identical_to_greedy']}/{paired['pairs'] if paired else 0}"
        per_dim = row.get("mean_bin_deviation_per_dim")
        per_dim = "-" if not relaxed or not per_dim else " / ".join(f"{d:.2f}" for d in per_dim)
        lines.append(
            f"| {name} | {row['episodes']} | {row['success_rate']:.1%} | {versus} | {discordant} "
            f"| {row['mean_episode_length']:.0f} | {median_ms} | {speeds} "
            f"| {row['target_forwards_per_call']:.2f} | {row['tokens_per_target_forward']:.2f} | {deviation} "
            f"| {per_dim} | {identical} |"
        )
    lines += ["", SPEEDUP_NOTE]
    by_phase = format_deviation_by_phase(summary)
    if by_phase:
        lines += ["", by_phase]
    by_position = format_acceptance_by_position(summary)
    if by_position:
        lines += [
            "",
            "Accepted drafts by token position of a call (share of calls; the rest are the target's own "
            "tokens: after a rejection, or the one that ends each forward):",
            "",
            by_position,
        ]
    timing = summary.get("timing")
    if timing:
        conditions = ", ".join(f"{k}={v}" for k, v in timing["conditions"].items() if k != "machine")
        machine = timing["conditions"].get("machine", {})
        left_out = timing["episodes_timed_otherwise"]
        left_out = f"; {left_out} timed otherwise are left out of the speed columns" if left_out else ""
        lines.append(
            f"Timed under {conditions} on {machine.get('cpu', '?')} ({machine.get('cpu_count', '?')} CPUs, torch "
            f"{machine.get('torch', '?')}): {timing['episodes_timed']} episodes{left_out}."
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
    for family, points in families.items():  # mean per call, with its 95% interval
        points = sorted(
            ((r, row["speedup_total"]) for r, row in points if row.get("speedup_total")), key=lambda p: p[0]
        )
        if not points:
            continue
        axis.errorbar(
            [p[0] for p in points],
            [p[1]["speedup"] for p in points],
            marker="o",
            capsize=3,
            label=family,
            yerr=[
                [p[1]["speedup"] - p[1]["ci_low"] for p in points],
                [p[1]["ci_high"] - p[1]["speedup"] for p in points],
            ],
        )
    _finish_plot(plt, figure, axis, 1.0, "speed-up vs greedy, mean per call (95% CI)", "Speed-up", paths[0])

    figure, axis = plt.subplots(figsize=(6, 4))
    for offset, (family, points) in enumerate(families.items()):
        points = sorted((r, row["vs_greedy"]) for r, row in points if "vs_greedy" in row)
        x = [p[0] + 0.08 * offset for p in points]
        y = [100 * p[1]["difference"] for p in points]
        errors = [
            [100 * (p[1]["difference"] - p[1]["ci_low"]) for p in points],
            [100 * (p[1]["ci_high"] - p[1]["difference"]) for p in points],
        ]
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
