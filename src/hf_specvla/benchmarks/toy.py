"""A toy OpenVLA-style target: a tiny Llava that reads a picture of a dot and answers with 7 action tokens.

The task has real structure, so a draft head has something to learn:

* the scene is a coloured dot on a 8x8 grid of a 32x32 image, plus one of a few instructions;
* the action (7 dims in [-1, 1], OpenVLA layout xyz / rpy / gripper) is a deterministic function of the dot's
  grid cell, its colour and the instruction: ``[x, y, z(task), colour, (x+y)/2, (x-y)/2, gripper(task)]``.

Everything is built locally and trains in a few minutes on 2 CPU cores (see [`train_toy_target`]): the target for
[`TOY_TARGET_STEPS`], enough for it to read the dot's cell off the image, then its draft head (head v3, drafting the
whole action before the prefill from the instruction and the encoded image).
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from transformers import AutoConfig, CLIPVisionConfig, LlavaConfig, LlavaForConditionalGeneration, LogitsProcessorList
from transformers.generation.logits_process import MinNewTokensLengthLogitsProcessor

from ..actions.tokenizer import ActionTokenizer
from ..actions.vla_tokenizer import build_vla_tokenizer, encode_prompt
from ..training.configuration import TrainingConfig
from ..training.loop import TrainingJob, run_training

logger = logging.getLogger(__name__)

#: the demo's toy target training steps: enough for it to read the dot's cell off the image (at 300 it had not: its
#: x / y tokens were one answer per instruction, and every action of a moving-dot episode the same)
TOY_TARGET_STEPS = 1500
#: the toy draft head (head v3): one block per head forward, the whole action drafted before the prefill from the
#: instruction and the encoded image (the target's vision output, which ``generate`` computes before the prefill)
TOY_HEAD_SETTINGS = dict(draft_mode="block", prefill_drafts=True, prefill_image_features=True)
#: the toy draft head's training steps: at 800 its tree drafted the whole action before the prefill on 29% of
#: held-out scenes (no previous action), at 2400 on 90%, at 4800 on 98% (same target, data and learning rate)
TOY_HEAD_STEPS = 4800

#: where the toy pipeline ``hf-specvla demo`` times is shipped, relative to the checkout's root: a target trained
#: [`TOY_TARGET_STEPS`] and its head [`TOY_HEAD_STEPS`], built by ``hf-specvla demo --train --output-dir
#: policies/toy_dot`` (its card says how); the same every run, so nothing is trained to see the verdict
SHIPPED_TOY_DIR = "policies/toy_dot"

GRID_SIZE = 8
IMAGE_SIZE = 32
PATCH_SIZE = 8
ACTION_DIM = 7
COLOURS = {"red": (1.0, 0.1, 0.1), "green": (0.1, 1.0, 0.1), "blue": (0.2, 0.3, 1.0), "yellow": (1.0, 1.0, 0.1)}
# instruction -> (z action, gripper action)
TASKS = {
    "reach the {colour} dot": (0.0, -1.0),
    "push the {colour} dot": (-0.5, -1.0),
    "grab the {colour} dot": (0.5, 1.0),
    "lift the {colour} dot": (0.9, 1.0),
}


@dataclass(frozen=True)
class DotScene:
    """One toy observation: dot at grid cell (col, row), a colour name and a task template."""

    col: int
    row: int
    colour: str
    task: str

    @property
    def instruction(self) -> str:
        return self.task.format(colour=self.colour)

    def image(self) -> torch.Tensor:
        """``[3, 32, 32]`` float image, dark background, a 3x3 dot in the scene's colour."""
        image = torch.full((3, IMAGE_SIZE, IMAGE_SIZE), 0.05)
        cell = IMAGE_SIZE // GRID_SIZE
        cy, cx = self.row * cell + cell // 2, self.col * cell + cell // 2
        image[:, cy - 1 : cy + 2, cx - 1 : cx + 2] = torch.tensor(COLOURS[self.colour])[:, None, None]
        return image

    def action(self) -> np.ndarray:
        """The ground-truth 7-dim action in [-1, 1]."""
        x = -0.875 + 0.25 * self.col
        y = -0.875 + 0.25 * self.row
        z, gripper = TASKS[self.task]
        colour_value = -0.6 + 0.4 * list(COLOURS).index(self.colour)
        return np.array([x, y, z, colour_value, 0.5 * (x + y), 0.5 * (x - y), gripper])


def all_scenes() -> list[DotScene]:
    """Every toy scene (8 x 8 cells x 4 colours x 4 tasks = 1024)."""
    return [
        DotScene(col, row, colour, task)
        for col in range(GRID_SIZE)
        for row in range(GRID_SIZE)
        for colour in COLOURS
        for task in TASKS
    ]


def split_scenes() -> tuple[list[DotScene], list[DotScene]]:
    """(train, held_out): a fixed random quarter of the scenes is held out of target and draft training."""
    scenes = all_scenes()
    held_out = set(np.random.default_rng(1234).permutation(len(scenes))[: len(scenes) // 4].tolist())
    return [s for i, s in enumerate(scenes) if i not in held_out], [s for i, s in enumerate(scenes) if i in held_out]


def toy_tokenizer():
    """The toy's word-level tokenizer (instructions + OpenVLA prompt + 256 action tokens)."""
    return build_vla_tokenizer([task.format(colour=c) for task in TASKS for c in COLOURS])


@dataclass
class ToyTargetSize:
    """Sizes of the toy target. The default trains in seconds; larger ones make the benchmark closer to a VLA's
    compute profile (target forward much costlier than a draft-head forward)."""

    hidden_size: int = 128
    num_hidden_layers: int = 4
    num_attention_heads: int = 4
    num_key_value_heads: int = 2
    intermediate_size: int = 256


def build_toy_target(size: ToyTargetSize | None = None, seed: int = 0, text_model_type: str = "llama"):
    """An untrained toy Llava target and its tokenizer.

    Args:
        text_model_type: the language model's family (a transformers ``model_type``: ``"llama"``, ``"qwen2"``,
            ``"gemma2"``...); Llava takes any of them behind its vision tower.

    Returns:
        (model, tokenizer, action_tokenizer)
    """
    size = size or ToyTargetSize()
    tokenizer = toy_tokenizer()
    vocab_size = len(tokenizer)
    vision = CLIPVisionConfig(
        hidden_size=64,
        intermediate_size=128,
        num_hidden_layers=2,
        num_attention_heads=4,
        image_size=IMAGE_SIZE,
        patch_size=PATCH_SIZE,
        projection_dim=64,
    )
    text = AutoConfig.for_model(
        text_model_type,
        vocab_size=vocab_size,
        hidden_size=size.hidden_size,
        intermediate_size=size.intermediate_size,
        num_hidden_layers=size.num_hidden_layers,
        num_attention_heads=size.num_attention_heads,
        num_key_value_heads=size.num_key_value_heads,
        head_dim=size.hidden_size // size.num_attention_heads,
        max_position_embeddings=256,
        bos_token_id=tokenizer.bos_token_id,
        eos_token_id=tokenizer.eos_token_id,
        pad_token_id=tokenizer.pad_token_id,
    )
    config = LlavaConfig(
        vision_config=vision,
        text_config=text,
        image_token_id=tokenizer.convert_tokens_to_ids("<image>"),
        image_seq_length=(IMAGE_SIZE // PATCH_SIZE) ** 2,
        vision_feature_select_strategy="default",
        vision_feature_layer=-1,
    )
    torch.manual_seed(seed)
    model = LlavaForConditionalGeneration(config)
    model.generation_config.pad_token_id = tokenizer.pad_token_id
    return model, tokenizer, ActionTokenizer(vocab_size)


def toy_inputs(scenes: list[DotScene], tokenizer) -> dict[str, torch.Tensor]:
    """Model inputs for a batch of scenes: ``input_ids`` ``[B, S]`` (same length for all toy prompts, no
    padding needed) and ``pixel_values`` ``[B, 3, 32, 32]``."""
    num_image_tokens = (IMAGE_SIZE // PATCH_SIZE) ** 2
    ids = [encode_prompt(tokenizer, scene.instruction, num_image_tokens) for scene in scenes]
    if len({len(i) for i in ids}) != 1:
        raise ValueError("toy prompts must all have the same length")
    return {"input_ids": torch.tensor(ids), "pixel_values": torch.stack([scene.image() for scene in scenes])}


def train_toy_target(
    model: LlavaForConditionalGeneration,
    tokenizer,
    action_tokenizer: ActionTokenizer,
    config: TrainingConfig,
    progress: bool = True,
) -> dict[str, float]:
    """Behaviour-clones the toy task on the training scenes (next-token loss on the 7 action tokens only) with the one
    training loop; saves the target and its tokenizer to ``config.output_dir``. Returns the last metrics."""

    def collate(scenes: list[DotScene]) -> dict[str, torch.Tensor]:
        inputs = toy_inputs(scenes, tokenizer)
        action_ids = torch.as_tensor(action_tokenizer.encode(np.stack([s.action() for s in scenes])))  # [B, 7]
        input_ids = torch.cat([inputs["input_ids"], action_ids], dim=1)
        labels = torch.full_like(input_ids, -100)
        labels[:, -ACTION_DIM:] = action_ids  # loss on the action tokens only
        return {"input_ids": input_ids, "pixel_values": inputs["pixel_values"], "labels": labels}

    def loss(model, batch: dict, step: int):
        loss = model(**batch).loss
        return loss, {"loss": loss.detach()}

    def save(model, folder: Path) -> None:
        model.save_pretrained(folder)
        tokenizer.save_pretrained(folder)

    job = TrainingJob(
        model,
        split_scenes()[0],
        loss,
        save,
        collate_fn=collate,
        checkpoint_name="target",
        description="train toy target",
    )
    _, metrics = run_training(job, config, Path(config.output_dir), progress=progress)
    return metrics


def toy_target_training_config(output_dir: str | Path, steps: int, seed: int) -> TrainingConfig:
    """How the demo trains its toy target: 32 scenes a step, AdamW 4e-3 with 10% warm-up then cosine, no checkpoints
    on the way (it takes a minute or two; the loop can resume it when ``save_every`` is set)."""
    return TrainingConfig(
        str(output_dir),
        max_steps=steps,
        batch_size=32,
        learning_rate=4e-3,
        warmup_steps=max(1, steps // 10),
        lr_schedule="cosine",
        save_every=0,
        seed=seed,
    )


@torch.no_grad()
def toy_action_accuracy(model, tokenizer, action_tokenizer, scenes: list[DotScene]) -> float:
    """Fraction of action tokens the target's greedy decoding gets exactly right on ``scenes``."""
    inputs = toy_inputs(scenes, tokenizer)
    out = model.generate(**inputs, max_new_tokens=ACTION_DIM, do_sample=False)[:, -ACTION_DIM:]
    truth = torch.as_tensor(action_tokenizer.encode(np.stack([s.action() for s in scenes])))
    return (out == truth).float().mean().item()


@dataclass
class ToyPipeline:
    """A trained toy target with its tokenizer, action tokenizer and a draft head trained on it, saved in
    ``output_dir`` (``target/`` and ``draft_head/``)."""

    output_dir: str
    target: LlavaForConditionalGeneration
    tokenizer: object
    action_tokenizer: ActionTokenizer
    draft_head: object


def build_toy_pipeline(
    output_dir: str,
    size: ToyTargetSize | None = None,
    target_steps: int = TOY_TARGET_STEPS,
    draft_steps: int = TOY_HEAD_STEPS,
    draft_learning_rate: float = 3e-3,
    seed: int = 0,
    progress: bool = True,
    overwrite: bool = False,
) -> ToyPipeline:
    """Builds and trains the toy target, then self-distils a draft head for it ([`TOY_HEAD_SETTINGS`],
    [`TOY_HEAD_STEPS`]; about 11 minutes on one CPU thread).
    Both see only the training scenes of [`split_scenes`].

    The target is saved to ``output_dir/target`` and the draft head to ``output_dir/draft_head``. The folder follows
    the folder rule (``run.json``, see [`hf_specvla.run_folder`]): a complete pipeline built with the same settings
    is loaded instead of retrained; one built with other settings (e.g. another ``size``) is refused, naming the
    setting, unless ``overwrite`` (which moves it aside).
    """
    from dataclasses import asdict
    from pathlib import Path

    from ..run_folder import RunRecord, claim_run_folder

    size = size or ToyTargetSize()
    root = Path(output_dir)
    settings = dict(
        size=asdict(size),
        target_steps=target_steps,
        draft_steps=draft_steps,
        draft_learning_rate=draft_learning_rate,
        seed=seed,
        draft_head=TOY_HEAD_SETTINGS,
    )
    with claim_run_folder(root, RunRecord("demo", settings), overwrite) as run:
        target, tokenizer, action_tokenizer, draft_head = _build_or_load(
            run.bound, size, target_steps, draft_steps, draft_learning_rate, seed, progress
        )
    return ToyPipeline(str(root), target, tokenizer, action_tokenizer, draft_head.eval())


def _build_or_load(
    root,
    size: ToyTargetSize,
    target_steps: int,
    draft_steps: int,
    draft_learning_rate: float,
    seed: int,
    progress: bool,
):
    """[`build_toy_pipeline`]'s work in a folder this process holds: (target, tokenizer, action tokenizer, head)."""
    from ..speculative import DraftHead, enable_speculation
    from ..training.draft_head import DraftTrainingConfig, build_distillation_dataset, train_draft_head

    target_dir, draft_dir = root / "target", root / "draft_head"
    if (target_dir / "config.json").exists():
        target, tokenizer, action_tokenizer = _load_toy_target(target_dir)
    else:
        target, tokenizer, action_tokenizer = build_toy_target(size, seed)
        config = toy_target_training_config(target_dir, target_steps, seed)
        train_toy_target(target, tokenizer, action_tokenizer, config, progress=progress)
    target = enable_speculation(target.eval())
    if (draft_dir / "config.json").exists():
        logger.info("loading toy draft head from %s", draft_dir)
        draft_head = DraftHead.from_pretrained(draft_dir)
    else:
        scenes = split_scenes()[0]
        prompts = [toy_inputs(scenes[i : i + 64], tokenizer) for i in range(0, len(scenes), 64)]
        dataset = build_distillation_dataset(
            target, prompts, ACTION_DIM, action_tokenizer, progress=progress, image_features=True
        )
        torch.manual_seed(seed)  # the head's initialisation, independent of what ran before
        draft_head = DraftHead.from_target(
            target, action_tokenizer, action_dim=ACTION_DIM, num_draft_tokens=ACTION_DIM - 1, **TOY_HEAD_SETTINGS
        )
        config = DraftTrainingConfig(
            str(draft_dir),
            max_steps=draft_steps,
            batch_size=32,
            learning_rate=draft_learning_rate,
            lr_schedule="cosine",
            warmup_steps=50,
            save_every=0,
            seed=seed,
            unroll_steps=ACTION_DIM - 1,
        )
        draft_head = train_draft_head(draft_head, target, dataset, config, progress=progress)
    return target, tokenizer, action_tokenizer, draft_head


def early_exit_assistant(target, num_layers: int = 1):
    """A small draft model for transformers' assisted generation made from ``target`` itself: the same Llava-style
    model with only its first ``num_layers`` decoder layers (vision tower, projector, embeddings, final norm and
    lm_head shared by value), so it shares the vocabulary and needs no training (LayerSkip's early exit, without its
    training). The peer's baseline in the toy benchmark.

    Raises:
        ValueError: ``num_layers`` is not in 1 .. the target's depth - 1.
    """
    config = copy.deepcopy(target.config)
    depth = config.text_config.num_hidden_layers
    if not 1 <= num_layers < depth:
        raise ValueError(
            f"an early-exit assistant keeps 1 .. {depth - 1} of the target's {depth} layers, got {num_layers}"
        )
    config.text_config.num_hidden_layers = num_layers
    assistant = _assistant_class(type(target))(config).to(target.device, target.dtype).eval()
    assistant.load_state_dict(target.state_dict(), strict=False)  # the deeper layers' weights are left out
    return assistant


class AssistantGenerationMixin:
    """``generate`` for a model that transformers' assisted generation calls as its assistant, without the two
    warnings transformers (5.24) logs at that call, which are of its own making: its ``AssistedCandidateGenerator``
    passes a ``generation_config`` together with ``min_new_tokens`` / ``max_new_tokens`` / ``use_cache`` ("Passing
    `generation_config` together with generation-related arguments ... is deprecated"), and the target's logits
    processors, among them the ``MinNewTokensLengthLogitsProcessor`` the assistant's ``generate`` builds again from
    that ``min_new_tokens`` ("... has been passed to `.generate()`, but it was also created"). Here the settings go
    into one copy of the config, and the target's processor is left to the one built from it: both mask the end of
    sequence up to the same position (the assistant continues the target's sequence), so the drafts are the same.
    """

    def generate(self, *args, generation_config=None, logits_processor=None, **kwargs):
        if generation_config is not None:
            generation_config = copy.copy(generation_config)  # transformers' own, reused at every round
            kwargs = generation_config.update(**kwargs)  # the generation settings in; the model's inputs back
            if logits_processor is not None and (generation_config.min_new_tokens or 0) > 0:
                logits_processor = LogitsProcessorList(
                    p for p in logits_processor if not isinstance(p, MinNewTokensLengthLogitsProcessor)
                )
        return super().generate(*args, generation_config=generation_config, logits_processor=logits_processor, **kwargs)


def _assistant_class(model_class: type) -> type:
    """``model_class`` with [`AssistantGenerationMixin`] (one class per model class)."""
    if model_class not in _ASSISTANT_CLASSES:
        _ASSISTANT_CLASSES[model_class] = type(model_class.__name__, (AssistantGenerationMixin, model_class), {})
    return _ASSISTANT_CLASSES[model_class]


_ASSISTANT_CLASSES: dict[type, type] = {}


def shipped_toy_dir() -> Path | None:
    """The shipped toy pipeline's folder ([`SHIPPED_TOY_DIR`]) under the working directory or the checkout this
    module runs from (an editable install), None where neither has it (an installed wheel: ``demo --train`` builds
    one)."""
    for root in (Path.cwd(), Path(__file__).resolve().parents[3]):
        folder = root / SHIPPED_TOY_DIR
        if (folder / "target" / "config.json").exists() and (folder / "draft_head" / "config.json").exists():
            return folder
    return None


def load_toy_pipeline(output_dir: str) -> ToyPipeline:
    """A complete pipeline saved by [`build_toy_pipeline`], read as it is (nothing is trained or written).

    Raises:
        FileNotFoundError: naming the folder when its ``target/`` or ``draft_head/`` is missing.
    """
    from pathlib import Path

    from ..speculative import DraftHead, enable_speculation

    root = Path(output_dir)
    target_dir, draft_dir = root / "target", root / "draft_head"
    if not (target_dir / "config.json").exists() or not (draft_dir / "config.json").exists():
        raise FileNotFoundError(f"{str(root)!r} has no target/ and draft_head/ saved by `hf-specvla demo`")
    target, tokenizer, action_tokenizer = _load_toy_target(target_dir)
    draft_head = DraftHead.from_pretrained(draft_dir)
    return ToyPipeline(str(root), enable_speculation(target.eval()), tokenizer, action_tokenizer, draft_head.eval())


def _load_toy_target(target_dir):
    from transformers import PreTrainedTokenizerFast

    logger.info("loading toy target from %s", target_dir)
    target = LlavaForConditionalGeneration.from_pretrained(target_dir)
    tokenizer = PreTrainedTokenizerFast.from_pretrained(target_dir)
    return target, tokenizer, ActionTokenizer(len(tokenizer))
