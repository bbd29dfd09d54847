"""Actions as tokens: OpenVLA's bin tokenizer, the normaliser, the token layout of an action, and the small
word-level prompt tokenizer the local policies use. Imports nothing else of the package (the engine uses it)."""

from .._lazy import lazy_exports

__all__ = [
    "DEFAULT_N_BINS",
    "ActionLayout",
    "ActionNormalizer",
    "ActionTokenizer",
    "ActionUnits",
    "build_vla_tokenizer",
    "encode_prompt",
    "openvla_prompt",
]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        ".tokenizer": ("DEFAULT_N_BINS", "ActionLayout", "ActionNormalizer", "ActionTokenizer", "ActionUnits"),
        ".vla_tokenizer": ("build_vla_tokenizer", "encode_prompt", "openvla_prompt"),
    },
    globals(),
)
