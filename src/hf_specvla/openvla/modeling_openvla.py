"""``OpenVLAForActionPrediction``: OpenVLA on transformers 5.x, computing what the official code computes.

The model is the official one, module for module, so that ``state_dict()`` keys are the checkpoint's own (no key
mapping, sharded or single-file checkpoints load as they are): ``vision_backbone`` (one or two ViTs, see
``vision.py``), ``projector`` and ``language_model`` (transformers' own ``LlamaForCausalLM``).

The image enters the language model as ``num_patches`` projected patch embeddings right after BOS. Two equivalent
inputs say so:

* the official one: ``input_ids`` without image rows plus ``pixel_values``; ``forward`` inserts the patches after
  position 0 (logits then have ``num_patches`` more rows than ``input_ids``), exactly as the official code does;
* the generation one: ``input_ids`` that already hold ``num_patches`` copies of ``config.image_token_id`` where the
  patches go (as Llava's prompts do). Sequence length, cache length and position ids then agree, which is what
  ``generate`` and the speculative loop (tree verification inside the prefill, cache surgery) rely on.
  ``generate`` turns the first form into the second and takes the image rows out of the returned sequences, so
  ``generate(input_ids, pixel_values=...)`` returns the official ``input_ids + new tokens``.

Speculation: ``generate(..., assistant_model=draft_head | drafter, draft_ids=..., bin_tolerance=r)`` and
``predict_action`` with the same options (see [`SpeculativeGenerationMixin`]).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn
from transformers import AutoModelForCausalLM, GenerationConfig, GenerationMixin, PreTrainedModel
from transformers import initialization as init
from transformers.modeling_outputs import CausalLMOutputWithPast

from ..actions.tokenizer import ActionLayout, ActionNormalizer, ActionTokenizer, ActionUnits
from ..speculative import (
    CACHE_KEY,
    SPECULATION_KWARGS,
    ActionPriorDrafter,
    Drafter,
    DraftHead,
    SpeculativeGenerationMixin,
    cache_of,
    episode_drafter,
    is_local_path,
    named_weight_errors,
    remember_actions,
    with_generation_config,
)
from .configuration_openvla import OpenVLAConfig
from .vision import AttentionPoolLatent, LayerScale, OpenVLAProjector, OpenVLAVisionBackbone, VisionTransformer

#: The token the official ``predict_action`` appends to a prompt that does not end with it (``"▁"``, what
#: "Out: " ends with when tokenized during training).
PROMPT_END_TOKEN_ID = 29871

IGNORE_INDEX = -100

#: How many offending key names an error message shows.
_KEYS_SHOWN = 5


def check_checkpoint_folder(name_or_path: str | os.PathLike) -> None:
    """Raises when a local ``name_or_path`` is not a complete OpenVLA checkpoint; does nothing for a hub repo id.

    Complete: ``config.json`` with ``model_type: "openvla"``, and ``model.safetensors`` or an index whose every shard
    is present.

    Raises:
        FileNotFoundError / ValueError: naming the path and what is missing or wrong.
    """
    if not is_local_path(name_or_path):
        return
    folder = Path(name_or_path).expanduser()
    if not folder.is_dir():
        raise FileNotFoundError(
            f"OpenVLA checkpoint folder {str(name_or_path)!r} does not exist (a local path: it is "
            f"not looked up on the hub)"
        )
    config_file = folder / "config.json"
    if not config_file.is_file():
        raise FileNotFoundError(f"{str(name_or_path)!r} has no config.json: not an OpenVLA checkpoint folder")
    model_type = json.loads(config_file.read_text()).get("model_type")
    if model_type != OpenVLAConfig.model_type:
        raise ValueError(
            f"{str(name_or_path)!r} holds a {model_type!r} model, not an OpenVLA checkpoint "
            f"(model_type {OpenVLAConfig.model_type!r})"
        )
    index_file = folder / "model.safetensors.index.json"
    if index_file.is_file():
        shards = sorted(set(json.loads(index_file.read_text())["weight_map"].values()))
        missing = [shard for shard in shards if not (folder / shard).is_file()]
        if missing:
            raise FileNotFoundError(
                f"{str(name_or_path)!r} is missing {len(missing)} of the {len(shards)} weight "
                f"shards its index lists: {missing[:_KEYS_SHOWN]}"
            )
    elif not (folder / "model.safetensors").is_file():
        raise FileNotFoundError(
            f"{str(name_or_path)!r} has neither model.safetensors nor model.safetensors.index.json: no weights to load"
        )


@dataclass
class OpenVLACausalLMOutputWithPast(CausalLMOutputWithPast):
    """The language model's output (its cache under the installed transformers' name, ``CACHE_KEY``), plus the
    projected patch features when asked for.

    Attributes:
        logits: ``[B, L, V]`` (``L`` counts the image rows).
        projector_features: ``[B, num_patches, llm_dim]`` or None.
    """

    projector_features: torch.FloatTensor | None = None


class OpenVLAPreTrainedModel(PreTrainedModel):
    config_class = OpenVLAConfig
    base_model_prefix = "model"
    main_input_name = "input_ids"
    supports_gradient_checkpointing = False
    _no_split_modules = ["VisionBlock", "OpenVLAProjector", "LlamaDecoderLayer"]
    _skip_keys_device_placement = CACHE_KEY
    _supports_sdpa = True
    _supports_flash_attn = True

    def _init_weights(self, module: nn.Module) -> None:
        super()._init_weights(module)
        std = self.config.text_config.initializer_range
        if isinstance(module, VisionTransformer):
            for token in (module.cls_token, module.reg_token, module.pos_embed):
                if token is not None:
                    init.normal_(token, mean=0.0, std=std)
        elif isinstance(module, LayerScale):
            init.constant_(module.scale_factor, 1e-5)
        elif isinstance(module, AttentionPoolLatent):
            init.normal_(module.latent, mean=0.0, std=module.latent.shape[-1] ** -0.5)


class OpenVLAForActionPrediction(SpeculativeGenerationMixin, OpenVLAPreTrainedModel, GenerationMixin):
    """OpenVLA: vision backbone -> projector -> Llama, with ``predict_action`` (7 action tokens -> un-normalised
    action).

    Attributes:
        action_tokenizer: the action tokens (the last ``n_action_bins`` ids below ``config.action_vocab_end``).
        norm_stats: ``config.norm_stats``.
    """

    def __init__(self, config: OpenVLAConfig):
        super().__init__(config)
        self.vision_backbone = OpenVLAVisionBackbone(
            config.timm_model_ids, config.image_sizes, config.use_fused_vision_backbone, config.tower_specs()
        )
        self.projector = OpenVLAProjector(
            self.vision_backbone.embed_dim, config.text_config.hidden_size, config.use_fused_vision_backbone
        )
        # the dtype the rest is built in (from_pretrained sets it); not text_config.dtype ("bfloat16" in the 7B's
        # config.json), which would build a bf16 Llama beside fp32 towers
        self.language_model = AutoModelForCausalLM.from_config(config.text_config, dtype=torch.get_default_dtype())
        self.action_tokenizer = ActionTokenizer(config.action_vocab_end, config.n_action_bins)
        self.norm_stats = config.norm_stats
        self.post_init()

    @classmethod
    def from_pretrained(cls, pretrained_model_name_or_path, *model_args, **kwargs):
        """``PreTrainedModel.from_pretrained`` for official OpenVLA checkpoints, strict about what it loads.

        A local folder is checked first (see [`check_checkpoint_folder`]; a local path is never sent to the hub);
        every checkpoint key must match a parameter and every parameter must be loaded, otherwise a ValueError names
        the first few keys (transformers would only warn and leave random weights).
        """
        check_checkpoint_folder(pretrained_model_name_or_path)
        output_loading_info = kwargs.pop("output_loading_info", False)
        with named_weight_errors(pretrained_model_name_or_path, "OpenVLA checkpoint"):
            model, loading_info = super().from_pretrained(
                pretrained_model_name_or_path, *model_args, output_loading_info=True, **kwargs
            )
        problems = []
        for kind in ("missing_keys", "unexpected_keys", "mismatched_keys"):
            keys = sorted(str(key) for key in loading_info.get(kind) or [])
            if keys:
                problems.append(f"{len(keys)} {kind.replace('_', ' ')} (e.g. {keys[:_KEYS_SHOWN]})")
        if problems:
            raise ValueError(
                f"the checkpoint at {str(pretrained_model_name_or_path)!r} does not match the OpenVLA architecture its "
                f"config.json describes: {'; '.join(problems)}"
            )
        return (model, loading_info) if output_loading_info else model

    # --- transformers plumbing -------------------------------------------------------------------------------
    def get_input_embeddings(self) -> nn.Module:
        return self.language_model.get_input_embeddings()

    def set_input_embeddings(self, value: nn.Module) -> None:
        self.language_model.set_input_embeddings(value)

    def get_output_embeddings(self) -> nn.Module:
        return self.language_model.get_output_embeddings()

    def set_output_embeddings(self, value: nn.Module) -> None:
        self.language_model.set_output_embeddings(value)

    def get_decoder(self) -> nn.Module:
        return self.language_model.get_decoder()

    @property
    def num_patches(self) -> int:
        """Image rows in the language model's sequence (256 at 224 px)."""
        return self.vision_backbone.num_patches

    # --- forward --------------------------------------------------------------------------------------------
    def get_image_features(self, pixel_values: torch.Tensor) -> torch.Tensor:
        """``[B, 3 or 6, H, W]`` -> projected patches ``[B, num_patches, llm_dim]``."""
        vision_dtype = self.projector.fc1.weight.dtype
        return self.projector(self.vision_backbone(pixel_values.to(vision_dtype)))

    def forward(
        self,
        input_ids: torch.LongTensor | None = None,
        attention_mask: torch.Tensor | None = None,
        pixel_values: torch.FloatTensor | None = None,
        labels: torch.LongTensor | None = None,
        inputs_embeds: torch.FloatTensor | None = None,
        cache=None,
        past_key_values=None,
        position_ids: torch.LongTensor | None = None,
        use_cache: bool | None = None,
        output_hidden_states: bool | None = None,
        output_projector_features: bool | None = None,
        return_dict: bool | None = None,
        **kwargs,
    ) -> OpenVLACausalLMOutputWithPast:
        """One forward of the language model over text, image rows and (in generation) cached tokens.

        Args:
            input_ids: ``[B, L]``. With ``pixel_values`` and no ``config.image_token_id`` in them, the patches are
                inserted after position 0 (the official layout); with ``num_patches`` image tokens per row, the
                patches replace those rows.
            pixel_values: ``[B, 6, H, W]`` (fused backbone) or ``[B, 3, H, W]``; None for text-only or cached steps.
            attention_mask: ``[B, L]`` 2D padding mask or a 4D mask (generation); extended with ones when
                patches are inserted.
            labels: ``[B, L]``; extended with ``IGNORE_INDEX`` when patches are inserted.
            cache / past_key_values: the KV cache, under either name (generate passes ``cache`` from transformers
                5.24, ``past_key_values`` before).
            kwargs: passed to the language model (``logits_to_keep``, ...).
        """
        cache = cache if cache is not None else past_key_values
        if (input_ids is None) == (inputs_embeds is None):
            raise ValueError("pass exactly one of input_ids and inputs_embeds")
        projected = None
        if pixel_values is not None:
            if input_ids is None:
                raise ValueError("pixel_values need input_ids (the image rows are placed by token position)")
            if pixel_values.shape[0] != input_ids.shape[0]:
                raise ValueError(
                    f"pixel_values has {pixel_values.shape[0]} images for {input_ids.shape[0]} prompts; pass one image "
                    f"per prompt"
                )
            projected = self.get_image_features(pixel_values)
            inputs_embeds = self.get_input_embeddings()(input_ids)
            image_rows = input_ids == self.config.image_token_id
            # compiled (the speculative prefill graph): generate always puts the image tokens in place (the official
            # layout is converted before), and a graph cannot branch on the ids' values, so the checks are left to
            # eager calls, as transformers' VLMs do
            counts = None if torch.compiler.is_compiling() else image_rows.sum(dim=1)
            if counts is not None and bool((counts == 0).all()):
                if position_ids is not None:
                    raise ValueError(
                        "position_ids cannot be given when the image is inserted after BOS (input_ids without image "
                        "tokens); put config.image_token_id rows in input_ids instead"
                    )
                inputs_embeds = torch.cat(
                    [inputs_embeds[:, :1], projected.to(inputs_embeds.dtype), inputs_embeds[:, 1:]], 1
                )
                if attention_mask is not None:
                    if attention_mask.ndim != 2:
                        raise ValueError("with the image inserted after BOS, attention_mask must be the 2D [B, L] mask")
                    ones = attention_mask.new_ones(attention_mask.shape[0], self.num_patches)
                    attention_mask = torch.cat([attention_mask[:, :1], ones, attention_mask[:, 1:]], dim=1)
                if labels is not None:
                    ignored = labels.new_full((labels.shape[0], self.num_patches), IGNORE_INDEX)
                    labels = torch.cat([labels[:, :1], ignored, labels[:, 1:]], dim=1)
            elif counts is None or bool((counts == self.num_patches).all()):
                inputs_embeds = inputs_embeds.masked_scatter(
                    image_rows[..., None].expand_as(inputs_embeds), projected.to(inputs_embeds.dtype)
                )
                if labels is not None:  # image rows are never predicted (as with the official layout's -100s)
                    labels = labels.masked_fill(image_rows, IGNORE_INDEX)
            else:
                raise ValueError(
                    f"each prompt must hold either no image token or exactly {self.num_patches} "
                    f"(config.image_token_id={self.config.image_token_id}); got {counts.tolist()}"
                )
            input_ids = None
        # (the cache first: a decoding step or verification never reads its ids' values here: one graph compiles)
        elif cache is None and input_ids is not None and bool((input_ids == self.config.image_token_id).any()):
            raise ValueError(
                f"input_ids hold image tokens (config.image_token_id={self.config.image_token_id}) but no pixel_values "
                f"were given"
            )
        outputs = self.language_model(
            input_ids=input_ids,
            inputs_embeds=inputs_embeds,
            attention_mask=attention_mask,
            position_ids=position_ids,
            labels=labels,
            use_cache=use_cache,
            output_hidden_states=output_hidden_states,
            return_dict=True,
            **{CACHE_KEY: cache},
            **kwargs,
        )
        return OpenVLACausalLMOutputWithPast(
            loss=outputs.loss,
            logits=outputs.logits,
            hidden_states=outputs.hidden_states,
            attentions=outputs.attentions,
            projector_features=projected if output_projector_features else None,
            **{CACHE_KEY: cache_of(outputs)},
        )

    # --- generation -----------------------------------------------------------------------------------------
    def add_image_tokens(
        self, input_ids: torch.LongTensor, attention_mask: torch.Tensor | None = None
    ) -> tuple[torch.LongTensor, torch.Tensor | None]:
        """The official layout's prompt with ``num_patches`` image tokens after position 0 (and its 2D mask)."""
        batch = input_ids.shape[0]
        image_ids = input_ids.new_full((batch, self.num_patches), self.config.image_token_id)
        input_ids = torch.cat([input_ids[:, :1], image_ids, input_ids[:, 1:]], dim=1)
        if attention_mask is not None:
            ones = attention_mask.new_ones(batch, self.num_patches)
            attention_mask = torch.cat([attention_mask[:, :1], ones, attention_mask[:, 1:]], dim=1)
        return input_ids, attention_mask

    @staticmethod
    def end_prompt(
        input_ids: torch.LongTensor, attention_mask: torch.Tensor | None = None
    ) -> tuple[torch.LongTensor, torch.Tensor | None]:
        """``input_ids`` ``[B, L]`` ending with ``PROMPT_END_TOKEN_ID`` (appended unless every row ends with it, as
        the official ``predict_action`` does), and the 2D mask extended to match (the official code leaves it one
        token short)."""
        if bool((input_ids[:, -1] == PROMPT_END_TOKEN_ID).all()):
            return input_ids, attention_mask
        input_ids = torch.cat([input_ids, input_ids.new_full((input_ids.shape[0], 1), PROMPT_END_TOKEN_ID)], dim=1)
        if attention_mask is not None and attention_mask.shape[1] == input_ids.shape[1] - 1:
            attention_mask = torch.cat([attention_mask, attention_mask.new_ones(attention_mask.shape[0], 1)], dim=1)
        return input_ids, attention_mask

    def generate(self, input_ids=None, pixel_values=None, attention_mask=None, **kwargs):
        """``GenerationMixin.generate`` (speculative with a hf_specvla assistant or ``draft_ids``).

        Prompts in the official layout (no image tokens) get their image rows for the call, and lose them again in
        the returned sequences, so the result is ``input_ids`` followed by the new tokens, as with the official code.
        """
        inserted = (
            pixel_values is not None
            and input_ids is not None
            and not bool((input_ids == self.config.image_token_id).any())
        )
        if inserted:
            input_ids, attention_mask = self.add_image_tokens(input_ids, attention_mask)
        if attention_mask is not None:
            kwargs["attention_mask"] = attention_mask
        output = super().generate(input_ids, pixel_values=pixel_values, **kwargs)
        if not inserted:
            return output
        if isinstance(output, torch.Tensor):
            return self._drop_image_rows(output)
        output.sequences = self._drop_image_rows(output.sequences)
        return output

    def _drop_image_rows(self, sequences: torch.Tensor) -> torch.Tensor:
        return torch.cat([sequences[:, :1], sequences[:, 1 + self.num_patches :]], dim=1)

    # --- actions --------------------------------------------------------------------------------------------
    def check_unnorm_key(self, unnorm_key: str | None) -> str:
        """The dataset whose statistics un-normalise actions.

        Raises:
            ValueError: when ``unnorm_key`` is unknown, or None while the checkpoint has several datasets (lists
                the valid keys).
        """
        keys = sorted(self.norm_stats or {})
        if not keys:
            raise ValueError("this checkpoint has no norm_stats, so it cannot un-normalise actions")
        if unnorm_key is None:
            if len(keys) > 1:
                raise ValueError(f"this checkpoint was trained on {len(keys)} datasets; pass unnorm_key, one of {keys}")
            return keys[0]
        if unnorm_key not in self.norm_stats:
            raise ValueError(f"unnorm_key={unnorm_key!r} is not in this checkpoint's norm_stats; valid keys: {keys}")
        return unnorm_key

    def get_action_stats(self, unnorm_key: str | None = None) -> dict:
        """The action statistics (q01, q99, mask, ...) of a dataset."""
        return self.norm_stats[self.check_unnorm_key(unnorm_key)]["action"]

    def get_action_dim(self, unnorm_key: str | None = None) -> int:
        """Action tokens per action (the length of the dataset's ``q01``)."""
        return len(self.get_action_stats(unnorm_key)["q01"])

    def action_normalizer(self, unnorm_key: str | None = None) -> ActionNormalizer:
        """The dataset's q01/q99 (un-)normalisation, with its mask."""
        stats = self.get_action_stats(unnorm_key)
        return ActionNormalizer(stats["q01"], stats["q99"], stats.get("mask"))

    def action_layout(self, unnorm_key: str | None = None) -> ActionLayout:
        """What relaxed acceptance needs: the action tokens, the tokens per action and what a bin is in the dataset's
        units (for rules that scale with the motion or bound the deviation in action space)."""
        dim = self.get_action_dim(unnorm_key)
        units = ActionUnits.from_normalizer(self.action_tokenizer, self.action_normalizer(unnorm_key), dim)
        return ActionLayout(self.action_tokenizer, dim, units)

    def action_token_ids(self, action, unnorm_key: str | None = None) -> torch.LongTensor:
        """The action tokens ``[1, action_dim]`` of an un-normalised action ``[action_dim]``: the previous action as
        ``draft_ids`` for the next call (``predict_action(..., draft_ids=model.action_token_ids(previous))``)."""
        tokens = self.action_tokenizer.encode(self.action_normalizer(unnorm_key).normalize(action))
        return torch.as_tensor(tokens, dtype=torch.long, device=self.device)[None]

    def predict_action(
        self,
        input_ids: torch.LongTensor | None = None,
        unnorm_key: str | None = None,
        *,
        image=None,
        instruction: str | None = None,
        processor=None,
        action_prior: bool = False,
        previous_action_ids: list[list[int]] | None = None,
        **kwargs,
    ) -> np.ndarray:
        """One action, ``[action_dim]`` float64, un-normalised with the dataset's q01/q99 (where its mask is True).

        Two calls:

        * the official one: ``predict_action(input_ids=..., pixel_values=..., unnorm_key=..., do_sample=False)``
          (``attention_mask`` may be passed as well);
        * ``predict_action(image=..., instruction="pick up the red block", processor=processor, unnorm_key=...)``,
          which builds the official prompt with the [`OpenVLAProcessor`].

        Every other keyword goes to ``generate``, speculation included: ``assistant_model=draft_head`` (or a
        drafter), ``draft_ids=`` (e.g. ``self.action_token_ids(previous_action)``), ``bin_tolerance=r``; a
        ``generation_config`` is honoured (copied, given the action's tokens). A decoding method's or preset's
        options work as they are (``DecodingMethod.parse("exact", action_dim=7).generate_kwargs(None)``), given the
        episode's memory:

        Args:
            previous_action_ids: the episode's previous actions as token ids, oldest first: a list the caller keeps
                per episode (``[]`` at its start; the model keeps no state), updated in place with this action. A
                draft head that reads the previous action reads its last.
            action_prior: draft this action from ``previous_action_ids`` ([`ActionPriorDrafter`], verified inside
                the prefill), before the ``assistant_model`` when one is given; no drafts at an episode's first step.

        Raises:
            ValueError / TypeError: ``action_prior`` without ``previous_action_ids``, a memory that is not a list of
                actions of ``action_dim`` action token ids, bad prompts or images (before any forward).

        Differences from the official code (bugs there): ``attention_mask`` is extended with the appended 29871
        token (the official call passes a mask one token short); the action tokens are always ``action_dim`` new
        tokens (EOS is suppressed until then, where the official code would decode prompt tokens as actions).
        """
        unnorm_key = self.check_unnorm_key(unnorm_key)
        action_dim = self.get_action_dim(unnorm_key)
        if "max_new_tokens" in kwargs:
            raise ValueError(
                f"predict_action decodes one action, its action_dim={action_dim} tokens: drop "
                f"max_new_tokens={kwargs['max_new_tokens']!r}"
            )
        # what relaxed acceptance and the prior read (built only for an episode's or a speculative call)
        layout = None if previous_action_ids is None else self.action_layout(unnorm_key)
        self._check_episode_memory(action_prior, previous_action_ids, layout)
        if image is not None or instruction is not None:
            if input_ids is not None or "pixel_values" in kwargs:
                raise ValueError("pass either input_ids / pixel_values or image / instruction, not both")
            if image is None or instruction is None or processor is None:
                raise ValueError(
                    "predict_action(image=..., instruction=...) needs all of image, instruction, processor"
                )
            inputs = processor(processor.prompt(instruction), image)
            input_ids = inputs["input_ids"].to(self.device)
            kwargs["attention_mask"] = inputs["attention_mask"].to(self.device)
            kwargs["pixel_values"] = inputs["pixel_values"].to(self.device)
        if input_ids is None:
            raise ValueError("predict_action needs input_ids (with pixel_values) or image, instruction and processor")
        if input_ids.shape[0] != 1:
            raise ValueError(
                f"predict_action predicts one action; got a batch of {input_ids.shape[0]} prompts (for a batch of "
                f"robots: hf_specvla.policies.OpenVLAPolicy(model, processor).predict_action(images, instructions))"
            )
        input_ids, mask = self.end_prompt(input_ids, kwargs.get("attention_mask"))
        if mask is not None:
            kwargs["attention_mask"] = mask
        if previous_action_ids is not None:  # the episode's drafter: the prior's drafts and / or the assistant's
            assistant, num_draft_tokens = kwargs.pop("assistant_model", None), kwargs.pop("num_draft_tokens", None)
            drafter = episode_drafter(assistant, num_draft_tokens, action_prior, [previous_action_ids], layout)
            if drafter is not None:
                kwargs["assistant_model"] = drafter
            elif action_prior and kwargs.get("draft_ids") is None:  # an episode's first step: plain decoding
                for name in SPECULATION_KWARGS:
                    kwargs.pop(name, None)
        drafts = isinstance(kwargs.get("assistant_model"), (DraftHead, Drafter)) or kwargs.get("draft_ids") is not None
        if drafts and "action_layout" not in kwargs:
            kwargs["action_layout"] = layout if layout is not None else self.action_layout(unnorm_key)
        kwargs = self._action_length(
            action_dim, kwargs.pop("min_new_tokens", action_dim), kwargs.pop("generation_config", None), kwargs
        )
        generated = self.generate(input_ids, **kwargs)
        sequences = generated if isinstance(generated, torch.Tensor) else generated.sequences
        action_token_ids = sequences[0, -action_dim:]
        if previous_action_ids is not None:
            remember_actions(previous_action_ids, action_token_ids[None], layout)
        normalized = self.action_tokenizer.decode(action_token_ids.cpu().numpy())
        return self.action_normalizer(unnorm_key).unnormalize(normalized)

    @staticmethod
    def _check_episode_memory(action_prior: bool, previous_action_ids, layout: ActionLayout | None) -> None:
        """Refuses, naming the value, an ``action_prior`` that is not a bool or has no memory to draft from, and a
        memory that is not a list of actions (each ``action_dim`` action token ids)."""
        if not isinstance(action_prior, bool):
            raise TypeError(f"action_prior must be True or False, got {action_prior!r}")
        if previous_action_ids is None:
            if action_prior:
                raise ValueError(
                    "action_prior=True drafts from the episode's previous actions, which the model does not keep: "
                    "pass previous_action_ids=<a list kept per episode, [] at its start>, updated in place with each "
                    "action"
                )
            return
        if not isinstance(previous_action_ids, list):
            raise TypeError(
                f"previous_action_ids must be a list of actions (token ids, oldest first; [] at an episode's start), "
                f"updated in place with each action; got {type(previous_action_ids).__name__}"
            )
        ActionPriorDrafter(previous_action_ids, layout)  # each a list of action_dim action token ids, or it names it

    @staticmethod
    def _action_length(
        action_dim: int, min_new_tokens: int, generation_config: GenerationConfig | None, kwargs: dict
    ) -> dict:
        """``generate``'s keyword arguments: ``kwargs`` with the length settings (``action_dim`` new tokens); or,
        given the caller's ``generation_config`` (which decides how to decode, e.g. its ``do_sample=True`` samples),
        a copy of it holding the length and every generation setting of ``kwargs`` (e.g. a compiled method's
        ``cache_implementation`` / ``compile_config``), the rest (inputs, drafters...) beside it: transformers
        deprecates a ``generation_config`` passed together with generation settings.

        Raises:
            TypeError: a ``generation_config`` that is not a ``GenerationConfig``.
        """
        length = dict(max_new_tokens=action_dim, min_new_tokens=min_new_tokens)
        if generation_config is None:
            return {**kwargs, **length}
        return with_generation_config(generation_config, {**kwargs, **length})
