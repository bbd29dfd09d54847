"""The speculative decode loop: drafters propose trees, the target verifies each in one forward.

One call reads as four steps (gpt-fast style), [`speculative_generate`]:

    prepare (every argument checked, the rows' drafter sessions, the [`RoundPlan`]) -> prefill -> decode_round until
    every row has stopped -> finish (the cache left as greedy leaves it, statistics, the output)

The prefill and every round run the same ladder, each step a short function below:

    propose (drafters) -> fit (fit_prefill_trees / fit_trees) -> one target forward (the prefill's over the model's
    prepared inputs; a round's [`verify`], compiled at a fixed width) -> settle: accept -> emit -> commit_paths ->
    observe (drafters) -> drop finished rows

What every round reads is decided once, before the prefill ([`RoundPlan`]: the acceptance rule, the static cache's
slots, the compiled model call when ``compile_config`` asks for one); the compiled widths are compiled right after the
prefill, outside the round loop.

Invariants kept between rounds, per batch row (each row has its own drafter session, tree, accepted path):

* a row's ``sequence`` holds its prompt and every token it emitted. ``pending`` tokens are not in the target cache yet:
  the whole prompt before the prefill, afterwards exactly the last emitted token (the previous bonus token).
* The tree proposed in a round hangs below the last pending token (the root). Drafts known before the target has
  run (``draft_ids``, the action prior) are proposed in round 0 and so verified *inside the prefill*: when all of
  them pass, the action costs exactly one target forward.
* After a round the target cache holds, for each row, the pending tokens and the accepted path as valid entries
  (an accepted node need not be leftmost in the tree: then the path is gathered). The cache is one rectangle for
  the batch: entries a row did not keep are invalid keys, masked like prompt padding (``DecodeState.key_valid``).
  Finished rows leave the batch; a static cache keeps its batch (compiled graphs hold its shape): finished rows stay
  in it as idle rows, fed filler and never read (``DecodeState.cache_rows``), and when its free slots run short every
  row's valid entries are moved to the front ([`compact_rows`]).

Entry point: [`speculative_generate`], a ``custom_generate`` callable for ``model.generate``.
"""

from __future__ import annotations

import itertools
import logging
import time
import warnings
import weakref
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch
from transformers import GenerationConfig, LogitsProcessorList, PreTrainedModel, StoppingCriteriaList
from transformers.cache_utils import Cache
from transformers.generation.logits_process import PrefixConstrainedLogitsProcessor
from transformers.generation.stopping_criteria import EosTokenCriteria, MaxLengthCriteria, MaxTimeCriteria

from ..actions.tokenizer import ActionLayout
from .acceptance import AcceptanceRule, AcceptedPath, accept_trees, make_acceptance_rule, sample_trees
from .assistant import as_drafter
from .cache import (
    ROLLBACK_LAYER_TYPES,
    cache_batch_size,
    cache_length,
    check_rollback_cache,
    compact_rows,
    holds_buffers,
    host_length,
    keep_cache_path,
    open_sliding_windows,
    select_cache_positions,
    select_cache_rows,
    sliding_window,
    static_capacity,
    truncate_cache,
    with_draft_slots,
)
from .compat import CACHE_KEY, check_transformers_support
from .compiled import (
    NODE_BUCKETS,
    SLOT_MULTIPLE,
    CompiledVerifier,
    PrefillCall,
    buckets_up_to,
    compiles_verification,
    verification_width,
)
from .config import SpeculationConfig
from .drafter import (
    CandidateDrafter,
    Commit,
    ComposedDrafter,
    DraftContext,
    Drafter,
    DraftRound,
    DraftSession,
    PerRowDrafter,
)
from .outputs import SpeculativeDecoderOnlyOutput
from .stats import SpeculationStats
from .tree import DraftTree, TreeBatch
from .verify import TargetOutput, prefill_inputs, target_greedy_ids, verify_trees

if TYPE_CHECKING:
    from .modeling_draft_head import DraftHead

logger = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- state
@dataclass
class RowState:
    """One batch row's decode: its tokens, its drafter session, its statistics."""

    index: int  # the row's index in the caller's batch
    sequence: torch.Tensor  # [1, L] the row's prompt (padding included) + its emitted tokens
    session: DraftSession
    stats: SpeculationStats
    num_generated: int = 0  # tokens emitted in this row
    num_action_tokens: int = 0  # action tokens emitted in this row (for action dimensions)
    relaxed_in_action: int = 0  # relaxed tokens (accepted at a bin distance > 0) in the action being emitted
    committed_length: int = 0  # entries the row has kept (its prompt and emitted tokens but the last)
    finished: bool = False
    scores: list = field(default_factory=list)  # [V] processed logits per emitted token (output_scores)
    logits: list = field(default_factory=list)  # [V] raw logits per emitted token (output_logits)


@dataclass
class DecodeState:
    """Everything one speculative decode carries between rounds (one explicit object, nothing on the models).

    The tensors hold the rows still generating, in ``rows`` order (finished rows are dropped from them and from a
    dynamic cache). The target cache is rectangular: a row that accepted fewer tokens than another in a round keeps
    *invalid* entries there, masked by ``key_valid`` like the prompt's left padding. A static cache keeps every row
    of the call: ``cache_rows`` says which of its rows the generating rows are.
    """

    rows: list[RowState]
    pending_ids: torch.Tensor  # [B, P] tokens not yet in the target cache (their last one is each tree's root)
    pending_positions: torch.Tensor  # [B, P] their (text) position ids
    position_offsets: torch.Tensor | None  # [K, B, 1] multi-component positions' offsets (Qwen2-VL), else None
    key_valid: torch.Tensor | None  # [B, C + P] False at invalid cached / pending keys; None = all valid
    target_cache: Cache
    cache_rows: torch.Tensor | None = None  # [B] the rows' indices in a static cache's batch; None: the same rows


def in_cache_batch(state: DecodeState, values: torch.Tensor, fill) -> torch.Tensor:
    """``values`` ``[B, ...]`` of the generating rows -> ``[B_cache, ...]`` over a static cache's batch, its idle
    rows (finished ones, kept in it) set to ``fill``; ``values`` itself when the cache holds exactly the rows."""
    if state.cache_rows is None:
        return values
    out = values.new_full((cache_batch_size(state.target_cache), *values.shape[1:]), fill)
    out[state.cache_rows] = values
    return out


class _Stopwatch:
    """Accumulates wall time of labelled sections into the stats, optionally device-synchronised."""

    def __init__(self, stats: SpeculationStats, device: torch.device, synchronize: bool):
        self.stats, self.device, self.synchronize = stats, device, synchronize

    def _sync(self):
        if self.synchronize and self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    @contextmanager
    def section(self, attribute: str):
        self._sync()
        start = time.perf_counter()
        yield
        self._sync()
        setattr(self.stats, attribute, getattr(self.stats, attribute) + time.perf_counter() - start)


# ----------------------------------------------------------------------------- inputs
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
    model, batch_size: int, drafter, draft_head, draft_ids, settings: SpeculationConfig
) -> tuple[Drafter, list[list[list[int]]] | None]:
    """The call's drafter: the assistant (a bare DraftHead drafts a chain), with ``draft_ids``'s candidates first when
    given; and those candidates (per row), or None.

    Raises:
        ValueError: both ``drafter`` and ``draft_head``, or nothing to draft with; bad ``draft_ids``.
    """
    if drafter is not None and draft_head is not None:
        raise ValueError("pass drafter= or draft_head=, not both")
    drafter = as_drafter(drafter if drafter is not None else draft_head, settings.num_draft_tokens)
    candidates = None
    if draft_ids is not None:
        vocab_size = model.get_output_embeddings().weight.shape[0]
        candidates = draft_id_candidates(draft_ids, batch_size, vocab_size)
        known = CandidateDrafter(candidates[0]) if batch_size == 1 else PerRowDrafter(
            [CandidateDrafter(row) for row in candidates]
        )  # fmt: skip
        drafter = known if drafter is None else ComposedDrafter([known, drafter])
    if drafter is None:
        raise ValueError(
            "speculative_generate needs something to draft with: drafter= (or generate(assistant_model=...)) "
            "and/or draft_ids="
        )
    return drafter, candidates


def _draft_contexts(
    model,
    batch_size: int,
    layout,
    eos_ids: list[int],
    prompt_padding,
    max_length: int,
    compile_config,
    cached_tokens: int = 0,
) -> list[DraftContext]:
    """What each row's drafter session starts from (the padding of the prompt tokens the prefill feeds, ``[1, P]``
    or None; the row's first ``cached_tokens`` tokens, which a continued cache already held)."""
    rows = [None if prompt_padding is None else prompt_padding[b : b + 1] for b in range(batch_size)]
    return [
        DraftContext(
            model,
            layout,
            eos_ids,
            padding,
            row=b,
            max_length=max_length,
            compile_config=compile_config,
            cached_tokens=cached_tokens,
        )
        for b, padding in enumerate(rows)
    ]


#: caches a batched call has decoded on: their rows keep entries of drafts some rows rejected (masked only inside that
#: call) and a dynamic one has lost its finished rows, so no later call can continue them exactly
_BATCH_DECODED_CACHES: weakref.WeakSet = weakref.WeakSet()


def check_continued_cache(cache: Cache, batch_size: int) -> None:
    """Refuses, before any forward, a cache this call cannot continue exactly: one holding entries a batched
    speculative call left, or one whose layers already hold another number of rows than ``input_ids`` (a static
    cache keeps its rows when emptied).

    Raises:
        ValueError: naming the cache's rows / history and what would work.
    """
    if not holds_buffers(cache) or any(type(layer) not in ROLLBACK_LAYER_TYPES for layer in cache.layers):
        return  # nothing allocated yet (any batch size), or a cache refused for its layers (check_rollback_cache)
    entries = cache_length(cache)
    if cache in _BATCH_DECODED_CACHES and entries:
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


def _leave_cache_as_greedy(cache: Cache, rows: list[RowState], offset: int) -> None:
    """Leaves a one-row cache as greedy decoding would: the entries of its sequence but the last token (a path the
    stopping criteria cut keeps no entries past the cut), so that a later call continues it exactly. ``offset``: the
    entries before the row's sequence (a continued cache given only the new tokens). A batch's cache is marked
    ([`check_continued_cache`] refuses it)."""
    if len(rows) > 1:
        _BATCH_DECODED_CACHES.add(cache)
        return
    _BATCH_DECODED_CACHES.discard(cache)
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


# ----------------------------------------------------------------------------- steps
def commit_paths(
    state: DecodeState,
    trees: TreeBatch,
    paths: list[AcceptedPath],
    hidden: torch.Tensor | None,
    target_ids: torch.Tensor | None = None,
) -> list[Commit]:
    """Keeps, for every row, its pending tokens and its accepted path in the target cache; says so to drafters.

    A row whose path is shorter than the longest one keeps invalid entries up to that length (``key_valid``), so
    that the cache stays rectangular; when every row's path is leftmost (always for chains) the cache is simply
    truncated (a shorter row's rejected entries stay, as invalid keys), else each row's path is gathered.
    Updates ``state`` (pending tokens, positions, key validity).

    Args:
        hidden: ``[B, P + N, H]`` the target's hidden states of the verification, or None.
        target_ids: ``[B, 1 + N]`` the target's greedy token after each row's root and each node, or None.
    Returns:
        one [`Commit`] per row: kept inputs = pending tokens + path nodes; the token after each; hidden states; the
        verified tree, the target's tokens on it and the accepted path.
    """
    batch_size, num_pending = state.pending_ids.shape
    base = cache_length(state.target_cache) - trees.num_nodes  # cache entries before the tree's
    device = state.pending_ids.device
    longest = max(len(p.nodes) for p in paths)
    path_valid = torch.tensor(
        [[i < len(p.nodes) for i in range(longest)] for p in paths], dtype=torch.bool, device=device
    )  # [B, A]
    node_index = torch.tensor([p.nodes + [0] * (longest - len(p.nodes)) for p in paths], device=device).long()
    if all(p.nodes == list(range(len(p.nodes))) for p in paths):  # leftmost paths (chains): a prefix, truncate
        truncate_cache(state.target_cache, base + longest)  # a shorter row's extra entries become invalid keys
    else:
        keep_cache_path(state.target_cache, base, in_cache_batch(state, node_index, 0))
    valid_before = state.key_valid
    if valid_before is None:
        valid_before = torch.ones(batch_size, base, dtype=torch.bool, device=device)
    key_valid = torch.cat([valid_before, path_valid], dim=1)  # [B, base + A]
    # every key valid: known on the host when no key was invalid before (else the device says)
    same_length = all(len(p.nodes) == longest for p in paths)
    all_valid = same_length and (state.key_valid is None or bool(key_valid.all()))
    commits = []
    for b, (row, path) in enumerate(zip(state.rows, paths)):
        accepted = len(path.nodes)
        nodes = node_index[b, :accepted]
        path_tokens = trees.token_ids[b, nodes][None]  # [1, A_b]
        bonus = path_tokens.new_full((1, 1), path.bonus_id)
        path_positions = state.pending_positions[b : b + 1, -1:] + 1 + torch.arange(accepted, device=device)[None]
        kept_hidden = None
        if hidden is not None:
            kept_hidden = torch.cat([hidden[b : b + 1, :num_pending], hidden[b : b + 1, num_pending + nodes]], dim=1)
        row.committed_length += num_pending + accepted
        commits.append(
            Commit(
                next_token_ids=torch.cat([state.pending_ids[b : b + 1, 1:], path_tokens, bonus], dim=1),
                positions=torch.cat([state.pending_positions[b : b + 1], path_positions], dim=1),
                target_hidden=kept_hidden,
                cache_length=row.committed_length,
                tree=trees.trees[b],
                tree_target_ids=None if target_ids is None else target_ids[b, : 1 + trees.trees[b].num_nodes],
                path_nodes=path.nodes,
                tree_target_list=path.target_ids,
            )
        )
    state.pending_ids = torch.cat([c.next_token_ids[:, -1:] for c in commits])  # [B, 1] the bonus tokens
    state.pending_positions = torch.cat([c.positions[:, -1:] + 1 for c in commits])
    state.key_valid = None if all_valid else torch.cat([key_valid, key_valid.new_ones(batch_size, 1)], 1)
    return commits


def drop_finished_rows(state: DecodeState, fixed_batch: bool = False) -> None:
    """Removes finished rows from the batch tensors, and from the target cache with the cache columns no row needs;
    with ``fixed_batch`` (a static cache) the cache keeps its rows and columns: the finished ones become idle rows
    (``state.cache_rows`` maps the rows still generating to theirs)."""
    active = [b for b, row in enumerate(state.rows) if not row.finished]
    if len(active) == len(state.rows):
        return
    state.rows = [state.rows[b] for b in active]
    if not active:
        return
    index = torch.tensor(active, device=state.pending_ids.device)
    state.pending_ids, state.pending_positions = state.pending_ids[index], state.pending_positions[index]
    if state.position_offsets is not None:
        state.position_offsets = state.position_offsets[:, index]
    if fixed_batch:
        state.cache_rows = index if state.cache_rows is None else state.cache_rows[index]
        if state.key_valid is not None:
            state.key_valid = state.key_valid[index]
        return
    select_cache_rows(state.target_cache, index)
    if state.key_valid is not None:
        key_valid = state.key_valid[index]
        needed = key_valid[:, :-1].any(dim=0)  # cached columns some remaining row attends to
        if not bool(needed.all()):
            select_cache_positions(state.target_cache, needed.nonzero()[:, 0])
            key_valid = torch.cat([key_valid[:, :-1][:, needed], key_valid[:, -1:]], dim=1)
        state.key_valid = None if bool(key_valid.all()) else key_valid


def emit_tokens(rows: list[RowState], emitted: list[list[int]], stopping_criteria: StoppingCriteriaList) -> list[int]:
    """Appends each row's ``emitted`` tokens up to where the stopping criteria first fire, as greedy decoding (which
    asks them after every token) would stop, and marks those rows finished.

    The criteria see exactly the prefixes greedy decoding shows them; prefixes of one length (across rows) are
    asked in one call.

    Returns:
        per row, how many of its tokens were kept.
    """
    lengths = [row.sequence.shape[1] for row in rows]
    extended = [torch.cat([row.sequence[0], row.sequence.new_tensor(tokens)]) for row, tokens in zip(rows, emitted)]
    by_length: dict[int, list[int]] = {}  # prefix length -> rows that reach it
    for b, tokens in enumerate(emitted):
        for count in range(1, len(tokens) + 1):
            by_length.setdefault(lengths[b] + count, []).append(b)
    stop_length: list[int | None] = [None] * len(rows)  # the shortest prefix the criteria stop at
    asked = [(length, by_length[length]) for length in sorted(by_length)]
    on_host = _host_stopping(stopping_criteria)
    if on_host is not None:  # generate's own criteria (length, EOS, time), answered from the host's tokens
        for length, group in asked:
            for b in group:
                if stop_length[b] is None and on_host(length, emitted[b][length - lengths[b] - 1]):
                    stop_length[b] = length
    elif asked:  # every prefix asked (the criteria are functions of the ids), then one read of all the answers
        answers = torch.cat([
            stopping_criteria(torch.stack([extended[b][:length] for b in group]), None).reshape(-1)
            for length, group in asked
        ]).tolist()  # fmt: skip
        for (length, group), start in zip(asked, itertools.accumulate([0] + [len(g) for _, g in asked])):
            for b, stop in zip(group, answers[start : start + len(group)]):
                if stop and stop_length[b] is None:
                    stop_length[b] = length
    num_kept = []
    for b, row in enumerate(rows):
        end = lengths[b] + len(emitted[b]) if stop_length[b] is None else stop_length[b]
        row.finished = stop_length[b] is not None
        row.sequence = extended[b][None, :end]
        row.num_generated += end - lengths[b]
        num_kept.append(end - lengths[b])
    return num_kept


def _host_stopping(stopping_criteria: StoppingCriteriaList) -> Callable[[int, int], bool] | None:
    """``stop(prefix_length, last_token)`` answering ``stopping_criteria`` on the host, exactly as they answer on the
    ids, when they are all transformers' length, EOS and time criteria (what ``generate`` builds); None otherwise."""
    known = (MaxLengthCriteria, EosTokenCriteria, MaxTimeCriteria)
    if not all(type(criteria) in known for criteria in stopping_criteria):
        return None
    max_lengths = [c.max_length for c in stopping_criteria if type(c) is MaxLengthCriteria]
    eos_ids = set()
    for criteria in stopping_criteria:
        if type(criteria) is EosTokenCriteria:
            if getattr(criteria, "_host_eos_ids", None) is None:  # read once per call, not once per round
                criteria._host_eos_ids = criteria.eos_token_id.reshape(-1).tolist()
            eos_ids.update(criteria._host_eos_ids)
    timers = [c for c in stopping_criteria if type(c) is MaxTimeCriteria]

    def stop(length: int, last_token: int) -> bool:
        return (
            any(length >= m for m in max_lengths)
            or last_token in eos_ids
            or any(time.time() - c.initial_timestamp > c.max_time for c in timers)
        )

    return stop


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


@dataclass(frozen=True)
class RoundPlan:
    """What every round of one call reads, decided once before the prefill."""

    max_length: int  # generate's max_length: no path drafts past it
    rule: AcceptanceRule
    layout: ActionLayout | None
    output_hidden: tuple[int, ...] | None  # the target's hidden states the drafters read (their layers), or None
    window: int | None  # the target cache's smallest sliding window
    capacity: int | None  # a static cache's slots: trees fit in the free ones
    verifier: CompiledVerifier | None  # the compiled verification of rounds after the prefill, or None (eager)
    compiled_prefill: PrefillCall | None  # the compiled prefill (its graph compiled by an earlier call), or None
    buckets: tuple[int, ...]  # the widths a compiled verification is padded to (up to the drafter's largest tree)
    prefix_attention: bool  # a prefix-LM prompt: the prefill verifies one chain
    max_drafts: int | None  # each row's tree is cut to its first this many nodes (``max_drafts_per_row``), or None
    keep_scores: bool
    keep_logits: bool
    sampling: bool = False  # do_sample: the drafts are verified by speculative sampling ([`sample_trees`])


def propose(state: DecodeState, plan: RoundPlan) -> list[DraftTree]:
    """1. Each row's drafter proposes a tree below its root (at the prefill: before any token of the call was emitted);
    no path drafts past ``max_length`` (the bonus token takes the last slot)."""
    trees = []
    for b, row in enumerate(state.rows):
        draft_round = DraftRound(
            sequence=row.sequence,
            num_generated=row.num_generated,
            max_depth=max(0, plan.max_length - row.sequence.shape[1] - 1),
            at_prefill=row.num_generated == 0,  # the prefill emits at least its bonus token
            root_position=state.pending_positions[b : b + 1, -1:],
        )
        trees.append(row.session.propose(draft_round).truncate_depth(draft_round.max_depth))
    return trees


def fit_prefill_trees(trees: list[DraftTree], state: DecodeState, plan: RoundPlan) -> TreeBatch:
    """The prefill's trees as one [`TreeBatch`]: a prefix-LM prompt keeps one chain; ``max_drafts_per_row`` and, on a
    static cache, its free slots cut each tree to its first nodes (the prefill's width is free: its compiled graph
    has a dynamic length)."""
    if plan.prefix_attention:
        trees = [tree.first_path() for tree in trees]
    if plan.max_drafts is not None:
        trees = [tree.truncate_nodes(plan.max_drafts) for tree in trees]
    if plan.capacity is not None:
        trees = [tree.truncate_nodes(_free_slots(state, plan)) for tree in trees]
    return TreeBatch(trees)


def _free_slots(state: DecodeState, plan: RoundPlan) -> int:
    """A static cache's slots left for a tree after its entries and the pending tokens."""
    return plan.capacity - cache_length(state.target_cache) - state.pending_ids.shape[1]


def fit_trees(trees: list[DraftTree], state: DecodeState, plan: RoundPlan, stats: SpeculationStats) -> TreeBatch:
    """A round's trees as one [`TreeBatch`]: ``max_drafts_per_row`` cuts every tree to its first nodes; on a static
    cache the pending token and the tree fit in the free slots (a batch's rows are compacted first when invalid
    entries take the slots the trees need), and a compiled round is padded (or cut) to its width bucket."""
    if plan.max_drafts is not None:
        trees = [tree.truncate_nodes(plan.max_drafts) for tree in trees]
    width = 0  # the node count a compiled verification is padded to
    if plan.capacity is not None:
        free = _free_slots(state, plan)
        widest = max(tree.num_nodes for tree in trees)
        wanted = verification_width(widest, plan.buckets[-1], plan.buckets) if plan.verifier is not None else widest
        if free < wanted and state.key_valid is not None:
            _compact(state)
            free = _free_slots(state, plan)
        if plan.verifier is not None:  # one width per bucket: padded, or cut to fit
            free = width = verification_width(widest, free, plan.buckets)
            stats.compiled_widths.append(width)
        trees = [tree.truncate_nodes(free) for tree in trees]
    return TreeBatch(trees, min_nodes=width)


def _compact(state: DecodeState) -> None:
    """[`compact_rows`] on a static cache's batch: each row's valid entries moved to the front (idle rows keep none)."""
    cached = cache_length(state.target_cache)
    valid = in_cache_batch(state, state.key_valid[:, :cached], False)  # [B_cache, C]
    if int(valid.sum(dim=1).max()) == cached:  # some row keeps every entry: nothing to free
        return
    compacted = compact_rows(state.target_cache, valid)  # [B_cache, C']
    if state.cache_rows is not None:
        compacted = compacted[state.cache_rows]
    key_valid = torch.cat([compacted, state.key_valid[:, cached:]], dim=1)  # [B, C' + P]
    state.key_valid = None if bool(key_valid.all()) else key_valid


def verify(model: PreTrainedModel, state: DecodeState, plan: RoundPlan, trees: TreeBatch) -> TargetOutput:
    """2. Every row's tree in one target forward on the cache (compiled when the plan has a compiled call). A static
    cache's idle rows (finished, kept in its batch) are fed a filler token and an empty tree, their outputs
    dropped."""
    pending_ids, positions, key_valid, offsets = (
        state.pending_ids, state.pending_positions, state.key_valid, state.position_offsets
    )  # fmt: skip
    if state.cache_rows is not None:
        pending_ids, positions = in_cache_batch(state, pending_ids, 0), in_cache_batch(state, positions, 0)
        if key_valid is None:
            columns = cache_length(state.target_cache) + state.pending_ids.shape[1]
            key_valid = torch.ones(state.pending_ids.shape[0], columns, dtype=torch.bool, device=pending_ids.device)
        key_valid = in_cache_batch(state, key_valid, False)
        key_valid[:, -1] = True  # an idle row's filler attends to itself
        if offsets is not None:
            offsets = in_cache_batch(state, offsets.transpose(0, 1), 0).transpose(0, 1)
        rows = [DraftTree.empty(pending_ids.device)] * pending_ids.shape[0]
        for tree, b in zip(trees.trees, state.cache_rows.tolist()):
            rows[b] = tree
        trees = TreeBatch(rows, min_nodes=trees.num_nodes)
    output = verify_trees(
        model,
        {CACHE_KEY: state.target_cache},
        pending_ids,
        positions,
        trees,
        key_valid,
        output_hidden=plan.output_hidden,
        sliding_window=plan.window,
        position_offsets=offsets,
        key_length=plan.capacity,
        forward=None if plan.verifier is None else plan.verifier.call,
    )
    if state.cache_rows is None:
        return output
    hidden = None if output.hidden is None else output.hidden[state.cache_rows]
    return TargetOutput(output.logits[state.cache_rows], hidden)


def accept(
    state: DecodeState, plan: RoundPlan, trees: TreeBatch, output: TargetOutput, logits_processor: LogitsProcessorList
) -> tuple[list[AcceptedPath], torch.Tensor, torch.Tensor]:
    """3. Per row, the longest passing path; its bonus token is the target's greedy choice after it (sampling: the path
    and bonus token drawn by speculative sampling, [`sample_trees`]).

    Returns:
        (the accepted paths, the target's greedy ids ``[B, 1 + N]``, the processed scores ``[B, 1 + N, V]``)."""
    target_ids, target_scores = target_greedy_ids(
        logits_processor, [row.sequence for row in state.rows], trees, output.logits
    )
    if plan.sampling:  # the target's distribution, exactly: every draft a point mass, recursive rejection sampling
        return sample_trees(trees, target_scores), target_ids, target_scores
    action_counts = [row.num_action_tokens for row in state.rows]
    top1_probs = target_scores.softmax(dim=-1).amax(dim=-1) if plan.rule.needs_probabilities else None  # [B, 1 + N]
    budgeted = plan.rule.max_relaxed_per_action is not None and plan.layout is not None  # counted per action
    dim = plan.layout.action_dim if plan.layout is not None else 1
    relaxed = [row.relaxed_in_action if row.num_action_tokens % dim else 0 for row in state.rows] if budgeted else None
    paths = accept_trees(trees, target_ids, plan.rule, plan.layout, action_counts, top1_probs, relaxed)
    return paths, target_ids, target_scores


def emit(
    state: DecodeState,
    plan: RoundPlan,
    trees: TreeBatch,
    paths: list[AcceptedPath],
    output: TargetOutput,
    target_scores: torch.Tensor,
    stopping_criteria: StoppingCriteriaList,
) -> None:
    """4. Appends each row's accepted tokens and bonus token, stopping it exactly where greedy would (EOS,
    ``max_length``, custom criteria); books statistics, scores and logits."""
    emitted = []
    for row, tree, path in zip(state.rows, trees.trees, paths):
        row.stats.record_verification(tree.max_depth, tree.num_nodes, [tree.sources[n] for n in path.nodes])
        emitted.append([tree.host_tokens[n] for n in path.nodes] + [path.bonus_id])
    num_kept = emit_tokens(state.rows, emitted, stopping_criteria)
    for b, (row, tree, path, count) in enumerate(zip(state.rows, trees.trees, paths, num_kept)):
        parents = tree.parent_list
        logit_rows = [parents[n] + 1 for n in path.nodes] + [path.nodes[-1] + 1 if path.nodes else 0]
        for token, logit_row, distance in zip(emitted[b][:count], logit_rows, path.distances + [0]):
            if plan.layout is not None and plan.layout.tokenizer.is_action_token(token):
                if row.num_action_tokens % plan.layout.action_dim == 0:  # the first token of an action
                    row.relaxed_in_action = 0
                row.num_action_tokens += 1
                row.relaxed_in_action += distance > 0
                row.stats.action_bin_distances.append(distance)
            if plan.keep_scores:
                row.scores.append(target_scores[b, logit_row])
            if plan.keep_logits:
                row.logits.append(output.logits[b, logit_row])
        row.stats.accept_lengths.append(count)


def observe(state: DecodeState, commits: list[Commit]) -> None:
    """5b. Tells the drafter of every row still generating what its round kept (after [`commit_paths`], 5a)."""
    for row, kept in zip(state.rows, commits):
        if not row.finished:
            row.session.observe(kept)


def _widest_tree(drafter: Drafter, max_depth: int, settings: SpeculationConfig) -> int | None:
    """The most nodes a round's tree can hold: the drafter's largest tree ``max_depth`` deep (None: unknown), cut to
    ``max_drafts_per_row``."""
    widest, cap = drafter.max_tree_nodes(max(0, max_depth)), settings.max_drafts_per_row
    known = [n for n in (widest, cap) if n is not None]
    return min(known) if known else None


# ----------------------------------------------------------------------------- the loop
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


def speculative_generate(
    model: PreTrainedModel,
    input_ids: torch.LongTensor,
    logits_processor: LogitsProcessorList,
    stopping_criteria: StoppingCriteriaList,
    generation_config: GenerationConfig,
    drafter: Drafter | DraftHead | None = None,
    draft_head: DraftHead | None = None,
    draft_ids: torch.LongTensor | None = None,
    bin_tolerance: int | Sequence[int] = SpeculationConfig.bin_tolerance,
    num_draft_tokens: int | None = SpeculationConfig.num_draft_tokens,
    action_layout: ActionLayout | None = SpeculationConfig.action_layout,
    profile_speculation: bool = SpeculationConfig.profile_speculation,
    confidence_gate: float | None = SpeculationConfig.confidence_gate,
    max_relaxed_per_action: int | None = SpeculationConfig.max_relaxed_per_action,
    max_drafts_per_row: int | None = SpeculationConfig.max_drafts_per_row,
    motion_scale: float | Sequence[float] | None = SpeculationConfig.motion_scale,
    max_deviation: float | Sequence[float] | None = SpeculationConfig.max_deviation,
    confirm_strict_tail: bool = SpeculationConfig.confirm_strict_tail,
    **model_kwargs,
) -> SpeculativeDecoderOnlyOutput | torch.LongTensor:
    """Greedy speculative decoding of a batch; a ``custom_generate`` callable for ``model.generate``.

    ``generate`` has already prepared ``input_ids`` ``[B, S]`` (left-padded when rows differ in length, with the
    2D ``attention_mask`` in ``model_kwargs``), the logits processors, stopping criteria and ``model_kwargs``
    (cache, position ids, encoded images). Extra keyword arguments of ``generate`` named like the parameters
    below arrive here (see [`SpeculationConfig`] for the settings).

    Each row drafts with its own drafter session, accepts its own number of tokens per target forward and stops on
    its own (EOS, ``max_length``, stopping criteria); finished rows leave the batch. With ``bin_tolerance=0`` every
    row's tokens are plain (batched) greedy decoding's.

    Args:
        drafter: a [`Drafter`] (the same for every row, or a [`PerRowDrafter`]) or a [`DraftHead`]
            (``draft_head=`` is the same, deprecated: a ``FutureWarning``).
        draft_ids: ``[B, k]`` or ``[B, C, k]`` drafts of the first generated tokens of each row, known up front:
            verified inside the prefill forward, with or without a drafter.
    Returns:
        ``[B, S + new]`` token ids (rows that stopped early right-padded with ``pad_token_id``), or with
        ``return_dict_in_generate=True`` a [`SpeculativeDecoderOnlyOutput`] whose ``.speculation`` is a
        [`SpeculationStats`] (summed over rows; ``.rows`` per row when B > 1).
    """
    check_transformers_support()
    if draft_head is not None:
        warnings.warn(
            "speculative_generate(draft_head=...) is deprecated and will be removed: pass drafter= (or "
            "model.generate(assistant_model=...)), which takes a DraftHead too",
            FutureWarning,
            stacklevel=2,
        )
    settings = SpeculationConfig(
        bin_tolerance, num_draft_tokens, action_layout, profile_speculation, confidence_gate, max_relaxed_per_action,
        max_drafts_per_row, motion_scale, max_deviation, confirm_strict_tail,
    )  # fmt: skip
    call = prepare(model, input_ids, logits_processor, generation_config, settings, drafter, draft_head, draft_ids,
                   model_kwargs)  # fmt: skip
    cache = call.state.target_cache
    with open_sliding_windows(cache), host_length(cache):  # exact: the generation fits the window (checked)
        prefill(model, call, logits_processor, stopping_criteria)
        while call.state.rows:
            decode_round(model, call, logits_processor, stopping_criteria)
    return finish(call, generation_config)


# ----------------------------------------------------------------------------- the call's steps
@dataclass
class SpeculativeCall:
    """One ``generate`` call's decode, as [`prepare`] sets it up: the rows' state, what every round reads, the
    prefill's inputs, the statistics."""

    state: DecodeState
    plan: RoundPlan
    all_rows: list[RowState]  # every row of the call, finished or not, in the caller's order
    stats: SpeculationStats
    stopwatch: _Stopwatch
    model_inputs: dict  # the prefill's prepared inputs (images, cache, ...)
    prompt: tuple[torch.Tensor, torch.Tensor]  # the prefill's pending ids and positions
    prefill_key: tuple | None  # the compiled prefill graph this call can use, or None (an eager prefill)
    past_length: int  # entries the cache held before the call
    cached_tokens: int  # the rows' first tokens the cache held before the call
    pad_token_id: int | None
    total_start: float


def _checked_call(model, input_ids, logits_processor, generation_config, settings, drafter, draft_head, draft_ids):
    """Every argument of the call checked (before any forward): the drafter, the acceptance rule and its layout, and
    the candidates of ``draft_ids``."""
    batch_size = input_ids.shape[0]
    drafter, candidates = _call_drafter(model, batch_size, drafter, draft_head, draft_ids, settings)
    _validate_call(model, generation_config, logits_processor, batch_size, drafter)
    layout = settings.action_layout or drafter.action_layout
    rule = make_acceptance_rule(
        settings.bin_tolerance, layout, settings.confidence_gate, settings.max_relaxed_per_action,
        settings.motion_scale, settings.max_deviation, settings.confirm_strict_tail,
    )  # fmt: skip
    if generation_config.do_sample and not rule.is_lossless:
        raise ValueError(
            f"relaxed acceptance ({rule!r}) is greedy only: with do_sample=True the drafts are verified by speculative "
            "sampling, which keeps the target's distribution exactly; drop bin_tolerance / motion_scale, or sample "
            "with do_sample=False's relaxed rules off"
        )
    if candidates is not None:
        _check_draft_ids_are_actions(candidates, rule, layout)
    return drafter, rule, layout


def prepare(
    model, input_ids, logits_processor, generation_config, settings, drafter, draft_head, draft_ids, model_kwargs
) -> SpeculativeCall:
    """1. The call checked and set up: the prefill's inputs on a cache with room for the trees, each row's drafter
    session, the round plan (compiled or eager, widths, rule)."""
    drafter, rule, layout = _checked_call(model, input_ids, logits_processor, generation_config, settings, drafter,
                                          draft_head, draft_ids)  # fmt: skip
    batch_size = input_ids.shape[0]
    eos_ids = generation_config.eos_token_id
    eos_ids = [] if eos_ids is None else ([eos_ids] if isinstance(eos_ids, int) else list(eos_ids))
    prompt_padding = model_kwargs.get("attention_mask")  # [B, past + new] or None (no padding)
    check_left_padded(prompt_padding)
    if model_kwargs.get(CACHE_KEY) is not None:
        check_continued_cache(model_kwargs[CACHE_KEY], batch_size)
    past_length, num_new = _tokens_to_prefill(input_ids, model_kwargs.get(CACHE_KEY), prompt_padding, generation_config)
    if prompt_padding is not None and bool(prompt_padding.all()):
        prompt_padding = None
    prompt_ids = input_ids[:, input_ids.shape[1] - num_new :]  # [B, new] what the prefill feeds
    stats = SpeculationStats()
    total_start = time.perf_counter()
    # generate's own static cache holds the tokens greedy decoding stores; a tree needs slots beside them
    model_kwargs[CACHE_KEY] = with_draft_slots(
        model, model_kwargs.get(CACHE_KEY), NODE_BUCKETS[-1], SLOT_MULTIPLE, batch_size
    )
    given_cache = model_kwargs.get(CACHE_KEY)
    if given_cache is not None:
        check_rollback_cache(given_cache, generation_config.max_length)
    model_inputs = prefill_inputs(model, prompt_ids, model_kwargs)
    if model_inputs[CACHE_KEY] is not given_cache:  # one the model's input preparation made
        check_rollback_cache(model_inputs[CACHE_KEY], generation_config.max_length)
    prompt_positions, position_offsets = _prompt_positions(model_inputs, prompt_ids, prompt_padding, past_length)
    cache = model_inputs[CACHE_KEY]
    verifier = None  # the compiled verification of every round after the prefill (fixed widths), or eager
    if compiles_verification(model, generation_config, cache):
        verifier = CompiledVerifier.for_model(model, generation_config.compile_config)
    cached_tokens = input_ids.shape[1] - num_new  # the rows' first tokens the cache held before the call
    contexts = _draft_contexts(
        model, batch_size, layout, eos_ids, None if prompt_padding is None else prompt_padding[:, -num_new:],
        generation_config.max_length, generation_config.compile_config if verifier is not None else None,
        cached_tokens,
    )  # fmt: skip
    rows = [
        RowState(b, input_ids[b : b + 1], drafter.start(context), SpeculationStats(), committed_length=cached_tokens)
        for b, context in enumerate(contexts)
    ]
    state = DecodeState(rows, prompt_ids, prompt_positions, position_offsets,
                        None if prompt_padding is None else prompt_padding.bool(), cache)  # fmt: skip
    plan, prefill_key = _round_plan(model, generation_config, settings, drafter, rule, layout, verifier, model_inputs,
                                    position_offsets, past_length, num_new, input_ids)  # fmt: skip
    return SpeculativeCall(
        state, plan, list(rows), stats, _Stopwatch(stats, input_ids.device, settings.profile_speculation),
        model_inputs, (prompt_ids, prompt_positions), prefill_key, past_length, cached_tokens,
        generation_config.pad_token_id if generation_config.pad_token_id is not None else (
            eos_ids[0] if eos_ids else None
        ), total_start,
    )  # fmt: skip


def _round_plan(model, generation_config, settings, drafter, rule, layout, verifier, model_inputs, position_offsets,
                past_length: int, num_new: int, input_ids) -> tuple[RoundPlan, tuple | None]:  # fmt: skip
    """What every round reads ([`RoundPlan`]), and the compiled prefill graph this call can use (None: eager)."""
    cache = model_inputs[CACHE_KEY]
    capacity = static_capacity(cache)
    output_hidden = tuple(drafter.hidden_state_layers) if drafter.needs_hidden_states else None
    # A prefix-LM prompt (PaliGemma's token_type_ids: the prompt attends to itself both ways at the prefill) needs
    # the model's own prefill mask, which a tree mask built here would not reproduce: the prefill verifies a chain.
    prefix_attention = model_inputs.get("token_type_ids") is not None
    prefill_key = None
    if verifier is not None and not prefix_attention and position_offsets is None and not past_length:
        prefill_key = verifier.prefill_key(capacity, output_hidden, num_new, input_ids.shape[0])
    return_dict = generation_config.return_dict_in_generate
    plan = RoundPlan(
        max_length=generation_config.max_length,
        rule=rule,
        layout=layout,
        output_hidden=output_hidden,
        window=sliding_window(cache),
        capacity=capacity,
        verifier=verifier,
        compiled_prefill=None if prefill_key is None else verifier.prefill_call(prefill_key),
        # the deepest a round after the prefill can draft: max_new_tokens - 1 (the bonus token takes the last slot)
        buckets=buckets_up_to(_widest_tree(drafter, generation_config.max_length - input_ids.shape[1] - 1, settings)),
        prefix_attention=prefix_attention,
        max_drafts=settings.max_drafts_per_row,
        keep_scores=bool(return_dict and generation_config.output_scores),
        keep_logits=bool(return_dict and generation_config.output_logits),
        sampling=bool(generation_config.do_sample),
    )
    return plan, prefill_key


def settle(call: SpeculativeCall, trees: TreeBatch, output: TargetOutput, logits_processor, stopping_criteria) -> None:
    """A verification's outcome: accept, emit, commit each row's path, tell the drafters (the prefill's and every
    round's)."""
    state, plan = call.state, call.plan
    call.stats.num_batch_forwards += 1
    paths, target_ids, target_scores = accept(state, plan, trees, output, logits_processor)
    emit(state, plan, trees, paths, output, target_scores, stopping_criteria)
    commits = commit_paths(state, trees, paths, output.hidden, target_ids)
    with call.stopwatch.section("draft_seconds"):
        observe(state, commits)


def prefill(model, call: SpeculativeCall, logits_processor, stopping_criteria) -> None:
    """2. The prompt and the drafts known up front, verified in one forward (the model's prepared inputs, images
    included; compiled when an earlier call compiled its graph); then, for a compiled call, every verification width
    compiled (and the next call's prefill graph), before any compiled round."""
    state, plan, stats = call.state, call.plan, call.stats
    with call.stopwatch.section("draft_seconds"):
        proposed = propose(state, plan)
    trees = fit_prefill_trees(proposed, state, plan)
    with call.stopwatch.section("target_seconds"):
        output = verify_trees(model, call.model_inputs, state.pending_ids, state.pending_positions, trees,
                              state.key_valid, plan.output_hidden, sliding_window=plan.window,
                              position_offsets=state.position_offsets, key_length=plan.capacity,
                              forward=plan.compiled_prefill)  # fmt: skip
    stats.compiled_prefills += plan.compiled_prefill is not None
    settle(call, trees, output, logits_processor, stopping_criteria)
    if plan.verifier is not None:  # every width compiled now, and the next call's prefill graph
        stats.compile_seconds = plan.verifier.compile_widths(
            model, state.target_cache, state.pending_ids, state.pending_positions, state.key_valid,
            state.position_offsets, plan.output_hidden, plan.window, plan.capacity, plan.buckets,
        )  # fmt: skip
        if call.prefill_key is not None and plan.compiled_prefill is None:
            stats.compile_seconds += plan.verifier.compile_prefill(
                model, call.prefill_key, call.model_inputs, *call.prompt, trees, plan.output_hidden, plan.window,
                plan.capacity,
            )  # fmt: skip
    drop_finished_rows(call.state, fixed_batch=plan.capacity is not None)


def decode_round(model, call: SpeculativeCall, logits_processor, stopping_criteria) -> None:
    """3. One round after the prefill: the rows' trees verified in one (compiled) forward; finished rows leave."""
    state, plan = call.state, call.plan
    with call.stopwatch.section("draft_seconds"):
        proposed = propose(state, plan)
    trees = fit_trees(proposed, state, plan, call.stats)
    with call.stopwatch.section("target_seconds"):
        output = verify(model, state, plan, trees)
    settle(call, trees, output, logits_processor, stopping_criteria)
    drop_finished_rows(call.state, fixed_batch=call.plan.capacity is not None)


def finish(call: SpeculativeCall, generation_config) -> SpeculativeDecoderOnlyOutput | torch.LongTensor:
    """4. The cache left as greedy decoding would leave it, the statistics gathered, the output."""
    state, stats, all_rows = call.state, call.stats, call.all_rows
    _leave_cache_as_greedy(state.target_cache, all_rows, call.past_length - call.cached_tokens)
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
