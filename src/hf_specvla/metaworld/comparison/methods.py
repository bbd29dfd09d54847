"""What a comparison runs: [`CompareConfig`] and the default methods. The decoding methods themselves (names, options,
presets) live in ``policies.decoding_methods``, shared by every command that decodes; they are re-exported here."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ..._validation import check_ranges
from ...policies.decoding_methods import (  # noqa: F401 (re-exported: this module's names before the move)
    ACTION_LAYOUTS,
    COMPILE,
    COMPILED_GREEDY,
    DRAFTER_CHOICES,
    GREEDY,
    METHOD_KEYS,
    ORACLE,
    PRESETS,
    DecodingMethod,
    Preset,
    Tolerance,
    check_tolerance_dims,
    resolve_preset,
)
from ..env import EnvConfig, resolve_tasks
from ..seeds import EVAL_SEED_START

if TYPE_CHECKING:
    from ...speculative import DraftTreeConfig

logger = logging.getLogger(__name__)

DEFAULT_METHODS = (
    "greedy",
    "head",
    "tree",
    "tree:r=4",
    "prior",
    "prior:r=2",
    "prior:r=4",
    "prior:r=8",
    "prior+tree:r=4",
)


def parse_methods(
    names: list[str], draft_head_given: bool = False, action_dim: int | None = None
) -> list[DecodingMethod]:
    """Parsed, de-duplicated methods (presets resolved for ``action_dim``-dimensional actions, see
    [`DecodingMethod.parse`]), greedy first (added when missing: it is the baseline)."""
    methods = [GREEDY]
    for name in names:
        method = DecodingMethod.parse(name, draft_head_given, action_dim, oracle=True)
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
        draft_head_given: whether a draft head comes with the policy (the presets ``exact`` / ``fast`` resolve to
            its methods).
        action_dim: the policy's action dimensions: the presets resolve to its layout and a per-dimension r of
            another length is refused (None: presets resolve to this project's policies' layout, x y z gripper).
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
    draft_head_given: bool = False  # presets resolve to the methods of a policy with a draft head
    action_dim: int | None = None  # presets resolve to its layout
    #: the size of greedy's action (|value| per dimension, in the policy's units) from which a motion counts as large in
    #: the deviation by phase (a summary setting: episodes do not depend on it); Meta-World's hand moves <= 1 per step
    motion_threshold: float = 0.25

    def __post_init__(self):
        self.tasks = resolve_tasks(self.tasks)
        names = ("episodes_per_task", "workers", "threads", "seed_start", "max_episode_steps")
        check_ranges(self, at_least_one=names[:3] + names[4:], non_negative=names[3:4], integers=names)
        if self.action_dim is not None:
            check_ranges(self, at_least_one=("action_dim",), integers=("action_dim",))
        threshold = self.motion_threshold
        if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not 0 < threshold < float("inf"):
            raise ValueError(
                f"motion_threshold must be a finite number > 0 (the size of greedy's action, in the "
                f"policy's units, from which a motion is large), got {threshold!r}"
            )
        for name in self.methods:
            resolved = resolve_preset(name, self.draft_head_given, self.action_dim)
            if resolved is not None:
                logger.info("preset %s = %s", name.strip(), resolved)
        self.methods = [m.name for m in parse_methods(list(self.methods), self.draft_head_given, self.action_dim)]
        self.tree_config()  # refuses bad tree settings now

    def tree_config(self) -> DraftTreeConfig:
        """The EAGLE-2 tree of the ``tree`` methods (raises ValueError naming a bad setting)."""
        from ...speculative import DraftTreeConfig

        settings = {"top_k": self.tree_top_k, "depth": self.tree_depth, "total_tokens": self.tree_total_tokens}
        return DraftTreeConfig(**{name: value for name, value in settings.items() if value is not None})

    def decoding_methods(self) -> list[DecodingMethod]:
        return [DecodingMethod.parse(name, oracle=True) for name in self.methods]

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
