"""What speculation saves on OpenVLA-7B, on a GPU: the OpenVLA port with random weights in bf16 (the table in
docs/benchmarks.md).

The model is ``hf_specvla.openvla.OpenVLAForActionPrediction`` built from the real ``openvla/openvla-7b``
config.json (DINOv2 ViT-L/14-reg4 + SigLIP So400m/14, fused-GELU projector, Llama-2-7B with its 32064-token
vocabulary, sdpa), with random weights (only times are meaningful), plus an untrained hf_specvla ``DraftHead`` sized
for it. The prompt is OpenVLA's: BOS + 256 image rows + 19 text tokens + 29871.

Measured interleaved: every round runs every operation once, in a fresh random order; medians over the rounds,
each operation synchronised on the device.

    python examples/benchmarks/gpu_openvla_shapes.py --config path/to/openvla-7b --rounds 30 --json out.json
    # check the script on a CPU (small towers, 2 Llama layers, fp32):
    python examples/benchmarks/gpu_openvla_shapes.py --config path/to/openvla-7b --device cpu --check --rounds 2
"""

from __future__ import annotations

import argparse
import json
import random
import statistics
import time

import torch
from transformers.cache_utils import DynamicCache

from hf_specvla import ActionPriorDrafter, DraftHead, DraftHeadDrafter, DraftTree, DraftTreeConfig, enable_speculation
from hf_specvla.openvla import OpenVLAConfig, OpenVLAForActionPrediction, VisionTowerSpec, register_vision_tower
from hf_specvla.speculative import CACHE_KEY
from hf_specvla.speculative.cache import truncate_cache
from hf_specvla.speculative.masks import causal_mask, to_additive_mask, tree_verification_allowed

#: "In: What action should the robot take to pick up the red block?\nOut:" (Llama-2 tokenizer) + 29871
PROMPT_IDS = [1, 512, 29901, 1724, 3158, 881, 278, 19964, 2125, 304, 5839, 701, 278, 2654, 2908, 29973, 13, 3744, 29901]
PROMPT_IDS = PROMPT_IDS + [29871]
ACTION_DIM = 7
UNNORM_KEY = "bridge_orig"


def build_model(config_path: str, device: torch.device, dtype: torch.dtype, check: bool):
    """The port with random weights, on ``device`` in ``dtype``; ``check``: small towers and 2 Llama layers."""
    config = OpenVLAConfig.from_pretrained(config_path)
    if check:
        register_vision_tower("check-tiny-siglip", VisionTowerSpec(144, 4, 2, 538, attention_pool=True), exist_ok=True)
        config.timm_model_ids = ["vit_small_patch14_reg4_dinov2.lvd142m", "check-tiny-siglip"]
        config.text_config.num_hidden_layers = 2
    config.text_config._attn_implementation = "sdpa"
    with torch.device(device):
        torch.set_default_dtype(dtype)
        model = OpenVLAForActionPrediction(config).eval()
        torch.set_default_dtype(torch.float32)
    with torch.no_grad():  # as the reference fixture does: action rows x4, so that greedy decoding emits actions
        model.get_output_embeddings().weight[31744:32000] *= 4
    return model


def random_tree(num_nodes: int, depth: int, generator: torch.Generator, device) -> DraftTree:
    """A draft tree of ``num_nodes`` nodes (EAGLE-2-like: a greedy backbone of ``depth`` plus branches)."""
    paths = [[int(x) for x in torch.randint(31744, 32000, (depth,), generator=generator)]]
    while DraftTree.from_paths(paths, "bench").num_nodes < num_nodes:
        base = random.Random(len(paths)).choice(paths)
        cut = random.Random(len(paths) + 1).randrange(depth)
        tail = torch.randint(31744, 32000, (depth - cut,), generator=generator).tolist()
        paths.append(base[:cut] + tail)
    tree = DraftTree.from_paths(paths, "bench", device=device)
    return tree.select(torch.arange(tree.num_nodes, device=device) < num_nodes)


def self_consistent_drafts(model, input_ids: torch.Tensor, pixel_values, drafts: torch.Tensor) -> torch.Tensor:
    """Drafts the prefill-with-drafts forward accepts in full: the fixed point of "append the drafts, take the
    argmax at each drafted place" (in fp32 these are greedy's own tokens; in bf16 the different kernel shapes of a
    decode step and of a longer prefill can flip a near-tied argmax)."""
    length = input_ids.shape[1]
    for _ in range(drafts.shape[1] + 1):
        logits = model(torch.cat([input_ids, drafts], 1), pixel_values=pixel_values).logits[:, length - 1 : -1]
        predicted = logits.argmax(-1)
        if torch.equal(predicted, drafts):
            return drafts
        drafts = predicted
    raise RuntimeError("no self-consistent drafts")


def lossless_checks(model, draft_head, tree_drafter, input_ids, pixel_values) -> dict:
    """r=0 on this device: every drafter gives plain greedy's tokens; right drafts take one target forward."""
    inputs = dict(input_ids=input_ids, pixel_values=pixel_values, max_new_tokens=ACTION_DIM,
                  min_new_tokens=ACTION_DIM, do_sample=False)  # fmt: skip
    greedy = model.generate(**inputs)
    greedy_ids = greedy[:, input_ids.shape[1] :]
    layout = model.action_layout(UNNORM_KEY)
    drafters = [("chain", draft_head), ("tree", tree_drafter)]
    if bool(layout.tokenizer.is_action_token(greedy_ids).all()):
        drafters.append(("prior", ActionPriorDrafter([greedy_ids[0].tolist()], layout)))
    checks = {}
    for name, drafter in drafters:
        out = model.generate(**inputs, assistant_model=drafter, action_layout=layout, return_dict_in_generate=True)
        checks[f"{name}: identical to greedy"] = bool(torch.equal(out.sequences, greedy))
        checks[f"{name}: target forwards"] = out.speculation.num_target_forwards
    scores = model.generate(**inputs, output_logits=True, return_dict_in_generate=True).logits
    top2 = torch.stack(scores).float().topk(2, dim=-1).values  # [steps, 1, 2]
    margins = (top2[..., 0] - top2[..., 1]).flatten().tolist()
    checks["greedy top-1 minus top-2 logit, per step"] = [round(x, 4) for x in margins]
    drafted = model(greedy, pixel_values=pixel_values).logits[:, input_ids.shape[1] - 1 : -1].float()
    checks["max |logit| difference, decode steps vs one prefill with the drafts"] = round(
        float((torch.stack(scores)[:, 0].float() - drafted[0]).abs().max()), 4
    )
    checks["self-consistent drafts equal greedy's tokens"] = bool(
        torch.equal(self_consistent_drafts(model, input_ids, pixel_values, greedy_ids), greedy_ids)
    )
    return checks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", required=True, help="openvla-7b's folder or config.json")
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--tree-nodes", type=int, default=50)
    parser.add_argument("--json", default=None, help="also write the results here")
    parser.add_argument("--device", default="cuda", help="cuda (the point), or cpu to check the script")
    parser.add_argument("--check", action="store_true", help="small towers and 2 Llama layers (a CPU check)")
    parser.add_argument("--exact-reduced-precision", default="on", choices=("on", "off"),
                        help="enable_speculation option: on = eager attention in bf16, off = sdpa")  # fmt: skip
    args = parser.parse_args()
    device = torch.device(args.device)
    dtype = torch.bfloat16 if device.type == "cuda" else torch.float32

    def synchronize():
        if device.type == "cuda":
            torch.cuda.synchronize()

    torch.manual_seed(0)
    model = build_model(args.config, device, dtype, args.check)
    enable_speculation(model, exact_reduced_precision=args.exact_reduced_precision == "on")
    draft_head = DraftHead.from_target(model, action_dim=ACTION_DIM).eval()
    handles = draft_head.target_handles(model)
    generator = torch.Generator().manual_seed(0)
    official_ids = torch.tensor([PROMPT_IDS], device=device)  # what predict_action receives
    input_ids = model.add_image_tokens(official_ids)[0]  # [1, 276]: BOS, 256 image rows, text
    prompt_length = input_ids.shape[1]
    pixel_values = torch.randn(1, 6, 224, 224, generator=generator).to(device, dtype)
    chain = torch.randint(31744, 32000, (1, ACTION_DIM), generator=generator).to(device)
    tree = random_tree(args.tree_nodes, ACTION_DIM - 1, generator, device)
    positions = torch.arange(prompt_length, device=device)[None]

    with torch.no_grad():
        prefilled = DynamicCache()
        out = model(input_ids, pixel_values=pixel_values, **{CACHE_KEY: prefilled}, use_cache=True,
                    output_hidden_states=True)  # fmt: skip
        prompt_hidden = out.hidden_states[-1]  # [1, S, H]
        head_cache = DynamicCache()
        embeds = handles.embed_tokens(input_ids)
        draft_head(embeds[:, 1:], prompt_hidden[:, :-1], positions[:, :-1],
                   causal_mask(prompt_length - 1, 0, dtype, device), head_cache)  # fmt: skip
        greedy = model.generate(input_ids, pixel_values=pixel_values, max_new_tokens=ACTION_DIM,
                                min_new_tokens=ACTION_DIM, do_sample=False)  # fmt: skip
        greedy_ids = greedy[:, prompt_length:]
        right_ids = self_consistent_drafts(model, input_ids, pixel_values, greedy_ids)

    tree_positions = torch.cat([positions, prompt_length + tree.depths[None]], dim=1)
    tree_mask = to_additive_mask(tree_verification_allowed(0, prompt_length, tree.ancestor_or_self), dtype)
    after_mask = to_additive_mask(tree_verification_allowed(prompt_length, 1, tree.ancestor_or_self), dtype)
    after_positions = torch.cat([positions[:, -1:] + 1, prompt_length + 1 + tree.depths[None]], dim=1)
    after_ids = torch.cat([greedy_ids[:, :1], tree.token_ids[None]], dim=1)

    def vision_op():
        model.get_image_features(pixel_values)

    def prefill():
        model(input_ids, pixel_values=pixel_values, use_cache=True, logits_to_keep=1)

    def prefill_chain():
        model(torch.cat([input_ids, chain], 1), pixel_values=pixel_values, use_cache=True,
              logits_to_keep=ACTION_DIM + 1)  # fmt: skip

    def prefill_tree():
        model(torch.cat([input_ids, tree.token_ids[None]], 1), pixel_values=pixel_values, attention_mask=tree_mask,
              position_ids=tree_positions, use_cache=True, logits_to_keep=tree.num_nodes + 1)  # fmt: skip

    def decode_step():
        model(greedy_ids[:, :1], **{CACHE_KEY: prefilled}, position_ids=positions[:, -1:] + 1, use_cache=True)
        truncate_cache(prefilled, prompt_length)

    def verify_tree_after_prefill():
        model(after_ids, **{CACHE_KEY: prefilled}, attention_mask=after_mask, position_ids=after_positions,
              use_cache=True, logits_to_keep=tree.num_nodes + 1)  # fmt: skip
        truncate_cache(prefilled, prompt_length)

    def draft_step():
        draft_head(embeds[:, -1:], prompt_hidden[:, -1:], positions[:, -1:] + 1, None, head_cache)
        truncate_cache(head_cache, prompt_length - 1)

    def draft_catch_up():
        cache = DynamicCache()
        draft_head(embeds[:, 1:], prompt_hidden[:, :-1], positions[:, :-1],
                   causal_mask(prompt_length - 1, 0, dtype, device), cache)  # fmt: skip

    def greedy_predict_action():
        model.predict_action(input_ids=official_ids, pixel_values=pixel_values, unnorm_key=UNNORM_KEY)

    stats_box = {}

    def speculative_all_right():
        model.predict_action(input_ids=official_ids, pixel_values=pixel_values, unnorm_key=UNNORM_KEY,
                             draft_ids=right_ids)  # fmt: skip

    tree_drafter = DraftHeadDrafter(draft_head, tree=DraftTreeConfig(top_k=8, depth=ACTION_DIM - 1, total_tokens=50))

    def speculative_tree():
        model.predict_action(input_ids=official_ids, pixel_values=pixel_values, unnorm_key=UNNORM_KEY,
                             assistant_model=tree_drafter)  # fmt: skip

    with torch.no_grad():
        for name, kwargs in (
            ("right drafts", dict(draft_ids=right_ids)),
            ("untrained tree", dict(assistant_model=tree_drafter)),
        ):
            out = model.generate(input_ids, pixel_values=pixel_values, max_new_tokens=ACTION_DIM,
                                 min_new_tokens=ACTION_DIM, action_layout=model.action_layout(UNNORM_KEY),
                                 return_dict_in_generate=True, **kwargs)  # fmt: skip
            stats_box[f"{name}: target forwards"] = out.speculation.num_target_forwards

    operations = {
        "vision towers + projector": vision_op,
        f"prefill ({prompt_length} tokens, vision included)": prefill,
        f"prefill + {ACTION_DIM} drafted (chain)": prefill_chain,
        f"prefill + {tree.num_nodes} drafted (tree mask)": prefill_tree,
        f"decode step (cache {prompt_length})": decode_step,
        f"verify a {tree.num_nodes}-node tree after the prefill": verify_tree_after_prefill,
        f"draft-head step (cache {prompt_length})": draft_step,
        "draft-head catch-up over the prompt": draft_catch_up,
        "greedy predict_action": greedy_predict_action,
        "speculative predict_action, 7 drafts all right": speculative_all_right,
        "speculative predict_action, EAGLE-2 tree of the untrained head (50 nodes)": speculative_tree,
    }
    times = {name: [] for name in operations}
    order = list(operations)
    with torch.no_grad():
        for round_index in range(args.warmup + args.rounds):
            random.Random(round_index).shuffle(order)
            for name in order:
                synchronize()
                start = time.perf_counter()
                operations[name]()
                synchronize()
                if round_index >= args.warmup:
                    times[name].append(1000 * (time.perf_counter() - start))
    median = {name: statistics.median(values) for name, values in times.items()}
    greedy_action = median["greedy predict_action"]
    prior_action = median["speculative predict_action, 7 drafts all right"]
    tree_action = (median[f"prefill ({prompt_length} tokens, vision included)"]
                   + median["draft-head catch-up over the prompt"]
                   + (ACTION_DIM - 1) * median[f"draft-head step (cache {prompt_length})"]
                   + median[f"verify a {tree.num_nodes}-node tree after the prefill"])  # fmt: skip
    device_name = torch.cuda.get_device_name() if device.type == "cuda" else "cpu"
    print(f"device: {device_name}, torch {torch.__version__}, {dtype}, sdpa; {args.rounds} rounds"
          + ("; CHECK MODE (small towers, 2 layers)" if args.check else ""))  # fmt: skip
    print("\n| operation | median ms | p10-p90 ms |\n|---|---:|---|")
    for name, values in times.items():
        deciles = statistics.quantiles(values, n=10)
        print(f"| {name} | {median[name]:.2f} | {deciles[0]:.2f}-{deciles[-1]:.2f} |")
    ideal = {
        "greedy predict_action": greedy_action,
        "all drafts right, verified in the prefill (one target forward)": prior_action,
        "EAGLE tree, best case (prefill, catch-up, 6 head steps, one tree verification)": tree_action,
    }
    print("\n| per action | ms | speed-up vs greedy |\n|---|---:|---:|")
    for name, value in ideal.items():
        print(f"| {name} | {value:.2f} | {greedy_action / value:.2f}x |")
    with torch.no_grad():
        checks = {dtype_name: None for dtype_name in ("bfloat16", "float32")}
        checks["bfloat16"] = lossless_checks(model, draft_head, tree_drafter, input_ids, pixel_values)
        if device.type == "cuda":
            model.float(), draft_head.float()
        checks["float32"] = lossless_checks(model, draft_head, tree_drafter, input_ids, pixel_values.float())
    stats_box["lossless checks"] = checks
    print(f"\nchecks: {json.dumps(stats_box, indent=1)}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"median_ms": median, "per_action_ms": ideal, "samples_ms": times, "check": stats_box,
                       "device": device_name, "rounds": args.rounds,
                       "attn_implementation": model.config.text_config._attn_implementation}, f, indent=2)  # fmt: skip


if __name__ == "__main__":
    main()
