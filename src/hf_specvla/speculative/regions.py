"""Repeated decoder layers compiled once: each a nested compile region.

A compiled forward of a 16-layer decoder is 16 copies of one layer's code to trace, lower and compile (Inductor's
code generation and the C++ compile are most of a graph's compile time on a CPU). ``torch.compiler.
nested_compile_region`` marks a function whose traced graph dynamo and Inductor reuse at every call with inputs of
the same kind: the language model's layers, each routed through one such function, are compiled once per graph
instead of once per layer (policy v3: ~32 s -> ~20 s a graph). The layers'
weights stay inputs of the region, so every layer computes with its own.

[`compile_layers_once`] routes a model's decoder layers through the region by setting each layer's ``forward`` on the
instance (its class, its hooks and its weights untouched; eagerly the region is a plain call of the class's
``forward``). Asked for with ``HF_SPECVLA_LAYER_REGIONS=on`` where the engine's graphs are files (``graph_files``):
the graphs' key records it. Off by default: each layer's graph is then called from the compiled forward, which costs
a forward ~0.5 ms on the CPU (policy v3, one thread: 1.12x at B=1, 1.06x at B=4), a trade of steady-state speed for a
first start's compile time that a user makes, not the engine.
"""

from __future__ import annotations

import functools
import os

import torch
from torch import nn

#: the attribute a routed layer's ``forward`` carries (its region's marker: routing twice changes nothing)
ROUTED_ATTRIBUTE = "_hf_specvla_region"


def _call_layer(layer: nn.Module, *args, **kwargs):
    """``layer``'s own class ``forward``: the body of the region every routed layer shares."""
    return type(layer).forward(layer, *args, **kwargs)


#: the environment variable that asks for the decoder layers compiled once ([`layer_regions_asked`])
LAYER_REGIONS_ENV = "HF_SPECVLA_LAYER_REGIONS"
_ON, _OFF = ("1", "on", "true", "yes"), ("", "0", "off", "false", "no")


def layer_regions_asked() -> bool:
    """Whether ``$HF_SPECVLA_LAYER_REGIONS`` asks for the decoder layers compiled once (``on``, ``1``, ``true``,
    ``yes``; unset, ``off``, ``0``, ``false``, ``no``: not); any other value is refused, naming it."""
    value = os.environ.get(LAYER_REGIONS_ENV, "").strip().lower()
    if value not in _ON + _OFF:
        raise ValueError(f"{LAYER_REGIONS_ENV}={value!r}: expected one of {', '.join(v for v in _ON + _OFF if v)}")
    return value in _ON


#: how many graphs of the region one compile may hold (layers whose guards differ: e.g. sliding and full attention
#: alternating) before torch refuses; past a model's layer count reuse gains nothing, so it is never the limit
REGION_VARIANTS = 1024

#: the one region every routed layer calls (dynamo reuses a region's graph per function object); None: a torch
#: without nested compile regions
_LAYER_REGION = (
    torch.compiler.nested_compile_region(_call_layer, max_reuse_entries=REGION_VARIANTS)
    if hasattr(torch.compiler, "nested_compile_region")
    else None
)


def repeated_layers(model: nn.Module) -> nn.ModuleList | None:
    """The language model's decoder layers (``model.get_decoder().layers``) when there are two or more of one class
    and none has its ``forward`` replaced on the instance by someone else; else None."""
    get_decoder = getattr(model, "get_decoder", None)
    decoder = get_decoder() if callable(get_decoder) else None
    layers = getattr(decoder, "layers", None)
    if not isinstance(layers, nn.ModuleList) or len(layers) < 2:
        return None
    if len({type(layer) for layer in layers}) != 1:
        return None
    for layer in layers:
        own = layer.__dict__.get("forward")
        if own is not None and not getattr(own, ROUTED_ATTRIBUTE, False):
            return None
    return layers


def compile_layers_once(model: nn.Module) -> int:
    """Routes ``model``'s repeated decoder layers ([`repeated_layers`]) through one nested compile region, so that a
    compiled forward compiles one layer's code for all of them; returns how many layers are routed (0: none, e.g. a
    torch without nested compile regions, a single layer, a layer whose ``forward`` was replaced)."""
    layers = repeated_layers(model) if _LAYER_REGION is not None else None
    if layers is None:
        return 0
    for layer in layers:
        if not getattr(layer.__dict__.get("forward"), ROUTED_ATTRIBUTE, False):
            routed = functools.partial(_LAYER_REGION, layer)
            setattr(routed, ROUTED_ATTRIBUTE, True)
            layer.forward = routed
    return len(layers)
