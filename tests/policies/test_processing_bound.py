"""``VLAProcessor.prompt_ids`` keeps the prompt prefixes of at most ``PROMPT_CACHE_SIZE`` instructions (issue 64): a
policy server's client sending a new instruction every call once grew the server's memory without bound. The ids
are those of an uncached computation, whatever was evicted."""

from __future__ import annotations

import itertools
import json
import threading
from pathlib import Path

import numpy as np
import pytest
from transformers import PreTrainedTokenizerFast

from hf_specvla.policies import VLAPolicyConfig, processing_vla
from hf_specvla.policies.processing_vla import PROMPT_CACHE_SIZE, VLAProcessor

POLICY = Path(__file__).resolve().parents[2] / "policies" / "mt10_vla3"


@pytest.fixture(scope="module")
def parts() -> tuple[PreTrainedTokenizerFast, VLAPolicyConfig]:
    """Policy v3's tokenizer (word level) and config: no weights loaded."""
    config = VLAPolicyConfig(**json.loads((POLICY / "policy_config.json").read_text()))
    return PreTrainedTokenizerFast.from_pretrained(POLICY), config


def _processor(parts) -> VLAProcessor:
    return VLAProcessor(*parts)


def _instructions(tokenizer, count: int) -> list[str]:
    """``count`` distinct instructions of words the tokenizer knows (so each makes its own ids), some with the
    capitals and full stop the prompt drops."""
    words = sorted(w for w in tokenizer.get_vocab() if w.isalpha() and w.isascii())
    assert len(words) >= 20, words
    combos = itertools.chain.from_iterable(itertools.product(words, repeat=n) for n in (1, 2, 3))
    out = [" ".join(c) for c in itertools.islice(combos, count)]
    return [f"{s.capitalize()}." if i % 7 == 0 else s for i, s in enumerate(out)]


def _uncached(tokenizer, config, instruction: str, state) -> list[int]:
    """The prompt's ids computed from the tokenizer alone (see processing_vla's docstring for the layout)."""

    def encode(text: str) -> list[int]:
        return tokenizer(text.lower(), add_special_tokens=False)["input_ids"]

    text = f"In: What action should the robot take to {instruction.lower().strip().rstrip('.')}?"
    ids = [tokenizer.bos_token_id] + [tokenizer.convert_tokens_to_ids("<image>")] * config.num_image_tokens
    ids += encode(text)
    if config.use_state:
        ids += encode("\nState:") + VLAProcessor(tokenizer, config).state_token_ids(state)
    return ids + encode("\nOut:")


def test_the_cache_never_holds_more_than_its_bound_and_the_ids_are_the_uncached_ones(parts):
    tokenizer, config = parts
    processor, state = _processor(parts), np.array([0.0, 0.6, 0.1, 0.5])
    instructions = _instructions(tokenizer, 3 * PROMPT_CACHE_SIZE)
    assert len(set(instructions)) == len(instructions)
    largest = 0
    for instruction in instructions:
        ids = processor.prompt_ids(instruction, state)
        largest = max(largest, len(processor._prefix_cache))
        assert ids == _uncached(tokenizer, config, instruction, state), instruction
    assert largest == len(processor._prefix_cache) == PROMPT_CACHE_SIZE
    assert list(processor._prefix_cache) == instructions[-PROMPT_CACHE_SIZE:]  # the most recent kept
    assert len({tuple(processor.prompt_ids(i, state)) for i in instructions[:50]}) == 50  # distinct prompts
    for instruction in instructions[:5] + instructions[-5:]:  # evicted (recomputed) and cached alike
        assert processor.prompt_ids(instruction, state) == _uncached(tokenizer, config, instruction, state)
    assert len(processor._prefix_cache) == PROMPT_CACHE_SIZE


def test_least_recently_used_goes_first_and_callers_get_copies(parts, monkeypatch):
    monkeypatch.setattr(processing_vla, "PROMPT_CACHE_SIZE", 3)
    tokenizer, config = parts
    processor, state = _processor(parts), np.zeros(config.state_dim)
    a, b, c, d = _instructions(tokenizer, 4)
    for instruction in (a, b, c, a, d):  # a used again: b is the least recently used when d arrives
        processor.prompt_ids(instruction, state)
    assert list(processor._prefix_cache) == [c, a, d]
    ids = processor.prompt_ids(a, state)
    ids.append(-1)  # a caller's list is its own
    assert processor.prompt_ids(a, state) == _uncached(tokenizer, config, a, state)


def test_threads_sharing_the_processor_keep_the_bound_and_the_ids(parts, monkeypatch):
    """A server tokenizes on its HTTP threads (the prompt limit) and its decoding thread at once."""
    monkeypatch.setattr(processing_vla, "PROMPT_CACHE_SIZE", 8)
    tokenizer, config = parts
    processor, state = _processor(parts), np.zeros(config.state_dim)
    instructions = _instructions(tokenizer, 64)
    expected = {i: _uncached(tokenizer, config, i, state) for i in instructions}
    errors: list = []

    def hammer(seed: int) -> None:
        order = np.random.default_rng(seed).integers(0, len(instructions), 400)
        try:
            for k in order:
                assert processor.prompt_ids(instructions[k], state) == expected[instructions[k]]
                assert len(processor._prefix_cache) <= 8 + 4  # at most one in-flight insertion per thread
        except BaseException as error:  # noqa: BLE001 (reported by the main thread)
            errors.append(error)

    threads = [threading.Thread(target=hammer, args=(seed,)) for seed in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors, errors
    assert len(processor._prefix_cache) <= 8
