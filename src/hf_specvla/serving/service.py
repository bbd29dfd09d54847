"""The policy service: requests from many robots -> batched decodes, each robot with its own drafts, each batch size
decoded speculatively or greedily, whichever pays. No HTTP here (``app``, ``server`` and ``ray_deployment`` carry it).
Three parts, each in its own module and tested alone, and the service that joins them:

- **sessions** ([`Sessions`]): each robot's previous actions, its drafts (echoed ``draft_state`` wins; ``reset``
  forgets; least recently used first out past ``max_sessions``).
- **the mode chooser** ([`ModeChooser`]): per bucket, the greedy baseline or one of the speculative methods (with a
  draft head, a preset's methods with and without it), from the start-up calibration and the traffic's call times
  (exploring the other modes now and then); its decisions recorded.
- **the decode step** ([`DecodeStep`]): one batched ``predict_action`` padded to its bucket, each row handed on as
  soon as it is decoded; the prompt tiers and the greedy baseline's caches its compiled graphs fix.

**Batches and buckets.** The requests decoded together are padded to the smallest *bucket* that holds them (default
1, 2, 4, 8, 16), so the compiled graphs hold a few batch shapes, all compiled by [`PolicyService.warm_up`] before
the first request: load never triggers a compile. More requests than the largest bucket are decoded in several
batches.

**Rows answered when done.** [`PolicyService.act_each`] hands each request's reply to ``on_reply`` the moment its row
is decoded, while the rest of its batch may still decode (a speculative batch runs as many forwards as its slowest
row). A batch whose call fails is decoded again one request at a time (the requests not answered yet), so one
request's failure fails only that request: the one fallback of both backends (the one-machine batcher, Ray Serve).

**One decoding thread.** Every decode (warm-up, calibration, traffic) runs on the service's own thread, whichever
thread asks (the batcher's, a Ray replica's pool): torch's compiler settings are per thread (dynamo's recompile limit,
raised for the graphs of every bucket), so graphs compiled in one thread are then served in another under the
default limit and fail (``FailOnRecompileLimitHit``, seen in the first load run).

At ``r = 0`` every mode gives greedy's actions, whatever batch a request lands in and whatever its drafts: the
service changes how fast an action comes, never which.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING

import numpy as np

from ..policies.devices import dtype_name
from .chooser import ModeChooser, format_calibration
from .config import ServeConfig
from .decoding import DecodedRow, DecodeStep
from .protocol import MAX_INSTRUCTION_LENGTH, ActReply, ActRequest, RequestError, ServedFigures
from .sessions import Sessions

if TYPE_CHECKING:
    from ..policies import ActionPolicy

logger = logging.getLogger(__name__)

#: the instruction of the calibration's synthetic observations
CALIBRATION_INSTRUCTION = "calibrate the policy server"
#: the side of the warm-up's synthetic images for a policy that takes images of any size (OpenVLA's camera size)
WARM_UP_IMAGE_SIZE = 224


class PolicyService:
    """A policy behind a server: [`act_each`] decodes a batch of requests, each row with its own robot's drafts.

    Safe to call from any thread: every decode runs on the service's one decoding thread, one batch at a time (the
    HTTP layer forms the batches).

    Args:
        policy: the loaded policy.
        config: [`ServeConfig`].
        draft_head: for methods that draft with a head (``tree``, ``prior+tree``, ...).
    """

    def __init__(self, policy: ActionPolicy, config: ServeConfig | None = None, draft_head=None):
        self.policy, self.config = policy, config or ServeConfig()
        self.step, self.draft_head = DecodeStep(policy, self.config, draft_head), draft_head
        self.method, self.baseline = self.step.method, self.step.baseline
        self.sessions = Sessions(self.config.max_sessions)
        self.chooser = ModeChooser(
            self.config.buckets,
            tuple(m.name for m in self.step.methods),
            self.config.speculate_buckets,
            self.config.explore_every,
            self.baseline.name,
        )
        self.failed_batches = 0  # batches whose call failed (then decoded one request at a time)
        #: the warm-up's phases (seconds) and whether it started warm: filled by ``warm_up``, shown by ``GET /info``
        self.startup: dict = {}
        self._decoder = ThreadPoolExecutor(1, "hf-specvla-decode")  # generate raises its recompile limit there

    @classmethod
    def from_pretrained(
        cls, policy_folder, config: ServeConfig | None = None, draft_head_folder=None, threads: int | None = None
    ) -> PolicyService:
        """Loads the policy (a Meta-World policy folder, or an OpenVLA checkpoint folder or hub id: ``load_policy``)
        and draft head onto ``config.device`` in ``config.dtype``; the draft head is checked against the policy as
        both were saved, then cast.

        Raises:
            ValueError: ``config.device`` is not on this machine (``cuda`` without CUDA), naming it; a draft head
                made for another policy.
        """
        import torch

        from ..policies.devices import Placement
        from ..policies.loading import load_policy, policy_kind

        config = config or ServeConfig()
        placement = Placement.resolve(config.device, config.dtype)  # a device not here: refused before loading
        if threads is not None:
            torch.set_num_threads(threads)
        # an OpenVLA checkpoint loads in the served dtype (a 7B model in float32 would need twice the memory)
        cast = {"dtype": placement.dtype} if policy_kind(policy_folder) == "openvla" else {}
        policy = load_policy(policy_folder, config.unnorm_key, **cast)
        draft_head = None
        if draft_head_folder is not None:
            from ..speculative import DraftHead

            draft_head = DraftHead.from_pretrained(draft_head_folder)
            policy.check_draft_head(draft_head)  # as saved: before the cast
        placement.place_policy(policy, draft_head)
        return cls(policy, config, draft_head)

    # ----------------------------------------------------------------------------- what the server says it is
    @property
    def methods_name(self) -> str:
        """The methods it picks from, for logs: ``exact``'s ``prior+jacobi:compile`` alone, or with a draft head
        ``prior+jacobi:compile or prior+jacobi+tree:compile``."""
        return " or ".join(method.name for method in self.step.methods) or self.method.name

    def info(self) -> dict:
        """What ``GET /info`` returns: the policy (its device and dtype too), what a robot must send (the instruction's
        limits too; an OpenVLA checkpoint's datasets, ``unnorm_keys``, and the default one, ``unnorm_key``), the
        method (``methods``: every speculative method the server picks from per bucket; ``method``: the first), the
        buckets and the calibration."""
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
            "unnorm_keys": list(self.policy.unnorm_keys),
            "unnorm_key": getattr(self.policy, "default_unnorm_key", None),
            "device": str(self.policy.model.device),
            "dtype": dtype_name(self.policy.model.dtype),
            "method": self.method.name,
            "methods": [method.name for method in self.step.methods],
            "baseline": self.baseline.name,
            "buckets": list(self.config.buckets),
            "speculate": {str(b): self.chooser.speculate(b) for b in self.config.buckets},
            "calibration": self.chooser.calibration,
            "max_instruction_chars": MAX_INSTRUCTION_LENGTH,
            "max_prompt_tokens": self.step.max_prompt_tokens,
            "prompt_tiers": [list(tier) for tier in self.step.prompt_tiers],
            "startup": self.startup,
        }

    def stats(self) -> dict:
        """What ``GET /stats`` returns: the chooser's figures per bucket (batches and rows in each mode and method,
        recent median ms, the mode chosen now, the speculative share) and its decisions; the robots remembered; failed
        batches."""
        return {**self.chooser.stats(), "sessions": len(self.sessions), "failed_batches": self.failed_batches}

    def parse(self, payload) -> ActRequest:
        """A decoded request body -> a checked [`ActRequest`] for this policy (its image size, state, and drafts
        that are this policy's action tokens).

        Raises:
            RequestError: naming the field at fault.
        """
        layout = self.policy.config
        request = ActRequest.parse(payload, layout.image_size, layout.state_dim, layout.use_state)
        if self.policy.unnorm_keys:  # an OpenVLA checkpoint's datasets: the request's, else the server's default
            try:
                request.unnorm_key = self.policy.check_unnorm_key(request.unnorm_key)
            except ValueError as error:
                raise RequestError(str(error), "unnorm_key") from None
        else:  # one set of statistics: OpenVLA's clients send a key all the same (accepted and ignored)
            request.unnorm_key = None
        if request.draft_state is not None:
            self._check_draft_state(request.draft_state)
        self._check_prompt(request)
        return request

    def _check_prompt(self, request: ActRequest) -> None:
        """The request's prompt tokenizes, and fits the graphs compiled at start-up (``max_prompt_tokens``)."""
        try:
            tokens = len(self.policy.prompt_ids(request.instruction, request.state))
        except Exception as error:  # noqa: BLE001 (the tokenizer's refusal, reported to the robot)
            raise RequestError(
                f"instruction could not be tokenized: {type(error).__name__}: {error}", "instruction"
            ) from None
        limit = self.step.max_prompt_tokens
        if limit is not None and tokens > limit:
            raise RequestError(
                f"instruction makes a prompt of {tokens} tokens; this server compiled its graphs for "
                f"prompts of at most {limit} tokens ({limit - self.step.shortest_prompt} for the "
                f"instruction; GET /info: max_prompt_tokens): send a shorter instruction, or start "
                f"the server with a larger max_prompt_tokens",
                "instruction",
            )

    def _check_draft_state(self, draft_state: list[list[int]]) -> None:
        dim, tokenizer = self.policy.config.action_dim, self.policy.action_tokenizer
        if len(draft_state) > self.policy.HISTORY_LENGTH or any(len(action) != dim for action in draft_state):
            raise RequestError(
                f"draft_state must hold at most {self.policy.HISTORY_LENGTH} actions of {dim} token "
                f"ids each (as the last reply sent), got {[len(a) for a in draft_state]}",
                "draft_state",
            )
        ids = np.asarray(draft_state, dtype=np.int64).reshape(-1)
        if ids.size and not bool(tokenizer.is_action_token(ids).all()):
            raise RequestError("draft_state holds ids that are not this policy's action tokens", "draft_state")

    def _zero_state(self) -> np.ndarray | None:
        return np.zeros(self.policy.config.state_dim) if self.policy.config.use_state else None

    @property
    def _warm_up_key(self) -> str | None:
        """The dataset the warm-up's synthetic requests name (the default, else the first; None: one set)."""
        keys = self.policy.unnorm_keys
        return (getattr(self.policy, "default_unnorm_key", None) or keys[0]) if keys else None

    # ----------------------------------------------------------------------------- decoding
    def bucket_for(self, rows: int) -> int:
        """The smallest bucket that holds ``rows`` requests."""
        return next(b for b in self.config.buckets if b >= rows)

    def act(self, requests: list[ActRequest], arrived: list[float] | None = None) -> list[ActReply]:
        """[`act_each`]'s replies, in order, once all are decoded.

        Raises:
            Exception: the first request's failure, if any failed (after each was tried alone).
        """
        results = self.act_each(requests, arrived)
        failure = next((r for r in results if isinstance(r, Exception)), None)
        if failure is not None:
            raise failure
        return results

    def act_each(
        self,
        requests: list[ActRequest],
        arrived: list[float] | None = None,
        on_reply: Callable[[int, ActReply | Exception], None] | None = None,
    ) -> list:
        """Decodes ``requests`` (any number: batches of at most the largest bucket) on the decoding thread; returns
        one result per request, in order: its reply, or the exception its decode raised when decoded alone (a
        batch that fails is decoded again one unanswered request at a time, so a failure fails only its request).
        ``on_reply(i, result)`` is called once per request, on the decoding thread, the moment its result is known
        (a robot's row may finish before the rest of its batch): it must not block. ``arrived``: each request's
        ``time.perf_counter()`` at arrival (for ``queue_ms`` / ``server_ms``; default now)."""
        return self._decoder.submit(self._act_each, requests, arrived, on_reply).result()

    def _act_each(self, requests, arrived, on_reply) -> list[ActReply | Exception]:
        arrived = arrived or [time.perf_counter()] * len(requests)
        results: list[ActReply | Exception | None] = [None] * len(requests)

        def answer(index: int, result: ActReply | Exception) -> None:
            if results[index] is None:
                results[index] = result
                if on_reply is not None:
                    on_reply(index, result)

        size = self.config.max_batch_size
        for start in range(0, len(requests), size):
            batch = list(range(start, min(start + size, len(requests))))
            try:
                self._decode(
                    [requests[i] for i in batch],
                    [arrived[i] for i in batch],
                    lambda row, reply, batch=batch: answer(batch[row], reply),
                )
            except Exception:  # one request at a time: a failing one fails alone
                self.failed_batches += 1
                unanswered = [i for i in batch if results[i] is None]
                logger.exception(
                    "a batch of %d failed; decoding its %d unanswered requests one at a time",
                    len(batch),
                    len(unanswered),
                )
                for i in unanswered:
                    try:
                        self._decode([requests[i]], [arrived[i]], lambda row, reply, i=i: answer(i, reply))
                    except Exception as error:  # noqa: BLE001 (reported to that request's robot)
                        answer(i, error)
        return results

    def _decode(
        self,
        requests: list[ActRequest],
        arrived: list[float],
        answer: Callable[[int, ActReply], None],
        mode: bool | None = None,
    ) -> None:
        """One batched call; ``answer(i, reply)`` per request as its row is decoded. ``mode``: None for traffic
        (the chooser's mode, the call's time observed), else the mode of a warm-up call (nothing counted)."""
        rows, bucket = len(requests), self.bucket_for(len(requests))
        traffic = mode is None
        mode = self.chooser.mode_for(bucket) if traffic else mode
        histories = [self.sessions.history(r) for r in requests]
        started = time.perf_counter()

        def reply(i: int, row: DecodedRow) -> None:
            request = requests[i]
            if request.session is not None:
                self.sessions.remember(request.session, row.history)
            figures = ServedFigures(
                self.step.name(mode),
                mode != 0,
                row.target_forwards,
                rows,
                bucket,
                queue_ms=1000 * (started - arrived[i]),
                decode_ms=1000 * (row.done - started),
                server_ms=1000 * (row.done - arrived[i]),
                session=request.session,
                draft_state=[list(a) for a in row.history],
                batch_forwards=row.batch_forwards,
                early=row.early,
                intake_ms=0.0 if request.received is None else 1000 * (request.received - arrived[i]),
            )
            answer(i, ActReply(np.asarray(row.action), figures))

        batch = self.step.run(requests, histories, bucket, mode, reply)
        if traffic:  # booked before the batch's last replies, so that /stats after a reply counts it
            self.chooser.observe(bucket, mode, batch.decode_ms, rows)
        for i, row in batch.rows.items():
            reply(i, row)

    # ----------------------------------------------------------------------------- start-up
    def warm_up(self, calibrate: bool = True, seed: int = 0) -> list[dict]:
        """Compiles every bucket's graphs for every mode and every prompt tier (so no request ever waits on a
        compile), then, with ``calibrate`` and ``calibration_calls`` > 0 (and a measured choice), times
        ``calibration_calls`` interleaved calls per bucket and mode on synthetic observations that drift like a
        robot's (drafts: the previous call's actions) and hands them to the chooser. Returns the calibration table
        (empty without calibration)."""
        return self._decoder.submit(self._warm_up_with_cache, calibrate, seed).result()

    def compile_cache(self):
        """The [`CompileCache`] of ``config.compile_cache`` for this service's graphs (None: no folder given, or
        nothing compiled)."""
        step = self.step
        if self.config.compile_cache is None or not (step.method.compiled or step.baseline.compiled):
            return None
        from ..run_folder import fingerprint
        from .compile_cache import CompileCache, environment_record

        record = {
            **environment_record(),
            "policy": self.policy.weights_fingerprint(),
            "draft_head": fingerprint(self.draft_head) if self.draft_head is not None else None,
            "methods": [step.name(mode) for mode in step.modes],
            "buckets": list(self.config.buckets),
            "prompt_tiers": [list(tier) for tier in step.prompt_tiers],
            "device": self.policy.model.device.type,
            "dtype": dtype_name(self.policy.model.dtype),
        }
        return CompileCache(self.config.compile_cache, record)

    def _warm_up_with_cache(self, calibrate: bool, seed: int) -> list[dict]:
        """[`_warm_up`] in the compile cache's folder (when there is one); the phases' times logged and kept in
        ``startup``."""
        cache = self.compile_cache()
        if cache is None and self.config.compile_cache is not None:
            logger.warning(
                "compile cache %s not used: %s compiles nothing", self.config.compile_cache, self.methods_name
            )
        from ..speculative import graphs_kept_in
        from .compile_cache import GRAPHS_FOLDER

        # the engine's graph files beside Inductor's caches: DIR/graphs, shared by every settings' key (their own keys)
        graphs = contextlib.nullcontext() if cache is None else graphs_kept_in(cache.root / GRAPHS_FOLDER)
        with cache.compiling() if cache is not None else contextlib.nullcontext() as warm, graphs:
            self.startup = (
                {"compile_cache": None}
                if cache is None
                else {"compile_cache": "warm" if warm else "cold", "compile_cache_folder": str(cache.folder)}
            )
            if cache is not None and cache.set_aside is not None:  # a damaged folder: the start compiles cold
                self.startup["compile_cache_set_aside"] = str(cache.set_aside)
            table = self._warm_up(calibrate, seed)
        phases = self.startup
        start = {"warm": " (warm start: the compile cache's graphs)", "cold": " (cold start, into the compile cache)"}
        logger.info(
            "warmed up: compile %.1f s%s, calibrate %.1f s",
            phases["compile_s"],
            start.get(phases["compile_cache"], ""),
            phases["calibrate_s"],
        )
        return table

    def _warm_up(self, calibrate: bool, seed: int) -> list[dict]:
        rng = np.random.default_rng(seed)
        size = self.policy.config.image_size or WARM_UP_IMAGE_SIZE  # (a policy that takes any size resizes it)
        base = rng.integers(0, 256, (size, size, 3), dtype=np.uint8)
        table = []
        measure = calibrate and self.chooser.measured and self.config.calibration_calls > 0
        modes = self.step.modes
        # every tier's graphs, compiled at its longest prompt, the longest tier first: the target's cache, sized by
        # generate, keeps the largest size it had (so one set of target graphs, not one per tier)
        step = self.step
        compiled = step.method.compiled or step.baseline.compiled
        longest = [step.tier_instruction(tier) for tier in step.prompt_tiers[::-1]] if compiled else []
        calibration, served = CALIBRATION_INSTRUCTION, self._zero_state()
        if step.prompt_tiers and len(self.policy.prompt_ids(calibration, served)) > step.max_prompt_tokens:
            calibration = longest[-1]  # a prompt served, so that calibrating compiles nothing more
        spent_ms = {"compile": 0.0, "calibrate": 0.0}
        for bucket in self.config.buckets:
            sessions = [f"calibration-{bucket}-{i}" for i in range(bucket)]
            times: dict[int, list[float]] = {mode: [] for mode in modes}
            for instruction in longest:  # without drafts, then with
                for first in (True, False):
                    for mode in modes:
                        images = np.repeat(base[None], bucket, axis=0)
                        spent_ms["compile"] += self._warm_up_call(sessions, instruction, images, first, mode)
            calls = 1 + (self.config.calibration_calls if measure else 0)
            for number in range(calls + 1):  # call 0 compiles (and leaves each session its first action)
                drift = rng.integers(-2, 3, (bucket, size, size, 3))
                images = np.clip(base.astype(np.int64) + drift, 0, 255).astype(np.uint8)
                for mode in _rotated(modes, number):  # interleaved, each mode first in turn
                    ms = self._warm_up_call(sessions, calibration, images, number == 0, mode)
                    if number >= 2:  # calls 0 and 1 compile (first without drafts, then with)
                        times[mode].append(ms)
                    spent_ms["calibrate" if number >= 2 else "compile"] += ms
            for session in sessions:
                self.sessions.forget(session)
            if measure:
                table.append(self.chooser.calibrate(bucket, times))
        if table:
            logger.info(
                "calibration (%d calls per bucket and mode):\n%s",
                self.config.calibration_calls,
                format_calibration(table),
            )
        self.startup.update({f"{phase}_s": round(ms / 1000, 2) for phase, ms in spent_ms.items()})
        return table

    def _warm_up_call(self, sessions: list[str], instruction: str, images: np.ndarray, first: bool, mode: int) -> float:
        """One warm-up call of ``len(sessions)`` robots in the given mode (nothing counted); its ms."""
        state = np.zeros(self.policy.config.state_dim)
        requests = [
            ActRequest(image, instruction, state, session, reset=first, unnorm_key=self._warm_up_key)
            for image, session in zip(images, sessions)
        ]
        started = time.perf_counter()
        self._decode(requests, [started] * len(requests), lambda i, reply: None, mode=mode)
        return 1000 * (time.perf_counter() - started)

    def close(self) -> None:
        """Stops the decoding thread (after the decodes it holds)."""
        self._decoder.shutdown(wait=True)


def _rotated(modes: tuple[int, ...], number: int) -> tuple[int, ...]:
    """``modes`` rotated by ``number``: the calibration's call ``number`` runs each mode in this order, so that every
    mode goes first as often as the others."""
    shift = number % len(modes)
    return modes[shift:] + modes[:shift]
