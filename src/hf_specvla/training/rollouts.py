"""On-policy rollouts of a [`VLAPolicy`] saved to a folder: what ``hf-specvla rollouts`` runs and what
``hf-specvla train-draft --rollouts`` trains a draft head on.

An episode is the policy's own greedy rollout from ``env.reset(seed)``, cut at ``max_steps`` policy calls, exactly as
``train-draft`` collects it in-process (``metaworld.evaluation.record_observations``: the same seeds, from
``DRAFT_SEED_START``, the same frames). Each episode is one file, ``episodes/<task>/<seed>.npz``, written through a
temporary file and a rename, so a killed run loses only the episodes in flight and ``resume`` skips the finished
ones. An episode's content depends only on (policy, task, seed, settings), never on the order, the worker or an
interruption: a collection in one go, in parts, or split between worker processes gives the same arrays.

The arrays of one episode of T frames (``H`` = the policy's chunk length, ``D`` = its action dimensions):

* ``image`` uint8 ``[T, S, S, 3]``, ``state`` float32 ``[T, state_dim]``: the observations the policy decided on;
* ``previous_action`` int64 ``[T, D]``: the token ids of the action executed before each frame (-1: none, at the
  first frame, or after an output that was not all action tokens);
* ``action_ids`` int64 ``[T, H * D]``: the policy's greedy action tokens for each frame (the labels);
* ``actions`` float64 ``[T, H, D]``: the un-normalised actions executed;
* ``task``, ``instruction`` (str), ``seed``, ``length`` (env steps), ``success`` (scalars).

Greedy tokens may come from the project's lossless speculative decoding (``method``, default ``exact``: the previous
action and Jacobi guesses verified at ``bin_tolerance=0``): the same tokens as plain greedy decoding, faster.

The folder follows the folder rule of [`hf_specvla.run_folder`]: ``run.json`` records the policy's weights
fingerprint, the env settings, the first seed, the step cut and the method; another policy or settings are refused,
naming what differs. More tasks or episodes continue a folder (``resume``). ``manifest.json`` lists every finished
episode with its content fingerprint, rewritten at the end of each run.

Seeds are taken seed by seed across the tasks (seed s of every task before seed s + 1), so that a collection cut
short holds the first seeds of every task: ``train-draft --rollouts`` can train on them while the rest runs.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .._validation import check_ranges
from ..metaworld.env import resolve_tasks
from ..metaworld.seeds import DRAFT_SEED_START

if TYPE_CHECKING:
    from ..metaworld.env import EnvConfig, MetaWorldEnv
    from ..policies import VLAPolicy
    from ..policies.decoding_methods import DecodingPlan

logger = logging.getLogger(__name__)

EPISODES_DIR = "episodes"
MANIFEST = "manifest.json"
#: the ``run.json`` command of a rollouts folder
COMMAND = "rollouts"
#: the scalar fields of an episode file (the rest are per-frame arrays)
SCALARS = ("task", "instruction", "seed", "length", "success")


# ----------------------------------------------------------------------------- settings
@dataclass
class RolloutConfig:
    """What ``hf-specvla rollouts`` collects.

    Args:
        tasks: Meta-World tasks (names or suites, e.g. "MT10"), resolved to task names.
        episodes_per_task: greedy episodes per task, seeds ``seed_start``, +1, ...
        seed_start: the first seed (the draft-training range, as ``train-draft``).
        max_steps: policy calls kept per episode (an episode is cut there; a chunked policy takes H env steps per
            call): ``train-draft``'s ``--rollout-max-steps``.
        method: how the greedy tokens are decoded: a lossless decoding method without a draft head (``greedy``,
            ``prior+jacobi``, ``exact``...; see ``policies.decoding_methods``); every one gives greedy's tokens.
        workers: processes the episodes are split between (1: this process).
        threads: torch CPU threads of each worker process.
        max_episodes: stop after this many new episodes (None: all); a collection in parts.
    """

    tasks: str | list[str] = "MT10"
    episodes_per_task: int = 100
    seed_start: int = DRAFT_SEED_START
    max_steps: int = 150
    method: str = "exact"
    workers: int = 1
    threads: int = 1
    max_episodes: int | None = None

    def __post_init__(self):
        self.tasks = resolve_tasks(self.tasks)
        check_ranges(
            self,
            at_least_one=("episodes_per_task", "max_steps", "workers", "threads"),
            non_negative=("seed_start",),
            integers=("episodes_per_task", "max_steps", "workers", "threads", "seed_start"),
        )
        if self.max_episodes is not None:
            check_ranges(self, at_least_one=("max_episodes",), integers=("max_episodes",))
        self.decoding_method()  # refuses a method that is unknown, relaxed or needs a head

    def decoding_method(self, action_dim: int | None = None):
        """The [`DecodingMethod`] ``method`` names (a preset resolved for ``action_dim``-dimensional actions).

        Raises:
            ValueError: an unknown method, a relaxed one (its tokens are not greedy's) or one that drafts with a head.
        """
        from ..policies.decoding_methods import DecodingMethod

        method = DecodingMethod.parse(self.method, draft_head_given=False, action_dim=action_dim)
        if not method.lossless or method.uses_draft_head:
            why = "relaxes acceptance (its tokens are not greedy's)" if not method.lossless else "needs a draft head"
            raise ValueError(
                f"RolloutConfig.method {self.method!r} {why}: the labels are the policy's greedy actions; "
                f"give a lossless method without a head: greedy, prior+jacobi, exact (the "
                f"fastest)"
            )
        return method

    def pairs(self) -> list[tuple[str, int]]:
        """Every (task, seed) of the collection, seed by seed across the tasks (see module docstring)."""
        return [(task, self.seed_start + i) for i in range(self.episodes_per_task) for task in self.tasks]


def env_config_for(policy_config) -> EnvConfig:
    """The env a policy's rollouts are rendered in: its image size and camera, Meta-World's step limit (as
    ``record_observations``)."""
    from ..metaworld.env import EnvConfig

    return EnvConfig(image_size=policy_config.image_size, camera=policy_config.camera)


def rollout_settings(policy: VLAPolicy, config: RolloutConfig) -> dict:
    """The settings a rollouts folder records and compares (``run.json``): what the episodes' content depends on."""
    method = config.decoding_method(policy.config.action_dim)
    return {
        "policy": policy.weights_fingerprint(),
        "env": asdict(env_config_for(policy.config)),
        "seed_start": config.seed_start,
        "max_steps": config.max_steps,
        "method": method.name,
    }


# ----------------------------------------------------------------------------- one episode
def episode_path(folder: str | Path, task: str, seed: int) -> Path:
    """``<folder>/episodes/<task>/<seed>.npz``."""
    return Path(folder) / EPISODES_DIR / task / f"{seed}.npz"


def collect_episode(
    policy: VLAPolicy,
    env: MetaWorldEnv,
    seed: int,
    max_steps: int,
    generate_kwargs: dict | None = None,
    decoding: DecodingPlan | None = None,
) -> dict[str, np.ndarray]:
    """One greedy episode from ``env.reset(seed)``, at most ``max_steps`` policy calls: the arrays of the module
    docstring (the frames ``record_observations`` records, plus the labels and the executed actions). ``decoding``
    (a lossless method's typed plan) and ``generate_kwargs`` go to every ``predict_action``."""
    from ..metaworld.rollout import rollout

    action_dim, tokens = policy.config.action_dim, policy.config.action_tokens
    frames: list[dict] = []
    policy.reset()

    def decide(rows: list[int], current: list[dict]) -> list:
        obs = current[0]
        previous = policy.previous_action_ids[-1] if policy.previous_action_ids else [-1] * action_dim
        action, output = policy.predict_action(
            obs["image"],
            obs["instruction"],
            obs["state"],
            return_output=True,
            decoding=decoding,
            **(generate_kwargs or {}),
        )
        sequences = output.sequences if hasattr(output, "sequences") else output
        frames.append(
            {
                "image": obs["image"],
                "state": obs["state"],
                "previous_action": previous,
                "action_ids": sequences[0, -tokens:].tolist(),
                "action": action,
            }
        )
        return [policy.action_steps(action)]

    (episode,) = rollout([env], [seed], decide, max_decisions=max_steps)
    chunk = policy.config.chunk_length
    return {
        "image": np.stack([f["image"] for f in frames]),  # [T, S, S, 3]
        "state": np.stack([np.asarray(f["state"], dtype=np.float32) for f in frames]),  # [T, state_dim]
        "previous_action": np.asarray([f["previous_action"] for f in frames], dtype=np.int64),  # [T, D]
        "action_ids": np.asarray([f["action_ids"] for f in frames], dtype=np.int64),  # [T, H * D]
        "actions": np.stack([np.asarray(f["action"], dtype=np.float64).reshape(chunk, -1) for f in frames]),
        "task": np.asarray(env.task),
        "instruction": np.asarray(env.instruction),
        "seed": np.asarray(seed, dtype=np.int64),
        "length": np.asarray(episode.length, dtype=np.int64),
        "success": np.asarray(episode.success),
    }


def save_episode(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Writes an episode's arrays to ``path`` (``.npz``, compressed) through a temporary file and a rename: the file
    is whole or absent."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with temporary.open("wb") as file:
        np.savez_compressed(file, **arrays)
        file.flush()
        os.fsync(file.fileno())
    os.replace(temporary, path)


def load_episode(path: str | Path) -> dict[str, np.ndarray]:
    """An episode file's arrays (see module docstring)."""
    with np.load(path, allow_pickle=False) as data:
        return {name: data[name] for name in data.files}


def episode_fingerprint(arrays: dict[str, np.ndarray]) -> str:
    """Content fingerprint (16 hex digits) of an episode's arrays, by name: equal arrays, equal fingerprints."""
    digest = hashlib.sha256()
    for name in sorted(arrays):
        array = np.ascontiguousarray(arrays[name])
        digest.update(f"{name}:{array.shape}:{array.dtype}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()[:16]


def episode_frames(arrays: dict[str, np.ndarray], max_steps: int | None = None) -> list[dict]:
    """An episode's first ``max_steps`` frames (all: None) as ``record_observations`` gives them: ``image``,
    ``instruction``, ``state`` and ``previous_action`` (token ids as a list, None where there was none)."""
    instruction = str(arrays["instruction"])
    count = len(arrays["image"]) if max_steps is None else min(max_steps, len(arrays["image"]))
    frames = []
    for t in range(count):
        previous = arrays["previous_action"][t]
        frames.append(
            {
                "image": arrays["image"][t],
                "instruction": instruction,
                "state": arrays["state"][t],
                "previous_action": None if previous[0] < 0 else previous.tolist(),
            }
        )
    return frames


# ----------------------------------------------------------------------------- collection
def _manifest_entry(arrays: dict[str, np.ndarray]) -> dict:
    return {
        "task": str(arrays["task"]),
        "seed": int(arrays["seed"]),
        "frames": len(arrays["image"]),
        "length": int(arrays["length"]),
        "success": bool(arrays["success"]),
        "fingerprint": episode_fingerprint(arrays),
    }


def rollouts_fingerprint(entries: list[dict]) -> str:
    """Fingerprint (16 hex digits) of a set of episodes: their (task, seed, content fingerprint), in any order (a
    ``train-draft --rollouts`` that reads every episode of a folder records its ``manifest.json`` fingerprint)."""
    text = json.dumps(sorted([e["task"], e["seed"], e["fingerprint"]] for e in entries))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def finished_pairs(folder: str | Path) -> set[tuple[str, int]]:
    """The (task, seed) of every finished episode in a rollouts folder."""
    root = Path(folder) / EPISODES_DIR
    if not root.is_dir():
        return set()
    return {(path.parent.name, int(path.stem)) for path in root.glob("*/*.npz") if path.stem.isdigit()}


def _remove_temporaries(folder: Path) -> None:
    """Deletes the temporary files of episodes a killed run had in flight (the folder is locked: none is live)."""
    for path in (folder / EPISODES_DIR).glob("*/.*.tmp"):
        logger.info("removing %s (an episode in flight when a run was stopped)", path.name)
        path.unlink()


class _EnvCache:
    """One env per task, built on first use (building one costs more than a reset) and closed at the end."""

    def __init__(self, env_config: EnvConfig):
        self.env_config, self.envs = env_config, {}

    def get(self, task: str) -> MetaWorldEnv:
        from ..metaworld.env import MetaWorldEnv

        if task not in self.envs:
            self.envs[task] = MetaWorldEnv(task, self.env_config)
        return self.envs[task]

    def close(self) -> None:
        for env in self.envs.values():
            env.close()
        self.envs = {}


def _collect_pairs(
    policy: VLAPolicy,
    config: RolloutConfig,
    pairs: list[tuple[str, int]],
    folder: Path,
    on_episode: Callable[[dict], None] | None = None,
) -> None:
    """Collects and saves each (task, seed) of ``pairs`` in order into ``folder``; ``on_episode(arrays)`` after each."""
    method = config.decoding_method(policy.config.action_dim)
    plan = method.plan(None, policy.model.device.type, action_dim=policy.config.action_dim)
    envs = _EnvCache(env_config_for(policy.config))
    try:
        for task, seed in pairs:
            arrays = collect_episode(policy, envs.get(task), seed, config.max_steps, decoding=plan)
            save_episode(episode_path(folder, task, seed), arrays)
            logger.debug("%s seed %d: %d frames, success %s", task, seed, len(arrays["image"]), bool(arrays["success"]))
            if on_episode is not None:
                on_episode(arrays)
    finally:
        envs.close()


def _worker_main(policy_dir: str, config: dict, pairs: list, folder: str) -> None:
    """Entry point of a worker process (spawned): its own torch threads and policy; saves its share of the episodes."""
    import torch
    from transformers.utils import logging as transformers_logging

    from ..metaworld.comparison.runner import _exit_with_parent
    from ..policies import VLAPolicy

    _exit_with_parent()  # an orphan would go on writing into a folder a new run may be resuming
    transformers_logging.disable_progress_bar()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(config["threads"])
    policy = VLAPolicy.from_pretrained(policy_dir)
    _collect_pairs(policy, RolloutConfig(**config), [tuple(p) for p in pairs], Path(folder))


def _collect_in_workers(policy_dir: str, config: RolloutConfig, pending: list, folder: Path, bar) -> None:
    """Splits ``pending`` between ``config.workers`` spawned processes (worker i takes every workers-th pair) and
    follows the saved files on ``bar``."""
    from concurrent.futures import FIRST_EXCEPTION, ProcessPoolExecutor, wait
    from multiprocessing import get_context

    shards = [pending[i :: config.workers] for i in range(config.workers)]
    start, shown = len(finished_pairs(folder)), 0
    with ProcessPoolExecutor(config.workers, mp_context=get_context("spawn")) as pool:
        running = {
            pool.submit(_worker_main, policy_dir, asdict(config), shard, str(folder)) for shard in shards if shard
        }
        while running:
            finished, running = wait(running, timeout=5, return_when=FIRST_EXCEPTION)
            for future in finished:
                future.result()  # a worker's exception surfaces here
            saved = len(finished_pairs(folder)) - start
            bar.update(saved - shown)
            shown = saved


def collect_rollouts(
    policy: VLAPolicy,
    config: RolloutConfig,
    output_dir: str | Path,
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = True,
) -> dict:
    """Collects ``config``'s greedy episodes of ``policy`` into ``output_dir`` (see module docstring); resumable.

    ``workers`` > 1 spawns processes that load the policy from ``policy.name_or_path``.

    Returns:
        The manifest (``manifest.json``): ``episodes`` (one entry per finished episode in the folder: task, seed,
        frames, length, success, fingerprint), ``fingerprint`` (of them all), ``complete`` (every episode of
        ``config`` is in the folder), ``new_episodes`` (collected by this call), ``seconds``.

    Raises:
        FileExistsError: a non-empty folder without ``resume`` / ``overwrite``, or one that holds another collection
            (naming the first differing setting), or one another live run holds.
        FileNotFoundError: ``resume`` of a folder that holds nothing.
        ValueError: ``workers`` > 1 for a policy not loaded from a folder.
    """
    from ..progress import progress_bar
    from ..run_folder import RunRecord, claim_run_folder

    output_dir = Path(output_dir)
    if config.workers > 1 and policy.name_or_path is None:
        raise ValueError(
            "RolloutConfig.workers > 1 loads the policy in each worker: load it with "
            "VLAPolicy.from_pretrained(folder), or use workers=1"
        )
    record = RunRecord(COMMAND, rollout_settings(policy, config), paths={"policy": policy.name_or_path})
    check_rollouts_folder(output_dir, record, resume, overwrite)
    started = time.perf_counter()
    with claim_run_folder(output_dir, record, overwrite) as run:
        if run.continued:  # again under the lock: the folder may have changed since the first look
            check_rollouts_folder(output_dir, record, resume, overwrite=False)
        folder = run.bound  # writes stay in the claimed folder, renamed or not
        _remove_temporaries(folder)
        done = finished_pairs(folder)
        wanted = config.pairs()
        missing = [pair for pair in wanted if pair not in done]
        pending = missing[: config.max_episodes]  # (None: all)
        finished = len(wanted) - len(missing)
        logger.info(
            "%d of %d episodes already in %s; collecting %d with %d worker(s), method %s",
            finished,
            len(wanted),
            output_dir,
            len(pending),
            config.workers,
            config.decoding_method(policy.config.action_dim).name,
        )
        bar = progress_bar(total=len(wanted), initial=finished, desc="rollouts", unit="episode", disable=not progress)
        successes, frames = [], []

        def on_episode(arrays: dict) -> None:
            successes.append(bool(arrays["success"]))
            frames.append(len(arrays["image"]))
            bar.update(1)
            bar.set_postfix(
                task=str(arrays["task"]), success=f"{np.mean(successes):.0%}", frames=f"{np.mean(frames):.0f}"
            )

        if config.workers == 1 or len(pending) <= 1:
            _collect_pairs(policy, config, pending, folder, on_episode)
        else:
            _collect_in_workers(policy.name_or_path, config, pending, folder, bar)
        bar.close()
        manifest = write_manifest(folder, set(wanted))
        manifest["new_episodes"], manifest["seconds"] = len(pending), time.perf_counter() - started
    rate = 60 * len(pending) / max(manifest["seconds"], 1e-9)
    logger.info(
        "%d new episodes in %.0f s (%.2f per minute); %d in %s, complete: %s",
        len(pending),
        manifest["seconds"],
        rate,
        len(manifest["episodes"]),
        output_dir,
        manifest["complete"],
    )
    return manifest


def check_rollouts_folder(output_dir: str | Path, record, resume: bool, overwrite: bool) -> None:
    """The refusals of [`collect_rollouts`] without writing anything (call it before a slow load); ``record`` None
    checks all but the comparison with the folder's ``run.json`` (``training.checkpoints.check_output_dir``'s rule).

    Raises:
        FileNotFoundError: ``resume`` of a missing or empty folder.
        FileExistsError: a non-empty folder without ``run.json`` (another tool's files), one that holds another run
            (naming the first differing setting), or one that holds this collection without ``resume``.
    """
    from .checkpoints import check_output_dir

    check_output_dir(Path(output_dir), record, resume, overwrite, kind="rollouts collection")


def write_manifest(folder: Path, wanted: set[tuple[str, int]]) -> dict:
    """``manifest.json``: every finished episode in ``folder`` (task, seed, frames, length, success, fingerprint),
    by task then seed, the set's fingerprint, and whether every episode of ``wanted`` is there."""
    from ..run_folder import write_json_atomic

    done = finished_pairs(folder)
    entries = [_manifest_entry(load_episode(episode_path(folder, task, seed))) for task, seed in sorted(done)]
    manifest = {"episodes": entries, "fingerprint": rollouts_fingerprint(entries), "complete": wanted <= done}
    write_json_atomic(folder / MANIFEST, manifest)
    return manifest


# ----------------------------------------------------------------------------- reading, for train-draft
def read_rollouts_record(folder: str | Path) -> dict:
    """The ``run.json`` settings of a rollouts folder (policy fingerprint, env, seed_start, max_steps, method).

    Raises:
        FileNotFoundError: no such folder, or one without the ``run.json`` of ``hf-specvla rollouts``.
    """
    from ..run_folder import RUN_FILE

    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"rollouts folder {str(folder)!r} does not exist; collect one with hf-specvla rollouts")
    run_file = folder / RUN_FILE
    record = json.loads(run_file.read_text()) if run_file.is_file() else {}
    if record.get("command") != COMMAND:
        raise FileNotFoundError(
            f"{str(folder)!r} is not a rollouts folder (no {RUN_FILE} of hf-specvla rollouts); "
            f"collect one with hf-specvla rollouts --policy ... --output-dir {folder}"
        )
    return record["settings"]


def finished_episodes_per_task(folder: str | Path, tasks: list[str], seed_start: int) -> int:
    """How many seeds from ``seed_start`` on, without a gap, every task of ``tasks`` has finished in ``folder``."""
    done = finished_pairs(folder)
    count = 0
    while all((task, seed_start + count) in done for task in tasks):
        count += 1
    return count


class EpisodeFrames(Sequence):
    """The frames of episode files, read one episode at a time: a frame's image is read when the frame is asked for,
    so that ``train-draft --rollouts`` never holds every image of a large folder (~49 KB a frame at 128 x 128).

    A sequence of observation dicts as [`episode_frames`] gives them (each a view into its episode's arrays); the
    episode last read is kept, so reading the frames in order reads each file once. ``instructions`` gives every
    frame's instruction without reading a file.

    Args:
        episodes: ``(path, frames, instruction)`` of each episode, in order: its file, how many of its first frames
            count, and its instruction.
    """

    def __init__(self, episodes: list[tuple[Path, int, str]]):
        self.episodes = list(episodes)
        self.starts = np.cumsum([0] + [count for _, count, _ in self.episodes])  # [E + 1] each episode's first frame
        self.instructions = [instruction for _, count, instruction in self.episodes for _ in range(count)]
        self._read: tuple[int, list[dict]] = (-1, [])  # (episode, its frames): the episode last read

    def __len__(self) -> int:
        return int(self.starts[-1])

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        index = index + len(self) if index < 0 else index
        if not 0 <= index < len(self):
            raise IndexError(f"frame {index} of {len(self)}")
        episode = int(np.searchsorted(self.starts, index, side="right")) - 1
        if self._read[0] != episode:
            path, count, _ = self.episodes[episode]
            self._read = (episode, episode_frames(load_episode(path), count))
        return self._read[1][index - int(self.starts[episode])]


@dataclass
class RolloutFrames:
    """What ``train-draft --rollouts`` trains on: the frames of a rollouts folder (observation dicts as
    ``record_observations`` gives them), split as the in-process collection splits them.

    Attributes:
        train / validation: [`EpisodeFrames`] of the first ``rollout_episodes - validation_episodes`` seeds of each
            task / of the last ``validation_episodes`` (task by task, seed by seed, frame by frame), read lazily.
        fingerprint: [`rollouts_fingerprint`] of the episodes used (the same episodes, the same fingerprint, whatever
            else the folder holds).
        episodes: how many episodes were read.
    """

    train: EpisodeFrames
    validation: EpisodeFrames
    fingerprint: str
    episodes: int


def check_rollouts_for(folder: str | Path, policy: VLAPolicy, data_config) -> None:
    """Refuses a rollouts folder that cannot give the frames ``data_config`` asks of ``policy`` (reads no episode).

    Raises:
        FileNotFoundError: not a rollouts folder.
        ValueError: a folder of another policy (weights fingerprint) or env, another first seed, shorter episodes than
            asked for, or too few finished episodes (naming how many there are and how to collect the rest).
    """
    folder = Path(folder)
    settings = read_rollouts_record(folder)
    if settings["policy"] != policy.weights_fingerprint():
        raise ValueError(
            f"rollouts folder {str(folder)!r} holds rollouts of another policy (weights fingerprint "
            f"{settings['policy']}; {policy.name_or_path or 'this policy'} is "
            f"{policy.weights_fingerprint()}); collect this policy's with hf-specvla rollouts --policy "
            f"{policy.name_or_path or '<folder>'}"
        )
    env = asdict(env_config_for(policy.config))
    if settings["env"] != env:
        raise ValueError(f"rollouts folder {str(folder)!r} was rendered with {settings['env']}, the policy sees {env}")
    if settings["seed_start"] != data_config.rollout_seed_start:
        raise ValueError(
            f"rollouts folder {str(folder)!r} starts at seed {settings['seed_start']}, "
            f"rollout_seed_start is {data_config.rollout_seed_start}: give --rollout-seed-start "
            f"{settings['seed_start']}"
        )
    if data_config.rollout_max_steps > settings["max_steps"]:
        raise ValueError(
            f"rollouts folder {str(folder)!r} cut its episodes at {settings['max_steps']} policy calls, "
            f"rollout_max_steps is {data_config.rollout_max_steps}: give --rollout-max-steps <= "
            f"{settings['max_steps']}"
        )
    available = finished_episodes_per_task(folder, data_config.tasks, settings["seed_start"])
    if available < data_config.rollout_episodes:
        raise ValueError(
            f"rollouts folder {str(folder)!r} holds {available} finished episodes of every task of "
            f"{data_config.tasks} (seeds from {settings['seed_start']}), rollout_episodes asks for "
            f"{data_config.rollout_episodes}: give --rollout-episodes <= {available}, or collect more with hf-specvla "
            f"rollouts --policy {policy.name_or_path or '<folder>'} --output-dir {folder} --episodes-per-task "
            f"{data_config.rollout_episodes} --resume (and the folder's other settings)"
        )


def read_rollout_frames(folder: str | Path, policy: VLAPolicy, data_config) -> RolloutFrames:
    """The frames ``data_config`` (a ``DraftDataConfig``: tasks, ``rollout_episodes`` per task from
    ``rollout_seed_start``, cut at ``rollout_max_steps``, the last ``validation_episodes`` held out) asks for, read from
    a rollouts folder of ``policy``: the frames the in-process collection (``policy_draft.rollout_frames``) gives.

    Raises:
        FileNotFoundError / ValueError: as [`check_rollouts_for`].
    """
    folder = Path(folder)
    check_rollouts_for(folder, policy, data_config)
    seeds = [data_config.rollout_seed_start + i for i in range(data_config.rollout_episodes)]
    held_out = set(seeds[-data_config.validation_episodes :])
    train, validation, entries = [], [], []
    for task in data_config.tasks:
        for seed in seeds:
            path = episode_path(folder, task, seed)
            arrays = load_episode(path)  # read once here for its fingerprint; its frames are read again when used
            entries.append(_manifest_entry(arrays))
            count = min(data_config.rollout_max_steps, len(arrays["image"]))
            (validation if seed in held_out else train).append((path, count, str(arrays["instruction"])))
    return RolloutFrames(EpisodeFrames(train), EpisodeFrames(validation), rollouts_fingerprint(entries), len(entries))
