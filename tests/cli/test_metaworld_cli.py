"""Smoke runs of the Meta-World commands, sized for CI: collect -> train-vla -> eval, and resume."""

import json

import pytest

pytest.importorskip("metaworld")

from hf_specvla.cli import main  # noqa: E402
from hf_specvla.metaworld.demonstrations import load_demonstrations  # noqa: E402


@pytest.mark.commands  # ~30 s: collect, train-vla and eval end to end
def test_collect_train_eval(tmp_path, capsys):
    data, noisy, policy, results = tmp_path / "demos", tmp_path / "noisy", tmp_path / "policy", tmp_path / "eval"
    assert (
        main(["collect", "--tasks", "reach", "--episodes", "2", "--output-dir", str(data), "--image-size", "32",
              "--camera", "workspace", "--hand-start-noise", "0.05"]) == 0
    )  # fmt: skip
    assert json.loads((data / "meta" / "info.json").read_text())["hand_start_noise"] == 0.05
    assert main(["collect", "--tasks", "reach", "--episodes", "1", "--output-dir", str(noisy), "--image-size", "32",
                 "--action-noise", "0.3", "--seed-start", "1000", "--camera", "workspace"]) == 0  # fmt: skip
    args = ["train-vla", "--data", str(data), str(noisy), "--output-dir", str(policy), "--max-steps", "3",
            "--batch-size", "8", "--eval-every", "2", "--save-every", "2", "--patch-size", "8"]  # fmt: skip
    assert main(args) == 0
    assert (policy / "policy_config.json").exists() and (policy / "checkpoint-2" / "policy" / "config.json").exists()
    saved_config = json.loads((policy / "policy_config.json").read_text())
    assert saved_config["patch_size"] == 8 and saved_config["camera"] == "workspace"  # evaluation renders from it
    with pytest.raises(SystemExit) as exit_info:  # a usage error, before the data is loaded
        main(args)
    assert exit_info.value.code == 2 and "pass --resume" in capsys.readouterr().err
    with pytest.raises(ValueError, match="patch_size=8"):  # resuming must rebuild the same model
        main([*args[:6], "--max-steps", "4", "--batch-size", "8", "--resume"])
    with pytest.raises(ValueError, match="vision_layers=3"):
        main([*args[:6], "--max-steps", "4", "--batch-size", "8", "--patch-size", "8", "--vision-layers", "2",
              "--resume"])  # fmt: skip
    assert main([*args[:6], "--max-steps", "4", "--batch-size", "8", "--patch-size", "8", "--resume"]) == 0
    log = [json.loads(line) for line in (policy / "training_log.jsonl").read_text().splitlines()]
    assert log[-1]["step"] == 4

    eval_args = ["eval", "--policy", str(policy), "--tasks", "reach", "--episodes", "2", "--max-episode-steps", "5",
                 "--output-dir", str(results), "--video", str(results / "first.gif")]  # fmt: skip
    assert main(eval_args) == 0
    out = capsys.readouterr().out
    assert "| reach-v3 | 2 |" in out
    assert "| median ms/call |" in out and "ms/call: the median wall time of a policy call (one call decides" in out
    summary = json.loads((results / "summary.json").read_text())
    assert summary["tasks"]["reach-v3"]["mean_episode_length"] <= 5
    assert (results / "first.gif").exists()
    # resuming an evaluation reuses the episodes already on disk
    assert main(eval_args) == 0
    assert len((results / "episodes.jsonl").read_text().splitlines()) == 2
    # the action prior at r=0 (lossless): the same episodes as greedy decoding
    prior_args = [*eval_args[:9], "--output-dir", str(tmp_path / "prior"), "--action-prior"]
    assert main(prior_args) == 0
    greedy_lengths = [json.loads(x)["length"] for x in (results / "episodes.jsonl").read_text().splitlines()]
    prior_log = (tmp_path / "prior" / "episodes.jsonl").read_text().splitlines()
    assert [json.loads(x)["length"] for x in prior_log] == greedy_lengths
    # the same method named as compare names it
    assert main([*eval_args[:9], "--output-dir", str(tmp_path / "prior_method"), "--method", "prior"]) == 0
    method_log = (tmp_path / "prior_method" / "episodes.jsonl").read_text().splitlines()
    assert [json.loads(x)["length"] for x in method_log] == greedy_lengths
    with pytest.raises(SystemExit) as exit_info:
        main([*eval_args[:9], "--output-dir", str(tmp_path / "wide_method"), "--method", "prior:r=999"])
    error = capsys.readouterr().err
    assert exit_info.value.code == 2 and "--method prior:r=999: r is wider than the action range" in error
    assert "use r in 0..255" in error and not (tmp_path / "wide_method").exists()
    # r beyond the 256 bins: a usage error before anything is written
    with pytest.raises(SystemExit) as exit_info:
        main([*prior_args[:-3], "--output-dir", str(tmp_path / "wide"), "--action-prior", "--bin-tolerance", "999"])
    error = capsys.readouterr().err
    assert exit_info.value.code == 2 and "--bin-tolerance 999: r is wider than the action range" in error
    assert not (tmp_path / "wide").exists()
    # the episode benchmark on the policy's own recorded rollouts
    bench = [
        "bench-episodes",
        "--policy",
        str(policy),
        "--tasks",
        "reach",
        "--steps",
        "3",
        "--bin-tolerances",
        "0",
        "--no-compile",
    ]
    assert main([*bench, "--chain-length", "2", "--tree-depth", "2", "--tree-total-tokens", "4"]) == 0
    assert "| prior+tree r=0 |" in capsys.readouterr().out
    # a policy only sees the camera it was trained on
    from hf_specvla.metaworld.env import EnvConfig
    from hf_specvla.metaworld.evaluation import evaluate
    from hf_specvla.policies import VLAPolicy

    with pytest.raises(ValueError, match="trained on camera 'workspace', the env renders 'corner'"):
        evaluate(VLAPolicy.from_pretrained(policy), "reach", 1, tmp_path / "e2", EnvConfig(32, "corner"))

    # DAgger: the trained policy drives a collection (its camera and image size by default), the expert labels
    dagger = tmp_path / "dagger"
    assert main(["collect", "--policy", str(policy), "--tasks", "reach", "--episodes", "1", "--expert-mix", "0.5",
                 "--max-episode-steps", "5", "--output-dir", str(dagger)]) == 0  # fmt: skip
    assert "the policy (the expert at 50% of the steps) solved" in capsys.readouterr().out
    info = json.loads((dagger / "meta" / "info.json").read_text())
    assert [info[k] for k in ("camera", "image_size", "policy", "expert_mix")] == ["workspace", 32, str(policy), 0.5]
    assert len(load_demonstrations(dagger, progress=False)) == 5  # the failed episode is kept
    with pytest.raises(SystemExit):  # --expert-mix without a policy to mix with
        main(["collect", "--expert-mix", "0.5", "--output-dir", str(tmp_path / "none")])

    # scene targets: the model also learns the object and goal positions recorded with the data
    scene = tmp_path / "scene"
    scene_args = ["train-vla", "--data", str(data), str(noisy), "--output-dir", str(scene), "--max-steps", "2",
                  "--batch-size", "8", "--eval-every", "2", "--scene-targets",
                  "--scene-loss-weight", "0.25"]  # fmt: skip
    assert main(scene_args) == 0
    assert json.loads((scene / "policy_config.json").read_text())["scene_state_dim"] == 6
    assert json.loads((scene / "training_config.json").read_text())["scene_loss_weight"] == 0.25
    last = json.loads((scene / "training_log.jsonl").read_text().splitlines()[-1])
    assert last["scene_loss"] > 0 and last["val_scene_loss"] > 0
    with pytest.raises(SystemExit):  # a scene loss weight without scene targets to weigh
        main(["train-vla", "--data", str(data), "--output-dir", str(tmp_path / "w"), "--scene-loss-weight", "1"])
    # the scene read where the actions are decoded: reported on validation, kept in checkpoints, not in the policy
    readout = tmp_path / "readout"
    readout_args = [*scene_args[:5], str(readout), *scene_args[6:], "--scene-readout-weight", "0.5",
                    "--save-every", "2"]  # fmt: skip
    assert main(readout_args) == 0
    last = json.loads((readout / "training_log.jsonl").read_text().splitlines()[-1])
    assert last["scene_readout_loss"] > 0 and last["val_scene_readout_goal_m"] > 0
    assert json.loads((readout / "run.json").read_text())["settings"]["scene_readout_weight"] == 0.5
    from safetensors import safe_open

    with safe_open(readout / "model.safetensors", "pt") as weights:
        assert not [name for name in weights.keys() if "readout" in name]  # noqa: SIM118
    readout_args[readout_args.index("--max-steps") + 1] = "3"
    assert main([*readout_args, "--resume"]) == 0  # the readout continues from the checkpoint
    with pytest.raises(SystemExit) as exit_info:  # a readout without scene statistics to read into
        main(["train-vla", "--data", str(data), "--output-dir", str(tmp_path / "r"), "--scene-readout-weight", "1"])
    assert exit_info.value.code == 2 and "--scene-readout-weight needs --scene-targets" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--bin-tolerance", "2"], "--bin-tolerance needs --draft-head and/or --action-prior"),
        (["--draft-tree"], "--draft-tree need --draft-head"),
        (["--draft-head", "d", "--draft-tree", "--num-draft-tokens", "2"], "give one of them"),
        (["--draft-head", "./runs/draft"], "--draft-head: draft head folder './runs/draft' does not exist"),
        (["--method", "priorx"], "--method: unknown decoding method 'priorx'"),
        (["--method", "prior", "--action-prior"], "--method prior already says how to decode; drop --action-prior"),
        (["--method", "tree:r=4"], "--method tree:r=4 drafts with the draft head: give --draft-head"),
    ],
)
def test_eval_speculation_flag_misuse_is_a_usage_error(tmp_path, capsys, flags, message):
    with pytest.raises(SystemExit) as exit_info:
        main(["eval", "--policy", str(tmp_path / "none"), "--output-dir", str(tmp_path / "e"), *flags])
    assert exit_info.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "e").exists()


def test_eval_refuses_missing_policy_and_stray_flags(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["eval", "--policy", str(tmp_path / "none"), "--output-dir", str(tmp_path / "e")])
    assert exit_info.value.code == 2
    assert "--policy: policy folder" in capsys.readouterr().err
    assert not (tmp_path / "e").exists()


def test_train_vla_refuses_a_folder_that_holds_no_demonstrations(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["train-vla", "--data", str(tmp_path / "none"), "--output-dir", str(tmp_path / "policy")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "--data: " in err and "is not a demonstrations folder" in err and "hf-specvla collect" in err
    assert not (tmp_path / "policy").exists()


@pytest.mark.parametrize(
    "argv",
    [
        ["collect", "--tasks", "nosuchtask", "--output-dir", "{out}"],
        ["eval", "--policy", "{policy}", "--tasks", "nosuchtask", "--output-dir", "{out}"],
        ["bench-episodes", "--policy", "{policy}", "--tasks", "nosuchtask"],
        ["train-vla", "--data", "{out}", "--tasks", "nosuchtask", "--output-dir", "{out}"],
    ],
)
def test_an_unknown_task_is_a_usage_error_before_anything_loads(tmp_path, capsys, argv):
    from pathlib import Path

    policy = Path(__file__).resolve().parents[2] / "policies" / "mt10_vla"
    argv = [a.format(out=tmp_path / "out", policy=policy) for a in argv]
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert "--tasks: unknown Meta-World task 'nosuchtask'" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_missing_policy_folder_names_the_flag_that_gave_it(tmp_path, capsys):
    import argparse

    from hf_specvla.cli.common import load_policy

    parser = argparse.ArgumentParser(prog="hf-specvla train-vla")
    with pytest.raises(SystemExit) as exit_info:
        load_policy(str(tmp_path / "none"), parser, "--init-from")
    assert exit_info.value.code == 2
    assert "error: --init-from: policy folder" in capsys.readouterr().err
