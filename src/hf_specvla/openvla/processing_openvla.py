"""``OpenVLAProcessor``: image -> the official 6-channel ``pixel_values``; instruction -> the official prompt ids.

It reads a checkpoint folder's own ``preprocessor_config.json`` (the official ``PrismaticImageProcessor`` fields) and
tokenizer files, without remote code. Each tower's transform is timm's eval transform as the official code applies
it: a bicubic PIL resize (``resize-naive``: straight to the tower's square size), a centre crop (a no-op there),
``[0, 1]`` scaling and the normalisation stored in the JSON. OpenVLA-7B's stored DINOv2 mean/std are the ImageNet
constants rounded to bfloat16 (the conversion ran with bf16 as default dtype); they are used as stored.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass

import numpy as np
import torch
from PIL import Image
from transformers import AutoTokenizer, BatchFeature, PreTrainedTokenizerBase

PREPROCESSOR_CONFIG = "preprocessor_config.json"

#: PIL resampling filters by the torchvision ``InterpolationMode`` values the official JSON stores.
_RESAMPLING = {0: Image.NEAREST, 2: Image.BILINEAR, 3: Image.BICUBIC, 1: Image.LANCZOS}

#: The prompt OpenVLA was trained with (``instruction`` is lower-cased, as in the official examples).
PROMPT_TEMPLATE = "In: What action should the robot take to {instruction}?\nOut:"


@dataclass(frozen=True)
class TowerTransform:
    """One tower's eval transform: resize to ``size`` (height, width), centre-crop to ``crop``, normalise."""

    size: tuple[int, int]
    crop: tuple[int, int]
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    resample: int = Image.BICUBIC

    def __call__(self, image: Image.Image) -> torch.Tensor:
        """RGB PIL image -> ``[3, crop_h, crop_w]`` float32."""
        height, width = self.size
        if image.size != (width, height):
            image = image.resize((width, height), resample=self.resample)
        crop_h, crop_w = self.crop
        top, left = int(round((height - crop_h) / 2.0)), int(round((width - crop_w) / 2.0))
        array = np.asarray(image, dtype=np.uint8)[top : top + crop_h, left : left + crop_w]
        tensor = torch.from_numpy(array.copy()).permute(2, 0, 1).float().div(255)
        mean = torch.tensor(self.mean, dtype=torch.float32)[:, None, None]
        std = torch.tensor(self.std, dtype=torch.float32)[:, None, None]
        return (tensor - mean) / std


#: PIL modes converted to RGB exactly as the official processor does (``image.convert("RGB")``): 8-bit colour, with or
#: without alpha (dropped), 8-bit grey (repeated), and palettes (looked up)
PIL_MODES = ("RGB", "RGBA", "L", "P")


def _as_pil(image) -> Image.Image:
    """A PIL image of an 8-bit mode (``PIL_MODES``) or an ``[H, W, 3]`` uint8 array -> RGB PIL image.

    Raises:
        TypeError / ValueError: naming what was given (type, PIL mode, dtype, shape) and what is valid. Images whose
            conversion to 8-bit RGB would lose or invent information (float ``F``, 16/32-bit ``I;16`` / ``I``, float
            arrays) are refused rather than silently turned black or saturated.
    """
    if isinstance(image, Image.Image):
        if image.mode not in PIL_MODES:
            raise ValueError(
                f"a PIL image of mode {image.mode!r} cannot be converted to 8-bit RGB faithfully; pass one of the "
                f"modes {PIL_MODES} (e.g. scale a 16-bit or float image to 0..255 and convert it to 'L' or 'RGB' first)"
            )
        return image.convert("RGB")
    if isinstance(image, torch.Tensor):
        image = image.detach().cpu().numpy()
    if not isinstance(image, np.ndarray):
        raise TypeError(f"image must be a PIL.Image or an [H, W, 3] uint8 array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        hint = " (a float image in [0, 1]: (image * 255).round().astype(np.uint8))" if image.dtype.kind == "f" else ""
        raise ValueError(f"an image array must be uint8 (0..255), got dtype {image.dtype}{hint}")
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"an image array must have shape [H, W, 3] (RGB), got {image.shape}")
    return Image.fromarray(image, mode="RGB")


class OpenVLAImageProcessor:
    """Images -> ``pixel_values`` ``[B, 3 * towers, H, W]`` (towers stacked on the channel axis).

    Args:
        transforms: one [`TowerTransform`] per vision tower.
    """

    def __init__(self, transforms: list[TowerTransform]):
        if not transforms:
            raise ValueError("an OpenVLA image processor needs at least one tower transform")
        self.transforms = list(transforms)

    @classmethod
    def from_dict(cls, config: dict) -> OpenVLAImageProcessor:
        """From the official ``preprocessor_config.json`` fields (``tvf_*_params``)."""
        strategy = config.get("image_resize_strategy")
        if strategy != "resize-naive":
            raise ValueError(
                f"image_resize_strategy={strategy!r} is not supported by the OpenVLA port (OpenVLA uses 'resize-naive')"
            )
        transforms = []
        for resize, crop, normalize in zip(
            config["tvf_resize_params"], config["tvf_crop_params"], config["tvf_normalize_params"], strict=True
        ):
            interpolation = resize.get("interpolation", 3)
            if interpolation not in _RESAMPLING:
                raise ValueError(
                    f"interpolation mode {interpolation} is not supported; supported: {sorted(_RESAMPLING)}"
                )
            transforms.append(
                TowerTransform(
                    size=tuple(resize["size"]),
                    crop=tuple(crop["output_size"]),
                    mean=tuple(normalize["mean"]),
                    std=tuple(normalize["std"]),
                    resample=_RESAMPLING[interpolation],
                )
            )
        return cls(transforms)

    def __call__(self, images) -> torch.Tensor:
        """One image or a list -> ``[B, 3 * towers, H, W]`` float32.

        Raises:
            ValueError: no image (None or an empty list), or an image of a kind [`_as_pil`] refuses.
        """
        if images is None:
            raise ValueError("images is None: pass one image (PIL.Image or [H, W, 3] uint8 array) per prompt")
        images = images if isinstance(images, (list, tuple)) else [images]
        if not images:
            raise ValueError("images is an empty list: pass one image (PIL.Image or [H, W, 3] uint8 array) per prompt")
        return torch.stack([torch.cat([t(_as_pil(image)) for t in self.transforms]) for image in images])


class OpenVLAProcessor:
    """Tokenizer + image processor of an OpenVLA checkpoint.

    ``processor(prompt, image)`` returns ``input_ids``, ``attention_mask`` and ``pixel_values`` as the official
    ``PrismaticProcessor`` does; ``processor.prompt(instruction)`` builds the official prompt.
    """

    def __init__(self, image_processor: OpenVLAImageProcessor, tokenizer: PreTrainedTokenizerBase):
        self.image_processor = image_processor
        self.tokenizer = tokenizer

    @classmethod
    def from_pretrained(cls, folder: str | os.PathLike, **tokenizer_kwargs) -> OpenVLAProcessor:
        """From a checkpoint folder holding ``preprocessor_config.json`` and the tokenizer files.

        Raises:
            FileNotFoundError: naming the missing file.
        """
        path = os.path.join(folder, PREPROCESSOR_CONFIG)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"{folder} has no {PREPROCESSOR_CONFIG}: not an OpenVLA checkpoint folder")
        with open(path) as handle:
            image_processor = OpenVLAImageProcessor.from_dict(json.load(handle))
        tokenizer = AutoTokenizer.from_pretrained(folder, **tokenizer_kwargs)
        return cls(image_processor, tokenizer)

    @staticmethod
    def prompt(instruction: str) -> str:
        """The official prompt for an instruction (lower-cased)."""
        if not isinstance(instruction, str) or not instruction.strip():
            raise ValueError(f"instruction must be a non-empty string, got {instruction!r}")
        return PROMPT_TEMPLATE.format(instruction=instruction.lower())

    def __call__(self, text, images, padding=False, return_tensors="pt") -> BatchFeature:
        """Prompt(s) and image(s) -> ``input_ids`` / ``attention_mask`` ``[B, L]`` and ``pixel_values``."""
        encoded = self.tokenizer(text, padding=padding, return_tensors=return_tensors)
        pixel_values = self.image_processor(images)
        if pixel_values.shape[0] != encoded["input_ids"].shape[0]:
            raise ValueError(
                f"got {encoded['input_ids'].shape[0]} prompts and {pixel_values.shape[0]} images; pass one image per "
                f"prompt"
            )
        return BatchFeature({**encoded, "pixel_values": pixel_values})
