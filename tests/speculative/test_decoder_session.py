"""A decoder session (issue 75 item 4): a robot's repeated calls without ``generate``'s set-up. Its calls return
``generate``'s tokens — one shape, a shape change (a new prompt length, a batch, padding), eager and compiled, images
encoded as ``generate`` encodes them, every drafter, drafts and no drafts (greedy through the engine) — and it refuses
settings it was not built for, naming them.

Compiled with dynamo's ``eager`` backend (it traces, guards and recompiles as inductor would)."""

from __future__ import annotations

import pytest
import torch
from transformers import GenerationConfig

from hf_specvla import DraftHead, DraftHeadDrafter, DraftTreeConfig, JacobiDrafter
from hf_specvla.speculative import DecoderSession, NoDrafter

from ..conftest import llava_prompt
from .test_compiled_verification import eager_compile_config

NEW_TOKENS = 6


def settings(compiled: bool) -> dict:
    base = dict(max_new_tokens=NEW_TOKENS, do_sample=False)
    return dict(base, cache_implementation="static", compile_config=eager_compile_config()) if compiled else base


def prompt(length: int, seed: int, batch: int = 1) -> torch.Tensor:
    return torch.randint(6, 64, (batch, length), generator=torch.Generator().manual_seed(seed))


@pytest.mark.parametrize(
    "compiled", [False, pytest.param(True, marks=pytest.mark.slow)], ids=["eager", "compiled"]
)  # compiled: every width and prefill of two prompt lengths (177 s in a loaded fast tier)
def test_session_calls_equal_generate_across_calls_and_shapes(tiny_llama, compiled):
    torch.manual_seed(1)
    head = DraftHead.from_target(tiny_llama, num_draft_tokens=3).eval()
    tree = DraftHeadDrafter(head, tree=DraftTreeConfig(top_k=2, depth=3, total_tokens=6))
    session = DecoderSession(tiny_llama, **settings(compiled))
    # one shape again and again, then another length (a new bucket), then back: each call generate's tokens
    assistants = (JacobiDrafter(), head, None) if compiled else (JacobiDrafter(), head, tree, None)  # (compile time)
    calls = [(7, 0), (7, 1), (11, 3), (7, 5)]
    for call, (length, seed) in enumerate(calls):
        input_ids = prompt(length, seed)
        expected = tiny_llama.generate(input_ids=input_ids, **settings(compiled))
        for assistant in assistants:
            out = session.generate(input_ids, assistant_model=assistant)
            assert torch.equal(out, expected), (call, length, type(assistant).__name__)
    # every shape's first call went through generate, the rest past it
    assert session.calls_through_generate == 2 and session.direct_calls == len(calls) * len(assistants) - 2
    assert all(prepared is not None for prepared in session.prepared.values())


@pytest.mark.parametrize("compiled", [False, True], ids=["eager", "compiled"])
def test_session_batches_padding_draft_ids_and_outputs_equal_generate(tiny_llama, compiled):
    session = DecoderSession(tiny_llama, return_dict_in_generate=True, pad_token_id=0, **settings(compiled))
    for seed in range(3):
        input_ids = prompt(9, seed, batch=3)
        mask = torch.ones_like(input_ids)
        mask[1, :3] = mask[2, :5] = 0  # left padding: rows of 9, 6 and 4 tokens
        input_ids = input_ids.masked_fill(mask == 0, 0)
        kwargs = dict(attention_mask=mask, pad_token_id=0, **settings(compiled))
        expected = tiny_llama.generate(input_ids=input_ids, **kwargs)
        drafts = expected[:, 9:-1].clone()
        drafts[0, 1] = (drafts[0, 1] + 1) % 64  # row 0's second draft wrong
        out = session.generate(input_ids, attention_mask=mask, draft_ids=drafts, assistant_model=JacobiDrafter())
        assert torch.equal(out.sequences, expected), seed
        assert out.speculation.num_new_tokens == 3 * NEW_TOKENS
        greedy = session.generate(input_ids, attention_mask=mask)  # no drafts: the engine's greedy
        assert torch.equal(greedy.sequences, expected)
        assert greedy.speculation.num_batch_forwards == NEW_TOKENS  # one token a forward
    assert session.direct_calls == 5


@pytest.mark.parametrize("compiled", [False, True], ids=["eager", "compiled"])
def test_session_encodes_images_as_generate_does(tiny_llava, random_llava_draft, compiled):
    session = DecoderSession(tiny_llava, **settings(compiled))
    for seed in range(3):
        inputs = llava_prompt(torch.Generator().manual_seed(seed), text_len=5)
        expected = tiny_llava.generate(**inputs, **settings(compiled))
        for assistant in (random_llava_draft, JacobiDrafter()):
            out = session.generate(**inputs, assistant_model=assistant)
            assert torch.equal(out, expected), (seed, type(assistant).__name__)
    assert session.direct_calls == 5


def test_generate_with_gradients_on_and_a_session_meet_the_same_compiled_graphs(tiny_llava, caplog):
    """``model.generate(assistant_model=...)`` called with gradients on (outside ``torch.no_grad``, as a script may
    call it) and a session's calls (without) alternate on one compiled model: its images are encoded without
    gradients either way, as ``generate`` encodes them, so no call fails the other's graph guards and compiles again
    (a compiled call's image features with gradients used to fail them at every alternation)."""
    import logging

    session = DecoderSession(tiny_llava, **settings(True))
    inputs = llava_prompt(torch.Generator().manual_seed(0), text_len=5)
    expected = tiny_llava.generate(**inputs, **settings(True))
    with caplog.at_level(logging.INFO, logger="hf_specvla"):
        for _ in range(2):
            assert torch.is_grad_enabled()
            out = tiny_llava.generate(**inputs, assistant_model=JacobiDrafter(), **settings(True))
            assert torch.equal(out, expected)
            assert torch.equal(session.generate(**inputs, assistant_model=JacobiDrafter()), expected)
    failed = [r.getMessage() for r in caplog.records if "failed its graph's guards" in r.getMessage()]
    assert failed == []


def test_a_shapes_later_calls_reuse_its_round_plan_while_it_fits(tiny_llama):
    """A session's calls of one shape plan once (``call.KeptPlan``: the round plan and its static cache) and reuse
    it, the prefill compiled by the first call included; a drafter that reads other hidden states has a plan of its
    own; graphs dropped by ``reset_compilation`` or another dtype written make a new one. Every call generate's."""
    from hf_specvla.speculative import SpeculativeDecoder

    torch.manual_seed(1)
    head = DraftHead.from_target(tiny_llama, num_draft_tokens=3).eval()
    SpeculativeDecoder.reset_compilation()
    session = DecoderSession(tiny_llama, **settings(True))
    input_ids = prompt(7, 0)
    expected = tiny_llama.generate(input_ids=input_ids, **settings(True))

    def call(assistant) -> object:
        assert torch.equal(session.generate(input_ids, assistant_model=assistant), expected)
        (shape,) = session.prepared.values()
        return shape.plans

    kept = [dict(call(JacobiDrafter())) for _ in range(3)]
    (first,) = kept[0].values()
    assert [list(plans.values())[0] for plans in kept] == [first] * 3 and all(len(p) == 1 for p in kept)
    assert all(list(plans.values())[0] is first for plans in kept)  # the first call's plan, reused
    assert first.cache is not None and first.plan.verifier.compiled_prefill  # prefills compiled from the 2nd call
    plans = call(head)  # a head reads hidden states: its own plan beside the first
    assert len(plans) == 2 and first in plans.values()
    SpeculativeDecoder.reset_compilation()  # the graphs the plans run are gone: planned anew
    plans = call(JacobiDrafter())
    assert len(plans) == 2 and first not in plans.values()
    renewed = [plan for plan in plans.values() if plan.plan.output_hidden is None]
    assert len(renewed) == 1 and renewed[0].plan.verifier.graphs is not first.plan.verifier.graphs
    SpeculativeDecoder.reset_compilation()


def test_a_clock_wrapped_around_the_compiled_calls_after_a_plan_was_kept_times_the_next_call(tiny_llama):
    """A benchmark's clock installed after a session's first calls (``get_compiled_call`` and the engine's compiled
    rounds wrapped on the instance, as ``ForwardClock`` does) sees the next call's compiled forwards: the kept plan,
    which holds the unwrapped calls, no longer fits and the call plans anew."""
    from hf_specvla.speculative import CALL_WRAPPER_ATTRIBUTE, SpeculativeDecoder

    SpeculativeDecoder.reset_compilation()
    session = DecoderSession(tiny_llama, **settings(True))
    input_ids = prompt(7, 2)
    expected = tiny_llama.generate(input_ids=input_ids, **settings(True))
    for _ in range(2):
        assert torch.equal(session.generate(input_ids, assistant_model=JacobiDrafter()), expected)
    (shape,) = session.prepared.values()
    (before,) = shape.plans.values()
    timed = []

    def clock(compiled):
        def timed_call(*args, **kwargs):
            timed.append(1)
            return compiled(*args, **kwargs)

        return timed_call

    original = tiny_llama.get_compiled_call
    tiny_llama.get_compiled_call = lambda config: clock(original(config))
    setattr(tiny_llama, CALL_WRAPPER_ATTRIBUTE, clock)
    try:
        assert torch.equal(session.generate(input_ids, assistant_model=JacobiDrafter()), expected)
        (after,) = shape.plans.values()
        assert after is not before and timed  # planned anew, its compiled rounds through the clock
    finally:
        del tiny_llama.get_compiled_call
        delattr(tiny_llama, CALL_WRAPPER_ATTRIBUTE)
        SpeculativeDecoder.reset_compilation()


def test_session_samples_as_generate_does(tiny_llama):
    config = GenerationConfig(do_sample=True, temperature=0.7, top_k=20, max_new_tokens=NEW_TOKENS)
    session = DecoderSession(tiny_llama, generation_config=config)
    for seed in range(3):
        input_ids = prompt(8, seed)
        torch.manual_seed(seed)
        expected = tiny_llama.generate(input_ids=input_ids, generation_config=config, assistant_model=JacobiDrafter())
        torch.manual_seed(seed)
        assert torch.equal(session.generate(input_ids, assistant_model=JacobiDrafter()), expected), seed
    assert session.direct_calls == 2


def test_session_keeps_nothing_that_depends_on_more_than_the_shape(tiny_llama):
    session = DecoderSession(tiny_llama, max_new_tokens=NEW_TOKENS, max_time=30.0)  # a timer: its start is per call
    input_ids = prompt(7, 0)
    expected = tiny_llama.generate(input_ids=input_ids, max_new_tokens=NEW_TOKENS)
    for _ in range(3):
        assert torch.equal(session.generate(input_ids, assistant_model=JacobiDrafter()), expected)
    assert session.direct_calls == 0 and session.calls_through_generate == 3
    assert list(session.prepared.values()) == [None]


def test_session_refuses_settings_it_was_not_built_for(tiny_llama):
    session = DecoderSession(tiny_llama, max_new_tokens=NEW_TOKENS, bin_tolerance=0)
    input_ids = prompt(7, 0)
    with pytest.raises(ValueError, match=r"bin_tolerance.*this one's: max_new_tokens=6, bin_tolerance=0"):
        session.generate(input_ids, assistant_model=JacobiDrafter(), bin_tolerance=2)
    with pytest.raises(ValueError, match="max_new_tokens"):
        session.generate(input_ids, assistant_model=JacobiDrafter(), max_new_tokens=3)
    with pytest.raises(ValueError, match="do_sample"):
        session.generate(input_ids, do_sample=True)
    with pytest.raises(ValueError, match="past_key_values.*belong to a call"):
        DecoderSession(tiny_llama, max_new_tokens=3, past_key_values=None)
    with pytest.raises(TypeError, match="speculation-enabled"):
        DecoderSession(torch.nn.Linear(2, 2))
    with pytest.raises(TypeError, match="DraftHead or Drafter, got str"):
        session.generate(input_ids, assistant_model="gpt2")
    assert session.calls_through_generate == session.direct_calls == 0  # nothing ran


def test_no_drafter_decodes_greedily_one_token_a_forward(tiny_llama):
    input_ids = prompt(7, 3)
    expected = tiny_llama.generate(input_ids=input_ids, max_new_tokens=NEW_TOKENS, do_sample=False)
    out = tiny_llama.generate(input_ids=input_ids, max_new_tokens=NEW_TOKENS, assistant_model=NoDrafter(),
                              return_dict_in_generate=True)  # fmt: skip
    assert torch.equal(out.sequences, expected)
    assert out.speculation.num_target_forwards == NEW_TOKENS and set(out.speculation.tree_sizes) == {0}


def test_a_model_that_wraps_generate_keeps_its_wrapper(tiny_llama):
    """A class whose own ``generate`` wraps the mixin's (the OpenVLA port inserts its image rows there): what the
    wrapper does is its own, so every session call goes through ``model.generate``."""
    from transformers import LlamaForCausalLM

    from hf_specvla.speculative import SpeculativeGenerationMixin

    class Wrapping(SpeculativeGenerationMixin, LlamaForCausalLM):
        calls = 0

        def generate(self, *args, **kwargs):
            Wrapping.calls += 1
            return super().generate(*args, **kwargs)

    model = Wrapping(tiny_llama.config).eval()
    model.load_state_dict(tiny_llama.state_dict())
    session = DecoderSession(model, max_new_tokens=NEW_TOKENS)
    input_ids = prompt(7, 0)
    expected = tiny_llama.generate(input_ids=input_ids, max_new_tokens=NEW_TOKENS, do_sample=False)
    for _ in range(3):
        assert torch.equal(session.generate(input_ids, assistant_model=JacobiDrafter()), expected)
    assert Wrapping.calls == 3 and session.direct_calls == 0
