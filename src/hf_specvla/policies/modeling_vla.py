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
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch
from transformers import (
    CLIPVisionConfig,
    GenerationConfig,
    LlamaConfig,
    LlavaConfig,
    LlavaForConditionalGeneration,
    PreTrainedTokenizerFast,
)

from ..actions.tokenizer import ActionLayout, ActionNormalizer, ActionUnits
from ..actions.vla_tokenizer import build_vla_tokenizer
from ..run_folder import fingerprint
from ..speculative import (
    RULE_ARGUMENTS,
    SPECULATION_KWARGS,
    ActionPriorDrafter,
    DecoderSession,
    DraftHead,
    enable_speculation,
    episode_drafter,
    named_weight_errors,
    remember_actions,
    with_generation_config,
)
from .configuration_vla import POLICY_CONFIG_NAME, VLAPolicyConfig, check_policy_folder
from .decoding_methods import DecodingPlan, check_decoding_plan
from .processing_vla import VLAProcessor


class VLAPolicy:
    """An OpenVLA-style policy: ``predict_action(image, instruction, state)`` -> un-normalised action.

    Attributes:
        model: the Llava model (speculation enabled: ``generate`` accepts a DraftHead assistant).
        tokenizer, action_tokenizer, action_normalizer, state_normalizer, config.
        action_layout: the action tokens and ``action_dim`` (what relaxed acceptance needs).
        previous_action_ids: this episode's actions so far as token ids, oldest first (cleared by ``reset``); the
            source of ``predict_action(action_prior=True)``'s drafts.
        decoder_sessions: speculative calls run through the model's [`DecoderSession`] for their settings (True, the
            default: ``generate``'s set-up done once per shape, the same tokens); False sends every call through
            ``model.generate`` (what benchmarks compare the session's path with).
    """

    #: previous actions kept for the action prior (as many as it reads).
    HISTORY_LENGTH = ActionPriorDrafter.history_length

    def __init__(self, model, tokenizer, config: VLAPolicyConfig):
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
        self.previous_action_ids: list[list[int]] = []
        self.name_or_path: str | None = None  # the folder it was loaded from (from_pretrained)
        self._weights_fingerprint: str | None = None
        self.decoder_sessions = True

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
        return self.processor.preprocess_images(images).to(self.model.device, self.model.dtype)

    def prompt_ids(self, instruction: str, state=None) -> list[int]:
        """[`VLAProcessor.prompt_ids`]: the prompt's token ids."""
        return self.processor.prompt_ids(instruction, state)

    def action_token_ids(self, actions) -> np.ndarray:
        """[`VLAProcessor.action_token_ids`]: raw actions ``[..., action_dim]`` -> their token ids."""
        return self.processor.action_token_ids(actions)

    def actions_from_token_ids(self, action_ids) -> np.ndarray:
        """The inverse of [`action_token_ids`]: token ids ``[..., action_dim]`` -> un-normalised actions."""
        return self.action_normalizer.unnormalize(self.action_tokenizer.decode(action_ids))

    def training_batch(self, images, states, actions, instructions: list[str], scene_states=None) -> dict:
        """[`VLAProcessor.training_batch`] on the model's device."""
        batch = self.processor.training_batch(images, states, actions, instructions, scene_states)
        batch["pixel_values"] = batch["pixel_values"].to(self.model.dtype)
        return {name: value.to(self.model.device) for name, value in batch.items()}

    # ----------------------------------------------------------------------------- acting
    def reset(self) -> None:
        """Start of an episode: forgets the previous actions (the action prior's drafts)."""
        self.previous_action_ids = []

    @torch.no_grad()
    def predict_action(
        self,
        image,
        instruction,
        state=None,
        return_output: bool = False,
        action_prior: bool = False,
        previous_action_ids: list[list[list[int]]] | None = None,
        decoding: DecodingPlan | None = None,
        **generate_kwargs,
    ):
        """The action for one observation, or the actions for a batch of observations (one ``generate`` call).

        Args:
            image: uint8 ``[S, S, 3]`` RGB, or ``[B, S, S, 3]`` for a batch (e.g. B environments in lockstep).
            instruction: the task in words (for a batch: one per row, or one for all rows).
            state: the proprio state ``[state_dim]`` (``[B, state_dim]`` for a batch; required when
                ``config.use_state``).
            return_output: also return ``generate``'s output (with ``return_dict_in_generate=True``: sequences,
                and ``.speculation`` when speculative decoding ran; per row in ``.speculation.rows`` for a batch).
            action_prior: draft this action from the episode's previous actions ([`ActionPriorDrafter`]), verified
                inside the prefill; combined with ``assistant_model`` when one is given (the head continues where
                the prior's drafts stop being accepted). No effect on the first step of an episode.
            previous_action_ids: for a batch, each row's episode memory (its previous actions as token ids, oldest
                first): read by ``action_prior`` and updated in place with the new actions. A single observation
                uses the policy's own ``previous_action_ids`` (cleared by ``reset``).
            decoding: a decoding method made concrete ([`DecodingMethod.plan`]: what drafts, the acceptance, the
                compilation), instead of the same as loose options (``assistant_model=``, ``action_prior=``,
                ``bin_tolerance=``, ...), which it may not be mixed with.
            generate_kwargs: anything ``generate`` accepts, e.g. ``assistant_model=draft_head, bin_tolerance=2``.
                Decoding is greedy unless asked otherwise: ``generation_config=GenerationConfig(do_sample=True, ...)``
                (or ``do_sample=True``) samples, verified by speculative sampling when drafts are given (lossless
                acceptance only); ``max_new_tokens`` / ``min_new_tokens`` are always the action's tokens.

        Returns:
            the un-normalised action, float64 ``[action_dim]`` (``[B, action_dim]`` for a batch), and the generate
            output if ``return_output``.

        Raises:
            ValueError: a batch whose images, instructions, states or memories disagree in number; a ``decoding``
                plan beside loose options that say the same.
            TypeError: ``decoding`` that is not a DecodingPlan.
        """
        plan = _decoding_plan(decoding, action_prior, generate_kwargs)
        batched = np.asarray(image).ndim == 4
        if not batched:
            if previous_action_ids is not None:
                raise ValueError("previous_action_ids is for a batch of images; one observation uses the policy's own")
            histories = [list(self.previous_action_ids)]  # a new list: callers may hold the old one
            images, instructions, states = np.asarray(image)[None], [instruction], [state]
        else:
            images = np.asarray(image)
            count = len(images)
            instructions = [instruction] * count if isinstance(instruction, str) else list(instruction)
            self._rows("instruction", instructions, count)
            states = [None] * count if state is None else self._rows("state", list(np.asarray(state)), count)
            histories = [[] for _ in images] if previous_action_ids is None else previous_action_ids
            self._rows("previous_action_ids", histories, count)
        actions, output = self._act(images, instructions, states, histories, plan, return_output, generate_kwargs)
        if not batched:
            self.previous_action_ids = histories[0]
            actions = actions[0]
        return (actions, output) if return_output else actions

    def action_steps(self, actions: np.ndarray) -> list[np.ndarray]:
        """One observation's ``predict_action`` output as the env steps to run, in order: ``[action]`` for a policy
        without chunks, the chunk's H actions for a chunked one (a chunk is executed whole before the next call)."""
        actions = np.asarray(actions)
        return list(actions) if self.config.chunk_length > 1 else [actions]

    @staticmethod
    def _rows(name: str, values: list, batch_size: int) -> list:
        if len(values) != batch_size:
            raise ValueError(f"a batch of {batch_size} images needs {batch_size} {name} rows, got {len(values)}")
        return values

    def _act(
        self, images, instructions, states, histories, plan: DecodingPlan, return_output: bool, generate_kwargs: dict
    ):
        """One ``generate`` over the batch (prompts left-padded) as ``plan`` decodes; updates ``histories`` in
        place."""
        prompts = [self.prompt_ids(i, s) for i, s in zip(instructions, states)]
        width = max(len(p) for p in prompts)
        pad_id = self.tokenizer.pad_token_id
        input_ids = torch.tensor([[pad_id] * (width - len(p)) + p for p in prompts], device=self.model.device)
        inputs = {"input_ids": input_ids, "pixel_values": self.preprocess_images(images)}
        if any(len(p) < width for p in prompts):
            mask = [[0] * (width - len(p)) + [1] * len(p) for p in prompts]
            inputs["attention_mask"] = torch.tensor(mask, device=self.model.device)
        length = [
            f"{name}={generate_kwargs[name]!r}"
            for name in ("max_new_tokens", "min_new_tokens", "max_length")
            if name in generate_kwargs
        ]
        if length:
            raise ValueError(
                f"predict_action decodes the policy's {self.config.action_tokens} action tokens: drop "
                f"{', '.join(length)}"
            )
        generate_kwargs = dict(generate_kwargs)
        generation_config = generate_kwargs.pop("generation_config", None)
        kwargs = self._generation_settings(
            generation_config, pad_id, return_output, {**plan.compile, **generate_kwargs}
        )
        drafter = episode_drafter(
            plan.assistant_model,
            plan.num_draft_tokens,
            plan.action_prior,
            histories,
            self.action_layout,
            self.config.chunk_length,
        )
        if drafter is not None:  # a robot's calls repeat one shape and settings: generate's set-up done once
            # the plan's speculation, whole: the episode's drafter is the call's; loose limits beside the plan join it
            beside = {name: kwargs.pop(name) for name in SPECULATION_KWARGS if name in kwargs}
            layout = beside.pop("action_layout", None) or plan.speculation.action_layout or self.action_layout
            speculation = replace(plan.speculation, drafter=None, num_draft_tokens=None, action_layout=layout, **beside)
            call = {name: kwargs.pop(name) for name in ("draft_ids", "on_row_finished") if name in kwargs}
            if self.decoder_sessions and DecoderSession.can_hold(kwargs):
                session = DecoderSession.of(self.model, speculation=speculation, **kwargs)
                output = session.generate(**inputs, assistant_model=drafter, **call)
            else:
                output = self.model.generate(
                    **inputs, assistant_model=drafter, speculation=speculation, **call, **kwargs
                )
        else:
            if plan.action_prior:  # the episodes' first step: nothing to draft from, plain greedy decoding
                for name in (*SPECULATION_KWARGS, "on_row_finished"):  # rows then finish together, after the call
                    kwargs.pop(name, None)
            else:
                kwargs.update(plan.acceptance)  # (generate refuses an acceptance rule with nothing to draft)
            output = self.model.generate(**inputs, **kwargs)
        actions, action_ids = self.actions_from_generated(output.sequences if hasattr(output, "sequences") else output)
        for history, ids in zip(histories, action_ids):
            remember_actions(history, ids, self.action_layout)
        return actions, output

    def actions_from_generated(self, sequences: torch.Tensor) -> tuple[np.ndarray, torch.Tensor]:
        """``generate``'s rows ``[B, T]`` (or a row's new tokens, e.g. ``on_row_finished``'s, as ``[1, n]``) -> the
        un-normalised actions, float64 ``[B, action_dim]`` (``[B, H, action_dim]`` for a chunked policy), and their
        token ids ``[B, H, action_dim]``: the rows' last ``H x action_dim`` tokens."""
        chunk, dim = self.config.chunk_length, self.config.action_dim
        action_ids = sequences[:, -chunk * dim :].reshape(-1, chunk, dim)  # [B, H, A]
        actions = self.actions_from_token_ids(action_ids)  # [B, H, A]
        return (actions[:, 0] if chunk == 1 else actions), action_ids

    def _generation_settings(
        self, generation_config: GenerationConfig | None, pad_id: int, return_output: bool, generate_kwargs: dict
    ) -> dict:
        """``generate``'s keyword arguments: the action's tokens, greedy decoding (whatever the model's saved
        generation config says) and the caller's ``generate_kwargs``; or, when the caller's ``generation_config``
        says how to decode (its ``do_sample=True`` samples), a copy of it holding the action's tokens and every
        generation setting of ``generate_kwargs`` (e.g. a compiled method's ``cache_implementation`` /
        ``compile_config``), the rest (drafters, ``bin_tolerance``...) beside it: transformers deprecates a
        ``generation_config`` passed together with generation settings.

        Raises:
            TypeError: a ``generation_config`` that is not a ``GenerationConfig``.
        """
        tokens = self.config.action_tokens
        settings = dict(max_new_tokens=tokens, min_new_tokens=tokens, pad_token_id=pad_id)
        if return_output:
            settings["return_dict_in_generate"] = True
        if generation_config is None:
            return dict(settings, do_sample=False, **generate_kwargs)
        return with_generation_config(generation_config, {**settings, **generate_kwargs})

    def weights_fingerprint(self) -> str:
        """Content fingerprint of the model's weights (computed once; a policy's weights do not change at
        inference)."""
        if self._weights_fingerprint is None:
            self._weights_fingerprint = fingerprint(self.model)
        return self._weights_fingerprint

    def check_draft_head(self, draft_head: DraftHead) -> None:
        """Raises ValueError when ``draft_head`` was made for another model (shapes, or distilled from other
        weights: see [`DraftHead.check_target`])."""
        draft_head.check_target(self.model, self.weights_fingerprint())

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


#: ``predict_action``'s loose options that a [`DecodingPlan`] holds (beside one they are refused)
_PLAN_OPTIONS = ("assistant_model", "num_draft_tokens", "cache_implementation", "compile_config")


def _decoding_plan(decoding: DecodingPlan | None, action_prior: bool, generate_kwargs: dict) -> DecodingPlan:
    """The call's [`DecodingPlan`]: ``decoding``, or the loose options' (taken out of ``generate_kwargs``: the
    assistant, a chain length, the acceptance rule's arguments and the compilation's).

    Raises:
        ValueError: ``decoding`` beside loose options that say the same, naming them.
    """
    check_decoding_plan(decoding, "predict_action")
    loose = [name for name in (*_PLAN_OPTIONS, *RULE_ARGUMENTS) if name in generate_kwargs]
    if decoding is not None:
        if action_prior or loose:
            given = ", ".join(loose + (["action_prior"] if action_prior else []))
            raise ValueError(
                f"predict_action got decoding={type(decoding).__name__}(...) and {given}: the plan says "
                f"what drafts, how drafts are accepted and whether the call compiles; pass one or the "
                f"other"
            )
        return decoding
    return DecodingPlan(
        assistant_model=generate_kwargs.pop("assistant_model", None),
        action_prior=action_prior,
        num_draft_tokens=generate_kwargs.pop("num_draft_tokens", None),
        acceptance={name: generate_kwargs.pop(name) for name in RULE_ARGUMENTS if name in generate_kwargs},
        compile={name: generate_kwargs.pop(name) for name in _PLAN_OPTIONS[2:] if name in generate_kwargs},
    )
