"""``hf-specvla robots``: its help and examples, bad flags as usage errors before any folder is written, a server that
is not there (or refuses the key) as a one-line error naming it, and a run against a stub HTTP server that speaks the
wire format (the end-to-end test against the real server lives in tests/serving/)."""

from __future__ import annotations

import json
import shlex
import socket
import subprocess
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

from hf_specvla.cli import main
from hf_specvla.cli import robots as robots_command
from hf_specvla.cli.main import build_parser


def _exit(argv: list[str], capsys) -> tuple[int, str, str]:
    """The exit code, stdout and stderr of a command that stops with SystemExit."""
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    out, err = capsys.readouterr()
    return exit_info.value.code, out, err


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_help_shows_the_examples_and_they_parse(capsys):
    code, out, _ = _exit(["robots", "--help"], capsys)
    assert code == 0 and "examples:" in out and "hf-specvla robots --server http://127.0.0.1:8000" in out
    assert "HF_SPECVLA_API_KEY" in out
    commands = robots_command.EXAMPLES.replace("\\\n", " ").splitlines()
    examples = [shlex.split(line) for line in commands if line.strip().startswith("hf-specvla robots")]
    assert len(examples) == 2
    for argv in examples:  # copy-paste runnable: every flag as the parser reads it
        args = build_parser().parse_args(argv[1:])
        assert args.command == "robots" and args.output_dir.startswith("runs/")


def test_the_command_module_and_the_fleet_load_no_torch():
    code = ("import sys, hf_specvla.cli.robots, hf_specvla.metaworld.fleet; "
            "print(' '.join(m for m in ('torch', 'transformers', 'mujoco') if m in sys.modules))")  # fmt: skip
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.split() == []


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--episodes", "0"], "--episodes: must be >= 1, got 0"),
        (["--robots", "0"], "--robots: must be >= 1, got 0"),
        (["--robots", "two"], "--robots: expected an integer >= 1, got 'two'"),
        (["--seed-start", "-1"], "--seed-start: must be >= 0, got -1"),
        (["--max-episode-steps", "501"], "RobotsConfig.max_episode_steps must be <= 500"),
        (["--tasks", "fly"], "--tasks: unknown Meta-World task 'fly'"),
        (["--server", "127.0.0.1:8000"], "RobotsConfig.server must be an http:// or https:// address"),
    ],
)
def test_bad_flags_are_usage_errors_before_any_folder_is_written(tmp_path, capsys, extra, message):
    output_dir = tmp_path / "out"
    code, _, err = _exit(["robots", "--server", f"http://127.0.0.1:{_free_port()}", "--tasks", "reach",
                          "--output-dir", str(output_dir), *extra], capsys)  # fmt: skip
    assert code == 2 and message in err and "Traceback" not in err, err
    assert not output_dir.exists()


def test_an_unreachable_server_is_a_one_line_error_naming_it(tmp_path, capsys):
    url = f"http://127.0.0.1:{_free_port()}"  # nothing listens there
    output_dir = tmp_path / "out"
    code, out, err = _exit(["robots", "--server", url, "--tasks", "reach", "--output-dir", str(output_dir)], capsys)
    assert code == 1 and out == "" and "Traceback" not in err
    (line,) = err.strip().splitlines()
    assert line.startswith("hf-specvla robots: error: cannot reach the policy server at " + url)
    assert not output_dir.exists()


# ----------------------------------------------------------------------------- against a stub server
INFO = {"policy": "policies/stub", "fingerprint": "0123456789abcdef", "image_size": 32, "camera": "corner",
        "state_dim": 4, "action_dim": 4, "chunk_length": 1, "use_state": True, "method": "exact",
        "buckets": [1, 2]}  # fmt: skip


class StubServer:
    """``GET /info`` and ``POST /act`` in the wire format (a fixed action), over HTTP on a free port; with ``api_key``
    it refuses requests without ``Authorization: Bearer <key>`` (401), as ``hf-specvla serve --api-key`` does;
    ``refuse_acts``: every ``/act`` is refused (422)."""

    def __init__(self, api_key: str | None = None, refuse_acts: bool = False):
        from hf_specvla.serving.protocol import ActReply, ServedFigures, loads

        stub = self
        self.acts: list[dict] = []

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):  # quiet
                pass

            def _reply(self, status: int, payload: dict) -> None:
                body = json.dumps(payload).encode()
                self.send_response(status)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def _authorized(self) -> bool:
                if api_key is None or self.headers.get("Authorization") == f"Bearer {api_key}":
                    return True
                self._reply(401, {"error": "a valid API key is required", "field": "api_key"})
                return False

            def do_GET(self):
                if not self._authorized():
                    return
                if self.path != "/info":
                    return self._reply(404, {"error": "no such path", "field": None})
                self._reply(200, INFO)

            def do_POST(self):
                request = loads(self.rfile.read(int(self.headers["Content-Length"])))
                if not self._authorized():
                    return
                if refuse_acts:
                    return self._reply(422, {"error": "state must be 4 numbers", "field": "state"})
                stub.acts.append({"session": request.get("session"), "reset": request.get("reset", False)})
                served = ServedFigures("exact", True, 2, 1, 1, 0.1, 1.0, 1.5, request.get("session"), [7, 8])
                self._reply(200, ActReply(np.array([0.1, 0.0, -0.1, 0.5]), served).to_payload())

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)

    def __enter__(self) -> StubServer:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


def test_robots_run_against_a_stub_server_and_resume_with_nothing_left(tmp_path, capsys, monkeypatch):
    pytest.importorskip("metaworld")
    monkeypatch.delenv("HF_SPECVLA_API_KEY", raising=False)
    output_dir = tmp_path / "out"
    with StubServer() as stub:
        argv = ["robots", "--server", stub.url, "--tasks", "reach", "--episodes", "2", "--robots", "2",
                "--max-episode-steps", "3", "--output-dir", str(output_dir)]  # fmt: skip
        assert main(argv) == 0
        out = capsys.readouterr().out
        assert "| reach-v3 | 2 | 0% | 3 |" in out and "methods (method: requests): exact: 6" in out
        records = [json.loads(line) for line in (output_dir / "episodes.jsonl").read_text().splitlines()]
        assert sorted(r["seed"] for r in records) == [100000, 100001]
        assert all(r["actions"] == [[0.1, 0.0, -0.1, 0.5]] * 3 for r in records)
        assert [a["reset"] for a in stub.acts].count(True) == 2 and len(stub.acts) == 6
        summary = json.loads((output_dir / "summary.json").read_text())
        assert summary["batch_sizes"] == {"1": 6} and summary["requests"] == 6
        assert main(argv) == 0 and len(stub.acts) == 6  # resumed: nothing left to run, not one request


def test_a_server_that_wants_a_key_is_a_one_line_error_and_the_env_var_gives_it(tmp_path, capsys, monkeypatch):
    pytest.importorskip("metaworld")
    monkeypatch.delenv("HF_SPECVLA_API_KEY", raising=False)
    output_dir = tmp_path / "out"
    with StubServer(api_key="sesame") as stub:
        argv = ["robots", "--server", stub.url, "--tasks", "reach", "--episodes", "1", "--robots", "1",
                "--max-episode-steps", "2", "--output-dir", str(output_dir)]  # fmt: skip
        code, _, err = _exit(argv, capsys)
        (line,) = err.strip().splitlines()
        assert code == 1 and f"the policy server at {stub.url} refused GET /info: HTTP 401" in line
        assert "--api-key or HF_SPECVLA_API_KEY" in line and not output_dir.exists()
        monkeypatch.setenv("HF_SPECVLA_API_KEY", "sesame")
        assert main(argv) == 0 and len(stub.acts) == 2
        assert "sesame" not in (output_dir / "run.json").read_text()  # the key is never recorded


def test_a_refused_request_mid_run_is_a_one_line_error_that_keeps_the_folder(tmp_path, capsys):
    pytest.importorskip("metaworld")
    output_dir = tmp_path / "out"
    with StubServer(refuse_acts=True) as stub:
        code, _, err = _exit(["robots", "--server", stub.url, "--tasks", "reach", "--episodes", "1", "--robots", "1",
                              "--max-episode-steps", "2", "--output-dir", str(output_dir)], capsys)  # fmt: skip
    line = err.strip().splitlines()[-1]  # after the run's log line and progress bar
    assert code == 1 and "Traceback" not in err
    assert f"the policy server at {stub.url}: HTTP 422: state must be 4 numbers (field 'state')" in line
    assert "the same command continues them" in line
    assert (output_dir / "run.json").exists() and (output_dir / "episodes.jsonl").read_text() == ""
