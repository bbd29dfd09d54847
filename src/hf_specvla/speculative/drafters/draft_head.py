"""Drafting with an EAGLE-style [`DraftHead`]: a chain (EAGLE-1) or a dynamic tree (EAGLE-2).

EAGLE-2's dynamic tree (Li et al. 2024, "EAGLE-2: Faster Inference of Language Models with Dynamic Draft Trees";
``topK_genrate`` in SafeAILab/EAGLE), as Spec-VLA uses it, expanded by [`expand_tree`] (``eagle_tree.py``):

* **expand**: the root's feature gives the ``top_k`` most probable first tokens. At each further level the
  ``top_k`` frontier nodes are fed to the head in one forward (a tree mask: each sees the committed cache, its
  ancestors and itself); each yields its ``top_k`` children, scored by parent score + child log-probability. The
  next frontier is the best children by cumulative score.
* **re-rank**: of every node created, the ``total_tokens`` with the highest cumulative score form the tree.

Deviation from EAGLE-2: the head's own greedy path (the top-1 child at every level, i.e. the chain) is a
*backbone*: always expanded, always kept, and the rest of the budget is filled by cumulative score. Without it
the re-ranking may spend the budget on shallow alternatives and drop the deep greedy nodes, so that a tree
accepts less than the plain chain: measured on the toy target (7-token actions), top_k=4 / 24 nodes needed 2.83
target forwards per action against the chain's 2.00. With the backbone a tree accepts at least what the chain of
the same depth accepts.

A chain of k tokens is the same procedure with ``top_k=1``, ``depth=k``, ``total_tokens=k``.

Defaults ([`DraftTreeConfig`]): the Spec-VLA / EAGLE-2 code uses ``total_tokens=50, depth=4, top_k=8`` for
OpenVLA's 7-token actions on a GPU, where verifying 50 tokens costs about as much as verifying one. Here the
defaults are ``total_tokens=24, depth=6, top_k=4``: ``depth`` 6 covers the 6 tokens left of a 7-token action after
the prefill (the loop caps every tree at the tokens still to come, so a 4-token action drafts at most 2 levels
after the prefill), and a smaller budget because on a CPU each verified token costs measurable time.

Compiled drafting: when the target verifies through its compiled call (``DraftContext.graphs``: a static
cache, batch 1), the head gets a static cache of its own (the call's ``max_length`` + the tree's entries, rounded up
to ``SLOT_MULTIPLE`` slots) and each round runs as one compiled graph (``torch.compile`` with the target's
``CompileConfig``), compiled before the call's first compiled round: one graph, expanded to that round's depth (the
deepest of the call); a shallower round passes its depth as data and gets the shallower expansion's tree. The round's
catch-up forward (the pairs the target committed, as many as were accepted) is in the same graph, padded to
``depth + 1`` pairs (the prompt's pairs after the prefill are fed eagerly, but for the last ones).

Head v3 (``head_block.py``): a head with ``draft_mode="block"`` drafts each round with one forward (the pairs the
target committed and mask queries after them), eagerly on the session's cache (static in a compiled call): one head
forward, where the chain's compiled round fuses several; a head with ``prefill_drafts`` drafts the whole action before
the prefill in one forward without a cache, compiled in a compiled call (one graph per prompt length).

Per-call state (the head's KV cache, the pairs not yet fed) lives in the session, never on the model.
Invariant: after a catch-up the head's cache holds exactly the target's committed positions, each computed from
the target's true hidden state; tree-drafting entries are dropped at the end of every proposal.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import torch
from transformers.cache_utils import DynamicCache, StaticCache

from ..cache import set_static_length, truncate_cache
from ..compiled import compile_settings, rounded_slots
from ..drafter import Commit, DraftContext, Drafter, DraftRound, DraftSession
from ..masks import causal_allowed, sequence_key_padding, to_additive_mask
from ..modeling_draft_head import DraftHead, DraftScorer, TargetHandles
from ..tree import DraftTree
from .eagle_tree import catch_up_and_expand, expand_tree, num_head_entries
from .head_block import block_round, product_tree

logger = logging.getLogger(__name__)


@dataclass
class DraftTreeConfig:
    """EAGLE-2 dynamic tree settings (see module docstring for the defaults' reasons).

    Args:
        top_k: children expanded per node, and frontier width per level.
        depth: levels drafted (the longest path); capped each round by the tokens still to come.
        total_tokens: nodes kept after re-ranking (the tree the target verifies).
    """

    top_k: int = 4
    depth: int = 6
    total_tokens: int = 24

    def __post_init__(self):
        for name in ("top_k", "depth", "total_tokens"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"DraftTreeConfig.{name} must be an int >= 1, got {value!r}")
        if self.total_tokens < self.depth:
            raise ValueError(
                f"DraftTreeConfig.total_tokens={self.total_tokens} cannot hold a path of depth={self.depth}: "
                f"use total_tokens >= depth"
            )


def padded_pairs(tree: DraftTreeConfig) -> int:
    """The pairs a compiled round's catch-up feeds (padded): the pending token and the longest accepted path."""
    return tree.depth + 1


def head_cache_slots(max_length: int, tree: DraftTreeConfig) -> int:
    """The slots of a draft head's static cache in a compiled call of ``max_length`` (the prompt and the new tokens):
    those, the padded catch-up pairs ([`padded_pairs`]) and the entries one expansion writes (``num_head_entries``),
    rounded up (``compiled.rounded_slots``). What the head's session allocates and what a server plans for."""
    return rounded_slots(max_length + padded_pairs(tree) + num_head_entries(tree.top_k, tree.depth))


def embed_tokens(handles: TargetHandles, token_ids: torch.Tensor) -> torch.Tensor:
    """Target embeddings ``[B, q, H]`` of ``token_ids`` ``[B, q]``; ids past the embedding (e.g. image
    placeholders of some VLMs) embed as id 0: the hidden state at that position carries the content."""
    num_embeddings = handles.embed_tokens.weight.shape[0]
    safe_ids = torch.where(token_ids < num_embeddings, token_ids, torch.zeros_like(token_ids))
    return handles.embed_tokens(safe_ids)


class DraftHeadDrafter(Drafter):
    """Drafts with a [`DraftHead`]: a chain of ``num_draft_tokens`` (default: the head's config), or an EAGLE-2
    dynamic tree when ``tree`` is given.

    Example:
        ```python
        drafter = DraftHeadDrafter(draft_head, tree=DraftTreeConfig(top_k=4, depth=6, total_tokens=24))
        model.generate(**inputs, assistant_model=drafter, max_new_tokens=7)
        ```
    """

    needs_hidden_states = True

    def __init__(self, draft_head: DraftHead, num_draft_tokens: int | None = None, tree: DraftTreeConfig | None = None):
        if not isinstance(draft_head, DraftHead):
            raise TypeError(f"DraftHeadDrafter needs a hf_specvla.DraftHead, got {type(draft_head).__name__}")
        if tree is not None and not isinstance(tree, DraftTreeConfig):
            raise TypeError(f"tree must be a DraftTreeConfig, got {type(tree).__name__}")
        if tree is not None and num_draft_tokens is not None:
            raise ValueError("give num_draft_tokens (a chain) or tree=DraftTreeConfig(...) (a tree), not both")
        if num_draft_tokens is not None and (
            isinstance(num_draft_tokens, bool) or not isinstance(num_draft_tokens, int) or num_draft_tokens < 1
        ):
            raise ValueError(
                f"num_draft_tokens must be an int >= 1 (tokens drafted per verification), got {num_draft_tokens!r}"
            )
        self.draft_head = draft_head
        self.hidden_state_layers = draft_head.config.hidden_state_layers
        # a head drafting before the prefill from the encoded images reads the prompt as the target's LM does
        self.needs_prompt_embeddings = draft_head.config.prefill_image_features
        #: ``[D]`` the robot's previous action's bins (see [`with_previous_action`]); None: none given
        self.previous_bins: torch.Tensor | None = None
        if tree is None:
            k = num_draft_tokens or draft_head.config.num_draft_tokens
            tree = DraftTreeConfig(top_k=1, depth=k, total_tokens=k)
            self.name = "head-chain"
        else:
            self.name = "head-tree"
        self.tree_config = tree
        self.action_layout = draft_head.config.action_layout()
        self._architecture: str | None = None  # the head's config as JSON: what its compiled round depends on

    def with_previous_action(self, previous_action: Sequence[int] | None) -> DraftHeadDrafter:
        """This drafter for a robot whose previous action was ``previous_action`` (``action_dim`` action token ids):
        a head with ``previous_action_input`` reads it (a copy sharing this drafter's caches and compiled graphs); any
        other head ignores it (``self``). None: no previous action (an episode's first step), as when never given.

        Raises:
            ValueError: not ``action_dim`` action token ids of the head's layout.
        """
        if previous_action is None or not self.draft_head.config.previous_action_input:
            return self
        conditioned = copy.copy(self)
        conditioned.previous_bins = self.draft_head.previous_action_bins(previous_action, self.draft_head.device)
        return conditioned

    def static_cache(self, decoder, key_length: int) -> StaticCache:
        """The head's static cache of ``key_length`` slots, emptied: kept by the target's ``decoder`` (its
        ``SpeculativeDecoder``; one per head architecture, size, dtype and device), reused by every later compiled
        call (as ``generate`` reuses its own; its buffers keep their addresses for compiled graphs)."""
        weights = self.draft_head.fuse.weight
        key = ("draft head", self._architecture_json(), key_length, weights.dtype, weights.device)
        config = self.draft_head.config  # as transformers' caches read it, once per cache made
        return decoder.static_cache(key, lambda: StaticCache(config=config.to_llama_config(), max_cache_len=key_length))

    def _architecture_json(self) -> str:
        """The head's config as JSON: what its caches and compiled round depend on (made once)."""
        if self._architecture is None:
            self._architecture = self.draft_head.config.to_json_string()
        return self._architecture

    def round_graph_key(self, compile_config, key_length: int, graph_depth: int) -> tuple:
        """What a compiled round's graph depends on: heads of one architecture share it (parameters are graph
        inputs), whatever their weights."""
        tree = (self.tree_config.top_k, self.tree_config.depth, self.tree_config.total_tokens)
        weights = self.draft_head.fuse.weight
        return (
            "draft-head round",
            self._architecture_json(),
            weights.dtype,
            weights.device,
            compile_settings(compile_config),
            key_length,
            tree,
            graph_depth,
        )

    def max_tree_nodes(self, max_depth: int) -> int | None:
        return self.tree_config.total_tokens

    def start(self, context: DraftContext) -> DraftSession:
        handles = self.draft_head.target_handles(context.model)
        scorer = self.draft_head.scorer(handles.lm_head, context.eos_token_ids)
        return _DraftHeadSession(self, handles, scorer, context)

    def settings_key(self) -> tuple | None:
        """The head (by identity: its weights) and the tree; None once conditioned on a robot's previous action."""
        if self.previous_bins is not None:
            return None
        tree = self.tree_config
        return id(self.draft_head), self.name, tree.top_k, tree.depth, tree.total_tokens

    def __repr__(self) -> str:
        return f"DraftHeadDrafter({self.name}, {self.tree_config})"


class _DraftHeadSession(DraftSession):
    """One row's drafting with the head. On a compiled target (``context.compile_config``, batch 1, no padding) the
    head's cache is static and each round (catch-up + expansion) runs as one compiled graph, compiled right after the
    call's prefill ([`warm_up`]), as is a block drafted before the prefill (which runs eagerly at its shape's first
    call, as the target's prefill does); otherwise the same expansion runs eagerly on a ``DynamicCache``."""

    def __init__(self, drafter: DraftHeadDrafter, handles: TargetHandles, scorer: DraftScorer, context: DraftContext):
        self.drafter = drafter
        self.head, self.config, self.name = drafter.draft_head, drafter.tree_config, drafter.name
        self.scorer, self.prompt_padding = scorer, context.prompt_padding
        self.prompt_embeddings = context.prompt_embeddings  # [1, S, H] or None (see DraftContext)
        self.embed = partial(embed_tokens, handles)
        self.compile_config = context.compile_config if context.prompt_padding is None else None
        self.key_length: int | None = None  # the static cache's slots (every mask spans them), None: dynamic
        if self.compile_config is None:
            self.cache = DynamicCache()
        else:
            self.key_length = head_cache_slots(context.max_length, self.config)
            self.cache = drafter.static_cache(context.decoder, self.key_length)
            # the call's compiled graphs own the head's graphs too (one owner per model and compile settings)
            self.compiled = context.graphs
            self.compiled_round = self.compiled.compiled_function(catch_up_and_expand, graphs=1)
        self.graph_depth: int | None = None  # the depth this call's compiled rounds expand to (its first round's)
        #: the first round's padded pairs and committed entries, made by [`warm_up`] (which compiled on them)
        self.first_round_inputs: tuple | None = None
        #: a block drafted eagerly before the prefill, to compile at [`warm_up`]: (graph key, its arguments)
        self.block_to_compile: tuple | None = None
        self.cache_length = 0  # committed entries in self.cache
        self.cached_tokens = context.cached_tokens  # the row's tokens the target held before the call (not fed here)
        self.unfed: list[Commit] = []  # commits whose (token, hidden) pairs the head has not seen yet
        self.root_feature: torch.Tensor | None = None  # [1, 1, H] estimate of the hidden state at the root
        self.num_forwards = 0
        # a head that reads the previous action, from the prefill on: its bins ([D]; "none" when not given) and the
        # position of the first generated token (0-dim), which tell each input's bin (DraftHead.slot_bins)
        self.previous: tuple[torch.Tensor, torch.Tensor] | None = None

    @property
    def num_padded_pairs(self) -> int:
        """The pairs a compiled round's catch-up feeds (padded): the pending token and the longest accepted path."""
        return padded_pairs(self.config)

    def observe(self, commit: Commit) -> None:
        if commit.target_hidden is None:
            raise ValueError("a draft head needs the target's hidden states in every Commit")
        self.unfed.append(commit)
        self.root_feature = None

    def _take_unfed(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, int]:
        """The pairs (token x[p+1], true hidden h[p]) at positions p of every commit not yet seen (``[1, q]``,
        ``[1, q, H]``, ``[1, q]``), and the committed entries once they are fed."""
        tokens = torch.cat([c.next_token_ids for c in self.unfed], dim=1)
        hidden = torch.cat([c.target_hidden for c in self.unfed], dim=1)
        positions = torch.cat([c.positions for c in self.unfed], dim=1)
        committed = self.unfed[-1].cache_length - self.cached_tokens
        self.unfed = []
        return tokens, hidden, positions, committed

    def _feed(self, tokens: torch.Tensor, hidden: torch.Tensor, positions: torch.Tensor) -> None:
        """Feeds pairs after the committed entries in one eager forward (the previous proposal's entries dropped)."""
        truncate_cache(self.cache, self.cache_length)
        q_len = tokens.shape[1]
        padding = sequence_key_padding(self.prompt_padding, self.cache_length + q_len)
        allowed = causal_allowed(q_len, self.cache_length, hidden.device, padding)  # [1, q, past + q]
        if self.key_length is not None:  # a static cache: its free slots are masked
            free = allowed.new_zeros(1, q_len, self.key_length - allowed.shape[-1])
            allowed = torch.cat([allowed, free], dim=-1)
        mask = to_additive_mask(allowed, hidden.dtype)
        features = self.head(self.embed(tokens), hidden, positions, mask, self.cache, self._previous_bins(positions))
        self.num_forwards += 1
        self.cache_length += q_len
        self.root_feature = features[:, -1:]

    def _previous_bins(self, positions: torch.Tensor) -> torch.Tensor | None:
        """``[1, q]`` the previous-action bins of inputs at ``positions`` (None: a head that does not read them)."""
        return None if self.previous is None else self.head.slot_bins(*self.previous, positions)

    def propose(self, draft_round: DraftRound) -> DraftTree:
        depth = min(self.config.depth, draft_round.max_depth)
        if draft_round.at_prefill and self.head.config.previous_action_input:
            bins = self.drafter.previous_bins
            bins = self.head.no_previous_action(self.head.device) if bins is None else bins
            self.previous = (bins, (draft_round.root_position.reshape(()) + 1).clone())
        if draft_round.at_prefill and self.head.config.prefill_drafts and depth >= 1:
            return self._prefill_block(draft_round, depth)
        if draft_round.at_prefill or depth < 1:
            return DraftTree.empty(draft_round.sequence.device)
        if self.head.config.draft_mode == "block":
            return self._block(depth) if self.unfed else DraftTree.empty(draft_round.sequence.device)
        root_position = _root_position(draft_round)
        if self.key_length is not None and self.graph_depth is None and self.unfed:
            self.warm_up(draft_round)  # a wrapping session that did not pass the call's warm-up on: compiled now
        if self.key_length is not None and (self.unfed or self.first_round_inputs is not None):
            token_ids, parents = self._compiled_round(depth, root_position)
        else:
            if self.unfed:
                tokens, hidden, positions, committed = self._take_unfed()
                self._feed(tokens, hidden, positions)
                if self.cache_length != committed:
                    raise RuntimeError(f"draft head cache out of step: {self.cache_length} entries, {committed} kept")
            if self.root_feature is None:  # proposed twice without a new commit after a compiled round
                return DraftTree.empty(draft_round.sequence.device)
            token_ids, parents = self._expand(depth, root_position)
        return self._tree(token_ids, parents, depth)

    # ------------------------------------------------------------------ head v3: blocks (head_block.py)
    def _prefill_block(self, draft_round: DraftRound, depth: int) -> DraftTree:
        """The whole action drafted before the prefill, in one head forward over the prompt's tokens (as pairs with a
        missing hidden state) and ``depth - 1`` mask queries, without a cache (the head's own cache starts with the
        target's true hidden states after the prefill). Compiled when the target's rounds are (one graph per prompt
        length: a policy has one), else eager."""
        sequence = draft_round.sequence  # [1, S]
        num_pairs = sequence.shape[1] - 1
        if num_pairs < 1:  # a one-token prompt: nothing to read
            return DraftTree.empty(sequence.device)
        start = draft_round.root_position.reshape(1, 1) - num_pairs  # the first token's position
        positions = start + torch.arange(num_pairs, device=sequence.device)[None]  # [1, S - 1]
        key_valid = None
        if self.prompt_padding is not None:  # the fed prompt's padding, aligned with the sequence's end
            known = self.prompt_padding[0].bool()
            key_valid = torch.cat([known.new_ones(max(sequence.shape[1] - known.shape[0], 0)), known])[:num_pairs]
        pair_embeddings = None  # the pairs' tokens x[p + 1] embedded by the head, or as the target's LM reads them
        if self.head.config.prefill_image_features:
            if self.prompt_embeddings is None or self.prompt_embeddings.shape[1] != sequence.shape[1]:
                raise ValueError(
                    "this draft head reads the prompt's encoded images before the prefill (prefill_image_features): "
                    "its drafter needs DraftContext.prompt_embeddings of the row's whole prompt"
                )
            pair_embeddings = self.prompt_embeddings[:, 1:]
        arguments = (
            self.head,
            self.embed,
            self.scorer,
            sequence[:, 1:],
            None,
            positions,
            num_pairs,
            None,
            0,
            depth - 1,
            self.config.top_k,
        )  # no cache: the block's entries are never kept
        settings = dict(key_valid=key_valid, previous=self.previous, pair_embeddings=pair_embeddings)
        key = None  # one graph per prompt length and depth
        if self.compile_config is not None:
            key = ("draft-head prefill block", self.drafter.round_graph_key(self.compile_config, num_pairs, depth))
        if key is not None and key in self.compiled.drafting_compiled:
            table = self.compiled.functions[block_round](*arguments, **settings)
        else:  # eager; a compiled call's graph compiled on the same inputs right after the prefill ([`warm_up`])
            table = block_round(*arguments, **settings)
            if key is not None:
                self.block_to_compile = (key, arguments, settings)
        self.num_forwards += 1
        return self._block_tree(table, depth)

    def _block(self, depth: int) -> DraftTree:
        """A block round: the pairs the target committed and ``depth - 1`` mask queries in one head forward (eager,
        on the session's cache, dynamic or static); the queries' entries are dropped afterwards."""
        tokens, hidden, positions, committed = self._take_unfed()
        truncate_cache(self.cache, self.cache_length)
        key_valid = sequence_key_padding(self.prompt_padding, self.cache_length + tokens.shape[1])
        try:
            table = block_round(
                self.head,
                self.embed,
                self.scorer,
                tokens,
                hidden,
                positions,
                tokens.shape[1],
                self.cache,
                self.cache_length,
                depth - 1,
                self.config.top_k,
                key_length=self.key_length,
                key_valid=None if key_valid is None else key_valid[0],
                previous=self.previous,
            )
        finally:
            truncate_cache(self.cache, committed)
        self.num_forwards += 1
        self.cache_length = committed
        if self.key_length is not None:
            set_static_length(self.cache, committed)
        return self._block_tree(table, depth)

    def _block_tree(self, table: torch.Tensor, depth: int) -> DraftTree:
        """``[depth, k]`` per-position candidates -> the chain of top-1 tokens, or their [`product_tree`]."""
        if self.config.top_k == 1 or table.shape[1] == 1:
            return DraftTree.chain(table[:, 0], self.name)
        picks, parents = product_tree(depth, table.shape[1], self.config.total_tokens)
        index = torch.tensor(picks, device=table.device)
        token_ids = table.flatten().index_select(0, index)
        parent_ids = torch.tensor(parents, device=table.device)
        return DraftTree(token_ids, parent_ids, [self.name] * len(picks), list(parents))

    def _tree(self, token_ids: torch.Tensor, parents: torch.Tensor, depth: int) -> DraftTree:
        """The drafted tree, its structure left on the device (nothing read back while drafting); a chain's is known
        on the host (node i below node i - 1): one candidate per level, or a budget the backbone fills."""
        num_nodes = token_ids.shape[0]
        if self.config.top_k == 1 or self.config.total_tokens <= depth:
            return DraftTree.chain(token_ids, self.name)
        return DraftTree(
            token_ids, parents, [self.name] * num_nodes, structure_on_device=True, depth_bound=min(depth, num_nodes)
        )

    def _expand(self, depth: int, root_position: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One eager expansion ([`expand_tree`]) below the root; the head's cache keeps only its committed entries."""
        padding = sequence_key_padding(self.prompt_padding, self.cache_length)
        try:
            self.num_forwards += depth - 1
            return expand_tree(
                self.head,
                self.embed,
                self.scorer,
                self.root_feature,
                root_position,
                self.cache,
                self.cache_length,
                None if padding is None else padding[0],
                self.config.top_k,
                depth,
                self.config.total_tokens,
                key_length=self.key_length,
                previous=self.previous,
            )
        finally:
            truncate_cache(self.cache, self.cache_length)

    def warm_up(self, draft_round: DraftRound) -> None:
        """Right after a compiled call's prefill: the block drafted eagerly before it compiled on the same inputs
        (one graph per prompt length), and the call's round graph compiled on the first round's inputs (the pairs
        the prefill committed: padded, any beyond the padding fed eagerly first, as that round would), kept for it.

        One round graph a call: expanded to the deepest any of its rounds can go (after a prefill that emitted one
        token, whatever the prefill accepted: the same for every call of a prompt length); a shallower round passes
        its depth as data ([`_compiled_round`])."""
        if self.key_length is None:  # an eager head
            return
        if self.block_to_compile is not None:
            key, arguments, settings = self.block_to_compile
            self.block_to_compile = None
            self._compile(
                key,
                lambda: self.compiled.compiled_function(block_round, graphs=1)(*arguments, **settings),
                "block before the prefill",
            )
        depth = min(self.config.depth, draft_round.max_depth)
        if self.head.config.draft_mode == "block" or depth < 1 or not self.unfed or self.graph_depth is not None:
            return
        self.first_round_inputs = self._round_inputs()
        if self.first_round_inputs is None:  # nothing left for the graph (a one-token prompt): eager rounds
            return
        self.graph_depth = min(self.config.depth, draft_round.max_depth + draft_round.num_generated - 1)
        key = self.drafter.round_graph_key(self.compile_config, self.key_length, self.graph_depth)
        pairs = self.first_round_inputs[0]
        self._compile(
            key,
            partial(self._run_round, pairs, _root_position(draft_round), self.graph_depth),
            f"round (depth {self.graph_depth})",
        )

    def _compile(self, key: tuple, compile_all, what: str) -> None:
        """``compile_all`` run once for ``key`` by the call's graphs (``CompiledGraphs.compile_once``), its seconds
        booked as this session's compile time."""
        seconds = self.compiled.compile_once(key, compile_all)
        if seconds:
            self.compile_seconds += seconds
            logger.info("compiled the draft head's %s in %.1f s", what, seconds)

    def _round_inputs(self) -> tuple[tuple, int] | None:
        """The unfed pairs as a compiled round takes them (padded to ``num_padded_pairs``: any beyond fed eagerly
        first, as is a never-written static cache's first entry, which allocates its buffers) and the committed
        entries once they are fed; None when nothing is left for the graph (a one-token prompt: an eager round)."""
        tokens, hidden, positions, committed = self._take_unfed()
        padded = self.num_padded_pairs
        # an unwritten static cache allocates its buffers at its first write: never inside a graph
        initialized = getattr(self.cache.layers[0], "is_initialized", False)
        split = max(tokens.shape[1] - padded, 0 if initialized else 1)
        if split:
            self._feed(tokens[:, :split], hidden[:, :split], positions[:, :split])
            if split == tokens.shape[1]:
                return None
            tokens, hidden, positions = tokens[:, split:], hidden[:, split:], positions[:, split:]
        truncate_cache(self.cache, self.cache_length)
        num_new, pad = tokens.shape[1], padded - tokens.shape[1]
        pairs = (
            torch.cat([tokens, tokens.new_zeros(1, pad)], dim=1),
            torch.cat([hidden, hidden.new_zeros(1, pad, hidden.shape[-1])], dim=1),
            torch.cat([positions, positions[:, -1:].expand(1, pad)], dim=1),
            torch.tensor(num_new, device=tokens.device),
        )
        return pairs, committed

    def _run_round(self, pairs: tuple, root_position: torch.Tensor, depth_limit: int):
        """The compiled round (catch-up of ``pairs``, expansion to ``graph_depth``, trees limited to
        ``depth_limit``); the head's cache keeps only its committed entries afterwards."""
        try:
            return self.compiled_round(
                self.head,
                self.embed,
                self.scorer,
                *pairs,
                root_position,
                self.cache,
                self.cache.layers[0].cumulative_length.clone(),
                self.key_length,
                self.config.top_k,
                self.graph_depth,
                self.config.total_tokens,
                torch.tensor(depth_limit, device=root_position.device),
                self.previous,
            )
        finally:
            truncate_cache(self.cache, self.cache_length)

    def _compiled_round(self, depth: int, root_position: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Catch-up and expansion in the call's compiled graph ([`catch_up_and_expand`], compiled by [`warm_up`]):
        the unfed pairs padded (the first round's made by [`warm_up`]); a round shallower than ``graph_depth`` passes
        its depth as data (``depth_limit``) and gets the shallower expansion's tree."""
        inputs, self.first_round_inputs = self.first_round_inputs or self._round_inputs(), None
        if inputs is None:  # nothing left for the graph (a one-token prompt): an eager round
            return self._expand(depth, root_position)
        pairs, committed = inputs
        token_ids, parents = self._run_round(pairs, root_position, depth)
        self.num_forwards += self.graph_depth
        self.cache_length, self.root_feature = committed, None
        set_static_length(self.cache, committed)  # the real pairs' entries, written by the round, are kept
        if depth < self.graph_depth:  # the nodes below the limit outranked the deeper ones: drop those
            if self.config.top_k == 1:  # a chain: its first nodes
                tree = self._tree(token_ids, parents, self.graph_depth).truncate_nodes(depth)
            else:  # the kept nodes of a tree limited in depth (a read of its structure, in a call's last rounds)
                tree = DraftTree(token_ids, parents).truncate_depth(depth)
            token_ids, parents = tree.token_ids, tree.parents
        return token_ids, parents


def _root_position(draft_round: DraftRound) -> torch.Tensor:
    """``[1, 1]`` the round's root position, contiguous (a compiled round's input)."""
    return draft_round.root_position.reshape(1, 1).clone(memory_format=torch.contiguous_format)
