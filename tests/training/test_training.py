"""Draft training: a self-distilled head on the toy target drafts well; training saves, resumes, never clobbers."""

import json

import pytest
import torch

from hf_specvla import DraftHead, DraftHeadDrafter, DraftTreeConfig
from hf_specvla.benchmarks.toy import ACTION_DIM, split_scenes, toy_inputs
from hf_specvla.training.draft_head import (
    DraftTrainingConfig,
    build_distillation_dataset,
    latest_checkpoint,
    train_draft_head,
)

from ..speculative.test_speculative_decoding import assert_within_tolerance


def held_out_prompts(pipeline, n):
    held_out = split_scenes()[1]
    return [toy_inputs([scene], pipeline.tokenizer) for scene in held_out[:: len(held_out) // n][:n]]


def run(pipeline, prompt, draft_head, **kwargs):
    return pipeline.target.generate(
        **prompt,
        max_new_tokens=ACTION_DIM,
        do_sample=False,
        assistant_model=draft_head,
        return_dict_in_generate=True,
        **kwargs,
    )


def test_trained_draft_accepts_at_least_3_tokens_per_target_forward(toy_pipeline):
    untrained = DraftHead.from_target(toy_pipeline.target, toy_pipeline.action_tokenizer, action_dim=ACTION_DIM)
    trained_stats = untrained_stats = None
    for prompt in held_out_prompts(toy_pipeline, 32):
        expected = toy_pipeline.target.generate(**prompt, max_new_tokens=ACTION_DIM, do_sample=False)
        trained = run(toy_pipeline, prompt, toy_pipeline.draft_head)
        baseline = run(toy_pipeline, prompt, untrained.eval())
        assert torch.equal(trained.sequences, expected) and torch.equal(baseline.sequences, expected)  # r=0
        trained_stats = trained.speculation if trained_stats is None else trained_stats.merge(trained.speculation)
        untrained_stats = (
            baseline.speculation if untrained_stats is None else untrained_stats.merge(baseline.speculation)
        )
    assert trained_stats.mean_accept_length >= 3.0, trained_stats
    assert untrained_stats.mean_accept_length < 1.5, untrained_stats


def test_eagle2_tree_with_a_trained_head_is_lossless_and_never_worse_than_the_chain(toy_pipeline):
    """The tree keeps the head's greedy path as a backbone, so it needs no more target forwards than the chain of
    its depth; and r=0 stays identical to greedy."""
    tree = DraftHeadDrafter(toy_pipeline.draft_head, tree=DraftTreeConfig())  # the defaults
    chain = DraftHeadDrafter(toy_pipeline.draft_head, num_draft_tokens=DraftTreeConfig().depth)
    stats = None
    for prompt in held_out_prompts(toy_pipeline, 16):
        expected = toy_pipeline.target.generate(**prompt, max_new_tokens=ACTION_DIM, do_sample=False)
        out, chained = run(toy_pipeline, prompt, tree), run(toy_pipeline, prompt, chain)
        assert torch.equal(out.sequences, expected) and torch.equal(chained.sequences, expected)  # r=0
        assert out.speculation.num_target_forwards <= chained.speculation.num_target_forwards
        stats = out.speculation if stats is None else stats.merge(out.speculation)
    assert stats.mean_accept_length >= 3.0, stats
    assert stats.accepted_by_drafter["head-tree"] > 0


def test_the_toy_head_drafts_most_actions_from_the_image_before_the_prefill(toy_pipeline):
    """The demo's kind of head (head v3 reading the encoded image before the prefill, ``TOY_HEAD_SETTINGS``; the
    tests' one trains 2400 steps, the demo's 4800) drafts the whole action before the target's first forward: on
    held-out scenes (no previous action) most calls take one target forward, every one greedy's tokens."""
    assert toy_pipeline.draft_head.config.prefill_image_features
    tree = DraftHeadDrafter(toy_pipeline.draft_head, tree=DraftTreeConfig())
    forwards = []
    for prompt in held_out_prompts(toy_pipeline, 32):
        expected = toy_pipeline.target.generate(**prompt, max_new_tokens=ACTION_DIM, do_sample=False)
        out = run(toy_pipeline, prompt, tree)
        assert torch.equal(out.sequences, expected)  # r=0
        forwards.append(out.speculation.num_target_forwards)
    assert sum(f == 1 for f in forwards) >= 0.5 * len(forwards), forwards


@pytest.mark.parametrize("bin_tolerance", [2, [4, 4, 4, 4, 4, 4, 0]])
def test_relaxed_decoding_on_the_toy_target(toy_pipeline, bin_tolerance):
    tolerance = bin_tolerance if isinstance(bin_tolerance, list) else [bin_tolerance] * ACTION_DIM
    for prompt in held_out_prompts(toy_pipeline, 12):
        out = run(toy_pipeline, prompt, toy_pipeline.draft_head, bin_tolerance=bin_tolerance)
        assert out.speculation.num_new_tokens == ACTION_DIM
        assert_within_tolerance(toy_pipeline.target, prompt, out.sequences, tolerance, toy_pipeline.action_tokenizer)


@pytest.fixture(scope="module")
def small_dataset(toy_pipeline):
    prompts = [toy_inputs(split_scenes()[0][:8], toy_pipeline.tokenizer)]
    return build_distillation_dataset(
        toy_pipeline.target, prompts, ACTION_DIM, toy_pipeline.action_tokenizer, progress=False
    )


def test_distillation_dataset_layout(small_dataset, toy_pipeline):
    item = small_dataset[0]
    length = item["input_ids"].shape[0]
    assert item["hidden"].shape == (length, toy_pipeline.target.config.text_config.hidden_size)
    # positions p with a generated action token at p+2: the last ACTION_DIM tokens, minus nothing
    assert int(item["loss_mask"].sum()) == ACTION_DIM
    assert bool(item["loss_mask"][length - ACTION_DIM - 2 : length - 2].all())


def test_checkpoints_resume_and_never_clobber(tmp_path, toy_pipeline, small_dataset):
    def head():
        torch.manual_seed(0)
        return DraftHead.from_target(toy_pipeline.target, toy_pipeline.action_tokenizer, action_dim=ACTION_DIM)

    settings = dict(batch_size=4, learning_rate=1e-3, save_every=2, keep_checkpoints=2)
    train_draft_head(
        head(),
        toy_pipeline.target,
        small_dataset,
        DraftTrainingConfig(str(tmp_path), max_steps=4, **settings),
        progress=False,
    )
    # every save_every steps and after the last step (so that a finished run can be continued)
    assert sorted(p.name for p in tmp_path.glob("checkpoint-*")) == ["checkpoint-2", "checkpoint-4"]
    assert (tmp_path / "checkpoint-2" / "draft_head" / "config.json").exists() and (tmp_path / "config.json").exists()

    # an existing run is not silently overwritten
    with pytest.raises(FileExistsError, match="resume=True"):
        train_draft_head(
            head(),
            toy_pipeline.target,
            small_dataset,
            DraftTrainingConfig(str(tmp_path), max_steps=6, **settings),
            progress=False,
        )

    # resuming continues from step 4 and equals an uninterrupted run of the same length
    resumed = train_draft_head(
        head(),
        toy_pipeline.target,
        small_dataset,
        DraftTrainingConfig(str(tmp_path), max_steps=6, resume=True, **settings),
        progress=False,
    )
    assert json.loads((tmp_path / "training_config.json").read_text())["steps"] == 6
    assert latest_checkpoint(tmp_path).name == "checkpoint-6"
    straight = train_draft_head(
        head(),
        toy_pipeline.target,
        small_dataset,
        DraftTrainingConfig(str(tmp_path / "straight"), max_steps=6, **settings),
        progress=False,
    )
    for (name, a), b in zip(resumed.state_dict().items(), straight.state_dict().values()):
        torch.testing.assert_close(a, b, msg=name, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize(
    "overrides, match",
    [
        (dict(max_steps=0), "max_steps"),
        (dict(learning_rate=0.0), "learning_rate"),
        (dict(feature_noise=-1.0), "feature_noise"),
    ],
)
def test_training_config_validation(tmp_path, overrides, match):
    with pytest.raises(ValueError, match=match):
        DraftTrainingConfig(str(tmp_path), **overrides)


def test_overwrite_moves_the_old_run_aside_and_resume_needs_a_checkpoint(tmp_path, toy_pipeline, small_dataset):
    """Regressions (reliability issue, cases 1 and 2): overwriting a folder that held an older run with more
    checkpoints used to keep the old checkpoints (a later --resume continued the *old* run); --resume on a finished
    folder without checkpoints used to train from scratch over it silently."""

    def train(folder, **overrides):
        torch.manual_seed(0)
        head = DraftHead.from_target(toy_pipeline.target, toy_pipeline.action_tokenizer, action_dim=ACTION_DIM)
        settings = {**dict(batch_size=4, learning_rate=1e-3, save_every=1, keep_checkpoints=5), **overrides}
        return train_draft_head(head, toy_pipeline.target, small_dataset, DraftTrainingConfig(str(folder), **settings),
                                progress=False)  # fmt: skip

    folder = tmp_path / "run"
    train(folder, max_steps=5, learning_rate=3e-3)  # the old run: checkpoints 1..5
    train(folder, max_steps=2, overwrite_output_dir=True)  # a new run, other settings
    assert sorted(p.name for p in folder.glob("checkpoint-*")) == ["checkpoint-1", "checkpoint-2"]  # only its own
    (aside,) = tmp_path.glob("run.replaced-*")
    assert sorted(p.name for p in aside.glob("checkpoint-*")) == [f"checkpoint-{i}" for i in range(1, 6)]
    resumed = train(folder, max_steps=3, resume=True)  # continues the new run, not the old one
    straight = train(tmp_path / "straight", max_steps=3)
    for (name, a), b in zip(resumed.state_dict().items(), straight.state_dict().values()):
        torch.testing.assert_close(a, b, msg=name, rtol=1e-4, atol=1e-5)
    with pytest.raises(FileExistsError, match="learning_rate: 0.003 here vs 0.001 there"):
        train(folder, max_steps=4, resume=True, learning_rate=3e-3)  # resuming is only for the same run

    finished = tmp_path / "finished"
    train(finished, max_steps=2, save_every=0)  # final weights only
    with pytest.raises(FileExistsError, match="no checkpoint-\\* to resume from"):
        train(finished, max_steps=3, resume=True)
    assert (finished / "config.json").exists()  # the finished run is untouched


def test_a_half_precision_set_teaches_the_head_what_a_float32_one_does(tmp_path, toy_pipeline):
    """train-draft stores the target's hidden states in float16 (half the memory): the same sequences, each hidden
    state float32's rounded, and the same training run ends at the same held-out loss and accuracy, up to noise far
    below what the training changes."""
    from hf_specvla.training.draft_head import collate_distillation, distillation_loss

    target, tokenizer, actions = toy_pipeline.target, toy_pipeline.tokenizer, toy_pipeline.action_tokenizer
    train_scenes, held_out_scenes = split_scenes()
    prompts = [toy_inputs(train_scenes[i : i + 32], tokenizer) for i in range(0, 96, 32)]
    sets = {dtype: build_distillation_dataset(target, prompts, ACTION_DIM, actions, progress=False, hidden_dtype=dtype)
            for dtype in (torch.float32, torch.float16)}  # fmt: skip
    for full, half in zip(sets[torch.float32], sets[torch.float16]):
        assert torch.equal(full["input_ids"], half["input_ids"]) and half["hidden"].dtype == torch.float16
        assert torch.equal(full["hidden"].half(), half["hidden"])
    held_out = build_distillation_dataset(target, [toy_inputs(held_out_scenes[:48], tokenizer)], ACTION_DIM, actions,
                                          progress=False)  # fmt: skip
    batch = collate_distillation(list(held_out))
    exact = DraftTrainingConfig(str(tmp_path / "eval"), feature_noise=0.0)

    def held_out_loss(head):
        with torch.no_grad():
            losses = distillation_loss(head.eval(), head.target_handles(target), batch, exact)
        return float(losses["loss"]), float(losses["token_accuracy"])

    def trained(dtype):
        torch.manual_seed(0)
        head = DraftHead.from_target(target, actions, action_dim=ACTION_DIM)
        if dtype is None:
            return head
        config = DraftTrainingConfig(str(tmp_path / str(dtype)), max_steps=40, batch_size=16, learning_rate=3e-3,
                                     save_every=0)  # fmt: skip
        return train_draft_head(head, target, sets[dtype], config, progress=False)

    (untrained, _), (full, full_accuracy), (half, half_accuracy) = (
        held_out_loss(trained(dtype)) for dtype in (None, torch.float32, torch.float16)
    )
    assert full < 0.8 * untrained  # the training moves the loss...
    assert abs(half - full) < 0.02 * (untrained - full), (untrained, full, half)  # ...float16 storage does not
    assert abs(half_accuracy - full_accuracy) <= 0.02, (full_accuracy, half_accuracy)
