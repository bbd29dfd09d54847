"""A compiled round's verification and acceptance as one graph: the target's forward, the logits processors that hide
EOS, the greedy tokens and the search for each row's longest passing path ([`search_paths`]) run in one compiled
call, which returns one packed ``[B, 5 N + 2]`` tensor; the host reads it once and never sees the logits.

Eager, acceptance after the forward is a dozen small kernels per round plus the logits processors (on a tiny model a
third of the loop's own time between forwards, docs/design.md); inside the forward's graph they fuse into a few
kernels and a CUDA graph's replay. It serves the lossless greedy rounds, the ones every preset at
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

import os
import re
import types
from collections.abc import Callable
from dataclasses import dataclass

import torch
from transformers import LogitsProcessorList

from .acceptance import AcceptanceRule, ExactMatch, search_paths
from .drafter import read_hidden_states
from .tree import TreeBatch
from .verify import eos_hidden_below

#: EOS ids the graph's mask holds (a fixed shape: one graph per width whatever the call's EOS ids; more is eager)
EOS_SLOTS = 8

_EXACT = ExactMatch()


def accepting_forward(model, output_hidden: tuple[int, ...] | None, name: str = "verify_and_accept") -> Callable:
    """The function compiled into one graph per (batch size, width) (uncompiled here: the [`CompiledGraphs`]
    compiles it with the model's ``CompileConfig`` and keeps it per ``output_hidden``), named ``name`` (for logs and
    profiles: its code object is its own whatever its name).

    Its arguments: ``inputs`` the model's (ids ``[B, 1 + N]``, positions, the additive tree mask, the cache,
    ``logits_to_keep``); the [`TreeBatch`]'s tensors ``token_ids`` / ``parents`` / ``depths`` / ``is_real`` ``[B, N]``
    and ``ancestor_or_self`` ``[B, N, N]``; ``lengths`` ``[B, 1]`` each row's sequence length (its prompt and emitted
    tokens: the prefix length at its root); ``eos_ids`` ``[EOS_SLOTS]`` and ``eos_below`` (0-dim): EOS is hidden where
    a prefix is shorter. Returns (packed ``[B, 5 N + 2]`` as [`search_paths`] packs it, or ``[B, 2]`` = (bonus, the
    target's token after the root) for a tree of no node; the asked hidden states ``[B, q, n H]`` at every query
    token, or None).
    """
    wants_hidden = bool(output_hidden)

    def verify_and_accept(
        inputs: dict, token_ids, parents, depths, is_real, ancestor_or_self, lengths, eos_ids, eos_below
    ):
        outputs = model(**inputs, output_hidden_states=wants_hidden, return_dict=True)
        scores = outputs.logits  # [B, 1 + N, V] in the model's dtype: its argmax is the float32 copy's
        prefix_lengths = torch.cat([lengths, lengths + 1 + depths], dim=1)  # [B, 1 + N]
        is_eos = torch.zeros(scores.shape[-1], dtype=torch.bool, device=scores.device).index_fill(0, eos_ids, True)
        scores = scores.masked_fill((prefix_lengths < eos_below)[..., None] & is_eos, -torch.inf)
        target_ids = scores.argmax(dim=-1)  # [B, 1 + N]
        if token_ids.shape[1] == 0:  # a plain decoding step: the bonus token is the target's after the root
            packed = torch.cat([target_ids[:, :1], target_ids], dim=1)
        else:
            packed = search_paths(
                token_ids, ancestor_or_self, parents, depths, is_real, target_ids, None, None, None, _EXACT, None
            )
        hidden = read_hidden_states(outputs.hidden_states, output_hidden) if wants_hidden else None
        return packed, hidden

    # a code object of its own per (model, hidden states): dynamo keeps graphs and guards per code object, so one
    # function's guard filter ([`round_guards`]) and graphs are its own, never another model's or caller's
    code = verify_and_accept.__code__
    return types.FunctionType(
        code.replace(co_name=name, co_qualname=name),
        verify_and_accept.__globals__,
        name,
        verify_and_accept.__defaults__,
        verify_and_accept.__closure__,
    )


#: the arguments of [`accepting_forward`]'s function: the only objects whose guards a compiled round keeps
ROUND_ARGUMENTS = (
    "inputs",
    "token_ids",
    "parents",
    "depths",
    "is_real",
    "ancestor_or_self",
    "lengths",
    "eos_ids",
    "eos_below",
)
#: the guards on the model a compiled round drops ([`round_guards`]): dict-membership checks, most of the model guards'
#: cost (modules' ``__dict__`` key sets, attributes absent from a class), which no change a graph depends on passes
#: unseen by the kept guards (a module's class, tensors, own forward, hooks)
DROPPED_MODEL_GUARDS = frozenset({"DICT_KEYS_MATCH", "DICT_CONTAINS", "DICT_NOT_CONTAINS", "HASATTR", "DICT_VERSION"})
#: the object a guard's source starts from: ``inputs['input_ids']``, ``dict(type(model).__dict__)`` -> inputs, model
_GUARD_ROOT = re.compile(r"^(?:\w+\()*(\w*)")


def round_guards(entries) -> list[bool]:
    """The guards a compiled round keeps (``torch.compile``'s ``guard_filter_fn``, for this function's graphs alone):

    * on its arguments ([`ROUND_ARGUMENTS`]): the inputs' shapes, dtypes and strides, the cache object and its
      layers' host state (a sliding window's length), which tell its graphs apart;
    * the ambient state (guards with no object source): grad mode, the autocast state of every device type, the
      default device, torch-function modes, deterministic algorithms;
    * on the model it closes over, every guard but the dict-membership ones ([`DROPPED_MODEL_GUARDS`]): its modules'
      classes, each parameter's and buffer's dtype, shape, strides, device and aliasing, an instance's own
      ``forward``, its hooks, its scalar attributes and config values.

    Dropped: the dict-membership guards on the model (key sets of its modules' dicts, attributes absent from a class)
    and every guard on globals (the modules of torch and transformers whose code the forward runs): the kept guards
    are a fraction of what dynamo checks a round (docs/design.md, "Guards"). A module
    swapped, wrapped or resized, a parameter of another dtype or shape, a hook, autocast: each fails a kept guard, so
    the round recompiles (a new graph, counted in the recompile budget) instead of running a stale one. The model
    object itself is the [`CompiledGraphs`]'s check (a deep copy gets its own verifier)."""
    return [
        not entry.name
        or (root := _GUARD_ROOT.match(entry.name).group(1)) in ROUND_ARGUMENTS
        or (root == "model" and entry.guard_type not in DROPPED_MODEL_GUARDS)
        for entry in entries
    ]


def full_guards_asked() -> bool:
    """Whether ``HF_SPECVLA_FULL_GUARDS=1`` asks every compiled round to keep all of dynamo's guards (a check of
    [`round_guards`]; read when a round's function is compiled)."""
    return os.environ.get("HF_SPECVLA_FULL_GUARDS") == "1"


@dataclass(frozen=True)
class GraphAcceptance:
    """One call's accepting verification: the compiled [`accepting_forward`] and the constants it reads.

    Attributes:
        call: the compiled function (a clock may wrap it, see [`CompiledGraphs.accepting_call`]); its guards are
            [`round_guards`]'.
        eos_ids: ``[EOS_SLOTS]`` long, the EOS ids the processors hide (padded by repeating the first).
        eos_below: 0-dim long, the prefix length below which they hide them (0: never).
    """

    call: Callable
    eos_ids: torch.Tensor
    eos_below: torch.Tensor

    def __call__(self, inputs: dict, trees: TreeBatch, lengths: torch.Tensor):
        """(packed ``[B, 5 N + 2]``, hidden or None) for one verification: ``lengths`` ``[B, 1]`` the rows' sequence
        lengths (an idle row's: any)."""
        return self.call(
            inputs,
            trees.token_ids,
            trees.parents,
            trees.depths,
            trees.is_real,
            trees.ancestor_or_self,
            lengths,
            self.eos_ids,
            self.eos_below,
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


def accepts_in_graph(
    rule: AcceptanceRule, sampling: bool, keep_scores: bool, keep_logits: bool, position_offsets
) -> bool:
    """Whether a compiled call's rounds can accept inside the verification's graph (besides its processors, see
    [`eos_hiding`]): exact acceptance of greedy tokens, nothing of the logits kept, 2D positions."""
    return (
        type(rule) is ExactMatch and not sampling and not keep_scores and not keep_logits and position_offsets is None
    )
