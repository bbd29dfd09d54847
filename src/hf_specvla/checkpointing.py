"""Training checkpoints shared by the trainers: ``output_dir/checkpoint-<step>/`` folders holding the model
(``save_pretrained``), the accelerate state (optimizer, scheduler, RNG) and ``trainer_state.pt`` (written last:
a checkpoint without it is incomplete and ignored)."""

from __future__ import annotations

import re
import shutil
from collections.abc import Callable
from pathlib import Path

import torch
from accelerate import Accelerator

CHECKPOINT_PATTERN = re.compile(r"^checkpoint-(\d+)$")
TRAINER_STATE = "trainer_state.pt"


def list_checkpoints(output_dir: Path) -> list[tuple[int, Path]]:
    """Complete checkpoints in ``output_dir``, oldest first."""
    found = []
    if output_dir.is_dir():
        for child in output_dir.iterdir():
            match = CHECKPOINT_PATTERN.match(child.name)
            if match and child.is_dir() and (child / TRAINER_STATE).exists():
                found.append((int(match.group(1)), child))
    return sorted(found)


def latest_checkpoint(output_dir: str | Path) -> Path | None:
    """The newest complete ``checkpoint-<step>`` folder in ``output_dir``, or None."""
    found = list_checkpoints(Path(output_dir))
    return found[-1][1] if found else None


def check_output_dir(output_dir: Path, resume: bool, overwrite: bool) -> None:
    """Refuses to train into a non-empty folder unless resuming or explicitly overwriting."""
    if not output_dir.exists() or not any(output_dir.iterdir()) or resume or overwrite:
        return
    raise FileExistsError(
        f"output_dir {str(output_dir)!r} is not empty; pass resume=True (--resume) to continue its training, "
        f"overwrite_output_dir=True (--overwrite-output-dir) to train from scratch into it, or choose another folder"
    )


def resume_step(accelerator: Accelerator, output_dir: Path) -> int:
    """Loads the newest checkpoint's accelerate state; returns its step (0 when there is none)."""
    checkpoint = latest_checkpoint(output_dir)
    if checkpoint is None:
        return 0
    accelerator.load_state(str(checkpoint))
    return int(torch.load(checkpoint / TRAINER_STATE, weights_only=True)["step"])


def save_checkpoint(
    accelerator: Accelerator,
    output_dir: Path,
    step: int,
    save_model: Callable[[Path], None],
    keep: int,
) -> Path:
    """Writes ``checkpoint-<step>`` (``save_model(folder)`` saves the model part) and prunes to ``keep``."""
    checkpoint = output_dir / f"checkpoint-{step}"
    accelerator.save_state(str(checkpoint))
    if accelerator.is_main_process:
        save_model(checkpoint)
        torch.save({"step": step}, checkpoint / TRAINER_STATE)
        for _, old in list_checkpoints(output_dir)[:-keep]:
            shutil.rmtree(old)
    accelerator.wait_for_everyone()
    return checkpoint
