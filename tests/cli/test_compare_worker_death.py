"""A compare worker killed with SIGKILL: a logged error naming the worker and its signal, that finished episodes
are saved and that the same command resumes; exit status 1, no traceback; the rerun completes (issue 55)."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from hf_specvla.metaworld.comparison.runner import WorkerDiedError, _describe_dead_worker


def test_the_dead_worker_is_named_with_its_signal():
    # once one worker dies the pool stops the others with SIGTERM: the one that ended otherwise is named
    processes = {11: SimpleNamespace(exitcode=-signal.SIGTERM), 12: SimpleNamespace(exitcode=-signal.SIGKILL)}
    assert _describe_dead_worker(processes) == "a compare worker process (pid 12) died: killed by signal SIGKILL"
    assert "(pid 11) died: killed by signal SIGTERM" in _describe_dead_worker({11: SimpleNamespace(exitcode=-15)})
    assert "(pid 13) died: exit code 3" in _describe_dead_worker({13: SimpleNamespace(exitcode=3)})
    assert "exit status is unknown" in _describe_dead_worker({14: SimpleNamespace(exitcode=None)})


def test_the_cli_logs_a_dead_worker_and_exits_1_without_a_traceback(tmp_path, monkeypatch, capsys):
    from hf_specvla.cli import compare, main
    from hf_specvla.metaworld import comparison
    from hf_specvla.policies.devices import Placement

    def die(*args, **kwargs):
        raise WorkerDiedError("a compare worker process (pid 7) died: killed by signal SIGKILL. The other workers ...")

    monkeypatch.setattr(compare, "load_policy", lambda *a, **k: None)
    monkeypatch.setattr(Placement, "place_policy", lambda *a, **k: None)  # no policy loaded: nothing to place
    monkeypatch.setattr(compare, "read_policy_config", lambda *a, **k: SimpleNamespace(action_dim=4))
    monkeypatch.setattr(comparison, "run_comparison", die)
    argv = ["compare", "--policy", "unused", "--tasks", "reach", "--methods", "prior", "--threads", "1",
            "--output-dir", str(tmp_path / "out")]  # fmt: skip
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "ERROR hf_specvla.cli.compare: a compare worker process (pid 7) died: killed by signal SIGKILL" in err
    assert "Traceback" not in err


# ----------------------------------------------------------------------------- a real kill -9, then the rerun
metaworld = pytest.importorskip("metaworld")
CLI = [sys.executable, "-m", "hf_specvla.cli"]


def worker_pids(pid: int) -> list[int]:
    """The pool workers among ``pid``'s children (Linux /proc; the resource tracker is not one)."""
    children = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        children += [int(c) for c in (task / "children").read_text().split()]
    return [c for c in children if b"spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes()]


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="finds the workers through Linux /proc")
def test_a_killed_worker_ends_the_run_cleanly_and_the_rerun_completes(tmp_path):
    from tests.training.test_policy_draft import build_policy

    policy = build_policy(tmp_path / "policy", seed=0)
    out = tmp_path / "compare"
    argv = [*CLI, "compare", "--policy", str(policy), "--tasks", "reach", "--episodes", "6", "--max-episode-steps",
            "25", "--methods", "prior", "--workers", "2", "--output-dir", str(out)]  # fmt: skip
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    process = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)

    def lines() -> int:
        return sum(len(p.read_text().splitlines()) for p in out.glob("episodes.worker-*.jsonl"))

    try:
        deadline = time.monotonic() + 180
        while not (out.exists() and lines() >= 1):  # a worker has finished an episode
            assert process.poll() is None, f"compare ended (exit {process.returncode}) before the kill point"
            assert time.monotonic() < deadline, "no episode finished in 180 s"
            time.sleep(0.1)
        workers = worker_pids(process.pid)
        assert len(workers) == 2
        os.kill(workers[-1], signal.SIGKILL)
        _, err = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 1 and "Traceback" not in err and "BrokenProcessPool" not in err
    assert f"a compare worker process (pid {workers[-1]}) died: killed by signal SIGKILL" in err
    assert "finished so far are saved in" in err and "rerun the same command to resume" in err
    subprocess.run(argv, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # the rerun
    records = [json.loads(line) for p in out.glob("episodes.worker-*.jsonl") for line in p.read_text().splitlines()]
    assert sorted((r["seed"], r["method"]) for r in records) == sorted(
        (100_000 + i, m) for i in range(6) for m in ("greedy", "prior")
    )  # every episode once
