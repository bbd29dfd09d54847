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
  dimension (e.g. 0 for a binary gripper), and both tokens must be action tokens (the official code compares
  raw id differences at every position, so it could accept a text token near the action range).
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

    def __call__(
        self, draft_ids: torch.Tensor, target_ids: torch.Tensor, action_dims: torch.Tensor | None = None
    ) -> torch.Tensor:
        """
        Args:
            draft_ids: ``[B, k]`` drafted token ids.
            target_ids: ``[B, k]`` the target's greedy token at the same positions (given the drafted prefix).
            action_dims: ``[B, k]`` action dimension of each drafted token (the number of action tokens generated
                before it in this call, modulo ``action_dim``).
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
        action_layout: the action-token range and the tokens per action.
        bin_tolerance: the paper's r; an int, or one int per action dimension.
    """

    def __init__(self, action_layout: ActionLayout, bin_tolerance: int | Sequence[int]):
        self.action_layout = action_layout
        self.action_tokenizer = action_layout.tokenizer
        self.bin_tolerance = validate_bin_tolerance(bin_tolerance, action_layout.action_dim)

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
        return (
            f"RelaxedBinMatch(bin_tolerance={tol}, {self.action_tokenizer}, action_dim={self.action_layout.action_dim})"
        )


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


def make_acceptance_rule(bin_tolerance: int | Sequence[int], action_layout: ActionLayout | None) -> AcceptanceRule:
    """[`ExactMatch`] when every tolerance is 0, else [`RelaxedBinMatch`] (which needs the action layout).

    Raises:
        ValueError: a relaxed tolerance without an action layout, naming where one can come from.
    """
    if action_layout is None:
        values = bin_tolerance.tolist() if isinstance(bin_tolerance, torch.Tensor) else bin_tolerance
        count = len(values) if isinstance(values, (Sequence, np.ndarray)) and not isinstance(values, str) else 1
        if all(t == 0 for t in validate_bin_tolerance(values, count)):
            return ExactMatch()
        raise ValueError(
            f"bin_tolerance={bin_tolerance!r} relaxes acceptance of action tokens, but nothing says which tokens are "
            "actions: pass action_layout=ActionLayout(ActionTokenizer(vocab_end, n_bins), action_dim) to generate, "
            "or use a DraftHead (its config records the layout)"
        )
    tolerance = validate_bin_tolerance(bin_tolerance, action_layout.action_dim)
    check_bin_tolerance_range(tolerance, action_layout.tokenizer.n_bins, f"bin_tolerance={bin_tolerance!r}")
    if all(t == 0 for t in tolerance):
        return ExactMatch()
    return RelaxedBinMatch(action_layout, tolerance)


# ----------------------------------------------------------------------------- choosing the path of a tree
class AcceptedPath(NamedTuple):
    """The outcome of verifying a draft tree.

    Attributes:
        nodes: accepted node indices, root's child first (empty when no drafted token passed).
        bonus_id: the target's greedy token after the path (always emitted after the path's tokens).
        distances: bin distance of each accepted drafted token to the target's greedy token at its place
            (0 for an exact match or a non-action token).
    """

    nodes: list[int]
    bonus_id: int
    distances: list[int]


def accept_tree(
    tree: DraftTree,
    target_ids: torch.Tensor,
    rule: AcceptanceRule,
    action_layout: ActionLayout | None,
    num_prior_action_tokens: int = 0,
) -> AcceptedPath:
    """The longest root-to-leaf path of ``tree`` whose every drafted token passes ``rule`` ([`accept_trees`] for
    one tree).

    Args:
        tree: the verified draft tree (N nodes).
        target_ids: ``[1 + N]`` the target's greedy token after the root (index 0) and after each node (1 + i),
            each given that node's own path as prefix (the tree mask guarantees it).
        num_prior_action_tokens: action tokens generated in this call before the root (for action dimensions).
    """
    return accept_trees(TreeBatch([tree]), target_ids[None], rule, action_layout, [num_prior_action_tokens])[0]


def accept_trees(
    trees: TreeBatch,
    target_ids: torch.Tensor,
    rule: AcceptanceRule,
    action_layout: ActionLayout | None,
    num_prior_action_tokens: Sequence[int],
) -> list[AcceptedPath]:
    """Per row, the longest root-to-leaf path of its tree whose every drafted token passes ``rule`` (all rows at
    once).

    Args:
        trees: the verified trees, padded to N nodes.
        target_ids: ``[B, 1 + N]`` each row's greedy token after its root (column 0) and after each node (1 + i),
            each given that node's own path as prefix (the tree mask guarantees it).
        num_prior_action_tokens: per row, action tokens generated in this call before the root (for action
            dimensions).
    Returns:
        one [`AcceptedPath`] per row; ties between equally long passing paths go to the smallest total bin
        distance, then to the lowest node index.
    """
    tokens, ancestor_or_self = trees.token_ids, trees.ancestor_or_self  # [B, N], [B, N, N]
    batch_size, num_nodes = tokens.shape
    if num_nodes == 0:
        return [AcceptedPath([], bonus, []) for bonus in target_ids[:, 0].tolist()]
    parent_targets = target_ids.gather(1, trees.parents + 1)  # [B, N] greedy token at each node's place
    if action_layout is not None:
        tokenizer = action_layout.tokenizer
        is_action = tokenizer.is_action_token(tokens)
        strict_ancestors = ancestor_or_self & ~torch.eye(num_nodes, dtype=torch.bool, device=tokens.device)
        # (integer products as masked sums: CUDA has no integer matmul)
        before = torch.tensor(num_prior_action_tokens, device=tokens.device)[:, None] + (
            strict_ancestors.long() * is_action.long()[:, None, :]
        ).sum(-1)  # [B, N]
        action_dims = before % action_layout.action_dim
        both_actions = is_action & tokenizer.is_action_token(parent_targets)
        distances = torch.where(both_actions, tokenizer.bin_distance(tokens, parent_targets), 0)
    else:
        action_dims = torch.zeros_like(tokens)
        distances = torch.zeros_like(tokens)
    passes = rule(tokens, parent_targets, action_dims) & trees.is_real  # [B, N] the node alone
    path_passes = ~(ancestor_or_self & ~passes[:, None, :]).any(dim=-1)  # [B, N] the node and all its ancestors
    total_distance = (ancestor_or_self.long() * distances[:, None, :]).sum(-1)  # [B, N] summed along the path
    # deepest, then closest, then first: argmax returns the first of equal maxima
    rank = (trees.depths + 1) * (int(total_distance.max()) + 1) - total_distance  # >= 1 for every node
    best = torch.where(path_passes, rank, 0).argmax(dim=-1)  # [B]
    accepted = path_passes.any(dim=-1)  # [B]
    bonus_ids = torch.where(accepted, target_ids.gather(1, best[:, None] + 1)[:, 0], target_ids[:, 0])
    on_path = ancestor_or_self[torch.arange(batch_size, device=tokens.device), best] & accepted[:, None]  # [B, N]
    paths = []
    for row_on_path, row_distances, bonus in zip(on_path.tolist(), distances.tolist(), bonus_ids.tolist()):
        nodes = [i for i, kept in enumerate(row_on_path) if kept]  # index order is depth order
        paths.append(AcceptedPath(nodes, bonus, [row_distances[i] for i in nodes]))
    return paths
