"""The policy server on one machine, a real HTTP server on 127.0.0.1 (started by each test, stopped after): OpenVLA's
unchanged client, batches that give each robot greedy's action, bad input, the API key, the size limit, overload,
robots that disconnect, and SIGTERM's drain."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from hf_specvla.policies import VLAPolicy
from hf_specvla.serving import PolicyClient, PolicyService, ServeConfig, ServerError
from hf_specvla.serving.protocol import dumps
from hf_specvla.serving.server import PolicyServer

ROOT = Path(__file__).resolve().parents[2]
POLICY = ROOT / "policies" / "mt10_vla3"
#: eager decoding (no compile): the server's behaviour, not its speed, is under test
METHOD = "prior+jacobi"
INSTRUCTIONS = ("reach the goal", "push the puck to the goal", "open the drawer", "press the button")


@pytest.fixture(scope="module")
def policy() -> VLAPolicy:
    return VLAPolicy.from_pretrained(POLICY)


def _service(policy, **settings) -> PolicyService:
    config = dict(method=METHOD, buckets=(1, 2, 4), calibration_calls=0, max_wait_ms=30.0)
    return PolicyService(policy, ServeConfig(**{**config, **settings}))


def _observation(policy, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    size = policy.config.image_size
    return {"image": rng.integers(0, 256, (size, size, 3), dtype=np.uint8),
            "instruction": INSTRUCTIONS[seed % len(INSTRUCTIONS)], "state": rng.uniform(-0.3, 0.3, 4)}  # fmt: skip


def _greedy(policy, observation) -> np.ndarray:
    """Plain greedy decoding, one observation alone: what every served action must equal."""
    policy.reset()
    return policy.predict_action(observation["image"], observation["instruction"], observation["state"])


def _post(url: str, body: bytes, headers: dict | None = None) -> tuple[int, dict, dict]:
    """Raw POST (no retries): status, JSON body, headers."""
    request = urllib.request.Request(url, body, {"Content-Type": "application/json", **(headers or {})})
    try:
        with urllib.request.urlopen(request, timeout=60) as response:
            return response.status, json.loads(response.read()), dict(response.headers)
    except urllib.error.HTTPError as error:
        return error.code, json.loads(error.read() or b"null"), dict(error.headers)


@contextmanager
def _json_numpy_patched():
    """``json_numpy.patch()`` as an OpenVLA client calls it, undone after."""
    json_numpy = pytest.importorskip("json_numpy")
    saved = json.dumps, json.loads, json.dump, json.load
    json_numpy.patch()
    try:
        yield
    finally:
        json.dumps, json.loads, json.dump, json.load = saved


def test_an_unchanged_openvla_client_gets_greedys_action(policy):
    requests = pytest.importorskip("requests")
    observation = _observation(policy, 0)
    expected = _greedy(policy, observation)
    with PolicyServer(_service(policy), port=0) as server, _json_numpy_patched():
        action = requests.post(server.url + "/act", json=observation).json()  # deploy.py's client, verbatim
        encoded = requests.post(server.url + "/act", json={"encoded": json.dumps(observation)}).json()
        encoded = json.loads(encoded)  # deploy.py's double-encoded reply: json_numpy text
    assert isinstance(action, np.ndarray) and action.dtype == np.float64
    np.testing.assert_array_equal(action, expected)
    np.testing.assert_array_equal(encoded, expected)  # OpenVLA's double-encoded form, answered alike


def test_concurrent_robots_are_batched_and_each_gets_greedys_action(policy):
    """8 robots at once, 3 steps each (their drafts: their own previous actions, kept by session): every action is
    what greedy gives that observation alone, whatever batches formed."""
    observations = [[_observation(policy, 10 * robot + step) for step in range(3)] for robot in range(8)]
    expected = [[_greedy(policy, o) for o in steps] for steps in observations]
    replies: dict = {}
    with PolicyServer(_service(policy), port=0) as server:
        info = PolicyClient(server.url).info()

        def robot(i: int) -> None:
            client = PolicyClient(server.url)
            for step, o in enumerate(observations[i]):
                reply = client.act(o["image"], o["instruction"], o["state"], session=f"r{i}", reset=step == 0)
                replies[i, step] = reply

        threads = [threading.Thread(target=robot, args=(i,)) for i in range(8)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        stats = json.loads(urllib.request.urlopen(server.url + "/stats").read())
    assert info["fingerprint"] == policy.weights_fingerprint() and info["image_size"] == policy.config.image_size
    for (i, step), reply in replies.items():
        np.testing.assert_array_equal(reply.action, expected[i][step], err_msg=f"robot {i} step {step}")
        assert reply.served.session == f"r{i}" and reply.served.bucket >= reply.served.batch_size >= 1
        assert len(reply.served.draft_state) == min(policy.HISTORY_LENGTH, policy.config.chunk_length * (step + 1))
        # the intake (body read, checks) is the first part of the queue, the queue the first part of the server's time
        assert 0 < reply.served.intake_ms <= reply.served.queue_ms <= reply.served.server_ms
    assert max(r.served.batch_size for r in replies.values()) > 1, "no batch formed: the test tests nothing"
    assert any(r.served.speculative and r.served.target_forwards < policy.config.action_tokens
               for r in replies.values()), "no request was decoded with fewer forwards than greedy's"  # fmt: skip
    assert stats["sessions"] == 8
    served = sum(row["speculative_rows"] + row["greedy_rows"] for row in stats["buckets"].values())
    assert served == 24


def test_echoed_draft_state_and_lost_state_give_the_same_action(policy):
    """A robot's drafts may come from its echo (another replica answered before) or be lost (a restarted replica):
    its action is greedy's either way; only the forwards differ."""
    first, second = _observation(policy, 1), _observation(policy, 2)
    expected = _greedy(policy, second)
    with PolicyServer(_service(policy), port=0) as server:
        client = PolicyClient(server.url)
        client.act(first["image"], first["instruction"], first["state"], session="a", reset=True)
        echoed = client.act(second["image"], second["instruction"], second["state"], session="a")
        fresh = PolicyClient(server.url)  # another client: no echo, and a session this server never saw
        lost = fresh.act(second["image"], second["instruction"], second["state"], session="never-seen")
    np.testing.assert_array_equal(echoed.action, expected)
    np.testing.assert_array_equal(lost.action, expected)


@pytest.mark.parametrize(
    ("change", "field", "status"),
    [
        (lambda o: o.pop("image"), "image", 422),
        (lambda o: o.update(image=o["image"].astype(np.float32)), "image", 422),
        (lambda o: o.update(image=o["image"][:64]), "image", 422),
        (lambda o: o.pop("instruction"), "instruction", 422),
        (lambda o: o.update(instruction=7), "instruction", 422),
        (lambda o: o.pop("state"), "state", 422),
        (lambda o: o.update(state=[0.1, float("nan"), 0, 0]), "state", 422),
        (lambda o: o.update(state=np.zeros(3)), "state", 422),
        (lambda o: o.update(session=12), "session", 422),
        (lambda o: o.update(session="x" * 129), "session", 422),
        (lambda o: o.update(reset="yes"), "reset", 422),
        (lambda o: o.update(draft_state=[1, 2]), "draft_state", 422),
        (lambda o: o.update(draft_state=[[1, 2, 3, 4]]), "draft_state", 422),  # not action tokens
        (lambda o: o.update(unnorm_key=3), "unnorm_key", 422),
    ],
)
def test_bad_input_gets_a_4xx_naming_the_field(policy, change, field, status):
    observation = _observation(policy, 3)
    change(observation)
    with PolicyServer(_service(policy), port=0) as server:
        code, body, _ = _post(server.url + "/act", dumps(observation))
        assert (code, body["field"]) == (status, field), body
        assert body["error"]
        pickled = json.dumps({"image": {"__numpy__": "AAAA", "dtype": "|O", "shape": [1]}}).encode()
        for raw, why in ((b"{not json", "not JSON"), (b"[1, 2]", "JSON object"), (pickled, "dtype")):
            code, body, _ = _post(server.url + "/act", raw)
            assert 400 <= code < 500 and why in body["error"], body
        assert _post(server.url + "/nothing", b"{}")[0] == 404


def test_a_bad_request_never_fails_or_delays_its_batch(policy):
    good = [_observation(policy, 20 + i) for i in range(3)]
    expected = [_greedy(policy, o) for o in good]
    bad = {**_observation(policy, 30), "state": [0.0]}
    results: dict = {}
    with PolicyServer(_service(policy, max_wait_ms=200.0), port=0) as server:

        def send(key, body):
            results[key] = _post(server.url + "/act", dumps(body))

        threads = [threading.Thread(target=send, args=(i, o)) for i, o in enumerate(good)]
        threads.append(threading.Thread(target=send, args=("bad", bad)))
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    assert results["bad"][0] == 422 and results["bad"][1]["field"] == "state"
    for i in range(3):
        code, body, _ = results[i]
        assert code == 200
        np.testing.assert_array_equal(np.frombuffer(__import__("base64").b64decode(body["__numpy__"])).reshape(
            body["shape"]), expected[i])  # fmt: skip


def test_the_api_key_is_required_everywhere_but_health(policy):
    observation = dumps(_observation(policy, 4))
    with PolicyServer(_service(policy), port=0, api_key="s3cret") as server:
        assert _post(server.url + "/act", observation)[0] == 401
        code, body, headers = _post(server.url + "/act", observation, {"Authorization": "Bearer wrong"})
        assert code == 401 and body["field"] == "api_key" and headers.get("www-authenticate") == "Bearer"
        assert _post(server.url + "/act", observation, {"Authorization": "Bearer s3cret"})[0] == 200
        assert _post(server.url + "/act", observation, {"X-API-Key": "s3cret"})[0] == 200
        with_key = dumps({**_observation(policy, 4), "api_key": "s3cret"})
        assert _post(server.url + "/act", with_key)[0] == 200
        with pytest.raises(ServerError) as refused:
            PolicyClient(server.url).info()
        assert refused.value.status == 401
        assert PolicyClient(server.url, api_key="s3cret").info()["policy"] == str(POLICY)
        assert json.loads(urllib.request.urlopen(server.url + "/health").read()) == {"status": "ok"}


def test_only_loopback_serves_without_an_api_key(policy):
    with pytest.raises(ValueError, match="reachable from other machines.*--api-key"):
        PolicyServer(_service(policy), host="0.0.0.0", port=0)


def test_an_oversize_body_is_refused_before_it_is_read(policy):
    with PolicyServer(_service(policy), port=0, max_request_bytes=10_000) as server:
        code, body, _ = _post(server.url + "/act", dumps(_observation(policy, 5)))  # a 128 x 128 image: ~65 KB
    assert code == 413 and "10000 bytes" in body["error"]


def _slowed(service: PolicyService, seconds: float) -> PolicyService:
    """``service`` whose every call sleeps ``seconds`` first; ``service.decoding`` is set once a call started."""
    act_each, service.decoding = service.act_each, threading.Event()

    def slow_act_each(requests, arrived=None, on_reply=None):
        service.decoding.set()
        time.sleep(seconds)
        return act_each(requests, arrived, on_reply)

    service.act_each = slow_act_each
    return service


def _wait_until(condition, what: str, timeout_s: float = 30.0) -> None:
    deadline = time.perf_counter() + timeout_s
    while not condition():
        assert time.perf_counter() < deadline, f"timed out waiting until {what}"
        time.sleep(0.01)


def test_overload_gets_503_with_retry_after_and_the_client_retries(policy):
    """One request is being decoded, so of five more the queue (max_queue=1) takes one and refuses four."""
    observation = _observation(policy, 6)
    expected = _greedy(policy, observation)
    service = _slowed(_service(policy, max_queue=1, buckets=(1,), max_wait_ms=0.0), 1.0)
    results: list = []

    def post():
        results.append(_post(server.url + "/act", dumps(observation)))

    with PolicyServer(service, port=0) as server:
        first = threading.Thread(target=post)
        first.start()
        assert service.decoding.wait(30), "the first request never reached the decoder"
        threads = [threading.Thread(target=post) for _ in range(5)]
        for thread in threads:
            thread.start()
        for thread in [first, *threads]:
            thread.join()
        client = PolicyClient(server.url, backoff_s=0.1)
        retried = [client.act(**observation) for _ in range(2)]
    refused = [r for r in results if r[0] == 503]
    assert len(refused) == 4 and all(int(r[2]["retry-after"]) >= 1 for r in refused)
    assert sum(r[0] == 200 for r in results) == 2
    for reply in retried:
        np.testing.assert_array_equal(reply.action, expected)


def test_a_robot_that_disconnects_does_not_stall_the_others(policy):
    """Robot A's request occupies the server; robot B sends one and hangs up while it waits: B's request is dropped
    before its batch, and robot C is served."""
    observation = _observation(policy, 7)
    service = _slowed(_service(policy, buckets=(1,), max_wait_ms=0.0), 0.6)
    with PolicyServer(service, port=0) as server:
        a = threading.Thread(target=_post, args=(server.url + "/act", dumps(observation)))
        a.start()
        assert service.decoding.wait(30), "robot A's request never reached the decoder"
        body = dumps(observation)
        with socket.create_connection(("127.0.0.1", server.port)) as b:
            b.sendall(b"POST /act HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                      + f"Content-Length: {len(body)}\r\n\r\n".encode() + body)  # fmt: skip
            _wait_until(lambda: server.backend.batcher.waiting == 1, "robot B's request is queued")
        started = time.perf_counter()
        code, _, _ = _post(server.url + "/act", dumps(observation))  # robot C
        waited = time.perf_counter() - started
        a.join()
        stats = json.loads(urllib.request.urlopen(server.url + "/stats").read())
    assert code == 200
    assert stats["dropped"] == 1 and stats["batches"] == 2, stats  # A and C decoded, B's request never
    assert waited < 3.0, f"robot C waited {waited:.2f} s: B's abandoned request was decoded in its way"


def test_sigterm_drains_the_requests_in_flight(policy, tmp_path):
    """``PolicyServer.run`` in its own process: SIGTERM while 3 requests are in flight; each gets its action, then
    the process exits 0 and stops listening."""
    script = tmp_path / "serve.py"
    script.write_text(f"""
import sys, time, torch
torch.set_num_threads(1)
from hf_specvla.serving import PolicyService, ServeConfig
from hf_specvla.serving.server import PolicyServer
service = PolicyService.from_pretrained({str(POLICY)!r}, ServeConfig(method={METHOD!r}, buckets=(1,), max_wait_ms=0.0,
                                                                     calibration_calls=0))
act_each = service.act_each
service.act_each = lambda requests, arrived=None, on_reply=None: (time.sleep(0.5), act_each(requests, arrived,
                                                                                        on_reply))[1]
server = PolicyServer(service, port=0)
print(server.url, flush=True)
server.run()
print("exited cleanly", flush=True)
""")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    process = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True, env=env)
    try:
        url = process.stdout.readline().strip()
        observation = dumps(_observation(policy, 8))
        for _ in range(100):  # the server is up once /health answers
            try:
                urllib.request.urlopen(url + "/health", timeout=1)
                break
            except OSError:
                time.sleep(0.1)
        results: list = []
        threads = [threading.Thread(target=lambda: results.append(_post(url + "/act", observation)[0]))
                   for _ in range(3)]  # fmt: skip
        for thread in threads:
            thread.start()
        _wait_until(lambda: json.loads(urllib.request.urlopen(url + "/stats").read())["waiting"] == 2,
                    "all three arrived: the first is being decoded, two wait")  # fmt: skip
        process.send_signal(signal.SIGTERM)
        for thread in threads:
            thread.join()
        assert process.wait(timeout=60) == 0
        assert results == [200, 200, 200]
        assert "exited cleanly" in process.stdout.read()
        with pytest.raises(OSError):
            urllib.request.urlopen(url + "/health", timeout=2)
    finally:
        process.kill()


def test_a_request_cancelled_by_its_server_cancels_its_decode(policy):
    """Ray Serve's proxy cancels the handler of a request whose robot hung up: the decode it waits for is cancelled
    too (a batch then skips it), not left to run."""
    import asyncio

    from starlette.requests import Request

    from hf_specvla.serving.app import PolicyRoutes

    service = _service(policy)
    cancelled = asyncio.Event()

    class Backend:
        def parse(self, payload):
            return service.parse(payload)

        async def act(self, request, arrived):
            try:
                await asyncio.sleep(60)
            except asyncio.CancelledError:
                cancelled.set()
                raise

    body = dumps(_observation(policy, 9))

    async def scenario():
        messages = [{"type": "http.request", "body": body, "more_body": False}]

        async def receive():
            if messages:
                return messages.pop()
            await asyncio.sleep(60)  # connected, nothing more to say

        scope = {"type": "http", "method": "POST", "path": "/act", "headers": [], "query_string": b""}
        handler = asyncio.ensure_future(PolicyRoutes(Backend()).act(Request(scope, receive)))
        await asyncio.sleep(0.2)
        handler.cancel()
        with pytest.raises(asyncio.CancelledError):
            await handler
        await asyncio.wait_for(cancelled.wait(), 2)

    asyncio.run(scenario())
    assert cancelled.is_set()


@pytest.mark.slow  # ~1 min: compiles every bucket's graphs (dynamo's eager backend)
def test_every_decode_runs_on_the_services_thread_with_room_for_every_buckets_graphs(
    policy, monkeypatch, graphs_in_memory
):
    """torch's compiler settings are per thread: graphs compiled at warm-up must be served under a recompile limit
    that holds them (the engine raises it from what dynamo holds for the model, in the thread that decodes),
    whichever thread (the batcher's, a Ray replica's pool) asks for an action. Compiled with dynamo's eager backend
    (it guards and recompiles as inductor would, without generating code)."""
    import torch
    from transformers import CompileConfig

    import hf_specvla.speculative as speculative
    from hf_specvla.speculative.compiled import graphs_held, reset_compilation
    from hf_specvla.speculative.decoder import SpeculativeDecoder

    def eager_backend(device_type="cpu"):
        config = CompileConfig(backend="eager", fullgraph=True, dynamic=False, mode="default")
        config._compile_all_devices = True
        return dict(cache_implementation="static", compile_config=config)

    monkeypatch.setattr(speculative, "compiled_decoding_kwargs", eager_backend)
    monkeypatch.setenv("HF_SPECVLA_DYNAMIC_WIDTHS", "0")  # a graph per round width: more than the default limit
    reset_compilation()
    service = _service(policy, method=METHOD + ":compile", buckets=(1, 2, 4))
    seen = []
    predict = policy.predict_action

    def spy(*args, **kwargs):
        action = predict(*args, **kwargs)
        # the most graphs one code object holds: the model's forward (prefills, greedy) or a round's accepting function
        functions = [type(policy.model).forward, *SpeculativeDecoder.of(policy.model).compiled_functions()]
        held = max(graphs_held(function) for function in functions)
        seen.append((threading.current_thread().name, torch._dynamo.config.recompile_limit, held))
        return action

    policy.predict_action = spy
    try:
        service.warm_up()
        request = service.parse(_observation(policy, 11))
        asker = threading.Thread(target=lambda: service.act([request]))
        asker.start()
        asker.join()
        service.act([request, request])
    finally:
        del policy.predict_action
        service.close()
        reset_compilation()
    assert {name.split("_")[0] for name, _, _ in seen} == {"hf-specvla-decode"}
    assert max(held for _, _, held in seen) > 8  # more graphs than dynamo's default limit: the test is not vacuous
    assert all(limit > held for _, limit, held in seen), seen


@pytest.mark.parametrize(
    ("method", "baseline"),
    [("exact", "none:compile"), ("prior+jacobi:compile", "none:compile"), ("greedy:compile", "greedy:compile"),
     ("prior+jacobi", "greedy"), ("greedy", "greedy")],
)  # fmt: skip
def test_the_greedy_mode_is_the_fastest_greedy_the_method_has(policy, method, baseline):
    """A compiled speculative method's greedy mode is the engine's own compiled greedy (measured faster than
    transformers' at every bucket, on the method's own graphs); a greedy-only server's is its method; an eager
    method's, transformers' eager greedy. Nothing is compiled to say so."""
    from hf_specvla.serving.decoding import DecodeStep

    step = DecodeStep(policy, ServeConfig(method=method, buckets=(1, 2)))
    assert step.baseline.name == baseline and step.name(0) == baseline


@pytest.mark.slow  # ~60 s: compiles one bucket
def test_the_greedy_mode_of_a_compiled_method_compiles_nothing_of_its_own(policy, caplog):
    """Mode 0 of ``exact`` runs on the graphs the method's own call compiled (the prefill, the one-token round): a
    greedy call after a speculative one compiles nothing, and gives greedy's actions."""
    import logging

    service = _service(policy, method="exact", buckets=(2,))
    observations = [_observation(policy, seed) for seed in (1, 2)]
    requests = [service.parse(o) for o in observations]
    try:
        service.step.run(requests, [[], []], 2, 1)  # the speculative method first: its graphs
        service.step.run(requests, [[], []], 2, 1)  # (its one-token round too, now that drafts are kept)
        with caplog.at_level(logging.INFO, logger="hf_specvla"):
            caplog.clear()  # only the greedy call's records (the logger may log INFO already, as another test left it)
            greedy = service.step.run(requests, [[], []], 2, 0)
    finally:
        service.close()
    # (the engine may say it has the one-token width's graph for this call: "compiled ... in 0.0 s")
    seconds = [
        float(m.group(1)) for r in caplog.records if (m := re.search(r"compiled .* in ([0-9.]+) s", r.getMessage()))
    ]
    tracing = [r.getMessage() for r in caplog.records if r.getMessage().startswith("compiling")]
    assert tracing == [] and all(value < 0.5 for value in seconds), (tracing, seconds)
    for row, o in enumerate(observations):
        np.testing.assert_array_equal(greedy.rows[row].action, _greedy(policy, o))


@pytest.mark.slow  # ~55 s: compiles every bucket
def test_compiled_greedy_keeps_one_graph_per_bucket_whatever_the_prompt_length(policy, monkeypatch):
    """The greedy baseline decodes on the service's own static cache per bucket: prompts of other lengths (other
    instructions) reuse it, and the actions are eager greedy's."""
    import hf_specvla.speculative as speculative

    service = _service(policy, method="greedy:compile", buckets=(2,))
    observations = [_observation(policy, seed) for seed in range(4)]  # 4 instructions of different lengths
    assert len({len(policy.prompt_ids(o["instruction"], o["state"])) for o in observations}) > 1
    caches, reusable = [], speculative.reusable_static_cache
    monkeypatch.setattr(speculative, "reusable_static_cache",
                        lambda *args, **kwargs: caches.append(reusable(*args, **kwargs)) or caches[-1])  # fmt: skip
    try:
        for pair in (observations[:2], observations[2:], observations[1:3]):
            replies = service.act([service.parse(o) for o in pair])
            for reply, o in zip(replies, pair):
                np.testing.assert_array_equal(reply.action, _greedy(policy, o))
                assert reply.served.method == "greedy:compile"
    finally:
        service.close()
    assert len(caches) == 3 and len({id(cache) for cache in caches}) == 1  # one cache (the engine's), one graph


def test_a_lone_robot_never_waits_for_a_batch_that_will_not_come(policy):
    """With a long batching window, one active robot is decoded at once; two active robots are batched together."""
    observation = _observation(policy, 12)
    with PolicyServer(_service(policy, max_wait_ms=400.0), port=0) as server:
        alone = PolicyClient(server.url)
        queued = [alone.act(**observation, session="alone", reset=i == 0).served.queue_ms for i in range(3)]
        time.sleep(1.2)  # "alone" is no longer active
        replies: list = []

        def robot(session: str) -> None:
            client = PolicyClient(server.url)
            for step in range(3):
                replies.append((step, client.act(**observation, session=session, reset=step == 0)))

        pair = [threading.Thread(target=robot, args=(s,)) for s in ("a", "b")]
        for thread in pair:
            thread.start()
        for thread in pair:
            thread.join()
    assert max(queued) < 100, queued  # not the 400 ms window
    later = [reply.served.batch_size for step, reply in replies if step > 0]  # both robots active by then
    assert sorted(later) in ([2, 2, 2, 2], [1, 2, 2, 2]), later  # out of step by one: the last request is alone
