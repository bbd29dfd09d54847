"""The command line: help shows examples; benchmark runs on a saved pipeline and refuses a wrong folder."""

from pathlib import Path

import pytest
import torch

from hf_specvla.cli import main


def test_help_shows_examples(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    assert "hf-specvla demo" in capsys.readouterr().out


def test_benchmark_on_saved_pipeline(toy_pipeline, capsys):
    args = ["--prompts", "2", "--repeats", "1", "--chain-lengths", "6", "--bin-tolerances", "2", "--no-compile"]
    assert main(["benchmark", "--pipeline-dir", toy_pipeline.output_dir, *args]) == 0
    out = capsys.readouterr().out
    assert "| greedy |" in out and "| spec k=6 r=2 |" in out and ":compile" not in out
    # transformers' own assisted generation (a 1-layer early exit of the target drafting) is timed beside ours: lossless
    assisted = next(line for line in out.splitlines() if line.startswith("| assisted (transformers) |"))
    assert assisted.endswith("| - | - | 0.00 / 0 |")  # it reports no statistics; its actions are greedy's


@pytest.mark.commands  # ~55 s: the benchmark command's compiled rows
def test_benchmark_times_transformers_assisted_generation_compiled_where_it_can(toy_pipeline, capsys, monkeypatch):
    from hf_specvla.benchmarks.speed import assisted_generation_compiles

    monkeypatch.setattr("hf_specvla.speculative.compiled_decoding_kwargs", eager_backend_compiled_kwargs)
    args = ["--prompts", "1", "--repeats", "1", "--chain-lengths", "2", "--bin-tolerances", "2"]
    assert main(["benchmark", "--pipeline-dir", toy_pipeline.output_dir, *args]) == 0
    out = capsys.readouterr().out
    assert "| greedy:compile |" in out and "| assisted (transformers) |" in out
    assert ("| assisted (transformers):compile |" in out) == assisted_generation_compiles()  # transformers >= 5.24


def eager_backend_compiled_kwargs(device_type="cpu"):
    """What ``:compile`` methods pass, with dynamo's cheap ``eager`` backend (traced and guarded, no codegen)."""
    from transformers import CompileConfig

    config = CompileConfig(backend="eager", fullgraph=True, dynamic=False, mode="default")
    config._compile_all_devices = True
    return dict(cache_implementation="static", compile_config=config)


def test_benchmark_refuses_a_folder_without_a_pipeline(tmp_path):
    with pytest.raises(SystemExit) as exit_info:
        main(["benchmark", "--pipeline-dir", str(tmp_path)])
    assert exit_info.value.code == 2


@pytest.mark.commands  # ~90 s: every episode method of bench-episodes, compiled rows included
def test_bench_episodes_on_the_toy(toy_pipeline, capsys, monkeypatch):
    """Eager and compiled rows (transformers' greedy:compile, our :compile; dynamo's eager backend here), speed-ups
    against the fastest greedy, and where the time goes (compiled calls timed from outside the graph)."""
    monkeypatch.setattr("hf_specvla.speculative.compiled_decoding_kwargs", eager_backend_compiled_kwargs)
    tree = ["--tree-top-k", "2", "--tree-depth", "3", "--tree-total-tokens", "5"]
    args = [
        "bench-episodes",
        "--pipeline-dir",
        toy_pipeline.output_dir,
        "--episodes",
        "1",
        "--bin-tolerances",
        "0",
        "2",
    ]
    assert main([*args, "--chain-length", "2", *tree]) == 0
    out = capsys.readouterr().out
    for row in ("| greedy |", "| prior r=0 |", "| prior r=2 |", "| head chain k=2 r=0 |", "| head tree r=2 |",
                "| prior+tree r=0 |", "| greedy:compile |", "| prior r=0:compile |", "| head tree r=0:compile |",
                "| prior+tree r=0:compile |", "| jacobi r=0 |", "| prior+jacobi r=2 |",
                "| prior+jacobi+tree r=0:compile |"):  # fmt: skip
        assert row in out
    assert "speed-up vs greedy" in out and "| vs greedy |" in out
    # r=0 is lossless, eager or compiled: its actions never move from greedy's
    for row in ("| prior r=0 |", "| prior+tree r=0:compile |", "| greedy:compile |", "| prior+jacobi r=0:compile |",
                "| prior+jacobi+tree r=0 |"):  # fmt: skip
        assert out.split(row)[1].split("\n")[0].endswith("0.00 / 0 |"), row
    # where the time goes: the parts add up to the call; greedy drafts nothing and decodes after its prefill
    split, jacobi = out.split("Where the time goes")[1].split("Jacobi guesses right")
    jacobi, by_position = jacobi.split("Accepted drafts by token position")
    assert "| greedy | 0% | 0% |" in by_position  # greedy drafts nothing
    assert "| jacobi r=0 | " in jacobi and "| +1 |" in jacobi  # how often the guesses were right, by position
    assert "| method | vision | prefill | later forwards | drafting | rest | total |" in split
    for line in [row for row in split.splitlines() if row.startswith("| ") and "method" not in row]:
        *parts, total = [float(cell) for cell in line.strip("|").split("|")[1:]]
        assert sum(parts) == pytest.approx(total, abs=0.3001), line  # 6 cells rounded to 0.1 ms: 6 x 0.05 at most
        assert min(parts[:4]) >= 0, line
    for row in ("| greedy |", "| greedy:compile |"):  # the compiled decoding steps are timed too
        greedy_parts = [float(cell) for cell in split.split(row)[1].split("\n")[0].strip(" |").split("|")]
        assert greedy_parts[3] == 0 and greedy_parts[2] > 0 and greedy_parts[0] > 0, row


@pytest.mark.parametrize(
    "extra, message",
    [(["--tree-total-tokens", "2", "--tree-depth", "4"], "total_tokens"), (["--steps", "0"], "--steps: must be >= 1")],
)
def test_bench_episodes_usage_errors(tmp_path, capsys, extra, message):
    with pytest.raises(SystemExit) as exit_info:
        main(["bench-episodes", "--pipeline-dir", str(tmp_path), *extra])
    assert exit_info.value.code == 2 and message in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["benchmark", "--pipeline-dir", "p", "--prompts", "0"], "argument --prompts: must be >= 1, got 0"),
        (["benchmark", "--pipeline-dir", "p", "--repeats", "0"], "argument --repeats: must be >= 1, got 0"),
        (["eval", "--policy", "p", "--output-dir", "o", "--threads", "-1"], "argument --threads: must be >= 1, got -1"),
        (["eval", "--policy", "p", "--output-dir", "o", "--threads", "0"], "argument --threads: must be >= 1, got 0"),
        (["demo", "--threads", "two"], "argument --threads: expected an integer >= 1, got 'two'"),
    ],
)
def test_bad_numbers_are_usage_errors(capsys, argv, message):
    """Regression (reliability issue, case 6): crashes (ZeroDivisionError, StatisticsError, RuntimeError) and a
    silent '--threads 0 means default' are now argparse usage errors, before anything is loaded."""
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2 and message in capsys.readouterr().err


def test_progress_bars_are_slow_when_redirected_and_logs_stay_ours():
    """Regression (reliability issue, case 11): a 300-step job used to write 38 KB of bar redraws to a log, and
    third-party INFO (OpenGL, accelerate) showed on every run."""
    import io
    import logging

    from hf_specvla.cli.common import configure_logging
    from hf_specvla.progress import progress_bar

    redirected = io.StringIO()  # not a terminal
    with progress_bar(total=300, desc="train", file=redirected) as bar:
        for step in range(300):
            bar.update(1)
            bar.set_postfix(loss=f"{1 / (step + 1):.3f}")  # tqdm's default would redraw here every step
    assert redirected.getvalue().count("\r") <= 3  # first draw, maybe one timed update, the final one
    configure_logging()
    assert logging.getLogger("hf_specvla.training.draft_head").isEnabledFor(logging.INFO)
    assert not logging.getLogger("OpenGL.acceleratesupport").isEnabledFor(logging.INFO)
    assert not logging.getLogger("accelerate.checkpointing").isEnabledFor(logging.INFO)


def test_demo_refuses_a_folder_holding_another_pipeline(toy_pipeline, capsys):
    """Regression (reliability issue, case 5): `demo --size medium` into a folder holding the small pipeline used
    to reuse the small one silently; the same settings still reuse it (nothing retrained)."""
    from hf_specvla.benchmarks.toy import build_toy_pipeline

    with pytest.raises(SystemExit) as exit_info:
        main(["demo", "--train", "--size", "medium", "--output-dir", toy_pipeline.output_dir])
    assert exit_info.value.code == 2 and "holds another run: size.hidden_size: " in capsys.readouterr().err
    again = build_toy_pipeline(toy_pipeline.output_dir, progress=False)  # loaded
    assert torch.equal(again.draft_head.fuse.weight, toy_pipeline.draft_head.fuse.weight)


def test_the_demos_default_steps_are_the_toys():
    """One default each: ``demo --train``'s ``--target-steps`` / ``--draft-steps`` (parsed without importing the toy)
    are ``toy.TOY_TARGET_STEPS`` / ``toy.TOY_HEAD_STEPS``, which the shipped pipeline was trained with."""
    import inspect
    import json

    from hf_specvla.benchmarks.toy import SHIPPED_TOY_DIR, TOY_HEAD_STEPS, TOY_TARGET_STEPS, build_toy_pipeline
    from hf_specvla.cli.demo import TRAINING_DEFAULTS
    from hf_specvla.cli.main import build_parser

    args = build_parser().parse_args(["demo", "--train"])
    assert not hasattr(args, "target_steps")  # given only with --train: the defaults fill in
    assert (TRAINING_DEFAULTS["target_steps"], TRAINING_DEFAULTS["draft_steps"]) == (TOY_TARGET_STEPS, TOY_HEAD_STEPS)
    assert inspect.signature(build_toy_pipeline).parameters["draft_steps"].default == TOY_HEAD_STEPS
    shipped = json.loads((Path(__file__).resolve().parents[2] / SHIPPED_TOY_DIR / "run.json").read_text())
    assert (shipped["settings"]["target_steps"], shipped["settings"]["draft_steps"]) == (TOY_TARGET_STEPS,
                                                                                         TOY_HEAD_STEPS)  # fmt: skip
