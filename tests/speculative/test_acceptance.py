"""Acceptance rules and tree-path choice on hand-built token ids (action ids are 64..319, text ids below 64)."""

import pytest
import torch

from hf_specvla import (
    ActionLayout,
    ConfidenceGate,
    DraftTree,
    ExactMatch,
    RelaxedBinMatch,
    RelaxedBudget,
    SpeculationConfig,
    make_acceptance_rule,
)
from hf_specvla.speculative import accept_tree


@pytest.fixture(scope="module")
def layout(action_tokenizer):
    return ActionLayout(action_tokenizer, 7)


def test_exact_match():
    draft = torch.tensor([[100, 101, 102]])
    target = torch.tensor([[100, 101, 999]])
    assert ExactMatch()(draft, target).tolist() == [[True, True, False]]


def test_relaxed_within_tolerance(layout):
    rule = RelaxedBinMatch(layout, bin_tolerance=2)
    draft = torch.tensor([[100, 150, 200, 250]])
    target = torch.tensor([[102, 147, 200, 253]])  # off by 2 (ok), 3 (too far), 0, 3
    assert rule(draft, target).tolist() == [[True, False, True, False]]


def test_relaxed_needs_both_action_tokens(layout):
    rule = RelaxedBinMatch(layout, bin_tolerance=5)
    # 62/63 are text ids next to the first action id 64: never accepted unless equal
    draft = torch.tensor([[62, 64, 63, 40]])
    target = torch.tensor([[63, 63, 65, 40]])
    assert rule(draft, target).tolist() == [[False, False, False, True]]


def test_per_dimension_tolerance(layout):
    # strict gripper (dimension 6), loose elsewhere
    rule = RelaxedBinMatch(layout, bin_tolerance=[3, 3, 3, 3, 3, 3, 0])
    draft = torch.tensor([[100, 100]])
    target = torch.tensor([[101, 101]])
    dims = torch.tensor([[5, 6]])
    assert rule(draft, target, dims).tolist() == [[True, False]]


def test_rule_factory(layout):
    assert isinstance(make_acceptance_rule(0, layout), ExactMatch)
    assert isinstance(make_acceptance_rule([0] * 7, layout), ExactMatch)
    relaxed = make_acceptance_rule(2, layout)
    assert isinstance(relaxed, RelaxedBinMatch) and not relaxed.is_lossless
    assert isinstance(make_acceptance_rule(0, None), ExactMatch)  # exact needs no layout
    with pytest.raises(ValueError, match="action_layout=ActionLayout"):
        make_acceptance_rule(2, None)  # relaxed does


@pytest.mark.parametrize(
    "tolerance, error, match",
    [
        (-1, ValueError, ">= 0"),
        (1.5, TypeError, "non-negative int"),
        (True, TypeError, "non-negative int"),
        ("2", TypeError, "non-negative int"),
        ([1, 2], ValueError, "7 dimensions"),
        ([1] * 6 + [-2], ValueError, r"\[6\]"),
        # the one wording the engine, compare and eval share
        (256, ValueError, r"bin_tolerance=256: r is wider than the action range .*256 bins.* use r in 0..255"),
        ([0] * 6 + [300], ValueError, r"bin_tolerance=\[0, 0, 0, 0, 0, 0, 300\]: r is wider"),
    ],
)
def test_bad_tolerance(layout, tolerance, error, match):
    with pytest.raises(error, match=match):
        make_acceptance_rule(tolerance, layout)


# ------------------------------------------------------------------------------- trees
def test_tree_buffers():
    #        root
    #      /      \
    #    100(0)   101(1)
    #    /   \       \
    # 110(2) 111(3)  112(4)
    #                  |
    #                120(5)
    tree = DraftTree.from_paths([[100, 110], [100, 111], [101, 112, 120]], "test")
    assert tree.token_ids.tolist() == [100, 110, 111, 101, 112, 120]
    assert tree.parents.tolist() == [-1, 0, 0, -1, 3, 4]
    assert tree.depths.tolist() == [0, 1, 1, 0, 1, 2]
    assert tree.ancestor_or_self[5].tolist() == [False, False, False, True, True, True]
    assert tree.ancestor_or_self[2].tolist() == [True, False, True, False, False, False]  # not its sibling
    assert tree.token_paths() == [[100, 110], [100, 111], [101, 112, 120]]
    assert tree.truncate_depth(2).token_paths() == [[100, 110], [100, 111], [101, 112]]
    merged = tree.merge(DraftTree.from_paths([[101, 112, 121], [102]], "other"))
    assert merged.num_nodes == 8 and merged.sources[-2:] == ["other", "other"]
    assert sorted(merged.token_paths()) == [[100, 110], [100, 111], [101, 112, 120], [101, 112, 121], [102]]
    with pytest.raises(ValueError, match="parents"):
        DraftTree(torch.tensor([5, 6]), torch.tensor([1, -1]))


def targets(root: int, per_node: list[int]) -> torch.Tensor:
    """target_ids [1 + N]: the greedy token after the root, then after each node."""
    return torch.tensor([root, *per_node])


def test_accepts_the_passing_branch_not_the_leftmost():
    tree = DraftTree.from_paths([[100, 110], [100, 111], [101, 112, 120]], "test")
    # greedy: 101 after the root, 112 after 101, 120 after 112, 130 after 120 -> the right branch, all of it
    path = accept_tree(tree, targets(101, [0, 0, 0, 112, 120, 130]), ExactMatch(), None)
    assert path.nodes == [3, 4, 5] and path.bonus_id == 130
    # greedy 100 then 111: the middle leaf (depth 2) is accepted, bonus is the target's token after it
    path = accept_tree(tree, targets(100, [111, 0, 77, 0, 0, 0]), ExactMatch(), None)
    assert path.nodes == [0, 2] and path.bonus_id == 77
    # nothing passes: no node, the bonus is the root's greedy token
    path = accept_tree(tree, targets(99, [0] * 6), ExactMatch(), None)
    assert path.nodes == [] and path.bonus_id == 99


def test_relaxed_ties_go_to_the_closest_path(layout):
    tree = DraftTree.from_paths([[100, 150], [103, 151], [101, 149]], "test")
    rule = RelaxedBinMatch(layout, bin_tolerance=3)
    # root greedy 102: all three first tokens pass (distances 2, 1, 1)
    path = accept_tree(tree, targets(102, [150, 0, 150, 0, 149, 0]), rule, layout)
    # all paths are 2 long; totals 2+0, 1+1, 1+0 -> the last one is closest to greedy
    assert path.nodes == [4, 5] and path.distances == [1, 0]
    # totals 2+0, 1+1, 1+1: a tie, the first proposed wins
    path = accept_tree(tree, targets(102, [150, 0, 150, 0, 150, 0]), rule, layout)
    assert path.nodes == [0, 1] and path.distances == [2, 0]
    # a longer passing path beats a closer, shorter one
    deeper = DraftTree.from_paths([[102], [99, 160, 170]], "test")
    path = accept_tree(deeper, targets(102, [0, 160, 170, 5]), rule, layout)
    assert path.nodes == [1, 2, 3] and path.distances == [3, 0, 0] and path.bonus_id == 5


def test_action_dimension_follows_the_path(layout):
    rule = RelaxedBinMatch(layout, bin_tolerance=[0, 5, 0, 0, 0, 0, 0])  # only dimension 1 is relaxed
    tree = DraftTree.from_paths([[100, 200]], "test")
    # 5 action tokens came before: node 0 is dimension 5 (strict), node 1 dimension 6 (strict)
    assert accept_tree(tree, targets(100, [203, 1]), rule, layout, 5).nodes == [0]
    # 7 came before: node 0 is dimension 0 (strict, exact here), node 1 dimension 1 (within 5)
    assert accept_tree(tree, targets(100, [203, 1]), rule, layout, 7).nodes == [0, 1]


def test_a_chain_is_known_as_one_so_that_it_verifies_under_the_causal_mask():
    assert DraftTree.from_paths([[5, 6, 7]], "x").is_chain
    assert not DraftTree.from_paths([[5, 6], [5, 7]], "x").is_chain  # siblings: a real tree mask is needed
    assert DraftTree.empty().is_chain


# ------------------------------------------------------------------------------- rules beyond a global r
def test_per_chunk_step_tolerance_the_last_row_serves_later_actions(layout):
    rule = RelaxedBinMatch(layout, bin_tolerance=[[1] * 6 + [0], [4] * 6 + [0]])  # the first action tight
    draft, target = torch.tensor([[100, 100, 100, 100]]), torch.tensor([[103, 103, 103, 101]])
    dims, steps = torch.tensor([[0, 0, 0, 6]]), torch.tensor([[0, 1, 5, 3]])  # step 5: the last row
    assert rule(draft, target, dims, steps).tolist() == [[False, True, True, False]]  # the gripper strict throughout
    assert not rule.is_lossless and "[[1, 1, 1, 1, 1, 1, 0], 4" not in repr(rule)


def test_confidence_gate_relaxes_only_where_the_target_is_unsure(layout):
    rule = make_acceptance_rule(3, layout, confidence_gate=0.6)
    assert isinstance(rule, ConfidenceGate) and rule.needs_probabilities and not rule.is_lossless
    draft, target = torch.tensor([[100, 100, 100, 100]]), torch.tensor([[102, 102, 100, 110]])
    top1 = torch.tensor([[0.3, 0.9, 0.99, 0.1]])  # unsure, sure, sure (but exact), unsure (but too far)
    assert rule(draft, target, torch.zeros_like(draft), None, top1).tolist() == [[True, False, True, False]]
    with pytest.raises(ValueError, match="top-1 probabilities"):
        rule(draft, target)


def test_relaxed_budget_counts_along_the_path_within_each_action(action_tokenizer):
    layout = ActionLayout(action_tokenizer, 2)  # 2 tokens per action: a chain of 4 drafts spans 2 actions
    rule = make_acceptance_rule(5, layout, max_relaxed_per_action=1)
    assert isinstance(rule, RelaxedBudget) and rule.max_relaxed_per_action == 1
    chain = DraftTree.from_paths([[100, 101, 102, 103]], "test")
    # every draft 1 bin off: one relaxed token per action -> drafts 0 (action 0) and 2 (action 1), each followed by a
    # rejection: the path stops at the first over-budget node
    path = accept_tree(chain, targets(101, [102, 103, 104, 105]), rule, layout)
    assert path.nodes == [0] and path.bonus_id == 102
    # exact drafts do not count: relaxed, exact | relaxed, exact -> all four
    path = accept_tree(chain, targets(101, [101, 103, 103, 7]), rule, layout)
    assert path.nodes == [0, 1, 2, 3] and path.distances == [1, 0, 1, 0]
    # a relaxed token emitted by an earlier round of the same action counts: the first draft is then over budget
    path = accept_tree(chain, targets(101, [101, 103, 103, 7]), rule, layout, 1, relaxed_in_action=1)
    assert path.nodes == [] and path.bonus_id == 101
    # the earlier count belongs to the root's action only: the next action starts from 0 (node 2 relaxed, accepted)
    path = accept_tree(chain, targets(100, [101, 103, 103, 7]), rule, layout, 1, relaxed_in_action=1)
    assert path.nodes == [0, 1, 2, 3] and path.distances == [0, 0, 1, 0]


def test_a_tree_keeps_the_branch_within_budget(action_tokenizer):
    layout = ActionLayout(action_tokenizer, 4)
    rule = make_acceptance_rule(5, layout, max_relaxed_per_action=1)
    # two branches: relaxed twice (over budget at its second node) or relaxed once then exact
    tree = DraftTree.from_paths([[100, 110, 120], [101, 111, 121]], "test")
    path = accept_tree(tree, targets(101, [112, 121, 7, 111, 121, 8]), rule, layout)
    assert path.nodes == [3, 4, 5] and path.bonus_id == 8


def test_r0_is_exact_whatever_the_gate_and_budget(layout):
    for gate, budget in ((None, None), (0.5, None), (None, 2), (0.9, 0)):
        assert isinstance(make_acceptance_rule(0, layout, gate, budget), ExactMatch)
        assert isinstance(make_acceptance_rule([[0] * 7, [0] * 7], layout, gate, budget), ExactMatch)
    assert isinstance(make_acceptance_rule(4, layout, None, 0), ExactMatch)  # a budget of 0: nothing relaxed


@pytest.mark.parametrize(
    "kwargs, error, match",
    [(dict(confidence_gate=0), ValueError, r"confidence_gate=0: .* in \(0, 1\]"),
     (dict(confidence_gate=1.5), ValueError, r"confidence_gate=1.5"),
     (dict(confidence_gate="high"), TypeError, r"'high'"),
     (dict(max_relaxed_per_action=-1), ValueError, r"max_relaxed_per_action=-1: .* >= 0"),
     (dict(max_relaxed_per_action=1.5), TypeError, r"1.5"),
     (dict(bin_tolerance=[[1] * 7, 2]), TypeError, "mixes numbers and lists"),
     (dict(bin_tolerance=[[1] * 7, [1] * 3]), ValueError, "7 dimensions"),
     (dict(bin_tolerance=[]), ValueError, "empty")],
)  # fmt: skip
def test_bad_rule_settings_are_named(layout, kwargs, error, match):
    kwargs = {"bin_tolerance": 2, **kwargs}
    with pytest.raises(error, match=match):
        make_acceptance_rule(kwargs.pop("bin_tolerance"), layout, **kwargs)
    if "bin_tolerance" not in kwargs and kwargs:  # the generate arguments are checked before any forward
        with pytest.raises(error, match=match):
            SpeculationConfig(**kwargs)
