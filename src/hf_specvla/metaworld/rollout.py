"""The one rollout: episodes from ``env.reset(seed)`` in lockstep, each decision executed whole, until success, the
step limit or a cap on decisions. Evaluation, the paired comparison, observation recording and demonstration
collection all run their episodes here; what each decides and records is its own (the ``decide`` function and the
``on_step`` callback).

A *decision* is one call of ``decide``: for every running episode, the env actions to execute before the next call
(one action for a plain policy or the expert, a chunk of H for a chunked policy). The episodes stay in lockstep: an
episode leaves the batch when it ends, and the others carry on.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from .env import MetaWorldEnv

#: ``decide(rows, observations) -> plans``: ``rows`` the running episodes' indices, ``observations`` theirs (dicts
#: with ``image``, ``instruction``, ``state``); one plan per row, the env actions to execute in order.
Decide = Callable[[list[int], list[dict]], Sequence[Sequence[np.ndarray]]]
#: ``on_step(row, observation, info)`` after every env step: the observation the action was decided on, the step's info.
OnStep = Callable[[int, dict, dict], None]


@dataclass
class Episode:
    """How one episode ended: ``length`` env steps, ``decisions`` calls of ``decide``."""

    task: str
    seed: int
    success: bool = False
    length: int = 0
    decisions: int = 0


def rollout(
    envs: Sequence[MetaWorldEnv],
    seeds: Sequence[int],
    decide: Decide,
    on_step: OnStep | None = None,
    max_decisions: int | None = None,
) -> list[Episode]:
    """Runs one episode per env (``envs[b].reset(seeds[b])``) in lockstep; ``max_decisions`` cuts an episode after
    that many decisions (unfinished: ``success`` False).

    Raises:
        ValueError: not one seed per env, the same env object twice, or a plan that is not a list of actions.
    """
    if len(envs) != len(seeds) or not envs:
        raise ValueError(f"rollout needs one seed per environment, got {len(envs)} envs and {len(seeds)} seeds")
    if len({id(env) for env in envs}) != len(envs):
        raise ValueError("rollout needs distinct environment objects, one per episode")
    observations = [env.reset(seed) for env, seed in zip(envs, seeds)]
    episodes = [Episode(env.task, seed) for env, seed in zip(envs, seeds)]
    running = list(range(len(envs)))
    while running:
        plans = decide(running, [observations[b] for b in running])
        if len(plans) != len(running):
            raise ValueError(f"decide returned {len(plans)} plans for {len(running)} running episodes")
        still_running = []
        for b, plan in zip(running, plans):
            episodes[b].decisions += 1
            done = False
            for action in plan:
                decided_on = observations[b]
                observations[b], _, done, info = envs[b].step(action)
                episodes[b].length += 1
                if on_step is not None:
                    on_step(b, decided_on, info)
                if done:
                    episodes[b].success = bool(info["success"])
                    break
            if not done and (max_decisions is None or episodes[b].decisions < max_decisions):
                still_running.append(b)
        running = still_running
    return episodes
