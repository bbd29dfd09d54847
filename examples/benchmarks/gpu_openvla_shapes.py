"""What speculation can save on OpenVLA-7B's shapes, on a GPU (random weights, bf16): the table in
docs/benchmarks.md ("OpenVLA-7B shapes on an H100").

Built here: the Llama-2-7B decoder exactly as the real ``openvla/openvla-7b`` config.json describes it
(transformers' LlamaForCausalLM, 32064-token vocabulary, sdpa), the two vision towers from timm when it is
installed (DINOv2 ViT-L/14-reg4 + SigLIP So400m/14 at 224 px: OpenVLA's fused backbone, run to their second-to-last
block as OpenVLA does) and the fused-GELU projector, plus a hf_specvla DraftHead sized for the decoder. This is
not the OpenVLA port (a later piece of work): the same shapes on the same kernels, so the same costs; the weights
are random, so only times are meaningful here.

Measured interleaved: every round runs every operation once, in a fresh random order; medians over the rounds,
each operation synchronised on the device. The prompt is OpenVLA's: 1 BOS + 256 image patches + 19 text tokens.

    python examples/benchmarks/gpu_openvla_shapes.py --config openvla-7b-config.json --rounds 30 --json out.json
"""

from __future__ import annotations

import argparse
import json
import random
import statistics
import time

import torch
from transformers import LlamaConfig, LlamaForCausalLM
from transformers.cache_utils import DynamicCache

from hf_specvla import (
    ActionLayout,
    ActionPriorDrafter,
    ActionTokenizer,
    DraftHead,
    DraftHeadDrafter,
    DraftTree,
    DraftTreeConfig,
    enable_speculation,
)
from hf_specvla.speculative.cache import truncate_cache
from hf_specvla.speculative.masks import causal_mask, to_additive_mask, tree_verification_allowed

PROMPT_LENGTH = 1 + 256 + 19
ACTION_DIM = 7


def build_vision(device, dtype):
    """OpenVLA's fused vision backbone + projector, or None without timm."""
    try:
        import timm
    except ImportError:
        return None
    towers = [
        timm.create_model(name, pretrained=False, num_classes=0, img_size=224).to(device, dtype).eval()
        for name in ("vit_large_patch14_reg4_dinov2", "vit_so400m_patch14_siglip_224")
    ]
    width = sum(t.embed_dim for t in towers)
    projector = torch.nn.Sequential(
        torch.nn.Linear(width, 4 * width), torch.nn.GELU(), torch.nn.Linear(4 * width, 4096), torch.nn.GELU(),
        torch.nn.Linear(4096, 4096),
    ).to(device, dtype)  # fmt: skip

    def vision(pixel_values):  # [1, 6, 224, 224]
        parts = torch.split(pixel_values, [3, 3], dim=1)
        patches = [t.get_intermediate_layers(x, n={len(t.blocks) - 2})[0] for t, x in zip(towers, parts)]
        return projector(torch.cat(patches, dim=2))  # [1, 256, 4096]

    return vision


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


def self_consistent_drafts(model, input_ids: torch.Tensor, drafts: torch.Tensor) -> torch.Tensor:
    """Drafts the prefill-with-drafts forward accepts in full: the fixed point of "append the drafts, take the
    argmax at each drafted place" (in fp32 these are greedy's own tokens; in bf16 the different kernel shapes of a
    decode step and of a longer prefill can flip a near-tied argmax)."""
    length = input_ids.shape[1]
    for _ in range(drafts.shape[1] + 1):
        logits = model(torch.cat([input_ids, drafts], 1)).logits[:, length - 1 : -1]
        predicted = logits.argmax(-1)
        if torch.equal(predicted, drafts):
            return drafts
        drafts = predicted
    raise RuntimeError("no self-consistent drafts")


def lossless_checks(model, draft_head, tree_drafter, input_ids) -> dict:
    """r=0 on this device: every drafter gives plain greedy's tokens; right drafts take one target forward."""
    greedy = model.generate(input_ids, max_new_tokens=ACTION_DIM, min_new_tokens=ACTION_DIM, do_sample=False)
    greedy_ids = greedy[:, input_ids.shape[1] :]
    layout = ActionLayout(ActionTokenizer(32000, 256), ACTION_DIM)
    drafters = [("chain", draft_head), ("tree", tree_drafter)]
    if bool(layout.tokenizer.is_action_token(greedy_ids).all()):
        drafters.append(("prior", ActionPriorDrafter([greedy_ids[0].tolist()], layout)))
    checks = {}
    for name, drafter in drafters:
        out = model.generate(input_ids, max_new_tokens=ACTION_DIM, min_new_tokens=ACTION_DIM, do_sample=False,
                             assistant_model=drafter, action_layout=layout, return_dict_in_generate=True)  # fmt: skip
        checks[f"{name}: identical to greedy"] = bool(torch.equal(out.sequences, greedy))
        checks[f"{name}: target forwards"] = out.speculation.num_target_forwards
    scores = model.generate(input_ids, max_new_tokens=ACTION_DIM, min_new_tokens=ACTION_DIM, do_sample=False,
                            output_logits=True, return_dict_in_generate=True).logits  # fmt: skip
    top2 = torch.stack(scores).float().topk(2, dim=-1).values  # [steps, 1, 2]
    margins = (top2[..., 0] - top2[..., 1]).flatten().tolist()
    checks["greedy top-1 minus top-2 logit, per step"] = [round(x, 4) for x in margins]
    drafted = model(torch.cat([input_ids, greedy_ids], 1)).logits[:, input_ids.shape[1] - 1 : -1].float()
    checks["max |logit| difference, decode steps vs one prefill with the drafts"] = round(
        float((torch.stack(scores)[:, 0].float() - drafted[0]).abs().max()), 4
    )
    checks["self-consistent drafts equal greedy's tokens"] = bool(
        torch.equal(self_consistent_drafts(model, input_ids, greedy_ids), greedy_ids)
    )
    return checks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", required=True, help="openvla-7b's config.json (its text_config is used)")
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--tree-nodes", type=int, default=50)
    parser.add_argument("--json", default=None, help="also write the results here")
    parser.add_argument("--device", default="cuda", help="cuda (the point), or cpu to check the script")
    args = parser.parse_args()
    device = torch.device(args.device)
    dtype = torch.bfloat16 if device.type == "cuda" else torch.float32

    def synchronize():
        if device.type == "cuda":
            torch.cuda.synchronize()

    torch.manual_seed(0)
    text_config = LlamaConfig(**json.load(open(args.config))["text_config"])
    text_config._attn_implementation = "sdpa"
    with torch.device(device):
        torch.set_default_dtype(dtype)
        model = LlamaForCausalLM(text_config).eval()
        torch.set_default_dtype(torch.float32)
    with torch.no_grad():  # as the reference fixture does: action rows x4, so that greedy decoding emits actions
        model.lm_head.weight[31744:32000] *= 4
    model = enable_speculation(model)
    vision = build_vision(device, dtype)
    draft_head = DraftHead.from_target(model, ActionTokenizer(32000, 256), action_dim=ACTION_DIM).eval()
    handles = draft_head.target_handles(model)
    generator = torch.Generator().manual_seed(0)
    input_ids = torch.randint(3, 31000, (1, PROMPT_LENGTH), generator=generator).to(device)
    pixel_values = torch.randn(1, 6, 224, 224, generator=generator).to(device, dtype)
    chain = torch.randint(31744, 32000, (1, ACTION_DIM), generator=generator).to(device)
    tree = random_tree(args.tree_nodes, ACTION_DIM - 1, generator, device)
    positions = torch.arange(PROMPT_LENGTH, device=device)[None]

    with torch.no_grad():
        prefilled = DynamicCache()
        out = model(input_ids, past_key_values=prefilled, use_cache=True, output_hidden_states=True)
        prompt_hidden = out.hidden_states[-1]  # [1, S, H]
        head_cache = DynamicCache()
        embeds = handles.embed_tokens(input_ids)
        draft_head(embeds[:, 1:], prompt_hidden[:, :-1], positions[:, :-1],
                   causal_mask(PROMPT_LENGTH - 1, 0, dtype, device), head_cache)  # fmt: skip
        greedy = model.generate(input_ids, max_new_tokens=ACTION_DIM, min_new_tokens=ACTION_DIM, do_sample=False)
        greedy_ids = greedy[:, PROMPT_LENGTH:]
        right_ids = self_consistent_drafts(model, input_ids, greedy_ids)

    tree_positions = torch.cat([positions, PROMPT_LENGTH + tree.depths[None]], dim=1)
    tree_mask = to_additive_mask(tree_verification_allowed(0, PROMPT_LENGTH, tree.ancestor_or_self), dtype)
    after_mask = to_additive_mask(tree_verification_allowed(PROMPT_LENGTH, 1, tree.ancestor_or_self), dtype)
    after_positions = torch.cat([positions[:, -1:] + 1, PROMPT_LENGTH + 1 + tree.depths[None]], dim=1)
    after_ids = torch.cat([greedy_ids[:, :1], tree.token_ids[None]], dim=1)

    def vision_op():
        if vision is not None:
            vision(pixel_values)

    def prefill():
        model(input_ids, use_cache=True, logits_to_keep=1)

    def prefill_chain():
        model(torch.cat([input_ids, chain], 1), use_cache=True, logits_to_keep=ACTION_DIM + 1)

    def prefill_tree():
        model(torch.cat([input_ids, tree.token_ids[None]], 1), attention_mask=tree_mask, position_ids=tree_positions,
              use_cache=True, logits_to_keep=tree.num_nodes + 1)  # fmt: skip

    def decode_step():
        model(greedy_ids[:, :1], past_key_values=prefilled, position_ids=positions[:, -1:] + 1, use_cache=True)
        truncate_cache(prefilled, PROMPT_LENGTH)

    def verify_tree_after_prefill():
        model(after_ids, past_key_values=prefilled, attention_mask=after_mask, position_ids=after_positions,
              use_cache=True, logits_to_keep=tree.num_nodes + 1)  # fmt: skip
        truncate_cache(prefilled, PROMPT_LENGTH)

    def draft_step():
        draft_head(embeds[:, -1:], prompt_hidden[:, -1:], positions[:, -1:] + 1, None, head_cache)
        truncate_cache(head_cache, PROMPT_LENGTH - 1)

    def draft_catch_up():
        cache = DynamicCache()
        draft_head(embeds[:, 1:], prompt_hidden[:, :-1], positions[:, :-1],
                   causal_mask(PROMPT_LENGTH - 1, 0, dtype, device), cache)  # fmt: skip

    def greedy_generate():
        model.generate(input_ids, max_new_tokens=ACTION_DIM, min_new_tokens=ACTION_DIM, do_sample=False)

    stats_box = {}

    def speculative_all_right():
        out = model.generate(input_ids, max_new_tokens=ACTION_DIM, min_new_tokens=ACTION_DIM, do_sample=False,
                             draft_ids=right_ids, return_dict_in_generate=True)  # fmt: skip
        stats_box["right drafts: target forwards"] = out.speculation.num_target_forwards

    tree_drafter = DraftHeadDrafter(draft_head, tree=DraftTreeConfig(top_k=8, depth=ACTION_DIM - 1, total_tokens=50))

    def speculative_tree():
        out = model.generate(input_ids, max_new_tokens=ACTION_DIM, min_new_tokens=ACTION_DIM, do_sample=False,
                             assistant_model=tree_drafter, return_dict_in_generate=True)  # fmt: skip
        stats_box["untrained tree: target forwards"] = out.speculation.num_target_forwards

    operations = {
        "vision towers + projector": vision_op,
        "prefill (276 tokens)": prefill,
        f"prefill + {ACTION_DIM} drafted (chain)": prefill_chain,
        f"prefill + {tree.num_nodes} drafted (tree mask)": prefill_tree,
        "decode step (cache 276)": decode_step,
        f"verify {tree.num_nodes}-node tree after the prefill": verify_tree_after_prefill,
        "draft-head step (cache 276)": draft_step,
        "draft-head catch-up over the prompt": draft_catch_up,
        f"greedy generate ({ACTION_DIM} tokens)": greedy_generate,
        "speculative generate, drafts all right": speculative_all_right,
        "speculative generate, EAGLE-2 tree of the untrained head (50 nodes)": speculative_tree,
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
    v = median["vision towers + projector"]
    greedy_action = v + median[f"greedy generate ({ACTION_DIM} tokens)"]
    prior_action = v + median["speculative generate, drafts all right"]
    tree_action = (v + median["prefill (276 tokens)"] + median["draft-head catch-up over the prompt"]
                   + (ACTION_DIM - 1) * median["draft-head step (cache 276)"]
                   + median[f"verify {tree.num_nodes}-node tree after the prefill"])  # fmt: skip
    device_name = torch.cuda.get_device_name() if device.type == "cuda" else "cpu"
    print(f"device: {device_name}, torch {torch.__version__}, {dtype}, sdpa; "
          f"vision: {'timm' if vision else 'not measured (no timm)'}; {args.rounds} rounds")  # fmt: skip
    print("\n| operation | median ms | p10-p90 ms |\n|---|---:|---|")
    for name, values in times.items():
        deciles = statistics.quantiles(values, n=10)
        print(f"| {name} | {median[name]:.2f} | {deciles[0]:.2f}-{deciles[-1]:.2f} |")
    ideal = {
        "greedy action (vision + generate)": greedy_action,
        "all drafts right, verified in the prefill (one target forward)": prior_action,
        "EAGLE tree, best case (prefill, catch-up, 6 head steps, one tree verification)": tree_action,
    }
    print("\n| per action | ms | speed-up vs greedy |\n|---|---:|---:|")
    for name, value in ideal.items():
        print(f"| {name} | {value:.2f} | {greedy_action / value:.2f}x |")
    with torch.no_grad():
        checks = {dtype_name: None for dtype_name in ("bfloat16", "float32")}
        checks["bfloat16"] = lossless_checks(model, draft_head, tree_drafter, input_ids)
        if device.type == "cuda":
            model.float(), draft_head.float()
        checks["float32"] = lossless_checks(model, draft_head, tree_drafter, input_ids)
    stats_box["lossless checks"] = checks
    print(f"\nchecks: {json.dumps(stats_box, indent=1)}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"median_ms": median, "per_action_ms": ideal, "samples_ms": times, "check": stats_box,
                       "device": device_name, "rounds": args.rounds}, f, indent=2)  # fmt: skip


if __name__ == "__main__":
    main()
