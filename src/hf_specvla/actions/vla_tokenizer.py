"""A small word-level tokenizer for OpenVLA-style prompts, built locally (nothing downloaded).

Layout of the vocabulary, OpenVLA's convention: special tokens, then the words seen in the given texts, then the
``n_action_bins`` action tokens as the *last* ids, so that ``ActionTokenizer(len(tokenizer), n_action_bins)``
describes it.
"""

from __future__ import annotations

import re
from collections.abc import Iterable

from tokenizers import Tokenizer, models, pre_tokenizers
from transformers import PreTrainedTokenizerFast

SPECIAL_TOKENS = ("<pad>", "<s>", "</s>", "<unk>", "<image>")
OPENVLA_PROMPT = "In: What action should the robot take to {instruction}?\nOut:"
_SPLIT = re.compile(r"\w+|[^\w\s]")


def openvla_prompt(instruction: str) -> str:
    """OpenVLA's prompt for an instruction (lower-cased, as ``predict_action`` does)."""
    return OPENVLA_PROMPT.format(instruction=instruction.lower().strip().rstrip("."))


def build_vla_tokenizer(texts: Iterable[str], n_action_bins: int = 256) -> PreTrainedTokenizerFast:
    """A word-level tokenizer whose vocabulary is the words of ``texts`` (and OpenVLA's prompt) plus action tokens.

    Args:
        texts: instructions or prompts the tokenizer must cover (unknown words map to ``<unk>``).
        n_action_bins: number of action tokens ``<act_0>`` .. at the end of the vocabulary.
    """
    words = sorted({w for text in [openvla_prompt("x"), *texts] for w in _SPLIT.findall(text.lower())})
    vocab = {token: i for i, token in enumerate(SPECIAL_TOKENS)}
    for word in words:
        vocab.setdefault(word, len(vocab))
    for i in range(n_action_bins):
        vocab[f"<act_{i}>"] = len(vocab)
    tokenizer = Tokenizer(models.WordLevel(vocab=vocab, unk_token="<unk>"))
    tokenizer.normalizer = None
    tokenizer.pre_tokenizer = pre_tokenizers.Sequence(
        [pre_tokenizers.WhitespaceSplit(), pre_tokenizers.Punctuation(), pre_tokenizers.Digits()]
    )
    wrapped = PreTrainedTokenizerFast(
        tokenizer_object=tokenizer,
        pad_token="<pad>",
        bos_token="<s>",
        eos_token="</s>",
        unk_token="<unk>",
        model_max_length=512,
    )
    wrapped.add_special_tokens({"additional_special_tokens": ["<image>"]})
    return wrapped


def encode_prompt(tokenizer: PreTrainedTokenizerFast, instruction: str, num_image_tokens: int = 0) -> list[int]:
    """``[<s>] + [<image>] * num_image_tokens + tokens(OpenVLA prompt)`` as ids (lower-cased words)."""
    image_id = tokenizer.convert_tokens_to_ids("<image>")
    text_ids = tokenizer(openvla_prompt(instruction).lower(), add_special_tokens=False)["input_ids"]
    return [tokenizer.bos_token_id] + [image_id] * num_image_tokens + text_ids
