"""Speculative decoding on the toy OpenVLA-style target, through the plain transformers API.

    python examples/speculative_decoding_toy.py            # trains (or reuses) runs/toy, then decodes 3 scenes

Shows: enable_speculation, generate(assistant_model=DraftHead, bin_tolerance=...), the .speculation statistics,
and decoding action tokens back to continuous actions.
"""

import torch

from hf_specvla.benchmarks.toy import ACTION_DIM, build_toy_pipeline, split_scenes, toy_inputs


def main() -> None:
    pipeline = build_toy_pipeline("runs/toy")  # target + draft head, trained on the spot or loaded
    for scene in split_scenes()[1][:3]:  # scenes neither model was trained on
        inputs = toy_inputs([scene], pipeline.tokenizer)
        greedy = pipeline.target.generate(**inputs, max_new_tokens=ACTION_DIM, do_sample=False)
        for bin_tolerance in (0, 4):
            out = pipeline.target.generate(
                **inputs,
                max_new_tokens=ACTION_DIM,
                do_sample=False,
                assistant_model=pipeline.draft_head,
                bin_tolerance=bin_tolerance,
                return_dict_in_generate=True,
            )
            action = pipeline.action_tokenizer.decode(out.sequences[0, -ACTION_DIM:])
            print(
                f"{scene.instruction!r:32} r={bin_tolerance}: same as greedy={torch.equal(out.sequences, greedy)}, "
                f"{out.speculation.num_target_forwards} target forwards for {ACTION_DIM} tokens "
                f"(accept lengths {out.speculation.accept_lengths}), action {action.round(2).tolist()}"
            )


if __name__ == "__main__":
    main()
