"""kill -9 at a random point, then the documented rerun: the same result as an uninterrupted run, never a mixed
folder (reliability issue). CI-sized: a tiny policy, 2-3 step episodes."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

pytest.importorskip("metaworld")

CLI = [sys.executable, "-m", "hf_specvla.cli"]


def run_until(argv: list[str], ready, timeout: float = 120.0) -> None:
    """Starts the CLI, waits until ``ready()`` is true, then kills it with SIGKILL (no cleanup of any kind)."""
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    process = subprocess.Popen([*CLI, *argv], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + timeout
    try:
        while not ready():
            if process.poll() is not None:
                pytest.fail(f"{argv[0]} ended (exit {process.returncode}) before the kill point")
            if time.monotonic() > deadline:
                pytest.fail(f"{argv[0]} did not reach the kill point in {timeout} s")
            time.sleep(0.05)
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait()


def run(argv: list[str]) -> None:
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    subprocess.run([*CLI, *argv], env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


@pytest.fixture(scope="module")
def policy_dir(tmp_path_factory):
    from hf_specvla import ActionNormalizer
    from hf_specvla.policies import VLAPolicy, VLAPolicyConfig

    config = VLAPolicyConfig(image_size=32, patch_size=16, vision_hidden_size=32, vision_layers=1,
                             text_hidden_size=64, text_layers=2, text_heads=4)  # fmt: skip
    policy = VLAPolicy.build(["reach the goal"], ActionNormalizer([-1.0] * 4, [1.0] * 4),
                             ActionNormalizer([-0.5, 0.3, 0.0, 0.0], [0.5, 1.0, 0.4, 1.0]), config, seed=5)  # fmt: skip
    folder = tmp_path_factory.mktemp("policy")
    policy.save_pretrained(folder)
    return folder


def episodes(folder):
    """The episode records without their wall times (which differ from run to run)."""
    lines = (folder / "episodes.jsonl").read_text().splitlines()
    return [{k: v for k, v in json.loads(line).items() if k != "latencies_ms"} for line in lines]


def test_eval_killed_mid_run_then_rerun_equals_an_uninterrupted_run(tmp_path, policy_dir):
    argv = ["eval", "--policy", str(policy_dir), "--tasks", "reach", "--episodes", "4", "--max-episode-steps", "3",
            "--threads", "1"]  # fmt: skip
    killed, straight = tmp_path / "killed", tmp_path / "straight"
    log = killed / "episodes.jsonl"
    run_until([*argv, "--output-dir", str(killed)], lambda: log.exists() and len(log.read_text().splitlines()) >= 1)
    assert 1 <= len(episodes(killed)) < 4
    run([*argv, "--output-dir", str(killed)])  # the documented rerun: the same command
    run([*argv, "--output-dir", str(straight)])
    assert episodes(killed) == episodes(straight)
    assert sorted(p.name for p in killed.iterdir()) == [".lock", "episodes.jsonl", "run.json", "summary.json"]
    assert (killed / ".lock").read_text() == ""  # the rerun released it; the killed run's holder is gone


def test_train_vla_killed_after_a_checkpoint_then_resumed_equals_an_uninterrupted_run(tmp_path):
    from safetensors.torch import load_file

    from hf_specvla.metaworld.demonstrations import collect_demonstrations
    from hf_specvla.metaworld.env import EnvConfig

    data = tmp_path / "demos"
    collect_demonstrations(data, "reach", 4, EnvConfig(image_size=32, max_episode_steps=150), progress=False)
    argv = ["train-vla", "--data", str(data), "--max-steps", "6", "--batch-size", "8", "--save-every", "2",
            "--eval-every", "100", "--threads", "1"]  # fmt: skip
    killed, straight = tmp_path / "killed", tmp_path / "straight"
    # killed as soon as the first checkpoint is complete (trainer_state.pt is written last)
    run_until([*argv, "--output-dir", str(killed)], lambda: (killed / "checkpoint-2" / "trainer_state.pt").exists())
    assert not (killed / "model.safetensors").exists()  # the run really was cut before its end
    run([*argv, "--output-dir", str(killed), "--resume"])  # the documented rerun
    run([*argv, "--output-dir", str(straight)])
    resumed_weights, straight_weights = (
        load_file(killed / "model.safetensors"),
        load_file(straight / "model.safetensors"),
    )
    assert resumed_weights.keys() == straight_weights.keys()
    for name, tensor in resumed_weights.items():
        assert bool((tensor == straight_weights[name]).all()), name  # bit-identical on CPU
    log = [json.loads(line)["step"] for line in (killed / "training_log.jsonl").read_text().splitlines()]
    assert log == sorted(set(log)) and log[-1] == 6  # one run's log, no step twice


def test_collect_killed_mid_run_then_rerun_equals_an_uninterrupted_run(tmp_path):
    import numpy as np

    from hf_specvla.metaworld.demonstrations import load_demonstrations

    argv = ["collect", "--tasks", "reach", "--episodes", "3", "--image-size", "32", "--max-episode-steps", "150"]
    killed, straight = tmp_path / "killed", tmp_path / "straight"
    run_until([*argv, "--output-dir", str(killed)], lambda: len(list(killed.glob("**/*.parquet"))) >= 1)
    run([*argv, "--output-dir", str(killed)])  # the documented rerun: the same command
    run([*argv, "--output-dir", str(straight)])
    a, b = load_demonstrations(killed, progress=False), load_demonstrations(straight, progress=False)
    assert a.tasks == b.tasks
    for field in ("images", "states", "actions", "episode_index"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)


def test_compare_killed_mid_run_then_rerun_equals_an_uninterrupted_run(tmp_path, policy_dir):
    """Two workers: the kill takes the main process, its workers end with it (no orphan appends to the folder),
    the stale lock is taken over, and the rerun runs only the missing (seed, method) episodes."""

    def records(folder):
        logs = sorted(folder.glob("episodes.worker-*.jsonl"))
        rows = [json.loads(line) for path in logs for line in path.read_text().splitlines()]
        return sorted(({k: v for k, v in r.items() if k != "latencies_ms"} for r in rows),
                      key=lambda r: (r["seed"], r["method"]))  # fmt: skip

    argv = ["compare", "--policy", str(policy_dir), "--tasks", "reach", "--episodes", "4", "--max-episode-steps",
            "10", "--methods", "prior", "prior:r=4", "--workers", "2"]  # fmt: skip
    total = 4 * 3  # greedy and the two methods
    killed, straight = tmp_path / "killed", tmp_path / "straight"
    run_until([*argv, "--output-dir", str(killed)], lambda: len(records(killed)) >= 2 if killed.exists() else False)
    time.sleep(3)  # the workers notice their parent is gone within a second
    frozen = records(killed)
    time.sleep(1.5)
    assert records(killed) == frozen and 2 <= len(frozen) < total  # nothing appended after the kill
    run([*argv, "--output-dir", str(killed)])  # the documented rerun: the same command
    run([*argv, "--output-dir", str(straight)])
    assert len(records(killed)) == total  # 4 seeds x 3 methods, none twice
    assert records(killed) == records(straight)
