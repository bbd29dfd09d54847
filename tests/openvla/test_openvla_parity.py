"""The OpenVLA port against the official code, stage by stage, on the reference fixture of make_fixture.sh.

``OPENVLA_REF_WORK`` names the folder make_fixture.sh wrote (``tox -e openvla`` builds the small variant there and
runs this module; ``VARIANTS="small full"`` adds the full-size towers). Each variant found there is checked: the
processor's pixel_values and prompt ids, each tower's patch features, the projector, the language model's hidden
states and logits (fp32, atol 1e-4), the training loss, and the generated ids, step logits, action tokens and action
(exact).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from hf_specvla.openvla import OpenVLAForActionPrediction, OpenVLAProcessor, VisionTowerSpec, register_vision_tower

REFERENCE = os.environ.get("OPENVLA_REF_WORK")
ATOL = 1e-4

# The fixture's small variant uses a test-only timm id (tiny_timm_ids.py): SigLIP So400m's flags (patch 14, no class
# token, MAP head, erf GELU) at width 144, 2 heads, 4 blocks, mlp_ratio 3.7362 -> int(144 * 3.7362) = 538.
register_vision_tower(
    "vit_tiny_patch14_siglip_224_fixture", VisionTowerSpec(144, 4, 2, 538, attention_pool=True), exist_ok=True
)

VARIANTS = {"small": ("tiny-openvla-small", "fixture-small"), "full": ("tiny-openvla", "fixture")}


def variant_folders(variant: str) -> tuple[Path, Path]:
    if not REFERENCE:
        pytest.skip("OPENVLA_REF_WORK is not set: run `tox -e openvla` (it builds the fixture with make_fixture.sh)")
    checkpoint, fixture = (Path(REFERENCE) / name for name in VARIANTS[variant])
    if not (checkpoint / "config.json").is_file() or not (fixture / "logits.npy").is_file():
        pytest.skip(f"no {variant} fixture in {REFERENCE} (make_fixture.sh with VARIANTS={variant} writes it)")
    return checkpoint, fixture


@pytest.fixture(scope="module", params=sorted(VARIANTS))
def reference(request):
    checkpoint, fixture = variant_folders(request.param)
    torch.manual_seed(0)
    model = OpenVLAForActionPrediction.from_pretrained(checkpoint, dtype=torch.float32).eval()
    processor = OpenVLAProcessor.from_pretrained(checkpoint)
    stored = {path.stem: np.load(path) for path in fixture.glob("*.npy")}
    manifest = json.loads((fixture / "manifest.json").read_text())
    return model, processor, stored, manifest


def close(actual: torch.Tensor, expected: np.ndarray, atol: float = ATOL):
    np.testing.assert_allclose(actual.detach().float().numpy(), expected, rtol=0, atol=atol)


def test_processor(reference):
    _, processor, stored, _ = reference
    assert torch.equal(
        processor.image_processor(stored["image_uint8_224x224"]), torch.from_numpy(stored["pixel_values"])
    )
    assert torch.equal(
        processor.image_processor(stored["image2_uint8_240x320"]), torch.from_numpy(stored["pixel_values_image2"])
    )
    prompt = processor.prompt("pick up the red block")
    inputs = processor(prompt, stored["image_uint8_224x224"])
    assert inputs["input_ids"].tolist() == stored["input_ids_prompt"].tolist()
    assert torch.equal(inputs["pixel_values"], torch.from_numpy(stored["pixel_values"]))


@torch.no_grad()
def test_towers_projector_hidden_states_and_logits(reference):
    model, _, stored, _ = reference
    pixels, ids = torch.from_numpy(stored["pixel_values"]), torch.from_numpy(stored["input_ids"])
    backbone = model.vision_backbone
    close(backbone.featurizer(pixels[:, :3]), stored["vision_featurizer_patches"])
    close(backbone.fused_featurizer(pixels[:, 3:]), stored["vision_fused_featurizer_patches"])
    close(backbone(pixels), stored["vision_patch_features"])
    output = model(
        input_ids=ids,
        attention_mask=torch.ones_like(ids),
        pixel_values=pixels,
        output_hidden_states=True,
        output_projector_features=True,
    )
    close(output.projector_features, stored["projector_features"])
    hidden = torch.cat([output.hidden_states[0], output.hidden_states[1], output.hidden_states[-1]])
    close(hidden, stored["llm_hidden_states"])
    close(output.logits, stored["logits"])


@torch.no_grad()
def test_training_forward_loss(reference):
    model, _, stored, manifest = reference
    output = model(
        input_ids=torch.from_numpy(stored["train_input_ids"]),
        labels=torch.from_numpy(stored["train_labels"]),
        pixel_values=torch.from_numpy(stored["pixel_values"]),
    )
    close(output.logits[:, -9:], stored["train_logits_last9"])
    assert abs(float(output.loss) - manifest["train_loss"]) < 1e-4


@torch.no_grad()
def test_generation_and_action(reference):
    model, _, stored, _ = reference
    pixels, ids = torch.from_numpy(stored["pixel_values"]), torch.from_numpy(stored["input_ids"])
    output = model.generate(
        ids, pixel_values=pixels, max_new_tokens=7, do_sample=False, output_scores=True, return_dict_in_generate=True
    )
    assert output.sequences.tolist() == stored["generated_ids"].tolist()
    close(torch.stack(output.scores, dim=1)[0], stored["generation_step_logits"])
    unnorm_key = next(iter(model.norm_stats))
    # the official call, with the prompt as tokenized (predict_action appends 29871)
    action = model.predict_action(
        input_ids=torch.from_numpy(stored["input_ids_prompt"]),
        pixel_values=pixels,
        unnorm_key=unnorm_key,
        do_sample=False,
    )
    np.testing.assert_array_equal(action, stored["action"])
    np.testing.assert_array_equal(model.action_token_ids(action, unnorm_key)[0].numpy(), stored["action_token_ids"])


@torch.no_grad()
def test_friendly_call_and_speculation_give_the_official_action(reference):
    from hf_specvla import DraftHead

    model, processor, stored, _ = reference
    unnorm_key = next(iter(model.norm_stats))
    image = stored["image_uint8_224x224"]
    friendly = model.predict_action(
        image=image, instruction="pick up the red block", processor=processor, unnorm_key=unnorm_key
    )
    np.testing.assert_array_equal(friendly, stored["action"])
    head = DraftHead.from_target(model, num_draft_tokens=3)
    wrong = torch.from_numpy(stored["action_token_ids"])[None].flip(1)
    for kwargs in (dict(assistant_model=head), dict(draft_ids=wrong), dict(draft_ids=wrong, assistant_model=head)):
        speculative = model.predict_action(
            image=image, instruction="pick up the red block", processor=processor, unnorm_key=unnorm_key, **kwargs
        )
        np.testing.assert_array_equal(speculative, stored["action"])
