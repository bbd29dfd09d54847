"""The package was split into folders by job: old import paths, the shipped policies and draft heads, and run
folders written before the move keep working."""

from __future__ import annotations

import importlib
import json
import shutil
import sys
import warnings
from pathlib import Path

import pytest

from hf_specvla._moved import MOVED_MODULES

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("old_name", sorted(MOVED_MODULES))
def test_an_old_module_path_is_the_new_module(old_name):
    sys.modules.pop(old_name, None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        old = importlib.import_module(old_name)
    assert old is importlib.import_module(MOVED_MODULES[old_name])
    assert any(issubclass(w.category, FutureWarning) and MOVED_MODULES[old_name] in str(w.message) for w in caught)


def test_old_from_imports_give_the_same_classes():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        from hf_specvla.comparison import CompareConfig as OldCompareConfig
        from hf_specvla.policy import VLAPolicy as OldVLAPolicy

        from hf_specvla.training import DraftTrainingConfig as OldDraftTrainingConfig
    from hf_specvla.metaworld.comparison import CompareConfig
    from hf_specvla.policies import VLAPolicy
    from hf_specvla.training.configuration import DraftTrainingConfig

    assert (OldVLAPolicy, OldCompareConfig, OldDraftTrainingConfig) == (VLAPolicy, CompareConfig, DraftTrainingConfig)


@pytest.mark.parametrize("draft_head", ["mt10_vla3_draft", "mt10_vla3_draft_v2"])
def test_the_shipped_policies_and_heads_load(draft_head, policy="mt10_vla3"):
    from hf_specvla import DraftHead
    from hf_specvla.policies import VLAPolicy

    loaded = VLAPolicy.from_pretrained(ROOT / "policies" / policy)
    loaded.check_draft_head(DraftHead.from_pretrained(ROOT / "policies" / draft_head))


def test_a_compare_folder_written_before_the_move_resumes(tmp_path, monkeypatch, capsys):
    """Written by the pre-move code (`compare --policy policies/mt10_vla --tasks reach --episodes 1 --methods greedy
    prior:r=4 --max-episode-steps 12`): the same command finds every episode done and runs none. Its episodes were
    rendered before the reset frame showed the goal marker (render revision 1), so as it is the same command refuses
    to add frames of revision 2 to it; stamped with today's revision, the paths are what is tested."""
    pytest.importorskip("metaworld")
    from hf_specvla.cli import main
    from hf_specvla.metaworld.comparison import runner

    command = ["compare", "--policy", str(ROOT / "policies" / "mt10_vla"), "--tasks", "reach", "--episodes", "1",
               "--methods", "greedy", "prior:r=4", "--max-episode-steps", "12", "--threads", "1",
               "--output-dir"]  # fmt: skip
    monkeypatch.setattr(runner, "run_method_episode", lambda *a, **k: pytest.fail("a finished episode ran again"))
    as_written = tmp_path / "as_written"
    shutil.copytree(ROOT / "tests" / "fixtures" / "compare_before_move", as_written)
    with pytest.raises(SystemExit):
        main([*command, str(as_written)])
    assert "env.render_revision: 2 here vs 1 there" in capsys.readouterr().err

    folder = tmp_path / "compare"
    shutil.copytree(ROOT / "tests" / "fixtures" / "compare_before_move", folder)
    record = json.loads((folder / "run.json").read_text())
    record["settings"]["env"]["render_revision"] = 2
    (folder / "run.json").write_text(json.dumps(record))
    main([*command, str(folder)])
    assert "| prior:r=4 | 1 |" in capsys.readouterr().out
    assert (folder / "summary.json").exists()


def test_a_train_vla_record_from_before_the_loop_reads_its_fixed_optimisation():
    """train-vla's betas, clipping, schedule and precision were hard-coded before the one training loop made them
    settings: an old record without them continues with the same values and refuses others."""
    from dataclasses import replace

    from hf_specvla.run_folder import RunRecord
    from hf_specvla.training.checkpoints import training_record
    from hf_specvla.training.configuration import VLATrainingConfig

    config = VLATrainingConfig("runs/x")
    now = training_record("train-vla", config, {"data": "abc"})
    old_settings = {k: v for k, v in now.settings.items()
                    if k not in ("betas", "max_grad_norm", "lr_schedule", "mixed_precision")}  # fmt: skip
    old = RunRecord("train-vla", old_settings)
    assert old.differences(now) == []
    other = training_record("train-vla", replace(config, max_grad_norm=0.5), {"data": "abc"})
    assert old.differences(other) == ["max_grad_norm: 0.5 here vs 1.0 there"]


def test_importing_the_package_registers_the_draft_head_with_the_auto_classes():
    """README: draft heads load with ``AutoModel``: ``import hf_specvla`` alone must register them (a fresh process, so
    no other test's import does it)."""
    import subprocess
    import sys

    head = str(ROOT / "policies" / "mt10_vla3_draft")
    code = "\n".join(["import hf_specvla", "from transformers import AutoModel",
                      f"print(type(AutoModel.from_pretrained({head!r})).__name__)"])  # fmt: skip
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                            env={**__import__("os").environ, "HF_HUB_OFFLINE": "1"})  # fmt: skip
    assert result.stdout.strip().endswith("DraftHead"), result.stderr[-2000:]
