"""Decoding methods of a comparison: ``<drafters>[:<option>,...][:compile]`` parsed, named and turned into
``predict_action`` options, and the presets ``exact`` and ``fast``. No torch at import: the CLI reads the choices
here. Every command that decodes takes these names (eval, compare, serve); ``metaworld.comparison.methods`` adds what a
comparison runs.

Drafters, joined by ``+``: ``head`` (the draft head's chain), ``tree`` (its EAGLE-2 tree), ``prior`` (the episode's
previous actions), ``jacobi`` (the target's own guesses past a rejection, [`JacobiDrafter`]); ``none`` alone drafts
nothing and decodes greedily through the engine ([`NoDrafter`], the baseline of the engine's own path).

Options (relaxed acceptance, see ``speculative.acceptance``): ``r=<r>`` the bin tolerance, one int or one per action
dimension joined by ``/`` (``r=4/4/4/0``: a strict gripper); ``rl=<r>`` the tolerance of a chunk's later actions
(default: ``r``); ``rho=<x>`` a tolerance that scales with the motion: also within x bins per bin the target's token
lies from the zero-motion bin (one number or one per dimension: ``rho=0.1/0.1/0.1/0``); ``dev=<x>`` never accept a token
whose action is more than x from the target's in the policy's units (one or one per dimension); ``m=<int>`` at most m
relaxed tokens per action; ``gate=<p>`` relax only where the target's top-1 probability is below p; ``confirm=1`` keep a
relaxed token only when its action's strict dimensions after it (the gripper) are drafted and confirmed in the same
verification; ``k=<int>`` the head chain's length. E.g. ``prior+jacobi:r=4/4/4/0,m=1:compile``,
``prior+jacobi:rho=0.1/0.1/0.1/0,confirm=1:compile``.

Presets: ``exact`` (the fastest setting identical to greedy decoding) and ``fast`` (the relaxed setting chosen on policy
v2, with ``confirm=1`` added on policy v3; there it flips episodes both ways beyond the fidelity criterion and is no
faster than ``exact`` in total decode time), resolved per policy, with or without a draft head, and to the policy's
action layout ([`PRESETS`], [`Preset`], chosen by the evidence in docs/results/record/metaworld-policies.md); every
place that takes a method string takes them and names what they resolved to. Given a draft head, a preset resolves to
the same head-less method (its head composition was slower than ``exact`` on policy v3 on a CPU, docs/training.md), and
a policy server measures both and decodes each batch size with the faster ([`serving_methods`]). A preset is defined by
what it relaxes, not by a table: ``fast`` relaxes the position dimensions (x y z) with r=4 and keeps the rotation and
the gripper strict, only where the target's top-1 probability is below 0.5, a relaxed token kept only when the gripper
after it is confirmed (``confirm=1``). On this project's 4-dimensional actions (x y z gripper) that is ``r=4/4/4/0``; on
OpenVLA's 7 (x y z roll pitch yaw gripper) ``r=4/4/4/0/0/0/0``; on 8 (x y z, a quaternion qx qy qz qw, gripper)
``r=4/4/4/0/0/0/0/0`` ([`ACTION_LAYOUTS`]). Rotations stay strict because no measurement here relaxed one (Meta-World's
hand does not rotate); any other number of dimensions is refused with the rule to spell out instead. ``exact`` relaxes
nothing, so it fits every layout.

``:compile`` decodes on a static cache with transformers' ``CompileConfig``: ``greedy:compile`` is transformers' own
compiled greedy decoding (the baseline a user who wants speed has), ``tree:compile`` / ``prior+tree:r=4:compile``
verify drafts through the same compiled model call (``speculative.compiled``)."""

from __future__ import annotations

import copy
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from .configuration_vla import VLAPolicyConfig

if TYPE_CHECKING:
    from ..speculative import DraftHead, DraftTreeConfig

DRAFTER_CHOICES = (
    "greedy",
    "head",
    "tree",
    "prior",
    "prior+head",
    "prior+tree",
    "jacobi",
    "prior+jacobi",
    "jacobi+tree",
    "prior+jacobi+tree",
    "none",
)
#: drafting nothing: ``greedy`` is transformers' own greedy decoding, ``none`` greedy decoding run by hf_specvla's
#: engine (one token a verification, through the policy's decoder session: what the engine's path alone saves)
DRAFTLESS = ("greedy", "none")
METHOD_KEYS = {
    "r": "bin tolerance: an int, or one per action dimension joined by / (0 = lossless)",
    "rl": "bin tolerance of a chunk's later actions (default: r)",
    "rho": "motion-scaled tolerance: bins per bin of the target's distance from zero motion, one number or "
    "one per action dimension joined by /",
    "dev": "the largest accepted deviation from the target's action in the policy's units, one number or "
    "one per action dimension joined by /",
    "m": "at most this many relaxed tokens per action",
    "gate": "relax only where the target's top-1 probability is below this (0 < p <= 1)",
    "confirm": "1: keep a relaxed token only when its action's strict dimensions after it are confirmed",
    "k": "draft-head chain length (head only)",
}
#: the bound a comparison measures beside the methods: greedy's own tokens (decoded off the clock on the same
#: observation) drafted in the prefill, so every draft is right and a call costs one target forward; only ``compare``
#: runs it (nothing else knows greedy's tokens before decoding)
ORACLE = "oracle"
#: the option word that compiles a method (static cache + transformers' CompileConfig)
COMPILE = "compile"


# ----------------------------------------------------------------------------- methods
Tolerance = int | tuple[int, ...]  # one r, or one per action dimension
Scale = float | tuple[float, ...]  # one number, or one per action dimension (rho, dev)


#: an option's integer and probability, in ASCII digits only (``str.isdigit`` and ``int`` / ``float`` also take
#: superscripts and other scripts' digits: ``r=²``, ``r=٣``)
_INTEGER = re.compile(r"-?[0-9]+")
_PROBABILITY = re.compile(r"[0-9]+(\.[0-9]*)?|\.[0-9]+")
_NUMBER = _PROBABILITY  # a non-negative decimal
#: the smallest value of each integer option (r, rl and m may be 0; a chain drafts at least one token)
_MINIMUM = {"r": 0, "rl": 0, "m": 0, "k": 1}


def _parse_integer(text: str, key: str, value: str) -> int:
    """One integer of option ``key`` (``value``: as written), at least ``_MINIMUM[key]``."""
    if not _INTEGER.fullmatch(value.strip()):
        raise ValueError(
            f"decoding method {text!r}: bad option '{key}={value}'; {key} is {METHOD_KEYS[key]} "
            f"(an integer in digits 0-9)"
        )
    number = int(value)
    if number < _MINIMUM[key]:
        raise ValueError(
            f"decoding method {text!r}: {key} must be an integer >= {_MINIMUM[key]} "
            f"({METHOD_KEYS[key]}), got {key}={value}"
        )
    return number


def _parse_tolerance(text: str, value: str, key: str) -> Tolerance:
    parts = value.split("/")
    if not all(_INTEGER.fullmatch(p.strip()) for p in parts):
        raise ValueError(
            f"decoding method {text!r}: bad option '{key}={value}'; {key} is {METHOD_KEYS[key]} "
            f"(integers in digits 0-9)"
        )
    numbers = [_parse_integer(text, key, p) for p in parts]
    return numbers[0] if len(numbers) == 1 else tuple(numbers)


def check_tolerance_dims(tolerance: Tolerance | None, action_dim: int, given: str) -> None:
    """Refuses a per-dimension tolerance (``4/4/4``) whose length is not ``action_dim``, naming ``given`` (what the
    user wrote) and the layout; an int fits any action.

    Raises:
        ValueError: the number of values differs from the action's dimensions.
    """
    if tolerance is None or isinstance(tolerance, (int, float)) or len(tolerance) == action_dim:
        return
    raise ValueError(
        f"{given} has {len(tolerance)} values, but the policy's actions have {action_dim} dimensions"
        f"{_layout_words(action_dim)}: give one value for all of them, or one per dimension ({action_dim})"
    )


def _check_action_dim(action_dim: int | None) -> None:
    """Refuses an ``action_dim`` (tokens per action, for presets and per-dimension options) that is not a positive int;
    None (this project's policies' layout) passes.

    Raises:
        ValueError: naming the value.
    """
    if action_dim is None:
        return
    if isinstance(action_dim, bool) or not isinstance(action_dim, int) or action_dim < 1:
        raise ValueError(
            f"action_dim must be a positive int (the policy's tokens per action, e.g. 4 for x y z gripper, 7 for "
            f"OpenVLA), or None for this project's policies' {VLAPolicyConfig.action_dim}; got {action_dim!r}"
        )


def _format_tolerance(tolerance: Tolerance | Scale) -> str:
    if isinstance(tolerance, (int, float)):
        return f"{tolerance:g}"
    return "/".join(f"{v:g}" for v in tolerance)


def _widest(tolerance: Tolerance | None) -> int:
    if tolerance is None:
        return 0
    return tolerance if isinstance(tolerance, int) else max(tolerance)


@dataclass(frozen=True)
class DecodingMethod:
    """One decoding method of a comparison (see module docstring for the names and options)."""

    drafters: str = "greedy"
    bin_tolerance: Tolerance = 0
    num_draft_tokens: int | None = None
    compiled: bool = False
    later_tolerance: Tolerance | None = None  # a chunk's later actions (None: bin_tolerance)
    max_relaxed_per_action: int | None = None
    confidence_gate: float | None = None
    motion_scale: Scale | None = None  # rho: a tolerance that scales with the motion
    max_deviation: Scale | None = None  # dev: the largest deviation in the policy's units
    confirm_tail: bool = False  # confirm=1: the strict dimensions after a relaxed token confirmed in its verification

    @classmethod
    def parse(
        cls, text: str, draft_head_given: bool = False, action_dim: int | None = None, oracle: bool = False
    ) -> DecodingMethod:
        """``"prior+tree:r=4"`` -> DecodingMethod("prior+tree", 4); a preset (``exact``, ``fast``) -> the method it
        names for a policy with (``draft_head_given``) or without a draft head and with ``action_dim``-dimensional
        actions ([`Preset.resolve`]; None: this project's policies' layout). With ``action_dim``, a per-dimension r
        of another length is refused here. ``oracle``: also accept the comparison's bound, ``oracle[:compile]``
        ([`ORACLE`]).

        Raises:
            ValueError: naming the bad part and listing what is valid (or the bad ``action_dim``).
        """
        _check_action_dim(action_dim)
        preset = PRESETS.get(text.strip())
        if preset is not None:
            return preset.resolve(draft_head_given, action_dim)
        valid = (
            f"valid: {', '.join(DRAFTER_CHOICES)}, optionally followed by :<option>=<value>,... and/or :compile "
            f"(e.g. prior+tree:r=4, greedy:compile, prior+jacobi:r=4/4/4/0,m=1:compile), or a preset: "
            f"{', '.join(PRESETS)}"
        )
        drafters, _, options = text.strip().partition(":")
        if drafters == ORACLE and not oracle:
            raise ValueError(
                f"decoding method {text!r}: {ORACLE} (greedy's own tokens drafted, the bound) is measured "
                f"by `compare` only, beside greedy; {valid}"
            )
        if drafters not in (*DRAFTER_CHOICES, *((ORACLE,) if oracle else ())):
            raise ValueError(f"unknown decoding method {text!r}: {drafters!r} is not a drafter; {valid}")
        values: dict = {}
        parts = options.replace(":", ",").split(",")
        compiled = COMPILE in parts
        if parts.count(COMPILE) > 1:
            raise ValueError(f"decoding method {text!r}: {COMPILE!r} given twice; {valid}")
        for option in filter(None, (p for p in parts if p != COMPILE)):
            key, _, value = option.partition("=")
            if key not in METHOD_KEYS or not value.strip():
                raise ValueError(
                    f"decoding method {text!r}: bad option {option!r}; options are "
                    + ", ".join(f"{k}=<value> ({v})" for k, v in METHOD_KEYS.items())
                )
            if key in values:
                raise ValueError(f"decoding method {text!r}: {key} given twice")
            values[key] = _parse_option(text, key, value.strip())
        if options and not values and not compiled:
            raise ValueError(f"decoding method {text!r}: empty options after ':'; {valid}")
        method = cls(
            drafters,
            values.get("r", 0),
            values.get("k"),
            compiled,
            values.get("rl"),
            values.get("m"),
            values.get("gate"),
            values.get("rho"),
            values.get("dev"),
            bool(values.get("confirm", 0)),
        )
        restricting = [key for key in ("m", "gate", "dev", "confirm") if key in values]
        relaxing = method.widest_tolerance or method.scales_with_motion or "rl" in values or "rho" in values
        if method.drafters in (*DRAFTLESS, ORACLE) and (relaxing or restricting or method.num_draft_tokens):
            why = "its drafts are greedy's own" if method.drafters == ORACLE else "it drafts nothing"
            raise ValueError(
                f"decoding method {text!r}: {method.drafters} takes no r, rl, rho, dev, m, gate, confirm or k ({why})"
            )
        if method.num_draft_tokens is not None and "head" not in method.drafters.split("+"):
            raise ValueError(f"decoding method {text!r}: k (a chain length) needs the head chain (head, prior+head)")
        if not method.widest_tolerance and not method.scales_with_motion and restricting:
            raise ValueError(
                f"decoding method {text!r}: {', '.join(restricting)} only restrict relaxed acceptance; "
                f"give r (or rl) > 0 or rho > 0 too"
            )
        if action_dim is not None:
            method.check_action_dim(action_dim)
        return method

    def check_action_dim(self, action_dim: int) -> None:
        """Refuses a per-dimension r (or rl) whose length is not ``action_dim`` (ValueError naming the method), and an
        ``action_dim`` that is not a positive int."""
        _check_action_dim(action_dim)
        for key, tolerance in (
            ("r", self.bin_tolerance),
            ("rl", self.later_tolerance),
            ("rho", self.motion_scale),
            ("dev", self.max_deviation),
        ):
            if tolerance is not None:
                given = f"decoding method {self.name!r}: {key}={_format_tolerance(tolerance)}"
                check_tolerance_dims(tolerance, action_dim, given)

    @property
    def name(self) -> str:
        """Canonical name (``prior+tree:r=4``, ``prior+jacobi:r=4/4/4/0,m=1:compile``; ``r=0`` is left out)."""
        options = [f"r={_format_tolerance(self.bin_tolerance)}"] if _widest(self.bin_tolerance) else []
        if self.later_tolerance is not None:
            options += [f"rl={_format_tolerance(self.later_tolerance)}"]
        options += [f"rho={_format_tolerance(self.motion_scale)}"] if self.motion_scale is not None else []
        options += [f"dev={_format_tolerance(self.max_deviation)}"] if self.max_deviation is not None else []
        options += [f"m={self.max_relaxed_per_action}"] if self.max_relaxed_per_action is not None else []
        options += [f"gate={self.confidence_gate:g}"] if self.confidence_gate is not None else []
        options += ["confirm=1"] if self.confirm_tail else []
        options += [f"k={self.num_draft_tokens}"] if self.num_draft_tokens is not None else []
        return self.drafters + (":" + ",".join(options) if options else "") + (f":{COMPILE}" if self.compiled else "")

    @property
    def widest_tolerance(self) -> int:
        """The largest r of any action dimension or chunk step (0: lossless)."""
        return max(_widest(self.bin_tolerance), _widest(self.later_tolerance))

    @property
    def scales_with_motion(self) -> bool:
        """Whether a motion-scaled tolerance (rho > 0 on some dimension) relaxes acceptance."""
        scale = self.motion_scale
        return scale is not None and any(v > 0 for v in ((scale,) if isinstance(scale, (int, float)) else scale))

    def tolerances(self) -> list[int]:
        """Every r the method names (for range checks)."""
        values = []
        for tolerance in (self.bin_tolerance, self.later_tolerance):
            if tolerance is not None:
                values += [tolerance] if isinstance(tolerance, int) else list(tolerance)
        return values

    def rule_kwargs(self, action_dim: int) -> dict:
        """The ``generate`` arguments of its acceptance rule (empty when lossless)."""
        if self.lossless:
            return {}
        tolerance = self.bin_tolerance
        if self.later_tolerance is not None:  # one row per action of the chunk: the first, then the later ones
            tolerance = [_row(self.bin_tolerance, action_dim), _row(self.later_tolerance, action_dim)]
        elif not isinstance(tolerance, int):
            tolerance = list(tolerance)
        kwargs: dict = {"bin_tolerance": tolerance}
        if self.max_relaxed_per_action is not None:
            kwargs["max_relaxed_per_action"] = self.max_relaxed_per_action
        if self.confidence_gate is not None:
            kwargs["confidence_gate"] = self.confidence_gate
        for key, value in (("motion_scale", self.motion_scale), ("max_deviation", self.max_deviation)):
            if value is not None:
                kwargs[key] = value if isinstance(value, (int, float)) else list(value)
        if self.confirm_tail:
            kwargs["confirm_strict_tail"] = True
        return kwargs

    @property
    def uses_draft_head(self) -> bool:
        return any(part in ("head", "tree") for part in self.drafters.split("+"))

    @property
    def lossless(self) -> bool:
        return (self.widest_tolerance == 0 and not self.scales_with_motion) or self.max_relaxed_per_action == 0

    def plan(
        self,
        draft_head: DraftHead | None,
        device_type: str = "cpu",
        tree: DraftTreeConfig | None = None,
        action_dim: int | None = None,
    ) -> DecodingPlan:
        """This method made concrete for a policy ([`DecodingPlan`]: its drafters, acceptance and compilation;
        ``device_type``: the policy's, for ``:compile``; ``tree``: the EAGLE-2 tree of ``tree`` methods, default
        ``DraftTreeConfig()``; ``action_dim``: the policy's, needed when a chunk's later actions have their own
        tolerance).

        Raises:
            ValueError: a method with a head and no ``draft_head``; ``rl`` without ``action_dim``.
        """
        from ..speculative import (
            ComposedDrafter,
            DraftHeadDrafter,
            DraftTreeConfig,
            JacobiDrafter,
            NoDrafter,
            compiled_decoding_kwargs,
        )

        _check_action_dim(action_dim)
        parts = self.drafters.split("+")
        assistant, num_draft_tokens = None, None
        # Jacobi drafts fill a round that nothing else drafts (the first); beside a tree, the tree drafts every round
        jacobi = [JacobiDrafter(fill="tree" not in parts)] if "jacobi" in parts else []
        if jacobi and not self.uses_draft_head:
            assistant = jacobi[0]
        if parts == ["none"]:
            assistant = NoDrafter()
        if self.uses_draft_head:
            if draft_head is None:
                raise ValueError(f"decoding method {self.name!r} needs a draft head (--draft-head)")
            if "tree" in parts:
                head_tree = DraftHeadDrafter(draft_head, tree=tree or DraftTreeConfig())
                assistant = ComposedDrafter(jacobi + [head_tree]) if jacobi else head_tree
            else:
                assistant, num_draft_tokens = draft_head, self.num_draft_tokens
        if self.later_tolerance is not None and action_dim is None and not self.lossless:
            raise ValueError(f"decoding method {self.name!r}: rl (a chunk's later actions) needs the action_dim")
        return DecodingPlan(
            assistant_model=assistant,
            action_prior="prior" in parts,
            num_draft_tokens=num_draft_tokens,
            acceptance=self.rule_kwargs(action_dim or 1),
            compile=compiled_decoding_kwargs(device_type) if self.compiled else {},
        )

    def generate_kwargs(
        self,
        draft_head: DraftHead | None,
        device_type: str = "cpu",
        tree: DraftTreeConfig | None = None,
        action_dim: int | None = None,
    ) -> dict:
        """``predict_action``'s keyword arguments for this method: [`plan`]'s as one dict
        ([`DecodingPlan.predict_kwargs`], what every entry point that takes ``generate`` options accepts)."""
        return self.plan(draft_head, device_type, tree, action_dim).predict_kwargs()


@dataclass(frozen=True)
class DecodingPlan:
    """A decoding method made concrete for one policy ([`DecodingMethod.plan`]), typed: what drafts, how drafts are
    accepted, whether the call compiles. ``predict_action(..., decoding=plan)`` takes it whole.

    Attributes:
        assistant_model: what drafts after the prefill (a [`Drafter`] or a bare [`DraftHead`]), or None (nothing,
            or the action prior alone).
        action_prior: draft each action from the episode's previous actions, verified inside the prefill.
        num_draft_tokens: a bare draft head's chain length, or None (its config's).
        acceptance: the acceptance rule's ``generate`` arguments (``bin_tolerance``, ``motion_scale``, ...; empty:
            lossless).
        compile: ``generate``'s compilation arguments (a static cache and a ``CompileConfig``; empty: eager).
    """

    assistant_model: object = None
    action_prior: bool = False
    num_draft_tokens: int | None = None
    acceptance: Mapping = field(default_factory=dict)
    compile: Mapping = field(default_factory=dict)

    def __post_init__(self):
        """Checks every field once, when the plan is made (as ``predict_action`` checks the same loose options), and
        holds ``acceptance`` / ``compile`` as read-only [`PlanOptions`] (a plan is hashable, equal for equal settings).

        Raises:
            TypeError: a field of the wrong type (a mapping that is not one, an assistant that drafts nothing),
                naming the field and its type.
            ValueError: a setting that is not the field's own (an action length, sampling, a compile setting among
                the acceptance's...) or a bad value, naming it and what is valid.
        """
        from ..speculative import RULE_ARGUMENTS, Drafter, DraftHead, SpeculationConfig

        if self.assistant_model is not None and not isinstance(self.assistant_model, (Drafter, DraftHead)):
            raise TypeError(
                f"DecodingPlan.assistant_model must be a hf_specvla Drafter or DraftHead, or None, got "
                f"{type(self.assistant_model).__name__}"
            )
        if not isinstance(self.action_prior, bool):
            raise TypeError(f"DecodingPlan.action_prior must be True or False, got {self.action_prior!r}")
        fields = {"acceptance": RULE_ARGUMENTS, "compile": COMPILE_SETTINGS}  # each field's own settings
        for name, valid in fields.items():
            _check_plan_options(name, getattr(self, name), valid, fields)
            object.__setattr__(self, name, PlanOptions(getattr(self, name)))
        speculation = SpeculationConfig(
            drafter=self.assistant_model, num_draft_tokens=self.num_draft_tokens, **self.acceptance
        )  # (the values' own checks)
        object.__setattr__(self, "_speculation", speculation)
        cache = self.compile.get("cache_implementation")
        if cache is not None and not isinstance(cache, str):
            raise TypeError(
                f"DecodingPlan.compile's cache_implementation must be a transformers cache name "
                f"('static'), got {type(cache).__name__}"
            )
        compile_config = self.compile.get("compile_config")
        if compile_config is not None:
            from transformers import CompileConfig

            if not isinstance(compile_config, CompileConfig):
                raise TypeError(
                    f"DecodingPlan.compile's compile_config must be a transformers CompileConfig, got "
                    f"{type(compile_config).__name__}"
                )

    @property
    def speculation(self):
        """The plan's speculation as the engine takes it whole (``generate(speculation=...)``): a
        ``SpeculationConfig`` of its assistant, chain length and acceptance, made (and checked) with the plan."""
        return self._speculation

    @property
    def speculates(self) -> bool:
        """Whether anything drafts (greedy decoding otherwise)."""
        return self.assistant_model is not None or self.action_prior

    def predict_kwargs(self) -> dict:
        """The plan as ``predict_action``'s loose keyword arguments (``assistant_model=``, ``action_prior=``, the
        acceptance and compilation arguments)."""
        kwargs: dict = dict(self.compile)
        if self.assistant_model is not None:
            kwargs["assistant_model"] = self.assistant_model
        if self.num_draft_tokens is not None:
            kwargs["num_draft_tokens"] = self.num_draft_tokens
        if self.action_prior:
            kwargs["action_prior"] = True
        return {**kwargs, **self.acceptance}


#: the compilation settings a plan's ``compile`` holds (``speculative.compiled_decoding_kwargs``'s)
COMPILE_SETTINGS = ("cache_implementation", "compile_config")
#: why a setting that is no plan field's own is not: what a user who put it there meant
_NOT_A_PLAN_SETTING = {
    **dict.fromkeys(
        ("max_new_tokens", "min_new_tokens", "max_length", "min_length"),
        "the action's length is the policy's own (its config's action tokens)",
    ),
    **dict.fromkeys(
        ("do_sample", "temperature", "top_k", "top_p", "min_p", "num_beams"),
        "how tokens are chosen is generate's: pass predict_action(generation_config=GenerationConfig("
        "do_sample=True, ...)); a plan's acceptance only says which drafts count",
    ),
}


class PlanOptions(Mapping):
    """A [`DecodingPlan`]'s ``acceptance`` or ``compile`` settings: a read-only mapping (``**plan.acceptance`` works),
    hashable, equal for equal settings; lists held as given (a folder's record reads them)."""

    def __init__(self, options: Mapping):
        self._options = {
            name: copy.deepcopy(value) if isinstance(value, (list, dict)) else value for name, value in options.items()
        }

    def __getitem__(self, name: str):
        return self._options[name]

    def __iter__(self):
        return iter(self._options)

    def __len__(self) -> int:
        return len(self._options)

    def __hash__(self) -> int:
        from ..speculative import hashable

        return hash(tuple(sorted((name, hashable(value)) for name, value in self._options.items())))

    def __repr__(self) -> str:
        return repr(self._options)


def _check_plan_options(field_name: str, options, valid: tuple[str, ...], fields: dict[str, tuple[str, ...]]) -> None:
    """Refuses a plan field (``acceptance`` / ``compile``) that is not a mapping of its own settings (``valid``;
    ``fields``: every field's, to say where a misplaced one belongs).

    Raises:
        TypeError: not a mapping (None, a list, a string), naming the field and its type.
        ValueError: a setting that is not among ``valid``, naming it, the field and what is valid.
    """
    if not isinstance(options, Mapping):
        raise TypeError(
            f"DecodingPlan.{field_name} must be a mapping of its settings ({', '.join(valid)}), got "
            f"{type(options).__name__} {options!r}"
        )
    for name in options:
        if name in valid:
            continue
        other = next((field for field, settings in fields.items() if name in settings), None)
        why = f"it belongs in DecodingPlan.{other}" if other else _NOT_A_PLAN_SETTING.get(name, "")
        raise ValueError(
            f"DecodingPlan.{field_name} holds {name!r}, which is not one of its settings (valid: "
            f"{', '.join(valid)}){'; ' + why if why else ''}"
        )


def check_decoding_plan(decoding, given_to: str) -> None:
    """Raises a TypeError naming ``decoding``'s type unless it is None or a [`DecodingPlan`]."""
    if decoding is not None and not isinstance(decoding, DecodingPlan):
        raise TypeError(
            f"{given_to} got decoding={type(decoding).__name__}: decoding= takes a DecodingPlan "
            f"(DecodingMethod.parse('exact').plan(draft_head=None)) or None; loose generate options go as keywords"
        )


def _parse_option(text: str, key: str, value: str):
    """One option's value: a tolerance (r, rl), numbers (rho, dev), an int (m, k), a probability (gate) or a flag
    (confirm)."""
    if key in ("r", "rl"):
        return _parse_tolerance(text, value, key)
    if key in ("rho", "dev"):
        parts = value.split("/")
        if not all(_NUMBER.fullmatch(p.strip()) for p in parts):
            raise ValueError(
                f"decoding method {text!r}: bad option '{key}={value}'; {key} is {METHOD_KEYS[key]} "
                f"(numbers >= 0 in digits 0-9, e.g. {key}=0.1 or {key}=0.1/0.1/0.1/0)"
            )
        numbers = [float(p) for p in parts]
        return numbers[0] if len(numbers) == 1 else tuple(numbers)
    if key == "confirm":
        if value not in ("0", "1"):
            raise ValueError(f"decoding method {text!r}: confirm is 0 or 1 ({METHOD_KEYS[key]}), got confirm={value}")
        return int(value)
    if key == "gate":
        gate = float(value) if _PROBABILITY.fullmatch(value) else -1.0
        if not 0 < gate <= 1:
            raise ValueError(
                f"decoding method {text!r}: gate must be a probability in (0, 1] written in digits 0-9 "
                f"({METHOD_KEYS[key]}), got gate={value}"
            )
        return gate
    return _parse_integer(text, key, value)


def _row(tolerance: Tolerance, action_dim: int) -> list[int]:
    """A tolerance as one int per action dimension."""
    return [tolerance] * action_dim if isinstance(tolerance, int) else list(tolerance)


# ----------------------------------------------------------------------------- presets
#: what each action dimension is, for the action sizes a preset can resolve to: this project's Meta-World hand
#: (x y z gripper), OpenVLA's end-effector delta (x y z roll pitch yaw gripper) and an end-effector pose whose
#: rotation is a quaternion (x y z qx qy qz qw gripper). A joint-space action of one of these sizes (7 joints, 7 joints
#: + gripper) would be misread: give such a policy an explicit per-dimension r instead of a relaxed preset.
ACTION_LAYOUTS = {
    4: ("x", "y", "z", "gripper"),
    7: ("x", "y", "z", "roll", "pitch", "yaw", "gripper"),
    8: ("x", "y", "z", "qx", "qy", "qz", "qw", "gripper"),
}
POSITION_DIMENSIONS, GRIPPER_DIMENSIONS = ("x", "y", "z"), ("gripper",)  # every other named dimension is a rotation


def _layout_words(action_dim: int) -> str:
    """`` (x y z gripper)`` for a known layout, else nothing (for messages)."""
    return f" ({' '.join(ACTION_LAYOUTS[action_dim])})" if action_dim in ACTION_LAYOUTS else ""


@dataclass(frozen=True)
class Preset:
    """A named decoding setting, defined by what it relaxes and resolved per policy ([`resolve`]).

    Args:
        name: what users write (``fast``).
        drafters / drafters_with_head: what drafts for a policy without / with a draft head.
        head_drafters: what drafts with the draft head in the same setting: a server given a head measures it
            beside ``drafters_with_head`` and decodes each batch size with the faster ([`serving_methods`]).
        position_tolerance: r on the position dimensions (x y z).
        rotation_tolerance: r on the rotation dimensions (roll pitch yaw, or a quaternion's four).
        gripper_tolerance: r on the gripper.
        confidence_gate: relax only where the target's top-1 probability is below this (None: wherever r allows).
        confirm_strict_tail: keep a relaxed token only when its action's strict dimensions after it (the gripper) are
            drafted and confirmed in the same verification (``confirm=1``).
        compiled: decode on a static cache with compiled forwards (``:compile``).
    """

    name: str
    drafters: str
    drafters_with_head: str
    head_drafters: str = "prior+jacobi+tree"
    position_tolerance: int = 0
    rotation_tolerance: int = 0
    gripper_tolerance: int = 0
    confidence_gate: float | None = None
    confirm_strict_tail: bool = False
    compiled: bool = True

    @property
    def lossless(self) -> bool:
        return not (self.position_tolerance or self.rotation_tolerance or self.gripper_tolerance)

    def tolerance(self, action_dim: int) -> Tolerance:
        """r per dimension of an ``action_dim``-dimensional action ([`ACTION_LAYOUTS`]); one int when all agree.

        Raises:
            ValueError: a relaxed preset and an action size with no known layout, naming the rule to spell out.
        """
        if self.lossless:
            return 0
        layout = ACTION_LAYOUTS.get(action_dim)
        if layout is None:
            known = "; ".join(f"{size}: {' '.join(dims)}" for size, dims in ACTION_LAYOUTS.items())
            guess = tuple(self.position_tolerance if i < 3 else 0 for i in range(action_dim))  # x y z first, a guess
            spelled = DecodingMethod(
                self.drafters,
                guess,
                compiled=self.compiled,
                confidence_gate=self.confidence_gate,
                confirm_tail=self.confirm_strict_tail,
            )
            raise ValueError(
                f"preset {self.name!r} relaxes by kind of action dimension, but the policy's {action_dim}-dimensional "
                f"actions have no known layout (known: {known}); spell the method out with one r per dimension, "
                f"e.g. {spelled.name}"
            )
        row = tuple(
            self.position_tolerance
            if dim in POSITION_DIMENSIONS
            else self.gripper_tolerance
            if dim in GRIPPER_DIMENSIONS
            else self.rotation_tolerance
            for dim in layout
        )
        return row[0] if len(set(row)) == 1 else row

    def resolve(self, draft_head_given: bool = False, action_dim: int | None = None) -> DecodingMethod:
        """The [`DecodingMethod`] for a policy with (``draft_head_given``) or without a draft head and with
        ``action_dim``-dimensional actions (None: this project's policies', ``VLAPolicyConfig.action_dim``).

        Raises:
            ValueError: ``action_dim`` not a positive int, or a relaxed preset and a layout it cannot resolve to.
        """
        return self._method(self.drafters_with_head if draft_head_given else self.drafters, action_dim)

    def candidates(self, draft_head_given: bool = False, action_dim: int | None = None) -> tuple[DecodingMethod, ...]:
        """The methods a server measures for this preset: [`resolve`]'s, and with a draft head also the head's
        composition in the same setting (``head_drafters``), the faster of them chosen per batch size.

        Raises:
            ValueError: as [`resolve`].
        """
        resolved = self.resolve(draft_head_given, action_dim)
        if not draft_head_given or self.head_drafters == resolved.drafters:
            return (resolved,)
        return resolved, self._method(self.head_drafters, action_dim)

    def _method(self, drafters: str, action_dim: int | None) -> DecodingMethod:
        _check_action_dim(action_dim)
        action_dim = VLAPolicyConfig.action_dim if action_dim is None else action_dim
        return DecodingMethod(
            drafters,
            self.tolerance(action_dim),
            compiled=self.compiled,
            confidence_gate=None if self.lossless else self.confidence_gate,
            confirm_tail=self.confirm_strict_tail and not self.lossless,
        )


#: the presets, chosen by the paired comparisons in the results record (docs/results/record/metaworld-policies.md):
#: ``exact`` is greedy's tokens on every episode; ``fast`` relaxes x y z by 4 bins where the target is unsure, with the
#: gripper confirmed after a relaxed token (the evidence for each choice, and what ``fast`` costs in fidelity on policy
#: v3, is in the record)
PRESETS = {
    preset.name: preset
    for preset in (
        Preset("exact", "prior+jacobi", "prior+jacobi"),
        Preset(
            "fast", "prior+jacobi", "prior+jacobi", position_tolerance=4, confidence_gate=0.5, confirm_strict_tail=True
        ),
    )
}


def resolve_preset(name: str, draft_head_given: bool, action_dim: int | None = None) -> str | None:
    """The method string a preset (``exact``, ``fast``) names for a policy with or without a draft head and with
    ``action_dim``-dimensional actions (see [`Preset.resolve`]); None for a method string that is not a preset."""
    preset = PRESETS.get(name.strip())
    return None if preset is None else preset.resolve(draft_head_given, action_dim).name


def serving_methods(
    text: str | tuple[str, ...] | list[str], draft_head_given: bool = False, action_dim: int | None = None
) -> tuple[DecodingMethod, ...]:
    """The speculative methods a policy server measures and picks from per batch size (``ServeConfig.method``): one
    method or preset, or several; a preset given a draft head stands for its methods with and without the head
    ([`Preset.candidates`]: ``exact`` -> ``prior+jacobi:compile`` and ``prior+jacobi+tree:compile``). ``greedy`` /
    ``greedy:compile`` alone: a greedy-only server (the one method returned is greedy).

    Raises:
        ValueError: an unknown method (as [`DecodingMethod.parse`]); none; greedy beside speculative methods; compiled
            and eager methods mixed (the greedy baseline they are measured against is one of the two).
    """
    texts = [text] if isinstance(text, str) else list(text)
    if not texts or not all(isinstance(t, str) for t in texts):
        raise ValueError(f"method must be a decoding method or preset, or a list of them, got {text!r}")
    methods: list[DecodingMethod] = []
    for one in texts:
        preset = PRESETS.get(one.strip())
        found = (
            preset.candidates(draft_head_given, action_dim)
            if preset is not None
            else (DecodingMethod.parse(one, draft_head_given, action_dim),)
        )
        methods += [m for m in found if m not in methods]
    if len(methods) > 1 and any(m.drafters == "greedy" for m in methods):
        raise ValueError(
            f"methods {[m.name for m in methods]}: greedy is the baseline every method is measured "
            f"against; list speculative methods only (or greedy alone: a greedy-only server)"
        )
    if len({m.compiled for m in methods}) > 1:
        raise ValueError(
            f"methods {[m.name for m in methods]} mix compiled and eager decoding: the greedy baseline "
            f"they are measured against is one or the other; add or drop :{COMPILE} on all"
        )
    return tuple(methods)


GREEDY = DecodingMethod()
#: transformers' own compiled greedy decoding (static cache + CompileConfig): the baseline a user who wants speed has
COMPILED_GREEDY = DecodingMethod(compiled=True)
#: greedy decoding run by the engine, compiled (``none:compile``: one token a verification, its prefill compiled too):
#: the fastest greedy here (policy v3 in a server's decode step, 1 thread: 1.21x / 1.10x / 1.08x transformers'
#: compiled greedy at 1 / 4 / 8 rows, the same actions), and its graphs are a compiled speculative method's own
ENGINE_GREEDY = DecodingMethod(drafters="none", compiled=True)
