"""A Ray Serve replica's batching (issue 77), without a cluster: K robots that each send their next request a few ms
after their reply, against a stand-in service whose decode sleeps and answers its rows at different times (as a
speculative batch does: each row when done). The replica batches by the one-machine server's rule (its ``Batcher``):
batches hold the robots waiting. Ray's ``serve.batch``, which the replica used before, forms the next batch while one
decodes, so the same robots split into batches of one."""

from __future__ import annotations

import asyncio
import statistics
import threading
import time

import numpy as np
import pytest

from hf_specvla.serving import ServeConfig
from hf_specvla.serving.batching import Batcher
from hf_specvla.serving.protocol import ActReply, ActRequest, ServedFigures
from hf_specvla.serving.ray_deployment import PolicyDeployment

DECODE_S, ROW_STAGGER_S, ROBOT_STEP_S = 0.03, 0.004, 0.002


class SleepingService:
    """A stand-in ``PolicyService``: a batch's decode sleeps; row i is answered (i + 1) x ``ROW_STAGGER_S`` in."""

    def __init__(self, config: ServeConfig):
        self.config, self.sizes, self._lock = config, [], threading.Lock()

    def act_each(self, requests, arrived, on_reply):
        with self._lock:  # one decoding thread, as the service has
            self.sizes.append(len(requests))
            started = time.perf_counter()
            for i, _ in enumerate(requests):
                time.sleep(max(0.0, started + (i + 1) * ROW_STAGGER_S - time.perf_counter()))
                figures = ServedFigures("stand-in", True, 1, len(requests), len(requests), 0.0, 0.0)
                on_reply(i, ActReply(np.zeros(4), figures))
            time.sleep(max(0.0, started + DECODE_S - time.perf_counter()))


def _request(robot: int) -> ActRequest:
    return ActRequest(np.zeros((8, 8, 3), np.uint8), "reach the goal", session=f"robot-{robot}")


async def _robots(act, robots: int, seconds: float) -> int:
    """``robots`` robots calling ``act`` in a loop for ``seconds``; the requests answered."""
    until = time.perf_counter() + seconds

    async def robot(index: int) -> int:
        answered = 0
        while time.perf_counter() < until:
            await act(_request(index), time.perf_counter())
            answered += 1
            await asyncio.sleep(ROBOT_STEP_S)
        return answered

    return sum(await asyncio.gather(*(robot(i) for i in range(robots))))


def _replica(service: SleepingService) -> PolicyDeployment:
    """A replica as Ray builds it, past its policy's load (which this test replaces by the stand-in)."""
    replica = PolicyDeployment.__new__(PolicyDeployment)
    replica.service, replica.batcher = service, Batcher(service).start()
    return replica


@pytest.mark.parametrize("robots", [4, 8])
def test_a_replica_batches_the_robots_waiting_whenever_their_replies_left(robots):
    service = SleepingService(ServeConfig(method="prior+jacobi", buckets=(1, 2, 4, 8), max_wait_ms=2.0))
    replica = _replica(service)
    try:
        answered = asyncio.run(_robots(replica.act, robots, seconds=1.5))
    finally:
        replica.batcher.stop()
    steady = service.sizes[3:]  # past the first batches, while the robots fall into step
    assert answered == sum(service.sizes) and len(steady) > 10
    assert statistics.mean(steady) >= 0.8 * robots, service.sizes


def test_serve_batch_splits_the_same_robots_into_batches_of_one():
    """Why the replica does not use ``serve.batch``: with each row answered when done, every robot's next request
    starts a batch of its own while the previous batch decodes (``max_concurrent_batches`` 1 only serialises them)."""
    batching = pytest.importorskip("ray.serve.batching")
    from ray import serve

    service = SleepingService(ServeConfig(method="prior+jacobi", buckets=(1, 2, 4, 8), max_wait_ms=2.0))

    async def run() -> int:
        loop = asyncio.get_running_loop()

        async def decode(items):
            def on_reply(index, reply):
                loop.call_soon_threadsafe(items[index][1].set_result, reply)

            await asyncio.to_thread(service.act_each, [r for r, _ in items], None, on_reply)
            return [None] * len(items)

        batched = serve.batch(max_batch_size=8, batch_wait_timeout_s=0.002)(decode)

        async def act(request, arrived):
            answer = loop.create_future()
            asyncio.ensure_future(batched((request, answer)))
            return await answer

        return await _robots(act, 8, seconds=1.5)

    # serve.batch reads a replica's context only to warn that max_ongoing_requests caps the batch: not here
    warn = batching._BatchQueue._warn_if_max_batch_size_exceeds_max_ongoing_requests
    batching._BatchQueue._warn_if_max_batch_size_exceeds_max_ongoing_requests = lambda queue: None
    try:
        asyncio.run(run())
    finally:
        batching._BatchQueue._warn_if_max_batch_size_exceeds_max_ongoing_requests = warn
    assert statistics.mean(service.sizes[3:]) < 2.0, service.sizes
