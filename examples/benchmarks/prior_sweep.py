"""Sweep the action prior's tree budget and neighbour alternatives on recorded Meta-World steps (interleaved, one
thread): the table "Tree size of the action prior" in docs/benchmarks.md.

    python examples/benchmarks/prior_sweep.py policies/mt10_vla
"""

import sys

import torch

from hf_specvla.benchmarks.speed import EpisodeMethod, format_episode_report, run_episode_benchmark
from hf_specvla.metaworld.evaluation import record_observations
from hf_specvla.policies import VLAPolicy
from hf_specvla.speculative import ActionPriorDrafter

torch.set_num_threads(1)
policy = VLAPolicy.from_pretrained(sys.argv[1])
episodes = record_observations(policy, "MT10", [500_000, 500_001], max_steps=60)


def act(observation, history, prior_settings, **generate_kwargs):
    policy.previous_action_ids = []
    if prior_settings and history:
        generate_kwargs["assistant_model"] = ActionPriorDrafter(
            history, policy.action_layout, chunk_length=policy.config.chunk_length, **prior_settings
        )
    elif not history:  # an episode's first step: nothing to draft from
        generate_kwargs.pop("bin_tolerance", None)
    _, output = policy.predict_action(observation["image"], observation["instruction"], observation["state"],
                                      return_output=True, **generate_kwargs)  # fmt: skip
    return output.sequences[0, -policy.config.action_tokens :].tolist(), output


methods = [EpisodeMethod("greedy")]
for r in (0, 4):
    for nodes, neighbours in ((3, 0), (8, 0), (8, 1), (16, 1), (24, 1), (48, 2)):
        settings = dict(max_nodes=nodes, neighbour_bins=neighbours)
        name = f"prior max_nodes={nodes} neighbours={neighbours} r={r}"
        methods.append(EpisodeMethod(name, dict(bin_tolerance=r), settings))
print(format_episode_report(run_episode_benchmark(act, episodes, methods, policy.config.action_tokens)))
