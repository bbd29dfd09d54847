"""How a Ray Serve replica's batching forms batches, apart from everything before it (no cluster, no proxy, no
router): K robots that each send their next request a few ms after their reply, a stand-in decode in a worker thread
that answers its rows one after another (``--row-stagger-ms`` apart, as a speculative batch answers each row when
done; 0: all at once), batched two ways: Ray's ``serve.batch`` (what replicas used before) and the replica's own
``Batcher`` (the one-machine server's rule, what ``PolicyDeployment`` runs now). Prints the robots a batch and the
event loop's lag, for a decode that releases the GIL (torch's kernels) and one that holds it (pure-Python host work).

    python examples/benchmarks/replica_batching.py                       # K = 4 8 16, bucket 8, 50 ms decodes
    python examples/benchmarks/replica_batching.py --robots 8 --seconds 2 --row-stagger-ms 0 --output runs/b.json

``serve.batch`` forms the next batch while one decodes: with replies all at once the robots' next requests arrive
together and fill it; with replies apart each robot's request starts a batch of its own (docs/serving.md).
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import sys
import threading
import time

import numpy as np

from hf_specvla.run_folder import write_json_atomic


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--robots", type=int, nargs="+", default=[4, 8, 16], help="K values (default: 4 8 16)")
    parser.add_argument("--bucket", type=int, default=8, help="the largest bucket: serve.batch's max_batch_size")
    parser.add_argument("--max-wait-ms", type=float, default=2.0, help="serve.batch's batch_wait_timeout_s, in ms")
    parser.add_argument("--decode-ms", type=float, default=50.0, help="the stand-in decode's duration (default: 50)")
    parser.add_argument("--seconds", type=float, default=5.0, help="per K and decode kind (default: 5)")
    parser.add_argument("--row-stagger-ms", type=float, default=4.0,
                        help="ms between the rows' replies within a batch (default: 4; 0: all at the end)")  # fmt: skip
    parser.add_argument("--output", default=None, help="also write the figures as JSON here")
    args = parser.parse_args(argv)
    if min(args.robots) < 1 or args.bucket < 1 or args.decode_ms <= 0 or args.seconds <= 0 or args.max_wait_ms < 0:
        parser.error("--robots and --bucket must be >= 1, --decode-ms and --seconds > 0, --max-wait-ms >= 0")
    if args.row_stagger_ms < 0:
        parser.error(f"--row-stagger-ms must be >= 0, got {args.row_stagger_ms:g}")
    return args


def _holding_the_gil(seconds: float) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


class _StandIn:
    """A stand-in ``PolicyService`` (what the replica's ``Batcher`` calls): one decoding thread; a batch's rows
    answered ``row_stagger_s`` apart, the call ``decode_s`` long in all."""

    def __init__(self, args, decode):
        from hf_specvla.serving import ServeConfig

        buckets = tuple(b for b in (1, 2, 4, 8, 16, 32, 64) if b < args.bucket) + (args.bucket,)
        self.config = ServeConfig(method="prior+jacobi", buckets=buckets, max_wait_ms=args.max_wait_ms)
        self.decode, self.decode_s, self.row_stagger_s = decode, args.decode_ms / 1000, args.row_stagger_ms / 1000
        self.sizes: list[int] = []
        self._lock = threading.Lock()

    def act_each(self, requests, arrived, on_reply) -> None:
        with self._lock:
            self.sizes.append(len(requests))
            started = time.perf_counter()
            for index in range(len(requests)):
                self.decode(max(0.0, started + (index + 1) * self.row_stagger_s - time.perf_counter()))
                on_reply(index, index)
            self.decode(max(0.0, started + self.decode_s - time.perf_counter()))


async def _measure(robots: int, decode, batching: str, args) -> dict:
    import ray.serve.batching as serve_batching
    from ray import serve

    from hf_specvla.serving.batching import Batcher
    from hf_specvla.serving.protocol import ActRequest

    service, loop = _StandIn(args, decode), asyncio.get_running_loop()
    batcher = None
    if batching == "serve.batch":
        # serve.batch reads the replica's context only to warn when max_ongoing_requests caps the batch: not here
        serve_batching._BatchQueue._warn_if_max_batch_size_exceeds_max_ongoing_requests = lambda queue: None

        async def decode_batch(items: list) -> list:
            def on_reply(index: int, result) -> None:
                loop.call_soon_threadsafe(items[index][1].set_result, result)

            await asyncio.to_thread(service.act_each, [r for r, _ in items], None, on_reply)
            return [None] * len(items)

        batched = serve.batch(max_batch_size=args.bucket, batch_wait_timeout_s=args.max_wait_ms / 1000)(decode_batch)

        async def act(request):
            answer = loop.create_future()
            asyncio.ensure_future(batched((request, answer)))
            return await answer
    else:
        batcher = Batcher(service).start()

        async def act(request):
            return await asyncio.wrap_future(batcher.submit(request))

    until = time.perf_counter() + args.seconds

    async def robot(index: int) -> int:
        sent = 0
        request = ActRequest(np.zeros((8, 8, 3), np.uint8), "reach the goal", session=f"robot-{index}")
        while time.perf_counter() < until:
            await act(request)
            sent += 1
            await asyncio.sleep(0.003)  # the robot's own step before its next request
        return sent

    lags: list[float] = []

    async def loop_lag() -> None:
        while time.perf_counter() < until:
            asked = time.perf_counter()
            await asyncio.sleep(0.01)
            lags.append(time.perf_counter() - asked - 0.01)

    sent = await asyncio.gather(*(robot(i) for i in range(robots)), loop_lag())
    if batcher is not None:
        batcher.stop()
    sizes = service.sizes
    return {"robots": robots, "requests": sum(sent[:-1]), "batches": len(sizes),
            "robots_a_batch": round(statistics.mean(sizes), 2),
            "loop_lag_p50_ms": round(1000 * statistics.median(lags), 1),
            "loop_lag_max_ms": round(1000 * max(lags), 1)}  # fmt: skip


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        import ray.serve  # noqa: F401
    except ImportError as error:
        sys.exit(f"needs Ray Serve ({error}): pip install 'hf_specvla[ray]'")
    rows = []
    for batching in ("serve.batch", "Batcher"):
        for kind, decode in (("releases the GIL", time.sleep), ("holds the GIL", _holding_the_gil)):
            for robots in args.robots:
                rows.append({"batching": batching, "decode": kind,
                             **asyncio.run(_measure(robots, decode, batching, args))})  # fmt: skip
    print(
        f"\nbatching alone: bucket {args.bucket}, max_wait_ms {args.max_wait_ms:g}, a {args.decode_ms:g} ms "
        f"decode in a worker thread, rows answered {args.row_stagger_ms:g} ms apart, {args.seconds:g} s each\n"
    )
    print("| batching | decode | robots (K) | requests | batches | robots a batch | event loop lag p50 / max ms |")
    print("|---|---|---:|---:|---:|---:|---|")
    for row in rows:
        print(f"| {row['batching']} | {row['decode']} | {row['robots']} | {row['requests']} | {row['batches']} | "
              f"{row['robots_a_batch']} | {row['loop_lag_p50_ms']} / {row['loop_lag_max_ms']} |")  # fmt: skip
    if args.output:
        write_json_atomic(args.output, {"settings": vars(args), "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
