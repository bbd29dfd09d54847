"""Robots that drive a policy server (``metaworld.fleet``), against a deterministic fake client and real Meta-World
envs (short episodes): the episodes are eval's, chunks are executed whole, every robot has its own session, a killed
run continues without rerunning a finished (task, seed), a folder never mixes two policies or methods, and the
summary's figures are computed right. The end-to-end test against the real server lives in tests/serving/."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest

pytest.importorskip("metaworld")

from hf_specvla.metaworld.env import MAX_EPISODE_STEPS  # noqa: E402
from hf_specvla.metaworld.fleet import (  # noqa: E402
    RobotEpisode,
    RobotsConfig,
    ServerInfo,
    ServerReplyError,
    format_summary,
    percentiles,
    run_robots,
    summarize,
)
from hf_specvla.metaworld.seeds import EVAL_SEED_START  # noqa: E402
from hf_specvla.serving.protocol import ActReply, ServedFigures  # noqa: E402

INFO = {"policy": "policies/fake", "fingerprint": "00112233aabbccdd", "image_size": 32, "camera": "corner",
        "state_dim": 4, "action_dim": 4, "chunk_length": 2, "use_state": True, "method": "exact",
        "buckets": [1, 2, 4], "extra": "ignored"}  # fmt: skip


class FakeServer:
    """What several fake clients share: every request in order, and a failure after ``fail_after`` requests."""

    def __init__(self, fail_after: int | None = None, **info):
        self.info = {**INFO, **info}
        self.requests: list[dict] = []
        self.fail_after = fail_after
        self.lock = threading.Lock()

    def client(self) -> FakeClient:
        return FakeClient(self)


class FakeClient:
    """``PolicyClient``'s ``info`` / ``act``: the action is a deterministic function of the state (so an episode's
    actions can be recomputed from what it sent), a chunk when ``/info`` says so."""

    def __init__(self, server: FakeServer):
        self.server = server

    def info(self) -> dict:
        return dict(self.server.info)

    def act(self, image, instruction, state=None, session=None, reset=False) -> ActReply:
        info = self.server.info
        with self.server.lock:
            if self.server.fail_after is not None and len(self.server.requests) >= self.server.fail_after:
                raise ConnectionError("POST http://fake/act failed after 9 attempts: connection refused")
            self.server.requests.append({"session": session, "reset": reset, "instruction": instruction,
                                         "state": None if state is None else np.asarray(state).tolist(),
                                         "image_shape": np.asarray(image).shape})  # fmt: skip
            batch = len(self.server.requests) % 3 + 1
        action = fake_action(state, info["chunk_length"])
        served = ServedFigures(method=info["method"], speculative=batch < 3, target_forwards=batch, batch_size=batch,
                               bucket=4, queue_ms=0.5, decode_ms=1.0, server_ms=2.0, session=session)  # fmt: skip
        return ActReply(action, served)


def fake_action(state, chunk_length: int) -> np.ndarray:
    """[4], or [chunk_length, 4]: a small move that depends on the state (zeros without one)."""
    base = np.zeros(4) if state is None else np.tanh(np.asarray(state, dtype=np.float64)) * 0.5
    rows = np.stack([base + 0.01 * (i + 1) for i in range(chunk_length)])  # rows differ: their order is visible
    return rows[0] if chunk_length == 1 else rows


def read_log(folder) -> list[dict]:
    return [json.loads(line) for line in (folder / "episodes.jsonl").read_text().splitlines()]


# ----------------------------------------------------------------------------- settings
@pytest.mark.parametrize(
    "overrides, message",
    [
        ({"episodes_per_task": 0}, "RobotsConfig.episodes_per_task must be >= 1, got 0"),
        ({"robots": 0}, "RobotsConfig.robots must be >= 1, got 0"),
        ({"robots": True}, "RobotsConfig.robots must be an integer >= 1, got True"),
        ({"seed_start": -1}, "RobotsConfig.seed_start must be >= 0, got -1"),
        ({"max_episode_steps": MAX_EPISODE_STEPS + 1}, f"must be <= {MAX_EPISODE_STEPS}"),
        ({"server": "127.0.0.1:8000"}, "RobotsConfig.server must be an http:// or https:// address"),
        ({"tasks": "fly"}, "unknown Meta-World task 'fly'"),
    ],
)
def test_config_refuses_bad_values_naming_them(overrides, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        RobotsConfig(**overrides)


def test_config_defaults_are_evals_and_the_pairs_are_task_by_task():
    config = RobotsConfig(tasks="reach push", episodes_per_task=2)
    assert config.seed_start == EVAL_SEED_START and config.max_episode_steps == MAX_EPISODE_STEPS
    assert len(RobotsConfig().tasks) == 10  # MT10
    assert config.pairs() == [("reach-v3", 100000), ("reach-v3", 100001), ("push-v3", 100000), ("push-v3", 100001)]
    assert "secret" not in repr(RobotsConfig(api_key="secret"))


@pytest.mark.parametrize(
    "change, message",
    [
        ({"fingerprint": None}, "/info field 'fingerprint' must be str, got None"),
        ({"use_state": 1}, "/info field 'use_state' must be bool"),
        ({"image_size": True}, "/info field 'image_size' must be int"),
        ({"buckets": []}, "'buckets' must be a non-empty list of ints >= 1"),
        ({"action_dim": 7}, "acts in 7 dimensions; Meta-World robots take 4"),
        ({"state_dim": 8}, "reads 8 state numbers; Meta-World robots send 4"),
        ({"camera": "ceiling"}, "cannot render: camera must be one of"),
        ({"image_size": 8}, r"cannot render: image_size must be in \[16, 512\]"),
    ],
)
def test_server_info_refuses_what_robots_cannot_run(change, message):
    with pytest.raises(ServerReplyError, match=message):
        ServerInfo.from_payload({**INFO, **change})


def test_server_info_reads_the_layout_and_checks_action_shapes():
    info = ServerInfo.from_payload(INFO)
    assert info.buckets == (1, 2, 4) and info.env_config(7).max_episode_steps == 7
    assert ServerInfo.from_payload({**INFO, "use_state": False, "state_dim": 0}).use_state is False
    rows = info.action_rows(np.arange(8.0).reshape(2, 4))
    assert [row.tolist() for row in rows] == [[0, 1, 2, 3], [4, 5, 6, 7]]  # the chunk's order
    with pytest.raises(ServerReplyError, match=r"action of shape \[4\]; its /info promised \[2, 4\]"):
        info.action_rows(np.zeros(4))
    single = ServerInfo.from_payload({**INFO, "chunk_length": 1})
    assert [row.tolist() for row in single.action_rows(np.ones(4))] == [[1, 1, 1, 1]]


# ----------------------------------------------------------------------------- the summary
def test_percentiles_interpolate_between_the_closest_ranks():
    # rank q/100 * (n - 1) over [10, 20, 30, 40]: p50 at 1.5 -> 25, p95 at 2.85 -> 38.5, p99 at 2.97 -> 39.7
    figures = percentiles([40.0, 10.0, 30.0, 20.0])
    assert figures == pytest.approx({"p50": 25.0, "p95": 38.5, "p99": 39.7})
    assert percentiles([]) == {"p50": None, "p95": None, "p99": None}
    assert percentiles([7.0]) == {"p50": 7.0, "p95": 7.0, "p99": 7.0}


def _episode(task, seed, success, length, run, started, finished, batch_sizes, methods):
    requests = len(batch_sizes)
    return RobotEpisode(task, seed, success, length, run=run, started=started, finished=finished,
                        actions=[[0.0] * 4] * length, latencies_ms=[10.0 * (seed + 1)] * requests,
                        server_ms=[5.0] * requests, queue_ms=[1.0] * requests, target_forwards=[3] * requests,
                        batch_sizes=batch_sizes, buckets=[4] * requests, methods=methods,
                        speculative=[m != "greedy" for m in methods])  # fmt: skip


def test_summary_figures_from_hand_made_episodes():
    episodes = [
        # run "a": 100.0 .. 110.0 (10 s); run "b": 500.0 .. 505.0 (5 s): 15 wall seconds, 60 steps
        _episode("reach-v3", 0, True, 20, "a", 100.0, 104.0, [1, 2], ["exact", "exact"]),
        _episode("reach-v3", 1, False, 10, "a", 101.0, 110.0, [2, 2, 4], ["exact", "greedy", "exact"]),
        _episode("reach-v3", 2, True, 10, "b", 500.0, 505.0, [1], ["exact"]),
        _episode("push-v3", 0, False, 20, "b", 500.0, 503.0, [4, 4], ["greedy", "greedy"]),
    ]
    summary = summarize(episodes)
    assert summary["episodes"] == 4 and summary["requests"] == 8 and summary["env_steps"] == 60
    assert summary["success_rate"] == 0.5
    assert summary["tasks"]["reach-v3"] == {"episodes": 3, "success_rate": pytest.approx(2 / 3),
                                            "mean_episode_length": pytest.approx(40 / 3)}  # fmt: skip
    assert summary["tasks"]["push-v3"]["success_rate"] == 0.0
    assert summary["mean_task_success_rate"] == pytest.approx(1 / 3)  # the tasks' mean, not the episodes'
    assert summary["runs"] == 2 and summary["wall_seconds"] == pytest.approx(15.0)
    assert summary["actions_per_second"] == pytest.approx(4.0)
    assert summary["batch_sizes"] == {"1": 2, "2": 3, "4": 3}  # size -> requests, in increasing size
    assert list(summary["batch_sizes"]) == ["1", "2", "4"]
    assert summary["methods"] == {"exact": 5, "greedy": 3}
    assert summary["speculative_fraction"] == pytest.approx(5 / 8)
    # latencies: 10 ms x 2 (seed 0), 20 ms x 3 (seed 1), 30 ms x 1 (seed 2), 10 ms x 2 (push seed 0)
    latencies = [10, 10, 20, 20, 20, 30, 10, 10]
    assert summary["latency_ms"] == pytest.approx({**percentiles(latencies), "mean": np.mean(latencies)})
    # sorted 10 10 10 10 20 20 20 30: p50 at rank 3.5 -> 15, p99 at 6.93 -> 29.3
    assert summary["latency_ms"]["p50"] == 15.0 and summary["latency_ms"]["p99"] == pytest.approx(29.3)
    assert summary["target_forwards_per_request"] == 3.0
    summary["robots"] = 2
    text = format_summary(summary)
    assert "| reach-v3 | 3 | 67% | 13 |" in text and "actions/s: 4.0 (60 env steps in 15.0 s over 2 run(s)" in text
    assert "batch sizes (size: requests): 1: 2, 2: 3, 4: 3" in text
    with pytest.raises(ValueError, match="at least one episode"):
        summarize([])


# ----------------------------------------------------------------------------- runs
def test_robots_run_evals_episodes_with_chunks_executed_whole_and_one_session_each(tmp_path):
    server = FakeServer()
    config = RobotsConfig(tasks="reach push", episodes_per_task=2, robots=3, max_episode_steps=3)
    summary = run_robots(config, tmp_path / "run", server.client, progress=False)
    records = read_log(tmp_path / "run")
    assert sorted((r["task"], r["seed"]) for r in records) == sorted(config.pairs())  # each pair once
    for record in records:
        # a chunk of 2 per request, executed whole: steps 1-2, then step 3 ends the episode inside the next chunk
        assert record["length"] == 3 and len(record["actions"]) == 3 and len(record["latencies_ms"]) == 2
        assert record["success"] is False and record["finished"] >= record["started"]
        assert len(record["batch_sizes"]) == len(record["methods"]) == len(record["target_forwards"]) == 2
        assert set(record["methods"]) == {"exact"}
    requests = server.requests
    assert len(requests) == 8 and all(r["image_shape"] == (32, 32, 3) for r in requests)  # /info's image size
    assert all(r["state"] is not None and len(r["state"]) == 4 for r in requests)
    # every episode starts its session: reset on a robot's 1st, 3rd, ... request (2 requests per episode)
    by_session: dict[str, list[bool]] = {}
    for request in requests:
        by_session.setdefault(request["session"], []).append(request["reset"])
    for resets in by_session.values():
        assert resets == [True, False] * (len(resets) // 2)
    sessions = {r["session"] for r in records}
    assert sessions == set(by_session) and 1 <= len(sessions) <= 3
    prefixes = {s.rsplit("/", 1)[0] for s in sessions}
    assert len(prefixes) == 1 and all(s.rsplit("/", 1)[1] == f"robot-{r['robot']}" for s, r in
                                      ((r["session"], r) for r in records))  # fmt: skip
    assert {r["run"] for r in records} == prefixes
    # the actions executed are the replies' rows in order: recompute the first episode's from its requests' states
    first = next(r for r in records if (r["task"], r["seed"]) == ("reach-v3", EVAL_SEED_START))
    own = [r for r in requests if r["session"] == first["session"]]
    start = next(i for i, r in enumerate(own) if r["reset"] and r["instruction"] == "reach the goal")
    expected = np.concatenate([fake_action(r["state"], 2) for r in own[start : start + 2]])[:3]
    np.testing.assert_allclose(first["actions"], expected)
    # the folder's record names the policy, its fingerprint and the method; the summary its figures
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["command"] == "robots" and run["settings"]["policy"] == INFO["fingerprint"]
    assert run["settings"]["decoding"] == {"method": "exact", "buckets": [1, 2, 4]} and run["settings"]["robots"] == 3
    assert run["paths"]["policy"] == "policies/fake" and run["settings"]["env"]["image_size"] == 32
    assert json.loads((tmp_path / "run" / "summary.json").read_text()) == summary
    assert summary["episodes"] == 4 and summary["requests"] == 8 and summary["env_steps"] == 12
    assert sum(summary["batch_sizes"].values()) == 8 and summary["methods"] == {"exact": 8}
    assert summary["fingerprint"] == INFO["fingerprint"] and summary["policy"] == "policies/fake"
    assert summary["actions_per_second"] > 0 and summary["latency_ms"]["p50"] > 0


def test_a_policy_without_state_or_chunks_gets_no_state_and_one_action_per_request(tmp_path):
    server = FakeServer(use_state=False, chunk_length=1)
    run_robots(RobotsConfig(tasks="reach", episodes_per_task=1, robots=1, max_episode_steps=3), tmp_path,
               server.client, progress=False)  # fmt: skip
    (record,) = read_log(tmp_path)
    assert record["length"] == 3 and len(record["latencies_ms"]) == 3
    assert [r["state"] for r in server.requests] == [None] * 3
    assert [r["reset"] for r in server.requests] == [True, False, False]
    np.testing.assert_allclose(record["actions"], [fake_action(None, 1)] * 3)


def test_a_killed_run_continues_without_rerunning_a_finished_pair(tmp_path):
    config = RobotsConfig(tasks="reach", episodes_per_task=4, robots=2, max_episode_steps=3)
    dying = FakeServer(fail_after=5)  # 2 requests per episode: the server goes away during the 3rd episode
    with pytest.raises(ConnectionError, match="connection refused"):
        run_robots(config, tmp_path, dying.client, progress=False)
    first = (tmp_path / "episodes.jsonl").read_text().splitlines()
    finished = {(r["task"], r["seed"]) for r in map(json.loads, first)}
    assert 1 <= len(finished) <= 2 and not (tmp_path / "summary.json").exists()
    server = FakeServer()
    summary = run_robots(config, tmp_path, server.client, progress=False)
    lines = (tmp_path / "episodes.jsonl").read_text().splitlines()
    assert lines[: len(first)] == first  # the finished episodes are kept as they were
    pairs = [(r["task"], r["seed"]) for r in map(json.loads, lines)]
    assert sorted(pairs) == config.pairs()  # every pair exactly once
    assert sum(r["reset"] for r in server.requests) == 4 - len(finished)  # only the pending episodes ran
    assert summary["episodes"] == 4 and summary["runs"] == 2
    again = FakeServer()
    assert run_robots(config, tmp_path, again.client, progress=False)["episodes"] == 4
    assert again.requests == []  # nothing left to run: not one request


@pytest.mark.parametrize(
    "change, named",
    [
        ({"fingerprint": "ffffffffffffffff"}, "policy: 'ffffffffffffffff' here vs '00112233aabbccdd' there"),
        ({"method": "fast"}, "decoding.method: 'fast' here vs 'exact' there"),
        ({"camera": "overview"}, "env.camera: 'overview' here vs 'corner' there"),
    ],
)
def test_a_folder_of_another_policy_or_method_is_refused(tmp_path, change, named):
    config = RobotsConfig(tasks="reach", episodes_per_task=1, robots=1, max_episode_steps=2)
    run_robots(config, tmp_path, FakeServer().client, progress=False)
    before = (tmp_path / "episodes.jsonl").read_text()
    other = FakeServer(**change)
    with pytest.raises(FileExistsError, match=named):
        run_robots(config, tmp_path, other.client, progress=False)
    assert other.requests == [] and (tmp_path / "episodes.jsonl").read_text() == before
    with pytest.raises(FileExistsError, match="robots: 2 here vs 1 there"):  # a fleet's figures are of its size
        run_robots(RobotsConfig(tasks="reach", episodes_per_task=1, robots=2, max_episode_steps=2), tmp_path,
                   FakeServer().client, progress=False)  # fmt: skip


def test_two_fleets_get_different_sessions_and_a_bad_reply_stops_the_fleet(tmp_path):
    config = RobotsConfig(tasks="reach", episodes_per_task=1, robots=1, max_episode_steps=2)
    servers = [FakeServer(), FakeServer()]
    for i, server in enumerate(servers):
        run_robots(config, tmp_path / str(i), server.client, progress=False)
    assert servers[0].requests[0]["session"] != servers[1].requests[0]["session"]

    class WrongShape(FakeClient):
        def act(self, *args, **kwargs):
            reply = super().act(*args, **kwargs)
            return ActReply(reply.action[0], reply.served)  # one action where /info promised a chunk

    server = FakeServer()
    with pytest.raises(ServerReplyError, match=r"action of shape \[4\]"):
        run_robots(RobotsConfig(tasks="reach", episodes_per_task=3, robots=2, max_episode_steps=2), tmp_path / "bad",
                   lambda: WrongShape(server), progress=False)  # fmt: skip
    assert (tmp_path / "bad" / "episodes.jsonl").read_text() == ""
    assert len(server.requests) <= 2  # each robot stopped at its first bad reply
