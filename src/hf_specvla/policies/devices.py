"""Where a policy runs and in what precision: the ``--device`` / ``--dtype`` of every command that runs one, and
``ServeConfig.device`` / ``dtype``, checked and resolved here only, as transformers and LeRobot users expect them:

- device: ``auto`` (``cuda`` when torch sees a GPU, else ``cpu``), ``cpu``, ``cuda``, ``cuda:N``;
- dtype: ``auto`` (``bfloat16`` on a CUDA device, ``float32`` on the CPU), ``bfloat16``, ``float16``, ``float32``.

The spelling is checked without torch ([`check_device`], [`check_dtype`]: the CLI parses its flags before torch
loads); whether the device is there needs torch ([`resolve_device`], [`Placement.resolve`]), asked right before a
model loads. [`Placement.place_policy`] moves a policy and its draft head once the head was checked against the policy
as saved: the head's check compares the weights it was distilled from with the policy's saved weights, not their
cast.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

#: the defaults of ``--device`` / ``--dtype`` and of ``ServeConfig``
DEFAULT_DEVICE, DEFAULT_DTYPE = "auto", "auto"
#: the devices and dtypes accepted (``cuda:N``: a GPU's index)
DEVICES = ("auto", "cpu", "cuda", "cuda:N")
DTYPES = ("auto", "bfloat16", "float16", "float32")
_DEVICE = re.compile(r"auto|cpu|cuda(:[0-9]+)?")


def check_device(device) -> str:
    """``device`` if it is spelled as a device (see module docstring); nothing imported, nothing asked of torch.

    Raises:
        ValueError: naming the value and the valid ones.
    """
    if not isinstance(device, str) or not _DEVICE.fullmatch(device):
        raise ValueError(f"{device!r} is not a device: give {', '.join(DEVICES)} (N: a GPU's index, e.g. cuda:0)")
    return device


def check_dtype(dtype) -> str:
    """``dtype`` if it is one of ``DTYPES``; nothing imported.

    Raises:
        ValueError: naming the value and the valid ones.
    """
    if dtype not in DTYPES:
        raise ValueError(f"{dtype!r} is not a dtype: give {', '.join(DTYPES)}")
    return dtype


def is_cuda(device) -> bool:
    """Whether ``device`` (a name as [`check_device`] takes it, or a ``torch.device``) is a CUDA device."""
    return str(device).split(":", 1)[0] == "cuda"


def resolve_device(device: str = DEFAULT_DEVICE) -> str:
    """The device to load onto: ``auto`` -> ``cuda`` when torch sees a GPU, else ``cpu``; any other device as given,
    once torch confirms it is there.

    Raises:
        ValueError: a misspelled device, or one this machine does not have (``cuda`` without CUDA, ``cuda:3`` with one
            GPU), naming it and the devices valid here.
    """
    check_device(device)
    if device == "cpu":
        return device
    import torch

    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    if device == "auto":
        return "cuda" if count else "cpu"
    index = int(device.partition(":")[2] or 0)
    if not count:
        raise ValueError(
            f"{device!r}: torch sees no CUDA device on this machine (torch.cuda.is_available() is False); valid here: "
            f"auto, cpu"
        )
    if index >= count:
        here = ", ".join(["auto", "cpu", "cuda", *(f"cuda:{i}" for i in range(count))])
        raise ValueError(f"{device!r}: this machine has {count} CUDA device(s); valid here: {here}")
    return device


def resolve_dtype(dtype: str = DEFAULT_DTYPE, device="cpu") -> torch.dtype:
    """The ``torch.dtype`` to cast to on ``device`` (a resolved device, or a ``torch.device``): ``auto`` ->
    ``torch.bfloat16`` on a CUDA device, ``torch.float32`` elsewhere; any other dtype as named. Asks nothing of the
    machine.

    Raises:
        ValueError: a dtype not in ``DTYPES``, naming it.
    """
    check_dtype(dtype)
    import torch

    if dtype == "auto":
        dtype = "bfloat16" if is_cuda(device) else "float32"
    return getattr(torch, dtype)


def dtype_name(dtype: torch.dtype) -> str:
    """``torch.bfloat16`` -> ``"bfloat16"`` (as ``--dtype`` and records spell it)."""
    return str(dtype).removeprefix("torch.")


@dataclass(frozen=True)
class Placement:
    """A resolved device and dtype: where the models of a command or a server go.

    Args:
        device: ``cpu``, ``cuda`` or ``cuda:N`` (never ``auto``: see [`resolve`]).
        dtype: the floating-point ``torch.dtype`` weights are cast to.
    """

    device: str
    dtype: torch.dtype

    @classmethod
    def resolve(cls, device: str = DEFAULT_DEVICE, dtype: str = DEFAULT_DTYPE) -> Placement:
        """``device`` and ``dtype`` as given (``--device`` / ``--dtype``, ``ServeConfig``) resolved on this machine
        ([`resolve_device`], [`resolve_dtype`]).

        Raises:
            ValueError: a misspelled value, or a device this machine does not have.
        """
        resolved = resolve_device(device)
        return cls(resolved, resolve_dtype(dtype, resolved))

    def __str__(self) -> str:
        return f"{self.device} in {dtype_name(self.dtype)}"

    def move(self, *modules) -> None:
        """Moves and casts each module (None skipped) in place."""
        for module in modules:
            if module is not None:
                module.to(device=self.device, dtype=self.dtype)

    def place_policy(self, policy, *modules) -> None:
        """Moves a [`VLAPolicy`]'s model and ``modules`` (its draft head), after pinning the policy's weights
        fingerprint to its weights as loaded (a draft head's check, run records and ``GET /info`` name the saved
        weights, whatever the dtype). Check a draft head (``policy.check_draft_head``) before: the check needs the
        head and the policy on one device and dtype, as both were saved."""
        policy.weights_fingerprint()
        self.move(policy.model, *modules)
