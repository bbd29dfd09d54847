"""``--device`` / ``--dtype`` on every command that runs a policy (issue 85, item 2), and ``ServeConfig``'s: one
resolver (``policies.devices``); a device that is not here or a misspelled value is a usage error naming it before the
policy loads and before any folder is written; ``--dtype bfloat16`` loads the policy in bf16, its draft head checked
against the weights as saved; run folders record the device and dtype; ``GET /info`` reports them."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from hf_specvla.cli import main
from hf_specvla.policies import VLAPolicy
from hf_specvla.policies.devices import Placement, check_device, check_dtype, resolve_device, resolve_dtype
from hf_specvla.serving import PolicyService, ServeConfig

ROOT = Path(__file__).resolve().parents[2]
POLICY = str(ROOT / "policies" / "mt10_vla")  # the small one: evaluated and compared in seconds
POLICY3, HEAD3 = str(ROOT / "policies" / "mt10_vla3"), str(ROOT / "policies" / "mt10_vla3_draft_v3")

#: each command that runs a policy, as a user starts it; ``{out}``: its output folder (None: it writes none)
COMMANDS = {
    "eval": (["eval", "--policy", POLICY, "--tasks", "reach", "--episodes", "1", "--output-dir", "{out}"], True),
    "compare": (
        [
            "compare",
            "--policy",
            POLICY,
            "--tasks",
            "reach",
            "--episodes",
            "1",
            "--methods",
            "greedy",
            "prior",
            "--output-dir",
            "{out}",
        ],
        True,
    ),  # fmt: skip
    "bench-episodes --policy": (["bench-episodes", "--policy", POLICY, "--tasks", "reach"], False),
    "bench-episodes --pipeline-dir": (["bench-episodes", "--pipeline-dir", str(ROOT / "policies" / "toy_dot")], False),
    "demo": (["demo", "--output-dir", "{out}"], True),
    "demo --train": (["demo", "--train", "--output-dir", "{out}"], True),
    "serve": (["serve", "--policy", POLICY3, "--method", "prior+jacobi", "--port", "0"], False),
    "serve --ray": (["serve", "--policy", POLICY3, "--method", "prior+jacobi", "--ray"], False),
}


def _argv(command: str, out: Path) -> list[str]:
    argv, _ = COMMANDS[command]
    return [word.replace("{out}", str(out)) for word in argv]


def _usage_error(argv: list[str], capsys) -> str:
    """The stderr of a command that must stop with a usage error (exit code 2, one line, no traceback)."""
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    err = capsys.readouterr().err
    assert exit_info.value.code == 2, err
    assert "Traceback" not in err
    return err.strip().splitlines()[-1]


@pytest.fixture
def nothing_loads(monkeypatch):
    """Every way a command loads a model fails the test (the policy, a draft head, a toy pipeline, its training)."""
    from hf_specvla import DraftHead
    from hf_specvla.benchmarks import toy

    def loaded(*args, **kwargs):
        pytest.fail(f"a model was loaded: {args}")

    monkeypatch.setattr(VLAPolicy, "from_pretrained", loaded)
    monkeypatch.setattr(DraftHead, "from_pretrained", loaded)
    monkeypatch.setattr(toy, "load_toy_pipeline", loaded)
    monkeypatch.setattr(toy, "build_toy_pipeline", loaded)


@pytest.fixture
def no_cuda(monkeypatch):
    """This machine as one without CUDA, whatever it has (the refusal is then the same on a GPU machine)."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)


# ----------------------------------------------------------------------------- usage errors before anything loads
@pytest.mark.parametrize("command", COMMANDS)
def test_a_device_that_is_not_here_is_a_usage_error_before_anything_loads(command, tmp_path, capsys, nothing_loads,
                                                                          no_cuda):  # fmt: skip
    if command == "serve --ray":
        pytest.importorskip("ray")
    out = tmp_path / "out"
    line = _usage_error(_argv(command, out) + ["--device", "cuda"], capsys)
    assert line.endswith(
        "error: --device: 'cuda': torch sees no CUDA device on this machine (torch.cuda.is_available() is False); "
        "valid here: auto, cpu"
    ), line
    assert not out.exists()  # nothing written


@pytest.mark.parametrize("command", ["eval", "compare", "bench-episodes --policy", "demo", "serve"])
@pytest.mark.parametrize(
    "flags, message",
    [
        (["--device", "gpu"], "argument --device: 'gpu' is not a device: give auto, cpu, cuda, cuda:N"),
        (["--device", "cuda:x"], "argument --device: 'cuda:x' is not a device: give auto, cpu, cuda, cuda:N"),
        (["--dtype", "fp8"], "argument --dtype: 'fp8' is not a dtype: give auto, bfloat16, float16, float32"),
    ],
)
def test_a_misspelled_device_or_dtype_is_a_usage_error_naming_it(command, flags, message, tmp_path, capsys,
                                                                 nothing_loads):  # fmt: skip
    out = tmp_path / "out"
    assert message in _usage_error(_argv(command, out) + flags, capsys)
    assert not out.exists()


def test_the_spelling_is_checked_without_torch():
    """The CLI parses its flags before torch loads (``--help`` and usage errors answer at once)."""
    code = (
        "import sys\nfrom hf_specvla.cli.main import build_parser\n"
        "for flags in (['--device', 'gpu'], ['--dtype', 'fp8']):\n"
        "    try:\n"
        "        build_parser().parse_args(['eval', '--policy', 'p', '--output-dir', 'o', *flags])\n"
        "    except SystemExit as stop:\n"
        "        assert stop.code == 2\n"
        "print(' '.join(m for m in ('torch', 'transformers') if m in sys.modules) or 'none')"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.split() == ["none"]
    assert "'gpu' is not a device" in result.stderr and "'fp8' is not a dtype" in result.stderr


# ----------------------------------------------------------------------------- the resolver
def test_auto_resolves_to_cpu_in_float32_without_a_gpu(no_cuda):
    assert resolve_device("auto") == "cpu" and resolve_device("cpu") == "cpu"
    assert resolve_dtype("auto", "cpu") is torch.float32
    assert Placement.resolve() == Placement("cpu", torch.float32)


def test_auto_dtype_is_bfloat16_on_cuda_and_names_pass_through():
    """Pure: asks nothing of the machine."""
    assert resolve_dtype("auto", "cuda") is torch.bfloat16
    assert resolve_dtype("auto", "cuda:1") is torch.bfloat16
    assert resolve_dtype("auto", torch.device("cuda", 0)) is torch.bfloat16
    assert resolve_dtype("auto", torch.device("cpu")) is torch.float32
    for name in ("bfloat16", "float16", "float32"):
        assert resolve_dtype(name, "cpu") is getattr(torch, name) is resolve_dtype(name, "cuda")


def test_auto_is_cuda_with_a_gpu_and_a_missing_index_is_refused_naming_the_valid_ones(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert (
        resolve_device("auto") == "cuda" and resolve_device("cuda") == "cuda" and resolve_device("cuda:0") == "cuda:0"
    )
    assert Placement.resolve("auto", "auto") == Placement("cuda", torch.bfloat16)
    with pytest.raises(ValueError) as refused:
        resolve_device("cuda:3")
    assert str(refused.value) == "'cuda:3': this machine has 1 CUDA device(s); valid here: auto, cpu, cuda, cuda:0"


@pytest.mark.parametrize("device", ["gpu", "CUDA", "cuda:", "cuda:-1", "cuda:٣", "mps", "", None, 0])
def test_check_device_refuses_what_is_not_a_device(device):
    with pytest.raises(ValueError, match="is not a device: give auto, cpu, cuda, cuda:N"):
        check_device(device)


@pytest.mark.parametrize("dtype", ["fp8", "bf16", "float64", "torch.float32", None])
def test_check_dtype_refuses_what_is_not_a_dtype(dtype):
    with pytest.raises(ValueError, match="is not a dtype: give auto, bfloat16, float16, float32"):
        check_dtype(dtype)


# ----------------------------------------------------------------------------- ServeConfig and Ray Serve
@pytest.mark.parametrize(
    "settings, message",
    [
        ({"device": "gpu"}, "ServeConfig.device: 'gpu' is not a device: give auto, cpu, cuda, cuda:N"),
        ({"dtype": "fp8"}, "ServeConfig.dtype: 'fp8' is not a dtype: give auto, bfloat16, float16, float32"),
    ],
)
def test_serve_config_refuses_a_bad_device_or_dtype_naming_it(settings, message):
    with pytest.raises(ValueError) as refused:
        ServeConfig(**settings)
    assert message in str(refused.value)


def test_ray_replicas_ask_a_gpu_for_a_cuda_device_and_refuse_an_index_they_cannot_see():
    pytest.importorskip("ray")
    from hf_specvla.serving.ray_deployment import PolicyAppArgs, policy_deployment

    on_gpu = PolicyAppArgs(POLICY3, ServeConfig(method="prior+jacobi", device="cuda"), threads=2)
    assert policy_deployment(on_gpu).ray_actor_options == {"num_cpus": 2, "num_gpus": 1}
    assert policy_deployment(PolicyAppArgs(POLICY3, ServeConfig(device="cpu"))).ray_actor_options == {"num_cpus": 1}
    assert PolicyAppArgs.from_args(on_gpu.to_args()).serve.device == "cuda"  # what serve_config writes reads back
    with pytest.raises(ValueError, match="device 'cuda:1': a Ray replica sees only the GPU Ray gives it"):
        PolicyAppArgs(POLICY3, ServeConfig(device="cuda:1"))
    with pytest.raises(ValueError, match="ServeConfig.device: 'gpu' is not a device"):
        PolicyAppArgs.from_args({"policy": POLICY3, "method": "prior+jacobi", "device": "gpu"})


# ----------------------------------------------------------------------------- bf16, and the draft head's check
def test_a_service_loads_the_policy_and_its_draft_head_in_bfloat16_checked_as_saved():
    """``PolicyService.from_pretrained`` (what a Ray replica runs) on ``dtype=bfloat16``: the policy and its head
    in bf16, the head checked against the saved weights (the check after the cast refuses it: the fingerprint of
    bf16 weights is not the one the head was distilled from), ``GET /info`` naming the device, the dtype and the
    saved weights' fingerprint; and the service decodes."""
    config = ServeConfig(method="prior+jacobi+tree", buckets=(1,), calibration_calls=0, device="cpu", dtype="bfloat16")
    service = PolicyService.from_pretrained(POLICY3, config, HEAD3)
    try:
        assert next(service.policy.model.parameters()).dtype is torch.bfloat16
        assert {p.dtype for p in service.draft_head.parameters()} == {torch.bfloat16}
        saved = json.loads((Path(HEAD3) / "config.json").read_text())["target_fingerprint"]
        info = service.info()
        assert (info["device"], info["dtype"], info["fingerprint"]) == ("cpu", "bfloat16", saved)
        from hf_specvla.serving.protocol import ActRequest

        size = service.policy.config.image_size
        image = np.random.default_rng(0).integers(0, 256, (size, size, 3), dtype=np.uint8)
        (reply,) = service.act([ActRequest(image, "reach the goal", np.zeros(4))])
        action = np.asarray(reply.action)  # [chunk_length, action_dim] (policy v3 acts 2 steps a call)
        assert action.shape[-1] == service.policy.config.action_dim and np.isfinite(action).all()
    finally:
        service.close()
    # the same head checked after the cast is refused: what the order above avoids
    cast = VLAPolicy.from_pretrained(POLICY3)
    cast.model.to(torch.bfloat16)
    with pytest.raises(ValueError, match="trained for another model"):
        cast.check_draft_head(service.draft_head)


def test_a_service_refuses_a_device_that_is_not_here_before_loading(monkeypatch, no_cuda):
    monkeypatch.setattr(VLAPolicy, "from_pretrained", lambda *a, **k: pytest.fail("the policy was loaded"))
    with pytest.raises(ValueError, match="'cuda': torch sees no CUDA device on this machine"):
        PolicyService.from_pretrained(POLICY3, ServeConfig(method="prior+jacobi", device="cuda"))


# ----------------------------------------------------------------------------- run folders record device and dtype
def test_eval_in_bfloat16_records_it_and_refuses_to_continue_in_float32(tmp_path, capsys):
    pytest.importorskip("metaworld")
    out = tmp_path / "eval"
    argv = ["eval", "--policy", POLICY, "--tasks", "reach", "--episodes", "1", "--max-episode-steps", "2",
            "--output-dir", str(out)]  # fmt: skip
    assert main(argv + ["--device", "cpu", "--dtype", "bfloat16"]) == 0
    settings = json.loads((out / "run.json").read_text())["settings"]
    assert (settings["device"], settings["dtype"]) == ("cpu", "bfloat16")
    assert settings["policy"] == VLAPolicy.from_pretrained(POLICY).weights_fingerprint()  # the weights as saved
    line = _usage_error(argv + ["--device", "cpu", "--dtype", "float32"], capsys)
    assert "holds another run: dtype: 'float32' here vs 'bfloat16' there" in line
    assert main(argv + ["--episodes", "2", "--device", "cpu", "--dtype", "bfloat16"]) == 0  # the same run, continued


def test_compare_records_the_device_and_dtype(tmp_path):
    pytest.importorskip("metaworld")
    out = tmp_path / "compare"
    argv = ["compare", "--policy", POLICY, "--tasks", "reach", "--episodes", "1", "--max-episode-steps", "2",
            "--methods", "greedy", "prior", "--device", "cpu", "--dtype", "bfloat16",
            "--output-dir", str(out)]  # fmt: skip
    assert main(argv) == 0
    run = json.loads((out / "run.json").read_text())["settings"]
    summary = json.loads((out / "summary.json").read_text())["settings"]
    assert (run["device"], run["dtype"]) == (summary["device"], summary["dtype"]) == ("cpu", "bfloat16")


def test_a_folder_recorded_before_device_and_dtype_continues_on_the_cpu_in_float32_only():
    from hf_specvla.run_folder import RunRecord

    old = RunRecord("eval", {"policy": "abc", "seed_start": 1})
    assert (
        old.differences(RunRecord("eval", {"policy": "abc", "seed_start": 1, "device": "cpu", "dtype": "float32"}))
        == []
    )
    now = RunRecord("eval", {"policy": "abc", "seed_start": 1, "device": "cuda", "dtype": "bfloat16"})
    assert old.differences(now) == ["device: 'cuda' here vs 'cpu' there", "dtype: 'bfloat16' here vs 'float32' there"]


# ----------------------------------------------------------------------------- the examples
@pytest.mark.parametrize("command", ["eval", "compare", "bench-episodes", "demo", "serve"])
def test_each_command_shows_a_cpu_float32_example_that_parses(command):
    from hf_specvla.cli.main import COMMANDS as MODULES
    from hf_specvla.cli.main import build_parser

    (module,) = [m for m in MODULES if m.NAME == command]
    lines = [line.strip() for line in module.EXAMPLES.replace("\\\n", " ").splitlines()]
    (example,) = [line for line in lines if line.startswith("hf-specvla ") and "--device cpu --dtype float32" in line]
    args = build_parser().parse_args(example.split()[1:])
    assert (args.device, args.dtype) == ("cpu", "float32")
