"""hf_specvla: speculative decoding with relaxed action acceptance for VLA models in transformers.

Importing the package is light (no torch, no transformers: ``hf-specvla --help`` answers at once); each name below
loads its module on first use. The draft head registers with transformers' Auto classes as soon as transformers'
Auto classes are imported, so ``AutoModel.from_pretrained(<draft head folder>)`` works after ``import hf_specvla``
whichever is imported first. The job folders (``training``, ``metaworld``, ``benchmarks``, ``policies``, ``cli``)
load their heavy parts on first use too.
"""

from . import _moved
from ._lazy import lazy_exports, when_imported

__version__ = "0.1.0"

_EXPORTS = {
    ".actions.tokenizer": ("ActionLayout", "ActionNormalizer", "ActionTokenizer", "ActionUnits"),
    ".speculative": (
        "AcceptanceRule",
        "ActionPriorDrafter",
        "CandidateDrafter",
        "ComposedDrafter",
        "ConfidenceGate",
        "DecoderSession",
        "Drafter",
        "DraftHead",
        "DraftHeadConfig",
        "DraftHeadDrafter",
        "DraftTree",
        "DraftTreeConfig",
        "ExactMatch",
        "JacobiDrafter",
        "NoDrafter",
        "PerRowDrafter",
        "RelaxedBinMatch",
        "RelaxedBudget",
        "SpeculationConfig",
        "SpeculationStats",
        "SpeculativeDecoderOnlyOutput",
        "SpeculativeGenerationMixin",
        "StrictTailConfirmed",
        "disable_speculation",
        "enable_speculation",
        "make_acceptance_rule",
        "speculative_generate",
    ),
}
__all__ = sorted(name for names in _EXPORTS.values() for name in names)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())

_moved.install()  # old module paths (hf_specvla.policy, hf_specvla.toy, ...) keep importing


def _register_draft_head() -> None:
    """Imports the engine, whose ``modeling_draft_head`` registers the draft head with AutoConfig / AutoModel (a
    no-op while the engine is already loading: it registers when it gets there)."""
    import importlib
    import sys

    if f"{__name__}.speculative" not in sys.modules:
        importlib.import_module(".speculative", __name__)


# configuration_auto: what both AutoConfig and AutoModel load first
when_imported("transformers.models.auto.configuration_auto", _register_draft_head)
