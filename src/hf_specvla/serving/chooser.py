"""How a batch decodes, per bucket ([`ModeChooser`]): with the greedy baseline or one of the speculative methods
(its *modes*: 0 the baseline, 1.. the methods, e.g. ``exact`` and, given a draft head, ``exact``'s composition with
the head). No policy, no clock, only the call times it is told, so it is tested with made-up timings.

Batched speculation loses to batched greedy once batches are large on a compute-bound machine (each forward verifies
every row's drafts, and a batch runs as many forwards as its slowest row), and a draft head pays only where its
forwards cost less than the target forwards it saves. So for each bucket the chooser picks the mode whose recent
calls were fastest: seeded by the start-up calibration ([`calibrate`]), then kept current on the traffic
([`mode_for`] runs another mode every ``explore_every``-th batch of a bucket, in turn; [`observe`] takes each call's
time; the choice follows the medians of the last ``TIMING_WINDOW`` calls of each mode). Or the user fixes which
buckets speculate (``speculate_buckets``; with several methods, which one is still measured). Every change of choice
is recorded ([`decisions`]: when, why, the medians that decided). At ``r = 0`` every mode gives greedy's actions, so
the choice changes speed, never behaviour.
"""

from __future__ import annotations

import logging
import statistics
from collections import deque
from collections.abc import Mapping

logger = logging.getLogger(__name__)

#: calls kept per bucket and mode for the choice (their median decides)
TIMING_WINDOW = 16
#: a gap between the chosen mode's median call time and the next fastest's past which the others are explored less
#: often, and how much
CLEAR_GAP, CLEAR_GAP_EXPLORE_FACTOR = 0.2, 4
#: decisions kept for ``GET /stats``
DECISIONS_KEPT = 64
#: the mode of the greedy baseline (modes 1.. are the speculative methods, in the order given)
GREEDY_MODE = 0


class ModeChooser:
    """The choice of mode per bucket: the greedy baseline (mode 0) or a speculative method (modes 1..).

    Args:
        buckets: the batch sizes decoded at.
        methods: the speculative methods' names, modes 1, 2, ... (empty: greedy everywhere, nothing measured).
        speculate_buckets: the buckets fixed to speculate, the others fixed to greedy (None: measured).
        explore_every: every n-th batch of a bucket runs a mode not chosen (0: never).
        baseline: the greedy baseline's name (mode 0).
    """

    def __init__(
        self,
        buckets: tuple[int, ...],
        methods: tuple[str, ...] = ("speculative",),
        speculate_buckets: tuple[int, ...] | None = None,
        explore_every: int = 16,
        baseline: str = "greedy",
    ):
        self.buckets, self.explore_every = tuple(buckets), explore_every
        self.names = (baseline, *methods)  # mode -> name
        self.speculates = bool(methods)
        speculative = tuple(range(1, len(self.names)))
        if not speculative:
            allowed = {b: (GREEDY_MODE,) for b in self.buckets}
        elif speculate_buckets is None:
            allowed = {b: (GREEDY_MODE, *speculative) for b in self.buckets}
        else:
            allowed = {b: speculative if b in speculate_buckets else (GREEDY_MODE,) for b in self.buckets}
        #: the modes each bucket chooses from (one: fixed)
        self.allowed: dict[int, tuple[int, ...]] = allowed
        #: whether any choice follows measurements (else every bucket's mode is fixed)
        self.measured = any(len(modes) > 1 for modes in allowed.values())
        self._choice = {b: next((m for m in allowed[b] if m != GREEDY_MODE), GREEDY_MODE) for b in self.buckets}
        modes = range(len(self.names))
        self.timings = {(b, mode): deque(maxlen=TIMING_WINDOW) for b in self.buckets for mode in modes}
        self.calls = {b: 0 for b in self.buckets}  # batches per bucket, for exploration
        self.served = {key: [0, 0] for key in self.timings}  # (bucket, mode) -> [batches, rows]
        self.calibration: list[dict] = []  # the start-up table ([`calibrate`])
        #: every change of choice, oldest first: ``{"bucket", "speculate", "method", "why", "batch",
        #: "speculative_ms", "greedy_ms", "medians_ms"}`` (``method``: the mode chosen, by name; ``why``:
        #: ``"calibration"`` or ``"traffic"``; ``batch``: the bucket's batches so far; ``speculative_ms``: the
        #: fastest speculative method's median; ``medians_ms``: every measured mode's, by name)
        self.decisions: deque[dict] = deque(maxlen=DECISIONS_KEPT)

    def speculate(self, bucket: int) -> bool:
        """Whether batches of ``bucket`` rows decode speculatively now (the choice, exploration aside)."""
        return self._choice[bucket] != GREEDY_MODE

    def choice(self, bucket: int) -> int:
        """The mode batches of ``bucket`` rows decode with now (exploration aside)."""
        return self._choice[bucket]

    def mode_for(self, bucket: int) -> int:
        """The mode of the bucket's next batch (counted): the chosen one, or every ``explore_every``-th batch one of
        the others, in turn (a measured choice only; ``CLEAR_GAP_EXPLORE_FACTOR`` times less often while the chosen
        mode's median is more than ``CLEAR_GAP`` below every other's: a clear choice needs fewer checks, and each
        costs that call the gap)."""
        self.calls[bucket] += 1
        chosen, every = self._choice[bucket], self.explore_every
        others = [m for m in self.allowed[bucket] if m != chosen]
        if not (others and every):
            return chosen
        medians = self._medians(bucket)
        mine, theirs = medians.get(chosen), [medians.get(m) for m in others]
        if mine is not None and None not in theirs and min(theirs) / mine - 1 > CLEAR_GAP:
            every *= CLEAR_GAP_EXPLORE_FACTOR
        if self.calls[bucket] % every:
            return chosen
        return others[(self.calls[bucket] // every - 1) % len(others)]

    def observe(self, bucket: int, mode: int, ms: float, rows: int) -> None:
        """A traffic batch of ``rows`` requests took ``ms`` in ``mode``: counted, and (measured choice) the choice
        follows the modes' medians."""
        self.served[(bucket, mode)][0] += 1
        self.served[(bucket, mode)][1] += rows
        self.timings[(bucket, mode)].append(ms)
        if len(self.allowed[bucket]) > 1:
            self._decide(bucket, "traffic")

    def calibrate(self, bucket: int, times_ms: Mapping[int, list[float]]) -> dict:
        """The start-up calibration of ``bucket``: its timed calls per mode (``{mode: [ms, ...]}``, every mode)
        seed the timings, set the choice (a measured one) and make its row of the calibration table (returned:
        ``greedy_ms``, ``speculative_ms`` (the fastest speculative method's median), ``speed_up`` (greedy over it),
        ``speculate``, ``method`` (the mode chosen, by name) and ``methods_ms`` (each mode's median, by name))."""
        for mode, times in times_ms.items():
            self.timings[(bucket, mode)].extend(times)
        if len(self.allowed[bucket]) > 1:
            self._decide(bucket, "calibration")
        medians = {mode: statistics.median(times) for mode, times in times_ms.items() if times}
        greedy, spec = medians.get(GREEDY_MODE), self._fastest_speculative(medians)
        row = {
            "bucket": bucket,
            "greedy_ms": _round(greedy),
            "speculative_ms": _round(spec),
            "speed_up": round(greedy / spec, 3) if greedy and spec else None,
            "speculate": self.speculate(bucket),
            "method": self.names[self._choice[bucket]],
            "methods_ms": {self.names[mode]: round(ms, 2) for mode, ms in medians.items()},
        }
        self.calibration.append(row)
        return row

    def _decide(self, bucket: int, why: str) -> None:
        medians = self._medians(bucket)
        measured = [m for m in self.allowed[bucket] if m in medians]
        if len(measured) < 2:
            return
        current = self._choice[bucket]
        fastest = min(measured, key=lambda m: (medians[m], m != current))  # a tie keeps the current choice
        if fastest != current or why == "calibration":
            if fastest != current:
                logger.info(
                    "bucket %d now decodes with %s (medians: %s; %s)",
                    bucket,
                    self.names[fastest],
                    _format_medians(medians, self.names),
                    why,
                )
            named = {self.names[m]: round(ms, 2) for m, ms in medians.items()}
            self.decisions.append(
                {
                    "bucket": bucket,
                    "speculate": fastest != GREEDY_MODE,
                    "method": self.names[fastest],
                    "why": why,
                    "batch": self.calls[bucket],
                    "speculative_ms": _round(self._fastest_speculative(medians)),
                    "greedy_ms": _round(medians.get(GREEDY_MODE)),
                    "medians_ms": named,
                }
            )
        self._choice[bucket] = fastest

    def _medians(self, bucket: int) -> dict[int, float]:
        """Each mode's median of its recent calls in ``bucket`` (the modes with none left out)."""
        return {
            mode: statistics.median(self.timings[(bucket, mode)])
            for mode in range(len(self.names))
            if self.timings[(bucket, mode)]
        }

    @staticmethod
    def _fastest_speculative(medians: Mapping[int, float]) -> float | None:
        spec = [ms for mode, ms in medians.items() if mode != GREEDY_MODE]
        return min(spec) if spec else None

    def stats(self) -> dict:
        """Per bucket: batches and rows decoded speculatively (every method together) and greedily, the median ms of
        the recent calls (speculative: the fastest method's), the mode chosen now (``mode``, ``speculate``,
        ``method``) and the share of its batches decoded speculatively; per method (``methods``, by name) its
        batches, rows and median; the same share over every bucket; the decisions."""
        buckets, counts = {}, {True: 0, False: 0}
        for bucket in self.buckets:
            chosen, medians = self._choice[bucket], self._medians(bucket)
            row = {
                "speculate": chosen != GREEDY_MODE,
                "mode": "speculative" if chosen else "greedy",
                "method": self.names[chosen],
            }
            methods = {}
            for mode, name in enumerate(self.names):
                batches, rows = self.served[(bucket, mode)]
                methods[name] = {"batches": batches, "rows": rows, "median_ms": _round(medians.get(mode))}
            spec = [self.served[(bucket, mode)] for mode in range(1, len(self.names))]
            row["speculative_batches"], row["speculative_rows"] = sum(b for b, _ in spec), sum(r for _, r in spec)
            row["speculative_median_ms"] = _round(self._fastest_speculative(medians))
            row["greedy_batches"], row["greedy_rows"] = self.served[(bucket, GREEDY_MODE)]
            row["greedy_median_ms"] = _round(medians.get(GREEDY_MODE))
            row["speculative_share"] = _share(row["speculative_batches"], row["greedy_batches"])
            row["methods"] = methods
            counts[True] += row["speculative_batches"]
            counts[False] += row["greedy_batches"]
            buckets[str(bucket)] = row
        return {
            "buckets": buckets,
            "speculative_share": _share(counts[True], counts[False]),
            "decisions": list(self.decisions),
        }


def _round(ms: float | None) -> float | None:
    return None if ms is None else round(ms, 2)


def _share(part: int, rest: int) -> float | None:
    """``part / (part + rest)``, rounded (None before anything was counted)."""
    return round(part / (part + rest), 4) if part + rest else None


def _format_medians(medians: Mapping[int, float], names: tuple[str, ...]) -> str:
    return ", ".join(f"{names[mode]} {ms:.1f} ms" for mode, ms in sorted(medians.items()))


def format_calibration(table: list[dict]) -> str:
    """Markdown table of a calibration ([`ModeChooser.calibrate`]'s rows): each mode's median ms per call, the
    greedy baseline first, the speed-up of the fastest speculative method over it, and the mode chosen."""
    if not table:
        return ""
    names = list(table[0]["methods_ms"])
    lines = [
        "| bucket | " + " | ".join(f"{name} ms/call" for name in names) + " | speed-up | decodes with |",
        "|---:|" + "---:|" * len(names) + "---:|---|",
    ]
    for row in table:
        times = " | ".join("-" if row["methods_ms"].get(n) is None else f"{row['methods_ms'][n]:.1f}" for n in names)
        speed_up = "-" if row["speed_up"] is None else f"{row['speed_up']:.2f}x"
        lines.append(f"| {row['bucket']} | {times} | {speed_up} | {row['method']} |")
    return "\n".join(lines)
