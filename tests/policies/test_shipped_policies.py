"""The policies shipped in policies/: each loads from its folder, v3 keeps v2's cost structure (the speed evidence
stays comparable), and speculation on the shipped weights is lossless at r=0."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hf_specvla import DraftHead
from hf_specvla.metaworld.env import MT10_TASKS, TASK_INSTRUCTIONS
from hf_specvla.policies import VLAPolicy

POLICIES = Path(__file__).resolve().parents[2] / "policies"
SHIPPED = ["mt10_vla", "mt10_vla3"]
#: policy v2's decoder and image tokens (policies/mt10_vla2, out of the tree since 2026-12-01: `git show
#: 9d833b3:policies/mt10_vla2/config.json`), which v3 keeps so that their speed figures compare
POLICY_V2_DECODER = dict(hidden_size=192, intermediate_size=384, num_hidden_layers=16, num_attention_heads=6,
                         num_key_value_heads=3)  # fmt: skip
POLICY_V2_IMAGE_TOKENS = 16


@pytest.mark.parametrize("name", SHIPPED)
def test_a_shipped_policy_loads_and_acts(name):
    policy = VLAPolicy.from_pretrained(POLICIES / name)
    size = policy.config.image_size
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (size, size, 3), dtype=np.uint8)
    chunk = policy.predict_action(image, TASK_INSTRUCTIONS["reach-v3"], np.array([0.0, 0.6, 0.2, 1.0]))
    assert chunk.shape == ((policy.config.chunk_length, 4) if policy.config.chunk_length > 1 else (4,))
    assert np.all(np.abs(chunk) <= 1.0 + 1e-9)  # MT10's action range, the statistics' q01 / q99


@pytest.mark.parametrize("name", ["mt10_vla3"])
def test_a_shipped_policy_card_names_its_lineage(name):
    card = (POLICIES / name / "README.md").read_text()
    assert card.startswith("---\nlibrary_name: hf_specvla") and "base_model: policies/" in card
    assert "## Training" in card or "## Lineage" in card
    assert "hf-specvla train-vla" in card  # the commands that produced it


def test_policy_v3_keeps_policy_v2s_cost_structure():
    """Policy v2's decoder (layers, widths, heads), the same 16 image tokens, 8 tokens per call: v3 sees a larger
    image (128 px) in larger patches (32 px), so only the patch embedding grows."""
    v3 = json.loads((POLICIES / "mt10_vla3" / "config.json").read_text())
    assert {k: v3["text_config"][k] for k in POLICY_V2_DECODER} == POLICY_V2_DECODER
    assert v3["image_seq_length"] == POLICY_V2_IMAGE_TOKENS
    p3 = VLAPolicy.from_pretrained(POLICIES / "mt10_vla3").config
    assert (p3.num_image_tokens, p3.action_tokens, p3.chunk_length) == (POLICY_V2_IMAGE_TOKENS, 8, 2)
    assert (p3.image_size, p3.patch_size) == (128, 32)


@pytest.mark.parametrize("head_folder", ["mt10_vla3_draft", "mt10_vla3_draft_v2", "mt10_vla3_draft_v3"])
def test_speculation_on_policy_v3_is_lossless(head_folder):
    """Its draft heads (v1; v2 reading the previous action the policy remembers; v3 drafting blocks, and the whole
    action before the prefill) and the action prior on the shipped weights: r=0 gives greedy's actions, in fewer
    forwards."""
    policy = VLAPolicy.from_pretrained(POLICIES / "mt10_vla3")
    head = DraftHead.from_pretrained(POLICIES / head_folder)
    policy.check_draft_head(head)
    rng = np.random.default_rng(1)
    forwards = 0
    for step in range(4):
        image = rng.integers(0, 256, (policy.config.image_size,) * 2 + (3,), dtype=np.uint8)
        state = rng.uniform([-0.1, 0.5, 0.05, 0.0], [0.1, 0.9, 0.3, 1.0])
        instruction = TASK_INSTRUCTIONS[MT10_TASKS[step]]
        plain = policy.predict_action(image, instruction, state)
        spec, out = policy.predict_action(
            image, instruction, state, return_output=True, assistant_model=head, action_prior=True
        )
        np.testing.assert_array_equal(plain, spec)
        forwards += out.speculation.num_target_forwards
    assert forwards < 4 * policy.config.action_tokens
