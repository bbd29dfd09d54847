"""``hf-specvla --help`` and every command's ``--help`` answer at once: importing the CLI loads no torch (nor
transformers), each command's parser is built from light modules, and the heavy parts load inside ``run``.

Each check runs in a fresh interpreter: in this one, torch is long loaded."""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hf_specvla.cli.main import COMMANDS

#: seconds; the commands take about 0.6 s on 2 busy CPU cores, importing torch alone takes 5-15 s there
HELP_SECONDS = 5.0


def _cli() -> list[str]:
    """The console script beside this interpreter (what a user runs), else ``python -m hf_specvla.cli``."""
    script = shutil.which("hf-specvla", path=str(Path(sys.executable).parent))
    return [script] if script else [sys.executable, "-m", "hf_specvla.cli"]


def test_importing_the_cli_loads_neither_torch_nor_transformers():
    """A command module that needs the engine (or a config class: transformers' load torch) imports it in ``run``."""
    code = "import sys, hf_specvla.cli; print(' '.join(m for m in ('torch', 'transformers') if m in sys.modules))"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.split() == []


@pytest.mark.parametrize("command", [None] + [command.NAME for command in COMMANDS])
def test_help_answers_at_once(command):
    args = [*_cli(), *([command] if command else []), "--help"]
    start = time.perf_counter()
    result = subprocess.run(args, capture_output=True, text=True, timeout=300)
    seconds = time.perf_counter() - start
    assert result.returncode == 0, result.stderr[-2000:]
    assert "examples:" in result.stdout
    assert seconds < HELP_SECONDS, f"{' '.join(args[-2:])} took {seconds:.1f} s"
