"""Batched speculative decoding (B > 1): at r=0 every row equals batched greedy decoding on the same left-padded
batch and decoding the row alone, whatever each row accepts; rows stop on their own; r > 0 stays within r bins
per row; statistics per row add up; bad batches are refused clearly."""

import re

import pytest
import torch

from hf_specvla import (
    ActionLayout,
    ActionPriorDrafter,
    DraftHeadDrafter,
    DraftTreeConfig,
    PerRowDrafter,
)
from hf_specvla.benchmarks.toy import ACTION_DIM, split_scenes, toy_inputs

from ..conftest import IMAGE_TOKEN
from .test_speculative_decoding import OracleDrafter

PAD = 0


def left_padded(rows: list[torch.Tensor]) -> dict[str, torch.Tensor]:
    """``[1, S_b]`` prompts -> ``input_ids`` / ``attention_mask`` ``[B, S_max]``, left-padded with PAD."""
    length = max(r.shape[1] for r in rows)
    input_ids = torch.full((len(rows), length), PAD, dtype=torch.long)
    attention_mask = torch.zeros(len(rows), length, dtype=torch.long)
    for b, row in enumerate(rows):
        input_ids[b, length - row.shape[1] :] = row[0]
        attention_mask[b, length - row.shape[1] :] = 1
    return {"input_ids": input_ids, "attention_mask": attention_mask}


def text_prompts(batch_size: int, seed: int) -> list[torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    lengths = torch.randint(2, 12, (batch_size,), generator=generator).tolist()
    lengths[0] = 12  # at least one row unpadded, others padded
    return [torch.randint(3, 320, (1, n), generator=generator) for n in lengths]


def greedy(model, **inputs):
    return model.generate(**inputs, do_sample=False, pad_token_id=PAD)


def assert_rows_equal_alone(model, prompts, sequences, extra_inputs=None, **generate_kwargs):
    """Row b of the batched output = row b decoded alone (unpadded), then right padding."""
    prompt_width = max(p.shape[1] for p in prompts)
    for b, prompt in enumerate(prompts):
        inputs = {"input_ids": prompt, **({} if extra_inputs is None else extra_inputs(b))}
        alone = greedy(model, **inputs, **generate_kwargs)[0, prompt.shape[1] :]
        generated = sequences[b, prompt_width:]
        assert torch.equal(generated[: len(alone)], alone), (b, generated, alone)
        assert bool((generated[len(alone) :] == PAD).all()), (b, generated, alone)


def eos_reached_early(model, batch, max_new_tokens) -> int:
    """A token row 0's greedy continuation emits at step 3: as EOS, row 0 (and maybe others) stops early."""
    reference = greedy(model, **batch, max_new_tokens=max_new_tokens)
    return int(reference[0, batch["input_ids"].shape[1] + 2])


# ------------------------------------------------------------------------------- lossless, Llama
@pytest.mark.parametrize("batch_size", [2, 3, 5])
@pytest.mark.parametrize("drafting", ["chain", "tree"])
def test_r0_batch_equals_batched_greedy_and_each_row_alone_llama(tiny_llama, random_draft, batch_size, drafting):
    assistant = random_draft if drafting == "chain" else DraftHeadDrafter(random_draft, tree=DraftTreeConfig())
    for seed in range(3):
        prompts = text_prompts(batch_size, seed)
        batch = left_padded(prompts)
        eos = eos_reached_early(tiny_llama, batch, 12)
        expected = greedy(tiny_llama, **batch, max_new_tokens=12, eos_token_id=eos)
        out = tiny_llama.generate(
            **batch, max_new_tokens=12, eos_token_id=eos, pad_token_id=PAD, assistant_model=assistant,
            return_dict_in_generate=True,
        )  # fmt: skip
        assert torch.equal(out.sequences, expected)
        assert_rows_equal_alone(tiny_llama, prompts, out.sequences, max_new_tokens=12, eos_token_id=eos)
        assert bool(out.sequences[0, -1] == PAD), "row 0 stops at its EOS, 9 steps before max_new_tokens"


@pytest.mark.parametrize("batch_size", [2, 3, 5])
def test_r0_batch_with_drafts_right_for_some_rows_and_wrong_for_others(tiny_llama, batch_size):
    prompts = text_prompts(batch_size, seed=10 + batch_size)
    batch = left_padded(prompts)
    width = batch["input_ids"].shape[1]
    expected = greedy(tiny_llama, **batch, max_new_tokens=10)
    right_rows = set(range(0, batch_size, 2))
    draft_ids = expected[:, width : width + 6].clone()  # the rows' true continuations, as up-front drafts
    for b in range(batch_size):
        if b not in right_rows:
            draft_ids[b, 1] = (draft_ids[b, 1] + 1) % 320  # wrong from the second token on
    oracles = PerRowDrafter(
        [OracleDrafter(expected[b : b + 1], 3, corrupt_at=None if b in right_rows else 0) for b in range(batch_size)]
    )
    out = tiny_llama.generate(
        **batch, max_new_tokens=10, pad_token_id=PAD, draft_ids=draft_ids, assistant_model=oracles,
        return_dict_in_generate=True,
    )  # fmt: skip
    assert torch.equal(out.sequences, expected)
    assert_rows_equal_alone(tiny_llama, prompts, out.sequences, max_new_tokens=10)
    rows = out.speculation.rows
    assert len(rows) == batch_size
    for b, row in enumerate(rows):
        # the prefill accepts all 6 drafts + its bonus token where they are right, 1 + 1 where they are wrong
        assert row.accept_lengths[0] == (7 if b in right_rows else 2), (b, row.accept_lengths)
        assert row.num_new_tokens == 10
    # per-row statistics add up to the summed ones; a batch forward counts once per row that took part
    assert out.speculation.accept_lengths == [n for row in rows for n in row.accept_lengths]
    assert out.speculation.num_batch_forwards == max(row.num_target_forwards for row in rows)
    assert out.speculation.num_target_forwards == sum(row.num_target_forwards for row in rows)


def test_r0_batch_with_per_row_action_priors(tiny_llama, action_tokenizer):
    layout = ActionLayout(action_tokenizer, action_dim=7)
    prompts = text_prompts(4, seed=20)
    batch = left_padded(prompts)
    width = batch["input_ids"].shape[1]
    expected = greedy(tiny_llama, **batch, max_new_tokens=7, suppress_tokens=list(range(64)))  # actions only
    histories = []
    for b in range(4):
        truth = expected[b, width:].tolist()
        histories.append([truth] if b % 2 == 0 else [[min(t + 9, 319) for t in truth]])  # right / 9 bins off
    drafter = PerRowDrafter([ActionPriorDrafter(h, layout) for h in histories])
    out = tiny_llama.generate(
        **batch, max_new_tokens=7, pad_token_id=PAD, suppress_tokens=list(range(64)), assistant_model=drafter,
        return_dict_in_generate=True,
    )  # fmt: skip
    assert torch.equal(out.sequences, expected)
    assert [row.num_target_forwards for row in out.speculation.rows][::2] == [1, 1]  # the whole action in the prefill


def test_r0_single_row_batch_matches_the_unbatched_call(tiny_llama, random_draft):
    prompt = text_prompts(1, seed=3)[0]
    padded = left_padded([prompt, prompt[:, :4]])
    out = tiny_llama.generate(**padded, max_new_tokens=9, pad_token_id=PAD, assistant_model=random_draft)
    alone = tiny_llama.generate(input_ids=prompt, max_new_tokens=9, pad_token_id=PAD, assistant_model=random_draft)
    assert torch.equal(out[:1], alone)


def test_batch_scores_are_batched_greedy_scores(tiny_llama, random_draft):
    batch = left_padded(text_prompts(3, seed=4))
    kwargs = dict(max_new_tokens=8, pad_token_id=PAD, return_dict_in_generate=True, output_scores=True)
    expected = tiny_llama.generate(**batch, do_sample=False, **kwargs)
    out = tiny_llama.generate(**batch, assistant_model=random_draft, **kwargs)
    assert len(out.scores) == len(expected.scores) == 8
    for ours, theirs in zip(out.scores, expected.scores):
        assert torch.allclose(ours, theirs, atol=1e-4)


# ------------------------------------------------------------------------------- lossless, Llava
@pytest.mark.parametrize("batch_size", [2, 3])
def test_r0_batch_equals_batched_greedy_llava(tiny_llava, random_llava_draft, batch_size):
    generator = torch.Generator().manual_seed(batch_size)
    prompts, images = [], []
    for b in range(batch_size):
        text = torch.randint(6, 64, (1, 2 + 3 * b), generator=generator)
        prompts.append(torch.cat([torch.tensor([[1] + [IMAGE_TOKEN] * 4]), text], dim=1))
        images.append(torch.randn(1, 3, 16, 16, generator=generator))
    batch = dict(left_padded(prompts), pixel_values=torch.cat(images))
    eos = eos_reached_early(tiny_llava, batch, 9)
    expected = greedy(tiny_llava, **batch, max_new_tokens=9, eos_token_id=eos)
    for assistant in (random_llava_draft, DraftHeadDrafter(random_llava_draft, tree=DraftTreeConfig())):
        out = tiny_llava.generate(**batch, max_new_tokens=9, eos_token_id=eos, pad_token_id=PAD,
                                  assistant_model=assistant)  # fmt: skip
        assert torch.equal(out, expected)
        assert_rows_equal_alone(
            tiny_llava, prompts, out, lambda b: {"pixel_values": images[b]}, max_new_tokens=9, eos_token_id=eos
        )


def test_r0_batch_with_a_trained_head_on_the_toy_target(toy_pipeline):
    held_out = split_scenes()[1]
    scenes = held_out[:8]
    batch = toy_inputs(scenes, toy_pipeline.tokenizer)
    expected = toy_pipeline.target.generate(**batch, max_new_tokens=ACTION_DIM, do_sample=False)
    out = toy_pipeline.target.generate(
        **batch, max_new_tokens=ACTION_DIM, assistant_model=toy_pipeline.draft_head, return_dict_in_generate=True
    )
    assert torch.equal(out.sequences, expected)
    for b, scene in enumerate(scenes):
        alone = toy_pipeline.target.generate(
            **toy_inputs([scene], toy_pipeline.tokenizer), max_new_tokens=ACTION_DIM, do_sample=False
        )
        assert torch.equal(out.sequences[b, -ACTION_DIM:], alone[0, -ACTION_DIM:])
    assert out.speculation.mean_accept_length >= 3.0  # the trained head still drafts well inside a batch


# ------------------------------------------------------------------------------- relaxed
@pytest.mark.parametrize("bin_tolerance", [3, 40])
def test_relaxed_batch_rows_stay_within_tolerance(tiny_llama, random_draft, action_tokenizer, bin_tolerance):
    prompts = text_prompts(4, seed=30)
    batch = left_padded(prompts)
    width = batch["input_ids"].shape[1]
    layout = ActionLayout(action_tokenizer, action_dim=7)
    reference = greedy(tiny_llama, **batch, max_new_tokens=7, suppress_tokens=list(range(64)))
    histories = [[[min(t + 2, 319) for t in reference[b, width:].tolist()]] for b in range(4)]  # 2 bins off
    drafter = PerRowDrafter([ActionPriorDrafter(h, layout) for h in histories])
    out = tiny_llama.generate(
        **batch, max_new_tokens=7, pad_token_id=PAD, suppress_tokens=list(range(64)), assistant_model=drafter,
        bin_tolerance=bin_tolerance, return_dict_in_generate=True,
    )  # fmt: skip
    for b, prompt in enumerate(prompts):
        sequence = torch.cat([prompt, out.sequences[b : b + 1, width:]], dim=1)  # the row's own prefix, unpadded
        logits = tiny_llama(input_ids=sequence).logits[0, prompt.shape[1] - 1 : -1]  # [7, V]
        greedy_ids = logits[:, 64:].argmax(-1) + 64  # the greedy token under suppress_tokens (text ids)
        distances = (sequence[0, prompt.shape[1] :] - greedy_ids).abs()  # action ids are bins
        assert int(distances.max()) <= bin_tolerance, (b, distances)
    assert sum(out.speculation.accepted_per_position) > 0  # relaxed drafts were accepted, not only bonus tokens


# ------------------------------------------------------------------------------- bad input
def test_per_row_drafter_must_match_the_batch(tiny_llama, action_tokenizer):
    layout = ActionLayout(action_tokenizer, action_dim=7)
    drafter = PerRowDrafter([ActionPriorDrafter([[100] * 7], layout)] * 3)
    batch = left_padded(text_prompts(2, seed=0))
    with pytest.raises(ValueError, match="one drafter per row for 3 rows .* input_ids has 2 rows"):
        tiny_llama.generate(**batch, max_new_tokens=3, pad_token_id=PAD, assistant_model=drafter)
    with pytest.raises(ValueError, match="draft_ids has batch size 1, input_ids has 2"):
        tiny_llama.generate(**batch, max_new_tokens=3, pad_token_id=PAD, draft_ids=torch.tensor([[100, 101]]))
    with pytest.raises(ValueError, match="one drafter per batch row, got none"):
        PerRowDrafter([])
    with pytest.raises(TypeError, match="one Drafter per row, got str at row 1"):
        PerRowDrafter([drafter.drafters[0], "prior"])


def test_prefix_constrained_decoding_is_refused_for_a_batch(tiny_llama, random_draft):
    batch = left_padded(text_prompts(2, seed=0))
    with pytest.raises(ValueError, match="prefix_allowed_tokens_fn .* 2 sequences"):
        tiny_llama.generate(
            **batch, max_new_tokens=3, pad_token_id=PAD, assistant_model=random_draft,
            prefix_allowed_tokens_fn=lambda batch_id, ids: list(range(320)),
        )  # fmt: skip


@pytest.mark.parametrize("drafting", ["head", "draft_ids", "custom_generate"])
def test_a_right_padded_batch_is_refused_before_any_forward(tiny_llama, random_draft, drafting):
    """Right padding would make a row continue after its padding (other tokens than the row alone: transformers
    only warns). Refused, naming the rows, before the target runs."""
    from hf_specvla import speculative_generate

    left = left_padded(text_prompts(3, seed=5))
    right = {k: torch.stack([torch.cat([row[row_mask.bool()], row[~row_mask.bool()]]) for row, row_mask
                             in zip(v, left["attention_mask"])]) for k, v in left.items()}  # fmt: skip
    assert not torch.equal(right["attention_mask"], left["attention_mask"])
    kwargs = {
        "head": dict(assistant_model=random_draft),
        "draft_ids": dict(draft_ids=torch.full((3, 2), 100)),
        "custom_generate": dict(custom_generate=speculative_generate, drafter=random_draft),
    }[drafting]
    forwards = []
    hook = tiny_llama.register_forward_pre_hook(lambda *args: forwards.append(1))
    try:
        with pytest.raises(ValueError, match=r"padding after the tokens of row\(s\) \[1, 2\]: the batch is right-padded"
                                             r".*padding_side = 'left'"):  # fmt: skip
            tiny_llama.generate(**right, max_new_tokens=4, do_sample=False, pad_token_id=PAD, **kwargs)
    finally:
        hook.remove()
    assert forwards == []
    # the same batch left-padded speculates as usual
    out = tiny_llama.generate(**left, max_new_tokens=4, do_sample=False, pad_token_id=PAD, **kwargs)
    assert out.shape == (3, left["input_ids"].shape[1] + 4)


# ------------------------------------------------------------------------------- max_drafts_per_row
@pytest.mark.parametrize("cap", [0, 1, 2])
def test_max_drafts_per_row_cuts_every_tree_and_stays_lossless(tiny_llama, random_draft, cap):
    """Batches verify fewer drafts per row than one row can afford (a compute-bound forward's cost grows with its
    tokens): every verified tree holds at most ``cap`` drafts, and r=0 is still batched greedy decoding."""
    prompts = [torch.randint(3, 320, (1, n), generator=torch.Generator().manual_seed(n)) for n in (5, 9, 7)]
    width = max(p.shape[1] for p in prompts)
    input_ids = torch.cat([torch.cat([torch.zeros(1, width - p.shape[1], dtype=torch.long), p], 1) for p in prompts])
    mask = torch.cat([torch.cat([torch.zeros(1, width - p.shape[1]), torch.ones(1, p.shape[1])], 1) for p in prompts])
    batch = {"input_ids": input_ids, "attention_mask": mask.long()}
    expected = tiny_llama.generate(**batch, max_new_tokens=10, do_sample=False)
    right = expected[:, width:]
    tree = DraftHeadDrafter(random_draft, tree=DraftTreeConfig(top_k=2, total_tokens=8))
    for kwargs in ({"draft_ids": right}, {"assistant_model": tree}):
        out = tiny_llama.generate(**batch, max_new_tokens=10, do_sample=False, max_drafts_per_row=cap,
                                  return_dict_in_generate=True, **kwargs)  # fmt: skip
        assert torch.equal(out.sequences, expected)
        assert max(out.speculation.tree_sizes) <= cap
    # right drafts, cut to `cap`: each forward emits cap + 1 tokens per row (until the last ones)
    out = tiny_llama.generate(**batch, max_new_tokens=10, do_sample=False, max_drafts_per_row=cap, draft_ids=right,
                              return_dict_in_generate=True)  # fmt: skip
    assert out.speculation.num_batch_forwards == -(-10 // (cap + 1))


@pytest.mark.parametrize("cap", [-1, 1.5, True, "2"])
def test_bad_max_drafts_per_row(tiny_llama, random_draft, cap):
    with pytest.raises(ValueError, match=f"max_drafts_per_row must be an int >= 0 .* got {re.escape(repr(cap))}"):
        tiny_llama.generate(input_ids=torch.tensor([[5, 6, 7]]), max_new_tokens=3, assistant_model=random_draft,
                            max_drafts_per_row=cap)  # fmt: skip


# ------------------------------------------------------------------------------- rows reported as they finish
@pytest.mark.parametrize("cache_implementation", [None, "static"])
def test_on_row_finished_reports_each_row_when_it_stops(tiny_llama, cache_implementation):
    """Rows whose drafts are right finish in the prefill, the others rounds later: each is reported once, in
    finishing order, with exactly the tokens the returned batch holds for it; the output is greedy's."""
    prompts = text_prompts(4, seed=31)
    batch = left_padded(prompts)
    width = batch["input_ids"].shape[1]
    eos = eos_reached_early(tiny_llama, batch, 8)
    expected = greedy(tiny_llama, **batch, max_new_tokens=8, eos_token_id=eos)
    draft_ids = expected[:, width : width + 7].clone()
    draft_ids[1::2, 0] = (draft_ids[1::2, 0] + 1) % 320  # rows 1 and 3: wrong drafts, one token a forward
    reported = []
    out = tiny_llama.generate(
        **batch, max_new_tokens=8, eos_token_id=eos, pad_token_id=PAD, draft_ids=draft_ids,
        on_row_finished=lambda row, new_tokens, stats: reported.append((row, new_tokens.clone(), stats)),
        cache_implementation=cache_implementation, return_dict_in_generate=True,
    )  # fmt: skip
    assert torch.equal(out.sequences, expected)
    assert sorted(row for row, _, _ in reported) == [0, 1, 2, 3]
    for row, tokens, stats in reported:
        generated = out.sequences[row, width:]
        assert torch.equal(tokens, generated[: len(tokens)]) and bool((generated[len(tokens) :] == PAD).all())
        assert stats.accept_lengths == out.speculation.rows[row].accept_lengths  # the row's final statistics
    forwards = [out.speculation.rows[row].num_target_forwards for row, _, _ in reported]
    assert forwards == sorted(forwards) and forwards[0] < forwards[-1], forwards  # early rows reported first


def test_on_row_finished_must_be_callable(tiny_llama):
    batch = left_padded(text_prompts(2, seed=1))
    with pytest.raises(TypeError, match="on_row_finished must be a callable.*got str"):
        tiny_llama.generate(**batch, max_new_tokens=4, pad_token_id=PAD, draft_ids=batch["input_ids"][:, :2],
                            on_row_finished="print")  # fmt: skip
