"""`hf-specvla train-draft`: a draft head for a policy, by self-distillation on its rollouts; resumable; a head
made for one policy is refused by another."""

import json
import shutil

import pytest
import torch

pytest.importorskip("metaworld")

from transformers import AutoModel  # noqa: E402

from hf_specvla import ActionNormalizer, DraftHead  # noqa: E402
from hf_specvla.cli import main  # noqa: E402
from hf_specvla.metaworld.env import TASK_INSTRUCTIONS  # noqa: E402
from hf_specvla.policies import VLAPolicy, VLAPolicyConfig  # noqa: E402
from hf_specvla.training.policy_draft import DraftDataConfig  # noqa: E402

TINY = dict(image_size=32, patch_size=16, vision_hidden_size=32, vision_layers=1, text_hidden_size=64, text_layers=2,
            text_heads=4)  # fmt: skip


def build_policy(folder, seed: int) -> str:
    """A tiny untrained policy for every Meta-World task, saved to ``folder``."""
    actions = ActionNormalizer(q01=[-1.0] * 4, q99=[1.0] * 4, mask=[True, True, True, False])
    states = ActionNormalizer(q01=[-0.2, 0.4, 0.0, 0.0], q99=[0.3, 0.9, 0.4, 1.0])
    policy = VLAPolicy.build(list(TASK_INSTRUCTIONS.values()), actions, states, VLAPolicyConfig(**TINY), seed=seed)
    policy.save_pretrained(folder)
    return str(folder)


@pytest.fixture(scope="session")
def policy_dirs(tmp_path_factory):
    root = tmp_path_factory.mktemp("policies")
    return build_policy(root / "a", seed=0), build_policy(root / "b", seed=1)


def train_args(policy: str, output_dir, max_steps: int) -> list[str]:
    return ["train-draft", "--policy", policy, "--tasks", "reach", "--rollout-episodes", "2", "--rollout-max-steps",
            "6", "--validation-frames", "3", "--max-steps", str(max_steps), "--save-every", "2", "--eval-every", "2",
            "--batch-size", "4", "--output-dir", str(output_dir)]  # fmt: skip


def test_train_draft_writes_a_loadable_head_that_resumes_and_knows_its_policy(policy_dirs, tmp_path, capsys):
    policy_dir, other_dir = policy_dirs
    out = tmp_path / "draft"
    assert main(train_args(policy_dir, out, 4)) == 0
    head = DraftHead.from_pretrained(out)
    assert isinstance(AutoModel.from_pretrained(out), DraftHead)
    policy = VLAPolicy.from_pretrained(policy_dir)
    assert head.config.target_fingerprint == policy.weights_fingerprint()
    assert head.config.target_name_or_path == policy_dir
    policy.check_draft_head(head)  # made for this policy: accepted
    card = (out / "README.md").read_text()
    assert card.startswith("---\nlibrary_name: hf_specvla") and f"base_model: {policy_dir}" in card
    assert "hf-specvla train-draft --policy" in card and "| drafted position | accepted |" in card
    validations = [json.loads(line) for line in (out / "validation.jsonl").read_text().splitlines()]
    assert [v["step"] for v in validations] == [2, 4]
    # what docs/folders.md says a finished run keeps: its final weights and its last two checkpoints
    assert sorted(p.name for p in out.glob("checkpoint-*")) == ["checkpoint-2", "checkpoint-4"]
    assert validations[-1]["sequences"] == 3 and 0 <= validations[-1]["acceptance_per_position"][0] <= 1
    assert 1 <= validations[-1]["tokens_per_target_forward"] <= 4

    # the same folder again without --resume: a usage error, nothing touched
    with pytest.raises(SystemExit) as exit_info:
        main(train_args(policy_dir, out, 4))
    assert exit_info.value.code == 2 and "--resume" in capsys.readouterr().err
    # resume continues from the last checkpoint (step 4) to the new max_steps
    before = head.state_dict()
    assert main([*train_args(policy_dir, out, 6), "--resume"]) == 0
    validations = [json.loads(line) for line in (out / "validation.jsonl").read_text().splitlines()]
    assert [v["step"] for v in validations] == [2, 4, 6]
    after = DraftHead.from_pretrained(out).state_dict()
    assert any(not torch.equal(before[k], after[k]) for k in before)
    # the same policy copied to another folder is the same input (identity by weights, not paths)
    copy = tmp_path / "copied_policy"
    shutil.copytree(policy_dir, copy)
    assert main([*train_args(str(copy), out, 8), "--resume"]) == 0
    run = json.loads((out / "run.json").read_text())
    assert run["paths"]["target"] == policy_dir and "target_name_or_path" not in run["settings"]["draft_head_config"]
    # resuming with another policy is refused, naming what differs, the weights first
    with pytest.raises(SystemExit) as exit_info:
        main([*train_args(other_dir, out, 10), "--resume"])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "holds another run: target: '" in err and "' here vs '" in err

    # a head distilled from one policy is refused by another with the same shapes
    other = VLAPolicy.from_pretrained(other_dir)
    with pytest.raises(ValueError, match="distilled from the weights of"):
        other.check_draft_head(head)
    with pytest.raises(SystemExit) as exit_info:
        main(["eval", "--policy", other_dir, "--draft-head", str(out), "--tasks", "reach", "--episodes", "1",
              "--output-dir", str(tmp_path / "eval")])  # fmt: skip
    assert exit_info.value.code == 2 and "trained for another model" in capsys.readouterr().err
    assert not (tmp_path / "eval").exists()


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--rollout-episodes", "1"], "must exceed validation_episodes"),
        (["--tasks", "bogus"], "bogus"),
        (["--max-steps", "0"], "--max-steps"),
        (["--policy", "./no/such/policy"], "--policy: policy folder 'no/such/policy' does not exist"),
        (["--data", "./no/such/data"], "not a demonstrations folder"),
    ],
)
def test_train_draft_bad_input_is_a_usage_error(policy_dirs, tmp_path, capsys, flags, message):
    args = ["train-draft", "--policy", policy_dirs[0], "--output-dir", str(tmp_path / "out"), *flags]
    with pytest.raises(SystemExit) as exit_info:
        main(args)
    assert exit_info.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_train_draft_names_a_folder_that_holds_no_run_and_a_resume_of_nothing(policy_dirs, tmp_path, capsys):
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("not a training run")
    for extra in ([], ["--resume"]):
        with pytest.raises(SystemExit) as exit_info:
            main([*train_args(policy_dirs[0], foreign, 2), *extra])
        assert exit_info.value.code == 2 and "holds no training run" in capsys.readouterr().err
    assert sorted(p.name for p in foreign.iterdir()) == ["notes.txt"]
    with pytest.raises(SystemExit) as exit_info:
        main([*train_args(policy_dirs[0], tmp_path / "missing", 2), "--resume"])
    assert exit_info.value.code == 2 and "does not exist, so there is no run to resume" in capsys.readouterr().err
    assert not (tmp_path / "missing").exists()


def test_draft_data_config_validates():
    with pytest.raises(ValueError, match="validation_frames must be >= 1"):
        DraftDataConfig(validation_frames=0)
    assert DraftDataConfig(tasks="MT10").tasks[0].endswith("-v3")


@pytest.mark.parametrize("policy_name", ["mt10_vla3"])  # v1's head left the tree (docs/results/index.md)
def test_the_shipped_draft_heads_load_and_fit_their_shipped_policies(policy_name):
    from pathlib import Path

    root = Path(__file__).resolve().parents[2] / "policies"
    head = DraftHead.from_pretrained(root / f"{policy_name}_draft")
    assert isinstance(AutoModel.from_pretrained(root / f"{policy_name}_draft"), DraftHead)
    policy = VLAPolicy.from_pretrained(root / policy_name)
    policy.check_draft_head(head)  # distilled from exactly these weights
    assert head.config.num_draft_tokens == policy.config.action_tokens - 1  # a chain completes one call's tokens
    card = (root / f"{policy_name}_draft" / "README.md").read_text()
    assert card.startswith("---\nlibrary_name: hf_specvla") and "## Measured acceptance" in card
    imports = [line for line in card.splitlines() if line.startswith("from hf_specvla")]
    assert imports
    exec("\n".join(imports), {})  # the card's example imports what it names
