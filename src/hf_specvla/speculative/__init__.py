"""The speculative engine: a transformers extension that knows nothing of robots or simulators.

Imports point down: this package uses transformers, torch and ``hf_specvla.actions.tokenizer`` only.
"""

from .acceptance import (
    AcceptanceRule,
    AcceptedPath,
    ConfidenceGate,
    ExactMatch,
    RelaxedBinMatch,
    RelaxedBudget,
    StrictTailConfirmed,
    accept_tree,
    accept_trees,
    check_bin_tolerance_range,
    make_acceptance_rule,
)
from .assistant import as_drafter
from .compat import (
    CACHE_KEY,
    NEWEST_TESTED_TRANSFORMERS,
    OLDEST_TESTED_TRANSFORMERS,
    SUPPORTED_TRANSFORMERS,
    cache_of,
    check_transformers_support,
)
from .compiled import (
    CALL_WRAPPER_ATTRIBUTE,
    ENCODER_WRAPPER_ATTRIBUTE,
    NODE_BUCKETS,
    SLOT_MULTIPLE,
    call_compile_config,
    compiled_decoding_kwargs,
    reset_compilation,
    rounded_slots,
    verification_slots,
    verification_width,
)
from .config import RULE_ARGUMENTS, SPECULATION_KWARGS, SpeculationConfig, hashable
from .configuration_draft_head import DraftHeadConfig
from .decoder import SpeculativeDecoder, reusable_static_cache
from .drafter import (
    CandidateDrafter,
    Commit,
    ComposedDrafter,
    DraftContext,
    Drafter,
    DraftRound,
    DraftSession,
    NoDrafter,
    PerRowDrafter,
    read_hidden_states,
)
from .drafters import (
    ActionPriorDrafter,
    DraftHeadDrafter,
    DraftTreeConfig,
    JacobiDrafter,
    episode_drafter,
    jacobi_tail,
    remember_actions,
    with_action_prior,
    with_action_priors,
    with_previous_actions,
)
from .drafters.draft_head import embed_tokens, head_cache_slots
from .drafters.eagle_tree import num_head_entries
from .generation import (
    PreparedCall,
    SpeculativeGenerationMixin,
    disable_speculation,
    enable_speculation,
    prepare_call,
    with_generation_config,
)
from .graph_files import graphs_kept_in
from .loop import speculative_generate
from .masks import causal_mask, to_additive_mask
from .modeling_draft_head import DraftHead, TargetHandles, check_draft_head_folder, is_local_path, softcap_logits
from .outputs import SpeculativeDecoderOnlyOutput
from .session import DecoderSession
from .stats import SpeculationStats
from .tree import DraftTree
from .vision import encode_images, prompt_input_embeddings, reads_encoded_images
from .weights import DamagedWeightsError, named_weight_errors

__all__ = [
    "CACHE_KEY",
    "CALL_WRAPPER_ATTRIBUTE",
    "ENCODER_WRAPPER_ATTRIBUTE",
    "NEWEST_TESTED_TRANSFORMERS",
    "OLDEST_TESTED_TRANSFORMERS",
    "SUPPORTED_TRANSFORMERS",
    "SPECULATION_KWARGS",
    "RULE_ARGUMENTS",
    "hashable",
    "with_generation_config",
    "NODE_BUCKETS",
    "SLOT_MULTIPLE",
    "compiled_decoding_kwargs",
    "call_compile_config",
    "graphs_kept_in",
    "verification_width",
    "cache_of",
    "reusable_static_cache",
    "reset_compilation",
    "SpeculativeDecoder",
    "DecoderSession",
    "NoDrafter",
    "check_transformers_support",
    "TargetHandles",
    "as_drafter",
    "causal_mask",
    "to_additive_mask",
    "read_hidden_states",
    "encode_images",
    "prompt_input_embeddings",
    "reads_encoded_images",
    "check_draft_head_folder",
    "embed_tokens",
    "num_head_entries",
    "head_cache_slots",
    "rounded_slots",
    "verification_slots",
    "is_local_path",
    "softcap_logits",
    "episode_drafter",
    "remember_actions",
    "with_action_prior",
    "with_action_priors",
    "with_previous_actions",
    "jacobi_tail",
    "AcceptanceRule",
    "AcceptedPath",
    "ActionPriorDrafter",
    "CandidateDrafter",
    "Commit",
    "ComposedDrafter",
    "PerRowDrafter",
    "DraftContext",
    "DraftHead",
    "DraftHeadConfig",
    "DraftHeadDrafter",
    "JacobiDrafter",
    "DraftRound",
    "DraftSession",
    "DraftTree",
    "DraftTreeConfig",
    "Drafter",
    "ConfidenceGate",
    "ExactMatch",
    "RelaxedBinMatch",
    "RelaxedBudget",
    "SpeculationConfig",
    "SpeculationStats",
    "SpeculativeDecoderOnlyOutput",
    "SpeculativeGenerationMixin",
    "PreparedCall",
    "prepare_call",
    "StrictTailConfirmed",
    "accept_tree",
    "accept_trees",
    "check_bin_tolerance_range",
    "disable_speculation",
    "enable_speculation",
    "make_acceptance_rule",
    "named_weight_errors",
    "DamagedWeightsError",
    "speculative_generate",
]
