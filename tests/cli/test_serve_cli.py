"""``hf-specvla serve``: its examples parse, bad flags are usage errors before the policy loads, and the command serves
a real policy on 127.0.0.1 until SIGTERM, then exits 0."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from hf_specvla.cli import serve as serve_command
from hf_specvla.cli.main import build_parser

ROOT = Path(__file__).resolve().parents[2]
POLICY = str(ROOT / "policies" / "mt10_vla3")


def test_help_shows_the_examples_and_they_parse():
    parser = build_parser()
    lines = serve_command.EXAMPLES.replace("\\\n", " ").splitlines()
    commands = [line.strip() for line in lines if "hf-specvla " in line and not line.strip().startswith("#")]
    assert len(commands) >= 5
    for command in commands:
        words = command.split()
        words = words[words.index("hf-specvla") + 1 :]  # after an environment assignment
        parser.parse_args(words)


def _run(*flags: str, env: dict | None = None) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "hf_specvla.cli", "serve", *flags]
    return subprocess.run(command, capture_output=True, text=True, timeout=120, env={**os.environ, **(env or {})})


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--host", "0.0.0.0"], "reachable from other machines: pass --api-key"),
        (["--method", "prior+bogus"], "unknown decoding method"),
        (["--method", "prior+tree"], "drafts with the draft head: give --draft-head"),
        (["--method", "prior+jacobi", "exact"], "mix compiled and eager decoding"),
        (["--buckets", "4", "2"], "--buckets: buckets must be increasing"),
        (["--buckets", "0"], "argument --buckets: must be >= 1, got 0"),
        (["--speculate-buckets", "3"], "speculate_buckets [3] are not buckets"),
        (["--calibration-calls", "-1"], "calibration_calls"),
        (["--calibration-calls", "100000000"], "calibration_calls must be 0..100 (timed calls per bucket"),
        (["--max-wait-ms", "inf"], "max_wait_ms must be a finite number >= 0, got inf"),
        (["--max-wait-ms", "nan"], "max_wait_ms must be a finite number >= 0, got nan"),
        (["--buckets", "1", "5000"], "--buckets: buckets must be batch sizes 1..1024, got [1, 5000]"),
        (["--max-prompt-tokens", "0"], "argument --max-prompt-tokens: must be >= 1, got 0"),
        (["--port", "99999"], "must be a TCP port 0..65535"),
        (["--replicas", "2"], "--replicas / --ray-address are for Ray Serve: add --ray"),
        (["--ray", "--port", "0"], "--port 0 (any free port) is for the server on one machine"),
        (["--ray", "--replicas", "4096"], "--replicas 4096 x --threads 1 need 4096 CPUs; this machine has"),
        (["--policy", "no/such/policy"], "no/such/policy"),
        (["--compile-cache", "/proc/version"], "--compile-cache /proc/version: is a file, not a folder"),
    ],
)
def test_bad_flags_are_usage_errors_before_the_policy_loads(flags, message):
    args = ["--policy", POLICY, *flags] if "--policy" not in flags else flags
    started = time.perf_counter()
    result = _run(*args)
    assert result.returncode == 2, result.stderr[-2000:]
    assert message in result.stderr and "Traceback" not in result.stderr
    assert time.perf_counter() - started < 60


def test_a_taken_port_is_a_usage_error_naming_it():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        result = _run("--policy", POLICY, "--port", str(port))
    assert result.returncode == 2 and f"cannot listen on 127.0.0.1:{port}" in result.stderr


def test_an_unused_draft_head_is_said_not_dropped_silently():
    """``--draft-head`` with a method that drafts without one: a warning naming both (as ``compare`` does); the
    taken port then stops the command before the policy loads. A preset with a head uses it: both named."""
    head = str(ROOT / "policies" / "mt10_vla3_draft_v2")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = str(taken.getsockname()[1])
        unused = _run("--policy", POLICY, "--method", "prior+jacobi:compile", "--draft-head", head, "--port", port)
        used = _run("--policy", POLICY, "--method", "exact", "--draft-head", head, "--port", port)
    assert unused.returncode == 2 == used.returncode
    assert f"--draft-head {head} is not used: --method prior+jacobi:compile does not draft" in unused.stderr
    assert "is not used" not in used.stderr
    assert "--method exact = prior+jacobi:compile prior+jacobi+tree:compile" in used.stderr


def test_serve_answers_act_and_exits_0_on_sigterm():
    from hf_specvla.serving import PolicyClient

    command = [sys.executable, "-m", "hf_specvla.cli", "serve", "--policy", POLICY, "--method", "prior+jacobi",
               "--buckets", "1", "2", "--calibration-calls", "1", "--port", "0"]  # fmt: skip
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "OMP_NUM_THREADS": "1"})  # fmt: skip
    try:
        line = process.stdout.readline()
        assert line.startswith("serving "), process.stderr.read()[-3000:]
        url = line.split(" on ", 1)[1].split(": POST", 1)[0]  # serving <policy> (<method>) on <url>: POST /act, ...
        client = PolicyClient(url)
        info = client.info()
        assert info["method"] == "prior+jacobi" and info["buckets"] == [1, 2] and len(info["calibration"]) == 2
        size = info["image_size"]
        reply = client.act(np.zeros((size, size, 3), np.uint8), "reach the goal", np.zeros(4), session="a", reset=True)
        assert reply.action.shape == (info["chunk_length"], info["action_dim"])
        assert urllib.request.urlopen(url + "/health").status == 200
        process.send_signal(signal.SIGTERM)
        _, err = process.communicate(timeout=120)  # read while it stops: a full pipe would block its logging
        assert process.returncode == 0, err[-3000:]
        # an eager server says what it does at start-up: no compile estimate (it once promised ~30 s a bucket)
        start_up = next(line for line in err.splitlines() if "buckets [1, 2]" in line)
        assert "calibrating buckets [1, 2]" in start_up and "compil" not in start_up, start_up
    finally:
        process.kill()


@pytest.mark.ray  # ~40 s each: a local Ray cluster
@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM])
def test_serve_on_ray_serve_answers_and_stops_on_ctrl_c_or_sigterm(stop):
    """``serve --ray``: the flags become a Serve config file that Ray Serve's own ``serve run`` runs on a local Ray
    cluster (one replica, the same API); Ctrl-C (SIGINT) is ``serve run``'s: Serve shut down, exit 0, and the local
    cluster with it: the port closes. SIGTERM (a supervisor's stop) does the same (Ray's own handler would abort)."""
    pytest.importorskip("ray")
    from hf_specvla.serving import PolicyClient

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    command = [sys.executable, "-m", "hf_specvla.cli", "serve", "--policy", POLICY, "--method", "prior+jacobi",
               "--buckets", "1", "--calibration-calls", "0", "--port", str(port), "--ray", "--replicas", "1",
               "--threads", "1"]  # fmt: skip
    # Ctrl-C's default: a runner that started this test in the background (SIGINT ignored, as shells do for `&`)
    # would hand its children an ignored SIGINT, which Python then keeps
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "OMP_NUM_THREADS": "1", "RAY_USAGE_STATS_ENABLED": "0"},
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # fmt: skip
    try:
        line = process.stdout.readline()
        while line and not line.startswith("serving "):  # serve run's own lines come first
            line = process.stdout.readline()
        assert line.startswith("serving ") and "Ray Serve, 1 replicas" in line, process.stderr.read()[-3000:]
        url = line.split(" on ", 1)[1].split(": POST", 1)[0]
        assert url == f"http://127.0.0.1:{port}"
        info = PolicyClient(url).info()
        assert info["deployment"] == "ray" and info["method"] == "prior+jacobi" and info["buckets"] == [1]
        size = info["image_size"]
        reply = PolicyClient(url).act(np.zeros((size, size, 3), np.uint8), "reach the goal", np.zeros(4))
        assert reply.action.shape == (info["chunk_length"], info["action_dim"])
        process.send_signal(stop)
        _, err = process.communicate(timeout=180)  # read while it stops: Serve's shutdown logs would fill a pipe
        assert process.returncode == 0, err[-3000:]
    finally:
        process.kill()
    with socket.socket() as probe:  # nothing answers there any more
        assert probe.connect_ex(("127.0.0.1", port)) != 0


@pytest.fixture(scope="module")
def openvla_checkpoint(tmp_path_factory) -> Path:
    from tests.openvla.test_openvla import HUB_7B

    if not HUB_7B.is_dir():
        pytest.skip(f"{HUB_7B} (the shared OpenVLA reference: its tokenizer files) is absent")
    from tests.openvla.tiny_checkpoint import write_tiny_checkpoint

    return write_tiny_checkpoint(tmp_path_factory.mktemp("tiny-openvla"))


def test_an_openvla_checkpoint_is_served_and_its_unnorm_key_checked_before_loading(openvla_checkpoint):
    """``serve --policy <an OpenVLA checkpoint folder>`` in a fresh process (its towers built from the specs its
    config.json carries): OpenVLA's request (an image of any size, its unnorm_key) gets the port's one-robot greedy
    action; a bad ``--unnorm-key`` is a usage error naming the valid keys, before the weights load."""
    from hf_specvla.policies import OpenVLAPolicy
    from hf_specvla.serving import PolicyClient

    folder = str(openvla_checkpoint)
    bad = _run("--policy", folder, "--unnorm-key", "bridge_orig")
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert "--unnorm-key: unnorm_key='bridge_orig' is not in this checkpoint's norm_stats; valid keys: " in bad.stderr
    mine = _run("--policy", POLICY, "--unnorm-key", "bridge_orig")
    assert mine.returncode == 2 and "is a Meta-World policy with one set of action statistics" in mine.stderr
    command = [sys.executable, "-m", "hf_specvla.cli", "serve", "--policy", folder, "--method", "prior+jacobi",
               "--buckets", "1", "2", "--calibration-calls", "0", "--unnorm-key", "tiny_dataset", "--device", "cpu",
               "--port", "0"]  # fmt: skip
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "OMP_NUM_THREADS": "1"})  # fmt: skip
    try:
        line = process.stdout.readline()
        assert line.startswith("serving "), process.stderr.read()[-3000:]
        url = line.split(" on ", 1)[1].split(": POST", 1)[0]
        client = PolicyClient(url)
        info = client.info()
        assert info["unnorm_key"] == "tiny_dataset" and info["image_size"] is None and info["dtype"] == "float32"
        image = np.random.default_rng(0).integers(0, 256, (120, 160, 3), dtype=np.uint8)
        replies = [client.act(image, "pick up the cup", unnorm_key=key) for key in (None, "other_dataset")]
        process.send_signal(signal.SIGTERM)
        _, err = process.communicate(timeout=120)
        assert process.returncode == 0, err[-3000:]
    finally:
        process.kill()
    policy = OpenVLAPolicy.from_pretrained(folder)  # two datasets, no default
    for reply, key in zip(replies, ("tiny_dataset", "other_dataset")):
        expected = policy.model.predict_action(image=image, instruction="pick up the cup", processor=policy.processor,
                                               unnorm_key=key)  # fmt: skip
        np.testing.assert_array_equal(reply.action, expected)
