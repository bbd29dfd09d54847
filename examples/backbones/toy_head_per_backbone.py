"""Trains the toy VLA target and its draft head on several language-model families, and measures the head.

The toy target (a Llava vision tower in front of a small language model, 7 action tokens per action; see
``hf_specvla.benchmarks.toy``) is built with each family's decoder (``llama``, ``qwen2``, ``gemma2``: Gemma-2 scales its
embeddings, caps its logits and alternates sliding-window layers), behaviour-cloned on the toy scenes, and a draft
head is self-distilled from it exactly as ``hf-specvla demo`` does. Reported per family, on the held-out scenes:
the target's action-token accuracy, and what the engine does with the head at r=0 (acceptance per drafted
position, tokens per target forward, target forwards per action) plus whether its tokens equal plain greedy's.

    python examples/backbones/toy_head_per_backbone.py --families llama qwen2 gemma2 --output-dir runs/backbone_heads
    python examples/backbones/toy_head_per_backbone.py --tiny --output-dir runs/backbone_heads_tiny   # seconds

Nothing about speed is measured here (see examples/benchmarks for that).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import torch

from hf_specvla import DraftHead, enable_speculation
from hf_specvla.benchmarks.toy import (
    ACTION_DIM,
    ToyTargetSize,
    build_toy_target,
    split_scenes,
    toy_action_accuracy,
    toy_inputs,
    toy_target_training_config,
    train_toy_target,
)
from hf_specvla.run_folder import RunRecord, claim_run_folder
from hf_specvla.training.draft_head import (
    DraftTrainingConfig,
    build_distillation_dataset,
    speculative_acceptance,
    train_draft_head,
)

FAMILIES = ("llama", "qwen2", "gemma2")


def measure_family(
    family: str, folder: Path, target_steps: int, draft_steps: int, seed: int, max_scenes: int | None = None
) -> dict:
    target, tokenizer, action_tokenizer = build_toy_target(ToyTargetSize(), seed, text_model_type=family)
    target_config = toy_target_training_config(folder / f"{family}-target", target_steps, seed)
    train_toy_target(target, tokenizer, action_tokenizer, target_config, progress=False)
    target = enable_speculation(target.eval())
    train_scenes, held_out = (scenes[:max_scenes] for scenes in split_scenes())
    prompts = [toy_inputs(train_scenes[i : i + 64], tokenizer) for i in range(0, len(train_scenes), 64)]
    dataset = build_distillation_dataset(target, prompts, ACTION_DIM, action_tokenizer, progress=False)
    torch.manual_seed(seed)
    head = DraftHead.from_target(target, action_tokenizer, action_dim=ACTION_DIM)
    config = DraftTrainingConfig(
        str(folder / family), max_steps=draft_steps, batch_size=32, learning_rate=3e-3, lr_schedule="cosine",
        warmup_steps=min(50, draft_steps), save_every=0, seed=seed,
    )  # fmt: skip
    head = train_draft_head(head, target, dataset, config, progress=False).eval()
    single = [toy_inputs([scene], tokenizer) for scene in held_out]
    acceptance = speculative_acceptance(target, head, single, ACTION_DIM)
    equal, tie_gaps = 0, []
    for inputs in single:
        speculative = target.generate(**inputs, max_new_tokens=ACTION_DIM, do_sample=False, assistant_model=head)
        greedy = target.generate(**inputs, max_new_tokens=ACTION_DIM, do_sample=False, output_scores=True,
                                 return_dict_in_generate=True)  # fmt: skip
        if torch.equal(speculative, greedy.sequences):
            equal += 1
            continue
        # where they part: how far apart were greedy's two best logits? (fp32 rounding can flip a near-tie)
        length = inputs["input_ids"].shape[1]
        first = int((speculative[0, length:] != greedy.sequences[0, length:]).nonzero()[0])
        best_two = greedy.scores[first][0].topk(2).values
        tie_gaps.append(float(best_two[0] - best_two[1]))
    return {
        "family": family,
        "target_action_accuracy": toy_action_accuracy(target, tokenizer, action_tokenizer, held_out),
        "head_final_logit_softcapping": head.config.final_logit_softcapping,
        "equal_to_greedy": equal == len(single),
        "sequences_equal_to_greedy": equal,
        "unequal_top2_logit_gaps": tie_gaps,
        **acceptance,
    }


def table(rows: list[dict]) -> str:
    lines = ["| family | target accuracy | 1st drafted accepted | 2nd | tokens / target forward | "
             "target forwards / action | r=0 == greedy |", "|---|---:|---:|---:|---:|---:|---|"]  # fmt: skip
    for row in rows:
        accepted = row["acceptance_per_position"] + [float("nan")] * 2
        lines.append(
            f"| {row['family']} | {row['target_action_accuracy']:.0%} | {accepted[0]:.0%} | {accepted[1]:.0%} | "
            f"{row['tokens_per_target_forward']:.2f} | {row['target_forwards_per_sequence']:.2f} | "
            f"{row['sequences_equal_to_greedy']}/{row['sequences']}"
            + "".join(f" (logit gap {gap:.1e})" for gap in row["unequal_top2_logit_gaps"])
            + " |"
        )
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--families", nargs="+", default=list(FAMILIES), help="transformers model_type of each decoder")
    parser.add_argument("--target-steps", type=int, default=300, help="behaviour-cloning steps of each toy target")
    parser.add_argument("--draft-steps", type=int, default=800, help="draft-head training steps")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument("--tiny", action="store_true", help="a few steps each (a smoke test: seconds)")
    parser.add_argument("--output-dir", required=True, help="heads, results.json and results.md")
    args = parser.parse_args(argv)
    from transformers import CONFIG_MAPPING

    unknown = [f for f in args.families if f not in CONFIG_MAPPING]
    if unknown:
        parser.error(f"unknown model_type(s) {unknown}; use transformers model types, e.g. {' '.join(FAMILIES)}")
    if min(args.target_steps, args.draft_steps) < 1:
        parser.error("--target-steps and --draft-steps must be >= 1")
    if args.tiny:
        args.target_steps, args.draft_steps = 3, 3
    if args.threads:
        torch.set_num_threads(args.threads)
    logging.basicConfig(level=logging.WARNING)
    settings = {k: v for k, v in vars(args).items() if k not in ("output_dir", "threads")}
    with claim_run_folder(args.output_dir, RunRecord("toy_head_per_backbone", settings), overwrite=False) as run:
        rows = []
        for family in args.families:
            max_scenes = 16 if args.tiny else None
            rows.append(measure_family(family, run.bound, args.target_steps, args.draft_steps, args.seed, max_scenes))
            print(table(rows[-1:]).splitlines()[-1], flush=True)
        (run.bound / "results.json").write_text(json.dumps({"settings": settings, "rows": rows}, indent=2))
        (run.bound / "results.md").write_text(table(rows) + "\n")
    print(table(rows))


if __name__ == "__main__":
    main()
