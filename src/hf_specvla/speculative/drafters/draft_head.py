"""Drafting with an EAGLE-style [`DraftHead`]: a chain (EAGLE-1) or a dynamic tree (EAGLE-2).

EAGLE-2's dynamic tree (Li et al. 2024, "EAGLE-2: Faster Inference of Language Models with Dynamic Draft Trees";
``topK_genrate`` in SafeAILab/EAGLE), as Spec-VLA uses it:

* **expand**: the root's feature gives the ``top_k`` most probable first tokens. At each further level the
  ``top_k`` frontier nodes with the highest *cumulative* draft log-probability are fed to the head in one
  forward (a tree mask: each sees the committed cache, its ancestors and itself); each yields its ``top_k``
  children, scored by parent score + child log-probability. The next frontier is the best ``top_k`` children.
* **re-rank**: of every node created, the ``total_tokens`` with the highest cumulative score form the tree
  (a child never scores above its parent, so the kept set is closed under ancestors; ties are closed explicitly).

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

Per-call state (the head's KV cache, the pairs not yet fed) lives in the session, never on the model.
Invariant: after a catch-up the head's cache holds exactly the target's committed positions, each computed from
the target's true hidden state; tree-drafting entries are dropped at the end of every proposal.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from transformers.cache_utils import DynamicCache

from ..cache import truncate_cache
from ..drafter import Commit, DraftContext, Drafter, DraftRound, DraftSession
from ..masks import block_allowed, causal_mask, sequence_key_padding, to_additive_mask
from ..modeling_draft_head import DraftHead, DraftScorer, TargetHandles
from ..tree import DraftTree


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
        if tree is None:
            k = num_draft_tokens or draft_head.config.num_draft_tokens
            tree = DraftTreeConfig(top_k=1, depth=k, total_tokens=k)
            self.name = "head-chain"
        else:
            self.name = "head-tree"
        self.tree_config = tree
        self.action_layout = draft_head.config.action_layout()

    def start(self, context: DraftContext) -> DraftSession:
        handles = self.draft_head.target_handles(context.model)
        scorer = self.draft_head.scorer(handles.lm_head, context.eos_token_ids)
        return _DraftHeadSession(self, handles, scorer, context.prompt_padding)

    def __repr__(self) -> str:
        return f"DraftHeadDrafter({self.name}, {self.tree_config})"


class _DraftHeadSession(DraftSession):
    def __init__(self, drafter: DraftHeadDrafter, handles: TargetHandles, scorer: DraftScorer, prompt_padding):
        self.head, self.config, self.name = drafter.draft_head, drafter.tree_config, drafter.name
        self.handles, self.scorer, self.prompt_padding = handles, scorer, prompt_padding
        self.cache = DynamicCache()
        self.cache_length = 0  # committed entries in self.cache
        self.unfed: list[Commit] = []  # commits whose (token, hidden) pairs the head has not seen yet
        self.root_feature: torch.Tensor | None = None  # [B, 1, H] estimate of the hidden state at the root
        self.num_forwards = 0

    def observe(self, commit: Commit) -> None:
        if commit.target_hidden is None:
            raise ValueError("a draft head needs the target's hidden states in every Commit")
        self.unfed.append(commit)
        self.root_feature = None

    def _catch_up(self) -> None:
        """Feeds the pairs (token x[p+1], true hidden h[p]) of every commit not yet seen, in one forward."""
        tokens = torch.cat([c.next_token_ids for c in self.unfed], dim=1)  # [B, q]
        hidden = torch.cat([c.target_hidden for c in self.unfed], dim=1)  # [B, q, H]
        positions = torch.cat([c.positions for c in self.unfed], dim=1)  # [B, q]
        truncate_cache(self.cache, self.cache_length)  # drop the previous proposal's tree entries
        q_len = tokens.shape[1]
        padding = sequence_key_padding(self.prompt_padding, self.cache_length + q_len)
        mask = causal_mask(q_len, self.cache_length, hidden.dtype, hidden.device, padding)
        features = self.head(embed_tokens(self.handles, tokens), hidden, positions, mask, self.cache)
        self.num_forwards += 1
        self.cache_length = self.unfed[-1].cache_length
        self.unfed = []
        self.root_feature = features[:, -1:]

    def propose(self, draft_round: DraftRound) -> DraftTree:
        depth = min(self.config.depth, draft_round.max_depth)
        if draft_round.at_prefill or depth < 1:
            return DraftTree.empty(draft_round.sequence.device)
        if self.unfed:
            self._catch_up()
        try:
            return self._expand(depth, draft_round.root_position)
        finally:
            truncate_cache(self.cache, self.cache_length)

    def _expand(self, depth: int, root_position: torch.Tensor) -> DraftTree:
        """EAGLE-2 expand + re-rank (module docstring), batch 1."""
        top_k = self.config.top_k
        log_probs = torch.log_softmax(self.scorer.logits(self.root_feature[0, 0]).float(), dim=-1)  # [C]
        top_k = min(top_k, log_probs.shape[-1])
        scores, best = log_probs.topk(top_k)
        token_ids = self._vocab_ids(best).tolist()
        parents = [-1] * top_k
        node_scores = scores.tolist()
        fed_index: dict[int, int] = {}  # node -> its entry in the head's cache, counted from cache_length
        backbone = [0]  # the greedy path: the top-1 child at every level (topk returns the best first)
        frontier = list(range(top_k))  # nodes to feed next
        frontier_features = self.root_feature.expand(1, top_k, -1)  # [1, F, H] parent features of the frontier
        device = self.root_feature.device
        for level in range(1, depth):
            # 1. feed the frontier (nodes at depth level-1) with their parents' features, one forward.
            num = len(frontier)
            if top_k == 1 and self.prompt_padding is None:  # a chain: every fed entry is an ancestor, all visible
                mask = frontier_features.new_zeros(1, 1, 1, self.cache_length + len(fed_index) + 1)
            else:
                allowed = block_allowed(self._tree_block(frontier, parents, fed_index, device), self.cache_length,
                                        sequence_key_padding(self.prompt_padding, self.cache_length))  # fmt: skip
                mask = to_additive_mask(allowed, frontier_features.dtype)
            tokens = torch.tensor([token_ids[n] for n in frontier], device=device)[None]  # [1, F]
            # EAGLE's pair (token x[p+1], feature ~h[p]) sits at p: a depth-d node pairs with its parent, at root + d
            positions = (root_position + level - 1).expand(1, num)
            features = self.head(embed_tokens(self.handles, tokens), frontier_features, positions, mask, self.cache)
            self.num_forwards += 1
            for node in frontier:
                fed_index[node] = len(fed_index)
            # 2. each fed node's top_k children, scored by cumulative log-probability.
            child_log_probs = torch.log_softmax(self.scorer.logits(features[0]).float(), dim=-1)  # [F, C]
            child_scores, child_best = child_log_probs.topk(top_k, dim=-1)  # [F, k]
            cumulative = torch.tensor([node_scores[n] for n in frontier], device=device)[:, None] + child_scores
            first_child = len(token_ids)
            token_ids += self._vocab_ids(child_best).flatten().tolist()
            parents += [node for node in frontier for _ in range(top_k)]
            node_scores += cumulative.flatten().tolist()
            backbone.append(first_child + frontier.index(backbone[-1]) * top_k)  # its parent is always fed
            # 3. the next frontier: the top_k children overall, and the backbone's new node.
            if level + 1 < depth:
                chosen = cumulative.flatten().topk(min(top_k, cumulative.numel())).indices.tolist()
                if backbone[-1] - first_child not in chosen:
                    chosen.append(backbone[-1] - first_child)
                frontier = [first_child + c for c in chosen]
                frontier_features = features[:, [c // top_k for c in chosen]]
        return self._rerank(token_ids, parents, node_scores, backbone, device)

    def _rerank(self, token_ids, parents, node_scores, backbone, device) -> DraftTree:
        """Keeps the backbone and the best other nodes by cumulative score, ``total_tokens`` in all (ancestors
        closed), parents first."""
        keep = set(backbone)
        for node in sorted(range(len(token_ids)), key=lambda n: -node_scores[n]):
            if len(keep) >= self.config.total_tokens:
                break
            keep.add(node)
        for node in list(keep):  # ties can leave an ancestor out: close the set
            while parents[node] >= 0 and parents[node] not in keep:
                node = parents[node]
                keep.add(node)
        nodes = sorted(keep)  # creation order is parents-first
        new_index = {node: i for i, node in enumerate(nodes)}
        return DraftTree(
            torch.tensor([token_ids[n] for n in nodes], dtype=torch.long, device=device),
            torch.tensor([new_index[parents[n]] if parents[n] >= 0 else -1 for n in nodes], dtype=torch.long,
                         device=device),
            [self.name] * len(nodes),
        )  # fmt: skip

    @staticmethod
    def _tree_block(frontier, parents, fed_index, device) -> torch.Tensor:
        """``[F, fed + F]`` bool: frontier node j sees the fed entries of its ancestors, and itself."""
        num_fed = len(fed_index)
        block = torch.zeros(len(frontier), num_fed + len(frontier), dtype=torch.bool)
        for j, node in enumerate(frontier):
            block[j, num_fed + j] = True
            ancestor = parents[node]
            while ancestor >= 0:
                block[j, fed_index[ancestor]] = True
                ancestor = parents[ancestor]
        return block.to(device)

    def _vocab_ids(self, scored_index: torch.Tensor) -> torch.Tensor:
        """Indices into the scorer's candidates -> vocabulary ids."""
        ids = self.scorer.candidate_ids
        return scored_index if ids is None else ids[scored_index]
