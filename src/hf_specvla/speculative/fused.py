"""A compiled round's verification and acceptance as one graph: the target's forward, the logits processors that hide
EOS, the greedy tokens and the search for each row's longest passing path ([`search_paths`]) run in one compiled
call, which returns one packed ``[B, 5 N + 2]`` tensor; the host reads it once and never sees the logits.

Eager, acceptance after the forward is a dozen small kernels per round plus the logits processors (on a tiny model
~0.17 ms of host time a round, a third of the loop's own time between forwards); inside the forward's graph they fuse
into a few kernels and a CUDA graph's replay. It serves the lossless greedy rounds, the ones every preset at
``r = 0`` runs (``exact``): acceptance by token equality ([`ExactMatch`]), greedy decoding (no sampling), logits
processors that only hide EOS below a length (what ``min_length`` / ``min_new_tokens`` add; one set of EOS ids), no
scores or logits returned, 2D positions. Everything else verifies through the compiled model call and accepts
eagerly, as before (see docs/design.md, "The compiled round"): relaxed rules read per-call state (tolerance tables,
motion scales, budgets) that would become graph constants, sampling draws on the host, other processors are
arbitrary code.

The drafters' next drafts (the Jacobi tail, the prior's continuation) and the cache commit stay on the host: a
chain's commit is a length counter (no device work), and the drafts walk each row's tree in Python from the packed
row the host reads anyway.
"""

from __future__ import annotations

import itertools
import os
import types
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from transformers import LogitsProcessorList

from .acceptance import AcceptanceRule, ExactMatch, search_paths
from .compat import CACHE_KEY
from .drafter import read_hidden_states
from .tree import TreeBatch
from .verify import eos_hidden_below

#: EOS ids the graph's mask holds (a fixed shape: one graph per width whatever the call's EOS ids; more is eager)
EOS_SLOTS = 8

_EXACT = ExactMatch()
_FUNCTION_NUMBERS = itertools.count()


def accepting_forward(model, output_hidden: tuple[int, ...] | None) -> Callable:
    """The function compiled into one graph per (batch size, width) (uncompiled here: the [`CompiledVerifier`]
    compiles it with the model's ``CompileConfig`` and keeps it per ``output_hidden``).

    Its arguments: ``inputs`` the model's (ids ``[B, 1 + N]``, positions, the additive tree mask, the cache,
    ``logits_to_keep``); the [`TreeBatch`]'s tensors ``token_ids`` / ``parents`` / ``depths`` / ``is_real`` ``[B, N]``
    and ``ancestor_or_self`` ``[B, N, N]``; ``lengths`` ``[B, 1]`` each row's sequence length (its prompt and emitted
    tokens: the prefix length at its root); ``eos_ids`` ``[EOS_SLOTS]`` and ``eos_below`` (0-dim): EOS is hidden where
    a prefix is shorter. Returns (packed ``[B, 5 N + 2]`` as [`search_paths`] packs it, or ``[B, 2]`` = (bonus, the
    target's token after the root) for a tree of no node; the asked hidden states ``[B, q, n H]`` at every query
    token, or None).
    """
    wants_hidden = bool(output_hidden)

    def verify_and_accept(inputs: dict, token_ids, parents, depths, is_real, ancestor_or_self, lengths, eos_ids,
                          eos_below):  # fmt: skip
        outputs = model(**inputs, output_hidden_states=wants_hidden, return_dict=True)
        scores = outputs.logits  # [B, 1 + N, V] in the model's dtype: its argmax is the float32 copy's
        prefix_lengths = torch.cat([lengths, lengths + 1 + depths], dim=1)  # [B, 1 + N]
        is_eos = torch.zeros(scores.shape[-1], dtype=torch.bool, device=scores.device).index_fill(0, eos_ids, True)
        scores = scores.masked_fill((prefix_lengths < eos_below)[..., None] & is_eos, -torch.inf)
        target_ids = scores.argmax(dim=-1)  # [B, 1 + N]
        if token_ids.shape[1] == 0:  # a plain decoding step: the bonus token is the target's after the root
            packed = torch.cat([target_ids[:, :1], target_ids], dim=1)
        else:
            packed = search_paths(token_ids, ancestor_or_self, parents, depths, is_real, target_ids, None, None, None,
                                  _EXACT, None)  # fmt: skip
        hidden = read_hidden_states(outputs.hidden_states, output_hidden) if wants_hidden else None
        return packed, hidden

    # a code object of its own per (model, hidden states): dynamo keeps graphs and guards per code object, so each
    # function's graphs are told apart by their inputs alone (what the guards skipped after a first round check)
    code = verify_and_accept.__code__
    name = f"verify_and_accept_{next(_FUNCTION_NUMBERS)}"
    return types.FunctionType(code.replace(co_name=name, co_qualname=name), verify_and_accept.__globals__, name,
                              verify_and_accept.__defaults__, verify_and_accept.__closure__)  # fmt: skip


@dataclass(frozen=True)
class GraphAcceptance:
    """One call's accepting verification: the compiled [`accepting_forward`] and the constants it reads.

    Guards: dynamo checks before every call of a compiled function that its graph still fits (each parameter's and
    input's dtype, shape, strides, device; global state): on policy v3 ~0.5 ms a call, a fifth of a round's host time.
    A round's inputs of one *key* (their shapes and dtype, the cache object, the attention implementation, the
    training mode, grad and autocast modes) are met with the full guards once; afterwards the call runs under dynamo's
    ``skip_guard_eval_unsafe`` stance, which checks only the guards that tell this function's graphs apart (the
    widths, the batch sizes). Safe because every graph a round uses is compiled before the first round
    ([`CompiledVerifier.compile_widths`]) and whatever else a guard would catch changes the key (a model cast to
    another dtype, another cache, another attention implementation: its first round is guarded again). Where no
    graph fits (a model whose graphs also depend on the cache's state: a sliding window's length), dynamo refuses
    to compile under that stance, before anything runs: the round then runs guarded (and compiles, as it would
    have), and its key is always guarded afterwards; a cache with other layers than plain static ones (a sliding
    window's, whose length is a constant of its graphs) is always guarded. Set ``HF_SPECVLA_FULL_GUARDS=1`` to keep
    every guard (a check, or a model changed in place in ways no key sees).

    Attributes:
        call: the compiled function (a clock may wrap it, see [`CompiledVerifier.accepting_call`]).
        eos_ids: ``[EOS_SLOTS]`` long, the EOS ids the processors hide (padded by repeating the first).
        eos_below: 0-dim long, the prefix length below which they hide them (0: never).
        model: the target (its attention implementation and training mode are part of the key).
        output_hidden: the hidden states the function returns (which function: part of the key).
        guarded: the keys already run with every guard (the verifier's set: forgotten with its graphs).
        always_guarded: the keys whose rounds keep every guard (the verifier's set).
    """

    call: Callable
    eos_ids: torch.Tensor
    eos_below: torch.Tensor
    model: object = None
    output_hidden: tuple[int, ...] | None = None
    guarded: set = field(default_factory=set)
    always_guarded: set = field(default_factory=set)

    def __call__(self, inputs: dict, trees: TreeBatch, lengths: torch.Tensor):
        """(packed ``[B, 5 N + 2]``, hidden or None) for one verification: ``lengths`` ``[B, 1]`` the rows' sequence
        lengths (an idle row's: any)."""
        arguments = (inputs, trees.token_ids, trees.parents, trees.depths, trees.is_real, trees.ancestor_or_self,
                     lengths, self.eos_ids, self.eos_below)  # fmt: skip
        mask = inputs["attention_mask"]
        key = (self.output_hidden, tuple(mask.shape), mask.dtype, mask.device, tuple(trees.token_ids.shape),
               id(inputs[CACHE_KEY]), getattr(self.model.config, "_attn_implementation", None), self.model.training,
               torch.is_grad_enabled(), torch.is_autocast_enabled())  # fmt: skip
        if key in self.guarded and _may_skip_guards():
            try:
                with torch.compiler.set_stance("default", skip_guard_eval_unsafe=True):
                    return self.call(*arguments)
            except RuntimeError as error:  # no graph fits: raised before the function runs (nothing was done)
                if "skip_guard_eval_unsafe" not in str(error):
                    raise
                self.guarded.discard(key)  # a key whose graphs depend on more (a sliding window's length)
                self.always_guarded.add(key)
        result = self.call(*arguments)
        if key not in self.always_guarded:
            if _only_static_layers(inputs[CACHE_KEY]):
                self.guarded.add(key)
            else:  # a layer with state of its own on the host: its graphs differ by more than their inputs' shapes
                self.always_guarded.add(key)
        return result


def _only_static_layers(cache) -> bool:
    """Whether every layer of ``cache`` is a plain ``StaticLayer``, whose graphs differ by their inputs' shapes alone
    (a static sliding-window layer keeps its length in a Python int, a constant of its graphs: one graph per length,
    which the guards skipped after a first round would not tell apart)."""
    from transformers.cache_utils import StaticLayer

    return all(type(layer) is StaticLayer for layer in getattr(cache, "layers", [None]))


def _may_skip_guards() -> bool:
    """Whether dynamo's stance is its default one (a caller's own stance, e.g. ``force_eager``, is kept) and the
    guards are not asked for (``HF_SPECVLA_FULL_GUARDS=1``)."""
    from torch._dynamo import eval_frame

    stance = getattr(eval_frame, "_stance", None)
    return (
        getattr(stance, "stance", None) == "default"
        and not getattr(stance, "skip_guard_eval_unsafe", True)
        and os.environ.get("HF_SPECVLA_FULL_GUARDS") != "1"
    )


def eos_hiding(logits_processor: LogitsProcessorList, device) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The processors as the graph's EOS mask: (``eos_ids`` ``[EOS_SLOTS]``, ``eos_below`` 0-dim), when every one of
    them only hides EOS below a prefix length ([`eos_hidden_below`]) with one set of at most ``EOS_SLOTS`` ids
    (hidden below the largest length: the union of what they hide); None otherwise (the round accepts eagerly)."""
    id_sets, below = set(), 0
    for processor in logits_processor:
        threshold = eos_hidden_below(processor)
        if threshold is None:
            return None
        id_sets.add(tuple(sorted(set(processor.eos_token_id.reshape(-1).tolist()))))
        below = max(below, int(threshold))
    if len(id_sets) > 1:
        return None
    ids = list(id_sets.pop()) if id_sets else [0]  # no processor: nothing hidden (below 0), any id
    if not ids or len(ids) > EOS_SLOTS:
        return None
    ids = ids + [ids[0]] * (EOS_SLOTS - len(ids))
    return torch.tensor(ids, dtype=torch.long, device=device), torch.tensor(below, dtype=torch.long, device=device)


def accepts_in_graph(rule: AcceptanceRule, sampling: bool, keep_scores: bool, keep_logits: bool,
                     position_offsets) -> bool:  # fmt: skip
    """Whether a compiled call's rounds can accept inside the verification's graph (besides its processors, see
    [`eos_hiding`]): exact acceptance of greedy tokens, nothing of the logits kept, 2D positions."""
    return (
        type(rule) is ExactMatch and not sampling and not keep_scores and not keep_logits and position_offsets is None
    )
