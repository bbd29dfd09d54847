"""Served = local: robots driving a real policy server on 127.0.0.1 get, episode by episode, the actions that greedy
decoding gives the same policy in one process on the same seeds, whatever batches the server formed."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hf_specvla.metaworld.fleet import RobotsConfig, run_robots
from hf_specvla.policies import VLAPolicy
from hf_specvla.serving import PolicyService, ServeConfig
from hf_specvla.serving.server import PolicyServer

from .episodes import EPISODES, MAX_STEPS, ROBOTS, SEED_START, TASKS, check_served, greedy_episodes

POLICY = Path(__file__).resolve().parents[2] / "policies" / "mt10_vla3"
HEAD = POLICY.parent / "mt10_vla3_draft_v3"


@pytest.fixture(scope="module")
def policy() -> VLAPolicy:
    return VLAPolicy.from_pretrained(POLICY)


def _served_episodes(policy: VLAPolicy, tmp_path, draft_head=None, **serve_settings) -> tuple[dict, dict]:
    service = PolicyService(policy, ServeConfig(**serve_settings), draft_head)
    service.warm_up()
    with PolicyServer(service, port=0) as server:
        config = RobotsConfig(tasks=TASKS, episodes_per_task=EPISODES, robots=ROBOTS, seed_start=SEED_START,
                              max_episode_steps=MAX_STEPS, server=server.url)  # fmt: skip
        summary = run_robots(config, tmp_path / "robots", progress=False)
    lines = (tmp_path / "robots" / "episodes.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in lines]
    return {(r["task"], r["seed"]): r for r in records}, summary


@pytest.fixture(scope="module")
def expected(policy) -> dict:
    return greedy_episodes(policy)


@pytest.mark.slow
@pytest.mark.parametrize(
    "settings",
    [
        pytest.param(dict(method="prior+jacobi", buckets=(1, 2, 4)), id="eager"),
        # the preset, compiled (static cache, compiled verification and greedy): one bucket holds the compile short
        pytest.param(dict(method="exact", buckets=(4,)), id="exact-compiled"),
        # with the shipped head v3: each bucket picks greedy, prior+jacobi or the head's composition (eager), every
        # other batch explores another, so the robots are served by all three
        pytest.param(
            dict(method=("prior+jacobi", "prior+jacobi+tree"), buckets=(1, 2, 4), explore_every=2),
            id="with-a-draft-head",
        ),  # fmt: skip
    ],
)
def test_robots_through_the_server_act_as_greedy_in_one_process(policy, expected, tmp_path, settings):
    head = None
    if "tree" in str(settings["method"]):
        from hf_specvla.speculative import DraftHead

        head = DraftHead.from_pretrained(HEAD)
    served, summary = _served_episodes(policy, tmp_path, head, max_wait_ms=5.0, calibration_calls=2, **settings)
    check_served(served, summary, expected)
    methods = [m.name for m in PolicyService(policy, ServeConfig(settings["method"]), head).step.methods]
    assert set(summary["methods"]) <= {*methods, "greedy", "greedy:compile", "none:compile"}
    assert summary["speculative_fraction"] > 0
    if head is not None:
        assert set(summary["methods"]) == {*methods, "greedy"}, summary["methods"]
