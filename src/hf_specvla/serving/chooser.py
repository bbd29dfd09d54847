"""Whether a batch decodes speculatively or with the greedy baseline, per bucket ([`ModeChooser`]): no policy, no
clock, only the call times it is told, so it is tested with made-up timings.

Batched speculation loses to batched greedy once batches are large on a compute-bound machine (each forward verifies
every row's drafts, and a batch runs as many forwards as its slowest row). So for each bucket the chooser picks the
mode whose recent calls were faster: seeded by the start-up calibration ([`calibrate`]), then kept current on the
traffic ([`mode_for`] runs the other mode every ``explore_every``-th batch of a bucket, [`observe`] takes each
call's time; the choice follows the medians of the last ``TIMING_WINDOW`` calls of each mode). Or the user fixes the
table (``speculate_buckets``). Every change of choice is recorded ([`decisions`]: when, why, the medians that
decided). At ``r = 0`` both modes give greedy's actions, so the choice changes speed, never behaviour.
"""

from __future__ import annotations

import logging
import statistics
from collections import deque

logger = logging.getLogger(__name__)

#: calls kept per bucket and mode for the choice (their median decides)
TIMING_WINDOW = 16
#: a gap between the two modes' median call times past which the other mode is explored less often, and how much
CLEAR_GAP, CLEAR_GAP_EXPLORE_FACTOR = 0.2, 4
#: decisions kept for ``GET /stats``
DECISIONS_KEPT = 64


class ModeChooser:
    """The speculate-or-greedy choice per bucket.

    Args:
        buckets: the batch sizes decoded at.
        speculates: whether the method speculates at all (False: greedy everywhere, nothing measured).
        speculate_buckets: the buckets fixed to speculate (None: measured).
        explore_every: every n-th batch of a bucket runs the mode not chosen (0: never).
    """

    def __init__(self, buckets: tuple[int, ...], speculates: bool = True,
                 speculate_buckets: tuple[int, ...] | None = None, explore_every: int = 16):  # fmt: skip
        self.buckets, self.speculates, self.explore_every = tuple(buckets), speculates, explore_every
        #: whether the choice follows measurements (else it is fixed: by ``speculate_buckets``, or never speculate)
        self.measured = speculates and speculate_buckets is None
        fixed = speculate_buckets if speculate_buckets is not None else buckets
        self._choice = {b: speculates and b in fixed for b in buckets}
        self.timings = {(b, mode): deque(maxlen=TIMING_WINDOW) for b in buckets for mode in (True, False)}
        self.calls = {b: 0 for b in buckets}  # batches per bucket, for exploration
        self.served = {key: [0, 0] for key in self.timings}  # (bucket, speculative) -> [batches, rows]
        self.calibration: list[dict] = []  # the start-up table ([`calibrate`])
        #: every change of choice, oldest first: ``{"bucket", "speculate", "why", "batch", "speculative_ms",
        #: "greedy_ms"}`` (``why``: ``"calibration"`` or ``"traffic"``; ``batch``: the bucket's batches so far)
        self.decisions: deque[dict] = deque(maxlen=DECISIONS_KEPT)

    def speculate(self, bucket: int) -> bool:
        """Whether batches of ``bucket`` rows decode speculatively now (the choice, exploration aside)."""
        return self._choice[bucket]

    def mode_for(self, bucket: int) -> bool:
        """The mode of the bucket's next batch (counted): the chosen one, or the other every ``explore_every``-th
        batch (a measured choice only; ``CLEAR_GAP_EXPLORE_FACTOR`` times less often while the two modes' medians
        differ by more than ``CLEAR_GAP``: a clear choice needs fewer checks, and each costs that call the gap)."""
        self.calls[bucket] += 1
        chosen, every = self._choice[bucket], self.explore_every
        if not (self.measured and every):
            return chosen
        spec, greedy = self._medians(bucket)
        if spec is not None and greedy is not None and abs(spec / greedy - 1) > CLEAR_GAP:
            every *= CLEAR_GAP_EXPLORE_FACTOR
        return not chosen if self.calls[bucket] % every == 0 else chosen

    def observe(self, bucket: int, speculative: bool, ms: float, rows: int) -> None:
        """A traffic batch of ``rows`` requests took ``ms`` in ``speculative`` mode: counted, and (measured choice)
        the choice follows the two modes' medians."""
        self.served[(bucket, speculative)][0] += 1
        self.served[(bucket, speculative)][1] += rows
        self.timings[(bucket, speculative)].append(ms)
        if self.measured:
            self._decide(bucket, "traffic")

    def calibrate(self, bucket: int, speculative_ms: list[float], greedy_ms: list[float]) -> dict:
        """The start-up calibration of ``bucket``: its timed calls in each mode seed the timings, set the choice (a
        measured one) and make its row of the calibration table (returned)."""
        for speculative, times in ((True, speculative_ms), (False, greedy_ms)):
            self.timings[(bucket, speculative)].extend(times)
        spec, greedy = statistics.median(speculative_ms), statistics.median(greedy_ms)
        if self.measured:
            self._decide(bucket, "calibration")
        row = {"bucket": bucket, "greedy_ms": round(greedy, 2), "speculative_ms": round(spec, 2),
               "speed_up": round(greedy / spec, 3), "speculate": spec < greedy}  # fmt: skip
        self.calibration.append(row)
        return row

    def _decide(self, bucket: int, why: str) -> None:
        spec, greedy = self._medians(bucket)
        if spec is None or greedy is None:
            return
        choice = spec < greedy
        if choice != self._choice[bucket] or why == "calibration":
            if choice != self._choice[bucket]:
                logger.info("bucket %d now decodes %s (median %.1f ms speculative vs %.1f ms greedy, %s)", bucket,
                            "speculatively" if choice else "greedily", spec, greedy, why)  # fmt: skip
            self.decisions.append({"bucket": bucket, "speculate": choice, "why": why, "batch": self.calls[bucket],
                                   "speculative_ms": round(spec, 2), "greedy_ms": round(greedy, 2)})  # fmt: skip
        self._choice[bucket] = choice

    def _medians(self, bucket: int) -> tuple[float | None, float | None]:
        spec, greedy = self.timings[(bucket, True)], self.timings[(bucket, False)]
        return (statistics.median(spec) if spec else None), (statistics.median(greedy) if greedy else None)

    def stats(self) -> dict:
        """Per bucket: batches and rows decoded in each mode, the median ms of the recent calls, the mode chosen
        now (``mode``, ``speculate``) and the share of its batches decoded speculatively; the same share over every
        bucket; the decisions."""
        buckets, counts = {}, {True: 0, False: 0}
        for bucket in self.buckets:
            row = {"speculate": self._choice[bucket], "mode": "speculative" if self._choice[bucket] else "greedy"}
            for (speculative, mode), median in zip(((True, "speculative"), (False, "greedy")), self._medians(bucket)):
                row[f"{mode}_batches"], row[f"{mode}_rows"] = self.served[(bucket, speculative)]
                row[f"{mode}_median_ms"] = None if median is None else round(median, 2)
                counts[speculative] += row[f"{mode}_batches"]
            row["speculative_share"] = _share(row["speculative_batches"], row["greedy_batches"])
            buckets[str(bucket)] = row
        return {"buckets": buckets, "speculative_share": _share(counts[True], counts[False]),
                "decisions": list(self.decisions)}  # fmt: skip


def _share(part: int, rest: int) -> float | None:
    """``part / (part + rest)``, rounded (None before anything was counted)."""
    return round(part / (part + rest), 4) if part + rest else None


def format_calibration(table: list[dict]) -> str:
    """Markdown table of a calibration ([`ModeChooser.calibrate`]'s rows)."""
    lines = ["| bucket | greedy ms/call | speculative ms/call | speed-up | decodes |", "|---:|---:|---:|---:|---|"]
    for row in table:
        lines.append(f"| {row['bucket']} | {row['greedy_ms']:.1f} | {row['speculative_ms']:.1f} | "
                     f"{row['speed_up']:.2f}x | {'speculative' if row['speculate'] else 'greedy'} |")  # fmt: skip
    return "\n".join(lines)
