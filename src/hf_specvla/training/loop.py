"""The one training loop. Behaviour cloning (``train-vla``), draft-head distillation (``train-draft``, the demo's head)
and the demo's toy target all train here; a caller gives a [`TrainingJob`] (the model, its data, a loss function
returning ``(loss, metrics)``, a save function and a validation hook) and its config's optimisation settings.

What every caller gets, alike: AdamW + a warm-up then constant or cosine schedule, gradient clipping at
``max_grad_norm``, accelerate (one process, or several under ``accelerate launch`` / ``torchrun`` on GPUs or on the
CPU: ``training.processes``; mixed precision, gradient accumulation), a progress bar,
``training_log.jsonl`` every ``log_every`` steps, validation every ``eval_every`` steps (0: only at the end) and
after the last step (``validation.jsonl``, and merged into that step's log line as ``val_<name>``),
``checkpoint-<step>`` every ``save_every`` steps and at the last step (so a finished run continues with a larger
``max_steps``), the final model through the caller's save function and ``training_config.json`` (settings, steps,
final metrics).

Resume is exact: the data order comes from accelerate's seedable sampler (epoch = step // batches per epoch, the
epoch's first batches skipped), and anything random in a step is seeded by ``(seed, step)`` inside the caller's loss
(the loop passes ``step``), so a run killed and resumed computes what an uninterrupted one computes. A loss that seeds
by ``(seed, step, example)`` (the draft head's) also computes the same on any number of processes.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
from accelerate import Accelerator
from accelerate.utils import DataLoaderConfiguration, set_seed
from torch.utils.data import DataLoader, Dataset

from ..progress import progress_bar
from .checkpoints import resume_step, save_checkpoint
from .processes import global_batch_size, mean_over_processes, on_cpu_processes

logger = logging.getLogger(__name__)

TRAINING_LOG = "training_log.jsonl"
VALIDATION_LOG = "validation.jsonl"
TRAINING_CONFIG = "training_config.json"


@dataclass
class TrainingJob:
    """What a caller trains.

    Args:
        model: the module optimised (its parameters with ``requires_grad``; frozen parts stay frozen).
        dataset: examples; batches come from a shuffled DataLoader with ``collate_fn``.
        loss: ``loss(model, batch, step) -> (loss, metrics)``; ``model`` is the accelerate-prepared module, ``metrics``
            numbers (or 0-d tensors) for the log; seed anything random from ``step``.
        save: ``save(model, folder)`` writes the unwrapped model (checkpoints and the final folder).
        validate: ``validate(model) -> metrics`` on the unwrapped model in eval mode without gradients, or None.
        collate_fn: the DataLoader's.
        drop_last: drop a last short batch of an epoch.
        checkpoint_name: the sub-folder of ``checkpoint-<step>`` the model is saved to (beside accelerate's state).
        description: the progress bar's label.
    """

    model: torch.nn.Module
    dataset: Dataset
    loss: Callable[[torch.nn.Module, Any, int], tuple[torch.Tensor, dict]]
    save: Callable[[torch.nn.Module, Path], None]
    validate: Callable[[torch.nn.Module], dict] | None = None
    collate_fn: Callable | None = None
    drop_last: bool = False
    checkpoint_name: str = "model"
    description: str = "train"


def learning_rate_factor(step: int, warmup_steps: int, max_steps: int, schedule: str) -> float:
    """Linear warm-up over ``warmup_steps``, then constant or cosine decay to 0 at ``max_steps``."""
    if step < warmup_steps:
        return (step + 1) / warmup_steps
    if schedule == "constant":
        return 1.0
    progress = (step - warmup_steps) / max(1, max_steps - warmup_steps)
    return 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress)))


def default_accelerator(config) -> Accelerator:
    """The accelerator a run gets unless the caller brings one: ``config.mixed_precision``, a seedable sampler (the
    data order resume relies on), gloo processes on a machine without an accelerator (``training.processes``), and
    the schedule stepped once an optimizer step (accelerate's default steps it once a process: n processes would
    warm up and decay n times faster than one)."""
    return Accelerator(
        mixed_precision=config.mixed_precision,
        dataloader_config=DataLoaderConfiguration(use_seedable_sampler=True),
        cpu=on_cpu_processes(),
        step_scheduler_with_optimizer=False,
    )


def _numbers(metrics: dict, over_processes: bool = False) -> dict:
    """One-number tensors as floats, longer ones as lists (per step, per position); other values as they are. With
    ``over_processes``, tensors are first averaged over a launched run's processes (``mean_over_processes``; every
    process must call it alike): the log shows the global batch's numbers, not the main process's share."""

    def number(value):
        if not isinstance(value, torch.Tensor):
            return value
        if over_processes:
            value = mean_over_processes(value.detach().float())
        return value.item() if value.numel() == 1 else [round(x, 4) for x in value.tolist()]  # per step, per position

    return {name: number(value) for name, value in metrics.items()}


def _append_jsonl(path: Path, row: dict) -> None:
    with path.open("a") as log:
        log.write(json.dumps(row) + "\n")


def run_training(
    job: TrainingJob, config, output_dir: Path, accelerator: Accelerator | None = None, progress: bool = True
) -> tuple[torch.nn.Module, dict[str, float]]:
    """Trains ``job.model`` for ``config.max_steps`` optimizer steps into ``output_dir`` (a folder the caller holds,
    see ``checkpoints.prepare_output_dir``); with ``config.resume`` continues from its newest checkpoint.

    ``config`` provides: ``max_steps, batch_size, learning_rate, betas, weight_decay, max_grad_norm, warmup_steps,
    lr_schedule, save_every, eval_every, log_every, keep_checkpoints, resume, seed, mixed_precision``.

    Returns:
        (the unwrapped model in eval mode, the last step's metrics with the final validation's).
    """
    output_dir = Path(output_dir)
    accelerator = accelerator or default_accelerator(config)
    if accelerator.is_main_process:
        output_dir.mkdir(parents=True, exist_ok=True)
    set_seed(config.seed)
    model = job.model
    model.train()
    # every parameter, as checkpoints written before this loop hold them (frozen ones get no gradient: never moved)
    optimizer = torch.optim.AdamW(
        model.parameters(), lr=config.learning_rate, betas=tuple(config.betas), weight_decay=config.weight_decay
    )
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda step: learning_rate_factor(step, config.warmup_steps, config.max_steps, config.lr_schedule)
    )
    loader = DataLoader(
        job.dataset, batch_size=config.batch_size, shuffle=True, collate_fn=job.collate_fn, drop_last=job.drop_last
    )
    model, optimizer, loader, scheduler = accelerator.prepare(model, optimizer, loader, scheduler)
    if len(loader) == 0:
        raise ValueError(f"batch_size={config.batch_size} leaves no batch of {len(job.dataset)} examples")

    def save(checkpoint: Path) -> None:
        job.save(accelerator.unwrap_model(model), checkpoint / job.checkpoint_name)

    def validate(step: int) -> dict[str, float]:
        unwrapped = accelerator.unwrap_model(model)
        unwrapped.eval()
        with torch.no_grad():
            metrics = _numbers(job.validate(unwrapped))
        unwrapped.train()
        logger.info("%s step %d validation: %s", job.description, step, metrics)
        if accelerator.is_main_process:
            _append_jsonl(output_dir / VALIDATION_LOG, {"step": step, **metrics})
        return {f"val_{name}": value for name, value in metrics.items()}

    step = start = resume_step(accelerator, output_dir) if config.resume else 0
    if step:
        logger.info("%s: resuming from step %d", job.description, step)
    if step >= config.max_steps:
        logger.info("%s: nothing to do, checkpoint step %d >= max_steps %d", job.description, step, config.max_steps)
    bar = progress_bar(
        total=config.max_steps,
        initial=step,
        desc=job.description,
        disable=not progress or not accelerator.is_main_process,
    )
    metrics: dict[str, float] = {}
    while step < config.max_steps:
        epoch, offset = divmod(step, len(loader))
        loader.set_epoch(epoch)
        for batch in accelerator.skip_first_batches(loader, offset) if offset else loader:
            with accelerator.accumulate(model):
                loss, step_metrics = job.loss(model, batch, step)
                accelerator.backward(loss)
                if accelerator.sync_gradients:
                    accelerator.clip_grad_norm_(model.parameters(), config.max_grad_norm)
                optimizer.step()
                scheduler.step()
                optimizer.zero_grad()
            step += 1
            metrics = _numbers(step_metrics, over_processes=True)
            bar.update(1)
            bar.set_postfix({name: f"{value:.4g}" for name, value in list(metrics.items())[:2]})
            last = step >= config.max_steps
            if job.validate is not None and (last or (config.eval_every and step % config.eval_every == 0)):
                metrics.update(validate(step))
            if accelerator.is_main_process and (last or step % config.log_every == 0):
                _append_jsonl(output_dir / TRAINING_LOG, {"step": step, "lr": scheduler.get_last_lr()[0], **metrics})
            if config.save_every and (last or step % config.save_every == 0):
                save_checkpoint(accelerator, output_dir, step, save, config.keep_checkpoints)
            if last:
                break
    bar.close()
    unwrapped = accelerator.unwrap_model(model).eval()
    finished_before = step == start and (output_dir / TRAINING_CONFIG).exists()  # resumed a finished run: keep it
    if accelerator.is_main_process and not finished_before:
        job.save(unwrapped, output_dir)
        (output_dir / TRAINING_CONFIG).write_text(
            json.dumps(
                {
                    **asdict(config),
                    "steps": step,
                    "processes": accelerator.num_processes,
                    "global_batch_size": global_batch_size(config.batch_size, accelerator.num_processes),
                    "final_metrics": metrics,
                },
                indent=2,
            )
        )
    accelerator.wait_for_everyone()
    logger.info("%s: %d steps, %s", job.description, step, metrics)
    return unwrapped, metrics
