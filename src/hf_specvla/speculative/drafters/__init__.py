"""Built-in drafters: the draft head (chain / EAGLE-2 tree), the action prior and Jacobi drafts (no model)."""

from .action_prior import (
    ActionPriorDrafter,
    episode_drafter,
    remember_actions,
    with_action_prior,
    with_action_priors,
    with_previous_actions,
)
from .draft_head import DraftHeadDrafter, DraftTreeConfig
from .jacobi import JacobiDrafter, jacobi_tail

__all__ = [
    "episode_drafter",
    "remember_actions",
    "with_action_prior",
    "with_action_priors",
    "with_previous_actions",
    "jacobi_tail",
    "ActionPriorDrafter",
    "DraftHeadDrafter",
    "DraftTreeConfig",
    "JacobiDrafter",
]
