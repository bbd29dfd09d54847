"""hf_specvla: speculative decoding with relaxed action acceptance for VLA models in transformers.

Importing the package imports the engine (``speculative``), which registers the draft head with transformers' Auto
classes (``AutoModel.from_pretrained(<draft head folder>)`` works after ``import hf_specvla``). The job folders
(``training``, ``metaworld``, ``benchmarks``, ``policies``, ``cli``) load their heavy parts on first use.
"""

from . import _moved
from .actions.tokenizer import ActionLayout, ActionNormalizer, ActionTokenizer
from .speculative import (
    AcceptanceRule,
    ActionPriorDrafter,
    CandidateDrafter,
    ComposedDrafter,
    ConfidenceGate,
    Drafter,
    DraftHead,
    DraftHeadConfig,
    DraftHeadDrafter,
    DraftTree,
    DraftTreeConfig,
    ExactMatch,
    JacobiDrafter,
    PerRowDrafter,
    RelaxedBinMatch,
    RelaxedBudget,
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
    "ConfidenceGate",
    "ExactMatch",
    "JacobiDrafter",
    "RelaxedBinMatch",
    "RelaxedBudget",
    "SpeculationConfig",
    "SpeculationStats",
    "SpeculativeDecoderOnlyOutput",
    "SpeculativeGenerationMixin",
    "disable_speculation",
    "enable_speculation",
    "make_acceptance_rule",
    "speculative_generate",
]
