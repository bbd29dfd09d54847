"""The decode step: one batched ``predict_action`` over a bucket's rows, each robot's drafts its own
([`DecodeStep.run`]), each row handed back the moment it is decoded; and what its compiled graphs fix: the prompt
lengths served (prompt tiers) and the greedy baseline's static caches. No HTTP, no sessions, no choice of mode here.

**Rows answered when done.** A speculative call's rows need their own numbers of target forwards (the batch runs as
many as its slowest row), and the engine calls ``on_row_finished(row, new_tokens, stats)`` the moment a row stops:
the step turns the row's tokens into its action and the robot's new draft state there and hands them on (with the
row's target forwards, from its statistics), so a robot's reply leaves while the rest of its batch decodes. The idle
rows that fill a bucket copy the first row, its
drafts included, so they never outlast the robots' rows. (A new request cannot take a finished row's place at the
next round: the engine's call holds the rows it started with.)

**The greedy baseline.** Mode 0 of a compiled speculative method is the engine's own compiled greedy decoding
(``none:compile``: no drafts, one token a verification, through the same decoder session and compiled graphs as the
method: its prefill and its width-0 round), the fastest greedy here (policy v3, one thread, in this step:
1.21x / 1.10x / 1.08x transformers' compiled greedy at 1 / 4 / 8 rows, the same actions), with no graphs of its own
to compile or load at start-up. A greedy-only server (``greedy:compile``) runs transformers' compiled greedy, on
the cache below; an eager method's baseline is transformers' eager greedy.

**A greedy-only server's cache.** transformers' compiled greedy decoding sizes its static cache to each call's prompt
length plus the new tokens, so every new prompt length (another instruction, another batch's widest prompt) compiles
a new graph mid-traffic. The step passes it the engine's reusable static cache per bucket and prompt tier instead
(``speculative.reusable_static_cache``), with room for the tier's longest prompt (emptied before each call): one
graph per bucket and tier, the same tokens. The recompile limit is the engine's too: ``generate`` raises it, in the
decoding thread, from what dynamo holds for the model.

**Prompt tiers: no compile under load.** A compiled method's graphs hold its static caches' slot counts, and those
grow with the batch's widest prompt (64 slots at a time: the target's cache with room for a draft tree, a draft
head's own). A prompt that needs more slots than any warmed-up call compiled new graphs mid-traffic: minutes on a
CPU, every robot waiting. So the prompt lengths served are bounded: [`DecodeStep.prompt_tiers`] groups the lengths
from this policy's shortest prompt up to ``max_prompt_tokens`` (default: as far as the shortest prompt's verification
cache stretches) by the slot counts they need; the service's warm-up compiles every tier and refuses a longer prompt
(422, field ``instruction``) before any forward.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from typing import TYPE_CHECKING

import numpy as np

from ..policies.decoding_methods import COMPILED_GREEDY, ENGINE_GREEDY, GREEDY, DecodingPlan, serving_methods
from .config import ServeConfig
from .protocol import ActRequest

if TYPE_CHECKING:
    from ..policies import ActionPolicy

logger = logging.getLogger(__name__)

#: the default prompt limit leaves the instruction at least this many tokens (MT50's longest takes 13 on policy v3;
#: on v3 the shortest prompt's verification cache leaves 54, so the default is that one tier)
MIN_INSTRUCTION_TOKENS = 32


@dataclass
class DecodedRow:
    """One robot's row of a decoded batch.

    Attributes:
        action: the un-normalised action, float64 ``[action_dim]`` (``[chunk, action_dim]`` for a chunked policy).
        history: the robot's previous actions after this one (token ids, oldest first): its next drafts.
        target_forwards: target forwards the row took part in.
        done: ``time.perf_counter()`` when the row was handed on.
        batch_forwards: target forwards the batch ran (a row handed on before the call returned: those run until
            it finished, its own).
        early: whether the row was handed on before the call returned.
    """

    action: np.ndarray
    history: list[list[int]]
    target_forwards: int
    done: float
    batch_forwards: int
    early: bool = False


@dataclass
class DecodedBatch:
    """A batched call: ``decode_ms`` the whole call, ``batch_forwards`` the target forwards it ran, ``rows`` the
    rows not handed on before it returned (request index -> row)."""

    decode_ms: float
    batch_forwards: int
    rows: dict[int, DecodedRow]


class DecodeStep:
    """Decodes batches of requests for one policy in any of its modes: the greedy baseline (mode 0) or one of the
    speculative methods (modes 1.., ``serving_methods``: e.g. ``exact`` and, given a draft head, ``exact``'s
    composition with the head).

    Args:
        policy: the loaded policy.
        config: [`ServeConfig`] (its method, buckets and ``max_prompt_tokens`` are read).
        draft_head: for methods that draft with a head.

    Raises:
        ValueError: an unknown method; ``max_prompt_tokens`` shorter than this policy's shortest prompt.
    """

    def __init__(self, policy: ActionPolicy, config: ServeConfig, draft_head=None):
        self.policy, self.config = policy, config
        layout = policy.config
        methods = serving_methods(config.method, draft_head is not None, layout.action_dim)
        device = policy.model.device.type
        #: the first method (the only one without a draft head, unless several were given)
        self.method = methods[0]
        #: whether the method speculates at all (``greedy`` / ``greedy:compile`` do not)
        self.speculates = self.method.drafters != "greedy"
        #: mode 0: a compiled speculative method's is the engine's own compiled greedy (the fastest greedy, on the
        #: method's own graphs); a greedy-only server's is its method; an eager method's, transformers' greedy
        if self.method.compiled:
            self.baseline = ENGINE_GREEDY if self.speculates else COMPILED_GREEDY
        else:
            self.baseline = GREEDY
        #: the speculative methods, modes 1, 2, ... (empty for a greedy-only server)
        self.methods = methods if self.speculates else ()
        #: mode -> its typed plan (what drafts, the acceptance, the compilation), made once, passed whole
        self._plans = {0: self.baseline.plan(None, device, action_dim=layout.action_dim)}
        for mode, method in enumerate(self.methods, 1):
            self._plans[mode] = method.plan(draft_head, device, action_dim=layout.action_dim)
        self.shortest_prompt = len(policy.prompt_ids("", self._zero_state()))  # image, state and the prompt's words
        self.prompt_tiers = self._prompt_tiers(draft_head)

    @property
    def modes(self) -> tuple[int, ...]:
        """Every mode: 0 the greedy baseline, then one per speculative method."""
        return tuple(range(1 + len(self.methods)))

    def name(self, mode: int) -> str:
        """The decoding a mode runs: the baseline's name (mode 0), or the method's."""
        return self.methods[mode - 1].name if mode else self.baseline.name

    @property
    def max_prompt_tokens(self) -> int | None:
        """The longest prompt served, in tokens (None: no limit beyond the instruction's characters: eager)."""
        return self.prompt_tiers[-1][1] if self.prompt_tiers else None

    def run(
        self,
        requests: list[ActRequest],
        histories: list[list[list[int]]],
        bucket: int,
        mode: int,
        on_row: Callable[[int, DecodedRow], None] | None = None,
    ) -> DecodedBatch:
        """Decodes ``requests`` (each with its robot's ``histories``, left as they were) in one call of ``bucket``
        rows in ``mode`` (0: the greedy baseline, else that speculative method). ``on_row(i, row)`` is called (in
        this thread) for each request's row the engine hands on before the call returns, all but the last of the
        robots' rows to finish; the batch returned holds the rest.

        Raises:
            ValueError: more requests than ``bucket``, or none.
        """
        rows = len(requests)
        if not 0 < rows <= bucket:
            raise ValueError(f"a batch of {bucket} rows decodes 1..{bucket} requests, got {rows}")
        padded = requests + [requests[0]] * (bucket - rows)  # idle rows: the first row's copies, its drafts too
        memories = [[list(a) for a in history] for history in histories]  # predict_action updates them in place
        memories += [[list(a) for a in histories[0]] for _ in range(bucket - rows)]
        shapes = {r.image.shape for r in padded}
        images = np.stack([r.image for r in padded]) if len(shapes) == 1 else [r.image for r in padded]
        keys = [r.unnorm_key for r in padded]  # each row's dataset (None: the policy's one set of statistics)
        states = np.stack([r.state for r in padded]) if self.policy.config.use_state else None
        instructions = [r.instruction for r in padded]
        plan, kwargs = (self._plans[mode], {}) if mode else self._greedy_plan(bucket, instructions, states)
        early: set[int] = set()
        if mode and on_row is not None:
            from ..speculative import remember_actions

            def finished(row: int, new_tokens, stats) -> None:  # the engine's on_row_finished, in finishing order
                if row < rows and len(early) < rows - 1:  # the last robot row comes back with the batch
                    early.add(row)
                    action, action_ids = self.policy.actions_from_generated(new_tokens[None], [keys[row]])
                    history = [list(a) for a in histories[row]]
                    remember_actions(history, action_ids[0], self.policy.action_layout)
                    forwards = stats.num_target_forwards  # the batch's forwards so far: the row took part in each
                    on_row(row, DecodedRow(action[0], history, forwards, time.perf_counter(), forwards, early=True))

            kwargs = {**kwargs, "on_row_finished": finished}
        started = time.perf_counter()
        if self.policy.unnorm_keys:
            kwargs = {**kwargs, "unnorm_key": keys}
        actions, output = self.policy.predict_action(
            images, instructions, states, return_output=True, previous_action_ids=memories, decoding=plan, **kwargs
        )
        done = time.perf_counter()
        forwards = self._target_forwards(output, bucket)
        stats = getattr(output, "speculation", None)
        batch_forwards = stats.num_batch_forwards if stats is not None else self.policy.config.action_tokens
        rest = {
            row: DecodedRow(np.asarray(actions[row]), memories[row], forwards[row], done, batch_forwards)
            for row in range(rows)
            if row not in early
        }
        return DecodedBatch(1000 * (done - started), batch_forwards, rest)

    def _target_forwards(self, output, bucket: int) -> list[int]:
        stats = getattr(output, "speculation", None)
        if stats is None:  # greedy: one forward per token
            return [self.policy.config.action_tokens] * bucket
        rows = stats.rows or [stats]
        return [row.num_target_forwards for row in rows]

    # ----------------------------------------------------------------------------- the greedy baseline's graphs
    def _greedy_plan(self, bucket: int, instructions: list[str], states) -> tuple[DecodingPlan, dict]:
        """The baseline's plan and ``generate`` arguments beside it; for transformers' compiled greedy (a greedy-only
        server's), an emptied static cache of this bucket with room for the widest prompt (see the module docstring)
        in place of the plan's ``cache_implementation``."""
        plan = self._plans[0]
        if self.baseline != COMPILED_GREEDY:  # eager, or the engine's own greedy (its caches are the engine's)
            return plan, {}
        from ..speculative import CACHE_KEY, reusable_static_cache, rounded_slots

        rows = states if states is not None else [None] * len(instructions)
        width = max(len(self.policy.prompt_ids(i, s)) for i, s in zip(instructions, rows))
        width = next((last for first, last in self.prompt_tiers if first <= width <= last), width)  # the tier's
        slots = rounded_slots(width + self.policy.config.action_tokens)
        cache = reusable_static_cache(self.policy.model, slots, bucket)  # the engine's, emptied: one graph per shape
        compile = {name: value for name, value in plan.compile.items() if name != "cache_implementation"}
        return replace(plan, compile=compile), {CACHE_KEY: cache}

    # ----------------------------------------------------------------------------- prompt tiers
    def _zero_state(self) -> np.ndarray | None:
        return np.zeros(self.policy.config.state_dim) if self.policy.config.use_state else None

    def _slot_rules(self, draft_head) -> list[Callable[[int], int]]:
        """Per static cache a compiled call decodes on, ``prompt tokens -> its slots`` (the graphs hold that count),
        asked of the engine: the target's cache (``speculative.verification_slots`` of ``generate``'s own: the prompt
        and the action tokens but the last), each draft head's (``speculative.head_cache_slots``), or, greedy only,
        the baseline's (``_greedy_plan``). Empty: eager, no graphs.

        transformers' ``generate`` never shrinks the target's cache (it keeps the largest size it made, so as not to
        recompile): once [`warm_up`] decoded the longest tier, every speculative call decodes on that tier's cache,
        whatever its prompt; the other caches follow each call's prompt."""
        from ..speculative import head_cache_slots, rounded_slots

        tokens = self.policy.config.action_tokens
        rules = []
        if self.method.compiled and self.speculates:
            rules.append(self._verification_rule())
            rules += [
                partial(lambda tree, length: head_cache_slots(length + tokens, tree), tree)
                for tree in self._head_trees(draft_head)
            ]
        if self.baseline.compiled and not rules:  # greedy only: its cache's own tiers (else it follows the method's)
            rules.append(lambda length: rounded_slots(length + tokens))
        return rules

    def _verification_rule(self) -> Callable[[int], int]:
        """``prompt tokens -> slots`` of the target's cache in a compiled speculative call (``_slot_rules``)."""
        from ..speculative import verification_slots

        tokens = self.policy.config.action_tokens
        return lambda length: verification_slots(length + tokens - 1)

    def _head_trees(self, draft_head) -> list:
        """The tree settings of the draft-head drafters the methods run (a chain is a tree of top-k 1)."""
        from ..speculative import ComposedDrafter, DraftHead, DraftHeadDrafter

        if draft_head is None:
            return []
        trees = []
        for mode in self.modes[1:]:
            plan = self._plans[mode]
            pending = [plan.assistant_model]
            while pending:
                drafter = pending.pop()
                if isinstance(drafter, ComposedDrafter):
                    pending += drafter.drafters
                elif isinstance(drafter, DraftHead):
                    trees.append(DraftHeadDrafter(drafter, plan.num_draft_tokens).tree_config)
                elif isinstance(drafter, DraftHeadDrafter):
                    trees.append(drafter.tree_config)
        return trees

    def _prompt_tiers(self, draft_head) -> list[tuple[int, int]]:
        """The prompt lengths served, grouped by the slot counts they decode on: ``[(first, last), ...]`` tokens,
        from the shortest prompt to ``max_prompt_tokens`` (default: the longest prompt whose verification cache has
        the shortest prompt's slot count, and at least ``MIN_INSTRUCTION_TOKENS`` for the instruction); each tier's
        graphs are compiled by [`warm_up`]. Empty for an eager method
        (no graphs: any prompt is served, unless ``max_prompt_tokens`` says otherwise).

        Raises:
            ValueError: ``max_prompt_tokens`` shorter than this policy's shortest prompt.
        """
        rules, shortest, longest = self._slot_rules(draft_head), self.shortest_prompt, self.config.max_prompt_tokens
        if longest is not None and longest < shortest:
            raise ValueError(
                f"max_prompt_tokens {longest} is shorter than this policy's shortest prompt ({shortest} "
                f"tokens: image, state and the prompt's words without an instruction)"
            )
        if not rules:
            return [] if longest is None else [(shortest, longest)]

        def slots(length: int) -> tuple[int, ...]:
            return tuple(rule(length) for rule in rules)

        if longest is None:  # as far as the shortest prompt's verification cache goes (whatever the method)
            verification = self._verification_rule()
            longest = shortest
            while verification(longest + 1) == verification(shortest):
                longest += 1
            longest = max(longest, shortest + MIN_INSTRUCTION_TOKENS)
        tiers = [(shortest, shortest)]
        for length in range(shortest + 1, longest + 1):
            first, _ = tiers[-1]
            tiers[-1:] = [(first, length)] if slots(length) == slots(first) else [tiers[-1], (length, length)]
        return tiers

    def tier_instruction(self, tier: tuple[int, int]) -> str:
        """A synthetic instruction whose prompt is the longest of ``tier`` (or near it) that words make: what
        [`warm_up`] compiles the tier with (the longest, so that the caches sized for it hold every prompt of the
        tier)."""
        first, last = tier
        state = self._zero_state()

        def length(words: int) -> int:
            return len(self.policy.prompt_ids(" ".join(["go"] * words), state))

        step = max(1, length(2) - length(1))  # tokens per word
        words = max(1, 1 + (last - length(1)) // step)  # then a few steps to the longest that fits
        while words > 1 and length(words) > last:
            words -= 1
        while length(words + 1) <= last:
            words += 1
        if not first <= length(words) <= last:
            raise RuntimeError(f"no synthetic instruction makes a prompt of {first}..{last} tokens for the warm-up")
        return " ".join(["go"] * words)
