"""hf_specvla: draft-head speculative decoding with relaxed action acceptance for VLA models in transformers."""

from .acceptance import AcceptanceRule, ExactMatch, RelaxedBinMatch, make_acceptance_rule
from .action_tokenizer import ActionNormalizer, ActionTokenizer
from .configuration_draft_head import DraftHeadConfig
from .decoding import SpeculationConfig, speculative_generate
from .generation import SpeculativeGenerationMixin, disable_speculation, enable_speculation
from .modeling_draft_head import DraftHead
from .outputs import SpeculativeDecoderOnlyOutput
from .stats import SpeculationStats

__version__ = "0.1.0"

__all__ = [
    "AcceptanceRule",
    "ActionNormalizer",
    "ActionTokenizer",
    "DraftHead",
    "DraftHeadConfig",
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
