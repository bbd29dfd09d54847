"""The OpenVLA port: config and keys of the real 7B, layouts, save/load, speculation, bad input (no fixture needed)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from accelerate import init_empty_weights
from PIL import Image
from safetensors.torch import load_file, save_file
from transformers import AutoConfig, AutoModelForImageTextToText

from hf_specvla import ActionPriorDrafter, ComposedDrafter, DraftHead, DraftHeadDrafter, DraftTreeConfig
from hf_specvla.openvla import (
    OpenVLAConfig,
    OpenVLAForActionPrediction,
    OpenVLAImageProcessor,
    OpenVLAProcessor,
    VisionTowerSpec,
    register_vision_tower,
)
from hf_specvla.openvla.modeling_openvla import PROMPT_END_TOKEN_ID
from hf_specvla.training.draft_head import DraftTrainingConfig
from hf_specvla.training.openvla_draft import (
    FRAMES_FILE,
    distillation_prompts,
    load_frames,
    openvla_prompts,
    train_openvla_draft_head,
)

HUB_7B = Path(__file__).resolve().parents[3] / "shared" / "openvla-reference" / "hub-openvla-7b"
needs_hub_files = pytest.mark.skipif(not HUB_7B.is_dir(), reason=f"{HUB_7B} (the shared OpenVLA reference) is absent")

TINY_DINO, TINY_SIGLIP = "test-tiny-dinov2-reg4", "test-tiny-siglip"
register_vision_tower(
    TINY_DINO,
    VisionTowerSpec(32, 3, 2, 64, class_token=True, num_register_tokens=4, no_embed_class=True, layer_scale=True),
    exist_ok=True,
)
register_vision_tower(TINY_SIGLIP, VisionTowerSpec(24, 3, 2, 40, attention_pool=True), exist_ok=True)

ACTION_DIM = 7
NORM_STATS = {
    "tiny_dataset": {
        "action": {
            "q01": [-0.5, -0.4, -0.3, -1.0, -1.0, -1.0, 0.0],
            "q99": [0.5, 0.4, 0.3, 1.0, 1.0, 1.0, 1.0],
            "mask": [True] * 6 + [False],
        }
    },
    "other_dataset": {"action": {"q01": [-1.0] * 7, "q99": [1.0] * 7}},
}
#: the fields of an official preprocessor_config.json the processor reads (resize-naive to 28 px, two towers)
PREPROCESSOR_FIELDS = {
    "image_resize_strategy": "resize-naive",
    "tvf_resize_params": [{"size": [28, 28], "interpolation": 3}] * 2,
    "tvf_crop_params": [{"output_size": [28, 28]}] * 2,
    "tvf_normalize_params": [{"mean": [0.5] * 3, "std": [0.5] * 3}] * 2,
}
PROMPT = [1, 512, 29901, 1724, 3158, 881, 278, 19964, 2125, 304, 5839, 701, 278, 2654, 2908, 29973, 13, 3744, 29901]


class FakePromptTokenizer:
    """Stands in for the Llama-2 tokenizer (not in the tests' files): every prompt gets ids from its words."""

    def __call__(self, text, padding=False, return_tensors="pt"):
        ids = [1] + [100 + sum(map(ord, word)) % 20000 for word in text.split()]
        return {"input_ids": torch.tensor([ids]), "attention_mask": torch.ones(1, len(ids), dtype=torch.long)}


def tiny_config(**overrides) -> OpenVLAConfig:
    settings = dict(
        norm_stats=NORM_STATS,
        timm_model_ids=[TINY_DINO, TINY_SIGLIP],
        image_sizes=[28, 28],
        text_config=dict(
            hidden_size=64,
            intermediate_size=128,
            num_hidden_layers=2,
            num_attention_heads=4,
            vocab_size=32064,
            pad_token_id=32000,
        ),
    )
    settings.update(overrides)
    return OpenVLAConfig(**settings)


@pytest.fixture(scope="module")
def tiny_openvla() -> OpenVLAForActionPrediction:
    torch.manual_seed(0)
    model = OpenVLAForActionPrediction(tiny_config()).eval()
    with torch.no_grad():  # make greedy decoding land on action tokens, as a trained OpenVLA does
        model.get_output_embeddings().weight[31744:32000] *= 8.0
    return model


def pixel_values(batch: int = 1, seed: int = 0) -> torch.Tensor:
    return torch.randn(batch, 6, 28, 28, generator=torch.Generator().manual_seed(seed))


def prompt_ids(extra: list[int] | None = None) -> torch.Tensor:
    return torch.tensor([PROMPT + (extra or [PROMPT_END_TOKEN_ID])])


# --- the real OpenVLA-7B config and keys ----------------------------------------------------------------------------
@needs_hub_files
def test_real_config_loads_and_round_trips(tmp_path):
    config = AutoConfig.from_pretrained(HUB_7B)  # no trust_remote_code: the registered local class
    assert isinstance(config, OpenVLAConfig)
    text = config.text_config
    assert (text.hidden_size, text.num_hidden_layers, text.intermediate_size, text.vocab_size) == (
        4096,
        32,
        11008,
        32064,
    )
    assert text.rms_norm_eps == 1e-6 and text.max_position_embeddings == 2048 and text.pad_token_id == 32000
    assert config.timm_model_ids == ["vit_large_patch14_reg4_dinov2.lvd142m", "vit_so400m_patch14_siglip_224"]
    assert config.image_sizes == [224, 224] and config.use_fused_vision_backbone
    assert config.action_vocab_end == 32000 and config.n_action_bins == 256
    bridge = config.norm_stats["bridge_orig"]["action"]
    assert len(bridge["q01"]) == 7 and bridge["mask"] == [True] * 6 + [False]
    config.save_pretrained(tmp_path)
    reloaded = OpenVLAConfig.from_pretrained(tmp_path)
    drop = {"_name_or_path"}
    assert {k: v for k, v in reloaded.to_dict().items() if k not in drop} == {
        k: v for k, v in config.to_dict().items() if k not in drop
    }


@needs_hub_files
def test_full_size_state_dict_keys_equal_the_real_index():
    config = AutoConfig.from_pretrained(HUB_7B)
    with init_empty_weights():
        model = OpenVLAForActionPrediction(config)
    index = json.loads((HUB_7B / "model.safetensors.index.json").read_text())["weight_map"]
    state = model.state_dict()
    assert len(index) == 982 and set(state) == set(index)
    shapes = {key: tuple(value.shape) for key, value in state.items()}
    assert shapes["language_model.model.embed_tokens.weight"] == (32064, 4096)
    assert shapes["language_model.lm_head.weight"] == (32064, 4096)
    assert shapes["vision_backbone.featurizer.pos_embed"] == (1, 256, 1024)
    assert shapes["vision_backbone.featurizer.reg_token"] == (1, 4, 1024)
    assert shapes["vision_backbone.featurizer.blocks.23.ls2.scale_factor"] == (1024,)
    assert shapes["vision_backbone.fused_featurizer.blocks.26.attn.qkv.weight"] == (3456, 1152)
    assert shapes["vision_backbone.fused_featurizer.blocks.0.mlp.fc1.weight"] == (4304, 1152)
    assert shapes["vision_backbone.fused_featurizer.attn_pool.kv.weight"] == (2304, 1152)
    assert shapes["projector.fc1.weight"] == (8704, 2176) and shapes["projector.fc3.weight"] == (4096, 4096)
    assert 7.5e9 < sum(value.numel() for value in state.values()) < 7.6e9


@needs_hub_files
def test_processor_from_the_real_files():
    processor = OpenVLAProcessor.from_pretrained(HUB_7B)
    prompt = processor.prompt("Pick up the red block")
    assert prompt == "In: What action should the robot take to pick up the red block?\nOut:"
    image = np.random.default_rng(0).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    inputs = processor(prompt, image)
    assert inputs["input_ids"].tolist() == [PROMPT]
    assert inputs["attention_mask"].tolist() == [[1] * len(PROMPT)]
    assert inputs["pixel_values"].shape == (1, 6, 224, 224) and inputs["pixel_values"].dtype == torch.float32
    from_pil = processor.image_processor(Image.fromarray(image))
    assert torch.equal(from_pil, inputs["pixel_values"])
    # the SigLIP half is (x - 0.5) / 0.5: a uniform grey image maps to one known value
    grey = processor.image_processor(np.full((50, 60, 3), 255, dtype=np.uint8))
    assert torch.allclose(grey[:, 3:], torch.ones(1, 3, 224, 224))


# --- layouts, save/load ---------------------------------------------------------------------------------------------
@torch.no_grad()
def test_official_layout_equals_image_token_layout(tiny_openvla):
    model, ids, pixels = tiny_openvla, prompt_ids(), pixel_values()
    official = model(input_ids=ids, attention_mask=torch.ones_like(ids), pixel_values=pixels).logits
    assert official.shape == (1, ids.shape[1] + model.num_patches, 32064)
    with_tokens, mask = model.add_image_tokens(ids, torch.ones_like(ids))
    assert int((with_tokens == model.config.image_token_id).sum()) == model.num_patches == 4
    placed = model(input_ids=with_tokens, attention_mask=mask, pixel_values=pixels).logits
    torch.testing.assert_close(placed, official, rtol=0, atol=0)
    # training: the same loss either way (image rows ignored)
    labels = ids.clone()
    official_loss = model(input_ids=ids, labels=labels, pixel_values=pixels).loss
    placed_loss = model(input_ids=with_tokens, labels=model.add_image_tokens(labels)[0], pixel_values=pixels).loss
    torch.testing.assert_close(placed_loss, official_loss, rtol=0, atol=0)
    # generate: the official layout's sequences come back without image rows, equal to the other layout's
    generated = model.generate(ids, pixel_values=pixels, max_new_tokens=ACTION_DIM, do_sample=False)
    generated_with_tokens = model.generate(with_tokens, pixel_values=pixels, max_new_tokens=ACTION_DIM, do_sample=False)
    assert generated.shape == (1, ids.shape[1] + ACTION_DIM)
    assert torch.equal(generated[:, ids.shape[1] :], generated_with_tokens[:, with_tokens.shape[1] :])
    # greedy generate's first token is the forward's argmax after the prompt
    assert int(generated[0, ids.shape[1]]) == int(official[0, -1].argmax())
    # a batched forward equals its rows
    batch = model(input_ids=ids.repeat(2, 1), pixel_values=torch.cat([pixels, pixel_values(seed=1)])).logits
    torch.testing.assert_close(batch[:1], official, rtol=1e-5, atol=1e-5)


@torch.no_grad()
def test_save_and_load_through_the_auto_class(tiny_openvla, tmp_path):
    tiny_openvla.save_pretrained(tmp_path)
    saved_keys = set(load_file(tmp_path / "model.safetensors"))
    assert saved_keys == set(tiny_openvla.state_dict())  # the checkpoint layout, no key mapping either way
    loaded = AutoModelForImageTextToText.from_pretrained(tmp_path)
    assert isinstance(loaded, OpenVLAForActionPrediction)
    ids, pixels = prompt_ids(), pixel_values()
    torch.testing.assert_close(
        loaded(input_ids=ids, pixel_values=pixels).logits, tiny_openvla(input_ids=ids, pixel_values=pixels).logits
    )
    bf16 = OpenVLAForActionPrediction.from_pretrained(tmp_path, dtype=torch.bfloat16)
    assert bf16.dtype == torch.bfloat16 and bf16(input_ids=ids, pixel_values=pixels).logits.dtype == torch.bfloat16
    assert {p.dtype for p in bf16.parameters()} == {torch.bfloat16}
    # sharded like the 7B (an index + shards), through accelerate's device_map and low_cpu_mem_usage
    tiny_openvla.save_pretrained(tmp_path / "sharded", max_shard_size="2MB")
    assert (tmp_path / "sharded" / "model.safetensors.index.json").is_file()
    sharded = OpenVLAForActionPrediction.from_pretrained(tmp_path / "sharded", device_map="cpu", low_cpu_mem_usage=True)
    torch.testing.assert_close(
        sharded(input_ids=ids, pixel_values=pixels).logits, tiny_openvla(input_ids=ids, pixel_values=pixels).logits
    )


@torch.no_grad()
def test_predict_action_official_semantics(tiny_openvla):
    model, pixels = tiny_openvla, pixel_values()
    generated = model.generate(prompt_ids(), pixel_values=pixels, max_new_tokens=ACTION_DIM, do_sample=False)
    tokens = generated[0, -ACTION_DIM:].numpy()
    assert model.action_tokenizer.is_action_token(tokens).all()
    stats = NORM_STATS["tiny_dataset"]["action"]
    bins = np.linspace(-1, 1, 256)
    centers = (bins[:-1] + bins[1:]) / 2
    normalized = centers[np.clip(32000 - tokens - 1, 0, 254)]
    low, high = np.array(stats["q01"]), np.array(stats["q99"])
    expected = np.where(stats["mask"], 0.5 * (normalized + 1) * (high - low) + low, normalized)
    # the official call: a prompt without the 29871 token, which predict_action appends
    action = model.predict_action(
        input_ids=torch.tensor([PROMPT]), pixel_values=pixels, unnorm_key="tiny_dataset", do_sample=False
    )
    np.testing.assert_array_equal(action, expected)
    # the mask passed with it (one token short in the official code) is extended
    with_mask = model.predict_action(
        input_ids=torch.tensor([PROMPT]),
        attention_mask=torch.ones(1, len(PROMPT), dtype=torch.long),
        pixel_values=pixels,
        unnorm_key="tiny_dataset",
    )
    np.testing.assert_array_equal(with_mask, expected)
    assert model.action_token_ids(action, "tiny_dataset").tolist() == [tokens.tolist()]


# --- speculation ----------------------------------------------------------------------------------------------------
@torch.no_grad()
def test_speculation_at_r0_equals_greedy(tiny_openvla):
    model, ids, pixels = tiny_openvla, prompt_ids(), pixel_values()
    greedy = model.generate(ids, pixel_values=pixels, max_new_tokens=ACTION_DIM, do_sample=False)
    torch.manual_seed(1)
    head = DraftHead.from_target(model, num_draft_tokens=3)
    assert head.config.action_vocab_size == 32000  # the target's action layout, not the padded vocabulary
    greedy_tokens = greedy[0, -ACTION_DIM:].tolist()
    wrong = [31744 + (t - 31744 + 50) % 256 for t in greedy_tokens]
    half_right = greedy_tokens[:3] + wrong[3:]
    layout = model.action_layout("tiny_dataset")
    tree = DraftHeadDrafter(head, tree=DraftTreeConfig(top_k=4, depth=4, total_tokens=12))
    prior = ActionPriorDrafter([wrong, half_right], layout)
    for kwargs in (
        dict(assistant_model=head),
        dict(assistant_model=tree),
        dict(assistant_model=ComposedDrafter([prior, tree]), action_layout=layout),
        dict(draft_ids=torch.tensor([greedy_tokens])),
        dict(draft_ids=torch.tensor([wrong])),
        dict(draft_ids=torch.tensor([half_right])),
        dict(assistant_model=head, draft_ids=torch.tensor([half_right])),
    ):
        output = model.generate(
            ids,
            pixel_values=pixels,
            max_new_tokens=ACTION_DIM,
            do_sample=False,
            return_dict_in_generate=True,
            bin_tolerance=0,
            **kwargs,
        )
        assert torch.equal(output.sequences, greedy), kwargs
    right = model.generate(
        ids,
        pixel_values=pixels,
        max_new_tokens=ACTION_DIM,
        draft_ids=torch.tensor([greedy_tokens]),
        return_dict_in_generate=True,
    )
    assert right.speculation.num_target_forwards == 1  # all 7 drafts verified inside the prefill
    action = model.predict_action(input_ids=ids, pixel_values=pixels, unnorm_key="tiny_dataset")
    for kwargs in (dict(assistant_model=head), dict(draft_ids=torch.tensor([wrong]), bin_tolerance=0)):
        np.testing.assert_array_equal(
            model.predict_action(input_ids=ids, pixel_values=pixels, unnorm_key="tiny_dataset", **kwargs), action
        )


def test_compiled_speculation_on_the_port_equals_greedy(tiny_openvla, caplog):
    """A static cache and a CompileConfig (dynamo's eager backend): every verification runs through the compiled call
    and r=0 stays greedy's action. The port's prefill compiles too (the first call compiles its graph, the second
    runs it): compiled, its forward takes the image-token layout that generate always passes, without reading the
    tokens' values (on an H100 that prefill had stayed eager: a launch-bound 7B forward of ~60 ms)."""
    from hf_specvla.speculative.compiled import reset_compilation
    from tests.speculative.test_compiled_verification import eager_compile_config

    model, ids, pixels = tiny_openvla, prompt_ids(), pixel_values()
    greedy = model.generate(ids, pixel_values=pixels, max_new_tokens=ACTION_DIM, do_sample=False)
    greedy_tokens = greedy[0, -ACTION_DIM:].tolist()
    half_right = greedy_tokens[:3] + [31744 + (t - 31744 + 50) % 256 for t in greedy_tokens[3:]]
    compiled = dict(cache_implementation="static", compile_config=eager_compile_config())
    reset_compilation()
    prefills = []
    try:
        with caplog.at_level("WARNING", logger="hf_specvla.speculative.compiled"):
            for _ in range(2):
                output = model.generate(ids, pixel_values=pixels, max_new_tokens=ACTION_DIM, do_sample=False,
                                        draft_ids=torch.tensor([half_right]), return_dict_in_generate=True,
                                        **compiled)  # fmt: skip
                assert torch.equal(output.sequences, greedy)
                prefills.append(output.speculation.compiled_prefills)
                assert output.speculation.compiled_widths
        assert prefills == [0, 1]  # the first call compiles the prefill graph (its own prefill eager), then runs it
        assert not [record for record in caplog.records if "stays eager" in record.getMessage()]
    finally:
        reset_compilation()


@torch.no_grad()
@pytest.mark.parametrize("preset", ["exact", "fast"])
def test_presets_work_end_to_end_on_the_port(tiny_openvla, preset, monkeypatch):
    """Issue 64: a preset's options (the previous actions + Jacobi drafts, compiled) went to generate as
    ``action_prior=True``, which the port refused. With the episode's memory (``previous_action_ids``) ``exact`` gives
    greedy's action at every step, the prior drafting from the memory; ``fast`` gives greedy's action whenever the
    previous action is greedy's (every draft right), and any action otherwise."""
    from hf_specvla.policies import DecodingMethod
    from hf_specvla.speculative.compiled import reset_compilation
    from tests.speculative.test_compiled_verification import eager_compile_config

    model, ids = tiny_openvla, prompt_ids()
    method = DecodingMethod.parse(preset, action_dim=ACTION_DIM)
    kwargs = method.generate_kwargs(None, action_dim=ACTION_DIM)
    assert kwargs["action_prior"] and kwargs["cache_implementation"] == "static"
    kwargs["compile_config"] = eager_compile_config()  # dynamo's eager backend: the same calls, compiled in seconds
    frames = [pixel_values(seed=seed) for seed in (0, 0, 1, 1, 2)]  # an observation seen twice: the prior is right
    greedy = [model.predict_action(input_ids=ids, pixel_values=p, unnorm_key="tiny_dataset") for p in frames]
    outputs = []  # what each call's generate returned (its speculation statistics)
    generate = model.generate

    def recorded_generate(*args, **options):
        outputs.append(generate(*args, **options))
        return outputs[-1]

    monkeypatch.setattr(model, "generate", recorded_generate)
    kwargs["return_dict_in_generate"] = True
    reset_compilation()
    try:
        memory: list[list[int]] = []  # the episode's, kept by the caller
        for step, pixels in enumerate(frames):
            previous = list(memory)
            action = model.predict_action(input_ids=ids, pixel_values=pixels, unnorm_key="tiny_dataset",
                                          previous_action_ids=memory, **kwargs)  # fmt: skip
            assert memory[-1] == model.action_token_ids(action, "tiny_dataset")[0].tolist()
            assert memory[:-1] == previous[-1:]  # the last two actions, oldest first
            repeated = step and np.array_equal(greedy[step - 1], greedy[step])
            if preset == "exact" or repeated:
                np.testing.assert_array_equal(action, greedy[step])
            stats = outputs[-1].speculation
            if repeated:  # the prior drafted greedy's action inside the prefill: one target forward
                assert stats.num_target_forwards == 1 and stats.accepted_by_drafter["prior"] == ACTION_DIM - 1
            elif step == 0:  # nothing to draft from but Jacobi guesses, verified through the compiled call
                assert stats.accepted_by_drafter["prior"] == 0 and stats.compiled_widths
            assert action.shape == (ACTION_DIM,) and np.isfinite(action).all()
    finally:
        reset_compilation()


def test_the_episode_memory_is_checked_before_decoding(tiny_openvla):
    model, ids, pixels = tiny_openvla, prompt_ids(), pixel_values()
    call = dict(input_ids=ids, pixel_values=pixels, unnorm_key="tiny_dataset")
    with pytest.raises(ValueError, match=r"action_prior=True drafts from the episode's previous actions.*pass "
                                         r"previous_action_ids="):  # fmt: skip
        model.predict_action(**call, action_prior=True)
    with pytest.raises(TypeError, match="previous_action_ids must be a list of actions .*got tuple"):
        model.predict_action(**call, previous_action_ids=())
    with pytest.raises(ValueError, match=r"previous action \[31800, 31801\] is not 7 action token ids"):
        model.predict_action(**call, previous_action_ids=[[31800, 31801]])
    with pytest.raises(TypeError, match="a flat list of ids is one action, wrap it in a list"):
        model.predict_action(**call, previous_action_ids=[31800] * ACTION_DIM)
    with pytest.raises(TypeError, match="action_prior must be True or False, got 1"):
        model.predict_action(**call, action_prior=1, previous_action_ids=[])
    with pytest.raises(ValueError, match="decodes one action, its action_dim=7 tokens: drop max_new_tokens=3"):
        model.predict_action(**call, max_new_tokens=3)
    # no previous action yet: nothing drafts, the options of a speculative call are harmless
    memory: list[list[int]] = []
    action = model.predict_action(**call, action_prior=True, previous_action_ids=memory, bin_tolerance=2)
    np.testing.assert_array_equal(action, model.predict_action(**call))
    assert len(memory) == 1


@torch.no_grad()
def test_a_sampling_generation_config_is_honoured_on_the_port(tiny_openvla):
    from transformers import GenerationConfig

    model, ids, pixels = tiny_openvla, prompt_ids(), pixel_values()
    call = dict(input_ids=ids, pixel_values=pixels, unnorm_key="tiny_dataset")
    greedy = model.predict_action(**call)
    sampling = GenerationConfig(do_sample=True, temperature=100.0, top_k=None)  # all but uniform
    draws = []
    for _ in range(2):
        torch.manual_seed(0)
        draws.append(model.predict_action(**call, generation_config=sampling))
    np.testing.assert_array_equal(draws[0], draws[1])  # seeded: the same draw
    assert not np.array_equal(draws[0], greedy)
    assert sampling.max_new_tokens is None  # the caller's config is left as it was
    np.testing.assert_array_equal(model.predict_action(**call, generation_config=sampling, do_sample=False), greedy)
    with pytest.raises(TypeError, match="generation_config must be a transformers GenerationConfig, got dict"):
        model.predict_action(**call, generation_config={"do_sample": True})


@torch.no_grad()
def test_relaxed_tokens_stay_within_r_bins_of_greedy_given_their_prefix(tiny_openvla):
    model, ids, pixels, tolerance = tiny_openvla, prompt_ids(), pixel_values(), 6
    greedy = model.generate(ids, pixel_values=pixels, max_new_tokens=ACTION_DIM, do_sample=False)[0, -ACTION_DIM:]
    drafts = [int(t) + (3 if int(t) + 3 < 32000 else -3) for t in greedy]  # every draft 3 bins off
    output = model.generate(
        ids,
        pixel_values=pixels,
        max_new_tokens=ACTION_DIM,
        draft_ids=torch.tensor([drafts]),
        bin_tolerance=tolerance,
        action_layout=model.action_layout("tiny_dataset"),
        return_dict_in_generate=True,
    )
    emitted = output.sequences[0, -ACTION_DIM:]
    assert not torch.equal(emitted, greedy)  # relaxed acceptance did accept off-greedy drafts
    full = model.add_image_tokens(output.sequences)[0]
    logits = model(input_ids=full, pixel_values=pixels).logits[0]
    start = full.shape[1] - ACTION_DIM
    for position in range(ACTION_DIM):
        own_greedy = int(logits[start + position - 1].argmax())
        distance = model.action_tokenizer.bin_distance(int(emitted[position]), own_greedy)
        assert distance <= tolerance, (position, int(emitted[position]), own_greedy)


# --- bad input ------------------------------------------------------------------------------------------------------
def test_unknown_unnorm_key_lists_the_valid_ones(tiny_openvla):
    with pytest.raises(ValueError, match=r"unnorm_key='nope'.*\['other_dataset', 'tiny_dataset'\]"):
        tiny_openvla.predict_action(input_ids=prompt_ids(), pixel_values=pixel_values(), unnorm_key="nope")
    with pytest.raises(ValueError, match="2 datasets; pass unnorm_key"):
        tiny_openvla.predict_action(input_ids=prompt_ids(), pixel_values=pixel_values())


def test_bad_images_are_refused():
    image_processor = OpenVLAImageProcessor.from_dict(PREPROCESSOR_FIELDS)
    with pytest.raises(TypeError, match="PIL.Image or an \\[H, W, 3\\] uint8 array, got str"):
        image_processor("frame.png")
    with pytest.raises(ValueError, match=r"shape \[H, W, 3\] \(RGB\), got \(32, 32, 4\)"):
        image_processor(np.zeros((32, 32, 4), dtype=np.uint8))
    with pytest.raises(ValueError, match=r"got \(32, 32\)"):
        image_processor(np.zeros((32, 32), dtype=np.uint8))
    with pytest.raises(ValueError, match="must be uint8"):
        image_processor(np.zeros((32, 32, 3), dtype=np.float32))


def test_image_modes_are_converted_exactly_or_refused_by_name():
    """8-bit modes become RGB as the official processor's ``convert("RGB")`` does; float and 16-bit images, which
    PIL would turn black or saturate, are refused naming the mode; an empty image list is a clear error."""
    image_processor = OpenVLAImageProcessor.from_dict(PREPROCESSOR_FIELDS)
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (40, 40, 3), dtype=np.uint8)
    expected = image_processor(Image.fromarray(rgb))
    torch.testing.assert_close(image_processor(rgb), expected)
    torch.testing.assert_close(image_processor(Image.fromarray(rgb).convert("RGBA")), expected)  # alpha dropped
    grey = Image.fromarray(rgb[..., 0])  # mode L
    torch.testing.assert_close(image_processor(grey), image_processor(np.repeat(rgb[..., :1], 3, axis=2)))
    palette = Image.fromarray(rgb).convert("P")
    torch.testing.assert_close(image_processor(palette), image_processor(palette.convert("RGB")))
    for mode, data in (("F", rgb[..., 0].astype(np.float32) / 255), ("I;16", rgb[..., 0].astype(np.uint16) * 257)):
        with pytest.raises(ValueError, match=f"a PIL image of mode '{mode}' cannot be converted to 8-bit RGB"):
            image = Image.fromarray(data)
            assert image.mode == mode
            image_processor(image)
    with pytest.raises(ValueError, match=r"got dtype float64 \(a float image in \[0, 1\]: \(image \* 255\)"):
        image_processor(rgb / 255.0)
    for empty in ([], None):
        with pytest.raises(ValueError, match="pass one image .* per prompt"):
            image_processor(empty)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (dict(image_sizes="28"), r"image_sizes must be a list of ints \(pixels\) or null, got '28' \(str\)"),
        (dict(timm_model_ids=TINY_DINO), r"timm_model_ids must be a list of timm model ids .*got 'test-tiny"),
        (dict(image_token_id="32063"), r"image_token_id must be an int \(a token id\) or null, got '32063' \(str\)"),
        (dict(use_fused_vision_backbone="no"), r"use_fused_vision_backbone must be true or false or null, got 'no'"),
        (dict(n_action_bins=True), r"n_action_bins must be an int, got True \(bool\)"),
        (dict(norm_stats=["bridge"]), r"norm_stats must be a dict of per-dataset statistics or null"),
    ],
)
def test_config_field_types_are_checked_naming_the_field(overrides, message):
    with pytest.raises(TypeError, match=message):
        tiny_config(**overrides)


def test_a_truncated_weights_file_is_named(tiny_openvla, tmp_path):
    folder = tmp_path / "ckpt"
    tiny_openvla.save_pretrained(folder)
    weights = folder / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:1000])  # an interrupted download
    with pytest.raises(OSError, match=r"could not read the OpenVLA checkpoint's weights '.*model.safetensors' "
                                      r"\(1,000 bytes\).*damaged or truncated.*download or save it again"):  # fmt: skip
        OpenVLAForActionPrediction.from_pretrained(folder)


def test_bad_pixel_values_and_prompts_are_refused(tiny_openvla):
    with pytest.raises(ValueError, match=r"\[B, 6, H, W\].*\(1, 3, 28, 28\)"):
        tiny_openvla(input_ids=prompt_ids(), pixel_values=torch.zeros(1, 3, 28, 28))
    with pytest.raises(ValueError, match="2 images for 1 prompts"):
        tiny_openvla(input_ids=prompt_ids(), pixel_values=pixel_values(2))
    partial = torch.cat([prompt_ids()[:, :1], torch.full((1, 2), tiny_openvla.config.image_token_id), prompt_ids()], 1)
    with pytest.raises(ValueError, match=r"exactly 4 .*got \[2\]"):
        tiny_openvla(input_ids=partial, pixel_values=pixel_values())


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (dict(arch_specifier="no-align+linear"), "arch_specifier='no-align\\+linear' is not supported"),
        (dict(timm_model_ids=["vit_large_patch14_clip_224.openai", TINY_SIGLIP]), "vit_large_patch14_clip_224.openai"),
        (dict(llm_backbone_id="phi-2-3b"), "llm_backbone_id='phi-2-3b' is not supported"),
        (dict(vision_backbone_id="clip-vit-l", timm_model_ids=None), "vision_backbone_id='clip-vit-l'"),
        (dict(timm_override_act_layers=["quick_gelu", None]), "timm_override_act_layers"),
    ],
)
def test_unsupported_architectures_are_named(overrides, message):
    with pytest.raises(ValueError, match=message):
        tiny_config(**overrides)


def test_broken_checkpoint_folders_are_named(tiny_openvla, tmp_path):
    folder = tmp_path / "ckpt"
    tiny_openvla.save_pretrained(folder)
    with pytest.raises(FileNotFoundError, match="does not exist .*not looked up on the hub"):
        OpenVLAForActionPrediction.from_pretrained(tmp_path / "missing")
    renamed = tmp_path / "renamed"
    shutil.copytree(folder, renamed)
    weights = load_file(renamed / "model.safetensors")
    weights["vision_backbone.featurizer.blocks.0.ls1.gamma"] = weights.pop(
        "vision_backbone.featurizer.blocks.0.ls1.scale_factor"
    )
    save_file(weights, renamed / "model.safetensors", metadata={"format": "pt"})
    with pytest.raises(
        ValueError, match=r"1 missing keys \(e.g. \['vision_backbone.featurizer.blocks.0.ls1.scale_factor'\]\)"
    ):
        AutoModelForImageTextToText.from_pretrained(renamed)
    with pytest.raises(FileNotFoundError, match="has no preprocessor_config.json: not an OpenVLA checkpoint folder"):
        OpenVLAProcessor.from_pretrained(folder)
    no_config = tmp_path / "no_config"
    shutil.copytree(folder, no_config)
    (no_config / "config.json").unlink()
    with pytest.raises(FileNotFoundError, match="has no config.json"):
        OpenVLAForActionPrediction.from_pretrained(no_config)
    (folder / "model.safetensors").unlink()
    with pytest.raises(FileNotFoundError, match="neither model.safetensors nor model.safetensors.index.json"):
        OpenVLAForActionPrediction.from_pretrained(folder)
    (folder / "model.safetensors.index.json").write_text(
        json.dumps({"weight_map": {"a": "model-00001-of-00002.safetensors"}})
    )
    with pytest.raises(FileNotFoundError, match=r"missing 1 of the 1 weight shards.*model-00001-of-00002"):
        OpenVLAForActionPrediction.from_pretrained(folder)


# --- draft-head training on OpenVLA frames --------------------------------------------------------------------------
def write_frames(folder: Path, count: int, previous_actions: list | None = None) -> None:
    rng = np.random.default_rng(3)
    (folder / "images").mkdir(parents=True)
    lines = []
    for index in range(count):
        Image.fromarray(rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)).save(folder / "images" / f"{index:03d}.png")
        instruction = ["Pick up the red block", "open the drawer"][index % 2]
        record = {"image": f"images/{index:03d}.png", "instruction": instruction}
        if previous_actions is not None and previous_actions[index] is not None:
            record["previous_action"] = previous_actions[index]
        lines.append(json.dumps(record))
    (folder / FRAMES_FILE).write_text("\n".join(lines) + "\n")


def test_draft_head_training_on_openvla_frames(tiny_openvla, tmp_path):
    processor = OpenVLAProcessor(OpenVLAImageProcessor.from_dict(PREPROCESSOR_FIELDS), FakePromptTokenizer())
    write_frames(tmp_path / "frames", 6)
    frames = load_frames(tmp_path / "frames")
    assert len(frames) == 6 and frames[1].instruction == "open the drawer" and frames[0].image.size == (40, 30)
    config = DraftTrainingConfig(
        output_dir=str(tmp_path / "head"), max_steps=4, batch_size=2, learning_rate=1e-3, save_every=2
    )
    head = train_openvla_draft_head(
        tiny_openvla, processor, frames[:4], frames[4:], config, unnorm_key="tiny_dataset", progress=False
    )
    assert (tmp_path / "head" / "validation.jsonl").is_file()
    loaded = DraftHead.from_pretrained(tmp_path / "head")
    assert loaded.config.target_fingerprint == head.config.target_fingerprint is not None
    prompt = openvla_prompts(tiny_openvla, processor, frames[4:5])[0]
    greedy = tiny_openvla.generate(**prompt, max_new_tokens=ACTION_DIM, do_sample=False)
    with torch.no_grad():
        drafted = tiny_openvla.generate(**prompt, max_new_tokens=ACTION_DIM, assistant_model=loaded, bin_tolerance=0)
    assert torch.equal(drafted, greedy)
    # resume continues the same run; the same folder with another model is refused before anything is labelled
    more = DraftTrainingConfig(**{**config.__dict__, "max_steps": 6, "resume": True})
    train_openvla_draft_head(
        tiny_openvla, processor, frames[:4], frames[4:], more, unnorm_key="tiny_dataset", progress=False
    )
    assert (tmp_path / "head" / "checkpoint-6").is_dir()
    torch.manual_seed(5)
    other = OpenVLAForActionPrediction(tiny_config()).eval()
    with pytest.raises(FileExistsError, match="holds another run: target: "):
        train_openvla_draft_head(
            other, processor, frames[:4], frames[4:], more, unnorm_key="tiny_dataset", progress=False
        )


def test_a_head_v2_trains_on_openvla_frames_with_previous_actions(tiny_openvla, tmp_path):
    """Head v2 (layers 2, middle, last; the robot's previous action; training-time test) through the OpenVLA recipe:
    trained, saved, and lossless with the previous action it reads."""
    processor = OpenVLAProcessor(OpenVLAImageProcessor.from_dict(PREPROCESSOR_FIELDS), FakePromptTokenizer())
    tokens = list(tiny_openvla.action_tokenizer.action_token_ids)
    previous = [
        None,
        tokens[:ACTION_DIM],
        tokens[10 : 10 + ACTION_DIM],
        None,
        tokens[-ACTION_DIM:],
        tokens[:ACTION_DIM],
    ]
    write_frames(tmp_path / "frames", 6, previous)
    frames = load_frames(tmp_path / "frames")
    assert frames[0].previous_action is None and frames[1].previous_action == tokens[:ACTION_DIM]
    config = DraftTrainingConfig(output_dir=str(tmp_path / "head"), max_steps=2, batch_size=2, learning_rate=1e-3,
                                 unroll_steps=3)  # fmt: skip
    train_openvla_draft_head(tiny_openvla, processor, frames[:4], frames[4:], config, unnorm_key="tiny_dataset",
                             progress=False, head_version="v2")  # fmt: skip
    loaded = DraftHead.from_pretrained(tmp_path / "head").eval()
    assert loaded.config.previous_action_input and loaded.config.feature_layers[-1] == -1
    prompt = openvla_prompts(tiny_openvla, processor, frames[4:5])[0]
    greedy = tiny_openvla.generate(**prompt, max_new_tokens=ACTION_DIM, do_sample=False)
    drafter = DraftHeadDrafter(loaded, tree=DraftTreeConfig(top_k=2, depth=4, total_tokens=8))
    drafter = drafter.with_previous_action(frames[4].previous_action)
    with torch.no_grad():
        drafted = tiny_openvla.generate(**prompt, max_new_tokens=ACTION_DIM, bin_tolerance=0, assistant_model=drafter)
    assert torch.equal(drafted, greedy)
    frames[5].previous_action = tokens[:3]
    with pytest.raises(ValueError, match=r"frame 0: previous_action must be 7 action token ids"):
        distillation_prompts(tiny_openvla, processor, frames[5:], "tiny_dataset")


def test_bad_frame_folders_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="has no frames.jsonl"):
        load_frames(tmp_path)
    (tmp_path / FRAMES_FILE).write_text('{"image": "missing.png", "instruction": "go"}\n')
    with pytest.raises(FileNotFoundError, match=r"frames.jsonl:1 names image 'missing.png'"):
        load_frames(tmp_path)
    (tmp_path / FRAMES_FILE).write_text('{"image": "missing.png"}\n')
    with pytest.raises(ValueError, match=r"frames.jsonl:1 has no instruction"):
        load_frames(tmp_path)
    (tmp_path / FRAMES_FILE).write_text("not json\n")
    with pytest.raises(ValueError, match=r"frames.jsonl:1 is not valid JSON"):
        load_frames(tmp_path)
