"""Target forwards: the prefill and every verification, each over pending tokens followed by a draft tree, run by
one of three strategies a call chooses once ([`Verification`]).

The prefill's pending tokens are the whole prompt (images included: the model's own input preparation runs once
and the image features are computed once), a later round's pending token is the last emitted one ([`Pending`]).
Tree nodes get depth-based position ids and a 4D tree mask ([`forward_inputs`]); for chains (or no drafts) an eager
forward lets the model build its own causal mask (the cheapest path, identical to a plain decoding step). Each batch
row has its own tree. The strategies, each ``verify(model, pending, trees) -> TargetOutput``:

- [`EagerVerification`]: the model itself;
- [`CompiledVerification`]: a compiled model call (a width's graph, or the prefill's [`PrefillCall`]), the explicit
  mask always, its inputs written into the verifier's buffers, its outputs copied;
- [`FusedVerification`]: the forward and the acceptance as one compiled graph (``speculative.fused``): the target's
  ids and the accepted paths, packed, no logits.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch.nn.utils.rnn import pad_sequence
from transformers import LogitsProcessorList, PreTrainedModel
from transformers.generation.logits_process import (
    MinLengthLogitsProcessor,
    MinNewTokensLengthLogitsProcessor,
    PrefixConstrainedLogitsProcessor,
)

from .cache import cache_length, note_appended
from .compat import CACHE_KEY
from .drafter import read_hidden_states
from .masks import to_additive_mask, tree_verification_allowed
from .tree import TreeBatch


class TargetOutput(NamedTuple):
    """What a verification forward returns.

    Attributes:
        logits: ``[B, 1 + N, V]`` float32 logits after the root (the last pending token) and after each node.
        hidden: ``[B, P + N, H]`` the last hidden state at every pending token and node, or None if not asked.
        accepted: ``[B, 5 N + 2]`` long, the acceptance decided inside the forward's graph (packed as
            [`search_paths`] packs it; see ``speculative.fused``), then ``logits`` is None; None when the round
            accepts after the forward.
    """

    logits: torch.Tensor | None
    hidden: torch.Tensor | None
    accepted: torch.Tensor | None = None


@dataclass(frozen=True)
class InputBuffers:
    """A compiled verification's inputs for one shape (batch size, query tokens, cache slots), written in place
    round after round, so that the compiled graph (and on CUDA its CUDA graph, which then copies nothing in) is fed
    the same tensors every time. Owned by the [`CompiledGraphs`] (``input_buffers``).

    Attributes:
        input_ids: ``[B, P + N]`` long, the pending tokens then the tree's nodes.
        position_ids: ``[B, P + N]`` long, their positions.
        attention_mask: ``[B, 1, P + N, slots]`` the model's dtype, the additive tree mask over the cache's slots.
    """

    input_ids: torch.Tensor
    position_ids: torch.Tensor
    attention_mask: torch.Tensor

    @classmethod
    def empty(cls, batch_size: int, queries: int, slots: int, dtype: torch.dtype, device) -> InputBuffers:
        ids = torch.zeros(batch_size, queries, dtype=torch.long, device=device)
        mask = torch.zeros(batch_size, 1, queries, slots, dtype=dtype, device=device)
        return cls(ids, ids.clone(), mask)

    def tensors(self) -> tuple[torch.Tensor, ...]:
        return self.input_ids, self.position_ids, self.attention_mask


def prefill_inputs(model: PreTrainedModel, input_ids: torch.Tensor, model_kwargs: dict) -> dict:
    """The model's own inputs for a first forward over ``input_ids`` ``[B, S]`` (cache, position ids, encoded
    images), as ``generate`` would build them."""
    return model.prepare_inputs_for_generation(input_ids, is_first_iteration=True, **model_kwargs)


@dataclass(frozen=True)
class Pending:
    """What a verification feeds before the trees: the tokens not yet in the target cache, where they go, which keys
    each row may attend to.

    Attributes:
        model_inputs: the other forward inputs (the cache, and at the prefill the model's prepared inputs).
        ids / positions: ``[B, P]`` the tokens not yet in the cache and their position ids.
        key_valid: ``[B, C + P]`` bool, False at every cached or pending key a row must not attend to (its prompt
            padding, entries of paths another row accepted); None when every key is valid.
        position_offsets: ``[K, B, 1]`` for models with K-component position ids (Qwen2-VL: text, temporal, height,
            width): each component of a generated token is its text position + the offset; the prefill's pending
            tokens keep the model's prepared ``[K, B, P]`` positions (images have their own). None: 2D positions.
        lengths: ``[B, 1]`` the rows' sequence lengths (what an acceptance inside the graph hides EOS by), or None.
    """

    model_inputs: dict
    ids: torch.Tensor
    positions: torch.Tensor
    key_valid: torch.Tensor | None = None
    position_offsets: torch.Tensor | None = None
    lengths: torch.Tensor | None = None

    @property
    def cache(self):
        return self.model_inputs[CACHE_KEY]


def forward_inputs(
    model: PreTrainedModel,
    pending: Pending,
    trees: TreeBatch,
    own_mask: bool,
    key_length: int | None = None,
    buffers: InputBuffers | None = None,
) -> dict:
    """The model's inputs for one forward over ``[pending tokens ; each row's tree nodes]`` on top of the cache (a
    node at depth d gets position ``last + 1 + d``).

    Args:
        own_mask: the model builds its own causal mask (a chain within the sliding window, eagerly): the invalid keys
            go in a 2D mask, as ``generate`` passes them; else the tree mask is built here.
        key_length: the number of keys attention sees when it is not the cached and new entries (a static cache: its
            slots); the explicit mask hides the slots past the new entries.
        buffers: the tensors to write the inputs into (a compiled width's, of this forward's shapes, with
            ``key_length`` slots and 2D positions); None: new tensors.
    """
    num_pending, num_nodes = pending.ids.shape[1], trees.num_nodes
    inputs = dict(pending.model_inputs)
    if buffers is not None and (pending.position_offsets is not None or key_length is None):
        raise ValueError("forward_inputs: input buffers take 2D positions and a static cache's key_length")
    out = {} if buffers is None else {"input_ids": buffers.input_ids, "position_ids": buffers.position_ids}
    inputs["input_ids"] = torch.cat([pending.ids, trees.token_ids], dim=1, out=out.get("input_ids"))
    node_positions = pending.positions[:, -1:] + 1 + trees.depths  # [B, N]
    offsets = pending.position_offsets
    if offsets is None:
        inputs["position_ids"] = torch.cat([pending.positions, node_positions], dim=1, out=out.get("position_ids"))
    else:
        prepared = pending.model_inputs.get("position_ids")
        prefill = prepared if prepared is not None and prepared.ndim == 3 else pending.positions[None] + offsets
        inputs["position_ids"] = torch.cat([prefill, node_positions[None] + offsets], dim=-1)  # [K, B, P + N]
    key_valid = pending.key_valid
    if own_mask:  # (in bf16 an explicit 4D mask selects other kernels than a plain decoding step's)
        if key_valid is None:
            inputs["attention_mask"] = None
        else:
            new_keys = key_valid.new_ones(key_valid.shape[0], num_nodes)
            inputs["attention_mask"] = torch.cat([key_valid, new_keys], dim=1).long()
    else:
        past_length = cache_length(pending.cache)
        allowed = tree_verification_allowed(past_length, num_pending, trees.ancestor_or_self, key_valid)
        if key_length is not None:  # [B, q, key_length]: the free slots after the new entries are hidden
            allowed = torch.nn.functional.pad(allowed, (0, key_length - allowed.shape[-1]), value=False)
        mask = None if buffers is None else buffers.attention_mask  # (a buffer has the model's dtype: no lookup)
        inputs["attention_mask"] = to_additive_mask(allowed, model.dtype if mask is None else mask.dtype, out=mask)
    inputs["logits_to_keep"] = num_nodes + 1
    inputs["use_cache"] = True
    return inputs


#: the node count from which a compiled round's width is a dynamic dimension of one graph ([`mark_width_dynamic`]);
#: below it (a plain decoding step, 0 nodes) a graph of its own (dynamo specialises sizes 0 and 1)
DYNAMIC_WIDTH_FROM = 2


def mark_width_dynamic(inputs: dict, trees: TreeBatch) -> None:
    """Marks a compiled round's node count dynamic in the model's inputs
    (``input_ids`` / ``position_ids`` ``[B, 1 + N]``, the tree mask ``[B, 1, 1 + N, slots]``) and the trees' tensors
    (``[B, N]``, ``ancestor_or_self`` ``[B, N, N]``), and keeps every logit (``logits_to_keep = 0``: the ``1 + N``
    queries, not an int the graph would hold), so that one graph serves every width from [`DYNAMIC_WIDTH_FROM`]
    nodes. ``torch._dynamo.maybe_mark_dynamic``: a model whose forward fixes the query length (a Python branch on it)
    gets a graph of that width, and one per width as before (a graph file keeps several per key, each for its own
    guards). Only for one pending token (a round's) and 2D positions; anything else is left as it is."""
    ids, positions = inputs["input_ids"], inputs["position_ids"]
    if trees.num_nodes < DYNAMIC_WIDTH_FROM or ids.shape[1] != 1 + trees.num_nodes or positions.ndim != 2:
        return
    mark = torch._dynamo.maybe_mark_dynamic
    for tensor in (ids, positions, trees.token_ids, trees.parents, trees.depths, trees.is_real):
        mark(tensor, 1)
    mark(inputs["attention_mask"], 2)
    mark(trees.ancestor_or_self, (1, 2))
    inputs["logits_to_keep"] = 0


class Verification:
    """How a call's target forwards run (chosen once per call, the same interface for the prefill and every round):
    ``verify(model, pending, trees)`` -> [`TargetOutput`], logits ``[B, 1 + N, V]`` after the root and after each
    node and hidden states ``[B, P + N, n H]`` (the ``output_hidden`` layers), or the accepted paths packed.

    Args:
        output_hidden: which of the model's ``hidden_states`` to return (indices; -1 the last), concatenated; None or
            ``()``: none.
        sliding_window: the target's smallest sliding window (None: full attention only). A mask the model builds
            hides keys more than a window away *in cache columns*, which in a batch's rectangle (or with drafts
            appended) are not the row's positions; past it the mask is built here (full attention: the cache's
            sliding layers are held open, see ``cache.open_sliding_windows``).
        key_length: a static cache's slots (the keys attention sees), or None.
    """

    #: whether ``verify`` reads ``pending.lengths`` (the rows' sequence lengths)
    reads_lengths = False

    def __init__(
        self, output_hidden: tuple[int, ...] | None, sliding_window: int | None = None, key_length: int | None = None
    ):
        self.output_hidden, self.sliding_window, self.key_length = output_hidden, sliding_window, key_length

    def verify(self, model: PreTrainedModel, pending: Pending, trees: TreeBatch) -> TargetOutput:
        raise NotImplementedError

    def _read(self, outputs, copy: bool) -> TargetOutput:
        """The forward's logits (float32) and asked hidden states, copied when a compiled call's next replay would
        overwrite them (a CUDA graph's outputs)."""
        logits, hidden = outputs.logits.float(), None
        if self.output_hidden:  # [B, q, n H]: the asked layers' hidden states, concatenated
            hidden = read_hidden_states(outputs.hidden_states, self.output_hidden)
        if copy:
            logits, hidden = logits.clone(), None if hidden is None else hidden.clone()
        return TargetOutput(logits, hidden)


class EagerVerification(Verification):
    """The model itself. A chain (or no drafts) within the sliding window gets the model's own causal mask: the
    kernels a plain decoding step uses (in bf16 an explicit 4D mask selects other kernels, whose rounding can flip a
    near-tied argmax away from plain greedy decoding's)."""

    def verify(self, model: PreTrainedModel, pending: Pending, trees: TreeBatch) -> TargetOutput:
        queries = pending.ids.shape[1] + trees.num_nodes
        window = self.sliding_window
        own_mask = trees.is_causal and (window is None or cache_length(pending.cache) + queries <= window)
        inputs = forward_inputs(model, pending, trees, own_mask, self.key_length)
        outputs = model(**inputs, output_hidden_states=bool(self.output_hidden), return_dict=True)
        note_appended(pending.cache, queries)
        return self._read(outputs, copy=False)


class CompiledVerification(Verification):
    """A compiled model call: every forward gets the explicit tree mask (one mask kind; a graph per width, or one for
    the widths from [`DYNAMIC_WIDTH_FROM`]: [`round_inputs`]), its outputs are copied (a CUDA graph's are overwritten
    by its next replay).

    Args:
        call: the compiled model call (transformers' ``get_compiled_call``), or the compiled prefill's
            [`PrefillCall`].
        verifier: the [`CompiledGraphs`] whose input buffers the forwards write into (2D positions only), or None:
            new tensors each forward (the prefill's dynamic graph).
        dtype: the target's (the buffers' mask dtype).
    """

    def __init__(
        self,
        call: Callable,
        output_hidden,
        sliding_window=None,
        key_length=None,
        verifier=None,
        dtype: torch.dtype | None = None,
    ):
        super().__init__(output_hidden, sliding_window, key_length)
        self.call, self.verifier, self.dtype = call, verifier, dtype

    def buffers(self, pending: Pending, trees: TreeBatch) -> InputBuffers | None:
        """The compiled width's own input tensors for this forward's shape, or None (no verifier, or K-component
        positions)."""
        if self.verifier is None or pending.position_offsets is not None:
            return None
        batch_size, queries = pending.ids.shape[0], pending.ids.shape[1] + trees.num_nodes
        return self.verifier.input_buffers(batch_size, queries, self.key_length, self.dtype, pending.ids.device)

    def round_inputs(self, model: PreTrainedModel, pending: Pending, trees: TreeBatch) -> dict:
        """The forward's inputs, written into the width's buffers; a round's width marked dynamic where the
        verifier's graphs serve every width from [`DYNAMIC_WIDTH_FROM`] with one graph ([`mark_width_dynamic`])."""
        inputs = forward_inputs(model, pending, trees, False, self.key_length, self.buffers(pending, trees))
        if self.verifier is not None and self.verifier.dynamic_widths:
            mark_width_dynamic(inputs, trees)
        return inputs

    def verify(self, model: PreTrainedModel, pending: Pending, trees: TreeBatch) -> TargetOutput:
        inputs = self.round_inputs(model, pending, trees)
        outputs = self.call(**inputs, output_hidden_states=bool(self.output_hidden), return_dict=True)
        note_appended(pending.cache, pending.ids.shape[1] + trees.num_nodes)
        return self._read(outputs, copy=True)


class FusedVerification(CompiledVerification):
    """The forward and the acceptance as one compiled call (``speculative.fused``, a compiled round's): the output
    holds the target's ids and the accepted paths, packed (``TargetOutput.accepted``), no logits; ``pending.lengths``
    the rows' sequence lengths.

    Args:
        acceptance: the call's [`GraphAcceptance`] (``speculative.fused``: the compiled function, as ``.call``, and
            the EOS constants it reads; called as ``acceptance(inputs, trees, lengths) -> (packed, hidden)``).
    """

    reads_lengths = True

    def __init__(
        self,
        acceptance: Callable,
        output_hidden,
        sliding_window=None,
        key_length=None,
        verifier=None,
        dtype: torch.dtype | None = None,
    ):
        super().__init__(acceptance.call, output_hidden, sliding_window, key_length, verifier, dtype)
        self.acceptance = acceptance

    def verify(self, model: PreTrainedModel, pending: Pending, trees: TreeBatch) -> TargetOutput:
        inputs = self.round_inputs(model, pending, trees)
        accepted, hidden = self.acceptance(inputs, trees, pending.lengths)
        note_appended(pending.cache, pending.ids.shape[1] + trees.num_nodes)
        return TargetOutput(None, None if hidden is None else hidden.clone(), accepted.clone())


class CallVerifier:
    """One call's target forwards, chosen once before its prefill: how its prefill verifies and how every round after
    it verifies (each a [`Verification`]: eager, compiled at fixed widths, or fused with the acceptance), the model's
    [`CompiledGraphs`] they run on, and what a compiled call compiles once its prefill has run
    ([`compile_ahead`]: the one place a call triggers compiling its target's graphs).

    Args:
        rounds: how every round after the prefill verifies.
        prefill_verification: how the prefill verifies until its compiled graph exists (eagerly): the compiled
            prefill graph for ``prefill_key`` once a call compiled it (an earlier call, or this verifier's
            [`compile_ahead`], for a later call that keeps it: a session's).
        graphs: the model's compiled graphs under the call's ``CompileConfig``, or None (an eager call).
        prefill_key: the compiled prefill graph this call can run or compiles ahead, or None (its prefill stays
            eager).
        buckets: the widths a compiled round is padded to (up to the drafter's widest tree).
    """

    def __init__(
        self,
        rounds: Verification,
        prefill_verification: Verification,
        graphs=None,
        prefill_key: tuple | None = None,
        buckets: tuple[int, ...] = (),
    ):
        self.rounds, self.prefill_verification, self.graphs = rounds, prefill_verification, graphs
        self.prefill_key, self.buckets = prefill_key, buckets
        self._take_compiled_prefill()

    def _take_compiled_prefill(self) -> None:
        """The compiled prefill graph for ``prefill_key`` becomes the prefill's verification once it exists."""
        prefill_call = None if self.prefill_key is None else self.graphs.prefill_call(self.prefill_key)
        if prefill_call is not None:
            rounds = self.rounds
            self.prefill_verification = CompiledVerification(
                prefill_call, rounds.output_hidden, rounds.sliding_window, rounds.key_length
            )

    @property
    def compiled(self) -> bool:
        """Whether the rounds run compiled graphs at fixed widths (the trees padded to a bucket)."""
        return self.graphs is not None

    @property
    def fused(self) -> bool:
        """Whether a round's acceptance runs inside its graph (the verification reads the rows' lengths)."""
        return self.rounds.reads_lengths

    @property
    def compiled_prefill(self) -> bool:
        """Whether the prefill runs the compiled prefill graph."""
        return isinstance(self.prefill_verification, CompiledVerification)

    def prefill(self, model: PreTrainedModel, prompt: Pending, trees: TreeBatch) -> TargetOutput:
        """The prefill's forward: the prompt and the drafts known up front."""
        return self.prefill_verification.verify(model, prompt, trees)

    def round(self, model: PreTrainedModel, pending: Pending, trees: TreeBatch) -> TargetOutput:
        """A round's forward: the pending token and the rows' trees."""
        return self.rounds.verify(model, pending, trees)

    def compile_ahead(self, model: PreTrainedModel, following: Pending, prompt: Pending, trees: TreeBatch) -> float:
        """After the prefill of a compiled call: every round width compiled (``following``: the next round's pending
        tokens, as it feeds them) and the next call's prefill graph (``prompt`` and ``trees``: this call's prefill,
        fed once more), so that no graph compiles mid-episode; a compiled prefill becomes this verifier's (a later
        call that keeps it: a session's). Returns the seconds it took (0: eager, or all held)."""
        if self.graphs is None:
            return 0.0
        seconds = self.graphs.compile_widths(model, self.rounds, following, self.buckets)
        if self.prefill_key is not None and not self.compiled_prefill:
            seconds += self.graphs.compile_prefill(model, self.prefill_key, self.rounds, prompt, trees)
            self._take_compiled_prefill()  # a later call that keeps this verifier (a session's) prefills through it
        return seconds


def apply_processors(logits_processor: LogitsProcessorList, input_ids: torch.Tensor, scores: torch.Tensor):
    """``logits_processor(input_ids, scores)`` without the list's per-call ``inspect.signature`` of every processor
    (the list only needs it to forward extra kwargs, and none are passed here)."""
    for processor in logits_processor:
        scores = processor(input_ids, scores)
    return scores


def eos_hidden_below(processor) -> int | None:
    """The prefix length below which ``processor`` sets its EOS scores to -inf, when that is all it does (transformers'
    ``MinLengthLogitsProcessor`` and ``MinNewTokensLengthLogitsProcessor``, what ``min_length`` / ``min_new_tokens``
    add); None for any other processor, subclasses included (they may do more)."""
    if type(processor) is MinLengthLogitsProcessor:
        return processor.min_length
    if type(processor) is MinNewTokensLengthLogitsProcessor:
        return processor.prompt_length_to_skip + processor.min_new_tokens
    return None


def target_greedy_ids(
    logits_processor: LogitsProcessorList, sequences: Sequence[torch.Tensor], trees: TreeBatch, logits: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Every row's greedy token after its root and after each of its nodes, with the logits processors applied.

    The processors at row b's node i see row b's sequence + the tokens on node i's path: exactly what plain greedy
    decoding would pass them had that path been generated. The leading processors that only hide EOS below a
    length (``min_length``, ``min_new_tokens``: [`eos_hidden_below`]) are applied to every (row, node) at once as
    the mask they are; every later processor runs once per prefix length over the (row, node)s of that length (the
    prefill: one call per depth for the whole batch), except processors that read the batch index
    (``prefix_allowed_tokens_fn``, batch size 1 only), which see each node alone as batch row 0. Order is kept, so
    the scores equal the list applied node by node.

    Args:
        sequences: per row, ``[1, L_b]`` the tokens emitted so far (ending with the root).
        trees: the verified trees, padded to N nodes.
        logits: ``[B, 1 + N, V]`` the verification's logits (column 0: after the root; 1 + i: after node i).
    Returns:
        (target_ids ``[B, 1 + N]``, scores ``[B, 1 + N, V]``); filler nodes' scores are never read (raw logits, or
        EOS hidden with every other column).
    """
    if len(logits_processor) == 0:
        return logits.argmax(dim=-1), logits
    device = logits.device
    # the shortest and longest prefix any scored (row, column) has, from the host's lengths and depth bounds
    shortest = min(s.shape[1] for s in sequences)
    longest = max(s.shape[1] + _depth_bound(tree) for s, tree in zip(sequences, trees.trees))
    scores, prefix_lengths, scored = logits, None, None
    num_masks = 0
    for processor in logits_processor:
        threshold = eos_hidden_below(processor)
        if threshold is None:
            break
        num_masks += 1
        if shortest >= threshold:  # no prefix is below it: the processor changes nothing
            continue
        eos_ids = processor.eos_token_id.to(device).reshape(-1)  # [E]
        scores = logits.clone() if scores is logits else scores
        if longest < threshold:  # every prefix is below it: EOS hidden everywhere (filler columns are never read)
            scores[..., eos_ids] = -torch.inf
            continue
        if prefix_lengths is None:
            prefix_lengths, scored = _prefix_lengths(sequences, trees)
        hidden = (prefix_lengths < threshold) & scored  # [B, 1 + N]
        scores[..., eos_ids] = torch.where(hidden[..., None], -torch.inf, scores[..., eos_ids])
    remaining = logits_processor[num_masks:]
    if remaining:
        scores = logits.clone() if scores is logits else scores
        if prefix_lengths is None:
            prefix_lengths, scored = _prefix_lengths(sequences, trees)
        _apply_by_prefix_length(remaining, sequences, trees, prefix_lengths, scored, scores)
    return scores.argmax(dim=-1), scores


def _prefix_lengths(sequences: Sequence[torch.Tensor], trees: TreeBatch) -> tuple[torch.Tensor, torch.Tensor]:
    """(``[B, 1 + N]`` each (row, column)'s prefix length, ``[B, 1 + N]`` bool whether it is scored: not filler)."""
    device = trees.token_ids.device
    lengths = torch.tensor([s.shape[1] for s in sequences], device=device)[:, None]  # [B, 1]
    prefix_lengths = torch.cat([lengths, lengths + 1 + trees.depths], dim=1)
    scored = torch.cat([trees.is_real.new_ones(len(sequences), 1), trees.is_real], dim=1)
    return prefix_lengths, scored


def _depth_bound(tree) -> int:
    """At most how many tokens a node of ``tree`` adds to its row's prefix (its depth + 1), known on the host
    without reading the device (a tree drafted there tells its bound)."""
    if tree.num_nodes == 0:
        return 0
    return tree.max_depth if tree.knows_structure() else (tree.depth_bound or tree.num_nodes)


def _apply_by_prefix_length(
    logits_processor, sequences: Sequence[torch.Tensor], trees: TreeBatch, prefix_lengths, scored, scores
) -> None:
    """``scores`` ``[B, 1 + N, V]`` through ``logits_processor`` in place, one call per prefix length (see
    [`target_greedy_ids`])."""
    batch_size, device = scores.shape[0], scores.device
    lengths = prefix_lengths[:, :1]  # [B, 1]
    sequence_table = pad_sequence([s[0] for s in sequences], batch_first=True)  # [B, L_max]
    path_tokens = trees.path_token_ids  # [B, N, D]
    path_tokens = torch.cat([path_tokens.new_zeros(batch_size, 1, path_tokens.shape[2]), path_tokens], dim=1)
    by_row = any(isinstance(p, PrefixConstrainedLogitsProcessor) for p in logits_processor)
    # which (row, column) has which prefix length, from the host's lengths and tree depths (no read of the device)
    by_length: dict[int, tuple[list[int], list[int]]] = {}
    for b, (sequence, tree) in enumerate(zip(sequences, trees.trees)):
        for column, length in enumerate([0] + [1 + depth for depth in tree.depth_list]):
            rows_of, columns_of = by_length.setdefault(sequence.shape[1] + length, ([], []))
            rows_of.append(b)
            columns_of.append(column)
    for length in sorted(by_length):
        rows, columns = (torch.tensor(v, dtype=torch.long, device=device) for v in by_length[length])  # [n] each
        # each (row, column)'s prefix: the row's sequence, then the node's path tokens
        offsets = torch.arange(length, device=device)[None]  # [1, length]
        row_lengths = lengths[rows]  # [n, 1]
        source = torch.cat([sequence_table[rows], path_tokens[rows, columns]], dim=1)  # [n, L_max + D]
        index = torch.where(offsets < row_lengths, offsets, sequence_table.shape[1] + offsets - row_lengths)
        input_ids = source.gather(1, index)  # [n, length]
        groups = [[i] for i in range(len(rows))] if by_row else [slice(None)]
        for group in groups:
            scores[rows[group], columns[group]] = apply_processors(
                logits_processor, input_ids[group], scores[rows[group], columns[group]]
            )
