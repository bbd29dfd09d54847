"""Rolling a [`VLAPolicy`] out on Meta-World and reporting per-task success.

Evaluation seeds start at ``EVAL_SEED_START`` (100000), far from the collection seeds (0, 1, ...), so a policy is
never scored on a start it was trained on. Results are appended to ``episodes.jsonl`` one episode at a time; an
interrupted evaluation resumes where it stopped, and only an evaluation of the same policy weights, env settings,
seeds and decoding settings continues a folder (``run.json``, see [`hf_specvla.run_folder`]). Any ``generate``
option passes through (``generate_kwargs``), so plain and speculative decoding are one flag apart.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import os
import re
import statistics
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..policies import VLAPolicy
from ..policies.decoding_methods import DecodingPlan, check_decoding_plan
from ..policies.devices import dtype_name
from ..progress import progress_bar
from ..run_folder import RunRecord, claim_run_folder, fingerprint, read_jsonl, write_json_atomic
from ..speculative import ComposedDrafter, DraftHead, DraftHeadDrafter, PerRowDrafter, SpeculationStats
from .env import EnvConfig, MetaWorldEnv, resolve_tasks
from .rollout import rollout as run_rollout
from .seeds import EVAL_SEED_START

logger = logging.getLogger(__name__)


@dataclass
class EpisodeResult:
    """One rollout. ``length``: env steps; ``latencies_ms``: wall time of each ``predict_action`` call (one per
    action, or per chunk of actions for a chunked policy); ``accept_lengths``: tokens per target forward over the
    episode (speculative decoding only)."""

    task: str
    seed: int
    success: bool
    length: int
    latencies_ms: list[float] = field(default_factory=list)
    accept_lengths: list[int] = field(default_factory=list)


def rollout(
    policy: VLAPolicy,
    env: MetaWorldEnv,
    seed: int,
    generate_kwargs: dict | None = None,
    frames: list | None = None,
    decoding: DecodingPlan | None = None,
) -> EpisodeResult:
    """Runs one episode from ``env.reset(seed)`` until success or the step limit ([`rollout_batch`] of one
    environment). Appends images to ``frames`` when given (for a video)."""
    return rollout_batch(policy, [env], [seed], generate_kwargs, frames, decoding)[0]


def rollout_batch(
    policy: VLAPolicy,
    envs: list[MetaWorldEnv],
    seeds: list[int],
    generate_kwargs: dict | None = None,
    frames: list | None = None,
    decoding: DecodingPlan | None = None,
) -> list[EpisodeResult]:
    """Runs one episode per environment in lockstep (``envs[b].reset(seeds[b])``): each step, one batched
    ``predict_action`` for every environment still running; an environment leaves the batch when its episode ends.
    Per episode the same as [`rollout`] (each row keeps its own action memory for ``action_prior``); a row's
    ``latencies_ms`` are the batched calls' wall times (what each environment waited). A chunked policy's chunk is
    executed whole (``VLAPolicy.action_steps``) before the next call; the rows stay in lockstep, since every row
    executes the same number of steps per call. ``frames`` gets the first environment's images. ``decoding`` (a
    method's typed plan: ``DecodingMethod.plan``) and ``generate_kwargs`` go to every ``predict_action``."""
    generate_kwargs = dict(generate_kwargs or {})
    results = [EpisodeResult(env.task, seed, False, 0) for env, seed in zip(envs, seeds)]
    memories: list[list[list[int]]] = [[] for _ in envs]  # each row's previous actions (the action prior's drafts)

    def decide(rows: list[int], observations: list[dict]) -> list:
        start = time.perf_counter()
        actions, output = policy.predict_action(
            np.stack([obs["image"] for obs in observations]),
            [obs["instruction"] for obs in observations],
            np.stack([obs["state"] for obs in observations]),
            return_output=True,
            previous_action_ids=[memories[b] for b in rows],
            decoding=decoding,
            **generate_kwargs,
        )
        latency_ms = 1000 * (time.perf_counter() - start)
        stats: SpeculationStats | None = getattr(output, "speculation", None)
        row_stats = (stats.rows or [stats]) if stats is not None else [None] * len(rows)
        for b, row in zip(rows, row_stats):
            results[b].latencies_ms.append(latency_ms)
            if row is not None:
                results[b].accept_lengths.extend(row.accept_lengths)
        return [policy.action_steps(action) for action in actions]

    def on_step(b: int, observation: dict, info: dict) -> None:
        if frames is not None and b == 0:
            frames.append(observation["image"])

    for result, episode in zip(results, run_rollout(envs, seeds, decide, on_step)):
        result.success, result.length = episode.success, episode.length
    return results


def record_observations(
    policy: VLAPolicy, tasks: str | list[str], seeds: list[int], max_steps: int, env_config: EnvConfig | None = None
) -> list[list[dict]]:
    """Greedy rollouts of ``policy``, one per task and seed, cut at ``max_steps`` calls: the observations it
    decided on (``image``, ``instruction``, ``state``; a chunked policy decides once per chunk) and the action it had
    taken before each (``previous_action``: its token ids, None at the first step), one list per episode. What the
    episode benchmark replays and draft heads train on."""
    env_config = env_config or EnvConfig(image_size=policy.config.image_size, camera=policy.config.camera)
    env_config.check_renders_for(policy.config)
    episodes = []
    for task in resolve_tasks(tasks):
        with MetaWorldEnv(task, env_config) as env:
            episodes += [_decided_observations(policy, env, seed, max_steps) for seed in seeds]
    return episodes


def _decided_observations(policy: VLAPolicy, env: MetaWorldEnv, seed: int, max_steps: int) -> list[dict]:
    """One greedy episode's observations that ``policy`` decided on, at most ``max_steps``."""
    observations: list[dict] = []
    policy.reset()

    def decide(rows: list[int], current: list[dict]) -> list:
        obs = current[0]
        previous = policy.previous_action_ids[-1] if policy.previous_action_ids else None
        observations.append({**{k: obs[k] for k in ("image", "instruction", "state")}, "previous_action": previous})
        return [policy.action_steps(policy.predict_action(obs["image"], obs["instruction"], obs["state"]))]

    run_rollout([env], [seed], decide, max_decisions=max_steps)
    return observations


def summarize(results: list[EpisodeResult]) -> dict:
    """Per-task and overall success rate, mean episode length, median per-action latency, mean accept length."""

    def block(items: list[EpisodeResult]) -> dict:
        latencies = [x for r in items for x in r.latencies_ms]
        accepts = [x for r in items for x in r.accept_lengths]
        return {
            "episodes": len(items),
            "success_rate": sum(r.success for r in items) / len(items),
            "mean_episode_length": statistics.mean(r.length for r in items),
            "median_latency_ms": statistics.median(latencies) if latencies else None,
            "mean_accept_length": (sum(accepts) / len(accepts)) if accepts else None,
        }

    tasks = sorted({r.task for r in results})
    per_task = {task: block([r for r in results if r.task == task]) for task in tasks}
    overall = block(results)
    overall["mean_task_success_rate"] = statistics.mean(t["success_rate"] for t in per_task.values())
    return {"tasks": per_task, "overall": overall}


def format_summary(summary: dict) -> str:
    """Markdown table of [`summarize`]'s result."""
    lines = [
        "| task | episodes | success | mean length | median ms/call | accept length |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    rows = [*summary["tasks"].items(), ("**mean over tasks**", summary["overall"])]
    for name, row in rows:
        rate = row.get("mean_task_success_rate", row["success_rate"])
        latency = "-" if row["median_latency_ms"] is None else f"{row['median_latency_ms']:.1f}"
        accept = "-" if row["mean_accept_length"] is None else f"{row['mean_accept_length']:.2f}"
        lines.append(
            f"| {name} | {row['episodes']} | {rate:.0%} | {row['mean_episode_length']:.0f} | {latency} | {accept} |"
        )
    return "\n".join(lines)


def describe_decoding(generate_kwargs: dict) -> dict:
    """JSON form of ``generate_kwargs`` for a folder's record, the same in every process for the same settings
    ([`describe_setting`])."""
    return {key: describe_setting(value) for key, value in sorted(generate_kwargs.items())}


#: a ``repr`` that holds a memory address (``<... object at 0x7f...>``): another in every process
_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")


def describe_setting(value):
    """One decoding setting as JSON that is the same in every process for the same setting: plain values as they
    are (sequences as lists), draft heads by weight fingerprint, a head's drafter by its head and tree, a composition
    or per-row drafter by its parts in order, any other object by its ``repr`` when that holds no memory address (the
    drafters' own: Jacobi, the action prior, a ``CompileConfig``), else by its class and public attributes."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, (list, tuple)):
        return [describe_setting(item) for item in value]
    if isinstance(value, Mapping):
        return {str(key): describe_setting(item) for key, item in sorted(value.items())}
    if isinstance(value, DraftHead):
        return {"draft_head": fingerprint(value)}
    if isinstance(value, DraftHeadDrafter):
        return {"draft_head": fingerprint(value.draft_head), "tree": asdict(value.tree_config)}
    if isinstance(value, (ComposedDrafter, PerRowDrafter)):
        return {type(value).__name__: [describe_setting(drafter) for drafter in value.drafters]}
    text = repr(value)
    if not _ADDRESS.search(text):
        return text
    attributes = {
        name: describe_setting(item) for name, item in sorted(vars(value).items()) if not name.startswith("_")
    }
    return {"type": f"{type(value).__module__}.{type(value).__qualname__}", **attributes}


def evaluate(
    policy: VLAPolicy,
    tasks: str | list[str],
    episodes_per_task: int,
    output_dir: str | Path,
    env_config: EnvConfig | None = None,
    seed_start: int = EVAL_SEED_START,
    generate_kwargs: dict | None = None,
    video_path: str | Path | None = None,
    progress: bool = True,
    overwrite: bool = False,
    num_envs: int = 1,
    decoding: DecodingPlan | None = None,
) -> dict:
    """Evaluates ``policy`` on ``episodes_per_task`` seeded episodes of each task; resumable.

    ``num_envs`` > 1 runs that many episodes in lockstep ([`rollout_batch`]: one batched policy call per step for
    all of them); the episodes and their results are the same (greedy decoding gives each row what it gives alone),
    only the wall time changes. It is not part of the folder's record: a folder may be resumed with another value.

    Writes ``output_dir/run.json`` (what produced the folder), ``output_dir/episodes.jsonl`` (one line per
    episode) and ``output_dir/summary.json``; returns the summary. ``video_path`` (``.gif`` or ``.mp4``) saves the
    first episode's frames. A folder holding another evaluation (other policy weights, env settings, seeds, decoding
    settings, or the policy on another kind of device or in another dtype: their actions may differ) is refused unless
    ``overwrite`` (which moves it aside); more tasks or episodes continue it.
    The decoding is ``decoding`` (a method's typed plan: ``DecodingMethod.plan``) with ``generate_kwargs`` beside
    it, or ``generate_kwargs`` alone; the folder records them as one set of ``generate`` options either way.
    """
    if episodes_per_task < 1:
        raise ValueError(f"episodes_per_task must be >= 1, got {episodes_per_task}")
    if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
        raise ValueError(f"num_envs must be an int >= 1 (episodes run in lockstep), got {num_envs!r}")
    check_decoding_plan(decoding, "evaluate")
    tasks = resolve_tasks(tasks)
    if video_path is not None:
        check_video_path(video_path)
    env_config = env_config or EnvConfig(image_size=policy.config.image_size, camera=policy.config.camera)
    env_config.check_renders_for(policy.config)
    output_dir = Path(output_dir)
    generate_kwargs = dict(generate_kwargs or {})
    settings = {
        "policy": policy.weights_fingerprint(),  # the weights as loaded, whatever their cast
        "env": asdict(env_config),
        "seed_start": seed_start,
        "device": policy.model.device.type,
        "dtype": dtype_name(policy.model.dtype),
        "decoding": describe_decoding({**(decoding.predict_kwargs() if decoding else {}), **generate_kwargs}),
    }
    with claim_run_folder(output_dir, RunRecord("eval", settings), overwrite) as run:
        folder = run.bound  # writes stay in the claimed folder, renamed or not
        log_path = folder / "episodes.jsonl"
        results = [EpisodeResult(**record) for record in read_jsonl(log_path, shown_as=output_dir / "episodes.jsonl")]
        done = {(r.task, r.seed) for r in results}
        bar = progress_bar(
            total=len(tasks) * episodes_per_task, initial=len(done), desc="eval", unit="episode", disable=not progress
        )
        frames: list | None = [] if video_path is not None else None  # the first episode this call runs
        wanted = [(t, seed_start + i) for t in tasks for i in range(episodes_per_task)]
        pending = [key for key in wanted if key not in done]
        with _EnvPool(env_config) as pool:
            for chunk_start in range(0, len(pending), num_envs):
                chunk = pending[chunk_start : chunk_start + num_envs]
                envs = pool.acquire([task for task, _ in chunk])
                seeds = [seed for _, seed in chunk]
                chunk_results = rollout_batch(policy, envs, seeds, generate_kwargs, frames, decoding)
                with log_path.open("a") as log:
                    for result in chunk_results:
                        log.write(json.dumps(asdict(result)) + "\n")
                results.extend(chunk_results)
                if frames is not None:  # after the episode is logged: a failing writer never costs an episode
                    _save_video(frames, video_path)
                    logger.info("saved %s (%s seed %d)", video_path, *chunk[0])
                    frames = None
                bar.update(len(chunk))
                bar.set_postfix(task=chunk[-1][0], success=f"{np.mean([r.success for r in results]):.0%}")
                pool.close_except({task for task, _ in pending[chunk_start + num_envs :]})
        bar.close()
        if frames is not None:
            logger.warning("no video written: every requested episode was already in %s (nothing ran)", output_dir)
        summary = summarize([r for r in results if (r.task, r.seed) in set(wanted)])
        write_json_atomic(folder / "summary.json", summary)
        return summary


class _EnvPool:
    """Environments by task, created on first use and reused (building a Meta-World env costs more than a reset)."""

    def __init__(self, env_config: EnvConfig):
        self.env_config = env_config
        self.envs: dict[str, list[MetaWorldEnv]] = {}

    def acquire(self, tasks: list[str]) -> list[MetaWorldEnv]:
        """One distinct environment per entry of ``tasks``."""
        out, used = [], {}
        for task in tasks:
            index = used.get(task, 0)
            available = self.envs.setdefault(task, [])
            if index == len(available):
                available.append(MetaWorldEnv(task, self.env_config))
            out.append(available[index])
            used[task] = index + 1
        return out

    def close_except(self, tasks: set[str]) -> None:
        """Closes the environments of every task not in ``tasks`` (no episode left needs them)."""
        for task in [t for t in self.envs if t not in tasks]:
            for env in self.envs.pop(task):
                env.close()

    def __enter__(self) -> _EnvPool:
        return self

    def __exit__(self, *exc) -> None:
        self.close_except(set())


VIDEO_SUFFIXES = (".gif", ".mp4")


def check_video_path(path: str | Path) -> None:
    """Raises ValueError, before anything runs, when ``path`` cannot be written: an unknown extension, ``.mp4``
    without an mp4 writer (``imageio-ffmpeg``), a folder of that name, a file where a folder above it would be made,
    or a nearest existing folder that is not writable."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in VIDEO_SUFFIXES:
        raise ValueError(f"video {str(path)!r}: the extension must be one of {VIDEO_SUFFIXES}, got {suffix!r}")
    if path.is_dir():
        raise ValueError(f"video {str(path)!r}: is a folder; give a file path (e.g. {str(path / 'episode.gif')!r})")
    existing = next((p for p in path.parents if p.exists()), Path("."))  # Path.exists: False under a file
    if not existing.is_dir():
        raise ValueError(
            f"video {str(path)!r}: {existing} is a file, so no folder can be made under it; give another path"
        )
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ValueError(f"video {str(path)!r}: {existing} is not writable; give a path you can write to")
    if suffix == ".mp4" and importlib.util.find_spec("imageio_ffmpeg") is None:
        raise ValueError(
            f"video {str(path)!r}: writing .mp4 needs imageio-ffmpeg (pip install imageio-ffmpeg); or use a .gif"
        )


def _save_video(frames: list, path: str | Path) -> None:
    import imageio.v2 as imageio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimsave(path, [np.asarray(f) for f in frames], duration=1 / 20 if path.suffix == ".gif" else None)
