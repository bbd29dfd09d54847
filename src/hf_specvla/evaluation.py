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
import statistics
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from .envs.metaworld import EnvConfig, MetaWorldEnv, resolve_tasks
from .policy import VLAPolicy
from .progress import progress_bar
from .run_folder import RunRecord, fingerprint, open_run_folder, read_jsonl, write_json_atomic
from .speculative import DraftHead, DraftHeadDrafter, SpeculationStats

logger = logging.getLogger(__name__)

EVAL_SEED_START = 100_000


@dataclass
class EpisodeResult:
    """One rollout. ``latencies_ms``: per-action ``predict_action`` wall time; ``accept_lengths``: tokens per
    target forward over the episode (speculative decoding only)."""

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
) -> EpisodeResult:
    """Runs one episode from ``env.reset(seed)`` until success or the step limit. Appends images to ``frames``
    when given (for a video)."""
    generate_kwargs = dict(generate_kwargs or {})
    obs = env.reset(seed)
    policy.reset()
    result = EpisodeResult(env.task, seed, False, 0)
    while True:
        if frames is not None:
            frames.append(obs["image"])
        start = time.perf_counter()
        action, output = policy.predict_action(
            obs["image"], obs["instruction"], obs["state"], return_output=True, **generate_kwargs
        )
        result.latencies_ms.append(1000 * (time.perf_counter() - start))
        stats: SpeculationStats | None = getattr(output, "speculation", None)
        if stats is not None:
            result.accept_lengths.extend(stats.accept_lengths)
        obs, _, done, info = env.step(action)
        result.length += 1
        if done:
            result.success = info["success"]
            return result


def record_observations(
    policy: VLAPolicy, tasks: str | list[str], seeds: list[int], max_steps: int, env_config: EnvConfig | None = None
) -> list[list[dict]]:
    """Greedy rollouts of ``policy``, one per task and seed, cut at ``max_steps``: the observations it saw
    (``image``, ``instruction``, ``state``), one list per episode. What the episode benchmark replays."""
    env_config = env_config or EnvConfig(image_size=policy.config.image_size, camera=policy.config.camera)
    policy.check_env_config(env_config)
    episodes = []
    for task in resolve_tasks(tasks):
        with MetaWorldEnv(task, env_config) as env:
            for seed in seeds:
                obs, observations = env.reset(seed), []
                policy.reset()
                for _ in range(max_steps):
                    observations.append({k: obs[k] for k in ("image", "instruction", "state")})
                    obs, _, done, _ = env.step(policy.predict_action(obs["image"], obs["instruction"], obs["state"]))
                    if done:
                        break
                episodes.append(observations)
    return episodes


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
        "| task | episodes | success | mean length | median ms/action | accept length |",
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
    """JSON form of ``generate_kwargs`` for a folder's record: draft heads by weight fingerprint, drafters by
    their settings, plain values as they are."""
    described = {}
    for key, value in sorted(generate_kwargs.items()):
        if isinstance(value, DraftHead):
            value = {"draft_head": fingerprint(value)}
        elif isinstance(value, DraftHeadDrafter):
            value = {"draft_head": fingerprint(value.draft_head), "tree": asdict(value.tree_config)}
        elif not isinstance(value, (bool, int, float, str, list, tuple, dict, type(None))):
            value = repr(value)
        described[key] = value
    return described


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
) -> dict:
    """Evaluates ``policy`` on ``episodes_per_task`` seeded episodes of each task; resumable.

    Writes ``output_dir/run.json`` (what produced the folder), ``output_dir/episodes.jsonl`` (one line per
    episode) and ``output_dir/summary.json``; returns the summary. ``video_path`` (``.gif`` or ``.mp4``) saves the
    first episode's frames. A folder holding another evaluation (other policy weights, env settings, seeds or
    decoding settings) is refused unless ``overwrite`` (which moves it aside); more tasks or episodes continue it.
    """
    if episodes_per_task < 1:
        raise ValueError(f"episodes_per_task must be >= 1, got {episodes_per_task}")
    tasks = resolve_tasks(tasks)
    if video_path is not None:
        check_video_path(video_path)
    env_config = env_config or EnvConfig(image_size=policy.config.image_size, camera=policy.config.camera)
    policy.check_env_config(env_config)
    output_dir = Path(output_dir)
    generate_kwargs = dict(generate_kwargs or {})
    settings = {"policy": fingerprint(policy.model), "env": asdict(env_config), "seed_start": seed_start,
                "decoding": describe_decoding(generate_kwargs)}  # fmt: skip
    open_run_folder(output_dir, RunRecord("eval", settings), overwrite)
    log_path = output_dir / "episodes.jsonl"
    results = [EpisodeResult(**record) for record in read_jsonl(log_path)]
    done = {(r.task, r.seed) for r in results}
    bar = progress_bar(
        total=len(tasks) * episodes_per_task, initial=len(done), desc="eval", unit="episode", disable=not progress
    )
    frames: list | None = [] if video_path is not None else None  # the first episode this call runs
    for task in tasks:
        seeds = [seed_start + i for i in range(episodes_per_task) if (task, seed_start + i) not in done]
        if not seeds:
            continue
        with MetaWorldEnv(task, env_config) as env:
            for seed in seeds:
                result = rollout(policy, env, seed, generate_kwargs, frames)
                results.append(result)
                with log_path.open("a") as log:
                    log.write(json.dumps(asdict(result)) + "\n")
                if frames is not None:  # after the episode is logged: a failing writer never costs an episode
                    _save_video(frames, video_path)
                    logger.info("saved %s (%s seed %d)", video_path, task, seed)
                    frames = None
                bar.update(1)
                bar.set_postfix(task=task, success=f"{np.mean([r.success for r in results]):.0%}")
    bar.close()
    if frames is not None:
        logger.warning("no video written: every requested episode was already in %s (nothing ran)", log_path)
    wanted = {(t, seed_start + i) for t in tasks for i in range(episodes_per_task)}
    summary = summarize([r for r in results if (r.task, r.seed) in wanted])
    write_json_atomic(output_dir / "summary.json", summary)
    return summary


VIDEO_SUFFIXES = (".gif", ".mp4")


def check_video_path(path: str | Path) -> None:
    """Raises ValueError, before anything runs, when ``path`` cannot be written: an unknown extension, or ``.mp4``
    without an mp4 writer (``imageio-ffmpeg``)."""
    suffix = Path(path).suffix.lower()
    if suffix not in VIDEO_SUFFIXES:
        raise ValueError(f"video {str(path)!r}: the extension must be one of {VIDEO_SUFFIXES}, got {suffix!r}")
    if suffix == ".mp4" and importlib.util.find_spec("imageio_ffmpeg") is None:
        raise ValueError(
            f"video {str(path)!r}: writing .mp4 needs imageio-ffmpeg (pip install imageio-ffmpeg); or use a .gif"
        )


def _save_video(frames: list, path: str | Path) -> None:
    import imageio.v2 as imageio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimsave(path, [np.asarray(f) for f in frames], duration=1 / 20 if path.suffix == ".gif" else None)
