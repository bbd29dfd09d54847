"""Training checkpoints shared by the trainers: ``output_dir/checkpoint-<step>/`` folders holding the model
(``save_pretrained``), the accelerate state (optimizer, scheduler, RNG) and ``trainer_state.pt`` (written last:
a checkpoint without it is incomplete and ignored).

The output folder follows the folder rule of [`hf_specvla.run_folder`]: ``run.json`` records the settings that
shape the run (not ``max_steps``: a resumed run may train longer) and the fingerprints of what it learns from;
``--resume`` continues only a matching run that has a checkpoint; ``--overwrite-output-dir`` moves the previous
run aside whole (its checkpoints and logs never mix with the new run's)."""

from __future__ import annotations

import re
import shutil
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import torch
from accelerate import Accelerator
from accelerate.utils import broadcast_object_list

from ..run_folder import (
    RUN_FILE,
    RunFolder,
    RunRecord,
    check_run_folder,
    claim_run_folder,
    follow_run_folder,
    is_empty_folder,
)
from .processes import global_batch_size, launched_processes, process_state

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


#: Training settings that do not change what a run computes: a resumed run may change them.
RUN_INDEPENDENT_SETTINGS = frozenset(
    {
        "output_dir",
        "resume",
        "overwrite_output_dir",
        "max_steps",
        "eval_every",
        "save_every",
        "log_every",
        "keep_checkpoints",
    }
)


def training_record(command: str, config, inputs: dict, paths: dict | None = None) -> RunRecord:
    """The [`RunRecord`] of a training run: ``config``'s run-shaping fields and ``inputs`` (fingerprints); ``paths``
    where the inputs were read from and how many processes trained (recorded, never compared). ``batch_size`` is
    recorded as the global batch (``training.processes``): n processes of b examples train as one process of n b."""
    settings = {k: v for k, v in asdict(config).items() if k not in RUN_INDEPENDENT_SETTINGS}
    processes = launched_processes()
    if "batch_size" in settings:
        settings["batch_size"] = global_batch_size(settings["batch_size"], processes)
    paths = {**(paths or {}), **({"processes": processes} if processes > 1 else {})}
    return RunRecord(command, {**settings, **inputs}, paths=paths)


def check_output_dir(
    output_dir: Path, record: RunRecord | None, resume: bool, overwrite: bool, kind: str = "training run"
) -> None:
    """The refusals of [`prepare_output_dir`], without writing anything (call it before a long preparation;
    ``record=None``: all but the comparison with the folder's record, e.g. before the data is known). ``kind``: what
    the folder holds, for messages; only a "training run" needs a checkpoint to resume (a folder of episodes, e.g.
    ``rollouts``, resumes from its files).

    Raises:
        FileNotFoundError: ``resume`` into a folder that does not exist or is empty (nothing to resume).
        FileExistsError: a non-empty folder that holds no run record (another tool's files); a non-empty folder
            without ``resume`` / ``overwrite``; ``resume`` with no checkpoint to resume from; or a folder that holds
            another run (naming the differing setting).
    """
    output_dir = Path(output_dir)
    training = kind == "training run"
    start_over = "train from scratch" if training else "start over"
    if overwrite:
        return
    if is_empty_folder(output_dir):
        if resume:
            state = "is empty" if output_dir.exists() else "does not exist"
            raise FileNotFoundError(
                f"--resume: {str(output_dir)!r} {state}, so there is no run to resume; drop --resume to start a new "
                f"run there, or give the folder of the run to continue"
            )
        return
    if not (output_dir / RUN_FILE).is_file():
        raise FileExistsError(
            f"{str(output_dir)!r} holds no {kind} (it is not empty and has no {RUN_FILE}: another tool's files, "
            f"or a folder written before run records existed); choose another folder, or pass --overwrite-output-dir "
            f"to move it aside and {start_over}"
        )
    if record is not None:
        check_run_folder(output_dir, record)  # another run's folder: named first, whatever the flags
    if not resume:
        raise FileExistsError(
            f"output_dir {str(output_dir)!r} already holds this {kind}; pass --resume (resume=True) to continue "
            f"{'its training' if training else 'it'}, --overwrite-output-dir (overwrite_output_dir=True) to move it "
            f"aside and {start_over}, or choose another folder"
        )
    if training and latest_checkpoint(output_dir) is None:
        raise FileExistsError(
            f"--resume: {str(output_dir)!r} has no checkpoint-* to resume from (the run stopped before its first "
            f"checkpoint); pass --overwrite-output-dir to move it aside and train from scratch, or choose another "
            f"folder"
        )


def prepare_output_dir(output_dir: Path, record: RunRecord, resume: bool, overwrite: bool) -> RunFolder:
    """Claims the folder for a training run: its lock first, then the refusals of [`check_output_dir`], then a new
    folder gets ``record`` as its ``run.json`` (an overwritten one is moved aside first). Hold the returned
    [`RunFolder`] for the whole run and write through ``run.bound``.

    In a launched run of several processes (``training.processes``) every process looks at the folder before any
    writes (each refuses alike), the main process claims it, then the others follow it (no lock of their own)."""
    output_dir = Path(output_dir)
    check_output_dir(output_dir, record, resume, overwrite)  # the refusals, before the folder is touched
    if launched_processes() > 1:
        return _claim_with_every_process(output_dir, record, resume, overwrite)
    return _claim(output_dir, record, resume, overwrite)


def _claim_with_every_process(output_dir: Path, record: RunRecord, resume: bool, overwrite: bool) -> RunFolder:
    state = process_state()
    state.wait_for_everyone()  # every process has looked before the main one writes
    run = _claim(output_dir, record, resume, overwrite) if state.is_main_process else None
    continued = broadcast_object_list([run.continued if run is not None else None])[0]
    return run if run is not None else follow_run_folder(output_dir, continued)


def _claim(output_dir: Path, record: RunRecord, resume: bool, overwrite: bool) -> RunFolder:
    run = claim_run_folder(output_dir, record, overwrite=overwrite)
    try:
        if run.continued:  # again under the lock: the folder may have changed since the first look
            check_output_dir(output_dir, record, resume, overwrite=False)
    except BaseException:
        run.release()
        raise
    return run


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
