"""How a Ray Serve replica's batching forms batches, apart from everything before it (no cluster, no proxy, no
router): ``serve.batch`` as ``PolicyDeployment`` builds it (the largest bucket, ``max_wait_ms``), a stand-in decode in
a worker thread as the replica runs its own (``asyncio.to_thread``), and K robots that each send their next request
a few ms after their reply. Prints the robots a batch and the event loop's lag while decodes run, for a decode that
releases the GIL (torch's kernels) and one that holds it (pure-Python host work).

    python examples/benchmarks/replica_batching.py                       # K = 4 8 16, bucket 8, 50 ms decodes
    python examples/benchmarks/replica_batching.py --robots 8 --seconds 2 --decode-ms 20 --output runs/batching.json

If the batches here hold K robots (up to the bucket) while a loaded Ray Serve deployment's hold one (docs/serving.md),
the replica's batching is not what splits them: the requests reach the replica one at a time.
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import sys
import time

from hf_specvla.run_folder import write_json_atomic


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--robots", type=int, nargs="+", default=[4, 8, 16], help="K values (default: 4 8 16)")
    parser.add_argument("--bucket", type=int, default=8, help="the largest bucket: serve.batch's max_batch_size")
    parser.add_argument("--max-wait-ms", type=float, default=2.0, help="serve.batch's batch_wait_timeout_s, in ms")
    parser.add_argument("--decode-ms", type=float, default=50.0, help="the stand-in decode's duration (default: 50)")
    parser.add_argument("--seconds", type=float, default=5.0, help="per K and decode kind (default: 5)")
    parser.add_argument("--output", default=None, help="also write the figures as JSON here")
    args = parser.parse_args(argv)
    if min(args.robots) < 1 or args.bucket < 1 or args.decode_ms <= 0 or args.seconds <= 0 or args.max_wait_ms < 0:
        parser.error("--robots and --bucket must be >= 1, --decode-ms and --seconds > 0, --max-wait-ms >= 0")
    return args


def _holding_the_gil(seconds: float) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


async def _measure(robots: int, decode, args) -> dict:
    import ray.serve.batching as batching
    from ray import serve

    # serve.batch reads the replica's context only to warn when max_ongoing_requests caps the batch: not here
    batching._BatchQueue._warn_if_max_batch_size_exceeds_max_ongoing_requests = lambda queue: None
    sizes: list[int] = []

    async def decode_batch(items: list[int]) -> list[int]:
        sizes.append(len(items))
        await asyncio.to_thread(decode, args.decode_ms / 1000)
        return items

    batched = serve.batch(max_batch_size=args.bucket, batch_wait_timeout_s=args.max_wait_ms / 1000)(decode_batch)
    until = time.perf_counter() + args.seconds

    async def robot(index: int) -> int:
        sent = 0
        while time.perf_counter() < until:
            await batched(index)
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
    for kind, decode in (("releases the GIL", time.sleep), ("holds the GIL", _holding_the_gil)):
        for robots in args.robots:
            rows.append({"decode": kind, **asyncio.run(_measure(robots, decode, args))})
    print(f"\nserve.batch alone: bucket {args.bucket}, max_wait_ms {args.max_wait_ms:g}, a {args.decode_ms:g} ms "
          f"decode in a worker thread, {args.seconds:g} s each\n")  # fmt: skip
    print("| decode | robots (K) | requests | batches | robots a batch | event loop lag p50 / max ms |")
    print("|---|---:|---:|---:|---:|---|")
    for row in rows:
        print(f"| {row['decode']} | {row['robots']} | {row['requests']} | {row['batches']} | {row['robots_a_batch']} "
              f"| {row['loop_lag_p50_ms']} / {row['loop_lag_max_ms']} |")  # fmt: skip
    if args.output:
        write_json_atomic(args.output, {"settings": vars(args), "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
