"""Served = local: robots driving a real policy server on 127.0.0.1 get, episode by episode, the actions that greedy
decoding gives the same policy in one process on the same seeds, whatever batches the server formed."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hf_specvla.metaworld.env import EnvConfig, MetaWorldEnv
from hf_specvla.metaworld.fleet import RobotsConfig, run_robots
from hf_specvla.metaworld.rollout import rollout
from hf_specvla.policies import VLAPolicy
from hf_specvla.serving import PolicyService, ServeConfig
from hf_specvla.serving.server import PolicyServer

POLICY = Path(__file__).resolve().parents[2] / "policies" / "mt10_vla3"
TASKS = ["reach-v3", "push-v3", "drawer-open-v3", "button-press-topdown-v3"]
EPISODES, ROBOTS, SEED_START, MAX_STEPS = 2, 4, 100000, 40


@pytest.fixture(scope="module")
def policy() -> VLAPolicy:
    return VLAPolicy.from_pretrained(POLICY)


def _greedy_episodes(policy: VLAPolicy) -> dict:
    """(task, seed) -> (success, length, actions) of greedy decoding in this process, one episode at a time."""
    config = EnvConfig(policy.config.image_size, policy.config.camera, MAX_STEPS)
    episodes = {}
    for task in TASKS:
        with MetaWorldEnv(task, config) as env:
            for seed in range(SEED_START, SEED_START + EPISODES):
                policy.reset()
                planned: list = []  # every action decided, in order; the episode runs a prefix of them

                def decide(rows, observations, planned=planned):
                    o = observations[0]
                    steps = policy.action_steps(policy.predict_action(o["image"], o["instruction"], o["state"]))
                    planned.extend(np.asarray(step).tolist() for step in steps)
                    return [steps]

                (episode,) = rollout([env], [seed], decide)
                episodes[task, seed] = (episode.success, episode.length, planned[: episode.length])
    return episodes


def _served_episodes(policy: VLAPolicy, tmp_path, **serve_settings) -> tuple[dict, dict]:
    service = PolicyService(policy, ServeConfig(**serve_settings))
    service.warm_up()
    with PolicyServer(service, port=0) as server:
        config = RobotsConfig(tasks=TASKS, episodes_per_task=EPISODES, robots=ROBOTS, seed_start=SEED_START,
                              max_episode_steps=MAX_STEPS, server=server.url)  # fmt: skip
        summary = run_robots(config, tmp_path / "robots", progress=False)
    lines = (tmp_path / "robots" / "episodes.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in lines]
    return {(r["task"], r["seed"]): r for r in records}, summary


@pytest.fixture(scope="module")
def greedy_episodes(policy) -> dict:
    return _greedy_episodes(policy)


@pytest.mark.slow
@pytest.mark.parametrize(
    "settings",
    [
        pytest.param(dict(method="prior+jacobi", buckets=(1, 2, 4)), id="eager"),
        # the preset, compiled (static cache, compiled verification and greedy): one bucket holds the compile short
        pytest.param(dict(method="exact", buckets=(4,)), id="exact-compiled"),
    ],
)
def test_robots_through_the_server_act_as_greedy_in_one_process(policy, greedy_episodes, tmp_path, settings):
    expected = greedy_episodes
    served, summary = _served_episodes(policy, tmp_path, max_wait_ms=5.0, calibration_calls=2, **settings)
    assert set(served) == set(expected)
    for key, (success, length, actions) in expected.items():
        record = served[key]
        assert (record["success"], record["length"]) == (success, length), key
        np.testing.assert_array_equal(np.array(record["actions"]), np.array(actions), err_msg=str(key))
    batch_sizes = {int(size) for size in summary["batch_sizes"]}
    assert set(summary["methods"]) <= {PolicyService(policy, ServeConfig(settings["method"])).method.name, "greedy",
                                       "greedy:compile"}  # fmt: skip
    assert max(batch_sizes) > 1, f"the server formed no batch ({batch_sizes}): the test tests nothing"
    assert summary["speculative_fraction"] > 0
