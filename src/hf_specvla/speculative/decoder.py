"""What the engine keeps for one target model between ``generate`` calls, in one object: [`SpeculativeDecoder`].

One decoder a model, made at its first speculative call and held by the model itself under one attribute
([`DECODER_ATTRIBUTE`]), as transformers keeps its compiled call on the model; nothing else is written onto the
model. It owns:

- the compiled verifications ([`CompiledGraphs`], one per ``CompileConfig``: the target's compiled call, every
  width and prefill compiled up front, the drafters' graphs, the rounds' input buffers);
- the static caches the calls reuse, the target's and its draft heads' ([`static_cache`]: emptied and handed out
  again, so that compiled graphs and CUDA graphs keep reading the same buffers);
- the caches a batched call decoded on ([`batch_decoded`]: no later call may continue them);
- the draft trees' structure tensors by shape (``tree_structures``: a round's trees repeat a few shapes);
- its decoder sessions by settings (``sessions``: [`DecoderSession`]'s, what ``generate`` prepared for each shape of
  a robot's calls), the most recently used [`MAX_SESSIONS`].

[`reset_compilation`] is a method of every decoder: ``torch._dynamo.reset()`` drops every model's graphs at once,
so it moves one epoch that all decoders compare to (the one thing they share), and each forgets what it compiled at
its next use. A deep copy of a model copies its decoder, whose compiled rounds close over the original: the copy gets
one of its own ([`of`]).
"""

from __future__ import annotations

import logging
import weakref
from collections import OrderedDict
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from transformers.cache_utils import Cache, StaticCache

logger = logging.getLogger(__name__)

#: the one attribute a target model holds: its decoder
DECODER_ATTRIBUTE = "_hf_specvla_decoder"
#: the decoder sessions a decoder keeps (settings a robot or server calls with), the least recently used dropped
MAX_SESSIONS = 8


class SpeculativeDecoder:
    """The engine's state for one target model (see the module docstring).

    Attributes:
        compiled_graphs: ``compile_settings(compile_config)`` -> its [`CompiledGraphs`] (``CompiledGraphs.for_model``
            makes them; this module imports nothing of the engine).
        static_caches: (slots, offloading, dtype written, device, batch size) -> a reusable ``StaticCache`` of the
            target's; ("draft head", its architecture, slots, dtype, device) -> a draft head's.
        epoch: the compilation epoch this decoder's compiled graphs were made in ([`reset_compilation`]).
    """

    #: moved by [`reset_compilation`]; a decoder of an older epoch forgets its compiled graphs at its next use
    _epoch = 0

    def __init__(self, model):
        self.model_ref = weakref.ref(model)
        self.compiled_graphs: dict = {}  # compile settings -> CompiledGraphs (no import of compiled: it imports this)
        self.static_caches: dict[tuple, StaticCache] = {}
        self._batch_decoded: weakref.WeakSet = weakref.WeakSet()
        #: draft trees' structure tensors by shape ([`TreeBatch`]'s ``structures``)
        self.tree_structures: dict[tuple, tuple[torch.Tensor, ...]] = {}
        #: settings key -> DecoderSession, least recently used first (``DecoderSession.of``)
        self.sessions: OrderedDict = OrderedDict()
        self.epoch = SpeculativeDecoder._epoch

    @classmethod
    def of(cls, model) -> SpeculativeDecoder:
        """``model``'s decoder, made at its first use; a copied model's (its decoder made for the original) replaced
        by one of its own."""
        decoder = model.__dict__.get(DECODER_ATTRIBUTE)
        if decoder is None or decoder.model_ref() is not model:
            if decoder is not None:
                logger.info(
                    "this %s is a copy of the model its compiled graphs were made for: compiling its own",
                    type(model).__name__,
                )
                _forget_copied_compiled_call(model)
            decoder = model.__dict__[DECODER_ATTRIBUTE] = cls(model)
        if decoder.epoch != SpeculativeDecoder._epoch:  # reset_compilation since: what it compiled is gone
            decoder.compiled_graphs.clear()
            decoder.epoch = SpeculativeDecoder._epoch
        return decoder

    # ----------------------------------------------------------------- compiled verification
    def compiled_functions(self) -> list:
        """The drafters' functions every verifier compiled (their graphs count against dynamo's limit)."""
        return [function for verifier in self.compiled_graphs.values() for function in verifier.functions]

    @classmethod
    def reset_compilation(cls) -> None:
        """``torch._dynamo.reset()``, and every model's decoder forgets what it compiled (its compiled graphs, made anew
        at their next use: the target's widths and prefills and its drafters' graphs)."""
        torch._dynamo.reset()
        cls._epoch += 1

    def session(self, key, make):
        """The decoder session under ``key`` (settings), or ``make()``'s, kept under it (the least recently used of
        more than [`MAX_SESSIONS`] dropped)."""
        session = self.sessions.get(key)
        if session is None:
            session = self.sessions[key] = make()
            while len(self.sessions) > MAX_SESSIONS:
                self.sessions.popitem(last=False)
        self.sessions.move_to_end(key)
        return session

    # ----------------------------------------------------------------- caches
    def static_cache(self, key: tuple, make, like=None) -> StaticCache:
        """The reusable static cache under ``key`` (emptied), or ``make()``'s, kept under it; one of other layer
        types than ``like``'s (a sliding-window model's) is made anew."""
        cache = self.static_caches.get(key)
        if cache is not None and (like is None or [type(a) for a in cache.layers] == [type(b) for b in like.layers]):
            cache.reset()
            return cache
        cache = self.static_caches[key] = make()
        return cache

    def mark_batch_decoded(self, cache: Cache, batched: bool) -> None:
        """Records whether a batched call decoded on ``cache`` last (its rows keep entries of drafts some rows
        rejected: no later call can continue it exactly)."""
        if batched:
            self._batch_decoded.add(cache)
        else:
            self._batch_decoded.discard(cache)

    def batch_decoded(self, cache: Cache) -> bool:
        """Whether a batched call of this model decoded on ``cache`` last ([`mark_batch_decoded`])."""
        return cache in self._batch_decoded


def _forget_copied_compiled_call(model) -> None:
    """Drops transformers' compiled model call from a deep copy of a model when it was compiled for the original
    (``torch.compile(original.__call__)``, copied as it is): ``get_compiled_call`` then compiles the copy's own."""
    compiled = model.__dict__.get("_compiled_call")
    original = getattr(compiled, "__wrapped__", None)
    if compiled is not None and getattr(original, "__self__", model) is not model:
        del model.__dict__["_compiled_call"]
