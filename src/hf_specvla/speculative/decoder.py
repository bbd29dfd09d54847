"""The engine for one target model, in one object: [`SpeculativeDecoder`] holds what the model's calls reuse and
decodes every call.

One decoder a model, made at its first speculative call and held by the model itself under one attribute
([`DECODER_ATTRIBUTE`]), as transformers keeps its compiled call on the model; nothing else is written onto the
model. It **decodes** ([`decode`]: prepare -> prefill -> warm up -> a round until every row has stopped -> finish) and
it is **the one place a call triggers compiling** ([`warm_up`], right after the prefill: every verification width,
the next call's prefill graph; [`encode_images`], before ``generate``'s prefill: the image encoder). What it holds,
the parts of the engine below it are handed (a call's set-up, its drafters' contexts), never look up:

- the compiled graphs ([`CompiledGraphs`], one per ``CompileConfig``, [`graphs`]: the target's compiled call, every
  width and prefill compiled up front, the drafters' graphs, the rounds' input buffers);
- the static caches the calls reuse, the target's and its draft heads' ([`static_cache`], [`target_cache`]: emptied
  and handed out again, so that compiled graphs and CUDA graphs keep reading the same buffers);
- the caches a batched call decoded on ([`batch_decoded`]: no later call may continue them);
- the draft trees' structure tensors by shape (``tree_structures``: a round's trees repeat a few shapes);
- its decoder sessions by settings (``sessions``: [`DecoderSession`]'s, what ``generate`` prepared for each shape of
  a robot's calls), the most recently used [`MAX_SESSIONS`].

[`reset_compilation`] (``compiled.reset_compilation``): ``torch._dynamo.reset()`` drops every model's graphs at
once, so it moves one epoch that all decoders compare to, and each forgets what it compiled at its next use. A deep
copy of a model copies its decoder, whose compiled rounds close over the original: the copy gets one of its own
([`of`]).
"""

from __future__ import annotations

import logging
import weakref
from collections import OrderedDict
from collections.abc import Callable

import torch
from transformers import GenerationConfig, LogitsProcessorList, PreTrainedModel, StoppingCriteriaList
from transformers.cache_utils import Cache, StaticCache

from .cache import host_length, open_sliding_windows, written_dtype
from .call import finish, prepare
from .compat import CACHE_KEY
from .compiled import (
    NODE_BUCKETS,
    CompiledGraphs,
    allow_graphs_beside,
    compile_settings,
    reset_compilation,
)
from .config import SpeculationConfig
from .outputs import SpeculativeDecoderOnlyOutput
from .rounds import CallStopping, decode_round, drop_finished_rows, next_draft_round, prefill
from .state import SpeculativeCall
from .stats import SpeculationStats
from .tree import TreeBatch
from .verify import Pending
from .vision import encoder_inputs, takes_encoded_images, with_encoded_images

logger = logging.getLogger(__name__)

#: the one attribute a target model holds: its decoder
DECODER_ATTRIBUTE = "_hf_specvla_decoder"
#: the decoder sessions a decoder keeps (settings a robot or server calls with), the least recently used dropped
MAX_SESSIONS = 8


class SpeculativeDecoder:
    """The engine for one target model: what its calls reuse, and the call itself (see the module docstring).

    Attributes:
        compiled_graphs: ``compile_settings(compile_config)`` -> its [`CompiledGraphs`] ([`graphs`]).
        static_caches: (slots, offloading, dtype written, device, batch size) -> a reusable ``StaticCache`` of the
            target's; ("draft head", its architecture, slots, dtype, device) -> a draft head's.
        epoch: the compilation epoch this decoder's compiled graphs were made in ([`reset_compilation`]).
    """

    def __init__(self, model: PreTrainedModel):
        self.model_ref = weakref.ref(model)
        self.compiled_graphs: dict[str, CompiledGraphs] = {}
        self.static_caches: dict[tuple, StaticCache] = {}
        self._batch_decoded: weakref.WeakSet = weakref.WeakSet()
        #: draft trees' structure tensors by shape ([`TreeBatch`]'s ``structures``)
        self.tree_structures: dict[tuple, tuple[torch.Tensor, ...]] = {}
        #: settings key -> DecoderSession, least recently used first (``DecoderSession.of``)
        self.sessions: OrderedDict = OrderedDict()
        self.epoch = CompiledGraphs.epoch

    @classmethod
    def of(cls, model: PreTrainedModel) -> SpeculativeDecoder:
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
        if decoder.epoch != CompiledGraphs.epoch:  # reset_compilation since: what it compiled is gone
            decoder.compiled_graphs.clear()
            decoder.epoch = CompiledGraphs.epoch
        return decoder

    @property
    def model(self) -> PreTrainedModel:
        return self.model_ref()

    # ----------------------------------------------------------------- a call
    def decode(
        self,
        input_ids: torch.LongTensor,
        logits_processor: LogitsProcessorList,
        stopping_criteria: StoppingCriteriaList,
        generation_config: GenerationConfig,
        speculation: SpeculationConfig,
        draft_ids: torch.LongTensor | None,
        model_kwargs: dict,
        on_row_finished: Callable[[int, torch.Tensor, SpeculationStats], None] | None = None,
        kept_plans: dict | None = None,
    ) -> SpeculativeDecoderOnlyOutput | torch.LongTensor:
        """One speculative call of the model, on what ``generate`` prepared (``speculative_generate``'s arguments,
        the settings whole): prepare (every argument checked, the rows' drafter sessions, the [`RoundPlan`]; a
        session's shape hands its ``kept_plans``: ``call.KeptPlan``) -> prefill -> [`warm_up`] -> a round until
        every row has stopped -> finish (the cache left as greedy leaves it, statistics, the output).

        Raises:
            TypeError: ``on_row_finished`` is neither callable nor None (and whatever [`prepare`] refuses).
        """
        if on_row_finished is not None and not callable(on_row_finished):
            raise TypeError(
                f"on_row_finished must be a callable (row: int, new_tokens: Tensor, stats: SpeculationStats) -> None "
                f"or None, got {type(on_row_finished).__name__}"
            )
        model = self.model
        call = prepare(
            self, input_ids, logits_processor, generation_config, speculation, draft_ids, model_kwargs, kept_plans
        )
        call.on_row_finished = on_row_finished
        cache = call.state.target_cache
        with open_sliding_windows(cache), host_length(cache):  # exact: the generation fits the window (checked)
            stopping = CallStopping(stopping_criteria)  # answered on the host where it can be, read once
            trees = prefill(model, call, logits_processor, stopping)
            self.warm_up(call, trees)
            drop_finished_rows(call.state, fixed_batch=call.plan.capacity is not None)
            while call.state.rows:
                decode_round(model, call, logits_processor, stopping)
        return finish(call, generation_config)

    def warm_up(self, call: SpeculativeCall, prefill_trees: TreeBatch) -> None:
        """The one place a call triggers compiling (the image encoder aside: [`encode_images`]): after a compiled
        call's prefill, before any compiled round, every graph its rounds and its next call run is compiled, so that
        nothing compiles mid-episode:

        - the target's: every verification width its rounds can meet (fed the next round's pending tokens, as it feeds
          them) and the next call's prefill graph (this prefill fed once more: ``CallVerifier.compile_ahead``);
        - each row's drafter's (``DraftSession.warm_up``, given the round that comes next: a draft head's round and
          its block before the prefill).

        The seconds it took are the call's ``compile_seconds`` (the drafters' booked by their sessions). Nothing for
        an eager call, or when every graph is held."""
        state, verifier = call.state, call.plan.verifier
        if not verifier.compiled:
            return
        with call.stopwatch.section("draft_seconds"):
            for b, row in enumerate(state.rows):  # finished rows too: a block drafted before their prefill
                row.session.warm_up(next_draft_round(state, call.plan, b))
        following = Pending(
            {CACHE_KEY: state.target_cache},
            state.pending_ids,
            state.pending_positions,
            state.key_valid,
            state.position_offsets,
        )
        prompt = Pending(call.model_inputs, *call.prompt)
        call.stats.compile_seconds = verifier.compile_ahead(self.model, following, prompt, prefill_trees)

    @torch.no_grad()
    def encode_images(self, kwargs: dict, compile_config) -> dict:
        """``generate``'s keyword arguments for a speculative call, its images encoded by the compiled image encoder
        when the call compiles its verifications (``compile_config``: the call's, [`compiled_call_config`]'s
        decision; None: eager) and the model takes pre-encoded images
        (its forward has ``mm_encoder_outputs``, its base model ``get_image_features``); else ``kwargs`` unchanged.
        Without gradients, as ``generate`` (decorated ``torch.no_grad``) encodes them: a call of ``model.generate``
        with gradients on and a session's call meet the same graphs (a graph traced with them on would fail its
        guards at the other's every call, and compile again).
        The encoder's inputs (``pixel_values`` and whatever else ``get_image_features`` takes from the call) leave
        the keyword arguments, as transformers' own encoding removes them. The encoder compiles at its first call of
        a shape, here (``generate`` encodes before its prefill, so before [`warm_up`])."""
        model = self.model
        if compile_config is None or not takes_encoded_images(model, kwargs):
            return kwargs
        graphs = self.graphs(compile_config)
        encoder = graphs.image_encoder(model, encoder_inputs(model.base_model.get_image_features, kwargs))
        return with_encoded_images(model, kwargs, encoder)

    # ----------------------------------------------------------------- compiled graphs
    def graphs(self, compile_config) -> CompiledGraphs:
        """The model's compiled graphs for ``compile_config`` (made at their first use), dynamo's recompile limit
        raised to hold one graph per bucket (past the limit dynamo would silently run eagerly); their model call
        fetched again (a caller may have wrapped ``get_compiled_call``: the benchmarks' clock). A model copied with
        ``copy.deepcopy`` gets its own ([`of`]). Changes to the model itself fail the guards its rounds keep
        (``fused.round_guards``) and recompile."""
        model = self.model
        settings = compile_settings(compile_config)
        graphs = self.compiled_graphs.get(settings)
        if graphs is None:
            graphs = self.compiled_graphs[settings] = CompiledGraphs(model, compile_config)
        else:
            graphs.call = graphs.model_call(model)
        graphs.reserve_graphs(2 * len(NODE_BUCKETS))  # every width, with / without hidden states
        return graphs

    def compiled_functions(self) -> list:
        """The drafters' functions every graph set compiled (their graphs count against dynamo's limit)."""
        return [function for graphs in self.compiled_graphs.values() for function in graphs.functions]

    @classmethod
    def reset_compilation(cls) -> None:
        """``torch._dynamo.reset()``, and every model's decoder forgets what it compiled (its compiled graphs, made
        anew at their next use: the target's widths and prefills and its drafters' graphs)."""
        reset_compilation()

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
    def static_cache(self, key: tuple, make: Callable[[], StaticCache], like=None) -> StaticCache:
        """The reusable static cache under ``key`` (emptied), or ``make()``'s, kept under it; one of other layer
        types than ``like``'s (a sliding-window model's) is made anew."""
        cache = self.static_caches.get(key)
        if cache is not None and (like is None or [type(a) for a in cache.layers] == [type(b) for b in like.layers]):
            cache.reset()
            return cache
        cache = self.static_caches[key] = make()
        return cache

    def target_cache(
        self, slots: int, batch_size: int, offloading: bool = False, like: StaticCache | None = None
    ) -> StaticCache:
        """An empty ``StaticCache`` of ``slots`` slots for ``batch_size`` rows of the model, made once per (slots,
        offloading, dtype written, device, batch size), then emptied and handed out again: its buffers keep their
        addresses, so compiled graphs (which hold the cache's shape) and CUDA graphs (its buffers) are reused. What
        ``cache.with_draft_slots`` puts in place of ``generate``'s own cache ([`reusable_static_cache`]).

        Args:
            like: a cache whose layer types the reused one must have (a sliding-window model's); None: any.
        """
        model = self.model
        key = (slots, offloading, written_dtype(model), model.device, batch_size)
        text_config = model.config.get_text_config(decoder=True)
        return self.static_cache(
            key, lambda: StaticCache(config=text_config, max_cache_len=slots, offloading=offloading), like
        )

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


def reusable_static_cache(
    model: PreTrainedModel, slots: int, batch_size: int, offloading: bool = False, like: StaticCache | None = None
) -> StaticCache:
    """``model``'s reusable static cache of ``slots`` slots for ``batch_size`` rows, emptied
    ([`SpeculativeDecoder.target_cache`]): what a caller passes as ``past_key_values`` for transformers' compiled
    greedy decoding to keep one graph per shape (a server's greedy baseline)."""
    return SpeculativeDecoder.of(model).target_cache(slots, batch_size, offloading, like)


def allow_graphs_held(model: PreTrainedModel) -> None:
    """Raises this thread's recompile limit to hold every graph dynamo holds for ``model``'s forward and for its
    compiled graphs' drafter functions (``compiled.graphs_held``), and transformers' own beside them: dynamo's
    settings are per thread (a ``ContextVar``), so a model compiled in one thread and decoding in another (a server's
    worker) would meet the default limit there, with more graphs than it allows, and fail at its next compile
    (``FailOnRecompileLimitHit`` under ``fullgraph=True``). Makes no decoder."""
    decoder = model.__dict__.get(DECODER_ATTRIBUTE)
    functions = decoder.compiled_functions() if decoder is not None else []
    allow_graphs_beside([type(model).forward, *functions])


def _forget_copied_compiled_call(model) -> None:
    """Drops transformers' compiled model call from a deep copy of a model when it was compiled for the original
    (``torch.compile(original.__call__)``, copied as it is): ``get_compiled_call`` then compiles the copy's own."""
    compiled = model.__dict__.get("_compiled_call")
    original = getattr(compiled, "__wrapped__", None)
    if compiled is not None and getattr(original, "__self__", model) is not model:
        del model.__dict__["_compiled_call"]
