"""Head v3: a block of drafts per head forward (mask queries), and the whole action drafted before the prefill.

Invariants: at r=0 a v3 head's block chain, block tree, drafts before the prefill, and their compositions with the
action prior and Jacobi decode exactly greedy's tokens (one row, a left-padded batch with a previous action per row,
dynamic, static and compiled caches; sampling keeps the target's distribution); a block round costs one head forward
whatever its depth; drafts known before the prefill are verified inside it (right ones: one target forward); the
block's first draft is the chain's; the training features are the drafting features (after and before the prefill);
v3 heads save and load; bad settings are refused naming the value and what is valid.
"""

from __future__ import annotations

import pytest
import torch
from transformers import LlamaForCausalLM
from transformers.cache_utils import DynamicCache

from hf_specvla import ActionTokenizer, ComposedDrafter, DraftHead, DraftHeadDrafter, DraftTreeConfig, JacobiDrafter
from hf_specvla.speculative import with_action_prior, with_action_priors
from hf_specvla.speculative.configuration_draft_head import DraftHeadConfig
from hf_specvla.speculative.drafters import draft_head as draft_head_module
from hf_specvla.speculative.drafters.draft_head import embed_tokens
from hf_specvla.speculative.drafters.head_block import block_round, product_tree
from hf_specvla.speculative.masks import causal_mask
from hf_specvla.training.draft_head import (
    DraftTrainingConfig,
    accuracy_by_position,
    block_entries,
    block_features,
    build_distillation_dataset,
    distillation_loss,
    head_settings,
    train_draft_head,
)

from ..conftest import VOCAB, tiny_llama_config
from .test_draft_head_v2 import NEW_TOKENS, Recorder, _action, _compile_config, _greedy, _ids, distilled_batch
from .test_speculative_sampling import NEW_TOKENS as SAMPLING_TOKENS
from .test_speculative_sampling import PROMPT, ROWS, SAMPLES, TOP_P, chi_square_p_value, exact_distribution
from .test_speculative_sampling import peaked as sampling_target  # noqa: F401 (a fixture, by this name)

ACTION_DIM = 4
TREE = DraftTreeConfig(top_k=3, depth=7, total_tokens=14)


@pytest.fixture(scope="module")
def target():
    from hf_specvla import enable_speculation

    torch.manual_seed(0)
    return enable_speculation(LlamaForCausalLM(tiny_llama_config(num_hidden_layers=3)).eval())


def _v3_head(target, **overrides) -> DraftHead:
    """A random v3 head whose every input matters (its layers' fuse, previous-action rows and mask inputs
    randomised)."""
    torch.manual_seed(3)
    settings = dict(feature_layers=[1, 2, -1], previous_action_input=True, draft_mode="block", prefill_drafts=True,
                    draft_action_tokens_only=False, num_draft_tokens=7)  # fmt: skip
    head = DraftHead.from_target(target, ActionTokenizer(VOCAB), action_dim=ACTION_DIM, **{**settings, **overrides})
    with torch.no_grad():
        head.feature_fuse.weight.normal_(0, 0.1)
        head.previous_embedding.weight.normal_(0, 1.0)
    return head.eval()


@pytest.fixture(scope="module")
def head_v3(target) -> DraftHead:
    return _v3_head(target)


# ----------------------------------------------------------------------------- lossless
def _drafters(head: DraftHead) -> dict:
    """The v3 head's drafters, alone and composed: what every lossless check runs."""
    layout = head.config.action_layout()
    previous = [_action(10, 200, 3, 255), _action(12, 180, 3, 0)]
    chain, tree = DraftHeadDrafter(head), DraftHeadDrafter(head, tree=TREE)
    jacobi_then_tree = ComposedDrafter([JacobiDrafter(fill=False), tree])
    return {
        "chain": chain,
        "tree": tree,
        "chain, previous action": chain.with_previous_action(previous[-1]),
        "tree, previous action": tree.with_previous_action(previous[-1]),
        "prior + tree": with_action_prior(tree, previous, layout, chunk_length=2),
        "prior + jacobi + tree": with_action_prior(jacobi_then_tree, previous, layout, chunk_length=2),
    }


@pytest.mark.parametrize("cache", ["dynamic", "static", "compiled"])
@pytest.mark.parametrize("modes", [("block", True), ("block", False), ("chain", True)])
def test_head_v3_decodes_exactly_as_greedy(target, cache, modes):
    """Block chain and tree, drafts before the prefill, with and without a previous action, after the action prior,
    beside Jacobi; each mode alone too (a block head without prefill drafts, a chain head with them)."""
    input_ids = _ids(1)
    expected = _greedy(target, input_ids)
    settings = {"dynamic": {}, "static": {"cache_implementation": "static"},
                "compiled": {"cache_implementation": "static", "compile_config": _compile_config()}}[cache]  # fmt: skip
    for name, drafter in _drafters(_v3_head(target, draft_mode=modes[0], prefill_drafts=modes[1])).items():
        assert torch.equal(_greedy(target, input_ids, assistant_model=drafter, **settings), expected), name


def test_head_v3_in_a_left_padded_batch_with_a_previous_action_per_row(target, head_v3):
    padding = torch.tensor([3, 0, 1])  # row b's prompt starts after padding[b] pad tokens
    mask = (torch.arange(10)[None] >= padding[:, None]).long()  # [3, 10]
    input_ids = _ids(2, batch=3).masked_fill(mask == 0, 0)
    expected = _greedy(target, input_ids, attention_mask=mask)
    histories = [[_action(1, 2, 3, 4)], [], [_action(9, 9, 9, 9), _action(100, 50, 25, 0)]]
    for drafter in (DraftHeadDrafter(head_v3), DraftHeadDrafter(head_v3, tree=TREE)):
        composed = with_action_priors(ComposedDrafter([JacobiDrafter(fill=False), drafter]), histories,
                                      head_v3.config.action_layout(), chunk_length=2)  # fmt: skip
        assert torch.equal(_greedy(target, input_ids, attention_mask=mask, assistant_model=composed), expected)


def test_a_padded_row_drafts_what_it_drafts_alone(target, head_v3):
    """Prompt padding is masked in the head's forwards: the row's drafts do not depend on it."""
    input_ids = _ids(9, length=7)
    padded = torch.cat([torch.zeros(1, 3, dtype=torch.long), input_ids], dim=1)
    mask = torch.cat([torch.zeros(1, 3, dtype=torch.long), torch.ones_like(input_ids)], dim=1)
    alone, beside = Recorder(DraftHeadDrafter(head_v3)), Recorder(DraftHeadDrafter(head_v3))
    _greedy(target, input_ids, assistant_model=alone)
    _greedy(target, padded, attention_mask=mask, assistant_model=beside)
    assert alone.trees == beside.trees and alone.trees[0]  # the prefill's drafts too


# ----------------------------------------------------------------------------- cost and the prefill
def test_a_block_round_costs_one_head_forward(target, head_v3):
    """One head forward per round that drafts (the prefill's included), where a chain costs one per level."""
    input_ids = _ids(4)
    rounds = {}
    for name, head in (("block", head_v3), ("chain", _v3_head(target, draft_mode="chain", prefill_drafts=False))):
        recorder = Recorder(DraftHeadDrafter(head))
        out = _greedy(target, input_ids, assistant_model=recorder, return_dict_in_generate=True)
        drafting = sum(1 for tree in recorder.trees if tree)
        rounds[name] = (out.speculation.num_draft_forwards, drafting, [len(tree) for tree in recorder.trees])
    forwards, drafting, sizes = rounds["block"]
    assert forwards == drafting and sizes[0] == NEW_TOKENS - 1  # the prefill drafts the whole action but its bonus
    chain_forwards, _, chain_sizes = rounds["chain"]
    assert chain_sizes[0] == 0 and chain_forwards > sum(1 for size in chain_sizes if size)  # levels cost forwards


def test_right_drafts_before_the_prefill_cost_one_target_forward(target, head_v3, monkeypatch):
    """The pre-prefill block's drafts are verified inside the prefill: when they are the target's tokens, the action
    costs one target forward (the drafter's table replaced by greedy's tokens)."""
    input_ids = _ids(5)
    expected = _greedy(target, input_ids)
    greedy = expected[0, input_ids.shape[1] :]

    def right_block(head, embed, scorer, token_ids, hidden, positions, num_new, cache, committed, num_queries, top_k,
                    **kwargs):  # fmt: skip
        right = greedy[: num_queries + 1]
        return torch.stack([right - rank for rank in range(top_k)], dim=1)  # [1 + M, k]: greedy first

    monkeypatch.setattr(draft_head_module, "block_round", right_block)
    for tree in (None, TREE):
        out = _greedy(target, input_ids, assistant_model=DraftHeadDrafter(head_v3, tree=tree),
                      return_dict_in_generate=True)  # fmt: skip
        assert torch.equal(out.sequences, expected) and out.speculation.num_target_forwards == 1


def test_the_blocks_first_draft_is_the_chains(target, head_v3):
    """Depth 0 of a block comes from the last committed pair's feature, as a chain's first draft does."""
    chain_head = _v3_head(target, draft_mode="chain", prefill_drafts=False)
    chain_head.load_state_dict(head_v3.state_dict(), strict=False)  # the same layer; a chain has no mask inputs
    input_ids = _ids(6)
    block, chain = Recorder(DraftHeadDrafter(head_v3)), Recorder(DraftHeadDrafter(chain_head))
    _greedy(target, input_ids, assistant_model=block)
    _greedy(target, input_ids, assistant_model=chain)
    assert block.trees[1][0] == chain.trees[1][0]  # the first round after the prefill


def test_product_tree_holds_the_backbone_then_alternatives_continued():
    assert product_tree(4, 1, 10) == ((0, 1, 2, 3), (-1, 0, 1, 2))
    picks, parents = product_tree(3, 2, 7)
    # backbone 0 2 4; rank-1 alternative at depth 0 continued by the backbone's depths 1, 2; then at depth 1
    assert picks == (0, 2, 4, 1, 2, 4, 3) and parents == (-1, 0, 1, -1, 3, 4, 0)
    assert len(product_tree(7, 3, 14)[0]) == 14 and len(product_tree(7, 3, 3)[0]) == 7  # a budget below the depth


# ----------------------------------------------------------------------------- training = drafting
@pytest.fixture(scope="module")
def v3_batch(target, head_v3):
    return distilled_batch(target, head_v3)


@pytest.mark.parametrize("before_prefill", [False, True])
def test_block_training_features_are_the_drafting_features(target, head_v3, v3_batch, before_prefill):
    """Entry j of a training block from root r drafts what the block round drafts from root r (as compiled into one
    training forward: several examples, right padding); before the prefill, from the prompt's pairs without hidden
    states."""
    _, batch = v3_batch
    handles = head_v3.target_handles(target)
    width, steps = head_v3.config.hidden_size, 5
    row, first = 1, int(batch["first_position"][1])
    root = first - 2 if before_prefill else first + 1
    inputs_hidden = None if before_prefill else batch["hidden"][:, :-1, : 3 * width]
    roots = torch.full((batch["input_ids"].shape[0],), root)
    with torch.no_grad():
        features = block_features(head_v3, handles, batch, inputs_hidden, roots, steps - 1)
        features = block_entries(features, roots, steps - 1)  # [B, steps, H]
    scorer = head_v3.scorer(handles.lm_head)
    trained = scorer.token_ids(features[row])
    ids = batch["input_ids"][row : row + 1]
    previous = (head_v3.previous_action_bins(None), torch.tensor(first))  # row 1 has no previous action
    hidden = None if before_prefill else inputs_hidden[row : row + 1, : root + 1]
    with torch.no_grad():
        table = block_round(head_v3, lambda t: embed_tokens(handles, t), scorer, ids[:, 1 : root + 2], hidden,
                            torch.arange(root + 1)[None], root + 1, DynamicCache(), 0, steps - 1, 1,
                            previous=previous)  # fmt: skip
    assert torch.equal(table[:, 0], trained)


def test_training_a_v3_head_reports_both_modes_and_learns(target, head_v3, v3_batch):
    dataset, batch = v3_batch
    head = _v3_head(target).train()
    config = DraftTrainingConfig("unused", unroll_steps=7, feature_noise=0.0)
    handles = head.target_handles(target)
    optimizer = torch.optim.AdamW(head.parameters(), lr=3e-3)
    before = accuracy_by_position(head.eval(), target, dataset)
    head.train()
    history = []
    for _ in range(150):
        losses = distillation_loss(head, handles, batch, config)
        optimizer.zero_grad()
        losses["loss"].backward()
        optimizer.step()
        history.append({name: value.detach() for name, value in losses.items()})
    first, last = history[0], history[-1]
    assert last["step_accuracy"].shape == (7,) and last["prefill_step_accuracy"].shape == (7,)
    # the random target's tokens are scored where they are action tokens: both modes learn them
    assert last["loss"] < 0.5 * first["loss"]
    assert last["token_accuracy"] > first["token_accuracy"] + 0.3
    assert last["prefill_token_accuracy"] > first["prefill_token_accuracy"] + 0.3
    after = accuracy_by_position(head.eval(), target, dataset)
    assert set(after) == {"after_prefill", "before_prefill"} and len(after["before_prefill"]) == 7
    assert sum(after["before_prefill"]) > sum(before["before_prefill"])


# ----------------------------------------------------------------------------- loading and refusals
def test_a_v3_head_saves_loads_and_drafts_the_same(tmp_path, target, head_v3):
    head_v3.save_pretrained(tmp_path)
    loaded = DraftHead.from_pretrained(tmp_path).eval()
    assert loaded.config.draft_mode == "block" and loaded.config.prefill_drafts
    input_ids = _ids(7)
    before, after = Recorder(DraftHeadDrafter(head_v3, tree=TREE)), Recorder(DraftHeadDrafter(loaded, tree=TREE))
    _greedy(target, input_ids, assistant_model=before)
    _greedy(target, input_ids, assistant_model=after)
    assert before.trees == after.trees


@pytest.mark.parametrize(
    "overrides, match",
    [
        ({"draft_mode": "tree"}, r"draft_mode must be one of \('chain', 'block'\).*'tree'"),
        ({"prefill_drafts": "yes"}, r"prefill_drafts must be True or False, got 'yes'"),
    ],
)
def test_bad_v3_settings_are_refused_naming_the_value(overrides, match):
    with pytest.raises(ValueError, match=match):
        DraftHeadConfig(hidden_size=64, intermediate_size=128, num_attention_heads=4, vocab_size=512,
                        action_vocab_size=512, **overrides)  # fmt: skip


def test_a_head_without_mask_queries_refuses_them_and_an_unknown_version_is_named(target):
    head = _v3_head(target, draft_mode="chain", prefill_drafts=False)
    assert head.mask_inputs is None
    with pytest.raises(ValueError, match="no mask queries.*draft_mode='block' or prefill_drafts=True"):
        head.mask_query_inputs(1, 2)
    with pytest.raises(ValueError, match=r"one of \('v1', 'v2', 'v3'\), got 'v4'"):
        head_settings("v4", target)
    assert head_settings("v3", target)["draft_mode"] == "block"


def test_a_v3_head_for_other_weights_is_refused(target, head_v3):
    head_v3.config.target_fingerprint = "0123456789abcdef"
    try:
        with pytest.raises(ValueError, match="fingerprint 0123456789abcdef.*trained for another model"):
            head_v3.check_target(target, "fedcba9876543210")
    finally:
        head_v3.config.target_fingerprint = None


def test_head_v3_causal_mask_helper_matches_the_heads_default():
    """The block's mask without padding or queries is the head's own causal mask (no drift between the two)."""
    from hf_specvla.speculative.drafters.head_block import block_mask

    mask = block_mask(5, 5, 0, 3, None, None, torch.float32, torch.device("cpu"))
    torch.testing.assert_close(mask, causal_mask(5, 3, torch.float32, torch.device("cpu")))


# ----------------------------------------------------------------------------- sampling
@pytest.fixture(scope="module")
def distilled_v3(sampling_target, action_tokenizer, tmp_path_factory):  # noqa: F811 (the imported fixture)
    """A v3 head (block, drafts before the prefill) distilled for a moment from the peaked target of the sampling
    tests, on the prompt and its likely 1- and 2-token prefixes: its drafts are accepted often and rejected often."""
    likely = sorted(exact_distribution(sampling_target, action_tokenizer, 1.0).items(), key=lambda item: -item[1])[:40]
    prefixes = sorted({outcome[:length] for outcome, _ in likely for length in (0, 1, 2)})
    prompts = [{"input_ids": torch.tensor([PROMPT + list(prefix)])} for prefix in prefixes]
    dataset = build_distillation_dataset(sampling_target, prompts, SAMPLING_TOKENS, action_tokenizer, progress=False)
    torch.manual_seed(8)
    head = DraftHead.from_target(sampling_target, action_tokenizer, action_dim=SAMPLING_TOKENS, draft_mode="block",
                                 draft_action_tokens_only=False, prefill_drafts=True,
                                 num_draft_tokens=SAMPLING_TOKENS)  # fmt: skip
    config = DraftTrainingConfig(str(tmp_path_factory.mktemp("distilled_v3")), max_steps=300, learning_rate=1e-3,
                                 feature_noise=0.0, unroll_steps=SAMPLING_TOKENS)  # fmt: skip
    return train_draft_head(head, sampling_target, dataset, config, progress=False)


@pytest.mark.sampling  # ~35 s each (the fast tier samples with candidates and the prior: test_speculative_sampling)
@pytest.mark.parametrize("tree", [None, DraftTreeConfig(top_k=2, depth=3, total_tokens=6)])
def test_speculative_sampling_with_a_v3_head_keeps_the_targets_distribution(
    sampling_target,  # noqa: F811 (the imported fixture)
    action_tokenizer,
    distilled_v3,
    tree,
):
    """Drafts before the prefill and blocks after it, verified by speculative sampling: the first 3 tokens are
    distributed as the target samples them (chi-square), and drafts were accepted (the speculative path ran)."""
    expected = exact_distribution(sampling_target, action_tokenizer, 1.0)
    counts, accepted = {}, 0
    torch.manual_seed(100)
    for _ in range(SAMPLES // ROWS):
        out = sampling_target.generate(
            input_ids=torch.tensor([PROMPT] * ROWS), max_new_tokens=SAMPLING_TOKENS, do_sample=True, temperature=1.0,
            top_p=TOP_P, top_k=0, suppress_tokens=list(range(action_tokenizer.action_token_begin)),
            assistant_model=DraftHeadDrafter(distilled_v3, tree=tree), return_dict_in_generate=True,
        )  # fmt: skip
        for row in out.sequences[:, len(PROMPT) :].tolist():
            counts[tuple(row)] = counts.get(tuple(row), 0) + 1
        accepted += sum(out.speculation.accepted_per_position)
    p_value, cells = chi_square_p_value(counts, expected, SAMPLES)
    assert cells >= 5 and p_value > 0.01, (p_value, cells)
    assert accepted > SAMPLES // 10, accepted


def test_the_model_card_shows_training_and_held_out_accuracy_by_token_side_by_side(head_v3):
    from hf_specvla.training.policy_draft import _head_v3_card

    by_position = {"train": {"after_prefill": [0.9, 0.8], "before_prefill": [0.7, 0.6]},
                   "held_out": {"after_prefill": [0.5, 0.4], "before_prefill": [0.3, 0.2]}}  # fmt: skip
    card = _head_v3_card(head_v3.config, DraftTrainingConfig("unused", unroll_steps=7), by_position)
    assert "| training | 70.0% | 60.0% |\n| held-out | 30.0% | 20.0% |" in card  # before the prefill: tokens 0, 1
    assert "| frames | token 1 | token 2 |" in card and "| held-out | 50.0% | 40.0% |" in card  # after it
    assert "drafts a block of 7 tokens per head forward" in card


def test_a_v3_head_trained_on_blocks_shorter_than_it_drafts_is_refused_before_any_data(target, tmp_path):
    from hf_specvla.training.draft_head import distil_draft_head

    def no_data():
        raise AssertionError("the data was built before the refusal")

    config = DraftTrainingConfig(str(tmp_path), unroll_steps=1)
    with pytest.raises(ValueError, match=r"num_draft_tokens=7.*set unroll_steps=7 .*got unroll_steps=1"):
        distil_draft_head(target, config, {}, no_data, NEW_TOKENS, action_tokenizer=ActionTokenizer(VOCAB),
                          action_dim=ACTION_DIM, num_draft_tokens=7,
                          head_settings=head_settings("v3", target))  # fmt: skip


@pytest.mark.parametrize("tree", [None, TREE])
def test_a_v3_head_reads_the_device_once_a_round(target, head_v3, tree):
    """Blocks and pre-prefill drafts leave their tokens on the device and their tree's structure on the host (it
    depends on the settings only): the drafter adds no read of its own to a round's one."""
    from hf_specvla.speculative.syncs import HostSyncCounter

    drafter = DraftHeadDrafter(head_v3, tree=tree).with_previous_action(_action(1, 2, 3, 4))
    _greedy(target, _ids(8), assistant_model=drafter)
    with HostSyncCounter() as counter:
        out = _greedy(target, _ids(8), assistant_model=drafter, return_dict_in_generate=True)
    in_the_drafter = sum(n for site, n in counter.sites.items() if "drafters/" in site or "draft_head" in site)
    assert in_the_drafter == 0, counter.sites.most_common()
    assert counter.count <= out.speculation.num_target_forwards + 6, counter.sites.most_common()  # + per call
