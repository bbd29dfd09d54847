"""The README's examples cannot rot: its Python example runs as written, every ``hf-specvla`` command of the README
and of the getting-started page parses with today's flags, and the comparison it shows runs on the smallest
arguments (one task, one seed, a few steps). The two setup commands are the tox commands CI runs
(tests/speculative/test_transformers_compat.py)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from hf_specvla.cli.main import build_parser

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", ROOT / "docs" / "index.md"]


def _blocks(page: Path, language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", page.read_text(), flags=re.S)


def _commands(page: Path) -> list[list[str]]:
    """Every ``hf-specvla`` command of the page's bash blocks, continuation lines joined, comments dropped."""
    commands = []
    for block in _blocks(page, "bash"):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split("  #")[0].strip()
            if line.startswith("hf-specvla "):
                commands.append(line.split()[1:])
    return commands


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_command_parses_with_todays_flags(page):
    commands = _commands(page)
    assert commands, f"{page.name} shows no hf-specvla command"
    parser = build_parser()
    for words in commands:
        parser.parse_args(words)  # a renamed or removed flag exits 2 here


def test_the_readme_is_a_short_page_with_its_parts():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 120
    for part in ("## Two commands", "python3 -m tox -e demo", "```python", "## Measured", "../shared", "docs/results"):
        assert part in readme, part


def _small(words: list[str], output_dir: Path) -> list[str]:
    """An ``eval`` / ``compare`` command of the pages on the smallest arguments that exercise it: its own policy,
    method(s) and seeds, one task, one episode of a few steps, a fresh folder."""
    args = build_parser().parse_args(words)
    small = [words[0], "--policy", args.policy, "--tasks", "reach-v3", "--episodes", "1", "--max-episode-steps", "6",
             "--output-dir", str(output_dir)]  # fmt: skip
    if words[0] == "compare":
        small += ["--seed-start", str(args.seed_start), "--methods", *args.methods]
    elif args.method:
        small += ["--method", args.method]
    return small


@pytest.mark.slow  # a minute each: the policy compiles its graphs
@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_the_python_example_runs_as_written(page, tmp_path):
    (example,) = _blocks(page, "python")
    if any(_blocks(other, "python") == [example] for other in PAGES[: PAGES.index(page)]):
        pytest.skip(f"{page.name}'s example is an earlier page's, run there as written")
    script = tmp_path / "example.py"
    script.write_text(example)
    result = subprocess.run([sys.executable, str(script)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]


@pytest.mark.slow  # a minute each: one short episode per method, compiled methods compile first
@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_eval_and_compare_run_on_the_smallest_arguments(page, tmp_path):
    commands = [words for words in _commands(page) if words[0] in ("eval", "compare")]
    assert commands
    # a compare whose policy and methods a page before this one runs is not run twice (at the smallest arguments
    # only its seed would differ)
    before = [words for other in PAGES[: PAGES.index(page)] for words in _commands(other) if words[0] == "compare"]
    commands = [words for words in commands if not any(_runs_the_same(words, other) for other in before)]
    for n, words in enumerate(commands):
        small = _small(words, tmp_path / f"run{n}")
        result = subprocess.run([sys.executable, "-m", "hf_specvla.cli", *small], cwd=ROOT, capture_output=True,
                                text=True, timeout=900)  # fmt: skip
        assert result.returncode == 0, (small, result.stderr[-3000:])


def _runs_the_same(words: list[str], other: list[str]) -> bool:
    """Whether ``compare`` command ``words`` runs nothing the ``compare`` command ``other`` does not: the same policy,
    a subset of its methods."""
    if words[0] != "compare":
        return False
    parser = build_parser()
    mine, theirs = parser.parse_args(words), parser.parse_args(other)
    return mine.policy == theirs.policy and set(mine.methods) <= set(theirs.methods)


def test_a_compare_that_another_page_runs_is_run_once():
    folder = ["--output-dir", "runs/x"]
    same = ["compare", "--policy", "p", *folder, "--methods", "greedy", "exact"]
    assert _runs_the_same(same, same + ["fast"]) and not _runs_the_same(same + ["fast"], same)
    assert not _runs_the_same(["eval", "--policy", "p", *folder, "--method", "exact"], same)
    assert not _runs_the_same(same, ["compare", "--policy", "q", *folder, "--methods", "greedy", "exact"])
