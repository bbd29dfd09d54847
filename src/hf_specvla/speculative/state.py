"""A speculative call's state: per row ([`RowState`]), per batch ([`DecodeState`]), what every round reads
([`RoundPlan`], decided once before the prefill) and the call itself ([`SpeculativeCall`])."""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import torch
from transformers.cache_utils import Cache

from ..actions.tokenizer import ActionLayout
from .acceptance import AcceptanceRule
from .cache import cache_batch_size
from .drafter import DraftSession
from .stats import SpeculationStats
from .verify import CallVerifier


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
    """Everything one speculative decode carries between rounds (one explicit object; what outlives the call is the
    model's [`SpeculativeDecoder`]'s).

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


class Stopwatch:
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


@dataclass(frozen=True)
class RoundPlan:
    """What every round of one call reads, decided once before the prefill."""

    max_length: int  # generate's max_length: no path drafts past it
    rule: AcceptanceRule
    layout: ActionLayout | None
    output_hidden: tuple[int, ...] | None  # the target's hidden states the drafters read (their layers), or None
    window: int | None  # the target cache's smallest sliding window
    capacity: int | None  # a static cache's slots: trees fit in the free ones
    #: the call's target forwards: its prefill's and its rounds' (eager, compiled at fixed widths, or with the
    #: acceptance in the graph), the compiled graphs they run on and what it compiles ahead
    verifier: CallVerifier
    prefix_attention: bool  # a prefix-LM prompt: the prefill verifies one chain
    max_drafts: int | None  # each row's tree is cut to its first this many nodes (``max_drafts_per_row``), or None
    keep_scores: bool
    keep_logits: bool
    sampling: bool = False  # do_sample: the drafts are verified by speculative sampling ([`sample_trees`])
    #: the decoder's tree structures by shape ([`TreeBatch`]'s ``structures``), or None: made per batch
    tree_structures: dict | None = field(default=None, repr=False, compare=False)


@dataclass
class SpeculativeCall:
    """One ``generate`` call's decode, as [`prepare`] sets it up: the rows' state, what every round reads, the
    prefill's inputs, the statistics."""

    state: DecodeState
    plan: RoundPlan
    all_rows: list[RowState]  # every row of the call, finished or not, in the caller's order
    stats: SpeculationStats
    stopwatch: Stopwatch
    model_inputs: dict  # the prefill's prepared inputs (images, cache, ...)
    prompt: tuple[torch.Tensor, torch.Tensor]  # the prefill's pending ids and positions
    past_length: int  # entries the cache held before the call
    cached_tokens: int  # the rows' first tokens the cache held before the call
    pad_token_id: int | None
    total_start: float
    #: ``(row, new_tokens [n], row stats)`` -> None, called as each row stops (``speculative_generate``'s argument)
    on_row_finished: Callable[[int, torch.Tensor, SpeculationStats], None] | None = None
    decoder: Any = None  # the model's SpeculativeDecoder (not imported: it imports this), what it keeps between calls
