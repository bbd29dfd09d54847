"""Built-in drafters: the draft head (chain / EAGLE-2 tree) and the action prior (no model)."""

from .action_prior import ActionPriorDrafter
from .draft_head import DraftHeadDrafter, DraftTreeConfig

__all__ = ["ActionPriorDrafter", "DraftHeadDrafter", "DraftTreeConfig"]
