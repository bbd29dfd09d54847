"""Compiled verification: the target's verification forwards at a few fixed widths, each compiled once.

A compiled graph (and a CUDA graph) holds one input shape. Every verification after the prefill feeds the pending
token and a draft tree: its node count is rounded **up** to a width bucket (filler nodes pad it, see
[`TreeBatch`]), its mask is always the explicit ``[1, 1, 1 + N, slots]`` tree mask over the static cache's slots,
and it keeps ``1 + N`` logits, so a call site compiles a graph per bucket it meets (per batch size: a batch keeps
its rows in the static cache, finished ones included) and none afterwards, whatever the drafts, the accepted lengths
or the tree shapes. On the CPU the buckets of 2 nodes and more are one graph whose node count is a dynamic dimension
([`dynamic_widths`], ``verify.mark_width_dynamic``), width 0 (a plain decoding step) its own. Near the end of the
cache, where a bucket no longer fits the free slots, the tree is cut to the largest bucket that does (fewer drafts,
still exact) rather than compiling a new width.

Compilation is transformers' own: ``model.get_compiled_call(generation_config.compile_config)``, under the criteria
of its compiled greedy decoding (a static cache; a CUDA / XPU device, or ``CompileConfig._compile_all_devices``; not
``disable_compile``; no quantizer that refuses it). So ``cache_implementation="static"`` speeds up speculative and
plain greedy decoding alike, and the two share the compiled model call.

The prefill (the prompt, images included, and the drafts verified inside it) runs through the same compiled call
as **one graph for every prompt length and draft count**: its sequence dimensions are marked dynamic
([`mark_length_dynamic`]). That graph is compiled at the end of a call site's first prefill, which runs eagerly
(some models install hooks on their first forward, which dynamo cannot trace), by a throw-away prefill over the
same inputs, the cache's entries saved and put back; later calls' prefills are compiled. A model whose forward over
the prompt does not trace into one graph keeps an eager prefill (logged once).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from functools import cache
from types import MappingProxyType

import torch
from transformers import PreTrainedModel

from .cache import cache_batch_size, cache_length, is_static_cache, preserved_entries, truncate_cache
from .exported import export_call
from .fused import accepting_forward, full_guards_asked, round_guards
from .graph_files import (
    FileBackedFunction,
    GraphStore,
    architecture,
    environment,
    graph_folder,
    signature,
    with_guard_filter,
)
from .precision import exact_compile_config
from .regions import compile_layers_once, layer_regions_asked
from .tree import DraftTree, TreeBatch
from .verify import CompiledVerification, InputBuffers, Pending, Verification

logger = logging.getLogger(__name__)

#: the node counts a compiled verification is padded to (0: a plain decoding step); a graph per bucket met (on the
#: CPU one for the buckets from 2: [`dynamic_widths`])
NODE_BUCKETS: tuple[int, ...] = (0, 2, 4, 8, 16, 32)  # checked by check_buckets below

#: generate's own static cache is rebuilt with room for the largest bucket, its slot count rounded up to a multiple of
#: this: the compiled graphs hold the slot count, so prompts of different lengths share them
SLOT_MULTIPLE = 64


def rounded_slots(entries: int) -> int:
    """``entries`` rounded up to a multiple of [`SLOT_MULTIPLE`]: the slots of a static cache compiled graphs hold."""
    return -(-entries // SLOT_MULTIPLE) * SLOT_MULTIPLE


def verification_slots(generate_slots: int) -> int:
    """The slots of the static cache a compiled speculative call decodes on, for ``generate``'s own static cache of
    ``generate_slots`` (its ``max_length - 1``: the prompt and the new tokens but the last, which is never fed): room
    for the widest verification (``NODE_BUCKETS[-1]``) beside them, rounded up ([`rounded_slots`]). What the call
    sizes its cache with ([`with_draft_slots`]) and what a server plans its prompt tiers with."""
    return rounded_slots(generate_slots + NODE_BUCKETS[-1])


#: graphs transformers' own compiled decoding may hold on the same model call (greedy's decode step, assisted
#: generation's verification lengths) beside ours: the recompile limit is raised to the buckets + this
_GRAPHS_BESIDE_OURS = 16

_DEVICES_COMPILED_BY_DEFAULT = ("cuda", "xpu", "neuron", "tpu")

#: a model attribute a clock may set: ``wrap(call) -> call``, applied to every compiled call the engine makes of its
#: own around the model's forward (a round's forward with its acceptance, ``speculative.fused``), as the clock wraps
#: transformers' ``get_compiled_call`` for the rest (``benchmarks.speed.ForwardClock``)
CALL_WRAPPER_ATTRIBUTE = "_hf_specvla_wrap_compiled_call"

#: the same for the engine's compiled image encoder (``speculative.vision``): ``wrap(encoder) -> encoder``
ENCODER_WRAPPER_ATTRIBUTE = "_hf_specvla_wrap_compiled_encoder"


def compiled_decoding_kwargs(device_type: str = "cpu") -> dict:
    """``generate`` arguments for transformers' compiled decoding on ``device_type``: a static cache and a
    ``CompileConfig`` (CUDA graphs on a GPU, inductor's default mode elsewhere, where transformers compiles only when
    told with ``_compile_all_devices``). The same for greedy (transformers' own compiled greedy decoding) and for
    speculative decoding (compiled verification)."""
    from transformers import CompileConfig

    if device_type in _DEVICES_COMPILED_BY_DEFAULT:
        return dict(cache_implementation="static", compile_config=CompileConfig(fullgraph=True, dynamic=False))
    config = CompileConfig(fullgraph=True, dynamic=False, mode="default")
    config._compile_all_devices = True
    return dict(cache_implementation="static", compile_config=config)


def call_compile_config(model: PreTrainedModel, compile_config, disable_compile: bool | None, static_cache: bool):
    """The one decision whether a speculative call compiles, and with what: the ``CompileConfig`` its graphs (the
    verification widths, the prefill, the image encoder, a draft head's rounds) are compiled with, or None (eager).

    transformers' criteria for its compiled greedy decoding: a cache whose layers are all static (``static_cache``);
    ``disable_compile`` unset; a CUDA / XPU / Neuron / TPU device, or ``compile_config._compile_all_devices`` (a
    warning once per device type where a ``compile_config`` is ignored); no quantizer that refuses compilation; no
    layer offloaded to the CPU or the disk. Where it compiles without a ``compile_config`` (a GPU), the model's
    default one (``_default_compile_config``), as transformers' ``get_compiled_call`` does.
    """
    if not static_cache or disable_compile:
        return None
    all_devices = compile_config is not None and bool(getattr(compile_config, "_compile_all_devices", False))
    if model.device.type not in _DEVICES_COMPILED_BY_DEFAULT and not all_devices:
        if compile_config is not None:
            _warn_eager_device(model.device.type)
        return None
    quantizer = getattr(model, "hf_quantizer", None)
    if quantizer is not None and not getattr(quantizer, "is_compileable", False):
        return None
    devices = set(getattr(model, "hf_device_map", {}).values())
    if "disk" in devices or ("cpu" in devices and len(devices) > 1):
        return None
    return compile_config or model._default_compile_config()


def compiled_call_config(model: PreTrainedModel, kwargs: dict):
    """[`call_compile_config`] for ``generate(**kwargs)`` before it runs: each setting as ``generate`` resolves it (the
    call's keyword, else its ``generation_config``'s, else the model's), the cache the call is given or names."""

    def setting(name: str):
        if name in kwargs:
            return kwargs[name]
        return getattr(kwargs.get("generation_config") or model.generation_config, name, None)

    cache = kwargs.get("past_key_values")
    static = setting("cache_implementation") == "static" if cache is None else is_static_cache(cache)
    return call_compile_config(model, setting("compile_config"), setting("disable_compile"), static)


@cache
def _warn_eager_device(device_type: str) -> None:
    """Says once per device type that a ``compile_config`` is ignored there."""
    logger.warning(
        "compile_config is set but the target is on %s, which transformers compiles only with "
        "compile_config._compile_all_devices = True: verifying eagerly",
        device_type,
    )


#: ``HF_SPECVLA_DYNAMIC_WIDTHS``: ``1`` one graph for a round's widths from 2 nodes on every device, ``0`` a graph per
#: width everywhere; unset: one graph on the CPU ([`dynamic_widths`])
DYNAMIC_WIDTHS_VARIABLE = "HF_SPECVLA_DYNAMIC_WIDTHS"


def dynamic_widths(device_type: str) -> bool:
    """Whether a compiled round's widths of 2 nodes and more run as one graph whose node count is a dynamic
    dimension (``verify.mark_width_dynamic``) instead of one graph per width: a compile instead of one per width
    (``NODE_BUCKETS`` 2 4 8: 3 -> 1), at a forward that costs about as much (docs/design.md, "The compiled round").
    On by default on the CPU; elsewhere (a CUDA graph per width either way, Triton kernels of a dynamic size not
    measured against static ones) with ``HF_SPECVLA_DYNAMIC_WIDTHS=1``; ``=0`` turns it off everywhere."""
    asked = os.environ.get(DYNAMIC_WIDTHS_VARIABLE, "")
    if asked not in ("", "0", "1"):
        raise ValueError(f"{DYNAMIC_WIDTHS_VARIABLE}={asked!r}: expected 1 (one graph), 0 (a graph per width) or unset")
    return asked == "1" if asked else device_type == "cpu"


def compile_settings(compile_config) -> str:
    """A hashable description of a ``CompileConfig`` (what its compiled graphs depend on)."""
    return repr(sorted(compile_config.to_dict().items()))


def reset_compilation() -> None:
    """``torch._dynamo.reset()`` and every model's decoder forgets what it compiled up front (the next call compiles
    every width, prefill and draft-head graph again, before its first compiled round): the compilation epoch that
    every ``SpeculativeDecoder`` compares to ([`CompiledGraphs.epoch`]) moves."""
    torch._dynamo.reset()
    CompiledGraphs.epoch += 1


#: the model inputs with a sequence dimension in a prefill, and that dimension, from the end ([`mark_length_dynamic`])
_SEQUENCE_DIMS = MappingProxyType(
    {"input_ids": -1, "inputs_embeds": -2, "position_ids": -1, "attention_mask": -2, "logits_to_keep": -1}
)


def mark_length_dynamic(inputs: dict) -> None:
    """Marks the sequence dimension of a prefill's inputs dynamic (``torch._dynamo.mark_dynamic``): ``input_ids`` /
    ``inputs_embeds`` ``[B, P + N]``, ``position_ids`` ``[B, P + N]``, the 4D mask ``[B, 1, P + N, slots]``, and the
    index tensor ``logits_to_keep`` ``[2 + N]``, so that one graph serves every prompt length and node count."""
    for name, dim in _SEQUENCE_DIMS.items():
        value = inputs.get(name)
        if isinstance(value, torch.Tensor):
            torch._dynamo.mark_dynamic(value, value.ndim + dim)


class PrefillCall:
    """A compiled model call run over a prefill as **one graph for every prompt length and node count**: the
    sequence dimensions of its inputs are marked dynamic ([`mark_length_dynamic`]) and the logits it keeps are chosen
    by an index tensor over one row more than asked (an int would be a constant of the graph, a dimension of size 1
    would be specialised), that row dropped from the outputs. Needs a prompt of 2 tokens or more.

    Args:
        forward: the compiled model call (transformers' ``get_compiled_call``).
    """

    def __init__(self, forward: Callable):
        self.forward = forward

    def __call__(self, *, logits_to_keep: int, **inputs):
        total = inputs["input_ids"].shape[-1]
        inputs["logits_to_keep"] = torch.arange(total - logits_to_keep - 1, total, device=inputs["input_ids"].device)
        mark_length_dynamic(inputs)
        outputs = self.forward(**inputs)
        outputs.logits = outputs.logits[:, 1:]
        return outputs


class CompiledGraphs:
    """Everything hf_specvla compiles for one model under one ``CompileConfig``: transformers' compiled model call
    (shared with its compiled greedy decoding) and what was compiled up front for it, by what the graphs depend on
    (cache slots, hidden states returned, buckets, batch size): every verification width, the prefill's graph, the
    prefills that stay eager; and its drafters' graphs (a draft head's compiled round, [`compiled_function`],
    [`compile_once`]). Kept by the model's ``SpeculativeDecoder`` (``graphs``), as transformers keeps its compiled call
    on the model; the decoder has a call compile what it needs right after its first prefill, outside the round loop
    (``SpeculativeDecoder.warm_up``: [`compile_widths`], [`compile_prefill`]).

    On a CUDA device transformers' ``CompileConfig`` compiles with ``mode="reduce-overhead"``: each (batch size,
    width) graph is captured as a CUDA graph, its inputs copied into static buffers at each replay (the outputs, which
    the next replay overwrites, are copied by [`CompiledVerification`]); elsewhere inductor's default mode.

    It also owns the graph budget: dynamo's recompile limit (a per-thread setting, counted per code object across
    every caller) is raised from the graphs dynamo itself holds for the model's forward and the drafters' functions
    ([`graphs_held`]) plus the ones about to be compiled, never from a count of our own. The model's
    ``SpeculativeDecoder`` holds them (one per ``CompileConfig``) and forgets them at [`reset_compilation`]
    (which moves [`epoch`])."""

    #: the compilation epoch: moved by [`reset_compilation`]; a decoder of an older one forgets its compiled graphs
    epoch = 0

    def __init__(self, model: PreTrainedModel, compile_config):
        #: the settings its graphs compile with (in bf16 / fp16, rounding as eager decoding does: precision.py)
        self.compile_config = exact_compile_config(model, compile_config)
        self.model_forward = type(model).forward  # the code dynamo compiles for ``call`` (its graphs: graphs_held)
        folder = graph_folder(model.device.type)
        #: where its graphs are files (None: compiled in memory, by dynamo, as transformers compiles)
        self.store = GraphStore(folder) if folder is not None else None
        #: the decoder layers compiled once for all (``regions``: where graphs are files and the user asks for it)
        self.layer_regions = compile_layers_once(model) if self.store is not None and layer_regions_asked() else 0
        #: what its graphs depend on besides their inputs (the versions, the model's architecture; no weights)
        self.graph_key = (
            {**environment(), "model": architecture(model), "layer_regions": self.layer_regions}
            if self.store is not None
            else None
        )
        #: the model call as a file-backed function (None: transformers' ``get_compiled_call``)
        self.file_call = self._file_backed(model_call(model), None) if self.store is not None else None
        self.call: Callable = self.model_call(model)
        #: whether a round's widths from ``DYNAMIC_WIDTH_FROM`` nodes share one graph ([`dynamic_widths`])
        self.dynamic_widths = dynamic_widths(model.device.type)
        self.widths_compiled: set[tuple] = set()  # (slots, hidden states, buckets, batch size)
        self.prefills_compiled: set[tuple] = set()  # (slots, hidden states, batch size)
        self.prefills_eager: set[tuple] = set()  # the same keys, whose forward over the prompt did not compile
        self.functions: dict[Callable, Callable] = {}  # drafters' functions, compiled ([`compiled_function`])
        self.image_batch_sizes: set[int] = set()  # the batch sizes the image encoder met ([`image_encoder`])
        #: the image encoder's inputs' signature -> it exported and compiled as a file, or None: export refused it
        self.image_encoders: dict[object, Callable | None] = {}
        #: (batch size, query tokens, slots, dtype, device) -> the rounds' input tensors ([`input_buffers`])
        self.buffers: dict[tuple, InputBuffers] = {}
        self.drafting_compiled: set[tuple] = set()  # drafters' work compiled up front ([`compile_once`])
        #: hidden states returned -> the round's forward and acceptance as one function ([`accepting_call`])
        self.accepting: dict[tuple[int, ...] | None, Callable] = {}

    def model_call(self, model: PreTrainedModel) -> Callable:
        """The compiled model call: its graphs as files ([`graph_files`]) wrapped by the model's clock when it has one
        ([`CALL_WRAPPER_ATTRIBUTE`]), else transformers' ``get_compiled_call`` (which a clock wraps itself)."""
        if self.file_call is None:
            return model.get_compiled_call(self.compile_config)
        wrap = model.__dict__.get(CALL_WRAPPER_ATTRIBUTE)
        return self.file_call if wrap is None else wrap(self.file_call)

    def _file_backed(self, function: Callable, guard_filter: Callable | None) -> FileBackedFunction:
        """``function`` compiled with this verifier's settings, its graphs as files in its store."""
        return FileBackedFunction(
            function, self.compile_config.to_dict(), self.graph_key, self.store, guard_filter=guard_filter
        )

    # ----------------------------------------------------------------- the graph budget
    def reserve_graphs(self, count: int, function: Callable | None = None) -> None:
        """Raises this thread's recompile limit so that ``count`` more graphs of ``function`` (default: the model's
        forward) fit beside the graphs dynamo holds for it already and transformers' own (past the limit dynamo
        would refuse under ``fullgraph=True``, or silently run eagerly)."""
        allow_graphs(graphs_held(function or self.model_forward) + count + _GRAPHS_BESIDE_OURS)

    # ----------------------------------------------------------------- the rounds' inputs
    def input_buffers(self, batch_size: int, queries: int, slots: int, dtype: torch.dtype, device) -> InputBuffers:
        """The input tensors every verification of this shape writes into ([`InputBuffers`]): made at the first one
        (the width's compile, [`compile_widths`]), the same tensors afterwards. On CUDA their addresses are marked
        static, so the (batch size, width) CUDA graph reads them where they are instead of copying them in."""
        key = (batch_size, queries, slots, dtype, torch.device(device))
        buffers = self.buffers.get(key)
        if buffers is None:
            buffers = self.buffers[key] = InputBuffers.empty(batch_size, queries, slots, dtype, device)
            if torch.device(device).type == "cuda":
                for tensor in buffers.tensors():
                    torch._dynamo.mark_static_address(tensor)
        return buffers

    # ----------------------------------------------------------------- drafters' graphs
    def compiled_function(
        self, function: Callable, graphs: int, fullgraph: bool | None = None, guard_filter: Callable | None = None
    ) -> Callable:
        """``torch.compile(function)`` with this verifier's ``CompileConfig`` settings (as transformers'
        ``get_compiled_call`` compiles a model's call; ``fullgraph`` overrides the config's), made once; dynamo's
        recompile limit is raised so that ``graphs`` graphs (one per input shape the caller will meet) fit beside
        others. ``guard_filter``: the guards its graphs keep (``torch.compile``'s ``guard_filter_fn``, for this
        function alone); None: all of them."""
        self.reserve_graphs(graphs, function)
        if function not in self.functions:
            settings = self.compile_config.to_dict()
            if fullgraph is not None:
                settings["fullgraph"] = fullgraph
            if self.store is not None and settings.get("fullgraph"):  # the file route saves whole graphs only
                self.functions[function] = self._file_backed(function, guard_filter)
                return self.functions[function]
            if guard_filter is not None:
                settings = with_guard_filter(settings, guard_filter)
            self.functions[function] = torch.compile(function, **settings)
        return self.functions[function]

    def image_encoder(self, model: PreTrainedModel, inputs: dict) -> Callable:
        """``model.base_model.get_image_features`` compiled for ``inputs`` (the tensors it takes, see
        ``speculative.vision``), wrapped by the model's clock when it has one ([`ENCODER_WRAPPER_ATTRIBUTE`]). With
        graph files ([`graph_files`]): exported as one graph per input signature ([`export_call`]: transformers'
        output-capturing wrappers do not trace into one dynamo graph) and compiled as a file, so that a later process
        loads it; without them, or where export refuses the code, compiled by dynamo in memory with graph breaks
        allowed, one graph per batch size."""
        wrap = model.__dict__.get(ENCODER_WRAPPER_ATTRIBUTE) or (lambda encoder: encoder)
        if self.store is not None:
            key = signature(inputs)
            if key not in self.image_encoders:
                self.image_encoders[key] = self._exported_encoder(model, inputs)
            if self.image_encoders[key] is not None:
                return wrap(self.image_encoders[key])
        function = model.base_model.get_image_features
        batch_size = inputs["pixel_values"].shape[0]
        if function not in self.functions or batch_size not in self.image_batch_sizes:
            self.image_batch_sizes.add(batch_size)
            self.compiled_function(function, len(self.image_batch_sizes), fullgraph=False)
        return wrap(self.functions[function])

    def _exported_encoder(self, model: PreTrainedModel, inputs: dict) -> Callable | None:
        """The image encoder exported for ``inputs``' signature and compiled as a graph file (keyed by the exported
        code's digest besides the model and the inputs), as a callable of ``get_image_features``' arguments; None
        where export refuses it."""
        exported = export_call(model.base_model, "get_image_features", inputs, {"return_dict": True})
        if exported is None:
            return None

        def encode_images(**tensors):
            return exported(**tensors)

        self.image_batch_sizes.add(inputs["pixel_values"].shape[0])
        self.reserve_graphs(len(self.image_encoders) + 1, encode_images)
        compiled = FileBackedFunction(
            encode_images, self.compile_config.to_dict(), {**self.graph_key, "exported": exported.digest}, self.store
        )

        def encoder(return_dict: bool = True, **tensors):
            return exported.unflatten(compiled(**{name: tensors[name] for name in exported.input_names}))

        return encoder

    def accepting_call(self, model: PreTrainedModel, output_hidden: tuple[int, ...] | None) -> Callable:
        """The compiled round whose graph holds the forward and the acceptance ([`accepting_forward`]; one function
        per ``output_hidden``, one graph per batch size and width), wrapped by the model's clock when it has one
        ([`CALL_WRAPPER_ATTRIBUTE`])."""
        function = self.accepting.get(output_hidden)
        if function is None:
            name = f"verify_and_accept_{type(model).__name__}_{len(self.accepting)}"
            function = self.accepting[output_hidden] = accepting_forward(model, output_hidden, name)
        guards = None if full_guards_asked() else round_guards
        compiled = self.compiled_function(function, len(NODE_BUCKETS), guard_filter=guards)
        wrap = model.__dict__.get(CALL_WRAPPER_ATTRIBUTE)
        return compiled if wrap is None else wrap(compiled)

    def compile_once(self, key: tuple, compile_all: Callable[[], None]) -> float:
        """Runs ``compile_all`` (throw-away calls that compile every graph a drafter will need) the first time ``key``
        (what those graphs depend on: e.g. a draft head's architecture, dtype, cache slots and tree settings) is met;
        returns the seconds it took (0 when ``key`` was met before)."""
        if key in self.drafting_compiled:
            return 0.0
        start = time.perf_counter()
        compile_all()
        self.drafting_compiled.add(key)
        return time.perf_counter() - start

    # ----------------------------------------------------------------- the prefill
    def prefill_key(self, slots: int, output_hidden: tuple[int, ...] | None, prompt_length: int, batch_size: int):
        """What this call's compiled prefill graph depends on, or None when its prefill stays eager: a prompt of one
        token (a size-1 dimension would be specialised), or a forward that did not compile over the prompt. The
        caller checks the rest: 2D positions, a causal prompt, a fresh cache."""
        key = (slots, output_hidden, batch_size)
        return None if prompt_length < 2 or key in self.prefills_eager else key

    def prefill_call(self, key: tuple | None) -> PrefillCall | None:
        """The compiled prefill for ``key`` when an earlier call compiled its graph, else None (an eager prefill)."""
        return PrefillCall(self.call) if key in self.prefills_compiled else None

    def compile_prefill(
        self, model: PreTrainedModel, key: tuple, verification: Verification, prompt: Pending, trees: TreeBatch
    ) -> float:
        """Compiles the prefill graph for ``key``: the call's own prefill (``prompt``: its ids and positions ``[B, P]``,
        the prepared inputs with its images; its ``trees``) once more through the compiled call, with the rounds'
        ``verification``'s hidden states, window and slots, from slot 0, the cache's entries saved and put back
        ([`preserved_entries`]). A forward that does not compile into one graph keeps an eager prefill (a warning,
        once per key).

        Returns:
            the seconds it took.
        """
        from torch._dynamo.exc import TorchDynamoException
        from torch._inductor.exc import InductorError
        from torch.fx.experimental.symbolic_shapes import ConstraintViolationError

        start = time.perf_counter()
        self.reserve_graphs(1)
        prefill = CompiledVerification(
            PrefillCall(self.call), verification.output_hidden, verification.sliding_window, verification.key_length
        )
        try:
            with preserved_entries(prompt.cache):
                prefill.verify(model, prompt, trees)
        # dynamo / inductor refusing the model's forward, or the model's code fixing the prompt's length (a Python
        # branch on it specialises the dimension marked dynamic)
        except (TorchDynamoException, InductorError, ConstraintViolationError) as error:
            self.prefills_eager.add(key)
            logger.warning(
                "the prefill of %s stays eager: its forward over the prompt does not compile into one graph (%s: %s)",
                type(model).__name__,
                type(error).__name__,
                str(error).splitlines()[0] if str(error) else "",
            )
            return time.perf_counter() - start
        self.prefills_compiled.add(key)
        seconds = time.perf_counter() - start
        logger.info(
            "compiled the prefill (every prompt length, %d slots, hidden states %s) in %.1f s", *key[:2], seconds
        )
        return seconds

    # ----------------------------------------------------------------- the rounds
    def compile_widths(
        self, model: PreTrainedModel, verification: CompiledVerification, pending: Pending, buckets: Sequence[int]
    ) -> float:
        """Compiles every bucket width that fits the free slots the first time this model meets ``(slots, hidden
        states, buckets, batch size, acceptance in the graph or not)``: one throw-away filler-only verification each
        through the rounds' ``verification``, after the committed entries (``pending``: as the next round feeds
        them), each rolled back, so that every graph is compiled before the first action, never mid-episode.

        Returns:
            the seconds it took (0 when the key was met before).
        """
        fused = verification.reads_lengths
        cache, slots, output_hidden = pending.cache, verification.key_length, verification.output_hidden
        key = (slots, output_hidden, tuple(buckets), cache_batch_size(cache), fused)
        if key in self.widths_compiled:
            return 0.0
        start, length = time.perf_counter(), cache_length(cache)
        ids = pending.ids
        widths = [b for b in buckets if b <= slots - length - ids.shape[1]]
        self.reserve_graphs(len(widths), self.accepting[output_hidden] if fused else None)
        empty = [DraftTree.empty(ids.device)] * ids.shape[0]
        if fused:  # any lengths: the filler trees accept nothing
            pending = replace(pending, lengths=torch.zeros(ids.shape[0], 1, dtype=torch.long, device=ids.device))
        for width in widths:
            verification.verify(model, pending, TreeBatch(empty, min_nodes=width))
            truncate_cache(cache, length)
        self.widths_compiled.add(key)
        seconds = time.perf_counter() - start
        logger.info(
            "compiled verification widths %s (%d slots, hidden states %s%s) in %.1f s",
            widths,
            slots,
            output_hidden,
            ", acceptance in the graph" if fused else "",
            seconds,
        )
        return seconds


def model_call(model: PreTrainedModel) -> Callable:
    """``model(**inputs)`` as a plain function closing over ``model`` (what a graph file is compiled from: the model
    is its external data, never saved in it)."""

    def call_model(**inputs):
        return model(**inputs)

    return call_model


def graphs_held(function: Callable) -> int:
    """The graphs dynamo holds for ``function``'s code, compiled by any caller (its recompile limit counts them per
    code object: a model class's forward is shared by its instances, and transformers' decorated forwards share
    their decorator's code); 0 when torch does not tell."""
    try:
        from torch._dynamo.eval_frame import _debug_get_cache_entry_list
    except ImportError:  # a torch without it: the limits fall back to the graphs about to be compiled
        return 0
    held = 0
    while function is not None:  # the function and what it wraps (dynamo may have compiled either)
        code = getattr(function, "__code__", None)
        if code is not None:
            held = max(held, len(_debug_get_cache_entry_list(code)))
        function = getattr(function, "__wrapped__", None)
    return held


def allow_graphs_beside(functions: Sequence[Callable]) -> None:
    """Raises this thread's recompile limit to hold every graph dynamo holds for any of ``functions`` (a model's
    forward, its drafters' compiled functions: [`graphs_held`]) and transformers' own beside them (dynamo's settings
    are per thread: a thread that did not compile the graphs it meets needs this)."""
    allow_graphs(max(graphs_held(f) for f in functions) + _GRAPHS_BESIDE_OURS)


def allow_graphs(count: int) -> None:
    """Raises dynamo's per-function recompile limit to ``count`` graphs when it is lower (never lowers it). The
    limit is per thread: this raises the calling thread's."""
    config = torch._dynamo.config
    name = "recompile_limit" if hasattr(config, "recompile_limit") else "cache_size_limit"
    if getattr(config, name) < count:
        logger.info("raising torch._dynamo.config.%s from %d to %d", name, getattr(config, name), count)
        setattr(config, name, count)


def buckets_up_to(max_nodes: int | None, buckets: Sequence[int] = NODE_BUCKETS) -> tuple[int, ...]:
    """The buckets a call whose trees never exceed ``max_nodes`` nodes can meet: up to the smallest that holds
    ``max_nodes`` (every bucket when None, unknown), so that no other width is compiled for it."""
    values = tuple(buckets)
    if max_nodes is None:
        return values
    return values[: next((i for i, b in enumerate(values) if b >= max_nodes), len(values) - 1) + 1]


def verification_width(num_nodes: int, free_slots: int, buckets: Sequence[int] = NODE_BUCKETS) -> int:
    """The node count a verification of a ``num_nodes``-node tree is padded (or cut) to.

    Args:
        num_nodes: the largest tree's real nodes.
        free_slots: cache slots left after the pending tokens (the padded tree must fit in them).
        buckets: the allowed node counts, ascending, starting at 0.
    Returns:
        the smallest bucket >= ``num_nodes`` that fits, else the largest bucket that fits (the tree is then cut to it;
        0, a plain decoding step, always fits).
    """
    fitting = [b for b in buckets if b <= free_slots]
    if not fitting:
        raise ValueError(f"no verification width fits {free_slots} free cache slots (buckets {tuple(buckets)})")
    return next((b for b in fitting if b >= num_nodes), fitting[-1])


def check_buckets(buckets: Sequence[int]) -> tuple[int, ...]:
    """Validates node buckets: distinct integers >= 0, ascending, starting at 0 (a plain decoding step)."""
    values = tuple(buckets)
    if not values or values[0] != 0 or any(not isinstance(b, int) or b < 0 for b in values):
        raise ValueError(f"node buckets must be integers >= 0 starting at 0, got {values}")
    if any(b >= c for b, c in zip(values, values[1:])):
        raise ValueError(f"node buckets must be strictly ascending, got {values}")
    return values


check_buckets(NODE_BUCKETS)
