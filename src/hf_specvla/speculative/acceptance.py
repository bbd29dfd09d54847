"""Acceptance: which drafted tokens the target's verification accepts, and which path of a draft tree is kept.

Greedy speculative decoding keeps the longest root-to-leaf path of the draft tree whose every token passes the
rule against the target's greedy token at its parent; the token after that path (the "bonus" token) is always the
target's own greedy choice. Among equally long passing paths (possible only with relaxed acceptance, since
siblings hold distinct tokens) the one with the smallest total bin distance to the target's greedy tokens wins,
then the one proposed first (lowest node index): the output stays as close to greedy as the rule allows.

* [`ExactMatch`]: the drafted token equals the target's greedy token. Output is token-identical to greedy.
* [`RelaxedBinMatch`] (Spec-VLA, arXiv 2507.22424, section 3.3 "relaxed acceptance"): a drafted *action*
  token is also accepted when its bin is within ``bin_tolerance`` (the paper's r) bins of the target's greedy
  token, because neighbouring bins are neighbouring actions. Non-action tokens still need an exact match.
  The accepted token is the *drafted* one. Deviation from the paper: the tolerance may differ per action
  dimension (e.g. 0 for a binary gripper) and per action of a chunk (later actions looser), and both tokens must be
  action tokens (the official code compares raw id differences at every position, so it could accept a text token
  near the action range).
* [`ConfidenceGate`] (after Medusa's typical acceptance): a relaxed acceptance counts only where the target is
  unsure, its greedy token's probability below a threshold; where it is confident the draft must match exactly.
* [`RelaxedBudget`]: at most m relaxed tokens per action, counted along the path and over the call's earlier rounds;
  past the budget acceptance is exact. A relaxed token changes the prefix of every later token, so this bounds how
  far one action can drift from greedy's, not only each token.

* Motion-scaled tolerance ([`RelaxedBinMatch`] with ``motion_scale``): a drafted action token is also accepted within
  ``motion_scale * |target bin - zero-motion bin|`` bins of the target's (per dimension), so a transport move is
  relaxed in proportion to its size and a fine motion near zero stays exact: a relative error bound.
* Action-space bound ([`RelaxedBinMatch`] with ``max_deviation``): whatever the tolerance, an accepted token's action
  is within ``max_deviation`` of the target's in the policy's own units, per dimension.
* [`StrictTailConfirmed`]: a relaxed token is kept only when the action's strict dimensions after it (a gripper) were
  drafted and confirmed by the target in the same verification, so a strict dimension's value never changes on a
  relaxed prefix; otherwise the path ends before the relaxed token and the next token is the target's own.

Sampling (``do_sample=True``): [`sample_trees`] verifies the drafts by speculative sampling (recursive rejection
sampling for trees, every draft a point mass), so the output is distributed exactly as the target's own sampling;
relaxed rules are greedy-only.

Every rule is exact where its tolerance is 0: ``bin_tolerance=0`` is greedy decoding whatever the gate or budget.

The rules say which token passes; the **path search** says which path of each tree is kept, under one contract,
[`accept_trees`]: ``(trees, the target's ids [B, 1 + N], rule, ...) -> one AcceptedPath a row`` (the deepest passing
path, then the closest, then the first; its bonus token). Three routes compute it, each chosen by what the call
already has, and they agree on random trees (tests/speculative/test_acceptance.py):

* [`exact_paths_on_host`]: exact matching on trees the host drafted (the previous action, Jacobi guesses), a walk in
  Python after one read of the target's ids;
* [`search_paths`]: any rule, on the device, tensors in and one packed tensor out ([`read_paths`] reads it);
* the same [`search_paths`] inside a compiled round's graph (``speculative.fused``, ``FusedVerification``): the
  verification returns its packed rows and the host reads them once.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch

from ..actions.tokenizer import ActionLayout
from .tree import DraftTree, TreeBatch


class AcceptanceRule:
    """Decides, per drafted token, whether it is acceptable in place of the target's greedy token."""

    #: whether ``__call__`` reads ``top1_probs`` (acceptance then computes the target's probabilities)
    needs_probabilities: bool = False
    #: at most this many relaxed tokens (accepted, not equal to the target's) per action, along the accepted path and
    #: over the call's earlier rounds ([`accept_trees`] applies it); None: no budget
    max_relaxed_per_action: int | None = None
    #: per action dimension d, the last strict dimension after d in an action (-1: none) when a relaxed token must see
    #: its action's strict dimensions confirmed in the same verification ([`StrictTailConfirmed`]); None: no such
    #: condition
    strict_tail: tuple[int, ...] | None = None
    #: whether the rule reads what a token means as an action (its dimension, its chunk step, its bin distance to the
    #: target's); a rule that only compares tokens ([`ExactMatch`]) lets acceptance skip the action layout's work
    reads_actions: bool = True

    def __call__(
        self,
        draft_ids: torch.Tensor,
        target_ids: torch.Tensor,
        action_dims: torch.Tensor | None = None,
        action_steps: torch.Tensor | None = None,
        top1_probs: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """
        Args:
            draft_ids: ``[B, k]`` drafted token ids.
            target_ids: ``[B, k]`` the target's greedy token at the same positions (given the drafted prefix).
            action_dims: ``[B, k]`` action dimension of each drafted token (the number of action tokens generated
                before it in this call, modulo ``action_dim``).
            action_steps: ``[B, k]`` which action of the call (of a chunk) each drafted token belongs to (the same
                count, divided by ``action_dim``).
            top1_probs: ``[B, k]`` the target's probability of its greedy token at each position (only passed to
                rules that declare ``needs_probabilities``).
        Returns:
            ``[B, k]`` bool, True where the drafted token is acceptable on its own.
        """
        raise NotImplementedError

    @property
    def is_lossless(self) -> bool:
        """Whether the rule reproduces plain greedy decoding exactly."""
        return False


class ExactMatch(AcceptanceRule):
    """Accept a drafted token iff it equals the target's greedy token."""

    reads_actions = False  # every accepted token is the target's: bin distance 0, whatever its dimension

    def __call__(self, draft_ids, target_ids, action_dims=None, action_steps=None, top1_probs=None):
        return draft_ids == target_ids

    @property
    def is_lossless(self) -> bool:
        return True

    def __repr__(self) -> str:
        return "ExactMatch()"


def validate_bin_tolerance(bin_tolerance, action_dim: int) -> tuple[int, ...]:
    """Normalises ``bin_tolerance`` (int, or one int per action dimension) to a tuple of ``action_dim`` ints.

    Raises:
        ValueError / TypeError naming the bad value and what would be valid.
    """

    def check(value, where: str) -> int:
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            raise TypeError(
                f"bin_tolerance{where} must be a non-negative int (a number of bins), got {value!r} "
                f"of type {type(value).__name__}"
            )
        if value < 0:
            raise ValueError(f"bin_tolerance{where} must be >= 0 (0 = exact match), got {value}")
        return int(value)

    if isinstance(bin_tolerance, torch.Tensor):
        bin_tolerance = bin_tolerance.tolist()
    if isinstance(bin_tolerance, (Sequence, np.ndarray)) and not isinstance(bin_tolerance, str):
        values = list(bin_tolerance)
        if len(values) != action_dim:
            raise ValueError(
                f"bin_tolerance has {len(values)} entries {values}, but an action has {action_dim} dimensions: give "
                f"one int per dimension, or a single int for all"
            )
        return tuple(check(v, f"[{i}]") for i, v in enumerate(values))
    return (check(bin_tolerance, ""),) * action_dim


def _is_sequence(value) -> bool:
    return isinstance(value, (Sequence, np.ndarray)) and not isinstance(value, str)


def validate_tolerance_table(bin_tolerance, action_dim: int) -> tuple[tuple[int, ...], ...]:
    """Normalises ``bin_tolerance`` to one row of ``action_dim`` ints per action of a chunk: an int (every dimension
    of every action), one int per dimension (every action), or a list of such rows, one per action of the chunk (the
    last row serves the later actions), e.g. ``[[2, 2, 2, 0], [4, 4, 4, 0]]``.

    Raises:
        ValueError / TypeError naming the bad value and what would be valid.
    """
    if isinstance(bin_tolerance, torch.Tensor):
        bin_tolerance = bin_tolerance.tolist()
    if _is_sequence(bin_tolerance) and len(bin_tolerance) and all(_is_sequence(row) for row in bin_tolerance):
        return tuple(validate_bin_tolerance(list(row), action_dim) for row in bin_tolerance)
    if _is_sequence(bin_tolerance) and any(_is_sequence(row) for row in bin_tolerance):
        raise TypeError(
            f"bin_tolerance={list(bin_tolerance)!r} mixes numbers and lists: give an int, one int per action "
            f"dimension, or one such list per action of a chunk"
        )
    if _is_sequence(bin_tolerance) and not len(bin_tolerance):
        raise ValueError("bin_tolerance=[] is empty: give an int, one int per action dimension, or one list per action")
    return (validate_bin_tolerance(bin_tolerance, action_dim),)


def validate_per_dimension(value, action_dim: int, name: str, meaning: str) -> tuple[float, ...]:
    """Normalises a non-negative finite number, or one per action dimension, to a tuple of ``action_dim`` floats.

    Raises:
        ValueError / TypeError naming ``name``, the bad value and what would be valid (``meaning``).
    """
    if isinstance(value, torch.Tensor):
        value = value.tolist()
    values = list(value) if _is_sequence(value) else [value] * action_dim
    if len(values) != action_dim:
        raise ValueError(
            f"{name} has {len(values)} entries {values}, but an action has {action_dim} dimensions: give one number "
            f"per dimension, or a single number for all ({meaning})"
        )
    for i, v in enumerate(values):
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise TypeError(f"{name}[{i}] must be a number >= 0 ({meaning}), got {v!r}")
        if not np.isfinite(v) or v < 0:
            raise ValueError(f"{name}[{i}] must be a finite number >= 0 ({meaning}), got {v!r}")
    return tuple(float(v) for v in values)


MOTION_SCALE_MEANING = "the tolerance in bins per bin of the target's distance from the zero-motion bin; 0 = none"
MAX_DEVIATION_MEANING = "the largest accepted deviation from the target's action, in the policy's units; 0 = exact"


class RelaxedBinMatch(AcceptanceRule):
    """Spec-VLA relaxed acceptance: action tokens within a tolerance of the target's bin are accepted.

    The tolerance of a drafted token at dimension d of action s of the call, when the target's token is at bin t::

        min(max(r[s][d], floor(motion_scale[d] * |t - zero_bin[d]|)), floor(max_deviation[d] / bin_width[d]))

    (each part only when given), computed once per (s, d, t) as an integer table.

    Args:
        action_layout: the action-token range and the tokens per action; its ``units`` (zero-motion bins, bin widths)
            are needed by ``motion_scale`` and ``max_deviation``.
        bin_tolerance: the paper's r; an int, one int per action dimension, or one such list per action of a chunk
            (the last one serving the later actions; [`validate_tolerance_table`]).
        motion_scale: rho, a number or one per dimension: also accept within ``rho`` bins per bin the target's token
            lies from the zero-motion bin (a relative error bound; fine motions stay exact). None: no scaling.
        max_deviation: a number or one per dimension: never accept a token whose action differs from the target's by
            more than this, in the policy's units. None: no bound.
    """

    def __init__(
        self,
        action_layout: ActionLayout,
        bin_tolerance: int | Sequence[int] | Sequence[Sequence[int]],
        motion_scale: float | Sequence[float] | None = None,
        max_deviation: float | Sequence[float] | None = None,
    ):
        self.action_layout = action_layout
        self.action_tokenizer = action_layout.tokenizer
        dims, n_bins = action_layout.action_dim, action_layout.tokenizer.n_bins
        self.tolerance_table = validate_tolerance_table(bin_tolerance, dims)  # [S][D]
        #: one row (every action alike) as a tuple of ints, else the table
        self.bin_tolerance = self.tolerance_table[0] if len(self.tolerance_table) == 1 else self.tolerance_table
        self.motion_scale = (
            None
            if motion_scale is None
            else validate_per_dimension(motion_scale, dims, "motion_scale", MOTION_SCALE_MEANING)
        )
        self.max_deviation = (
            None
            if max_deviation is None
            else validate_per_dimension(max_deviation, dims, "max_deviation", MAX_DEVIATION_MEANING)
        )
        units = action_layout.units
        if (self.motion_scale is not None or self.max_deviation is not None) and units is None:
            raise ValueError(
                "motion_scale and max_deviation read what a bin is in the policy's units, but the action layout has "
                "none: pass action_layout=ActionLayout(tokenizer, action_dim, ActionUnits.from_normalizer(tokenizer, "
                "normalizer, action_dim)) (a VLAPolicy's and an OpenVLA model's action_layout have them)"
            )
        table = np.array(self.tolerance_table, dtype=np.int64)[:, :, None].repeat(n_bins, axis=2)  # [S, D, bins]
        if self.motion_scale is not None:
            offset = np.abs(np.arange(n_bins)[None, :] - np.array(units.zero_bins)[:, None])  # [D, bins]
            scaled = np.floor(np.array(self.motion_scale)[:, None] * offset + 1e-9).astype(np.int64)  # [D, bins]
            table = np.maximum(table, scaled[None])
        if self.max_deviation is not None:
            cap = np.floor(np.array(self.max_deviation) / np.array(units.bin_widths) + 1e-9).astype(np.int64)  # [D]
            table = np.minimum(table, cap[None, :, None])
        #: ``[S, D, n_bins]`` the tolerance in bins of a token at (chunk step, dimension, the target's bin)
        self.tolerance_by_bin = torch.from_numpy(np.minimum(table, n_bins - 1))
        self._lossless = bool((table == 0).all())
        self._on_device: dict = {}

    def tolerances(self, target_ids: torch.Tensor, action_dims=None, action_steps=None) -> torch.Tensor:
        """``[B, k]`` the tolerance in bins of each position, given the target's token there (0 where it is not an
        action token)."""
        device = target_ids.device
        table = self._on_device.get(device)
        if table is None:
            table = self._on_device[device] = self.tolerance_by_bin.to(device)
        if action_dims is None:
            action_dims = torch.zeros_like(target_ids)
        steps = torch.zeros_like(target_ids) if action_steps is None else action_steps.clamp(max=table.shape[0] - 1)
        bins = self.action_tokenizer.token_to_bin(target_ids).clamp(0, table.shape[2] - 1)
        tolerance = table[steps, action_dims, bins]  # [B, k]
        return torch.where(self.action_tokenizer.is_action_token(target_ids), tolerance, 0)

    def __call__(self, draft_ids, target_ids, action_dims=None, action_steps=None, top1_probs=None):
        exact = draft_ids == target_ids
        both_actions = self.action_tokenizer.is_action_token(draft_ids) & self.action_tokenizer.is_action_token(
            target_ids
        )
        tolerance = self.tolerances(target_ids, action_dims, action_steps)
        within = self.action_tokenizer.bin_distance(draft_ids, target_ids) <= tolerance
        return exact | (both_actions & within)

    @property
    def strict_dims(self) -> tuple[bool, ...]:
        """Per action dimension, whether every token there must match exactly (tolerance 0 for every chunk step and
        every target bin)."""
        return tuple(bool(x) for x in (self.tolerance_by_bin.amax(dim=(0, 2)) == 0).tolist())

    @property
    def is_lossless(self) -> bool:
        return self._lossless

    def __repr__(self) -> str:
        rows = [row[0] if len(set(row)) == 1 else list(row) for row in self.tolerance_table]
        tol = rows[0] if len(rows) == 1 else rows
        extra = "" if self.motion_scale is None else f", motion_scale={list(self.motion_scale)}"
        extra += "" if self.max_deviation is None else f", max_deviation={list(self.max_deviation)}"
        return (
            f"RelaxedBinMatch(bin_tolerance={tol}{extra}, {self.action_tokenizer}, "
            f"action_dim={self.action_layout.action_dim})"
        )


def check_confidence_gate(confidence_gate) -> float | None:
    """Validates a confidence gate: None (no gate) or a probability in (0, 1].

    Raises:
        ValueError / TypeError naming the value and what would be valid.
    """
    if confidence_gate is None:
        return None
    if isinstance(confidence_gate, bool) or not isinstance(confidence_gate, (int, float, np.floating, np.integer)):
        raise TypeError(f"confidence_gate must be a probability in (0, 1] or None, got {confidence_gate!r}")
    if not 0 < confidence_gate <= 1:
        raise ValueError(
            f"confidence_gate={confidence_gate!r}: a relaxed token counts only where the target's greedy token has a "
            f"probability below the gate, so it must be in (0, 1] (1 = no gate; e.g. 0.5)"
        )
    return float(confidence_gate)


def check_relaxed_budget(max_relaxed_per_action) -> int | None:
    """Validates a relaxed-token budget: None (no budget) or an int >= 0.

    Raises:
        ValueError / TypeError naming the value and what would be valid.
    """
    if max_relaxed_per_action is None:
        return None
    if isinstance(max_relaxed_per_action, bool) or not isinstance(max_relaxed_per_action, (int, np.integer)):
        raise TypeError(f"max_relaxed_per_action must be an int >= 0 or None, got {max_relaxed_per_action!r}")
    if max_relaxed_per_action < 0:
        raise ValueError(
            f"max_relaxed_per_action={max_relaxed_per_action}: the relaxed tokens allowed per action must be >= 0 "
            f"(0 = exact acceptance, None = no budget)"
        )
    return int(max_relaxed_per_action)


class ConfidenceGate(AcceptanceRule):
    """``rule``'s relaxed acceptances, kept only where the target is unsure: its greedy token's probability is below
    ``threshold`` (a draft equal to the target's token always passes).

    Guarantee: wherever the target's top-1 probability is >= ``threshold``, the emitted token is the target's own.
    """

    needs_probabilities = True

    def __init__(self, rule: AcceptanceRule, threshold: float):
        self.rule, self.threshold = rule, check_confidence_gate(threshold)
        self.max_relaxed_per_action, self.strict_tail = rule.max_relaxed_per_action, rule.strict_tail

    def __call__(self, draft_ids, target_ids, action_dims=None, action_steps=None, top1_probs=None):
        if top1_probs is None:
            raise ValueError("ConfidenceGate needs the target's top-1 probabilities (top1_probs)")
        relaxed = self.rule(draft_ids, target_ids, action_dims, action_steps, top1_probs)
        return (draft_ids == target_ids) | (relaxed & (top1_probs < self.threshold))

    @property
    def is_lossless(self) -> bool:
        return self.rule.is_lossless

    def __repr__(self) -> str:
        return f"ConfidenceGate({self.rule!r}, threshold={self.threshold})"


class RelaxedBudget(AcceptanceRule):
    """``rule`` with at most ``max_relaxed_per_action`` relaxed tokens per action (counted along each path and over the
    call's earlier rounds by [`accept_trees`]); past it, acceptance is exact.

    Guarantee: every action the call emits differs from the target's greedy tokens (given its prefix) in at most
    ``max_relaxed_per_action`` tokens, each within ``rule``'s tolerance.
    """

    def __init__(self, rule: AcceptanceRule, max_relaxed_per_action: int):
        self.rule = rule
        self.max_relaxed_per_action = check_relaxed_budget(max_relaxed_per_action)
        self.needs_probabilities, self.strict_tail = rule.needs_probabilities, rule.strict_tail

    def __call__(self, draft_ids, target_ids, action_dims=None, action_steps=None, top1_probs=None):
        return self.rule(draft_ids, target_ids, action_dims, action_steps, top1_probs)

    @property
    def is_lossless(self) -> bool:
        return self.rule.is_lossless or self.max_relaxed_per_action == 0

    def __repr__(self) -> str:
        return f"RelaxedBudget({self.rule!r}, max_relaxed_per_action={self.max_relaxed_per_action})"


def strict_tails(strict_dims: Sequence[bool]) -> tuple[int, ...]:
    """Per action dimension d, the last strict dimension after d (-1: none): ``(False, False, False, True)`` (a
    strict gripper last) -> ``(3, 3, 3, -1)``."""
    return tuple(
        max((e for e in range(d + 1, len(strict_dims)) if strict_dims[e]), default=-1) for d in range(len(strict_dims))
    )


class StrictTailConfirmed(AcceptanceRule):
    """``rule``, where a relaxed token (accepted, not the target's) is kept only when every strict dimension after it in
    its action (e.g. the gripper after x y z) was drafted and matched by the target in the same verification
    ([`accept_trees`] applies it); otherwise the accepted path ends before the relaxed token and the token emitted there
    is the target's own.

    Guarantee: a strict dimension's token emitted after a relaxed token of its action is the one drafted for it before
    verification (the previous action's, for a prior): a strict dimension changes value only when decoded from an
    exact prefix of its action.

    Args:
        rule: a rule built on [`RelaxedBinMatch`] (its ``strict_dims`` say which dimensions are strict).
    """

    def __init__(self, rule: AcceptanceRule):
        inner = rule
        while not isinstance(inner, RelaxedBinMatch):
            inner = getattr(inner, "rule", None)
            if inner is None:
                raise TypeError(f"StrictTailConfirmed needs a rule built on RelaxedBinMatch, got {rule!r}")
        self.rule = rule
        self.strict_tail = strict_tails(inner.strict_dims)
        self.needs_probabilities = rule.needs_probabilities
        self.max_relaxed_per_action = rule.max_relaxed_per_action

    def __call__(self, draft_ids, target_ids, action_dims=None, action_steps=None, top1_probs=None):
        return self.rule(draft_ids, target_ids, action_dims, action_steps, top1_probs)

    @property
    def is_lossless(self) -> bool:
        return self.rule.is_lossless

    def __repr__(self) -> str:
        return f"StrictTailConfirmed({self.rule!r})"


def check_bin_tolerance_range(tolerances: Sequence[int], n_bins: int, given: str) -> None:
    """Refuses an r wider than the action range, naming ``given`` (what the user wrote: ``bin_tolerance=300``,
    ``--bin-tolerance 300``, ``methods ['prior:r=300']``): the one wording the engine and the CLI share.

    Raises:
        ValueError: some tolerance exceeds ``n_bins - 1``.
    """
    widest = n_bins - 1
    if max(tolerances) > widest:
        raise ValueError(
            f"{given}: r is wider than the action range (with {n_bins} bins two action tokens are at most {widest} "
            f"bins apart; r={widest} already accepts any action token); use r in 0..{widest}"
        )


def make_acceptance_rule(
    bin_tolerance: int | Sequence[int] | Sequence[Sequence[int]],
    action_layout: ActionLayout | None,
    confidence_gate: float | None = None,
    max_relaxed_per_action: int | None = None,
    motion_scale: float | Sequence[float] | None = None,
    max_deviation: float | Sequence[float] | None = None,
    confirm_strict_tail: bool = False,
) -> AcceptanceRule:
    """[`ExactMatch`] when nothing is relaxed (every tolerance 0 and no motion scale, whatever the gate, budget and
    bound), else [`RelaxedBinMatch`] (which needs the action layout; its ``units`` for ``motion_scale`` and
    ``max_deviation``), inside a [`ConfidenceGate`] when ``confidence_gate`` is given, a [`RelaxedBudget`] when
    ``max_relaxed_per_action`` is and a [`StrictTailConfirmed`] when ``confirm_strict_tail``.

    Raises:
        ValueError / TypeError naming the bad value and what would be valid (before anything runs).
    """
    confidence_gate = check_confidence_gate(confidence_gate)
    max_relaxed_per_action = check_relaxed_budget(max_relaxed_per_action)
    if not isinstance(confirm_strict_tail, (bool, np.bool_)):
        raise TypeError(f"confirm_strict_tail must be True or False, got {confirm_strict_tail!r}")
    scaling = motion_scale is not None and any(
        v != 0
        for v in (
            motion_scale.tolist()
            if isinstance(motion_scale, torch.Tensor)
            else motion_scale
            if _is_sequence(motion_scale)
            else [motion_scale]
        )
    )
    if action_layout is None:
        values = bin_tolerance.tolist() if isinstance(bin_tolerance, torch.Tensor) else bin_tolerance
        rows = values if _is_sequence(values) and len(values) and all(_is_sequence(r) for r in values) else [values]
        lossless = all(
            t == 0 for row in rows for t in validate_bin_tolerance(row, len(row) if _is_sequence(row) else 1)
        )
        if lossless and not scaling:
            return ExactMatch()
        raise ValueError(
            f"bin_tolerance={bin_tolerance!r}, motion_scale={motion_scale!r} relax acceptance of action tokens, but "
            "nothing says which tokens are actions: pass action_layout=ActionLayout(ActionTokenizer(vocab_end, "
            "n_bins), action_dim) to generate, or use a DraftHead (its config records the layout)"
        )
    table = validate_tolerance_table(bin_tolerance, action_layout.action_dim)
    given = f"bin_tolerance={bin_tolerance!r}"
    check_bin_tolerance_range([t for row in table for t in row], action_layout.tokenizer.n_bins, given)
    rule = RelaxedBinMatch(action_layout, table, motion_scale, max_deviation)  # validates the scale and the bound
    if rule.is_lossless or max_relaxed_per_action == 0:
        return ExactMatch()
    if confidence_gate is not None and confidence_gate < 1:
        rule = ConfidenceGate(rule, confidence_gate)
    if max_relaxed_per_action is not None:
        rule = RelaxedBudget(rule, max_relaxed_per_action)
    if confirm_strict_tail:
        rule = StrictTailConfirmed(rule)
    return rule


# ----------------------------------------------------------------------------- choosing the path of a tree
class AcceptedPath(NamedTuple):
    """The outcome of verifying a draft tree.

    Attributes:
        nodes: accepted node indices, root's child first (empty when no drafted token passed).
        bonus_id: the target's greedy token after the path (always emitted after the path's tokens).
        distances: bin distance of each accepted drafted token to the target's greedy token at its place
            (0 for an exact match or a non-action token).
        target_ids: the target's greedy token after the root and after each of the tree's nodes (``1 + n`` of the
            row's own tree), on the host; None when not read.
    """

    nodes: list[int]
    bonus_id: int
    distances: list[int]
    target_ids: list[int] | None = None


def accept_tree(
    tree: DraftTree,
    target_ids: torch.Tensor,
    rule: AcceptanceRule,
    action_layout: ActionLayout | None,
    num_prior_action_tokens: int = 0,
    top1_probs: torch.Tensor | None = None,
    relaxed_in_action: int = 0,
) -> AcceptedPath:
    """The longest root-to-leaf path of ``tree`` whose every drafted token passes ``rule`` ([`accept_trees`] for
    one tree).

    Args:
        tree: the verified draft tree (N nodes).
        target_ids: ``[1 + N]`` the target's greedy token after the root (index 0) and after each node (1 + i),
            each given that node's own path as prefix (the tree mask guarantees it).
        num_prior_action_tokens: action tokens generated in this call before the root (for action dimensions).
        top1_probs: ``[1 + N]`` the target's probability of each of those tokens (rules that need it).
        relaxed_in_action: relaxed tokens already emitted in the action the root's next token belongs to.
    """
    probs = None if top1_probs is None else top1_probs[None]
    return accept_trees(
        TreeBatch([tree]), target_ids[None], rule, action_layout, [num_prior_action_tokens], probs, [relaxed_in_action]
    )[0]


def accept_trees(
    trees: TreeBatch,
    target_ids: torch.Tensor,
    rule: AcceptanceRule,
    action_layout: ActionLayout | None,
    num_prior_action_tokens: Sequence[int],
    top1_probs: torch.Tensor | None = None,
    relaxed_in_action: Sequence[int] | None = None,
) -> list[AcceptedPath]:
    """Per row, the longest root-to-leaf path of its tree whose every drafted token passes ``rule`` (all rows at
    once), within the rule's relaxed-token budget per action.

    Args:
        trees: the verified trees, padded to N nodes.
        target_ids: ``[B, 1 + N]`` each row's greedy token after its root (column 0) and after each node (1 + i),
            each given that node's own path as prefix (the tree mask guarantees it).
        num_prior_action_tokens: per row, action tokens generated in this call before the root (for action
            dimensions and the action of the chunk each token belongs to).
        top1_probs: ``[B, 1 + N]`` the target's probability of each of those greedy tokens; needed by rules that
            declare ``needs_probabilities``.
        relaxed_in_action: per row, relaxed tokens (accepted, not the target's) already emitted in the action the
            root's next token belongs to (earlier rounds of the call); counted against ``rule.max_relaxed_per_action``.
    Returns:
        one [`AcceptedPath`] per row; ties between equally long passing paths go to the smallest total bin
        distance, then to the lowest node index.
    """
    tokens = trees.token_ids  # [B, N]
    batch_size, num_nodes = tokens.shape
    if num_nodes == 0:
        return [AcceptedPath([], bonus, [], [bonus]) for bonus in target_ids[:, 0].tolist()]
    if rule.needs_probabilities and top1_probs is None:
        raise ValueError(f"{rule!r} needs the target's top-1 probabilities: pass top1_probs")
    if type(rule) is ExactMatch and all(tree.token_list is not None and tree.knows_structure() for tree in trees.trees):
        return exact_paths_on_host(trees, target_ids)
    prior = earlier = None  # what only a rule reading actions needs
    if action_layout is not None and rule.reads_actions:
        prior = torch.tensor(num_prior_action_tokens, device=tokens.device)[:, None]  # [B, 1]
        earlier = torch.tensor(relaxed_in_action or [0] * batch_size, device=tokens.device)[:, None]  # [B, 1]
    # one read from the device per verification: the paths, distances, bonus tokens, drafted and target tokens, the
    # parents (a tree drafted on the device is then known on the host too)
    packed = search_paths(
        tokens,
        trees.ancestor_or_self,
        trees.parents,
        trees.depths,
        trees.is_real,
        target_ids,
        prior,
        earlier,
        top1_probs,
        rule,
        action_layout,
    ).tolist()
    return read_paths(packed, trees)


def exact_paths_on_host(trees: TreeBatch, target_ids: torch.Tensor) -> list[AcceptedPath]:
    """[`accept_trees`] under [`ExactMatch`] for trees whose tokens and parents are on the host (drafted there: the
    previous action, Jacobi guesses): the paths [`search_paths`] finds (the deepest path whose every token is the
    target's, the first of equal depth), from one read of ``target_ids`` ``[B, 1 + N]`` and a walk of each tree in
    Python, where the device search is a dozen small kernels."""
    paths = []
    for tree, targets in zip(trees.trees, target_ids.tolist()):
        tokens, parents = tree.token_list, tree.host_parents
        depth = [0] * len(tokens)  # where the node's path passes: 1 + its depth; else 0
        best = -1
        for node, (token, parent) in enumerate(zip(tokens, parents)):  # a parent comes before its children
            if token == targets[parent + 1] and (parent < 0 or depth[parent]):
                depth[node] = 1 if parent < 0 else depth[parent] + 1
                if best < 0 or depth[node] > depth[best]:
                    best = node
        nodes, at = [], best
        while at >= 0:
            nodes.append(at)
            at = parents[at]
        nodes.reverse()  # index order (a parent's index is below its children's)
        bonus = targets[best + 1] if best >= 0 else targets[0]
        paths.append(AcceptedPath(nodes, bonus, [0] * len(nodes), targets[: 1 + len(tokens)]))
    return paths


def read_paths(packed: list[list[int]], trees: TreeBatch) -> list[AcceptedPath]:
    """The rows' [`AcceptedPath`]s from [`search_paths`]'s packed rows (read from the device in one go, by
    [`accept_trees`] or from a compiled round's graph); a tree drafted on the device learns its tokens and parents
    from them.

    Args:
        packed: per row, ``5 N + 2`` ints (N = ``trees.num_nodes``, see [`search_paths`]).
    """
    num_nodes = trees.num_nodes
    paths = []
    for row, tree in zip(packed, trees.trees):
        row_on_path, row_distances, bonus = row[:num_nodes], row[num_nodes : 2 * num_nodes], row[2 * num_nodes]
        if tree.token_list is None:
            tree.token_list = row[2 * num_nodes + 1 : 2 * num_nodes + 1 + tree.num_nodes]
        if tree.host_parents is None:
            tree.host_parents = row[4 * num_nodes + 2 : 4 * num_nodes + 2 + tree.num_nodes]
        nodes = [i for i, kept in enumerate(row_on_path) if kept]  # index order is depth order
        row_targets = row[3 * num_nodes + 1 : 3 * num_nodes + 2 + tree.num_nodes]
        paths.append(AcceptedPath(nodes, bonus, [row_distances[i] for i in nodes], row_targets))
    return paths


def search_paths(
    tokens: torch.Tensor,
    ancestor_or_self: torch.Tensor,
    parents: torch.Tensor,
    depths: torch.Tensor,
    is_real: torch.Tensor,
    target_ids: torch.Tensor,
    prior: torch.Tensor | None,
    earlier: torch.Tensor | None,
    top1_probs: torch.Tensor | None,
    rule: AcceptanceRule,
    action_layout: ActionLayout | None,
) -> torch.Tensor:
    """[`accept_trees`]'s work on the device, tensors in and one tensor out: no read of the device and no host value
    but the rule's and the layout's settings, so that it traces into one graph (``torch.compile(search_paths,
    dynamic=True, fullgraph=True)`` finds the same paths, tests/speculative/test_acceptance.py), the step a fused
    compiled round would hold after the target's forward.

    Args:
        tokens / parents / depths / is_real: ``[B, N]`` the trees (a [`TreeBatch`]'s); ancestor_or_self ``[B, N, N]``.
        target_ids: ``[B, 1 + N]``; prior / earlier: ``[B, 1]`` the action tokens before each root, and the relaxed
            tokens already emitted in the root's action (None where the rule reads no action, or no layout);
            top1_probs: ``[B, 1 + N]`` or None.
    Returns:
        ``[B, 4 N + 2 + N]`` packed per row: on-path flags ``[N]``, bin distances ``[N]``, the bonus token, the drafted
        tokens ``[N]``, the target's tokens ``[1 + N]``, the parents ``[N]``.
    """
    batch_size, num_nodes = tokens.shape
    parent_targets = target_ids.gather(1, parents + 1)  # [B, N] greedy token at each node's place
    if action_layout is not None and rule.reads_actions:
        tokenizer = action_layout.tokenizer
        is_action = tokenizer.is_action_token(tokens)
        strict_ancestors = ancestor_or_self & ~torch.eye(num_nodes, dtype=torch.bool, device=tokens.device)
        # (integer products as masked sums: CUDA has no integer matmul)
        before = prior + (strict_ancestors.long() * is_action.long()[:, None, :]).sum(-1)  # [B, N]
        action_dims = before % action_layout.action_dim
        action_steps = before // action_layout.action_dim  # [B, N] which action of the call (chunk step)
        both_actions = is_action & tokenizer.is_action_token(parent_targets)
        distances = torch.where(both_actions, tokenizer.bin_distance(tokens, parent_targets), 0)
    elif rule.reads_actions:  # no layout: every token at dimension 0 of the call's first action
        action_dims = action_steps = torch.zeros_like(tokens)
        distances = torch.zeros_like(tokens)
    else:  # a rule that only compares tokens: every accepted token is the target's
        action_dims = action_steps = None
        distances = torch.zeros_like(tokens)
    parent_probs = None if top1_probs is None else top1_probs.gather(1, parents + 1)  # [B, N]
    passes = rule(tokens, parent_targets, action_dims, action_steps, parent_probs) & is_real  # [B, N] alone
    budget = rule.max_relaxed_per_action
    if budget is not None and action_layout is not None and rule.reads_actions:
        # relaxed tokens on each node's path within its own action (and, for the action the root continues, those
        # emitted by earlier rounds): a node over the budget fails, and with it every path through it
        relaxed = passes & (tokens != parent_targets)  # [B, N]
        same_action = action_steps[:, :, None] == action_steps[:, None, :]  # [B, N, N]
        count = (ancestor_or_self & same_action & relaxed[:, None, :]).long().sum(-1)  # [B, N]
        first_step = prior // action_layout.action_dim  # [B, 1] the action the root's next token belongs to
        count = count + torch.where(action_steps == first_step, earlier, 0)
        passes = passes & (count <= budget)
    path_passes = ~(ancestor_or_self & ~passes[:, None, :]).any(dim=-1)  # [B, N] the node and all its ancestors
    if rule.strict_tail is not None and action_layout is not None and rule.reads_actions:
        # a relaxed node's path may end only at or past its action's last strict dimension after it (confirmed there)
        relaxed = passes & (tokens != parent_targets) & is_action  # [B, N]
        last_strict = torch.tensor(rule.strict_tail, device=tokens.device)[action_dims]  # [B, N] (-1: none)
        must_reach = torch.where(
            relaxed & (last_strict >= 0), action_steps * action_layout.action_dim + last_strict, -1
        )
        reach = torch.where(ancestor_or_self, must_reach[:, None, :], -1).amax(dim=-1)  # [B, N] over the path
        path_passes = path_passes & (before >= reach)  # ``before``: the node's own index among the call's actions
    # deepest, then closest, then first: argmax returns the first of equal maxima. Any bound above every path's total
    # distance orders the same; this one is known on the host (no read of the device's maximum)
    if action_layout is not None and rule.reads_actions:
        total_distance = (ancestor_or_self.long() * distances[:, None, :]).sum(-1)  # [B, N] summed along the path
        widest = (action_layout.tokenizer.n_bins - 1) * num_nodes
        rank = (depths + 1) * (widest + 1) - total_distance  # >= 1 for every node
    else:  # no distances: the deepest, then the first
        rank = depths + 1
    best = torch.where(path_passes, rank, 0).argmax(dim=-1)  # [B]
    accepted = path_passes.any(dim=-1)  # [B]
    bonus_ids = torch.where(accepted, target_ids.gather(1, best[:, None] + 1)[:, 0], target_ids[:, 0])
    on_path = ancestor_or_self[torch.arange(batch_size, device=tokens.device), best] & accepted[:, None]  # [B, N]
    return torch.cat([on_path.long(), distances, bonus_ids[:, None], tokens, target_ids, parents], dim=1)


# ----------------------------------------------------------------------------- sampling
def sample_trees(
    trees: TreeBatch, scores: torch.Tensor, generator: torch.Generator | None = None
) -> list[AcceptedPath]:
    """Lossless speculative sampling of each row's tree: the emitted tokens are distributed exactly as sampling from
    the target token by token (``softmax`` of its processed scores: temperature, top-k, top-p, ... as ``generate``
    applies them).

    Every drafted token is a point mass (a drafter's choice, whatever distribution it came from): at a node, its
    children are tried in order, child ``c`` accepted with probability ``p(c)`` under the current distribution ``p``;
    a rejected child's token is removed from ``p`` (renormalised: recursive rejection sampling, SpecInfer / EAGLE's
    for trees, with one-hot drafts) and the next child tried. An accepted child continues the path from its own
    distribution; where no child is accepted (or at a leaf) the bonus token is sampled from what is left.

    Args:
        trees: the verified trees, padded to N nodes.
        scores: ``[B, 1 + N, V]`` the target's processed scores after each row's root (column 0) and each node
            (1 + i), each given that node's own path as prefix.
        generator: the random source (a CPU generator; default: torch's global one, seeded by ``torch.manual_seed``).
    Returns:
        one [`AcceptedPath`] per row (distances 0: sampling never relaxes).
    """
    probs = scores.float().softmax(dim=-1).cpu()  # [B, 1 + N, V] one copy to the host per round
    paths = []
    for b, tree in enumerate(trees.trees):
        tokens = tree.host_tokens
        children: dict[int, list[int]] = {}
        for node, parent in enumerate(tree.parent_list):
            children.setdefault(parent, []).append(node)
        nodes, at = [], -1  # at: the node whose next token is decided (-1: the root)
        while True:
            p = probs[b, at + 1].clone()
            chosen = None
            for child in children.get(at, []):
                token = tokens[child]
                if float(torch.rand((), generator=generator)) < float(p[token]):
                    chosen = child
                    break
                p[token] = 0.0
                total = float(p.sum())
                if total <= 0.0:  # every token with mass was drafted and rejected: cannot happen (p(c) = 1 accepts)
                    break
                p /= total
            if chosen is None:
                bonus = int(torch.multinomial(p, 1, generator=generator))
                break
            nodes.append(chosen)
            at = chosen
        paths.append(AcceptedPath(nodes, bonus, [0] * len(nodes), None))
    return paths
