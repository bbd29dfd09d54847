"""Head v2: several target layers (EAGLE-3), the robot's previous action as input, training-time test.

Invariants: at r=0 a v2 head's chain, tree, prior-seeded tree and + Jacobi decode exactly greedy's tokens (one row,
a left-padded batch with a previous action per row, static and compiled caches); the previous action reaches the
drafts (another previous action, other drafts) the same way eagerly and in the compiled round; a head saved before
v2 drafts exactly what it drafted before; training-time test's unrolled features are the features the head computes
when it drafts a chain; bad previous actions and mismatched data are refused with what would be valid.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from transformers import CompileConfig, LlamaForCausalLM
from transformers.cache_utils import DynamicCache

from hf_specvla import ActionTokenizer, ComposedDrafter, DraftHead, DraftHeadDrafter, DraftTreeConfig, JacobiDrafter
from hf_specvla.speculative import Drafter, with_action_prior, with_action_priors
from hf_specvla.speculative.masks import causal_mask, to_additive_mask
from hf_specvla.training.draft_head import (
    DraftTrainingConfig,
    build_distillation_dataset,
    collate_distillation,
    distillation_loss,
    unrolled_features,
)

from ..conftest import VOCAB, tiny_llama_config

ROOT = Path(__file__).resolve().parents[2]
ACTION_DIM = 4
NEW_TOKENS = 8  # a chunk of two 4-token actions, as policy v3 decodes
TREE = DraftTreeConfig(top_k=3, depth=5, total_tokens=12)


class Recorder(Drafter):
    """Wraps a drafter and records the token ids of every tree its sessions propose."""

    def __init__(self, inner: Drafter):
        self.inner, self.trees = inner, []
        self.name, self.action_layout = inner.name, inner.action_layout
        self.needs_hidden_states, self.hidden_state_layers = inner.needs_hidden_states, inner.hidden_state_layers
        self.needs_prompt_embeddings = inner.needs_prompt_embeddings

    def start(self, context):
        session = self.inner.start(context)
        propose = session.propose

        def record(draft_round):
            tree = propose(draft_round)
            self.trees.append(tree.token_ids.tolist())
            return tree

        session.propose = record
        return session


@pytest.fixture(scope="module")
def target():
    torch.manual_seed(0)
    from hf_specvla import enable_speculation

    return enable_speculation(LlamaForCausalLM(tiny_llama_config(num_hidden_layers=3)).eval())


@pytest.fixture(scope="module")
def head_v2(target) -> DraftHead:
    """A random v2 head whose every input matters (its layers' fuse and previous-action rows randomised)."""
    torch.manual_seed(3)
    head = DraftHead.from_target(target, ActionTokenizer(VOCAB), action_dim=ACTION_DIM, feature_layers=[1, 2, -1],
                                 previous_action_input=True, draft_action_tokens_only=False)  # fmt: skip
    with torch.no_grad():
        head.feature_fuse.weight.normal_(0, 0.1)
        head.previous_embedding.weight.normal_(0, 1.0)
    return head.eval()


def _ids(seed: int, length: int = 10, batch: int = 1) -> torch.Tensor:
    return torch.randint(3, VOCAB - 256, (batch, length), generator=torch.Generator().manual_seed(seed))


def _greedy(model, input_ids, **kwargs):
    return model.generate(input_ids, max_new_tokens=NEW_TOKENS, min_new_tokens=NEW_TOKENS, do_sample=False, **kwargs)


def _action(*bins: int) -> list[int]:
    tokenizer = ActionTokenizer(VOCAB)
    return [int(tokenizer.vocab_size - 1 - b) for b in bins]


def _compile_config() -> CompileConfig:
    config = CompileConfig(backend="eager", fullgraph=True, dynamic=False, mode="default")
    config._compile_all_devices = True
    return config


# ----------------------------------------------------------------------------- lossless
@pytest.mark.parametrize("cache", ["dynamic", "static", "compiled"])
def test_head_v2_decodes_exactly_as_greedy(target, head_v2, cache):
    """Chain, tree, the prior's action then the tree, and + Jacobi, with and without a previous action."""
    input_ids = _ids(1)
    expected = _greedy(target, input_ids)
    layout = head_v2.config.action_layout()
    previous = [_action(10, 200, 3, 255), _action(12, 180, 3, 0)]
    chain, tree = DraftHeadDrafter(head_v2), DraftHeadDrafter(head_v2, tree=TREE)
    drafters = [
        chain,
        tree,
        chain.with_previous_action(previous[-1]),
        tree.with_previous_action(previous[-1]),
        with_action_prior(tree, previous, layout, chunk_length=2),
        with_action_prior(ComposedDrafter([JacobiDrafter(fill=False), tree]), previous, layout, chunk_length=2),
    ]
    kwargs = {} if cache == "dynamic" else {"cache_implementation": "static"}
    if cache == "compiled":
        kwargs["compile_config"] = _compile_config()
    for drafter in drafters:
        assert torch.equal(_greedy(target, input_ids, assistant_model=drafter, **kwargs), expected), drafter


def test_head_v2_in_a_left_padded_batch_with_a_previous_action_per_row(target, head_v2):
    input_ids = _ids(2, batch=3)
    mask = torch.ones_like(input_ids)
    mask[0, :3] = 0
    mask[2, :1] = 0
    input_ids = input_ids.masked_fill(mask == 0, 0)
    expected = _greedy(target, input_ids, attention_mask=mask)
    histories = [[_action(1, 2, 3, 4)], [], [_action(9, 9, 9, 9), _action(100, 50, 25, 0)]]
    tree = DraftHeadDrafter(head_v2, tree=TREE)
    drafter = with_action_priors(ComposedDrafter([JacobiDrafter(fill=False), tree]), histories,
                                 head_v2.config.action_layout(), chunk_length=2)  # fmt: skip
    assert torch.equal(_greedy(target, input_ids, attention_mask=mask, assistant_model=drafter), expected)


# ----------------------------------------------------------------------------- the previous action is read
@pytest.mark.parametrize("compiled", [False, True])
def test_the_previous_action_changes_the_drafts_the_same_way_eagerly_and_compiled(target, head_v2, compiled):
    input_ids = _ids(3)
    kwargs = {"cache_implementation": "static", "compile_config": _compile_config()} if compiled else {}
    drafted = {}
    for name, previous in (("none", None), ("a", _action(0, 0, 0, 0)), ("b", _action(255, 128, 64, 255))):
        recorder = Recorder(DraftHeadDrafter(head_v2, tree=TREE).with_previous_action(previous))
        _greedy(target, input_ids, assistant_model=recorder, **kwargs)
        drafted[name] = recorder.trees
    assert drafted["a"] != drafted["b"] and drafted["none"] != drafted["a"]
    if compiled:  # the eager rounds' trees, for the same previous actions
        for name, previous in (("a", _action(0, 0, 0, 0)), ("b", _action(255, 128, 64, 255))):
            recorder = Recorder(DraftHeadDrafter(head_v2, tree=TREE).with_previous_action(previous))
            _greedy(target, input_ids, assistant_model=recorder)
            assert recorder.trees == drafted[name], name


def test_slot_bins_read_the_previous_action_at_the_predicted_dimension(head_v2):
    previous = torch.tensor([10, 20, 30, 40])
    positions = torch.arange(5, 16)[None]  # the first generated token sits at position 8
    bins = head_v2.slot_bins(previous, 8, positions)
    # input p predicts token p + 2, generated token k = p - 6: inputs 5..5 read "none", 6.. read dims 0 1 2 3 0 ...
    none = head_v2.config.n_action_bins
    assert bins.tolist() == [[none, 10, 20, 30, 40, 10, 20, 30, 40, 10, 20]]


def test_a_bad_previous_action_is_refused_with_what_is_valid(head_v2):
    drafter = DraftHeadDrafter(head_v2)
    with pytest.raises(ValueError, match=r"4 action token ids .*got \[319, 318\]"):
        drafter.with_previous_action(_action(0, 1))
    with pytest.raises(ValueError, match=r"action token ids \(ids 64\.\.319\)"):
        drafter.with_previous_action([5, 6, 7, 8])  # text ids
    embeds = torch.zeros(1, 2, head_v2.config.hidden_size)
    with pytest.raises(ValueError, match="pass previous_bins"):
        head_v2(embeds, embeds, torch.arange(2)[None])


def test_a_previous_action_that_is_not_a_flat_sequence_of_ints_is_refused_not_coerced(head_v2):
    # issue 64: floats were truncated to ids and nested lists flattened, silently
    drafter = DraftHeadDrafter(head_v2)
    ids = _action(1, 2, 3, 4)  # [318, 317, 316, 315]
    valid = r"4 action token ids \(ids 64\.\.319\), a flat sequence of ints, got "
    bad = {
        "floats": ([i + 0.7 for i in ids], r"\[318\.7, 317\.7, 316\.7, 315\.7\] \(torch\.float32 values, not ints\)"),
        "whole floats": ([float(i) for i in ids], r"\[318\.0, 317\.0, 316\.0, 315\.0\] \(torch\.float32 values"),
        "a float tensor": (torch.tensor(ids, dtype=torch.float64), r"\[318\.0, .*\(torch\.float64 values"),
        "a float array": (np.asarray(ids, dtype=np.float32), r".*\(torch\.float32 values"),
        "one float among ints": ([*ids[:3], 315.5], r"\[318, 317, 316, 315\.5\] \(torch\.float32 values"),
        "nested": ([ids[:2], ids[2:]], r"\[\[318, 317\], \[316, 315\]\] \(nested\)"),
        "a [1, D] tensor": (torch.tensor([ids]), r".*\(nested\)"),
        "ragged": ([ids[:1], ids[1:]], r"\[\[318\], \[317, 316, 315\]\]$"),
        "bools": ([True, False, True, False], r"\[True, False, True, False\] \(bools\)"),
        "one id": (ids[0], r"318 \(not a sequence\)"),
        "too many": ([*ids, ids[0]], r"\[318, 317, 316, 315, 318\]$"),
        "out of range": ([*ids[:3], 320], r"\[318, 317, 316, 320\]$"),
    }
    for value, shown in bad.values():  # (the keys name the cases)
        with pytest.raises(ValueError, match=valid + shown):
            drafter.with_previous_action(value)
        with pytest.raises(ValueError, match=valid):
            head_v2.previous_action_bins(value)
    # what is valid: a list, a tuple, an int tensor or array (of any int dtype), one action of D ids
    expected = head_v2.previous_action_bins(ids).tolist()
    assert expected == [1, 2, 3, 4]
    for value in (tuple(ids), torch.tensor(ids), torch.tensor(ids, dtype=torch.int32), np.asarray(ids, np.int16),
                  [np.int64(i) for i in ids]):  # fmt: skip
        assert head_v2.previous_action_bins(value).tolist() == expected
        assert drafter.with_previous_action(value).previous_bins.tolist() == expected


def test_a_head_without_the_input_ignores_the_previous_action_and_refuses_its_bins(target):
    torch.manual_seed(0)
    head = DraftHead.from_target(target, ActionTokenizer(VOCAB), action_dim=ACTION_DIM).eval()
    drafter = DraftHeadDrafter(head)
    assert drafter.with_previous_action(_action(1, 2, 3, 4)) is drafter
    embeds = torch.zeros(1, 2, head.config.hidden_size)
    with pytest.raises(ValueError, match="does not read a previous action"):
        head(embeds, embeds, torch.arange(2)[None], previous_bins=torch.zeros(1, 2, dtype=torch.long))


def test_feature_layers_are_validated_and_saved(tmp_path, head_v2):
    with pytest.raises(ValueError, match=r"feature_layers must be None .* got \[2, 2\]"):
        DraftHead.from_target(LlamaForCausalLM(tiny_llama_config()), ActionTokenizer(VOCAB), feature_layers=[2, 2])
    head_v2.save_pretrained(tmp_path)
    loaded = DraftHead.from_pretrained(tmp_path).eval()
    assert loaded.config.hidden_state_layers == (1, 2, -1) and loaded.config.previous_action_input
    for (name, a), b in zip(head_v2.state_dict().items(), loaded.state_dict().values()):
        assert torch.equal(a, b), name


# ----------------------------------------------------------------------------- heads saved before v2
def test_a_head_saved_before_v2_drafts_what_it_drafted_before():
    """The committed policy-v3 head (v1) on three fixed frames, chain then tree: the trees recorded with the code
    before head v2 (commit 3d7757c; tests/fixtures/head_v1_drafts.json)."""
    from hf_specvla.policies import VLAPolicy

    expected = json.loads((ROOT / "tests/fixtures/head_v1_drafts.json").read_text())
    policy = VLAPolicy.from_pretrained(ROOT / "policies/mt10_vla3")
    head = DraftHead.from_pretrained(ROOT / "policies/mt10_vla3_draft").eval()
    assert head.feature_fuse is None and head.previous_embedding is None
    assert head.config.hidden_state_layers == (-1,) and not head.config.previous_action_input
    rng = np.random.default_rng(0)
    for tree, trees in zip((None, DraftTreeConfig()), expected):
        recorder = Recorder(DraftHeadDrafter(head, tree=tree))
        for _ in range(3):
            image = rng.integers(0, 256, (128, 128, 3), dtype=np.uint8)
            policy.predict_action(image, "reach the goal", np.zeros(4), assistant_model=recorder)
        assert recorder.trees == trees


# ----------------------------------------------------------------------------- training-time test
def distilled_batch(target, head):
    """(a distillation set of 4 examples for ``head``, one with a previous action per row, and it collated)."""
    previous = torch.tensor([_action(5, 6, 7, 8), [-1] * ACTION_DIM])
    prompts = [{"input_ids": _ids(seed, length=9, batch=2), "previous_action": previous} for seed in (4, 5)]
    dataset = build_distillation_dataset(target, prompts, NEW_TOKENS, ActionTokenizer(VOCAB), progress=False,
                                         hidden_state_layers=head.config.hidden_state_layers)  # fmt: skip
    return dataset, collate_distillation([dataset[i] for i in range(len(dataset))])


@pytest.fixture(scope="module")
def v2_batch(target, head_v2):
    return distilled_batch(target, head_v2)


def test_unrolled_training_features_are_the_features_of_a_drafted_chain(target, head_v2, v2_batch):
    """Step j of root r in training equals the head drafting a chain from root r whose drafts were right."""
    _, batch = v2_batch
    handles = head_v2.target_handles(target)
    width = head_v2.config.hidden_size
    inputs_hidden = batch["hidden"][:, :-1, : 3 * width]
    steps = 4
    with torch.no_grad():
        unrolled = unrolled_features(head_v2, handles, batch, inputs_hidden, steps)
    row, root = 0, 10  # a root after the prompt (9 tokens): as after a prefill
    ids, first = batch["input_ids"][row : row + 1], int(batch["first_position"][row])
    previous = head_v2.previous_action_bins(batch["previous_action"][row])
    embed = handles.embed_tokens
    cache = DynamicCache()
    with torch.no_grad():
        positions = torch.arange(root + 1)[None]
        features = head_v2(embed(ids[:, 1 : root + 2]), inputs_hidden[row : row + 1, : root + 1], positions,
                           causal_mask(root + 1, 0, torch.float32, ids.device), cache,
                           head_v2.slot_bins(previous, first, positions))[:, -1:]  # fmt: skip
        torch.testing.assert_close(features[0, 0], unrolled[0][row, root])
        for step in range(1, steps):
            position = torch.tensor([[root + step]])
            mask = to_additive_mask(torch.ones(1, 1, cache.get_seq_length() + 1, dtype=torch.bool), torch.float32)
            features = head_v2(embed(ids[:, root + step + 1 : root + step + 2]), features, position, mask, cache,
                               head_v2.slot_bins(previous, first, position))  # fmt: skip
            torch.testing.assert_close(features[0, 0], unrolled[step][row, root], msg=f"step {step}")


def test_training_a_v2_head_resumes_bit_exactly(tmp_path, target, head_v2, v2_batch):
    from hf_specvla.training.draft_head import train_draft_head

    dataset, _ = v2_batch

    def fresh():
        head = DraftHead(head_v2.config)
        head.load_state_dict(head_v2.state_dict())
        return head

    settings = dict(batch_size=2, learning_rate=1e-3, save_every=2, unroll_steps=3)
    train_draft_head(fresh(), target, dataset, DraftTrainingConfig(str(tmp_path / "a"), max_steps=2, **settings),
                     progress=False)  # fmt: skip
    resumed = train_draft_head(fresh(), target, dataset, DraftTrainingConfig(str(tmp_path / "a"), max_steps=4,
                               resume=True, **settings), progress=False)  # fmt: skip
    straight = train_draft_head(fresh(), target, dataset, DraftTrainingConfig(str(tmp_path / "b"), max_steps=4,
                                **settings), progress=False)  # fmt: skip
    for (name, a), b in zip(resumed.state_dict().items(), straight.state_dict().values()):
        assert torch.equal(a, b), name
    logged = [json.loads(line) for line in (tmp_path / "b" / "training_log.jsonl").read_text().splitlines()]
    assert len(logged[-1]["step_accuracy"]) == 3  # one accuracy per unrolled step


def test_a_distillation_set_built_for_another_head_is_refused(target, head_v2):
    prompts = [{"input_ids": _ids(6, length=9)}]
    top_only = build_distillation_dataset(target, prompts, NEW_TOKENS, ActionTokenizer(VOCAB), progress=False)
    batch = collate_distillation([top_only[0]])
    with pytest.raises(ValueError, match=r"reads layers \[1, 2, -1\]"):
        distillation_loss(head_v2, head_v2.target_handles(target), batch, DraftTrainingConfig("unused"))


# ----------------------------------------------------------------------------- cost structure
def test_head_v2_costs_at_most_12_percent_of_a_policy_v3_decode_step():
    """Multiply-adds per token (weights touched; attention over the cache aside): a head v2 step (the fuses, its one
    decoder layer, the action-only scorer) against a decode step of policy v3 (16 decoder layers + lm_head). What it
    costs in time is measured by examples/benchmarks/policy_cost.py --heads v1 v2."""
    from hf_specvla.policies import VLAPolicy
    from hf_specvla.training import head_v2_settings

    policy = VLAPolicy.from_pretrained(ROOT / "policies/mt10_vla3")
    language_model = policy.model.model.language_model
    head = DraftHead.from_target(policy.model, policy.action_tokenizer, 4, **head_v2_settings(policy.model))
    assert head.config.hidden_state_layers == (2, 8, -1)

    def weights(module) -> int:
        return sum(p.numel() for name, p in module.named_parameters() if p.dim() == 2 and "embed" not in name)

    decode = weights(language_model) + policy.model.lm_head.weight.numel()
    scorer = head.scorer(policy.model.lm_head, [policy.tokenizer.eos_token_id]).weight.numel()
    step = weights(head.layer) + weights(head.fuse) + weights(head.feature_fuse) + scorer
    assert step / decode <= 0.12, f"a head v2 step touches {step:,} weights, a decode step {decode:,}"
    matrices = {name.split(".")[0] for name, p in head.named_parameters() if p.dim() == 2}
    assert matrices == {"layer", "fuse", "feature_fuse", "previous_embedding"}  # the last one is looked up, not run
