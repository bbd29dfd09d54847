"""One rule for every command that writes a folder: the folder records what produced it, and a run continues
into it only when that matches.

``run.json`` holds the command, the settings that shape its results (model identities by content fingerprint,
not by path) and the code version. [`open_run_folder`]:

* an empty or missing folder: starts a new run and writes ``run.json`` first;
* a folder whose ``run.json`` matches: continues it (a differing code version is only logged);
* a folder whose ``run.json`` differs: refuses, naming the first differing setting, and offers a new folder or
  the explicit overwrite;
* a non-empty folder without ``run.json`` (another tool, an older hf_specvla): refuses, as it cannot be checked;
* ``overwrite=True``: moves the previous contents aside to ``<folder>.replaced-<UTC time>`` (nothing is deleted,
  nothing is half-kept), then starts a new run.

Append-only logs are read with [`read_jsonl`], which drops a torn last line (a crash mid-write) with a warning so
that its record is redone; summaries are written with [`write_json_atomic`].
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

logger = logging.getLogger(__name__)

RUN_FILE = "run.json"


def fingerprint(module: torch.nn.Module) -> str:
    """Content fingerprint of a model's weights (16 hex digits of a SHA-256 over names, shapes, dtypes, bytes):
    the same weights give the same fingerprint wherever they were loaded from."""
    digest = hashlib.sha256()
    for name, tensor in sorted(module.state_dict().items()):
        digest.update(f"{name}:{tuple(tensor.shape)}:{tensor.dtype}".encode())
        digest.update(tensor.detach().cpu().contiguous().view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()[:16]


def fingerprint_arrays(*arrays) -> str:
    """Content fingerprint (16 hex digits) of numpy arrays / tensors, e.g. a dataset's actions and states."""
    digest = hashlib.sha256()
    for array in arrays:
        if isinstance(array, torch.Tensor):
            array = array.detach().cpu().numpy()
        digest.update(f"{array.shape}:{array.dtype}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()[:16]


def code_version() -> str:
    """hf_specvla's version (recorded, compared only to warn)."""
    from . import __version__

    return __version__


@dataclass
class RunRecord:
    """What produced a folder: ``command`` and ``settings`` must match to continue; ``code_version`` is logged."""

    command: str
    settings: dict
    code_version: str = ""

    def __post_init__(self):
        self.code_version = self.code_version or code_version()
        self.settings = json.loads(json.dumps(self.settings))  # JSON-normal form (tuples -> lists), as saved

    def differences(self, other: RunRecord) -> list[str]:
        """Human-readable differences of ``other`` (this run) from ``self`` (the folder's record)."""
        if self.command != other.command:
            return [f"it was written by `hf-specvla {self.command}`, this is `hf-specvla {other.command}`"]
        keys = sorted(set(self.settings) | set(other.settings))
        return [
            f"{key}={self.settings.get(key)!r} there, {other.settings.get(key)!r} now"
            for key in keys
            if self.settings.get(key) != other.settings.get(key)
        ]


def check_run_folder(folder: str | Path, record: RunRecord) -> bool:
    """The refusals of [`open_run_folder`] without writing anything: call it before a long preparation (data,
    models) so that a folder that would be refused is refused first.

    Returns:
        True when an existing run would be continued.
    """
    folder = Path(folder)
    run_file = folder / RUN_FILE
    if not folder.exists() or not any(folder.iterdir()):
        return False
    ways_out = "choose another output folder, or pass --overwrite-output-dir to move this one aside and start over"
    if not run_file.is_file():
        raise FileExistsError(
            f"{str(folder)!r} is not empty and has no {RUN_FILE}, so what produced it cannot be checked (another "
            f"tool, or hf_specvla before this rule); {ways_out}"
        )
    saved = RunRecord(**json.loads(run_file.read_text()))
    differences = saved.differences(record)
    if differences:
        raise FileExistsError(f"{str(folder)!r} holds another run: {'; '.join(differences)}; {ways_out}")
    if saved.code_version != record.code_version:
        logger.warning("%s was written by hf_specvla %s; continuing with %s", folder, saved.code_version,
                       record.code_version)  # fmt: skip
    return True


def open_run_folder(folder: str | Path, record: RunRecord, overwrite: bool = False) -> bool:
    """Applies the module's rule to ``folder`` for a run described by ``record``.

    Returns:
        True when an existing run is continued, False when a new run starts (``run.json`` is then written).
    Raises:
        FileExistsError: the folder holds another run's (or an unrecorded) results; the message names the
            differing setting and the two ways out.
    """
    folder = Path(folder)
    empty = not folder.exists() or not any(folder.iterdir())
    if overwrite and not empty:
        aside = folder.with_name(f"{folder.name}.replaced-{time.strftime('%Y%m%dT%H%M%S', time.gmtime())}")
        os.replace(folder, aside)
        logger.warning("moved the previous contents of %s aside to %s (--overwrite-output-dir)", folder, aside)
    if check_run_folder(folder, record):
        return True
    folder.mkdir(parents=True, exist_ok=True)
    write_json_atomic(folder / RUN_FILE, asdict(record))
    return False


def write_json_atomic(path: str | Path, data) -> None:
    """Writes JSON to ``path`` through a temporary file and a rename: a crash leaves the old file or the new one."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.tmp")
    temporary.write_text(json.dumps(data, indent=2))
    os.replace(temporary, path)


def read_jsonl(path: str | Path) -> list[dict]:
    """The records of an append-only JSON-lines log. A torn last line (a crash mid-write) is dropped from the file
    with a warning, so that its record is redone; a torn line elsewhere is an error naming the line."""
    path = Path(path)
    if not path.exists():
        return []
    lines = path.read_text().splitlines()
    records = []
    for number, line in enumerate(lines, 1):
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            if number < len(lines):
                raise ValueError(f"{str(path)!r} line {number} is not valid JSON: the log is damaged") from None
            logger.warning("%s: dropping a torn last line (a crash mid-write); that record is redone", path)
            path.write_text("".join(line + "\n" for line in lines[:-1]))
    return records
