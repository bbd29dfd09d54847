"""Draft-head training on several processes (``torchrun`` / ``accelerate launch``, gloo on the CPU): the head two
processes train with b examples each is the head one process trains with 2 b; one process writes and logs; a run
resumes on another process count with the same global batch, and is refused with another global batch."""

import json
import os
import subprocess
import sys

import pytest
import torch
from safetensors.torch import load_file

pytest.importorskip("metaworld")

from hf_specvla.cli import main  # noqa: E402
from hf_specvla.training import DraftTrainingConfig  # noqa: E402
from hf_specvla.training.checkpoints import training_record  # noqa: E402
from hf_specvla.training.draft_head import EXAMPLE_INDEX, example_generators  # noqa: E402

from .test_policy_draft import build_policy  # noqa: E402


def _args(policy: str, output_dir, max_steps: int, batch_size: int, *extra: str) -> list[str]:
    return ["train-draft", "--policy", policy, "--tasks", "reach", "--rollout-episodes", "2", "--rollout-max-steps",
            "8", "--validation-frames", "3", "--max-steps", str(max_steps), "--save-every", "2", "--eval-every", "2",
            "--warmup-steps", "2", "--lr-schedule", "constant", "--batch-size", str(batch_size), "--output-dir",
            str(output_dir), *extra]  # fmt: skip


def _two_processes(args: list[str]) -> subprocess.CompletedProcess:
    """``torchrun --nproc_per_node 2 -m hf_specvla.cli ...`` (as docs/training.md gives it), one thread each."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("RANK", None), env.pop("WORLD_SIZE", None)
    launcher = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]
    command = [*launcher, "-m", "hf_specvla.cli", *args]
    return subprocess.run(command, capture_output=True, text=True, env=env, timeout=600)


def _max_difference(folder_a, folder_b) -> float:
    a, b = load_file(folder_a / "model.safetensors"), load_file(folder_b / "model.safetensors")
    assert a.keys() == b.keys()
    return max((a[name] - b[name]).abs().max().item() for name in a)


@pytest.fixture(scope="module")
def policy(tmp_path_factory):
    return build_policy(tmp_path_factory.mktemp("policy") / "p", seed=0)


@pytest.mark.commands
def test_two_processes_train_the_head_one_process_trains_on_their_global_batch(policy, tmp_path, capsys):
    one, two = tmp_path / "one", tmp_path / "two"
    assert main(_args(policy, one, 4, 4)) == 0
    done = _two_processes(_args(policy, two, 4, 2))
    assert done.returncode == 0, done.stderr[-3000:]
    assert _max_difference(one, two) < 1e-5  # float sums in another order, nothing more
    final = [json.loads((folder / "training_config.json").read_text()) for folder in (one, two)]
    assert [f["processes"] for f in final] == [1, 2] and [f["global_batch_size"] for f in final] == [4, 4]
    assert final[1]["final_metrics"]["loss"] == pytest.approx(final[0]["final_metrics"]["loss"], abs=1e-5)
    # the global batch's numbers, written once by the main process
    for name in ("training_log.jsonl", "validation.jsonl"):
        steps = [[json.loads(line)["step"] for line in (f / name).read_text().splitlines()] for f in (one, two)]
        assert steps[0] == steps[1], name
    assert (two / "README.md").is_file() and (two / "distillation_set.json").is_file()
    assert json.loads((two / "run.json").read_text())["settings"]["batch_size"] == 4
    assert json.loads((two / "run.json").read_text())["paths"]["processes"] == 2
    assert done.stdout.count("draft head saved to") == 1
    assert done.stderr.count("distillation set:") == 1  # the second process logs warnings only
    assert {"random_states_0.pkl", "random_states_1.pkl"} <= set(os.listdir(two / "checkpoint-4"))  # each its own


@pytest.mark.commands
def test_a_run_resumes_on_another_process_count_with_the_same_global_batch_and_not_with_another(policy, tmp_path):
    whole, split = tmp_path / "whole", tmp_path / "split"
    assert main(_args(policy, whole, 4, 4)) == 0
    assert main(_args(policy, split, 2, 4)) == 0  # one process to step 2, then two processes on
    done = _two_processes(_args(policy, split, 4, 2, "--resume"))
    assert done.returncode == 0, done.stderr[-3000:]
    assert "resuming from step 2" in done.stderr
    assert _max_difference(whole, split) < 1e-5
    # two processes of 4 would learn from 8 examples a step: another run, refused before anything is written
    before = sorted(os.listdir(split))
    refused = _two_processes(_args(policy, split, 6, 4, "--resume"))
    assert refused.returncode != 0
    assert "holds another run: batch_size: 8 here vs 4 there" in refused.stderr
    assert sorted(os.listdir(split)) == before and not (split / "checkpoint-6").exists()


def test_the_record_holds_the_global_batch(monkeypatch):
    """n launched processes of b examples record n b: a resume with another split of the same batch continues."""
    config = DraftTrainingConfig("unused", batch_size=4)
    assert training_record("train-draft", config, {}).settings["batch_size"] == 4
    monkeypatch.setenv("WORLD_SIZE", "2")
    record = training_record("train-draft", config, {})
    assert record.settings["batch_size"] == 8 and record.paths == {"processes": 2}


def test_an_examples_noise_is_its_own_whatever_batch_it_is_in():
    """The loss seeds each example's noise by (seed, step, its index): the same in any batch, process or order."""
    alone = example_generators({EXAMPLE_INDEX: torch.tensor([5])}, seed=0, step=3)
    batched = example_generators({EXAMPLE_INDEX: torch.tensor([2, 5, 7])}, seed=0, step=3)
    assert torch.equal(torch.rand(4, generator=alone[0]), torch.rand(4, generator=batched[1]))
    other_step = example_generators({EXAMPLE_INDEX: torch.tensor([5])}, seed=0, step=4)
    assert not torch.equal(torch.rand(4, generator=other_step[0]), torch.rand(4, generator=batched[1]))
