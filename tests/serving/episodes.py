"""Greedy episodes in one process, what robots served by a policy server must reproduce action for action."""

from __future__ import annotations

import numpy as np

from hf_specvla.metaworld.env import EnvConfig, MetaWorldEnv
from hf_specvla.metaworld.rollout import rollout
from hf_specvla.policies import VLAPolicy

#: 4 MT10 tasks, 2 episodes each (4 robots x 2 episodes), cut at 24 steps: the served = local check
TASKS = ["reach-v3", "push-v3", "drawer-open-v3", "button-press-topdown-v3"]
EPISODES, ROBOTS, SEED_START, MAX_STEPS = 2, 4, 100000, 24


def greedy_episodes(policy: VLAPolicy) -> dict:
    """(task, seed) -> (success, length, actions executed) of greedy decoding, one episode at a time."""
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


def check_served(records: dict, summary: dict, expected: dict) -> None:
    """The robots' episodes (``episodes.jsonl`` records by (task, seed)) equal greedy's, and batches formed."""
    assert set(records) == set(expected)
    for key, (success, length, actions) in expected.items():
        record = records[key]
        assert (record["success"], record["length"]) == (success, length), key
        np.testing.assert_array_equal(np.array(record["actions"]), np.array(actions), err_msg=str(key))
    batch_sizes = {int(size) for size in summary["batch_sizes"]}
    assert max(batch_sizes) > 1, f"the server formed no batch ({batch_sizes}): the test tests nothing"
