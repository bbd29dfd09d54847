"""The CI helper scripts (.ci/): tox's ``openvla`` env skips, saying why and exiting 0, where the OpenVLA reference is
absent (the README's test command on a fresh clone), and runs the fixture builder then the tests where it is."""

from __future__ import annotations

import configparser
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / ".ci" / "with_openvla_reference.py"


def _run(tmp_path: Path, reference: Path, *command: str, **env: str) -> subprocess.CompletedProcess:
    environment = {k: v for k, v in os.environ.items() if k != "OPENVLA_REFERENCE_REQUIRED"} | env
    return subprocess.run([sys.executable, str(SCRIPT), str(reference), *command], capture_output=True, text=True,
                          cwd=tmp_path, env=environment)  # fmt: skip


def _write(tmp_path: Path, builder: str = "echo built > built.txt") -> Path:
    reference = tmp_path / "openvla-reference"
    reference.mkdir()
    (reference / "make_fixture.sh").write_text(builder + "\n")
    return reference


def test_without_the_reference_it_says_it_skipped_and_exits_0(tmp_path):
    touch = [sys.executable, "-c", "open('ran.txt', 'w')"]
    result = _run(tmp_path, tmp_path / "absent", *touch)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(f"openvla: skipped: no OpenVLA reference at {tmp_path / 'absent'}")
    assert "../shared/openvla-reference" in result.stdout and not (tmp_path / "ran.txt").exists()
    # a CI that must run the parity tests can make the absence an error
    result = _run(tmp_path, tmp_path / "absent", *touch, OPENVLA_REFERENCE_REQUIRED="1")
    assert result.returncode == 1 and "OPENVLA_REFERENCE_REQUIRED is set" in result.stderr
    assert not (tmp_path / "ran.txt").exists()


def test_with_the_reference_it_builds_the_fixture_then_runs_the_command(tmp_path):
    reference = _write(tmp_path)
    check = [sys.executable, "-c", "import sys; sys.exit(0 if open('built.txt').read() == 'built\\n' else 3)"]
    result = _run(tmp_path, reference, *check)
    assert result.returncode == 0, result.stdout + result.stderr
    # the command's failure is the script's
    assert _run(tmp_path, reference, sys.executable, "-c", "raise SystemExit(4)").returncode == 4


def test_a_failing_builder_or_a_folder_without_it_fails(tmp_path):
    reference = _write(tmp_path, builder="exit 7")
    touch = [sys.executable, "-c", "open('ran.txt', 'w')"]
    assert _run(tmp_path, reference, *touch).returncode == 7 and not (tmp_path / "ran.txt").exists()
    (reference / "make_fixture.sh").unlink()
    result = _run(tmp_path, reference, *touch)
    assert result.returncode == 1 and "has no make_fixture.sh" in result.stderr
    assert _run(tmp_path, reference).returncode == 2  # no command: the usage


def test_tox_openvla_runs_the_parity_tests_through_the_script():
    parser = configparser.ConfigParser(interpolation=None)
    parser.read(ROOT / "tox.ini")
    commands = parser["testenv:openvla"]["commands"].strip()
    assert commands.startswith("python {tox_root}{/}.ci{/}with_openvla_reference.py")
    assert "shared{/}openvla-reference}" in commands and "pytest tests/openvla/test_openvla_parity.py" in commands
    assert "make_fixture.sh" not in commands  # the script runs it, only where the reference is
