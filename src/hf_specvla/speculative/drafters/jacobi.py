"""Jacobi drafts: the target's own guesses past a rejection become the next round's drafts (no model, no training).

When a verification rejects a drafted token, the target has still computed its greedy token after every deeper
node, each conditioned on a prefix that holds the rejected token. Jacobi (parallel) decoding reuses those guesses as
the next round's drafts: the new root is the bonus token that replaced the rejected one, and the guesses for the
positions after it are the target's argmax after the rejected node and its descendants. They cost nothing (they come
out of a forward that ran anyway) and are often right when the later tokens depend little on the one that changed,
as an action chunk's later dimensions do on an earlier one (PD-VLA, arXiv 2503.02310; Lookahead decoding).

The tail follows, below the last accepted node, the rejected child closest to the bonus token (in bins for action
tokens, else the first child), then at each level the child that equals the target's guess there (its prefix is
then right but for the one rejected token), else the first child. For action chunks, the guess of the rejected
token's dimension in the next action is moved by as many bins as the bonus token moved the rejected one (on policy
v2 that guess was right 7-15% of the time as the target made it, 42-49% moved).

When nothing was rejected (no tail) and no drafter before it in a [`ComposedDrafter`] proposed anything this round,
the drafter proposes a fill chain (the given ``initial_ids``, else the root token repeated) so that the target's
forward produces guesses: the first iterate of Jacobi decoding. Greedy decides every token, so at r=0 the output is
greedy decoding's.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from ...actions.tokenizer import ActionLayout
from ..drafter import Commit, DraftContext, Drafter, DraftRound, DraftSession
from ..stats import SpeculationStats
from ..tree import DraftTree


def jacobi_tail(
    parents: Sequence[int],
    token_ids: Sequence[int],
    target_ids: Sequence[int],
    path_nodes: Sequence[int],
    action_layout: ActionLayout | None = None,
) -> list[int]:
    """The target's guesses for the tokens after a verification's bonus token (see module docstring).

    Args:
        parents / token_ids: the verified tree's ``N`` nodes (``parents[i] < i``, -1 = child of the root).
        target_ids: ``1 + N`` the target's greedy token after the root (0) and after each node (1 + i).
        path_nodes: the accepted path (node indices, root's child first).
        action_layout: when given and the bonus token is an action token, the rejected child closest in bins to
            it starts the tail, and a guess of the same action dimension in a later action of the chunk (every
            ``action_dim``-th guess) is moved by the bins the bonus token moved the rejected one (consecutive
            actions move together: the guess was conditioned on the rejected value).
    Returns:
        the guesses, first the token after the bonus; empty when no node below the path's end was rejected.
    """
    end = path_nodes[-1] if path_nodes else -1
    children: dict[int, list[int]] = {}
    for node, parent in enumerate(parents):
        children.setdefault(parent, []).append(node)
    rejected = children.get(end, [])
    if not rejected:
        return []
    bonus = target_ids[end + 1]
    node, shift, period = rejected[0], 0, 0  # period 0: no guess is moved
    is_action = action_layout.tokenizer.is_action_token if action_layout is not None else None
    if is_action is not None and is_action(bonus):
        actions = [c for c in rejected if is_action(token_ids[c])]
        if actions:  # ids are bins (reversed); min keeps the first of equals
            node = min(actions, key=lambda c: abs(token_ids[c] - bonus))
            shift, period = bonus - token_ids[node], action_layout.action_dim
    tail: list[int] = []
    while True:
        guess = target_ids[node + 1]
        moved = guess + shift
        if period and (len(tail) + 1) % period == 0 and is_action(guess) and is_action(moved):
            tail.append(moved)
        else:
            tail.append(guess)
        below = children.get(node, [])
        if not below:
            return tail
        node = next((c for c in below if token_ids[c] == guess), below[0])


class JacobiDrafter(Drafter):
    """Drafts the target's guesses from the previous verification (see module docstring); composes with any drafter:
    ``ComposedDrafter([prior, JacobiDrafter(), tree])`` verifies the prior's drafts in the prefill, then the Jacobi
    tail past their first rejection, with the head's tree beside it.

    Args:
        max_tokens: the longest tail (or fill) proposed; None = as deep as the call can still draft.
        initial_ids: the fill's guesses of the first generated tokens (aligned with the first generated token, as
            ``draft_ids``); None = the root token repeated.
        fill: propose a fill chain when there is no tail and no earlier drafter proposed anything (off when a draft
            head composed after it drafts every round anyway).

    Example:
        ```python
        out = model.generate(**inputs, assistant_model=JacobiDrafter(), max_new_tokens=7, do_sample=False)
        ```
    """

    name = "jacobi"

    def __init__(self, max_tokens: int | None = None, initial_ids: Sequence[int] | None = None, fill: bool = True):
        if max_tokens is not None and (
            isinstance(max_tokens, bool) or not isinstance(max_tokens, int) or max_tokens < 1
        ):
            raise ValueError(f"JacobiDrafter max_tokens must be an int >= 1 or None, got {max_tokens!r}")
        if not isinstance(fill, bool):
            raise TypeError(f"JacobiDrafter fill must be True or False, got {fill!r}")
        if initial_ids is not None:
            initial_ids = [int(t) for t in initial_ids]
            if not initial_ids or min(initial_ids) < 0:
                raise ValueError(f"JacobiDrafter initial_ids must be non-negative token ids, got {initial_ids}")
        self.max_tokens, self.initial_ids, self.fill = max_tokens, initial_ids, fill

    def start(self, context: DraftContext) -> DraftSession:
        return _JacobiSession(self, context)

    def max_tree_nodes(self, max_depth: int) -> int | None:
        return max_depth if self.max_tokens is None else min(max_depth, self.max_tokens)  # one chain

    def settings_key(self) -> tuple:
        return self.max_tokens, None if self.initial_ids is None else tuple(self.initial_ids), self.fill

    def __repr__(self) -> str:
        return f"JacobiDrafter(max_tokens={self.max_tokens}, initial_ids={self.initial_ids}, fill={self.fill})"


class _JacobiSession(DraftSession):
    def __init__(self, drafter: JacobiDrafter, context: DraftContext):
        self.drafter, self.layout = drafter, context.action_layout
        self.device = context.model.device
        self.tail: list[int] = []
        self.tail_at = -1  # the sequence length the tail follows (its root is that sequence's last token)
        self.tails: list[tuple[int, list[int]]] = []  # every tail, with the sequence length it follows

    def propose(self, draft_round: DraftRound) -> DraftTree:
        limit = draft_round.max_depth
        if self.drafter.max_tokens is not None:
            limit = min(limit, self.drafter.max_tokens)
        length = draft_round.sequence.shape[1]
        if self.tail and self.tail_at == length:
            return DraftTree.from_paths([self.tail[:limit]], self.drafter.name, self.device)
        if not self.drafter.fill or (draft_round.proposed is not None and draft_round.proposed.num_nodes):
            return DraftTree.empty(self.device)
        if self.drafter.initial_ids is not None:
            guesses = self.drafter.initial_ids[draft_round.num_generated :][:limit]
        else:  # the root's token repeated, on the device (the verification's read brings it to the host)
            return DraftTree.chain(draft_round.sequence[0, -1:].expand(limit).clone(), self.drafter.name)
        return DraftTree.from_paths([guesses] if guesses else [], self.drafter.name, self.device)

    def observe(self, commit: Commit) -> None:
        self.tail = []
        if commit.tree is None or commit.tree_target_ids is None:
            return
        tree = commit.tree
        targets = commit.tree_target_list if commit.tree_target_list is not None else commit.tree_target_ids.tolist()
        self.tail = jacobi_tail(tree.parent_list, tree.host_tokens, targets, commit.path_nodes, self.layout)
        self.tail_at = commit.cache_length + 1
        if self.tail:
            self.tails.append((self.tail_at, self.tail))

    def report(self, stats: SpeculationStats, sequence: torch.Tensor) -> None:
        tokens = sequence[0].tolist()
        for start, tail in self.tails:
            reached = tail[: max(0, len(tokens) - start)]
            if reached:
                stats.record_guesses([guess == tokens[start + j] for j, guess in enumerate(reached)])
