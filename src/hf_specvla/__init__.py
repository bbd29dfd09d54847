"""hf_specvla: speculative decoding with relaxed action acceptance for VLA models in transformers."""

from .action_tokenizer import ActionLayout, ActionNormalizer, ActionTokenizer
from .speculative import (
    AcceptanceRule,
    ActionPriorDrafter,
    CandidateDrafter,
    ComposedDrafter,
    Drafter,
    DraftHead,
    DraftHeadConfig,
    DraftHeadDrafter,
    DraftTree,
    DraftTreeConfig,
    ExactMatch,
    RelaxedBinMatch,
    SpeculationConfig,
    SpeculationStats,
    SpeculativeDecoderOnlyOutput,
    SpeculativeGenerationMixin,
    disable_speculation,
    enable_speculation,
    make_acceptance_rule,
    speculative_generate,
)

__version__ = "0.1.0"

__all__ = [
    "AcceptanceRule",
    "ActionLayout",
    "ActionNormalizer",
    "ActionPriorDrafter",
    "ActionTokenizer",
    "CandidateDrafter",
    "ComposedDrafter",
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
