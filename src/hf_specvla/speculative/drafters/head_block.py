"""Head v3's block drafting: one head forward drafts every remaining token of an action (DFlash-style).

A round feeds, in one forward of the [`DraftHead`], the pairs the target committed since the last round (token
x[p+1], the target's hidden state h[p], as EAGLE feeds them) followed by ``M`` mask queries at the next positions
(the learned "unknown token" and "missing hidden state" inputs, ``DraftHead.mask_query_inputs``). The last real
pair's feature drafts depth 0; query j drafts depth j. Before the prefill ([`prefill_block`]) the prompt's tokens are
the pairs, each with a missing hidden state (the target has not run), so the whole action is drafted from the prompt
and the previous action.

Per position the ``top_k`` best tokens are kept; [`product_tree`] arranges them as a tree whose structure depends on
the settings only (never on the drafted tokens, so nothing is read back while drafting): the chain of top-1 tokens
(the backbone), then each alternative at depth j below the backbone's node j - 1, continued by the backbone's tokens
of the deeper positions (block predictions are not conditioned on the tokens before them, so an alternative's
continuation is the same block's). Alternatives are added rank by rank, shallow first, while ``total_tokens`` allows.

[`block_round`] has fixed shapes for fixed ``Q``, ``M`` and ``key_length`` (the real pairs' count is data), so the
same function runs eagerly and, on a static cache, compiled.
"""

from __future__ import annotations

from functools import lru_cache

import torch

from ..masks import to_additive_mask


@lru_cache(maxsize=64)
def product_tree(depth: int, top_k: int, total_tokens: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The tree over a ``[depth, top_k]`` table of per-position candidates (module docstring).

    Returns:
        ``(picks, parents)``: node i holds the table's flat entry ``picks[i]`` (``position * top_k + rank``) and
        hangs below node ``parents[i]`` (-1: the root); at most ``max(total_tokens, depth)`` nodes, parents first.
    """
    picks = [position * top_k for position in range(depth)]  # the backbone: top-1 at every position
    parents = list(range(-1, depth - 1))
    budget = max(total_tokens, depth)
    for rank in range(1, top_k):
        for position in range(depth):
            if len(picks) >= budget:
                return tuple(picks), tuple(parents)
            parent = position - 1  # the backbone's node at the depth above (node index = its depth)
            for continued in range(position, depth):
                if len(picks) >= budget:
                    break
                picks.append(continued * top_k + (rank if continued == position else 0))
                parents.append(parent)
                parent = len(picks) - 1
    return tuple(picks), tuple(parents)


def block_mask(
    num_pairs: int,
    num_new: int | torch.Tensor,
    num_queries: int,
    committed: int | torch.Tensor,
    key_length: int | None,
    key_valid: torch.Tensor | None,
    dtype: torch.dtype,
    device: torch.device,
) -> torch.Tensor:
    """The mask of one block forward: ``Q`` pairs (the first ``num_new`` real, the rest padding that sees only itself)
    at slots ``committed ..``, then ``M`` queries; each real pair sees the committed entries and the real pairs up to
    itself, each query every real pair and the queries up to itself.

    Args:
        key_valid: ``[committed + Q]`` bool, False at prompt padding (a padded batch row on a dynamic cache), or None.
        key_length: a static cache's slots (keys past the block masked), or None: ``committed + Q + M`` keys.
    Returns:
        ``[1, 1, Q + M, key_length]`` additive float mask.
    """
    length = committed + num_pairs + num_queries if key_length is None else key_length
    slots = torch.arange(length, device=device)[None]  # [1, L]
    query = torch.arange(num_pairs + num_queries, device=device)[:, None]  # [Q + M, 1]
    own_slot = committed + query
    is_pair = query < num_pairs
    real_pair = query < num_new
    key_is_real = (slots < committed + num_new) | ((slots >= committed + num_pairs) & (slots <= own_slot))
    allowed = (slots <= own_slot) & key_is_real & (real_pair | ~is_pair)
    allowed = allowed | (slots == own_slot)  # padding sees itself
    if key_valid is not None:
        valid = torch.cat([key_valid.bool(), key_valid.new_ones(length - key_valid.shape[0]).bool()])
        allowed = allowed & (valid[None] | (slots == own_slot))
    return to_additive_mask(allowed[None], dtype)


def block_round(
    head,
    embed,
    scorer,
    token_ids: torch.Tensor,
    hidden: torch.Tensor | None,
    positions: torch.Tensor,
    num_new: int | torch.Tensor,
    cache,
    committed: int | torch.Tensor,
    num_queries: int,
    top_k: int,
    key_length: int | None = None,
    key_valid: torch.Tensor | None = None,
    previous: tuple[torch.Tensor, torch.Tensor] | None = None,
    pair_embeddings: torch.Tensor | None = None,
) -> torch.Tensor:
    """One block forward (module docstring). Batch 1.

    Args:
        head: the [`DraftHead`]; ``embed``: ids ``[1, q]`` -> target embeddings ``[1, q, H]``; ``scorer``: its
            [`DraftScorer`].
        token_ids / positions: ``[1, Q]`` the pairs' tokens x[p+1] and positions p (the first ``num_new`` real).
        hidden: ``[1, Q, n H]`` the target's hidden states h[p], or None: missing (before the prefill).
        num_new: the real pairs (an int, or a 0-dim int64 tensor in a compiled graph).
        cache: the head's cache (a static one is written at its counter, which must be ``committed``); the pairs'
            entries stay for the caller to keep, the queries' (and padding's) for it to drop.
        committed: the head's entries before the pairs.
        num_queries: M, the mask queries (depths 1..M are drafted).
        top_k: candidates kept per position (capped at the scored tokens).
        key_length / key_valid: as [`block_mask`].
        previous: ``(previous_bins [D], first_position)`` for a head that reads the previous action, else None.
        pair_embeddings: ``[1, Q, H]`` the pairs' token inputs when not ``embed(token_ids)`` (before the prefill, a
            head with ``prefill_image_features``: the target's input embeddings, images encoded), else None.
    Returns:
        ``[1 + M, k]`` int64 vocabulary ids: each depth's best tokens, best first.
    """
    num_pairs = token_ids.shape[1]
    query_embeds, query_hidden = head.mask_query_inputs(1, num_queries)
    last = positions.index_select(1, torch.as_tensor(num_new, device=positions.device).reshape(1) - 1)  # [1, 1]
    query_positions = last + torch.arange(1, num_queries + 1, device=positions.device)[None]  # [1, M]
    if hidden is None:
        pair_hidden = head.mask_query_inputs(1, num_pairs, unknown_token=False)[1]
    else:
        pair_hidden = head.fuse_features(hidden)
    pair_embeddings = embed(token_ids) if pair_embeddings is None else pair_embeddings
    embeds = torch.cat([pair_embeddings.to(query_embeds.dtype), query_embeds], dim=1)  # [1, Q + M, H]
    all_hidden = torch.cat([pair_hidden.to(query_hidden.dtype), query_hidden], dim=1)
    all_positions = torch.cat([positions, query_positions], dim=1)
    mask = block_mask(num_pairs, num_new, num_queries, committed, key_length, key_valid, embeds.dtype, embeds.device)
    bins = None if previous is None else head.slot_bins(*previous, all_positions)
    features = head(embeds, all_hidden, all_positions, mask, cache, bins)  # [1, Q + M, H]
    last_pair = torch.as_tensor(num_new, device=features.device).reshape(1) - 1
    drafting = torch.cat([features.index_select(1, last_pair), features[:, num_pairs:]], dim=1)[0]  # [1 + M, H]
    logits = scorer.logits(drafting)
    k = min(top_k, logits.shape[-1])
    return scorer.vocab_ids(logits.topk(k, dim=-1).indices)  # [1 + M, k]
