"""Rows answered when done: a robot whose row of a speculative batch is decoded gets its reply while the rest of the
batch still decodes, its action still greedy's. On the small shipped policy ``mt10_vla`` (eager ``prior+jacobi``): a
robot that repeats its last observation is drafted its previous action, all accepted at the prefill (1 target
forward), while a robot starting an episode drafts with Jacobi alone (several forwards)."""

from __future__ import annotations

import functools
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from hf_specvla.policies import VLAPolicy
from hf_specvla.serving import PolicyClient, PolicyService, ServeConfig
from hf_specvla.serving.decoding import DecodeStep
from hf_specvla.serving.protocol import ActReply, ActRequest
from hf_specvla.serving.server import PolicyServer

POLICY = Path(__file__).resolve().parents[2] / "policies" / "mt10_vla"
CONFIG = ServeConfig(method="prior+jacobi", buckets=(1, 2, 4), calibration_calls=0)
INSTRUCTION = "reach the goal"
#: how long each target forward after a call's first sleeps, where a test slows the batch's later rounds down
SLOW_FORWARD_S = 0.4

pytestmark = pytest.mark.skipif(not POLICY.is_dir(), reason=f"the shipped policy {POLICY} is missing")


@pytest.fixture(scope="module")
def policy() -> VLAPolicy:
    import torch

    torch.set_num_threads(1)
    return VLAPolicy.from_pretrained(POLICY)


def _observation(policy: VLAPolicy, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    size = policy.config.image_size
    return rng.integers(0, 256, (size, size, 3), dtype=np.uint8), rng.uniform(-0.3, 0.3, policy.config.state_dim)


def _greedy(policy: VLAPolicy, image, state) -> np.ndarray:
    policy.reset()
    action = policy.predict_action(image, INSTRUCTION, state)
    policy.reset()
    return np.asarray(action)


def _previous_action(policy: VLAPolicy, image, state) -> list[list[int]]:
    """A robot's memory after one greedy step on this observation (what drafts its repeat perfectly)."""
    history: list[list[int]] = []
    policy.predict_action(image[None], [INSTRUCTION], state[None], previous_action_ids=[history])
    return history


@contextmanager
def _later_forwards_slowed(policy):
    """Within: every target forward of a ``predict_action`` call but its first sleeps ``SLOW_FORWARD_S``; yields the
    list of each call's ``time.perf_counter()`` at its return."""
    forward, predict, returned, count = policy.model.forward, policy.predict_action, [], [0]

    @functools.wraps(forward)  # transformers reads the forward's signature
    def slow_forward(*args, **kwargs):
        count[0] += 1
        if count[0] > 1:
            time.sleep(SLOW_FORWARD_S)
        return forward(*args, **kwargs)

    def timed_predict(*args, **kwargs):
        count[0] = 0
        try:
            return predict(*args, **kwargs)
        finally:
            returned.append(time.perf_counter())

    policy.model.forward, policy.predict_action = slow_forward, timed_predict
    try:
        yield returned
    finally:
        del policy.model.forward, policy.predict_action


def test_the_decode_step_hands_on_a_row_the_moment_it_is_decoded(policy):
    """Row 0 repeats its observation (drafted right: 1 forward), rows 1 and 2 start episodes: row 0 comes back
    during the call, with the action and memory the whole call gives it; the last robot row comes back with the
    batch, with its figures."""
    step = DecodeStep(policy, CONFIG)
    observations = [_observation(policy, seed) for seed in (1, 2, 3)]
    requests = [ActRequest(image, INSTRUCTION, state) for image, state in observations]
    histories = [_previous_action(policy, *observations[0]), [], []]
    expected = [(_greedy(policy, *o), _previous_action(policy, *o)) for o in observations]
    handed: dict[int, tuple] = {}
    with _later_forwards_slowed(policy) as returned:
        batch = step.run(requests, histories, 4, 1, lambda i, row: handed.setdefault(i, (row, time.perf_counter())))
    call_returned = returned[-1]
    assert 0 in handed and set(handed) | set(batch.rows) == {0, 1, 2} and not set(handed) & set(batch.rows)
    row, at = handed[0]
    assert at < call_returned - SLOW_FORWARD_S / 2  # before the rounds the other rows needed
    assert row.target_forwards == row.batch_forwards == 1 and row.early  # drafted right: the prefill's forward alone
    assert len(batch.rows) >= 1 and batch.batch_forwards > 1
    for i, (action, memory) in enumerate(expected):
        got = handed[i][0] if i in handed else batch.rows[i]
        np.testing.assert_array_equal(got.action, action)
        assert got.history == (memory if i else (histories[0] + memory)[-len(got.history) :]), i
    assert histories[1:] == [[], []]  # the caller's memories are left as they were
    late = next(iter(batch.rows.values()))
    assert late.target_forwards == late.batch_forwards == batch.batch_forwards and not late.early


def test_greedy_batches_answer_every_row_after_the_call(policy):
    step = DecodeStep(policy, CONFIG)
    observations = [_observation(policy, seed) for seed in (4, 5)]
    requests = [ActRequest(image, INSTRUCTION, state) for image, state in observations]
    handed = []
    batch = step.run(requests, [[], []], 2, 0, lambda i, row: handed.append(i))
    assert handed == [] and sorted(batch.rows) == [0, 1]
    assert [r.target_forwards for r in batch.rows.values()] == [policy.config.action_tokens] * 2
    with pytest.raises(ValueError, match="a batch of 2 rows decodes 1..2 requests, got 3"):
        step.run(requests + requests[:1], [[], [], []], 2, 0)


def test_a_failed_batch_retries_only_the_requests_not_answered_yet(policy):
    """The call fails after row 0 was answered early: row 1 alone is decoded again; each robot is answered once,
    with greedy's action."""
    service = PolicyService(policy, CONFIG)
    observations = [_observation(policy, seed) for seed in (6, 7)]
    service.act([ActRequest(*_fields(observations[0]), session="a")])  # a's memory: this observation's action
    predict, calls = policy.predict_action, []

    def failing_once(*args, **kwargs):
        calls.append(len(args[0]))
        result = predict(*args, **kwargs)
        if len(calls) == 1:
            raise RuntimeError("the batch's call failed")
        return result

    requests = [ActRequest(*_fields(observations[0]), session="a"), ActRequest(*_fields(observations[1]), session="b")]
    answered = []
    policy.predict_action = failing_once
    try:
        results = service.act_each(requests, on_reply=lambda i, result: answered.append(i))
    finally:
        del policy.predict_action
        service.close()
    assert calls == [2, 1] and answered == [0, 1] and service.failed_batches == 1
    for result, (image, state) in zip(results, observations):
        assert isinstance(result, ActReply)
        np.testing.assert_array_equal(result.action, _greedy(policy, image, state))
    assert results[0].served.batch_size == 2 and results[1].served.batch_size == 1  # b: decoded again, alone


def _fields(observation: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, str, np.ndarray]:
    image, state = observation
    return image, INSTRUCTION, state


def test_a_robot_whose_row_finishes_early_gets_its_reply_before_its_batch_ends(policy):
    """A real server on 127.0.0.1, two robots in one batch: "repeat" sends its last observation again (drafted
    right: done at the prefill), "new" starts an episode (more rounds, each slowed down): "repeat" holds its reply
    while the batch still decodes; both actions are greedy's."""
    service = PolicyService(policy, ServeConfig(method="prior+jacobi", buckets=(2,), calibration_calls=0,
                                                max_wait_ms=3000.0))  # fmt: skip
    repeat, new, other = _observation(policy, 8), _observation(policy, 9), _observation(policy, 10)
    expected = {"repeat": _greedy(policy, *repeat), "new": _greedy(policy, *other)}
    received: dict[str, tuple[ActReply, float]] = {}
    with PolicyServer(service, port=0) as server, _later_forwards_slowed(policy) as returned:
        clients = {name: PolicyClient(server.url) for name in ("repeat", "new")}

        def robot(name: str, observation, reset: bool) -> None:
            reply = clients[name].act(observation[0], INSTRUCTION, observation[1], session=name, reset=reset)
            received[name] = (reply, time.perf_counter())

        def together(steps: dict[str, tuple]) -> None:
            """The robots' requests in one batch: "repeat" first (answered early, it counts as active for
            ACTIVE_WINDOW_S after its reply only; arriving first it is active), then "new", within max_wait_ms."""
            threads = [threading.Thread(target=robot, args=(name, *step)) for name, step in steps.items()]
            for thread in threads:
                thread.start()
                time.sleep(0.1)
            for thread in threads:
                thread.join(120)

        together({"repeat": (repeat, True), "new": (new, True)})  # both robots active: the next batch holds both
        together({"repeat": (repeat, False), "new": (other, True)})
    call_returned = returned[-1]
    (early, early_at), (late, late_at) = received["repeat"], received["new"]
    assert early.served.batch_size == late.served.batch_size == 2
    assert early.served.target_forwards == early.served.batch_forwards == 1  # its forwards when it finished
    assert early.served.early and not late.served.early
    assert late.served.target_forwards == late.served.batch_forwards > 1
    assert early_at < call_returned - SLOW_FORWARD_S / 2 < late_at, (early_at, call_returned, late_at)
    assert early.served.server_ms < late.served.server_ms - 1000 * SLOW_FORWARD_S / 2
    np.testing.assert_array_equal(early.action, expected["repeat"])
    np.testing.assert_array_equal(late.action, expected["new"])
    assert len(early.served.draft_state) == 2  # its memory: the previous action and this one
