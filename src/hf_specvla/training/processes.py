"""The processes of one training run: one, or several started by ``accelerate launch`` / ``torchrun`` (one a GPU;
on a machine without any accelerator, processes on the CPU that talk over gloo, which accelerate only does when
told ``cpu=True``: [`process_state`] tells it).

Every process computes; only the main one writes (the run folder's claim and ``run.json``, logs, the saved model,
the model card). A step's batch is ``batch_size`` examples *per process*: ``n`` processes with ``batch_size=b``
train on what one process with ``batch_size=n b`` trains on (accelerate deals the shuffled epoch out batch by batch),
so the run's record holds the global batch: a resume with another process count and the same global batch continues
the run, one with another global batch is refused as another run.
"""

from __future__ import annotations

import os

import torch
from accelerate import PartialState

from ..progress import is_secondary_process


def launched_processes() -> int:
    """How many processes the launcher started (``WORLD_SIZE``; 1 without a launcher). Cheap: no process group."""
    return int(os.environ.get("WORLD_SIZE", "1"))


def _has_accelerator() -> bool:
    accelerator = getattr(torch, "accelerator", None)
    if accelerator is not None:
        return accelerator.is_available()
    return torch.cuda.is_available()


def on_cpu_processes() -> bool:
    """Several launched processes on a machine without an accelerator: accelerate's MULTI_CPU (gloo)."""
    return launched_processes() > 1 and not _has_accelerator()


def process_state() -> PartialState:
    """accelerate's state of this process (its process group started on first use), the one the run's
    ``Accelerator`` shares."""
    return PartialState(cpu=on_cpu_processes())


def global_batch_size(batch_size: int, processes: int | None = None) -> int:
    """The examples one optimizer step learns from: ``batch_size`` per process times the processes."""
    return batch_size * (launched_processes() if processes is None else processes)


def is_main_process() -> bool:
    """True in a run of one process, and in the main process of a launched group: the one that writes (the launcher's
    ``RANK`` 0, as ``progress.is_secondary_process`` reads it)."""
    return not is_secondary_process()


def mean_over_processes(value: torch.Tensor) -> torch.Tensor:
    """``value`` averaged over the launched processes (every process must call it alike, in the same order); itself in
    a run of one process or outside a process group."""
    if launched_processes() == 1 or not torch.distributed.is_available() or not torch.distributed.is_initialized():
        return value
    total = value.detach().clone()
    torch.distributed.all_reduce(total)
    return total / torch.distributed.get_world_size()
