"""KV-cache surgery after a verification: keep the accepted entries, drop the rest.

Works on transformers' layered caches (``cache.layers[i].keys / .values``, each ``[B, H_kv, S, D]``).
``DynamicCache.crop`` only takes a number of tokens to remove in 5.x and is missing on some layer types, so the
slicing is done here, explicitly, for the layer types where it is correct:

* ``DynamicLayer`` (full attention): every entry is kept, any prefix or path can be kept.
* ``DynamicSlidingWindowLayer`` (Gemma-2/3, PaliGemma-2, Mistral with a window): the layer keeps only its last
  ``sliding_window - 1`` entries, so a rejected draft could push out an entry the accepted path still needs. When
  the whole generation fits in the window (prompt + ``max_new_tokens`` <= window, always true for a VLA prompt of a
  few hundred tokens against a 4096 window), sliding attention *is* full attention for every token greedy decoding
  emits, so [`open_sliding_windows`] holds the layers open (nothing dropped) while the loop runs and restores them
  afterwards. A generation that does not fit is refused before the first forward ([`check_rollback_cache`]).

Any other layer (static, quantized, linear-attention / recurrent states, offloaded or indexed layers) cannot be
rolled back here and is refused before the first forward.
"""

from __future__ import annotations

from contextlib import contextmanager

import torch
from transformers.cache_utils import Cache, DynamicLayer, DynamicSlidingWindowLayer

#: the layer types whose entries can be sliced (exact types: subclasses change how entries are stored)
ROLLBACK_LAYER_TYPES = (DynamicLayer, DynamicSlidingWindowLayer)

#: what a sliding layer's window is raised to while held open (larger than any sequence)
_OPEN_WINDOW = 2**62


def _layers(cache: Cache) -> list:
    layers = getattr(cache, "layers", None)
    if layers is None:
        raise TypeError(
            f"{type(cache).__name__} has no per-layer storage; speculative decoding needs a DynamicCache "
            f"(cache_implementation=None)"
        )
    return layers


def check_rollback_cache(cache: Cache, max_length: int) -> None:
    """Refuses, before any forward runs, a cache that speculative decoding cannot roll back exactly.

    Args:
        max_length: the longest sequence the generation can reach (prompt + ``max_new_tokens``).
    Raises:
        TypeError: a layer type that cannot be rolled back (names the layer and what would work).
        ValueError: a sliding-window layer whose window is shorter than ``max_length`` (names both).
    """
    for index, layer in enumerate(_layers(cache)):
        kind = type(layer)
        if kind not in ROLLBACK_LAYER_TYPES:
            raise TypeError(
                f"speculative decoding rolls back rejected drafts by slicing the KV cache, which it cannot do for "
                f"layer {index}'s {kind.__name__}; it supports DynamicLayer and DynamicSlidingWindowLayer (the "
                f"default DynamicCache, cache_implementation=None). Static, quantized, offloaded and recurrent / "
                f"linear-attention caches are not supported: generate without assistant_model / draft_ids for those"
            )
        if kind is DynamicSlidingWindowLayer and max_length > layer.sliding_window:
            raise ValueError(
                f"layer {index} attends over a sliding window of {layer.sliding_window} tokens, but this generation "
                f"can reach {max_length} tokens (prompt + max_new_tokens): past the window, a rejected draft would "
                f"push out entries the accepted tokens still need. Keep prompt + max_new_tokens <= "
                f"{layer.sliding_window}, or generate without assistant_model / draft_ids"
            )


def sliding_window(cache: Cache) -> int | None:
    """The smallest sliding window among the cache's layers (None: no sliding layer)."""
    windows = [layer.sliding_window for layer in _layers(cache) if type(layer) is DynamicSlidingWindowLayer]
    return min(windows) if windows else None


@contextmanager
def open_sliding_windows(cache: Cache):
    """Holds every sliding-window layer of ``cache`` open (it keeps all entries, like a full layer) inside the block;
    afterwards restores its window and keeps its last ``window - 1`` entries, as the layer itself would have.

    Only exact when the sequence stays within the window (see [`check_rollback_cache`]): then the sliding window
    never hides a key from a token greedy decoding emits.
    """
    held = [layer for layer in _layers(cache) if type(layer) is DynamicSlidingWindowLayer]
    windows = [layer.sliding_window for layer in held]
    for layer in held:
        layer.sliding_window = _OPEN_WINDOW
    try:
        yield
    finally:
        for layer, window in zip(held, windows):
            layer.sliding_window = window
            if getattr(layer, "is_initialized", False) and layer.keys is not None:
                layer.keys = layer.keys[..., -window + 1 :, :]
                layer.values = layer.values[..., -window + 1 :, :]


def _stored_layers(cache: Cache):
    """The layers holding entries (each of a type [`check_rollback_cache`] accepts)."""
    for layer in _layers(cache):
        if type(layer) not in ROLLBACK_LAYER_TYPES:
            raise TypeError(
                f"speculative decoding can roll back only DynamicLayer and DynamicSlidingWindowLayer cache layers, "
                f"got {type(layer).__name__}; use the default DynamicCache (cache_implementation=None)"
            )
        if getattr(layer, "is_initialized", True) and layer.keys is not None and layer.keys.numel():
            yield layer


def _stored(layer, keys: torch.Tensor, values: torch.Tensor) -> None:
    layer.keys, layer.values = keys, values
    if type(layer) is DynamicSlidingWindowLayer:  # its length is a counter, not the tensor's (held open: the same)
        layer.cumulative_length = keys.shape[-2]


def truncate_cache(cache: Cache, length: int) -> None:
    """Keeps the first ``length`` positions of every layer, in place."""
    for layer in _stored_layers(cache):
        _stored(layer, layer.keys[..., :length, :], layer.values[..., :length, :])


def select_cache_positions(cache: Cache, positions: torch.Tensor) -> None:
    """Keeps only ``positions`` of every layer, in place (e.g. a tree's accepted path).

    Args:
        positions: ``[K]`` int64 ascending (the same entries for every row), or ``[B, K]`` (row b keeps
            ``positions[b]``: a batch whose rows accepted different paths).
    """
    for layer in _stored_layers(cache):
        if positions.ndim == 1:
            _stored(layer, layer.keys.index_select(-2, positions), layer.values.index_select(-2, positions))
        else:
            heads, dim = layer.keys.shape[1], layer.keys.shape[-1]
            index = positions[:, None, :, None].expand(-1, heads, -1, dim)  # [B, H_kv, K, D]
            _stored(layer, layer.keys.gather(2, index), layer.values.gather(2, index))


def select_cache_rows(cache: Cache, rows: torch.Tensor) -> None:
    """Keeps only batch ``rows`` (``[B']`` int64) of every layer, in place (e.g. the rows still generating)."""
    for layer in _stored_layers(cache):
        _stored(layer, layer.keys.index_select(0, rows), layer.values.index_select(0, rows))
