"""OpenVLA on transformers 5.x without remote code: config, model, processor (see docs/openvla.md).

Importing this package registers ``model_type="openvla"`` with ``AutoConfig`` and ``OpenVLAForActionPrediction``
with ``AutoModelForImageTextToText`` and ``AutoModelForCausalLM``, so an official checkpoint folder loads with
``AutoModelForImageTextToText.from_pretrained(folder)``.
"""

import importlib.util

if importlib.util.find_spec("PIL") is None:  # the processor and the draft-training frames read images with Pillow
    raise ImportError("hf_specvla.openvla needs Pillow, which is not installed: pip install 'hf_specvla[openvla]'")

from transformers import AutoConfig, AutoModelForCausalLM, AutoModelForImageTextToText

from .configuration_openvla import OpenVLAConfig
from .modeling_openvla import OpenVLAForActionPrediction
from .processing_openvla import OpenVLAImageProcessor, OpenVLAProcessor
from .vision import VISION_TOWERS, VisionTowerSpec, register_vision_tower

AutoConfig.register(OpenVLAConfig.model_type, OpenVLAConfig, exist_ok=True)
AutoModelForImageTextToText.register(OpenVLAConfig, OpenVLAForActionPrediction, exist_ok=True)
AutoModelForCausalLM.register(OpenVLAConfig, OpenVLAForActionPrediction, exist_ok=True)

__all__ = [
    "VISION_TOWERS",
    "OpenVLAConfig",
    "OpenVLAForActionPrediction",
    "OpenVLAImageProcessor",
    "OpenVLAProcessor",
    "VisionTowerSpec",
    "register_vision_tower",
]
