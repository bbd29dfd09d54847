"""Behaviour cloning of a [`VLAPolicy`] on Meta-World demonstrations, on accelerate.

Next-token cross-entropy on the action tokens only (the prompt, image and state tokens carry no loss; a policy
with ``scene_state_dim`` also learns the scene-state tokens after them, weighted by ``scene_loss_weight``, and / or,
with ``scene_readout_weight``, a linear readout of the scene state where the first action token is decoded:
[`PolicyWithSceneReadout`]), AdamW with
warm-up and cosine decay, random-shift image augmentation (pad 4 px by edge replication, crop back: DrQ's
augmentation, which matters for behaviour cloning from pixels). Validation on held-out *episodes*: loss and
action-token accuracy (teacher-forced argmax == demonstrated token). Periodic checkpoints with full accelerate
state; ``resume=True`` continues from the newest one.
"""

from __future__ import annotations

import json
import logging
from dataclasses import fields
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from ..metaworld.demonstrations import Demonstrations
from ..metaworld.env import TASK_INSTRUCTIONS
from ..policies import POLICY_CONFIG_NAME, VLAPolicy, VLAPolicyConfig
from ..run_folder import fingerprint_arrays
from .checkpoints import latest_checkpoint, prepare_output_dir, training_record
from .configuration import VLATrainingConfig
from .loop import TrainingJob, run_training

logger = logging.getLogger(__name__)


def action_chunk_indices(episode_index: np.ndarray, chunk_length: int) -> np.ndarray:
    """For every frame, the frames whose actions form its chunk: ``[N, chunk_length]`` int64.

    Row j is ``j, j+1, ..., j+H-1`` (the frame's action and the next ones of the same episode); past the
    episode's last frame the last frame repeats (the last action is held: an expert episode ends at success,
    where holding still is the right continuation). Frames of an episode must be stored consecutively, in step
    order (as [`load_demonstrations`] returns them).
    """
    count = len(episode_index)
    indices = np.arange(count)[:, None] + np.arange(chunk_length)[None, :]  # [N, H]
    # the last frame of each frame's episode: episodes are contiguous runs of equal episode ids
    is_last = np.append(episode_index[1:] != episode_index[:-1], True)
    last_of_run = np.flatnonzero(is_last)
    episode_last = last_of_run[np.searchsorted(last_of_run, np.arange(count))]  # [N]
    return np.minimum(indices, episode_last[:, None])


class FrameDataset(Dataset):
    """Frames of some episodes of a [`Demonstrations`]: ``(image, state, action_chunk, instruction, scene_state)``
    with ``action_chunk`` ``[chunk_length, action_dim]`` (see [`action_chunk_indices`]) and ``scene_state`` None
    when the demonstrations have none."""

    def __init__(self, demos: Demonstrations, indices: np.ndarray, chunk_length: int = 1):
        self.demos, self.indices = demos, indices
        self.chunks = action_chunk_indices(demos.episode_index, chunk_length)

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int):
        j = int(self.indices[i])
        demos = self.demos
        scene_state = None if demos.scene_states is None else demos.scene_states[j]
        actions = demos.actions[self.chunks[j]]  # [H, A]
        return demos.images[j], demos.states[j], actions, TASK_INSTRUCTIONS[demos.tasks[j]], scene_state


def split_episodes(demos: Demonstrations, val_episodes: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Frame indices (train, val): ``val_episodes`` random episodes of every task go to validation."""
    rng = np.random.default_rng(seed)
    tasks = np.asarray(demos.tasks)
    val_ids: set[int] = set()
    for task in sorted(set(demos.tasks)):
        episodes = np.unique(demos.episode_index[tasks == task])
        if len(episodes) > val_episodes:
            val_ids.update(rng.choice(episodes, val_episodes, replace=False).tolist())
    is_val = np.isin(demos.episode_index, list(val_ids))
    return np.flatnonzero(~is_val), np.flatnonzero(is_val)


def random_shift(images: np.ndarray, pad: int, rng: np.random.Generator) -> np.ndarray:
    """DrQ augmentation: edge-pad ``[B, S, S, 3]`` uint8 images by ``pad`` and crop back at random offsets."""
    if pad == 0:
        return images
    size = images.shape[1]
    padded = np.pad(images, ((0, 0), (pad, pad), (pad, pad), (0, 0)), mode="edge")
    out = np.empty_like(images)
    for b, (dy, dx) in enumerate(rng.integers(0, 2 * pad + 1, size=(len(images), 2))):
        out[b] = padded[b, dy : dy + size, dx : dx + size]
    return out


def _collate(batch):
    images, states, actions, instructions, scene_states = zip(*batch)
    scene_states = None if scene_states[0] is None else np.stack(scene_states)
    return np.stack(images), np.stack(states), np.stack(actions), list(instructions), scene_states


def target_losses(logits: torch.Tensor, labels: torch.Tensor, action_dim: int) -> dict[str, torch.Tensor]:
    """Next-token cross-entropy split into the action tokens and the scene-state tokens after them.

    Args:
        logits: ``[B, L, V]``; labels: ``[B, L]``, -100 except on the target tokens (``training_batch``).
        action_dim: the first ``action_dim`` targets of each row are the action tokens (a chunk's: all of them).

    Returns:
        ``action_loss`` (mean over action tokens), ``action_correct`` (how many argmax predictions equal the
        action tokens), ``action_count``, and ``scene_loss`` when the rows have scene-state targets.
    """
    labels = labels[:, 1:]
    logits = logits[:, :-1]
    is_target = labels != -100
    is_action = is_target & (is_target.cumsum(dim=1) <= action_dim)
    is_scene = is_target & ~is_action
    losses = {
        "action_loss": torch.nn.functional.cross_entropy(logits[is_action].float(), labels[is_action]),
        "action_correct": (logits[is_action].argmax(-1) == labels[is_action]).sum(),
        "action_count": is_action.sum(),
    }
    if is_scene.any():
        losses["scene_loss"] = torch.nn.functional.cross_entropy(logits[is_scene].float(), labels[is_scene])
    return losses


class PolicyWithSceneReadout(torch.nn.Module):
    """Training only: a policy's model with a linear readout from the decoder's last hidden state at the position that
    decodes the first action token (the prompt's last) to the frame's scene state (object and goal xyz, normalised
    like the scene tokens). Its loss asks the representation the actions are decoded from to hold where the object and
    the goal are, with nothing to copy them from (scene tokens after the actions can lean on the demonstrated actions,
    which point at both). The readout is kept in checkpoints (a resumed run continues it) and never in the policy
    folder: acting is unchanged.

    Attributes:
        model: the policy's ``LlavaForConditionalGeneration``; readout: ``Linear(text hidden size, scene_dim)``.
    """

    def __init__(self, model, scene_dim: int):
        super().__init__()
        self.model = model
        self.readout = torch.nn.Linear(model.config.text_config.hidden_size, scene_dim)

    def forward(self, readout_positions: torch.Tensor, **inputs) -> tuple[torch.Tensor, torch.Tensor]:
        """``inputs``: the model's (``input_ids`` ``[B, L]``, ``attention_mask``, ``pixel_values``);
        ``readout_positions`` ``[B]``: where each row's readout reads. Returns logits ``[B, L, V]`` and the readout
        ``[B, scene_dim]``."""
        output = self.model(**inputs, output_hidden_states=True)
        hidden = output.hidden_states[-1]  # [B, L, D], after the final norm
        rows = torch.arange(len(hidden), device=hidden.device)
        return output.logits, self.readout(hidden[rows, readout_positions])


def _forward(
    policy: VLAPolicy, model, images, states, actions, instructions, scene_states, readout: bool = False
) -> dict[str, torch.Tensor]:
    """The action (and scene-state) token losses of ``model`` (the policy's model, maybe accelerate-wrapped); with
    ``readout`` (``model`` a [`PolicyWithSceneReadout`]) also ``scene_readout_loss`` (mean squared error against the
    normalised scene state) and the readout's mean ``scene_readout_object_m`` / ``scene_readout_goal_m`` errors."""
    batch = policy.training_batch(images, states, actions, instructions, scene_states)
    labels = batch.pop("labels")
    if not readout:
        return target_losses(model(**batch).logits, labels, policy.config.action_tokens)
    positions = (labels != -100).int().argmax(dim=1) - 1  # [B]: the position that decodes the first target token
    logits, predicted = model(readout_positions=positions, **batch)
    losses = target_losses(logits, labels, policy.config.action_tokens)
    normalizer, scene_states = policy.scene_normalizer, np.asarray(scene_states)  # [B, 6]
    target = torch.as_tensor(normalizer.normalize(scene_states), dtype=predicted.dtype)
    losses["scene_readout_loss"] = torch.nn.functional.mse_loss(predicted, target.to(predicted.device))
    metres = normalizer.unnormalize(predicted.detach().float().cpu().numpy()) - scene_states  # [B, 6]
    losses["scene_readout_object_m"] = torch.tensor(np.linalg.norm(metres[:, :3], axis=1).mean())
    losses["scene_readout_goal_m"] = torch.tensor(np.linalg.norm(metres[:, 3:6], axis=1).mean())
    return losses


@torch.no_grad()
def validate(policy: VLAPolicy, model, loader: DataLoader, readout: bool = False) -> dict[str, float]:
    """Mean action-token ``loss`` and ``action_token_accuracy`` (teacher-forced) over a loader; and the scene-state
    tokens' ``scene_loss`` for a policy that learns them; with ``readout``, the scene readout's loss and mean object /
    goal errors in metres (see [`_forward`]). ``model`` in eval mode (the training loop's hook)."""
    sums: dict[str, float] = {}
    correct = count = batches = 0
    for images, states, actions, instructions, scene_states in loader:
        losses = _forward(policy, model, images, states, actions, instructions, scene_states, readout)
        correct += int(losses.pop("action_correct"))
        count += int(losses.pop("action_count"))
        for name, value in losses.items():
            sums[name] = sums.get(name, 0.0) + value.item()
        batches += 1
    metrics = {"loss": sums.get("action_loss", 0.0) / max(batches, 1), "action_token_accuracy": correct / max(count, 1)}
    for name in ("scene_loss", "scene_readout_loss", "scene_readout_object_m", "scene_readout_goal_m"):
        if name in sums:
            metrics[name] = sums[name] / batches
    return metrics


def decoder_layer_map(source_layers: int, target_layers: int) -> dict[int, int]:
    """Where each of a trained decoder's ``source_layers`` layers goes in a deeper one: spread evenly, in order,
    the first at 0 (``{source: target}``)."""
    if target_layers < source_layers:
        raise ValueError(
            f"a policy can only be grown: the source decoder has {source_layers} layers, the new one {target_layers}"
        )
    return {i: (i * target_layers) // source_layers for i in range(source_layers)}


@torch.no_grad()
def grow_from(policy: VLAPolicy, source: VLAPolicy) -> dict[int, int]:
    """Initialises ``policy`` from a trained ``source`` policy with a shallower decoder of the same width.

    Every weight whose name and shape match is copied (vision tower, projector, embeddings, lm_head, final norm);
    the source's decoder layers go to the places [`decoder_layer_map`] gives, and every *new* layer starts as
    the identity: its attention output and MLP down projections are zero, so its residual branches add nothing
    and the grown model computes exactly the source's function (until training moves them). Returns the layer map.

    A finer image with the same token grid (e.g. 128 px in 32 px patches from 64 px in 16 px patches) is allowed: the
    patch embedding's kernel is spread over the f x f pixels each source pixel became (repeated, divided by f^2), so
    on an image upsampled by f (nearest) the grown model computes the source's function; the finer image's extra
    detail is for training to use.

    Raises:
        ValueError: the two policies differ in anything but decoder depth and image resolution at the same token
            grid (widths, vocabulary, token grid).
    """
    keys = (
        "action_dim",
        "state_dim",
        "use_state",
        "vision_hidden_size",
        "vision_layers",
        "text_hidden_size",
        "text_heads",
    )
    new, old = policy.config, source.config
    scale = new.image_size // old.image_size
    finer = new.num_image_tokens == old.num_image_tokens and scale >= 1 and new.patch_size == scale * old.patch_size
    if (new.image_size, new.patch_size) != (old.image_size, old.patch_size) and not finer:
        raise ValueError(
            f"--init-from: the source policy sees {source.config.image_size} px images in "
            f"{source.config.patch_size} px patches, the new one {policy.config.image_size} px in "
            f"{policy.config.patch_size} px patches; the image may only be finer by an integer factor f with patches "
            f"f times larger (the same token grid), e.g. {source.config.image_size * 2} px in "
            f"{source.config.patch_size * 2} px patches"
        )
    for key in keys:
        if getattr(policy.config, key) != getattr(source.config, key):
            raise ValueError(
                f"--init-from: the source policy has {key}={getattr(source.config, key)!r}, the new one "
                f"{getattr(policy.config, key)!r}; only the decoder's depth (and chunk_length) may differ"
            )
    if len(policy.tokenizer) != len(source.tokenizer) or policy.tokenizer.get_vocab() != source.tokenizer.get_vocab():
        raise ValueError("--init-from: the source policy's vocabulary differs from this one's")
    layer_map = decoder_layer_map(source.config.text_layers, policy.config.text_layers)
    prefix = "model.language_model.layers."
    source_state = source.model.state_dict()
    renamed = {}
    for name, tensor in source_state.items():
        if name.startswith(prefix):
            index, rest = name[len(prefix) :].split(".", 1)
            name = f"{prefix}{layer_map[int(index)]}.{rest}"
        renamed[name] = tensor
    target_state = policy.model.state_dict()
    for name, tensor in target_state.items():
        if name in renamed and name.endswith("patch_embedding.weight") and scale > 1:  # [H, C, p, p] -> [H, C, fp, fp]
            source_kernel = renamed[name].repeat_interleave(scale, dim=-1).repeat_interleave(scale, dim=-2)
            tensor.copy_(source_kernel / scale**2)
        elif name in renamed:
            if renamed[name].shape != tensor.shape:
                raise ValueError(
                    f"--init-from: {name} has shape {tuple(renamed[name].shape)} in the source, "
                    f"{tuple(tensor.shape)} here"
                )
            tensor.copy_(renamed[name])
        elif name.startswith(prefix) and name.endswith(("self_attn.o_proj.weight", "mlp.down_proj.weight")):
            tensor.zero_()  # a new layer: its residual branches start silent
    return layer_map


def _check_resumed_policy_config(output_dir: Path, policy_config) -> None:
    """A resumed run must build the same model as its checkpoint; names the option that differs."""
    checkpoint = latest_checkpoint(output_dir)
    saved_path = checkpoint / "policy" / POLICY_CONFIG_NAME if checkpoint else None
    if saved_path is None or not saved_path.exists():
        return
    saved = json.loads(saved_path.read_text())
    # every option that shapes the model; the statistics are the data's, recomputed on each run
    model_keys = [f.name for f in fields(policy_config) if not f.name.endswith("_stats")]
    for key in model_keys:
        if key in saved and saved[key] != getattr(policy_config, key):
            raise ValueError(
                f"--resume: {checkpoint} was trained with {key}={saved[key]!r} but this run asks for "
                f"{getattr(policy_config, key)!r}; repeat the original options"
            )


def check_demonstrations(demos: Demonstrations, config: VLATrainingConfig, policy_config: VLAPolicyConfig) -> None:
    """Refuses, before a policy is built or trained, demonstrations that ``config`` cannot train a policy of
    ``policy_config`` on: another action size, missing scene states, fewer training frames than a batch.

    Raises:
        ValueError: naming the mismatch and what to change.
    """
    if demos.actions.shape[1] != policy_config.action_dim:
        raise ValueError(
            f"the demonstrations have {demos.actions.shape[1]}-dim actions, the policy action_dim="
            f"{policy_config.action_dim}; build the policy from this dataset's statistics"
        )
    scene_dim = 0 if demos.scene_states is None else demos.scene_states.shape[1]
    if policy_config.scene_state_dim and scene_dim != policy_config.scene_state_dim:
        raise ValueError(
            f"the policy learns scene_state_dim={policy_config.scene_state_dim} scene targets but the "
            f"demonstrations have {scene_dim or 'no'} scene-state values per frame (collected before the "
            "scene_state column existed?); collect them again or train without scene targets"
        )
    if config.scene_readout_weight > 0 and not policy_config.scene_state_dim:
        raise ValueError(
            f"scene_readout_weight={config.scene_readout_weight} reads the scene state into the policy's scene-state "
            "statistics: build the policy with scene_state_dim (train-vla --scene-targets)"
        )
    train_idx, _ = split_episodes(demos, config.val_episodes, config.seed)
    if len(train_idx) < config.batch_size:  # drop_last would leave no batch at all
        raise ValueError(
            f"batch_size={config.batch_size} is larger than the {len(train_idx)} training frames (after holding out "
            f"{config.val_episodes} validation episodes); use --batch-size {max(1, len(train_idx))} or less, or "
            "collect more episodes"
        )


def train_vla(
    policy: VLAPolicy,
    demos: Demonstrations,
    config: VLATrainingConfig,
    progress: bool = True,
    init_from: VLAPolicy | None = None,
) -> dict:
    """Behaviour-clones ``policy`` on ``demos``; saves it to ``config.output_dir``; returns the last metrics.

    ``init_from``: a trained policy with a shallower decoder to start from ([`grow_from`]); its weights'
    fingerprint is part of the run's record.
    """
    output_dir = Path(config.output_dir)
    check_demonstrations(demos, config, policy.config)
    train_idx, val_idx = split_episodes(demos, config.val_episodes, config.seed)
    if config.resume and not config.overwrite_output_dir:
        _check_resumed_policy_config(output_dir, policy.config)
    model_settings = {
        f.name: getattr(policy.config, f.name) for f in fields(policy.config) if not f.name.endswith("_stats")
    }
    inputs = {
        "policy_config": model_settings,
        "data": fingerprint_arrays(demos.actions, demos.states, demos.episode_index),
    }
    if init_from is not None:
        inputs["init_from"] = init_from.weights_fingerprint()
        layer_map = grow_from(policy, init_from)  # in memory only: refusals come before the folder is touched
        logger.info("initialised from %s (decoder layers %s)", init_from.name_or_path, layer_map)
    if config.freeze_vision:  # the loop trains the parameters that require gradients
        policy.model.model.vision_tower.requires_grad_(False)
    readout = config.scene_readout_weight > 0
    model = PolicyWithSceneReadout(policy.model, policy.config.scene_state_dim) if readout else policy.model
    record = training_record("train-vla", config, inputs)
    with prepare_output_dir(output_dir, record, config.resume, config.overwrite_output_dir) as run:
        chunk = policy.config.chunk_length
        val_loader = DataLoader(FrameDataset(demos, val_idx, chunk), batch_size=config.batch_size, collate_fn=_collate)

        def loss(model, batch, step: int):
            images, states, actions, instructions, scene_states = batch
            rng = np.random.default_rng((config.seed, step))  # per step: a resumed run augments identically
            images = random_shift(images, config.augment_shift, rng)
            losses = _forward(policy, model, images, states, actions, instructions, scene_states, readout)
            metrics = {"loss": losses["action_loss"].detach()}
            total = losses["action_loss"]
            if "scene_loss" in losses:
                total = total + config.scene_loss_weight * losses["scene_loss"]
                metrics["scene_loss"] = losses["scene_loss"].detach()
            if readout:
                total = total + config.scene_readout_weight * losses["scene_readout_loss"]
                metrics["scene_readout_loss"] = losses["scene_readout_loss"].detach()
            return total, metrics

        def policy_model(model):  # what a policy folder holds: a scene readout stays in the checkpoint
            return model.model if isinstance(model, PolicyWithSceneReadout) else model

        def save(model, folder: Path) -> None:
            policy.model = policy_model(model)  # the unwrapped model
            policy.save_pretrained(folder)

        job = TrainingJob(
            model,
            FrameDataset(demos, train_idx, chunk),
            loss,
            save,
            validate=(lambda model: validate(policy, model, val_loader, readout)) if len(val_idx) else None,
            collate_fn=_collate,
            drop_last=True,
            checkpoint_name="policy",
            description="train-vla",
        )
        model, metrics = run_training(job, config, run.bound, progress=progress)  # the claimed folder
        policy.model = policy_model(model)
        return metrics
