"""The shipped toy pipeline (``policies/toy_dot``, what the demo and the tests load) is what ``hf-specvla demo --train``
still makes: rebuilt from nothing with the defaults (the command's code, ``build_toy_pipeline``; ~15 min on one CPU
thread), the target decodes the held-out scenes as the shipped one does and the head drafts as the shipped head does.
Compared by behaviour, not bits: another CPU rounds the training's floats differently."""

import json
from pathlib import Path

import pytest
import torch

from hf_specvla.benchmarks.toy import (
    ACTION_DIM,
    SHIPPED_TOY_DIR,
    TOY_HEAD_STEPS,
    TOY_TARGET_STEPS,
    build_toy_pipeline,
    load_toy_pipeline,
    split_scenes,
    toy_inputs,
)

pytestmark = pytest.mark.training

SHIPPED = Path(__file__).resolve().parents[2] / SHIPPED_TOY_DIR


def test_the_shipped_toy_records_the_command_that_made_it():
    record = json.loads((SHIPPED / "run.json").read_text())
    assert record["command"] == "demo"
    assert (record["settings"]["target_steps"], record["settings"]["draft_steps"]) == (TOY_TARGET_STEPS,
                                                                                       TOY_HEAD_STEPS)  # fmt: skip
    assert "hf-specvla demo --train --output-dir policies/toy_dot" in (SHIPPED / "README.md").read_text()


@torch.no_grad()
def _greedy_actions(pipeline, scenes):
    """Greedy action tokens ``[S, 7]`` on ``scenes``."""
    inputs = toy_inputs(scenes, pipeline.tokenizer)
    actions = pipeline.target.generate(**inputs, max_new_tokens=ACTION_DIM, do_sample=False)[:, -ACTION_DIM:]
    return actions


def test_demo_train_still_makes_the_shipped_toy(tmp_path):
    shipped = load_toy_pipeline(str(SHIPPED))
    rebuilt = build_toy_pipeline(str(tmp_path / "toy"), progress=False)  # demo --train's defaults
    scenes = split_scenes()[1]  # held out of both trainings
    ours, theirs = _greedy_actions(rebuilt, scenes), _greedy_actions(shipped, scenes)
    agreement = (ours == theirs).float().mean().item()
    assert agreement >= 0.95, f"the rebuilt target agrees with the shipped one on {agreement:.1%} of action tokens"
    # the heads: the same architecture and settings, and most of their weights where the shipped head's are
    assert rebuilt.draft_head.config.to_dict() == shipped.draft_head.config.to_dict()
    from hf_specvla import DraftHeadDrafter, DraftTreeConfig

    one_forward = []
    for pipeline in (rebuilt, shipped):
        tree = DraftHeadDrafter(pipeline.draft_head, tree=DraftTreeConfig())
        calls = [pipeline.target.generate(**toy_inputs([scene], pipeline.tokenizer), max_new_tokens=ACTION_DIM,
                                          do_sample=False, assistant_model=tree, return_dict_in_generate=True)
                 for scene in scenes[:32]]  # fmt: skip
        one_forward.append(sum(call.speculation.num_target_forwards == 1 for call in calls))
    assert one_forward[0] >= one_forward[1] - 4, (
        f"whole actions drafted: rebuilt {one_forward[0]}, shipped {one_forward[1]}"
    )
