"""Warm starts: torch's own compile caches kept in a folder of the server's (``hf-specvla serve --compile-cache DIR``,
the Serve config's ``compile_cache`` argument), so that a server or a replica started again with the same policy,
methods, buckets and versions reuses the previous start's compile.

The caches are torch's, not ours: while the service warms up, Inductor's cache folder (``TORCHINDUCTOR_CACHE_DIR``:
its FX graph cache, the AOTAutograd cache and the compiled C++ kernels) is ``DIR/<key>/inductor``, where ``key``
fingerprints everything the graphs depend on ([`CompileCache.record`]: torch, transformers, Python, hf_specvla's code,
the policy's and the draft head's weights, the methods, the buckets, the longest prompt, the device). A start whose key
finds a folder that a finished warm-up recorded (``record.json``) starts warm; any other start is cold, compiles
into a folder of its own key, and records it once its warm-up is done. A cache made under other versions or settings
lives under another key: it is never used, and the start-up log names how it differs.

What a warm start still pays: dynamo traces every graph again (torch 2.13 keeps no cache of its own traced bytecode
outside the experimental ``TORCH_CACHING_PRECOMPILE``) and builds its guards; Inductor's compile and the C++ compile
of its kernels are what the folder saves (docs/serving.md, "Warm starts", has the figures).

The cache folder is set for the warm-up only (torch's ``temporary_cache_dir``): a compile in another thread meanwhile
writes its (content-keyed) artefacts there too, which costs nothing and changes no result.
"""

from __future__ import annotations

import hashlib
import json
import logging
import platform
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

logger = logging.getLogger(__name__)

#: a warm-up's record in its key's folder: written once the warm-up is done (a folder without it is cold)
RECORD_FILE = "record.json"
#: Inductor's cache folder inside a key's folder
INDUCTOR_FOLDER = "inductor"


@dataclass
class CompileCache:
    """The compile cache of one set of settings in ``root`` (see module docstring).

    Attributes:
        root: the folder given (``--compile-cache``); one sub-folder per key.
        record: what the graphs depend on (JSON values); its fingerprint is the key.
    """

    root: Path
    record: dict

    def __post_init__(self):
        self.root = Path(self.root)
        self.record = json.loads(json.dumps(self.record, sort_keys=True))  # JSON-normal form, as saved

    @property
    def key(self) -> str:
        """16 hex digits of a SHA-256 over the record."""
        return hashlib.sha256(json.dumps(self.record, sort_keys=True).encode()).hexdigest()[:16]

    @property
    def folder(self) -> Path:
        return self.root / self.key

    @property
    def warm(self) -> bool:
        """Whether a finished warm-up of these settings recorded its folder."""
        try:
            return json.loads((self.folder / RECORD_FILE).read_text()) == self.record
        except (OSError, ValueError):
            return False

    def others(self) -> list[str]:
        """The other keys' caches in ``root``, each as ``<key>: <its first difference from this record>``."""
        described = []
        for record_file in sorted(self.root.glob(f"*/{RECORD_FILE}")):
            if record_file.parent == self.folder:
                continue
            try:
                theirs = json.loads(record_file.read_text())
            except (OSError, ValueError):
                described.append(f"{record_file.parent.name}: an unreadable {RECORD_FILE}")
                continue
            differing = sorted(k for k in set(theirs) | set(self.record) if theirs.get(k) != self.record.get(k))
            if not differing:  # another key for the same record: a folder renamed by hand
                described.append(f"{record_file.parent.name}: the same settings under another name")
                continue
            first = differing[0]
            described.append(f"{record_file.parent.name}: {first} {theirs.get(first)!r} there, "
                             f"{self.record.get(first)!r} here")  # fmt: skip
        return described

    @contextmanager
    def compiling(self) -> Iterator[bool]:
        """Within the block, torch compiles with this key's folder as Inductor's cache; yields whether the start is
        warm (and says so in the log). The record is written when the block ends without an error."""
        from torch._inductor.runtime.cache_dir_utils import temporary_cache_dir

        warm = self.warm
        if warm:
            logger.info("compile cache %s: warm (%s)", self.root, self.folder)
        else:
            others = self.others()
            beside = f"; it holds other settings' caches, not used: {'; '.join(others[:3])}" if others else ""
            logger.info("compile cache %s: cold, compiling into %s%s", self.root, self.folder, beside)
        inductor = self.folder / INDUCTOR_FOLDER
        inductor.mkdir(parents=True, exist_ok=True)
        with temporary_cache_dir(str(inductor)):
            yield warm
        from ..run_folder import write_json_atomic

        write_json_atomic(self.folder / RECORD_FILE, self.record)


def environment_record() -> dict:
    """The versions compiled graphs depend on: torch, transformers, Python, hf_specvla's code, the machine."""
    import torch
    import transformers

    from ..run_folder import code_version

    return {"torch": torch.__version__, "transformers": transformers.__version__,
            "python": ".".join(map(str, sys.version_info[:3])), "hf_specvla": code_version(),
            "machine": platform.machine()}  # fmt: skip
