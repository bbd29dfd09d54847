"""Explicit 4D attention masks for multi-token forwards against a KV cache.

Both the target (verification) and the draft head (catch-up, training) run forwards with several query tokens
on top of a cache. transformers would build a causal mask itself, but (see NOTES.md) a decoder layer called
directly with ``attention_mask=None`` attends wrongly, eager attention reads bool masks wrongly, and tree
verification needs non-causal masks. So masks are always built here, additive float, shape
``[B, 1, q_len, past_len + q_len]`` (0 = attend, dtype min = masked).
"""

from __future__ import annotations

import torch


def to_additive_mask(allowed: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """Bool "may attend" mask ``[B, q, kv]`` -> additive float mask ``[B, 1, q, kv]``."""
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
