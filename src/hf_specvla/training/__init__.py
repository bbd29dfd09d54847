"""Training: one loop (``training.loop``) behind behaviour cloning of the Meta-World policy, draft-head
distillation and the toy target; checkpoints and resumable run folders; the draft-head recipes for a policy and
for OpenVLA; a policy's on-policy rollouts saved for draft-head training (``training.rollouts``).

``from hf_specvla.training import DraftTrainingConfig, train_draft_head`` keeps working: the draft-head names
are re-exported here.
"""

from .._lazy import lazy_exports

_EXPORTS = {
    ".configuration": (
        "DraftDataConfig",
        "DraftTrainingConfig",
        "PolicyDraftTrainingConfig",
        "TrainingConfig",
        "VLATrainingConfig",
    ),
    ".loop": ("TRAINING_LOG", "VALIDATION_LOG", "TrainingJob", "learning_rate_factor", "run_training"),
    ".draft_head": (
        "build_distillation_dataset",
        "collate_distillation",
        "distillation_loss",
        "draft_training_record",
        "head_settings",
        "head_v2_settings",
        "head_v3_settings",
        "speculative_acceptance",
        "train_draft_head",
        "accuracy_by_position",
    ),
    ".behaviour_cloning": ("train_vla",),
    ".rollouts": ("RolloutConfig", "collect_rollouts", "read_rollout_frames"),
}
__all__ = sorted(name for names in _EXPORTS.values() for name in names)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
