"""A compiled speculative call's image encoder, compiled too.

transformers' ``generate`` encodes a VLM's images before decoding starts (the base model's ``get_image_features``)
and hands the result to the model's forward as ``mm_encoder_outputs``; it runs that encoder eagerly even under a
``CompileConfig``, which compiles the language model's forward only. On a small policy the eager encoder is mostly
host time, which compiling it cuts (docs/benchmarks.md, "The call's own work"). A compiled
speculative call (``assistant_model=`` / ``draft_ids=`` with a static cache and a ``compile_config``: the calls whose
verifications the engine compiles) encodes its images (``SpeculativeDecoder.encode_images``, with this module's
[`with_encoded_images`]) with the base model's ``get_image_features`` compiled by the model's ``CompiledGraphs``
(``CompiledGraphs.image_encoder``), and passes them to ``generate`` as ``mm_encoder_outputs``, which transformers
forwards to the model unchanged: the same tensors its own encoding would give, up to the float rounding of compiled
kernels (as the compiled language forwards round). Greedy calls are left to transformers.
"""

from __future__ import annotations

import inspect
from functools import cache

from transformers import PreTrainedModel

#: the name transformers reads a VLM's pre-encoded images from (``generate`` kwargs and the model's forward)
ENCODED_INPUTS = "mm_encoder_outputs"


@cache
def _forward_takes_encoded_images(model_class: type) -> bool:
    return ENCODED_INPUTS in inspect.signature(model_class.forward).parameters


@cache
def _encoder_parameters(encoder_function) -> tuple[str, ...]:
    return tuple(name for name in inspect.signature(encoder_function).parameters if name not in ("self", "kwargs"))


def encoder_inputs(encoder, kwargs: dict) -> dict:
    """The entries of ``kwargs`` the base model's ``get_image_features`` (``encoder``, bound) takes."""
    return {name: kwargs[name] for name in _encoder_parameters(encoder.__func__) if name in kwargs}


def takes_encoded_images(model: PreTrainedModel, kwargs: dict) -> bool:
    """Whether ``generate(**kwargs)`` encodes ``kwargs``' images before the prefill (raw ``pixel_values``, no
    ``mm_encoder_outputs`` yet, an image VLM whose forward takes them encoded and whose base model encodes them)."""
    if kwargs.get("pixel_values") is None or kwargs.get(ENCODED_INPUTS) is not None:
        return False
    if getattr(model.base_model, "get_image_features", None) is None or not _forward_takes_encoded_images(type(model)):
        return False
    return "image" in getattr(model, "input_modalities", ())


def with_encoded_images(model: PreTrainedModel, kwargs: dict, encoder=None) -> dict:
    """``kwargs`` with their images encoded as ``generate`` encodes them (by ``encoder``, a compiled
    ``get_image_features``, or the base model's own), under ``mm_encoder_outputs``; the encoder's inputs removed."""
    inputs = encoder_inputs(model.base_model.get_image_features, kwargs)
    rest = {name: value for name, value in kwargs.items() if name not in inputs}
    encoded = (encoder or model.base_model.get_image_features)(**inputs, return_dict=True)
    return {**rest, ENCODED_INPUTS: {"image": encoded}}


def reads_encoded_images(model: PreTrainedModel) -> bool:
    """Whether ``generate`` encodes ``model``'s images before its prefill and a drafter can find them in the prompt
    ([`prompt_input_embeddings`]): an image VLM whose forward takes ``mm_encoder_outputs``, whose base model has
    ``get_image_features`` and whose config names its ``image_token_id`` (Llava and its kind)."""
    return (
        "image" in getattr(model, "input_modalities", ())
        and _forward_takes_encoded_images(type(model))
        and getattr(model.base_model, "get_image_features", None) is not None
        and getattr(model.config, "image_token_id", None) is not None
    )


def encode_images(model: PreTrainedModel, inputs: dict):
    """The images of ``inputs`` encoded as ``generate`` encodes them before the prefill (the base model's
    ``get_image_features`` on the inputs it takes, ``return_dict=True``), or None when ``inputs`` hold no
    ``pixel_values``. For a training set built from prompts; a ``generate`` call has them in ``mm_encoder_outputs``.

    Raises:
        ValueError: a model whose base model has no ``get_image_features``.
    """
    if inputs.get("pixel_values") is None:
        return None
    encoder = getattr(model.base_model, "get_image_features", None)
    if encoder is None:
        raise ValueError(
            f"{type(model).__name__} has no base_model.get_image_features: its images cannot be encoded "
            f"before its forward"
        )
    return encoder(**encoder_inputs(encoder, inputs), return_dict=True)


def prompt_input_embeddings(model: PreTrainedModel, input_ids, model_kwargs: dict, start: int = 0):
    """``[B, S, H]`` what a Llava-style VLM's language model reads for ``input_ids`` ``[B, S]``: the token
    embeddings, the image tokens (``config.image_token_id``) from ``start`` on replaced, in order, by the encoded
    images of ``model_kwargs[mm_encoder_outputs]["image"]`` (their ``pooler_output``), as the model's forward
    places them. Without encoded images the token embeddings alone.

    Raises:
        ValueError: ``model_kwargs`` hold raw ``pixel_values`` (the model's ``generate`` does not encode images
            before the prefill), the model has no ``image_token_id``, or the images' features do not fill its
            image tokens.
    """
    import torch

    table = model.get_input_embeddings()
    # ids past the table (some VLMs' placeholders) embed as id 0, as a draft head embeds them
    embeddings = table(torch.where(input_ids < table.weight.shape[0], input_ids, torch.zeros_like(input_ids)))
    encoded = (model_kwargs.get(ENCODED_INPUTS) or {}).get("image")
    if encoded is None:
        if model_kwargs.get("pixel_values") is not None:
            raise ValueError(
                f"{type(model).__name__}'s generate does not encode its images before the prefill "
                f"({ENCODED_INPUTS}): a draft head with prefill_image_features cannot read them; use a head without "
                f"(prefill_image_features=False)"
            )
        return embeddings
    image_token_id = getattr(model.config, "image_token_id", None)
    if image_token_id is None:
        raise ValueError(f"{type(model).__name__}'s config has no image_token_id: its image tokens cannot be found")
    pooled = encoded.pooler_output
    pieces = pooled if isinstance(pooled, list | tuple) else [pooled]
    features = torch.cat([piece.reshape(-1, piece.shape[-1]) for piece in pieces]).to(embeddings.dtype)
    fed = embeddings[:, start:]
    is_image = (input_ids[:, start:] == image_token_id)[..., None]  # [B, S - start, 1]
    if int(is_image.sum()) != features.shape[0] or features.shape[-1] != fed.shape[-1]:
        raise ValueError(
            f"the encoded images give {features.shape[0]} features of width {features.shape[-1]} for "
            f"{int(is_image.sum())} image tokens of width {fed.shape[-1]}"
        )
    return torch.cat([embeddings[:, :start], fed.masked_scatter(is_image, features)], dim=1)
