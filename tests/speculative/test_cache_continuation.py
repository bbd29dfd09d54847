"""A cache that already holds entries is continued as greedy decoding continues it (issue 55, item 1).

Continuing a conversation or an episode on one cache is what transformers users do: the second ``generate`` call
passes the cache of the first with the sequence it returned plus new tokens (or only the new tokens, with an attention
mask over the cached and the new ones). The prefill then feeds only the tokens the cache does not hold, and at r=0
every drafter gives greedy's tokens on both turns, on a DynamicCache and a StaticCache, eager and compiled. Caches
that cannot be continued exactly are refused before any forward, with an error that names their length.
"""

from __future__ import annotations

import pytest
import torch
from transformers import DynamicCache
from transformers.cache_utils import StaticCache

from hf_specvla import (
    ActionLayout,
    ActionPriorDrafter,
    ComposedDrafter,
    DraftHead,
    DraftHeadDrafter,
    DraftTreeConfig,
    JacobiDrafter,
)
from hf_specvla.speculative import CACHE_KEY
from hf_specvla.speculative.compiled import reset_compilation

from ..conftest import llava_prompt
from .test_compiled_verification import _model as fresh_model
from .test_compiled_verification import eager_compile_config

NEW_TOKENS = 7
TURN_2 = torch.tensor([[7, 8]])  # the user's next tokens


@pytest.fixture(scope="module")
def model():
    """A tiny Llama of this module's own: the session's ``tiny_llama`` carries other tests' compiled graphs."""
    return fresh_model("llama")


@pytest.fixture(scope="module")
def prompt():
    return torch.randint(3, 60, (1, 12), generator=torch.Generator().manual_seed(4))


def new_cache(model, kind: str, batch_size: int = 1):
    if kind == "dynamic":
        return DynamicCache(config=model.config)
    return StaticCache(config=model.config, max_cache_len=64)


def two_turns(model, prompt, cache, only_new: bool = False, first: dict | None = None, second: dict | None = None,
              **common):  # fmt: skip
    """Turn 1 on ``prompt``, then turn 2 on the same cache: its sequence + ``TURN_2`` (or, with ``only_new``, just
    ``TURN_2`` with a mask over the cached and the new tokens). Returns both turns' sequences."""
    kwargs = dict(max_new_tokens=NEW_TOKENS, do_sample=False, **common)
    turn_1 = model.generate(input_ids=prompt, **{CACHE_KEY: cache}, **kwargs, **(first or {}))
    if only_new:
        ids = torch.cat([turn_1[:, -1:], TURN_2], dim=1)  # the last emitted token is not in the cache yet
        mask = torch.ones(1, turn_1.shape[1] + TURN_2.shape[1], dtype=torch.long)  # cached + new tokens
        turn_2 = model.generate(input_ids=ids, attention_mask=mask, **{CACHE_KEY: cache}, **kwargs, **(second or {}))
    else:
        ids = torch.cat([turn_1, TURN_2], dim=1)
        turn_2 = model.generate(input_ids=ids, **{CACHE_KEY: cache}, **kwargs, **(second or {}))
    return turn_1, turn_2


def drafters_for(model, action_tokenizer) -> dict:
    """Every drafter, each a fresh object per call (a drafter is stateless across calls)."""
    torch.manual_seed(1)
    head = DraftHead.from_target(model, action_tokenizer, action_dim=7, draft_action_tokens_only=False).eval()
    layout = ActionLayout(action_tokenizer, 7)
    previous = [[100 + d for d in range(7)]]
    return {
        "jacobi": lambda: dict(assistant_model=JacobiDrafter()),
        "head chain": lambda: dict(assistant_model=head),
        "head tree": lambda: dict(assistant_model=DraftHeadDrafter(head, tree=DraftTreeConfig(3, 3, 10))),
        "prior": lambda: dict(assistant_model=ActionPriorDrafter(previous, layout)),
        "prior+jacobi": lambda: dict(
            assistant_model=ComposedDrafter([ActionPriorDrafter(previous, layout), JacobiDrafter()])
        ),
        "prior+tree": lambda: dict(
            assistant_model=ComposedDrafter(
                [ActionPriorDrafter(previous, layout), DraftHeadDrafter(head, tree=DraftTreeConfig(3, 3, 10))]
            )
        ),
    }


@pytest.mark.parametrize("only_new", [False, True], ids=["sequence+new", "new-only"])
@pytest.mark.parametrize("kind", ["dynamic", "static"])
def test_two_turns_on_one_cache_equal_greedys_for_every_drafter(model, prompt, action_tokenizer, kind, only_new):
    expected = two_turns(model, prompt, new_cache(model, kind), only_new)
    for name, make in drafters_for(model, action_tokenizer).items():
        got = two_turns(model, prompt, new_cache(model, kind), only_new, first=make(), second=make())
        for turn, (a, b) in enumerate(zip(got, expected), start=1):
            assert torch.equal(a, b), (
                f"{name}, {kind}, turn {turn}: {a[0, -NEW_TOKENS:]} != greedy {b[0, -NEW_TOKENS:]}"
            )
        if name in ("jacobi", "prior+tree"):  # greedy first, speculation second, and the other way round
            mixed = two_turns(model, prompt, new_cache(model, kind), only_new, second=make())
            assert torch.equal(mixed[1], expected[1]), name
            mixed = two_turns(model, prompt, new_cache(model, kind), only_new, first=make())
            assert torch.equal(mixed[1], expected[1]), name


def test_draft_ids_on_a_continued_cache(model, prompt):
    """Drafts known up front are verified in the prefill of the new tokens: right ones all pass in one forward."""
    _, expected = two_turns(model, prompt, new_cache(model, "dynamic"))
    cache = new_cache(model, "dynamic")
    turn_1 = model.generate(input_ids=prompt, max_new_tokens=NEW_TOKENS, do_sample=False, **{CACHE_KEY: cache})
    ids = torch.cat([turn_1, TURN_2], dim=1)
    right = expected[:, ids.shape[1] : -1]
    out = model.generate(input_ids=ids, max_new_tokens=NEW_TOKENS, do_sample=False, draft_ids=right,
                         return_dict_in_generate=True, **{CACHE_KEY: cache})  # fmt: skip
    assert torch.equal(out.sequences, expected)
    assert out.speculation.num_target_forwards == 1


def test_a_cut_path_leaves_greedys_cache(model, prompt):
    """A path the stopping criteria cut (max_new_tokens inside accepted drafts) keeps no entries past the cut: the
    cache holds the returned sequence but its last token, as greedy's does."""
    expected = model.generate(input_ids=prompt, max_new_tokens=NEW_TOKENS, do_sample=False)
    cache = new_cache(model, "dynamic")
    out = model.generate(input_ids=prompt, max_new_tokens=3, do_sample=False, draft_ids=expected[:, 12:],
                         **{CACHE_KEY: cache})  # fmt: skip
    assert out.shape[1] == 12 + 3
    assert cache.get_seq_length() == out.shape[1] - 1


def test_compiled_verification_continues_a_static_cache(model, prompt, action_tokenizer):
    reset_compilation()
    try:
        expected = two_turns(model, prompt, new_cache(model, "static"))
        compiled = dict(compile_config=eager_compile_config())
        for name in ("jacobi", "head tree", "prior+jacobi"):
            make = drafters_for(model, action_tokenizer)[name]
            got = two_turns(model, prompt, new_cache(model, "static"), first=make(), second=make(), **compiled)
            assert torch.equal(got[0], expected[0]) and torch.equal(got[1], expected[1]), name
    finally:
        reset_compilation()


def test_a_vlm_continues_after_its_image(tiny_llava, random_llava_draft):
    """Turn 2 feeds only its new text: the image features stay in the cache from turn 1."""
    prompt = llava_prompt(torch.Generator().manual_seed(5))

    def turns(**drafting):
        cache = DynamicCache(config=tiny_llava.config)
        kwargs = dict(max_new_tokens=NEW_TOKENS, do_sample=False, **{CACHE_KEY: cache})
        first = tiny_llava.generate(**prompt, **kwargs, **drafting)
        second = tiny_llava.generate(input_ids=torch.cat([first, TURN_2], dim=1), **kwargs, **drafting)
        return first, second

    expected = turns()
    for drafting in (dict(assistant_model=random_llava_draft), dict(assistant_model=JacobiDrafter())):
        got = turns(**drafting)
        assert torch.equal(got[0], expected[0]) and torch.equal(got[1], expected[1])


def test_a_greedy_batchs_cache_is_continued_by_a_batch(model):
    """A batch continues a cache greedy decoding left (left padding included): each row gives greedy's tokens."""
    generator = torch.Generator().manual_seed(6)
    ids = torch.randint(3, 60, (2, 9), generator=generator)
    mask = torch.ones_like(ids)
    mask[1, :3] = 0
    ids[1, :3] = 0

    def turns(**drafting):
        cache = DynamicCache(config=model.config)
        kwargs = dict(max_new_tokens=NEW_TOKENS, do_sample=False, **{CACHE_KEY: cache})
        first = model.generate(input_ids=ids, attention_mask=mask, **kwargs)  # greedy leaves the cache
        more = torch.cat([first, TURN_2.expand(2, -1)], dim=1)
        more_mask = torch.cat([mask, torch.ones(2, more.shape[1] - mask.shape[1], dtype=torch.long)], dim=1)
        return model.generate(input_ids=more, attention_mask=more_mask, **kwargs, **drafting)

    assert torch.equal(turns(assistant_model=JacobiDrafter()), turns())


def test_a_cache_a_batch_decoded_on_is_refused(model):
    ids = torch.randint(3, 60, (2, 9), generator=torch.Generator().manual_seed(7))
    cache = DynamicCache(config=model.config)
    kwargs = dict(max_new_tokens=NEW_TOKENS, do_sample=False, assistant_model=JacobiDrafter(), **{CACHE_KEY: cache})
    first = model.generate(input_ids=ids, **kwargs)
    with pytest.raises(ValueError, match=r"holds \d+ entries left by a batched speculative generate call"):
        model.generate(input_ids=torch.cat([first, TURN_2.expand(2, -1)], dim=1), **kwargs)


@pytest.mark.parametrize("emptied", [False, True])
def test_a_cache_of_another_batch_size_is_refused_before_any_forward(model, prompt, emptied):
    """A static cache used at B=1, then (emptied or not) at B=2: refused up front, not failing inside the model."""
    cache = StaticCache(config=model.config, max_cache_len=64)
    first = model.generate(input_ids=prompt, max_new_tokens=3, do_sample=False, **{CACHE_KEY: cache})
    ids = torch.cat([first, TURN_2], dim=1).expand(2, -1)
    if emptied:
        cache.reset()
    calls = []
    handle = model.register_forward_hook(lambda *args: calls.append(1))
    try:
        entries = 0 if emptied else 14
        with pytest.raises(
            ValueError, match=rf"holds {entries} entries for 1 row\(s\) \(StaticCache\), but input_ids has 2"
        ):
            model.generate(input_ids=ids, max_new_tokens=3, do_sample=False, assistant_model=JacobiDrafter(),
                           **{CACHE_KEY: cache})  # fmt: skip
    finally:
        handle.remove()
    assert not calls


@pytest.mark.parametrize(
    "ids_length, mask_length, match",
    [
        (10, None, r"cache already holds 14 entries but input_ids has only 10 tokens"),
        (3, 20, r"holds 14 entries, input_ids has 3 tokens and the attention mask 20 columns"),
    ],
)
def test_inputs_a_cache_cannot_continue_are_refused(model, prompt, ids_length, mask_length, match):
    cache = DynamicCache(config=model.config)
    model.generate(input_ids=prompt, max_new_tokens=3, do_sample=False, **{CACHE_KEY: cache})
    kwargs = {} if mask_length is None else dict(attention_mask=torch.ones(1, mask_length, dtype=torch.long))
    with pytest.raises(ValueError, match=match):
        model.generate(input_ids=prompt[:, :ids_length], max_new_tokens=3, do_sample=False,
                       assistant_model=JacobiDrafter(), **{CACHE_KEY: cache}, **kwargs)  # fmt: skip
