"""Training a draft head for an OpenVLA checkpoint on a user's own frames (self-distillation, the one trainer).

The data is a folder of frames: ``frames.jsonl`` with one JSON object per line,
``{"image": "images/000123.png", "instruction": "put the cup in the sink"}`` (image paths relative to the folder;
any size and format PIL reads, RGB). The OpenVLA model labels every frame itself (greedy, 7 action tokens), so no
actions are needed: the head learns to predict what this model would output, on the observations it will see.

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
from .configuration import DraftTrainingConfig
from .draft_head import distil_draft_head

logger = logging.getLogger(__name__)

FRAMES_FILE = "frames.jsonl"


@dataclass
class OpenVLAFrame:
    """One observation: an RGB image (PIL or ``[H, W, 3]`` uint8) and the instruction given with it."""

    image: Image.Image | np.ndarray
    instruction: str


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
        path = folder / record["image"]
        if not path.is_file():
            raise FileNotFoundError(f"{where} names image {record['image']!r}, which is not in {folder}")
        with Image.open(path) as image:
            frames.append(OpenVLAFrame(image.convert("RGB"), instruction))
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


def train_openvla_draft_head(
    model: OpenVLAForActionPrediction,
    processor: OpenVLAProcessor,
    train_frames: list[OpenVLAFrame],
    validation_frames: list[OpenVLAFrame],
    training_config: DraftTrainingConfig,
    num_draft_tokens: int = 3,
    unnorm_key: str | None = None,
    progress: bool = True,
) -> DraftHead:
    """Trains a [`DraftHead`] for ``model`` into ``training_config.output_dir`` and returns it.

    The head records the model it was distilled from (``target_name_or_path`` and a fingerprint of its weights),
    validation (the engine at r=0 on ``validation_frames``) goes to ``validation.jsonl``, checkpoints and resume
    work as for every draft head (the folder's ``run.json`` is checked before any frame is labelled).
    """
    if not train_frames or not validation_frames:
        raise ValueError(f"need training and validation frames, got {len(train_frames)} and {len(validation_frames)}")
    action_dim = model.get_action_dim(unnorm_key)
    train_prompts = openvla_prompts(model, processor, train_frames)
    recipe = {"data": {"frames": len(train_prompts), "fingerprint": fingerprint_prompts(train_prompts)}}

    def prompts() -> tuple[list, list]:
        logger.info("labelling %d frames with the model's own greedy actions", len(train_prompts))
        return train_prompts, openvla_prompts(model, processor, validation_frames)

    return distil_draft_head(
        model, training_config, recipe, prompts, action_dim, action_dim=action_dim,
        num_draft_tokens=num_draft_tokens, action_layout=model.action_layout(unnorm_key),
        target_name_or_path=model.config._name_or_path or None, progress=progress,
    )  # fmt: skip


def fingerprint_prompts(prompts: list[dict[str, torch.Tensor]]) -> str:
    """A short hash of every prompt's ids and pixels (what ``resume`` compares)."""
    return fingerprint_arrays(*[p["input_ids"] for p in prompts], *[p["pixel_values"] for p in prompts])
