"""The loop's batched steps against one-node-at-a-time references: the target's greedy ids under logits processors,
the accepted path of every row's tree, and where each row's stopping criteria fire (no model needed).

Rows have different sequence lengths and trees of different shapes, as in a batch after ragged acceptances."""

import random

import pytest
import torch
from transformers import (
    LogitsProcessorList,
    MinLengthLogitsProcessor,
    MinNewTokensLengthLogitsProcessor,
    NoRepeatNGramLogitsProcessor,
    RepetitionPenaltyLogitsProcessor,
    StoppingCriteria,
    StoppingCriteriaList,
)
from transformers.generation.stopping_criteria import EosTokenCriteria, MaxLengthCriteria

from hf_specvla import ActionLayout, DraftTree, ExactMatch, RelaxedBinMatch
from hf_specvla.speculative import SpeculationStats, accept_trees
from hf_specvla.speculative.drafter import PathSession
from hf_specvla.speculative.loop import RowState, emit_tokens
from hf_specvla.speculative.tree import TreeBatch
from hf_specvla.speculative.verify import eos_hidden_below, target_greedy_ids

VOCAB = 320  # action ids 64..319 (the conftest action tokenizer), text ids below


def random_tree(generator: random.Random, max_nodes: int, low: int = 64) -> DraftTree:
    """A trie of random paths (depth 1..4) over a few tokens, so that siblings and shared prefixes occur."""
    paths = [[generator.randrange(low, low + 4) for _ in range(generator.randint(1, 4))] for _ in range(max_nodes)]
    tree = DraftTree.from_paths(paths, "test")
    return tree.select(torch.arange(tree.num_nodes) < max_nodes) if tree.num_nodes > max_nodes else tree


def random_batch(seed: int, batch_size: int = 5):
    generator = random.Random(seed)
    trees = TreeBatch([random_tree(generator, generator.choice([0, 1, 3, 9])) for _ in range(batch_size)])
    sequences = [torch.randint(60, 70, (1, generator.randint(4, 9)), generator=torch.Generator().manual_seed(seed + b))
                 for b in range(batch_size)]  # fmt: skip
    return trees, sequences


def min_lengths():
    """What ``min_length`` / ``min_new_tokens`` add: hide EOS (66, an id the random trees draft) below a length that
    falls inside the trees' depths."""
    return [
        MinLengthLogitsProcessor(8, eos_token_id=66),
        MinNewTokensLengthLogitsProcessor(prompt_length_to_skip=5, min_new_tokens=4, eos_token_id=[66, 67]),
    ]


PROCESSOR_LISTS = {
    # reads the tokens of the whole prefix, then its length
    "general, then lengths": lambda: [
        RepetitionPenaltyLogitsProcessor(1.7),
        NoRepeatNGramLogitsProcessor(2),
        *min_lengths(),
    ],
    "lengths only (applied as one mask)": min_lengths,
    "lengths (one mask), then general": lambda: [
        *min_lengths(),
        RepetitionPenaltyLogitsProcessor(1.7),
        NoRepeatNGramLogitsProcessor(2),
    ],
    "mask, general, mask": lambda: [min_lengths()[0], RepetitionPenaltyLogitsProcessor(0.6), min_lengths()[1]],
}


@pytest.mark.parametrize("processors", PROCESSOR_LISTS.values(), ids=PROCESSOR_LISTS.keys())
@pytest.mark.parametrize("seed", range(6))
def test_batched_target_ids_equal_each_node_processed_alone(seed, processors):
    trees, sequences = random_batch(seed)
    logits = torch.randn(len(sequences), 1 + trees.num_nodes, VOCAB, generator=torch.Generator().manual_seed(seed))
    processors = LogitsProcessorList(processors())
    target_ids, scores = target_greedy_ids(processors, sequences, trees, logits)
    assert target_ids.shape == logits.shape[:2]
    masked = 0
    for b, (tree, sequence) in enumerate(zip(trees.trees, sequences)):
        for column in range(1 + tree.num_nodes):
            path = [] if column == 0 else tree.token_ids[tree.path_to(column - 1)].tolist()
            prefix = torch.cat([sequence, torch.tensor([path], dtype=torch.long)], dim=1)
            expected = processors(prefix, logits[b, column][None])[0]  # transformers' own list, node by node
            torch.testing.assert_close(scores[b, column], expected, rtol=0, atol=0)
            assert int(target_ids[b, column]) == int(expected.argmax())
            masked += bool(torch.isinf(expected[66]))
    assert masked > 0  # the lengths fall inside the trees: some nodes hide EOS, others do not


class HidesEosAndMore(MinLengthLogitsProcessor):
    def __call__(self, input_ids, scores):
        return super().__call__(input_ids, scores) * 2


def test_only_transformers_own_length_processors_become_masks():
    assert eos_hidden_below(MinLengthLogitsProcessor(8, eos_token_id=2)) == 8
    assert eos_hidden_below(MinNewTokensLengthLogitsProcessor(5, 4, eos_token_id=2)) == 9
    assert eos_hidden_below(HidesEosAndMore(8, eos_token_id=2)) is None  # a subclass may do more
    assert eos_hidden_below(RepetitionPenaltyLogitsProcessor(1.5)) is None


def reference_path(tree: DraftTree, target_ids: list[int], rule, layout, prior_actions: int):
    """Brute force: every node whose path passes; the deepest, then smallest summed distance, then first."""
    best = None
    for node in range(tree.num_nodes):
        path = tree.path_to(node)
        distances, ok = [], True
        for depth, n in enumerate(path):
            draft = int(tree.token_ids[n])
            target = target_ids[0 if depth == 0 else path[depth - 1] + 1]
            dim = (prior_actions + depth) % layout.action_dim  # every drafted token here is an action token
            ok &= bool(rule(torch.tensor([[draft]]), torch.tensor([[target]]), torch.tensor([[dim]]))[0, 0])
            distances.append(int(layout.tokenizer.bin_distance(torch.tensor(draft), torch.tensor(target))))
        key = (-len(path), sum(distances), node)
        if ok and (best is None or key < best[0]):
            best = (key, path, distances)
    if best is None:
        return [], target_ids[0], []
    return best[1], target_ids[best[1][-1] + 1], best[2]


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("bin_tolerance", [0, 1, 2])
def test_batched_acceptance_equals_brute_force_per_row(seed, bin_tolerance, action_tokenizer):
    layout = ActionLayout(action_tokenizer, 3)
    rule = ExactMatch() if bin_tolerance == 0 else RelaxedBinMatch(layout, bin_tolerance)
    trees, _ = random_batch(seed)
    generator = torch.Generator().manual_seed(seed)
    target_ids = torch.randint(64, 68, (len(trees.trees), 1 + trees.num_nodes), generator=generator)
    prior_actions = [seed % 3, 0, 1, 2, 5]
    paths = accept_trees(trees, target_ids, rule, layout, prior_actions)
    for b, (tree, path) in enumerate(zip(trees.trees, paths)):
        nodes, bonus, distances = reference_path(tree, target_ids[b].tolist(), rule, layout, prior_actions[b])
        assert (path.nodes, path.bonus_id, path.distances) == (nodes, int(bonus), distances)
    if bin_tolerance == 0:
        assert all(d == 0 for p in paths for d in p.distances)


class StopAfterPair(StoppingCriteria):
    """Reads content: stops a row once its last two tokens are (65, 66)."""

    def __call__(self, input_ids, scores, **kwargs):
        return (input_ids[:, -2] == 65) & (input_ids[:, -1] == 66)


@pytest.mark.parametrize("seed", range(6))
def test_rows_stop_where_per_token_stopping_stops(seed):
    generator = random.Random(seed)
    criteria = StoppingCriteriaList([MaxLengthCriteria(14), EosTokenCriteria(67), StopAfterPair()])
    rows, emitted = [], []
    for b in range(6):
        sequence = torch.tensor([[generator.randrange(60, 70) for _ in range(generator.randint(5, 10))]])
        rows.append(RowState(b, sequence, PathSession([], "none", torch.device("cpu")), SpeculationStats()))
        emitted.append([generator.randrange(64, 68) for _ in range(generator.randint(1, 5))])
    expected = []
    for row, tokens in zip(rows, emitted):  # the reference: ask the criteria after every token, as greedy does
        sequence, kept, finished = row.sequence, 0, False
        for token in tokens:
            sequence = torch.cat([sequence, torch.tensor([[token]])], dim=1)
            kept += 1
            if bool(criteria(sequence, None).any()):
                finished = True
                break
        expected.append((sequence.tolist(), kept, finished))
    num_kept = emit_tokens(rows, emitted, criteria)
    assert [(r.sequence.tolist(), k, r.finished) for r, k in zip(rows, num_kept)] == expected
    assert [r.num_generated for r in rows] == num_kept


@pytest.mark.parametrize("seed", range(6))
def test_a_batch_of_trees_is_its_rows_padded_with_filler_whether_or_not_the_structure_was_met_before(seed):
    """TreeBatch makes a structure's tensors once (by N and every row's parents) and reuses them: every batch, made
    fresh or from that store, is each row's own tree (tokens, parents, depths, tree mask) followed by filler nodes
    (token 0, parent -1, depth 0, attending to themselves only)."""
    generator = random.Random(seed)
    trees = [random_tree(generator, generator.choice([0, 1, 3, 9])) for _ in range(4)]
    width = max(t.num_nodes for t in trees) + generator.choice([0, 2])
    for _ in range(2):  # first made, then from the store
        batch = TreeBatch([DraftTree.from_lists(t.host_tokens, t.parent_list, t.sources) for t in trees], width)
        for b, tree in enumerate(trees):
            k = tree.num_nodes
            assert batch.token_ids[b, :k].tolist() == tree.host_tokens and not batch.token_ids[b, k:].any()
            assert batch.parents[b, :k].tolist() == tree.parent_list and (batch.parents[b, k:] == -1).all()
            assert batch.depths[b, :k].tolist() == tree.depth_list and not batch.depths[b, k:].any()
            assert torch.equal(batch.ancestor_or_self[b, :k, :k], tree.ancestor_or_self)
            filler = batch.ancestor_or_self[b, k:]
            assert (
                torch.equal(filler, torch.eye(width, dtype=torch.bool)[k:])
                and not batch.ancestor_or_self[b, :k, k:].any()
            )
            assert batch.is_real[b].tolist() == [i < k for i in range(width)]
