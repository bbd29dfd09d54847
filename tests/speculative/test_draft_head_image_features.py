"""Head v3 drafting before the prefill from the current frame (``DraftHeadConfig.prefill_image_features``).

Invariants: the prompt embeddings a drafter gets are exactly what the VLM's language model reads (image tokens
replaced by the encoded image, in order, batch rows apart); at r=0 such a head decodes greedy's tokens (one row, a
left-padded batch of different images, dynamic, static and compiled caches, alone and after the action prior); its
drafts before the prefill change with the image where a head without the option's do not; training reads the same
inputs as drafting; a set built without the images, a head without prefill drafts and a model that does not encode
its images before the prefill are refused, naming what to do.
"""

from __future__ import annotations

import pytest
import torch
from transformers.cache_utils import DynamicCache

from hf_specvla import ActionTokenizer, DraftHead, DraftHeadDrafter, DraftTreeConfig
from hf_specvla.speculative import with_action_prior
from hf_specvla.speculative.configuration_draft_head import DraftHeadConfig
from hf_specvla.speculative.decoder import SpeculativeDecoder
from hf_specvla.speculative.drafters import draft_head as draft_head_module
from hf_specvla.speculative.drafters.draft_head import embed_tokens
from hf_specvla.speculative.drafters.head_block import block_round
from hf_specvla.speculative.vision import encode_images, prompt_input_embeddings
from hf_specvla.training.draft_head import (
    block_entries,
    block_features,
    build_distillation_dataset,
    collate_distillation,
    head_settings,
)

from ..conftest import IMAGE_TOKEN, VOCAB, llava_prompt
from .test_draft_head_v2 import _compile_config

ACTION_DIM = 4
NEW_TOKENS = 8
TREE = DraftTreeConfig(top_k=3, depth=7, total_tokens=14)


def _image_head(target, **overrides) -> DraftHead:
    """A random v3 head that drafts before the prefill from the encoded image (its mask inputs and previous-action
    rows randomised, so that every input matters)."""
    torch.manual_seed(5)
    settings = dict(previous_action_input=True, draft_mode="block", prefill_drafts=True, prefill_image_features=True,
                    draft_action_tokens_only=False, num_draft_tokens=7)  # fmt: skip
    head = DraftHead.from_target(target, ActionTokenizer(VOCAB), action_dim=ACTION_DIM, **{**settings, **overrides})
    with torch.no_grad():
        head.previous_embedding.weight.normal_(0, 1.0)
        head.mask_inputs.weight.normal_(0, 1.0)
    return head.eval()


@pytest.fixture(scope="module")
def image_head(tiny_llava) -> DraftHead:
    return _image_head(tiny_llava)


def _prompts(seed: int, count: int) -> list[dict]:
    generator = torch.Generator().manual_seed(seed)
    return [llava_prompt(generator, text_len=5) for _ in range(count)]


def _greedy(model, **inputs):
    return model.generate(**inputs, max_new_tokens=NEW_TOKENS, min_new_tokens=NEW_TOKENS, do_sample=False)


def _action(*bins: int) -> list[int]:
    return [int(VOCAB - 1 - b) for b in bins]


# ----------------------------------------------------------------------------- what the drafter reads
def test_prompt_embeddings_are_what_the_language_model_reads(tiny_llava):
    """Two rows, different images: each row's image tokens hold its own encoded image, the text its embeddings,
    exactly the ``inputs_embeds`` the model's language model gets."""
    prompts = _prompts(0, 2)
    inputs = {name: torch.cat([p[name] for p in prompts]) for name in ("input_ids", "pixel_values")}
    seen = {}
    hook = tiny_llava.model.language_model.register_forward_pre_hook(
        lambda module, args, kwargs: seen.update(embeds=kwargs["inputs_embeds"]), with_kwargs=True
    )
    try:
        with torch.no_grad():
            tiny_llava(**inputs)
    finally:
        hook.remove()
    encoded = {"mm_encoder_outputs": {"image": encode_images(tiny_llava, inputs)}}
    with torch.no_grad():
        embeddings = prompt_input_embeddings(tiny_llava, inputs["input_ids"], encoded)
    assert torch.equal(embeddings, seen["embeds"])
    is_image = inputs["input_ids"] == IMAGE_TOKEN
    assert not torch.equal(embeddings[0][is_image[0]], embeddings[1][is_image[1]])  # each row its own image


def test_a_model_that_does_not_encode_images_first_is_refused(tiny_llava):
    input_ids = torch.tensor([[1] + [IMAGE_TOKEN] * 4 + [7, 8]])
    with pytest.raises(ValueError, match="does not encode its images before the prefill"):
        prompt_input_embeddings(tiny_llava, input_ids, {"pixel_values": torch.zeros(1, 3, 16, 16)})
    text_only = prompt_input_embeddings(tiny_llava, input_ids[:, :1], {})  # no image: the token embeddings
    assert torch.equal(text_only, tiny_llava.get_input_embeddings()(input_ids[:, :1]))


# ----------------------------------------------------------------------------- lossless
@pytest.mark.parametrize("cache", ["dynamic", "static", "compiled"])
def test_an_image_reading_head_decodes_exactly_as_greedy(tiny_llava, image_head, cache):
    prompt = _prompts(1, 1)[0]
    expected = _greedy(tiny_llava, **prompt)
    settings = {"dynamic": {}, "static": {"cache_implementation": "static"},
                "compiled": {"cache_implementation": "static", "compile_config": _compile_config()}}[cache]  # fmt: skip
    layout = image_head.config.action_layout()
    chain, tree = DraftHeadDrafter(image_head), DraftHeadDrafter(image_head, tree=TREE)
    previous = [_action(10, 200, 3, 255), _action(12, 180, 3, 0)]
    drafters = {"chain": chain, "tree, previous action": tree.with_previous_action(previous[-1]),
                "prior + tree": with_action_prior(tree, previous, layout, chunk_length=2)}  # fmt: skip
    for name, drafter in drafters.items():
        out = _greedy(tiny_llava, **prompt, assistant_model=drafter, **settings)
        assert torch.equal(out, expected), name
    if cache == "compiled":  # the block before the prefill ran compiled, its graph made once per prompt length
        compiled = SpeculativeDecoder.of(tiny_llava).graphs(settings["compile_config"])
        assert block_round in compiled.functions
        again = tiny_llava.generate(**prompt, max_new_tokens=NEW_TOKENS, min_new_tokens=NEW_TOKENS, do_sample=False,
                                    assistant_model=chain, return_dict_in_generate=True, **settings)  # fmt: skip
        assert torch.equal(again.sequences, expected) and again.speculation.compile_seconds == 0


def test_an_image_reading_head_in_a_left_padded_batch_of_different_images(tiny_llava, image_head):
    prompts = _prompts(2, 2)
    short = {"input_ids": prompts[1]["input_ids"][:, :-2], "pixel_values": prompts[1]["pixel_values"]}
    input_ids = torch.cat([prompts[0]["input_ids"], torch.cat([torch.zeros(1, 2, dtype=torch.long),
                                                                short["input_ids"]], dim=1)])  # fmt: skip
    mask = torch.ones_like(input_ids)
    mask[1, :2] = 0
    pixel_values = torch.cat([prompts[0]["pixel_values"], short["pixel_values"]])
    expected = _greedy(tiny_llava, input_ids=input_ids, attention_mask=mask, pixel_values=pixel_values)
    out = _greedy(tiny_llava, input_ids=input_ids, attention_mask=mask, pixel_values=pixel_values,
                  assistant_model=DraftHeadDrafter(image_head, tree=TREE))  # fmt: skip
    assert torch.equal(out, expected)


def test_the_drafts_before_the_prefill_read_the_image(tiny_llava, image_head, monkeypatch):
    """The pre-prefill block's pairs hold the row's encoded image at its image tokens (the vision tower's projected
    patches, in order) and the token embeddings elsewhere; a head without the option gets the placeholder's
    embedding there."""
    seen = []

    def recording(*args, **kwargs):
        seen.append(kwargs.get("pair_embeddings"))
        return block_round(*args, **kwargs)

    monkeypatch.setattr(draft_head_module, "block_round", recording)
    prompt = _prompts(3, 1)[0]
    _greedy(tiny_llava, **prompt, assistant_model=DraftHeadDrafter(image_head))
    pairs = seen[0][0]  # [S - 1, H]: pair p holds token p + 1
    with torch.no_grad():
        patches = tiny_llava.model.get_image_features(pixel_values=prompt["pixel_values"], return_dict=True)
        tokens = tiny_llava.get_input_embeddings()(prompt["input_ids"])[0, 1:]
    is_image = prompt["input_ids"][0, 1:] == IMAGE_TOKEN
    assert int(is_image.sum()) == 4
    assert torch.equal(pairs[is_image], torch.cat(list(patches.pooler_output)).reshape(-1, pairs.shape[-1]))
    assert torch.equal(pairs[~is_image], tokens[~is_image])
    seen.clear()
    blind = _image_head(tiny_llava, prefill_image_features=False)
    _greedy(tiny_llava, **prompt, assistant_model=DraftHeadDrafter(blind))
    assert seen[0] is None  # block_round embeds the tokens themselves: the placeholder at the image tokens


# ----------------------------------------------------------------------------- training = drafting
@pytest.fixture(scope="module")
def image_batch(tiny_llava):
    prompts = [{name: torch.cat([p[name] for p in _prompts(seed, 2)]) for name in ("input_ids", "pixel_values")}
               for seed in (4, 5)]  # fmt: skip
    dataset = build_distillation_dataset(tiny_llava, prompts, NEW_TOKENS, ActionTokenizer(VOCAB), progress=False,
                                         action_dim=ACTION_DIM, image_features=True)  # fmt: skip
    return dataset, collate_distillation([dataset[i] for i in range(len(dataset))])


def test_the_pre_prefill_training_block_is_the_drafting_block(tiny_llava, image_head, image_batch):
    """Entry j of the training block from the prompt's last pair drafts what the engine's pre-prefill block drafts
    from the same prompt, image included (as compiled into one training forward over several examples)."""
    _, batch = image_batch
    handles = image_head.target_handles(tiny_llava)
    steps, row, first = 5, 2, int(batch["first_position"][2])
    roots = torch.full((batch["input_ids"].shape[0],), first - 2)
    with torch.no_grad():
        features = block_entries(block_features(image_head, handles, batch, None, roots, steps - 1), roots, steps - 1)
    scorer = image_head.scorer(handles.lm_head)
    ids = batch["input_ids"][row : row + 1, :first]
    prompt = {"input_ids": ids, "pixel_values": torch.cat([p["pixel_values"] for p in _prompts(5, 2)])[:1]}
    encoded = {"mm_encoder_outputs": {"image": encode_images(tiny_llava, prompt)}}
    previous = (image_head.previous_action_bins(None), torch.tensor(first))
    with torch.no_grad():
        embeddings = prompt_input_embeddings(tiny_llava, ids, encoded)
        table = block_round(image_head, lambda t: embed_tokens(handles, t), scorer, ids[:, 1:], None,
                            torch.arange(first - 1)[None], first - 1, DynamicCache(), 0, steps - 1, 1,
                            previous=previous, pair_embeddings=embeddings[:, 1:])  # fmt: skip
    assert torch.equal(table[:, 0], scorer.token_ids(features[row]))
    # and without the image the block drafts something else: the image is what the set adds
    blind = {name: value for name, value in batch.items() if not name.startswith("image")}
    with torch.no_grad(), pytest.raises(ValueError, match="image_features=True"):
        block_features(image_head, handles, blind, None, roots, steps - 1)


def test_head_v3_reads_the_image_only_when_asked_and_only_where_generate_encodes_it(tiny_llava, tiny_llama):
    assert "prefill_image_features" not in head_settings("v3", tiny_llava)
    assert head_settings("v3", tiny_llava, image_features=True)["prefill_image_features"] is True
    with pytest.raises(ValueError, match="LlamaForCausalLM's generate does not encode its images before the prefill"):
        head_settings("v3", tiny_llama, image_features=True)
    with pytest.raises(ValueError, match="not by a v2 head"):
        head_settings("v2", tiny_llava, image_features=True)


def test_image_features_without_prefill_drafts_are_refused():
    with pytest.raises(ValueError, match="prefill_image_features=True needs prefill_drafts=True"):
        DraftHeadConfig(prefill_image_features=True)
    with pytest.raises(ValueError, match="prefill_image_features must be True or False, got 'yes'"):
        DraftHeadConfig(prefill_drafts=True, prefill_image_features="yes")
