"""Scripted-expert demonstrations on Meta-World, stored as plain Parquet files.

Layout of a dataset folder (readable with pandas / pyarrow / polars; images are PNG bytes):

    meta/info.json          format, version, image size, camera, action/state dims, the column schema
    meta/stats.json         q01 / q99 (and the normalisation mask) of actions and states, over all episodes
    data/<task>/episode_<seed>.parquet   one episode, one row per step

Columns: ``episode_index`` int64 (``task_index * 1_000_000 + seed``), ``step_index`` int32, ``task`` str,
``instruction`` str, ``seed`` int64, ``image`` binary (PNG, uint8 [S, S, 3], upright), ``state`` list<float32>[4]
(hand xyz, gripper), ``action`` list<float32>[4] (the expert's action clipped to [-1, 1]), ``success`` bool (the
task is solved after this step), ``scene_state`` list<float32>[6] (object xyz and goal xyz from the simulator:
privileged, never given to a policy, used as an auxiliary training target; absent from datasets collected before
it existed).

Only successful episodes are kept, except in a *policy-driven* (DAgger) collection: there a trained policy
drives (``collect --policy``), the expert only labels the states it reaches, and every episode is kept, failed
ones included (they hold the states the policy needs to learn to leave; ``success`` tells them apart).

Each episode file is written to a temporary name and renamed, so an interrupted collection leaves whole episodes
only; running the same command again skips the seeds already on disk and collects the rest (no duplicates,
nothing lost).
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..actions.tokenizer import ActionNormalizer
from ..progress import progress_bar
from ..run_folder import LOCK_FILE, RUN_FILE, fingerprint, is_empty_folder, lock_folder, write_json_atomic
from .env import (
    ACTION_DIM,
    MAX_EPISODE_STEPS,
    SCENE_STATE_DIM,
    STATE_DIM,
    TASK_INSTRUCTIONS,
    EnvConfig,
    MetaWorldEnv,
    resolve_tasks,
)
from .rollout import rollout

logger = logging.getLogger(__name__)

FORMAT_NAME = "hf_specvla-demonstrations"
FORMAT_VERSION = 1
#: Normalisation mask of the 4-dim action: xyz are scaled by q01/q99, the gripper (+-1) passes through.
ACTION_NORM_MASK = (True, True, True, False)
TASK_INDEX = {task: i for i, task in enumerate(TASK_INSTRUCTIONS)}


def _png(image: np.ndarray) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="PNG")
    return buffer.getvalue()


def decode_png(data: bytes) -> np.ndarray:
    """PNG bytes -> uint8 ``[S, S, 3]``."""
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


def episode_path(root: Path, task: str, seed: int) -> Path:
    return root / "data" / task / f"episode_{seed:06d}.parquet"


def _write_episode(path: Path, rows: dict[str, list]) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pa.table(
        {
            "episode_index": pa.array(rows["episode_index"], pa.int64()),
            "step_index": pa.array(rows["step_index"], pa.int32()),
            "task": pa.array(rows["task"], pa.string()),
            "instruction": pa.array(rows["instruction"], pa.string()),
            "seed": pa.array(rows["seed"], pa.int64()),
            "image": pa.array(rows["image"], pa.binary()),
            "state": pa.array(rows["state"], pa.list_(pa.float32(), STATE_DIM)),
            "action": pa.array(rows["action"], pa.list_(pa.float32(), ACTION_DIM)),
            "success": pa.array(rows["success"], pa.bool_()),
            "scene_state": pa.array(rows["scene_state"], pa.list_(pa.float32(), SCENE_STATE_DIM)),
        }
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".parquet.tmp")
    pq.write_table(table, tmp)
    os.replace(tmp, path)  # atomic: a crash leaves either no episode or a whole one


def check_action_noise(action_noise: float) -> None:
    """Raises ValueError naming ``action_noise`` unless it is in [0, 1] (NaN included)."""
    if not 0.0 <= action_noise <= 1.0:
        raise ValueError(f"action_noise must be in [0, 1] (a standard deviation in action units), got {action_noise}")


def check_expert_mix(expert_mix: float) -> None:
    """Raises ValueError naming ``expert_mix`` unless it is a probability in [0, 1] (NaN included)."""
    if not 0.0 <= expert_mix <= 1.0:
        raise ValueError(
            f"expert_mix must be in [0, 1] (the probability that a step runs the expert), got {expert_mix}"
        )


def record_episode(
    env: MetaWorldEnv, seed: int, action_noise: float = 0.0, policy=None, expert_mix: float = 0.0
) -> dict[str, list] | None:
    """Runs one episode from ``reset(seed)`` and returns its rows; the action of every row is the scripted
    expert's action in that row's state.

    Without ``policy`` the expert drives and a failed episode gives None. With ``action_noise > 0`` the env
    executes the expert's action plus Gaussian noise of that standard deviation (clipped to [-1, 1]) while the
    rows record the expert's clean action: the demonstrations then visit states a little off the expert's path
    and show how the expert recovers from them (DART, Laskey et al. 2017).

    With ``policy`` (a [`VLAPolicy`], greedy) the policy drives instead, except that each step runs the expert's
    action with probability ``expert_mix``; the expert still labels every state (DAgger, Ross et al. 2011: the
    labels cover the states the policy itself reaches, its mistakes included). The episode is returned whether
    or not it succeeded. The noise and the mixing are drawn from ``seed``, so an episode is reproducible.
    """
    check_action_noise(action_noise)
    check_expert_mix(expert_mix)
    rng = np.random.default_rng(seed)
    if policy is not None:
        policy.reset()
    rows: dict[str, list] = {k: [] for k in ("image", "state", "action", "success", "scene_state")}

    def decide(running: list[int], observations: list[dict]) -> list:
        obs = observations[0]
        action = env.expert_action()
        rows["image"].append(_png(obs["image"]))
        rows["state"].append(obs["state"].tolist())
        rows["scene_state"].append(env.scene_state().tolist())
        rows["action"].append(action.tolist())
        executed = action
        if policy is not None and rng.random() >= expert_mix:
            executed = policy.action_steps(policy.predict_action(obs["image"], obs["instruction"], obs["state"]))[0]
        if action_noise > 0:
            noise = rng.normal(0.0, action_noise, size=action.shape)
            executed = np.clip(executed + noise, -1.0, 1.0).astype(np.float32)
        return [[executed]]  # one step per decision: the expert labels every state

    def on_step(b: int, observation: dict, info: dict) -> None:
        rows["success"].append(info["success"])

    episode = rollout([env], [seed], decide, on_step)[0]
    if not episode.success and policy is None:
        return None
    n = len(rows["image"])
    rows.update(
        episode_index=[TASK_INDEX[env.task] * 1_000_000 + seed] * n,
        step_index=list(range(n)),
        task=[env.task] * n,
        instruction=[env.instruction] * n,
        seed=[seed] * n,
    )
    return rows


#: info.json keys added after format version 1 was first written, with the value that older datasets had.
_INFO_DEFAULTS = {
    "action_noise": 0.0,
    "hand_start_noise": 0.0,
    "max_episode_steps": MAX_EPISODE_STEPS,
    "policy": None,
    "expert_mix": None,
    "policy_weights": None,
    "render_revision": 1,  # datasets collected before the reset frame showed the goal marker at the goal
}


def _check_info(
    root: Path,
    env_config: EnvConfig,
    action_noise: float,
    driver: dict,
    write: bool = True,
    shown_as: Path | None = None,
) -> None:
    """Refuses a folder holding a dataset collected with other settings; ``write``: record ours in a new one;
    ``shown_as``: the folder's name in messages (``root`` may be a held folder's bound ``/proc`` path)."""
    info_path = root / "meta" / "info.json"
    info = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "image_size": env_config.image_size,
        "camera": env_config.camera,
        "action_dim": ACTION_DIM,
        "state_dim": STATE_DIM,
        "action_noise": action_noise,
        "hand_start_noise": env_config.hand_start_noise,
        "max_episode_steps": env_config.max_episode_steps,
        "render_revision": env_config.render_revision,
        **driver,
        "columns": [
            "episode_index",
            "step_index",
            "task",
            "instruction",
            "seed",
            "image",
            "state",
            "action",
            "success",
            "scene_state",
        ],
    }
    if info_path.exists():
        existing = json.loads(info_path.read_text())
        for key, default in _INFO_DEFAULTS.items():
            existing.setdefault(key, default)  # datasets written before the option existed
        # a driving policy is identified by its weights (a moved folder is the same policy); by its path only in
        # datasets written before the fingerprint was recorded
        identity = "policy_weights" if existing.get("policy_weights") is not None else "policy"
        compared = [identity] + [k for k in _INFO_DEFAULTS if k not in ("policy", "policy_weights")]
        for key in ("format", "image_size", "camera", "action_dim", *compared):
            if existing.get(key) != info[key]:
                raise ValueError(
                    f"{shown_as or root} holds a dataset with {key}={existing.get(key)!r}, but this collection uses "
                    f"{info[key]!r}; collect into another folder or use the same settings"
                )
        return
    _check_unrecorded(root, shown_as or root)
    if write:
        info_path.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(info_path, info)


def _check_unrecorded(root: Path, shown_as: Path) -> None:
    """Refuses a folder without a dataset record (``meta/info.json``) that holds anything but its lock: another
    command's run (its ``run.json``) or files of unknown origin, which a collection would mix with its own."""
    if is_empty_folder(root):
        return
    run_file = root / RUN_FILE
    if run_file.is_file():
        try:
            command = json.loads(run_file.read_text()).get("command")
        except (ValueError, AttributeError):
            command = None
        made_by = f"`hf-specvla {command}`" if isinstance(command, str) else "another command"
        raise ValueError(
            f"{shown_as} holds a run of {made_by} ({RUN_FILE}), not a dataset; collect into another folder"
        )
    shown = ", ".join(sorted(entry.name for entry in root.iterdir() if entry.name != LOCK_FILE)[:5])
    raise ValueError(
        f"{shown_as} is not empty ({shown}) and holds no dataset record (meta/info.json): it cannot be "
        "told what it holds; collect into an empty or new folder"
    )


def collected_seeds(root: Path, task: str) -> list[int]:
    """Seeds of the complete episodes of ``task`` on disk."""
    folder = root / "data" / task
    if not folder.is_dir():
        return []
    return sorted(int(p.stem.split("_")[1]) for p in folder.glob("episode_*.parquet"))


@dataclass
class CollectSummary:
    episodes_written: int
    episodes_present: int
    expert_failures: int
    #: policy-driven collections: how many of the episodes written this run the policy (with the mixed-in
    #: expert steps) solved
    driven_successes: int = 0


def check_dataset_folder(
    output_dir: str | Path, env_config: EnvConfig, action_noise: float = 0.0, policy=None, expert_mix: float = 0.0
) -> dict:
    """Refuses, before anything is written, settings out of range and a folder holding a dataset collected with
    other settings (see [`collect_demonstrations`]); returns what ``meta/info.json`` records of the driving policy.

    Raises:
        ValueError: naming the bad value, or the folder and the setting that differs.
    """
    check_action_noise(action_noise)
    check_expert_mix(expert_mix)
    driver = {"policy": None, "expert_mix": None, "policy_weights": None}
    if policy is not None:
        env_config.check_renders_for(policy.config)
        driver = {
            "policy": policy.name_or_path or "in-memory",
            "expert_mix": float(expert_mix),
            "policy_weights": fingerprint(policy.model),
        }
    _check_info(Path(output_dir), env_config, float(action_noise), driver, write=False)
    return driver


def collect_demonstrations(
    output_dir: str | Path,
    tasks: str | list[str],
    episodes_per_task: int,
    env_config: EnvConfig | None = None,
    seed_start: int = 0,
    max_seed_tries: int = 3,
    progress: bool = True,
    action_noise: float = 0.0,
    policy=None,
    expert_mix: float = 0.0,
) -> CollectSummary:
    """Collects ``episodes_per_task`` successful expert episodes per task (resumable; see module docstring).

    Seeds ``seed_start, seed_start + 1, ...`` are tried in order; a seed whose expert episode fails is skipped
    (at most ``max_seed_tries * episodes_per_task`` seeds per task). ``action_noise``: see `record_episode`.

    With ``policy`` (a [`VLAPolicy`]) the collection is policy-driven (DAgger; see `record_episode`): the policy
    acts, a step runs the expert's action with probability ``expert_mix``, the expert labels every state, and the
    seeds ``seed_start .. seed_start + episodes_per_task - 1`` each give one episode, failed or not. The policy's
    folder, ``expert_mix``, ``action_noise`` and the env settings are recorded in ``meta/info.json``; a dataset
    is only ever extended with the same values.
    """
    if episodes_per_task < 1:
        raise ValueError(f"episodes_per_task must be >= 1, got {episodes_per_task}")
    if seed_start < 0 or max_seed_tries < 1:  # checked before anything is written (a seed is a uint32)
        raise ValueError(f"seed_start must be >= 0 and max_seed_tries >= 1, got {seed_start} and {max_seed_tries}")
    root = Path(output_dir)
    env_config = env_config or EnvConfig()
    tasks = resolve_tasks(tasks)
    driver = check_dataset_folder(root, env_config, action_noise, policy, expert_mix)  # refusals first
    with lock_folder(root) as held:
        # under the lock: writes meta/info.json
        _check_info(held.bound, env_config, float(action_noise), driver, shown_as=root)
        return _collect_into(
            held.bound,
            tasks,
            episodes_per_task,
            env_config,
            seed_start,
            max_seed_tries,
            progress,
            action_noise,
            policy,
            expert_mix,
        )


def _collect_into(
    root: Path,
    tasks: list[str],
    episodes_per_task: int,
    env_config: EnvConfig,
    seed_start: int,
    max_seed_tries: int,
    progress: bool,
    action_noise: float,
    policy,
    expert_mix: float,
) -> CollectSummary:
    """[`collect_demonstrations`]'s work, in a folder this process holds."""
    if policy is not None:
        max_seed_tries = 1  # every seed gives an episode
    written = failures = driven_successes = 0
    total = len(tasks) * episodes_per_task
    done = {task: collected_seeds(root, task) for task in tasks}
    bar = progress_bar(
        total=total,
        initial=sum(min(len(s), episodes_per_task) for s in done.values()),
        desc="collect",
        unit="episode",
        disable=not progress,
    )
    for task in tasks:
        have = set(done[task])
        if len(have) >= episodes_per_task:
            continue
        with MetaWorldEnv(task, env_config) as env:
            for seed in range(seed_start, seed_start + max_seed_tries * episodes_per_task):
                if len(have) >= episodes_per_task:
                    break
                if seed in have:
                    continue
                rows = record_episode(env, seed, action_noise, policy, expert_mix)
                if rows is None:
                    failures += 1
                    logger.info("expert failed on %s seed %d; skipped", task, seed)
                    continue
                _write_episode(episode_path(root, task, seed), rows)
                have.add(seed)
                written += 1
                driven_successes += policy is not None and rows["success"][-1]
                bar.update(1)
        if len(have) < episodes_per_task:
            logger.warning("%s: only %d successful episodes within the seed budget", task, len(have))
    bar.close()
    write_stats(root)
    present = sum(len(collected_seeds(root, t)) for t in tasks)
    return CollectSummary(written, present, failures, driven_successes)


# ----------------------------------------------------------------------------- reading
class EncodedFrames:
    """Camera frames kept PNG-encoded in memory and decoded when indexed, an array-like of uint8 ``[N, S, S, 3]``:
    ``frames[i]`` is ``[S, S, 3]``; a slice, list or index array gives ``[K, S, S, 3]``; ``np.asarray(frames)``
    decodes them all.

    A dataset at 128 px decodes to 48 KB a frame (2000 expert episodes and some snippets of 12 steps: 11 GB, 22 GB
    at the peak of stacking them); PNG-encoded it holds a fifth of that, and decoding the frames of a training batch
    costs milliseconds against seconds for the step.
    """

    def __init__(self, encoded: list[bytes]):
        if not encoded:
            raise ValueError("EncodedFrames needs at least one frame")
        self._encoded = encoded
        first = decode_png(encoded[0])
        self.shape = (len(encoded), *first.shape)
        self.dtype = first.dtype

    def __len__(self) -> int:
        return len(self._encoded)

    def __getitem__(self, index) -> np.ndarray:
        if isinstance(index, (int, np.integer)):
            return decode_png(self._encoded[index])
        positions = range(len(self))[index] if isinstance(index, slice) else np.asarray(index).reshape(-1)
        frames = [decode_png(self._encoded[int(i)]) for i in positions]
        return np.stack(frames) if frames else np.zeros((0, *self.shape[1:]), self.dtype)

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        frames = self[:]
        return frames if dtype is None else frames.astype(dtype)

    @property
    def nbytes(self) -> int:
        """Bytes held (encoded), not the decoded size."""
        return sum(len(b) for b in self._encoded)


@dataclass
class Demonstrations:
    """A dataset in memory. ``images`` uint8 ``[N, S, S, 3]`` (PNG-encoded until indexed: [`EncodedFrames`]),
    ``states`` / ``actions`` float32 ``[N, 4]``, ``tasks`` list of N task names, ``episode_index`` int64 ``[N]``,
    ``scene_states`` float32 ``[N, 6]`` (None when some episode was collected without them)."""

    images: EncodedFrames
    states: np.ndarray
    actions: np.ndarray
    tasks: list[str]
    episode_index: np.ndarray
    scene_states: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.actions)


#: Episode ids of the i-th of several loaded folders are offset by ``i * DATASET_EPISODE_OFFSET`` (unique).
DATASET_EPISODE_OFFSET = 100_000_000


def _episode_files(root: Path) -> list[Path]:
    return sorted((root / "data").glob("*/episode_*.parquet"))


def _as_roots(roots: str | Path | list[str | Path] | tuple[str | Path, ...]) -> list[Path]:
    roots = [Path(r) for r in ([roots] if isinstance(roots, (str, Path)) else roots)]
    if not roots:
        raise ValueError("no demonstrations folder given")
    for root in roots:
        if not (root / "meta" / "info.json").exists():
            raise FileNotFoundError(
                f"{root} is not a demonstrations folder (no meta/info.json); run hf-specvla collect"
            )
    return roots


def dataset_fingerprint(root: str | Path) -> str:
    """Content identity of a dataset folder (16 hex digits): its recorded settings and the name and size of every
    episode file, never its path (a copied dataset is the same dataset)."""
    root = _as_roots(root)[0]
    info = json.loads((root / "meta" / "info.json").read_text())
    info.pop("policy", None)  # a path; the driving policy is identified by policy_weights
    digest = hashlib.sha256(json.dumps(info, sort_keys=True).encode())
    for file in _episode_files(root):
        digest.update(f"{file.relative_to(root).as_posix()}:{file.stat().st_size}\n".encode())
    return digest.hexdigest()[:16]


def dataset_info(roots: str | Path | list[str | Path]) -> dict:
    """``meta/info.json`` of a dataset folder; of several, the first one's after checking that they agree on
    image size, camera and action / state dimensions (they may differ in ``action_noise``)."""
    roots = _as_roots(roots)
    infos = [json.loads((root / "meta" / "info.json").read_text()) for root in roots]
    for root, info in zip(roots[1:], infos[1:]):
        for key in ("format", "image_size", "camera", "action_dim", "state_dim"):
            if info.get(key) != infos[0].get(key):
                raise ValueError(
                    f"{root} has {key}={info.get(key)!r} but {roots[0]} has {infos[0].get(key)!r}; "
                    "only datasets collected with the same settings can be combined"
                )
    return infos[0]


def load_demonstrations(
    roots: str | Path | list[str | Path], tasks: str | list[str] | None = None, progress: bool = True
) -> Demonstrations:
    """Reads every episode (of ``tasks``, default all) of one dataset folder or of several compatible ones
    (see `dataset_info`); episode ids stay unique (`DATASET_EPISODE_OFFSET`)."""
    import pyarrow.parquet as pq

    roots = _as_roots(roots)
    dataset_info(roots)
    wanted = None if tasks is None else set(resolve_tasks(tasks))
    files = [
        (position, f)
        for position, root in enumerate(roots)
        for f in _episode_files(root)
        if wanted is None or f.parent.name in wanted
    ]
    if not files:
        raise FileNotFoundError(f"no episodes in {', '.join(str(r / 'data') for r in roots)}")
    images, states, actions, task_names, episodes, scene_states = [], [], [], [], [], []
    for position, file in progress_bar(files, desc="load episodes", disable=not progress):
        table = pq.read_table(file).to_pydict()
        images.extend(table["image"])  # PNG bytes: decoded when a batch reads them
        states.extend(table["state"])
        actions.extend(table["action"])
        task_names.extend(table["task"])
        episodes.extend(e + position * DATASET_EPISODE_OFFSET for e in table["episode_index"])
        if scene_states is not None and "scene_state" in table:
            scene_states.extend(table["scene_state"])
        else:
            scene_states = None
    return Demonstrations(
        EncodedFrames(images),
        np.asarray(states, np.float32),
        np.asarray(actions, np.float32),
        task_names,
        np.asarray(episodes, np.int64),
        None if scene_states is None else np.asarray(scene_states, np.float32),
    )


def _compute_stats(files: list[Path]) -> dict:
    import pyarrow.parquet as pq

    actions, states, scene_states = [], [], []
    for file in files:
        parquet = pq.ParquetFile(file)  # one open: the schema says which columns exist, then read those
        present = parquet.schema_arrow.names
        table = parquet.read(columns=[c for c in ("action", "state", "scene_state") if c in present]).to_pydict()
        actions.extend(table["action"])
        states.extend(table["state"])
        if scene_states is not None and "scene_state" in table:
            scene_states.extend(table["scene_state"])
        else:
            scene_states = None
    stats = {
        "action": ActionNormalizer.from_actions(np.asarray(actions), ACTION_NORM_MASK).to_dict(),
        "state": ActionNormalizer.from_actions(np.asarray(states)).to_dict(),
        "num_frames": len(actions),
        "num_episodes": len(files),
    }
    if scene_states:  # only when every episode has them
        stats["scene_state"] = ActionNormalizer.from_actions(np.asarray(scene_states)).to_dict()
    return stats


def write_stats(root: str | Path) -> dict:
    """(Re)computes ``meta/stats.json`` from every episode on disk."""
    root = Path(root)
    files = _episode_files(root)
    if not files:
        return {}
    stats = _compute_stats(files)
    write_json_atomic(root / "meta" / "stats.json", stats)  # a crash leaves the old file or the new one
    return stats


@dataclass
class DatasetStats:
    """The normalisers of a dataset (`dataset_stats`); ``scene_state`` is None when some episode has no
    ``scene_state`` column."""

    action: ActionNormalizer
    state: ActionNormalizer
    scene_state: ActionNormalizer | None
    source: str  # the folder(s), for error messages

    def scene_normalizer(self) -> ActionNormalizer:
        """The scene-state normaliser.

        Raises:
            ValueError: some episode was collected before scene states were recorded (re-collect it).
        """
        if self.scene_state is None:
            raise ValueError(
                f"{self.source} has episodes without the scene_state column (collected by an older hf-specvla); "
                "collect the data again to train with scene targets"
            )
        return self.scene_state


def dataset_stats(roots: str | Path | list[str | Path]) -> DatasetStats:
    """The statistics of a dataset folder (its ``meta/stats.json``); of several folders, computed over all their
    episodes together (one pass over the files)."""
    source = str(roots)
    roots = _as_roots(roots)
    if len(roots) > 1:
        stats = _compute_stats([f for root in roots for f in _episode_files(root)])
    else:
        path = roots[0] / "meta" / "stats.json"
        if not path.exists():
            raise FileNotFoundError(f"{path} is missing; run hf-specvla collect (it writes the statistics)")
        try:
            stats = json.loads(path.read_text())
        except json.JSONDecodeError:  # torn by a crash mid-write (older versions wrote it in place): derived data
            logger.warning("%s is damaged; recomputing it from the episodes", path)
            stats = write_stats(roots[0])
    scene = ActionNormalizer.from_dict(stats["scene_state"]) if "scene_state" in stats else None
    return DatasetStats(
        ActionNormalizer.from_dict(stats["action"]), ActionNormalizer.from_dict(stats["state"]), scene, source
    )


def read_stats(roots: str | Path | list[str | Path]) -> tuple[ActionNormalizer, ActionNormalizer]:
    """(action normaliser, state normaliser) of one or several dataset folders (see `dataset_stats`)."""
    stats = dataset_stats(roots)
    return stats.action, stats.state


def read_scene_stats(roots: str | Path | list[str | Path]) -> ActionNormalizer:
    """The scene-state normaliser of one or several dataset folders (see `DatasetStats.scene_normalizer`)."""
    return dataset_stats(roots).scene_normalizer()
