"""The engine's state for a model lives in one object, its ``SpeculativeDecoder`` (issue 75 item 1): two models in one
process, their compiled calls alternating, each get their own greedy tokens from their own decoder; a model holds
nothing of the engine but its decoder; ``reset_compilation`` makes every decoder forget what it compiled; a deep copy
gets a decoder of its own; speculative/ keeps no module-level mutable registries.

Compiled with dynamo's ``eager`` backend (it traces, guards and recompiles as inductor would)."""

from __future__ import annotations

import ast
import copy
from pathlib import Path

import pytest
import torch
from transformers import LlamaForCausalLM

from hf_specvla import DraftHead, DraftHeadDrafter, JacobiDrafter, disable_speculation, enable_speculation
from hf_specvla.speculative import SpeculativeDecoder, reusable_static_cache
from hf_specvla.speculative.compiled import reset_compilation
from hf_specvla.speculative.decoder import DECODER_ATTRIBUTE
from hf_specvla.speculative.generation import SpeculativeGenerationMixin
from hf_specvla.speculative.graph_files import MIXED_FROM

from ..conftest import tiny_llama_config
from .test_compiled_verification import eager_compile_config, greedy

SPECULATIVE = Path(__file__).resolve().parents[2] / "src" / "hf_specvla" / "speculative"


@pytest.fixture(autouse=True)
def fresh_dynamo():
    reset_compilation()
    yield
    reset_compilation()


def _llama(seed: int):
    torch.manual_seed(seed)
    return enable_speculation(LlamaForCausalLM(tiny_llama_config()).eval())


def compiled() -> dict:
    return dict(cache_implementation="static", compile_config=eager_compile_config())


def test_two_models_alternating_compiled_calls_each_get_their_own_greedy():
    models = [_llama(0), _llama(1)]
    heads = [DraftHead.from_target(model, num_draft_tokens=3).eval() for model in models]
    prompts = [torch.randint(6, 64, (1, n), generator=torch.Generator().manual_seed(n)) for n in (6, 9)]
    expected = {(m, p): greedy(models[m], prompt) for m in range(2) for p, prompt in enumerate(prompts)}
    assert not torch.equal(expected[0, 0], expected[1, 0])  # the two models decode differently
    for round_ in range(2):  # model 0, model 1, model 0, ...: each call reuses what its own model compiled
        for p, prompt in enumerate(prompts):
            for m, model in enumerate(models):
                for assistant in (JacobiDrafter(), heads[m]):
                    out = greedy(model, prompt, assistant_model=assistant, **compiled())
                    assert torch.equal(out, expected[m, p]), (round_, p, m, type(assistant).__name__)
    decoders = [SpeculativeDecoder.of(model) for model in models]
    assert decoders[0] is not decoders[1] and all(d.model_ref() is m for d, m in zip(decoders, models))
    assert all(len(d.compiled_graphs) == 1 and d.static_caches for d in decoders)
    assert all(any(key[0] == "draft head" for key in d.static_caches) for d in decoders)  # the heads' too
    caches = [{id(c) for c in d.static_caches.values()} for d in decoders]
    assert not caches[0] & caches[1]  # each model's static caches are its own
    # a model holds nothing of the engine but its decoder (transformers keeps its own compiled call)
    for model in models:
        ours = [name for name in model.__dict__ if "specvla" in name]
        assert ours == [DECODER_ATTRIBUTE], ours


def test_reset_compilation_makes_every_decoder_forget_what_it_compiled():
    models = [_llama(0), _llama(1)]
    prompt = torch.randint(6, 64, (1, 6), generator=torch.Generator().manual_seed(6))
    for model in models:
        greedy(model, prompt, assistant_model=JacobiDrafter(), **compiled())
    verifiers = [SpeculativeDecoder.of(model).graphs(eager_compile_config()) for model in models]
    SpeculativeDecoder.reset_compilation()  # one decoder's method, every decoder's effect: dynamo's graphs are gone
    for model, verifier in zip(models, verifiers):
        assert SpeculativeDecoder.of(model).compiled_graphs == {}
        out = greedy(model, prompt, assistant_model=JacobiDrafter(), **compiled())
        assert torch.equal(out, greedy(model, prompt))
        assert SpeculativeDecoder.of(model).graphs(eager_compile_config()) is not verifier


def test_a_deep_copy_gets_a_decoder_of_its_own():
    model = _llama(0)
    prompt = torch.randint(6, 64, (1, 6), generator=torch.Generator().manual_seed(6))
    greedy(model, prompt, assistant_model=JacobiDrafter(), **compiled())
    clone = copy.deepcopy(model)
    with torch.no_grad():
        clone.lm_head.weight.mul_(-1.0)  # the copy decodes differently: its graphs must read its own weights
    out = greedy(clone, prompt, assistant_model=JacobiDrafter(), **compiled())
    assert torch.equal(out, greedy(clone, prompt))
    assert SpeculativeDecoder.of(clone) is not SpeculativeDecoder.of(model)
    assert SpeculativeDecoder.of(clone).model_ref() is clone


def test_reusable_static_caches_are_the_models_decoders():
    model = _llama(0)
    cache = reusable_static_cache(model, 64, 1)
    assert reusable_static_cache(model, 64, 1) is cache  # handed out again, emptied
    assert reusable_static_cache(_llama(1), 64, 1) is not cache


def test_a_draft_heads_static_cache_is_the_target_models_decoders():
    """Drafters of one head on one target share its static cache (one compiled call at a time on a model); another
    target keeps its own; a drafter holds none."""
    model, other = _llama(0), _llama(1)
    head = DraftHead.from_target(model, num_draft_tokens=3).eval()
    first, second = DraftHeadDrafter(head), DraftHeadDrafter(head, num_draft_tokens=2)
    decoder, other_decoder = SpeculativeDecoder.of(model), SpeculativeDecoder.of(other)  # handed to the drafters
    cache = first.static_cache(decoder, 64)
    assert second.static_cache(decoder, 64) is cache  # handed out again, emptied
    assert first.static_cache(decoder, 128) is not cache and first.static_cache(other_decoder, 64) is not cache
    assert cache in SpeculativeDecoder.of(model).static_caches.values()
    assert not any(isinstance(value, dict) for value in vars(first).values())
    assert cache in SpeculativeDecoder.of(model).static_caches.values()


def test_speculative_keeps_no_module_level_mutable_registries():
    """No module of speculative/ binds a dict, set, list, weak map or counter at module level (constants are
    tuples, frozensets, strings, numbers): what the engine keeps is its decoders'."""
    mutable_calls = {"dict", "set", "list", "WeakKeyDictionary", "WeakValueDictionary", "WeakSet", "count",
                     "defaultdict", "OrderedDict"}  # fmt: skip
    found = []
    for path in sorted(SPECULATIVE.rglob("*.py")):
        for node in ast.parse(path.read_text()).body:
            targets, value = [], None
            if isinstance(node, ast.Assign):
                targets, value = node.targets, node.value
            elif isinstance(node, ast.AnnAssign) and node.value is not None:
                targets, value = [node.target], node.value
            names = [t.id for t in targets if isinstance(t, ast.Name)]
            call = value.func if isinstance(value, ast.Call) else None
            called = getattr(call, "attr", None) or getattr(call, "id", None)
            if isinstance(value, ast.Dict | ast.Set | ast.List | ast.DictComp | ast.SetComp | ast.ListComp) or (
                called in mutable_calls
            ):
                names = [name for name in names if not name.startswith("__")]  # __all__
                found += [(path.name, name) for name in names]
    assert found == []


def test_one_speculative_class_a_model_class_found_without_a_registry():
    """Two models of one class enabled apart share one mixed class (found among the class's subclasses); disabling
    gives the original class back, and enabling again finds the same mixed class."""
    first, second = _llama(0), _llama(1)
    mixed = type(first)
    assert type(second) is mixed and mixed.__bases__[1] is LlamaForCausalLM
    assert mixed.__name__ == "LlamaForCausalLM"  # save_pretrained records the original architecture
    assert type(disable_speculation(first)) is LlamaForCausalLM
    assert type(enable_speculation(first)) is mixed
    assert type(enable_speculation(first)) is mixed  # enabling twice changes nothing
    assert [sub for sub in LlamaForCausalLM.__subclasses__() if vars(sub).get(MIXED_FROM)] == [mixed]


def test_a_users_own_subclass_of_the_same_bases_is_never_taken_for_the_mixed_class():
    """A class of the user's with the mixin and a model class as its bases (its own ``generate``, say: the OpenVLA port
    has one), made before any model of that class is enabled, is not the class ``enable_speculation`` mixes in: the
    model keeps the mixin's ``generate`` and decodes."""

    class Plain(LlamaForCausalLM):  # a model class no test has enabled yet
        pass

    class Wrapping(SpeculativeGenerationMixin, Plain):
        def generate(self, *args, **kwargs):
            raise AssertionError("the user's class, not the mixed one")

    torch.manual_seed(0)
    model = enable_speculation(Plain(tiny_llama_config()).eval())
    assert type(model) is not Wrapping and vars(type(model)).get(MIXED_FROM) is Plain
    input_ids = torch.randint(6, 64, (1, 5), generator=torch.Generator().manual_seed(0))
    assert greedy(model, input_ids, draft_ids=torch.randint(6, 64, (1, 3))).shape == (1, 5 + 7)


def test_nothing_is_written_on_transformers_cache_objects(tiny_llama, monkeypatch):
    """The host's count of a static cache's entries during a call is the call's own (engine v6): every forward of a
    speculative call on a static cache sees a cache with no attribute of hf_specvla's, and the tokens are greedy's."""
    from hf_specvla.speculative.compat import CACHE_KEY

    seen = []
    forward = tiny_llama.forward

    def spying_forward(*args, **kwargs):
        cache = kwargs.get(CACHE_KEY)
        if cache is not None:
            seen.append([name for name in vars(cache) if "hf_specvla" in name])
        return forward(*args, **kwargs)

    monkeypatch.setattr(tiny_llama, "forward", spying_forward)
    input_ids = torch.randint(6, 64, (1, 9), generator=torch.Generator().manual_seed(0))
    settings = dict(max_new_tokens=6, do_sample=False, cache_implementation="static")
    out = tiny_llama.generate(input_ids, assistant_model=JacobiDrafter(), **settings)
    assert len(seen) >= 2 and all(names == [] for names in seen), seen
    monkeypatch.undo()
    assert torch.equal(out, tiny_llama.generate(input_ids, **settings))


def test_a_compiled_call_compiles_only_in_its_decoders_warm_up(monkeypatch):
    """The one place a call triggers compiling: every graph of the target (its widths, the next call's prefill) and
    of a draft head (its round; a v3 head's block before the prefill, which runs eagerly at its shape's first call)
    is compiled by ``SpeculativeDecoder.warm_up``, after the prefill and before the first round; no round compiles;
    a second call compiles nothing; both decode greedy's tokens."""
    import hf_specvla.speculative.decoder as decoder_module
    from hf_specvla import DraftTreeConfig
    from hf_specvla.speculative.compiled import CompiledGraphs

    from .test_draft_head_v3 import _v3_head

    torch.manual_seed(0)
    target = enable_speculation(LlamaForCausalLM(tiny_llama_config(num_hidden_layers=3)).eval())
    phase, compiled_in = ["before the prefill"], []

    def recording(name, original):
        def compile_then_record(self, *args, **kwargs):
            seconds = original(self, *args, **kwargs)
            if seconds:  # 0: held already
                compiled_in.append((name, phase[0]))
            return seconds

        return compile_then_record

    def in_phase(name, original):
        def run(*args, **kwargs):
            phase[0] = name
            return original(*args, **kwargs)

        return run

    for name in ("compile_once", "compile_widths", "compile_prefill"):
        monkeypatch.setattr(CompiledGraphs, name, recording(name, getattr(CompiledGraphs, name)))
    monkeypatch.setattr(decoder_module, "prefill", in_phase("prefill", decoder_module.prefill))
    monkeypatch.setattr(decoder_module, "decode_round", in_phase("round", decoder_module.decode_round))
    monkeypatch.setattr(SpeculativeDecoder, "warm_up", in_phase("warm_up", SpeculativeDecoder.warm_up))
    tree = DraftTreeConfig(top_k=3, depth=4, total_tokens=12)
    heads = {
        "tree": (DraftHeadDrafter(DraftHead.from_target(target, num_draft_tokens=3).eval(), tree=tree), 1),
        "v3 chain, block before the prefill": (
            DraftHeadDrafter(_v3_head(target, draft_mode="chain", prefill_drafts=True)),
            2,
        ),
    }
    prompt = torch.randint(6, 64, (1, 7), generator=torch.Generator().manual_seed(0))
    expected = greedy(target, prompt)
    for name, (drafter, head_graphs) in heads.items():
        reset_compilation()
        for call in range(2):
            compiled_in.clear()
            out = greedy(target, prompt, assistant_model=drafter, return_dict_in_generate=True, **compiled())
            assert torch.equal(out.sequences, expected), (name, call)
            assert phase[0] == "round"  # the call ran rounds after its warm-up
            if call == 0:
                assert sorted(compiled_in) == sorted(
                    [("compile_widths", "warm_up"), ("compile_prefill", "warm_up")]
                    + [("compile_once", "warm_up")] * head_graphs
                ), name
                assert out.speculation.compile_seconds > 0
            else:
                assert compiled_in == [], name
