"""The one place the speculative ``generate`` keyword arguments are declared, with their defaults."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from ..actions.tokenizer import ActionLayout
from .acceptance import (
    MAX_DEVIATION_MEANING,
    MOTION_SCALE_MEANING,
    check_confidence_gate,
    check_relaxed_budget,
    validate_per_dimension,
)

#: Appended to the AttributeError transformers' own assisted generation raises when it is handed a hf_specvla
#: assistant because the target's ``generate`` was never speculation-enabled (it is not enabled automatically).
NOT_ENABLED_HINT = (
    "a hf_specvla assistant (DraftHead or Drafter) needs a speculation-enabled target: call "
    "hf_specvla.enable_speculation(model) once, or pass generate(custom_generate=hf_specvla.speculative_generate, "
    "drafter=...)"
)


@dataclass
class SpeculationConfig:
    """Runtime settings of one speculative ``generate`` call (passed as ``generate`` keyword arguments).

    Args:
        bin_tolerance: the paper's r: accept a drafted action token within this many bins of the target's greedy
            token. An int, one int per action dimension, or one such list per action of a chunk (the last one serving
            the later actions). 0 = lossless (identical to greedy decoding).
        num_draft_tokens: chain length k when the assistant is a bare ``DraftHead``; None = the head's
            ``config.num_draft_tokens``. (For a tree, pass ``assistant_model=DraftHeadDrafter(head, tree=...)``.)
        action_layout: which tokens are actions and how many make an action; None = the drafter's (a draft head's
            config), needed only for relaxed acceptance and bin-distance statistics.
        profile_speculation: synchronise the device around timed sections so the time split is exact.
        confidence_gate: a relaxed token counts only where the target's greedy token has a probability below this
            (the target is unsure); None = no gate.
        max_relaxed_per_action: at most this many relaxed tokens per action (past it acceptance is exact); None = no
            budget.
        motion_scale: rho: also accept an action token within ``rho * |target bin - zero-motion bin|`` bins of the
            target's (a number or one per dimension; a relative error bound; needs ``action_layout.units``). None = no
            scaling.
        max_deviation: never accept a token whose action differs from the target's by more than this, in the
            policy's units (a number or one per dimension; needs ``action_layout.units``). None = no bound.
        confirm_strict_tail: keep a relaxed token only when its action's strict dimensions after it (a gripper) were
            drafted and confirmed in the same verification.
        max_drafts_per_row: each row's draft tree is cut to its first this many tokens per verification (the prefill
            included); None = as the drafter proposes. A verification's cost grows with its tokens once the forward is
            compute-bound (a batch on a CPU: docs/benchmarks.md, "The arithmetic floor"), so batches verify fewer
            drafts per row than one row can afford.
    """

    bin_tolerance: int | Sequence[int] | Sequence[Sequence[int]] = 0
    num_draft_tokens: int | None = None
    action_layout: ActionLayout | None = None
    profile_speculation: bool = False
    confidence_gate: float | None = None
    max_relaxed_per_action: int | None = None
    max_drafts_per_row: int | None = None
    motion_scale: float | Sequence[float] | None = None
    max_deviation: float | Sequence[float] | None = None
    confirm_strict_tail: bool = False

    def __post_init__(self):
        k = self.num_draft_tokens
        if k is not None and (isinstance(k, bool) or not isinstance(k, int) or k < 1):
            raise ValueError(f"num_draft_tokens must be an int >= 1 (tokens drafted per verification), got {k!r}")
        check_confidence_gate(self.confidence_gate)
        check_relaxed_budget(self.max_relaxed_per_action)
        for name, meaning in (("motion_scale", MOTION_SCALE_MEANING), ("max_deviation", MAX_DEVIATION_MEANING)):
            value = getattr(self, name)
            if value is not None:  # the number of dimensions is checked against the action layout later
                values = list(value) if isinstance(value, Sequence) and not isinstance(value, str) else [value]
                validate_per_dimension(values, len(values), name, meaning)
        if not isinstance(self.confirm_strict_tail, bool):
            raise TypeError(f"confirm_strict_tail must be True or False, got {self.confirm_strict_tail!r}")
        cap = self.max_drafts_per_row
        if cap is not None and (isinstance(cap, bool) or not isinstance(cap, int) or cap < 0):
            raise ValueError(
                f"max_drafts_per_row must be an int >= 0 (drafted tokens verified per row and forward; 0 = none) or "
                f"None (as the drafter proposes), got {cap!r}"
            )
        if self.action_layout is not None and not isinstance(self.action_layout, ActionLayout):
            raise TypeError(f"action_layout must be a hf_specvla.ActionLayout, got {type(self.action_layout).__name__}")


#: the acceptance rule's settings among [`SpeculationConfig`]'s (``make_acceptance_rule``'s arguments but the layout;
#: a test keeps the two equal)
RULE_ARGUMENTS = ("bin_tolerance", "confidence_gate", "max_relaxed_per_action", "motion_scale", "max_deviation",
                  "confirm_strict_tail")  # fmt: skip
