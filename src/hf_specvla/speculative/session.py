"""A decoder session: one model's repeated speculative calls with one set of settings (a robot's 150-500 calls an
episode, a server's decode step), without ``generate``'s set-up at every call.

Before the engine runs, transformers' ``generate`` prepares the call: the generation config (copied, validated), the
logits processors and stopping criteria, the model's keyword arguments (the cache, position ids, the images encoded).
For calls of one shape and one set of settings all of it is the same but the images and the prompt's ids. A
[`DecoderSession`] sends the first call of each shape through ``generate`` and keeps what ``generate`` prepared
([`PreparedShape`]); a later call of that shape goes straight to the engine ([`speculative_generate`]) with it, only
the prompt, its mask, the images and the drafter made anew. The tokens are ``generate``'s (tests compare them): what
a session keeps is only what ``generate`` would make again, the same.

Kept only when it is a function of the shape alone: transformers' length and EOS stopping criteria, the logits
processors of [`SHAPE_ONLY_PROCESSORS`], position ids from the prompt's mask, a static cache ``generate`` made (the
engine empties it) or a dynamic one (made anew each call). Anything else (``max_time``, a processor of the caller's,
multi-component positions) sends every call of that shape through ``generate``, as correct and as slow as before.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from collections.abc import Callable
from dataclasses import dataclass

import torch
from transformers import CompileConfig, GenerationConfig, LogitsProcessorList, PreTrainedModel, StoppingCriteriaList
from transformers.cache_utils import Cache, DynamicCache, StaticCache
from transformers.generation import logits_process
from transformers.generation.stopping_criteria import EosTokenCriteria, MaxLengthCriteria

from .cache import holds_buffers
from .compat import CACHE_KEY
from .compiled import allow_graphs_held, compile_settings
from .config import SPECULATION_KWARGS, SpeculationConfig
from .decoder import SpeculativeDecoder
from .drafter import Drafter, NoDrafter
from .generation import SpeculativeGenerationMixin, speculative_call_kwargs
from .loop import speculative_generate
from .modeling_draft_head import DraftHead
from .precision import keep_greedy_exact
from .vision import ENCODED_INPUTS, takes_encoded_images, with_compiled_image_features, with_encoded_images

logger = logging.getLogger(__name__)

#: what ``generate`` hands [`speculative_generate`] beside the model's keyword arguments (the engine's, not kept)
CALL_SETTINGS = ("speculation", "draft_ids", "on_row_finished")
#: a call's own arguments of [`DecoderSession.generate`], never a session's settings
CALL_ARGUMENTS = ("input_ids", "attention_mask", "assistant_model", "draft_ids", "on_row_finished")
#: what a session never holds: a call's arguments, a cache (every session call starts from a fresh one) and what
#: decodes another way
NOT_SETTINGS = (*CALL_ARGUMENTS, "past_key_values", "cache", "streamer", "custom_generate", "inputs")

#: logits processors whose effect is a function of (the shape's prompt length, the ids, the scores) alone: kept
SHAPE_ONLY_PROCESSORS = tuple(
    getattr(logits_process, name)
    for name in (
        "MinLengthLogitsProcessor",
        "MinNewTokensLengthLogitsProcessor",
        "TemperatureLogitsWarper",
        "TopKLogitsWarper",
        "TopPLogitsWarper",
        "MinPLogitsWarper",
        "RepetitionPenaltyLogitsProcessor",
        "SuppressTokensLogitsProcessor",
    )
    if hasattr(logits_process, name)
)
_SHAPE_ONLY_CRITERIA = (MaxLengthCriteria, EosTokenCriteria)


@dataclass
class PreparedShape:
    """What ``generate`` prepared for calls of one shape, kept by a [`DecoderSession`].

    Attributes:
        generation_config: ``generate``'s copy of the settings, special tokens and lengths resolved.
        logits_processor / stopping_criteria: the lists it built (all [`SHAPE_ONLY_PROCESSORS`] / length and EOS).
        shared: the model keyword arguments every call of the shape gets as they are (``logits_to_keep``,
            ``use_cache``, position ids of an unpadded prompt, ...).
        cache: ``generate``'s static cache (emptied before each call), or None: a dynamic cache made anew each call.
        positions_from_mask: the position ids follow the prompt's padding (``[B, S]`` from its mask), made each call.
        encodes_images: ``generate`` encoded the images before the prefill (``mm_encoder_outputs``).
    """

    generation_config: GenerationConfig
    logits_processor: LogitsProcessorList
    stopping_criteria: StoppingCriteriaList
    shared: dict
    cache: StaticCache | None
    positions_from_mask: bool
    encodes_images: bool


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
        prepared = None if self.wraps_generate else self.prepared.get(key, ...)
        if prepared is ...:  # this shape's first call: through generate, keeping what it prepared
            output, self.prepared[key] = self._through_generate(input_ids, attention_mask, inputs, call)
            return output
        if prepared is None:
            self.calls_through_generate += 1
            return self.model.generate(
                input_ids=input_ids,
                attention_mask=attention_mask,
                **inputs,
                **call,
                speculation=self.speculation,
                **self.generate_settings,
            )
        self.direct_calls += 1
        return self._direct(prepared, input_ids, attention_mask if padded else None, inputs, call)

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

    def _through_generate(self, input_ids, attention_mask, inputs: dict, call: dict) -> tuple:
        """A call through ``model.generate``: (its output, what it prepared when a later call of the shape can reuse
        it, else None)."""
        self.calls_through_generate += 1
        kept: dict = {}

        @functools.wraps(speculative_generate)  # generate reads the engine's keywords from its signature
        def recording_generate(model, input_ids, logits_processor, stopping_criteria, generation_config, **kwargs):
            kept.update(
                logits_processor=logits_processor,
                stopping_criteria=stopping_criteria,
                generation_config=generation_config,
                model_kwargs=dict(kwargs),
            )
            return speculative_generate(
                model, input_ids, logits_processor, stopping_criteria, generation_config, **kwargs
            )

        model = self.model
        kwargs = self._mixin_steps(dict(input_ids=input_ids, attention_mask=attention_mask, **inputs), call)
        output = super(SpeculativeGenerationMixin, model).generate(custom_generate=recording_generate, **kwargs)
        prepared = self._keepable(kept, attention_mask, inputs)
        if prepared is None:
            logger.info(
                "DecoderSession: calls of shape %s go through generate every time (it prepared what a later "
                "call cannot reuse)",
                tuple(input_ids.shape),
            )
        return output, prepared

    def _mixin_steps(self, kwargs: dict, call: dict) -> dict:
        """What the speculative ``generate`` of the model's mixin does before transformers' (its precision, the
        thread's graph limit, the checks, a compiled call's images encoded)."""
        self._ready_model()
        call_kwargs = {name: value for name, value in call.items() if name not in ("assistant_model", "draft_ids")}
        return speculative_call_kwargs(
            self.model,
            call["assistant_model"],
            call["draft_ids"],
            self.speculation,
            {**kwargs, **call_kwargs, **self.generate_settings},
        )

    def _ready_model(self) -> None:
        """What the mixin's ``generate`` does to the model before every call: its precision, and this thread's
        graph limit for a compiled call."""
        keep_greedy_exact(self.model)
        if self.settings.get("compile_config") is not None:
            allow_graphs_held(self.model)

    def _keepable(self, kept: dict, attention_mask, inputs: dict) -> PreparedShape | None:
        """What ``generate`` prepared, as a later call of the shape can reuse it; None when some of it depends on
        more than the shape."""
        if not kept:
            return None
        processors, criteria = kept["logits_processor"], kept["stopping_criteria"]
        if not all(type(p) in SHAPE_ONLY_PROCESSORS for p in processors):
            return None
        if not all(type(c) in _SHAPE_ONLY_CRITERIA for c in criteria):
            return None
        model_kwargs = {name: value for name, value in kept["model_kwargs"].items() if name not in CALL_SETTINGS}
        cache = model_kwargs.pop(CACHE_KEY, None)
        if type(cache) is StaticCache:
            kept_cache = cache
        elif type(cache) is DynamicCache and not getattr(cache, "offloading", False):
            kept_cache = None
        else:
            return None
        positions = model_kwargs.pop("position_ids", None)
        padded = attention_mask is not None and not bool(attention_mask.all())
        if positions is not None and padded:  # made from each call's mask
            if not torch.equal(positions, _positions_from_mask(attention_mask)):
                return None
        elif positions is not None:  # an unpadded prompt's: the same every call of the shape
            if not torch.equal(positions, torch.arange(positions.shape[-1], device=positions.device)[None]):
                return None
            model_kwargs["position_ids"] = positions
        encodes_images = model_kwargs.pop(ENCODED_INPUTS, None) is not None
        for name in ("attention_mask", *inputs):
            model_kwargs.pop(name, None)  # a call's own
        return PreparedShape(
            kept["generation_config"],
            processors,
            criteria,
            model_kwargs,
            kept_cache,
            positions is not None and padded,
            encodes_images,
        )

    def _direct(self, prepared: PreparedShape, input_ids, attention_mask, inputs: dict, call: dict):
        """A call of a kept shape: the engine on what ``generate`` prepared, the call's inputs made as it makes
        them."""
        model = self.model
        self._ready_model()
        model_kwargs = dict(prepared.shared)
        encoded = with_compiled_image_features(model, {**inputs, **self.generate_settings})
        if prepared.encodes_images and takes_encoded_images(model, encoded):
            encoded = with_encoded_images(model, encoded)
        model_kwargs.update({name: value for name, value in encoded.items() if name not in self.generate_settings})
        model_kwargs["attention_mask"] = attention_mask
        if prepared.positions_from_mask:
            model_kwargs["position_ids"] = _positions_from_mask(attention_mask)
        model_kwargs[CACHE_KEY] = self._fresh_cache(prepared)
        drafter = call["assistant_model"]
        speculation = SpeculationConfig.fold(self.speculation, {} if drafter is None else {"drafter": drafter})
        return speculative_generate(
            model,
            input_ids,
            prepared.logits_processor,
            prepared.stopping_criteria,
            prepared.generation_config,
            speculation,
            call["draft_ids"],
            call["on_row_finished"],
            **model_kwargs,
        )

    def _fresh_cache(self, prepared: PreparedShape) -> Cache:
        """``generate``'s static cache emptied (as its next call would), or a new dynamic cache (as it makes one)."""
        if prepared.cache is None:
            return DynamicCache(config=self.model.config.get_text_config(decoder=True))
        if holds_buffers(prepared.cache):
            prepared.cache.reset()
        return prepared.cache


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
