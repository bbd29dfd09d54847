"""Relaxed acceptance rules beyond a global r, end to end through ``generate``: every emitted token keeps each rule's
bound against the target's greedy token given its own prefix (per action and chunk step, the confidence gate, the
relaxed-token budget per action), and r=0 is greedy decoding whatever the gate and budget."""

from __future__ import annotations

import pytest
import torch

from hf_specvla import ActionLayout, ActionPriorDrafter, ComposedDrafter, JacobiDrafter

from .test_speculative_decoding import greedy, random_prompts

ACTION_DIM, NEW_TOKENS = 4, 8  # chunks of 2 actions


def _checked_run(model, action_tokenizer, input_ids, offset: int, **rule):
    """Decodes with the prior drafting greedy's tokens moved by ``offset`` bins (+ Jacobi) and returns, per emitted
    token, (bin distance to the target's greedy token given its prefix, the target's top-1 probability)."""
    actions_only = dict(suppress_tokens=list(range(action_tokenizer.action_token_begin)))
    layout = ActionLayout(action_tokenizer, ACTION_DIM)
    reference = greedy(model, input_ids=input_ids, max_new_tokens=NEW_TOKENS, **actions_only)
    last = action_tokenizer.vocab_size - 1
    moved = [min(t + offset, last) for t in reference[0, input_ids.shape[1] :].tolist()]
    history = [moved[:ACTION_DIM], moved[ACTION_DIM:]]  # the previous chunk: two actions
    drafter = ComposedDrafter([ActionPriorDrafter(history, layout, chunk_length=2), JacobiDrafter()])
    out = model.generate(input_ids=input_ids, max_new_tokens=NEW_TOKENS, do_sample=False, assistant_model=drafter,
                         return_dict_in_generate=True, **actions_only, **rule)  # fmt: skip
    sequence = out.sequences
    logits = model(input_ids=sequence).logits[0, input_ids.shape[1] - 1 : -1, action_tokenizer.action_token_begin :]
    probs = logits.float().softmax(-1)  # over the action tokens: what the processed scores leave
    greedy_ids = probs.argmax(-1) + action_tokenizer.action_token_begin
    distances = (sequence[0, input_ids.shape[1] :] - greedy_ids).abs()  # action ids are bins
    return distances.tolist(), probs.amax(-1).tolist(), sequence


def test_per_action_tolerance_holds_token_by_token(tiny_llama, action_tokenizer):
    table = [[1, 1, 1, 0], [3, 3, 3, 0]]  # the first action of the chunk tighter, the gripper exact
    relaxed = 0
    for input_ids in random_prompts(4, seed=21):
        distances, _, _ = _checked_run(tiny_llama, action_tokenizer, input_ids, 2, bin_tolerance=table)
        for i, d in enumerate(distances):
            assert d <= table[i // ACTION_DIM][i % ACTION_DIM], (i, distances)
        relaxed += sum(d > 0 for d in distances)
    assert relaxed > 0  # the rule fired (the test is not vacuous)


def test_confidence_gate_leaves_confident_tokens_to_the_target(tiny_llama, action_tokenizer):
    gate, relaxed, confident = 0.006, 0, 0  # random weights: top-1 probabilities 0.005-0.008; the gate splits them
    for input_ids in random_prompts(6, seed=22):
        distances, top1, _ = _checked_run(tiny_llama, action_tokenizer, input_ids, 1, bin_tolerance=3,
                                          confidence_gate=gate)  # fmt: skip
        for d, p in zip(distances, top1):
            assert d <= 3 and (d == 0 or p < gate), (distances, top1)
        relaxed += sum(d > 0 for d in distances)
        confident += sum(p >= gate for p in top1)
    assert relaxed > 0 and confident > 0  # both sides of the gate were met


def test_relaxed_budget_bounds_each_action(tiny_llama, action_tokenizer):
    relaxed = 0
    for input_ids in random_prompts(4, seed=23):
        distances, _, _ = _checked_run(tiny_llama, action_tokenizer, input_ids, 1, bin_tolerance=4,
                                       max_relaxed_per_action=1)  # fmt: skip
        for start in range(0, NEW_TOKENS, ACTION_DIM):
            assert sum(d > 0 for d in distances[start : start + ACTION_DIM]) <= 1, distances
        relaxed += sum(d > 0 for d in distances)
    assert relaxed > 0


@pytest.mark.parametrize("rule", [dict(confidence_gate=0.5), dict(max_relaxed_per_action=2),
                                  dict(bin_tolerance=[[0] * 4, [0] * 4], confidence_gate=0.9)])  # fmt: skip
def test_r0_is_greedy_whatever_the_rule(tiny_llama, action_tokenizer, rule):
    for input_ids in random_prompts(3, seed=24):
        distances, _, sequence = _checked_run(tiny_llama, action_tokenizer, input_ids, 2, **rule)
        expected = greedy(tiny_llama, input_ids=input_ids, max_new_tokens=NEW_TOKENS,
                          suppress_tokens=list(range(action_tokenizer.action_token_begin)))  # fmt: skip
        assert torch.equal(sequence, expected) and max(distances) == 0
