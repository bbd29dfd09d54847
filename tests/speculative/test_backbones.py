"""One set of checks over every supported backbone, the way transformers' ``GenerationTesterMixin`` runs one test over
every architecture: tiny random models (built in milliseconds), the last 256 ids of a 320-id vocabulary as action
bins, fp32.

For each text backbone and VLM: right drafts known up front pass in one target forward and give greedy's tokens;
wrong drafts, an untrained head's EAGLE-2 tree and a left-padded batch of 3 give greedy's tokens exactly at r=0; at
r > 0 every emitted action token is within r bins of the target's greedy token given its prefix. A static cache
(``cache_implementation="static"``, batch 1) gives the same tokens for every drafter and keeps the bound. Then the
cache kinds: sliding windows shorter than the drafts (exact), shorter than the generation (refused before any
forward), and caches that cannot be rolled back (refused before any forward).
"""

from __future__ import annotations

import pytest
import torch
from transformers import (
    AutoConfig,
    AutoModelForCausalLM,
    CLIPVisionConfig,
    DynamicCache,
    Gemma2Config,
    GemmaConfig,
    Idefics3Config,
    Idefics3ForConditionalGeneration,
    Idefics3VisionConfig,
    LlamaConfig,
    LlavaConfig,
    LlavaForConditionalGeneration,
    PaliGemmaConfig,
    PaliGemmaForConditionalGeneration,
    Qwen2VLConfig,
    Qwen2VLForConditionalGeneration,
    SiglipVisionConfig,
)
from transformers.cache_utils import DynamicIndexedLayer, DynamicSlidingWindowLayer, StaticCache

from hf_specvla import (
    ActionLayout,
    ActionTokenizer,
    ComposedDrafter,
    DraftHead,
    DraftHeadDrafter,
    DraftTreeConfig,
    JacobiDrafter,
    enable_speculation,
)
from hf_specvla.speculative import CACHE_KEY, cache_of

VOCAB = 320  # ids 64..319 are the 256 action bins
IMAGE = 5
PAD = 0
NEW_TOKENS = 7
TEXT = dict(vocab_size=VOCAB, hidden_size=64, intermediate_size=128, num_hidden_layers=2, num_attention_heads=4,
            num_key_value_heads=2, max_position_embeddings=256, bos_token_id=1, eos_token_id=2,
            pad_token_id=PAD)  # fmt: skip
VISION = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2, image_size=16,
              patch_size=8)  # fmt: skip
#: a window longer than prompt + new tokens (so the generation fits) but shorter than prompt + a draft tree
WINDOW = 24

#: text backbone -> the config overrides of its tiny model (``AutoConfig.for_model``)
TEXT_BACKBONES = {
    "llama": {},
    "mistral": {"sliding_window": WINDOW},
    "qwen2": {},
    "qwen3": {"head_dim": 16},
    "gemma": {"head_dim": 16},
    "gemma2": {"head_dim": 16, "sliding_window": WINDOW},
    "gemma3_text": {"head_dim": 16, "sliding_window": WINDOW, "layer_types": ["sliding_attention", "full_attention"]},
    "phi3": {},
    "olmo2": {},
}


class Backbone:
    """A tiny model and how to build its inputs (one prompt per row, text lengths differing, left-padded)."""

    def __init__(self, model, image_prefix, image_inputs, image_after_bos=True):
        self.model = enable_speculation(model.float().eval())
        self.image_prefix, self.image_inputs, self.image_after_bos = image_prefix, image_inputs, image_after_bos

    def inputs(self, text_lengths: list[int], seed: int = 0) -> dict:
        generator = torch.Generator().manual_seed(seed)
        rows = []
        for length in text_lengths:
            text = torch.randint(6, 64, (length,), generator=generator).tolist()
            rows.append([1, *self.image_prefix, *text] if self.image_after_bos else [*self.image_prefix, 1, *text])
        width = max(len(r) for r in rows)
        input_ids = torch.tensor([[PAD] * (width - len(r)) + r for r in rows])
        inputs = {"input_ids": input_ids}
        if any(len(r) < width for r in rows):
            inputs["attention_mask"] = (
                torch.arange(width)[None] >= torch.tensor([width - len(r) for r in rows])[:, None]
            ).long()
        inputs.update(self.image_inputs(input_ids, generator))
        return inputs


def _text(name: str) -> Backbone:
    torch.manual_seed(0)
    config = AutoConfig.for_model(name, **TEXT, **TEXT_BACKBONES[name])
    return Backbone(AutoModelForCausalLM.from_config(config), [], lambda ids, g: {})


def _llava() -> Backbone:
    torch.manual_seed(0)
    vision = CLIPVisionConfig(**VISION, projection_dim=32)
    config = LlavaConfig(vision_config=vision, text_config=LlamaConfig(**TEXT), image_token_id=IMAGE,
                         image_seq_length=4, vision_feature_select_strategy="default",
                         vision_feature_layer=-1)  # fmt: skip
    images = lambda ids, g: {"pixel_values": torch.randn(ids.shape[0], 3, 16, 16, generator=g)}  # noqa: E731
    return Backbone(LlavaForConditionalGeneration(config), [IMAGE] * 4, images)


def _paligemma(text_config) -> Backbone:
    torch.manual_seed(0)
    config = PaliGemmaConfig(vision_config=SiglipVisionConfig(**VISION), text_config=text_config, image_token_id=IMAGE,
                             projection_dim=64)  # fmt: skip
    config.text_config.num_image_tokens = 4

    def images(input_ids, generator):  # image tokens first, then <bos> and the prompt; a prefix of token type 0
        return {"pixel_values": torch.randn(input_ids.shape[0], 3, 16, 16, generator=generator),
                "token_type_ids": torch.zeros_like(input_ids)}  # fmt: skip

    # eager attention: sdpa drops the prefix's two-way attention (transformers 5.23), eager keeps it: the test sees it
    model = PaliGemmaForConditionalGeneration._from_config(config, attn_implementation="eager")
    return Backbone(model, [IMAGE] * 4, images, image_after_bos=False)


def _idefics3() -> Backbone:
    torch.manual_seed(0)
    config = Idefics3Config(vision_config=Idefics3VisionConfig(**VISION), text_config=LlamaConfig(**TEXT),
                            image_token_id=IMAGE, scale_factor=1)  # fmt: skip

    def images(input_ids, generator):  # one image per row (no splitting), every pixel real
        batch = input_ids.shape[0]
        return {"pixel_values": torch.randn(batch, 1, 3, 16, 16, generator=generator),
                "pixel_attention_mask": torch.ones(batch, 1, 16, 16, dtype=torch.bool)}  # fmt: skip

    return Backbone(Idefics3ForConditionalGeneration(config), [IMAGE] * 4, images)


def _qwen2_vl() -> Backbone:
    torch.manual_seed(0)
    text = {k: v for k, v in TEXT.items()}
    rope = {"rope_type": "default", "rope_theta": 10000.0, "mrope_section": [2, 3, 3]}
    vision = dict(depth=1, embed_dim=32, hidden_size=64, num_heads=2, patch_size=4, spatial_merge_size=2,
                  temporal_patch_size=2, in_channels=3)  # fmt: skip
    config = Qwen2VLConfig(text_config=dict(**text, rope_parameters=rope), vision_config=vision, image_token_id=IMAGE,
                           vision_start_token_id=3, vision_end_token_id=4)  # fmt: skip

    def images(input_ids, generator):  # a 4 x 4 grid of 4 x 4 patches, merged 2 x 2: four image tokens per row,
        batch = input_ids.shape[0]  # two rotary steps wide: text after the image is 2 positions behind its index
        return {"pixel_values": torch.randn(batch * 16, 3 * 2 * 4 * 4, generator=generator),
                "image_grid_thw": torch.tensor([[1, 4, 4]] * batch),
                "mm_token_type_ids": (input_ids == IMAGE).long()}  # fmt: skip

    return Backbone(Qwen2VLForConditionalGeneration(config), [3, *[IMAGE] * 4, 4], images)


VLMS = {
    "llava": _llava,
    "paligemma": lambda: _paligemma(GemmaConfig(**TEXT, head_dim=16)),
    "paligemma2": lambda: _paligemma(Gemma2Config(**TEXT, head_dim=16, sliding_window=WINDOW)),
    "idefics3": _idefics3,
    "qwen2_vl": _qwen2_vl,
}
BACKBONES = [*TEXT_BACKBONES, *VLMS]


@pytest.fixture(scope="module", params=BACKBONES)
def backbone(request) -> Backbone:
    name = request.param
    return VLMS[name]() if name in VLMS else _text(name)


def greedy(model, inputs, **kwargs):
    return model.generate(**inputs, max_new_tokens=NEW_TOKENS, min_new_tokens=NEW_TOKENS, do_sample=False, **kwargs)


def untrained_head(model) -> DraftHead:
    torch.manual_seed(1)
    return DraftHead.from_target(model, ActionTokenizer(VOCAB), action_dim=7, draft_action_tokens_only=False).eval()


# ----------------------------------------------------------------------------- r = 0
def test_right_drafts_pass_in_the_prefill(backbone):
    inputs = backbone.inputs([5])
    expected = greedy(backbone.model, inputs)
    drafts = expected[:, inputs["input_ids"].shape[1] : -1]  # all but the last token: it comes as the bonus
    out = greedy(backbone.model, inputs, draft_ids=drafts, return_dict_in_generate=True)
    assert torch.equal(out.sequences, expected)
    assert out.speculation.num_batch_forwards == 1  # the whole continuation verified inside the prefill


def test_wrong_drafts_and_candidates_decode_exactly(backbone):
    """Tokens and the target's logits at every emitted token are greedy's (logits catch a prefill that saw the
    prompt otherwise, e.g. without PaliGemma's two-way prefix attention, even where the argmax survives)."""
    inputs = backbone.inputs([6])
    expected = greedy(backbone.model, inputs, return_dict_in_generate=True, output_logits=True)
    right = expected.sequences[:, inputs["input_ids"].shape[1] : -1]
    wrong = right.clone()
    wrong[:, 2] = (wrong[:, 2] + 1) % VOCAB
    candidates = torch.stack([wrong, (right + 7) % VOCAB, right[:, [0, 0, 0, 0, 0, 0]]], dim=1)  # [1, 3, 6]
    for drafts in (wrong, candidates):
        out = greedy(backbone.model, inputs, draft_ids=drafts, return_dict_in_generate=True, output_logits=True)
        assert torch.equal(out.sequences, expected.sequences)
        torch.testing.assert_close(torch.stack(out.logits), torch.stack(expected.logits), rtol=1e-4, atol=1e-4)


def test_untrained_head_chain_and_tree_decode_exactly(backbone):
    inputs = backbone.inputs([4])
    expected = greedy(backbone.model, inputs)
    head = untrained_head(backbone.model)
    for assistant in (head, DraftHeadDrafter(head, tree=DraftTreeConfig(top_k=3, depth=4, total_tokens=12))):
        assert torch.equal(greedy(backbone.model, inputs, assistant_model=assistant), expected)


def head_v2(model) -> DraftHead:
    """An untrained head v2 (a low and the top layer, the previous action as input), its inputs randomised."""
    torch.manual_seed(2)
    head = DraftHead.from_target(model, ActionTokenizer(VOCAB), action_dim=7, draft_action_tokens_only=False,
                                 feature_layers=[1, -1], previous_action_input=True)  # fmt: skip
    with torch.no_grad():
        head.feature_fuse.weight.normal_(0, 0.1)
        head.previous_embedding.weight.normal_(0, 1.0)
    return head.eval()


@pytest.mark.parametrize("cache_implementation", [None, "static"])
def test_head_v2_with_a_previous_action_decodes_exactly(backbone, cache_implementation):
    """Head v2's chain and tree, told a previous action, alone and after the target's Jacobi guesses."""
    inputs = backbone.inputs([4], seed=5)
    expected = greedy(backbone.model, inputs)
    previous = [VOCAB - 1 - b for b in (3, 250, 128, 0, 17, 99, 255)]
    head = head_v2(backbone.model)
    chain = DraftHeadDrafter(head).with_previous_action(previous)
    tree = DraftHeadDrafter(head, tree=DraftTreeConfig(top_k=3, depth=4, total_tokens=12))
    tree = tree.with_previous_action(previous)
    for assistant in (chain, tree, ComposedDrafter([JacobiDrafter(fill=False), tree])):
        out = greedy(backbone.model, inputs, assistant_model=assistant, cache_implementation=cache_implementation)
        assert torch.equal(out, expected), assistant


def test_jacobi_drafts_decode_exactly(backbone):
    """The target's own guesses past a rejection: alone (from a fill chain), after wrong drafts in the prefill, and
    beside the head's tree."""
    inputs = backbone.inputs([4], seed=4)
    expected = greedy(backbone.model, inputs)
    wrong = expected[:, inputs["input_ids"].shape[1] : -1].clone()
    wrong[:, 1] = (wrong[:, 1] + 1) % VOCAB
    tree = DraftHeadDrafter(untrained_head(backbone.model), tree=DraftTreeConfig(top_k=3, depth=4, total_tokens=12))
    jacobi_tree = ComposedDrafter([JacobiDrafter(fill=False), tree])
    for kwargs in (dict(assistant_model=JacobiDrafter()), dict(draft_ids=wrong, assistant_model=JacobiDrafter()),
                   dict(draft_ids=wrong, assistant_model=jacobi_tree)):  # fmt: skip
        assert torch.equal(greedy(backbone.model, inputs, **kwargs), expected), kwargs


def test_left_padded_batch_decodes_like_batched_greedy(backbone):
    inputs = backbone.inputs([3, 7, 5], seed=1)
    expected = greedy(backbone.model, inputs)
    head = untrained_head(backbone.model)
    tree = DraftHeadDrafter(head, tree=DraftTreeConfig(top_k=3, depth=4, total_tokens=12))
    drafts = expected[:, inputs["input_ids"].shape[1] : -1].clone()
    drafts[1, 1] = (drafts[1, 1] + 1) % VOCAB  # row 1 rejects early, rows 0 and 2 pass: ragged acceptance
    for kwargs in (dict(assistant_model=head), dict(assistant_model=tree), dict(draft_ids=drafts),
                   dict(draft_ids=drafts, assistant_model=JacobiDrafter())):  # fmt: skip
        assert torch.equal(greedy(backbone.model, inputs, **kwargs), expected), kwargs


class BufferAddresses:
    """Records the address of the static cache's first key buffer after every forward of ``model``."""

    def __init__(self, model):
        self.seen: set[int] = set()
        model.register_forward_hook(self, with_kwargs=True)

    def __call__(self, module, args, kwargs, output):
        cache = kwargs.get(CACHE_KEY)
        if cache is not None and getattr(cache.layers[0], "keys", None) is not None:
            self.seen.add(cache.layers[0].keys.data_ptr())


def test_static_cache_decodes_exactly(backbone):
    """``cache_implementation="static"``: right drafts in one forward, wrong drafts, candidates and the head's chain
    and tree give greedy's tokens; the cache's buffers are never re-allocated (rolled back in place)."""
    inputs = backbone.inputs([5], seed=3)
    expected = greedy(backbone.model, inputs)
    right = expected[:, inputs["input_ids"].shape[1] : -1]
    wrong = right.clone()
    wrong[:, 2] = (wrong[:, 2] + 1) % VOCAB
    head = untrained_head(backbone.model)
    tree = DraftHeadDrafter(head, tree=DraftTreeConfig(top_k=3, depth=4, total_tokens=12))
    candidates = torch.stack([wrong, (right + 7) % VOCAB, right[:, [0, 0, 0, 0, 0, 0]]], dim=1)
    calls = [dict(draft_ids=right), dict(draft_ids=wrong), dict(draft_ids=candidates), dict(assistant_model=head),
             dict(assistant_model=tree), dict(draft_ids=wrong, assistant_model=tree),
             dict(draft_ids=wrong, assistant_model=JacobiDrafter())]  # fmt: skip
    buffers = BufferAddresses(backbone.model)
    for kwargs in calls:
        buffers.seen = set()
        out = greedy(backbone.model, inputs, cache_implementation="static", return_dict_in_generate=True, **kwargs)
        assert torch.equal(out.sequences, expected), kwargs
        if kwargs.get("draft_ids") is right:
            assert out.speculation.num_batch_forwards == 1
        assert len(buffers.seen) == 1, kwargs  # one buffer address through every round: rolled back in place


# ----------------------------------------------------------------------------- r > 0
@pytest.mark.parametrize("cache_implementation", [None, "static"])
def test_relaxed_action_tokens_stay_within_r_bins(backbone, cache_implementation):
    tokenizer, tolerance = ActionTokenizer(VOCAB), 3
    layout = ActionLayout(tokenizer, 7)
    actions_only = dict(suppress_tokens=list(range(tokenizer.action_token_begin)))  # the policy emits actions only
    inputs = backbone.inputs([5], seed=2)
    prompt_length = inputs["input_ids"].shape[1]
    expected = greedy(backbone.model, inputs, **actions_only)[:, prompt_length:]
    # drafts `tolerance` bins off greedy's action tokens (clamped to the bins): relaxed acceptance takes them
    nudged = (expected + tolerance).clamp(max=VOCAB - 1)
    out = greedy(backbone.model, inputs, draft_ids=nudged[:, :-1], bin_tolerance=tolerance, action_layout=layout,
                 return_dict_in_generate=True, cache_implementation=cache_implementation, **actions_only)  # fmt: skip
    sequence = out.sequences
    assert sum(out.speculation.accepted_per_position) > 0  # relaxed drafts were accepted: the bound is exercised
    for position in range(prompt_length, sequence.shape[1]):
        prefix = _prefix_inputs(inputs, sequence[:, :position])
        target = backbone.model.generate(**prefix, max_new_tokens=1, do_sample=False, **actions_only)[0, -1]
        token = sequence[0, position]
        assert abs(int(token) - int(target)) <= tolerance, (position, int(token), int(target))


def _prefix_inputs(inputs: dict, prefix: torch.Tensor) -> dict:
    """``inputs`` with ``input_ids`` = ``prefix`` (prompt + emitted tokens); per-token inputs extended for text."""
    extra = prefix.shape[1] - inputs["input_ids"].shape[1]
    out = dict(inputs, input_ids=prefix)
    for name, fill in (("token_type_ids", 1), ("mm_token_type_ids", 0), ("attention_mask", 1)):
        if name in inputs:  # generated tokens: PaliGemma's causal suffix (1), text (0), real (1)
            out[name] = torch.cat([inputs[name], inputs[name].new_full((prefix.shape[0], extra), fill)], dim=1)
    return out


# ----------------------------------------------------------------------------- caches
def _sliding_model(window: int):
    torch.manual_seed(0)
    config = AutoConfig.for_model("gemma2", **TEXT, head_dim=16, sliding_window=window)
    return enable_speculation(AutoModelForCausalLM.from_config(config).float().eval())


class ForwardCounter:
    def __init__(self, model):
        self.count = 0
        model.register_forward_pre_hook(self)

    def __call__(self, module, args):
        self.count += 1


def test_sliding_window_shorter_than_prompt_plus_drafts_is_exact():
    model = _sliding_model(window=14)
    inputs = {"input_ids": torch.randint(6, 64, (1, 7), generator=torch.Generator().manual_seed(3))}
    expected = greedy(model, inputs)  # 7 + 7 = 14 tokens: the generation fits the window
    right = expected[:, 7:-1]
    candidates = torch.stack([(right + k) % VOCAB for k in (1, 2, 0)], dim=1)  # 18 tree nodes after 7 prompt tokens
    out = greedy(model, inputs, draft_ids=candidates, return_dict_in_generate=True)
    assert torch.equal(out.sequences, expected)
    assert out.speculation.num_batch_forwards == 1
    layers = [layer for layer in cache_of(out).layers if isinstance(layer, DynamicSlidingWindowLayer)]
    assert layers and all(layer.sliding_window == 14 and layer.keys.shape[-2] <= 13 for layer in layers)  # restored


def test_generation_longer_than_the_sliding_window_is_refused_before_any_forward():
    model = _sliding_model(window=10)
    counter = ForwardCounter(model)
    inputs = {"input_ids": torch.randint(6, 64, (1, 7))}
    with pytest.raises(ValueError, match=r"sliding window of 10 tokens.*reach 14 tokens"):
        greedy(model, inputs, draft_ids=torch.tensor([[70, 71]]))
    assert counter.count == 0


def test_static_cache_too_short_is_refused_before_any_forward(tiny_llama):
    counter = ForwardCounter(tiny_llama)
    cache = StaticCache(config=tiny_llama.config, max_cache_len=6)
    with pytest.raises(ValueError, match=r"holds 6 tokens .* feeds up to 8 .* max_cache_len >= 8"):
        tiny_llama.generate(input_ids=torch.tensor([[1, 7, 9]]), max_new_tokens=6, do_sample=False,
                            draft_ids=torch.tensor([[70]]), **{CACHE_KEY: cache})  # fmt: skip
    assert counter.count == 0


def test_static_sliding_layer_shorter_than_the_generation_is_refused_before_any_forward():
    model = _sliding_model(window=10)
    counter = ForwardCounter(model)
    with pytest.raises(ValueError, match=r"StaticSlidingWindowLayer.*its window \(10\)"):
        greedy(model, {"input_ids": torch.randint(6, 64, (1, 7))}, draft_ids=torch.tensor([[70, 71]]),
               cache_implementation="static")  # fmt: skip
    assert counter.count == 0


def test_unsupported_cache_layer_is_refused_before_any_forward(tiny_llama):
    counter = ForwardCounter(tiny_llama)
    cache = DynamicCache(config=tiny_llama.config)
    cache.layers[1] = DynamicIndexedLayer()
    with pytest.raises(TypeError, match="layer 1's DynamicIndexedLayer"):
        tiny_llama.generate(input_ids=torch.tensor([[1, 7, 9]]), max_new_tokens=3, do_sample=False,
                            draft_ids=torch.tensor([[70]]), **{CACHE_KEY: cache})  # fmt: skip
    assert counter.count == 0


# ----------------------------------------------------------------------------- draft heads on other families
def test_head_borrows_what_the_target_sees():
    """Gemma scales embeddings inside its embedding module (borrowed as is) and Gemma-2 caps its logits: the head's
    logits are capped the same way; Gemma-3's per-layer-type rotary settings give the head the full-attention ones."""
    gemma2 = _text("gemma2").model
    gemma2.config.final_logit_softcapping = 5.0
    head = untrained_head(gemma2)
    assert head.config.final_logit_softcapping == 5.0
    scorer = head.scorer(gemma2.get_output_embeddings())
    assert float(scorer.logits(torch.randn(4, 64) * 100).detach().abs().max()) <= 5.0
    gemma3 = _text("gemma3_text").model
    expected = gemma3.config.rope_parameters["full_attention"]["rope_theta"]
    assert untrained_head(gemma3).config.rope_parameters["rope_theta"] == expected
