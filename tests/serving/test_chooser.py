"""The mode chooser alone: made-up call times, no policy, no clock."""

from __future__ import annotations

import pytest

from hf_specvla.serving.chooser import CLEAR_GAP_EXPLORE_FACTOR, TIMING_WINDOW, ModeChooser, format_calibration

GREEDY, SPECULATIVE = 0, 1  # the modes of a chooser with one speculative method


def _traffic(chooser: ModeChooser, bucket: int, calls: int, *mode_ms: float) -> list[int]:
    """``calls`` batches of ``bucket``, each taking the made-up time of the mode the chooser picked (``mode_ms``:
    the speculative methods' times, then greedy's); the modes."""
    *spec_ms, greedy_ms = mode_ms
    modes = []
    for _ in range(calls):
        mode = chooser.mode_for(bucket)
        chooser.observe(bucket, mode, spec_ms[mode - 1] if mode else greedy_ms, rows=bucket)
        modes.append(mode)
    return modes


def _calibrate(chooser: ModeChooser, bucket: int, spec_ms: list[float], greedy_ms: list[float], *more: list[float]):
    """Calibrates ``bucket`` with the made-up times of the greedy baseline and each speculative method."""
    return chooser.calibrate(bucket, {GREEDY: greedy_ms, SPECULATIVE: spec_ms, **dict(enumerate(more, 2))})


def test_calibration_sets_each_bucket_s_choice_and_is_recorded():
    chooser = ModeChooser((1, 4))
    small = _calibrate(chooser, 1, [20.0, 22.0, 21.0], [30.0, 31.0, 29.0])  # speculation 1.43x faster
    large = _calibrate(chooser, 4, [60.0, 61.0, 59.0], [50.0, 52.0, 51.0])  # greedy faster
    assert (chooser.speculate(1), chooser.speculate(4)) == (True, False)
    assert small == {"bucket": 1, "greedy_ms": 30.0, "speculative_ms": 21.0, "speed_up": round(30 / 21, 3),
                     "speculate": True, "method": "speculative",
                     "methods_ms": {"greedy": 30.0, "speculative": 21.0}}  # fmt: skip
    assert large["speculate"] is False and chooser.calibration == [small, large]
    decided = [(d["bucket"], d["speculate"], d["why"]) for d in chooser.decisions]
    assert decided == [(1, True, "calibration"), (4, False, "calibration")]
    table = format_calibration(chooser.calibration)
    assert table.startswith("| bucket | greedy ms/call | speculative ms/call | speed-up | decodes with |")
    assert "| 4 | 51.0 | 60.0 | 0.85x | greedy |" in table


def test_the_choice_follows_the_traffic_and_each_change_is_recorded():
    """Speculation was faster at start-up; on the traffic it turns slower: the choice flips once the medians cross,
    the flip is recorded with the medians that decided it, and speculation is still explored now and then."""
    chooser = ModeChooser((2,), explore_every=4)
    _calibrate(chooser, 2, [10.0] * 3, [12.0] * 3)
    modes = _traffic(chooser, 2, 64, 20.0, 12.0)
    assert modes[:3] == [SPECULATIVE] * 3 and not any(modes[3:15])  # 3 slow calls flip it (the median passes 12 ms)
    assert modes[-32:].count(SPECULATIVE) == 32 // (4 * CLEAR_GAP_EXPLORE_FACTOR)  # a clear gap: explored 4x less
    flip = chooser.decisions[-1]
    assert (flip["bucket"], flip["speculate"], flip["why"]) == (2, False, "traffic")
    assert flip["speculative_ms"] > flip["greedy_ms"] == 12.0
    stats = chooser.stats()["buckets"]["2"]
    assert stats["mode"] == "greedy" and stats["speculative_batches"] + stats["greedy_batches"] == 64
    assert stats["greedy_rows"] == 2 * stats["greedy_batches"]
    assert chooser.stats()["speculative_share"] == stats["speculative_share"] == round(modes.count(1) / 64, 4)


def test_only_the_recent_calls_decide():
    chooser = ModeChooser((1,), explore_every=2)
    _calibrate(chooser, 1, [10.0] * 3, [30.0] * 3)
    _traffic(chooser, 1, 2 * TIMING_WINDOW, 10.0, 30.0)
    assert chooser.speculate(1)
    _traffic(chooser, 1, 4 * TIMING_WINDOW, 40.0, 30.0)  # speculation slows down for good
    assert not chooser.speculate(1)
    assert len(chooser.timings[(1, SPECULATIVE)]) == TIMING_WINDOW


def test_the_other_mode_is_explored_less_often_when_the_choice_is_clear():
    explored = []
    for spec_ms, greedy_ms in ((10.0, 11.0), (10.0, 20.0)):  # a 10% gap, then a clear 2x
        chooser = ModeChooser((1,), explore_every=4)
        _calibrate(chooser, 1, [spec_ms] * 5, [greedy_ms] * 5)
        modes = [chooser.mode_for(1) for _ in range(32)]  # no observations: the medians stay
        explored.append(modes.count(GREEDY))
    assert explored == [32 // 4, 32 // (4 * CLEAR_GAP_EXPLORE_FACTOR)]


@pytest.mark.parametrize(
    ("settings", "expected"),
    [
        ({"speculate_buckets": (1,)}, [SPECULATIVE, GREEDY]),  # fixed by the user
        ({"methods": ()}, [GREEDY, GREEDY]),  # a greedy-only method
        ({"explore_every": 0}, [SPECULATIVE, SPECULATIVE]),  # measured, never explored
    ],
)
def test_a_fixed_or_unexplored_choice_never_changes(settings, expected):
    chooser = ModeChooser((1, 2), **settings)
    for bucket in (1, 2):
        modes = _traffic(chooser, bucket, 40, 50.0, 10.0)  # greedy far faster: no matter
        assert set(modes) == {expected[bucket - 1]}
    assert [chooser.choice(b) for b in (1, 2)] == expected
    assert not chooser.decisions


def test_stats_before_any_batch():
    stats = ModeChooser((1, 2)).stats()
    assert stats["speculative_share"] is None and stats["decisions"] == []
    nothing = {"batches": 0, "rows": 0, "median_ms": None}
    assert stats["buckets"]["1"] == {"speculate": True, "mode": "speculative", "method": "speculative",
                                     "speculative_batches": 0, "speculative_rows": 0, "speculative_median_ms": None,
                                     "greedy_batches": 0, "greedy_rows": 0, "greedy_median_ms": None,
                                     "speculative_share": None,
                                     "methods": {"greedy": nothing, "speculative": nothing}}  # fmt: skip


# ----------------------------------------------------------------------------- several speculative methods
METHODS = ("prior+jacobi:compile", "prior+jacobi+tree:compile")  # exact, and exact with a draft head


def test_calibration_picks_the_fastest_of_several_methods_per_bucket():
    """exact with a draft head: the head's composition is fastest alone, exact in pairs, greedy from 4 rows; the
    table names every mode's median and the one chosen."""
    chooser = ModeChooser((1, 2, 4), METHODS, baseline="greedy:compile")
    rows = [
        _calibrate(chooser, 1, [20.0] * 3, [30.0] * 3, [15.0] * 3),
        _calibrate(chooser, 2, [25.0] * 3, [40.0] * 3, [28.0] * 3),
        _calibrate(chooser, 4, [60.0] * 3, [50.0] * 3, [65.0] * 3),
    ]
    assert [chooser.choice(b) for b in (1, 2, 4)] == [2, 1, 0]
    assert [row["method"] for row in rows] == ["prior+jacobi+tree:compile", "prior+jacobi:compile", "greedy:compile"]
    assert rows[0]["speculative_ms"] == 15.0 and rows[0]["speed_up"] == 2.0 and rows[2]["speculate"] is False
    assert rows[0]["methods_ms"] == {"greedy:compile": 30.0, "prior+jacobi:compile": 20.0,
                                     "prior+jacobi+tree:compile": 15.0}  # fmt: skip
    assert [d["method"] for d in chooser.decisions] == [row["method"] for row in rows]
    table = format_calibration(chooser.calibration).splitlines()
    assert table[0] == ("| bucket | greedy:compile ms/call | prior+jacobi:compile ms/call | "
                        "prior+jacobi+tree:compile ms/call | speed-up | decodes with |")  # fmt: skip
    assert table[2] == "| 1 | 30.0 | 20.0 | 15.0 | 2.00x | prior+jacobi+tree:compile |"


def test_every_other_method_is_explored_in_turn_and_a_slower_head_loses_the_bucket():
    """The head's composition wins the calibration, then turns slower on the traffic than exact (a robot's
    scenes the synthetic ones did not show): exact takes over once the medians cross, and greedy and the head keep
    being explored, in turn."""
    chooser = ModeChooser((1,), METHODS, explore_every=4, baseline="greedy:compile")
    _calibrate(chooser, 1, [20.0] * 3, [30.0] * 3, [15.0] * 3)
    modes = _traffic(chooser, 1, 64, 20.0, 26.0, 30.0)  # exact 20 ms, the head 26 ms, greedy 30 ms
    assert chooser.choice(1) == 1 and modes[:3] == [2, 2, 2]
    flip = next(d for d in chooser.decisions if d["why"] == "traffic")
    assert flip["method"] == "prior+jacobi:compile" and flip["medians_ms"]["prior+jacobi:compile"] == 20.0
    explored = [mode for mode in modes[8:] if mode != 1]
    assert set(explored) == {0, 2} and abs(explored.count(0) - explored.count(2)) <= 1
    stats = chooser.stats()["buckets"]["1"]
    assert stats["method"] == "prior+jacobi:compile" and stats["speculate"] is True
    assert {name: row["batches"] for name, row in stats["methods"].items()} == {
        name: modes.count(mode) for mode, name in enumerate(("greedy:compile", *METHODS))
    }
    assert stats["speculative_batches"] == modes.count(1) + modes.count(2)
    assert stats["speculative_median_ms"] == 20.0 and stats["greedy_median_ms"] == 30.0


def test_fixed_speculating_buckets_still_measure_which_method():
    """speculate_buckets fixes speculate-or-greedy; which speculative method is still the faster one."""
    chooser = ModeChooser((1, 2), METHODS, speculate_buckets=(1,), explore_every=4)
    assert chooser.allowed == {1: (1, 2), 2: (0,)} and chooser.measured
    _calibrate(chooser, 1, [20.0] * 3, [5.0] * 3, [15.0] * 3)  # greedy fastest, but bucket 1 is fixed to speculate
    _calibrate(chooser, 2, [20.0] * 3, [30.0] * 3, [15.0] * 3)  # speculation fastest, but bucket 2 is fixed greedy
    assert (chooser.choice(1), chooser.choice(2)) == (2, 0)
    assert set(_traffic(chooser, 1, 32, 20.0, 15.0, 5.0)) == {1, 2}  # never greedy
    assert set(_traffic(chooser, 2, 32, 20.0, 15.0, 30.0)) == {0}  # never explored
