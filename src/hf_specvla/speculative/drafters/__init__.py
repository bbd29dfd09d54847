"""Built-in drafters: the draft head (chain / EAGLE-2 tree) and the action prior (no model)."""

from .action_prior import ActionPriorDrafter, with_action_prior, with_action_priors
from .draft_head import DraftHeadDrafter, DraftTreeConfig

__all__ = ["with_action_prior", "with_action_priors", "ActionPriorDrafter", "DraftHeadDrafter", "DraftTreeConfig"]
