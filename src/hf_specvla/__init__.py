"""hf_specvla: speculative decoding with relaxed action acceptance for VLA models in transformers."""

from . import _moved
from ._lazy import lazy_exports

__version__ = "0.1.0"

_moved.install()  # old module paths (hf_specvla.policy, hf_specvla.toy, ...) keep importing

__all__ = [
    "AcceptanceRule",
    "ActionLayout",
    "ActionNormalizer",
    "ActionPriorDrafter",
    "ActionTokenizer",
    "CandidateDrafter",
    "ComposedDrafter",
    "PerRowDrafter",
    "DraftHead",
    "DraftHeadConfig",
    "DraftHeadDrafter",
    "DraftTree",
    "DraftTreeConfig",
    "Drafter",
    "ExactMatch",
    "RelaxedBinMatch",
    "SpeculationConfig",
    "SpeculationStats",
    "SpeculativeDecoderOnlyOutput",
    "SpeculativeGenerationMixin",
    "disable_speculation",
    "enable_speculation",
    "make_acceptance_rule",
    "speculative_generate",
]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        ".actions": ("ActionLayout", "ActionNormalizer", "ActionTokenizer"),
        ".speculative": tuple(sorted(set(__all__) - {"ActionLayout", "ActionNormalizer", "ActionTokenizer"})),
    },
    globals(),
)  # fmt: skip
