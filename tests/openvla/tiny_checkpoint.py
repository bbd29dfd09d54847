"""A tiny random OpenVLA saved as a checkpoint folder beside the real openvla-7b tokenizer files (from the shared
reference) and a 28-pixel ``preprocessor_config.json``: what ``hf-specvla serve --policy <folder>`` loads. Its vision
towers are not registered in a fresh process: the folder's config.json carries their shapes."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import torch

from hf_specvla.openvla import OpenVLAForActionPrediction

from .test_openvla import HUB_7B, PREPROCESSOR_FIELDS, tiny_config

#: the openvla-7b files a checkpoint's tokenizer reads
TOKENIZER_FILES = ("tokenizer.json", "tokenizer.model", "tokenizer_config.json", "special_tokens_map.json",
                   "added_tokens.json")  # fmt: skip


def tiny_openvla_model(seed: int = 0) -> OpenVLAForActionPrediction:
    """A tiny random OpenVLA whose greedy decoding lands on action tokens (as a trained one does)."""
    torch.manual_seed(seed)
    model = OpenVLAForActionPrediction(tiny_config()).eval()
    with torch.no_grad():
        model.get_output_embeddings().weight[31744:32000] *= 8.0
    return model


def write_tiny_checkpoint(folder: Path, seed: int = 0, **config_overrides) -> Path:
    """Saves [`tiny_openvla_model`] with the real tokenizer files and a preprocessor config into ``folder``."""
    model = tiny_openvla_model(seed)
    if config_overrides:
        for name, value in config_overrides.items():
            setattr(model.config, name, value)
    model.save_pretrained(folder)
    for name in TOKENIZER_FILES:
        shutil.copy(HUB_7B / name, folder / name)
    (folder / "preprocessor_config.json").write_text(json.dumps(PREPROCESSOR_FIELDS))
    return folder
