"""Acceptance rules on hand-built token ids (action ids are 64..319, text ids below 64)."""

import pytest
import torch

from hf_specvla import ExactMatch, RelaxedBinMatch, make_acceptance_rule
from hf_specvla.acceptance import accepted_prefix_length, action_dimensions


def test_exact_match():
    draft = torch.tensor([[100, 101, 102]])
    target = torch.tensor([[100, 101, 999]])
    accepted = ExactMatch()(draft, target)
    assert accepted.tolist() == [[True, True, False]]
    assert accepted_prefix_length(accepted).tolist() == [2]  # accepts 2


def test_prefix_stops_at_first_rejection():
    # rejects 2nd, so the accepted 3rd does not count
    assert accepted_prefix_length(torch.tensor([[True, False, True]])).tolist() == [1]
    assert accepted_prefix_length(torch.tensor([[False, True, True], [True, True, True]])).tolist() == [0, 3]
    assert accepted_prefix_length(torch.zeros(1, 0, dtype=torch.bool)).tolist() == [0]


def test_relaxed_within_tolerance(action_tokenizer):
    rule = RelaxedBinMatch(action_tokenizer, bin_tolerance=2, action_dim=7)
    draft = torch.tensor([[100, 150, 200, 250]])
    target = torch.tensor([[102, 147, 200, 253]])  # off by 2 (ok), 3 (too far), 0, 3
    assert rule(draft, target).tolist() == [[True, False, True, False]]


def test_relaxed_needs_both_action_tokens(action_tokenizer):
    rule = RelaxedBinMatch(action_tokenizer, bin_tolerance=5, action_dim=7)
    # 62/63 are text ids next to the first action id 64: never accepted unless equal
    draft = torch.tensor([[62, 64, 63, 40]])
    target = torch.tensor([[63, 63, 65, 40]])
    assert rule(draft, target).tolist() == [[False, False, False, True]]


def test_per_dimension_tolerance(action_tokenizer):
    # strict gripper (dimension 6), loose elsewhere
    rule = RelaxedBinMatch(action_tokenizer, bin_tolerance=[3, 3, 3, 3, 3, 3, 0], action_dim=7)
    draft = torch.tensor([[100, 100]])
    target = torch.tensor([[101, 101]])
    dims = torch.tensor([[5, 6]])
    assert rule(draft, target, dims).tolist() == [[True, False]]


def test_action_dimensions(action_tokenizer):
    draft = torch.tensor([[100, 101, 10, 102]])  # 10 is text: does not advance the dimension
    assert action_dimensions(draft, action_tokenizer, 5, 7).tolist() == [[5, 6, 0, 0]]


def test_rule_factory(action_tokenizer):
    assert isinstance(make_acceptance_rule(0, action_tokenizer, 7), ExactMatch)
    assert isinstance(make_acceptance_rule([0] * 7, action_tokenizer, 7), ExactMatch)
    relaxed = make_acceptance_rule(2, action_tokenizer, 7)
    assert isinstance(relaxed, RelaxedBinMatch) and not relaxed.is_lossless


@pytest.mark.parametrize(
    "tolerance, error, match",
    [
        (-1, ValueError, ">= 0"),
        (1.5, TypeError, "non-negative int"),
        (True, TypeError, "non-negative int"),
        ("2", TypeError, "non-negative int"),
        ([1, 2], ValueError, "7 dimensions"),
        ([1] * 6 + [-2], ValueError, r"\[6\]"),
    ],
)
def test_bad_tolerance(action_tokenizer, tolerance, error, match):
    with pytest.raises(error, match=match):
        make_acceptance_rule(tolerance, action_tokenizer, 7)
