"""Acceptance rules and tree-path choice on hand-built token ids (action ids are 64..319, text ids below 64)."""

import numpy as np
import pytest
import torch

from hf_specvla import (
    ActionLayout,
    ActionNormalizer,
    ActionUnits,
    ConfidenceGate,
    DraftTree,
    ExactMatch,
    RelaxedBinMatch,
    RelaxedBudget,
    SpeculationConfig,
    StrictTailConfirmed,
    make_acceptance_rule,
)
from hf_specvla.speculative import accept_tree
from hf_specvla.speculative.acceptance import strict_tails


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


# ----------------------------------------------------------------------------- rules that read the action's units
@pytest.fixture(scope="module")
def units_layout(action_tokenizer):
    """7-dim actions whose zero-motion bin is 127 and whose bins are 0.01 units apart (0.02 for the last)."""
    return ActionLayout(action_tokenizer, 7, ActionUnits((127,) * 7, (0.01,) * 6 + (0.02,)))


def test_units_from_the_normaliser(action_tokenizer):
    """The zero-motion bin decodes to the action nearest 0; a bin is (q99 - q01) / (n_bins - 1) units wide on a
    normalised dimension and 2 / (n_bins - 1) on a pass-through one."""
    normalizer = ActionNormalizer([-0.02, 0.0, -1.0], [0.06, 0.5, 1.0], mask=[True, True, False])
    units = ActionUnits.from_normalizer(action_tokenizer, normalizer, 3)
    spacing = 2 / (action_tokenizer.n_bins - 1)
    assert units.bin_widths == pytest.approx((0.08 / 2 * spacing, 0.5 / 2 * spacing, spacing))
    for d, zero_bin in enumerate(units.zero_bins):
        ids = action_tokenizer.vocab_size - 1 - torch.arange(action_tokenizer.n_bins - 1)  # every decodable bin
        actions = normalizer.unnormalize(np.stack([action_tokenizer.decode(ids.numpy())] * 3, axis=1))[:, d]
        assert abs(actions[zero_bin]) == pytest.approx(np.abs(actions).min())
    assert ActionUnits.from_normalizer(action_tokenizer, None, 2).zero_bins == (127, 127)
    with pytest.raises(ValueError, match="3 dimensions, an action 4"):
        ActionUnits.from_normalizer(action_tokenizer, normalizer, 4)
    with pytest.raises(ValueError, match="units describes 3 dimensions, but an action has 7"):
        ActionLayout(action_tokenizer, 7, units)


def test_motion_scaled_tolerance_table(units_layout, action_tokenizer):
    """max(r, floor(rho * |t - zero|)), capped by floor(max_deviation / width), per (dimension, target bin)."""
    rule = RelaxedBinMatch(units_layout, [1] * 6 + [0], motion_scale=[0.1] * 6 + [0], max_deviation=[0.05] * 7)
    table = rule.tolerance_by_bin[0]  # [D, bins]
    assert table[0, 127] == 1 and table[0, 127 + 29] == 2 and table[0, 127 + 30] == 3 and table[0, 0] == 5  # capped
    assert table[6].max() == 0 and rule.strict_dims == (False,) * 6 + (True,)
    bins = torch.arange(action_tokenizer.n_bins)
    expected = torch.clamp(torch.maximum(torch.ones_like(bins), (0.1 * (bins - 127).abs()).floor().long()), max=5)
    assert torch.equal(table[0], expected)
    target = action_tokenizer.vocab_size - 1 - torch.tensor([[127, 187, 187, 20]])  # bins 127, 187 (60 away), 20
    draft = target + torch.tensor([[2, 5, 6, -5]])  # r=1 near zero; 6 bins at 60 away, capped at 5
    dims = torch.tensor([[0, 1, 2, 3]])
    assert rule(draft, target, dims).tolist() == [[False, True, False, True]]


def test_strict_tails():
    assert strict_tails((False, False, False, True)) == (3, 3, 3, -1)
    assert strict_tails((False, True, False, True, False)) == (3, 3, 3, -1, -1)
    assert strict_tails((False, False)) == (-1, -1)


def test_a_relaxed_token_needs_its_strict_tail_on_the_path(action_tokenizer):
    """Chain x y z g x y z g with x relaxed: kept only with g confirmed; a chain stopping before g ends before x."""
    layout = ActionLayout(action_tokenizer, 4)
    rule = make_acceptance_rule([3, 3, 3, 0], layout, confirm_strict_tail=True)
    assert isinstance(rule, StrictTailConfirmed) and rule.strict_tail == (3, 3, 3, -1)
    chain = DraftTree.from_paths([[201, 150, 160, 100, 210, 151, 161, 101]], "test")
    greedy = [200, 150, 160, 100, 210, 151, 161, 101, 90]  # x drafted 1 bin off, the rest right
    path = accept_tree(chain, torch.tensor(greedy), rule, layout)
    assert path.nodes == list(range(8)) and path.distances[0] == 1  # the gripper confirmed: all kept
    wrong_gripper = [200, 150, 160, 102, 210, 151, 161, 101, 90]  # the target's gripper after the relaxed x differs
    path = accept_tree(chain, torch.tensor(wrong_gripper), rule, layout)
    assert path.nodes == [] and path.bonus_id == 200  # back to before x: the target's own x
    relaxed_y = [200 + 1, 152, 160, 100, 210, 151, 161, 101, 90]  # x exact, y relaxed, gripper confirmed
    assert accept_tree(chain, torch.tensor(relaxed_y), rule, layout).nodes == list(range(8))
    short = DraftTree.from_paths([[201, 150]], "test")  # the gripper not drafted: nothing confirms it
    assert accept_tree(short, torch.tensor([200, 150, 160]), rule, layout).nodes == []
    second = [201, 150, 160, 100, 211, 151, 161, 99, 90]  # action 1's x relaxed, its gripper not confirmed
    assert accept_tree(chain, torch.tensor(second), rule, layout).nodes == [0, 1, 2, 3]
    plain = make_acceptance_rule([3, 3, 3, 0], layout)
    assert accept_tree(chain, torch.tensor(wrong_gripper), plain, layout).nodes == [0, 1, 2]


def test_random_trees_keep_every_rules_bound(units_layout, action_tokenizer):
    """On random trees and random greedy tokens: every accepted token is within its tolerance (motion-scaled, capped
    in units), and with confirm_strict_tail no accepted path ends between a relaxed token and its strict tail."""
    generator = torch.Generator().manual_seed(5)
    rule = make_acceptance_rule([2] * 6 + [0], units_layout, motion_scale=[0.2] * 6 + [0],
                                max_deviation=[0.06] * 6 + [0], confirm_strict_tail=True)  # fmt: skip
    kept = 0
    for _ in range(200):
        n = int(torch.randint(1, 12, (1,), generator=generator))
        parents = [-1] + [int(torch.randint(-1, i, (1,), generator=generator)) for i in range(1, n)]
        depth = [0] * n
        for i, p in enumerate(parents):
            depth[i] = 0 if p < 0 else depth[p] + 1
        targets = torch.randint(64, 320, (1 + n,), generator=generator)
        tokens = (targets[torch.tensor(parents) + 1] + torch.randint(-4, 5, (n,), generator=generator)).clamp(64, 319)
        prior = int(torch.randint(0, 7, (1,), generator=generator))
        tree = DraftTree(tokens, torch.tensor(parents))
        path = accept_tree(tree, targets, rule, units_layout, num_prior_action_tokens=prior)
        index = prior
        relaxed_tails = []
        for node, distance in zip(path.nodes, path.distances):
            d = index % 7
            target_bin = action_tokenizer.token_to_bin(int(targets[parents[node] + 1]))
            tolerance = min(max(2 if d < 6 else 0, int(0.2 * abs(target_bin - 127) + 1e-9) if d < 6 else 0), 6)
            assert distance <= tolerance and distance * 0.01 <= 0.06 + 1e-12
            if distance and d < 6:
                relaxed_tails.append(index - d + 6)
            kept += distance > 0
            index += 1
        assert all(index - 1 >= tail for tail in relaxed_tails), (path, prior)
    assert kept > 0


@pytest.mark.parametrize(
    "kwargs, error, match",
    [(dict(motion_scale=-0.1), ValueError, r"motion_scale\[0\] must be a finite number >= 0"),
     (dict(motion_scale=[0.1] * 3), ValueError, "motion_scale has 3 entries"),
     (dict(motion_scale="big"), TypeError, "motion_scale"),
     (dict(max_deviation=float("nan")), ValueError, r"max_deviation\[0\]"),
     (dict(confirm_strict_tail="yes"), TypeError, "confirm_strict_tail must be True or False")],
)  # fmt: skip
def test_bad_unit_rule_settings_are_named(units_layout, kwargs, error, match):
    with pytest.raises(error, match=match):
        make_acceptance_rule(2, units_layout, **kwargs)


def test_rules_that_read_units_need_them(layout):
    with pytest.raises(ValueError, match="the action layout has none: pass .*ActionUnits.from_normalizer"):
        make_acceptance_rule(0, layout, motion_scale=0.1)
    with pytest.raises(ValueError, match="nothing says which tokens are actions"):
        make_acceptance_rule(0, None, motion_scale=0.1)
    assert isinstance(make_acceptance_rule(0, None, motion_scale=0.0), ExactMatch)
    assert isinstance(make_acceptance_rule(4, layout, max_relaxed_per_action=0, confirm_strict_tail=True), ExactMatch)


# ~75 s: random batches at every width; the fast tier's compiled rounds (test_compiled_round) accept in the graph
@pytest.mark.slow
def test_the_acceptance_compiles_into_one_graph_that_finds_the_eager_paths(units_layout, action_tokenizer):
    """The acceptance's device part (``search_paths``) compiled into one graph, dynamic sizes, against eager on random
    batches of random trees, for every kind of rule (exact, relaxed, motion-scaled with a budget and the strict tail,
    gated by the target's confidence): the same paths, distances and bonus tokens at one row and at several, at
    every width, with earlier rounds' relaxed tokens counted (what a fused compiled round would need of it)."""
    from hf_specvla.speculative.acceptance import search_paths
    from hf_specvla.speculative.tree import TreeBatch

    generator = torch.Generator().manual_seed(11)
    rules = {
        "exact": make_acceptance_rule(0, units_layout),
        "relaxed": make_acceptance_rule(3, units_layout),
        "budget and strict tail": make_acceptance_rule([2] * 6 + [0], units_layout, motion_scale=[0.2] * 6 + [0],
                                                       max_relaxed_per_action=1, confirm_strict_tail=True),
        "confidence gate": make_acceptance_rule(2, units_layout, confidence_gate=0.5),
    }  # fmt: skip
    compiled, compared, relaxed = torch.compile(search_paths, dynamic=True, fullgraph=True), 0, 0
    for name, rule in rules.items():
        for batch_size, width in ((1, 2), (1, 8), (3, 4), (2, 16), (1, 16), (4, 2)):
            rows, targets = [], []
            for _ in range(batch_size):
                parents = [-1] + [int(torch.randint(-1, i, (1,), generator=generator)) for i in range(1, width)]
                row_targets = torch.randint(64, 320, (1 + width,), generator=generator)
                noise = torch.randint(-3, 4, (width,), generator=generator) * (torch.rand(width, generator=generator)
                                                                                < 0.5)  # fmt: skip
                tokens = (row_targets[torch.tensor(parents) + 1] + noise).clamp(64, 319)
                rows.append(DraftTree(tokens, torch.tensor(parents)))
                targets.append(row_targets)
            trees, target_ids = TreeBatch(rows), torch.stack(targets)
            prior = torch.randint(0, 14, (batch_size, 1), generator=generator)
            earlier = torch.randint(0, 2, (batch_size, 1), generator=generator)
            probs = torch.rand(batch_size, 1 + width, generator=generator) if rule.needs_probabilities else None
            inputs = (trees.token_ids, trees.ancestor_or_self, trees.parents, trees.depths, trees.is_real, target_ids,
                      prior, earlier, probs, rule, units_layout)  # fmt: skip
            eager, fused = search_paths(*inputs), compiled(*inputs)
            assert torch.equal(eager, fused), (name, batch_size, width)
            compared += 1
            relaxed += int(eager[:, width : 2 * width].bool().any())
    assert compared == 24 and relaxed > 0  # relaxed paths were kept, not only exact ones


def test_exact_acceptance_on_the_host_finds_the_device_searchs_paths():
    """Trees drafted on the host (the previous action, Jacobi guesses) are accepted at r=0 by a walk in Python
    (``exact_paths_on_host``) instead of the device search: on random batches of random trees of different sizes
    (padded in the batch; duplicate siblings, so that equally deep passing paths tie), tokens right with
    probability 0.7, the same nodes, bonus tokens, distances and target tokens as ``search_paths`` read back; and
    ``accept_trees`` takes that walk only where every tree is on the host."""
    from hf_specvla.speculative.acceptance import accept_trees, exact_paths_on_host, read_paths, search_paths
    from hf_specvla.speculative.tree import TreeBatch

    generator = torch.Generator().manual_seed(5)
    compared, accepted, ties = 0, 0, 0
    for trial in range(200):
        batch_size = 1 + trial % 4
        rows, targets = [], []
        for _ in range(batch_size):
            width = int(torch.randint(1, 12, (1,), generator=generator))
            parents = [-1] + [int(torch.randint(-1, i, (1,), generator=generator)) for i in range(1, width)]
            row_targets = torch.randint(64, 70, (1 + width,), generator=generator)
            right = torch.rand(width, generator=generator) < 0.7
            tokens = torch.where(
                right, row_targets[torch.tensor(parents) + 1], torch.randint(64, 70, (width,), generator=generator)
            )
            rows.append(DraftTree.from_lists(tokens.tolist(), parents, ["test"] * width))
            targets.append(row_targets)
        trees = TreeBatch(rows)
        target_ids = torch.stack([torch.nn.functional.pad(t, (0, 1 + trees.num_nodes - len(t)), value=64)
                                  for t in targets])  # fmt: skip
        on_host = exact_paths_on_host(trees, target_ids)
        packed = search_paths(trees.token_ids, trees.ancestor_or_self, trees.parents, trees.depths, trees.is_real,
                              target_ids, None, None, None, ExactMatch(), None)  # fmt: skip
        on_device = read_paths(packed.tolist(), trees)
        assert on_host == on_device, trial
        assert accept_trees(trees, target_ids, ExactMatch(), None, [0] * batch_size) == on_device
        compared += batch_size
        accepted += sum(bool(path.nodes) for path in on_host)
        for tree, path, row_targets in zip(rows, on_host, targets):  # another passing path as deep: a tie broken
            passing = _passing_depths(tree, row_targets.tolist())
            ties += sum(depth == len(path.nodes) > 0 for depth in passing) > 1
    assert compared > 400 and accepted > compared // 2 and ties > 0


def _passing_depths(tree, targets: list[int]) -> list[int]:
    """Per node: the length of its path when every token on it is the target's, else 0."""
    depths = []
    for token, parent in zip(tree.token_list, tree.host_parents):
        passes = token == targets[parent + 1] and (parent < 0 or depths[parent] > 0)
        depths.append((1 if parent < 0 else depths[parent] + 1) if passes else 0)
    return depths
