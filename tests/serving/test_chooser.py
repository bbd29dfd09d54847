"""The mode chooser alone: made-up call times, no policy, no clock."""

from __future__ import annotations

import pytest

from hf_specvla.serving.chooser import CLEAR_GAP_EXPLORE_FACTOR, TIMING_WINDOW, ModeChooser, format_calibration


def _traffic(chooser: ModeChooser, bucket: int, calls: int, spec_ms: float, greedy_ms: float) -> list[bool]:
    """``calls`` batches of ``bucket``, each taking the made-up time of the mode the chooser picked; the modes."""
    modes = []
    for _ in range(calls):
        speculative = chooser.mode_for(bucket)
        chooser.observe(bucket, speculative, spec_ms if speculative else greedy_ms, rows=bucket)
        modes.append(speculative)
    return modes


def test_calibration_sets_each_bucket_s_choice_and_is_recorded():
    chooser = ModeChooser((1, 4))
    small = chooser.calibrate(1, [20.0, 22.0, 21.0], [30.0, 31.0, 29.0])  # speculation 1.43x faster
    large = chooser.calibrate(4, [60.0, 61.0, 59.0], [50.0, 52.0, 51.0])  # greedy faster
    assert (chooser.speculate(1), chooser.speculate(4)) == (True, False)
    assert small == {"bucket": 1, "greedy_ms": 30.0, "speculative_ms": 21.0, "speed_up": round(30 / 21, 3),
                     "speculate": True}  # fmt: skip
    assert large["speculate"] is False and chooser.calibration == [small, large]
    decided = [(d["bucket"], d["speculate"], d["why"]) for d in chooser.decisions]
    assert decided == [(1, True, "calibration"), (4, False, "calibration")]
    assert "| 4 | 51.0 | 60.0 | 0.85x | greedy |" in format_calibration(chooser.calibration)


def test_the_choice_follows_the_traffic_and_each_change_is_recorded():
    """Speculation was faster at start-up; on the traffic it turns slower: the choice flips once the medians cross,
    the flip is recorded with the medians that decided it, and speculation is still explored now and then."""
    chooser = ModeChooser((2,), explore_every=4)
    chooser.calibrate(2, [10.0] * 3, [12.0] * 3)
    modes = _traffic(chooser, 2, 64, spec_ms=20.0, greedy_ms=12.0)
    assert modes[:3] == [True] * 3 and not any(modes[3:15])  # 3 slow calls flip it (the median passes 12 ms)
    assert modes[-32:].count(True) == 32 // (4 * CLEAR_GAP_EXPLORE_FACTOR)  # a clear gap: explored 4x less often
    flip = chooser.decisions[-1]
    assert (flip["bucket"], flip["speculate"], flip["why"]) == (2, False, "traffic")
    assert flip["speculative_ms"] > flip["greedy_ms"] == 12.0
    stats = chooser.stats()["buckets"]["2"]
    assert stats["mode"] == "greedy" and stats["speculative_batches"] + stats["greedy_batches"] == 64
    assert stats["greedy_rows"] == 2 * stats["greedy_batches"]
    assert chooser.stats()["speculative_share"] == stats["speculative_share"] == round(modes.count(True) / 64, 4)


def test_only_the_recent_calls_decide():
    chooser = ModeChooser((1,), explore_every=2)
    chooser.calibrate(1, [10.0] * 3, [30.0] * 3)
    _traffic(chooser, 1, 2 * TIMING_WINDOW, spec_ms=10.0, greedy_ms=30.0)
    assert chooser.speculate(1)
    _traffic(chooser, 1, 4 * TIMING_WINDOW, spec_ms=40.0, greedy_ms=30.0)  # speculation slows down for good
    assert not chooser.speculate(1)
    assert len(chooser.timings[(1, True)]) == TIMING_WINDOW


def test_the_other_mode_is_explored_less_often_when_the_choice_is_clear():
    explored = []
    for spec_ms, greedy_ms in ((10.0, 11.0), (10.0, 20.0)):  # a 10% gap, then a clear 2x
        chooser = ModeChooser((1,), explore_every=4)
        chooser.calibrate(1, [spec_ms] * 5, [greedy_ms] * 5)
        modes = [chooser.mode_for(1) for _ in range(32)]  # no observations: the medians stay
        explored.append(modes.count(False))
    assert explored == [32 // 4, 32 // (4 * CLEAR_GAP_EXPLORE_FACTOR)]


@pytest.mark.parametrize(
    ("settings", "expected"),
    [
        ({"speculate_buckets": (1,)}, [True, False]),  # fixed by the user
        ({"speculates": False}, [False, False]),  # a greedy-only method
        ({"explore_every": 0}, [True, True]),  # measured, never explored
    ],
)
def test_a_fixed_or_unexplored_choice_never_changes(settings, expected):
    chooser = ModeChooser((1, 2), **settings)
    for bucket in (1, 2):
        modes = _traffic(chooser, bucket, 40, spec_ms=50.0, greedy_ms=10.0)  # greedy far faster: no matter
        assert set(modes) == {expected[bucket - 1]}
    assert [chooser.speculate(b) for b in (1, 2)] == expected
    assert not chooser.decisions


def test_stats_before_any_batch():
    stats = ModeChooser((1, 2)).stats()
    assert stats["speculative_share"] is None and stats["decisions"] == []
    assert stats["buckets"]["1"] == {"speculate": True, "mode": "speculative", "speculative_batches": 0,
                                     "speculative_rows": 0, "speculative_median_ms": None, "greedy_batches": 0,
                                     "greedy_rows": 0, "greedy_median_ms": None, "speculative_share": None}  # fmt: skip
