"""`hf-specvla compare` resumed under other timing conditions (threads, workers, machine): refused before anything
loads, naming both; ``--restart-timing`` keeps the finished episodes and times only the new ones (issue 55)."""

import json

import pytest
import torch

pytest.importorskip("metaworld")

from hf_specvla.cli import main  # noqa: E402
from tests.training.test_policy_draft import build_policy  # noqa: E402


@pytest.fixture(scope="module")
def policy_dir(tmp_path_factory):
    return build_policy(tmp_path_factory.mktemp("compare_timing") / "policy", seed=0)


@pytest.fixture(autouse=True)
def keep_torch_threads():
    """The CLI sets torch's threads in this process (--threads): give the next test what it had."""
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def command(policy_dir, out, episodes: int, *flags: str) -> list[str]:
    return ["compare", "--policy", str(policy_dir), "--tasks", "reach", "--episodes", str(episodes),
            "--max-episode-steps", "3", "--methods", "prior", "--output-dir", str(out), *flags]  # fmt: skip


def log_records(out) -> list[dict]:
    return [json.loads(line) for line in (out / "episodes.worker-0.jsonl").read_text().splitlines()]


def refusal(capsys, monkeypatch, argv) -> str:
    """The usage error ``argv`` ends with, checked to come before the policy loads."""
    from hf_specvla.cli import compare

    capsys.readouterr()
    with monkeypatch.context() as patch:
        patch.setattr(compare, "load_policy", lambda *a, **k: pytest.fail("the policy loaded before the refusal"))
        with pytest.raises(SystemExit) as exit_info:
            main(argv)
    assert exit_info.value.code == 2
    return capsys.readouterr().err


def test_a_resume_under_other_threads_or_workers_is_refused_unless_the_timing_restarts(
    policy_dir, tmp_path, capsys, monkeypatch
):
    out = tmp_path / "compare"
    assert main(command(policy_dir, out, 2, "--threads", "1")) == 0
    first = log_records(out)
    assert len(first) == 4 and all(r["timing"]["threads"] == 1 and r["timing"]["workers"] == 1 for r in first)
    assert json.loads((out / "timing.json").read_text())["conditions"] == first[0]["timing"]
    assert main(command(policy_dir, out, 2, "--threads", "1")) == 0  # the same conditions continue

    # other threads, other workers: usage errors naming both conditions, before anything loads or runs
    error = refusal(capsys, monkeypatch, command(policy_dir, out, 3, "--threads", "2"))
    assert "holds episodes timed under other conditions (threads: 2 here vs 1 there" in error
    assert "recorded workers=1, threads=1, torch_threads=1 on " in error
    assert "this run workers=1, threads=2, torch_threads=2 (the same machine)" in error and "--restart-timing" in error
    error = refusal(capsys, monkeypatch, command(policy_dir, out, 3, "--workers", "2"))
    assert "workers: 2 here vs 1 there" in error and "this run workers=2, threads=1" in error
    assert "Traceback" not in error and len(log_records(out)) == 4  # nothing ran

    # --restart-timing: the finished episodes are kept, only the episodes timed under 2 threads enter speed
    assert main(command(policy_dir, out, 3, "--threads", "2", "--restart-timing")) == 0
    records = log_records(out)
    assert records[:4] == first and [r["timing"]["threads"] for r in records[4:]] == [2, 2]
    summary = json.loads((out / "summary.json").read_text())
    row = summary["methods"]["prior"]
    assert row["episodes"] == 3 and row["vs_greedy"]["pairs"] == 3  # success: every episode
    assert row["timed_episodes"] == 1 and row["speedup_total"]["pairs"] == 1  # speed: the new seed only
    assert set(summary["per_call_ms"]["prior"]) == set(summary["per_call_ms"]["greedy"]) == {"reach-v3:100002"}
    new = {r["method"]: r["latencies_ms"] for r in records[4:]}
    expected = (sum(new["greedy"]) / len(new["greedy"])) / (sum(new["prior"]) / len(new["prior"]))
    assert row["speedup_total"]["speedup"] == pytest.approx(expected)
    assert summary["timing"]["conditions"]["threads"] == 2
    assert (summary["timing"]["episodes_timed"], summary["timing"]["episodes_timed_otherwise"]) == (2, 4)
    assert "2 episodes; 4 timed otherwise are left out of the speed columns" in (out / "compare.md").read_text()
    # the folder is now timed under 2 threads: they continue without the flag, 1 thread is refused
    assert main(command(policy_dir, out, 3, "--threads", "2")) == 0
    assert "threads: 1 here vs 2 there" in refusal(capsys, monkeypatch, command(policy_dir, out, 3, "--threads", "1"))


def test_a_folder_from_before_timing_conditions_resumes(policy_dir, tmp_path, capsys, monkeypatch):
    """Records without conditions are taken as timed under the first continuing run's (with a warning) when the
    folder's summary names the same workers and threads; other threads are refused, naming the summary's."""
    out = tmp_path / "old"
    assert main(command(policy_dir, out, 1, "--threads", "1")) == 0
    log = out / "episodes.worker-0.jsonl"  # as an older hf_specvla wrote it: no timing anywhere
    log.write_text("".join(json.dumps({k: v for k, v in r.items() if k != "timing"}) + "\n" for r in log_records(out)))
    (out / "timing.json").unlink()
    error = refusal(capsys, monkeypatch, command(policy_dir, out, 1, "--threads", "2"))
    assert "threads: 2 here vs 1 there" in error and "recorded workers=1, threads=1;" in error
    assert main(command(policy_dir, out, 1, "--threads", "1")) == 0
    assert "2 records were written before timing conditions were recorded" in capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["methods"]["prior"]["speedup_total"]["pairs"] == 1  # adopted: their timings count
    assert json.loads((out / "timing.json").read_text())["untimed_conditions"]["threads"] == 1
