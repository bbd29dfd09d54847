"""A speculative call's set-up and end: every argument checked before any forward ([`prepare`]: the drafter,
``draft_ids``, the cache it continues, the rows' drafter sessions, the [`RoundPlan`]) and the output ([`finish`]: the
cache left as greedy decoding leaves it, statistics, sequences)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import torch
from transformers import GenerationConfig, LogitsProcessorList
from transformers.cache_utils import Cache
from transformers.generation.logits_process import PrefixConstrainedLogitsProcessor

from ..actions.tokenizer import ActionLayout
from .acceptance import AcceptanceRule
from .assistant import as_drafter
from .cache import (
    ROLLBACK_LAYER_TYPES,
    cache_batch_size,
    cache_length,
    check_rollback_cache,
    holds_buffers,
    is_static_cache,
    sliding_window,
    static_capacity,
    truncate_cache,
    with_draft_slots,
    written_dtype,
)
from .compat import CACHE_KEY
from .compiled import (
    CALL_WRAPPER_ATTRIBUTE,
    CompiledGraphs,
    buckets_up_to,
    call_compile_config,
    verification_slots,
)
from .config import SpeculationConfig
from .drafter import (
    CandidateDrafter,
    ComposedDrafter,
    DraftContext,
    Drafter,
    PerRowDrafter,
)
from .fused import GraphAcceptance, accepts_in_graph, eos_hiding
from .outputs import SpeculativeDecoderOnlyOutput
from .state import DecodeState, RoundPlan, RowState, SpeculativeCall, Stopwatch
from .stats import SpeculationStats
from .verify import CallVerifier, CompiledVerification, EagerVerification, FusedVerification, prefill_inputs
from .vision import prompt_input_embeddings

logger = logging.getLogger(__name__)


def draft_id_candidates(draft_ids, batch_size: int, vocab_size: int) -> list[list[list[int]]]:
    """Validates ``generate(draft_ids=...)``: a LongTensor ``[B, k]`` or ``[B, C, k]`` -> per row, C candidate lists.

    Raises:
        TypeError / ValueError naming the shape, dtype or id that is wrong and what is valid.
    """
    if not isinstance(draft_ids, torch.Tensor):
        raise TypeError(f"draft_ids must be a LongTensor [B, k] or [B, C, k], got {type(draft_ids).__name__}")
    if draft_ids.dtype not in (torch.int64, torch.int32, torch.int16, torch.uint8):
        raise TypeError(f"draft_ids must hold integer token ids, got dtype {draft_ids.dtype}")
    if draft_ids.ndim not in (2, 3):
        raise ValueError(
            f"draft_ids must have shape [B, k] (one continuation) or [B, C, k] (C candidates), got "
            f"{tuple(draft_ids.shape)}"
        )
    if draft_ids.shape[0] != batch_size:
        raise ValueError(f"draft_ids has batch size {draft_ids.shape[0]}, input_ids has {batch_size}")
    if draft_ids.shape[-1] == 0:
        raise ValueError(f"draft_ids has no tokens (shape {tuple(draft_ids.shape)}); pass k >= 1 or leave it out")
    if draft_ids.numel() and (int(draft_ids.min()) < 0 or int(draft_ids.max()) >= vocab_size):
        raise ValueError(
            f"draft_ids must be token ids in 0..{vocab_size - 1}, got values "
            f"{int(draft_ids.min())}..{int(draft_ids.max())}"
        )
    return draft_ids.reshape(batch_size, -1, draft_ids.shape[-1]).tolist()


def _call_drafter(
    model, batch_size: int, draft_ids, settings: SpeculationConfig
) -> tuple[Drafter, list[list[list[int]]] | None]:
    """The call's drafter: the settings' (a bare DraftHead drafts a chain), with ``draft_ids``'s candidates first
    when given; and those candidates (per row), or None.

    Raises:
        ValueError: nothing to draft with; bad ``draft_ids``.
    """
    drafter = as_drafter(settings.drafter, settings.num_draft_tokens)
    candidates = None
    if draft_ids is not None:
        vocab_size = model.get_output_embeddings().weight.shape[0]
        candidates = draft_id_candidates(draft_ids, batch_size, vocab_size)
        known = (
            CandidateDrafter(candidates[0])
            if batch_size == 1
            else PerRowDrafter([CandidateDrafter(row) for row in candidates])
        )
        drafter = known if drafter is None else ComposedDrafter([known, drafter])
    if drafter is None:
        raise ValueError(
            "speculative_generate needs something to draft with: drafter= (or generate(assistant_model=...)) "
            "and/or draft_ids="
        )
    return drafter, candidates


def _draft_contexts(
    decoder,
    batch_size: int,
    layout,
    eos_ids: list[int],
    prompt_padding,
    max_length: int,
    graphs,
    cached_tokens: int = 0,
    prompt_embeddings=None,
) -> list[DraftContext]:
    """What each row's drafter session starts from (the padding of the prompt tokens the prefill feeds, ``[1, P]``
    or None; the row's first ``cached_tokens`` tokens, which a continued cache already held; the prompt's input
    embeddings ``[B, S, H]`` for drafters that read them, else None)."""
    rows = [None if prompt_padding is None else prompt_padding[b : b + 1] for b in range(batch_size)]
    return [
        DraftContext(
            decoder.model,
            layout,
            eos_ids,
            padding,
            row=b,
            max_length=max_length,
            graphs=graphs,
            decoder=decoder,
            cached_tokens=cached_tokens,
            prompt_embeddings=None if prompt_embeddings is None else prompt_embeddings[b : b + 1],
        )
        for b, padding in enumerate(rows)
    ]


def check_continued_cache(decoder, cache: Cache, batch_size: int) -> None:
    """Refuses, before any forward, a cache this call cannot continue exactly: one holding entries a batched
    speculative call left, or one whose layers already hold another number of rows than ``input_ids`` (a static
    cache keeps its rows when emptied).

    Raises:
        ValueError: naming the cache's rows / history and what would work.
    """
    if not holds_buffers(cache) or any(type(layer) not in ROLLBACK_LAYER_TYPES for layer in cache.layers):
        return  # nothing allocated yet (any batch size), or a cache refused for its layers (check_rollback_cache)
    entries = cache_length(cache)
    if entries and decoder.batch_decoded(cache):
        raise ValueError(
            f"this cache holds {entries} entries left by a batched speculative generate call: a batch's "
            f"rows accept different numbers of drafts, so its cache keeps entries of rejected drafts (masked only "
            f"inside that call) and drops finished rows, and it cannot be continued exactly. Continue each row with "
            f"batch size 1 on its own cache, or start from a fresh cache (pass the whole sequence again)"
        )
    rows = cache_batch_size(cache)
    if rows != batch_size:
        raise ValueError(
            f"the cache holds {entries} entries for {rows} row(s) ({type(cache).__name__}), but input_ids "
            f"has {batch_size} rows: a cache is used again by calls of the same batch size (a static cache keeps its "
            f"rows when emptied). Pass a fresh cache (e.g. DynamicCache() or a new StaticCache) for a batch of "
            f"{batch_size}"
        )


def _leave_cache_as_greedy(decoder, cache: Cache, rows: list[RowState], offset: int) -> None:
    """Leaves a one-row cache as greedy decoding would: the entries of its sequence but the last token (a path the
    stopping criteria cut keeps no entries past the cut), so that a later call continues it exactly. ``offset``: the
    entries before the row's sequence (a continued cache given only the new tokens). A batch's cache is marked on the
    model's decoder ([`check_continued_cache`] refuses it: its rows keep entries of drafts some rows rejected, masked
    only inside that call, and a dynamic one has lost its finished rows)."""
    decoder.mark_batch_decoded(cache, len(rows) > 1)
    if len(rows) > 1:
        return
    keep = offset + rows[0].sequence.shape[1] - 1
    if cache_length(cache) > keep:
        truncate_cache(cache, keep)


def _validate_call(model, generation_config: GenerationConfig, logits_processor, batch_size: int, drafter) -> None:
    if (generation_config.num_beams or 1) > 1 or (generation_config.num_return_sequences or 1) > 1:
        raise ValueError(
            f"speculative decoding needs num_beams=1 and num_return_sequences=1, got "
            f"num_beams={generation_config.num_beams}, num_return_sequences={generation_config.num_return_sequences}"
        )
    if generation_config.output_attentions or generation_config.output_hidden_states:
        raise ValueError(
            "output_attentions / output_hidden_states are not returned by speculative decoding; set them to False "
            "(return_dict_in_generate=True still returns sequences, scores, logits and .speculation)"
        )
    if model.config.is_encoder_decoder:
        raise ValueError(f"speculative decoding needs a decoder-only target, got {type(model).__name__}")
    if batch_size > 1 and any(isinstance(p, PrefixConstrainedLogitsProcessor) for p in logits_processor):
        raise ValueError(
            f"prefix_allowed_tokens_fn reads the batch index, which batched speculative decoding does not pass; got "
            f"{batch_size} sequences: generate one sequence per call with prefix_allowed_tokens_fn"
        )
    if drafter.batch_size is not None and drafter.batch_size != batch_size:
        raise ValueError(
            f"the assistant holds one drafter per row for {drafter.batch_size} rows (PerRowDrafter), but input_ids "
            f"has {batch_size} rows"
        )


def _check_draft_ids_are_actions(
    candidates: list[list[list[int]]], rule: AcceptanceRule, layout: ActionLayout | None
) -> None:
    if rule.is_lossless or layout is None:
        return
    tokenizer = layout.tokenizer
    bad = sorted({t for row in candidates for c in row for t in c if not tokenizer.is_action_token(t)})
    if bad:
        raise ValueError(
            f"draft_ids holds non-action token ids {bad[:8]} but relaxed acceptance (bin_tolerance > 0) compares "
            f"action bins: draft only action ids {tokenizer.action_token_begin}..{tokenizer.vocab_size - 1}, or use "
            f"bin_tolerance=0"
        )


def _prompt_positions(
    model_inputs: dict, input_ids: torch.Tensor, prompt_padding: torch.Tensor | None, past_length: int = 0
):
    """The position ids ``[B, P]`` of the prompt tokens the prefill feeds (``input_ids`` ``[B, P]``; the model's
    prepared ones, else as generate derives them, after the ``past_length`` entries a continued cache holds) and, for
    models with multi-component positions (Qwen2-VL's ``[4, B, P]``: text positions, then temporal / height / width
    rotary positions), each component's offset from the text positions after the prompt, ``[K, B, 1]`` (else None).

    After the prompt every component advances with the text position (a generated token is text), so a token at
    text position p gets ``p + offset`` in each component: what the model's own generate would give it.

    Args:
        prompt_padding: ``[B, past_length + P]`` the 2D attention mask over the cached and the new tokens, or None.
    """
    positions = model_inputs.get("position_ids")
    if positions is not None and positions.ndim == 3:
        text_positions = positions[0].expand(input_ids.shape[0], -1)
        return text_positions, positions[:, :, -1:] - positions[:1, :, -1:]
    if positions is not None:
        return positions.expand(input_ids.shape[0], -1), None
    length = input_ids.shape[1]
    if prompt_padding is None:
        arange = torch.arange(past_length, past_length + length, device=input_ids.device)
        return arange[None].expand(input_ids.shape[0], -1), None
    return (prompt_padding.long().cumsum(-1) - 1).masked_fill(prompt_padding == 0, 0)[:, -length:], None


def _tokens_to_prefill(
    input_ids: torch.Tensor, cache: Cache | None, attention_mask: torch.Tensor | None, generation_config
) -> tuple[int, int]:
    """How a call continues a cache that already holds entries (a second turn of a conversation, the next step of an
    episode on one cache), as ``generate`` does: ``(past_length, new)``, the entries the cache holds and the number
    of ``input_ids``' last columns not in it yet, which the prefill feeds. ``input_ids`` ``[B, S]`` either repeat the
    cached tokens (an attention mask as long as they are, or none) or are only the new ones (then the attention mask
    covers the cached and the new tokens: ``past_length + S`` columns). A fresh cache: ``(0, S)``.

    Raises:
        ValueError: the cache already holds every token of ``input_ids`` (nothing new to feed), or an attention mask
            whose length fits neither reading; each names the lengths and what would be valid.
    """
    length = input_ids.shape[1]
    past_length = 0 if cache is None else cache_length(cache)
    if past_length == 0:
        return 0, length
    mask_length = attention_mask.shape[1] if attention_mask is not None else None
    if mask_length is None:  # generate drops an all-ones mask and keeps its length
        mask_length = getattr(generation_config, "_mask_length", None) or length
    if mask_length == length:  # the cached tokens repeated, then the new ones (what generate returned, extended)
        new = length - past_length
    elif mask_length == past_length + length:  # only the new tokens
        new = length
    else:
        raise ValueError(
            f"the cache holds {past_length} entries, input_ids has {length} tokens and the attention mask "
            f"{mask_length} columns: pass the cached tokens followed by the new ones (a mask of the same length), or "
            f"only the new ones with a mask over the cached and the new tokens ({past_length} + {length} columns)"
        )
    if new < 1:
        raise ValueError(
            f"the cache already holds {past_length} entries but input_ids has only {length} tokens: there is nothing "
            f"new to feed. Pass the cached tokens followed by at least one new token (e.g. the sequence the previous "
            f"generate call returned plus the next turn), or a fresh cache"
        )
    return past_length, new


def _padded_rows(rows: list[RowState], pad_token_id: int | None) -> torch.Tensor:
    """The rows' sequences ``[B, L_max]``, right-padded with ``pad_token_id`` as batched greedy decoding pads."""
    length = max(row.sequence.shape[1] for row in rows)
    if any(row.sequence.shape[1] < length for row in rows) and pad_token_id is None:
        raise ValueError(
            "rows stopped at different lengths and there is no pad_token_id to right-pad them with: set "
            "generation_config.pad_token_id (or eos_token_id)"
        )
    out = rows[0].sequence.new_full((len(rows), length), pad_token_id if pad_token_id is not None else 0)
    for b, row in enumerate(rows):
        out[b, : row.sequence.shape[1]] = row.sequence[0]
    return out


def _per_step(rows: list[RowState], attribute: str) -> tuple[torch.Tensor, ...]:
    """Per-row lists of ``[V]`` tensors -> one ``[B, V]`` tensor per generated step (zeros after a row's end)."""
    steps = max(len(getattr(row, attribute)) for row in rows)
    template = next(getattr(row, attribute)[0] for row in rows if getattr(row, attribute))
    out = []
    for step in range(steps):
        values = [getattr(row, attribute) for row in rows]
        out.append(torch.stack([v[step] if step < len(v) else torch.zeros_like(template) for v in values]))
    return tuple(out)


def _widest_tree(drafter: Drafter, max_depth: int, settings: SpeculationConfig) -> int | None:
    """The most nodes a round's tree can hold: the drafter's largest tree ``max_depth`` deep (None: unknown), cut to
    ``max_drafts_per_row``."""
    widest, cap = drafter.max_tree_nodes(max(0, max_depth)), settings.max_drafts_per_row
    known = [n for n in (widest, cap) if n is not None]
    return min(known) if known else None


@torch.no_grad()
def check_left_padded(attention_mask: torch.Tensor | None) -> None:
    """Refuses a 2D ``attention_mask`` ``[B, S]`` with padding anywhere but at the start of a row: each row's new
    tokens are appended after its last column, so a right-padded row would continue after its padding and decode
    other tokens than the row alone (transformers only warns; we promise exact batches).

    Raises:
        ValueError: naming the rows and what to do.
    """
    if attention_mask is None or attention_mask.ndim != 2:
        return
    real = attention_mask.bool()
    # left padding: once a row's tokens start, every later column is a token
    started = real.long().cummax(dim=1).values.bool()
    bad_rows = (started & ~real).any(dim=1).nonzero().flatten().tolist()
    if bad_rows:
        raise ValueError(
            f"attention_mask has padding after the tokens of row(s) {bad_rows[:8]}: the batch is right-padded (or "
            f"padded inside a row), and a row's new tokens would follow its padding. Pad on the left "
            f"(tokenizer.padding_side = 'left', as transformers' generate expects for decoder-only models)"
        )


@dataclass(frozen=True)
class CheckedCall:
    """A call's arguments once checked ([`_checked_call`], before any forward): what ``generate`` prepared, the
    engine's settings, what drafts and how drafts are accepted."""

    generation_config: GenerationConfig
    logits_processor: LogitsProcessorList
    settings: SpeculationConfig
    drafter: Drafter
    rule: AcceptanceRule
    layout: ActionLayout | None


def _checked_call(model, input_ids, logits_processor, generation_config, settings, draft_ids) -> CheckedCall:
    """Every argument of the call checked (before any forward): the drafter, the acceptance rule and its layout, and
    the candidates of ``draft_ids``."""
    batch_size = input_ids.shape[0]
    drafter, candidates = _call_drafter(model, batch_size, draft_ids, settings)
    _validate_call(model, generation_config, logits_processor, batch_size, drafter)
    layout = settings.action_layout or drafter.action_layout
    rule = settings.acceptance_rule(layout)
    if generation_config.do_sample and not rule.is_lossless:
        raise ValueError(
            f"relaxed acceptance ({rule!r}) is greedy only: with do_sample=True the drafts are verified by speculative "
            "sampling, which keeps the target's distribution exactly; drop bin_tolerance / motion_scale, or sample "
            "with do_sample=False's relaxed rules off"
        )
    if candidates is not None:
        _check_draft_ids_are_actions(candidates, rule, layout)
    return CheckedCall(generation_config, logits_processor, settings, drafter, rule, layout)


@dataclass
class KeptPlan:
    """A call's [`RoundPlan`] and the static cache its rounds ran on, kept for the later calls of its shape (a
    [`DecoderSession`]'s: the same shape, settings, generation config, processors and dtype), which then make
    neither again: they reuse the plan (its verifier, whose prefill runs compiled once a call compiled it) and empty
    the cache. Taken while it still fits the call ([`fits`]).

    Attributes:
        plan: the round plan.
        cache: the target's static cache with draft slots (emptied by each call), or None: each call's own cache (a
            dynamic one).
        written: the dtype the target wrote its keys in (autocast's, inside ``torch.autocast``).
        wrappers: the model's clock wrappers of its compiled calls when the plan was made (``get_compiled_call`` and
            [`CALL_WRAPPER_ATTRIBUTE`] on the instance, or None).
    """

    plan: RoundPlan
    cache: Cache | None
    written: torch.dtype
    wrappers: tuple

    def fits(self, decoder, checked: CheckedCall) -> bool:
        """Whether a call of its shape may reuse it: the same rule and layout, the dtype the target writes, the
        model's compiled graphs still the ones the plan runs (none dropped by ``reset_compilation``) and no clock
        wrapped around its compiled calls since."""
        plan, graphs = self.plan, self.plan.verifier.graphs
        return (
            plan.rule is checked.rule
            and plan.layout is checked.layout
            and self.written == written_dtype(decoder.model)
            and self.wrappers == _call_wrappers(decoder.model)
            and (graphs is None or graphs in decoder.compiled_graphs.values())
        )


def _call_wrappers(model) -> tuple:
    """What wraps ``model``'s compiled calls on the instance (a benchmark's clock): kept plans hold the calls it
    wrapped."""
    return model.__dict__.get("get_compiled_call"), model.__dict__.get(CALL_WRAPPER_ATTRIBUTE)


def prepare(
    decoder,
    input_ids,
    logits_processor,
    generation_config,
    settings: SpeculationConfig,
    draft_ids,
    model_kwargs,
    kept_plans: dict | None = None,
) -> SpeculativeCall:
    """1. The call checked and set up: the prefill's inputs on a cache with room for the trees, each row's drafter
    session, the round plan (compiled or eager, widths, rule). ``decoder``: the target's ``SpeculativeDecoder``
    (the model, and what its calls reuse: caches, compiled graphs, tree structures), handed to what needs it.

    Args:
        kept_plans: a session's plans for calls of this shape ([`KeptPlan`], by what of the drafter decides one),
            reused when one fits and kept when one is made; None (``model.generate``): every call plans anew. A
            session's call starts from a new or emptied cache: nothing to continue.
    """
    model = decoder.model
    checked = _checked_call(model, input_ids, logits_processor, generation_config, settings, draft_ids)
    drafter, layout = checked.drafter, checked.layout
    batch_size = input_ids.shape[0]
    eos_ids = generation_config.eos_token_id
    eos_ids = [] if eos_ids is None else ([eos_ids] if isinstance(eos_ids, int) else list(eos_ids))
    prompt_padding = model_kwargs.get("attention_mask")  # [B, past + new] or None (no padding)
    check_left_padded(prompt_padding)
    if kept_plans is not None:  # a session's call: its cache is new (generate's) or emptied for it, nothing continued
        past_length, num_new = 0, input_ids.shape[1]
    else:
        cache = model_kwargs.get(CACHE_KEY)
        if cache is not None:
            check_continued_cache(decoder, cache, batch_size)
        past_length, num_new = _tokens_to_prefill(input_ids, cache, prompt_padding, generation_config)
    if prompt_padding is not None and bool(prompt_padding.all()):
        prompt_padding = None
    prompt_ids = input_ids[:, input_ids.shape[1] - num_new :]  # [B, new] what the prefill feeds
    stats = SpeculationStats()
    total_start = time.perf_counter()
    # what of the drafter decides the round plan: the hidden states it reads, its widest tree (the widths compiled)
    output_hidden = tuple(drafter.hidden_state_layers) if drafter.needs_hidden_states else None
    # (the deepest a round after the prefill can draft: max_new_tokens - 1, the bonus token takes the last slot)
    widest = _widest_tree(drafter, generation_config.max_length - input_ids.shape[1] - 1, settings)
    plan_key = (output_hidden, widest)
    kept = None if kept_plans is None else kept_plans.get(plan_key)
    if kept is not None and not kept.fits(decoder, checked):
        kept = None
    model_inputs, graphs = _inputs_and_graphs(decoder, kept, prompt_ids, model_kwargs, generation_config)
    prompt_positions, position_offsets = _prompt_positions(model_inputs, prompt_ids, prompt_padding, past_length)
    cache = model_inputs[CACHE_KEY]
    cached_tokens = input_ids.shape[1] - num_new  # the rows' first tokens the cache held before the call
    prompt_embeddings = None
    if drafter.needs_prompt_embeddings:  # a head drafting before the prefill from the encoded images
        prompt_embeddings = prompt_input_embeddings(model, input_ids, model_kwargs, start=cached_tokens)
    contexts = _draft_contexts(
        decoder,
        batch_size,
        layout,
        eos_ids,
        None if prompt_padding is None else prompt_padding[:, -num_new:],
        generation_config.max_length,
        graphs,
        cached_tokens,
        prompt_embeddings,
    )
    rows = [
        RowState(b, input_ids[b : b + 1], drafter.start(context), SpeculationStats(), committed_length=cached_tokens)
        for b, context in enumerate(contexts)
    ]
    state = DecodeState(
        rows,
        prompt_ids,
        prompt_positions,
        position_offsets,
        None if prompt_padding is None else prompt_padding.bool(),
        cache,
    )
    if kept is not None:
        plan = kept.plan
    else:
        plan = _round_plan(
            model,
            checked,
            graphs,
            decoder.tree_structures,
            model_inputs,
            prompt_ids,
            position_offsets,
            past_length,
            output_hidden,
            widest,
        )
        if kept_plans is not None:
            static = cache if is_static_cache(cache) else None
            kept_plans[plan_key] = KeptPlan(plan, static, written_dtype(model), _call_wrappers(model))
    pad_token_id = generation_config.pad_token_id
    return SpeculativeCall(
        state=state,
        plan=plan,
        all_rows=list(rows),
        stats=stats,
        stopwatch=Stopwatch(stats, input_ids.device, settings.profile_speculation),
        model_inputs=model_inputs,
        prompt=(prompt_ids, prompt_positions),
        past_length=past_length,
        cached_tokens=cached_tokens,
        pad_token_id=pad_token_id if pad_token_id is not None else (eos_ids[0] if eos_ids else None),
        total_start=total_start,
        decoder=decoder,
    )


def _inputs_and_graphs(
    decoder, kept: KeptPlan | None, prompt_ids, model_kwargs: dict, generation_config
) -> tuple[dict, CompiledGraphs | None]:
    """The prefill's inputs (the model's own, ``prompt_ids`` ``[B, P]`` on the call's cache) and the compiled graphs
    the call's rounds run (None: eager): a kept plan's (its static cache emptied), else decided here: ``generate``'s
    own static cache swapped for one with room for the trees beside the tokens greedy decoding stores, and whether
    the call compiles (``call_compile_config``)."""
    model = decoder.model
    if kept is not None:
        if kept.cache is not None:
            model_kwargs[CACHE_KEY] = kept.cache
            if holds_buffers(kept.cache):
                kept.cache.reset()
        return prefill_inputs(model, prompt_ids, model_kwargs), kept.plan.verifier.graphs
    given = model_kwargs[CACHE_KEY] = with_draft_slots(
        decoder, model_kwargs.get(CACHE_KEY), verification_slots, prompt_ids.shape[0]
    )
    if given is not None:
        check_rollback_cache(given, generation_config.max_length)
    model_inputs = prefill_inputs(model, prompt_ids, model_kwargs)
    cache = model_inputs[CACHE_KEY]
    if cache is not given:  # one the model's input preparation made
        check_rollback_cache(cache, generation_config.max_length)
    compile_config = call_compile_config(
        model, generation_config.compile_config, generation_config.disable_compile, is_static_cache(cache)
    )
    return model_inputs, None if compile_config is None else decoder.graphs(compile_config)


def _round_plan(
    model,
    checked: CheckedCall,
    graphs: CompiledGraphs | None,
    tree_structures: dict,
    model_inputs: dict,
    prompt_ids: torch.Tensor,
    position_offsets,
    past_length: int,
    output_hidden: tuple[int, ...] | None,
    widest: int | None,
) -> RoundPlan:
    """What every round reads ([`RoundPlan`]), its [`CallVerifier`] chosen here: the prefill's and the rounds'
    verifications (``graphs``: the model's compiled graphs under the call's ``CompileConfig``, or None: eager;
    ``tree_structures``: the decoder's, by shape).

    Args:
        prompt_ids: ``[B, P]`` the tokens the prefill feeds.
        output_hidden: the target's hidden states the drafter reads (its layers), or None.
        widest: the most nodes a round after the prefill can verify ([`_widest_tree`]; None: unknown).
    """
    generation_config, settings = checked.generation_config, checked.settings
    num_new, batch_size = prompt_ids.shape[1], prompt_ids.shape[0]
    cache = model_inputs[CACHE_KEY]
    capacity = static_capacity(cache)
    # A prefix-LM prompt (PaliGemma's token_type_ids: the prompt attends to itself both ways at the prefill) needs
    # the model's own prefill mask, which a tree mask built here would not reproduce: the prefill verifies a chain.
    prefix_attention = model_inputs.get("token_type_ids") is not None
    prefill_key = None
    if graphs is not None and not prefix_attention and position_offsets is None and not past_length:
        prefill_key = graphs.prefill_key(capacity, output_hidden, num_new, batch_size)
    return_dict = generation_config.return_dict_in_generate
    keep_scores = bool(return_dict and generation_config.output_scores)
    keep_logits = bool(return_dict and generation_config.output_logits)
    sampling = bool(generation_config.do_sample)
    window = sliding_window(cache)
    verification = prefill_verification = EagerVerification(output_hidden, window, capacity)
    if graphs is not None:  # rounds at fixed widths through the compiled call, the acceptance in its graph if it can
        eos = None
        if accepts_in_graph(checked.rule, sampling, keep_scores, keep_logits, position_offsets):
            eos = eos_hiding(checked.logits_processor, prompt_ids.device)
        if eos is not None:
            acceptance = GraphAcceptance(graphs.accepting_call(model, output_hidden), *eos)
            verification = FusedVerification(acceptance, output_hidden, window, capacity, graphs, model.dtype)
        else:
            verification = CompiledVerification(graphs.call, output_hidden, window, capacity, graphs, model.dtype)
    plan = RoundPlan(
        max_length=generation_config.max_length,
        rule=checked.rule,
        layout=checked.layout,
        output_hidden=output_hidden,
        window=window,
        capacity=capacity,
        verifier=CallVerifier(
            verification,
            prefill_verification,
            graphs,
            prefill_key,
            buckets_up_to(widest),
        ),
        prefix_attention=prefix_attention,
        max_drafts=settings.max_drafts_per_row,
        keep_scores=keep_scores,
        keep_logits=keep_logits,
        sampling=sampling,
        tree_structures=tree_structures,
    )
    return plan


def finish(call: SpeculativeCall, generation_config) -> SpeculativeDecoderOnlyOutput | torch.LongTensor:
    """4. The cache left as greedy decoding would leave it, the statistics gathered, the output."""
    state, stats, all_rows = call.state, call.stats, call.all_rows
    _leave_cache_as_greedy(call.decoder, state.target_cache, all_rows, call.past_length - call.cached_tokens)
    for row in all_rows:
        row.stats.num_draft_forwards = row.session.num_forwards
        row.session.report(row.stats, row.sequence)
        stats.rows.append(row.stats)
    stats.absorb_rows()
    stats.compile_seconds += sum(row.session.compile_seconds for row in all_rows)
    stats.total_seconds = time.perf_counter() - call.total_start
    logger.debug("speculation: %s", stats)
    batch_size = len(all_rows)
    sequences = all_rows[0].sequence if batch_size == 1 else _padded_rows(all_rows, call.pad_token_id)
    if not generation_config.return_dict_in_generate:
        return sequences
    if batch_size == 1:
        stats.rows = []
    return SpeculativeDecoderOnlyOutput(
        sequences=sequences,
        scores=_per_step(all_rows, "scores") if call.plan.keep_scores else None,
        logits=_per_step(all_rows, "logits") if call.plan.keep_logits else None,
        speculation=stats,
        **{CACHE_KEY: state.target_cache if batch_size == 1 else None},
    )
