"""Serving under load: K concurrent robots against three embedded policy servers and Ray Serve, in turn.

Three servers over one policy in one server process (the graphs compiled once, shared): **greedy** (transformers'
compiled greedy decoding at every batch size: what a plain server does), **always** (the speculative method at every
batch size) and **adaptive** (speculative or greedy per batch size, whichever its start-up calibration and the
traffic measure faster: ``hf-specvla serve``'s default). For each K in ``--robots`` and each repeat, the three are
driven in turn (order rotated per repeat) by K robot threads over the same episodes; each run starts on fresh
servers (new services: no sessions, timings or per-bucket choices from an earlier run; adaptive calibrates anew on
the compiled graphs), and its row records that server's final mode and share of speculative batches per bucket.

**Ray Serve** (``ray``, a fourth server; ``--no-ray`` leaves it out, ``--ray-replicas`` sets its size, default 2):
the application ``hf-specvla serve --ray`` and ``serve run`` deploy (``hf_specvla.serving.ray_deployment:build_app``)
with the same policy, method, buckets, batching wait, calibration calls and queue, and no ``speculate_buckets``: each
replica runs ``hf-specvla serve``'s default, adaptive (it compiles, calibrates and chooses per bucket on its own).
Each replica gets ``--ray-threads`` torch threads (default 1) and as many of the cluster's CPUs, so 2 replicas x 1
thread fill this machine's 2 cores where an embedded server decodes on 1: the row is what a second replica buys, not
a like-for-like decode. The local Ray cluster (``replicas x threads`` CPUs, no dashboard) and Serve's HTTP proxy
start once per script run, in this process, after the embedded servers' warm-up; every Ray run deploys the
application anew (fresh replicas: no sessions, timings or choices from an earlier run; each compiles and calibrates
again, timed as ``deploy_s``) and deletes it after, so no replica is up during the other servers' runs. The cluster's
idle processes stay up throughout (a little CPU under every server's runs alike). The robots' client echoes each
robot's ``draft_state``, so its drafts do not depend on the replica that answers. A Ray row's server record holds,
per replica, its calibration and its choices (each replica's own ``/info`` and ``/stats``, read until every replica
has answered).

**Robots** (``--driver``): ``replay`` (default) sends the observations of recorded greedy episodes (Meta-World,
tasks x seeds, recorded once in this process): at r = 0 every server acts as greedy, so a robot would meet exactly
these observations, and the load is the real one without K simulators competing with the server for this machine's
2 cores (on a lab's network the robots are other machines). ``simulate`` runs K Meta-World robots
(``hf_specvla.metaworld.fleet``, as ``hf-specvla robots``): actions per second then include the simulators' time.

Reported per K and server (medians over repeats, ``[min-max]`` for actions/s, the ratio to the same repeat's
greedy run and p95): actions per second (actions returned to all robots / wall time;
a chunked policy returns its chunk), request latency p50 / p95 (client side), and where a request's time goes:
waiting for its batch (queue; in brackets the part of it before the request could join one, its intake: the
body read and checked), the batch's decode (the server's own ``predict_action`` call: a local call on the
same observations) and the rest (HTTP, serialisation, the client); ``early``: the share of replies that left before
their batch's call returned (their row done first: the reply's ``served.early``).
Every server's actions are checked equal, Ray Serve's included.

    python examples/benchmarks/serving_load.py --output runs/serving_load.json            # 2 idle cores: ~30 min +
                                                                                          # a Ray deployment per run
    python examples/benchmarks/serving_load.py --no-ray --output runs/serving_load.json   # embedded only, ~30 min
    python examples/benchmarks/serving_load.py --tiny --output /tmp/serving_load.json     # eager, K = 1, 2
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
KINDS = ("greedy", "always", "adaptive")  # the embedded servers
RAY = "ray"  # Ray Serve's row
TASKS = ["reach-v3", "push-v3", "drawer-open-v3", "button-press-topdown-v3", "window-open-v3", "door-open-v3"]

logger = logging.getLogger("serving_load")


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)  # fmt: skip
    parser.add_argument("--policy", default=str(ROOT / "policies" / "mt10_vla3"))
    parser.add_argument("--method", default="exact", help="the speculative method (a preset or a method name)")
    parser.add_argument("--robots", type=int, nargs="+", default=[1, 2, 4, 8, 16], help="the K values")
    parser.add_argument("--buckets", type=int, nargs="+", default=None, help="default: 1 2 4 ... up to the largest K")
    parser.add_argument("--repeats", type=int, default=3, help="rounds over the servers, order rotated (ABCD, BCDA...)")
    parser.add_argument("--episodes", type=int, default=None, help="episodes per run (default: max(2 K, 6))")
    parser.add_argument("--max-episode-steps", type=int, default=60)
    parser.add_argument("--seed-start", type=int, default=100000)
    parser.add_argument("--calibration-calls", type=int, default=5)
    parser.add_argument("--max-wait-ms", type=float, default=2.0)
    parser.add_argument("--output", required=True, help="the JSON of every run and the table")
    parser.add_argument("--driver", choices=("replay", "simulate"), default="replay", help="see the module docstring")
    parser.add_argument("--no-ray", action="store_true", help="leave Ray Serve out: the three embedded servers only")
    parser.add_argument("--ray-replicas", type=int, default=2, help="Ray Serve's replicas")
    parser.add_argument("--ray-threads", type=int, default=1, help="torch threads (and Ray CPUs) per replica")
    parser.add_argument("--ray-speculate", choices=("adaptive", "always"), default="adaptive",
                        help="the replicas' choice: calibrated per bucket (the default), or speculative at every "
                             "bucket (as the embedded 'always' server): tells the chooser's part apart")  # fmt: skip
    parser.add_argument("--tiny", action="store_true", help="eager prior+jacobi, K = 1 2, 1 repeat, short episodes")
    parser.add_argument("--serve", default=None, help=argparse.SUPPRESS)  # internal: the server process's settings
    args = parser.parse_args(argv)
    if args.tiny:
        args.method, args.robots, args.repeats, args.max_episode_steps = "prior+jacobi", [1, 2], 1, 6
        args.calibration_calls, args.episodes = 1, 2
    if any(k < 1 for k in args.robots) or args.repeats < 1:
        parser.error(f"--robots must be >= 1 and --repeats >= 1, got {args.robots} and {args.repeats}")
    if args.ray_replicas < 1 or args.ray_threads < 1:
        parser.error(f"--ray-replicas and --ray-threads must be >= 1, got {args.ray_replicas} and {args.ray_threads}")
    cpus = args.ray_replicas * args.ray_threads
    if args.serve is None and not args.no_ray:
        if cpus > (os.cpu_count() or 1):
            parser.error(f"--ray-replicas {args.ray_replicas} x --ray-threads {args.ray_threads} need {cpus} CPUs; "
                         f"this machine has {os.cpu_count()}: fewer replicas or threads, or --no-ray")  # fmt: skip
        try:
            from hf_specvla.serving.ray_deployment import require_ray

            require_ray()
        except ImportError as error:
            parser.error(f"{error}; or --no-ray for the embedded servers only")
    args.kinds = KINDS if args.no_ray else (*KINDS, RAY)
    args.buckets = args.buckets or [2**i for i in range(max(args.robots).bit_length() + 1) if 2**i <= max(args.robots)]
    if args.buckets[-1] < max(args.robots):
        args.buckets.append(2 ** (max(args.robots) - 1).bit_length())
    return args


# ----------------------------------------------------------------------------- the server process
def serve(settings: dict) -> None:
    """Three servers over one policy; prints one JSON line (their URLs, the calibration), then, for every line read
    on stdin (one per run), stops them and starts fresh ones (new services: no sessions, timings or per-bucket
    choices from an earlier run; the compiled graphs are the process's and stay) and prints their URLs again. Ends
    at the end of stdin."""
    import torch

    from hf_specvla.serving import PolicyService, ServeConfig
    from hf_specvla.serving.server import PolicyServer

    torch.set_num_threads(1)
    buckets = tuple(settings["buckets"])
    base = dict(method=settings["method"], buckets=buckets, max_wait_ms=settings["max_wait_ms"],
                calibration_calls=settings["calibration_calls"], max_queue=4 * buckets[-1])  # fmt: skip
    adaptive = PolicyService.from_pretrained(settings["policy"], ServeConfig(**base))
    started = time.perf_counter()
    calibration = adaptive.warm_up()  # compiles every bucket in both modes; the others share the graphs
    compile_s = time.perf_counter() - started
    policy, generation = adaptive.policy, 0
    while True:
        services = {
            "adaptive": adaptive,
            "always": PolicyService(policy, ServeConfig(**{**base, "speculate_buckets": buckets})),
            "greedy": PolicyService(policy, ServeConfig(**{**base, "speculate_buckets": ()})),
        }
        servers = {kind: PolicyServer(service, port=0) for kind, service in services.items()}
        for server in servers.values():
            server.__enter__()
        print(json.dumps({"urls": {k: s.url for k, s in servers.items()}, "calibration": calibration,
                          "warm_up_s": round(compile_s, 1), "method": adaptive.method.name,
                          "baseline": adaptive.baseline.name, "generation": generation}), flush=True)  # fmt: skip
        command = sys.stdin.readline()
        for server in servers.values():
            server.__exit__(None, None, None)
        for service in services.values():
            service.close()
        if not command:
            return
        generation += 1
        adaptive = PolicyService(policy, ServeConfig(**base))
        calibration = adaptive.warm_up()  # calibrates anew (the graphs are compiled: nothing compiles again)


# ----------------------------------------------------------------------------- Ray Serve
class RayServeRuns:
    """A local Ray cluster and Serve's HTTP proxy, started once (``with``: ``replicas x threads`` CPUs, no
    dashboard; stopped at the end), and the policy application deployed fresh for each run ([`deploy`]) and deleted
    after it ([`delete`]), as ``serve run hf_specvla.serving.ray_deployment:build_app`` would deploy it."""

    def __init__(self, settings: dict, replicas: int, threads: int, speculate: str = "adaptive"):
        from hf_specvla.serving.ray_deployment import require_ray

        self.ray, self.serve = require_ray()
        self.replicas, self.threads, self.deployments = replicas, threads, 0
        buckets = settings["buckets"]
        #: the builder's arguments: the embedded servers' settings, adaptive (no speculate_buckets)
        self.app_args = {"policy": str(Path(settings["policy"]).resolve()), "method": settings["method"],
                         "buckets": list(buckets), "max_wait_ms": settings["max_wait_ms"],
                         "calibration_calls": settings["calibration_calls"], "max_queue": 4 * buckets[-1],
                         "num_replicas": replicas, "threads": threads}  # fmt: skip
        if speculate == "always":
            self.app_args["speculate_buckets"] = list(buckets)
        self.url = ""

    def __enter__(self) -> RayServeRuns:
        import socket

        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        started = time.perf_counter()
        self.ray.init(address="local", num_cpus=self.replicas * self.threads, num_gpus=0, include_dashboard=False,
                      object_store_memory=100 * 2**20, log_to_driver=False,
                      runtime_env={"env_vars": {"OMP_NUM_THREADS": str(self.threads)}})  # fmt: skip
        with socket.socket() as probe:  # a free port for the proxy
            probe.bind(("127.0.0.1", 0))
            port = probe.getsockname()[1]
        self.serve.start(http_options={"host": "127.0.0.1", "port": port})
        self.url = f"http://127.0.0.1:{port}"
        logger.info("Ray cluster (%d CPUs) and Serve's proxy on %s up in %.0f s", self.replicas * self.threads,
                    self.url, time.perf_counter() - started)  # fmt: skip
        return self

    def __exit__(self, *exc) -> None:
        try:
            self.serve.shutdown()
        finally:
            self.ray.shutdown()

    def deploy(self) -> dict:
        """The application deployed anew (returns once every replica has compiled and calibrated): its URL, its
        number (1, 2, ... in this script run) and the seconds it took (``deploy_s``)."""
        from hf_specvla.serving.ray_deployment import APP_NAME, build_app

        started = time.perf_counter()
        self.serve.run(build_app(self.app_args), name=APP_NAME, route_prefix="/")
        self.deployments += 1
        return {"url": self.url, "deployment": self.deployments, "deploy_s": round(time.perf_counter() - started, 1)}

    def delete(self) -> None:
        """The application deleted (its replicas stopped): nothing of it runs during the other servers' runs."""
        from hf_specvla.serving.ray_deployment import APP_NAME

        self.serve.delete(APP_NAME)


def _per_replica(url: str, route: str, replicas: int, tries: int = 100) -> dict[str, dict]:
    """``GET route`` until every replica has answered (Ray routes each request to one): ``{replica: body}``."""
    bodies: dict[str, dict] = {}
    for _ in range(tries):
        body = _get_json(url + route)
        bodies.setdefault(body["replica"], body)
        if len(bodies) == replicas:
            break
    else:
        logger.warning("%s: %d of %d replicas answered in %d tries", route, len(bodies), replicas, tries)
    return bodies


# ----------------------------------------------------------------------------- the robots
def _choices(stats: dict) -> dict:
    """A server's (or replica's) choices over a run: each bucket's final mode and share of speculative batches, and
    the run's share of speculative batches."""
    buckets = stats["buckets"]
    return {
        "speculative_share": stats.get("speculative_share"),
        "final_modes": {bucket: row.get("mode") for bucket, row in buckets.items()},
        "bucket_speculative_share": {bucket: row.get("speculative_share") for bucket, row in buckets.items()},
    }


def _server_record(started: dict, stats: dict) -> dict:
    """What a run's embedded server was and chose: its generation (a fresh one per run), its start-up calibration
    and its choices ([`_choices`])."""
    return {"generation": started["generation"], "calibration": started["calibration"], **_choices(stats)}


def _ray_record(deployed: dict, replicas: int) -> dict:
    """What a run's Ray deployment was and chose: its number and deployment time, and per replica its start-up
    calibration and its choices ([`_choices`])."""
    infos = _per_replica(deployed["url"], "/info", replicas)
    stats = _per_replica(deployed["url"], "/stats", replicas)
    per_replica = {replica: {"calibration": infos[replica]["calibration"] if replica in infos else None,
                             **_choices(body)} for replica, body in stats.items()}  # fmt: skip
    return {"deployment": deployed["deployment"], "deploy_s": deployed["deploy_s"], "replicas": per_replica}


def _get_json(url: str) -> dict:
    import urllib.request

    with urllib.request.urlopen(url, timeout=30) as response:  # loopback, the servers this script started
        return json.loads(response.read())


def replay(url: str, robots: int, episodes: list[list[dict]], chunk_length: int) -> dict:
    """One run: ``robots`` threads, each taking the next recorded episode and sending its observations in order
    (a new session per episode, reset at its first); the figures of :func:`drive`'s rows."""
    import queue
    import threading

    from hf_specvla.serving import PolicyClient

    pending: queue.SimpleQueue = queue.SimpleQueue()
    for index, episode in enumerate(episodes):
        pending.put((index, episode))
    records: list[dict] = []
    errors: list[BaseException] = []

    def robot(number: int) -> None:
        try:
            run_episodes(number)
        except BaseException as error:  # noqa: BLE001 (re-raised by the run)
            errors.append(error)

    def run_episodes(number: int) -> None:
        client = PolicyClient(url)
        while True:
            try:
                index, episode = pending.get_nowait()
            except queue.Empty:
                return
            record = {"key": str(index), "latencies_ms": [], "server_ms": [], "queue_ms": [], "intake_ms": [],
                      "batch_sizes": [], "target_forwards": [], "batch_forwards": [], "speculative": [], "early": [],
                      "actions": []}  # fmt: skip
            for step, o in enumerate(episode):
                sent = time.perf_counter()
                reply = client.act(o["image"], o["instruction"], o["state"], session=f"{number}-{index}",
                                   reset=step == 0)  # fmt: skip
                record["latencies_ms"].append(1000 * (time.perf_counter() - sent))
                for key in (
                    "server_ms",
                    "queue_ms",
                    "intake_ms",
                    "batch_size",
                    "target_forwards",
                    "batch_forwards",
                    "speculative",
                    "early",
                ):
                    record[key + "s" if key == "batch_size" else key].append(getattr(reply.served, key))
                record["actions"].append(reply.action.tolist())
            records.append(record)

    started = time.perf_counter()
    threads = [threading.Thread(target=robot, args=(i,)) for i in range(robots)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    wall = time.perf_counter() - started
    if errors:
        raise RuntimeError(f"{len(errors)} of {robots} robots failed, the first with {errors[0]!r}") from errors[0]
    requests = sum(len(r["latencies_ms"]) for r in records)
    summary = {"actions_per_second": requests * chunk_length / wall, "env_steps": requests * chunk_length,
               "speculative_fraction": sum(x for r in records for x in r["speculative"]) / requests,
               "target_forwards_per_request": statistics.mean(x for r in records for x in r["target_forwards"]),
               }  # fmt: skip
    return _figures(summary, sorted(records, key=lambda r: int(r["key"])))


def drive(url: str, robots: int, episodes: int, args, folder: Path) -> dict:
    """One run: ``robots`` robot threads over ``episodes`` episodes; the fleet's summary plus where time went."""
    from hf_specvla.metaworld.fleet import RobotsConfig, run_robots

    per_task = -(-episodes // len(TASKS))
    config = RobotsConfig(tasks=TASKS, episodes_per_task=per_task, robots=robots, seed_start=args.seed_start,
                          max_episode_steps=args.max_episode_steps, server=url)  # fmt: skip
    summary = run_robots(config, folder, progress=False)
    records = [json.loads(line) for line in (folder / "episodes.jsonl").read_text().splitlines()]
    for record in records:
        record["key"] = f"{record['task']}/{record['seed']}"
    return _figures(summary, records)


def _figures(summary: dict, records: list[dict]) -> dict:
    """A run's row: throughput, latency percentiles and where a request's time went."""
    from hf_specvla.metaworld.fleet import percentiles

    latency = [x for r in records for x in r["latencies_ms"]]
    server = [x for r in records for x in r["server_ms"]]
    queue = [x for r in records for x in r["queue_ms"]]
    decode = [s - q for s, q in zip(server, queue)]  # the batch's call (and building the reply)
    return {
        "actions_per_second": summary["actions_per_second"],
        **{f"latency_{k}_ms": v for k, v in percentiles(latency, (50, 95)).items()},
        **{f"decode_{k}_ms": v for k, v in percentiles(decode, (50, 95)).items()},
        "queue_mean_ms": statistics.mean(queue),
        # of the queue, the request's intake before it could join a batch (its body read, its checks); 0 where a
        # record does not hold it (the simulate driver's fleet records)
        "intake_mean_ms": statistics.mean(x for r in records for x in r.get("intake_ms", [0.0])),
        "decode_mean_ms": statistics.mean(decode),
        "rest_mean_ms": statistics.mean(lat - s for lat, s in zip(latency, server)),
        "mean_batch_size": statistics.mean(x for r in records for x in r["batch_sizes"]),
        "speculative_fraction": summary["speculative_fraction"],
        "forwards_per_request": summary["target_forwards_per_request"],
        "batch_forwards_per_request": statistics.mean(x for r in records for x in r["batch_forwards"]),
        "answered_early_share": statistics.mean(x for r in records for x in r["early"]),
        "requests": len(latency),
        "env_steps": summary["env_steps"],
        "actions": {r["key"]: r["actions"] for r in records},
    }


def record(args) -> tuple[list[list[dict]], int]:
    """Greedy episodes of the policy (observations it decided on), enough for the largest run; its chunk length."""
    import torch

    from hf_specvla.metaworld.evaluation import record_observations
    from hf_specvla.policies import VLAPolicy

    torch.set_num_threads(1)
    policy = VLAPolicy.from_pretrained(args.policy)
    needed = args.episodes or max(2 * max(args.robots), 6)
    seeds = list(range(args.seed_start, args.seed_start + -(-needed // len(TASKS))))
    chunk = policy.config.chunk_length
    started = time.perf_counter()
    episodes = record_observations(policy, TASKS, seeds, max_steps=-(-args.max_episode_steps // chunk))
    logger.info("recorded %d greedy episodes (%d observations) in %.0f s", len(episodes),
                sum(map(len, episodes)), time.perf_counter() - started)  # fmt: skip
    n = len(seeds)  # task-major -> seed-major: a run of any size covers the tasks alike
    episodes = [episodes[t * n + i] for i in range(n) for t in range(len(TASKS))]
    return episodes[:needed], chunk


def _spread(runs: list[dict], key: str, digits: int = 1, unit: str = "") -> str:
    """``median [min-max]`` of ``key`` over the repeats."""
    values = [r[key] for r in runs]
    low, median, high = (f"{v:.{digits}f}{unit}" for v in (min(values), statistics.median(values), max(values)))
    return f"{median} [{low}-{high}]"


def table(rows: list[dict], robots: list[int], servers: dict[str, str]) -> str:
    """The report: a line per K and server (``servers``: kind -> its label, in order)."""
    header = ("| K | server | actions/s | vs greedy | p50 ms | p95 ms | queue (intake) / decode / rest ms | batch "
              "| spec. | early | fwd/req |")  # fmt: skip
    lines = [header, "|---:|---|---:|---:|---:|---:|---|---:|---:|---:|---:|"]
    for k in robots:
        runs = {kind: sorted((r for r in rows if r["robots"] == k and r["kind"] == kind), key=lambda r: r["repeat"])
                for kind in servers}  # fmt: skip
        for kind, label in servers.items():
            m = {key: statistics.median(r[key] for r in runs[kind]) for key in runs[kind][0] if
                 isinstance(runs[kind][0][key], int | float) and key not in ("robots", "repeat")}  # fmt: skip
            ratios = [{"ratio": r["actions_per_second"] / g["actions_per_second"]}  # the same repeat's greedy run
                      for r, g in zip(runs[kind], runs["greedy"])]  # fmt: skip
            forwards = m.get("forwards_per_request")
            lines.append(f"| {k} | {label} | {_spread(runs[kind], 'actions_per_second')} | "
                         f"{_spread(ratios, 'ratio', 2, 'x')} | {m['latency_p50_ms']:.1f} | "
                         f"{_spread(runs[kind], 'latency_p95_ms')} | {m['queue_mean_ms']:.1f} "
                         f"({m.get('intake_mean_ms', 0):.1f}) / "
                         f"{m['decode_mean_ms']:.1f} / {m['rest_mean_ms']:.1f} | {m['mean_batch_size']:.2f} | "
                         f"{m['speculative_fraction']:.0%} | {m.get('answered_early_share', 0):.0%} | "
                         f"{'-' if forwards is None else f'{forwards:.2f}'} |")  # fmt: skip
    return "\n".join(lines)


def run_once(url: str, robots: int, args, recorded: list, chunk_length: int, folder: Path) -> dict:
    """One run against the server at ``url``: ``robots`` robots, replaying or simulating (``--driver``)."""
    episodes = args.episodes or max(2 * robots, 6)
    if args.driver == "replay":
        return replay(url, robots, recorded[:episodes], chunk_length)
    return drive(url, robots, episodes, args, folder)


def main(argv=None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    if args.serve is not None:
        serve(json.loads(args.serve))
        return 0
    settings = {"policy": args.policy, "method": args.method, "buckets": args.buckets,
                "max_wait_ms": args.max_wait_ms, "calibration_calls": args.calibration_calls}  # fmt: skip
    recorded, chunk_length = [], 0
    if args.driver == "replay":
        recorded, chunk_length = record(args)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    process = subprocess.Popen([sys.executable, __file__, "--output", "-", "--serve", json.dumps(settings)],
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)  # fmt: skip
    rows: list[dict] = []
    ray_runs = None
    try:
        started = first = json.loads(process.stdout.readline())
        logger.info("servers up after %.0f s of warm-up: %s", started["warm_up_s"], started["urls"])
        with contextlib.ExitStack() as stack:
            if RAY in args.kinds:  # the cluster once; the application deployed per run
                ray_runs = stack.enter_context(
                    RayServeRuns(settings, args.ray_replicas, args.ray_threads, args.ray_speculate)
                )
            scratch = Path(stack.enter_context(tempfile.TemporaryDirectory()))
            fresh = True  # the embedded servers have served no run since they (re)started
            for repeat in range(args.repeats):
                for k in args.robots:
                    shift = repeat % len(args.kinds)
                    for kind in args.kinds[shift:] + args.kinds[:shift]:
                        folder = scratch / f"{kind}-{k}-{repeat}"
                        if kind == RAY:
                            run = _ray_run(ray_runs, k, args, recorded, chunk_length, folder)
                        else:
                            if not fresh:  # every run on fresh servers: no state from the runs before
                                process.stdin.write("restart\n")
                                process.stdin.flush()
                                started = json.loads(process.stdout.readline())
                            fresh = False
                            run = run_once(started["urls"][kind], k, args, recorded, chunk_length, folder)
                            run["server"] = _server_record(started, _get_json(started["urls"][kind] + "/stats"))
                        rows.append({"robots": k, "kind": kind, "repeat": repeat, **run})
                        logger.info("K=%d %s: %.1f actions/s, p95 %.1f ms", k, kind, run["actions_per_second"],
                                    run["latency_p95_ms"])  # fmt: skip
    finally:
        process.stdin.close()  # the server process stops its servers and ends
        try:
            process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            process.kill()
    for k in args.robots:  # lossless: every server's episodes executed the same actions
        runs = [r for r in rows if r["robots"] == k]
        for run in runs[1:]:
            assert run["actions"] == runs[0]["actions"], f"K={k}: {run['kind']} acted otherwise than {runs[0]['kind']}"
    servers = {kind: kind for kind in KINDS}
    if ray_runs is not None:
        servers[RAY] = f"ray x{args.ray_replicas}"
    text = table(rows, args.robots, servers)
    print(f"method {started['method']} vs {started['baseline']}; buckets {args.buckets}; calibration:")
    print(json.dumps(started["calibration"]))
    if ray_runs is not None:
        deploy = [{"deploy_s": r["server"]["deploy_s"]} for r in rows if r["kind"] == RAY]
        each = _spread(deploy, "deploy_s", unit=" s")
        print(f"ray x{args.ray_replicas}: Ray Serve, {args.ray_replicas} replicas x {args.ray_threads} thread(s), "
              f"{args.ray_speculate}; {len(deploy)} deployments, {each} each")  # fmt: skip
    print(text)
    for row in rows:
        row.pop("actions")
    ray = None if ray_runs is None else {"replicas": args.ray_replicas, "threads": args.ray_threads,
                                         "app_args": ray_runs.app_args}  # fmt: skip
    output = {"settings": vars(args), "servers": first, "ray": ray, "rows": rows, "table": text}
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    Path(args.output).write_text(json.dumps(output, indent=1))
    return 0


def _ray_run(ray_runs: RayServeRuns, robots: int, args, recorded: list, chunk_length: int, folder: Path) -> dict:
    """One run on Ray Serve: the application deployed fresh, driven, its replicas' records read, deleted."""
    deployed = ray_runs.deploy()
    try:
        run = run_once(deployed["url"], robots, args, recorded, chunk_length, folder)
        run["server"] = _ray_record(deployed, ray_runs.replicas)
    finally:
        ray_runs.delete()
    return run


if __name__ == "__main__":
    sys.exit(main())
