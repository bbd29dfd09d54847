"""Per-call speculation statistics, returned as ``generate(...).speculation``."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field


@dataclass
class SpeculationStats:
    """What one (or several merged) speculative ``generate`` calls did.

    Attributes:
        accept_lengths: tokens emitted by each target forward, in order: the accepted drafted tokens + 1 token of
            the target's own. ``sum(accept_lengths)`` is the number of new tokens. The prefill is a target forward
            too: it emits 1 token, or more when drafts known up front were verified inside it.
        tree_sizes: drafted tokens (tree nodes) verified by each target forward (0 = a plain decoding step).
        num_draft_forwards: forwards run by drafters (draft-head catch-ups and tree levels; model-free drafters 0).
        drafted_per_position / accepted_per_position: ``[d]`` = how many verifications had a drafted token at
            depth d / accepted a drafted token at depth d.
        accepted_by_drafter: accepted drafted tokens per drafter name (e.g. ``{"prior": 9, "head-tree": 4}``).
        action_bin_distances: for each emitted action token, its bin distance to the target's greedy token at that
            position (0 under exact acceptance, at most the tolerance under relaxed acceptance).
        target_seconds / draft_seconds / total_seconds: wall time in target forwards, in drafters, and in the
            whole decode (the rest is bookkeeping). Device-synchronised only with ``profile_speculation=True``.
        num_batch_forwards: the target forwards actually run. For a batch of B rows the counts above are summed
            over rows (a batch forward counts once for every row that took part in it: each row's tokens per
            forward is what the batch achieves per forward for that row); at B = 1 it equals ``num_target_forwards``.
        compile_seconds: time spent compiling every verification width before the first compiled round, the prefill
            graph after the first prefill (which runs eagerly), and the drafters' compiled work (a draft head's
            expansion graphs) at their first proposal (the first call per model, slot count and drafter kind; 0
            afterwards); inside ``total_seconds`` (and the draft head's part inside ``draft_seconds``).
        compiled_widths: the node count (width bucket, filler included) of each verification that ran through the
            compiled model call (see ``speculative.compiled``); empty when every forward ran eagerly.
        compiled_prefills: prefills that ran through the compiled model call (one graph for every prompt length; a
            call site's first prefill runs eagerly and compiles it).
        jacobi_guesses_per_position / jacobi_right_per_position: ``[j]`` = how many of the target's guesses of the
            j-th token after a bonus token ([`JacobiDrafter`]'s tails, j = 0 first) reached a position the row emitted /
            equalled the token emitted there (whether or not they were verified).
        rows: one [`SpeculationStats`] per batch row (B > 1 only; their times are 0: a batch forward is shared).
    """

    accept_lengths: list[int] = field(default_factory=list)
    tree_sizes: list[int] = field(default_factory=list)
    num_draft_forwards: int = 0
    drafted_per_position: list[int] = field(default_factory=list)
    accepted_per_position: list[int] = field(default_factory=list)
    accepted_by_drafter: Counter = field(default_factory=Counter)
    action_bin_distances: list[int] = field(default_factory=list)
    target_seconds: float = 0.0
    draft_seconds: float = 0.0
    total_seconds: float = 0.0
    num_batch_forwards: int = 0
    compiled_widths: list[int] = field(default_factory=list)
    compile_seconds: float = 0.0
    compiled_prefills: int = 0
    jacobi_guesses_per_position: list[int] = field(default_factory=list)
    jacobi_right_per_position: list[int] = field(default_factory=list)
    rows: list[SpeculationStats] = field(default_factory=list)

    @property
    def num_target_forwards(self) -> int:
        return len(self.accept_lengths)

    def accepted_positions(self, tokens: int | None = None) -> list[bool]:
        """For one call (or one batch row), which emitted tokens were drafted tokens the target accepted, in order:
        each forward emits its accepted drafts and then one token of its own, so ``accept_lengths`` ``[3, 1, 4]`` gives
        accepted, accepted, own, own, accepted, accepted, accepted, own. ``tokens``: cut or pad (with own) to this
        many (default: every new token)."""
        drafted: list[bool] = []
        for length in self.accept_lengths:
            drafted += [True] * (length - 1) + [False]
        tokens = len(drafted) if tokens is None else tokens
        return drafted[:tokens] + [False] * (tokens - len(drafted))

    @property
    def num_new_tokens(self) -> int:
        return sum(self.accept_lengths)

    @property
    def mean_accept_length(self) -> float:
        """New tokens per target forward (the prefill included): the paper's tau counted over every forward."""
        return self.num_new_tokens / max(self.num_target_forwards, 1)

    tokens_per_target_forward = mean_accept_length

    @property
    def acceptance_rate_per_position(self) -> list[float]:
        """Fraction of verifications that accepted a drafted token at each depth, among those that drafted one."""
        return [a / d if d else 0.0 for a, d in zip(self.accepted_per_position, self.drafted_per_position)]

    @property
    def jacobi_right_rate_per_position(self) -> list[float]:
        """Fraction of the Jacobi guesses of the j-th token after a bonus token that were right."""
        return [r / g if g else 0.0 for r, g in zip(self.jacobi_right_per_position, self.jacobi_guesses_per_position)]

    def record_guesses(self, right: list[bool]) -> None:
        """Books one tail of guesses checked against the emitted tokens (``right[j]``: the j-th guess was right)."""
        self.jacobi_guesses_per_position = _add_padded(self.jacobi_guesses_per_position, [1] * len(right))
        self.jacobi_right_per_position = _add_padded(self.jacobi_right_per_position, [int(r) for r in right])

    def add_guesses(self, other: SpeculationStats) -> None:
        """Adds ``other``'s Jacobi guess counts to this object's (e.g. over the calls of a benchmark)."""
        self.jacobi_guesses_per_position = _add_padded(
            self.jacobi_guesses_per_position, other.jacobi_guesses_per_position
        )
        self.jacobi_right_per_position = _add_padded(self.jacobi_right_per_position, other.jacobi_right_per_position)

    def record_verification(self, tree_depth: int, tree_size: int, accepted_sources: list[str]) -> None:
        """Books one target forward that verified a tree of ``tree_size`` nodes and ``tree_depth`` levels and
        accepted a path whose nodes came from ``accepted_sources`` (one name per accepted token)."""
        self.tree_sizes.append(tree_size)
        grow = tree_depth - len(self.drafted_per_position)
        if grow > 0:
            self.drafted_per_position.extend([0] * grow)
            self.accepted_per_position.extend([0] * grow)
        for depth in range(tree_depth):
            self.drafted_per_position[depth] += 1
            self.accepted_per_position[depth] += int(depth < len(accepted_sources))
        self.accepted_by_drafter.update(accepted_sources)

    def absorb_rows(self) -> None:
        """Adds every row's counts (``rows``) into this object's (the loop's batch total)."""
        for row in self.rows:
            self.accept_lengths += row.accept_lengths
            self.tree_sizes += row.tree_sizes
            self.num_draft_forwards += row.num_draft_forwards
            self.drafted_per_position = _add_padded(self.drafted_per_position, row.drafted_per_position)
            self.accepted_per_position = _add_padded(self.accepted_per_position, row.accepted_per_position)
            self.accepted_by_drafter += row.accepted_by_drafter
            self.action_bin_distances += row.action_bin_distances
            self.add_guesses(row)

    def merge(self, other: SpeculationStats) -> SpeculationStats:
        """Sum of two runs' statistics (e.g. over a benchmark); ``rows`` are concatenated."""
        merged = SpeculationStats(
            accept_lengths=self.accept_lengths + other.accept_lengths,
            tree_sizes=self.tree_sizes + other.tree_sizes,
            num_draft_forwards=self.num_draft_forwards + other.num_draft_forwards,
            drafted_per_position=_add_padded(self.drafted_per_position, other.drafted_per_position),
            accepted_per_position=_add_padded(self.accepted_per_position, other.accepted_per_position),
            accepted_by_drafter=self.accepted_by_drafter + other.accepted_by_drafter,
            action_bin_distances=self.action_bin_distances + other.action_bin_distances,
            target_seconds=self.target_seconds + other.target_seconds,
            draft_seconds=self.draft_seconds + other.draft_seconds,
            total_seconds=self.total_seconds + other.total_seconds,
            num_batch_forwards=self.num_batch_forwards + other.num_batch_forwards,
            compiled_widths=self.compiled_widths + other.compiled_widths,
            compile_seconds=self.compile_seconds + other.compile_seconds,
            compiled_prefills=self.compiled_prefills + other.compiled_prefills,
            rows=self.rows + other.rows,
        )
        merged.add_guesses(self)
        merged.add_guesses(other)
        return merged


def _add_padded(a: list[int], b: list[int]) -> list[int]:
    """Element-wise sum of two count lists, the shorter one padded with zeros."""
    width = max(len(a), len(b))
    return [x + y for x, y in zip(a + [0] * (width - len(a)), b + [0] * (width - len(b)))]
