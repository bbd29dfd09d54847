"""KV-cache surgery after a verification: keep the accepted entries, drop the rest.

Works on transformers' layered caches (``cache.layers[i].keys / .values``, each ``[B, H_kv, S, D]``), for the layer
types where it is exact:

* ``DynamicLayer`` (full attention): every entry is kept, any prefix or path can be kept (by slicing).
* ``DynamicSlidingWindowLayer`` (Gemma-2/3, PaliGemma-2, Mistral with a window): the layer keeps only its last
  ``sliding_window - 1`` entries, so a rejected draft could push out an entry the accepted path still needs. When
  the whole generation fits in the window (prompt + ``max_new_tokens`` <= window, always true for a VLA prompt of a
  few hundred tokens against a 4096 window), sliding attention *is* full attention for every token greedy decoding
  emits, so [`open_sliding_windows`] holds the layers open (nothing dropped) while the loop runs and restores them
  afterwards. A generation that does not fit is refused before the first forward ([`check_rollback_cache`]).
* ``StaticLayer`` (``cache_implementation="static"``, a ``StaticCache``): preallocated ``[B, H_kv, max_cache_len, D]``
  buffers written at a length counter. Rolled back **in place**, never re-allocated (compiled graphs and CUDA graphs
  hold the buffers' addresses): a rejected entry is dropped by moving the counter back (the next forward overwrites
  it; keys past the counter are masked), a tree's accepted path is copied into consecutive slots. A batch keeps one
  counter for all rows: a row that kept fewer entries than another in a round leaves invalid slots (masked like
  prompt padding); when the free slots run short, [`compact_rows`] moves every row's valid entries to the front.
* ``StaticSlidingWindowLayer`` (a static cache of a model with sliding layers): allocates ``min(window,
  max_cache_len)`` slots and rolls its entries once full. When the generation fits in those slots it never rolls
  and is rolled back like a ``StaticLayer``; a generation that does not fit is refused before the first forward.

Any other layer (quantized, linear-attention / recurrent states, offloaded or indexed layers) cannot be rolled back
here and is refused before the first forward.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from contextlib import contextmanager
from contextvars import ContextVar

import torch
from transformers.cache_utils import (
    Cache,
    DynamicLayer,
    DynamicSlidingWindowLayer,
    StaticCache,
    StaticLayer,
    StaticSlidingWindowLayer,
)

#: preallocated layers written at a counter (exact types)
STATIC_LAYER_TYPES = (StaticLayer, StaticSlidingWindowLayer)
#: the layer types whose entries can be rolled back (exact types: subclasses change how entries are stored)
ROLLBACK_LAYER_TYPES = (DynamicLayer, DynamicSlidingWindowLayer, *STATIC_LAYER_TYPES)

#: what a sliding layer's window is raised to while held open (larger than any sequence)
_OPEN_WINDOW = 2**62


def is_static_cache(cache) -> bool:
    """Whether every layer of ``cache`` is static (a static cache, sliding windows included): what compiled decoding
    needs of a cache."""
    layers = getattr(cache, "layers", None)
    return bool(layers) and all(type(layer) in STATIC_LAYER_TYPES for layer in layers)


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
        ValueError: a sliding-window layer whose window is shorter than ``max_length``, a static layer with fewer
            slots than ``max_length`` (each names the values and the fix).
    """
    for index, layer in enumerate(_layers(cache)):
        kind = type(layer)
        if kind not in ROLLBACK_LAYER_TYPES:
            raise TypeError(
                f"speculative decoding rolls back rejected drafts in the KV cache, which it cannot do for layer "
                f"{index}'s {kind.__name__}; it supports DynamicLayer, DynamicSlidingWindowLayer (DynamicCache, the "
                f"default), StaticLayer and StaticSlidingWindowLayer (StaticCache, cache_implementation='static'). "
                f"Quantized, offloaded and recurrent / linear-attention caches are not supported: generate without "
                f"assistant_model / draft_ids for those, or with the default cache"
            )
        if kind is DynamicSlidingWindowLayer and max_length > layer.sliding_window:
            raise ValueError(
                f"layer {index} attends over a sliding window of {layer.sliding_window} tokens, but this generation "
                f"can reach {max_length} tokens (prompt + max_new_tokens): past the window, a rejected draft would "
                f"push out entries the accepted tokens still need. Keep prompt + max_new_tokens <= "
                f"{layer.sliding_window}, or generate without assistant_model / draft_ids"
            )
        if kind in STATIC_LAYER_TYPES:
            if layer.max_cache_len < max_length - 1:  # the last token is emitted, never fed (as in generate)
                raise ValueError(
                    f"the static KV cache holds {layer.max_cache_len} tokens (layer {index}'s {kind.__name__}) but "
                    f"this generation feeds up to {max_length - 1} (prompt + max_new_tokens - 1): build it with "
                    f"max_cache_len >= {max_length - 1}"
                    + (
                        f"; a sliding layer holds at most its window ({layer.max_cache_len}): keep prompt + "
                        f"max_new_tokens <= {layer.max_cache_len + 1} or use the default DynamicCache"
                        if kind is StaticSlidingWindowLayer
                        else ""
                    )
                )


def with_draft_slots(
    decoder, cache: Cache | None, slots_for: Callable[[int], int], batch_size: int = 1
) -> Cache | None:
    """``generate``'s own static cache (``cache_implementation="static"``) replaced by one of ``slots_for(its
    slots)`` slots, so that a draft tree fits beside the tokens greedy decoding would store (``generate`` sizes it
    for those alone; ``compiled.verification_slots``: room for the widest verification, rounded up). The larger
    cache is kept per model and size by its ``decoder`` (``SpeculativeDecoder.target_cache``) and reused, emptied,
    by later calls (its buffers keep their addresses, as compiled graphs want); a new one is allocated lazily, at
    the prefill, like the one it replaces. A cache the user passed, a cache already holding entries, or any other
    cache is returned as it is (a user's static cache: trees are cut to its free slots). With sliding-window layers
    (which hold at most their window) it grows only up to the window, so that every layer keeps the same number of
    slots (one explicit mask serves them all).

    Args:
        decoder: the target's ``SpeculativeDecoder`` (what keeps the reusable caches).
        slots_for: ``generate``'s slot count -> the slot count wanted (rounded: compiled graphs hold the cache's
            shape, so prompts of different lengths then share one graph per width).
        batch_size: the call's rows (a cache is reused only by calls of the same batch size: its layers take their
            batch dimension from the first forward).
    """
    if type(cache) is not StaticCache or getattr(cache, "_is_user_defined", False):
        return cache
    if any(getattr(layer, "is_initialized", False) for layer in cache.layers):
        return cache
    capacity = max(layer.max_cache_len for layer in cache.layers)
    slots = slots_for(capacity) - capacity
    if slots <= 0:
        return cache
    windows = [layer.max_cache_len for layer in cache.layers if type(layer) is StaticSlidingWindowLayer]
    if windows:  # a sliding layer holds at most its window: grow only within it (every layer keeps one slot count)
        slots = min(slots, min(windows) - capacity)
        if slots <= 0 or any(w != capacity for w in windows):
            return cache
    offloading = bool(getattr(cache, "offloading", False))
    return decoder.target_cache(capacity + slots, batch_size, offloading, like=cache)


def written_dtype(model) -> torch.dtype:
    """The dtype ``model``'s forward writes its keys and values in now: the autocast dtype of its device type inside
    ``torch.autocast`` for that device (a CPU model's keys are bfloat16 under ``torch.autocast("cpu")``), else the
    model's own (a static cache's layers take the dtype of their first write and keep it when reused)."""
    device_type = model.device.type
    if torch.is_autocast_enabled(device_type):
        return torch.get_autocast_dtype(device_type)
    return model.dtype


def static_capacity(cache: Cache) -> int | None:
    """The number of slots of the cache's static layers (the smallest), None when it has none: a forward over
    ``q`` tokens fits when ``cache_length(cache) + q <= static_capacity(cache)``."""
    sizes = [layer.max_cache_len for layer in _layers(cache) if type(layer) in STATIC_LAYER_TYPES]
    return min(sizes) if sizes else None


#: the host's count of each cache's entries while a speculative call works on it ([`host_length`]; a static layer
#: counts on the device, and reading its counter waits for the device): the call's own, by cache (``id`` -> entries),
#: in a context variable (each thread's call its own, a nested call its own copy), never an attribute written on
#: transformers' cache objects
_HOST_LENGTHS: ContextVar[dict[int, int] | None] = ContextVar("hf_specvla_host_lengths", default=None)
#: set to 1 (the tests do) to check the host's count against the cache's own counter at every read
CHECK_HOST_LENGTH = os.environ.get("HF_SPECVLA_CHECK_CACHE_LENGTH") == "1"


def cache_length(cache: Cache) -> int:
    """The number of entries the cache holds: the host's count inside [`host_length`], else the cache's own (a
    static layer's counter read from the device)."""
    lengths = _HOST_LENGTHS.get()
    known = None if lengths is None else lengths.get(id(cache))
    if known is None:
        return int(cache.get_seq_length())
    if CHECK_HOST_LENGTH and known != int(cache.get_seq_length()):
        raise RuntimeError(f"the host counts {known} cache entries, the cache holds {int(cache.get_seq_length())}")
    return known


@contextmanager
def host_length(cache: Cache):
    """Counts ``cache``'s entries on the host inside the block (a static cache: no read of its device counter per
    use); every change of the entries inside goes through this module's functions or [`note_appended`] (a forward
    that wrote new entries). Read once from the cache on entry; forgotten on exit."""
    if static_capacity(cache) is None:  # a dynamic cache counts on the host already
        yield
        return
    outer = _HOST_LENGTHS.get()
    token = _HOST_LENGTHS.set({**(outer or {}), id(cache): int(cache.get_seq_length())})
    try:
        yield
    finally:
        _HOST_LENGTHS.reset(token)


def _note_length(cache: Cache, length: int) -> None:
    lengths = _HOST_LENGTHS.get()
    if lengths is not None and id(cache) in lengths:
        lengths[id(cache)] = length


def note_appended(cache: Cache, count: int) -> None:
    """A forward wrote ``count`` new entries after the cache's (what [`host_length`] counts)."""
    lengths = _HOST_LENGTHS.get()
    if lengths is not None and id(cache) in lengths:
        lengths[id(cache)] += count


def holds_buffers(cache: Cache) -> bool:
    """Whether any layer has its entry buffers already (written once: a static layer keeps them, and its batch size,
    when emptied)."""
    return any(
        getattr(layer, "is_initialized", True) and getattr(layer, "keys", None) is not None and layer.keys.numel()
        for layer in _layers(cache)
    )


def cache_batch_size(cache: Cache) -> int:
    """The number of rows the cache's layers hold (after the first forward)."""
    return next(_stored_layers(cache)).keys.shape[0]


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
                f"speculative decoding can roll back only {', '.join(t.__name__ for t in ROLLBACK_LAYER_TYPES)} "
                f"cache layers, got {type(layer).__name__}; use the default DynamicCache (cache_implementation=None)"
            )
        if getattr(layer, "is_initialized", True) and layer.keys is not None and layer.keys.numel():
            yield layer


def _stored(layer, keys: torch.Tensor, values: torch.Tensor) -> None:
    """Makes ``keys`` / ``values`` ``[B, H_kv, K, D]`` the layer's entries (a static layer: copied into its first K
    slots in place, its counter set to K)."""
    if type(layer) in STATIC_LAYER_TYPES:
        length = keys.shape[-2]
        layer.keys[..., :length, :].copy_(keys)
        layer.values[..., :length, :].copy_(values)
        _set_static_length(layer, length)
        return
    layer.keys, layer.values = keys, values
    if type(layer) is DynamicSlidingWindowLayer:  # its length is a counter, not the tensor's (held open: the same)
        layer.cumulative_length = keys.shape[-2]


def _set_static_length(layer, length: int) -> None:
    """Moves a static layer's length counter(s) in place (the tensor keeps its address; a sliding layer also
    counts on the host)."""
    layer.cumulative_length.fill_(length)
    if type(layer) is StaticSlidingWindowLayer:
        layer.cumulative_length_int = length


def set_static_length(cache: Cache, length: int) -> None:
    """Moves every static layer's counter to ``length``, forward or back, in place (a forward move keeps entries that
    were written past the counter, e.g. by a compiled round that wrote them and was rolled back to replay)."""
    for layer in _stored_layers(cache):
        if type(layer) not in STATIC_LAYER_TYPES:
            raise TypeError(f"set_static_length needs static cache layers, got {type(layer).__name__}")
        if not 0 <= length <= layer.max_cache_len:
            raise ValueError(f"a static layer of {layer.max_cache_len} slots cannot hold {length} entries")
        _set_static_length(layer, length)
    _note_length(cache, length)


@contextmanager
def preserved_entries(cache: Cache):
    """Empties ``cache`` for the block (e.g. a throw-away forward writing from slot 0) and puts its entries back
    afterwards, in place (a static layer's buffers keep their addresses)."""
    length = cache_length(cache)
    saved = [
        (layer, layer.keys[..., :length, :].clone(), layer.values[..., :length, :].clone())
        for layer in _stored_layers(cache)
    ]
    truncate_cache(cache, 0)
    try:
        yield
    finally:
        for layer, keys, values in saved:
            _stored(layer, keys, values)
        _note_length(cache, length)


def truncate_cache(cache: Cache, length: int) -> None:
    """Keeps the first ``length`` positions of every layer, in place (a static layer: its counter moves back)."""
    lengths = _HOST_LENGTHS.get()
    if lengths is not None and id(cache) in lengths:
        lengths[id(cache)] = min(lengths[id(cache)], length)
    for layer in _stored_layers(cache):
        if type(layer) in STATIC_LAYER_TYPES:  # the counter only moves back, on the device (no host read)
            layer.cumulative_length.clamp_(max=length)
            if type(layer) is StaticSlidingWindowLayer:
                layer.cumulative_length_int = min(layer.cumulative_length_int, length)
        else:
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
    _note_length(cache, positions.shape[-1])


def keep_cache_path(cache: Cache, base: int, path: torch.Tensor) -> None:
    """Keeps the first ``base`` entries of every layer followed by the entries at ``base + path`` (a tree's accepted
    path), in place: only the path's entries move (a static layer: copied into the slots after ``base``).

    Args:
        base: the entries before the tree's (all kept).
        path: ``[B, A]`` int64 offsets of the kept nodes within the tree (row b keeps ``path[b]``).
    """
    length = path.shape[1]
    for layer in _stored_layers(cache):
        heads, dim = layer.keys.shape[1], layer.keys.shape[-1]
        index = (base + path)[:, None, :, None].expand(-1, heads, -1, dim)  # [B, H_kv, A, D]
        keys, values = layer.keys.gather(2, index), layer.values.gather(2, index)  # copies: no overlap with the slots
        if type(layer) in STATIC_LAYER_TYPES:
            layer.keys[..., base : base + length, :].copy_(keys)
            layer.values[..., base : base + length, :].copy_(values)
            _set_static_length(layer, base + length)
        else:
            prefix_keys, prefix_values = layer.keys[..., :base, :], layer.values[..., :base, :]
            _stored(layer, torch.cat([prefix_keys, keys], dim=-2), torch.cat([prefix_values, values], dim=-2))
    _note_length(cache, base + length)


def compact_rows(cache: Cache, valid: torch.Tensor) -> torch.Tensor:
    """Moves every row's valid entries to the front of the cache, in order, in place (a static layer's buffers keep
    their addresses and its counter moves to the longest row): the batch's rectangle shrinks to its longest row. The
    entries keep their positions (rotary positions are in the keys) and what attends to them does not change.

    Args:
        valid: ``[B, C]`` bool, True at the entries row b keeps (C: the cache's length).
    Returns:
        ``[B, C']`` bool, the entries' validity afterwards (row b: its first ``valid[b].sum()``), C' the longest row.
    """
    counts = valid.sum(dim=1)  # [B]
    length = int(counts.max())
    # per row, the columns of its valid entries first, in order (a stable sort of "is invalid"), cut to the longest row
    order = torch.sort((~valid).to(torch.uint8), dim=1, stable=True).indices[:, :length]  # [B, C']
    for layer in _stored_layers(cache):
        heads, dim = layer.keys.shape[1], layer.keys.shape[-1]
        index = order[:, None, :, None].expand(-1, heads, -1, dim)  # [B, H_kv, C', D]
        _stored(layer, layer.keys.gather(2, index), layer.values.gather(2, index))  # copies: then written in place
    _note_length(cache, length)
    return torch.arange(length, device=valid.device)[None] < counts[:, None]


def select_cache_rows(cache: Cache, rows: torch.Tensor) -> None:
    """Keeps only batch ``rows`` (``[B']`` int64) of every layer, in place (e.g. the rows still generating)."""
    for layer in _stored_layers(cache):
        _stored(layer, layer.keys.index_select(0, rows), layer.values.index_select(0, rows))
