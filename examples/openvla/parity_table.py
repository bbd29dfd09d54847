"""Prints the OpenVLA port's largest deviation from the official code at every stage, as a markdown table.

bash ../shared/openvla-reference/make_fixture.sh            # writes ~/.cache/openvla-reference (full + small)
python examples/openvla/parity_table.py --reference ~/.cache/openvla-reference
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from hf_specvla.openvla import OpenVLAForActionPrediction, OpenVLAProcessor, VisionTowerSpec, register_vision_tower

VARIANTS = {"small": ("tiny-openvla-small", "fixture-small"), "full": ("tiny-openvla", "fixture")}


def deviation(actual: torch.Tensor, expected: np.ndarray) -> float:
    return float(np.abs(actual.detach().float().numpy() - expected).max())


@torch.no_grad()
def variant_row(checkpoint: Path, fixture: Path) -> dict[str, str]:
    model = OpenVLAForActionPrediction.from_pretrained(checkpoint, dtype=torch.float32).eval()
    processor = OpenVLAProcessor.from_pretrained(checkpoint)
    ref = {path.stem: np.load(path) for path in fixture.glob("*.npy")}
    pixels = processor.image_processor(ref["image_uint8_224x224"])
    ids = torch.from_numpy(ref["input_ids"])
    out = model(input_ids=ids, pixel_values=pixels, output_hidden_states=True, output_projector_features=True)
    generated = model.generate(ids, pixel_values=pixels, max_new_tokens=7, output_scores=True,
                               return_dict_in_generate=True)  # fmt: skip
    unnorm_key = next(iter(model.norm_stats))
    action = model.predict_action(input_ids=torch.from_numpy(ref["input_ids_prompt"]), pixel_values=pixels,
                                  unnorm_key=unnorm_key)  # fmt: skip
    hidden = torch.cat([out.hidden_states[0], out.hidden_states[1], out.hidden_states[-1]])
    second_image = processor.image_processor(ref["image2_uint8_240x320"])
    backbone = model.vision_backbone
    deviations = {
        "pixel_values (2 images)": max(deviation(pixels, ref["pixel_values"]),
                                       deviation(second_image, ref["pixel_values_image2"])),
        "featurizer patches": deviation(backbone.featurizer(pixels[:, :3]), ref["vision_featurizer_patches"]),
        "fused featurizer patches": deviation(backbone.fused_featurizer(pixels[:, 3:]),
                                              ref["vision_fused_featurizer_patches"]),
        "projector features": deviation(out.projector_features, ref["projector_features"]),
        "LLM hidden states": deviation(hidden, ref["llm_hidden_states"]),
        "logits": deviation(out.logits, ref["logits"]),
        "generation step logits": deviation(torch.stack(generated.scores, 1)[0], ref["generation_step_logits"]),
    }  # fmt: skip
    row = {stage: f"{value:.1e}" for stage, value in deviations.items()}
    row["generated ids"] = "equal" if generated.sequences.tolist() == ref["generated_ids"].tolist() else "DIFFER"
    row["action"] = "equal" if np.array_equal(action, ref["action"]) else "DIFFER"
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--reference", type=Path, required=True, help="the folder make_fixture.sh wrote")
    args = parser.parse_args()
    torch.set_num_threads(2)
    # the small variant's test-only SigLIP id (the fixture's tiny_timm_ids.py)
    register_vision_tower("vit_tiny_patch14_siglip_224_fixture", VisionTowerSpec(144, 4, 2, 538, attention_pool=True))
    rows = {}
    for variant, (checkpoint, fixture) in VARIANTS.items():
        if (args.reference / fixture / "logits.npy").is_file():
            rows[variant] = variant_row(args.reference / checkpoint, args.reference / fixture)
    if not rows:
        raise SystemExit(f"no fixture in {args.reference}: run make_fixture.sh first")
    print("| stage (max abs deviation, fp32) | " + " | ".join(rows) + " |")
    print("|---|" + "---:|" * len(rows))
    for stage in next(iter(rows.values())):
        print(f"| {stage} | " + " | ".join(row[stage] for row in rows.values()) + " |")
    print(json.dumps({variant: row["action"] for variant, row in rows.items()}))


if __name__ == "__main__":
    main()
