"""A compiled round's acceptance inside its verification's graph (``speculative.fused``): greedy's tokens for every
drafter and batch, EOS hidden as ``min_new_tokens`` hides it, the rounds that cannot accept there accepting after
the forward, and a round's own guards (``fused.round_guards``: its arguments, the ambient state, the model's classes
and tensors; not dict-membership or global ones): whatever changes between compiled calls (a module swapped, an
adapter, a resized vocabulary, a deep copy, CPU autocast, a sliding window's length) gets greedy's tokens, and other
threads' compiled code keeps all its guards.

Compiled with dynamo's ``eager`` backend (it traces, guards and recompiles as inductor would)."""

from __future__ import annotations

import pytest
import torch

from hf_specvla import DraftHead, DraftHeadDrafter, DraftTreeConfig, JacobiDrafter
from hf_specvla.speculative.compiled import graphs_held, reset_compilation
from hf_specvla.speculative.decoder import SpeculativeDecoder
from hf_specvla.speculative.graph_files import graph_folder

from .test_compiled_verification import _model, eager_compile_config, greedy


@pytest.fixture(autouse=True)
def fresh_dynamo():
    reset_compilation()
    yield
    reset_compilation()


def compiled() -> dict:
    return dict(cache_implementation="static", compile_config=eager_compile_config())


def test_every_drafter_and_batch_accepts_inside_the_graph_with_greedys_tokens():
    model = _model("llama")
    torch.manual_seed(1)
    head = DraftHead.from_target(model, num_draft_tokens=3).eval()
    tree = DraftHeadDrafter(head, tree=DraftTreeConfig(top_k=3, depth=4, total_tokens=12))
    prompts = [torch.randint(6, 64, (1, n), generator=torch.Generator().manual_seed(n)) for n in (6, 9, 4)]
    for kwargs in (dict(assistant_model=JacobiDrafter()), dict(assistant_model=head), dict(assistant_model=tree)):
        for input_ids in prompts[:1]:
            out = greedy(model, input_ids, return_dict_in_generate=True, **compiled(), **kwargs)
            assert torch.equal(out.sequences, greedy(model, input_ids)), kwargs
            assert len(out.speculation.compiled_widths) == out.speculation.num_batch_forwards - 1 > 0
        width = max(p.shape[1] for p in prompts)  # a batch of rows of other lengths, left-padded
        batch = torch.cat([torch.nn.functional.pad(p, (width - p.shape[1], 0), value=0) for p in prompts])
        mask = (torch.arange(width)[None] >= torch.tensor([[width - p.shape[1]] for p in prompts])).long()
        expected = greedy(model, batch, attention_mask=mask, pad_token_id=0)
        out = greedy(model, batch, attention_mask=mask, pad_token_id=0, **compiled(), **kwargs)
        assert torch.equal(out, expected), kwargs
    verifier = SpeculativeDecoder.of(model).graphs(eager_compile_config())
    assert len(verifier.accepting) == 2  # without hidden states (Jacobi), with them (the head)
    if graph_folder(model.device.type) is not None:  # files (tests/conftest.py; off in tf520, tflatest)
        rounds = [verifier.functions[f] for f in verifier.accepting.values()]
        assert all(function.compiled + function.loaded > 0 for function in rounds)
    else:
        assert all(graphs_held(function) > 0 for function in verifier.accepting.values())


def test_eos_is_hidden_inside_the_graph_as_min_new_tokens_hides_it():
    """EOS is greedy's third token: ``min_new_tokens`` hides it from the shorter prefixes of every tree (prefix
    lengths inside one verification straddle the limit), as greedy decoding hides it step by step."""
    model = _model("llama")
    input_ids = torch.randint(6, 64, (2, 6), generator=torch.Generator().manual_seed(5))
    free = greedy(model, input_ids)
    eos = int(free[0, 8])
    for min_new_tokens in (2, 4, 6):
        settings = dict(eos_token_id=eos, pad_token_id=0, min_new_tokens=min_new_tokens)
        expected = greedy(model, input_ids, **settings)
        for kwargs in (dict(assistant_model=JacobiDrafter()), dict(draft_ids=free[:, 6:12])):
            out = greedy(model, input_ids, **settings, **compiled(), **kwargs)
            assert torch.equal(out, expected), (min_new_tokens, kwargs)
    assert SpeculativeDecoder.of(model).graphs(eager_compile_config()).accepting  # the rounds accepted in the graph


def test_rounds_that_keep_scores_accept_after_the_forward_with_greedys_scores():
    model = _model("llama")
    input_ids = torch.randint(6, 64, (1, 6), generator=torch.Generator().manual_seed(3))
    expected = greedy(model, input_ids, output_scores=True, return_dict_in_generate=True)
    out = greedy(model, input_ids, output_scores=True, return_dict_in_generate=True, assistant_model=JacobiDrafter(),
                 **compiled())  # fmt: skip
    assert torch.equal(out.sequences, expected.sequences) and out.speculation.compiled_widths
    assert all(torch.allclose(a, b, atol=1e-5) for a, b in zip(out.scores, expected.scores))
    assert not SpeculativeDecoder.of(model).graphs(eager_compile_config()).accepting  # nothing compiled for it


def _swap_and_check(model, input_ids, change, calls=None):
    """A compiled speculative call, then ``change(model)``, then every call of ``calls`` (generate kwargs) compiled
    again: greedy's tokens of the changed model (eager, uncompiled) each time."""
    calls = calls or [dict(assistant_model=JacobiDrafter()), dict(draft_ids=greedy(model, input_ids)[:, 6:12])]
    for kwargs in calls:
        assert torch.equal(greedy(model, input_ids, **compiled(), **kwargs), greedy(model, input_ids)), kwargs
    before = greedy(model, input_ids)
    change(model)
    expected = greedy(model, input_ids)
    for kwargs in calls:
        out = greedy(model, input_ids, return_dict_in_generate=True, **compiled(), **kwargs)
        assert torch.equal(out.sequences, expected), kwargs
        assert out.speculation.compiled_widths  # the rounds ran compiled
    return before, expected


class NegatedHead(torch.nn.Linear):
    """The same weights as the head it replaces, another ``forward``: what calibration or adaptation code installs."""

    def forward(self, hidden):
        return -super().forward(hidden)


class LoraLinear(torch.nn.Module):
    """A LoRA-style adapter injected around a linear layer (``base`` + ``B A x``), as peft wraps one."""

    def __init__(self, base: torch.nn.Linear, rank: int = 2):
        super().__init__()
        self.base = base
        self.lora_a = torch.nn.Linear(base.in_features, rank, bias=False)
        self.lora_b = torch.nn.Linear(rank, base.out_features, bias=False)
        torch.nn.init.normal_(self.lora_b.weight, std=0.5)

    def forward(self, x):
        return self.base(x) + self.lora_b(self.lora_a(x))


def _prompt(seed: int = 3):
    return torch.randint(6, 64, (1, 6), generator=torch.Generator().manual_seed(seed))


def test_a_module_swapped_after_a_compiled_call_gets_greedys_tokens():
    model = _model("llama")

    def swap(model):
        head = NegatedHead(model.lm_head.in_features, model.lm_head.out_features, bias=False)
        head.weight = model.lm_head.weight
        model.lm_head = head

    before, after = _swap_and_check(model, _prompt(), swap)
    assert not torch.equal(before, after)  # the swap changed the greedy tokens: a stale graph would return before's


def test_an_adapter_injected_after_a_compiled_call_gets_greedys_tokens():
    model = _model("llama")

    def inject(model):
        torch.manual_seed(4)
        for layer in model.model.layers:
            layer.self_attn.q_proj = LoraLinear(layer.self_attn.q_proj)
            layer.mlp.down_proj = LoraLinear(layer.mlp.down_proj)

    before, after = _swap_and_check(model, _prompt(), inject)
    assert not torch.equal(before, after)


def test_a_resized_vocabulary_after_a_compiled_call_gets_greedys_tokens():
    model = _model("llama")

    def resize(model):
        torch.manual_seed(5)
        model.resize_token_embeddings(model.config.vocab_size + 16)
        with torch.no_grad():
            model.lm_head.weight[-16:].normal_(std=2.0)  # the new ids win some steps

    _swap_and_check(model, _prompt(), resize)


def test_a_deep_copy_with_other_weights_gets_its_own_greedy_tokens():
    import copy

    model = _model("llama")
    input_ids = _prompt()
    assert torch.equal(greedy(model, input_ids, assistant_model=JacobiDrafter(), **compiled()),
                       greedy(model, input_ids))  # fmt: skip
    twin = copy.deepcopy(model)
    with torch.no_grad():
        torch.manual_seed(6)
        for parameter in twin.parameters():
            parameter.add_(torch.randn_like(parameter) * 0.5)
    expected = greedy(twin, input_ids)
    assert not torch.equal(expected, greedy(model, input_ids))
    for kwargs in (dict(assistant_model=JacobiDrafter()), dict(draft_ids=expected[:, 6:12])):
        assert torch.equal(greedy(twin, input_ids, **compiled(), **kwargs), expected), kwargs
    # and the original still decodes as itself, its own graphs intact
    assert torch.equal(greedy(model, input_ids, assistant_model=JacobiDrafter(), **compiled()),
                       greedy(model, input_ids))  # fmt: skip


def test_cpu_autocast_after_a_static_cache_call_outside_it_gets_greedys_tokens():
    model = _model("llama")
    input_ids = _prompt()
    drafts = dict(draft_ids=greedy(model, input_ids)[:, 6:12])
    assert torch.equal(greedy(model, input_ids, **compiled(), **drafts), greedy(model, input_ids))
    with torch.autocast("cpu", torch.bfloat16):
        expected = greedy(model, input_ids)
        for kwargs in (dict(assistant_model=JacobiDrafter()), drafts):
            assert torch.equal(greedy(model, input_ids, **compiled(), **kwargs), expected), kwargs
    assert torch.equal(greedy(model, input_ids, **compiled(), **drafts), greedy(model, input_ids))  # and after it


def test_a_sliding_window_cache_follows_its_length():
    """A static sliding-window layer keeps its length in a Python int, a constant of its graphs: the round's guards on
    its arguments (the cache among them) tell those graphs apart."""
    model = _model("gemma2")
    input_ids = _prompt()
    expected = greedy(model, input_ids)
    for _ in range(2):
        assert torch.equal(greedy(model, input_ids, assistant_model=JacobiDrafter(), **compiled()), expected)


def _round_guard_text(model) -> str:
    from torch._dynamo.eval_frame import _debug_get_cache_entry_list

    verifier = SpeculativeDecoder.of(model).graphs(eager_compile_config())
    function = verifier.accepting[None]
    entries = _debug_get_cache_entry_list(function.__code__)
    assert entries
    return "\n".join(str(entry.guard_manager) for entry in entries)


def _model_guards(text: str) -> list[str]:
    """The kinds of the guards on the model alone (not the relational ones beside the round's inputs)."""
    lines = [line for line in text.splitlines() if "L['model']" in line and "L['inputs']" not in line and "+- " in line]
    return [line.split("+- ", 1)[1].split(":")[0] for line in lines]


def test_a_compiled_round_keeps_the_guards_that_tell_a_change_and_drops_the_dict_and_global_ones(
    monkeypatch, graphs_in_memory
):
    model = _model("llama")
    input_ids = _prompt()
    assert torch.equal(greedy(model, input_ids, assistant_model=JacobiDrafter(), **compiled()),
                       greedy(model, input_ids))  # fmt: skip
    guards = _round_guard_text(model)
    kept = _model_guards(guards)
    assert "L['inputs']" in guards and "GLOBAL_STATE" in guards  # the arguments, the ambient state (autocast)
    # the modules' classes, the tensors' dtypes and shapes, no instance forward ("not ___dict_contains('forward')")
    assert {"TYPE_MATCH", "TENSOR_MATCH", "DICT_CONTAINS"} <= set(kept)
    assert not {"HASATTR", "NO_HASATTR", "DICT_KEYS_MATCH"} & set(kept) and "G['" not in guards
    reset_compilation()
    monkeypatch.setenv("HF_SPECVLA_FULL_GUARDS", "1")
    assert torch.equal(greedy(model, input_ids, assistant_model=JacobiDrafter(), **compiled()),
                       greedy(model, input_ids))  # fmt: skip
    full = _round_guard_text(model)
    assert {"HASATTR", "NO_HASATTR"} & set(_model_guards(full)) and "G['" in full
    assert len(_model_guards(full)) > len(kept)


def test_another_threads_compiled_function_keeps_its_guards_while_rounds_run():
    """A function another thread compiled for ``negate=True`` alone (one graph: other inputs run eagerly, a guard
    tells them apart) returns its own results, never that graph's and never a refusal, over a few hundred calls made
    while compiled speculative calls run (a process-wide guard-skipping stance would run its one graph for both)."""
    import threading

    model = _model("llama")
    input_ids = _prompt()
    expected = greedy(model, input_ids)
    assert torch.equal(greedy(model, input_ids, assistant_model=JacobiDrafter(), **compiled()), expected)

    def sign(x, negate: bool):
        return -x if negate else x + 0

    signed = torch.compile(sign, backend="eager", recompile_limit=1)
    x = torch.arange(4.0)
    assert torch.equal(signed(x, True), -x)
    decoding, done, failures, during = threading.Event(), threading.Event(), [], [0]

    def other_thread():
        call = 0
        while not done.is_set():
            negate, busy = call % 2 == 0, decoding.is_set()
            try:
                result = signed(x, negate)
            except Exception as error:  # noqa: BLE001 (a refusal is a failure too)
                failures.append(repr(error))
                return
            if not torch.equal(result, -x if negate else x):
                failures.append(f"call {call}: {result.tolist()} for negate={negate}")
            during[0] += busy and decoding.is_set()
            call += 1

    thread = threading.Thread(target=other_thread)
    thread.start()
    try:
        decoding.set()
        for _ in range(40):
            assert torch.equal(greedy(model, input_ids, assistant_model=JacobiDrafter(), **compiled()), expected)
            if during[0] >= 300 or failures:
                break
    finally:
        decoding.clear()
        done.set()
        thread.join()
    assert not failures, failures[:3]
    assert during[0] >= 300, during[0]
