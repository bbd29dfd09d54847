"""Acceptance rules and tree-path choice on hand-built token ids (action ids are 64..319, text ids below 64)."""

import pytest
import torch

from hf_specvla import ActionLayout, DraftTree, ExactMatch, RelaxedBinMatch, make_acceptance_rule
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
