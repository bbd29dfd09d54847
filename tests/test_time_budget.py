"""A test's verdict never depends on the machine's speed: a fast-tier test over the tier's time target is listed at
the end of the run, not failed; only a budget that CI sets (``HF_SPECVLA_TEST_BUDGET_S``, in ``.ci/run``) fails it."""

from __future__ import annotations

import os
from pathlib import Path

pytest_plugins = ["pytester"]

ROOT = Path(__file__).resolve().parents[1]
SLEEPY = "import time\n\ndef test_sleepy():\n    time.sleep(0.6)\n\ndef test_quick():\n    pass\n"


def test_a_slow_fast_tier_test_is_listed_not_failed_unless_a_budget_is_set(pytester, monkeypatch):
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("HF_SPECVLA_TEST_TARGET_S", "0.3")  # the tier's target, shrunk: a 0.6 s test is over it
    monkeypatch.delenv("HF_SPECVLA_TEST_BUDGET_S", raising=False)
    pytester.makeconftest("from tests.conftest import pytest_addoption, pytest_runtest_makereport, "
                          "pytest_terminal_summary")  # fmt: skip
    pytester.makepyfile(test_sleepy=SLEEPY)
    listed = pytester.runpytest_subprocess("-p", "no:xdist", "-p", "no:cacheprovider")
    listed.assert_outcomes(passed=2)
    listed.stdout.fnmatch_lines(
        ["*fast-tier tests over its 0.3 s target (not failed)*", "*s  test_sleepy.py::test_sleepy (call)"]
    )
    assert "test_quick" not in listed.stdout.str().split("target (not failed)")[1]
    monkeypatch.setenv("HF_SPECVLA_TEST_BUDGET_S", "0.4")  # CI's budget: over it fails, naming the test
    failed = pytester.runpytest_subprocess("-p", "no:xdist", "-p", "no:cacheprovider")
    failed.assert_outcomes(passed=1, failed=1)
    failed.stdout.fnmatch_lines(["*test_sleepy*its call took 1 s, over the fast tier's 0.4 s a test*"])


def test_ci_sets_the_budget_and_tox_passes_it_on():
    assert "export HF_SPECVLA_TEST_BUDGET_S=" in (ROOT / ".ci" / "run").read_text()
    assert "pass_env = HF_SPECVLA_TEST_BUDGET_S" in (ROOT / "tox.ini").read_text()
