"""Per-call speculation statistics, returned as ``generate(...).speculation``."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class SpeculationStats:
    """What one (or several merged) speculative ``generate`` calls did.

    Attributes:
        accept_lengths: tokens produced by each target forward, in order. The prefill forward produces 1; a
            verification forward produces the accepted drafted tokens + 1 bonus token. ``sum(accept_lengths)``
            is the number of new tokens.
        num_target_forwards: target forwards (prefill included) = ``len(accept_lengths)``.
        num_draft_forwards: draft-head forwards (catch-up and chain steps).
        drafted_per_position: ``[j]`` = how many verifications had a drafted token at draft position j.
        accepted_per_position: ``[j]`` = how many of those accepted the drafted token at position j.
        target_seconds / draft_seconds / total_seconds: wall time in target forwards, in draft forwards, and in
            the whole decode (the rest is bookkeeping). Device-synchronised only with ``profile_speculation=True``.
    """

    accept_lengths: list[int] = field(default_factory=list)
    num_draft_forwards: int = 0
    drafted_per_position: list[int] = field(default_factory=list)
    accepted_per_position: list[int] = field(default_factory=list)
    target_seconds: float = 0.0
    draft_seconds: float = 0.0
    total_seconds: float = 0.0

    @property
    def num_target_forwards(self) -> int:
        return len(self.accept_lengths)

    @property
    def num_new_tokens(self) -> int:
        return sum(self.accept_lengths)

    @property
    def mean_accept_length(self) -> float:
        """New tokens per target forward (prefill included), the paper's tau counted over every forward."""
        return self.num_new_tokens / max(self.num_target_forwards, 1)

    @property
    def acceptance_rate_per_position(self) -> list[float]:
        """Fraction of drafted tokens accepted at each draft position."""
        return [a / d if d else 0.0 for a, d in zip(self.accepted_per_position, self.drafted_per_position)]

    def record_verification(self, num_drafted: int, num_accepted: int) -> None:
        """Books one verification forward that checked ``num_drafted`` tokens and accepted ``num_accepted``."""
        grow = num_drafted - len(self.drafted_per_position)
        if grow > 0:
            self.drafted_per_position.extend([0] * grow)
            self.accepted_per_position.extend([0] * grow)
        for j in range(num_drafted):
            self.drafted_per_position[j] += 1
            self.accepted_per_position[j] += int(j < num_accepted)

    def merge(self, other: SpeculationStats) -> SpeculationStats:
        """Sum of two runs' statistics (e.g. over a benchmark)."""
        merged = SpeculationStats(
            accept_lengths=self.accept_lengths + other.accept_lengths,
            num_draft_forwards=self.num_draft_forwards + other.num_draft_forwards,
            target_seconds=self.target_seconds + other.target_seconds,
            draft_seconds=self.draft_seconds + other.draft_seconds,
            total_seconds=self.total_seconds + other.total_seconds,
        )
        merged.drafted_per_position = _add_padded(self.drafted_per_position, other.drafted_per_position)
        merged.accepted_per_position = _add_padded(self.accepted_per_position, other.accepted_per_position)
        return merged


def _add_padded(a: list[int], b: list[int]) -> list[int]:
    """Element-wise sum of two count lists, the shorter one padded with zeros."""
    width = max(len(a), len(b))
    return [x + y for x, y in zip(a + [0] * (width - len(a)), b + [0] * (width - len(b)))]
