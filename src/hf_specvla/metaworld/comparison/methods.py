"""Decoding methods of a comparison: ``<drafters>[:r=<bin tolerance>][,k=<chain length>][:compile]`` parsed, named
and turned into ``predict_action`` options, and [`CompareConfig`], what a comparison runs. No torch at import: the
CLI reads the choices and defaults here.

Drafters, joined by ``+``: ``head`` (the draft head's chain), ``tree`` (its EAGLE-2 tree), ``prior`` (the episode's
previous actions), ``jacobi`` (the target's own guesses past a rejection, [`JacobiDrafter`]).

``:compile`` decodes on a static cache with transformers' ``CompileConfig``: ``greedy:compile`` is transformers' own
compiled greedy decoding (the baseline a user who wants speed has), ``tree:compile`` / ``prior+tree:r=4:compile``
verify drafts through the same compiled model call (``speculative.compiled``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from ..._validation import check_ranges
from ..env import EnvConfig, resolve_tasks
from ..seeds import EVAL_SEED_START

if TYPE_CHECKING:
    from ...speculative import DraftHead, DraftTreeConfig

DRAFTER_CHOICES = ("greedy", "head", "tree", "prior", "prior+head", "prior+tree", "jacobi", "prior+jacobi",
                   "jacobi+tree", "prior+jacobi+tree")  # fmt: skip
METHOD_KEYS = {"r": "bin tolerance (relaxed acceptance; 0 = lossless)", "k": "draft-head chain length (head only)"}
#: the option word that compiles a method (static cache + transformers' CompileConfig)
COMPILE = "compile"
DEFAULT_METHODS = ("greedy", "head", "tree", "tree:r=4", "prior", "prior:r=2", "prior:r=4", "prior:r=8",
                   "prior+tree:r=4")  # fmt: skip


# ----------------------------------------------------------------------------- methods
@dataclass(frozen=True)
class DecodingMethod:
    """One decoding method of a comparison (see module docstring for the names)."""

    drafters: str = "greedy"
    bin_tolerance: int = 0
    num_draft_tokens: int | None = None
    compiled: bool = False

    @classmethod
    def parse(cls, text: str) -> DecodingMethod:
        """``"prior+tree:r=4"`` -> DecodingMethod("prior+tree", 4).

        Raises:
            ValueError: naming the bad part and listing what is valid.
        """
        valid = (f"valid: {', '.join(DRAFTER_CHOICES)}, optionally followed by :r=<int>[,k=<int>] and/or :compile "
                 f"(e.g. prior+tree:r=4, greedy:compile, prior+tree:r=4:compile)")  # fmt: skip
        drafters, _, options = text.strip().partition(":")
        if drafters not in DRAFTER_CHOICES:
            raise ValueError(f"unknown decoding method {text!r}: {drafters!r} is not a drafter; {valid}")
        values: dict[str, int] = {}
        parts = options.replace(":", ",").split(",")
        compiled = COMPILE in parts
        if parts.count(COMPILE) > 1:
            raise ValueError(f"decoding method {text!r}: {COMPILE!r} given twice; {valid}")
        for option in filter(None, (p for p in parts if p != COMPILE)):
            key, _, value = option.partition("=")
            if key in METHOD_KEYS and value.strip().lstrip("-").isdigit() and int(value) < 0:
                raise ValueError(f"decoding method {text!r}: {key} must be an integer >= 0 ({METHOD_KEYS[key]}), "
                                 f"got {int(value)}")  # fmt: skip
            if key not in METHOD_KEYS or not value.strip().isdigit():
                raise ValueError(
                    f"decoding method {text!r}: bad option {option!r}; options are "
                    + ", ".join(f"{k}=<int> ({v})" for k, v in METHOD_KEYS.items())
                )
            values[key] = int(value)
        if options and not values and not compiled:
            raise ValueError(f"decoding method {text!r}: empty options after ':'; {valid}")
        method = cls(drafters, values.get("r", 0), values.get("k"), compiled)
        if method.drafters == "greedy" and (method.bin_tolerance or method.num_draft_tokens):
            raise ValueError(f"decoding method {text!r}: greedy drafts nothing, so it takes no r or k")
        if method.num_draft_tokens is not None and "head" not in method.drafters.split("+"):
            raise ValueError(f"decoding method {text!r}: k (a chain length) needs the head chain (head, prior+head)")
        if method.num_draft_tokens == 0:
            raise ValueError(f"decoding method {text!r}: k must be >= 1")
        return method

    @property
    def name(self) -> str:
        """Canonical name (``prior+tree:r=4``, ``prior+tree:r=4:compile``; ``r=0`` is left out)."""
        options = [f"r={self.bin_tolerance}"] if self.bin_tolerance else []
        options += [f"k={self.num_draft_tokens}"] if self.num_draft_tokens is not None else []
        return self.drafters + (":" + ",".join(options) if options else "") + (f":{COMPILE}" if self.compiled else "")

    @property
    def uses_draft_head(self) -> bool:
        return any(part in ("head", "tree") for part in self.drafters.split("+"))

    @property
    def lossless(self) -> bool:
        return self.bin_tolerance == 0

    def generate_kwargs(
        self, draft_head: DraftHead | None, device_type: str = "cpu", tree: DraftTreeConfig | None = None
    ) -> dict:
        """``predict_action`` options for this method (``device_type``: the policy's, for ``:compile``; ``tree``: the
        EAGLE-2 tree of ``tree`` methods, default ``DraftTreeConfig()``)."""
        from ...speculative import (
            ComposedDrafter,
            DraftHeadDrafter,
            DraftTreeConfig,
            JacobiDrafter,
            compiled_decoding_kwargs,
        )

        parts = self.drafters.split("+")
        kwargs: dict = compiled_decoding_kwargs(device_type) if self.compiled else {}
        # Jacobi drafts fill a round that nothing else drafts (the first); beside a tree, the tree drafts every round
        jacobi = [JacobiDrafter(fill="tree" not in parts)] if "jacobi" in parts else []
        if jacobi and not self.uses_draft_head:
            kwargs["assistant_model"] = jacobi[0]
        if self.uses_draft_head:
            if draft_head is None:
                raise ValueError(f"decoding method {self.name!r} needs a draft head (--draft-head)")
            if "tree" in parts:
                head_tree = DraftHeadDrafter(draft_head, tree=tree or DraftTreeConfig())
                kwargs["assistant_model"] = ComposedDrafter(jacobi + [head_tree]) if jacobi else head_tree
            else:
                kwargs["assistant_model"] = draft_head
                if self.num_draft_tokens is not None:
                    kwargs["num_draft_tokens"] = self.num_draft_tokens
        if "prior" in parts:
            kwargs["action_prior"] = True
        if self.bin_tolerance:
            kwargs["bin_tolerance"] = self.bin_tolerance
        return kwargs


GREEDY = DecodingMethod()
#: transformers' own compiled greedy decoding (static cache + CompileConfig): the baseline a user who wants speed has
COMPILED_GREEDY = DecodingMethod(compiled=True)


def parse_methods(names: list[str]) -> list[DecodingMethod]:
    """Parsed, de-duplicated methods, greedy first (added when missing: it is the baseline)."""
    methods = [GREEDY]
    for name in names:
        method = DecodingMethod.parse(name)
        if method not in methods:
            methods.append(method)
    return methods


@dataclass
class CompareConfig:
    """What a comparison runs.

    Args:
        tasks: Meta-World tasks (names or suites).
        episodes_per_task: seeds per task (``seed_start``, +1, ...); every method runs every seed.
        methods: method names (see module docstring); greedy is added first when missing.
        seed_start: first seed (evaluation seeds start at 100000; the second fidelity range at 200000).
        max_episode_steps: step limit of an episode.
        workers: processes the seeds are split between.
        threads: torch CPU threads per worker.
        order_seed: seeds the random method order of every seed.
        tree_top_k / tree_depth / tree_total_tokens: the EAGLE-2 tree of the ``tree`` methods (None:
            ``DraftTreeConfig``'s default).
    """

    tasks: str | list[str] = "MT10"
    episodes_per_task: int = 20
    methods: list[str] | tuple[str, ...] = DEFAULT_METHODS
    seed_start: int = EVAL_SEED_START
    max_episode_steps: int = EnvConfig.max_episode_steps
    workers: int = 1
    threads: int = 1
    order_seed: int = 0
    tree_top_k: int | None = None
    tree_depth: int | None = None
    tree_total_tokens: int | None = None

    def __post_init__(self):
        self.tasks = resolve_tasks(self.tasks)
        names = ("episodes_per_task", "workers", "threads", "seed_start", "max_episode_steps")
        check_ranges(self, at_least_one=names[:3] + names[4:], non_negative=names[3:4], integers=names)
        self.methods = [m.name for m in parse_methods(list(self.methods))]
        self.tree_config()  # refuses bad tree settings now

    def tree_config(self) -> DraftTreeConfig:
        """The EAGLE-2 tree of the ``tree`` methods (raises ValueError naming a bad setting)."""
        from ...speculative import DraftTreeConfig

        settings = {"top_k": self.tree_top_k, "depth": self.tree_depth, "total_tokens": self.tree_total_tokens}
        return DraftTreeConfig(**{name: value for name, value in settings.items() if value is not None})

    def decoding_methods(self) -> list[DecodingMethod]:
        return [DecodingMethod.parse(name) for name in self.methods]

    def draft_head_methods(self) -> list[str]:
        """The methods that draft with a draft head (head, tree, prior+head, prior+tree)."""
        return [method.name for method in self.decoding_methods() if method.uses_draft_head]

    def check_draft_head_given(self, given: bool) -> None:
        """Raises ValueError when a method drafts with a draft head and none is given."""
        if self.draft_head_methods() and not given:
            raise ValueError(f"methods {self.draft_head_methods()} draft with a draft head: pass --draft-head <folder>")

    def pairs(self) -> list[tuple[str, int]]:
        """Every (task, seed), seed-major (each task's first seed, then each task's second, ...): a run stopped
        part-way has covered every task alike, and workers that take every n-th pair share the load."""
        return [(task, self.seed_start + i) for i in range(self.episodes_per_task) for task in self.tasks]
