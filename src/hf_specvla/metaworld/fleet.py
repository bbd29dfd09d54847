"""Robots that drive a policy server: K Meta-World environments, each in its own thread with its own client, run
seeded episodes against ``hf-specvla serve`` (observation -> ``POST /act`` -> execute the returned action), the way
robots in a lab share one policy server.

The robots learn everything about the policy from the server's ``GET /info`` ([`ServerInfo`]): what to render
(image size, camera), whether to send the proprio state, the action and chunk layout, the policy's name and weights
fingerprint and the decoding method. The episodes are those of ``eval`` (``env.reset(seed)`` for
``seed_start, seed_start + 1, ...`` of each task; success read at the step that ends the episode; the env cuts it at
``max_episode_steps``); a chunked policy's chunk is executed whole before the next request, as ``eval`` does.

A run writes a folder like ``eval``'s (see [`hf_specvla.run_folder`]): ``run.json`` (the policy's fingerprint, the
method, the env settings, the seeds and the number of robots: a folder never mixes two policies, methods or fleet
sizes), ``episodes.jsonl`` (one [`RobotEpisode`] per line, written the moment it ends) and ``summary.json``
([`summarize`]). A finished (task, seed) is never run again: a killed run continues where it stopped.

Example:
    ```python
    config = RobotsConfig(tasks="reach", episodes_per_task=2, robots=4, server="http://127.0.0.1:8000")
    summary = run_robots(config, "runs/robots_reach")
    summary["actions_per_second"], summary["latency_ms"]["p95"], summary["batch_sizes"]
    ```
"""

from __future__ import annotations

import json
import logging
import queue
import secrets
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from .._validation import check_ranges
from ..progress import progress_bar
from ..serving.client import PolicyClient
from ..serving.config import DEFAULT_HOST, DEFAULT_PORT
from .env import ACTION_DIM, MAX_EPISODE_STEPS, STATE_DIM, EnvConfig, MetaWorldEnv, resolve_tasks
from .seeds import EVAL_SEED_START

logger = logging.getLogger(__name__)

#: where ``hf-specvla serve`` listens unless told otherwise
DEFAULT_SERVER = f"http://{DEFAULT_HOST}:{DEFAULT_PORT}"
#: the request latency percentiles the summary reports
LATENCY_PERCENTILES = (50, 95, 99)


class ServerReplyError(ValueError):
    """The server answered, but not as an hf_specvla policy server for Meta-World robots does (``/info`` lacks a
    field or names a layout the simulator cannot run, or an action of another shape than ``/info`` promised)."""


# ----------------------------------------------------------------------------- settings
@dataclass
class RobotsConfig:
    """What a fleet of robots runs.

    Args:
        tasks: Meta-World tasks (names or suites), resolved to task names.
        episodes_per_task: seeds per task (``seed_start``, +1, ...).
        robots: concurrent robots, each its own environment, thread and client session.
        seed_start: first seed (evaluation seeds by default, as ``eval``).
        max_episode_steps: env steps before an episode is cut (at most Meta-World's 500).
        server: the policy server's address.
        api_key: sent as a Bearer token (a server started with an API key needs it); never recorded.
    """

    tasks: str | list[str] = "MT10"
    episodes_per_task: int = 20
    robots: int = 4
    seed_start: int = EVAL_SEED_START
    max_episode_steps: int = EnvConfig.max_episode_steps
    server: str = DEFAULT_SERVER
    api_key: str | None = field(default=None, repr=False)

    def __post_init__(self):
        self.tasks = resolve_tasks(self.tasks)
        check_ranges(
            self,
            at_least_one=("episodes_per_task", "robots", "max_episode_steps"),
            non_negative=("seed_start",),
            integers=("episodes_per_task", "robots", "max_episode_steps", "seed_start"),
        )
        if self.max_episode_steps > MAX_EPISODE_STEPS:
            raise ValueError(
                f"RobotsConfig.max_episode_steps must be <= {MAX_EPISODE_STEPS} (Meta-World's "
                f"max_path_length), got {self.max_episode_steps}"
            )
        if not isinstance(self.server, str) or not self.server.startswith(("http://", "https://")):
            raise ValueError(
                f"RobotsConfig.server must be an http:// or https:// address (e.g. {DEFAULT_SERVER}), "
                f"got {self.server!r}"
            )

    def pairs(self) -> list[tuple[str, int]]:
        """Every (task, seed) the run holds, task by task (the order robots take them in)."""
        return [(task, self.seed_start + i) for task in self.tasks for i in range(self.episodes_per_task)]


@dataclass(frozen=True)
class ServerInfo:
    """The server's ``GET /info`` as the robots read it.

    Attributes:
        policy: the policy's name (its path or hub id; recorded, never compared).
        fingerprint: the policy weights' content fingerprint (a folder holds one policy's episodes).
        image_size / camera: what the robots render (``EnvConfig``).
        state_dim / use_state: the proprio numbers the policy reads, and whether it reads them.
        action_dim / chunk_length: an action is ``[action_dim]``, or ``[chunk_length, action_dim]`` when
            ``chunk_length`` > 1 (the chunk's actions in the order they are executed).
        method: the decoding method the server runs.
        buckets: the batch sizes the server decodes at.
    """

    policy: str
    fingerprint: str
    image_size: int
    camera: str
    state_dim: int
    action_dim: int
    chunk_length: int
    use_state: bool
    method: str
    buckets: tuple[int, ...]

    @classmethod
    def from_payload(cls, payload: Any) -> ServerInfo:
        """``GET /info``'s JSON object -> a ServerInfo; other fields are ignored.

        Raises:
            ServerReplyError: a missing or mistyped field (named), or a layout Meta-World robots cannot run (an
                action of other than 4 numbers, a state of other than 4, a camera or image size ``EnvConfig``
                refuses).
        """
        if not isinstance(payload, dict):
            raise ServerReplyError(f"/info must be a JSON object, got {type(payload).__name__}")
        kinds = {
            "policy": str,
            "fingerprint": str,
            "image_size": int,
            "camera": str,
            "state_dim": int,
            "action_dim": int,
            "chunk_length": int,
            "use_state": bool,
            "method": str,
            "buckets": list,
        }
        for name, kind in kinds.items():
            value = payload.get(name)
            if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
                raise ServerReplyError(
                    f"/info field {name!r} must be {kind.__name__}, got {value!r}: not an hf-specvla policy server?"
                )
        buckets = payload["buckets"]
        if not buckets or not all(isinstance(b, int) and not isinstance(b, bool) and b >= 1 for b in buckets):
            raise ServerReplyError(f"/info field 'buckets' must be a non-empty list of ints >= 1, got {buckets!r}")
        info = cls(**{name: payload[name] for name in kinds if name != "buckets"}, buckets=tuple(buckets))
        if info.action_dim != ACTION_DIM:
            raise ServerReplyError(
                f"the server's policy acts in {info.action_dim} dimensions; Meta-World robots take "
                f"{ACTION_DIM} (xyz delta + gripper)"
            )
        if info.use_state and info.state_dim != STATE_DIM:
            raise ServerReplyError(
                f"the server's policy reads {info.state_dim} state numbers; Meta-World robots send "
                f"{STATE_DIM} (hand xyz + gripper opening)"
            )
        if info.chunk_length < 1:
            raise ServerReplyError(f"/info field 'chunk_length' must be >= 1, got {info.chunk_length}")
        info.env_config()  # a camera or image size the simulator refuses
        return info

    def env_config(self, max_episode_steps: int = MAX_EPISODE_STEPS) -> EnvConfig:
        """The env settings that render what the server's policy reads."""
        try:
            return EnvConfig(image_size=self.image_size, camera=self.camera, max_episode_steps=max_episode_steps)
        except ValueError as error:
            raise ServerReplyError(f"the server's policy reads images the robots cannot render: {error}") from None

    def action_rows(self, action: np.ndarray) -> list[np.ndarray]:
        """One reply's action as the env steps to run, in order (one, or the chunk's ``chunk_length``).

        Raises:
            ServerReplyError: an action of another shape than ``/info`` promised.
        """
        action = np.asarray(action, dtype=np.float64)
        expected = (self.action_dim,) if self.chunk_length == 1 else (self.chunk_length, self.action_dim)
        if action.shape != expected:
            raise ServerReplyError(
                f"the server sent an action of shape {list(action.shape)}; its /info promised {list(expected)}"
            )
        return [action] if action.ndim == 1 else list(action)


# ----------------------------------------------------------------------------- one episode
@dataclass
class RobotEpisode:
    """One robot's episode, as ``episodes.jsonl`` holds it (one line each).

    Attributes:
        task / seed: the episode (``env.reset(seed)``).
        success: the task was solved at the step that ended the episode.
        length: env steps taken.
        robot: the robot that ran it (0 .. robots - 1).
        session: the robot's session id at the server (``<run>/robot-<i>``).
        run: the run (one ``run_robots`` call) it belongs to: a random token.
        started / finished: wall-clock times (Unix seconds) of its reset and of its last step.
        actions: ``[length][action_dim]``, the actions sent to ``env.step`` in order (the env clips to [-1, 1]).
        latencies_ms: per request, client side: from sending the observation to holding the action.
        server_ms / queue_ms: per request, the server's own time and the part its request waited for a batch.
        target_forwards: per request, the target forwards its batch row took part in.
        batch_sizes: per request, the robots' requests the server decoded together.
        buckets: per request, the batch size the server's call ran at.
        methods: per request, the decoding that ran.
        speculative: per request, whether it was decoded speculatively.
    """

    task: str
    seed: int
    success: bool = False
    length: int = 0
    robot: int = 0
    session: str = ""
    run: str = ""
    started: float = 0.0
    finished: float = 0.0
    actions: list[list[float]] = field(default_factory=list)
    latencies_ms: list[float] = field(default_factory=list)
    server_ms: list[float] = field(default_factory=list)
    queue_ms: list[float] = field(default_factory=list)
    target_forwards: list[int] = field(default_factory=list)
    batch_sizes: list[int] = field(default_factory=list)
    buckets: list[int] = field(default_factory=list)
    methods: list[str] = field(default_factory=list)
    speculative: list[bool] = field(default_factory=list)

    def record_reply(self, latency_ms: float, served) -> None:
        """Appends one request's figures (``served``: the reply's [`ServedFigures`])."""
        self.latencies_ms.append(round(latency_ms, 3))
        self.server_ms.append(round(served.server_ms, 3))
        self.queue_ms.append(round(served.queue_ms, 3))
        self.target_forwards.append(served.target_forwards)
        self.batch_sizes.append(served.batch_size)
        self.buckets.append(served.bucket)
        self.methods.append(served.method)
        self.speculative.append(bool(served.speculative))


def run_episode(
    env: MetaWorldEnv, seed: int, client, info: ServerInfo, session: str, stop: threading.Event | None = None
) -> RobotEpisode | None:
    """One episode of one robot: ``env.reset(seed)``, then request -> execute the action (a chunk whole) until the
    env ends the episode (success, or its step limit). The first request starts the session's episode (``reset``).

    Args:
        env: the robot's environment (it renders what ``info`` names).
        client: a [`PolicyClient`] (or an object with its ``act``), this robot's alone.
        session: the robot's id at the server.
        stop: set by another thread to abandon the episode before its next request.
    Returns:
        The episode, or None when ``stop`` was set before it ended.
    """
    episode = RobotEpisode(env.task, int(seed), session=session, started=time.time())
    observation = env.reset(seed)
    done = False
    while not done:
        if stop is not None and stop.is_set():
            return None
        state = observation["state"] if info.use_state else None
        start = time.perf_counter()
        reply = client.act(
            observation["image"], observation["instruction"], state, session=session, reset=not episode.latencies_ms
        )
        episode.record_reply(1000 * (time.perf_counter() - start), reply.served)
        for action in info.action_rows(reply.action):
            observation, _, done, step_info = env.step(action)
            episode.actions.append(action.tolist())
            episode.length += 1
            if done:
                episode.success = bool(step_info["success"])
                break
    episode.finished = time.time()
    return episode


# ----------------------------------------------------------------------------- the fleet
@dataclass
class _Fleet:
    """What the robot threads share: the pairs left, the log (written under ``lock``), the stop signal, the bar."""

    pairs: queue.SimpleQueue
    info: ServerInfo
    env_config: EnvConfig
    run: str
    log: TextIO
    bar: Any
    episodes: list[RobotEpisode]
    lock: threading.Lock = field(default_factory=threading.Lock)
    stop: threading.Event = field(default_factory=threading.Event)
    errors: list[BaseException] = field(default_factory=list)
    steps: int = 0  # env steps of this run's finished episodes
    started: float = field(default_factory=time.perf_counter)

    def drive(self, robot: int, client) -> None:
        """One robot's thread: takes (task, seed) pairs until none is left or another robot failed; keeps one
        environment, rebuilt when the task changes. A failure stops every robot after its current request."""
        env: MetaWorldEnv | None = None
        session = f"{self.run}/robot-{robot}"
        try:
            while not self.stop.is_set():
                try:
                    task, seed = self.pairs.get_nowait()
                except queue.Empty:
                    return
                if env is None or env.task != task:
                    if env is not None:
                        env.close()
                    env = None  # never left pointing at a closed env if the next one fails to build
                    env = MetaWorldEnv(task, self.env_config)
                episode = run_episode(env, seed, client, self.info, session, self.stop)
                if episode is not None:
                    episode.robot, episode.run = robot, self.run
                    self.finish(episode)
        except BaseException as error:  # the main thread re-raises the first one
            with self.lock:
                self.errors.append(error)
            self.stop.set()
            logger.debug("robot %d stopped the fleet: %r", robot, error)
        finally:
            if env is not None:
                env.close()

    def finish(self, episode: RobotEpisode) -> None:
        """Logs a finished episode (one flushed line: a killed run keeps it) and counts it on the bar."""
        with self.lock:
            self.log.write(json.dumps(asdict(episode)) + "\n")
            self.log.flush()
            self.episodes.append(episode)
            self.steps += episode.length
            self.bar.update(1)
            rate = self.steps / max(time.perf_counter() - self.started, 1e-9)
            success = np.mean([e.success for e in self.episodes])
            self.bar.set_postfix(task=episode.task, success=f"{success:.0%}", actions_per_s=f"{rate:.1f}")


def _drive_fleet(fleet: _Fleet, clients: list) -> None:
    """Runs one thread per client until the pairs are done; re-raises the first robot's error (the others stop after
    their current request; their unfinished episodes are not logged)."""
    threads = [
        threading.Thread(target=fleet.drive, args=(robot, client), name=f"robot-{robot}", daemon=True)
        for robot, client in enumerate(clients)
    ]
    for thread in threads:
        thread.start()
    try:
        for thread in threads:
            thread.join()
    except KeyboardInterrupt:
        fleet.stop.set()
        for thread in threads:
            thread.join(timeout=10.0)
        raise
    if fleet.errors:
        raise fleet.errors[0]


def run_robots(
    config: RobotsConfig,
    output_dir: str | Path,
    client_factory: Callable[[], Any] | None = None,
    overwrite: bool = False,
    progress: bool = True,
) -> dict:
    """Runs ``config.robots`` concurrent robots against the policy server until every (task, seed) of ``config`` is
    in ``output_dir``; resumable.

    Args:
        config: what to run.
        output_dir: the run folder (``run.json``, ``episodes.jsonl``, ``summary.json``).
        client_factory: makes one client per robot (and one to read ``/info``); default a [`PolicyClient`] of
            ``config.server`` and ``config.api_key``. Anything with ``info()`` and ``act(...)`` as the client's.
        overwrite: move a folder holding another run aside and start over.
        progress: show a progress bar.
    Returns:
        The summary ([`summarize`] of the folder's episodes of ``config``), also written to ``summary.json``.
    Raises:
        ServerReplyError: ``/info`` or a reply that Meta-World robots cannot use.
        FileExistsError: the folder holds another run (another policy fingerprint, method, env, seeds or number
            of robots), naming the differing setting.
        ConnectionError / ServerError: from a robot's client (the server went away, refused a request); the
            finished episodes stay in the folder and the same call continues them.
    """
    # run_folder loads torch (weights fingerprints): imported here, so that the CLI's --help never loads it
    from ..run_folder import RunRecord, claim_run_folder, read_jsonl, write_json_atomic

    make_client = client_factory or (lambda: PolicyClient(config.server, config.api_key))
    info = ServerInfo.from_payload(make_client().info())
    env_config = info.env_config(config.max_episode_steps)
    output_dir = Path(output_dir)
    settings = {
        "policy": info.fingerprint,
        "decoding": {"method": info.method, "buckets": list(info.buckets)},
        "env": asdict(env_config),
        "seed_start": config.seed_start,
        "robots": config.robots,
    }
    record = RunRecord("robots", settings, paths={"policy": info.policy, "server": config.server})
    with claim_run_folder(output_dir, record, overwrite) as run:
        folder = run.bound  # writes stay in the claimed folder, renamed or not
        log_path = folder / "episodes.jsonl"
        episodes = [RobotEpisode(**r) for r in read_jsonl(log_path, shown_as=output_dir / "episodes.jsonl")]
        wanted = config.pairs()
        done = {(e.task, e.seed) for e in episodes}
        pending = [pair for pair in wanted if pair not in done]
        if pending:
            robots = min(config.robots, len(pending))
            logger.info(
                "%d robots drive %s (%s, method %s) at %s: %d episodes to run, %d already in %s",
                robots,
                info.policy,
                info.fingerprint,
                info.method,
                config.server,
                len(pending),
                len(wanted) - len(pending),
                output_dir,
            )
            pairs: queue.SimpleQueue = queue.SimpleQueue()
            for pair in pending:
                pairs.put(pair)
            bar = progress_bar(
                total=len(wanted),
                initial=len(wanted) - len(pending),
                desc="robots",
                unit="episode",
                disable=not progress,
            )
            clients = [make_client() for _ in range(robots)]  # one each: a client's draft states are its robot's
            try:
                with log_path.open("a") as log:
                    fleet = _Fleet(pairs, info, env_config, secrets.token_hex(4), log, bar, episodes)
                    _drive_fleet(fleet, clients)
            finally:
                bar.close()
        wanted_set = set(wanted)
        summary = summarize([e for e in episodes if (e.task, e.seed) in wanted_set])
        summary.update(policy=info.policy, fingerprint=info.fingerprint, method=info.method, robots=config.robots)
        write_json_atomic(folder / "summary.json", summary)
        return summary


# ----------------------------------------------------------------------------- the summary
def percentiles(values: list[float], quantiles=LATENCY_PERCENTILES) -> dict:
    """``{"p50": ..., "p95": ..., "p99": ...}`` of ``values`` (numpy's linear interpolation between the closest
    ranks); None for each when there are no values."""
    if not values:
        return {f"p{q}": None for q in quantiles}
    return {f"p{q}": float(np.percentile(values, q)) for q in quantiles}


def _histogram(values: list) -> dict:
    """value -> count, keys as JSON writes them (strings), in increasing order of the values."""
    return {str(value): count for value, count in sorted(Counter(values).items())}


def summarize(episodes: list[RobotEpisode]) -> dict:
    """The figures of a fleet's episodes.

    Returns a dict with:
        ``episodes``, ``success_rate`` (over episodes), ``mean_task_success_rate`` (the mean of the tasks' rates);
        ``tasks``: task -> ``episodes``, ``success_rate``, ``mean_episode_length``;
        ``env_steps``, ``requests``;
        ``wall_seconds``: the runs' wall times summed (each run, one ``run_robots`` call, from its first reset to
            its last finished step), ``actions_per_second``: ``env_steps / wall_seconds``; ``runs``: how many;
        ``latency_ms`` (client side) and ``server_ms``: ``p50`` / ``p95`` / ``p99`` / ``mean`` over requests;
        ``batch_sizes``: the server's batch size -> requests; ``methods``: the decoding that ran -> requests;
        ``speculative_fraction``: the share of requests decoded speculatively;
        ``target_forwards_per_request``: the mean.

    Raises:
        ValueError: no episodes.
    """
    if not episodes:
        raise ValueError("summarize needs at least one episode")
    tasks = sorted({e.task for e in episodes})
    per_task = {}
    for task in tasks:
        items = [e for e in episodes if e.task == task]
        per_task[task] = {
            "episodes": len(items),
            "success_rate": sum(e.success for e in items) / len(items),
            "mean_episode_length": float(np.mean([e.length for e in items])),
        }
    runs: dict[str, list[RobotEpisode]] = {}
    for episode in episodes:
        runs.setdefault(episode.run, []).append(episode)
    wall = sum(max(e.finished for e in items) - min(e.started for e in items) for items in runs.values())
    steps = sum(e.length for e in episodes)
    latencies = [x for e in episodes for x in e.latencies_ms]
    server = [x for e in episodes for x in e.server_ms]
    forwards = [x for e in episodes for x in e.target_forwards]
    speculative = [x for e in episodes for x in e.speculative]
    return {
        "episodes": len(episodes),
        "success_rate": sum(e.success for e in episodes) / len(episodes),
        "mean_task_success_rate": float(np.mean([t["success_rate"] for t in per_task.values()])),
        "tasks": per_task,
        "env_steps": steps,
        "requests": len(latencies),
        "wall_seconds": wall,
        "actions_per_second": steps / wall if wall > 0 else None,
        "runs": len(runs),
        "latency_ms": {**percentiles(latencies), "mean": float(np.mean(latencies)) if latencies else None},
        "server_ms": {**percentiles(server), "mean": float(np.mean(server)) if server else None},
        "batch_sizes": _histogram([x for e in episodes for x in e.batch_sizes]),
        "methods": _histogram([x for e in episodes for x in e.methods]),
        "speculative_fraction": float(np.mean(speculative)) if speculative else None,
        "target_forwards_per_request": float(np.mean(forwards)) if forwards else None,
    }


def format_summary(summary: dict) -> str:
    """[`summarize`]'s result as a Markdown table of the tasks' success and a few lines of serving figures."""

    def number(value, spec: str) -> str:
        return "-" if value is None else format(value, spec)

    lines = ["| task | episodes | success | mean length |", "|---|---:|---:|---:|"]
    for task, row in summary["tasks"].items():
        lines.append(f"| {task} | {row['episodes']} | {row['success_rate']:.0%} | {row['mean_episode_length']:.0f} |")
    lines.append(f"| **mean over tasks** | {summary['episodes']} | {summary['mean_task_success_rate']:.0%} | |")
    latency = summary["latency_ms"]
    lines += [
        "",
        f"actions/s: {number(summary['actions_per_second'], '.1f')} ({summary['env_steps']} env steps in "
        f"{summary['wall_seconds']:.1f} s over {summary['runs']} run(s), {summary.get('robots', '?')} robots)",
        f"request latency ms (client): p50 {number(latency['p50'], '.1f')}, p95 {number(latency['p95'], '.1f')}, "
        f"p99 {number(latency['p99'], '.1f')} over {summary['requests']} requests",
        "batch sizes (size: requests): " + ", ".join(f"{k}: {v}" for k, v in summary["batch_sizes"].items()),
        "methods (method: requests): " + ", ".join(f"{k}: {v}" for k, v in summary["methods"].items()),
    ]
    return "\n".join(lines)
