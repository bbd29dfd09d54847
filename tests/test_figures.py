"""The figures the README and the guide quote are the ones their result files hold (issue 64): the README's table is
the one ``figures.measured_table`` computes from docs/results/, every named figure of ``figures.quoted_figures`` is
quoted where its page says it, and every decimal, percentage and count the README's measured parts show is one of
the computed figures, so a stale or hand-typed figure fails here. Reads JSON only: no model runs."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from hf_specvla.metaworld.comparison import figures
from hf_specvla.metaworld.comparison.statistics import paired_speedup, per_call_latencies

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
#: this checkout's result files (the package may be installed elsewhere, as tox installs it)
RESULTS = ROOT / "docs" / "results"

#: page -> the named figures it quotes (figures.quoted_figures)
PAGE_QUOTES = {
    "README.md": [
        "greedy success", "fast vs exact range", "fast vs exact per call", "fast calls", "fast decided differently",
        "serve warm-up", "serve 1 robot", "serve 1 robot repeats", "serve 2 robots", "serve 2 robots repeats",
        "serve 4-16 robots", "serve 4-16 robots repeats", "serve calibration speculates up to",
        "serve speculative at 4", "serve speculative at 16", "compiled vs eager greedy",
        "compiled vs eager greedy, other rows",
    ],
    "docs/index.md": ["greedy success"],
    "docs/metaworld.md": ["fast calls"],
    "docs/serving.md": [
        "serve warm-up", "exact vs compiled runs", "exact vs compiled run 1", "exact vs compiled run 2",
        "serve speculative at 4", "serve speculative at 16", "serve 1 robot", "serve 1 robot repeats",
        "serve 2 robots", "serve 2 robots repeats", "serve 4-16 robots",
    ],
    "docs/usage.md": [
        "fast vs exact range", "fast vs exact per call", "fast decided differently", "v2 fast per-call median",
    ],
}  # fmt: skip

#: a figure of the measured parts: a decimal (with its x if a ratio), a percentage, a count out of a total
FIGURE = re.compile(r"\d+\.\d+x?|\d+%|\d+/\d+")
#: numbers that are settings, not measurements
NOT_MEASURED = {"95%"}


@pytest.fixture(scope="module")
def quotes() -> dict[str, str]:
    return figures.quoted_figures(RESULTS)


@pytest.fixture(scope="module")
def table() -> str:
    return figures.measured_table(RESULTS)


def _normalized(text: str) -> str:
    """Line breaks of a wrapped paragraph read as spaces."""
    return re.sub(r"\s+", " ", text)


def _measured_parts(readme: str) -> str:
    """The README's parts that quote measurements: the example's comments and the Measured and Serve sections,
    code reduced to its comments and addresses dropped."""
    parts = []
    for title in ("## Faster", "## Measured", "## Serve robots"):
        start = readme.index(title)
        end = readme.find("\n## ", start + 1)
        parts.append(readme[start : end if end > 0 else None])
    text, kept, code = "\n".join(parts), [], False
    for line in text.splitlines():
        code ^= line.startswith("```")
        if code:
            line = line.split("# ", 1)[1] if "# " in line else ""
        kept.append(re.sub(r"\d+\.\d+\.\d+\.\d+(:\d+)?", "", line))
    return "\n".join(kept)


def test_the_readme_shows_the_computed_table(table):
    readme = README.read_text()
    assert table in readme, "README.md's table differs from figures.measured_table(RESULTS):\n" + table


@pytest.mark.parametrize("page", sorted(PAGE_QUOTES))
def test_each_page_quotes_the_computed_figures(page, quotes):
    text = _normalized((ROOT / page).read_text())
    missing = {name: quotes[name] for name in PAGE_QUOTES[page] if quotes[name] not in text}
    assert not missing, f"{page} does not quote (or quotes stale) {missing}"


def test_every_figure_the_readme_measures_is_computed(table, quotes):
    computed = set(FIGURE.findall(table + "\n" + "\n".join(quotes.values()))) | NOT_MEASURED
    shown = FIGURE.findall(_measured_parts(README.read_text()))
    assert shown, "found no figure in the README's measured parts"
    stale = sorted(set(shown) - computed)
    assert not stale, f"README.md quotes figures no result file gives: {stale}"


def test_the_figures_can_fail(table):
    """The check sees a changed figure: the old 'fast' per-call speed-up typed as a total makes a stale table."""
    readme = README.read_text()
    assert table.replace("1.70x [1.54, 1.86]", "1.78x [1.70, 1.86]") not in readme
    computed = set(FIGURE.findall(table))
    assert "1.78" not in computed and "0/600" not in computed and "2.5" not in computed


def test_the_script_prints_the_table_and_the_figures(table, quotes):
    script = ROOT / "examples" / "metaworld" / "figures.py"
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, check=True)
    assert table in result.stdout and f"fast calls: {quotes['fast calls']}" in result.stdout


# ----------------------------------------------------------------------------- the statistics themselves
def test_total_time_is_sum_over_sum_and_per_call_is_the_mean_ratio():
    summary = {"per_call_ms": {"greedy": {"t:0": "10 10", "t:1": "20"}, "m": {"t:0": "5", "t:1": "10 10 10"}}}
    total = figures.total_time_speedup(summary, "m", resamples=200)
    assert total["speedup"] == pytest.approx(40 / 35)
    assert (total["baseline_calls"], total["method_calls"], total["pairs"]) == (3, 4, 2)
    assert total["ci_low"] <= total["speedup"] <= total["ci_high"]
    assert figures.per_call_speedup(summary, "m") == pytest.approx((40 / 3) / (35 / 4))


@pytest.mark.parametrize("name", ["compare_v3_head_v2_100k_summary.json", "compare_v3_fast_300k_summary.json"])
def test_a_lossless_methods_total_time_is_compares_figure(name):
    """Same calls as greedy: the total-time ratio and its interval are exactly what compare stored."""
    summary = figures.load(name, RESULTS)
    stored = summary["methods"][figures.EXACT]["speedup_total"]
    mine = figures.total_time_speedup(summary, figures.EXACT)
    assert mine["method_calls"] == mine["baseline_calls"]
    for key in ("speedup", "ci_low", "ci_high"):
        assert mine[key] == pytest.approx(stored[key], rel=1e-4)


def test_fast_makes_other_calls_so_compares_stored_figure_is_per_call():
    summary = figures.load("compare_v3_relaxed_100k_summary.json", RESULTS)
    total = figures.total_time_speedup(summary, figures.FAST)
    assert (total["method_calls"], total["baseline_calls"]) == (14_741, 14_073)
    per_call = figures.per_call_speedup(summary, figures.FAST)
    assert per_call == pytest.approx(summary["methods"][figures.FAST]["speedup_total"]["speedup"], rel=1e-4)
    latencies = per_call_latencies(summary)
    keys = sorted(latencies[figures.FAST])
    recomputed = paired_speedup([latencies["greedy"][k] for k in keys], [latencies[figures.FAST][k] for k in keys])
    assert recomputed["speedup"] == pytest.approx(per_call)
    assert round(total["speedup"], 2) == 1.70 and round(per_call, 2) == 1.78


def test_fast_over_exact_contains_one_on_every_range():
    """The README says so: every interval of fast's total decode time over exact's contains 1."""
    for seeds in figures.SEED_RANGES:
        versus = figures.total_time_speedup(
            figures.load(figures.RUNS["fast", seeds][0], RESULTS), figures.FAST, figures.EXACT
        )
        assert versus["ci_low"] < 1 < versus["ci_high"], seeds


def test_the_runs_are_the_same_pairs_under_the_same_conditions():
    for (preset, seeds), names in figures.RUNS.items():
        summaries = [figures.load(name, RESULTS) for name in names]
        assert {s["settings"]["seed_start"] for s in summaries} == {int(seeds.rstrip("+"))}, names
        keys = [frozenset(per_call_latencies(s)[figures.PRESETS[preset]]) for s in summaries]
        assert all(len(k) == 200 for k in keys) and len(set(keys)) == 1, names
        conditions = {repr(s["timing"]["conditions"]) for s in summaries}
        assert len(conditions) == 1, names
        # the README's "200 held-out episodes per seed range (10 tasks x 20 seeds), 2 workers x 1 CPU thread"
        assert (summaries[0]["timing"]["conditions"]["workers"], summaries[0]["timing"]["conditions"]["threads"]) == (
            2,
            1,
        )
        assert all(len(s["methods"][figures.GREEDY]["task_success_rates"]) == 10 for s in summaries), names
        assert {s["settings"]["policy"] for s in summaries} == {summaries[0]["settings"]["policy"]}


def test_each_row_is_of_one_cpu_and_says_which():
    """A speed-up holds for the CPU it was timed on: the table's plain rows are ``RUNS_CPU``'s, and a run timed on
    another CPU is a row of its own whose label names that CPU (its timing conditions say it)."""
    for names in figures.RUNS.values():
        cpus = {figures.load(name, RESULTS)["timing"]["conditions"]["machine"]["cpu"] for name in names}
        assert all(cpu.startswith(figures.RUNS_CPU) for cpu in cpus), (names, cpus)
    for (_, seeds, label), names in figures.OTHER_RUNS.items():
        summaries = [figures.load(name, RESULTS) for name in names]
        assert len({repr(s["timing"]["conditions"]) for s in summaries}) == 1, names
        for summary in summaries:
            cpu = " ".join(summary["timing"]["conditions"]["machine"]["cpu"].replace("(R)", "").split())
            assert label.split(",")[0] in cpu and summary["settings"]["seed_start"] == int(seeds.rstrip("+"))
            assert (summary["timing"]["conditions"]["workers"], summary["timing"]["conditions"]["threads"]) == (2, 1)
        assert f"{seeds} ({label})" in figures.measured_table(RESULTS)


def test_the_serving_ratios_are_of_the_medians_as_the_serving_table():
    table = figures.load(figures.SERVING, RESULTS)["table"]
    for robots in (1, 2, 4, 8, 16):
        ratio, repeats = figures._throughput_ratios(RESULTS, robots)
        row = next(line for line in table.splitlines() if line.startswith(f"| {robots} | adaptive |"))
        assert f"| {ratio:.2f}x [{min(repeats):.2f}x-{max(repeats):.2f}x] |" in row, row
        assert len(repeats) == 3
