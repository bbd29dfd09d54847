"""bf16: a speculation-enabled target runs eager attention, for greedy and speculative calls alike, so that r=0 departs
from greedy decoding only at rare rounding flips instead of at every near-tie (sdpa); the option turns it off."""

import copy
import logging

import pytest
import torch
from transformers import LlamaForCausalLM

from hf_specvla import DraftHead, DraftHeadDrafter, DraftTreeConfig, JacobiDrafter, enable_speculation
from hf_specvla.speculative import ComposedDrafter, disable_speculation

from ..conftest import llava_prompt, tiny_llama_config


def bf16_llama(**options):
    torch.manual_seed(0)  # 4 layers: deep enough for sdpa's rounding to flip near-ties (8 of 60 prompts here)
    model = LlamaForCausalLM(tiny_llama_config(num_hidden_layers=4, attn_implementation="sdpa")).eval()
    return enable_speculation(model, **options).to(torch.bfloat16)


def prompts(n: int, seed: int = 0) -> list[torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    lengths = torch.randint(2, 30, (n,), generator=generator).tolist()
    return [torch.randint(3, 320, (1, length), generator=generator) for length in lengths]


def drafters(head):
    tree = DraftTreeConfig(top_k=3, total_tokens=12)
    return {
        "head chain": {"assistant_model": head},
        "head tree": {"assistant_model": DraftHeadDrafter(head, tree=tree)},
        "jacobi": {"assistant_model": JacobiDrafter()},
        "jacobi + tree": {
            "assistant_model": ComposedDrafter([JacobiDrafter(fill=False), DraftHeadDrafter(head, tree=tree)])
        },
    }


def departures(model, head, count: int) -> tuple[int, int]:
    """(generations that differ from greedy decoding's, generations) over ``count`` prompts, every drafter, drafts known
    up front (right, and wrong from the 5th token), and left-padded batches of 3 prompts."""
    differ = total = 0
    rows = prompts(count)
    for input_ids in rows:
        expected = model.generate(input_ids=input_ids, max_new_tokens=16, do_sample=False)
        right = expected[:, input_ids.shape[1] :]
        wrong_from_4 = right.clone()
        wrong_from_4[:, 4:] = (wrong_from_4[:, 4:] + 1) % 320
        cases = {**drafters(head), "right drafts": {"draft_ids": right}, "wrong from 4": {"draft_ids": wrong_from_4}}
        for kwargs in cases.values():
            out = model.generate(input_ids=input_ids, max_new_tokens=16, do_sample=False, **kwargs)
            differ, total = differ + int(not torch.equal(out, expected)), total + 1
    for start in range(0, count - 2, 3):
        batch = left_padded(rows[start : start + 3])
        expected = model.generate(**batch, max_new_tokens=12, do_sample=False)
        for kwargs in drafters(head).values():
            out = model.generate(**batch, max_new_tokens=12, do_sample=False, **kwargs)
            differ, total = differ + int(not torch.equal(out, expected)), total + 1
    return differ, total


def left_padded(rows: list[torch.Tensor]) -> dict:
    width = max(r.shape[1] for r in rows)
    input_ids = torch.cat([torch.cat([torch.zeros(1, width - r.shape[1], dtype=torch.long), r], 1) for r in rows])
    mask = torch.cat([torch.cat([torch.zeros(1, width - r.shape[1]), torch.ones(1, r.shape[1])], 1) for r in rows])
    return {"input_ids": input_ids, "attention_mask": mask.long()}


def head_for(model, action_tokenizer):
    torch.manual_seed(2)
    head = DraftHead.from_target(model, action_tokenizer, action_dim=7, draft_action_tokens_only=False)
    return head.eval().to(torch.bfloat16)


@pytest.mark.sampling  # ~85 s: a rate over many bf16 calls
def test_bf16_eager_attention_makes_r0_departures_rare(action_tokenizer):
    """sdpa departs from greedy at near-ties (25 of 200 generations of this model on the CPU it was written on); the
    switch to eager attention leaves the rare rounding flip of a matmul whose accumulation order depends on the
    forward's token count (0 of 200 there). On any CPU: at most a quarter of sdpa's departures, or one."""
    exact = bf16_llama()
    kept = bf16_llama(exact_reduced_precision=False)
    differ_exact, total = departures(exact, head_for(exact, action_tokenizer), 24)
    differ_kept, _ = departures(kept, head_for(kept, action_tokenizer), 24)
    assert exact.config._attn_implementation == "eager" and kept.config._attn_implementation == "sdpa"
    assert differ_exact <= max(1, differ_kept // 4), (differ_exact, differ_kept, total)


def test_bf16_llava_switches_every_attention_and_decodes_as_greedy(tiny_llava, random_llava_draft):
    model, head = copy.deepcopy(tiny_llava).to(torch.bfloat16), copy.deepcopy(random_llava_draft).to(torch.bfloat16)
    generator = torch.Generator().manual_seed(0)
    differ = 0
    for i in range(10):
        prompt = llava_prompt(generator, text_len=2 + i % 5)
        prompt["pixel_values"] = prompt["pixel_values"].to(torch.bfloat16)
        expected = model.generate(**prompt, max_new_tokens=9, do_sample=False)
        out = model.generate(**prompt, max_new_tokens=9, do_sample=False, assistant_model=head)
        differ += int(not torch.equal(out, expected))
    assert model.config.text_config._attn_implementation == "eager"
    assert model.config.vision_config._attn_implementation == "eager"
    assert differ <= 1


def test_the_switch_is_logged_once_and_can_be_turned_off(caplog):
    model = bf16_llama()
    input_ids = prompts(1)[0]
    with caplog.at_level(logging.WARNING, logger="hf_specvla.speculative.precision"):
        model.generate(input_ids=input_ids, max_new_tokens=2, do_sample=False)
        model.generate(input_ids=input_ids, max_new_tokens=2, do_sample=False, assistant_model=JacobiDrafter())
    switched = [r for r in caplog.records if "switched from sdpa to eager" in r.getMessage()]
    assert len(switched) == 1 and "exact_reduced_precision=False" in switched[0].getMessage()

    kept = bf16_llama(exact_reduced_precision=False)
    kept.generate(input_ids=input_ids, max_new_tokens=2, do_sample=False, assistant_model=JacobiDrafter())
    assert kept.config._attn_implementation == "sdpa"
    disable_speculation(kept)
    assert not hasattr(kept, "_speculation_exact_reduced_precision")


def test_fp32_keeps_its_attention(tiny_llama, random_draft):
    before = tiny_llama.config._attn_implementation
    tiny_llama.generate(input_ids=prompts(1)[0], max_new_tokens=3, do_sample=False, assistant_model=random_draft)
    assert tiny_llama.config._attn_implementation == before


def test_bad_option_is_rejected():
    with pytest.raises(TypeError, match="exact_reduced_precision must be True or False, got 'yes'"):
        enable_speculation(LlamaForCausalLM(tiny_llama_config()), exact_reduced_precision="yes")


# --- compiled graphs in reduced precision: inductor's emulate_precision_casts -----------------------------------------
def test_the_engine_compiles_a_bf16_model_rounding_as_eager_decoding_does():
    """A bf16 / fp16 model's graphs compile with ``emulate_precision_casts`` (the mode turned into its options, which
    torch takes instead); an fp32 model, another backend or ``exact_reduced_precision=False`` keep the config as it
    is."""
    from transformers import CompileConfig

    from hf_specvla.speculative.precision import exact_compile_config

    model = LlamaForCausalLM(tiny_llama_config()).to(torch.bfloat16)
    enable_speculation(model)
    gpu = CompileConfig(fullgraph=True, dynamic=False)  # mode reduce-overhead: CUDA graphs
    adjusted = exact_compile_config(model, gpu)
    assert adjusted.mode is None and adjusted.options == {"triton.cudagraphs": True, "emulate_precision_casts": True}
    assert gpu.mode == "reduce-overhead" and gpu.options is None  # the caller's config untouched
    cpu = CompileConfig(fullgraph=True, dynamic=False, mode="default")
    cpu._compile_all_devices = True
    adjusted = exact_compile_config(model, cpu)
    assert adjusted.options == {"emulate_precision_casts": True} and adjusted._compile_all_devices
    assert exact_compile_config(model, CompileConfig(backend="eager")).backend == "eager"
    assert exact_compile_config(model, CompileConfig(backend="eager")).options is None
    assert exact_compile_config(model.float(), cpu) is cpu
    disable_speculation(model)
    enable_speculation(model.to(torch.bfloat16), exact_reduced_precision=False)
    assert exact_compile_config(model, cpu) is cpu


@pytest.mark.slow  # ~3 min: compiled greedy and compiled speculation, bf16, on the CPU
def test_bf16_compiled_speculation_keeps_compiled_greedys_tokens_in_one_forward():
    """Issue 85 item 3 on the CPU: a tiny random OpenVLA in bf16, 4 left-padded rows, drafts = transformers' compiled
    greedy's own tokens: compiled r=0 speculation gives those tokens, each call in one forward (before the engine's
    graphs emulated eager rounding: 5 of 168 tokens unlike, 7 forwards for 6 calls)."""
    pytest.importorskip("PIL")
    from hf_specvla.openvla import OpenVLAForActionPrediction
    from hf_specvla.speculative import compiled_decoding_kwargs
    from tests.openvla.test_openvla import PROMPT, tiny_config

    torch.manual_seed(0)
    model = OpenVLAForActionPrediction(tiny_config()).to(torch.bfloat16).eval()
    with torch.no_grad():
        model.get_output_embeddings().weight[31744:32000] *= 4
    enable_speculation(model)
    common = dict(max_new_tokens=7, min_new_tokens=7, do_sample=False, return_dict_in_generate=True, pad_token_id=32000)
    compiled = compiled_decoding_kwargs("cpu")
    unlike = forwards = 0
    for seed in range(4):
        generator = torch.Generator().manual_seed(seed)
        extra = [torch.randint(1000, 20000, (k,), generator=generator).tolist() for k in (0, 3, 7, 1)]
        image = [model.config.image_token_id] * model.num_patches  # each row: BOS, the image's rows, the words
        prompts = [PROMPT[:1] + image + PROMPT[1:] + words + [29871] for words in extra]
        width = max(map(len, prompts))
        ids = torch.tensor([[32000] * (width - len(p)) + p for p in prompts])
        mask = torch.tensor([[0] * (width - len(p)) + [1] * len(p) for p in prompts])
        pixels = torch.randn(4, 6, 28, 28, generator=generator).to(torch.bfloat16)
        inputs = dict(input_ids=ids, attention_mask=mask, pixel_values=pixels)
        with torch.no_grad():
            greedy = model.generate(**inputs, **common, **compiled).sequences[:, ids.shape[1] :]
            output = model.generate(**inputs, **common, **compiled, draft_ids=greedy[:, :-1])
        unlike += int((output.sequences[:, ids.shape[1] :] != greedy).sum())
        forwards += output.speculation.num_batch_forwards
    assert unlike == 0 and forwards == 4
