"""The policy server under hostile input and bad luck (issue 64's probe), a real HTTP server on 127.0.0.1 per test:
prompts longer than the graphs compiled at start-up, settings out of range, a dead batching thread, a backlog behind
a slow batch, malformed bodies, the API key before the body, robots that hang up mid-body."""

from __future__ import annotations

import json
import logging
import socket
import threading
import time
import urllib.error
import urllib.request

import numpy as np
import pytest

from hf_specvla.policies import VLAPolicy
from hf_specvla.serving import ServeConfig
from hf_specvla.serving.batching import ACTIVE_WINDOW_S
from hf_specvla.serving.protocol import decode_array, dumps, encode_array
from hf_specvla.serving.server import PolicyServer

from .test_server import POLICY, _greedy, _observation, _post, _service, _slowed, _wait_until


@pytest.fixture(scope="module")
def policy() -> VLAPolicy:
    return VLAPolicy.from_pretrained(POLICY)


def _get(url: str) -> tuple[int, dict]:
    try:
        with urllib.request.urlopen(url, timeout=10) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as error:
        return error.code, json.loads(error.read() or b"null")


def _post_together(url: str, bodies: dict) -> dict:
    """Each of ``bodies`` (key -> request) POSTed at once from its own thread, so that they can share a batch: key ->
    ``_post``'s (status, body, headers)."""
    results: dict = {}

    def send(key, body):
        results[key] = _post(url, dumps(body))

    threads = [threading.Thread(target=send, args=item) for item in bodies.items()]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return results


def _spy_on_decoding(policy) -> list:
    """Replaces ``policy.predict_action`` (undo with ``del policy.predict_action``) by one that records each call's
    instructions and returns zeros, as fast as a test wants."""
    calls = []

    def fake(images, instructions, states=None, return_output=False, previous_action_ids=None, **kwargs):
        calls.append(list(instructions))
        shape = (len(images), policy.config.chunk_length, policy.config.action_dim)
        actions = np.zeros(shape if policy.config.chunk_length > 1 else shape[::2])
        return (actions, None) if return_output else actions

    policy.predict_action = fake
    return calls


# ----------------------------------------------------------------------------- prompts and compiled graphs
def test_a_prompt_longer_than_the_compiled_graphs_is_refused_before_any_forward(policy):
    """A 230-token prompt (600 characters, within the character limit) once compiled new verification widths under
    load (110 s, every robot waiting): now a compiled server states its limit in /info and refuses it (422 naming the
    instruction and the limit) without a forward; a prompt within the limit is accepted."""
    calls = _spy_on_decoding(policy)
    try:
        service = _service(policy, method="exact")  # compiled; nothing is compiled until a call (none here)
        with PolicyServer(service, port=0) as server:
            _, info = _get(server.url + "/info")
            long = {**_observation(policy, 0), "instruction": "go " * 200}
            code, body, _ = _post(server.url + "/act", dumps(long))
    finally:
        del policy.predict_action
        service.close()
    limit = info["max_prompt_tokens"]
    assert info["prompt_tiers"] == [[service.step.shortest_prompt, limit]] and limit > service.step.shortest_prompt
    assert len(policy.prompt_ids(long["instruction"], long["state"])) > limit  # the probe's case
    assert (code, body["field"]) == (422, "instruction") and f"at most {limit} tokens" in body["error"], body
    assert calls == []
    within = service.step.tier_instruction((limit, limit))  # the longest prompt served: it parses
    assert service.parse({**_observation(policy, 0), "instruction": within}).instruction == within


def test_every_prompt_of_a_tier_decodes_on_the_slot_count_the_engine_gives_its_longest(policy):
    """The service plans its prompt tiers with the engine's own sizing (``verification_slots``, asked, not restated):
    every prompt length of a tier gets, from the engine's ``with_draft_slots`` on ``generate``'s own cache (prompt +
    action tokens - 1), one slot count (one set of graphs), and the lengths just outside it another."""
    from transformers import StaticCache

    from hf_specvla.speculative import verification_slots
    from hf_specvla.speculative.cache import with_draft_slots
    from hf_specvla.speculative.decoder import SpeculativeDecoder

    service = _service(policy, method="exact")
    service.close()
    first, last = service.step.prompt_tiers[0]
    text_config = policy.model.config.get_text_config(decoder=True)

    def engines(length: int) -> int:
        generates = StaticCache(config=text_config, max_cache_len=length + policy.config.action_tokens - 1)
        cache = with_draft_slots(SpeculativeDecoder.of(policy.model), generates, verification_slots)
        return max(layer.max_cache_len for layer in cache.layers)

    assert len({engines(length) for length in range(first, last + 1)}) == 1, "a tier decodes on one slot count"
    assert engines(last + 1) > engines(last)  # the next length needs more slots: the tier ends where it must
    assert [rule(last) for rule in service.step._slot_rules(None)] == [engines(last)]


def test_warm_up_compiles_every_prompt_tier_and_the_limit_follows_max_prompt_tokens(policy):
    calls = _spy_on_decoding(policy)
    try:
        service = _service(policy, method="exact", buckets=(1, 2), max_prompt_tokens=150)
        service.warm_up()
    finally:
        del policy.predict_action
        service.close()
    assert service.step.max_prompt_tokens == 150 and len(service.step.prompt_tiers) == 2
    state = np.zeros(policy.config.state_dim)
    assert len(policy.prompt_ids(calls[0][0], state)) == 150  # the longest first: generate's cache keeps its size
    for bucket in (1, 2):
        widths = {len(policy.prompt_ids(rows[0], state)) for rows in calls if len(rows) == bucket}
        for first, last in service.step.prompt_tiers:
            assert any(first <= w <= last for w in widths), (bucket, (first, last), widths)
    with pytest.raises(ValueError, match="max_prompt_tokens 10 is shorter than this policy's shortest prompt"):
        _service(policy, method="exact", max_prompt_tokens=10)


def test_the_default_limit_leaves_the_instruction_room(policy, monkeypatch):
    """A policy whose shortest prompt sits just below a slot boundary (many image tokens) still serves instructions
    of ``MIN_INSTRUCTION_TOKENS`` by default: one more tier, compiled at start-up."""
    from hf_specvla.serving import decoding

    monkeypatch.setattr(decoding, "MIN_INSTRUCTION_TOKENS", 100)
    service = _service(policy, method="exact")
    service.close()
    assert service.step.max_prompt_tokens == service.step.shortest_prompt + 100 and len(service.step.prompt_tiers) == 2


# ----------------------------------------------------------------------------- settings
@pytest.mark.parametrize(
    ("settings", "message"),
    [
        (dict(max_wait_ms=float("inf")), "max_wait_ms must be a finite number >= 0, got inf"),
        (dict(max_wait_ms=float("nan")), "max_wait_ms must be a finite number >= 0, got nan"),
        (dict(max_wait_ms=1e9), "max_wait_ms must be a finite number"),
        (dict(buckets=(1, 10**6)), "buckets must be batch sizes 1..1024"),
        (dict(max_prompt_tokens=0), "max_prompt_tokens must be >= 1, got 0"),
        (dict(max_prompt_tokens=12.5), "max_prompt_tokens must be an integer"),
        (dict(unnorm_key=""), "ServeConfig.unnorm_key must be a dataset's name"),
        (dict(unnorm_key=3), "ServeConfig.unnorm_key must be a dataset's name"),
    ],
)
def test_a_setting_out_of_range_is_refused_naming_it(settings, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(".", r"\.")):
        ServeConfig(**settings)


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        (dict(drain_timeout_s=float("inf")), "drain_timeout_s must be seconds 0..3600, got inf"),
        (dict(drain_timeout_s=float("nan")), "drain_timeout_s must be seconds 0..3600, got nan"),
        (dict(max_request_bytes=0), "max_request_bytes must be an integer >= 1, got 0"),
    ],
)
def test_a_server_setting_out_of_range_is_refused_naming_it(policy, settings, message):
    service = _service(policy)
    try:
        with pytest.raises(ValueError, match=message.replace(".", r"\.")):
            PolicyServer(service, port=0, **settings)
    finally:
        service.close()


def test_health_is_not_ok_once_the_batcher_died_and_requests_fail_instead_of_hanging(policy):
    """The probe's ``--max-wait-ms inf`` killed the batching thread (``OverflowError``) while /health said ok and
    every request hung; the setting is refused now, so the same death is forced here."""
    with PolicyServer(_service(policy), port=0) as server:
        assert _get(server.url + "/health") == (200, {"status": "ok"})
        server.backend.batcher.max_wait_s = float("inf")  # what max_wait_ms=inf did: queue.get(timeout=inf) raises
        started = time.perf_counter()
        code, body, _ = _post(server.url + "/act", dumps(_observation(policy, 1)))
        waited = time.perf_counter() - started
        health = _get(server.url + "/health")
        again = _post(server.url + "/act", dumps(_observation(policy, 2)))[0]
    assert code == 500 and "batching thread failed" in body["error"] and waited < 10, (code, body)
    assert health[0] == 503 and health[1]["status"] == "unavailable" and "OverflowError" in health[1]["error"]
    assert again == 500


# ----------------------------------------------------------------------------- batching under a backlog
def test_a_backlog_behind_a_slow_batch_is_decoded_in_full_batches(policy):
    """The first batch takes longer than the "active robot" window while 12 robots queue a request each: they are
    decoded 4 at a time (the largest bucket), not one by one (as 190 of 200 requests from 32 robots once were)."""
    service = _service(policy)
    act_each, first_started, release = service.act_each, threading.Event(), threading.Event()

    def slow_first(requests, arrived=None, on_reply=None):
        if not first_started.is_set():
            first_started.set()
            assert release.wait(30)
        return act_each(requests, arrived, on_reply)

    service.act_each = slow_first
    replies: dict = {}
    with PolicyServer(service, port=0) as server:

        def robot(i: int) -> None:
            observation = {**_observation(policy, i), "session": f"robot-{i}"}
            replies[i] = _post(server.url + "/act", dumps(observation))

        threads = [threading.Thread(target=robot, args=(0,))]
        threads[0].start()
        assert first_started.wait(30)
        threads += [threading.Thread(target=robot, args=(i,)) for i in range(1, 13)]
        for thread in threads[1:]:
            thread.start()
        _wait_until(lambda: server.backend.batcher.waiting == 12, "the 12 robots' requests are queued")
        time.sleep(ACTIVE_WINDOW_S + 0.2)  # every queued request is "old" by the time it is dequeued
        release.set()
        for thread in threads:
            thread.join()
        _, stats = _get(server.url + "/stats")
    sizes = [replies[i][1]["served"]["batch_size"] for i in range(1, 13)]
    assert all(replies[i][0] == 200 for i in replies) and sizes == [4] * 12, sizes
    assert stats["batches"] == 4 and stats["buckets"]["4"]["mode"] == "speculative"
    assert stats["speculative_share"] == 1.0 and stats["buckets"]["4"]["speculative_share"] == 1.0


# ----------------------------------------------------------------------------- malformed bodies
def _array(dtype: str, shape: list, data: bytes = b"") -> dict:
    import base64

    return {"__numpy__": base64.b64encode(data).decode(), "dtype": dtype, "shape": shape}


def _malformed(policy) -> list[tuple[str, bytes, str | None, int]]:
    """(what, body, the field named, status): each once a 500 (or named the field "array")."""
    good = _observation(policy, 4)
    image, state = encode_array(good["image"]), good["state"].tolist()

    def body(**fields) -> bytes:
        return json.dumps({"image": image, "instruction": good["instruction"], "state": state, **fields}).encode()

    deep = b'{"image": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"
    return [
        ("an unsupported image dtype", body(image=_array("<U1", [1], b"a\0\0\0")), "image", 422),
        ("an unsupported state dtype", body(state=_array("|O", [4], b"\0" * 32)), "state", 422),
        ("an unreadable dtype", body(image=_array("not a dtype", [1], b"a")), "image", 422),
        ("100 dimensions", body(image=_array("|u1", [1] * 100, b"a")), "image", 422),
        ("an absurd empty shape", body(image=_array("|u1", [0, 2**70])), "image", 422),
        ("an absurd state shape", body(state=_array("<f8", [2**62, 0])), "state", 422),
        ("very deep JSON", deep, None, 400),
        ("a huge integer in state", body(state=[10**400, 0, 0, 0]), "state", 422),
        ("a 5000-digit number", body(state=[0, 0, 0]).replace(b"[0, 0, 0]", b"[" + b"9" * 5000 + b"]"), None, 400),
        ("a huge integer in draft_state", body(draft_state=[[10**30] * 4]), "draft_state", 422),
        ("an int64 draft_state past any token", body(draft_state=_array("<u8", [1, 4], b"\xff" * 32)), "draft_state",
         422),
        ("a lone surrogate in the instruction", body(instruction="reach the goal \ud800"), "instruction", 422),
        ("a lone surrogate in the session", body(session="robot-\udfff"), "session", 422),
    ]  # fmt: skip


def test_every_malformed_body_is_a_4xx_naming_its_field(policy):
    cases = _malformed(policy)
    with PolicyServer(_service(policy), port=0) as server:
        results = [(what, field, status, *_post(server.url + "/act", raw)[:2]) for what, raw, field, status in cases]
        _, stats = _get(server.url + "/stats")
    for what, field, status, code, body in results:
        assert (code, body["field"]) == (status, field), (what, code, body)
        assert body["error"] and "internal error" not in body["error"], (what, body)
    assert stats["batches"] == 0  # refused before batching


def test_a_lone_surrogate_never_fails_the_batch_it_would_have_joined(policy, caplog):
    """It once reached the tokenizer inside a batch: the batch failed and its other robots were decoded twice."""
    good = [_observation(policy, 40 + i) for i in range(2)]
    bad = {**_observation(policy, 42), "instruction": "open the drawer \ud800"}
    with caplog.at_level(logging.INFO, logger="hf_specvla"), PolicyServer(_service(policy, max_wait_ms=300.0),
                                                                          port=0) as server:  # fmt: skip
        results = _post_together(server.url + "/act", {**dict(enumerate(good)), "bad": bad})
    assert results["bad"][0] == 422 and results["bad"][1]["field"] == "instruction"
    assert results[0][0] == results[1][0] == 200
    assert not [r for r in caplog.records if "failed" in r.getMessage()], [r.getMessage() for r in caplog.records]


@pytest.mark.parametrize("words", ["push <image> the button", "reach the goal <pad>", "open the drawer </s> <s>",
                                   "press the <IMAGE> button"])  # fmt: skip
def test_special_token_text_in_an_instruction_is_words_and_never_fails_the_batch(policy, words, caplog):
    """``<image>`` in a robot's words once became an image placeholder (and ``<pad>`` a padding token) in the prompt:
    its whole batch failed ("Image features and image tokens do not match", "attention_mask has padding after the
    tokens") and the other robots were decoded again alone. The words are text now: the robot gets greedy's action
    for them, the robots beside it theirs, nothing fails."""
    tokenizer = policy.processor.tokenizer
    ids = policy.prompt_ids(words, np.zeros(4))
    image_id = tokenizer.convert_tokens_to_ids("<image>")
    assert ids[0] == tokenizer.bos_token_id and ids.count(tokenizer.bos_token_id) == 1
    assert ids.count(image_id) == policy.config.num_image_tokens == ids[1:].index(next(i for i in ids[1:]
                                                                                        if i != image_id))  # fmt: skip
    assert not {tokenizer.pad_token_id, tokenizer.eos_token_id} & set(ids)
    good = [_observation(policy, 50 + i) for i in range(2)]
    bad = {**_observation(policy, 52), "instruction": words}
    expected = {key: _greedy(policy, body) for key, body in (*enumerate(good), ("bad", bad))}
    with caplog.at_level(logging.INFO, logger="hf_specvla"), PolicyServer(_service(policy, max_wait_ms=300.0),
                                                                          port=0) as server:  # fmt: skip
        results = _post_together(server.url + "/act", {**dict(enumerate(good)), "bad": bad})
        _, stats = _get(server.url + "/stats")
    for key, (code, body, _) in results.items():
        assert code == 200, (key, body)
        np.testing.assert_array_equal(decode_array(body, "action"), expected[key])
    assert stats["failed_batches"] == 0
    assert not [r for r in caplog.records if "failed" in r.getMessage()], [r.getMessage() for r in caplog.records]


# ----------------------------------------------------------------------------- the key first; robots that hang up
def test_a_key_inside_openvlas_double_encoded_body_is_read(policy):
    """OpenVLA's ``{"encoded": <json_numpy text>}`` with the key among its fields once got 401 (the key was looked for
    beside ``encoded``); a wrong key there is still 401, and so is a double-encoded body that is not JSON."""
    observation = {name: encode_array(value) if isinstance(value, np.ndarray) else value
                   for name, value in _observation(policy, 6).items()}  # fmt: skip

    def encoded(**fields) -> bytes:
        return json.dumps({"encoded": json.dumps({**observation, **fields})}).encode()

    with PolicyServer(_service(policy), port=0, api_key="s3cret") as server:
        right = _post(server.url + "/act", encoded(api_key="s3cret"))
        wrong = _post(server.url + "/act", encoded(api_key="wrong"))
        keyless = _post(server.url + "/act", encoded())
        not_json = _post(server.url + "/act", json.dumps({"encoded": "{not json"}).encode())
    assert right[0] == 200 and isinstance(right[1], str)  # OpenVLA's double-encoded reply: json_numpy text
    np.testing.assert_array_equal(decode_array(json.loads(right[1])), _greedy(policy, _observation(policy, 6)))
    assert (wrong[0], wrong[1]["field"]) == (401, "api_key")
    assert keyless[0] == not_json[0] == 401


def test_the_api_key_is_checked_before_the_body(policy):
    with PolicyServer(_service(policy), port=0, api_key="s3cret") as server:
        keyless = _post(server.url + "/act", b"{not json")
        keyed = _post(server.url + "/act", b"{not json", {"Authorization": "Bearer s3cret"})
        wrong_in_body = _post(server.url + "/act", json.dumps({"api_key": "wrong", "image": 3}).encode())
    assert keyless[0] == 401 and keyless[1]["field"] == "api_key"  # was 400: the body was parsed first
    assert keyed[0] == 400 and "not JSON" in keyed[1]["error"]
    assert wrong_in_body[0] == 401


def test_a_robot_that_hangs_up_mid_body_is_counted_not_logged_as_an_error(policy, caplog):
    with caplog.at_level(logging.DEBUG, logger="hf_specvla"), PolicyServer(_service(policy), port=0) as server:
        with socket.create_connection(("127.0.0.1", server.port)) as robot:
            robot.sendall(b"POST /act HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                          b"Content-Length: 100000\r\n\r\n" + b'{"image": ' + b"1" * 1000)  # fmt: skip
            time.sleep(0.2)  # the server is reading the body
        _wait_until(lambda: _get(server.url + "/stats")[1]["client_hangups"] == 1, "the hang-up is counted")
        code, _, _ = _post(server.url + "/act", dumps(_observation(policy, 5)))  # and the server serves on
    assert code == 200
    serving = [r for r in caplog.records if r.name.startswith("hf_specvla.serving")]
    assert not [r for r in serving if r.levelno >= logging.WARNING or r.exc_info], [r.getMessage() for r in serving]
    assert any("hung up" in r.getMessage() for r in serving)


# ----------------------------------------------------------------------------- reliability-6: hang-ups and shutdown
class _HeldService:
    """A service stub whose batches wait until ``release`` is set (the queue fills behind the first); each reply is
    the request's session."""

    def __init__(self, max_queue: int):
        self.config = ServeConfig(method="exact", buckets=(1, 2), max_queue=max_queue, max_wait_ms=1.0)
        self.release = threading.Event()

    def act_each(self, requests, arrived=None, on_reply=None):
        self.release.wait(30)
        for index, request in enumerate(requests):
            on_reply(index, request.session)


def test_a_hung_up_robots_request_frees_its_queue_slot_at_once():
    """Reliability-6 row 8: a robot that hung up while its request waited kept its queue slot until the worker reached
    it, so a live robot got a 503 it should not; a cancelled request now frees its slot the moment it is cancelled."""
    from hf_specvla.serving.batching import Batcher
    from hf_specvla.serving.protocol import ActRequest, Overloaded

    service = _HeldService(max_queue=3)
    batcher = Batcher(service).start()
    try:
        first = batcher.submit(ActRequest(image=None, instruction="x", session="decoding"))
        _wait_until(lambda: batcher.waiting == 0, "the first request is taken into a (held) batch")
        queued = [batcher.submit(ActRequest(image=None, instruction="x", session=f"r{i}")) for i in range(3)]
        with pytest.raises(Overloaded):  # full: three live requests wait
            batcher.submit(ActRequest(image=None, instruction="x", session="late"))
        for future in queued[:2]:
            assert future.cancel()  # their robots hang up
        assert batcher.waiting == 1
        live = [batcher.submit(ActRequest(image=None, instruction="x", session=f"live{i}")) for i in range(2)]
        service.release.set()
        assert first.result(30) == "decoding" and queued[2].result(30) == "r2"
        assert [future.result(30) for future in live] == ["live0", "live1"]
        _wait_until(lambda: batcher.dropped == 2, "the hung-up requests are dropped, not decoded")
    finally:
        service.release.set()
        batcher.stop()


def test_shutdown_ends_a_half_sent_bodys_wait_within_the_body_timeout(policy):
    """Reliability-6 row 9: a client that sent half a body held a shutdown for the whole drain timeout (30 s); its
    request is now answered 408 once ``body_timeout_s`` passes (10 s by default, 2 here), so the shutdown ends then,
    while a request already received is still answered during the drain."""
    server = PolicyServer(_service(policy), port=0, drain_timeout_s=30.0)
    server.routes.body_timeout_s = 2.0
    with server:
        with socket.create_connection(("127.0.0.1", server.port)) as stalled:
            stalled.sendall(b"POST /act HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                            b"Content-Length: 100000\r\n\r\n" + b'{"image": ' + b"1" * 1000)  # fmt: skip
            stalled.settimeout(20)
            started = time.perf_counter()
            answer = stalled.recv(4096)  # the server gives up on the body
            waited = time.perf_counter() - started
            code, _, _ = _post(server.url + "/act", dumps(_observation(policy, 5)))  # the server serves on
            stalled2 = socket.create_connection(("127.0.0.1", server.port))
            stalled2.sendall(b"POST /act HTTP/1.1\r\nHost: x\r\nContent-Length: 100000\r\n\r\n" + b"{" * 100)
            time.sleep(0.2)  # the server is reading its body when the shutdown begins
            closing = time.perf_counter()
    closed = time.perf_counter() - closing  # leaving the block: close() drains, then stops
    stalled2.close()
    assert answer.startswith(b"HTTP/1.1 408") and b"did not arrive whole within 2 s" in answer, answer[:300]
    assert 1.5 < waited < 15 and code == 200
    assert closed < 15, f"the shutdown waited {closed:.1f} s for a half-sent body (drain timeout 30 s)"


def _send_whole(port: int, body: bytes) -> socket.socket:
    """A raw connection that has sent a whole ``POST /act`` (and not yet read its answer)."""
    robot = socket.create_connection(("127.0.0.1", port))
    robot.sendall(b"POST /act HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                  + f"Content-Length: {len(body)}\r\n\r\n".encode() + body)  # fmt: skip
    return robot


def test_robots_that_hung_up_leave_the_full_queue_to_a_live_robot_over_http(policy):
    """Reliability-6 item 5 over HTTP: two robots fill the queue (max_queue=2) behind a batch being decoded, then hang
    up; a live robot's request right after is queued and answered (it once got a 503 "queue full": the hung-up
    requests held their slots until the worker reached them), and the hung-up ones are dropped, never decoded."""
    service = _service(policy, max_queue=2, buckets=(1,), max_wait_ms=0.0)
    act_each, decoding, release = service.act_each, threading.Event(), threading.Event()

    def held(requests, arrived=None, on_reply=None):
        decoding.set()
        assert release.wait(30)
        return act_each(requests, arrived, on_reply)

    service.act_each = held
    body, results = dumps(_observation(policy, 60)), {}
    with PolicyServer(service, port=0) as server:
        batcher = server.backend.batcher
        robots = {key: threading.Thread(target=lambda k=key: results.update({k: _post(server.url + "/act", body)}))
                  for key in ("first", "live")}  # fmt: skip
        try:
            robots["first"].start()
            assert decoding.wait(30), "the first request never reached the decoder"
            gone = [_send_whole(server.port, body) for _ in range(2)]
            _wait_until(lambda: batcher.waiting == 2, "the two robots' requests fill the queue")
            for robot in gone:
                robot.close()
            _wait_until(lambda: server.routes.client_hangups == 2, "both hang-ups are noticed")
            robots["live"].start()
            _wait_until(lambda: "live" in results or batcher.waiting == 1, "the live request is answered or queued")
        finally:
            release.set()
            for robot in robots.values():
                if robot.ident is not None:
                    robot.join()
        _, stats = _get(server.url + "/stats")
    assert results["live"][0] == 200, results["live"][:2]
    assert results["first"][0] == 200
    assert stats["dropped"] == 2 and stats["batches"] == 2 and stats["client_hangups"] == 2, stats


def test_a_shutdown_beside_a_half_sent_body_still_answers_the_requests_received(policy):
    """Reliability-6 item 5: the shutdown begins while robot A's request is being decoded, robot C's waits behind it
    and a client holds a half-sent body: A and C get their actions during the drain, the half-sent body its 408 once
    ``body_timeout_s`` (2 s here) passes, and ``close()`` returns then, far inside the 30 s drain timeout."""
    service = _slowed(_service(policy, buckets=(1,), max_wait_ms=0.0), 0.5)
    server = PolicyServer(service, port=0, drain_timeout_s=30.0)
    server.routes.body_timeout_s = 2.0
    body, results = dumps(_observation(policy, 61)), {}
    robots = {key: threading.Thread(target=lambda k=key: results.update({k: _post(server.url + "/act", body)}))
              for key in ("a", "c")}  # fmt: skip
    with server, socket.create_connection(("127.0.0.1", server.port)) as stalled:
        robots["a"].start()
        assert service.decoding.wait(30), "robot A's request never reached the decoder"
        robots["c"].start()
        _wait_until(lambda: server.backend.batcher.waiting == 1, "robot C's request is queued behind A's")
        stalled.sendall(b"POST /act HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                        b"Content-Length: 100000\r\n\r\n" + b'{"image": ' + b"1" * 1000)  # fmt: skip
        time.sleep(0.2)  # the server is reading its body
        started = time.perf_counter()
        server.close()
        closed = time.perf_counter() - started
        for robot in robots.values():
            robot.join()
        stalled.settimeout(10)
        answer = stalled.recv(4096)
    assert results["a"][0] == results["c"][0] == 200, (results["a"][:2], results["c"][:2])
    assert answer.startswith(b"HTTP/1.1 408"), answer[:300]
    assert closed < 2.0 + 8, f"the shutdown took {closed:.1f} s beside a half-sent body (drain timeout 30 s)"


def test_a_flood_of_robots_that_hang_up_holds_at_most_twice_the_queue():
    """Cancelled requests free their slots at once but wait in the queue for the worker; a flood of them (robots that
    send and hang up, over and over, during a long batch) is let go of before the queue holds twice ``max_queue``."""
    from hf_specvla.serving.batching import Batcher
    from hf_specvla.serving.protocol import ActRequest

    service = _HeldService(max_queue=4)
    batcher = Batcher(service).start()
    try:
        batcher.submit(ActRequest(image=None, instruction="x", session="decoding"))
        _wait_until(lambda: batcher.waiting == 0, "the first request is taken into a (held) batch")
        for i in range(100):
            assert batcher.submit(ActRequest(image=None, instruction="x", session=f"r{i}")).cancel()
            assert batcher._queue.qsize() <= 2 * 4 + 1
        live = batcher.submit(ActRequest(image=None, instruction="x", session="live"))
        service.release.set()
        assert live.result(30) == "live"
        _wait_until(lambda: batcher.dropped == 100, "every hung-up request dropped, none decoded")
    finally:
        service.release.set()
        batcher.stop()


def test_the_body_timeout_is_a_setting_checked_before_anything_loads(policy, capsys):
    """``serve --body-timeout-s`` (and ``PolicyServer(body_timeout_s=)``, Ray's ``body_timeout_s=``): seconds in
    (0, 600]; another value is a usage error naming the flag, before the policy loads."""
    from hf_specvla.cli import main
    from hf_specvla.serving.ray_deployment import PolicyAppArgs

    for value in ("0", "601", "nan", "soon"):
        with pytest.raises(SystemExit) as exited:
            main(["serve", "--policy", "does/not/exist", "--body-timeout-s", value])
        assert exited.value.code == 2
        assert "--body-timeout-s" in capsys.readouterr().err, value
    with pytest.raises(ValueError, match=r"body_timeout_s must be seconds in \(0, 600\]"):
        PolicyServer(_service(policy), port=0, body_timeout_s=-1)
    assert PolicyAppArgs.from_args({"policy": str(POLICY), "body_timeout_s": "2.5"}).body_timeout_s == 2.5
    with pytest.raises(ValueError, match="body_timeout_s"):
        PolicyAppArgs.from_args({"policy": str(POLICY), "body_timeout_s": "0"})
