"""The decode loop behind generate(): lossless at r=0, bounded at r>0, exact on stopping, clear on bad input."""

import pytest
import torch
from transformers import LlamaForCausalLM

import hf_specvla.decoding as decoding
from hf_specvla import DraftHead, SpeculativeDecoderOnlyOutput, disable_speculation, enable_speculation

from .conftest import llava_prompt, tiny_llama_config


def random_prompts(n: int, seed: int = 0):
    generator = torch.Generator().manual_seed(seed)
    return [
        torch.randint(3, 320, (1, int(torch.randint(2, 12, (1,), generator=generator))), generator=generator)
        for _ in range(n)
    ]


def greedy(model, **inputs):
    return model.generate(**inputs, do_sample=False)


# ------------------------------------------------------------------------------- lossless
def test_r0_equals_greedy_llama_untrained_draft(tiny_llama, random_draft):
    accept_lengths = []
    for input_ids in random_prompts(40):
        expected = greedy(tiny_llama, input_ids=input_ids, max_new_tokens=12)
        out = tiny_llama.generate(
            input_ids=input_ids,
            max_new_tokens=12,
            do_sample=False,
            assistant_model=random_draft,
            return_dict_in_generate=True,
        )
        assert torch.equal(out.sequences, expected)
        accept_lengths += out.speculation.accept_lengths
    # an untrained head is (almost) always rejected: about one token per target forward
    assert sum(accept_lengths) / len(accept_lengths) < 1.2


def test_r0_equals_greedy_llava(tiny_llava, random_llava_draft):
    generator = torch.Generator().manual_seed(0)
    for i in range(20):
        prompt = llava_prompt(generator, text_len=2 + i % 5)
        expected = greedy(tiny_llava, **prompt, max_new_tokens=9)
        out = tiny_llava.generate(**prompt, max_new_tokens=9, do_sample=False, assistant_model=random_llava_draft)
        assert torch.equal(out, expected)


def oracle_chain(continuation: torch.Tensor, corrupt_at: int | None = None):
    """A draft_chain that drafts the greedy continuation itself (optionally wrong at one draft position)."""

    def chain(draft_head, handles, scorer, state, num_draft_tokens):
        start = state.sequence.shape[1]
        drafts = continuation[:, start : start + num_draft_tokens].clone()
        if drafts.shape[1] < num_draft_tokens:  # past the end of the reference: pad with anything
            drafts = torch.cat([drafts, drafts.new_full((1, num_draft_tokens - drafts.shape[1]), 7)], 1)
        if corrupt_at is not None and corrupt_at < num_draft_tokens:
            drafts[0, corrupt_at] = (drafts[0, corrupt_at] + 1) % 320
        return drafts, num_draft_tokens - 1

    return chain


def test_perfect_draft_is_fully_accepted(tiny_llama, random_draft, monkeypatch):
    for input_ids in random_prompts(10, seed=1):
        expected = greedy(tiny_llama, input_ids=input_ids, max_new_tokens=14)
        monkeypatch.setattr(decoding, "draft_chain", oracle_chain(expected))
        out = tiny_llama.generate(
            input_ids=input_ids,
            max_new_tokens=14,
            do_sample=False,
            assistant_model=random_draft,
            num_draft_tokens=4,
            return_dict_in_generate=True,
        )
        assert torch.equal(out.sequences, expected)
        # prefill emits 1, then every verification accepts all 4 drafts + 1 bonus (last one is cut at max length)
        assert out.speculation.accept_lengths == [1, 5, 5, 3]
        assert out.speculation.acceptance_rate_per_position == [1.0, 1.0, 1.0, 1.0]


@pytest.mark.parametrize("corrupt_at", [0, 2])
def test_wrong_draft_is_rejected_from_that_position(tiny_llama, random_draft, monkeypatch, corrupt_at):
    input_ids = random_prompts(1, seed=2)[0]
    expected = greedy(tiny_llama, input_ids=input_ids, max_new_tokens=10)
    monkeypatch.setattr(decoding, "draft_chain", oracle_chain(expected, corrupt_at))
    out = tiny_llama.generate(
        input_ids=input_ids,
        max_new_tokens=10,
        do_sample=False,
        assistant_model=random_draft,
        num_draft_tokens=4,
        return_dict_in_generate=True,
    )
    assert torch.equal(out.sequences, expected)  # caches stay consistent after every rejection
    stats = out.speculation
    assert all(n == corrupt_at + 1 for n in stats.accept_lengths[1:-1])  # accepts corrupt_at drafts + bonus
    assert stats.accepted_per_position[corrupt_at] == 0


def test_stats_add_up(tiny_llama, random_draft):
    out = tiny_llama.generate(
        input_ids=random_prompts(1)[0],
        max_new_tokens=11,
        do_sample=False,
        assistant_model=random_draft,
        return_dict_in_generate=True,
    )
    stats = out.speculation
    assert isinstance(out, SpeculativeDecoderOnlyOutput)
    assert stats.num_new_tokens == 11 == sum(stats.accept_lengths)
    assert stats.num_target_forwards == len(stats.accept_lengths)
    assert stats.num_draft_forwards > 0 and stats.total_seconds >= stats.target_seconds + stats.draft_seconds
    assert all(a <= d for a, d in zip(stats.accepted_per_position, stats.drafted_per_position))


# ------------------------------------------------------------------------------- stopping and processors
def test_eos_and_max_length_stop_where_greedy_stops(tiny_llama, random_draft, monkeypatch):
    input_ids = random_prompts(1, seed=3)[0]
    reference = greedy(tiny_llama, input_ids=input_ids, max_new_tokens=10)
    eos = int(reference[0, input_ids.shape[1] + 3])  # make the 4th generated token the EOS
    expected = greedy(tiny_llama, input_ids=input_ids, max_new_tokens=10, eos_token_id=eos)
    assert expected.shape[1] <= input_ids.shape[1] + 4
    monkeypatch.setattr(decoding, "draft_chain", oracle_chain(reference))  # drafts run past the EOS
    out = tiny_llama.generate(
        input_ids=input_ids, max_new_tokens=10, do_sample=False, eos_token_id=eos, assistant_model=random_draft
    )
    assert torch.equal(out, expected)
    one = tiny_llama.generate(input_ids=input_ids, max_new_tokens=1, do_sample=False, assistant_model=random_draft)
    assert torch.equal(one, reference[:, : input_ids.shape[1] + 1])


def test_logits_processors_apply_to_every_verified_position(tiny_llama, random_draft, monkeypatch):
    input_ids = random_prompts(1, seed=4)[0]
    kwargs = dict(max_new_tokens=10, repetition_penalty=1.5, suppress_tokens=list(range(100, 200)))
    expected = greedy(tiny_llama, input_ids=input_ids, **kwargs)
    monkeypatch.setattr(decoding, "draft_chain", oracle_chain(expected))
    out = tiny_llama.generate(input_ids=input_ids, do_sample=False, assistant_model=random_draft, **kwargs)
    assert torch.equal(out, expected)
    generated = out[0, input_ids.shape[1] :]
    assert not bool(((generated >= 100) & (generated < 200)).any())


def test_left_padded_prompt(tiny_llama, random_draft):
    input_ids = torch.cat([torch.zeros(1, 3, dtype=torch.long), random_prompts(1, seed=5)[0]], dim=1)
    attention_mask = (input_ids != 0).long()
    attention_mask[:, 3:] = 1
    expected = greedy(tiny_llama, input_ids=input_ids, attention_mask=attention_mask, max_new_tokens=8)
    out = tiny_llama.generate(
        input_ids=input_ids,
        attention_mask=attention_mask,
        max_new_tokens=8,
        do_sample=False,
        assistant_model=random_draft,
    )
    assert torch.equal(out, expected)


# ------------------------------------------------------------------------------- relaxed acceptance
def assert_within_tolerance(model, prompt: dict, sequence: torch.Tensor, tolerance: list[int], action_tokenizer):
    """Every generated action token is within tolerance[dim] bins of the target's greedy token given the same
    prefix; every non-action token equals it."""
    prompt_len = prompt["input_ids"].shape[1]
    logits = model(**dict(prompt, input_ids=sequence)).logits[0]  # [L, V]
    action_count = 0
    for position in range(prompt_len, sequence.shape[1]):
        token, target = int(sequence[0, position]), int(logits[position - 1].argmax())
        if action_tokenizer.is_action_token(token) and action_tokenizer.is_action_token(target):
            assert abs(token - target) <= tolerance[action_count % len(tolerance)]
        else:
            assert token == target
        action_count += int(action_tokenizer.is_action_token(token))


@pytest.mark.parametrize("bin_tolerance", [3, 40, [40, 0, 40, 0, 40, 0, 0]])
def test_relaxed_tokens_stay_within_tolerance(tiny_llama, random_draft, action_tokenizer, bin_tolerance):
    tolerance = bin_tolerance if isinstance(bin_tolerance, list) else [bin_tolerance] * 7
    relaxed_accepts = 0
    for input_ids in random_prompts(25, seed=6):
        out = tiny_llama.generate(
            input_ids=input_ids,
            max_new_tokens=14,
            min_new_tokens=14,
            do_sample=False,
            assistant_model=random_draft,
            bin_tolerance=bin_tolerance,
            return_dict_in_generate=True,
        )
        assert_within_tolerance(tiny_llama, {"input_ids": input_ids}, out.sequences, tolerance, action_tokenizer)
        relaxed_accepts += sum(out.speculation.accepted_per_position)
    if max(tolerance) >= 40:
        assert relaxed_accepts > 0  # the invariant was exercised on accepted drafts, not only on bonus tokens


# ------------------------------------------------------------------------------- bad input
def test_batch_and_sampling_are_rejected(tiny_llama, random_draft):
    batch = torch.randint(3, 320, (2, 5))
    with pytest.raises(ValueError, match="batch size 1 .* got 2"):
        tiny_llama.generate(input_ids=batch, max_new_tokens=3, assistant_model=random_draft)
    with pytest.raises(ValueError, match="greedy only"):
        tiny_llama.generate(input_ids=batch[:1], max_new_tokens=3, do_sample=True, assistant_model=random_draft)
    with pytest.raises(ValueError, match="num_beams=1"):
        tiny_llama.generate(input_ids=batch[:1], max_new_tokens=3, num_beams=2, assistant_model=random_draft)


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(bin_tolerance=-1), ValueError, ">= 0"),
        (dict(bin_tolerance=0.5), TypeError, "non-negative int"),
        (dict(bin_tolerance=[1, 2, 3]), ValueError, "7 dimensions"),
        (dict(num_draft_tokens=0), ValueError, "num_draft_tokens"),
    ],
)
def test_bad_speculation_settings(tiny_llama, random_draft, kwargs, error, match):
    with pytest.raises(error, match=match):
        tiny_llama.generate(input_ids=random_prompts(1)[0], max_new_tokens=3, assistant_model=random_draft, **kwargs)


def test_mismatched_draft_is_rejected(tiny_llama):
    other = LlamaForCausalLM(tiny_llama_config(hidden_size=32, num_attention_heads=2, num_key_value_heads=1))
    draft = DraftHead.from_target(other)
    with pytest.raises(ValueError, match="does not fit"):
        tiny_llama.generate(input_ids=random_prompts(1)[0], max_new_tokens=3, assistant_model=draft)


def test_other_assistants_fall_through_to_transformers(tiny_llama):
    input_ids = random_prompts(1, seed=7)[0]
    expected = greedy(tiny_llama, input_ids=input_ids, max_new_tokens=6)
    assistant = LlamaForCausalLM(tiny_llama_config(num_hidden_layers=1)).eval()
    out = tiny_llama.generate(input_ids=input_ids, max_new_tokens=6, do_sample=False, assistant_model=assistant)
    assert torch.equal(out, expected)  # transformers' own assisted decoding is lossless too
    with pytest.raises(ValueError, match="bin_tolerance only apply"):
        tiny_llama.generate(input_ids=input_ids, max_new_tokens=6, assistant_model=assistant, bin_tolerance=2)


def test_enable_disable_keeps_the_model_class(tmp_path):
    model = LlamaForCausalLM(tiny_llama_config())
    enable_speculation(model)
    assert type(model).__name__ == "LlamaForCausalLM" and isinstance(model, LlamaForCausalLM)
    model.save_pretrained(tmp_path)
    assert '"LlamaForCausalLM"' in (tmp_path / "config.json").read_text()
    assert type(enable_speculation(model)) is type(model)  # idempotent
    disable_speculation(model)
    assert type(model) is LlamaForCausalLM
    with pytest.raises(TypeError, match="PreTrainedModel"):
        enable_speculation(torch.nn.Linear(2, 2))


def test_custom_generate_callable_without_the_mixin(random_draft, tiny_llama):
    from hf_specvla import speculative_generate

    plain = LlamaForCausalLM(tiny_llama_config())
    plain.load_state_dict(tiny_llama.state_dict())
    input_ids = random_prompts(1, seed=8)[0]
    expected = greedy(plain.eval(), input_ids=input_ids, max_new_tokens=5)
    out = plain.generate(
        input_ids=input_ids,
        max_new_tokens=5,
        do_sample=False,
        custom_generate=speculative_generate,
        draft_head=random_draft,
    )
    assert torch.equal(out, expected)
