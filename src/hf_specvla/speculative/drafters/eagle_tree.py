"""EAGLE-2's dynamic draft tree, expanded with fixed-shape tensor operations and no host reads.

One function, [`expand_tree`], runs eagerly on the head's ``DynamicCache``; on the head's static cache
[`catch_up_and_expand`] (the round's catch-up forward, padded to a fixed count, then the expansion) is compiled by
``torch.compile`` as one graph (see [`DraftHeadDrafter`]): every shape depends only on ``top_k``, ``depth`` and
``total_tokens``, never on the drafted tokens, their scores, how many were accepted or how deep a round may draft
(``depth_limit``, data).

The procedure (EAGLE-2, Li et al. 2024, ``topK_genrate`` in SafeAILab/EAGLE), with the backbone rule of
[`DraftHeadDrafter`] (the head's greedy path is always expanded and always kept):

* **level 0**: the root feature scores the first tokens; its ``k`` (= ``top_k``) best children are the frontier.
* **level l >= 1**: the frontier's ``k`` nodes are fed to the head in one forward (a tree mask: each sees the
  committed entries, its ancestors' entries and itself); each yields its ``k`` best children, scored by cumulative
  log-probability (parent score + child log-probability). The next frontier: the backbone's greedy child (always in
  position 0) and the ``k - 1`` best other children. Level l's frontier is written at the head's entries
  ``tree_start + (l - 1) k .. tree_start + l k - 1``.
* **re-rank**: the backbone and the best other nodes by cumulative score, ``total_tokens`` in all, returned in
  creation order (parents first). A child never scores above its parent and ties go to the node created first, so
  the kept set is closed under ancestors by construction.

Deviation from EAGLE-2 (and from a frontier of the ``k`` best children overall): when the backbone's greedy child is
not among the ``k`` best children, it replaces the ``k``-th, so that the frontier keeps one width.
"""

from __future__ import annotations

import torch

from ..masks import to_additive_mask


def num_created_nodes(top_k: int, depth: int) -> int:
    """Nodes one expansion creates: ``top_k`` children of the root, then ``top_k`` children per frontier node."""
    return top_k + (depth - 1) * top_k * top_k


def num_head_entries(top_k: int, depth: int) -> int:
    """Entries one expansion writes into the head's cache after the committed ones (one per fed frontier node)."""
    return (depth - 1) * top_k


def frontier_mask(
    visible: torch.Tensor,
    past: int | torch.Tensor,
    tree_start: int | torch.Tensor,
    key_length: int | None,
    committed_visible: torch.Tensor | None,
    dtype: torch.dtype,
) -> torch.Tensor:
    """The attention mask of one frontier forward of the head.

    Args:
        visible: ``[F, E]`` bool, which of the tree's ``E`` head entries (from slot ``tree_start`` on; the last
            ``F`` are the frontier's own) each frontier node sees: its ancestors' and its own.
        past: the committed entries every node sees (slots ``0 .. past - 1``): an int, or a 0-dim int64 tensor so
            that a compiled graph does not depend on its value.
        tree_start: the slot of the tree's first entry (``past``, or later when slots between hold padding).
        key_length: the keys attended over: None for a dynamic cache (``tree_start + E``), the slot count of a static
            cache (slots past the tree are masked).
        committed_visible: ``[past]`` bool, False at prompt padding (dynamic cache only), or None.
    Returns:
        ``[1, 1, F, key_length]`` additive float mask.
    """
    num_tree = visible.shape[1]
    length = tree_start + num_tree if key_length is None else key_length
    slots = torch.arange(length, device=visible.device)
    offset = slots - tree_start  # [L] the slot's index among the tree's entries (negative: before the tree)
    in_tree = (offset >= 0) & (offset < num_tree)
    allowed = visible[:, offset.clamp(0, num_tree - 1)] & in_tree  # [F, L]
    seen = slots < past
    if committed_visible is not None:
        seen = seen & torch.cat([committed_visible.bool(), committed_visible.new_zeros(length - past).bool()])
    return to_additive_mask((allowed | seen)[None], dtype)


def catch_up_and_expand(
    head,
    embed,
    scorer,
    token_ids: torch.Tensor,
    hidden: torch.Tensor,
    positions: torch.Tensor,
    num_new: torch.Tensor,
    root_position: torch.Tensor,
    cache,
    committed: torch.Tensor,
    key_length: int,
    top_k: int,
    depth: int,
    total_tokens: int,
    depth_limit: torch.Tensor | None = None,
    previous: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """One drafting round on a static cache in one graph: feeds the pairs the target committed (padded to a fixed
    count), then [`expand_tree`] from the last one's feature.

    Args:
        token_ids / hidden / positions: ``[1, Q]`` / ``[1, Q, H]`` / ``[1, Q]`` the pairs (token x[p+1], hidden h[p])
            at positions p; the first ``num_new`` are real, the rest padding (written, never seen, then overwritten).
        num_new: 0-dim int64, the real pairs (1 .. Q).
        committed: 0-dim int64, the head's committed entries before these pairs (its static counter).
        the rest: as in [`expand_tree`].
    Returns:
        as [`expand_tree`]; the cache then holds ``committed + num_new`` real entries (and padding and the tree's
        entries after them, for the caller to drop).
    """
    q_len = token_ids.shape[1]
    slots = torch.arange(key_length, device=token_ids.device)[None]  # [1, L]
    query = torch.arange(q_len, device=token_ids.device)[:, None]  # [Q, 1]
    own_slot = committed + query
    real = query < num_new
    allowed = ((slots <= own_slot) & real) | (slots == own_slot)  # padding sees itself only
    mask = to_additive_mask(allowed[None], hidden.dtype)
    bins = None if previous is None else head.slot_bins(*previous, positions)
    features = head(embed(token_ids), hidden, positions, mask, cache, bins)
    root_feature = features.index_select(1, (num_new - 1).reshape(1))  # [1, 1, H]
    return expand_tree(
        head,
        embed,
        scorer,
        root_feature,
        root_position,
        cache,
        committed + num_new,
        None,
        top_k,
        depth,
        total_tokens,
        tree_start=committed + q_len,
        key_length=key_length,
        depth_limit=depth_limit,
        previous=previous,
    )


def expand_tree(
    head,
    embed,
    scorer,
    root_feature: torch.Tensor,
    root_position: torch.Tensor,
    cache,
    past: int | torch.Tensor,
    committed_visible: torch.Tensor | None,
    top_k: int,
    depth: int,
    total_tokens: int,
    tree_start: int | torch.Tensor | None = None,
    key_length: int | None = None,
    depth_limit: torch.Tensor | None = None,
    previous: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Expands and re-ranks one EAGLE-2 tree below the root (module docstring). Batch 1.

    Args:
        head: the [`DraftHead`]; ``embed``: ids ``[1, F]`` -> target embeddings ``[1, F, H]``; ``scorer``: the
            [`DraftScorer`] (features -> logits over its candidates; candidate index -> vocabulary id).
        root_feature: ``[1, 1, H]`` the head's estimate of the root's hidden state.
        root_position: the root's position id (``[1, 1]`` or 0-dim int64); a level-l frontier is fed at
            ``root_position + l - 1`` (EAGLE pairs a node's token with its parent's feature at the parent's position).
        cache: the head's cache; the tree's entries are written at its end (a static cache: at its counter, which must
            be ``tree_start``); the caller drops them afterwards.
        past / committed_visible / tree_start (default ``past``) / key_length (default: a dynamic cache): as in
            [`frontier_mask`].
        top_k / depth / total_tokens: the tree's settings (``top_k`` is capped at the scored candidates).
        depth_limit: 0-dim int64, or None: only nodes of depth < ``depth_limit`` (0 = the root's children) compete
            for the budget, so that one graph expanded to ``depth`` serves every shallower round (its nodes below
            the limit are the shallower expansion's, in the same order: the same tree); the deeper ones rank last.
        previous: for a head that reads the robot's previous action, ``(previous_bins [D], first_position)`` as
            [`DraftHead.slot_bins`] takes them; None for any other head.
    Returns:
        ``(token_ids, parents)``, each ``[T]`` int64, T = ``min(total_tokens, num_created_nodes(k, depth))``:
        vocabulary ids, and each node's parent index (-1 for the root's children), parents first.
    """
    device = root_feature.device
    tree_start = past if tree_start is None else tree_start
    log_probs = torch.log_softmax(scorer.logits(root_feature[0, 0]).float(), dim=-1)  # [C]
    k = min(top_k, log_probs.shape[-1])
    frontier_scores, best = log_probs.topk(k)  # [k], best first: position 0 is the backbone
    frontier_tokens = scorer.vocab_ids(best)
    frontier = torch.arange(k, device=device)  # each frontier node's index among the created nodes
    frontier_features = root_feature.expand(1, k, -1)  # [1, F, H] the parents' features
    ancestors = torch.zeros(k, 0, dtype=torch.bool, device=device)  # [F, fed] the fed entries each node descends from
    token_ids, scores, parents = [frontier_tokens], [frontier_scores], [torch.full_like(frontier, -1)]
    backbone, num_created = [0], k
    eye = torch.eye(k, dtype=torch.bool, device=device)
    for level in range(1, depth):
        visible = torch.cat([ancestors, eye], dim=1)  # [F, fed + F]
        mask = frontier_mask(visible, past, tree_start, key_length, committed_visible, root_feature.dtype)
        positions = (root_position.reshape(1, 1) + (level - 1)).expand(1, k)
        bins = None if previous is None else head.slot_bins(*previous, positions)
        features = head(embed(frontier_tokens[None]), frontier_features, positions, mask, cache, bins)  # [1, F, H]
        child_log_probs = torch.log_softmax(scorer.logits(features[0]).float(), dim=-1)  # [F, C]
        child_scores, child_best = child_log_probs.topk(k, dim=-1)  # [F, k]
        cumulative = (frontier_scores[:, None] + child_scores).flatten()  # [F * k]
        child_tokens = scorer.vocab_ids(child_best).flatten()
        token_ids.append(child_tokens)
        scores.append(cumulative)
        parents.append(frontier.repeat_interleave(k))
        backbone.append(num_created)  # the backbone node (frontier position 0)'s best child
        if level + 1 < depth:
            ranked = torch.cat([cumulative.new_full((1,), float("inf")), cumulative[1:]])
            chosen = ranked.topk(k).indices  # [F] the backbone's child first
            frontier = num_created + chosen
            frontier_scores, frontier_tokens = cumulative[chosen], child_tokens[chosen]
            parent_slot = chosen // k  # the fed frontier node each chosen child hangs below
            frontier_features = features[:, parent_slot]
            ancestors = visible[parent_slot]
        num_created += k * k
    node_depths = torch.cat([torch.full_like(level_ids, level) for level, level_ids in enumerate(token_ids)])
    too_deep = None if depth_limit is None else node_depths >= depth_limit
    return _rerank(torch.cat(token_ids), torch.cat(parents), torch.cat(scores), backbone, total_tokens, too_deep)


def _rerank(
    token_ids: torch.Tensor,
    parents: torch.Tensor,
    scores: torch.Tensor,
    backbone: list[int],
    total_tokens: int,
    too_deep: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The backbone and the best other created nodes (``[N]`` each), ``total_tokens`` in all, in creation order,
    their parents renumbered; nodes marked ``too_deep`` (``[N]`` bool) rank last."""
    num_created = token_ids.shape[0]
    kept_count = min(total_tokens, num_created)
    backbone_index = torch.tensor(backbone, device=scores.device)
    ranked = scores.index_fill(0, backbone_index, float("inf"))
    if too_deep is not None:  # a too-deep node's descendants are too deep: the kept set stays closed
        ranked = ranked.masked_fill(too_deep, float("-inf"))
    # stable: among equal scores the node created first (a parent before its children) ranks first
    kept = torch.sort(ranked, descending=True, stable=True).indices[:kept_count].sort().values  # [T]
    new_index = torch.full_like(parents, -1).index_copy(0, kept, torch.arange(kept_count, device=kept.device))
    kept_parents = parents[kept]
    renumbered = torch.where(kept_parents >= 0, new_index[kept_parents.clamp(min=0)], kept_parents)
    return token_ids[kept], renumbered
