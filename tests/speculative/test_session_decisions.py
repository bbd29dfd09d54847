"""A decoder session is a cache of work, never of decisions (reliability-6 item 1): after any change to what decides
the tokens — the model's ``generation_config`` (its stop tokens, suppressed tokens, lengths; mutated or replaced), the
session's own ``GenerationConfig`` mutated, the model's dtype — each call through a kept session equals
``model.generate`` with the same settings after the change; a generate setting passed to a call (a tensor-valued
``eos_token_id`` included) is refused naming it, and a tensor-valued setting of the session itself is followed."""

from __future__ import annotations

import copy

import pytest
import torch
from transformers import GenerationConfig, LlamaForCausalLM

from hf_specvla import JacobiDrafter, enable_speculation
from hf_specvla.speculative import DecoderSession, NoDrafter

from ..conftest import tiny_llama_config

NEW_TOKENS = 8


@pytest.fixture
def model():
    """A fresh tiny Llama each test: the tests change its generation config."""
    torch.manual_seed(3)
    return enable_speculation(LlamaForCausalLM(tiny_llama_config()).eval())


def prompt(seed: int, length: int = 7) -> torch.Tensor:
    return torch.randint(6, 64, (1, length), generator=torch.Generator().manual_seed(seed))


def greedy(model, input_ids, **settings) -> torch.Tensor:
    return model.generate(input_ids=input_ids, max_new_tokens=NEW_TOKENS, do_sample=False, **settings)


def kept_session(model, input_ids) -> DecoderSession:
    """A session that has kept the prompt's shape (its next call goes past generate)."""
    session = DecoderSession(model, max_new_tokens=NEW_TOKENS, do_sample=False)
    for _ in range(2):
        assert torch.equal(session.generate(input_ids, assistant_model=JacobiDrafter()), greedy(model, input_ids))
    assert session.direct_calls == 1
    return session


def test_a_changed_stop_token_of_the_models_generation_config_is_followed(model):
    input_ids = prompt(0)
    session = kept_session(model, input_ids)
    before = greedy(model, input_ids)
    stop = int(before[0, input_ids.shape[1] + 2])  # the third generated token becomes the stop token
    model.generation_config.eos_token_id = stop
    expected = greedy(model, input_ids)
    assert expected.shape[1] == input_ids.shape[1] + 3  # generate now stops there
    for assistant in (JacobiDrafter(), NoDrafter(), None):
        assert torch.equal(session.generate(input_ids, assistant_model=assistant), expected)
    model.generation_config = GenerationConfig(eos_token_id=2, pad_token_id=0)  # replaced: back to the old stop
    assert torch.equal(session.generate(input_ids, assistant_model=JacobiDrafter()), before)


def test_suppressed_tokens_set_between_calls_are_suppressed(model):
    input_ids = prompt(1)
    session = kept_session(model, input_ids)
    before = greedy(model, input_ids)
    model.generation_config.suppress_tokens = [int(before[0, input_ids.shape[1]])]  # greedy's first token
    expected = greedy(model, input_ids)
    assert not torch.equal(expected, before)
    assert torch.equal(session.generate(input_ids, assistant_model=JacobiDrafter()), expected)
    model.generation_config.suppress_tokens = None
    assert torch.equal(session.generate(input_ids, assistant_model=JacobiDrafter()), before)


def test_the_sessions_own_generation_config_mutated_is_followed(model):
    input_ids = prompt(2)
    config = GenerationConfig(max_new_tokens=NEW_TOKENS, do_sample=False, eos_token_id=2, pad_token_id=0)
    session = DecoderSession(model, generation_config=config)
    for _ in range(2):
        session.generate(input_ids, assistant_model=JacobiDrafter())
    config.max_new_tokens = 3
    expected = model.generate(input_ids=input_ids, generation_config=config)
    assert expected.shape[1] == input_ids.shape[1] + 3
    assert torch.equal(session.generate(input_ids, assistant_model=JacobiDrafter()), expected)


def test_a_dtype_change_is_followed(model):
    input_ids = prompt(4)
    session = kept_session(model, input_ids)
    model.to(torch.float64)
    expected = greedy(model, input_ids)
    assert torch.equal(session.generate(input_ids, assistant_model=JacobiDrafter()), expected)
    assert session.calls_through_generate == 2  # the new dtype prepared its own shape


def test_a_generate_setting_passed_to_a_call_is_refused_naming_it_even_as_a_tensor(model):
    input_ids = prompt(5)
    session = kept_session(model, input_ids)
    for name in ("eos_token_id", "pad_token_id", "suppress_tokens"):
        with pytest.raises(ValueError, match=rf"{name} is a generate setting, not a model input"):
            session.generate(input_ids, assistant_model=JacobiDrafter(), **{name: torch.tensor([3])})
    assert session.calls_through_generate == 1 and session.direct_calls == 1  # nothing ran


def test_a_tensor_valued_stop_token_of_the_session_is_followed(model):
    input_ids = prompt(6)
    before = greedy(model, input_ids)
    generated = before[0, input_ids.shape[1] :].tolist()
    stops = [generated[1], next(t for t in generated[2:] if t not in generated[:2])]  # two tokens, the second later
    for stop in stops:
        session = DecoderSession.of(
            model, max_new_tokens=NEW_TOKENS, do_sample=False, eos_token_id=torch.tensor([stop])
        )
        expected = greedy(model, input_ids, eos_token_id=stop)
        for _ in range(2):
            assert torch.equal(session.generate(input_ids, assistant_model=JacobiDrafter()), expected)
    tensor = torch.tensor([stops[0]])
    first = DecoderSession.of(model, max_new_tokens=NEW_TOKENS, do_sample=False, eos_token_id=tensor)
    tensor[0] = stops[1]  # changed in place: another setting, another session; the first kept its own copy
    second = DecoderSession.of(model, max_new_tokens=NEW_TOKENS, do_sample=False, eos_token_id=tensor)
    assert second is not first
    assert torch.equal(
        first.generate(input_ids, assistant_model=JacobiDrafter()), greedy(model, input_ids, eos_token_id=stops[0])
    )


def test_a_deep_copied_model_with_another_generation_config_decodes_its_own(model):
    input_ids = prompt(7)
    kept_session(model, input_ids)
    other = copy.deepcopy(model)
    other.generation_config.suppress_tokens = [int(greedy(model, input_ids)[0, input_ids.shape[1]])]
    session = DecoderSession.of(other, max_new_tokens=NEW_TOKENS, do_sample=False)
    assert torch.equal(session.generate(input_ids, assistant_model=JacobiDrafter()), greedy(other, input_ids))


# engine v6 item 2: one builder of a call's set-up (prepare_call) for generate and sessions; what a session reuses is
# decided by the settings (PER_CALL_SETTINGS), not by an allow-list of processor types


class BanTokenProcessor:
    """A caller's own logits processor (no transformers type): bans one token, the same in every call."""

    def __init__(self, token: int):
        self.token = token

    def __call__(self, input_ids, scores):
        return scores.index_fill(-1, torch.tensor([self.token]), float("-inf"))


def test_a_callers_own_processor_is_reused_as_generate_reuses_it(model):
    first = prompt(4)
    banned = int(greedy(model, first)[0, first.shape[1]])  # greedy's first token
    processors = [BanTokenProcessor(banned)]
    session = DecoderSession(model, max_new_tokens=NEW_TOKENS, do_sample=False, logits_processor=processors)
    for seed in (4, 5, 6):
        input_ids = prompt(seed)
        expected = greedy(model, input_ids, logits_processor=processors)
        assert banned not in expected[0, input_ids.shape[1] :].tolist()
        assert torch.equal(session.generate(input_ids, assistant_model=JacobiDrafter()), expected), seed
    assert session.calls_through_generate == 1 and session.direct_calls == 2  # set up once, reused


def test_a_processor_that_holds_the_prompt_is_made_for_each_call(model):
    """``encoder_repetition_penalty``'s processor holds the call's prompt: a kept one would penalise the previous
    prompt's tokens. Every call of the session is set up anew and equals generate."""
    session = DecoderSession(model, max_new_tokens=NEW_TOKENS, do_sample=False, encoder_repetition_penalty=4.0)
    for seed in (7, 8, 9):
        input_ids = prompt(seed)
        expected = greedy(model, input_ids, encoder_repetition_penalty=4.0)
        assert not torch.equal(expected, greedy(model, input_ids))  # the setting changes the tokens
        assert torch.equal(session.generate(input_ids, assistant_model=JacobiDrafter()), expected), seed
    assert session.direct_calls == 0 and list(session.prepared.values()) == [None]


def test_per_call_settings_are_read_from_the_generation_config():
    from hf_specvla.speculative.session import PER_CALL_SETTINGS, per_call_settings

    assert per_call_settings(GenerationConfig()) == []
    assert per_call_settings(GenerationConfig(encoder_repetition_penalty=1.0, guidance_scale=1.0)) == []
    turned_on = GenerationConfig(max_time=3.0, encoder_repetition_penalty=1.2, encoder_no_repeat_ngram_size=2)
    assert per_call_settings(turned_on) == ["max_time", "encoder_repetition_penalty", "encoder_no_repeat_ngram_size"]
    assert all(name in vars(GenerationConfig()) for name in PER_CALL_SETTINGS)  # each a generation setting


def test_generate_and_a_session_set_calls_up_through_one_builder(model, monkeypatch):
    """The mixin's ``generate`` and a session's first call of a shape both run ``prepare_call``; a kept shape's
    call runs the same engine on the kept set-up."""
    from hf_specvla.speculative import generation
    from hf_specvla.speculative import session as session_module

    built = []
    original = generation.prepare_call

    def counting(*args, **kwargs):
        built.append(args[0])
        return original(*args, **kwargs)

    monkeypatch.setattr(generation, "prepare_call", counting)
    monkeypatch.setattr(session_module, "prepare_call", counting)
    input_ids = prompt(10)
    expected = model.generate(input_ids=input_ids, max_new_tokens=NEW_TOKENS, assistant_model=JacobiDrafter())
    assert len(built) == 1
    session = DecoderSession(model, max_new_tokens=NEW_TOKENS)
    for _ in range(3):
        assert torch.equal(session.generate(input_ids, assistant_model=JacobiDrafter()), expected)
    assert len(built) == 2 and session.direct_calls == 2
