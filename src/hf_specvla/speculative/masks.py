"""Explicit 4D attention masks for multi-token forwards against a KV cache.

Both the target (prefill and verification) and the draft head (catch-up, tree drafting, training) run forwards
with several query tokens on top of a cache. transformers would build a causal mask itself, but (see NOTES.md)
a decoder layer called directly with ``attention_mask=None`` attends wrongly, eager attention reads bool masks
wrongly, and tree verification needs non-causal masks. So masks are always built here, additive float, shape
``[B, 1, q_len, past_len + q_len]`` (0 = attend, dtype min = masked).
"""

from __future__ import annotations

import torch


def to_additive_mask(allowed: torch.Tensor, dtype: torch.dtype, out: torch.Tensor | None = None) -> torch.Tensor:
    """Bool "may attend" mask ``[B, q, kv]`` -> additive float mask ``[B, 1, q, kv]`` (written into ``out``, of that
    shape and ``dtype``, when given)."""
    if out is not None:
        return out.zero_().masked_fill_(~allowed[:, None], torch.finfo(dtype).min)
    mask = torch.zeros(allowed.shape, dtype=dtype, device=allowed.device)
    mask.masked_fill_(~allowed, torch.finfo(dtype).min)
    return mask[:, None]


def causal_allowed(
    q_len: int, past_len: int, device: torch.device, key_padding: torch.Tensor | None = None
) -> torch.Tensor:
    """Bool mask ``[B, q_len, past_len + q_len]``: query i sees all past keys and new keys 0..i.

    Args:
        key_padding: optional ``[B, past_len + q_len]`` bool, False where a key is padding (never attended).
    """
    query_pos = torch.arange(q_len, device=device)[:, None] + past_len  # [q, 1]
    key_pos = torch.arange(past_len + q_len, device=device)[None, :]  # [1, kv]
    allowed = (key_pos <= query_pos)[None]  # [1, q, kv]
    if key_padding is not None:
        allowed = allowed & key_padding[:, None, :].bool()
    return allowed


def causal_mask(
    q_len: int,
    past_len: int,
    dtype: torch.dtype,
    device: torch.device,
    key_padding: torch.Tensor | None = None,
) -> torch.Tensor:
    """Additive causal mask ``[B, 1, q_len, past_len + q_len]`` (B = 1 without ``key_padding``)."""
    return to_additive_mask(causal_allowed(q_len, past_len, device, key_padding), dtype)


def tree_verification_allowed(
    past_len: int,
    num_pending: int,
    ancestor_or_self: torch.Tensor,
    key_padding: torch.Tensor | None = None,
) -> torch.Tensor:
    """Bool mask ``[B, P + N, past_len + P + N]`` of one target forward over ``P`` pending tokens then a draft tree.

    Pending token i sees the cache and pending tokens 0..i (causal); tree node j sees the cache, every pending token
    and its own ancestors and itself (``ancestor_or_self``), never its siblings.

    Args:
        ancestor_or_self: ``[N, N]`` (one tree for every row) or ``[B, N, N]`` (one per row, see [`TreeBatch`]).
        key_padding: optional ``[B, past_len + P]`` bool, False where a cached or pending key is invalid (prompt
            padding, or an entry a batch row did not keep).
    """
    if ancestor_or_self.ndim == 2:
        ancestor_or_self = ancestor_or_self[None]
    num_trees, num_nodes = ancestor_or_self.shape[0], ancestor_or_self.shape[-1]
    device = ancestor_or_self.device
    pending_rows = torch.cat(
        [
            torch.ones(num_pending, num_pending, dtype=torch.bool, device=device).tril(),
            torch.zeros(num_pending, num_nodes, dtype=torch.bool, device=device),
        ],
        dim=1,
    ).expand(num_trees, -1, -1)
    tree_rows = torch.cat(
        [torch.ones(num_trees, num_nodes, num_pending, dtype=torch.bool, device=device), ancestor_or_self.bool()], 2
    )
    block = torch.cat([pending_rows, tree_rows], dim=1)  # [B, P + N, P + N]
    past = torch.ones(num_trees, num_pending + num_nodes, past_len, dtype=torch.bool, device=device)
    allowed = torch.cat([past, block], dim=2)  # [B, P + N, past + P + N]
    if key_padding is None:
        return allowed
    keys = torch.cat(
        [key_padding.bool(), torch.ones(key_padding.shape[0], num_nodes, dtype=torch.bool, device=device)], 1
    )
    return allowed & keys[:, None, :]  # [B, P + N, past + P + N]


def sequence_key_padding(prompt_padding: torch.Tensor | None, length: int) -> torch.Tensor | None:
    """Bool ``[B, length]`` "is a real token" mask for the first ``length`` positions of a sequence whose prompt
    has the 2D mask ``prompt_padding`` ``[B, S]``; positions past the prompt (generated or drafted) are real.
    None when there is no padding at all."""
    if prompt_padding is None:
        return None
    if length <= prompt_padding.shape[1]:
        return prompt_padding[:, :length].bool()
    extra = prompt_padding.new_ones(prompt_padding.shape[0], length - prompt_padding.shape[1])
    return torch.cat([prompt_padding, extra], dim=1).bool()
