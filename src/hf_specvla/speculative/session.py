"""A decoder session: one model's repeated speculative calls with one set of settings (a robot's 150-500 calls an
episode, a server's decode step), without ``generate``'s set-up at every call.

A speculative call is set up by one builder, [`prepare_call`] (the model's ``generate`` uses it too): the checks,
the settings folded, then transformers' ``generate`` set-up through its public ``custom_generate`` hook (generation
config, special tokens, lengths, logits processors, stopping criteria, cache, position ids, images encoded). For calls
of one shape and one set of settings all of it is the same but the prompt, its mask, the images and the drafter. A
[`DecoderSession`] keeps a shape's set-up ([`PreparedShape`]) keyed by everything that decides tokens (the shape,
the model's generation config and the session's own by content, dtype, device), so that any change makes a new one;
a later call of that shape is the kept set-up with the call's inputs made as ``generate`` makes them.

What is made for one call is never kept: settings whose processors or criteria belong to one call
([`PER_CALL_SETTINGS`]: a clock, a watermark's state, the prompt held by a processor) set every call up anew, and
so does a cache the engine cannot empty or make anew, or position ids that are not the prompt's mask's.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass
from types import MappingProxyType

import torch
from transformers import CompileConfig, GenerationConfig, LogitsProcessorList, PreTrainedModel, StoppingCriteriaList
from transformers.cache_utils import Cache, DynamicCache, StaticCache

from .cache import holds_buffers
from .compat import CACHE_KEY
from .compiled import compile_settings, compiled_call_config
from .config import SPECULATION_KWARGS, SpeculationConfig
from .decoder import SpeculativeDecoder
from .drafter import Drafter, NoDrafter
from .generation import PreparedCall, SpeculativeGenerationMixin, prepare_call, ready_model
from .modeling_draft_head import DraftHead
from .vision import ENCODED_INPUTS, takes_encoded_images, with_encoded_images

logger = logging.getLogger(__name__)

#: a call's own arguments of [`DecoderSession.generate`], never a session's settings
CALL_ARGUMENTS = ("input_ids", "attention_mask", "assistant_model", "draft_ids", "on_row_finished")
#: what a session never holds: a call's arguments, a cache (every session call starts from a fresh one) and what
#: decodes another way
NOT_SETTINGS = (*CALL_ARGUMENTS, "past_key_values", "cache", "streamer", "custom_generate", "inputs")

#: generation settings whose logits processors or stopping criteria are made for one call, and why: a session whose
#: generation config turns one on sets every call up anew, as ``generate`` does
PER_CALL_SETTINGS = MappingProxyType(
    {
        "max_time": "its stopping criterion's clock starts when the call is set up",
        "guidance_scale": "classifier-free guidance keeps the negative prompt's cache through a call",
        "watermarking_config": "a watermark's processor keeps state through a call",
        "encoder_repetition_penalty": "its processor holds the call's prompt",
        "encoder_no_repeat_ngram_size": "its processor holds the call's prompt",
    }
)
#: the values that leave a [`PER_CALL_SETTINGS`] entry off (``generate`` makes nothing of it)
_OFF = MappingProxyType({"guidance_scale": (None, 1, 1.0), "encoder_repetition_penalty": (None, 1, 1.0)})


def per_call_settings(generation_config: GenerationConfig) -> list[str]:
    """The [`PER_CALL_SETTINGS`] that ``generation_config`` turns on."""
    return [
        name for name in PER_CALL_SETTINGS if getattr(generation_config, name, None) not in _OFF.get(name, (None, 0))
    ]


@dataclass
class PreparedShape:
    """A shape's set-up ([`prepare_call`]'s) as a later call of that shape reuses it, kept by a [`DecoderSession`].

    Attributes:
        generation_config: ``generate``'s copy of the settings, special tokens and lengths resolved.
        logits_processor / stopping_criteria: the lists it built from the settings (a caller's own processors among
            them, reused as ``generate`` reuses them).
        shared: the model keyword arguments every call of the shape gets as they are (``logits_to_keep``,
            ``use_cache``, position ids of an unpadded prompt, ...).
        cache: ``generate``'s static cache (emptied before each call), or None: a dynamic cache made anew each call.
        positions_from_mask: the position ids follow the prompt's padding (``[B, S]`` from its mask), made each call.
        encodes_images: ``generate`` encoded the images before the prefill (``mm_encoder_outputs``).
        compile_config: whether the calls compile and with what (``compiled.compiled_call_config``'s decision, made
            once for the shape), or None: eager.
        plans: the engine's round plans for the shape's calls (``call.KeptPlan``: made by one call, reused by the
            next), by what of the drafter decides one.
    """

    generation_config: GenerationConfig
    logits_processor: LogitsProcessorList
    stopping_criteria: StoppingCriteriaList
    shared: dict
    cache: StaticCache | None
    positions_from_mask: bool
    encodes_images: bool
    compile_config: object = None
    plans: dict = dataclasses.field(default_factory=dict)

    @classmethod
    def reusable(cls, prepared: PreparedCall, attention_mask, inputs: dict, compile_config) -> PreparedShape | None:
        """What of ``prepared`` (a shape's first call, [`prepare_call`]'s) a later call of the shape reuses; None
        when some of it is made for one call ([`PER_CALL_SETTINGS`], a cache that is neither ``generate``'s static
        one nor a plain dynamic one, position ids that are not the mask's): that shape's calls are each set up anew
        (logged)."""
        why = [f"{name} ({PER_CALL_SETTINGS[name]})" for name in per_call_settings(prepared.generation_config)]
        model_kwargs = dict(prepared.model_kwargs)
        cache = model_kwargs.pop(CACHE_KEY, None)
        if type(cache) is StaticCache:
            kept_cache = cache
        elif type(cache) is DynamicCache and not getattr(cache, "offloading", False):
            kept_cache = None
        else:
            kept_cache = why.append(f"a {type(cache).__name__} (made for one call)")
        positions = model_kwargs.pop("position_ids", None)
        padded = attention_mask is not None and not bool(attention_mask.all())
        if positions is not None and padded:  # made from each call's mask
            if not torch.equal(positions, _positions_from_mask(attention_mask)):
                why.append("position ids that are not the prompt mask's")
        elif positions is not None:  # an unpadded prompt's: the same every call of the shape
            if not torch.equal(positions, torch.arange(positions.shape[-1], device=positions.device)[None]):
                why.append("position ids that are not the prompt's")
            model_kwargs["position_ids"] = positions
        if why:
            logger.info(
                "DecoderSession: calls of shape %s are each set up anew: %s",
                tuple(prepared.input_ids.shape),
                "; ".join(why),
            )
            return None
        encodes_images = model_kwargs.pop(ENCODED_INPUTS, None) is not None
        for name in ("attention_mask", *inputs):
            model_kwargs.pop(name, None)  # a call's own
        return cls(
            prepared.generation_config,
            prepared.logits_processor,
            prepared.stopping_criteria,
            model_kwargs,
            kept_cache,
            positions is not None and padded,
            encodes_images,
            compile_config,
        )

    def for_call(
        self,
        model: PreTrainedModel,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor | None,
        inputs: dict,
        speculation: SpeculationConfig,
        generate_settings: dict,
        assistant_model=None,
        draft_ids: torch.Tensor | None = None,
        on_row_finished: Callable | None = None,
    ) -> PreparedCall:
        """A later call of this shape set up: the kept set-up with the call's own inputs made as ``generate`` makes
        them (``attention_mask`` ``[B, S]``, None when nothing is padded; position ids from it; the images encoded;
        a fresh cache) and its drafter folded into ``speculation``."""
        model_kwargs = dict(self.shared)
        encoded = SpeculativeDecoder.of(model).encode_images({**inputs, **generate_settings}, self.compile_config)
        if self.encodes_images and takes_encoded_images(model, encoded):
            encoded = with_encoded_images(model, encoded)
        model_kwargs.update({name: value for name, value in encoded.items() if name not in generate_settings})
        model_kwargs["attention_mask"] = attention_mask
        if self.positions_from_mask:
            model_kwargs["position_ids"] = _positions_from_mask(attention_mask)
        model_kwargs[CACHE_KEY] = self._fresh_cache(model)
        drafter = {} if assistant_model is None else {"drafter": assistant_model}
        return PreparedCall(
            input_ids,
            self.logits_processor,
            self.stopping_criteria,
            self.generation_config,
            model_kwargs,
            SpeculationConfig.fold(speculation, drafter),
            draft_ids,
            on_row_finished,
            self.plans,
        )

    def _fresh_cache(self, model: PreTrainedModel) -> Cache:
        """``generate``'s static cache emptied (as its next call would), or a new dynamic cache (as it makes one)."""
        if self.cache is None:
            return DynamicCache(config=model.config.get_text_config(decoder=True))
        if holds_buffers(self.cache):
            self.cache.reset()
        return self.cache


class DecoderSession:
    """One model's speculative calls with one set of ``generate`` settings, each shape's set-up done once.

    ``session.generate(input_ids, attention_mask=..., pixel_values=..., assistant_model=drafter)`` returns what
    ``model.generate(..., assistant_model=drafter, **settings)`` returns, token for token; without ``assistant_model``
    and ``draft_ids`` it decodes greedily through the engine ([`NoDrafter`]: one token a forward), the baseline that
    shows what the session's path saves apart from what speculation saves.

    Args:
        model: a speculation-enabled model ([`enable_speculation`]).
        settings: the ``generate`` keyword arguments every call shares (``max_new_tokens``, ``bin_tolerance``,
            ``action_layout``, a compiled method's ``cache_implementation`` / ``compile_config``, a
            ``generation_config``...); a call's inputs, drafter and cache are not settings ([`NOT_SETTINGS`]).

    Example:
        ```python
        session = DecoderSession(model, max_new_tokens=7, min_new_tokens=7, bin_tolerance=0)
        for observation in episode:
            out = session.generate(**processor(observation), assistant_model=drafter)
        ```

    Raises:
        TypeError: a model without speculation enabled.
        ValueError: a call's argument among the settings, naming it.
    """

    @staticmethod
    def can_hold(settings: dict) -> bool:
        """Whether ``settings`` are a session's (no cache to continue, nothing that decodes another way): else the
        call goes through ``generate`` as it is."""
        return not any(name in settings for name in NOT_SETTINGS if name not in CALL_ARGUMENTS)

    @classmethod
    def of(cls, model: PreTrainedModel, **settings) -> DecoderSession:
        """The model's session for ``settings``, kept by its [`SpeculativeDecoder`] (equal settings find the same
        session: values compared as ``generate`` reads them, a ``CompileConfig`` or ``GenerationConfig`` by its
        contents, other objects (drafters, layouts) by identity)."""
        key = tuple(sorted((name, _frozen(value)) for name, value in settings.items()))
        return SpeculativeDecoder.of(model).session(key, lambda: cls(model, **settings))

    def __init__(self, model: PreTrainedModel, **settings):
        if not isinstance(model, SpeculativeGenerationMixin):
            raise TypeError(
                f"DecoderSession needs a speculation-enabled model (hf_specvla.enable_speculation(model)), got "
                f"{type(model).__name__}"
            )
        misplaced = sorted(name for name in settings if name in NOT_SETTINGS)
        if misplaced:
            raise ValueError(
                f"{', '.join(misplaced)} belong to a call, not to a DecoderSession's settings: pass the inputs, "
                f"assistant_model, draft_ids and on_row_finished to session.generate(...); a session starts every "
                f"call from a fresh cache (settings are the generate keywords every call shares, e.g. "
                f"max_new_tokens, bin_tolerance)"
            )
        # a tensor setting (a stop token) copied: the caller may change theirs in place, which is another setting
        self.model = model
        self.settings = {
            name: value.clone() if isinstance(value, torch.Tensor) else value for name, value in settings.items()
        }
        #: the settings' speculation, one [`SpeculationConfig`] (``speculation=`` or the loose settings folded), and
        #: the rest: ``generate``'s own
        self.generate_settings = dict(self.settings)
        loose = {name: self.generate_settings.pop(name) for name in SPECULATION_KWARGS if name in self.settings}
        self.speculation = SpeculationConfig.fold(self.generate_settings.pop("speculation", None), loose)
        #: the model's class wraps ``generate`` above the mixin (OpenVLA's port: its image rows): what its wrapper
        #: does is its own, so every call goes through ``model.generate``
        self.wraps_generate = type(model).generate is not SpeculativeGenerationMixin.generate
        #: shape -> what generate prepared for it; None: that shape's calls all go through generate
        self.prepared: dict[tuple, PreparedShape | None] = {}
        #: calls run through ``generate`` (each shape's first, and those of shapes it cannot keep), and past it
        self.calls_through_generate = self.direct_calls = 0

    @torch.no_grad()
    def generate(
        self,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor | None = None,
        assistant_model: DraftHead | Drafter | None = None,
        draft_ids: torch.Tensor | None = None,
        on_row_finished: Callable | None = None,
        **inputs,
    ):
        """One call: ``input_ids`` ``[B, S]`` (left-padded, ``attention_mask`` ``[B, S]``), the model's other inputs
        (tensors: ``pixel_values``...), the call's drafter and ``draft_ids``. Returns what ``model.generate`` returns.

        Raises:
            ValueError: a setting passed to the call (the session holds its own), naming it and the session's.
            TypeError: an assistant that is not a hf_specvla DraftHead or Drafter.
        """
        self._check_inputs(inputs)
        if assistant_model is None and draft_ids is None and self.speculation.drafter is None:
            assistant_model = NoDrafter()
        if not isinstance(assistant_model, (DraftHead, Drafter)) and assistant_model is not None:
            raise TypeError(
                f"a DecoderSession speculates: assistant_model must be a hf_specvla DraftHead or Drafter, got "
                f"{type(assistant_model).__name__}"
            )
        padded = attention_mask is not None and not bool(attention_mask.all())
        key = (
            tuple(input_ids.shape),
            input_ids.device,
            padded,
            tuple(
                (name, tuple(value.shape), value.dtype) for name, value in sorted(inputs.items()) if value is not None
            ),
            self._decisions(),
        )
        call = dict(assistant_model=assistant_model, draft_ids=draft_ids, on_row_finished=on_row_finished)
        if self.wraps_generate:  # the class's own generate runs first, every call
            self.calls_through_generate += 1
            return self.model.generate(
                input_ids=input_ids,
                attention_mask=attention_mask,
                **inputs,
                **call,
                speculation=self.speculation,
                **self.generate_settings,
            )
        kept = self.prepared.get(key, ...)
        if kept is ... or kept is None:  # set up by the builder; a shape's first call keeps what it may
            self.calls_through_generate += 1
            prepared = prepare_call(
                self.model,
                (),
                call["assistant_model"],
                call["draft_ids"],
                self.speculation,
                dict(
                    input_ids=input_ids,
                    attention_mask=attention_mask,
                    **inputs,
                    **self.generate_settings,
                    on_row_finished=on_row_finished,
                ),
            )
            if kept is ...:
                compile_config = compiled_call_config(self.model, self.settings)
                kept = self.prepared[key] = PreparedShape.reusable(prepared, attention_mask, inputs, compile_config)
                if kept is not None:  # the engine's plan of this first call kept too
                    prepared.kept_plans = kept.plans
            return prepared.run(self.model)
        self.direct_calls += 1
        ready_model(self.model, kept.compile_config)
        mask = attention_mask if padded else None
        prepared = kept.for_call(self.model, input_ids, mask, inputs, self.speculation, self.generate_settings, **call)
        return prepared.run(self.model)

    def _decisions(self) -> tuple:
        """Everything besides the shape that decides what ``generate`` prepares, read at every call: the model's
        ``generation_config`` (its stop and pad tokens, suppressed tokens, lengths...: mutated or replaced), the
        contents of a ``GenerationConfig`` among the session's settings (the caller may change it), the model's
        dtype and device. A change makes a new prepared shape (a call through ``generate``), never a stale one."""
        model = self.model
        own = self.settings.get("generation_config")
        weight = next(model.parameters(), None)  # its dtype and device: what model.dtype / .device read, 4x faster
        return (
            generation_config_key(model.generation_config),
            None if own is None else generation_config_key(own),
            None if weight is None else (weight.dtype, weight.device),
        )

    def _check_inputs(self, inputs: dict) -> None:
        decisions = sorted(name for name in inputs if name in GENERATE_SETTINGS and name not in self.settings)
        if decisions:
            raise ValueError(
                f"{', '.join(decisions)} is a generate setting, not a model input: a DecoderSession's calls take "
                f"inputs (tensors), a drafter and draft_ids. Make a DecoderSession with {decisions[0]}=... (a "
                f"tensor value too) for calls that want it"
            )
        settings = sorted(
            name
            for name, value in inputs.items()
            if value is not None and (name in self.settings or not isinstance(value, torch.Tensor))
        )
        if settings:
            held = ", ".join(f"{name}={value!r}" for name, value in self.settings.items()) or "none"
            raise ValueError(
                f"{', '.join(settings)}: a DecoderSession's calls take inputs (tensors), a drafter and draft_ids; "
                f"its settings are fixed when it is made (this one's: {held}). Make a DecoderSession with "
                f"{', '.join(settings)} for calls that want them"
            )


def _frozen(value):
    """A hashable stand-in for a setting's value (objects by identity: the session holds them, so no other object
    takes their id while it lives)."""
    if value is None or isinstance(value, (str, int, float, bool)):
        return value
    if isinstance(value, (list, tuple)):
        return tuple(_frozen(item) for item in value)
    if isinstance(value, dict):
        return "dict", tuple(sorted((str(key), _frozen(item)) for key, item in value.items()))
    if isinstance(value, torch.Tensor):  # by content: a tensor changed in place is another setting
        return "tensor", value.dtype, tuple(value.shape), tuple(value.detach().cpu().flatten().tolist())
    if isinstance(value, GenerationConfig):
        return "GenerationConfig", generation_config_key(value)
    if isinstance(value, SpeculationConfig):  # by its settings (each made anew by a robot's call)
        return "SpeculationConfig", tuple((f.name, _frozen(getattr(value, f.name))) for f in dataclasses.fields(value))
    if isinstance(value, CompileConfig):
        return "CompileConfig", compile_settings(value)
    return "object", id(value)


def generation_config_key(config: GenerationConfig) -> tuple:
    """A hashable stand-in for every value of ``config`` (what ``generate`` reads to decide tokens): equal for equal
    contents, different after any change, whether ``config`` was mutated or replaced (~20 us)."""
    return tuple(
        (name, value if type(value) in _PLAIN else _frozen(value)) for name, value in sorted(vars(config).items())
    )


#: values that stand for themselves in a key (most of a generation config's)
_PLAIN = frozenset((type(None), str, int, float, bool))


#: ``generate``'s settings (a ``GenerationConfig``'s fields, the engine's), never a model input of a session's call
GENERATE_SETTINGS = (
    frozenset(vars(GenerationConfig()))
    | frozenset(SPECULATION_KWARGS)
    | frozenset(
        (
            "speculation",
            "generation_config",
            "logits_processor",
            "stopping_criteria",
            "prefix_allowed_tokens_fn",
            "synced_gpus",
            "negative_prompt_ids",
            "negative_prompt_attention_mask",
            "use_model_defaults",
        )
    )
)


def _positions_from_mask(attention_mask: torch.Tensor) -> torch.Tensor:
    """``[B, S]`` a left-padded prompt's position ids from its mask: the real tokens counted from 0, padding 0."""
    return (attention_mask.long().cumsum(-1) - 1).masked_fill(attention_mask == 0, 0)
