"""The benchmark scripts run (in their tiny modes: seconds, nothing about speed is asserted)."""

import json
import math
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_policy_cost_script_runs_and_reports_every_ratio(tmp_path):
    output = tmp_path / "cost.json"
    result = subprocess.run(
        [sys.executable, str(ROOT / "examples/benchmarks/policy_cost.py"), "--tiny", "--output", str(output)],
        capture_output=True, text=True, timeout=300, check=True,
    )  # fmt: skip
    assert "| decoder | decode step | head step | head / decode |" in result.stdout
    rows = json.loads(output.read_text())["rows"]
    assert [row["decoder"] for row in rows] == ["1x12", "2x12"]
    for row in rows:
        for key in ("decode_ms", "head_step_over_decode", "drafted_over_prompt", "greedy_call_ms"):
            assert math.isfinite(row[key]), (key, row)


def test_policy_cost_script_refuses_a_bad_decoder_shape():
    result = subprocess.run(
        [sys.executable, str(ROOT / "examples/benchmarks/policy_cost.py"), "--decoders", "12by192"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert result.returncode == 2 and "a decoder is LAYERSxWIDTH, e.g. 12x192, got '12by192'" in result.stderr
