"""A draft head for a [`VLAPolicy`]: what ``hf-specvla train-draft`` runs.

Self-distillation (see [`hf_specvla.training.draft_head`]) on the policy's own greedy actions, over two kinds of frames:

* **on-policy**: the states the policy itself reaches in greedy rollouts (seeds from ``DRAFT_SEED_START``,
  400000), which is where the head is used; the last ``validation_episodes`` rollouts of every task are held out.
  Collected in-process, or read from a folder of ``hf-specvla rollouts`` (``rollouts=``, [`read_rollout_frames`]:
  the same frames, collected once, resumably, by several workers);
* **demonstrations** (optional): frames of ``hf-specvla collect`` folders, sampled per task.

Validation runs the speculative engine itself (draft-head chain, ``bin_tolerance=0``) on the held-out rollouts'
frames and reports its per-position acceptance and tokens per target forward: the numbers a user will see.

Seed ranges, kept apart: demonstrations 0.., evaluation 100000.., the second fidelity range 200000.., the episode
benchmark 300000.., draft training 400000.., so that a head is never measured on a start it was trained on.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import ConcatDataset

from ..metaworld.demonstrations import dataset_fingerprint, dataset_info, load_demonstrations
from ..metaworld.env import TASK_INSTRUCTIONS, EnvConfig
from ..metaworld.evaluation import record_observations
from ..policies import VLAPolicy
from ..run_folder import read_jsonl
from ..speculative import DraftHead
from .configuration import HEAD_VERSIONS, DraftDataConfig, DraftTrainingConfig, check_draft_chain
from .draft_head import PREVIOUS_ACTION, distil_draft_head, head_settings
from .loop import VALIDATION_LOG
from .processes import is_main_process
from .rollouts import EpisodeFrames, read_rollout_frames

logger = logging.getLogger(__name__)

MODEL_CARD = "README.md"


# ----------------------------------------------------------------------------- frames
def rollout_frames(policy: VLAPolicy, config: DraftDataConfig, env_config: EnvConfig) -> tuple[list, list]:
    """Greedy rollouts of ``policy``: (training frames, held-out frames), each a list of observation dicts."""
    seeds = [config.rollout_seed_start + i for i in range(config.rollout_episodes)]
    held_out = set(seeds[-config.validation_episodes :])
    train, validation = [], []
    for task in config.tasks:
        episodes = record_observations(policy, [task], seeds, config.rollout_max_steps, env_config)
        for seed, episode in zip(seeds, episodes):
            (validation if seed in held_out else train).extend(episode)
    return train, validation


def demonstration_frames(roots: list[str | Path], config: DraftDataConfig, policy: VLAPolicy) -> list[dict]:
    """``demo_frames_per_task`` frames of each task sampled from demonstration folders (fewer if a task has
    fewer); each an observation dict."""
    info = dataset_info(roots)
    if info.get("image_size") != policy.config.image_size or info.get("camera") != policy.config.camera:
        raise ValueError(
            f"the demonstrations have image_size={info.get('image_size')}, camera={info.get('camera')!r}; the policy "
            f"sees image_size={policy.config.image_size}, camera={policy.config.camera!r}: collect them with the "
            f"policy's settings"
        )
    demos = load_demonstrations(roots, config.tasks, progress=False)
    rng = np.random.default_rng(config.seed)
    tasks = np.asarray(demos.tasks)
    frames = []
    for task in config.tasks:
        indices = np.flatnonzero(tasks == task)
        if len(indices) == 0:
            raise ValueError(f"the demonstrations in {[str(r) for r in roots]} have no frames of {task!r}")
        chosen = np.sort(rng.choice(indices, min(config.demo_frames_per_task, len(indices)), replace=False))
        frames.extend(
            {"image": demos.images[i], "instruction": TASK_INSTRUCTIONS[task], "state": demos.states[i]} for i in chosen
        )
    return frames


class PolicyPrompts(Sequence):
    """Model inputs for frames, batched by instruction (one prompt length per batch, so no padding), each batch built
    when it is asked for: only the batch in use holds pixel values (``[B, 3, H, W]`` float32, 196 KB a frame at
    128 x 128), never every frame's. Iterate it as often as needed (a batch is rebuilt each time, the same).

    A batch: ``input_ids`` ``[B, S]``, ``pixel_values`` ``[B, 3, H, W]``, and each frame's ``previous_action``
    ``[B, D]`` (token ids; -1 where a frame has none: an episode's first step, a demonstration frame).
    ``num_examples``: the frames, over every batch.
    """

    def __init__(self, policy: VLAPolicy, frames: Sequence[dict], batch_size: int, instructions: list[str]):
        self.policy, self.frames = policy, frames
        by_instruction: dict[str, list[int]] = {}  # frame indices per instruction, in order of first appearance
        for index, instruction in enumerate(instructions):
            by_instruction.setdefault(instruction, []).append(index)
        self.batches = [
            group[start : start + batch_size]
            for group in by_instruction.values()
            for start in range(0, len(group), batch_size)
        ]
        self.num_examples = len(instructions)

    def __len__(self) -> int:
        return len(self.batches)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        policy, chunk = self.policy, [self.frames[i] for i in self.batches[index]]
        input_ids = torch.tensor([policy.prompt_ids(f["instruction"], f["state"]) for f in chunk])
        pixel_values = policy.preprocess_images(np.stack([f["image"] for f in chunk]))
        none = [-1] * policy.config.action_dim
        previous = torch.tensor([list(f.get("previous_action") or none) for f in chunk])
        return {"input_ids": input_ids.to(policy.model.device), "pixel_values": pixel_values, PREVIOUS_ACTION: previous}


def policy_prompts(policy: VLAPolicy, frames: Sequence[dict], batch_size: int) -> PolicyPrompts:
    """[`PolicyPrompts`] for ``frames`` (observation dicts, or [`EpisodeFrames`] read lazily; a list of both kinds is
    a ``ConcatDataset`` of them), in batches of at most ``batch_size`` frames of one instruction."""
    return PolicyPrompts(policy, frames, batch_size, frame_instructions(frames))


def frame_instructions(frames: Sequence[dict]) -> list[str]:
    """Each frame's instruction, without reading an [`EpisodeFrames`]' images."""
    if isinstance(frames, EpisodeFrames):
        return frames.instructions
    if isinstance(frames, ConcatDataset):
        return [instruction for part in frames.datasets for instruction in frame_instructions(part)]
    return [frame["instruction"] for frame in frames]


def _spread(frames: list, count: int) -> list:
    """At most ``count`` of ``frames``, evenly spread (deterministic)."""
    if len(frames) <= count:
        return frames
    return [frames[int(i)] for i in np.linspace(0, len(frames) - 1, count).round()]


# ----------------------------------------------------------------------------- training
def train_policy_draft_head(
    policy: VLAPolicy,
    training_config: DraftTrainingConfig,
    data_config: DraftDataConfig | None = None,
    demonstrations: list[str | Path] | tuple = (),
    num_draft_tokens: int | None = None,
    progress: bool = True,
    command: str | None = None,
    head_version: str = "v1",
    rollouts: str | Path | None = None,
    image_features: bool = False,
) -> DraftHead:
    """Trains a [`DraftHead`] for ``policy`` (see module docstring) into ``training_config.output_dir``.

    The head records the policy it was distilled from (``target_name_or_path``, ``target_fingerprint``), so that
    a head used with another policy is refused. The folder gets the head, ``validation.jsonl`` and a model card
    (``README.md``, with the measured acceptance and ``command``). The folder rule (``run.json``: the policy's
    weights, the data recipe, the training settings) is checked before any rollout runs.

    ``head_version``: "v1" (the last hidden state, no previous action: every head before v2), "v2"
    ([`head_v2_settings`]: a low, a middle and the top layer, and the robot's previous action; train it with
    ``training_config.unroll_steps`` > 1, training-time test) or "v3" ([`head_v3_settings`]: v2's inputs, a block per
    head forward and drafts before the prefill; ``unroll_steps`` = the block's length); ``image_features``: a v3 head's
    drafts before the prefill read the encoded image too.

    ``rollouts``: a folder of ``hf-specvla rollouts`` of this policy to read the on-policy frames from (those
    ``data_config`` asks for) instead of rolling the policy out here; ``run.json`` and the model card record its path
    and the fingerprint of the episodes read. A folder of another policy is refused.
    """
    if head_version not in HEAD_VERSIONS:
        raise ValueError(f"head_version must be one of {HEAD_VERSIONS}, got {head_version!r}")
    data_config = data_config or DraftDataConfig()
    demonstrations = [str(Path(root)) for root in demonstrations]
    output_dir = Path(training_config.output_dir)
    if num_draft_tokens is None:
        num_draft_tokens = policy.config.action_tokens - 1
    check_draft_chain(
        num_draft_tokens, policy.config.action_tokens, training_config.unroll_steps, head_version == "v3"
    )  # before any rollout
    env_config = EnvConfig(image_size=policy.config.image_size, camera=policy.config.camera)
    recipe = {
        "data": {
            **asdict(data_config),
            "demonstration_fingerprints": [dataset_fingerprint(root) for root in demonstrations],
            "demonstration_info": [dataset_info(root) for root in demonstrations],
        }
    }
    paths = {"demonstrations": demonstrations}
    read = None  # the frames of a rollouts folder, read (and fingerprinted) before the folder rule is checked
    if rollouts is not None:
        read = read_rollout_frames(rollouts, policy, data_config)
        recipe["data"]["rollouts_fingerprint"] = read.fingerprint
        paths["rollouts"] = str(rollouts)
        logger.info(
            "read %d episodes (%d + %d frames) from %s (fingerprint %s)",
            read.episodes,
            len(read.train),
            len(read.validation),
            rollouts,
            read.fingerprint,
        )
    sequences = 0  # training sequences, one per frame (for the model card)

    def prompts() -> tuple[PolicyPrompts, PolicyPrompts]:
        if read is not None:  # read lazily, an episode at a time, as each batch of prompts is built
            train_frames, validation_frames = read.train, read.validation
        else:
            logger.info(
                "on-policy rollouts: %d per task on %d tasks", data_config.rollout_episodes, len(data_config.tasks)
            )
            train_frames, validation_frames = rollout_frames(policy, data_config, env_config)
        if demonstrations:
            train_frames = ConcatDataset([train_frames, demonstration_frames(demonstrations, data_config, policy)])
        validation_frames = _spread(validation_frames, data_config.validation_frames)
        logger.info("%d training frames, %d held-out frames", len(train_frames), len(validation_frames))
        nonlocal sequences
        sequences = len(train_frames)
        return (
            policy_prompts(policy, train_frames, data_config.prompt_batch_size),
            policy_prompts(policy, validation_frames, batch_size=1),
        )

    head = distil_draft_head(
        policy.model,
        training_config,
        recipe,
        prompts,
        policy.config.action_tokens,
        action_tokenizer=policy.action_tokenizer,
        action_dim=policy.config.action_dim,
        num_draft_tokens=num_draft_tokens,
        action_layout=policy.action_layout,
        target_name_or_path=policy.name_or_path,
        target_fingerprint=policy.weights_fingerprint(),
        paths=paths,
        progress=progress,
        head_settings=head_settings(head_version, policy.model, image_features),
    )
    if is_main_process():
        write_model_card(
            output_dir,
            head,
            training_config,
            data_config,
            demonstrations,
            sequences,
            command,
            policy.config.action_tokens,
            paths.get("rollouts"),
            read.fingerprint if read else None,
        )
    return head


# ----------------------------------------------------------------------------- model card
def _head_v3_card(config, training_config: DraftTrainingConfig, by_position: dict) -> str:
    """The model card's head-v3 paragraph: its modes, and its top-1 by token position on training and held-out frames
    (``accuracy_by_position`` of the last validation), side by side so that overfitting shows."""
    modes = [
        f"drafts a block of {config.num_draft_tokens} tokens per head forward"
        if config.draft_mode == "block"
        else "drafts a chain (one head forward per token)"
    ]
    if config.prefill_drafts:
        modes.append("drafts the whole action before the prefill (from the prompt and the previous action)")
    text = (
        f"\nHead v3: it reads the policy's hidden states of layers {list(config.hidden_state_layers)} and the "
        f"robot's previous action; it {' and '.join(modes)}; {training_config.unroll_steps} steps per example.\n"
    )
    for mode in ("before_prefill", "after_prefill"):
        train, held_out = by_position.get("train", {}).get(mode), by_position.get("held_out", {}).get(mode)
        if not train or not held_out:
            continue
        first = 0 if mode == "before_prefill" else 1  # the action's token each entry drafts
        header = " | ".join(f"token {first + i}" for i in range(len(train)))
        text += (
            f"\nTop-1 by token {mode.replace('_', ' ')} (teacher-forced, the policy's own greedy tokens):\n\n"
            f"| frames | {header} |\n|---|{'---:|' * len(train)}\n"
            f"| training | {' | '.join(f'{x:.1%}' for x in train)} |\n"
            f"| held-out | {' | '.join(f'{x:.1%}' for x in held_out)} |\n"
        )
    return text


def write_model_card(
    output_dir: Path,
    head: DraftHead,
    training_config: DraftTrainingConfig,
    data_config: DraftDataConfig,
    demonstrations: list[str],
    num_examples: int,
    command: str | None,
    tokens_per_call: int | None = None,
    rollouts: str | None = None,
    rollouts_fingerprint: str | None = None,
) -> None:
    """``README.md`` with YAML metadata, as hub models have: target, data, command, measured acceptance (and the
    ``rollouts`` folder the on-policy frames were read from, with its episodes' fingerprint)."""
    validations = read_jsonl(output_dir / VALIDATION_LOG)
    final = validations[-1] if validations else {}
    acceptance = final.get("acceptance_per_position", [])
    rows = "\n".join(f"| {depth + 1} | {rate:.1%} |" for depth, rate in enumerate(acceptance))
    config = head.config
    version = ""
    if config.feature_layers is not None or config.previous_action_input:
        reads = [f"the policy's hidden states of layers {list(config.hidden_state_layers)} (fused)"]
        if config.previous_action_input:
            reads.append("the robot's previous action")
        version = (
            f"\nHead v2: it reads {' and '.join(reads)}; trained on {training_config.unroll_steps} unrolled "
            f"draft steps of its own features (training-time test).\n"
        )
    if config.uses_mask_queries:
        version = _head_v3_card(config, training_config, final.get("accuracy_by_position", {}))
    tasks = ", ".join(data_config.tasks)
    kept_rollouts = data_config.rollout_episodes - data_config.validation_episodes
    source = (
        f", read from the `hf-specvla rollouts` folder `{rollouts}` (episodes fingerprint `{rollouts_fingerprint}`)"
        if rollouts
        else ""
    )
    demo_text = (
        f"and {data_config.demo_frames_per_task} demonstration frames per task from {', '.join(demonstrations)}"
        if demonstrations
        else "(no demonstrations)"
    )
    card = f"""---
library_name: hf_specvla
pipeline_tag: robotics
tags:
- speculative-decoding
- draft-head
- eagle
- vision-language-action
base_model: {config.target_name_or_path}
---

# Draft head for `{config.target_name_or_path}`

An EAGLE-style draft head (one decoder layer, {head.num_parameters():,} parameters) for speculative decoding of
the vision-language-action policy `{config.target_name_or_path}` (weights fingerprint `{config.target_fingerprint}`;
a head is refused by a policy with other weights). It borrows the policy's embedding and lm_head at run time.
{version}
```python
from hf_specvla import DraftHead
from hf_specvla.policies import VLAPolicy

policy = VLAPolicy.from_pretrained("{config.target_name_or_path}")
draft_head = DraftHead.from_pretrained("{output_dir}")
action = policy.predict_action(image, instruction, state, assistant_model=draft_head)  # identical to greedy
```

## Training

Self-distillation on the policy's own greedy actions (`hf-specvla train-draft`), {num_examples} frames:
greedy rollouts of the policy on {tasks} ({kept_rollouts} per task, seeds from {data_config.rollout_seed_start},
cut at {data_config.rollout_max_steps} steps{source}) {demo_text}; {training_config.max_steps} steps, batch
{training_config.batch_size}, learning rate {training_config.learning_rate} ({training_config.lr_schedule}), chain
length {config.num_draft_tokens}.

```bash
{command or "(trained from Python: hf_specvla.training.policy_draft.train_policy_draft_head)"}
```

## Measured acceptance

The speculative engine itself (draft-head chain, `bin_tolerance=0`) on {final.get("sequences", 0)} held-out frames (the
last {data_config.validation_episodes} rollout(s) of each task), after {final.get("step", 0)} steps: tokens per target
forward **{final.get("tokens_per_target_forward", float("nan")):.2f}**, target forwards per action
**{final.get("target_forwards_per_sequence", float("nan")):.2f}** (greedy: {tokens_per_call or config.action_dim}).

| drafted position | accepted |
|---:|---:|
{rows}

Every validation is in `validation.jsonl`; what produced this folder is in `run.json`.
"""
    (output_dir / MODEL_CARD).write_text(card)
