"""The one training loop: what every trainer gets alike (logs, validation, checkpoints at the last step, the final
save), and resume equal to an uninterrupted run for each of its three callers (a tiny model here; the toy target
below; draft heads in test_training.py; behaviour cloning killed with -9 in test_kill_resume.py)."""

from __future__ import annotations

import json

import pytest
import torch

from hf_specvla.training.configuration import TrainingConfig
from hf_specvla.training.loop import TrainingJob, learning_rate_factor, run_training


class Killed(Exception):
    """Stands for kill -9 in the middle of a run."""


def _job(seed: int = 0, killed_at: int | None = None) -> TrainingJob:
    torch.manual_seed(seed)
    model = torch.nn.Linear(3, 1)
    data = [
        (torch.randn(3, generator=torch.Generator().manual_seed(i)), torch.tensor([float(i % 3)])) for i in range(10)
    ]

    def loss(model, batch, step):
        if step == killed_at:
            raise Killed
        inputs, targets = batch
        noise = torch.randn(targets.shape, generator=torch.Generator().manual_seed(step)) * 0.01  # per-step seeded
        value = torch.nn.functional.mse_loss(model(inputs), targets + noise)
        return value, {"loss": value.detach()}

    def save(model, folder):
        folder.mkdir(parents=True, exist_ok=True)
        torch.save(model.state_dict(), folder / "weights.pt")

    def validate(model):
        return {"weight_norm": model.weight.norm().item()}

    return TrainingJob(model, data, loss, save, validate=validate)


def _config(folder, **overrides) -> TrainingConfig:
    settings = dict(max_steps=7, batch_size=4, learning_rate=0.05, warmup_steps=2, lr_schedule="cosine", save_every=3,
                    eval_every=0, log_every=2, seed=0)  # fmt: skip
    return TrainingConfig(str(folder), **{**settings, **overrides})


def test_the_loop_logs_validates_checkpoints_and_saves(tmp_path):
    model, metrics = run_training(_job(), _config(tmp_path), tmp_path, progress=False)
    assert sorted(p.name for p in tmp_path.glob("checkpoint-*")) == ["checkpoint-6", "checkpoint-7"]  # and the last
    assert (tmp_path / "checkpoint-7" / "model" / "weights.pt").exists() and (tmp_path / "weights.pt").exists()
    log = [json.loads(line) for line in (tmp_path / "training_log.jsonl").read_text().splitlines()]
    assert [row["step"] for row in log] == [2, 4, 6, 7]
    validations = [json.loads(line) for line in (tmp_path / "validation.jsonl").read_text().splitlines()]
    assert [row["step"] for row in validations] == [7]  # eval_every=0: only after the last step
    assert metrics["val_weight_norm"] == pytest.approx(validations[0]["weight_norm"]) and not model.training
    assert json.loads((tmp_path / "training_config.json").read_text())["steps"] == 7
    # resuming a finished run with the same max_steps trains nothing and keeps its final record
    _, again = run_training(_job(), _config(tmp_path, resume=True), tmp_path, progress=False)
    assert again == {} and json.loads((tmp_path / "training_config.json").read_text())["final_metrics"] == metrics


def test_a_resumed_run_equals_an_uninterrupted_one(tmp_path):
    with pytest.raises(Killed):  # killed at step 5: checkpoint-3 is the newest
        run_training(_job(killed_at=5), _config(tmp_path / "resumed"), tmp_path / "resumed", progress=False)
    resumed, _ = run_training(_job(seed=1), _config(tmp_path / "resumed", resume=True), tmp_path / "resumed",
                              progress=False)  # fmt: skip
    straight, _ = run_training(_job(), _config(tmp_path / "straight"), tmp_path / "straight", progress=False)
    for name, value in straight.state_dict().items():
        assert torch.equal(resumed.state_dict()[name], value), name


def test_the_toy_target_resumes_like_an_uninterrupted_run(tmp_path):
    from hf_specvla.benchmarks.toy import ToyTargetSize, build_toy_target, train_toy_target

    size = ToyTargetSize(hidden_size=32, num_hidden_layers=1, num_attention_heads=2, num_key_value_heads=1,
                         intermediate_size=64)  # fmt: skip

    def train(folder, max_steps, resume=False):
        target, tokenizer, action_tokenizer = build_toy_target(size, seed=0)
        config = TrainingConfig(str(folder), max_steps=max_steps, batch_size=8, learning_rate=4e-3, save_every=2,
                                resume=resume, seed=0)  # fmt: skip
        train_toy_target(target, tokenizer, action_tokenizer, config, progress=False)
        return target

    train(tmp_path / "resumed", 2)
    resumed = train(tmp_path / "resumed", 4, resume=True)
    straight = train(tmp_path / "straight", 4)
    for name, value in straight.state_dict().items():
        assert torch.equal(resumed.state_dict()[name], value), name
    assert (tmp_path / "resumed" / "config.json").exists() and (tmp_path / "resumed" / "tokenizer.json").exists()


def test_the_learning_rate_schedule():
    assert [learning_rate_factor(s, 2, 10, "constant") for s in (0, 1, 2, 9)] == [0.5, 1.0, 1.0, 1.0]
    assert learning_rate_factor(2, 2, 10, "cosine") == 1.0 and learning_rate_factor(10, 2, 10, "cosine") == 0.0


@pytest.mark.parametrize(("overrides", "match"), [(dict(max_steps=0), "TrainingConfig.max_steps must be >= 1"),
                                                  (dict(lr_schedule="linear"), "lr_schedule"),
                                                  (dict(mixed_precision="fp8"), "mixed_precision"),
                                                  (dict(max_grad_norm=0), "max_grad_norm")])  # fmt: skip
def test_the_loop_settings_are_validated(tmp_path, overrides, match):
    with pytest.raises(ValueError, match=match):
        _config(tmp_path, **overrides)
