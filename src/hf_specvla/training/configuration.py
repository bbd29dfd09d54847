"""Training settings, defined once: the draft-head distillation run, behaviour cloning of the Meta-World policy,
the data a policy's draft head learns from, and ``train-draft``'s defaults for policy-sized targets.

Plain validated dataclasses: the CLI reads its defaults here without loading accelerate or the trainers.
"""

from __future__ import annotations

from dataclasses import dataclass

from .._validation import check_ranges
from ..metaworld.env import resolve_tasks
from ..metaworld.seeds import DRAFT_SEED_START

#: the draft-head architectures ``train-draft`` builds: v1 (the target's last hidden state), v2 (a low, a middle and
#: the top layer, and the robot's previous action; see ``training.draft_head.head_v2_settings``) and v3 (v2's inputs,
#: a block per head forward and the whole action drafted before the prefill: ``head_v3_settings``)
HEAD_VERSIONS = ("v1", "v2", "v3")


def default_unroll_steps(head_version: str, num_draft_tokens: int) -> int:
    """The draft steps a head is trained on per example when none are given: 1 (teacher forcing) for v1, the chain
    it drafts (``num_draft_tokens``) for v2 (training-time test) and v3 (a block of that length)."""
    return 1 if head_version == "v1" else num_draft_tokens


def check_draft_chain(num_draft_tokens: int, tokens_per_call: int, unroll_steps: int, blocks: bool = False) -> None:
    """A head's chain and training depth that fit the target's calls: ``1 <= num_draft_tokens < tokens_per_call``
    (the prefill makes a call's first token), ``unroll_steps <= num_draft_tokens`` (a step past the chain is never
    drafted) and, for a head that drafts blocks (``blocks``: v3), ``unroll_steps == num_draft_tokens``.

    Raises:
        ValueError: naming the value, the bound and the setting to change.
    """
    if not 1 <= num_draft_tokens <= tokens_per_call - 1:
        raise ValueError(
            f"num_draft_tokens={num_draft_tokens}: a call generates {tokens_per_call} tokens, the "
            f"first from the prefill, so a chain drafts 1..{tokens_per_call - 1} of them"
        )
    if blocks and unroll_steps != num_draft_tokens:
        raise ValueError(
            f"a head v3 drafts blocks of num_draft_tokens={num_draft_tokens} tokens and is trained on as "
            f"many: set unroll_steps={num_draft_tokens} (or leave it to its default), got "
            f"unroll_steps={unroll_steps}"
        )
    if unroll_steps > num_draft_tokens:
        raise ValueError(
            f"unroll_steps={unroll_steps} trains more draft steps than the head's chain of "
            f"num_draft_tokens={num_draft_tokens} drafts: use 1..{num_draft_tokens}"
        )


@dataclass
class TrainingConfig:
    """The training loop's settings ([`run_training`]), shared by every trainer; each trainer's config extends it
    with its own fields and defaults.

    Args:
        output_dir: checkpoints (``checkpoint-<step>/``), logs and the final model go here.
        max_steps: optimizer steps.
        batch_size: examples per step per process.
        learning_rate, betas, weight_decay, max_grad_norm: AdamW + gradient clipping.
        warmup_steps: linear warm-up steps.
        lr_schedule: after warm-up, "constant" or "cosine" (decays to 0 at max_steps).
        save_every: steps between checkpoints (0 = none on the way; the last step always gets one).
        eval_every: steps between validations (0 = only after the last step).
        log_every: steps between lines of ``training_log.jsonl``.
        keep_checkpoints: most recent checkpoints kept on disk.
        resume: continue from the newest ``checkpoint-*`` in output_dir if there is one.
        overwrite_output_dir: train from scratch into a non-empty output_dir: the previous contents are moved aside
            whole to ``<output_dir>.replaced-<UTC time>`` (nothing deleted, nothing of the old run mixed in).
        seed: data order and per-step noise.
        mixed_precision: accelerate's "no" / "fp16" / "bf16".
    """

    output_dir: str
    max_steps: int = 1000
    batch_size: int = 32
    learning_rate: float = 1e-3
    betas: tuple[float, float] = (0.9, 0.999)
    weight_decay: float = 0.0
    max_grad_norm: float = 1.0
    warmup_steps: int = 0
    lr_schedule: str = "constant"
    save_every: int = 500
    eval_every: int = 0
    log_every: int = 100
    keep_checkpoints: int = 2
    resume: bool = False
    overwrite_output_dir: bool = False
    seed: int = 0
    mixed_precision: str = "no"

    def __post_init__(self):
        check_ranges(
            self,
            at_least_one=("max_steps", "batch_size", "log_every", "keep_checkpoints"),
            positive=("learning_rate", "max_grad_norm"),
            non_negative=("weight_decay", "warmup_steps", "save_every", "eval_every"),
        )
        if self.lr_schedule not in ("constant", "cosine"):
            raise ValueError(f"lr_schedule must be 'constant' or 'cosine', got {self.lr_schedule!r}")
        if self.mixed_precision not in ("no", "fp16", "bf16"):
            raise ValueError(f"mixed_precision must be 'no', 'fp16' or 'bf16', got {self.mixed_precision!r}")


@dataclass
class DraftTrainingConfig(TrainingConfig):
    """Settings of [`train_draft_head`]: the loop's ([`TrainingConfig`]) with the paper's defaults for a 7B target
    (AdamW 5e-5, betas (0.9, 0.95), no weight decay, clipping at 0.5; a toy target wants a larger learning rate),
    and the distillation's own.

    Args:
        feature_loss_weight / token_loss_weight: weights of the SmoothL1 feature loss and the soft cross-entropy.
        feature_noise: width of the uniform noise added to the input hidden states (U(-a/2, a/2)).
        unroll_steps: draft steps each example is trained on (training-time test): 1 = teacher forcing only (heads
            before v2); n > 1 = n - 1 more steps on the head's own features, as it drafts a chain of n.
    """

    max_steps: int = 2000
    batch_size: int = 8
    learning_rate: float = 5e-5
    betas: tuple[float, float] = (0.9, 0.95)
    max_grad_norm: float = 0.5
    feature_loss_weight: float = 1.0
    token_loss_weight: float = 0.1
    feature_noise: float = 0.2
    unroll_steps: int = 1

    def __post_init__(self):
        super().__post_init__()
        check_ranges(
            self,
            non_negative=("feature_noise", "feature_loss_weight", "token_loss_weight"),
            at_least_one=("unroll_steps",),
            integers=("unroll_steps",),
        )
        if self.feature_loss_weight == 0 and self.token_loss_weight == 0:
            raise ValueError(
                "feature_loss_weight and token_loss_weight are both 0: the loss would be 0 and the head "
                "untrained; give one of them a weight > 0"
            )


@dataclass
class VLATrainingConfig(TrainingConfig):
    """Settings of [`train_vla`]: the loop's ([`TrainingConfig`]) with behaviour cloning's defaults (AdamW 1e-3,
    weight decay 0.01, 200 warm-up steps then cosine decay), and its own.

    Args:
        val_episodes: episodes per task held out for validation.
        augment_shift: pixels of random-shift augmentation (0 = off).
        scene_loss_weight: weight of the scene-state tokens' loss against the action tokens' (policies with
            ``scene_state_dim`` only).
        freeze_vision: the vision tower is not trained (e.g. a tower pretrained to locate the scene:
            ``examples/metaworld/localization_probe.py --save-policy``); the projector and the decoder are.
        scene_readout_weight: weight of a linear readout's loss (mean squared error on the normalised object and goal
            xyz) read from the decoder where the first action token is decoded (0 = none; training only, the policy
            folder is unchanged: [`PolicyWithSceneReadout`]); policies with ``scene_state_dim`` only.
    """

    max_steps: int = 6000
    batch_size: int = 64
    weight_decay: float = 0.01
    warmup_steps: int = 200
    lr_schedule: str = "cosine"
    eval_every: int = 500
    save_every: int = 1000
    val_episodes: int = 2
    augment_shift: int = 4
    scene_loss_weight: float = 0.5
    freeze_vision: bool = False
    scene_readout_weight: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        check_ranges(self, non_negative=("val_episodes", "augment_shift", "scene_loss_weight", "scene_readout_weight"))


@dataclass
class PolicyDraftTrainingConfig(DraftTrainingConfig):
    """``train-draft``'s settings for a policy-sized target (a few-million-parameter policy on a CPU): a larger
    learning rate than [`DraftTrainingConfig`]'s (the paper's, for a 7B target), cosine decay after 50 warm-up
    steps, validation and a checkpoint every 500 steps. The chain length is not here: it defaults to the policy's
    tokens per call minus one (the prefill makes the first token, so 3 drafted tokens complete a 4-token action and
    7 a chunk of two)."""

    max_steps: int = 3000
    batch_size: int = 32
    learning_rate: float = 3e-3
    lr_schedule: str = "cosine"
    warmup_steps: int = 50
    eval_every: int = 500
    save_every: int = 500


@dataclass
class DraftDataConfig:
    """What a policy's draft head learns from.

    Args:
        tasks: Meta-World tasks (names or a suite, e.g. "MT10").
        rollout_episodes: greedy on-policy episodes per task (seeds ``rollout_seed_start``, +1, ...); the last
            ``validation_episodes`` of each task are held out for validation.
        rollout_max_steps: policy calls kept per rollout (an episode is cut there; a chunked policy takes H env
            steps per call).
        rollout_seed_start: first rollout seed.
        validation_episodes: held-out rollouts per task (>= 1).
        validation_frames: at most this many held-out frames are validated (evenly spread; the engine runs once
            per frame).
        demo_frames_per_task: frames sampled per task from the demonstration folders (when given).
        prompt_batch_size: prompts per batched greedy pass when the targets are computed.
        seed: the demonstration sampling.
    """

    tasks: str | list[str] = "MT10"
    rollout_episodes: int = 6
    rollout_max_steps: int = 150
    rollout_seed_start: int = DRAFT_SEED_START
    validation_episodes: int = 1
    validation_frames: int = 200
    demo_frames_per_task: int = 300
    prompt_batch_size: int = 32
    seed: int = 0

    def __post_init__(self):
        self.tasks = resolve_tasks(self.tasks)
        check_ranges(
            self,
            at_least_one=("rollout_max_steps", "validation_episodes", "validation_frames", "prompt_batch_size"),
            non_negative=("demo_frames_per_task", "rollout_seed_start"),
        )
        if self.rollout_episodes <= self.validation_episodes:
            raise ValueError(
                f"rollout_episodes ({self.rollout_episodes}) must exceed validation_episodes "
                f"({self.validation_episodes}): the last validation_episodes rollouts of each task are held out"
            )
