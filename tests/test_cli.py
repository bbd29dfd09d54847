"""The command line: help shows examples; benchmark runs on a saved pipeline and refuses a wrong folder."""

import pytest

from hf_specvla.cli import main


def test_help_shows_examples(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    assert "hf-specvla demo" in capsys.readouterr().out


def test_benchmark_on_saved_pipeline(toy_pipeline, capsys):
    args = ["--prompts", "2", "--repeats", "1", "--chain-lengths", "6", "--bin-tolerances", "2"]
    assert main(["benchmark", "--pipeline-dir", toy_pipeline.output_dir, *args]) == 0
    out = capsys.readouterr().out
    assert "| greedy |" in out and "| spec k=6 r=2 |" in out


def test_benchmark_refuses_a_folder_without_a_pipeline(tmp_path):
    with pytest.raises(SystemExit) as exit_info:
        main(["benchmark", "--pipeline-dir", str(tmp_path)])
    assert exit_info.value.code == 2
