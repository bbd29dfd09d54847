"""Running a comparison: every method on every (task, seed), seed-major, methods in a fresh random order per seed,
in one or several worker processes; one resumable log per worker; the summary, table and plots at the end.

Every episode record carries the conditions it was timed under (workers, threads, torch's threads, the machine:
``run_folder.timing_conditions``); a folder continues only under its recorded conditions, or with
``restart_timing`` (``--restart-timing``), which keeps the finished episodes and lets only the episodes timed from
then on into the speed figures (``run_folder.resolve_timing``)."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import random
import signal
import threading
import time
from collections import Counter
from concurrent.futures import FIRST_EXCEPTION, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import torch

from ...policies import VLAPolicy
from ...policies.devices import Placement, dtype_name
from ...progress import progress_bar
from ...run_folder import (
    FolderTiming,
    RunRecord,
    claim_run_folder,
    fingerprint,
    read_jsonl,
    resolve_timing,
    timing_conditions,
    write_json_atomic,
    write_timing,
)
from ...speculative import DraftHead, DraftTreeConfig, check_bin_tolerance_range, make_acceptance_rule
from ..env import EnvConfig, MetaWorldEnv
from ..rollout import rollout
from ..seeds import BENCH_SEED_START
from .methods import ORACLE, CompareConfig, DecodingMethod
from .statistics import format_comparison, plot_comparison, summarize_comparison

logger = logging.getLogger(__name__)

LOG_PATTERN = "episodes.worker-*.jsonl"
RESTART_TIMING_FLAG = "--restart-timing"


class WorkerDiedError(RuntimeError):
    """A comparison worker process ended abruptly (killed, out of memory); the finished episodes are saved and
    rerunning the same command resumes."""


# ----------------------------------------------------------------------------- episodes
def _greedy_action_ids(policy: VLAPolicy, obs: dict) -> list[int]:
    """Greedy's action ids on ``obs``, leaving the policy's episode memory as it was."""
    memory = policy.previous_action_ids
    try:
        _, output = policy.predict_action(obs["image"], obs["instruction"], obs["state"], return_output=True)
    finally:
        policy.previous_action_ids = memory
    return output.sequences[0, -policy.config.action_tokens :].tolist()


def check_method_rule(method: DecodingMethod, policy: VLAPolicy) -> None:
    """Builds ``method``'s acceptance rule for ``policy``'s actions, so that a tolerance with the wrong number of
    dimensions (``r=4/4/0`` for 4-dimensional actions) is refused before anything runs.

    Raises:
        ValueError / TypeError naming the method.
    """
    if method.lossless:
        return
    try:
        make_acceptance_rule(action_layout=policy.action_layout, **method.rule_kwargs(policy.config.action_dim))
    except (ValueError, TypeError) as error:
        raise type(error)(f"decoding method {method.name!r}: {error}") from None


def run_method_episode(
    policy: VLAPolicy,
    env: MetaWorldEnv,
    seed: int,
    method: DecodingMethod,
    draft_head: DraftHead | None,
    tree: DraftTreeConfig | None = None,
) -> dict:
    """One episode of ``method`` from ``env.reset(seed)``: the record a comparison log holds (``tree``: the EAGLE-2
    tree of ``tree`` methods, default ``DraftTreeConfig()``)."""
    plan = method.plan(draft_head, policy.model.device.type, tree, policy.config.action_dim)
    action_dim = policy.config.action_tokens  # tokens per call (a chunk's, for a chunked policy)
    dims = policy.config.action_dim
    policy.reset()
    latencies, accept_counts, digest = [], Counter(), hashlib.sha256()
    target_forwards = new_tokens = 0
    accepted_by_position = [0] * action_dim  # calls whose token at each position was a drafted token accepted
    distances: list[int] = []
    reference_magnitudes: list[float] = []  # per token of a relaxed call: |greedy's action| there, policy's units

    def decide(rows: list[int], observations: list[dict]) -> list:
        nonlocal target_forwards, new_tokens
        obs = observations[0]
        drafts = {}
        if method.drafters == ORACLE:  # off the clock: greedy's own tokens, drafted (all right: the bound)
            drafts["draft_ids"] = torch.tensor([_greedy_action_ids(policy, obs)], device=policy.model.device)
        start = time.perf_counter()
        action, output = policy.predict_action(
            obs["image"], obs["instruction"], obs["state"], return_output=True, decoding=plan, **drafts
        )
        latencies.append(round(1000 * (time.perf_counter() - start), 3))
        action_ids = output.sequences[0, -action_dim:].tolist()
        stats = getattr(output, "speculation", None)
        if stats is None:  # plain greedy decoding: one target forward per token
            target_forwards, new_tokens = target_forwards + action_dim, new_tokens + action_dim
            accept_counts[1] += action_dim
        else:
            target_forwards, new_tokens = target_forwards + stats.num_target_forwards, new_tokens + stats.num_new_tokens
            accept_counts.update(stats.accept_lengths)
            for position, drafted in enumerate(stats.accepted_positions(action_dim)):
                accepted_by_position[position] += drafted
        if not method.lossless:  # off the clock: how far is this from greedy's action on the same observation?
            reference = _greedy_action_ids(policy, obs)
            distances.extend(abs(a - b) for a, b in zip(action_ids, reference))  # every token of the call, in order
            reference_actions = policy.actions_from_token_ids(np.asarray(reference).reshape(-1, dims))  # [H, D]
            reference_magnitudes.extend(round(abs(float(x)), 4) for x in np.ravel(reference_actions))
        digest.update(np.asarray(action_ids, np.int64).tobytes())
        return [policy.action_steps(action)]

    episode = rollout([env], [seed], decide)[0]
    return {
        "task": env.task,
        "seed": seed,
        "method": method.name,
        "success": episode.success,
        "length": episode.length,
        "latencies_ms": latencies,
        "target_forwards": target_forwards,
        "new_tokens": new_tokens,
        "accept_length_counts": {str(k): v for k, v in sorted(accept_counts.items())},
        "bin_distance_sum": sum(distances),
        "bin_distance_count": len(distances),
        "bin_distance_max": max(distances, default=0),
        "actions_digest": digest.hexdigest()[:16],
        # per action dimension (token i of a call is dimension i % action_dim)
        "bin_distance_sum_per_dim": [sum(distances[d::dims]) for d in range(dims)],
        "bin_distance_max_per_dim": [max(distances[d::dims], default=0) for d in range(dims)],
        # per token position of a call (action 0's dimensions, then action 1's, ...): calls that took a draft there
        "accepted_by_position": accepted_by_position,
        # relaxed methods, per token of every call: its bin distance from greedy's and the size of greedy's action
        # there (|value| in the policy's units), for the deviation by phase (large / small motions); bin widths in units
        **(
            {
                "bin_distances": distances,
                "reference_magnitudes": reference_magnitudes,
                "bin_widths": list(policy.action_layout.units.bin_widths),
            }
            if distances
            else {}
        ),
    }


def warm_up_compiled(
    policy: VLAPolicy,
    env: MetaWorldEnv,
    methods: list[DecodingMethod],
    draft_head: DraftHead | None,
    calls: int = 3,
    tree: DraftTreeConfig | None = None,
) -> None:
    """Runs every ``:compile`` method ``calls`` times on the first observation of ``env``'s task (off the clock, not
    logged), so that compilation (one graph per prompt length and verification width) never lands in a timed
    episode; the policy's episode memory is cleared afterwards."""
    compiled = [m for m in methods if m.compiled]
    if not compiled:
        return
    obs = env.reset(BENCH_SEED_START)  # a seed of the timing range, never one a comparison evaluates
    for method in compiled:
        plan = method.plan(draft_head, policy.model.device.type, tree, policy.config.action_dim)
        drafts = {}
        if method.drafters == ORACLE:  # its graphs are those of a prefill with drafts: compile them with right ones
            drafts["draft_ids"] = torch.tensor([_greedy_action_ids(policy, obs)], device=policy.model.device)
        policy.reset()
        for _ in range(calls):
            policy.predict_action(obs["image"], obs["instruction"], obs["state"], decoding=plan, **drafts)
    policy.reset()


def _run_shard(
    policy: VLAPolicy,
    draft_head: DraftHead | None,
    config: CompareConfig,
    pairs: list[tuple[str, int]],
    log_path: Path,
    done: set[tuple[str, int, str]],
    timing: dict,
    bar=None,
) -> None:
    """Runs every method not yet ``done`` on each (task, seed) of ``pairs``, seed by seed, appending to
    ``log_path`` records that carry ``timing`` (the conditions they were timed under)."""
    env_config = EnvConfig(policy.config.image_size, policy.config.camera, config.max_episode_steps)
    methods, tree = config.decoding_methods(), config.tree_config()
    env = None
    try:
        for task, seed in pairs:  # in order (seed-major): an env is made when the task changes
            todo = [m for m in methods if (task, seed, m.name) not in done]
            if not todo:
                continue
            if env is None or env.task != task:
                if env is not None:
                    env.close()
                env = MetaWorldEnv(task, env_config)
                warm_up_compiled(policy, env, methods, draft_head, tree=tree)
            random.Random(f"{config.order_seed}:{task}:{seed}").shuffle(todo)
            for method in todo:
                record = {**run_method_episode(policy, env, seed, method, draft_head, tree), "timing": timing}
                with log_path.open("a") as log:
                    log.write(json.dumps(record) + "\n")
                if bar is not None:
                    bar.update(1)
    finally:
        if env is not None:
            env.close()


def _exit_with_parent(poll_seconds: float = 1.0) -> None:
    """Ends this worker when the process that started it is gone (killed, crashed): an orphaned worker would go
    on appending to a folder that a new run may be resuming."""
    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_seconds)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="exit-with-parent").start()


def _worker_main(
    policy_dir: str,
    draft_head_dir: str | None,
    config: dict,
    pairs: list,
    log_path: str,
    done: list,
    placement: tuple[str, str] = ("cpu", "float32"),
) -> None:
    """Entry point of a worker process (spawned: loads its own policy and head onto ``placement``, the device and
    dtype of the parent's policy)."""
    from transformers.utils import logging as transformers_logging

    _exit_with_parent()
    transformers_logging.disable_progress_bar()  # a worker's weight loading draws no bars of its own
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    config = CompareConfig(**config)
    torch.set_num_threads(config.threads)
    timing = timing_conditions(config.workers, config.threads, torch.get_num_threads())  # as this worker times
    policy = VLAPolicy.from_pretrained(policy_dir)
    draft_head = None if draft_head_dir is None else DraftHead.from_pretrained(draft_head_dir).eval()
    if draft_head is not None:  # as saved, before the cast (the parent checked it too)
        policy.check_draft_head(draft_head)
    Placement.resolve(*placement).place_policy(policy, draft_head)
    _run_shard(policy, draft_head, config, [tuple(p) for p in pairs], Path(log_path), {tuple(d) for d in done}, timing)


def _count_log_lines(output_dir: Path) -> int:
    return sum(path.read_bytes().count(b"\n") for path in output_dir.glob(LOG_PATTERN))


def read_episode_logs(output_dir: Path, shown_as: Path | None = None) -> list[dict]:
    """Every episode record of a comparison folder (all workers' logs; messages name ``shown_as``, the folder the user
    gave, when ``output_dir`` is the claimed folder's ``/proc`` binding)."""
    return [
        record
        for path in sorted(output_dir.glob(LOG_PATTERN))
        for record in read_jsonl(path, shown_as=None if shown_as is None else shown_as / path.name)
    ]


def _peek_episode_logs(output_dir: Path) -> list[dict]:
    """The episode records of a folder read without repairing anything (a folder this process does not hold: a torn
    line may be another run's line being written)."""
    records = []
    for path in sorted(output_dir.glob(LOG_PATTERN)):
        for line in path.read_text().splitlines():
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return records


def compare_timing_conditions(config: CompareConfig) -> dict:
    """The conditions a comparison's episodes are timed under: workers set torch's threads to ``config.threads``;
    one worker decodes in this process, with torch's threads as they are (the CLI sets them to ``--threads``)."""
    torch_threads = config.threads if config.workers > 1 else torch.get_num_threads()
    return timing_conditions(config.workers, config.threads, torch_threads)


def _untimed_hint(output_dir: Path) -> dict | None:
    """What a folder written before episodes carried their timing conditions says about them: the workers and
    threads its last ``summary.json`` names (None: no summary)."""
    path = output_dir / "summary.json"
    try:
        settings = json.loads(path.read_text()).get("settings", {})
    except (OSError, json.JSONDecodeError):
        return None
    hint = {key: settings[key] for key in ("workers", "threads") if key in settings}
    return hint or None


def check_timing(output_dir: str | Path, config: CompareConfig, restart_timing: bool = False) -> None:
    """The timing refusal of [`run_comparison`] ahead of it, writing nothing (call it before loading models).

    Raises:
        TimingConditionsError: ``output_dir`` holds episodes timed under other conditions and ``restart_timing`` is
            False; the message names both.
    """
    output_dir = Path(output_dir)
    if output_dir.is_dir():
        records = _peek_episode_logs(output_dir)
        resolve_timing(
            output_dir,
            compare_timing_conditions(config),
            records,
            restart_timing,
            _untimed_hint(output_dir),
            RESTART_TIMING_FLAG,
            announce=False,
        )


def run_comparison(
    policy: VLAPolicy,
    config: CompareConfig,
    output_dir: str | Path,
    draft_head: DraftHead | None = None,
    policy_dir: str | None = None,
    draft_head_dir: str | None = None,
    overwrite: bool = False,
    progress: bool = True,
    restart_timing: bool = False,
) -> dict:
    """Runs (or resumes) a comparison into ``output_dir`` and writes its summary, table and plots.

    ``workers > 1`` spawns processes that load the policy (and head) from ``policy_dir`` (``draft_head_dir``)
    onto ``policy``'s device and dtype; with one worker everything runs in this process on ``policy``. The folder
    records the policy's device type and dtype: continuing it on another (whose actions may differ) is refused.
    ``restart_timing``: continue a folder timed under other conditions (workers, threads, machine), keeping its
    finished episodes; only episodes timed under this run's conditions enter the speed figures.

    Raises:
        ValueError: a method needs a draft head and none was given, or the head was made for another policy.
        FileExistsError: ``output_dir`` holds another comparison (other weights, env, seeds or methods).
        TimingConditionsError (a FileExistsError): ``output_dir``'s episodes were timed under other conditions
            and ``restart_timing`` is False.
        WorkerDiedError: a worker process died (killed, out of memory); the finished episodes are saved.
    """
    methods = config.decoding_methods()
    config.check_draft_head_given(draft_head is not None)
    if draft_head is not None:
        policy.check_draft_head(draft_head)
    if config.workers > 1 and policy_dir is None:
        raise ValueError("workers > 1 load the policy in each process: pass policy_dir (and draft_head_dir)")
    n_bins = policy.action_tokenizer.n_bins
    too_wide = [m.name for m in methods if m.widest_tolerance > n_bins - 1]
    check_bin_tolerance_range([m.widest_tolerance for m in methods], n_bins, f"methods {too_wide}")
    for method in methods:
        check_method_rule(method, policy)
    output_dir = Path(output_dir)
    env_config = EnvConfig(policy.config.image_size, policy.config.camera, config.max_episode_steps)
    settings = {
        "policy": policy.weights_fingerprint(),
        "draft_head": None if draft_head is None else fingerprint(draft_head),
        "env": asdict(env_config),
        "seed_start": config.seed_start,
        "methods": sorted(config.methods),
        "order_seed": config.order_seed,
        "device": policy.model.device.type,
        "dtype": dtype_name(policy.model.dtype),
    }
    if any("tree" in m.drafters.split("+") for m in methods):
        settings["tree"] = asdict(config.tree_config())  # what the tree methods drafted with
    with claim_run_folder(output_dir, RunRecord("compare", settings), overwrite) as run:
        output_dir = run.bound  # writes stay in the claimed folder, renamed or not
        records = read_episode_logs(output_dir, run.path)
        timing = resolve_timing(
            run.path,
            compare_timing_conditions(config),
            records,
            restart_timing,
            _untimed_hint(output_dir),
            RESTART_TIMING_FLAG,
        )
        write_timing(output_dir, timing)
        done = {(r["task"], r["seed"], r["method"]) for r in records}
        pairs = config.pairs()
        total = len(pairs) * len(methods)
        remaining = sum((t, s, m.name) not in done for t, s in pairs for m in methods)
        logger.info(
            "compare: %d episodes (%d methods x %d seeds), %d to run", total, len(methods), len(pairs), remaining
        )
        bar = progress_bar(total=total, initial=total - remaining, desc="compare", unit="episode", disable=not progress)
        if config.workers == 1:
            _run_shard(
                policy, draft_head, config, pairs, output_dir / "episodes.worker-0.jsonl", done, timing.conditions, bar
            )
        else:
            try:
                placement = (str(policy.model.device), dtype_name(policy.model.dtype))
                _run_in_workers(config, pairs, done, output_dir, policy_dir, draft_head_dir, bar, placement)
            except WorkerDiedError as error:
                bar.close()
                saved = len(
                    read_episode_logs(output_dir, run.path)
                )  # the workers are gone: a torn last line is dropped
                raise WorkerDiedError(
                    f"{error}. The other workers were stopped; the {saved} episodes finished so far are saved in "
                    f"{str(run.path)!r}: rerun the same command to resume (finished episodes are not run again)"
                ) from None
        bar.close()
        records = read_episode_logs(output_dir, run.path)
        wanted = {(t, s) for t, s in pairs}
        in_folder = len(records)
        records = [r for r in records if (r["task"], r["seed"]) in wanted and r["method"] in config.methods]
        if len(records) < in_folder:
            logger.warning(
                "summary.json and compare.md cover the %d episodes this run asked for (%d tasks x %d seeds x %d "
                "methods); the folder holds %d, and a run with more --episodes summarises them all",
                len(records),
                len(config.tasks),
                config.episodes_per_task,
                len(methods),
                in_folder,
            )
        summary = summarize_comparison(
            records, config.methods, timed=timing.timed, motion_threshold=config.motion_threshold
        )
        summary["settings"] = {
            **settings,
            "tasks": config.tasks,
            "episodes_per_task": config.episodes_per_task,
            "workers": config.workers,
            "threads": config.threads,
        }
        summary["timing"] = _timing_summary(timing, records)
        summary["action_dim"] = policy.config.action_dim  # names the token positions of a call
        write_json_atomic(output_dir / "summary.json", summary)
        (output_dir / "compare.md").write_text(format_comparison(summary) + "\n")
        plot_comparison(summary, output_dir)
        return summary


def _timing_summary(timing: FolderTiming, records: list[dict]) -> dict:
    """The conditions the speed figures are of, and how many of the summarised episodes were timed under them (the
    others count for success, forwards and deviation, not speed)."""
    timed = sum(timing.timed(r) for r in records)
    left_out = len(records) - timed
    if left_out:
        logger.warning(
            "speed figures: %d of %d episodes were timed under other conditions (or before conditions "
            "were recorded) and are left out of them; success and the other columns count them all",
            left_out,
            len(records),
        )
    return {"conditions": timing.conditions, "episodes_timed": timed, "episodes_timed_otherwise": left_out}


def _describe_exit(exitcode: int | None) -> str:
    if exitcode is None:
        return "exit status unknown"
    if exitcode < 0:
        try:
            return f"killed by signal {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    return f"exit code {exitcode}"


def _describe_dead_worker(processes: dict) -> str:
    """The worker that ended first, as far as its exit status tells: once one dies the pool stops the others with
    SIGTERM, so a worker that ended otherwise is named first."""
    ended = [(pid, p.exitcode) for pid, p in processes.items() if p.exitcode not in (None, 0)]
    first = [e for e in ended if e[1] != -signal.SIGTERM] or ended
    if not first:
        return "a compare worker process died (its exit status is unknown)"
    pid, exitcode = first[0]
    return f"a compare worker process (pid {pid}) died: {_describe_exit(exitcode)}"


def _run_in_workers(
    config: CompareConfig,
    pairs: list,
    done: set,
    output_dir: Path,
    policy_dir: str | None,
    draft_head_dir: str | None,
    bar,
    placement: tuple[str, str] = ("cpu", "float32"),
) -> None:
    """Splits ``pairs`` between ``config.workers`` spawned processes (a seed never spans two), each loading the
    policy onto ``placement`` (device, dtype), and follows their logs on ``bar``.

    Raises:
        WorkerDiedError: a worker process ended abruptly (naming its exit signal when known).
    """
    shards = [pairs[i :: config.workers] for i in range(config.workers)]
    bar_start, lines_at_start = bar.n, _count_log_lines(output_dir)
    with ProcessPoolExecutor(config.workers, mp_context=get_context("spawn")) as pool:
        pending = {
            pool.submit(
                _worker_main,
                policy_dir,
                draft_head_dir,
                asdict(config),
                shard,
                str(output_dir / f"episodes.worker-{i}.jsonl"),
                sorted(done),
                placement,
            )
            for i, shard in enumerate(shards)
            if shard
        }
        processes = dict(getattr(pool, "_processes", None) or {})  # the workers, for their exit status
        try:
            while pending:
                finished, pending = wait(pending, timeout=10, return_when=FIRST_EXCEPTION)
                for future in finished:
                    future.result()  # a worker's exception surfaces here
                # new finished lines only (workers write only wanted episodes; repairing a log with read_jsonl while
                # its worker appends would race); update() keeps the bar's redraw interval
                written = min(bar.total, bar_start + _count_log_lines(output_dir) - lines_at_start)
                if written > bar.n:
                    bar.update(written - bar.n)
        except BrokenProcessPool:  # a worker died; the pool stops the others
            processes.update(getattr(pool, "_processes", None) or {})
        else:
            return
    # read once the pool is shut down: its own join has collected every worker's exit status by then
    raise WorkerDiedError(_describe_dead_worker(processes))
