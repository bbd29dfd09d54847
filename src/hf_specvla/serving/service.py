"""The policy service: requests from many robots -> one batched ``predict_action`` per batch, each robot with its own
drafts; the decision per batch size whether speculation pays. No HTTP here (``app`` and ``ray_deployment`` carry it).

**Batches and buckets.** The requests decoded together are padded to the smallest *bucket* that holds them (default
1, 2, 4, 8, 16) with idle rows (copies of the first row, no drafts; their actions are dropped), so the compiled
graphs hold a few batch shapes, all compiled by [`PolicyService.warm_up`] before the first request: load never
triggers a compile. More requests than the largest bucket are decoded in several batches.

**Each robot's drafts.** A robot names itself with ``session``; its previous actions (token ids, as
``VLAPolicy.previous_action_ids``) are kept per session (least recently used first out past ``max_sessions``) and
returned in every reply as ``draft_state``, which the robot may echo: then its drafts do not depend on which
replica answers. A robot whose state is lost gets its action without prior drafts (one step of greedy's speed).
``reset`` starts a new episode.

**One decoding thread.** Every decode (warm-up, calibration, traffic) runs on the service's own thread, whichever
thread asks (the batcher's, a Ray replica's pool): torch's compiler settings are per thread (dynamo's recompile limit,
raised for the graphs of every bucket), so graphs compiled in one thread are then served in another under the
default limit and fail (``FailOnRecompileLimitHit``, seen in the first load run).

**The greedy baseline's cache.** transformers' compiled greedy decoding sizes its static cache to each call's prompt
length plus the new tokens, so every new prompt length (another instruction, another batch's widest prompt) compiles
a new graph mid-traffic. The service passes it a static cache of its own per bucket and prompt tier instead (below),
with room for the tier's longest prompt (emptied before each call): one graph per bucket and tier, the same tokens.

**Prompt tiers: no compile under load.** A compiled method's graphs hold its static caches' slot counts, and those
grow with the batch's widest prompt (64 slots at a time: the target's cache with room for a draft tree, a draft
head's own). A prompt that needs more slots than any warmed-up call compiled new graphs mid-traffic: minutes on a
CPU, every robot waiting. So the prompt lengths served are bounded: [`PolicyService.prompt_tiers`] groups the lengths
from this policy's shortest prompt up to ``max_prompt_tokens`` (default: as far as the shortest prompt's verification
cache stretches) by the slot counts they need, [`PolicyService.warm_up`] compiles every tier, and
[`PolicyService.parse`] refuses a longer prompt (422, field ``instruction``, the limit named; ``GET /info`` states it)
before any forward.

**Speculate only where it pays.** For each bucket the service decodes either speculatively (the method, e.g.
``exact`` = previous action + Jacobi drafts, compiled) or with the greedy baseline (transformers' compiled greedy
for a compiled method, eager greedy otherwise), whichever is faster: measured at start-up
([`PolicyService.warm_up`]: a few interleaved calls per bucket on synthetic observations that drift like a robot's),
then kept current on the real traffic (every ``explore_every``-th batch of a bucket runs the other mode; the choice
follows the medians of the last calls). Or the user fixes the table (``speculate_buckets``). At ``r = 0`` both modes
give greedy's actions, so the choice changes speed, never behaviour.
"""

from __future__ import annotations

import logging
import math
import statistics
import time
from collections import OrderedDict, deque
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING

import numpy as np

from ..policies.decoding_methods import COMPILED_GREEDY, GREEDY, DecodingMethod
from .config import ServeConfig
from .protocol import MAX_INSTRUCTION_LENGTH, ActReply, ActRequest, RequestError, ServedFigures

if TYPE_CHECKING:
    from ..policies import VLAPolicy

logger = logging.getLogger(__name__)

#: calls kept per bucket and mode for the choice (their median decides)
TIMING_WINDOW = 16
#: the instruction of the calibration's synthetic observations
CALIBRATION_INSTRUCTION = "calibrate the policy server"
#: the default prompt limit leaves the instruction at least this many tokens (MT50's longest takes 13 on policy v3;
#: on v3 the shortest prompt's verification cache leaves 54, so the default is that one tier)
MIN_INSTRUCTION_TOKENS = 32
#: a gap between the two modes' median call times past which the other mode is explored less often, and how much
CLEAR_GAP, CLEAR_GAP_EXPLORE_FACTOR = 0.2, 4
#: dynamo graphs allowed per bucket and prompt tier on the decoding thread (verification widths, prefill, greedy
#: steps, with and without hidden states) beyond the engine's own raise, and a margin for transformers' own
GRAPHS_PER_BUCKET, GRAPHS_MARGIN = 16, 16


class PolicyService:
    """A policy behind a server: [`act`] decodes a batch of requests, each row with its own robot's drafts.

    Safe to call from any thread: every decode runs on the service's one decoding thread, one batch at a time (the
    HTTP layer forms the batches).

    Args:
        policy: the loaded policy.
        config: [`ServeConfig`].
        draft_head: for methods that draft with a head (``tree``, ``prior+tree``, ...).
    """

    def __init__(self, policy: VLAPolicy, config: ServeConfig | None = None, draft_head=None):
        self.policy, self.config = policy, config or ServeConfig()
        layout = policy.config
        self.method = DecodingMethod.parse(self.config.method, draft_head is not None, layout.action_dim)
        device = policy.model.device.type
        self.baseline = COMPILED_GREEDY if self.method.compiled else GREEDY
        self._kwargs = {
            True: self.method.generate_kwargs(draft_head, device, action_dim=layout.action_dim),
            False: self.baseline.generate_kwargs(None, device),
        }
        self.speculates = self.method.drafters != "greedy"
        self.sessions: OrderedDict[str, list[list[int]]] = OrderedDict()
        self.timings = {(b, mode): deque(maxlen=TIMING_WINDOW) for b in self.config.buckets for mode in (True, False)}
        self.calls = {b: 0 for b in self.config.buckets}  # batches per bucket, for exploration
        self.batches = {key: [0, 0] for key in self.timings}  # (bucket, speculative) -> [batches, rows] served
        self.calibration: list[dict] = []
        self._choice = {b: self.speculates for b in self.config.buckets}
        if self.config.speculate_buckets is not None:
            self._choice = {b: self.speculates and b in self.config.speculate_buckets for b in self.config.buckets}
        self._greedy_caches: dict[tuple[int, int], object] = {}  # (bucket, slots) -> the baseline's static cache
        self.shortest_prompt = len(policy.prompt_ids("", self._zero_state()))  # image, state and the prompt's words
        self.prompt_tiers = self._prompt_tiers(draft_head)
        self._decoder = ThreadPoolExecutor(1, "hf-specvla-decode", initializer=self._allow_graphs)

    @classmethod
    def from_pretrained(cls, policy_folder, config: ServeConfig | None = None, draft_head_folder=None,
                        threads: int | None = None) -> PolicyService:  # fmt: skip
        """Loads the policy (and draft head) from their folders."""
        import torch

        from ..policies import VLAPolicy

        if threads is not None:
            torch.set_num_threads(threads)
        policy = VLAPolicy.from_pretrained(policy_folder)
        draft_head = None
        if draft_head_folder is not None:
            from ..speculative import DraftHead

            draft_head = DraftHead.from_pretrained(draft_head_folder)
            policy.check_draft_head(draft_head)
        return cls(policy, config, draft_head)

    # ----------------------------------------------------------------------------- what the server says it is
    def info(self) -> dict:
        """What ``GET /info`` returns: the policy, what a robot must send (the instruction's limits too), the method and
        the buckets."""
        layout = self.policy.config
        return {
            "server": "hf_specvla",
            "policy": self.policy.name_or_path,
            "fingerprint": self.policy.weights_fingerprint(),
            "image_size": layout.image_size,
            "camera": layout.camera,
            "state_dim": layout.state_dim,
            "use_state": layout.use_state,
            "action_dim": layout.action_dim,
            "chunk_length": layout.chunk_length,
            "method": self.method.name,
            "baseline": self.baseline.name,
            "buckets": list(self.config.buckets),
            "speculate": {str(b): self._choice[b] for b in self.config.buckets},
            "calibration": self.calibration,
            "max_instruction_chars": MAX_INSTRUCTION_LENGTH,
            "max_prompt_tokens": self.max_prompt_tokens,
            "prompt_tiers": [list(tier) for tier in self.prompt_tiers],
        }

    @property
    def max_prompt_tokens(self) -> int | None:
        """The longest prompt served, in tokens (None: no limit beyond the instruction's characters: eager)."""
        return self.prompt_tiers[-1][1] if self.prompt_tiers else None

    def parse(self, payload) -> ActRequest:
        """A decoded request body -> a checked [`ActRequest`] for this policy (its image size, state, and drafts
        that are this policy's action tokens).

        Raises:
            RequestError: naming the field at fault.
        """
        layout = self.policy.config
        request = ActRequest.parse(payload, layout.image_size, layout.state_dim, layout.use_state)
        if request.draft_state is not None:
            self._check_draft_state(request.draft_state)
        self._check_prompt(request)
        return request

    def _check_prompt(self, request: ActRequest) -> None:
        """The request's prompt tokenizes, and fits the graphs compiled at start-up (``max_prompt_tokens``)."""
        try:
            tokens = len(self.policy.prompt_ids(request.instruction, request.state))
        except Exception as error:  # noqa: BLE001 (the tokenizer's refusal, reported to the robot)
            raise RequestError(f"instruction could not be tokenized: {type(error).__name__}: {error}",
                               "instruction") from None  # fmt: skip
        limit = self.max_prompt_tokens
        if limit is not None and tokens > limit:
            raise RequestError(f"instruction makes a prompt of {tokens} tokens; this server compiled its graphs for "
                               f"prompts of at most {limit} tokens ({limit - self.shortest_prompt} for the "
                               f"instruction; GET /info: max_prompt_tokens): send a shorter instruction, or start "
                               f"the server with a larger max_prompt_tokens", "instruction")  # fmt: skip

    # ----------------------------------------------------------------------------- prompt tiers
    def _zero_state(self) -> np.ndarray | None:
        return np.zeros(self.policy.config.state_dim) if self.policy.config.use_state else None

    def _slot_rules(self, draft_head) -> list[tuple[int, int]]:
        """``(extra, multiple)`` per static cache a compiled call decodes on: a prompt of ``P`` tokens needs
        ``multiple * ceil((P + extra) / multiple)`` slots in it (the graphs hold that count). Empty: eager, no graphs.
        The engine's own sizing, restated (tests check it against the engine's): the target's cache
        ([`_verification_rule`]); a draft head's holds the prompt, the action tokens, its padded catch-up pairs and
        its tree's entries; the greedy baseline's is the service's own (``_greedy_kwargs``).

        transformers' ``generate`` never shrinks the target's cache (it keeps the largest size it made, so as not to
        recompile): once [`warm_up`] decoded the longest tier, every speculative call decodes on that tier's cache,
        whatever its prompt; the other caches follow each call's prompt."""
        from ..speculative import SLOT_MULTIPLE

        rules = []
        if self.method.compiled and self.speculates:
            rules.append(self._verification_rule())
            rules += [self._head_rule(tree) for tree in self._head_trees(draft_head)]
        if self.baseline.compiled and not rules:  # greedy only: its cache's own tiers (else it follows the method's)
            rules.append((self.policy.config.action_tokens, SLOT_MULTIPLE))
        return rules

    def _verification_rule(self) -> tuple[int, int]:
        """The target's cache in a compiled speculative call (``_slot_rules``): ``generate`` sizes its static cache
        ``max_length - 1`` (the prompt and the action tokens but the last, which is never fed), the engine adds room
        for the widest verification and rounds up."""
        from ..speculative import NODE_BUCKETS, SLOT_MULTIPLE

        return self.policy.config.action_tokens - 1 + NODE_BUCKETS[-1], SLOT_MULTIPLE

    def _head_rule(self, tree) -> tuple[int, int]:
        """A draft head's cache in a compiled call (``_slot_rules``; the engine's ``DraftHeadSession.key_length``):
        ``max_length`` (the prompt and the action tokens), the padded catch-up pairs (``depth + 1``) and the entries
        one expansion writes (``num_head_entries``), rounded up."""
        from ..speculative import SLOT_MULTIPLE, num_head_entries

        tokens = self.policy.config.action_tokens
        return tokens + tree.depth + 1 + num_head_entries(tree.top_k, tree.depth), SLOT_MULTIPLE

    def _head_trees(self, draft_head) -> list:
        """The tree settings of the draft-head drafters the method runs (a chain is a tree of top-k 1)."""
        from ..speculative import ComposedDrafter, DraftHead, DraftHeadDrafter

        if draft_head is None:
            return []
        kwargs, trees = self._kwargs[True], []
        pending = [kwargs.get("assistant_model")]
        while pending:
            drafter = pending.pop()
            if isinstance(drafter, ComposedDrafter):
                pending += drafter.drafters
            elif isinstance(drafter, DraftHead):
                trees.append(DraftHeadDrafter(drafter, kwargs.get("num_draft_tokens")).tree_config)
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
            raise ValueError(f"max_prompt_tokens {longest} is shorter than this policy's shortest prompt ({shortest} "
                             f"tokens: image, state and the prompt's words without an instruction)")  # fmt: skip
        if not rules:
            return [] if longest is None else [(shortest, longest)]

        def slots(length: int) -> tuple[int, ...]:
            return tuple(multiple * math.ceil((length + extra) / multiple) for extra, multiple in rules)

        if longest is None:  # as far as the shortest prompt's verification cache goes (whatever the method)
            extra, multiple = self._verification_rule()
            longest = max(multiple * math.ceil((shortest + extra) / multiple) - extra,
                          shortest + MIN_INSTRUCTION_TOKENS)  # fmt: skip
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

    def _check_draft_state(self, draft_state: list[list[int]]) -> None:
        dim, tokenizer = self.policy.config.action_dim, self.policy.action_tokenizer
        if len(draft_state) > self.policy.HISTORY_LENGTH or any(len(action) != dim for action in draft_state):
            raise RequestError(f"draft_state must hold at most {self.policy.HISTORY_LENGTH} actions of {dim} token "
                               f"ids each (as the last reply sent), got {[len(a) for a in draft_state]}",
                               "draft_state")  # fmt: skip
        ids = np.asarray(draft_state, dtype=np.int64).reshape(-1)
        if ids.size and not bool(tokenizer.is_action_token(ids).all()):
            raise RequestError("draft_state holds ids that are not this policy's action tokens", "draft_state")

    def stats(self) -> dict:
        """What ``GET /stats`` returns: per bucket, batches and rows decoded in each mode, the median ms per call
        of the recent calls, the mode chosen now (``mode``, ``speculate``) and the share of its batches decoded
        speculatively; the same share over every bucket; the robots remembered."""
        buckets, counts = {}, {True: 0, False: 0}
        for bucket in self.config.buckets:
            row = {"speculate": self._choice[bucket], "mode": "speculative" if self._choice[bucket] else "greedy"}
            for speculative, mode in ((True, "speculative"), (False, "greedy")):
                recent = self.timings[(bucket, speculative)]
                row[f"{mode}_batches"], row[f"{mode}_rows"] = self.batches[(bucket, speculative)]
                row[f"{mode}_median_ms"] = round(statistics.median(recent), 2) if recent else None
                counts[speculative] += row[f"{mode}_batches"]
            row["speculative_share"] = _share(row["speculative_batches"], row["greedy_batches"])
            buckets[str(bucket)] = row
        return {"buckets": buckets, "speculative_share": _share(counts[True], counts[False]),
                "sessions": len(self.sessions)}  # fmt: skip

    # ----------------------------------------------------------------------------- deciding
    def speculate(self, bucket: int) -> bool:
        """Whether batches of ``bucket`` rows decode speculatively now."""
        return self._choice[bucket]

    def bucket_for(self, rows: int) -> int:
        """The smallest bucket that holds ``rows`` requests."""
        return next(b for b in self.config.buckets if b >= rows)

    def act(self, requests: list[ActRequest], arrived: list[float] | None = None) -> list[ActReply]:
        """Decodes ``requests`` (any number: split into batches of at most the largest bucket) and returns one reply
        per request, in order, on the decoding thread. ``arrived``: each request's ``time.perf_counter()`` at arrival
        (for ``queue_ms``)."""
        return self._decoder.submit(self._act, requests, arrived).result()

    def _act(self, requests: list[ActRequest], arrived: list[float] | None) -> list[ActReply]:
        now = time.perf_counter()
        arrived = arrived or [now] * len(requests)
        replies: list[ActReply] = []
        size = self.config.max_batch_size
        for start in range(0, len(requests), size):
            replies += self._decode(requests[start : start + size], arrived[start : start + size])
        return replies

    def _decode(self, requests: list[ActRequest], arrived: list[float], measured: bool = True) -> list[ActReply]:
        """One batched call (``measured``: counts toward the mode choice; False for the calibration's own calls)."""
        rows, bucket = len(requests), self.bucket_for(len(requests))
        self.calls[bucket] += measured
        speculative = self._mode_for(bucket) if measured else self._choice[bucket]
        histories = [self._history(r) for r in requests] + [[] for _ in range(bucket - rows)]
        padded = requests + [requests[0]] * (bucket - rows)
        images = np.stack([r.image for r in padded])
        states = np.stack([r.state for r in padded]) if self.policy.config.use_state else None
        started = time.perf_counter()
        instructions = [r.instruction for r in padded]
        kwargs = self._kwargs[speculative] if speculative else self._greedy_kwargs(bucket, instructions, states)
        actions, output = self.policy.predict_action(
            images, instructions, states, return_output=True, previous_action_ids=histories, **kwargs
        )
        decode_ms = 1000 * (time.perf_counter() - started)
        if measured:
            self._observe(bucket, speculative, decode_ms)
            self.batches[(bucket, speculative)][0] += 1
            self.batches[(bucket, speculative)][1] += rows
        forwards = self._target_forwards(output, bucket)
        stats = getattr(output, "speculation", None)
        batch_forwards = stats.num_batch_forwards if stats is not None else self.policy.config.action_tokens
        name = self.method.name if speculative else self.baseline.name
        replies = []
        for i, request in enumerate(requests):
            if request.session is not None:
                self._remember(request.session, histories[i])
            figures = ServedFigures(name, speculative, forwards[i], rows, bucket,
                                    queue_ms=1000 * (started - arrived[i]), decode_ms=decode_ms,
                                    session=request.session, draft_state=[list(a) for a in histories[i]],
                                    batch_forwards=batch_forwards)  # fmt: skip
            replies.append(ActReply(np.asarray(actions[i]), figures))
        return replies

    def _greedy_kwargs(self, bucket: int, instructions: list[str], states) -> dict:
        """The baseline's ``generate`` arguments; for compiled greedy, an emptied static cache of this bucket with
        room for the widest prompt (see the module docstring) in place of ``cache_implementation``."""
        kwargs = self._kwargs[False]
        if kwargs.get("cache_implementation") != "static":
            return kwargs
        from transformers import StaticCache

        from ..speculative import CACHE_KEY, SLOT_MULTIPLE

        rows = states if states is not None else [None] * len(instructions)
        width = max(len(self.policy.prompt_ids(i, s)) for i, s in zip(instructions, rows))
        width = next((last for first, last in self.prompt_tiers if first <= width <= last), width)  # the tier's
        slots = SLOT_MULTIPLE * math.ceil((width + self.policy.config.action_tokens) / SLOT_MULTIPLE)
        cache = self._greedy_caches.get((bucket, slots))
        if cache is None:
            logger.info("greedy baseline: a static cache of %d slots for batches of %d", slots, bucket)
            config = self.policy.model.config.get_text_config()
            cache = self._greedy_caches[(bucket, slots)] = StaticCache(config=config, max_cache_len=slots)
        else:
            cache.reset()
        return {**{k: v for k, v in kwargs.items() if k != "cache_implementation"}, CACHE_KEY: cache}

    def _allow_graphs(self) -> None:
        """On the decoding thread: dynamo's recompile limit (a per-thread setting) raised for the graphs of every
        bucket and prompt tier."""
        import torch

        config = torch._dynamo.config
        name = "recompile_limit" if hasattr(config, "recompile_limit") else "cache_size_limit"
        wanted = GRAPHS_PER_BUCKET * len(self.config.buckets) * max(1, len(self.prompt_tiers)) + GRAPHS_MARGIN
        if getattr(config, name) < wanted:
            setattr(config, name, wanted)

    def _target_forwards(self, output, bucket: int) -> list[int]:
        stats = getattr(output, "speculation", None)
        if stats is None:  # greedy: one forward per token
            return [self.policy.config.action_tokens] * bucket
        rows = stats.rows or [stats]
        return [row.num_target_forwards for row in rows]

    def _history(self, request: ActRequest) -> list[list[int]]:
        """The robot's previous actions (its drafts): none at a reset, the echoed ones, else the session's."""
        if request.reset or request.session is None:
            if request.session is not None:
                self.sessions.pop(request.session, None)
            return []
        if request.draft_state is not None:
            return [list(a) for a in request.draft_state]
        return [list(a) for a in self.sessions.get(request.session, [])]

    def _remember(self, session: str, history: list[list[int]]) -> None:
        self.sessions[session] = history
        self.sessions.move_to_end(session)
        while len(self.sessions) > self.config.max_sessions:
            self.sessions.popitem(last=False)

    # ----------------------------------------------------------------------------- measuring
    def _mode_for(self, bucket: int) -> bool:
        """This batch's mode: the chosen one, or the other every ``explore_every``-th call (measured choice only;
        ``CLEAR_GAP_EXPLORE_FACTOR`` times less often while the two modes' medians differ by more than
        ``CLEAR_GAP``: a clear choice needs fewer checks, and each costs that call the gap)."""
        chosen = self._choice[bucket]
        every = self.config.explore_every
        if not (self.speculates and self.config.speculate_buckets is None and every):
            return chosen
        spec, greedy = self.timings[(bucket, True)], self.timings[(bucket, False)]
        if spec and greedy and abs(statistics.median(spec) / statistics.median(greedy) - 1) > CLEAR_GAP:
            every *= CLEAR_GAP_EXPLORE_FACTOR
        return not chosen if self.calls[bucket] % every == 0 else chosen

    def _observe(self, bucket: int, speculative: bool, ms: float) -> None:
        self.timings[(bucket, speculative)].append(ms)
        if self.config.speculate_buckets is not None or not self.speculates:
            return
        spec, greedy = self.timings[(bucket, True)], self.timings[(bucket, False)]
        if spec and greedy:
            choice = statistics.median(spec) < statistics.median(greedy)
            if choice != self._choice[bucket]:
                logger.info("bucket %d now decodes %s (median %.1f ms speculative vs %.1f ms greedy)", bucket,
                            "speculatively" if choice else "greedily", statistics.median(spec),
                            statistics.median(greedy))  # fmt: skip
            self._choice[bucket] = choice

    def warm_up(self, calibrate: bool = True, seed: int = 0) -> list[dict]:
        """Compiles every bucket's graphs for both modes (so no request ever waits on a compile), then, with
        ``calibrate`` and ``calibration_calls`` > 0, times ``calibration_calls`` interleaved calls per bucket and
        mode on synthetic observations that drift like a robot's (drafts: the previous call's actions) and sets the
        choice per bucket. Returns the calibration table (empty without calibration)."""
        return self._decoder.submit(self._warm_up, calibrate, seed).result()

    def _warm_up(self, calibrate: bool, seed: int) -> list[dict]:
        rng = np.random.default_rng(seed)
        size, dim = self.policy.config.image_size, self.policy.config.state_dim
        base = rng.integers(0, 256, (size, size, 3), dtype=np.uint8)
        table = []
        measure = calibrate and self.speculates and self.config.calibration_calls > 0
        measure = measure and self.config.speculate_buckets is None
        # every tier's graphs, compiled at its longest prompt, the longest tier first: the target's cache, sized by
        # generate, keeps the largest size it had (so one set of target graphs, not one per tier)
        compiled = self.method.compiled or self.baseline.compiled
        longest = [self.tier_instruction(tier) for tier in self.prompt_tiers[::-1]] if compiled else []
        calibration, served = CALIBRATION_INSTRUCTION, self._zero_state()
        if self.prompt_tiers and len(self.policy.prompt_ids(calibration, served)) > self.max_prompt_tokens:
            calibration = longest[-1]  # a prompt served, so that calibrating compiles nothing more
        for bucket in self.config.buckets:
            sessions = [f"calibration-{bucket}-{i}" for i in range(bucket)]
            times: dict[bool, list[float]] = {True: [], False: []}
            modes = (False, True) if self.speculates else (False,)
            for instruction in longest:  # without drafts, then with
                for call in range(2):
                    images = np.repeat(base[None], bucket, axis=0)
                    requests = [ActRequest(images[i], instruction, np.zeros(dim), sessions[i], reset=call == 0)
                                for i in range(bucket)]  # fmt: skip
                    for speculative in modes:
                        self._choice[bucket], saved = speculative, self._choice[bucket]
                        self._decode_unexplored(requests)
                        self._choice[bucket] = saved
            calls = 1 + (self.config.calibration_calls if measure else 0)
            for call in range(calls + 1):  # call 0 compiles (and leaves each session its first action)
                drift = rng.integers(-2, 3, (bucket, size, size, 3))
                images = np.clip(base.astype(np.int64) + drift, 0, 255).astype(np.uint8)
                requests = [ActRequest(images[i], calibration, np.zeros(dim), sessions[i], reset=call == 0)
                            for i in range(bucket)]  # fmt: skip
                for speculative in modes if call % 2 else modes[::-1]:  # interleaved, alternating which goes first
                    self._choice[bucket], saved = speculative, self._choice[bucket]
                    started = time.perf_counter()
                    self._decode_unexplored(requests)
                    if call >= 2:  # calls 0 and 1 compile (first without drafts, then with)
                        times[speculative].append(1000 * (time.perf_counter() - started))
                    self._choice[bucket] = saved
            for session in sessions:
                self.sessions.pop(session, None)
            if measure:
                spec, greedy = statistics.median(times[True]), statistics.median(times[False])
                self._choice[bucket] = spec < greedy
                for speculative in (True, False):  # the calibration's timings seed the choice; traffic refines it
                    self.timings[(bucket, speculative)].extend(times[speculative])
                table.append({"bucket": bucket, "greedy_ms": round(greedy, 2), "speculative_ms": round(spec, 2),
                              "speed_up": round(greedy / spec, 3), "speculate": spec < greedy})  # fmt: skip
        self.calibration = table
        if table:
            logger.info("calibration (%d calls per bucket and mode, %s vs %s):\n%s", self.config.calibration_calls,
                        self.method.name, self.baseline.name, format_calibration(table))  # fmt: skip
        return table

    def _decode_unexplored(self, requests: list[ActRequest]) -> None:
        """A calibration call in the mode ``_choice`` names (not counted, no exploration)."""
        self._decode(requests, [time.perf_counter()] * len(requests), measured=False)

    def close(self) -> None:
        """Stops the decoding thread (after the decodes it holds)."""
        self._decoder.shutdown(wait=True)


def _share(part: int, rest: int) -> float | None:
    """``part / (part + rest)``, rounded (None before anything was counted)."""
    return round(part / (part + rest), 4) if part + rest else None


def format_calibration(table: list[dict]) -> str:
    """Markdown table of [`PolicyService.warm_up`]'s calibration."""
    lines = ["| bucket | greedy ms/call | speculative ms/call | speed-up | decodes |", "|---:|---:|---:|---:|---|"]
    for row in table:
        lines.append(f"| {row['bucket']} | {row['greedy_ms']:.1f} | {row['speculative_ms']:.1f} | "
                     f"{row['speed_up']:.2f}x | {'speculative' if row['speculate'] else 'greedy'} |")  # fmt: skip
    return "\n".join(lines)
