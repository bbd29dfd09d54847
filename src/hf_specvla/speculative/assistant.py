"""What an ``assistant_model`` drafts with: the seam between what a user passes to ``generate`` (a [`DraftHead`], a
[`Drafter`]) and the [`Drafter`] the loop asks for drafts. It sits above the draft head's model and its drafter, so
that neither imports the other's user (the model knows nothing of drafting, the drafter builds on the model)."""

from __future__ import annotations

from .drafter import Drafter
from .drafters.draft_head import DraftHeadDrafter
from .modeling_draft_head import DraftHead


def as_drafter(assistant, num_draft_tokens: int | None) -> Drafter | None:
    """The [`Drafter`] behind an ``assistant_model`` / ``draft_head`` argument: a bare [`DraftHead`] drafts its chain
    of ``num_draft_tokens`` (default ``config.num_draft_tokens``, a [`DraftHeadDrafter`]); a [`Drafter`] is one.

    Raises:
        TypeError: for anything that is neither a DraftHead nor a Drafter.
        ValueError: ``num_draft_tokens`` given with a Drafter (it carries its own settings).
    """
    if assistant is None:
        return None
    if isinstance(assistant, DraftHead):
        return DraftHeadDrafter(assistant, num_draft_tokens=num_draft_tokens)
    if isinstance(assistant, Drafter):
        return assistant.as_drafter(num_draft_tokens)
    raise TypeError(
        f"the assistant must be a hf_specvla DraftHead or Drafter (DraftHeadDrafter, ActionPriorDrafter, "
        f"ComposedDrafter, ...), got {type(assistant).__name__}"
    )
