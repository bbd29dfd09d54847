"""The policy server on Ray Serve (``serving.ray_deployment``): the application builder's arguments and the example
Serve config files (no cluster); then a local Ray cluster started and stopped here, serving the builder's application
as ``serve run`` does (its ``key=value`` arguments as text): 2 replicas of the small shipped policy ``mt10_vla``
(64-pixel images, 3 layers) with an eager method (no compile), the same HTTP API as the server on one machine, the
policy's own actions whichever replica answers, and a replica killed under load."""

from __future__ import annotations

import ast
import json
import os
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

ray = pytest.importorskip("ray")
serve = pytest.importorskip("ray.serve")
requests = pytest.importorskip("requests")

from hf_specvla.serving import ray_deployment  # noqa: E402
from hf_specvla.serving.client import PolicyClient  # noqa: E402
from hf_specvla.serving.config import ServeConfig  # noqa: E402
from hf_specvla.serving.protocol import ActReply, ActRequest, dumps  # noqa: E402
from hf_specvla.serving.ray_deployment import (  # noqa: E402
    APP_NAME,
    DEPLOYMENT_NAME,
    IMPORT_PATH,
    PolicyAppArgs,
    build_app,
    policy_deployment,
)
from hf_specvla.serving.server import PolicyServer  # noqa: E402
from hf_specvla.serving.service import PolicyService  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
POLICY = ROOT / "policies" / "mt10_vla"
CONFIG = ServeConfig(method="prior+jacobi", buckets=(1, 2, 4), calibration_calls=0)
#: the builder's arguments as ``serve run ... key=value`` passes them: text
ARGS = {"policy": str(POLICY), "method": "prior+jacobi", "buckets": "1,2,4", "calibration_calls": "0",
        "num_replicas": "2", "threads": "1"}  # fmt: skip
EXAMPLE_CONFIGS = sorted((ROOT / "examples" / "serving").glob("serve_config*.yaml"))
INSTRUCTION = "reach the goal"
REPLICAS = 2
#: Ray 2.60's proxy's answer for a request in flight on a replica that died (plain text, not this API's JSON)

pytestmark = pytest.mark.skipif(not POLICY.is_dir(), reason=f"the shipped policy {POLICY} is missing")


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="module")
def url():
    """A local Ray cluster (2 CPUs, no dashboard) serving ``mt10_vla`` with 2 replicas of 1 thread, the builder's
    application run as ``serve run`` runs it; its URL."""
    saved = {name: os.environ.get(name) for name in ("RAY_USAGE_STATS_ENABLED", "OMP_NUM_THREADS")}
    os.environ.update(RAY_USAGE_STATS_ENABLED="0", OMP_NUM_THREADS="1")
    ray.init(address="local", num_cpus=2, num_gpus=0, include_dashboard=False, object_store_memory=100 * 2**20,
             log_to_driver=False)  # fmt: skip
    try:
        port = _free_port()
        serve.start(http_options={"host": "127.0.0.1", "port": port})
        serve.run(build_app(ARGS), name=APP_NAME, route_prefix="/")
        yield f"http://127.0.0.1:{port}"
    finally:
        serve.shutdown()
        ray.shutdown()
        for name, value in saved.items():
            os.environ.pop(name) if value is None else os.environ.__setitem__(name, value)


@pytest.fixture(scope="module")
def local() -> PolicyService:
    """The same policy and config in this process: the reference."""
    return PolicyService.from_pretrained(POLICY, CONFIG, threads=1)


def _observation(seed: int, size: int, state_dim: int = 4) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (size, size, 3), dtype=np.uint8), np.zeros(state_dim)


def _greedy(service: PolicyService, image, state) -> np.ndarray:
    """The policy's greedy action (no drafts, no memory)."""
    service.policy.reset()
    action = service.policy.predict_action(image, INSTRUCTION, state)
    service.policy.reset()
    return np.asarray(action)


# ----------------------------------------------------------------------------- without a cluster
def test_the_module_imports_ray_only_inside_functions():
    tree = ast.parse(Path(ray_deployment.__file__).read_text())
    top = [node for node in tree.body if isinstance(node, ast.Import | ast.ImportFrom)]
    names = [alias.name for node in top if isinstance(node, ast.Import) for alias in node.names]
    names += [node.module or "" for node in top if isinstance(node, ast.ImportFrom)]
    assert not [name for name in names if name == "ray" or name.startswith("ray.")]


def test_without_ray_the_error_says_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(ImportError, match=r"pip install 'hf_specvla\[ray\]'"):
        ray_deployment.require_ray()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"policy": None}, "the argument policy is required"),
        ({"bukets": "1,2"}, "unknown argument(s) ['bukets']; the arguments are ["),
        ({"buckets": "1,two"}, "argument buckets must be integers (a list, or '1,2,4'), got '1,two'"),
        ({"buckets": "4,2"}, "buckets must be increasing"),
        ({"max_wait_ms": "soon"}, "argument max_wait_ms must be a number, got 'soon'"),
        ({"num_replicas": "0"}, "num_replicas must be an integer >= 1, got 0"),
        ({"threads": 1.5}, "argument threads must be an integer, got 1.5"),
        ({"method": "prior+bogus"}, "unknown decoding method"),
        ({"method": "prior+tree"}, "method prior+tree drafts with the draft head: give draft_head=<its folder>"),
        ({"method": ["prior+jacobi", "prior+tree"]}, "method prior+tree drafts with the draft head: give draft_head"),
        ({"policy": "no/such/policy"}, "argument policy: no folder 'no/such/policy' (looked in"),
        ({"policy": str(ROOT / "examples")}, "holds neither policy_config.json (a Meta-World policy"),
        ({"unnorm_key": "bridge_orig"}, "is a Meta-World policy with one set of action statistics"),
    ],
)
def test_a_bad_argument_is_refused_naming_it_before_any_replica_starts(change, message):
    args = {k: v for k, v in {**ARGS, **change}.items() if v is not None}
    with pytest.raises(ValueError) as refused:
        build_app(args)
    assert message in str(refused.value)


def test_the_builder_reads_text_and_typed_arguments_alike():
    from_text = PolicyAppArgs.from_args(ARGS)
    typed = PolicyAppArgs.from_args({**ARGS, "buckets": [1, 2, 4], "calibration_calls": 0, "num_replicas": 2,
                                     "threads": 1})  # fmt: skip
    assert from_text == typed and from_text.serve == CONFIG and from_text.num_replicas == 2
    assert PolicyAppArgs.from_args(from_text.to_args()) == from_text  # what serve_config writes reads back
    assert PolicyAppArgs.from_args({**ARGS, "speculate_buckets": ""}).serve.speculate_buckets == ()  # never
    # several methods, the faster per bucket: a YAML list (one method's options hold commas: never split text)
    several = PolicyAppArgs.from_args({**ARGS, "method": ["prior+jacobi", "prior+jacobi:r=4,m=1"]})
    assert several.serve.method == ("prior+jacobi", "prior+jacobi:r=4,m=1")
    assert PolicyAppArgs.from_args(several.to_args()) == several
    assert PolicyAppArgs.from_args({**ARGS, "method": "prior+jacobi:r=4,m=1"}).serve.method == "prior+jacobi:r=4,m=1"


@pytest.mark.parametrize("path", EXAMPLE_CONFIGS, ids=lambda p: p.name)
def test_the_example_serve_configs_are_valid_and_name_our_application(path):
    """Each example file passes Serve's own schema, names the builder and the deployment, and its arguments pass
    the builder's checks (the policy read from the repository root, as ``serve run`` there reads it)."""
    import yaml
    from ray.serve.schema import ServeDeploySchema

    config = ServeDeploySchema.model_validate(yaml.safe_load(path.read_text()))
    (application,) = config.applications
    assert application.import_path == IMPORT_PATH and application.route_prefix == "/"
    assert [d.name for d in application.deployments] == [DEPLOYMENT_NAME]
    deployment = application.deployments[0].model_dump(exclude_unset=True)
    assert {"max_ongoing_requests", "ray_actor_options"} <= set(deployment)
    assert {"num_replicas", "autoscaling_config"} & set(deployment)
    cwd = os.getcwd()
    os.chdir(ROOT)
    try:
        app_args = PolicyAppArgs.from_args(application.args)
    finally:
        os.chdir(cwd)
    assert deployment["max_ongoing_requests"] == ray_deployment.max_ongoing_requests(app_args.serve)
    # a relative compile cache read from where the application was built: the replicas' working directory may differ
    assert app_args.serve.compile_cache == str(ROOT / "runs" / "compile_cache")


def test_the_deployment_takes_its_batching_and_overload_limits_from_the_arguments():
    app_args = PolicyAppArgs(str(POLICY), ServeConfig(method="prior+jacobi", buckets=(1, 2, 8), max_queue=5),
                             threads=2, num_replicas=3)  # fmt: skip
    deployment = policy_deployment(app_args)
    assert deployment.name == DEPLOYMENT_NAME and deployment.num_replicas == 3
    assert deployment.ray_actor_options["num_cpus"] == 2
    assert deployment.max_ongoing_requests == 16  # the batch being decoded (8) and the next one filling
    assert deployment.max_queued_requests == 5
    backpressure = deployment._deployment_config.backpressure_config
    assert backpressure.status_code == 503 and backpressure.retry_after_s == ray_deployment.OVERLOAD_RETRY_AFTER_S
    unset = policy_deployment(PolicyAppArgs(str(POLICY)))._deployment_config
    assert "num_replicas" not in unset.user_configured_option_names  # a config file's autoscaling_config is free


# ----------------------------------------------------------------------------- on a local cluster
def test_info_and_actions_are_the_local_policy_s(url, local):
    client = PolicyClient(url)
    info = client.info()
    assert info["deployment"] == "ray" and info["replicas"] == REPLICAS
    assert info["replica_actor"].startswith(f"SERVE_REPLICA::{APP_NAME}#{DEPLOYMENT_NAME}#")
    layout = local.policy.config
    assert info["fingerprint"] == local.policy.weights_fingerprint()
    assert (info["image_size"], info["state_dim"], info["action_dim"]) == (64, layout.state_dim, layout.action_dim)
    assert (info["method"], info["buckets"]) == ("prior+jacobi", [1, 2, 4])
    stats = requests.get(url + "/stats", timeout=30).json()
    assert stats["deployment"] == "ray" and set(stats["buckets"]) == {"1", "2", "4"}
    assert {"batches", "waiting", "dropped", "failed_batches"} <= set(stats)  # the one-machine server's batcher's

    image, state = _observation(0, layout.image_size)
    greedy = _greedy(local, image, state)
    reply = client.act(image, INSTRUCTION, state)
    np.testing.assert_array_equal(reply.action, greedy)
    (expected,) = local.act([ActRequest(image, INSTRUCTION, state)])
    np.testing.assert_array_equal(reply.action, expected.action)

    json_numpy = pytest.importorskip("json_numpy")
    saved = json.dumps, json.loads, json.dump, json.load
    json_numpy.patch()  # an unchanged OpenVLA client
    try:
        action = requests.post(url + "/act", json={"image": image, "instruction": INSTRUCTION, "state": state},
                               timeout=30).json()  # fmt: skip
    finally:
        json.dumps, json.loads, json.dump, json.load = saved
    assert isinstance(action, np.ndarray)
    np.testing.assert_array_equal(action, greedy)


def test_a_robot_s_drafts_do_not_depend_on_the_replica(url, local):
    """The client echoes draft_state: every step's action, drafts (target forwards) and draft_state are those of
    one service that saw the whole episode, whichever replica answered each step."""
    client = PolicyClient(url)
    size = local.policy.config.image_size
    base, state = _observation(1, size)
    drift = np.random.default_rng(2)
    for step in range(10):
        image = np.clip(base.astype(int) + drift.integers(-3, 4, base.shape), 0, 255).astype(np.uint8)
        reply = client.act(image, INSTRUCTION, state, session="robot", reset=step == 0)
        (expected,) = local.act([ActRequest(image, INSTRUCTION, state, "robot", reset=step == 0)])
        np.testing.assert_array_equal(reply.action, expected.action)
        np.testing.assert_array_equal(reply.action, _greedy(local, image, state))
        assert reply.served.target_forwards == expected.served.target_forwards, step
        assert reply.served.draft_state == expected.served.draft_state, step
    assert len(reply.served.draft_state) == local.policy.HISTORY_LENGTH


def test_a_robot_whose_drafts_are_lost_gets_the_same_action_without_them(url, local):
    """A session no replica knows (its replica restarted, its draft_state not echoed): greedy's action, its memory
    starting again from this action."""
    image, state = _observation(3, local.policy.config.image_size)
    body = dumps({"image": image, "instruction": INSTRUCTION, "state": state, "session": "forgotten-robot"})
    reply = ActReply.from_payload(requests.post(url + "/act", data=body, timeout=30).json())
    np.testing.assert_array_equal(reply.action, _greedy(local, image, state))
    assert len(reply.served.draft_state) == 1  # this action only: no prior drafts were there


def test_bad_input_gets_the_local_server_s_errors(url, local):
    image, state = _observation(4, local.policy.config.image_size)
    cases = {
        "wrong image shape": ("POST", "/act", dumps({"image": image[:10], "instruction": "x", "state": state})),
        "no instruction": ("POST", "/act", dumps({"image": image, "state": state})),
        "bad state": ("POST", "/act", dumps({"image": image, "instruction": "x", "state": [1, 2]})),
        "bad draft_state": (
            "POST",
            "/act",
            dumps({"image": image, "instruction": "x", "state": state, "session": "s", "draft_state": [[1, 2]]}),
        ),  # fmt: skip
        "not JSON": ("POST", "/act", b"{not json"),
        "too large": ("POST", "/act", b" " * (5 * 2**20)),
        "unknown route": ("GET", "/nowhere", None),
        "wrong method": ("GET", "/act", None),
    }
    with PolicyServer(local, port=0) as server:
        for name, (method, path, body) in cases.items():
            ours = requests.request(method, url + path, data=body, timeout=30)
            theirs = requests.request(method, server.url + path, data=body, timeout=30)
            assert 400 <= ours.status_code < 500, (name, ours.status_code, ours.text)
            assert (ours.status_code, ours.json()) == (theirs.status_code, theirs.json()), name
    assert requests.post(url + "/act", data=cases["wrong image shape"][2], timeout=30).json()["field"] == "image"


def _replica_actors() -> set[str]:
    prefix = f"SERVE_REPLICA::{APP_NAME}#{DEPLOYMENT_NAME}#"
    return {a["name"] for a in ray.util.list_named_actors(all_namespaces=True) if a["name"].startswith(prefix)}


def _wait_for_replacement(victim: str, timeout_s: float = 240.0) -> float:
    """Seconds until the victim is gone and ``REPLICAS`` replicas run again (a new replica loads the policy and
    compiles its buckets: on 2 busy cores that took over 90 s once)."""
    started = time.time()
    while time.time() - started < timeout_s:
        actors = _replica_actors()
        deployment = serve.status().applications[APP_NAME].deployments[DEPLOYMENT_NAME]
        if victim not in actors and len(actors) == REPLICAS and deployment.replica_states == {"RUNNING": REPLICAS}:
            return time.time() - started
        time.sleep(0.25)
    raise AssertionError(f"{victim} was not replaced in {timeout_s} s: {_replica_actors()}, {serve.status()}")


def test_a_replica_killed_under_load_loses_no_action(url, local):
    """Robots loop on the server while one replica is killed: each request eventually gets the policy's action
    (the method at r = 0 is lossless), and Ray replaces the replica."""
    size = local.policy.config.image_size
    observations = [_observation(10 + i, size) for i in range(4)]
    expected = [_greedy(local, image, state) for image, state in observations]
    stop, lock = threading.Event(), threading.Lock()
    served, mismatches, failures = [0, 0, 0], [], []
    clients = [PolicyClient(url, timeout_s=30) for _ in range(3)]

    def robot(index: int) -> None:
        client, session = clients[index], f"robot-{index}"
        step = 0
        while not stop.is_set():
            image, state = observations[(index + step) % len(observations)]
            try:  # a request in flight on the killed replica gets Ray's plain 500: the client retries it
                reply = client.act(image, INSTRUCTION, state, session=session, reset=step == 0)
            except Exception as error:  # noqa: BLE001 (reported below)
                failures.append(repr(error))
                return
            if not np.array_equal(reply.action, expected[(index + step) % len(observations)]):
                mismatches.append((index, step, reply.action))
            with lock:
                served[index] += 1
            step += 1

    threads = [threading.Thread(target=robot, args=(i,), daemon=True) for i in range(3)]
    for thread in threads:
        thread.start()
    time.sleep(1.0)
    victim = PolicyClient(url).info()["replica_actor"]
    before = list(served)
    ray.kill(ray.get_actor(victim, namespace="serve"), no_restart=False)
    replaced_after_s = _wait_for_replacement(victim)
    after_replacement = list(served)
    time.sleep(1.0)
    stop.set()
    for thread in threads:
        thread.join(60)

    assert failures == [] and mismatches == []
    assert all(b > 0 for b in before) and all(s > a for s, a in zip(served, after_replacement)), (before, served)
    assert sum(c.retried for c in clients) <= 3 * clients[0].retries  # the requests in flight, retried
    new = {PolicyClient(url).info()["replica"] for _ in range(30)}
    assert victim.rsplit("#", 1)[1] not in new and len(new) == REPLICAS
    print(f"replaced in {replaced_after_s:.1f} s; {sum(served)} actions; {sum(c.retried for c in clients)} retried")


def test_robots_through_ray_serve_act_as_greedy_in_one_process(url, local, tmp_path):
    """Served = local on Ray Serve: 4 Meta-World robots x 2 episodes on each of 4 MT10 tasks through the 2 replicas
    act, episode by episode, as greedy decoding in this process, whichever replica answered each request."""
    import json

    from hf_specvla.metaworld.fleet import RobotsConfig, run_robots

    from .episodes import EPISODES, MAX_STEPS, ROBOTS, SEED_START, TASKS, check_served, greedy_episodes

    config = RobotsConfig(tasks=TASKS, episodes_per_task=EPISODES, robots=ROBOTS, seed_start=SEED_START,
                          max_episode_steps=MAX_STEPS, server=url)  # fmt: skip
    summary = run_robots(config, tmp_path / "robots", progress=False)
    lines = (tmp_path / "robots" / "episodes.jsonl").read_text().splitlines()
    records = {(r["task"], r["seed"]): r for r in map(json.loads, lines)}
    check_served(records, summary, greedy_episodes(local.policy))
