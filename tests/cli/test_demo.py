"""The demo's last screen (issue 65): a verdict read from the measured rows, and a heartbeat through compiles.

The demo's own calls run in tests/test_transformers_warnings.py (on an untrained toy, warnings as errors)."""

import logging
import time

import pytest

from hf_specvla.benchmarks.speed import (
    EpisodeMethodResult,
    MethodResult,
    VerdictRow,
    format_verdict,
    verdict_rows,
)
from hf_specvla.speculative import SpeculationStats

ACTION_DIM = 2


def episode_row(name, latency, forwards, distances):
    """A measured episode row: one latency a call, ``forwards`` target forwards a call, a bin distance a token."""
    calls = len(distances) // ACTION_DIM
    return EpisodeMethodResult(name, latencies=[latency] * calls, target_forwards=[forwards] * calls,
                               bin_distances=list(distances))  # fmt: skip


def measured(
    exact_latency=0.010, head_latency=0.012, relaxed_latency=0.008, relaxed_distances=(0, 0, 1, 0, 0, 0, 2, 3)
):
    """4 actions a row: greedy 20 ms, compiled greedy 15 ms, `exact` and the head lossless, a relaxed row that
    changes the actions ``relaxed_distances`` says (2 of 4 by default)."""
    same = [0] * (4 * ACTION_DIM)
    return [
        episode_row("greedy", 0.020, 2, same),
        episode_row("greedy:compile", 0.015, 2, same),
        episode_row("prior r=0", 0.018, 1, same),  # not a verdict row
        episode_row("prior+jacobi r=0:compile", exact_latency, 1, same),
        episode_row("prior+jacobi r=1:compile", relaxed_latency, 1, relaxed_distances),
        episode_row("prior+jacobi+tree r=0:compile", head_latency, 1.25, same),
    ]


def table_row(text, role):
    return next(line for line in text.splitlines() if line.startswith(f"| {role} |")).split(" | ")


def test_the_verdict_reads_its_rows_from_the_measurements():
    results = measured()
    rows = [row for row, _ in verdict_rows(results, ACTION_DIM)]
    assert [row.role for row in rows] == ["greedy", "compiled greedy", "`exact`", "draft head", "relaxed r=1"]
    assert [row.method for row in rows] == [r.name for r in results if r.name != "prior r=0"][:2] + [
        "prior+jacobi r=0:compile", "prior+jacobi+tree r=0:compile", "prior+jacobi r=1:compile"]  # fmt: skip
    relaxed = rows[-1]
    assert (relaxed.identical, relaxed.actions) == (2, 4)  # an action is identical when all its tokens are
    assert [row.lossless for row in rows] == [True, True, True, True, False]

    text = format_verdict(results, ACTION_DIM)
    assert "speed-up vs compiled greedy" in text  # the fastest greedy row is the baseline
    # ms/action, speed-up over compiled greedy (15 ms), target forwards per action, identical to greedy
    assert table_row(text, "`exact`")[3:] == ["10.0", "1.50x", "1.00", "4/4 |"]
    assert table_row(text, "greedy")[3:] == ["20.0", "0.75x", "2.00", "4/4 |"]
    assert table_row(text, "relaxed r=1")[3:] == ["8.0", "1.88x", "1.00", "2/4 |"]
    sentence = text.splitlines()[-1]
    assert sentence == (
        "In one sentence: `exact` (prior+jacobi r=0:compile) gives greedy's actions, all 4, 1.50x as fast as compiled "
        "greedy (1.0 target forwards per action instead of 2); relaxed r=1 is faster still (1.88x) but changes 50% of "
        "the actions: fidelity traded for speed."
    )


def test_the_sentence_follows_the_numbers():
    """Nothing in the verdict is written in advance: a slow `exact`, a relaxed row no faster than it, one that
    changed nothing, each says so."""
    slow = format_verdict(measured(0.030, 0.020, 0.050), ACTION_DIM).splitlines()[-1]
    assert slow == (
        "In one sentence: no lossless setting beat compiled greedy on this machine: the best, draft head "
        "(prior+jacobi+tree r=0:compile), gives greedy's actions at 0.75x its speed (1.2 target forwards per action "
        "instead of 2); relaxed r=1 changes 50% of the actions and is no faster (0.30x): keep draft head."
    )
    unchanged = format_verdict(measured(relaxed_distances=[0] * 8), ACTION_DIM).splitlines()[-1]
    assert unchanged.endswith("relaxed r=1 changed no action here (1.88x).")


def test_without_episodes_the_verdict_reads_the_held_out_scene_table():
    """``demo --episodes 0``: the held-out scene table's rows stand in (Jacobi drafts, the head's chain, relaxed
    chains); target forwards per action from the speculation statistics, greedy's one a token."""
    stats = SpeculationStats(accept_lengths=[2, 1, 1])  # 3 target forwards over the row's 2 calls

    def scene_row(name, latency, stats=None, distances=(0, 0, 0, 0)):
        return MethodResult(name, latencies=[latency, latency], stats=stats, bin_distances=list(distances))

    results = [scene_row("greedy", 0.02), scene_row("greedy:compile", 0.01), scene_row("spec k=2 r=0", 0.015, stats),
               scene_row("jacobi r=0:compile", 0.009, stats), scene_row("spec k=2 r=0:compile", 0.008, stats),
               scene_row("spec k=6 r=1", 0.012, stats, (0, 1, 0, 0))]  # fmt: skip
    described = verdict_rows(results, ACTION_DIM)
    rows = {row.role: row for row, _ in described}
    assert "no previous action" in dict((row.role, what) for row, what in described)["`exact`"]  # it says which
    assert {role: row.method for role, row in rows.items()} == {
        "greedy": "greedy", "compiled greedy": "greedy:compile", "`exact`": "jacobi r=0:compile",
        "draft head": "spec k=2 r=0:compile", "relaxed r=1": "spec k=6 r=1"}  # fmt: skip
    assert rows["greedy"].target_forwards == ACTION_DIM and rows["`exact`"].target_forwards == 1.5
    assert (rows["relaxed r=1"].identical, rows["relaxed r=1"].actions) == (1, 2)
    assert "no verdict" in format_verdict([scene_row("prior r=0", 0.01)], ACTION_DIM).lower()


def test_a_verdict_row_refuses_impossible_counts():
    with pytest.raises(ValueError, match=r"exact: 5 identical of 4 actions"):
        VerdictRow("`exact`", "exact", 0.01, 1.0, identical=5, actions=4)


def test_a_heartbeat_logs_through_a_silent_step_and_nothing_for_a_short_one(caplog):
    from hf_specvla.progress import heartbeat

    with caplog.at_level(logging.INFO, logger="hf_specvla"):
        with heartbeat("warm-up", interval=0.05) as beat:
            beat.begin("greedy:compile (2/25)")
            time.sleep(0.3)  # a compile that says nothing
        lines = [r.getMessage() for r in caplog.records if r.name == "hf_specvla.progress"]
        assert len(lines) >= 2 and all(line.startswith("warm-up: greedy:compile (2/25), ") for line in lines)
        assert lines[-1].endswith("0 min 0 s in all")
        caplog.clear()
        with heartbeat("quick", interval=60):
            pass
        assert not caplog.records  # the thread is gone with the block: nothing later either
    with pytest.raises(ValueError, match="positive number of seconds, got 0"):
        with heartbeat("bad", interval=0):
            pass
