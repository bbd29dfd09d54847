"""The benchmark scripts run (in their tiny modes: seconds, nothing about speed is asserted)."""

import importlib.util
import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


def run_example(script: str, *args, timeout: int = 300, check: bool = True) -> subprocess.CompletedProcess:
    """Runs ``examples/<script>`` with ``args`` in a fresh interpreter; its stdout / stderr captured as text."""
    command = [sys.executable, str(ROOT / "examples" / script), *map(str, args)]
    return subprocess.run(command, capture_output=True, text=True, timeout=timeout, check=check)


def test_policy_cost_script_runs_and_reports_every_ratio(tmp_path):
    output = tmp_path / "cost.json"
    result = run_example("benchmarks/policy_cost.py", "--tiny", "--output", str(output))
    assert "| decoder | head | decode step | head step | head / decode |" in result.stdout
    rows = json.loads(output.read_text())["rows"]
    assert [(row["decoder"], row["head"]) for row in rows] == [("1x12", "v1"), ("1x12", "v2"), ("2x12", "v1"),
                                                               ("2x12", "v2")]  # fmt: skip
    for row in rows:
        for key in ("decode_ms", "head_step_over_decode", "drafted_over_prompt", "features_over_prompt",
                    "greedy_call_ms"):  # fmt: skip
            assert math.isfinite(row[key]), (key, row)


def test_head_bound_script_reports_every_generated_token(tmp_path):
    output = tmp_path / "bound.json"
    result = run_example("benchmarks/head_bound.py", "--tiny", "--output", str(output))
    assert "| head | token | head top-1 | head top-4 | chain from the prefill |" in result.stdout
    (rows,) = json.loads(output.read_text())["heads"].values()
    assert [row["token"] for row in rows] == ["a0.y", "a0.z", "a0.grip", "a1.x", "a1.y", "a1.z", "a1.grip"]
    for row in rows:
        assert all(0 <= row[key] <= 1 for key in ("head_top1", "head_top4", "chain", "target_top1_probability"))
        assert row["head_top1"] <= row["head_top4"]


def test_policy_cost_script_refuses_a_bad_decoder_shape():
    result = run_example("benchmarks/policy_cost.py", "--decoders", "12by192", timeout=120, check=False)
    assert result.returncode == 2 and "a decoder is LAYERSxWIDTH, e.g. 12x192, got '12by192'" in result.stderr


def test_toy_head_per_backbone_script_trains_a_head_on_a_non_llama_family(tmp_path):
    output = tmp_path / "heads"
    result = run_example("backbones/toy_head_per_backbone.py", "--tiny", "--families", "gemma2", "--output-dir",
                         output, "--threads", 1, timeout=600)  # fmt: skip
    assert "| family | target accuracy |" in result.stdout
    (row,) = json.loads((output / "results.json").read_text())["rows"]
    assert row["family"] == "gemma2" and row["equal_to_greedy"] is True  # r=0 decodes as greedy on Gemma-2
    assert (output / "gemma2" / "config.json").exists()  # the trained head was saved


def test_toy_head_per_backbone_script_refuses_an_unknown_family(tmp_path):
    result = run_example("backbones/toy_head_per_backbone.py", "--families", "lama", "--output-dir", tmp_path / "x",
                         timeout=120, check=False)  # fmt: skip
    assert result.returncode == 2 and "unknown model_type(s) ['lama']" in result.stderr
    assert not (tmp_path / "x").exists()  # refused before any folder was written


def test_compile_strategies_script_times_every_strategy_at_every_width(tmp_path):
    output = tmp_path / "strategies.json"
    result = run_example(
        "benchmarks/compile_strategies.py", "--tiny", "--backend", "eager", "--repeats", "2", "--output", str(output)
    )
    assert "| width (pending + nodes) | eager | regional | whole model |" in result.stdout
    figures = json.loads(output.read_text())
    assert figures["layers"] == 2 and len(figures["rows"]) == 4
    for row in figures["rows"]:
        assert all(math.isfinite(row[s]) and row[s] > 0 for s in ("eager", "regional", "whole")), row


def test_attention_cost_script_times_both_attentions_in_both_dtypes(tmp_path):
    pytest.importorskip("metaworld")
    output = tmp_path / "attention.json"
    result = run_example("benchmarks/attention_cost.py", "--tiny", "--output", str(output), timeout=600)
    assert "| dtype | method | sdpa | eager | eager / sdpa |" in result.stdout
    rows = json.loads(output.read_text())["rows"]
    assert [(row["dtype"], row["method"]) for row in rows] == [
        ("float32", "greedy"),
        ("float32", "prior+jacobi"),
        ("bfloat16", "greedy"),
        ("bfloat16", "prior+jacobi"),
    ]
    assert all(math.isfinite(row["eager_over_sdpa"]) for row in rows)


def test_bf16_departures_script_runs_with_and_without_the_option(tmp_path):
    """The script runs end to end, its option reaches the policy (eager attention on, sdpa kept off), and with it on no
    r=0 method departs from bf16 greedy (the invariant itself is tested on a deeper model in
    tests/speculative/test_reduced_precision.py, which fails with the option off)."""
    pytest.importorskip("metaworld")
    from hf_specvla import ActionNormalizer
    from hf_specvla.policies import VLAPolicy, VLAPolicyConfig

    config = VLAPolicyConfig(image_size=32, patch_size=16, vision_hidden_size=32, vision_layers=1,
                             text_hidden_size=64, text_layers=2, text_heads=4)  # fmt: skip
    actions = ActionNormalizer(q01=[-1.0] * 4, q99=[1.0] * 4)
    states = ActionNormalizer(q01=[-0.5, 0.3, 0.0, 0.0], q99=[0.5, 1.0, 0.4, 1.0])
    VLAPolicy.build(["reach the goal"], actions, states, config, seed=3).save_pretrained(tmp_path / "policy")
    for option, attention in (("on", "eager"), ("off", "sdpa")):
        output = tmp_path / f"departures-{option}.json"
        result = run_example("benchmarks/bf16_departures.py", "--policy", tmp_path / "policy", "--tasks", "reach-v3",
                             "--steps", 4, "--methods", "prior", "jacobi", "prior+jacobi", "--exact-reduced-precision",
                             option, "--output", output, timeout=600)  # fmt: skip
        assert f"bfloat16, {attention} attention, 4 calls" in result.stdout
        figures = json.loads(output.read_text())
        assert figures["attn_implementation"] == attention
        assert [row["method"] for row in figures["rows"]] == ["prior", "jacobi", "prior+jacobi"]
        assert all(row["calls"] == 4 for row in figures["rows"])
        if option == "on":
            assert all(row["departed"] == 0 for row in figures["rows"]), figures["rows"]


def test_batch_forward_cost_script_compares_every_width_with_a_greedy_step(tmp_path):
    output = tmp_path / "forward_cost.json"
    result = run_example("benchmarks/batch_forward_cost.py", "--tiny", "--output", str(output))
    assert "| B | new tokens per row | ms | / greedy step (1 token) |" in result.stdout
    rows = json.loads(output.read_text())["rows"]
    assert [(row["batch_size"], row["tokens_per_row"]) for row in rows] == [(1, 1), (1, 3), (4, 1), (4, 3)]
    assert all(row["over_greedy_step"] == 1.0 for row in rows if row["tokens_per_row"] == 1)


def test_batch_forward_cost_script_needs_the_greedy_step():
    result = run_example("benchmarks/batch_forward_cost.py", "--tiny", "--tokens", "3", "5", timeout=120, check=False)
    assert result.returncode == 2 and "--tokens must include 1" in result.stderr


def test_batch_throughput_script_refuses_an_unknown_method_before_loading_anything(tmp_path):
    result = run_example("benchmarks/batch_throughput.py", "--toy", tmp_path / "toy", "--max-drafts-per-row", 2,
                         "--methods", "prior:cap=3", timeout=120, check=False)  # fmt: skip
    assert result.returncode == 2 and "--methods: unknown ['prior:cap=3']" in result.stderr
    assert "prior:cap=2" in result.stderr  # the choices name the capped methods asked for
    assert not (tmp_path / "toy").exists()


@pytest.mark.parametrize("second_view", ["none", "front"])
def test_localization_probe_script_prints_the_error_table(second_view):
    pytest.importorskip("metaworld")
    decoder = ["--decoder-steps", 2] if second_view == "none" else []  # the decoder reads the policy's own view
    result = run_example("metaworld/localization_probe.py", "--policy", ROOT / "policies" / "mt10_vla3", "--tasks",
                         "push", "--scenes", 3, "--validation-scenes", 2, "--steps", 2, "--second-view", second_view,
                         *decoder, timeout=600)  # fmt: skip
    header = "| the policy's scene tokens: object / goal | the training mean: object / goal"
    assert header in result.stdout
    assert ("| the decoder, scene tokens first (2 steps): object / goal |" in result.stdout) == bool(decoder)
    cells = next(line for line in result.stdout.splitlines() if line.startswith("| push-v3 |")).strip("|").split("|")
    assert all(math.isfinite(float(cell)) for cell in cells[1:5])
    own = cells[5].strip()  # the policy learned scene targets on its own (overview) images only
    assert own == "-" if second_view == "front" else all(math.isfinite(float(x)) for x in own.split(" / "))
    assert all(math.isfinite(float(x)) for x in cells[6].split(" / "))  # the training mean's errors
    assert len(cells) == (8 if decoder else 7)
    assert all(math.isfinite(float(x)) for cell in cells[7:] for x in cell.split(" / "))  # the decoder's errors


def test_localization_probe_saves_the_policy_with_its_scene_trained_tower(tmp_path):
    pytest.importorskip("metaworld")
    from hf_specvla.policies import VLAPolicy

    folder = tmp_path / "pretrained"
    run_example("metaworld/localization_probe.py", "--policy", ROOT / "policies" / "mt10_vla3", "--tasks", "push",
                "--scenes", 3, "--validation-scenes", 1, "--steps", 2, "--save-policy", folder,
                timeout=600)  # fmt: skip
    record = json.loads((folder / "scene_pretraining.json").read_text())
    assert record["tasks"] == ["push-v3"] and record["steps"] == 2
    saved, original = VLAPolicy.from_pretrained(folder), VLAPolicy.from_pretrained(ROOT / "policies" / "mt10_vla3")
    towers = [dict(p.model.model.vision_tower.named_parameters()) for p in (saved, original)]
    assert any(not torch.equal(towers[0][name], towers[1][name]) for name in towers[1])  # the tower was trained
    decoders = [dict(p.model.model.language_model.named_parameters()) for p in (saved, original)]
    assert all(torch.equal(decoders[0][name], decoders[1][name]) for name in decoders[1])  # nothing else
    again = run_example("metaworld/localization_probe.py", "--policy", ROOT / "policies" / "mt10_vla3",
                        "--save-policy", folder, timeout=120, check=False)  # fmt: skip
    assert again.returncode == 2 and "is not empty" in again.stderr
    assert json.loads((folder / "scene_pretraining.json").read_text()) == record  # untouched


def test_localization_probe_script_refuses_bad_counts_before_rendering():
    result = run_example("metaworld/localization_probe.py", "--policy", ROOT / "policies" / "mt10_vla3", "--scenes", 1,
                         timeout=120, check=False)  # fmt: skip
    assert result.returncode == 2 and "--scenes >= 2" in result.stderr
    result = run_example("metaworld/localization_probe.py", "--policy", ROOT / "policies" / "mt10_vla3",
                         "--decoder-steps", 5, "--second-view", "front", timeout=120, check=False)  # fmt: skip
    assert result.returncode == 2 and "--decoder-steps trains the policy's decoder on its own view" in result.stderr


def _check_load_rows(rows: list[dict], kinds: tuple[str, ...]) -> None:
    """A row per K (1 and 2) and server; each row's forwards within what its share of speculative requests allows."""
    assert sorted((r["robots"], r["kind"]) for r in rows) == sorted((k, kind) for k in (1, 2) for kind in kinds)
    # a greedy request takes one target forward per token (T, greedy's forwards per request); a speculative one
    # between 1 and T: a server that decoded a fraction f of its R requests speculatively made between R (T - f (T - 1))
    # and R T target forwards (adaptive: f is whatever its calibration and the traffic chose, each request one mode)
    for row in rows:
        assert row["requests"] > 0 and row["actions_per_second"] > 0
        fraction, requests, forwards = row["speculative_fraction"], row["requests"], row["forwards_per_request"]
        speculative = fraction * requests  # the requests decoded speculatively: a count
        assert 0 <= fraction <= 1 and speculative == pytest.approx(round(speculative), abs=1e-9), row
        greedy = next(r for r in rows if r["robots"] == row["robots"] and r["kind"] == "greedy")
        tokens = greedy["forwards_per_request"]
        assert tokens == int(tokens) and tokens > 1
        assert tokens - fraction * (tokens - 1) - 1e-9 <= forwards <= tokens + 1e-9, row
        if row["kind"] in ("always", "greedy"):
            assert fraction == (1.0 if row["kind"] == "always" else 0.0), row
    # every embedded run on fresh servers: no sessions, timings or choices carried over from the runs before
    embedded = [row for row in rows if row["kind"] != "ray"]
    assert sorted(row["server"]["generation"] for row in embedded) == list(range(len(embedded)))
    for choices in [row["server"] for row in embedded] + [
        replica for row in rows if row["kind"] == "ray" for replica in row["server"]["replicas"].values()
    ]:  # what each server (each replica) chose, per bucket: its final mode and its share of speculative batches
        assert set(choices["final_modes"].values()) <= {"speculative", "greedy"} and choices["final_modes"]
        share = choices["speculative_share"]  # None: a Ray replica the router sent no request (K = 1, 2 replicas)
        unserved = all(bucket_share is None for bucket_share in choices["bucket_speculative_share"].values())
        assert (0 <= share <= 1) if share is not None else unserved, choices


def test_serving_load_script_drives_three_servers_and_reports_every_k(tmp_path, request):
    """The load benchmark's tiny mode without Ray: greedy / always / adaptive servers, K = 1 and 2 replayed robots,
    one repeat; every server's actions equal (the script checks it), a row per K and server. Where the Ray test runs
    in the same session (the whole suite, Ray installed) it checks these rows too, and this run is skipped."""
    ray_test = test_serving_load_script_drives_ray_serve_with_two_replicas_beside_the_embedded_servers.__name__
    if importlib.util.find_spec("ray") and any(item.name == ray_test for item in request.session.items):
        pytest.skip(f"{ray_test} drives the same three servers in this session (and Ray Serve beside them)")
    output = tmp_path / "load.json"
    result = run_example("benchmarks/serving_load.py", "--tiny", "--no-ray", "--output", output, timeout=600)
    assert "| K | server | actions/s | vs greedy |" in result.stdout and "ray x" not in result.stdout
    report = json.loads(output.read_text())
    assert report["ray"] is None
    _check_load_rows(report["rows"], ("greedy", "always", "adaptive"))


@pytest.mark.slow
def test_serving_load_script_drives_ray_serve_with_two_replicas_beside_the_embedded_servers(tmp_path):
    """The tiny mode with Ray Serve (a local cluster, 2 replicas x 1 thread; about a minute on 2 cores): a Ray row
    per K, each on a fresh deployment whose every replica reported its calibration and choices; its actions equal
    the embedded servers' (the script checks it)."""
    pytest.importorskip("ray.serve")
    output = tmp_path / "load.json"
    result = run_example("benchmarks/serving_load.py", "--tiny", "--ray-replicas", 2, "--ray-threads", 1, "--output",
                         output, timeout=900)  # fmt: skip
    assert "| 2 | ray x2 |" in result.stdout
    report = json.loads(output.read_text())
    assert report["ray"]["replicas"] == 2 and report["ray"]["app_args"]["num_replicas"] == 2
    assert "speculate_buckets" not in report["ray"]["app_args"]  # adaptive, hf-specvla serve's default
    rows = report["rows"]
    _check_load_rows(rows, ("greedy", "always", "adaptive", "ray"))
    ray_rows = [row["server"] for row in rows if row["kind"] == "ray"]
    assert sorted(server["deployment"] for server in ray_rows) == [1, 2]  # a fresh deployment per run
    for server in ray_rows:
        assert len(server["replicas"]) == 2 and server["deploy_s"] > 0
        assert all(replica["calibration"] for replica in server["replicas"].values())  # each calibrated itself


def test_serving_load_script_refuses_more_ray_cpus_than_the_machine_has():
    too_many = (os.cpu_count() or 1) + 1
    result = run_example("benchmarks/serving_load.py", "--ray-replicas", too_many, "--output", "-", timeout=120,
                         check=False)  # fmt: skip
    assert result.returncode == 2
    assert f"--ray-replicas {too_many} x --ray-threads 1 need {too_many} CPUs" in result.stderr
    assert "or --no-ray" in result.stderr


@pytest.mark.slow
def test_gpu_openvla_benchmark_runs_on_the_cpu(tmp_path):
    """Its CPU mode (a tiny random OpenVLA): every method and batch size reports its forwards and syncs; drafts that
    are all right take one target forward."""
    output = tmp_path / "gpu.json"
    # a budget no CPU run reaches: on a loaded machine the default 420 s skipped the head chain's warm-up (CI, stop 72)
    result = run_example("benchmarks/gpu_openvla.py", "--tiny", "--batch-sizes", "1", "--right-probabilities", "0.5",
                         "1.0", "--budget-s", "3600", "--json", str(output), timeout=1800)  # fmt: skip
    assert "| method | B | ms / call | ms / action | target fwd / call |" in result.stdout
    rows = {row["method"]: row for row in json.loads(output.read_text())["rows"]}
    assert set(rows) == {"greedy", "greedy:compile", "none:compile", "drafts p=0.5", "drafts p=1", "head chain"}
    assert rows["drafts p=1"]["target_forwards_per_call"] == 1 and rows["greedy"]["target_forwards_per_call"] == 7
    assert rows["none:compile"]["target_forwards_per_call"] == 7  # the engine's greedy: one token a forward
    fastest = json.loads(output.read_text())["fastest_greedy"]["1"]
    assert fastest in ("greedy", "greedy:compile", "none:compile")
    assert f"the fastest greedy is {fastest}" in result.stdout
    assert all(row["syncs_per_round"] > 0 and math.isfinite(row["ms_per_forward"]) for row in rows.values())
    report = json.loads(output.read_text())
    assert report["complete"] and report["batches"] == [
        {"batch_size": 1, "rounds_run": 2, "skipped": [], "failed": {}, "drafts_from": "greedy:compile"}]  # fmt: skip
    assert rows["drafts p=0.5"]["warm_up_s"] < rows["drafts p=1"]["warm_up_s"]  # the graphs compiled once, shared
    assert all(row["tokens_unlike_greedy"] == 0 and len(row["samples_ms"]) == 2 for row in rows.values())


@pytest.mark.slow
def test_gpu_openvla_benchmark_keeps_to_its_budget(tmp_path):
    """One-shot safe: with no budget left after the baselines' warm-ups, every other method is skipped and listed,
    the baselines are still timed (a few rounds), and the JSON holds every batch size."""
    output = tmp_path / "gpu.json"
    run_example("benchmarks/gpu_openvla.py", "--tiny", "--batch-sizes", "1", "2", "--right-probabilities", "1.0",
                "--budget-s", "0.01", "--json", str(output), timeout=900)  # fmt: skip
    report = json.loads(output.read_text())
    assert report["complete"] and [b["batch_size"] for b in report["batches"]] == [1, 2]
    assert all(b["skipped"] == ["drafts p=1", "head chain"] and b["rounds_run"] >= 1 for b in report["batches"])
    assert sorted((r["method"], r["batch_size"]) for r in report["rows"]) == [
        ("greedy", 1), ("greedy", 2), ("greedy:compile", 1), ("greedy:compile", 2), ("none:compile", 1),
        ("none:compile", 2)]  # fmt: skip


@pytest.mark.slow
def test_host_overhead_benchmark_small_mode(tmp_path):
    """Its small mode: every method's forwards per call (right drafts one forward, greedy one per token), where a
    speculative call's time goes, and the two comparisons of issue 66's targets."""
    output = tmp_path / "host.json"
    result = run_example("benchmarks/host_overhead.py", "--small", "--json", str(output), timeout=900)
    assert "| method | ms / call | target fwd / call | ms / round |" in result.stdout
    report = json.loads(output.read_text())
    rows = {row["method"]: row for row in report["rows"]}
    assert set(rows) == {"greedy:compile 1", "greedy:compile 2", "greedy:compile 8", "drafts right", "jacobi"}
    forwards = {name: row["target_forwards_per_call"] for name, row in rows.items()}
    assert forwards["greedy:compile 8"] == 8 and forwards["drafts right"] == 1 and 1 < forwards["jacobi"] <= 8
    for name in ("drafts right", "jacobi"):
        parts = rows[name]["parts_ms"]
        assert set(parts) == {"generate_outside_loop", "target_forwards", "drafting", "loop_other"}
        assert parts["target_forwards"] > 0 and all(value >= 0 for value in parts.values())
    summary = report["summary"]
    assert summary["greedy_step_ms"] > 0 and summary["right_drafts_call_over_greedy_2"] > 0


@pytest.mark.slow
def test_compiled_round_benchmark_compares_the_acceptance_in_and_after_the_graph(tmp_path):
    """The tiny mode of the before / after benchmark: both variants of every speculative method timed (their tokens
    checked against greedy's inside the script), and --plain refused without a policy."""
    output = tmp_path / "round.json"
    run_example("benchmarks/compiled_round.py", "--rounds", 3, "--json", str(output), timeout=900)
    rows = {row["method"]: row for row in json.loads(output.read_text())["rows"]}
    assert set(rows) == {"jacobi", "drafts right", "jacobi B=4"}
    assert all(row["ms_in_graph"] > 0 and row["ms_after"] > 0 for row in rows.values())
    refused = run_example("benchmarks/compiled_round.py", "--plain", timeout=120, check=False)
    assert refused.returncode == 2 and "--plain and --call-work need --policy" in refused.stderr


def test_replica_batching_script_compares_serve_batch_with_the_replicas_batcher(tmp_path):
    """Both batchings on the same stand-in decode (rows answered 4 ms apart): the replica's Batcher batches the robots
    waiting (3 robots, bucket 2: batches of 2, the third robot alone or with the next); every row of the table."""
    pytest.importorskip("ray.serve")
    output = tmp_path / "batching.json"
    result = run_example("benchmarks/replica_batching.py", "--robots", 1, 3, "--bucket", 2, "--decode-ms", 20,
                         "--seconds", 1, "--output", output, timeout=120)  # fmt: skip
    assert "| batching | decode | robots (K) | requests | batches | robots a batch |" in result.stdout
    rows = {(row["batching"], row["decode"], row["robots"]): row for row in json.loads(output.read_text())["rows"]}
    assert set(rows) == {
        (b, kind, k)
        for b in ("serve.batch", "Batcher")
        for kind in ("releases the GIL", "holds the GIL")
        for k in (1, 3)
    }
    for (batching, _, robots), row in rows.items():
        assert row["batches"] > 5 and row["requests"] >= row["batches"]
        if batching == "Batcher":
            assert row["robots_a_batch"] == 1.0 if robots == 1 else 1.3 <= row["robots_a_batch"] <= 2.0, row


@pytest.mark.slow
def test_session_path_benchmark_tiny_mode(tmp_path):
    """Its tiny mode: every path decodes the same calls as greedy, greedy through the engine one forward a token,
    ``exact`` fewer; an existing --json is refused before anything runs."""
    output = tmp_path / "session.json"
    result = run_example("benchmarks/session_path.py", "--tiny", "--json", str(output), timeout=600)
    assert "| path | calls | ms a call (median) | vs greedy:compile (total) |" in result.stdout
    rows = {row["path"]: row for row in json.loads(output.read_text())["rows"]}
    assert set(rows) == {"greedy:compile", "none:compile session", "exact generate", "exact session"}
    calls = rows["greedy:compile"]["calls"]
    assert all(row["calls_unlike_greedy"] == 0 and row["calls"] == calls for row in rows.values())
    tokens = rows["greedy:compile"]["target_forwards_per_call"]
    assert rows["none:compile session"]["target_forwards_per_call"] == tokens
    assert rows["exact session"]["target_forwards_per_call"] == rows["exact generate"]["target_forwards_per_call"]
    assert rows["exact session"]["target_forwards_per_call"] < tokens
    refused = run_example("benchmarks/session_path.py", "--tiny", "--json", str(output), timeout=120, check=False)
    assert refused.returncode == 2 and "exists" in refused.stderr


@pytest.mark.slow
def test_call_path_benchmark_counts_a_sessions_call_that_plans_nothing(tmp_path):
    """It counts the functions from ``predict_action`` to the prefill's forward (fewer than the whole call's); a
    session's third call reuses its shape's plan (no round plan made, no cache sized), a call through
    ``model.generate`` makes both; an existing --json is refused before anything runs."""
    output = tmp_path / "path.json"
    result = run_example("benchmarks/call_path.py", "--json", output, timeout=600)
    assert "| span | functions | files | + comprehensions, lambdas |" in result.stdout
    counts = json.loads(output.read_text())
    forward, whole = counts["to the forward"], counts["whole call"]
    assert 0 < forward["functions"] < whole["functions"] and 0 < forward["files"] <= whole["files"]
    session = [name for names in forward["by_file"].values() for name in names]
    assert "ActionPolicy.predict_action" in session and "SpeculativeDecoder.decode" in session
    assert "_round_plan" not in session and "with_draft_slots" not in session
    result = run_example("benchmarks/call_path.py", "--no-session", "--json", tmp_path / "generate.json", timeout=600)
    generate = json.loads((tmp_path / "generate.json").read_text())["to the forward"]["by_file"]
    assert {"_round_plan", "with_draft_slots"} <= {name for names in generate.values() for name in names}
    refused = run_example("benchmarks/call_path.py", "--json", output, timeout=120, check=False)
    assert refused.returncode == 2 and "exists" in refused.stderr


@pytest.mark.slow
def test_start_time_benchmark_tiny_mode(tmp_path):
    """Its tiny mode: three fresh server processes (graphs in memory, files first, files again), every served action
    equal to the policy's greedy one; the later start loads every graph, the image encoder's included: dynamo traces
    none (and it is no slower than the first start's warm-up)."""
    output = tmp_path / "start.json"
    # the machine's Inductor cache: what is tested is the starts, not a machine's first C++ build of the kernels
    result = run_example("benchmarks/start_time.py", "--tiny", "--inductor-cache", "machine", "--json", str(output),
                         timeout=900)  # fmt: skip
    assert "| start | ready from launch | warm-up | graphs traced | actions unlike greedy |" in result.stdout
    rows = {row["start"]: row for row in json.loads(output.read_text())["rows"]}
    assert set(rows) == {"in memory", "files, first start", "files, later start"}
    assert all(row["actions_unlike_greedy"] == 0 and row["actions"] == 1 for row in rows.values())
    assert rows["files, later start"]["warm_up_s"] < rows["files, first start"]["warm_up_s"]
    assert rows["in memory"]["graphs_traced"] > 0 and rows["files, later start"]["graphs_traced"] == 0, rows
    refused = run_example("benchmarks/start_time.py", "--tiny", "--json", str(output), timeout=120, check=False)
    assert refused.returncode == 2 and "exists" in refused.stderr


def test_openvla_serving_benchmark_serves_the_port_to_robots(tmp_path):
    """Its eager mode (no compile): a tiny random OpenVLA with the real tokenizer behind two servers, K = 1 and 2
    robots; every served action equal to the greedy server's, the table and the JSON written."""
    from tests.openvla.test_openvla import HUB_7B

    if not HUB_7B.is_dir():
        pytest.skip(f"{HUB_7B} (the shared OpenVLA reference: its tokenizer files) is absent")
    output = tmp_path / "serving.json"
    flags = ["--method", "prior+jacobi", "--robots", "1", "2", "--repeats", "1", "--steps", "3", "--threads", "1"]
    result = run_example("benchmarks/openvla_serving.py", *flags, "--output", str(output), timeout=600)
    assert "| K | server | actions/s [min-max] | vs greedy |" in result.stdout
    report = json.loads(output.read_text())
    assert [(row["robots"], row["server"]) for row in report["table"]] == [
        (1, "greedy"), (1, "speculative"), (2, "greedy"), (2, "speculative")]  # fmt: skip
    assert all(row["unlike_greedy"] == 0 and row["actions_per_s"] > 0 for row in report["table"])
    assert {run["forwards_per_call"] for run in report["runs"] if run["server"] == "greedy"} == {7}


@pytest.mark.slow  # ~150 s: a cold and a warm process of gpu_openvla.py --tiny
def test_gpu_checks_script_refuses_a_bad_part_and_runs_its_start_part_on_a_tiny_model(tmp_path):
    """The device checks' script (issues 84 and 85), in its CPU mode: a part or a count it does not know is a usage
    error (exit 2) before anything runs; ``start 1`` twice on one graph folder is a cold process, then a warm one that
    finds every graph file the first saved (none added), each writing its JSON."""
    script = ROOT / "examples" / "benchmarks" / "gpu_checks.sh"
    env = {**os.environ, "GPU_CHECKS_TINY": "1", "PYTHON": sys.executable, "OUT": str(tmp_path / "out"),
           "GPU_CHECKS_GRAPHS": str(tmp_path / "graphs"), "OMP_NUM_THREADS": "1"}  # fmt: skip
    for bad in (["compile", "1"], ["start", "zero"], []):
        refused = subprocess.run(["bash", str(script), *bad], capture_output=True, text=True, env=env, timeout=60)
        assert refused.returncode == 2 and "usage:" in refused.stderr, (bad, refused.stderr)
    assert not (tmp_path / "out").exists()
    lines = []
    for _ in range(2):
        done = subprocess.run(["bash", str(script), "start", "1"], capture_output=True, text=True, env=env, timeout=900)
        assert done.returncode == 0, done.stderr[-3000:] + done.stdout[-3000:]
        lines.append(done.stdout.strip().splitlines()[-1])
    (cold, cold_files), (warm, warm_files) = [re.match(r"(\w+) process: \d+ s .*\((\d+) graph files\)", line).groups()
                                              for line in lines]  # fmt: skip
    assert (cold, warm) == ("cold", "warm") and int(cold_files) > 0 and warm_files == cold_files, lines
    assert {p.name for p in (tmp_path / "out").iterdir()} >= {"gpu_openvla_cold.json", "gpu_openvla_warm.json"}
