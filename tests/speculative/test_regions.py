"""A model's repeated decoder layers compiled once (``speculative.regions``): routed through one nested compile
region, each layer still computes with its own weights (eagerly and compiled), routing twice changes nothing, a layer
someone else replaced is left alone, a copy's layers route to the copy's, and a compiled graph's file records it."""

from __future__ import annotations

import copy

import pytest
import torch
from transformers import CompileConfig, LlamaForCausalLM

from hf_specvla.speculative import graph_files
from hf_specvla.speculative.compiled import CompiledGraphs
from hf_specvla.speculative.regions import (
    LAYER_REGIONS_ENV,
    ROUTED_ATTRIBUTE,
    compile_layers_once,
    layer_regions_asked,
    repeated_layers,
)

from ..conftest import tiny_llama_config

pytestmark = pytest.mark.skipif(
    not hasattr(torch.compiler, "nested_compile_region"), reason="a torch without nested compile regions"
)


def _model(layers: int = 3) -> LlamaForCausalLM:
    torch.manual_seed(0)
    return LlamaForCausalLM(tiny_llama_config(num_hidden_layers=layers)).eval()


def _logits(model, ids: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        return model(input_ids=ids).logits


def _routed_to(layer) -> object:
    routed = layer.__dict__.get("forward")
    assert routed is not None and getattr(routed, ROUTED_ATTRIBUTE, False)
    return routed.args[0]


def test_routed_layers_compute_what_they_computed_with_their_own_weights():
    """Every decoder layer is routed, to itself; the eager logits are bit for bit the unrouted ones, and a changed
    weight of one layer changes them as it would unrouted (each layer reads its own weights); routing again changes
    nothing."""
    model, ids = _model(), torch.randint(0, 300, (2, 7), generator=torch.Generator().manual_seed(1))
    before = _logits(model, ids)
    assert compile_layers_once(model) == 3
    assert all(_routed_to(layer) is layer for layer in model.model.layers)
    forwards = [layer.forward for layer in model.model.layers]
    assert torch.equal(_logits(model, ids), before)
    assert compile_layers_once(model) == 3 and [layer.forward for layer in model.model.layers] == forwards

    plain = _model()
    with torch.no_grad():
        for m in (model, plain):
            m.model.layers[1].mlp.down_proj.weight.mul_(-1.0)
    assert torch.equal(_logits(model, ids), _logits(plain, ids))
    assert not torch.equal(_logits(model, ids), before)


def test_a_compiled_forward_of_routed_layers_equals_the_eager_one():
    """One graph over the routed layers (the region compiled once for three layers) gives the eager logits."""
    model, ids = _model(), torch.randint(0, 300, (1, 5), generator=torch.Generator().manual_seed(2))
    want = _logits(model, ids)
    compile_layers_once(model)
    compiled = torch.compile(lambda **inputs: model(**inputs), fullgraph=True, dynamic=False)
    with torch.no_grad():
        got = compiled(input_ids=ids).logits
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)


def test_layers_that_cannot_share_one_region_are_left_alone():
    """A single layer, or a layer whose forward someone else replaced on the instance, is not routed (0), and no
    layer of that model is."""
    single = _model(layers=1)
    assert repeated_layers(single) is None and compile_layers_once(single) == 0

    model = _model()
    own = model.model.layers[2].forward
    model.model.layers[2].forward = lambda *args, **kwargs: own(*args, **kwargs)
    assert compile_layers_once(model) == 0
    assert "forward" not in vars(model.model.layers[0])


def test_a_copy_of_a_routed_model_routes_its_layers_to_its_own():
    """``copy.deepcopy`` of a routed model: the copy's layers call the copy's layers (its own weights), not the
    original's."""
    model, ids = _model(), torch.randint(0, 300, (1, 6), generator=torch.Generator().manual_seed(3))
    compile_layers_once(model)
    twin = copy.deepcopy(model)
    assert all(_routed_to(layer) is layer for layer in twin.model.layers)
    with torch.no_grad():
        twin.model.layers[0].self_attn.q_proj.weight.mul_(2.0)
    assert not torch.equal(_logits(twin, ids), _logits(model, ids))


def test_the_graphs_key_records_the_routed_layers(monkeypatch, tmp_path):
    """Where graphs are files and ``HF_SPECVLA_LAYER_REGIONS`` asks for it the model's layers are routed and their
    count is in the graphs' key (a file compiled without regions is never taken for one with them); in memory, or
    not asked for, the model is left as it is; a value the variable does not take is refused, naming it."""
    monkeypatch.setenv(graph_files.FOLDER_ENV, str(tmp_path))
    monkeypatch.delenv(LAYER_REGIONS_ENV, raising=False)
    unasked = _model()
    assert CompiledGraphs(unasked, CompileConfig(fullgraph=True, dynamic=False)).layer_regions == 0
    assert "forward" not in vars(unasked.model.layers[0])
    monkeypatch.setenv(LAYER_REGIONS_ENV, "maybe")
    with pytest.raises(ValueError, match="HF_SPECVLA_LAYER_REGIONS='maybe': expected one of 1, on"):
        layer_regions_asked()
    monkeypatch.setenv(LAYER_REGIONS_ENV, "on")
    model = _model()
    graphs = CompiledGraphs(model, CompileConfig(fullgraph=True, dynamic=False))
    assert graphs.layer_regions == 3 and graphs.graph_key["layer_regions"] == 3
    monkeypatch.setenv(graph_files.FOLDER_ENV, "off")
    other = _model()
    assert CompiledGraphs(other, CompileConfig(fullgraph=True, dynamic=False)).layer_regions == 0
    assert "forward" not in vars(other.model.layers[0])
