"""Autoscaling on a local Ray cluster of two nodes (Ray's own ``ray.cluster_utils.Cluster``: a head and a second
node, one CPU each, so that a second replica of one CPU can only start on the other node): the example Serve
config's ``autoscaling_config`` (its delays shortened), robots added until Ray starts a second replica, which
serves; robots removed until Ray takes one away; every request answered on the way up and down.

The policy is the small shipped ``mt10_vla`` with an eager method: a replica's start is its load, no compile (a
compiled method's start is what ``--compile-cache`` shortens, tested in test_compile_cache.py)."""

from __future__ import annotations

import os
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

ray = pytest.importorskip("ray")
serve = pytest.importorskip("ray.serve")
requests = pytest.importorskip("requests")

from ray.cluster_utils import Cluster  # noqa: E402

from hf_specvla.serving.protocol import dumps  # noqa: E402
from hf_specvla.serving.ray_deployment import APP_NAME, DEPLOYMENT_NAME, PolicyAppArgs, policy_deployment  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
POLICY = ROOT / "policies" / "mt10_vla"
EXAMPLE = ROOT / "examples" / "serving" / "serve_config_autoscaling.yaml"
#: the example's delays, shortened so that the test sees a scale-up and a scale-down in a minute or two
FAST_AUTOSCALING = {"upscale_delay_s": 2, "downscale_delay_s": 8, "look_back_period_s": 2, "metrics_interval_s": 0.5,
                    "target_ongoing_requests": 2}  # fmt: skip
BUSY_ROBOTS = 8
#: seconds the second replica has to start and serve after the load rises, and Ray has to take it away after the
#: load falls: bounds on a loaded 2-core runner (the slow tier's other worker beside the cluster), not the figures
#: (measured alone: serving 35.6 s after the load rose; docs/serving.md), which the test prints
UP_WITHIN_S = 240
DOWN_WITHIN_S = 180

#: Serve's proxy (on the head node) sends every request to a replica on its own node until that one holds
#: ``max_ongoing_requests``; off, so that the second replica is sent robots wherever Ray starts it (docs/serving.md)
LOCAL_ROUTING = "RAY_SERVE_PROXY_PREFER_LOCAL_NODE_ROUTING"

pytestmark = [pytest.mark.ray, pytest.mark.skipif(not POLICY.is_dir(), reason=f"{POLICY} is missing")]


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _example_deployment() -> tuple[dict, dict]:
    """The example config's application args and its deployment's options."""
    config = yaml.safe_load(EXAMPLE.read_text())
    application = config["applications"][0]
    return application["args"], application["deployments"][0]


class Robots:
    """Robot threads posting ``/act`` in a loop; every answer that is not a 200 is kept."""

    def __init__(self, url: str, size: int):
        image = np.random.default_rng(0).integers(0, 256, (size, size, 3), dtype=np.uint8)
        self.body = dumps({"image": image, "instruction": "reach the goal", "state": np.zeros(4)})
        self.url, self.threads, self.failures, self.answered = url, [], [], 0
        self.lock = threading.Lock()

    def add(self, count: int) -> None:
        for _ in range(count):
            stop = threading.Event()
            thread = threading.Thread(target=self._run, args=(stop,), daemon=True)
            thread.start()
            self.threads.append((thread, stop))

    def remove(self, count: int) -> None:
        for _ in range(count):
            thread, stop = self.threads.pop()
            stop.set()
            thread.join(timeout=60)

    def _run(self, stop: threading.Event) -> None:
        with requests.Session() as session:
            while not stop.is_set():
                try:
                    reply = session.post(f"{self.url}/act", data=self.body, timeout=120)
                    failure = None if reply.status_code == 200 else f"{reply.status_code}: {reply.text[:200]}"
                except requests.RequestException as error:
                    failure = repr(error)
                with self.lock:
                    self.answered += failure is None
                    if failure is not None:
                        self.failures.append(failure)


#: (time, the deployment's replica states) each time they changed, for the test's report
TRANSITIONS: list[tuple[float, dict]] = []


def _replicas(state: str = "RUNNING") -> int:
    states = dict(serve.status().applications[APP_NAME].deployments[DEPLOYMENT_NAME].replica_states)
    if not TRANSITIONS or TRANSITIONS[-1][1] != states:
        TRANSITIONS.append((time.perf_counter(), states))
    return states.get(state, 0)


#: replica id -> (its node, its batches) as its ``/stats`` last said, for the test's report
STATS: dict[str, tuple[str, int]] = {}


def _serving_replicas(url: str, tries: int = 40) -> dict[str, str]:
    """replica id -> its node, for the replicas that have decoded a batch (``/stats``, asked ``tries`` times: the
    router spreads the asks)."""
    seen = {}
    for _ in range(tries):
        stats = requests.get(f"{url}/stats", timeout=30).json()
        STATS[stats["replica"]] = (stats["node"][:8], stats["batches"])
        if stats["batches"] > 0:
            seen[stats["replica"]] = stats["node"]
    return seen


def _wait_until(condition, timeout: float, what: str, step: float = 0.5) -> float:
    """Seconds until ``condition()``; past ``timeout``, an AssertionError that says what was awaited and the replica
    states seen on the way."""
    started = time.perf_counter()
    while not condition():
        if time.perf_counter() - started > timeout:
            seen = ", ".join(f"{t - started:+.1f} s {states}" for t, states in TRANSITIONS)
            raise AssertionError(f"{what}: not within {timeout} s; replica states: {seen}; /stats said (replica: node,"
                                 f" batches): {STATS}")  # fmt: skip
        time.sleep(step)
    return time.perf_counter() - started


def test_the_example_config_scales_out_to_a_second_node_and_back_without_a_failed_request():
    args, options = _example_deployment()
    assert options["autoscaling_config"]["min_replicas"] == 1 and options["autoscaling_config"]["max_replicas"] > 1
    saved = {name: os.environ.get(name) for name in ("RAY_USAGE_STATS_ENABLED", "OMP_NUM_THREADS", LOCAL_ROUTING)}
    os.environ.update(RAY_USAGE_STATS_ENABLED="0", OMP_NUM_THREADS="1", **{LOCAL_ROUTING: "0"})
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "num_gpus": 0, "include_dashboard": False,
                                                            "object_store_memory": 100 * 2**20})  # fmt: skip
    cluster.add_node(num_cpus=1, num_gpus=0, object_store_memory=100 * 2**20)
    robots = None
    try:
        ray.init(address=cluster.address, log_to_driver=False)
        assert len([node for node in ray.nodes() if node["Alive"]]) == 2
        port = _free_port()
        serve.start(http_options={"host": "127.0.0.1", "port": port})
        url = f"http://127.0.0.1:{port}"
        args = {name: value for name, value in args.items() if name != "compile_cache"}  # eager: nothing to compile
        eager = {"policy": str(POLICY), "method": "prior+jacobi", "buckets": "1,2,4,8", "calibration_calls": "0",
                 "threads": "1"}  # fmt: skip
        app_args = PolicyAppArgs.from_args({**args, **eager})
        autoscaling = {**options["autoscaling_config"], **FAST_AUTOSCALING, "max_replicas": 2}
        deployment = policy_deployment(app_args).options(
            autoscaling_config=autoscaling, ray_actor_options=options["ray_actor_options"],
            max_ongoing_requests=options["max_ongoing_requests"],
        )  # fmt: skip
        serve.run(deployment.bind(app_args), name=APP_NAME, route_prefix="/")
        assert _replicas() == 1
        robots = Robots(url, size=64)
        robots.add(1)
        _wait_until(lambda: robots.answered >= 5, 60, "5 answers from the first replica")
        first = _serving_replicas(url)
        assert len(first) == 1
        first_on_head = next(iter(first.values())) == cluster.head_node.node_id  # the proxy's node

        robots.add(BUSY_ROBOTS - 1)  # the load rises: 8 robots for a target of 2 ongoing requests a replica
        rose = time.perf_counter()
        up = _wait_until(lambda: _replicas() == 2 and len(_serving_replicas(url, tries=8)) == 2, UP_WITHIN_S,
                         f"a second replica serving beside the first, {BUSY_ROBOTS} robots")  # fmt: skip
        serving = _serving_replicas(url)
        assert len(serving) == 2 and len(set(serving.values())) == 2  # one replica on each node
        answered_at_two = robots.answered

        robots.remove(BUSY_ROBOTS - 1)  # back to one robot: Ray takes a replica away, draining it first
        fell = time.perf_counter()
        down = _wait_until(lambda: _replicas() == 1 and _replicas("STOPPING") == 0, DOWN_WITHIN_S,
                           "one replica again after the load fell")  # fmt: skip
        answered_before = robots.answered
        _wait_until(lambda: robots.answered >= answered_before + 5, 60, "5 answers after the scale-down")
        robots.remove(1)
        assert robots.failures == [], robots.failures[:5]
        print(f"the first replica on the {'head' if first_on_head else 'second'} node (the proxy's: {first_on_head}); "
              f"second replica serving {up:.1f} s after the load rose; removed {down:.1f} s after it fell; "
              f"{robots.answered} requests, {answered_at_two} by the time two served, 0 failed; replica states: "
              + ", ".join(f"{t - rose:+.1f} s {states}" for t, states in TRANSITIONS) + f" (the load fell at "
              f"{fell - rose:+.1f} s)")  # fmt: skip
    finally:
        if robots is not None:
            robots.remove(len(robots.threads))
        serve.shutdown()
        ray.shutdown()
        cluster.shutdown()
        for name, value in saved.items():
            os.environ.pop(name) if value is None else os.environ.__setitem__(name, value)
