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


def test_toy_head_per_backbone_script_trains_a_head_on_a_non_llama_family(tmp_path):
    output = tmp_path / "heads"
    result = subprocess.run(
        [sys.executable, str(ROOT / "examples/backbones/toy_head_per_backbone.py"), "--tiny", "--families", "gemma2",
         "--output-dir", str(output), "--threads", "1"],
        capture_output=True, text=True, timeout=600, check=True,
    )  # fmt: skip
    assert "| family | target accuracy |" in result.stdout
    (row,) = json.loads((output / "results.json").read_text())["rows"]
    assert row["family"] == "gemma2" and row["equal_to_greedy"] is True  # r=0 decodes as greedy on Gemma-2
    assert (output / "gemma2" / "config.json").exists()  # the trained head was saved


def test_toy_head_per_backbone_script_refuses_an_unknown_family(tmp_path):
    result = subprocess.run(
        [sys.executable, str(ROOT / "examples/backbones/toy_head_per_backbone.py"), "--families", "lama",
         "--output-dir", str(tmp_path / "x")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert result.returncode == 2 and "unknown model_type(s) ['lama']" in result.stderr
    assert not (tmp_path / "x").exists()  # refused before any folder was written


def test_compile_strategies_script_times_every_strategy_at_every_width(tmp_path):
    output = tmp_path / "strategies.json"
    result = subprocess.run(
        [sys.executable, str(ROOT / "examples/benchmarks/compile_strategies.py"), "--tiny", "--backend", "eager",
         "--repeats", "2", "--output", str(output)],
        capture_output=True, text=True, timeout=300, check=True,
    )  # fmt: skip
    assert "| width (pending + nodes) | eager | regional | whole model |" in result.stdout
    figures = json.loads(output.read_text())
    assert figures["layers"] == 2 and len(figures["rows"]) == 4
    for row in figures["rows"]:
        assert all(math.isfinite(row[s]) and row[s] > 0 for s in ("eager", "regional", "whole")), row
