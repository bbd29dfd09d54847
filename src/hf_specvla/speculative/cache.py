"""KV-cache surgery after a verification: keep the accepted entries, drop the rest.

Works on transformers' layered caches (``cache.layers[i].keys / .values``, each ``[B, H_kv, S, D]``).
``DynamicCache.crop`` only takes a number of tokens to remove in 5.x and is missing on some layer types, so the
slicing is done here, explicitly, for the layer types where it is correct.
"""

from __future__ import annotations

import torch
from transformers.cache_utils import Cache, DynamicLayer


def _dynamic_layers(cache: Cache):
    layers = getattr(cache, "layers", None)
    if layers is None:
        raise TypeError(f"{type(cache).__name__} has no per-layer storage; speculative decoding needs a DynamicCache")
    for layer in layers:
        # Sliding-window layers drop old entries and cannot be rolled back safely.
        if type(layer) is not DynamicLayer:
            raise TypeError(
                f"speculative decoding can roll back only plain dynamic cache layers, got {type(layer).__name__}; "
                f"use the default DynamicCache (cache_implementation=None) on a model without sliding-window layers"
            )
        yield layer


def truncate_cache(cache: Cache, length: int) -> None:
    """Keeps the first ``length`` positions of every layer, in place."""
    for layer in _dynamic_layers(cache):
        if getattr(layer, "is_initialized", True) and layer.keys is not None and layer.keys.numel():
            layer.keys = layer.keys[..., :length, :]
            layer.values = layer.values[..., :length, :]


def select_cache_positions(cache: Cache, positions: torch.Tensor) -> None:
    """Keeps only ``positions`` of every layer, in place (e.g. a tree's accepted path).

    Args:
        positions: ``[K]`` int64 ascending (the same entries for every row), or ``[B, K]`` (row b keeps
            ``positions[b]``: a batch whose rows accepted different paths).
    """
    for layer in _dynamic_layers(cache):
        if getattr(layer, "is_initialized", True) and layer.keys is not None and layer.keys.numel():
            if positions.ndim == 1:
                layer.keys = layer.keys.index_select(-2, positions)
                layer.values = layer.values.index_select(-2, positions)
            else:
                heads, dim = layer.keys.shape[1], layer.keys.shape[-1]
                index = positions[:, None, :, None].expand(-1, heads, -1, dim)  # [B, H_kv, K, D]
                layer.keys = layer.keys.gather(2, index)
                layer.values = layer.values.gather(2, index)


def select_cache_rows(cache: Cache, rows: torch.Tensor) -> None:
    """Keeps only batch ``rows`` (``[B']`` int64) of every layer, in place (e.g. the rows still generating)."""
    for layer in _dynamic_layers(cache):
        if getattr(layer, "is_initialized", True) and layer.keys is not None and layer.keys.numel():
            layer.keys = layer.keys.index_select(0, rows)
            layer.values = layer.values.index_select(0, rows)
