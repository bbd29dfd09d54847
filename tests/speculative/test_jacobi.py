"""Jacobi drafts ([`JacobiDrafter`]): the drafter proposes exactly the target's guesses past the last verification's
first rejection (checked against a plain causal forward), r=0 stays greedy decoding alone and composed, the relaxed
bound holds, the tail's choices (closest rejected child, matching descendants, the next action's shift) follow the
rule, bad settings are refused."""

from __future__ import annotations

import pytest
import torch

from hf_specvla import (
    ActionLayout,
    ActionPriorDrafter,
    ActionTokenizer,
    ComposedDrafter,
    DraftHead,
    DraftHeadDrafter,
    DraftTreeConfig,
    JacobiDrafter,
)
from hf_specvla.speculative import jacobi_tail

from .test_compiled_verification import RecordingDrafter
from .test_speculative_decoding import greedy, random_prompts

VOCAB = 320


def test_the_drafter_proposes_the_targets_guesses_past_the_first_rejection(tiny_llama):
    for seed in range(4):
        input_ids = random_prompts(1, seed=10 + seed)[0]
        prompt = input_ids.shape[1]
        expected = greedy(tiny_llama, input_ids=input_ids, max_new_tokens=8)
        drafts = expected[:, prompt:-1].clone()  # 7 drafts, the third one wrong
        drafts[0, 2] = (drafts[0, 2] + 1) % VOCAB
        recording = RecordingDrafter(JacobiDrafter())
        out = tiny_llama.generate(input_ids=input_ids, max_new_tokens=8, do_sample=False, draft_ids=drafts,
                                  assistant_model=recording, return_dict_in_generate=True)  # fmt: skip
        assert torch.equal(out.sequences, expected)
        assert recording.trees[0] == ([], [])  # the prefill: the drafts known up front are there, no fill
        # the prefill accepted 2 drafts, its bonus replaced the third: the target's argmax after the wrong third draft
        # and the drafts after it, as a plain causal forward over prompt + drafts computes them
        logits = tiny_llama(input_ids=torch.cat([input_ids, drafts], dim=1)).logits[0]
        guesses = logits[prompt + 2 : prompt + 6].argmax(-1).tolist()  # 4 = the tokens still to draft after the bonus
        assert recording.trees[1] == (guesses, [-1, 0, 1, 2])


def test_the_tail_follows_the_closest_rejected_child_and_the_guesses():
    # root -> 0 (100) -> {2 (50), 3 (51)}; root -> 1 (103); target after the root 104, after node i at 1 + i
    parents, tokens, target = [-1, -1, 0, 0], [100, 103, 50, 51], [104, 51, 160, 70, 71]
    # without an action layout: the first rejected child, then the child equal to the guess (51 -> node 3)
    assert jacobi_tail(parents, tokens, target, []) == [51, 71]
    # with one: the child closest to the bonus in bins (103), and its guess moved by the bins the bonus moved it
    one_dim = ActionLayout(ActionTokenizer(VOCAB), 1)
    assert jacobi_tail(parents, tokens, target, [], one_dim) == [160 + 1]
    # a chain, 2 action dimensions: only the guess of the rejected token's dimension in the next action moves
    two_dims = ActionLayout(ActionTokenizer(VOCAB), 2)
    assert jacobi_tail([-1, 0, 1], [100, 101, 102], [103, 110, 111, 112], [], two_dims) == [110, 111 + 3, 112]
    # nothing rejected below the path's end: no tail
    assert jacobi_tail(parents, tokens, target, [1]) == [] and jacobi_tail([], [], [7], []) == []


def test_r0_equals_greedy_alone_composed_and_with_initial_guesses(tiny_llama):
    torch.manual_seed(2)
    head = DraftHead.from_target(tiny_llama, ActionTokenizer(VOCAB), action_dim=7, draft_action_tokens_only=False)
    tree = DraftHeadDrafter(head.eval(), tree=DraftTreeConfig(top_k=2, depth=3, total_tokens=8))
    forwards, length = {}, dict(max_new_tokens=10, min_new_tokens=10)  # no EOS before 10 tokens
    for input_ids in random_prompts(12, seed=5):
        expected = greedy(tiny_llama, input_ids=input_ids, **length)
        prompt = input_ids.shape[1]
        wrong = expected[:, prompt:-1].clone()
        wrong[0, 3] = (wrong[0, 3] + 1) % VOCAB
        calls = {"jacobi": dict(assistant_model=JacobiDrafter()),
                 "jacobi k=3": dict(assistant_model=JacobiDrafter(max_tokens=3)),
                 "drafts+jacobi": dict(draft_ids=wrong, assistant_model=JacobiDrafter()),
                 "jacobi+tree": dict(assistant_model=ComposedDrafter([JacobiDrafter(fill=False), tree])),
                 "initial guesses": dict(assistant_model=JacobiDrafter(initial_ids=expected[0, prompt:]))}  # fmt: skip
        for name, kwargs in calls.items():
            out = tiny_llama.generate(input_ids=input_ids, do_sample=False, return_dict_in_generate=True, **length,
                                      **kwargs)  # fmt: skip
            assert torch.equal(out.sequences, expected), name
            forwards.setdefault(name, []).append(out.speculation.num_target_forwards)
    assert set(forwards["initial guesses"]) == {1}  # right initial guesses: verified in the prefill
    assert max(forwards["jacobi"]) <= 10


def test_max_tokens_bounds_every_proposal(tiny_llama):
    recording = RecordingDrafter(JacobiDrafter(max_tokens=2))
    tiny_llama.generate(input_ids=random_prompts(1, seed=7)[0], max_new_tokens=9, do_sample=False,
                        assistant_model=recording)  # fmt: skip
    assert recording.trees and all(len(tokens) <= 2 for tokens, _ in recording.trees)
    assert len(recording.trees[0][0]) == 2  # alone, it fills the prefill with guesses


def test_guesses_are_counted_by_position(tiny_llama):
    input_ids = random_prompts(1, seed=8)[0]
    out = tiny_llama.generate(input_ids=input_ids, max_new_tokens=10, do_sample=False,
                              assistant_model=JacobiDrafter(), return_dict_in_generate=True)  # fmt: skip
    stats = out.speculation
    assert stats.jacobi_guesses_per_position and stats.jacobi_guesses_per_position[0] >= 1
    assert all(r <= g for r, g in zip(stats.jacobi_right_per_position, stats.jacobi_guesses_per_position))
    # each verification but the last leaves a tail; every guess of position +1 reaches an emitted token
    assert stats.jacobi_guesses_per_position[0] >= stats.num_target_forwards - 1
    twice = stats.merge(stats)  # sums over calls, as the benchmarks do
    assert twice.jacobi_guesses_per_position == [2 * g for g in stats.jacobi_guesses_per_position]
    assert twice.jacobi_right_per_position == [2 * r for r in stats.jacobi_right_per_position]


def test_relaxed_tokens_stay_within_r_bins_of_greedy_given_their_prefix(tiny_llama, action_tokenizer):
    layout, tolerance = ActionLayout(action_tokenizer, action_dim=7), 3
    actions_only = dict(suppress_tokens=list(range(action_tokenizer.action_token_begin)))
    for input_ids in random_prompts(4, seed=9):
        reference = greedy(tiny_llama, input_ids=input_ids, max_new_tokens=7, **actions_only)
        history = [[min(t + 2, VOCAB - 1) for t in reference[0, input_ids.shape[1] :].tolist()]]  # 2 bins off
        drafter = ComposedDrafter([ActionPriorDrafter(history, layout), JacobiDrafter()])
        out = tiny_llama.generate(input_ids=input_ids, max_new_tokens=7, do_sample=False, assistant_model=drafter,
                                  bin_tolerance=tolerance, return_dict_in_generate=True, **actions_only)  # fmt: skip
        sequence = out.sequences
        logits = tiny_llama(input_ids=sequence).logits[0, input_ids.shape[1] - 1 : -1]  # [7, V]
        greedy_ids = logits[:, action_tokenizer.action_token_begin :].argmax(-1) + action_tokenizer.action_token_begin
        distances = (sequence[0, input_ids.shape[1] :] - greedy_ids).abs()  # action ids are bins
        assert int(distances.max()) <= tolerance, distances


@pytest.mark.parametrize(
    "kwargs, error, message",
    [(dict(max_tokens=0), ValueError, "max_tokens must be an int >= 1 or None, got 0"),
     (dict(max_tokens=2.5), ValueError, "got 2.5"), (dict(initial_ids=[]), ValueError, "initial_ids"),
     (dict(initial_ids=[3, -1]), ValueError, r"\[3, -1\]"),
     (dict(fill="yes"), TypeError, "fill must be True or False")],
)  # fmt: skip
def test_bad_settings_are_refused(kwargs, error, message):
    with pytest.raises(error, match=message):
        JacobiDrafter(**kwargs)
