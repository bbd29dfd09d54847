"""``model.generate(..., assistant_model=drafter, draft_ids=...)``: the glue between transformers and the loop.

transformers 5.x has no public hook for a new assistant type, but ``generate(custom_generate=callable)`` is public:
generate() prepares inputs, cache, logits processors and stopping criteria and then calls the callable. The mixin
below intercepts ``assistant_model`` when it is a [`DraftHead`] or a [`Drafter`] (``assistant_model`` is not
forwarded to a callable), or ``draft_ids`` (drafts known up front, with or without an assistant), and hands over to
[`speculative_generate`]. A transformers model as assistant, or none, goes to transformers untouched.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass

import torch
from transformers import GenerationConfig, LogitsProcessorList, PreTrainedModel, StoppingCriteriaList

from .compat import check_transformers_support
from .compiled import compiled_call_config
from .config import SPECULATION_KWARGS, SpeculationConfig
from .decoder import SpeculativeDecoder, allow_graphs_held
from .drafter import Drafter
from .graph_files import MIXED_FROM
from .modeling_draft_head import DraftHead
from .precision import EXACT_ATTRIBUTE, keep_greedy_exact


def with_generation_config(generation_config: GenerationConfig, settings: dict) -> dict:
    """``generate``'s keyword arguments for ``settings`` when a caller passes its own ``generation_config`` (which
    decides how to decode, e.g. its ``do_sample=True`` samples): a copy of it (the caller's is left as it was) holding
    every generation setting of ``settings`` (lengths, a compiled method's ``cache_implementation`` /
    ``compile_config``, ...), the rest (inputs, drafters, ``bin_tolerance``...) beside it, since transformers
    deprecates a ``generation_config`` passed together with generation settings.

    Raises:
        TypeError: a ``generation_config`` that is not a ``GenerationConfig``.
    """
    if not isinstance(generation_config, GenerationConfig):
        raise TypeError(
            f"generation_config must be a transformers GenerationConfig, got {type(generation_config).__name__}"
        )
    generation_config = copy.deepcopy(generation_config)
    rest = generation_config.update(**settings)  # what is not a generation setting
    return {"generation_config": generation_config, **rest}


class SpeculativeGenerationMixin:
    """Mix in before a transformers model class to make ``generate`` speculate.

    ``generate(..., speculation=SpeculationConfig(drafter=..., bin_tolerance=r), draft_ids=...)``, or the same as
    loose keywords (``assistant_model=draft_head_or_drafter, bin_tolerance=r``, folded into one [`SpeculationConfig`]
    here, once), runs speculative decoding (see [`speculative_generate`]): [`prepare_call`] sets the call up (the one
    builder a [`DecoderSession`] uses too), [`PreparedCall.run`] decodes it. Every other call behaves exactly as the
    base class's ``generate``. In bf16 / fp16 every call first makes sure the model runs eager attention
    (``speculative.precision``), which keeps r=0 speculative calls with greedy ones at near-ties. A compiled
    speculative call of a VLM encodes its images with a compiled encoder too (``speculative.vision``).
    """

    def generate(self, *args, assistant_model=None, draft_ids=None, speculation=None, **kwargs):
        ours = isinstance(assistant_model, (DraftHead, Drafter))
        if ours or draft_ids is not None or speculation is not None:
            return prepare_call(self, args, assistant_model, draft_ids, speculation, kwargs).run(self)
        ready_model(self, compiled_call_config(self, kwargs))
        if assistant_model is not None and not isinstance(assistant_model, PreTrainedModel):
            raise TypeError(
                f"assistant_model must be a hf_specvla DraftHead or Drafter (DraftHeadDrafter, ActionPriorDrafter, "
                f"ComposedDrafter, ...), or a transformers model for transformers' assisted generation; got "
                f"{type(assistant_model).__name__}"
            )
        stray = [name for name in SPECULATION_KWARGS if name in kwargs and kwargs.get("custom_generate") is None]
        if stray:
            raise ValueError(
                f"{', '.join(stray)} only apply to speculative decoding with a hf_specvla DraftHead / Drafter or "
                f"draft_ids, but assistant_model is {type(assistant_model).__name__}; pass assistant_model=<DraftHead> "
                f"or drop them"
            )
        return super().generate(*args, assistant_model=assistant_model, **kwargs)


def ready_model(model: PreTrainedModel, compile_config) -> None:
    """What every ``generate`` call of a speculation-enabled model does to it first (its own ``generate`` and a
    [`DecoderSession`]'s calls alike): its precision ([`keep_greedy_exact`]) and, for a compiled call (its
    ``compile_config``, [`compiled_call_config`]'s decision; None: eager), this thread's leave to run the graphs the
    model holds."""
    keep_greedy_exact(model)
    if compile_config is not None:  # this thread may not have compiled the graphs it meets
        allow_graphs_held(model)


@dataclass
class PreparedCall:
    """One speculative call set up (by [`prepare_call`]), ready for the engine: what transformers' ``generate`` hands
    a ``custom_generate`` callable (its public hook), and the call's speculation.

    Attributes:
        input_ids: ``[B, S]`` the prompts, left-padded.
        logits_processor / stopping_criteria: the lists ``generate`` built from the generation settings.
        generation_config: ``generate``'s copy of the settings, special tokens and lengths resolved.
        model_kwargs: the model's keyword arguments (the cache, ``attention_mask`` ``[B, S]`` or None when nothing is
            padded, position ids, the images encoded...).
        speculation: the call's [`SpeculationConfig`], whole (its drafter the call's).
        draft_ids: ``[B, k]`` / ``[B, C, k]`` drafts known up front, or None.
        on_row_finished: the call's per-row callback, or None.
        kept_plans: the round plans a [`DecoderSession`] keeps for the call's shape (``call.KeptPlan``), or None.
    """

    input_ids: torch.Tensor
    logits_processor: LogitsProcessorList
    stopping_criteria: StoppingCriteriaList
    generation_config: GenerationConfig
    model_kwargs: dict
    speculation: SpeculationConfig
    draft_ids: torch.Tensor | None = None
    on_row_finished: Callable | None = None
    kept_plans: dict | None = None

    @torch.no_grad()
    def run(self, model: PreTrainedModel):
        """Decodes the call (the model's ``SpeculativeDecoder.decode``, what [`speculative_generate`] runs: the
        settings are whole already); returns what ``model.generate`` returns."""
        return SpeculativeDecoder.of(model).decode(
            self.input_ids,
            self.logits_processor,
            self.stopping_criteria,
            self.generation_config,
            self.speculation,
            self.draft_ids,
            dict(self.model_kwargs),
            self.on_row_finished,
            self.kept_plans,
        )


def prepare_call(
    model: PreTrainedModel, args: tuple, assistant_model, draft_ids, speculation, kwargs: dict
) -> PreparedCall:
    """The one builder of a speculative call's set-up, for ``model.generate`` and a [`DecoderSession`] alike: the
    model made ready ([`ready_model`]), the call checked and its settings folded into one [`SpeculationConfig`]
    ([`speculative_call_kwargs`]), then transformers' own ``generate`` set-up (generation config, special tokens,
    lengths, logits processors, stopping criteria, cache, position ids, images encoded) through its public
    ``custom_generate`` hook, which returns the prepared call instead of decoding it.

    Args:
        args / kwargs: ``generate``'s positional and keyword arguments (inputs and generation settings).
        assistant_model / draft_ids / speculation: the call's drafter, up-front drafts and settings (see the mixin).

    Raises:
        ValueError / TypeError: as [`speculative_call_kwargs`], and whatever ``generate`` refuses.
    """
    compile_config = compiled_call_config(model, kwargs)  # whether the call compiles, decided once
    ready_model(model, compile_config)
    kwargs = speculative_call_kwargs(model, assistant_model, draft_ids, speculation, kwargs, compile_config)
    return super(SpeculativeGenerationMixin, model).generate(*args, custom_generate=_set_up, **kwargs)


def speculative_call_kwargs(
    model: PreTrainedModel, assistant_model, draft_ids, speculation, kwargs: dict, compile_config
) -> dict:
    """The keyword arguments of transformers' ``generate`` for a speculative call (checked): one
    [`SpeculationConfig`] (``speculation``, or the loose keywords and ``assistant_model`` folded into one) and
    ``draft_ids`` as [`speculative_generate`] takes them, a compiled call's images encoded by the compiled encoder
    (``compile_config``: the call's, [`compiled_call_config`]; None: eager); ``custom_generate`` is the caller's to
    add.

    Raises:
        ValueError / TypeError: ``custom_generate`` or a ``streamer`` beside a speculative call, an assistant that is
            not ours beside ``draft_ids`` or ``speculation``, ``speculation`` beside loose settings that say the same.
    """
    check_transformers_support()
    if kwargs.get("custom_generate") is not None:
        raise ValueError("pass either a hf_specvla assistant_model / draft_ids or custom_generate, not both")
    if kwargs.get("streamer") is not None:
        raise ValueError("streamer is not supported with speculative decoding; drop streamer=")
    if assistant_model is not None and not isinstance(assistant_model, (DraftHead, Drafter)):
        raise TypeError(
            f"draft_ids= / speculation= speculate with hf_specvla's loop, whose assistant must be a DraftHead or a "
            f"Drafter, got {type(assistant_model).__name__}"
        )
    kwargs = dict(kwargs)
    loose = {name: kwargs.pop(name) for name in SPECULATION_KWARGS if name in kwargs}
    if assistant_model is not None:
        loose["drafter"] = assistant_model
    speculation = SpeculationConfig.fold(speculation, loose)
    kwargs = SpeculativeDecoder.of(model).encode_images(kwargs, compile_config)  # a compiled call's: compiled
    return {**kwargs, "speculation": speculation, "draft_ids": draft_ids}


def _set_up(
    model,
    input_ids,
    logits_processor,
    stopping_criteria,
    generation_config,
    speculation=None,
    draft_ids=None,
    on_row_finished=None,
    **model_kwargs,
) -> PreparedCall:
    """The ``custom_generate`` callable of [`prepare_call`]: what ``generate`` prepared, as a [`PreparedCall`]
    (``generate`` returns its callable's result as it is). Its parameters beside ``_sample``'s are what ``generate``
    routes to it."""
    return PreparedCall(
        input_ids,
        logits_processor,
        stopping_criteria,
        generation_config,
        model_kwargs,
        speculation,
        draft_ids,
        on_row_finished,
    )


def speculative_class(model_class: type[PreTrainedModel]) -> type[PreTrainedModel]:
    """``model_class`` with [`SpeculativeGenerationMixin`] mixed in; keeps the class name, so that
    ``save_pretrained`` records the original architecture. One such class per model class while any exists: it is
    found among ``model_class``'s own subclasses (Python keeps that list) by the mark it was made with
    ([`MIXED_FROM`]), so that nothing is kept here and a user's own subclass of the same bases (one that overrides
    ``generate``, say) is never taken for it."""
    if issubclass(model_class, SpeculativeGenerationMixin):
        return model_class
    bases = (SpeculativeGenerationMixin, model_class)
    for subclass in model_class.__subclasses__():
        if subclass.__bases__ == bases and vars(subclass).get(MIXED_FROM) is model_class:
            return subclass
    namespace = {"__module__": model_class.__module__, "__qualname__": model_class.__qualname__}
    return type(model_class.__name__, bases, {**namespace, MIXED_FROM: model_class})


def enable_speculation(model: PreTrainedModel, exact_reduced_precision: bool = True) -> PreTrainedModel:
    """Makes ``model.generate`` accept ``assistant_model=<DraftHead | Drafter>`` and ``draft_ids=`` (in place).

    Args:
        exact_reduced_precision: when the model runs in bf16 / fp16, switch its attention to transformers' ``eager``
            implementation at its next ``generate`` (greedy and speculative calls alike, logged), whose result per
            token depends far less on how many tokens a forward holds than sdpa's: r=0 speculative decoding then
            departs from greedy decoding only at rare rounding flips instead of at near-ties (measured on the CPU;
            see ``speculative.precision``). False keeps the model's attention (e.g. sdpa). No effect in fp32, where
            r=0 is exact with any attention.

    Example:
        ```python
        model = enable_speculation(AutoModelForCausalLM.from_pretrained(path))
        draft = DraftHead.from_pretrained(draft_path)
        out = model.generate(**inputs, assistant_model=draft, bin_tolerance=2, max_new_tokens=7)
        ```
    """
    if not isinstance(model, PreTrainedModel):
        raise TypeError(f"enable_speculation expects a transformers PreTrainedModel, got {type(model).__name__}")
    if not isinstance(exact_reduced_precision, bool):
        raise TypeError(f"exact_reduced_precision must be True or False, got {exact_reduced_precision!r}")
    model.__class__ = speculative_class(type(model))
    setattr(model, EXACT_ATTRIBUTE, exact_reduced_precision)
    return model


def disable_speculation(model: PreTrainedModel) -> PreTrainedModel:
    """Undoes [`enable_speculation`] (in place; returns the model). An attention switched for reduced precision
    stays switched (``model.set_attn_implementation`` sets it back)."""
    if isinstance(model, SpeculativeGenerationMixin):
        model.__class__ = type(model).__mro__[2]
        model.__dict__.pop(EXACT_ATTRIBUTE, None)
    return model
