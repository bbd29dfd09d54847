"""Counting host syncs: the tensor methods that make the host wait for the device (on CUDA, each drains the queue of
launched kernels before the host goes on). Used by the tests that bound the engine's syncs per round and by
``examples/benchmarks/gpu_openvla.py``."""

from __future__ import annotations

import traceback
from collections import Counter

import torch
from torch.overrides import TorchFunctionMode

#: the tensor methods that read a value (or a data-dependent shape) back to the host
SYNC_METHODS = frozenset(
    {
        torch.Tensor.item,
        torch.Tensor.tolist,
        torch.Tensor.cpu,
        torch.Tensor.numpy,
        torch.Tensor.__bool__,
        torch.Tensor.__int__,
        torch.Tensor.__float__,
        torch.Tensor.__index__,
        torch.Tensor.nonzero,
        torch.Tensor.unique,
    }
)


class HostSyncCounter(TorchFunctionMode):
    """Counts the host syncs ([`SYNC_METHODS`]) made while it is active, and where (the innermost ``hf_specvla``
    frame, else ``"elsewhere"``), whatever the device (on the CPU they cost nothing, but they are the same calls).

    Example:
        ```python
        with HostSyncCounter() as syncs:
            model.generate(**inputs, assistant_model=drafter)
        print(syncs.count, syncs.sites.most_common(5))
        ```
    """

    def __init__(self):
        super().__init__()
        self.count = 0
        self.sites: Counter = Counter()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if func in SYNC_METHODS:
            self.count += 1
            stack = traceback.extract_stack()[:-1]
            frames = [f for f in stack if "hf_specvla" in f.filename and f.filename != __file__]
            self.sites[
                f"{frames[-1].filename.rsplit('hf_specvla/', 1)[-1]}:{frames[-1].lineno}" if frames else "elsewhere"
            ] += 1
        return func(*args, **(kwargs or {}))
