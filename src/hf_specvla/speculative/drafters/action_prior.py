"""Drafts from the previous actions: no model, known before the target runs, so verified inside the prefill.

A policy's consecutive actions are close (on the shipped Meta-World policy the median per-dimension distance
between consecutive actions is 0 bins). The prior proposes, as one tree, in this order:

1. the previous action;
2. constant velocity: ``2 * previous - the one before`` (per dimension, in bins, clipped to the action range);
3. the action before the previous one;
4. per-dimension alternatives: the previous action with one dimension replaced by a neighbouring bin
   (``+-1 .. +-neighbour_bins``), by the constant-velocity value or by the older action's value.

For a policy that predicts a chunk of H actions per call (``chunk_length=H``), each candidate is continued to H
actions the way it began: a held action is held (``[last] * H``), constant velocity keeps its velocity
(``last + v, last + 2v, ...``), an alternative is held.

Paths are added in that order until the tree holds ``max_nodes`` nodes (shared prefixes cost nothing). Drafting
alone, after a partial acceptance the prior proposes the remaining dimensions of the same candidates again (see
[`CandidateDrafter`]). Before another drafter ([`with_action_prior`]) it proposes the held action alone, in the
prefill only: its other candidates and re-proposals widen the verifications for few accepted tokens once Jacobi
guesses or a draft head follow (measured in [`with_action_prior`]).
This is transformers' prompt-lookup idea (drafts from what is already known) applied to actions.
"""

from __future__ import annotations

from collections.abc import Sequence

from ...actions.tokenizer import ActionLayout
from ..drafter import CandidateDrafter, DraftContext, Drafter, DraftSession, PathSession, PerRowDrafter


def _actions_as_lists(previous_actions, action_dim: int) -> list[list[int]]:
    """``previous_actions`` (a sequence of actions, each a sequence of token ids) as lists of ints.

    Raises:
        TypeError: a flat list of ids or anything else that is not a sequence of actions (names what was given).
    """
    actions = previous_actions.tolist() if hasattr(previous_actions, "tolist") else previous_actions  # array, tensor
    try:
        return [[int(t) for t in action] for action in actions]
    except TypeError:
        raise TypeError(
            f"previous_actions must be a list of actions, each a list of {action_dim} action token ids (oldest "
            f"first), e.g. [[...{action_dim} ids...]] for one action; got {str(actions)[:80]}: a flat list of ids "
            f"is one action, wrap it in a list"
        ) from None


class ActionPriorDrafter(Drafter):
    """Candidate action-token sequences from the episode's previous actions (see module docstring).

    Args:
        previous_actions: the episode's previous actions as token ids, oldest first, each ``action_dim`` long.
        action_layout: the action layout (for clipping extrapolations to the action range, and for relaxed
            acceptance when no other drafter knows it).
        neighbour_bins: per-dimension alternatives reach this many bins either side of the previous action.
        max_nodes: the tree's node budget.
        chunk_length: actions the target generates per call (H); every candidate drafts H actions.
        later_rounds: after a partial acceptance, propose the candidates' remaining parts again (False: draft in
            the prefill only, as when another drafter continues).
    """

    name = "prior"
    #: previous actions the prior reads (the last one, and the one before for constant velocity)
    history_length = 2

    def __init__(
        self,
        previous_actions: Sequence[Sequence[int]],
        action_layout: ActionLayout,
        neighbour_bins: int = 1,
        max_nodes: int = 16,
        chunk_length: int = 1,
        later_rounds: bool = True,
    ):
        if not isinstance(action_layout, ActionLayout):
            raise TypeError(f"action_layout must be an ActionLayout, got {type(action_layout).__name__}")
        checks = (("neighbour_bins", neighbour_bins, 0), ("max_nodes", max_nodes, 1), ("chunk_length", chunk_length, 1))
        for name, value, low in checks:
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ValueError(f"ActionPriorDrafter {name} must be an int >= {low}, got {value!r}")
        if not isinstance(later_rounds, bool):
            raise TypeError(f"ActionPriorDrafter later_rounds must be True or False, got {later_rounds!r}")
        history = _actions_as_lists(previous_actions, action_layout.action_dim)
        tokenizer = action_layout.tokenizer
        for action in history:
            if len(action) != action_layout.action_dim or not all(tokenizer.is_action_token(t) for t in action):
                raise ValueError(
                    f"previous action {action} is not {action_layout.action_dim} action token ids "
                    f"({tokenizer.action_token_begin}..{tokenizer.vocab_size - 1})"
                )
        self.previous_actions = history
        self.action_layout = action_layout
        self.neighbour_bins = neighbour_bins
        self.max_nodes = max_nodes
        self.chunk_length = chunk_length
        self.later_rounds = later_rounds

    def candidate_paths(self) -> list[list[int]]:
        """The candidate action-token sequences (``chunk_length * action_dim`` tokens each), most likely first
        (before the node budget is applied)."""
        if not self.previous_actions:
            return []
        tokenizer = self.action_layout.tokenizer
        low, high = tokenizer.action_token_begin, tokenizer.vocab_size - 1
        chunk = self.chunk_length
        last = self.previous_actions[-1]
        older = self.previous_actions[-2] if len(self.previous_actions) > 1 else None
        paths = [last * chunk]
        velocity = None
        if older is not None:
            steps = [
                [min(max(a + (n + 1) * (a - b), low), high) for a, b in zip(last, older)] for n in range(chunk)
            ]  # ids are bins (reversed): the velocity is in bins
            velocity = steps[0]
            paths += [[t for action in steps for t in action], older * chunk]
        for dim, value in enumerate(last):
            alternatives = []
            for step in range(1, self.neighbour_bins + 1):
                alternatives += [value - step, value + step]
            if velocity is not None:
                alternatives += [velocity[dim], older[dim]]
            for alternative in alternatives:
                if low <= alternative <= high and alternative != value:
                    paths.append((last[:dim] + [alternative] + last[dim + 1 :]) * chunk)
        return paths

    def max_tree_nodes(self, max_depth: int) -> int | None:
        return self.max_nodes if self.later_rounds else 0

    def start(self, context: DraftContext) -> DraftSession:
        device = context.model.device
        return PathSession(self.candidate_paths(), self.name, device, self.max_nodes, not self.later_rounds)

    def __repr__(self) -> str:
        return (
            f"ActionPriorDrafter(previous_actions={len(self.previous_actions)}, "
            f"neighbour_bins={self.neighbour_bins}, max_nodes={self.max_nodes}, chunk_length={self.chunk_length}, "
            f"later_rounds={self.later_rounds})"
        )


def with_action_prior(
    drafter: Drafter | None,
    previous_actions: Sequence[Sequence[int]],
    action_layout: ActionLayout,
    chunk_length: int = 1,
) -> Drafter | None:
    """``drafter`` preceded by an [`ActionPriorDrafter`] over ``previous_actions``; ``drafter`` unchanged when there
    is no previous action yet; the prior alone when ``drafter`` is None. ``chunk_length``: actions per call (see
    [`ActionPriorDrafter`]).

    Before another drafter the prior proposes its first candidate only (the held action, a chain verified inside the
    prefill through the model's own causal path) and nothing after the prefill: ``drafter`` continues where it stops
    being accepted. Its other candidates and later re-proposals cost more than they gave (the prior's candidates on
    policy v2, docs/results/record/benchmarks-history.md)."""
    from ..drafter import ComposedDrafter

    if not previous_actions:
        return drafter
    if drafter is None:
        return ActionPriorDrafter(previous_actions, action_layout, chunk_length=chunk_length)
    # before another drafter: the held action alone, in the prefill only (a chain: the model's causal path)
    held = ActionPriorDrafter(
        previous_actions,
        action_layout,
        max_nodes=chunk_length * action_layout.action_dim,
        chunk_length=chunk_length,
        later_rounds=False,
    )
    return ComposedDrafter([held, drafter.with_previous_action(previous_actions[-1])])


def with_action_priors(
    drafter: Drafter | None,
    histories: Sequence[Sequence[Sequence[int]]],
    action_layout: ActionLayout,
    chunk_length: int = 1,
) -> Drafter | None:
    """[`with_action_prior`] for a batch: ``histories[b]`` is row b's previous actions. One row: that row's drafter;
    several: a [`PerRowDrafter`] (a row with no previous action drafts with ``drafter`` alone, or nothing); no
    previous action in any row: ``drafter`` unchanged."""
    if not any(histories):
        return drafter
    if len(histories) == 1:
        return with_action_prior(drafter, histories[0], action_layout, chunk_length)
    nothing = CandidateDrafter([], name=ActionPriorDrafter.name)  # a row at its episode's first step
    return PerRowDrafter([with_action_prior(drafter, h, action_layout, chunk_length) or nothing for h in histories])


def with_previous_actions(drafter: Drafter | None, histories: Sequence[Sequence[Sequence[int]]]) -> Drafter | None:
    """``drafter`` told each row's previous action (``histories[b][-1]``, see [`Drafter.with_previous_action`]),
    without the prior's drafts: one row: that row's drafter; several: a [`PerRowDrafter`] when it reads them;
    ``drafter`` unchanged when it does not (or no row has a previous action)."""
    if drafter is None or not any(histories):
        return drafter
    rows = [drafter.with_previous_action(history[-1] if history else None) for history in histories]
    if len(rows) == 1 or all(row is drafter for row in rows):
        return rows[0]
    return PerRowDrafter(rows)


# ----------------------------------------------------------------------------- an episode's step
def episode_drafter(
    assistant,
    num_draft_tokens: int | None,
    action_prior: bool,
    histories: Sequence[Sequence[Sequence[int]]],
    action_layout: ActionLayout,
    chunk_length: int = 1,
) -> Drafter | None:
    """The drafter of one step of B episodes (what ``predict_action`` drafts with, on a policy or the OpenVLA port):
    the ``assistant_model``'s (a bare DraftHead drafts a chain of ``num_draft_tokens``), told each row's previous
    action (``histories[b][-1]``); with ``action_prior``, preceded by the action prior over ``histories[b]``
    ([`with_action_priors`]). None: nothing drafts (no assistant, and no previous action or no prior).

    Raises:
        ValueError: ``num_draft_tokens`` without an assistant.
        TypeError: an assistant that is neither a DraftHead nor a Drafter.
    """
    from ..assistant import as_drafter  # above the drafters: it builds a draft head's

    if num_draft_tokens is not None and assistant is None:
        raise ValueError("num_draft_tokens needs assistant_model=<DraftHead>")
    drafter = as_drafter(assistant, num_draft_tokens)
    if not action_prior:  # a draft head that reads the previous action still gets it
        return with_previous_actions(drafter, histories)
    return with_action_priors(drafter, histories, action_layout, chunk_length)


def remember_actions(history: list[list[int]], action_ids, action_layout: ActionLayout) -> None:
    """Adds one call's actions to an episode's memory (``history``, token ids oldest first, changed in place), keeping
    the last [`ActionPriorDrafter.history_length`]. An output that is not all action tokens (an untrained model may
    emit text ids) clears the memory: text ids never become drafts.

    Args:
        action_ids: ``[H, action_dim]`` int tensor: the call's H actions (H = 1 without chunks).
    """
    if bool(action_layout.tokenizer.is_action_token(action_ids).all()):
        history[:] = [*history, *action_ids.tolist()][-ActionPriorDrafter.history_length :]
    else:
        history.clear()
