"""Acceptance rules: which drafted tokens the target's verification accepts.

Greedy speculative decoding accepts the longest prefix of the draft whose every token passes the rule; the
token after that prefix (the "bonus" token) is always the target's own greedy choice.

* [`ExactMatch`]: the drafted token equals the target's greedy token. Output is token-identical to greedy.
* [`RelaxedBinMatch`] (Spec-VLA, arXiv 2507.22424, section 3.3 "relaxed acceptance"): a drafted *action*
  token is also accepted when its bin is within ``bin_tolerance`` (the paper's r) bins of the target's greedy
  token, because neighbouring bins are neighbouring actions. Non-action tokens still need an exact match.
  The accepted token is the *drafted* one. Deviation from the paper: the tolerance may differ per action
  dimension (e.g. 0 for a binary gripper), and both tokens must be action tokens (the official code compares
  raw id differences at every position, so it could accept a text token near the action range).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from .action_tokenizer import ActionTokenizer


def accepted_prefix_length(accepted: torch.Tensor) -> torch.Tensor:
    """Length of the leading run of True per row: ``[B, k]`` bool -> ``[B]`` int64."""
    return accepted.long().cumprod(dim=-1).sum(dim=-1)


def action_dimensions(
    draft_ids: torch.Tensor,
    action_tokenizer: ActionTokenizer,
    num_prior_action_tokens: torch.Tensor | int,
    action_dim: int,
) -> torch.Tensor:
    """Action dimension of each drafted token, assuming all drafted tokens before it are accepted.

    The dimension of an action token is the number of action tokens generated before it, modulo ``action_dim``.

    Args:
        draft_ids: ``[B, k]`` drafted ids.
        num_prior_action_tokens: ``[B]`` (or int) action tokens already generated in this call.
    Returns:
        ``[B, k]`` int64 dimension in ``0..action_dim-1``.
    """
    is_action = action_tokenizer.is_action_token(draft_ids).long()
    before = torch.cumsum(is_action, dim=-1) - is_action  # action tokens among draft_ids[:, :j]
    prior = torch.as_tensor(num_prior_action_tokens, device=draft_ids.device).reshape(-1, 1)
    return (prior + before) % action_dim


class AcceptanceRule:
    """Decides, per drafted token, whether it is acceptable in place of the target's greedy token."""

    def __call__(
        self, draft_ids: torch.Tensor, target_ids: torch.Tensor, action_dims: torch.Tensor | None = None
    ) -> torch.Tensor:
        """
        Args:
            draft_ids: ``[B, k]`` drafted token ids.
            target_ids: ``[B, k]`` the target's greedy token at the same positions (given the drafted prefix).
            action_dims: ``[B, k]`` action dimension of each drafted token (see [`action_dimensions`]).
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

    def __call__(self, draft_ids, target_ids, action_dims=None):
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


class RelaxedBinMatch(AcceptanceRule):
    """Spec-VLA relaxed acceptance: action tokens within ``bin_tolerance`` bins of the target's are accepted.

    Args:
        action_tokenizer: the action-token layout.
        bin_tolerance: the paper's r; an int, or one int per action dimension.
        action_dim: action tokens per action.
    """

    def __init__(self, action_tokenizer: ActionTokenizer, bin_tolerance: int | Sequence[int], action_dim: int):
        self.action_tokenizer = action_tokenizer
        self.action_dim = action_dim
        self.bin_tolerance = validate_bin_tolerance(bin_tolerance, action_dim)

    def __call__(self, draft_ids, target_ids, action_dims=None):
        exact = draft_ids == target_ids
        both_actions = self.action_tokenizer.is_action_token(draft_ids) & self.action_tokenizer.is_action_token(
            target_ids
        )
        if action_dims is None:
            action_dims = torch.zeros_like(draft_ids)
        tolerance = torch.tensor(self.bin_tolerance, device=draft_ids.device)[action_dims]  # [B, k]
        within = self.action_tokenizer.bin_distance(draft_ids, target_ids) <= tolerance
        return exact | (both_actions & within)

    @property
    def is_lossless(self) -> bool:
        return all(t == 0 for t in self.bin_tolerance)

    def __repr__(self) -> str:
        tol = self.bin_tolerance[0] if len(set(self.bin_tolerance)) == 1 else list(self.bin_tolerance)
        return f"RelaxedBinMatch(bin_tolerance={tol}, {self.action_tokenizer})"


def make_acceptance_rule(
    bin_tolerance: int | Sequence[int], action_tokenizer: ActionTokenizer, action_dim: int
) -> AcceptanceRule:
    """[`ExactMatch`] when every tolerance is 0, else [`RelaxedBinMatch`]."""
    tolerance = validate_bin_tolerance(bin_tolerance, action_dim)
    if all(t == 0 for t in tolerance):
        return ExactMatch()
    return RelaxedBinMatch(action_tokenizer, tolerance, action_dim)
