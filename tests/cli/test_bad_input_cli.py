"""Bad inputs a new user tried (issue 55, items 3-5): each is a usage error (``error:``, exit code 2, no traceback)
before any folder is written and before the slow work (model load where it can be avoided, environments,
rollouts)."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import pytest

from hf_specvla.cli import main
from hf_specvla.cli.main import build_parser

POLICY = Path(__file__).resolve().parents[2] / "policies" / "mt10_vla"


def _usage_error(argv: list[str], capsys) -> str:
    """The stderr of a command that must stop with a usage error."""
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    err = capsys.readouterr().err
    assert exit_info.value.code == 2, err
    assert "error: " in err and "Traceback" not in err
    return err


@pytest.fixture
def afile(tmp_path) -> Path:
    path = tmp_path / "afile"
    path.write_text("not a folder")
    return path


# ----------------------------------------------------------------------------- --output-dir under a file
@pytest.mark.parametrize(
    "argv",
    [
        ["collect", "--tasks", "reach", "--episodes", "1"],
        ["eval", "--policy", str(POLICY), "--tasks", "reach", "--episodes", "1"],
        ["train-vla", "--data", "{tmp}/nodata"],
        ["train-draft", "--policy", str(POLICY)],
        ["rollouts", "--policy", str(POLICY), "--tasks", "reach"],
    ],
)
@pytest.mark.parametrize("under", [True, False])
def test_an_output_dir_that_is_or_is_under_a_file_is_a_usage_error(tmp_path, afile, capsys, argv, under):
    output_dir = afile / "sub" if under else afile
    err = _usage_error([a.format(tmp=tmp_path) for a in argv] + ["--output-dir", str(output_dir)], capsys)
    if under:
        assert f"--output-dir {output_dir}: {afile} is a file, so no folder can be made under it" in err
    else:
        assert f"--output-dir {afile}: is a file, not a folder" in err
    assert afile.read_text() == "not a folder"


def test_check_output_dir_flag_accepts_new_and_existing_folders(tmp_path):
    import argparse

    from hf_specvla.cli.common import check_output_dir_flag

    parser = argparse.ArgumentParser()
    check_output_dir_flag(str(tmp_path), parser)
    check_output_dir_flag(str(tmp_path / "new" / "deeper"), parser)
    assert not (tmp_path / "new").exists()  # a check writes nothing


# ----------------------------------------------------------------------------- collect's values
@pytest.mark.parametrize(
    "extra, message",
    [
        (["--action-noise", "-1"], "--action-noise: action_noise must be in [0, 1]"),
        (["--action-noise", "nan"], "--action-noise: action_noise must be in [0, 1]"),
        (["--policy", str(POLICY), "--expert-mix", "1.5"], "--expert-mix: expert_mix must be in [0, 1]"),
        (["--policy", str(POLICY), "--expert-mix", "-0.1"], "--expert-mix: expert_mix must be in [0, 1]"),
        (["--max-episode-steps", "0"], "max_episode_steps must be in [1, "),
        (["--hand-start-noise", "-1"], "hand_start_noise must be in [0, "),
        (["--policy", str(POLICY), "--image-size", "128"], "the policy reads 64px images, the env makes 128px"),
    ],
)
def test_collect_values_are_checked_before_anything_loads(tmp_path, capsys, monkeypatch, extra, message):
    from hf_specvla.cli import collect

    monkeypatch.setattr(collect, "load_policy", lambda *a, **k: pytest.fail("the policy was loaded"))
    err = _usage_error(["collect", "--tasks", "reach", "--output-dir", str(tmp_path / "d"), *extra], capsys)
    assert message in err
    assert not (tmp_path / "d").exists()


def test_collect_refuses_a_dataset_of_other_settings_as_a_usage_error(tmp_path, capsys):
    from hf_specvla.metaworld.demonstrations import check_dataset_folder
    from hf_specvla.metaworld.env import EnvConfig

    (tmp_path / "d" / "meta").mkdir(parents=True)
    info = {"format": "hf_specvla.metaworld.demonstrations", "image_size": 32, "camera": "corner", "action_dim": 4}
    (tmp_path / "d" / "meta" / "info.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match="holds a dataset with"):
        check_dataset_folder(tmp_path / "d", EnvConfig())
    err = _usage_error(["collect", "--tasks", "reach", "--output-dir", str(tmp_path / "d")], capsys)
    assert f"--output-dir: {tmp_path / 'd'} holds a dataset with" in err
    assert sorted(p.name for p in (tmp_path / "d").rglob("*")) == ["info.json", "meta"]


# ----------------------------------------------------------------------------- eval: tolerances and presets
def test_eval_refuses_tolerances_that_do_not_fit_the_action_before_the_folder_is_claimed(tmp_path, capsys):
    """Regression: --bin-tolerance 4 4 4 on 4-dimensional actions wrote run.json and started the environment, then
    failed in generate; the corrected rerun was refused as 'another run'."""
    out = tmp_path / "X"
    err = _usage_error(["eval", "--policy", str(POLICY), "--action-prior", "--bin-tolerance", "4", "4", "4",
                        "--output-dir", str(out)], capsys)  # fmt: skip
    assert "--bin-tolerance 4 4 4 has 3 values, but the policy's actions have 4 dimensions (x y z gripper)" in err
    assert not out.exists()
    err = _usage_error(["eval", "--policy", str(POLICY), "--method", "prior:r=4/4/4", "--output-dir", str(out)], capsys)
    assert "--method: decoding method 'prior:r=4/4/4': r=4/4/4 has 3 values" in err
    err = _usage_error(["eval", "--policy", str(POLICY), "--action-prior", "--bin-tolerance", "999",
                        "--output-dir", str(out)], capsys)  # fmt: skip
    assert "--bin-tolerance 999: r is wider than the action range" in err and "use r in 0..255" in err
    assert not out.exists()


def test_eval_checks_tolerances_from_the_policy_config_before_loading_the_model(tmp_path, capsys, monkeypatch):
    from hf_specvla.cli import eval as eval_command

    monkeypatch.setattr(eval_command, "load_policy", lambda *a, **k: pytest.fail("the model was loaded"))
    argv = ["eval", "--policy", str(POLICY), "--action-prior", "--output-dir", str(tmp_path / "X")]
    assert "has 3 values" in _usage_error(argv + ["--bin-tolerance", "1", "2", "3"], capsys)
    assert "max_episode_steps must be in [1, " in _usage_error(argv + ["--max-episode-steps", "0"], capsys)


def _seven_dimensional_policy(tmp_path) -> Path:
    """A policy folder whose config says 7-dimensional actions (OpenVLA's layout); no weights."""
    folder = tmp_path / "policy7"
    folder.mkdir()
    config = json.loads((POLICY / "policy_config.json").read_text())
    config["action_dim"] = 7
    (folder / "policy_config.json").write_text(json.dumps(config))
    return folder


@pytest.mark.parametrize(
    "method, resolved",
    [("fast", "prior+jacobi:r=4/4/4/0/0/0/0,gate=0.5,confirm=1:compile"), ("exact", "prior+jacobi:compile")],
)
def test_eval_resolves_presets_to_the_policys_layout(tmp_path, method, resolved):
    from hf_specvla.cli.common import read_policy_config
    from hf_specvla.cli.eval import decoding_method

    parser = build_parser()
    args = parser.parse_args(["eval", "--policy", str(_seven_dimensional_policy(tmp_path)), "--method", method,
                              "--output-dir", str(tmp_path / "X")])  # fmt: skip
    action_dim = read_policy_config(args.policy, args.command_parser).action_dim
    assert action_dim == 7
    assert decoding_method(args, args.command_parser, action_dim).name == resolved


def test_eval_on_seven_dimensions_refuses_a_four_value_table(tmp_path, capsys):
    policy = _seven_dimensional_policy(tmp_path)
    argv = ["eval", "--policy", str(policy), "--method", "prior:r=4/4/4/0", "--output-dir", str(tmp_path / "X")]
    err = _usage_error(argv, capsys)
    assert "r=4/4/4/0 has 4 values, but the policy's actions have 7 dimensions (x y z roll pitch yaw gripper)" in err
    assert not (tmp_path / "X").exists()


def test_a_broken_policy_config_is_a_usage_error(tmp_path, capsys):
    folder = tmp_path / "broken"
    folder.mkdir()
    (folder / "policy_config.json").write_text("{not json")
    err = _usage_error(["eval", "--policy", str(folder), "--output-dir", str(tmp_path / "X")], capsys)
    assert f"--policy {folder}: {folder / 'policy_config.json'} is not a policy configuration" in err


@pytest.mark.parametrize(
    "method, message",
    [
        ("prior:r=²", "decoding method 'prior:r=²': bad option 'r=²'"),
        ("prior:r=٣", "decoding method 'prior:r=٣': bad option 'r=٣'"),
        (
            "head:k=-1",
            "decoding method 'head:k=-1': k must be an integer >= 1 (draft-head chain length (head only)), got k=-1",
        ),
        (
            "head:k=0",
            "decoding method 'head:k=0': k must be an integer >= 1 (draft-head chain length (head only)), got k=0",
        ),
    ],
)
def test_eval_method_numbers(tmp_path, capsys, method, message):
    argv = ["eval", "--policy", str(tmp_path / "none"), "--draft-head", str(tmp_path / "none"), "--method", method,
            "--output-dir", str(tmp_path / "X")]  # fmt: skip
    assert f"--method: {message}" in _usage_error(argv, capsys)


# ----------------------------------------------------------------------------- bench-episodes, benchmark
def test_bench_episodes_checks_the_tolerances_before_recording_rollouts(capsys, monkeypatch):
    pytest.importorskip("metaworld")
    from hf_specvla.metaworld import evaluation

    monkeypatch.setattr(evaluation, "record_observations", lambda *a, **k: pytest.fail("rollouts were recorded"))
    err = _usage_error(["bench-episodes", "--policy", str(POLICY), "--tasks", "reach", "--bin-tolerances", "2",
                        "999"], capsys)  # fmt: skip
    assert "--bin-tolerances 2 999: r is wider than the action range" in err and "use r in 0..255" in err


@pytest.mark.parametrize("command", ["benchmark", "bench-episodes"])
def test_toy_timings_check_the_tolerances_first(tmp_path, capsys, monkeypatch, command):
    from hf_specvla.cli import bench_episodes, benchmark

    pipeline = SimpleNamespace(action_tokenizer=SimpleNamespace(n_bins=256))
    for module in (benchmark, bench_episodes):
        monkeypatch.setattr(module, "load_pipeline", lambda *a, **k: pipeline)
    monkeypatch.setattr(benchmark, "time_pipeline", lambda *a, **k: pytest.fail("timing started"))
    err = _usage_error([command, "--pipeline-dir", str(tmp_path), "--bin-tolerances", "256"], capsys)
    assert "--bin-tolerances 256: r is wider than the action range" in err


def test_image_features_for_a_head_before_v3_is_a_usage_error_before_anything_loads(tmp_path, capsys, monkeypatch):
    import hf_specvla.cli.train_draft as train_draft

    monkeypatch.setattr(train_draft, "load_policy", lambda *args: pytest.fail("loaded the policy"))
    argv = ["train-draft", "--policy", str(POLICY), "--head", "v2", "--prefill-image-features",
            "--output-dir", str(tmp_path / "head")]  # fmt: skip
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert "--prefill-image-features is read by a head v3's drafts before the prefill; got --head v2" in (
        capsys.readouterr().err
    )
    assert not (tmp_path / "head").exists()


# ----------------------------------------------------------------------------- issue 76: saved work and numeric flags
def test_collect_refuses_another_commands_folder_and_an_unrecorded_one(tmp_path, capsys):
    """``collect --output-dir <a policy folder>`` once wrote ``data/`` and ``meta/`` beside train-vla's run.json,
    and into any non-empty folder without a record: both are refused now, the folders untouched."""
    policy_run = tmp_path / "policy"
    policy_run.mkdir()
    (policy_run / "run.json").write_text(json.dumps({"command": "train-vla", "settings": {}}))
    (policy_run / "model.safetensors").write_bytes(b"weights")
    unrecorded = tmp_path / "mine"
    unrecorded.mkdir()
    (unrecorded / "notes.txt").write_text("my notes")
    for folder, message in ((policy_run, "holds a run of `hf-specvla train-vla` (run.json), not a dataset"),
                            (unrecorded, "is not empty (notes.txt) and holds no dataset record")):  # fmt: skip
        before = sorted(p.name for p in folder.rglob("*"))
        err = _usage_error(["collect", "--tasks", "reach", "--output-dir", str(folder)], capsys)
        assert f"--output-dir: {folder} {message}" in err
        assert sorted(p.name for p in folder.rglob("*")) == before


def test_collect_image_size_zero_is_refused_not_replaced_by_the_default(tmp_path, capsys):
    """``--image-size 0`` once collected 64-pixel images (0 read as "not given")."""
    err = _usage_error(["collect", "--tasks", "reach", "--image-size", "0", "--output-dir", str(tmp_path / "d")],
                       capsys)  # fmt: skip
    assert "image_size must be in [16, 512] pixels, got 0" in err
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--feature-loss-weight", "0", "--token-loss-weight", "0"],
         "feature_loss_weight and token_loss_weight are both 0"),
        (["--num-draft-tokens", "100"],
         "--head v1 --num-draft-tokens 100 for a policy of 4 tokens a call: num_draft_tokens=100: a call generates 4 "
         "tokens, the first from the prefill, so a chain drafts 1..3 of them"),
        (["--head", "v2", "--unroll-steps", "9"],
         "unroll_steps=9 trains more draft steps than the head's chain of num_draft_tokens=3 drafts: use 1..3"),
        (["--num-draft-tokens", "2", "--unroll-steps", "3"], "unroll_steps=3 trains more draft steps than"),
        (["--head", "v3", "--unroll-steps", "2"], "a head v3 drafts blocks of num_draft_tokens=3 tokens"),
        (["--demo-frames-per-task", "10"], "--demo-frames-per-task samples frames of the --data folders: give --data"),
        (["--token-loss-weight", "inf"], "token_loss_weight must be a finite number >= 0, got inf"),
        (["--learning-rate", "inf"], "learning_rate must be a finite number > 0, got inf"),
    ],
)  # fmt: skip
def test_train_draft_numbers_are_checked_before_anything_loads(tmp_path, capsys, monkeypatch, extra, message):
    """Each was accepted silently (an untrained head saved with exit 0, a chain longer than the action) or failed
    with a traceback after the rollouts."""
    import hf_specvla.cli.train_draft as train_draft

    monkeypatch.setattr(train_draft, "load_policy", lambda *args: pytest.fail("loaded the policy"))
    err = _usage_error(["train-draft", "--policy", str(POLICY), "--output-dir", str(tmp_path / "head"), *extra],
                       capsys)  # fmt: skip
    assert message in err
    assert not (tmp_path / "head").exists()


@pytest.mark.parametrize("head, unroll", [("v1", 1), ("v2", 3), ("v3", 3), ("v3", None)])
def test_train_draft_defaults_are_valid_for_every_head(tmp_path, monkeypatch, head, unroll):
    """``--head v3`` without ``--unroll-steps`` was a traceback (``got unroll_steps=1``): each head's default depth
    is now the one its training takes (v1: 1; v2 and v3: the chain, tokens per call - 1), as the trainer receives it."""
    import hf_specvla.training.policy_draft as policy_draft

    received = {}

    def train(policy, training_config, data_config, demonstrations, num_draft_tokens, **kwargs):
        received.update(unroll=training_config.unroll_steps, chain=num_draft_tokens, head=kwargs["head_version"])
        return SimpleNamespace(num_parameters=lambda: 0)

    monkeypatch.setattr(policy_draft, "train_policy_draft_head", train)
    argv = ["train-draft", "--policy", str(POLICY), "--head", head, "--output-dir", str(tmp_path / "head")]
    assert main(argv + (["--unroll-steps", str(unroll)] if unroll and head != "v1" else [])) == 0
    assert received == {"unroll": unroll or 3, "chain": None, "head": head}


def _damaged_copy(source: Path, folder: Path) -> Path:
    """A copy of a saved model folder whose model.safetensors is cut in half (an interrupted copy)."""
    import shutil

    shutil.copytree(source, folder)
    weights = folder / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 2])
    return folder


def test_damaged_weights_are_one_line_naming_the_file(tmp_path, capsys):
    """A truncated model.safetensors (policy or head) ended in two chained tracebacks in serve, eval and compare (the
    server binds its port first: 0, any free one)."""
    policy = _damaged_copy(POLICY, tmp_path / "policy")
    head = _damaged_copy(POLICY.parent / "mt10_vla3_draft_v2", tmp_path / "head")
    good_v3 = str(POLICY.parent / "mt10_vla3")
    cases = [
        (["eval", "--policy", str(policy), "--tasks", "reach", "--output-dir", str(tmp_path / "e")],
         "--policy", policy),
        (["compare", "--policy", str(policy), "--methods", "greedy", "prior", "--tasks", "reach",
          "--output-dir", str(tmp_path / "c")], "--policy", policy),
        (["compare", "--policy", good_v3, "--methods", "greedy", "head", "--draft-head", str(head), "--tasks", "reach",
          "--output-dir", str(tmp_path / "ch")], "--draft-head", head),
        (["serve", "--policy", str(policy), "--method", "prior+jacobi", "--port", "0"], "--policy", policy),
        (["serve", "--policy", good_v3, "--method", "prior+tree", "--draft-head", str(head), "--port", "0"],
         "--draft-head", head),
        (["eval", "--policy", good_v3, "--method", "head", "--draft-head", str(head), "--tasks", "reach",
          "--output-dir", str(tmp_path / "h")], "--draft-head", head),
    ]  # fmt: skip
    for argv, flag, folder in cases:
        err = _usage_error(argv, capsys)
        line = next(line for line in err.splitlines() if "error: " in line)
        assert f"{flag}: could not read the " in line and f"'{folder / 'model.safetensors'}'" in line, err
        assert "damaged or truncated" in line and "The above exception" not in err


def test_eval_video_under_a_file_is_refused_before_the_first_episode(tmp_path, afile, capsys, monkeypatch):
    """``eval --video <a file>/x.gif`` ran the episode, then failed with "[Errno 17] File exists"."""
    from hf_specvla.cli import eval as eval_command

    monkeypatch.setattr(eval_command, "load_policy", lambda *a, **k: pytest.fail("the policy was loaded"))
    argv = ["eval", "--policy", str(POLICY), "--tasks", "reach", "--output-dir", str(tmp_path / "e")]
    err = _usage_error(argv + ["--video", str(afile / "x.gif")], capsys)
    assert f"--video: video '{afile / 'x.gif'}': {afile} is a file, so no folder can be made under it" in err
    err = _usage_error(argv + ["--video", str(tmp_path)], capsys)
    assert "the extension must be one of" in err
    (tmp_path / "v.gif").mkdir()
    assert "is a folder; give a file path" in _usage_error(argv + ["--video", str(tmp_path / "v.gif")], capsys)
    assert not (tmp_path / "e").exists()
