"""The figures the README and the guide quote, computed from the result files in ``docs/results/`` (issue 64).

One statistic per word:

* **total decode time** (``total_time_speedup``): the baseline's decode time summed over the paired episodes divided
  by the method's (sum over sum), with a 95% paired bootstrap interval (the episode pairs resampled, 2,000 times,
  seed 0, as ``compare`` does). A method whose episodes make other calls than greedy's (a relaxed one: its episodes
  end elsewhere) is charged for them.
* **per call** (``per_call_speedup``): the baseline's mean ms per call over the method's. ``compare`` stores this as
  ``speedup_total`` (labelled "total time" in its ``compare.md``); it equals the total-time ratio only when both made
  the same calls, as lossless methods do.
* **per-call median**: ``compare``'s ``speedup``, the median over episodes of the ratio of the two episodes' median
  ms per call.
* success rates, the paired success difference (points, 95% interval), the discordant episodes and the episodes
  identical to greedy's, as each summary holds them.

``python examples/metaworld/figures.py`` prints the README's table and every quoted figure ([`report`]);
``tests/test_figures.py`` checks that the pages quote exactly these, so a figure that goes stale fails a test.
A headline speed-up gives the interval of one run and the range over every run of the same comparison on the same
200 pairs that kept per-call times (``RUNS``); the two earliest presets runs (``compare_v3_presets_100k_summary.json``,
``compare_v3_presets_200k_summary.json``) kept only per-call medians and are left out of the ranges.
"""

from __future__ import annotations

import json
import statistics
from functools import cache
from pathlib import Path

import numpy as np

from .statistics import SPEEDUP_RESAMPLES, per_call_latencies


def _results_folder() -> Path:
    """docs/results/ of the checkout: the source tree's when the package runs from it (an editable install), else the
    working directory's (an installed package, as tox installs it, run from the checkout's root). The files are not
    installed with the package."""
    source_tree = Path(__file__).resolve().parents[4] / "docs" / "results"
    working_dir = Path.cwd() / "docs" / "results"
    return source_tree if source_tree.is_dir() or not working_dir.is_dir() else working_dir


#: docs/results/ of this checkout (see ``_results_folder``)
RESULTS = _results_folder()

EXACT = "prior+jacobi:compile"
FAST = "prior+jacobi:r=4/4/4/0,gate=0.5,confirm=1:compile"
GREEDY, COMPILED = "greedy", "greedy:compile"
PRESETS = {"exact": EXACT, "fast": FAST}
SEED_RANGES = ("100000+", "200000+", "300000+")

#: (preset, seed range) -> the runs of that preset against greedy on the same 200 pairs (policy v3, 2 workers x 1
#: thread) that kept per-call times; the first is the run whose interval, success and identical count are quoted
RUNS = {
    ("exact", "100000+"): (
        "compare_v3_head_v2_100k_summary.json",
        "compare_v3_presets_100k_total_summary.json",
        "compare_v3_relaxed_100k_summary.json",
    ),
    ("exact", "200000+"): ("compare_v3_head_v2_200k_summary.json", "compare_v3_relaxed_200k_summary.json"),
    ("exact", "300000+"): ("compare_v3_fast_300k_summary.json",),
    ("fast", "100000+"): ("compare_v3_relaxed_100k_summary.json",),
    ("fast", "200000+"): ("compare_v3_relaxed_200k_summary.json",),
    ("fast", "300000+"): ("compare_v3_fast_300k_summary.json",),
}
#: the CPU the runs of ``RUNS`` were timed on (their timing conditions say so)
RUNS_CPU = "AMD EPYC"
#: (preset, seed range, what the row says) -> runs timed on another CPU or engine: rows of their own, since a
#: speed-up holds for the machine it was measured on (on an Intel Xeon compiled greedy gains more over eager greedy
#: than on the AMD EPYC of ``RUNS``: 1.47-1.51x against 1.17-1.24x); engines v5's and v6's on other EPYCs (1.42x and
#: 1.47x there)
OTHER_RUNS = {
    ("exact", "100000+", "Intel Xeon, engine v4"): ("compare_v3_exact_engine_v4_100k_summary.json",),
    ("exact", "100000+", "AMD EPYC, engine v5: the policy's decoder session"): (
        "compare_v3_exact_engine_v5_session_100k_summary.json",
    ),
    # run back to back with engine v5's code (c9a0673): docs/benchmarks.md, session 37
    ("exact", "100000+", "AMD EPYC, engine v6: the decoder decodes"): ("compare_v3_exact_engine_v6_100k_summary.json",),
}
SERVING = "serving_load_v3_serving_v2.json"
#: policy v2's relaxed rules (issue 35): ``fast`` before ``confirm=1`` was added on policy v3
V2_RULES = ("compare_v2_rules_100k_summary.json", "compare_v2_rules_200k_summary.json")
V2_FAST = "prior+jacobi:r=4/4/4/0,gate=0.5:compile"


@cache
def load(name: str, results: Path = RESULTS) -> dict:
    """A result file of ``results`` (JSON), read once."""
    return json.loads((Path(results) / name).read_text())


def _paired(summary: dict, method: str, baseline: str) -> tuple[list[list[float]], list[list[float]]]:
    """The baseline's and the method's per-call ms of the episodes both timed, in one order."""
    latencies = per_call_latencies(summary)
    if method not in latencies or baseline not in latencies:
        raise KeyError(f"the summary keeps no per-call times of {method!r} and {baseline!r}")
    keys = sorted(set(latencies[method]) & set(latencies[baseline]))
    return [latencies[baseline][k] for k in keys], [latencies[method][k] for k in keys]


def total_time_speedup(
    summary: dict, method: str, baseline: str = GREEDY, resamples: int = SPEEDUP_RESAMPLES, seed: int = 0
) -> dict:
    """The baseline's total decode time over the method's on their paired episodes (sum over sum), with a 95%
    percentile-bootstrap interval over the pairs.

    Returns:
        ``speedup``, ``ci_low``, ``ci_high``, ``pairs``, ``baseline_calls``, ``method_calls``.
    """
    baseline_ms, method_ms = _paired(summary, method, baseline)
    base = np.array([np.sum(e, dtype=np.float64) for e in baseline_ms])
    mine = np.array([np.sum(e, dtype=np.float64) for e in method_ms])
    index = np.random.default_rng(seed).integers(0, len(base), (resamples, len(base)))
    low, high = np.percentile(base[index].sum(-1) / mine[index].sum(-1), [2.5, 97.5])
    return {
        "speedup": float(base.sum() / mine.sum()),
        "ci_low": float(low),
        "ci_high": float(high),
        "pairs": len(base),
        "baseline_calls": sum(len(e) for e in baseline_ms),
        "method_calls": sum(len(e) for e in method_ms),
    }


def per_call_speedup(summary: dict, method: str, baseline: str = GREEDY) -> float:
    """The baseline's mean ms per call over the method's, on their paired episodes (``compare``'s ``speedup_total``)."""
    baseline_ms, method_ms = _paired(summary, method, baseline)
    mean = lambda episodes: sum(map(sum, episodes)) / sum(map(len, episodes))  # noqa: E731
    return mean(baseline_ms) / mean(method_ms)


def format_speedup(speedup: dict) -> str:
    """``1.72x [1.69, 1.76]``."""
    return f"{speedup['speedup']:.2f}x [{speedup['ci_low']:.2f}, {speedup['ci_high']:.2f}]"


def format_range(values, digits: int = 2, unit: str = "x") -> str:
    """``1.40-1.48x`` (one value: ``1.40x``), each value rounded first."""
    low, high = f"{min(values):.{digits}f}", f"{max(values):.{digits}f}"
    return f"{low}{unit}" if low == high else f"{low}-{high}{unit}"


def format_points(paired: dict) -> str:
    """A paired success difference in points: ``+3.0 [-1.5, +7.5]``."""
    return f"{100 * paired['difference']:+.1f} [{100 * paired['ci_low']:+.1f}, {100 * paired['ci_high']:+.1f}]"


def _speed_cell(preset: str, runs: tuple[str, ...], baseline: str, results: Path) -> str:
    """The quoted run's total-time speed-up and interval, then the range over the runs (when more than one)."""
    files = [name for name in runs if baseline in load(name, results).get("per_call_ms", {})]
    if not files:
        return "-"
    runs = [total_time_speedup(load(name, results), PRESETS[preset], baseline) for name in files]
    quoted = format_speedup(runs[0])
    if preset == "exact":
        quoted = f"**{quoted.split(' ', 1)[0]}** {quoted.split(' ', 1)[1]}"
    if len(runs) > 1:
        quoted += f"; {len(runs)} runs: {format_range([r['speedup'] for r in runs])}"
    return quoted


def measured_table(results: Path = RESULTS) -> str:
    """The README's table: per preset and seed range, the total-decode-time speed-ups, success and identical count."""
    lines = [
        "| preset | seeds | vs eager greedy | vs compiled greedy | vs `exact` | success vs greedy (points) "
        "| identical to greedy |",
        "|---|---|---|---|---|---|---:|",
    ]
    rows = [(preset, seeds, RUNS[preset, seeds]) for preset in PRESETS for seeds in SEED_RANGES]
    rows += [(preset, f"{seeds} ({label})", runs) for (preset, seeds, label), runs in OTHER_RUNS.items()]
    for preset, seeds_cell, runs in rows:
        summary = load(runs[0], results)
        row = summary["methods"][PRESETS[preset]]
        versus_exact = "-" if preset == "exact" else format_speedup(total_time_speedup(summary, FAST, EXACT))
        cells = [
            f"`{preset}`",
            seeds_cell,
            _speed_cell(preset, runs, GREEDY, results),
            _speed_cell(preset, runs, COMPILED, results),
            versus_exact,
            format_points(row["vs_greedy"]),
            f"{row['identical_to_greedy']}/{row['vs_greedy']['pairs']}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _runs_with(method: str, results: Path = RESULTS) -> list[str]:
    """The files of ``RUNS`` (each once) that timed ``method``."""
    names = dict.fromkeys(name for runs in RUNS.values() for name in runs)
    return [name for name in names if method in load(name, results).get("per_call_ms", {})]


def _fast_runs(results: Path) -> list[dict]:
    return [load(RUNS["fast", seeds][0], results) for seeds in SEED_RANGES]


def _serving(results: Path) -> dict[tuple[int, str], list[dict]]:
    """serving_load_v3.json's rows by (robots, server), in repeat order."""
    rows: dict[tuple[int, str], list[dict]] = {}
    for row in sorted(load(SERVING, results)["rows"], key=lambda r: r["repeat"]):
        rows.setdefault((row["robots"], row["kind"]), []).append(row)
    return rows


def _throughput_ratios(results: Path, robots: int, server: str = "adaptive") -> tuple[float, list[float]]:
    """(the median over the repeats of each repeat's ratio of actions/s, as serving.md's table; each repeat's ratio)
    of a server over the greedy one run in the same repeat, at ``robots`` robots."""
    rows = _serving(results)
    mine = [r["actions_per_second"] for r in rows[robots, server]]
    greedy = [r["actions_per_second"] for r in rows[robots, "greedy"]]
    ratios = [a / b for a, b in zip(mine, greedy)]
    return statistics.median(ratios), ratios


def quoted_figures(results: Path = RESULTS) -> dict[str, str]:
    """Every figure the README and the guide quote outside the table, by name, formatted as the pages write it."""
    greedy_success = [
        load(RUNS["exact", seeds][0], results)["methods"][GREEDY]["success_rate"] for seeds in SEED_RANGES
    ]
    fast = _fast_runs(results)
    head_100k, presets_100k = (load(name, results) for name in RUNS["exact", "100000+"][:2])
    compiled_runs = [total_time_speedup(summary, EXACT, COMPILED) for summary in (head_100k, presets_100k)]
    robots = sorted({k for k, _ in _serving(results)})
    many = [k for k in robots if k >= 4]
    calibration = load(SERVING, results)["servers"]["calibration"]
    serving_rows = _serving(results)
    v2 = [load(name, results)["methods"][V2_FAST]["speedup"] for name in V2_RULES]
    return {
        # the shipped policy v3: greedy's success on MT10 over the three seed ranges
        "greedy success": format_range([100 * s for s in greedy_success], 1, "%"),
        # fast over exact, each range's run: total decode time, then per call
        "fast vs exact": " / ".join(format_speedup(total_time_speedup(s, FAST, EXACT)) for s in fast),
        "fast vs exact range": format_range([total_time_speedup(s, FAST, EXACT)["speedup"] for s in fast]),
        "fast vs exact per call": format_range([per_call_speedup(s, FAST, EXACT) for s in fast]),
        "fast calls": "{method_calls:,} calls vs greedy's {baseline_calls:,}".format(
            **total_time_speedup(fast[0], FAST, GREEDY)
        ),
        "fast decided differently": " / ".join(
            str(s["methods"][FAST]["vs_greedy"]["greedy_only"] + s["methods"][FAST]["vs_greedy"]["method_only"])
            for s in fast
        ),
        # exact over compiled greedy on 100000+: the two runs on the same 200 pairs
        "exact vs compiled runs": format_range([r["speedup"] for r in compiled_runs]),
        "exact vs compiled run 1": format_speedup(compiled_runs[0]),
        "exact vs compiled run 2": format_speedup(compiled_runs[1]),
        # compiled greedy over eager greedy: on the EPYC of RUNS (every run that timed both), and on the other rows'
        # CPUs (why their rows stand apart)
        "compiled vs eager greedy": format_range(
            [
                total_time_speedup(load(name, results), COMPILED, GREEDY)["speedup"]
                for name in _runs_with(COMPILED, results)
            ]
        ),
        "compiled vs eager greedy, other rows": format_range(
            [total_time_speedup(load(runs[0], results), COMPILED, GREEDY)["speedup"] for runs in OTHER_RUNS.values()]
        ),
        # the policy server (serving_load_v3_serving_v2.json): adaptive over the compiled greedy server, actions/s
        "serve warm-up": f"{load(SERVING, results)['servers']['warm_up_s']:.0f} s",
        "serve 1 robot": f"{_throughput_ratios(results, 1)[0]:.2f}x",
        "serve 1 robot repeats": format_range(_throughput_ratios(results, 1)[1]),
        "serve 2 robots": f"{_throughput_ratios(results, 2)[0]:.2f}x",
        "serve 2 robots repeats": format_range(_throughput_ratios(results, 2)[1]),
        "serve 4-16 robots": format_range([_throughput_ratios(results, k)[0] for k in many]),
        "serve 4-16 robots repeats": format_range([x for k in many for x in _throughput_ratios(results, k)[1]]),
        "serve calibration speculates up to": f"batch {max(c['bucket'] for c in calibration if c['speculate'])}",
        "serve speculative at 4": " / ".join(f"{r['speculative_fraction']:.0%}" for r in serving_rows[4, "adaptive"]),
        "serve speculative at 16": format_range(
            [100 * r["speculative_fraction"] for r in serving_rows[16, "adaptive"]], 0, "%"
        ),
        # policy v2: fast without confirm=1, per-call median over eager greedy on its two seed ranges
        "v2 fast per-call median": format_range(v2),
    }


def report(results: Path = RESULTS) -> str:
    """The README's table, then every quoted figure by name (``examples/metaworld/figures.py`` prints it)."""
    quotes = quoted_figures(results)
    return measured_table(results) + "\n\n" + "\n".join(f"{name}: {value}" for name, value in quotes.items())
