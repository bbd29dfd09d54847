"""Relaxed acceptance rules beyond a global r, end to end through ``generate``: every emitted token keeps each rule's
bound against the target's greedy token given its own prefix (per action and chunk step, the confidence gate, the
relaxed-token budget per action), and r=0 is greedy decoding whatever the gate and budget."""

from __future__ import annotations

import pytest
import torch

from hf_specvla import ActionLayout, ActionPriorDrafter, ActionUnits, ComposedDrafter, JacobiDrafter

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


# ----------------------------------------------------------------------------- rules that read the action's units
def _units_layout(action_tokenizer) -> ActionLayout:
    """4-dim actions whose zero-motion bin is the middle one and whose bins are 0.01 units apart (x, y, z) and 0.02
    (the gripper)."""
    middle = action_tokenizer.n_bins // 2
    return ActionLayout(action_tokenizer, ACTION_DIM, ActionUnits((middle,) * 4, (0.01, 0.01, 0.01, 0.02)))


def _decode_with(model, action_tokenizer, input_ids, history, layout, drafters="prior", **rule):
    """Decodes with ``history`` (one chunk, two actions) as the prior's drafts (+ Jacobi) and returns (the emitted
    ids, the target's greedy id given each one's prefix)."""
    actions_only = dict(suppress_tokens=list(range(action_tokenizer.action_token_begin)))
    prior = ActionPriorDrafter(history, layout, chunk_length=2)
    drafter = ComposedDrafter([prior, JacobiDrafter()]) if drafters == "prior+jacobi" else prior
    out = model.generate(input_ids=input_ids, max_new_tokens=NEW_TOKENS, do_sample=False, assistant_model=drafter,
                         action_layout=layout, **actions_only, **rule)  # fmt: skip
    logits = model(input_ids=out).logits[0, input_ids.shape[1] - 1 : -1, action_tokenizer.action_token_begin :]
    return out[0, input_ids.shape[1] :].tolist(), (logits.argmax(-1) + action_tokenizer.action_token_begin).tolist()


def _moved_history(model, action_tokenizer, input_ids, offset: int, gripper_too: bool = True) -> list[list[int]]:
    """Greedy's own chunk with x, y, z (and the gripper when ``gripper_too``) moved by ``offset`` bins."""
    reference = greedy(model, input_ids=input_ids, max_new_tokens=NEW_TOKENS,
                       suppress_tokens=list(range(action_tokenizer.action_token_begin)))  # fmt: skip
    low, high = action_tokenizer.action_token_begin, action_tokenizer.vocab_size - 1
    ids = reference[0, input_ids.shape[1] :].tolist()
    moved = [t if (i % ACTION_DIM == ACTION_DIM - 1 and not gripper_too) else min(max(t + offset, low), high)
             for i, t in enumerate(ids)]  # fmt: skip
    return [moved[:ACTION_DIM], moved[ACTION_DIM:]]


def test_motion_scaled_tolerance_holds_token_by_token(tiny_llama, action_tokenizer):
    """Each emitted token is within max(r, floor(rho * |target bin - zero bin|)) bins of the target's greedy token
    given its prefix: large motions relaxed, motions near zero exact."""
    layout, rho = _units_layout(action_tokenizer), (0.1, 0.1, 0.1, 0.0)
    zero = layout.units.zero_bins[0]
    relaxed = exact_near_zero = 0
    for input_ids in random_prompts(6, seed=31):
        for offset in (2, -3, 6):
            history = _moved_history(tiny_llama, action_tokenizer, input_ids, offset)
            emitted, target = _decode_with(tiny_llama, action_tokenizer, input_ids, history, layout, "prior+jacobi",
                                           motion_scale=rho)  # fmt: skip
            for i, (e, t) in enumerate(zip(emitted, target)):
                size = abs(action_tokenizer.token_to_bin(t) - zero)
                assert abs(e - t) <= rho[i % ACTION_DIM] * size + 1e-6, (i, e, t, size)
                relaxed += e != t
                exact_near_zero += size < 10 and i % ACTION_DIM < 3
    assert relaxed > 0 and exact_near_zero > 0  # both sides of the scale were met


def test_action_space_bound_holds_in_the_policys_units(tiny_llama, action_tokenizer):
    """With a wide r, no accepted token's action is further than max_deviation from the target's (units: bins x
    width, the decoded actions' distance)."""
    layout, bound = _units_layout(action_tokenizer), (0.035, 0.05, 0.02, 0.0)
    widths = layout.units.bin_widths
    relaxed = 0
    for input_ids in random_prompts(6, seed=32):
        history = _moved_history(tiny_llama, action_tokenizer, input_ids, 3)
        emitted, target = _decode_with(tiny_llama, action_tokenizer, input_ids, history, layout, "prior+jacobi",
                                       bin_tolerance=8, max_deviation=bound)  # fmt: skip
        for i, (e, t) in enumerate(zip(emitted, target)):
            d = i % ACTION_DIM
            units = abs(action_tokenizer.decode(e) - action_tokenizer.decode(t)) / (2 / (action_tokenizer.n_bins - 1))
            assert abs(e - t) * widths[d] <= bound[d] + 1e-9 and units * widths[d] <= bound[d] + 1e-9, (i, e, t)
            relaxed += e != t
    assert relaxed > 0


def test_a_relaxed_token_keeps_the_drafted_gripper_or_is_dropped(tiny_llama, action_tokenizer):
    """confirm_strict_tail: in every action holding a relaxed token, the (strict) gripper emitted is the one drafted for
    it. Not vacuous: without it the same drafts leave relaxed actions whose gripper the target changed, and drafts
    whose gripper the target confirms after the relaxed prefix keep their relaxed tokens."""
    layout = ActionLayout(action_tokenizer, ACTION_DIM)
    rule = dict(bin_tolerance=[3, 3, 3, 0])

    def decode(drafts, **confirm):  # the emitted ids and, per action token, its distance to the verifier's greedy one
        # verified in the prefill and nothing drafted after it: every drafted token is known
        out = tiny_llama.generate(
            input_ids=input_ids,
            max_new_tokens=NEW_TOKENS,
            do_sample=False,
            draft_ids=torch.tensor([[*drafts[0], *drafts[1]]]),
            action_layout=layout,
            return_dict_in_generate=True,
            suppress_tokens=list(range(action_tokenizer.action_token_begin)),
            **rule,
            **confirm,
        )
        return out.sequences[0, input_ids.shape[1] :].tolist(), out.speculation.action_bin_distances

    def relaxed_actions(emitted, distances):  # the engine's own record: a distance > 0 is a relaxed token
        return [s for s in range(0, NEW_TOKENS, ACTION_DIM) if any(distances[s : s + 3])]

    kept = changed_without = 0
    for input_ids in random_prompts(8, seed=33):
        for offset in (1, 2, -2):
            history = _moved_history(tiny_llama, action_tokenizer, input_ids, offset, gripper_too=False)
            without = decode(history)
            changed_without += sum(without[0][s + 3] != history[s // ACTION_DIM][3] for s in relaxed_actions(*without))
            for drafts in (history, [without[0][:ACTION_DIM], without[0][ACTION_DIM:]]):
                emitted, distances = decode(drafts, confirm_strict_tail=True)
                for s in relaxed_actions(emitted, distances):
                    assert emitted[s + 3] == drafts[s // ACTION_DIM][3], (emitted, drafts)
                    kept += 1
    assert kept > 0 and changed_without > 0


@pytest.mark.parametrize("rule", [dict(motion_scale=0.0), dict(motion_scale=[0, 0, 0, 0], max_deviation=0.5),
                                  dict(bin_tolerance=4, max_deviation=0.0), dict(confirm_strict_tail=True),
                                  dict(motion_scale=0.0, confirm_strict_tail=True, confidence_gate=0.5)])  # fmt: skip
def test_rho0_and_a_zero_bound_are_greedy(tiny_llama, action_tokenizer, rule):
    layout = _units_layout(action_tokenizer)
    for input_ids in random_prompts(3, seed=34):
        history = _moved_history(tiny_llama, action_tokenizer, input_ids, 2)
        emitted, _ = _decode_with(tiny_llama, action_tokenizer, input_ids, history, layout, "prior+jacobi", **rule)
        expected = greedy(tiny_llama, input_ids=input_ids, max_new_tokens=NEW_TOKENS,
                          suppress_tokens=list(range(action_tokenizer.action_token_begin)))  # fmt: skip
        assert emitted == expected[0, input_ids.shape[1] :].tolist()
