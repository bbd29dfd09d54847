"""Forming batches on one machine: requests that arrive together are decoded in one call ([`Batcher`]).

A worker thread takes the first waiting request and waits up to ``max_wait_ms`` for more (up to the largest bucket),
but only for robots that may send one: not once it holds a request of every session active in the last
``ACTIVE_WINDOW_S`` (one robot alone never waits; while requests without a session arrive, it always may). Requests
already queued always join (a backlog behind a slow batch is drained in full batches, not one by one), and a robot
counts as active from its request's arrival until ``ACTIVE_WINDOW_S`` after its reply (however long it queued). It drops
the requests whose robots gave up meanwhile (their futures cancelled) and hands the rest to
[`PolicyService.act_each`], which answers each robot as soon as its row is decoded. The queue is bounded: past
``max_queue`` waiting requests, [`submit`] raises [`Overloaded`] with the seconds after which a retry is likely to be
served (HTTP 503 + Retry-After), rather than letting latency grow without bound. Only live requests count: one whose
robot gave up (its future cancelled) frees its slot at once, though the worker drops it from the queue only when it
reaches it. A
batch whose call fails is retried one request at a time (by the service, as on Ray Serve), so one request's failure
never fails the others. Each Ray Serve replica batches the same way, with a [`Batcher`] of its own
(``ray_deployment``).
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass, field

from .protocol import ActRequest, Overloaded
from .service import PolicyService

logger = logging.getLogger(__name__)

#: a session that sent a request this recently is a robot a batch may wait for
ACTIVE_WINDOW_S = 1.0


@dataclass
class _Pending:
    request: ActRequest
    arrived: float = field(default_factory=time.perf_counter)
    future: Future = field(default_factory=Future)
    counted: bool = True  # it holds one of the queue's ``max_queue`` slots (until taken or cancelled)


class Batcher:
    """Batches requests for a [`PolicyService`] on a worker thread ([`start`], [`stop`])."""

    def __init__(self, service: PolicyService):
        self.service = service
        config = service.config
        self.max_wait_s, self.max_batch_size = config.max_wait_ms / 1000, config.max_batch_size
        self.max_queue = config.max_queue
        #: requests in arrival order (live ones, and cancelled ones the worker has not reached yet)
        self._queue: queue.Queue[_Pending] = queue.Queue()
        self._live = 0  # the queued requests whose robots still wait: what ``max_queue`` bounds
        self._slots = threading.Lock()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._recent_batch_s = 0.05  # a running mean, for Retry-After
        self.batches = 0
        self.dropped = 0  # requests whose robots gave up before their batch started
        self._last_seen: dict[str | None, float] = {}  # session (None: anonymous) -> its last request or reply
        self.failure: BaseException | None = None  # what stopped the worker thread, if anything did
        self._in_hand: list[_Pending] = []  # the batch being formed or decoded (failed with the thread, if it fails)

    def start(self) -> Batcher:
        self._thread = threading.Thread(target=self._run, name="hf-specvla-batcher", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 60.0) -> None:
        """Decodes what is queued, then stops the worker."""
        self._stopping.set()
        if self._thread is not None:
            self._thread.join(timeout_s)

    @property
    def waiting(self) -> int:
        """Queued requests whose robots still wait."""
        return self._live

    def _release(self, pending: _Pending) -> None:
        """Frees ``pending``'s queue slot (once: when the worker takes it, or the moment its robot gives up)."""
        with self._slots:
            if pending.counted:
                pending.counted = False
                self._live -= 1

    def unhealthy(self) -> str | None:
        """Why requests would not be served now (None: the worker is running)."""
        if self.failure is not None:
            return f"the batching thread failed: {type(self.failure).__name__}: {self.failure}"
        if self._thread is None or not self._thread.is_alive():
            return "the batching thread is not running" + (" (stopping)" if self._stopping.is_set() else "")
        return None

    def submit(self, request: ActRequest, arrived: float | None = None) -> Future:
        """Queues ``request`` (``arrived``: its ``time.perf_counter()`` at arrival, default now); its future gets
        the [`ActReply`] (cancel it to drop a request not yet decoded).

        Raises:
            Overloaded: the queue is full.
            RuntimeError: the batcher is stopping.
        """
        if self._stopping.is_set():
            raise RuntimeError("the server is shutting down")
        if self.failure is not None:
            raise RuntimeError(self.unhealthy())
        pending = _Pending(request) if arrived is None else _Pending(request, arrived)
        with self._slots:
            full = self._live >= self.max_queue
            if not full:
                self._live += 1
        if full:
            batches_ahead = self.max_queue / self.max_batch_size + 1
            retry_after_s = max(1, math.ceil(batches_ahead * self._recent_batch_s))
            raise Overloaded(
                f"{self.max_queue} requests are waiting, the most this server queues: retry in {retry_after_s} s",
                retry_after_s,
            )
        # a robot that gives up while its request waits frees the slot at once
        pending.future.add_done_callback(lambda future: future.cancelled() and self._release(pending))
        if self._queue.qsize() > 2 * self.max_queue:  # mostly requests nobody waits for: let go of their data now
            self._drop_cancelled()
        self._queue.put_nowait(pending)
        return pending.future

    def _drop_cancelled(self) -> None:
        """Takes the cancelled requests out of the queue (a flood of robots that hang up holds at most
        ``2 * max_queue`` requests' images until the worker reaches them)."""
        with self._queue.mutex:
            kept = [pending for pending in self._queue.queue if not pending.future.cancelled()]
            self.dropped += len(self._queue.queue) - len(kept)
            self._queue.queue.clear()
            self._queue.queue.extend(kept)

    def _run(self) -> None:
        try:
            self._serve()
        except BaseException as error:  # noqa: BLE001 (a bug: /health says so, the queued requests get the error)
            self.failure = error
            logger.exception("the batching thread failed: no more requests are served")
            stranded = list(self._in_hand)
            while True:
                try:
                    stranded.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            for pending in stranded:  # their robots get a 500 saying why, rather than waiting forever
                if not pending.future.done() and (
                    pending.future.running() or pending.future.set_running_or_notify_cancel()
                ):
                    pending.future.set_exception(RuntimeError(self.unhealthy()))

    def _serve(self) -> None:
        while not (self._stopping.is_set() and self._queue.empty()):
            try:
                first = self._take(timeout=0.1)
            except queue.Empty:
                continue
            batch = self._in_hand = [self._seen(first)]
            deadline = time.perf_counter() + self.max_wait_s
            while len(batch) < min(self.max_batch_size, self._active_robots(len(batch)) + self.waiting):
                try:
                    remaining = deadline - time.perf_counter()
                    pending = self._take(timeout=remaining) if remaining > 0 else self._take()
                except queue.Empty:
                    break
                batch.append(self._seen(pending))
            live = [p for p in batch if p.future.set_running_or_notify_cancel()]
            self.dropped += len(batch) - len(live)
            if live:
                self._decode(live)

    def _take(self, timeout: float | None = None) -> _Pending:
        """The next live queued request (cancelled ones on the way dropped and counted), its slot freed.

        Raises:
            queue.Empty: none within ``timeout`` (None: none now).
        """
        deadline = None if timeout is None else time.perf_counter() + timeout
        while True:
            if deadline is None:
                pending = self._queue.get_nowait()
            else:
                pending = self._queue.get(timeout=max(0.0, deadline - time.perf_counter()))
            self._release(pending)
            if not pending.future.cancelled():
                return pending
            self.dropped += 1

    def _seen(self, pending: _Pending, at: float | None = None) -> _Pending:
        """Notes the request's session as active (``at``: its reply's time; default its arrival)."""
        session = pending.request.session
        self._last_seen[session] = max(self._last_seen.get(session, -math.inf), at or pending.arrived)
        return pending

    def _active_robots(self, in_hand: int) -> int:
        """How many requests a batch may still expect: the sessions active in the last ``ACTIVE_WINDOW_S`` (any
        number while anonymous requests arrive), at least the ``in_hand`` ones."""
        now = time.perf_counter()
        recent = [s for s, seen in self._last_seen.items() if now - seen < ACTIVE_WINDOW_S]
        if len(self._last_seen) > 4 * len(recent) + 64:  # forget robots long gone
            self._last_seen = {s: self._last_seen[s] for s in recent}
        return self.max_batch_size if None in recent else max(len(recent), in_hand)

    def _decode(self, batch: list[_Pending]) -> None:
        """Decodes the batch; each robot's future gets its reply the moment its row is decoded (a failing batch is
        retried one request at a time by the service: a failure reaches only its own robot)."""
        started, left = time.perf_counter(), [len(batch)]

        def on_reply(index: int, result) -> None:
            left[0] -= 1
            if not left[0]:  # booked before the batch's last reply, so that /stats after a reply counts it
                self._count(batch, started)
            future = batch[index].future
            if isinstance(result, BaseException):
                future.set_exception(result)
            else:
                future.set_result(result)

        self.service.act_each([p.request for p in batch], [p.arrived for p in batch], on_reply)

    def _count(self, batch: list[_Pending], started: float) -> None:
        """Books a decoded batch."""
        done = time.perf_counter()
        for pending in batch:  # a robot is active until a while after its reply, however long it queued
            self._seen(pending, done)
        self.batches += 1
        self._recent_batch_s = 0.8 * self._recent_batch_s + 0.2 * (done - started)
