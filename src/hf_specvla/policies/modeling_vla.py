"""An OpenVLA-style vision-language-action policy, small enough to train and run on a CPU.

Model: a transformers ``LlavaForConditionalGeneration`` (CLIP vision encoder -> MLP projector -> Llama decoder),
built from small configs; its decoder is a plain transformers language model, so ``generate`` (and the
speculative engine, via ``assistant_model=DraftHead``) drives it unchanged.

The prompt and the inputs are built by [`VLAProcessor`] (``processing_vla.py``). The model generates
``chunk_length * action_dim`` action tokens greedily; ``predict_action`` maps them back through the bin centers and
the action statistics.

One folder is a complete policy: ``save_pretrained`` writes the model, the tokenizer and ``policy_config.json``
(image processing, prompt layout and the normalisation statistics).
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from transformers import (
    CLIPVisionConfig,
    LlamaConfig,
    LlavaConfig,
    LlavaForConditionalGeneration,
    PreTrainedTokenizerFast,
)

from ..actions.tokenizer import ActionLayout, ActionNormalizer, ActionUnits
from ..actions.vla_tokenizer import build_vla_tokenizer
from ..speculative import (
    enable_speculation,
    named_weight_errors,
)
from .acting import ActionPolicy
from .configuration_vla import POLICY_CONFIG_NAME, VLAPolicyConfig, check_policy_folder
from .processing_vla import VLAProcessor


class VLAPolicy(ActionPolicy):
    """An OpenVLA-style policy: ``predict_action(image, instruction, state)`` -> un-normalised action (acting:
    [`ActionPolicy`]).

    Attributes:
        model: the Llava model (speculation enabled: ``generate`` accepts a DraftHead assistant).
        tokenizer, action_tokenizer, action_normalizer, state_normalizer, config.
        action_layout: the action tokens and ``action_dim`` (what relaxed acceptance needs).
    """

    def __init__(self, model, tokenizer, config: VLAPolicyConfig):
        super().__init__()
        self.model = enable_speculation(model)
        self.tokenizer = tokenizer
        self.config = config
        self.processor = VLAProcessor(tokenizer, config)
        self.action_tokenizer = self.processor.action_tokenizer
        self.action_normalizer = self.processor.action_normalizer
        self.state_normalizer = self.processor.state_normalizer
        self.scene_normalizer = self.processor.scene_normalizer
        units = ActionUnits.from_normalizer(self.action_tokenizer, self.action_normalizer, config.action_dim)
        self.action_layout = ActionLayout(self.action_tokenizer, config.action_dim, units)

    # ----------------------------------------------------------------------------- building
    @classmethod
    def build(
        cls,
        instructions: list[str],
        action_normalizer: ActionNormalizer,
        state_normalizer: ActionNormalizer | None,
        config: VLAPolicyConfig | None = None,
        seed: int = 0,
        scene_normalizer: ActionNormalizer | None = None,
    ) -> VLAPolicy:
        """A new, untrained policy whose tokenizer covers ``instructions`` (``scene_normalizer``: the scene-state
        statistics, needed when ``config.scene_state_dim > 0``)."""
        config = config or VLAPolicyConfig()
        if action_normalizer.action_dim != config.action_dim:
            raise ValueError(
                f"the action statistics have {action_normalizer.action_dim} dimensions, the policy "
                f"action_dim={config.action_dim}"
            )
        scene_dim = scene_normalizer.action_dim if scene_normalizer is not None else 0
        if config.scene_state_dim and scene_dim != config.scene_state_dim:
            raise ValueError(
                f"scene_state_dim={config.scene_state_dim} needs scene-state statistics of that many dimensions, "
                f"got {scene_dim}"
            )
        config.action_stats = action_normalizer.to_dict()
        config.state_stats = state_normalizer.to_dict() if state_normalizer is not None else {}
        config.scene_stats = scene_normalizer.to_dict() if config.scene_state_dim else {}
        tokenizer = build_vla_tokenizer([*instructions, "state:"])
        vision = CLIPVisionConfig(
            hidden_size=config.vision_hidden_size,
            intermediate_size=2 * config.vision_hidden_size,
            num_hidden_layers=config.vision_layers,
            num_attention_heads=4,
            image_size=config.image_size,
            patch_size=config.patch_size,
            projection_dim=config.vision_hidden_size,
        )
        text = LlamaConfig(
            vocab_size=len(tokenizer),
            hidden_size=config.text_hidden_size,
            intermediate_size=2 * config.text_hidden_size,
            num_hidden_layers=config.text_layers,
            num_attention_heads=config.text_heads,
            num_key_value_heads=max(1, config.text_heads // 2),
            max_position_embeddings=256,
            bos_token_id=tokenizer.bos_token_id,
            eos_token_id=tokenizer.eos_token_id,
            pad_token_id=tokenizer.pad_token_id,
        )
        llava = LlavaConfig(
            vision_config=vision,
            text_config=text,
            image_token_id=tokenizer.convert_tokens_to_ids("<image>"),
            image_seq_length=config.num_image_tokens,
            vision_feature_select_strategy="default",
            vision_feature_layer=-1,
        )
        torch.manual_seed(seed)
        model = LlavaForConditionalGeneration(llava)
        model.generation_config.pad_token_id = tokenizer.pad_token_id
        return cls(model.eval(), tokenizer, config)

    # ----------------------------------------------------------------------------- inputs
    def preprocess_images(self, images) -> torch.Tensor:
        """[`VLAProcessor.preprocess_images`], on the model's device and dtype."""
        images = np.stack(images) if isinstance(images, list | tuple) else images
        return self.processor.preprocess_images(images).to(self.model.device, self.model.dtype)

    def prompt_ids(self, instruction: str, state=None) -> list[int]:
        """[`VLAProcessor.prompt_ids`]: the prompt's token ids."""
        return self.processor.prompt_ids(instruction, state)

    def action_token_ids(self, actions) -> np.ndarray:
        """[`VLAProcessor.action_token_ids`]: raw actions ``[..., action_dim]`` -> their token ids."""
        return self.processor.action_token_ids(actions)

    def actions_from_token_ids(self, action_ids, unnorm_key: str | None = None) -> np.ndarray:
        """The inverse of [`action_token_ids`]: token ids ``[..., action_dim]`` -> un-normalised actions (one set of
        statistics: ``unnorm_key`` is None)."""
        self.check_unnorm_key(unnorm_key)
        return self.action_normalizer.unnormalize(self.action_tokenizer.decode(action_ids))

    def training_batch(self, images, states, actions, instructions: list[str], scene_states=None) -> dict:
        """[`VLAProcessor.training_batch`] on the model's device."""
        batch = self.processor.training_batch(images, states, actions, instructions, scene_states)
        batch["pixel_values"] = batch["pixel_values"].to(self.model.dtype)
        return {name: value.to(self.model.device) for name, value in batch.items()}

    # ----------------------------------------------------------------------------- persistence
    def save_pretrained(self, folder: str | Path) -> None:
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        self.model.save_pretrained(folder)
        self.tokenizer.save_pretrained(folder)
        (folder / POLICY_CONFIG_NAME).write_text(json.dumps(asdict(self.config), indent=2))

    @classmethod
    def from_pretrained(cls, folder: str | Path, **model_kwargs) -> VLAPolicy:
        """Loads a policy folder written by ``save_pretrained``.

        Raises:
            FileNotFoundError: naming the missing folder or file.
        """
        folder = Path(folder)
        check_policy_folder(folder)
        config = VLAPolicyConfig(**json.loads((folder / POLICY_CONFIG_NAME).read_text()))
        with named_weight_errors(folder, "policy"):
            model = LlavaForConditionalGeneration.from_pretrained(folder, **model_kwargs)
        tokenizer = PreTrainedTokenizerFast.from_pretrained(folder)
        policy = cls(model.eval(), tokenizer, config)
        policy.name_or_path = str(folder)
        return policy
