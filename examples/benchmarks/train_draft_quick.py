"""A quick self-distilled DraftHead for a Meta-World policy (what docs/benchmarks.md used; `train-draft` is the
real command to come). On-policy states: greedy rollouts on seeds 400000+ (the episode benchmark replays seeds
300000+, evaluation uses 100000+).

    python examples/benchmarks/train_draft_quick.py policies/mt10_vla runs/mt10_draft_quick 1500
"""

import logging
import sys

import numpy as np
import torch

from hf_specvla import DraftHead
from hf_specvla.metaworld.evaluation import record_observations
from hf_specvla.policies import VLAPolicy
from hf_specvla.training.draft_head import DraftTrainingConfig, build_distillation_dataset, train_draft_head

logging.basicConfig(level=logging.INFO)
torch.set_num_threads(1)
policy_dir, output_dir, steps = sys.argv[1], sys.argv[2], int(sys.argv[3])
policy = VLAPolicy.from_pretrained(policy_dir)
episodes = record_observations(policy, "MT10", [400_000 + i for i in range(4)], max_steps=120)
prompts = []
for episode in episodes:  # one batch per 32 steps of an episode: one task, so prompts of one length
    for start in range(0, len(episode), 32):
        chunk = episode[start : start + 32]
        input_ids = torch.tensor([policy.prompt_ids(o["instruction"], o["state"]) for o in chunk])
        pixel_values = policy.preprocess_images(np.stack([o["image"] for o in chunk]))
        prompts.append({"input_ids": input_ids, "pixel_values": pixel_values})
dataset = build_distillation_dataset(policy.model, prompts, policy.config.action_dim, policy.action_tokenizer)
torch.manual_seed(0)
head = DraftHead.from_target(policy.model, policy.action_tokenizer, action_dim=policy.config.action_dim,
                             num_draft_tokens=3)  # fmt: skip
config = DraftTrainingConfig(output_dir, max_steps=steps, batch_size=32, learning_rate=3e-3, lr_schedule="cosine",
                             warmup_steps=50, save_every=0, seed=0)  # fmt: skip
train_draft_head(head, policy.model, dataset, config)
