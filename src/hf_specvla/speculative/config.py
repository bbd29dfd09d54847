"""The one speculation setting: [`SpeculationConfig`], what drafts and how drafts count, checked once when made and
passed whole (``model.generate(..., speculation=...)``); the loose ``generate`` keywords (``assistant_model=``,
``bin_tolerance=``, ...) are folded into one at the boundary ([`SpeculationConfig.fold`]), as transformers folds
its keywords into a ``GenerationConfig``. The one place these settings are declared, with their defaults."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from ..actions.tokenizer import ActionLayout
from .acceptance import (
    MAX_DEVIATION_MEANING,
    MOTION_SCALE_MEANING,
    AcceptanceRule,
    check_confidence_gate,
    check_relaxed_budget,
    make_acceptance_rule,
    validate_per_dimension,
)
from .drafter import Drafter
from .modeling_draft_head import DraftHead


@dataclass(frozen=True)
class SpeculationConfig:
    """The settings of speculative ``generate`` calls, whole: ``model.generate(**inputs, speculation=settings)``, or
    the same as loose ``generate`` keywords (``assistant_model=`` for ``drafter``). Frozen and hashable (equal for
    equal settings); checked when made, each refusal naming its field.

    Args:
        drafter: what drafts after the prefill: a [`Drafter`] or a bare [`DraftHead`] (its chain), or None (only
            ``draft_ids``, a call's own, then draft). ``generate``'s ``assistant_model``.
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

    drafter: object = None
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
        if self.drafter is not None and not isinstance(self.drafter, (Drafter, DraftHead)):
            raise TypeError(
                f"SpeculationConfig.drafter (generate's assistant_model) must be a hf_specvla DraftHead or Drafter "
                f"(DraftHeadDrafter, JacobiDrafter, ComposedDrafter, ...) or None, got {type(self.drafter).__name__}"
            )
        if isinstance(self.drafter, Drafter):  # a chain length is a bare head's: the drafter's own check
            self.drafter.as_drafter(self.num_draft_tokens)
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

    def __hash__(self) -> int:
        return hash(tuple(hashable(getattr(self, f.name)) for f in dataclasses.fields(self)))

    @classmethod
    def fold(cls, speculation: SpeculationConfig | None, loose: Mapping) -> SpeculationConfig:
        """The call's one setting: ``speculation``, or the loose keywords' (``loose``: names of its fields, e.g.
        ``{"drafter": head, "bin_tolerance": 2}``), made once at the boundary; both at once only when the loose
        ones add a drafter to a ``speculation`` without one (a robot's drafter, made each call).

        Raises:
            ValueError: ``speculation`` beside loose settings that say the same, naming them.
            TypeError: ``speculation`` that is not a SpeculationConfig.
        """
        if speculation is None:
            return cls(**loose)
        if not isinstance(speculation, SpeculationConfig):
            raise TypeError(
                f"speculation must be a hf_specvla SpeculationConfig (or left out for loose keywords), got "
                f"{type(speculation).__name__}"
            )
        clash = sorted(name for name in loose if name != "drafter" or speculation.drafter is not None)
        if clash:
            raise ValueError(
                f"generate got speculation=SpeculationConfig(...) and {', '.join(clash)}: the setting holds them "
                f"whole; pass one or the other (dataclasses.replace(speculation, {clash[0]}=...) for another value)"
            )
        if not loose:
            return speculation
        folded = dataclasses.replace(speculation, **loose)
        if set(loose) == {"drafter"}:  # the same acceptance: the rules built for it are the folded setting's too
            folded.__dict__["_rules"] = speculation.__dict__.setdefault("_rules", {})
        return folded

    def acceptance_rule(self, layout: ActionLayout | None) -> AcceptanceRule:
        """The acceptance rule of these settings for ``layout`` (the settings' own, else the drafter's), built once
        per layout and kept: a setting [`fold`] made from this one by adding a drafter (a robot's call through a
        decoder session) shares them. Rules hold no per-call state."""
        rules = self.__dict__.setdefault("_rules", {})  # not a field: equality and hash ignore it
        kept = rules.get(id(layout))
        if kept is None:  # the layout kept beside its rule: its id is not another's while the entry lives
            rule = make_acceptance_rule(
                self.bin_tolerance,
                layout,
                self.confidence_gate,
                self.max_relaxed_per_action,
                self.motion_scale,
                self.max_deviation,
                self.confirm_strict_tail,
            )
            kept = rules[id(layout)] = (layout, rule)
        return kept[1]


#: [`SpeculationConfig`]'s fields as ``generate``'s loose keywords (``drafter`` is ``assistant_model`` there)
SPECULATION_KWARGS = tuple(f.name for f in dataclasses.fields(SpeculationConfig) if f.name != "drafter")


def hashable(value):
    """A hash stand-in consistent with ``==``: sequences and mappings by their items, an object that cannot hash (a
    ``CompileConfig``, an ``ActionLayout``) by its type."""
    if isinstance(value, (list, tuple)):
        return tuple(hashable(item) for item in value)
    if isinstance(value, Mapping):
        return tuple(sorted((str(name), hashable(item)) for name, item in value.items()))
    try:
        hash(value)
    except TypeError:
        return type(value).__qualname__
    return value


#: the acceptance rule's settings among [`SpeculationConfig`]'s (``make_acceptance_rule``'s arguments but the layout;
#: a test keeps the two equal)
RULE_ARGUMENTS = (
    "bin_tolerance",
    "confidence_gate",
    "max_relaxed_per_action",
    "motion_scale",
    "max_deviation",
    "confirm_strict_tail",
)
