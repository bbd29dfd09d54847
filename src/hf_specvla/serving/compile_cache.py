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

A damaged folder heals: the warm-up that records a folder also lists its files with their sizes and SHA-256
(``files.json``), and a start checks them before it uses the folder. A folder whose record or list cannot be read, or
whose listed files are missing, unreadable, shorter, longer or changed (a disk that filled up, a copy cut short, a
crash before the data reached the disk) is set aside, renamed ``DIR/<key>.damaged-<UTC time>`` (never deleted), with a
warning naming it and its first damaged file, and the start compiles cold into a fresh ``DIR/<key>``. Files torch adds
after the list is written (a later compile's) are not damage. Should a start that reuses a folder's files still fail
while it compiles, the folder is set aside the same way and the error says so: the next start compiles cold.

The engine's own graphs (the rounds, the prefill, the image encoder: ``speculative.graph_files``) are files in
``DIR/graphs`` ([`GRAPHS_FOLDER`]), which a later start loads without dynamo tracing them; Inductor's folder keeps
the compile of whatever stays in memory (transformers' own compiled greedy of a greedy-only server). On a GPU, where
graph files are off unless ``HF_SPECVLA_GRAPH_CACHE`` turns them on, dynamo traces every graph again and Inductor's
compile and the C++ compile of its kernels are what the folder saves (docs/serving.md, "Warm starts", has the
figures).

The cache folder is set for the warm-up only (torch's ``temporary_cache_dir``): a compile in another thread meanwhile
writes its (content-keyed) artefacts there too, which costs nothing and changes no result.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import platform
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

logger = logging.getLogger(__name__)

#: the engine's own graph files (``speculative.graph_files``) in the folder given: ``DIR/graphs``, one for every key
#: (each file keyed by what its graph depends on), what a warm start loads without dynamo tracing
GRAPHS_FOLDER = "graphs"
#: a warm-up's record in its key's folder: written once the warm-up is done (a folder without it is cold)
RECORD_FILE = "record.json"
#: Inductor's cache folder inside a key's folder
INDUCTOR_FOLDER = "inductor"
#: a warm-up's list of its Inductor folder's files (``{"files": {path in the key's folder: [size, SHA-256]}}``),
#: written just before the record
FILES_FILE = "files.json"
#: a damaged key's folder is renamed ``<key><DAMAGED><UTC time>`` beside it (never deleted)
DAMAGED = ".damaged-"
#: files torch writes and removes as it goes, never read as a cache: not listed (lock files, half-written temporaries)
TRANSIENT_SUFFIXES = (".lock", ".tmp")


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for chunk in iter(lambda: file.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _cache_files(folder: Path) -> list[Path]:
    """The files under ``folder/inductor`` that torch may read again (not its transient ones), sorted."""
    found = []
    for parent, _, names in os.walk(folder / INDUCTOR_FOLDER):
        found += [Path(parent, name) for name in names if not name.endswith(TRANSIENT_SUFFIXES)]
    return sorted(found)


@dataclass
class CompileCache:
    """The compile cache of one set of settings in ``root`` (see module docstring).

    Attributes:
        root: the folder given (``--compile-cache``); one sub-folder per key.
        record: what the graphs depend on (JSON values); its fingerprint is the key.
    """

    root: Path
    record: dict
    #: where the last [`compiling`] set this key's damaged folder aside (None: it set nothing aside)
    set_aside: Path | None = field(default=None, init=False, compare=False)

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
        """Whether a finished warm-up of these settings recorded its folder, and its files are as recorded."""
        return (self.folder / RECORD_FILE).exists() and self.damage() is None

    def damage(self) -> str | None:
        """What is wrong with this key's folder, the first thing found: its record or its list of files unreadable,
        or a listed file missing, unreadable, of another size or changed. None when nothing is: a sound folder, or
        one that no warm-up recorded (no folder, or a warm-up's that did not finish: a cold start's to compile into)."""
        record_file = self.folder / RECORD_FILE
        if not record_file.exists():
            return None
        try:
            record = json.loads(record_file.read_text())
        except (OSError, ValueError) as error:
            return f"{RECORD_FILE} cannot be read ({type(error).__name__}: {error})"
        if record != self.record:
            return f"{RECORD_FILE} holds other settings than its key's"
        try:
            files = json.loads((self.folder / FILES_FILE).read_text())["files"]
            listed = {str(name): (int(size), str(sha256)) for name, (size, sha256) in files.items()}
        except FileNotFoundError:
            return f"{FILES_FILE} is missing"
        except (OSError, ValueError, TypeError, KeyError, AttributeError) as error:
            return f"{FILES_FILE} cannot be read ({type(error).__name__}: {error})"
        for name, (size, sha256) in sorted(listed.items()):
            path = self.folder / name
            try:
                found = path.stat().st_size
                if found != size:
                    return f"{name} has {found} bytes, {size} when recorded"
                if _sha256(path) != sha256:
                    return f"{name} changed since it was recorded (its SHA-256 differs)"
            except FileNotFoundError:
                return f"{name} is missing"
            except OSError as error:
                return f"{name} cannot be read ({type(error).__name__}: {error})"
        return None

    def _set_folder_aside(self) -> Path:
        """Renames this key's folder ``<key>.damaged-<UTC time>`` (a free name) beside it; returns the new name."""
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        aside, n = self.root / f"{self.key}{DAMAGED}{stamp}", 1
        while aside.exists():
            aside, n = self.root / f"{self.key}{DAMAGED}{stamp}-{n}", n + 1
        self.folder.rename(aside)
        self.set_aside = aside
        return aside

    def _record_files(self) -> None:
        """Writes the list of the Inductor folder's files (sizes and SHA-256s), then the record."""
        from ..run_folder import write_json_atomic

        files = {}
        for path in _cache_files(self.folder):
            try:
                files[path.relative_to(self.folder).as_posix()] = [path.stat().st_size, _sha256(path)]
            except FileNotFoundError:  # removed meanwhile (by another start's torch): not a file to check later
                continue
        write_json_atomic(self.folder / FILES_FILE, {"files": files})
        write_json_atomic(self.folder / RECORD_FILE, self.record)

    def others(self) -> list[str]:
        """The other keys' caches in ``root``, each as ``<key>: <its first difference from this record>``."""
        described = []
        for record_file in sorted(self.root.glob(f"*/{RECORD_FILE}")):
            if record_file.parent == self.folder or DAMAGED in record_file.parent.name:
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
            described.append(
                f"{record_file.parent.name}: {first} {theirs.get(first)!r} there, {self.record.get(first)!r} here"
            )
        return described

    @contextmanager
    def compiling(self) -> Iterator[bool]:
        """Within the block, torch compiles with this key's folder as Inductor's cache; yields whether the start is
        warm (and says so in the log). The record is written when the block ends without an error.

        A damaged folder ([`damage`]) is set aside first, with a warning naming it, and the start is cold. An
        exception in the block of a start that reused the folder's files sets the folder aside too, and is raised
        again as a RuntimeError naming the folder (the next start compiles cold)."""
        from torch._inductor.runtime.cache_dir_utils import temporary_cache_dir

        self.set_aside = None
        damage = self.damage()
        if damage is not None:
            try:
                aside = self._set_folder_aside()
            except FileNotFoundError:  # another start (a replica) set it aside meanwhile
                aside = "another start's name"
            except OSError as error:  # e.g. a folder the server may read but not rename: compile without it
                logger.warning(
                    "compile cache %s: %s is damaged, %s, and cannot be set aside (%s): this start "
                    "compiles without the compile cache",
                    self.root,
                    self.folder,
                    damage,
                    error,
                )
                yield False
                return
            logger.warning(
                "compile cache %s: %s is damaged, %s: set aside as %s; this start compiles cold",
                self.root,
                self.folder,
                damage,
                aside,
            )
        warm = damage is None and (self.folder / RECORD_FILE).exists()
        inductor = self.folder / INDUCTOR_FOLDER
        reused = warm or bool(_cache_files(self.folder))  # a warm folder, or what an unfinished warm-up left
        if warm:
            logger.info("compile cache %s: warm (%s)", self.root, self.folder)
        else:
            others = self.others()
            beside = f"; it holds other settings' caches, not used: {'; '.join(others[:3])}" if others else ""
            logger.info("compile cache %s: cold, compiling into %s%s", self.root, self.folder, beside)
        inductor.mkdir(parents=True, exist_ok=True)
        try:
            with temporary_cache_dir(str(inductor)):
                yield warm
        except Exception as error:
            if not reused:
                raise
            try:
                healed = f"set aside as {self._set_folder_aside()}: the next start compiles cold"
            except OSError as rename_error:  # e.g. gone already: another start set it aside
                healed = f"not set aside ({rename_error}): a start compiles cold once it is gone"
            logger.warning(
                "compile cache %s: a start from the compiled files in %s failed (%s); the folder is %s",
                self.root,
                self.folder,
                type(error).__name__,
                healed,
            )
            raise RuntimeError(
                f"compile cache {self.root}: a start from the compiled files in {self.folder} failed "
                f"({type(error).__name__}, above); the folder is {healed}"
            ) from error
        self._record_files()


def environment_record() -> dict:
    """The versions compiled graphs depend on: torch, transformers, Python, hf_specvla's code, the machine."""
    import torch
    import transformers

    from ..run_folder import code_version

    return {
        "torch": torch.__version__,
        "transformers": transformers.__version__,
        "python": ".".join(map(str, sys.version_info[:3])),
        "hf_specvla": code_version(),
        "machine": platform.machine(),
    }
