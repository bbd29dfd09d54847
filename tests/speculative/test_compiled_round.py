"""A compiled round's acceptance inside its verification's graph (``speculative.fused``): greedy's tokens for every
drafter and batch, EOS hidden as ``min_new_tokens`` hides it, the rounds that cannot accept there accepting after
the forward, and dynamo's guards skipped only after a key's first round (never on a sliding-window cache, never when
``HF_SPECVLA_FULL_GUARDS=1``, again after the model changes dtype).

Compiled with dynamo's ``eager`` backend (it traces, guards and recompiles as inductor would)."""

from __future__ import annotations

import pytest
import torch

from hf_specvla import DraftHead, DraftHeadDrafter, DraftTreeConfig, JacobiDrafter
from hf_specvla.speculative.compiled import CompiledVerifier, graphs_held, reset_compilation

from .test_compiled_verification import _model, eager_compile_config, greedy


@pytest.fixture(autouse=True)
def fresh_dynamo():
    reset_compilation()
    yield
    reset_compilation()


def compiled() -> dict:
    return dict(cache_implementation="static", compile_config=eager_compile_config())


@pytest.fixture
def skipped_guards(monkeypatch):
    """Counts the rounds run under dynamo's ``skip_guard_eval_unsafe`` stance."""
    count = {"rounds": 0}
    set_stance = torch.compiler.set_stance

    def counting(*args, **kwargs):
        count["rounds"] += bool(kwargs.get("skip_guard_eval_unsafe"))
        return set_stance(*args, **kwargs)

    monkeypatch.setattr(torch.compiler, "set_stance", counting)
    return count


def test_every_drafter_and_batch_accepts_inside_the_graph_with_greedys_tokens():
    model = _model("llama")
    torch.manual_seed(1)
    head = DraftHead.from_target(model, num_draft_tokens=3).eval()
    tree = DraftHeadDrafter(head, tree=DraftTreeConfig(top_k=3, depth=4, total_tokens=12))
    prompts = [torch.randint(6, 64, (1, n), generator=torch.Generator().manual_seed(n)) for n in (6, 9, 4)]
    for kwargs in (dict(assistant_model=JacobiDrafter()), dict(assistant_model=head), dict(assistant_model=tree)):
        for input_ids in prompts[:2]:
            out = greedy(model, input_ids, return_dict_in_generate=True, **compiled(), **kwargs)
            assert torch.equal(out.sequences, greedy(model, input_ids)), kwargs
            assert len(out.speculation.compiled_widths) == out.speculation.num_batch_forwards - 1 > 0
        width = max(p.shape[1] for p in prompts)  # a batch of rows of other lengths, left-padded
        batch = torch.cat([torch.nn.functional.pad(p, (width - p.shape[1], 0), value=0) for p in prompts])
        mask = (torch.arange(width)[None] >= torch.tensor([[width - p.shape[1]] for p in prompts])).long()
        expected = greedy(model, batch, attention_mask=mask, pad_token_id=0)
        out = greedy(model, batch, attention_mask=mask, pad_token_id=0, **compiled(), **kwargs)
        assert torch.equal(out, expected), kwargs
    verifier = CompiledVerifier.for_model(model, eager_compile_config())
    assert len(verifier.accepting) == 2  # without hidden states (Jacobi), with them (the head)
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
    assert CompiledVerifier.for_model(model, eager_compile_config()).accepting  # the rounds accepted in the graph


def test_rounds_that_keep_scores_accept_after_the_forward_with_greedys_scores():
    model = _model("llama")
    input_ids = torch.randint(6, 64, (1, 6), generator=torch.Generator().manual_seed(3))
    expected = greedy(model, input_ids, output_scores=True, return_dict_in_generate=True)
    out = greedy(model, input_ids, output_scores=True, return_dict_in_generate=True, assistant_model=JacobiDrafter(),
                 **compiled())  # fmt: skip
    assert torch.equal(out.sequences, expected.sequences) and out.speculation.compiled_widths
    assert all(torch.allclose(a, b, atol=1e-5) for a, b in zip(out.scores, expected.scores))
    assert not CompiledVerifier.for_model(model, eager_compile_config()).accepting  # nothing compiled for it


def test_guards_are_skipped_after_a_keys_first_round_only_where_graphs_differ_by_shape(skipped_guards, monkeypatch):
    model = _model("llama")
    input_ids = torch.randint(6, 64, (1, 6), generator=torch.Generator().manual_seed(3))
    expected = greedy(model, input_ids)
    for _ in range(2):
        assert torch.equal(greedy(model, input_ids, assistant_model=JacobiDrafter(), **compiled()), expected)
    assert skipped_guards["rounds"] > 0
    monkeypatch.setenv("HF_SPECVLA_FULL_GUARDS", "1")
    skipped_guards["rounds"] = 0
    assert torch.equal(greedy(model, input_ids, assistant_model=JacobiDrafter(), **compiled()), expected)
    assert skipped_guards["rounds"] == 0
    monkeypatch.delenv("HF_SPECVLA_FULL_GUARDS")
    model.double()  # the same model in another dtype: its rounds are new keys, guarded first (their graphs compiled)
    expected = greedy(model, input_ids)
    for _ in range(2):
        assert torch.equal(greedy(model, input_ids, assistant_model=JacobiDrafter(), **compiled()), expected)


def test_a_sliding_window_cache_keeps_every_guard(skipped_guards):
    """A static sliding-window layer keeps its length in a Python int, a constant of its graphs: the guards that tell
    its graphs apart are not the shapes, so its rounds are always guarded."""
    model = _model("gemma2")
    input_ids = torch.randint(6, 64, (1, 6), generator=torch.Generator().manual_seed(3))
    expected = greedy(model, input_ids)
    for _ in range(2):
        assert torch.equal(greedy(model, input_ids, assistant_model=JacobiDrafter(), **compiled()), expected)
    assert skipped_guards["rounds"] == 0
