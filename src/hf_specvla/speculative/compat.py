"""The transformers releases the engine supports, and the one seam where they differ: the KV cache's name.

transformers 5.24 renamed the cache in generation and in every model forward: ``prepare_inputs_for_generation``
returns it as ``model_inputs["cache"]`` (5.20-5.23: ``"past_key_values"``), models take ``cache=`` and outputs
carry ``.cache``; the old name is still accepted as an input, with a deprecation warning, until 5.40. The engine
reads and passes the cache only through [`CACHE_KEY`], the name the installed release uses, so it runs on every
supported release without a deprecation warning.

[`check_transformers_support`] runs at the first speculative call: when a release changes something else the
engine relies on, a user gets an error naming the installed version, the supported range and what is missing,
not a ``KeyError`` from deep inside a round.
"""

from __future__ import annotations

import dataclasses
import inspect
import logging
from functools import cache

import transformers
from packaging.version import Version
from transformers import GenerationMixin
from transformers.cache_utils import DynamicCache
from transformers.generation.utils import GenerateDecoderOnlyOutput
from transformers.modeling_outputs import CausalLMOutputWithPast

logger = logging.getLogger(__name__)

#: the oldest and the newest transformers release the test matrix runs (tox: tf520 pins the oldest, tf525 the
#: newest, which the demo also pins; tflatest installs whatever is newest when it runs)
OLDEST_TESTED_TRANSFORMERS = "5.20.0"
NEWEST_TESTED_TRANSFORMERS = "5.25.0"
#: what ``pyproject.toml`` admits
SUPPORTED_TRANSFORMERS = f">={OLDEST_TESTED_TRANSFORMERS},<6"


def _cache_key() -> str:
    parameters = inspect.signature(GenerationMixin.prepare_inputs_for_generation).parameters
    return "cache" if "cache" in parameters else "past_key_values"


#: the name of the KV cache in generate's model kwargs, model forwards and model outputs of the installed
#: transformers: ``"cache"`` from 5.24, ``"past_key_values"`` before
CACHE_KEY: str = _cache_key()


def cache_of(outputs):
    """The cache a model output (or generate's output) carries, under the installed release's name."""
    return getattr(outputs, CACHE_KEY, None)


def _field_names(cls) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


def _requirements() -> list[tuple[str, bool]]:
    """What the engine relies on in transformers, each with whether the installed release has it."""
    prepare = inspect.signature(GenerationMixin.prepare_inputs_for_generation).parameters
    generate = inspect.signature(GenerationMixin.generate).parameters
    empty = DynamicCache()
    return [
        ("generate(custom_generate=callable)", "custom_generate" in generate),
        (f"prepare_inputs_for_generation(..., {CACHE_KEY}=...)", CACHE_KEY in prepare),
        ("prepare_inputs_for_generation(..., is_first_iteration=...)", "is_first_iteration" in prepare),
        (f"model outputs carrying .{CACHE_KEY}", CACHE_KEY in _field_names(CausalLMOutputWithPast)),
        (f"GenerateDecoderOnlyOutput.{CACHE_KEY}", CACHE_KEY in _field_names(GenerateDecoderOnlyOutput)),
        ("Cache.layers (per-layer keys / values)", isinstance(getattr(empty, "layers", None), list)),
    ]


@cache
def check_transformers_support(version: str | None = None) -> None:
    """Refuses a transformers release that lacks something the engine relies on (run once, at the first call).

    A release newer than the newest tested one that has everything is used, with one warning.

    Args:
        version: the release to judge (default: the installed one); for tests.
    Raises:
        RuntimeError: naming the installed version, the supported range and what is missing.
    """
    version = version or transformers.__version__
    release = Version(Version(version).base_version)  # 5.25.0.dev0 -> 5.25.0
    if release < Version(OLDEST_TESTED_TRANSFORMERS):
        raise RuntimeError(
            f"hf_specvla's speculative decoding needs transformers {SUPPORTED_TRANSFORMERS}, but {version} is "
            f"installed: pip install 'transformers{SUPPORTED_TRANSFORMERS}'"
        )
    missing = [name for name, present in _requirements() if not present]
    if missing:
        raise RuntimeError(
            f"transformers {version} changed what hf_specvla's speculative decoding relies on (missing: "
            f"{'; '.join(missing)}). Tested releases: {OLDEST_TESTED_TRANSFORMERS} .. {NEWEST_TESTED_TRANSFORMERS}: "
            f"pip install 'transformers>={OLDEST_TESTED_TRANSFORMERS},<={NEWEST_TESTED_TRANSFORMERS}', or upgrade "
            f"hf_specvla"
        )
    if release > Version(NEWEST_TESTED_TRANSFORMERS):
        logger.warning(
            "transformers %s is newer than the newest release hf_specvla was tested with (%s); the features the "
            "speculative engine uses are present",
            version,
            NEWEST_TESTED_TRANSFORMERS,
        )


#: Appended to the AttributeError transformers' own assisted generation raises when it is handed a hf_specvla
#: assistant because the target's ``generate`` was never speculation-enabled (it is not enabled automatically).
NOT_ENABLED_HINT = (
    "a hf_specvla assistant (DraftHead or Drafter) needs a speculation-enabled target: call "
    "hf_specvla.enable_speculation(model) once, or pass generate(custom_generate=hf_specvla.speculative_generate, "
    "drafter=...)"
)
