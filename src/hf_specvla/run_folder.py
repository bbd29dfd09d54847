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

**A run holds its folder** ([`claim_run_folder`], used by every command that writes one): it takes the folder's
lock (``.lock``, an OS file lock released even by a killed process; it names the holder's pid, command and start
time) *before* it checks, moves aside or writes anything, and holds it for the whole run. A second run on a locked
folder is refused naming the holder, ``--overwrite-output-dir`` included; a lock whose process is gone is taken
over with a warning. The run then writes through ``RunFolder.bound``, a path bound to the directory it claimed
(``/proc/<pid>/fd/<n>`` on Linux), so that renaming the folder, or moving it aside, never redirects a live run's
writes into another folder of the same name.

**Timings are of their conditions** ([`resolve_timing`], used by the commands whose records hold wall times): each
timed record carries the conditions it was timed under ([`timing_conditions`]: workers, threads, torch's threads,
[`machine_fingerprint`]), and ``timing.json`` names the folder's conditions, those its speed figures are of. A run
under other conditions is refused, naming both, unless it restarts the timing: then the earlier records keep
everything but their timings' place in speed figures (they stay in the logs), and only records timed under the new
conditions enter them. Records written before conditions were recorded are taken as timed under the conditions of
the first run that continues the folder (a warning says so), unless what the folder recorded elsewhere (e.g. a
summary's threads and workers) disagrees, or that run restarts the timing: then they are left out of speed figures.
"""

from __future__ import annotations

import fcntl
import functools
import hashlib
import json
import logging
import os
import platform
import shlex
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

logger = logging.getLogger(__name__)

RUN_FILE = "run.json"
LOCK_FILE = ".lock"
TIMING_FILE = "timing.json"


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


@functools.cache
def code_version() -> str:
    """hf_specvla's version and a digest of its source files, e.g. ``0.1.0+src.1a2b3c4d5e6f`` (recorded in every
    folder, compared only to warn: results written by different code are told apart)."""
    from . import __version__

    digest = hashlib.sha256()
    package = Path(__file__).resolve().parent
    for path in sorted(package.rglob("*.py")):
        digest.update(path.relative_to(package).as_posix().encode() + b"\0" + path.read_bytes())
    return f"{__version__}+src.{digest.hexdigest()[:12]}"


#: settings named first when a folder holds another run: what the results are *of* (weights, data) before how
#: they were made
IMPORTANT_SETTINGS = (
    "target",
    "policy",
    "init_from",
    "device",  # before the draft head: a draft head cast to another dtype has another fingerprint too
    "dtype",
    "draft_head",
    "data",
    "demonstrations",
    "methods",
    "env",
    "seed_start",
    "decoding",
    "policy_config",
    "draft_head_config",
)


#: dotted settings that hold paths in records written before ``RunRecord.paths`` existed: never compared
LEGACY_PATH_SETTINGS = frozenset({"draft_head_config.target_name_or_path", "data.demonstrations"})
#: a setting an old record cannot be compared on (see ``ADDED_SETTINGS``)
NOT_COMPARED = object()
#: settings added to records later: a record written before one existed (and a run that records it) is read with the
#: value it implied then, or not compared on it (``NOT_COMPARED``)
ADDED_SETTINGS = {
    "data.demonstration_fingerprints": NOT_COMPARED,
    # train-draft stored the target's hidden states in float32 before it stored them in float16
    "distillation.hidden_dtype": "float32",
    "draft_head_config.final_logit_softcapping": NOT_COMPARED,
    # train-vla's optimisation, hard-coded until the one training loop made it settings
    "betas": [0.9, 0.999],
    "max_grad_norm": 1.0,
    "lr_schedule": "cosine",
    "mixed_precision": "no",
    # compare's EAGLE-2 tree, DraftTreeConfig() until it became settings
    "tree.top_k": 4,
    "tree.depth": 6,
    "tree.total_tokens": 24,
    # train-vla trained every parameter before it could freeze the vision tower
    "freeze_vision": False,
    # ... and before it could read the scene where the actions are decoded
    "scene_readout_weight": 0.0,
    # the env's rendering (metaworld.env.RENDER_REVISION): runs before it was recorded rendered revision 1
    "env.render_revision": 1,
    # eval and compare ran every policy on the CPU in float32 before --device / --dtype
    "device": "cpu",
    "dtype": "float32",
}


def _flatten(settings: dict, prefix: str = "") -> dict:
    """Nested settings as dotted keys (``draft_head_config.hidden_size``), so that a difference names its leaf."""
    flat = {}
    for key, value in settings.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}."))  # an empty dict adds nothing: {} and absent agree
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _shorten(value, width: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= width else f"{text[: width - 3]}..."


def _importance(key: str) -> tuple[int, str]:
    top = key.split(".", 1)[0]
    return (IMPORTANT_SETTINGS.index(top) if top in IMPORTANT_SETTINGS else len(IMPORTANT_SETTINGS), key)


@dataclass
class RunRecord:
    """What produced a folder: ``command`` and ``settings`` must match to continue; ``code_version`` is logged;
    ``paths`` (where the inputs were read from) are recorded for people and never compared: inputs are identified by
    content fingerprints in ``settings``, so a moved or copied model is the same model."""

    command: str
    settings: dict
    code_version: str = ""
    paths: dict = field(default_factory=dict)

    def __post_init__(self):
        self.code_version = self.code_version or code_version()
        self.settings = json.loads(json.dumps(self.settings))  # JSON-normal form (tuples -> lists), as saved
        self.paths = json.loads(json.dumps(self.paths))

    def differences(self, other: RunRecord) -> list[str]:
        """The differences of ``other`` (this run) from ``self`` (the folder's record), most important first, each as
        ``name: <this run's value> here vs <the folder's> there`` (values shortened)."""
        if self.command != other.command:
            return [f"it was written by `hf-specvla {self.command}`, this is `hf-specvla {other.command}`"]
        saved, now = _flatten(self.settings), _flatten(other.settings)
        for key, implied in ADDED_SETTINGS.items():
            if key in now and key not in saved:
                saved[key] = now[key] if implied is NOT_COMPARED else implied
        keys = sorted((set(saved) | set(now)) - LEGACY_PATH_SETTINGS, key=_importance)
        missing = "(not set)"
        return [
            f"{key}: {_shorten(now.get(key, missing))} here vs {_shorten(saved.get(key, missing))} there"
            for key in keys
            if saved.get(key, missing) != now.get(key, missing)
        ]


def check_run_folder(folder: str | Path, record: RunRecord) -> bool:
    """The refusals of [`open_run_folder`] without writing anything: call it before a long preparation (data,
    models) so that a folder that would be refused is refused first.

    Returns:
        True when an existing run would be continued.
    """
    folder = Path(folder)
    run_file = folder / RUN_FILE
    if is_empty_folder(folder):
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
        shown = differences[:4] + ([f"and {len(differences) - 4} more"] if len(differences) > 4 else [])
        raise FileExistsError(f"{str(folder)!r} holds another run: {'; '.join(shown)}; {ways_out}")
    if saved.code_version != record.code_version:
        logger.warning(
            "%s was written by hf_specvla %s; continuing with %s", folder, saved.code_version, record.code_version
        )
    return True


def is_empty_folder(folder: str | Path) -> bool:
    """True for a missing folder, or one that holds nothing but its lock file."""
    folder = Path(folder)
    return not folder.exists() or all(entry.name == LOCK_FILE for entry in folder.iterdir())


class FolderInUseError(FileExistsError):
    """Another live run holds the folder's lock."""


def _describe_holder(text: str) -> str:
    try:
        holder = json.loads(text)
    except json.JSONDecodeError:
        holder = None
    if not isinstance(holder, dict):  # an older hf_specvla wrote the bare pid
        return f"pid {text.strip()}" if text.strip() else "an unknown process"
    return f"pid {holder.get('pid')}, `{holder.get('command')}`, started {holder.get('started')}"


class FolderLock:
    """The OS lock on ``<folder>/.lock`` (``fcntl.flock``: released when its process ends, however it ends).

    Args:
        dir_fd: an open descriptor of the folder (the lock follows the folder if it is renamed).
        folder: the folder's name, for messages.
    Raises:
        FolderInUseError: a live process holds it (named: pid, command, start time).
    """

    def __init__(self, dir_fd: int, folder: Path):
        self.folder = folder
        self.fd = os.open(LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644, dir_fd=dir_fd)
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _describe_holder(os.pread(self.fd, 4096, 0).decode(errors="replace"))
            os.close(self.fd)
            raise FolderInUseError(
                f"{str(folder)!r} is in use by another run ({holder}); wait for it to end, or choose another folder "
                f"(--overwrite-output-dir does not take a folder from a live run)"
            ) from None
        previous = os.pread(self.fd, 4096, 0).decode(errors="replace")
        if previous.strip():  # a holder that never released: its process died
            logger.warning(
                "%s: taking over the lock of a run that is no longer running (%s)", folder, _describe_holder(previous)
            )
        holder = {
            "pid": os.getpid(),
            "command": shlex.join([Path(sys.argv[0]).name, *sys.argv[1:]]),
            "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
        os.ftruncate(self.fd, 0)
        os.pwrite(self.fd, json.dumps(holder).encode(), 0)

    def release(self) -> None:
        """Empties the lock file (a clean end leaves no holder behind) and releases the lock."""
        if self.fd < 0:
            return
        os.ftruncate(self.fd, 0)
        fcntl.flock(self.fd, fcntl.LOCK_UN)
        os.close(self.fd)
        self.fd = -1


def _bound_path(dir_fd: int, folder: Path) -> Path:
    """A path that reaches the directory behind ``dir_fd`` even after it is renamed (Linux ``/proc``; elsewhere the
    folder's name)."""
    bound = Path(f"/proc/{os.getpid()}/fd/{dir_fd}")
    return bound if bound.is_dir() else folder


class RunFolder:
    """A run folder claimed by this process (see the module docstring); a context manager that releases it.

    Attributes:
        path: the folder's name as given (for messages).
        bound: the path to write through: it stays on the claimed directory if the folder is renamed or moved aside.
        continued: True when an existing run of the same settings is continued.
    """

    def __init__(self, path: Path, dir_fd: int, lock: FolderLock | None, continued: bool):
        self.path, self.dir_fd, self.lock, self.continued = path, dir_fd, lock, continued
        self.bound = _bound_path(dir_fd, path)

    def release(self) -> None:
        if self.lock is not None:
            self.lock.release()
        if self.dir_fd >= 0:
            os.close(self.dir_fd)
            self.dir_fd = -1

    def __enter__(self) -> RunFolder:
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def _lock_folder(folder: Path) -> tuple[int, FolderLock]:
    folder.mkdir(parents=True, exist_ok=True)
    dir_fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        return dir_fd, FolderLock(dir_fd, folder)
    except BaseException:
        os.close(dir_fd)
        raise


def lock_folder(folder: str | Path) -> RunFolder:
    """Locks ``folder`` (created if missing) for a writer whose folder has a record of its own kind (a dataset's
    ``meta/info.json``); hold it for the whole run and write through ``.bound``.

    Raises:
        FolderInUseError: another live run holds the folder.
    """
    folder = Path(folder)
    dir_fd, lock = _lock_folder(folder)
    return RunFolder(folder, dir_fd, lock, continued=not is_empty_folder(folder))


def follow_run_folder(folder: str | Path, continued: bool) -> RunFolder:
    """The folder another process of the same launched run claimed (its main process): a [`RunFolder`] without the
    lock, for a secondary process that writes only what the run's every process writes (accelerate's per-process
    state in checkpoints)."""
    folder = Path(folder)
    return RunFolder(folder, os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0)), None, continued)


def claim_run_folder(folder: str | Path, record: RunRecord, overwrite: bool = False) -> RunFolder:
    """Locks ``folder``, then applies the module's rule for a run described by ``record``; hold the returned
    [`RunFolder`] for the whole run (``with claim_run_folder(...) as run:``) and write through ``run.bound``.

    Raises:
        FolderInUseError: another live run holds the folder (``overwrite`` or not).
        FileExistsError: the folder holds another run's (or an unrecorded) results; the message names the
            differing setting and the two ways out.
    """
    folder = Path(folder)
    dir_fd, lock = _lock_folder(folder)
    try:
        if overwrite and not is_empty_folder(folder):
            aside = folder.with_name(f"{folder.name}.replaced-{time.strftime('%Y%m%dT%H%M%S', time.gmtime())}")
            os.replace(folder, aside)  # the old folder's lock moves with it, still held: nobody starts in it now
            logger.warning("moved the previous contents of %s aside to %s (--overwrite-output-dir)", folder, aside)
            old_fd, old_lock = dir_fd, lock
            try:
                dir_fd, lock = _lock_folder(folder)
            finally:
                old_lock.release()
                os.close(old_fd)
        run = RunFolder(folder, dir_fd, lock, continued=False)
        if check_run_folder(folder, record):
            run.continued = True
        else:
            write_json_atomic(run.bound / RUN_FILE, asdict(record))
        return run
    except BaseException:
        lock.release()
        os.close(dir_fd)
        raise


def open_run_folder(folder: str | Path, record: RunRecord, overwrite: bool = False) -> bool:
    """[`claim_run_folder`] for a caller that writes nothing more, or that holds no lock while it writes (kept for
    compatibility; commands use `claim_run_folder`).

    Returns:
        True when an existing run is continued, False when a new run starts (``run.json`` is then written).
    """
    with claim_run_folder(folder, record, overwrite) as run:
        return run.continued


def write_json_atomic(path: str | Path, data) -> None:
    """Writes JSON to ``path`` through a temporary file and a rename: a crash leaves the old file or the new one."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.tmp")
    temporary.write_text(json.dumps(data, indent=2))
    os.replace(temporary, path)


def read_jsonl(path: str | Path, shown_as: str | Path | None = None) -> list[dict]:
    """The records of an append-only JSON-lines log. A torn last line (a crash mid-write) is dropped from the file
    with a warning, so that its record is redone; a torn line elsewhere is an error naming the line.

    Args:
        shown_as: the path messages name (e.g. the run folder the user gave, when ``path`` goes through the claimed
            folder's ``/proc/<pid>/fd`` binding); default ``path``.
    """
    path = Path(path)
    shown = str(shown_as if shown_as is not None else path)
    if not path.exists():
        return []
    lines = path.read_text().splitlines()
    records = []
    for number, line in enumerate(lines, 1):
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            if number < len(lines):
                raise ValueError(f"{shown!r} line {number} is not valid JSON: the log is damaged") from None
            logger.warning("%s: dropping a torn last line (a crash mid-write); that record is redone", shown)
            path.write_text("".join(line + "\n" for line in lines[:-1]))
    return records


# ----------------------------------------------------------------------------- timing conditions
def _cpu_model() -> str:
    """The CPU's model name (Linux ``/proc/cpuinfo``; elsewhere ``platform.processor()``)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


@functools.cache
def machine_fingerprint() -> dict:
    """What a wall time depends on besides a run's settings: OS, architecture, CPU model, CPU count, torch version.
    The host name is left out on purpose: identical machines (or a restarted container) time alike."""
    return {
        "system": platform.system(),
        "arch": platform.machine(),
        "cpu": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
    }


def timing_conditions(workers: int, threads: int, torch_threads: int) -> dict:
    """The conditions a record's wall times were measured under (recorded with each timed record).

    Args:
        workers: processes the run is split between (they share the machine's cores).
        threads: the CPU threads each worker was asked for.
        torch_threads: the threads torch actually decodes with in the process that times (``torch.get_num_threads()``).
    """
    return {"workers": workers, "threads": threads, "torch_threads": torch_threads, "machine": machine_fingerprint()}


def describe_conditions(conditions: dict, machine: bool = True) -> str:
    """``workers=2, threads=1, torch_threads=1 on Linux x86_64, 'AMD EPYC' x 2 CPUs, torch 2.5.1`` (the keys a record
    holds; ``machine=False`` leaves the machine out)."""
    text = ", ".join(f"{key}={value}" for key, value in conditions.items() if key != "machine")
    box = conditions.get("machine")
    if machine and box:
        text += (
            f" on {box.get('system')} {box.get('arch')}, {box.get('cpu')!r} x {box.get('cpu_count')} CPUs, "
            f"torch {box.get('torch')}"
        )
    return text


class TimingConditionsError(FileExistsError):
    """A folder's records were timed under other conditions than this run's (see [`resolve_timing`])."""


@dataclass
class FolderTiming:
    """A folder's timing state, ``timing.json``.

    Attributes:
        conditions: the conditions the folder's speed figures are of (see [`timing_conditions`]).
        untimed_conditions: what records without conditions (written before they were recorded) are taken as timed
            under; None: they are left out of speed figures.
    """

    conditions: dict
    untimed_conditions: dict | None = None

    def timed(self, record: dict) -> bool:
        """Whether ``record``'s wall times enter speed figures: it was timed under the folder's conditions."""
        return record.get("timing", self.untimed_conditions) == self.conditions


def _condition_differences(recorded: dict, now: dict) -> list[str]:
    """``name: <now> here vs <recorded> there`` for every key ``recorded`` holds (a partial record compares only
    what it knows)."""
    saved, current = _flatten(recorded), _flatten(now)
    return [
        f"{key}: {_shorten(current.get(key, '(not set)'))} here vs {_shorten(value)} there"
        for key, value in saved.items()
        if current.get(key, "(not set)") != value
    ]


def _silent(*args, **kwargs) -> None:
    pass


def _read_timing(folder: Path) -> FolderTiming | None:
    path = folder / TIMING_FILE
    return FolderTiming(**json.loads(path.read_text())) if path.is_file() else None


def resolve_timing(
    folder: str | Path,
    conditions: dict,
    records: list[dict],
    restart: bool = False,
    untimed_hint: dict | None = None,
    restart_flag: str = "--restart-timing",
    announce: bool = True,
) -> FolderTiming:
    """The timing state a run under ``conditions`` continues ``folder`` with; writes nothing (see [`write_timing`]).

    Args:
        folder: the run folder (its ``timing.json`` is read when present).
        conditions: this run's [`timing_conditions`].
        records: the folder's records; those with a ``timing`` key say what they were timed under.
        restart: start timing afresh under ``conditions``: records timed otherwise stay, out of speed figures.
        untimed_hint: what the folder recorded elsewhere about the conditions of records without ``timing``, e.g.
            ``{"workers": 2, "threads": 1}`` from a summary (only its keys are compared).
        restart_flag: the option to name in the refusal.
        announce: log what is done with earlier records (False for a check ahead of the run, which logs it).
    Returns:
        The folder's timing state from now on: a new folder's, the saved one, or the restarted one. Records without
        conditions are taken as timed under ``conditions`` when nothing the folder holds says otherwise (a warning
        says so), and left out of speed figures on a restart.
    Raises:
        TimingConditionsError: the folder's records were timed under other conditions and ``restart`` is False; the
            message names both and the ways out.
    """
    folder = Path(folder)
    conditions = json.loads(json.dumps(conditions))  # JSON-normal form, as saved
    saved = _read_timing(folder)
    untimed = sum("timing" not in r for r in records)
    recorded: list[dict] = []  # the conditions this run must match to continue without a restart
    if saved is not None:
        recorded = [saved.conditions]
    else:  # no timing.json: what the records say (written by a run that recorded conditions) or the hint
        for record in records:
            if "timing" in record and record["timing"] not in recorded:
                recorded.append(record["timing"])
        if not recorded and untimed and untimed_hint:
            recorded = [untimed_hint]
    differences = [d for r in recorded if (d := _condition_differences(r, conditions))]
    if differences and not restart:
        there = "; ".join(describe_conditions(r) for r in recorded)
        same_machine = all(r.get("machine", conditions["machine"]) == conditions["machine"] for r in recorded)
        here = describe_conditions(conditions, machine=not same_machine) + (" (the same machine)" * same_machine)
        raise TimingConditionsError(
            f"{str(folder)!r} holds episodes timed under other conditions ({'; '.join(differences[0])}): recorded "
            f"{there}; this run {here}. Their speed figures would mix: rerun under the "
            f"recorded conditions, pass {restart_flag} to keep the finished episodes and time only the episodes run "
            f"from now on (the earlier timings stay in the folder, out of the speed figures), or choose another "
            f"output folder"
        )
    warn, inform = (logger.warning, logger.info) if announce else (_silent, _silent)
    if saved is not None and not differences:
        if restart:
            inform(
                "%s: the timing conditions are unchanged (%s): nothing to restart",
                folder,
                describe_conditions(conditions),
            )
        return saved
    if differences:  # restart: records timed otherwise keep their place, out of speed figures
        warn(
            "%s: timing restarted (%s): episodes timed under %s stay in the folder, out of the speed figures",
            folder,
            describe_conditions(conditions),
            "; ".join(describe_conditions(r) for r in recorded),
        )
        return FolderTiming(conditions, saved.untimed_conditions if saved else None)
    if untimed and not restart:
        warn(
            "%s: %d records were written before timing conditions were recorded; they are taken as timed "
            "under this run's (%s); if they were not, rerun with %s to time only new episodes",
            folder,
            untimed,
            describe_conditions(conditions),
            restart_flag,
        )
        return FolderTiming(conditions, conditions)
    if untimed:
        warn(
            "%s: %d records written before timing conditions were recorded are left out of the speed figures (%s)",
            folder,
            untimed,
            restart_flag,
        )
    return FolderTiming(conditions, None)


def write_timing(folder: str | Path, timing: FolderTiming) -> None:
    """Saves a folder's timing state (``timing.json``)."""
    write_json_atomic(Path(folder) / TIMING_FILE, asdict(timing))
