"""Training a draft head for an OpenVLA checkpoint on a user's own frames (self-distillation, the one trainer).

The data is a folder of frames: ``frames.jsonl`` with one JSON object per line,
``{"image": "images/000123.png", "instruction": "put the cup in the sink"}`` (image paths relative to the folder;
any size and format PIL reads, RGB). The OpenVLA model labels every frame itself (greedy, 7 action tokens), so no
actions are needed: the head learns to predict what this model would output, on the observations it will see.
A frame may also give the action the robot took before it, ``"previous_action": [7 action token ids]``, which a
head v2 (``head_version="v2"``) reads; a frame without one trains its "no previous action" input.

Recipe (see docs/openvla.md)::

    model = OpenVLAForActionPrediction.from_pretrained(folder, dtype=torch.bfloat16, device_map="cuda")
    processor = OpenVLAProcessor.from_pretrained(folder)
    frames = load_frames("my_frames")
    head = train_openvla_draft_head(model, processor, frames[:-50], frames[-50:],
                                    DraftTrainingConfig(output_dir="openvla_draft", max_steps=2000))
    head.push_to_hub(...)  # or share the folder: DraftHead.from_pretrained("openvla_draft")
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from ..openvla.modeling_openvla import OpenVLAForActionPrediction
from ..openvla.processing_openvla import OpenVLAProcessor
from ..run_folder import fingerprint_arrays
from ..speculative import DraftHead
from .configuration import HEAD_VERSIONS, DraftTrainingConfig
from .draft_head import PREVIOUS_ACTION, distil_draft_head, head_v2_settings

logger = logging.getLogger(__name__)

FRAMES_FILE = "frames.jsonl"


@dataclass
class OpenVLAFrame:
    """One observation: an RGB image (PIL or ``[H, W, 3]`` uint8) and the instruction given with it."""

    image: Image.Image | np.ndarray
    instruction: str
    previous_action: list[int] | None = None  # the robot's action before this frame, as action token ids


def load_frames(folder: str | Path) -> list[OpenVLAFrame]:
    """The frames of a folder in the format above, images loaded as RGB.

    Raises:
        FileNotFoundError / ValueError: naming the file and line that is missing or malformed.
    """
    folder = Path(folder)
    index = folder / FRAMES_FILE
    if not index.is_file():
        raise FileNotFoundError(f"{folder} has no {FRAMES_FILE} (one {{'image': ..., 'instruction': ...}} per line)")
    frames = []
    for number, line in enumerate(index.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        where = f"{index}:{number}"
        try:
            record = json.loads(line)
        except json.JSONDecodeError as error:
            raise ValueError(f"{where} is not valid JSON ({error})") from None
        if not isinstance(record, dict) or not isinstance(record.get("image"), str):
            raise ValueError(f"{where} must be an object with a string 'image' path and an 'instruction'")
        instruction = record.get("instruction")
        if not isinstance(instruction, str) or not instruction.strip():
            raise ValueError(f"{where} has no instruction (a non-empty string), got {instruction!r}")
        previous = record.get("previous_action")
        if previous is not None and (
            not isinstance(previous, list) or not all(isinstance(t, int) and not isinstance(t, bool) for t in previous)
        ):
            raise ValueError(f"{where}: previous_action must be a list of action token ids, got {previous!r}")
        path = folder / record["image"]
        if not path.is_file():
            raise FileNotFoundError(f"{where} names image {record['image']!r}, which is not in {folder}")
        with Image.open(path) as image:
            frames.append(OpenVLAFrame(image.convert("RGB"), instruction, previous))
    if not frames:
        raise ValueError(f"{index} lists no frames")
    return frames


def openvla_prompts(
    model: OpenVLAForActionPrediction, processor: OpenVLAProcessor, frames: list[OpenVLAFrame]
) -> list[dict[str, torch.Tensor]]:
    """One generation input per frame, as ``predict_action`` builds it: the official prompt + 29871, with the image
    rows as image tokens (so sequences and hidden states line up for distillation)."""
    prompts = []
    for frame in frames:
        inputs = processor(processor.prompt(frame.instruction), frame.image)
        input_ids, mask = model.add_image_tokens(*model.end_prompt(inputs["input_ids"], inputs["attention_mask"]))
        prompts.append({"input_ids": input_ids, "attention_mask": mask, "pixel_values": inputs["pixel_values"]})
    return prompts


def distillation_prompts(
    model: OpenVLAForActionPrediction,
    processor: OpenVLAProcessor,
    frames: list[OpenVLAFrame],
    unnorm_key: str | None = None,
) -> list[dict[str, torch.Tensor]]:
    """[`openvla_prompts`] with each frame's ``previous_action`` ``[1, D]`` (-1: none), as the distillation reads
    them.

    Raises:
        ValueError: a previous action that is not ``D`` of the model's action token ids (naming the frame).
    """
    tokenizer, action_dim = model.action_tokenizer, model.get_action_dim(unnorm_key)
    for index, frame in enumerate(frames):
        previous = frame.previous_action
        if previous is not None and (
            len(previous) != action_dim or not all(tokenizer.is_action_token(t) for t in previous)
        ):
            raise ValueError(
                f"frame {index}: previous_action must be {action_dim} action token ids (ids "
                f"{tokenizer.action_token_begin}..{tokenizer.vocab_size - 1}), got {previous}"
            )
    return [
        {**prompt, PREVIOUS_ACTION: torch.tensor([frame.previous_action or [-1] * action_dim])}
        for prompt, frame in zip(openvla_prompts(model, processor, frames), frames)
    ]


def train_openvla_draft_head(
    model: OpenVLAForActionPrediction,
    processor: OpenVLAProcessor,
    train_frames: list[OpenVLAFrame],
    validation_frames: list[OpenVLAFrame],
    training_config: DraftTrainingConfig,
    num_draft_tokens: int = 3,
    unnorm_key: str | None = None,
    progress: bool = True,
    head_version: str = "v1",
) -> DraftHead:
    """Trains a [`DraftHead`] for ``model`` into ``training_config.output_dir`` and returns it.

    The head records the model it was distilled from (``target_name_or_path`` and a fingerprint of its weights),
    validation (the engine at r=0 on ``validation_frames``) goes to ``validation.jsonl``, checkpoints and resume
    work as for every draft head (the folder's ``run.json`` is checked before any frame is labelled).
    ``head_version`` "v2" builds a head v2 ([`head_v2_settings`]: layers 2, 16 and the last of OpenVLA-7B's 32, and
    the frames' previous actions); train it with ``training_config.unroll_steps`` > 1 (training-time test).
    """
    if head_version not in HEAD_VERSIONS:
        raise ValueError(f"head_version must be one of {HEAD_VERSIONS}, got {head_version!r}")
    if not train_frames or not validation_frames:
        raise ValueError(f"need training and validation frames, got {len(train_frames)} and {len(validation_frames)}")
    action_dim = model.get_action_dim(unnorm_key)
    train_prompts = distillation_prompts(model, processor, train_frames, unnorm_key)
    recipe = {"data": {"frames": len(train_prompts), "fingerprint": fingerprint_prompts(train_prompts)}}

    def prompts() -> tuple[list, list]:
        logger.info("labelling %d frames with the model's own greedy actions", len(train_prompts))
        return train_prompts, distillation_prompts(model, processor, validation_frames, unnorm_key)

    return distil_draft_head(
        model,
        training_config,
        recipe,
        prompts,
        action_dim,
        action_dim=action_dim,
        num_draft_tokens=num_draft_tokens,
        action_layout=model.action_layout(unnorm_key),
        target_name_or_path=model.config._name_or_path or None,
        progress=progress,
        head_settings=head_v2_settings(model) if head_version == "v2" else None,
    )


def fingerprint_prompts(prompts: list[dict[str, torch.Tensor]]) -> str:
    """A short hash of every prompt's ids and pixels, and of the previous actions any frame gives (what ``resume``
    compares)."""
    arrays = [p["input_ids"] for p in prompts] + [p["pixel_values"] for p in prompts]
    previous = [p[PREVIOUS_ACTION] for p in prompts if bool((p[PREVIOUS_ACTION] >= 0).any())]
    return fingerprint_arrays(*arrays, *previous)
