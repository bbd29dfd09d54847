"""What every policy does to act: one batched ``generate`` over left-padded prompts as a [`DecodingPlan`] says, each
row's episode memory (the action prior's drafts) kept, the action tokens un-normalised. [`ActionPolicy`] is the base of
the Meta-World policy ([`VLAPolicy`]) and of an OpenVLA checkpoint served as a policy ([`OpenVLAPolicy`]); a subclass
says how an observation becomes a prompt and pixels, and how action tokens become actions.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch
from transformers import GenerationConfig

from ..run_folder import fingerprint
from ..speculative import (
    RULE_ARGUMENTS,
    SPECULATION_KWARGS,
    ActionPriorDrafter,
    DecoderSession,
    DraftHead,
    episode_drafter,
    remember_actions,
    with_generation_config,
)
from .decoding_methods import DecodingPlan, check_decoding_plan


class ActionPolicy:
    """A vision-language-action model as a policy: ``predict_action(image, instruction, state)`` -> un-normalised
    action, for one observation or a batch.

    A subclass sets ``model`` (its ``generate`` speculative), ``tokenizer`` (its ``pad_token_id`` pads prompts on the
    left), ``config`` (``action_dim``, ``chunk_length``, ``action_tokens``, ``image_size`` (None: any size),
    ``state_dim``, ``use_state``, ``camera``), ``action_layout``, ``name_or_path``, and implements
    [`prompt_ids`], [`preprocess_images`] and [`actions_from_token_ids`].

    Attributes:
        previous_action_ids: this episode's actions so far as token ids, oldest first (cleared by ``reset``); the
            source of ``predict_action(action_prior=True)``'s drafts.
        decoder_sessions: speculative calls run through the model's [`DecoderSession`] for their settings (True, the
            default: ``generate``'s set-up done once per shape, the same tokens); False sends every call through
            ``model.generate`` (what benchmarks compare the session's path with).
    """

    #: previous actions kept for the action prior (as many as it reads).
    HISTORY_LENGTH = ActionPriorDrafter.history_length

    def __init__(self):
        self.previous_action_ids: list[list[int]] = []
        self.name_or_path: str | None = None  # the folder it was loaded from (from_pretrained)
        self._weights_fingerprint: str | None = None
        self.decoder_sessions = True

    # ----------------------------------------------------------------------------- what a subclass says
    def prompt_ids(self, instruction: str, state=None) -> list[int]:
        """The prompt's token ids for one observation's instruction (and proprio ``state``), image rows included."""
        raise NotImplementedError

    def preprocess_images(self, images) -> torch.Tensor:
        """Images ``[B, H, W, 3]`` uint8 (or a list) -> ``pixel_values`` on the model's device and dtype."""
        raise NotImplementedError

    def actions_from_token_ids(self, action_ids, unnorm_key: str | None = None) -> np.ndarray:
        """Action token ids ``[..., action_dim]`` -> un-normalised actions (``unnorm_key``: the dataset, for a policy
        with several)."""
        raise NotImplementedError

    @property
    def pad_token_id(self) -> int:
        """What pads a batch's shorter prompts on the left (the tokenizer's pad token, else the model's)."""
        pad_id = self.tokenizer.pad_token_id
        return pad_id if pad_id is not None else self.model.generation_config.pad_token_id

    @property
    def unnorm_keys(self) -> tuple[str, ...]:
        """The datasets whose statistics can un-normalise actions (empty: one set, the policy's own)."""
        return ()

    def check_unnorm_key(self, unnorm_key: str | None) -> str | None:
        """The dataset a call un-normalises with. This base has one set of statistics: None only.

        Raises:
            ValueError: a key given to a policy with one set of statistics.
        """
        if unnorm_key is not None:
            raise ValueError(
                f"unnorm_key={unnorm_key!r}: this policy has one set of action statistics, its own; pass none"
            )
        return None

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
        unnorm_key: str | list[str | None] | None = None,
        **generate_kwargs,
    ):
        """The action for one observation, or the actions for a batch of observations (one ``generate`` call).

        Args:
            image: uint8 ``[S, S, 3]`` RGB, or ``[B, S, S, 3]`` (or a list of B images) for a batch (e.g. B
                environments in lockstep).
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
            unnorm_key: for a policy trained on several datasets (``unnorm_keys``), the one whose statistics
                un-normalise the action (for a batch: one for all rows, or one per row); None: the policy's default.
            generate_kwargs: anything ``generate`` accepts, e.g. ``assistant_model=draft_head, bin_tolerance=2``.
                Decoding is greedy unless asked otherwise: ``generation_config=GenerationConfig(do_sample=True, ...)``
                (or ``do_sample=True``) samples, verified by speculative sampling when drafts are given (lossless
                acceptance only); ``max_new_tokens`` / ``min_new_tokens`` are always the action's tokens.

        Returns:
            the un-normalised action, float64 ``[action_dim]`` (``[B, action_dim]`` for a batch), and the generate
            output if ``return_output``.

        Raises:
            ValueError: a batch whose images, instructions, states, memories or keys disagree in number; a
                ``decoding`` plan beside loose options that say the same; an ``unnorm_key`` the policy does not have
                (naming the valid ones).
            TypeError: ``decoding`` that is not a DecodingPlan.
        """
        plan = _decoding_plan(decoding, action_prior, generate_kwargs)
        batched = isinstance(image, list | tuple) or np.asarray(image).ndim == 4
        if not batched:
            if previous_action_ids is not None:
                raise ValueError("previous_action_ids is for a batch of images; one observation uses the policy's own")
            histories = [list(self.previous_action_ids)]  # a new list: callers may hold the old one
            images, instructions, states = np.asarray(image)[None], [instruction], [state]
        else:
            images = list(image) if isinstance(image, list | tuple) else np.asarray(image)
            count = len(images)
            instructions = [instruction] * count if isinstance(instruction, str) else list(instruction)
            self._rows("instruction", instructions, count)
            states = [None] * count if state is None else self._rows("state", list(np.asarray(state)), count)
            histories = [[] for _ in images] if previous_action_ids is None else previous_action_ids
            self._rows("previous_action_ids", histories, count)
        keys = unnorm_key if isinstance(unnorm_key, list | tuple) else [unnorm_key] * len(images)
        keys = [self.check_unnorm_key(key) for key in self._rows("unnorm_key", list(keys), len(images))]
        actions, output = self._act(images, instructions, states, histories, plan, return_output, generate_kwargs, keys)
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
        self,
        images,
        instructions,
        states,
        histories,
        plan: DecodingPlan,
        return_output: bool,
        generate_kwargs: dict,
        keys: list[str | None],
    ):
        """One ``generate`` over the batch (prompts left-padded) as ``plan`` decodes; updates ``histories`` in
        place."""
        prompts = [self.prompt_ids(i, s) for i, s in zip(instructions, states)]
        width = max(len(p) for p in prompts)
        pad_id = self.pad_token_id
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
        sequences = output.sequences if hasattr(output, "sequences") else output
        actions, action_ids = self.actions_from_generated(sequences, keys)
        for history, ids in zip(histories, action_ids):
            remember_actions(history, ids, self.action_layout)
        return actions, output

    def actions_from_generated(
        self, sequences: torch.Tensor, unnorm_keys: list[str | None] | None = None
    ) -> tuple[np.ndarray, torch.Tensor]:
        """``generate``'s rows ``[B, T]`` (or a row's new tokens, e.g. ``on_row_finished``'s, as ``[1, n]``) -> the
        un-normalised actions, float64 ``[B, action_dim]`` (``[B, H, action_dim]`` for a chunked policy), and their
        token ids ``[B, H, action_dim]``: the rows' last ``H x action_dim`` tokens (``unnorm_keys``: each row's
        dataset, checked by [`check_unnorm_key`]; None: the default's)."""
        chunk, dim = self.config.chunk_length, self.config.action_dim
        action_ids = sequences[:, -chunk * dim :].reshape(-1, chunk, dim)  # [B, H, A]
        keys = unnorm_keys or [None] * len(action_ids)
        actions = np.stack([self.actions_from_token_ids(ids.cpu(), key) for ids, key in zip(action_ids, keys)])
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
