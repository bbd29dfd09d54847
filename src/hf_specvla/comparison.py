"""Paired side-by-side evaluation of decoding methods on Meta-World: ``hf-specvla compare``.

**Pairing.** Every method runs the same (task, seed) starts. For each seed, every method runs its episode before
the next seed starts, in a fresh random order per seed, in one process: each method's speed is measured next to
greedy's under the same load, and success is compared on identical starts. With ``workers > 1`` the seeds are
split between processes (one CPU thread each by default); a seed's methods always run in one worker, so every
timing ratio is taken within a worker.

**Methods** are named ``<drafters>[:r=<bin tolerance>][,k=<chain length>]`` with drafters one of
``greedy``, ``head`` (the draft head's chain), ``tree`` (its EAGLE-2 tree), ``prior`` (the episode's previous
actions), ``prior+head``, ``prior+tree``: e.g. ``greedy``, ``head:k=3``, ``tree:r=4``, ``prior:r=2``,
``prior+tree:r=4``. Greedy is always run: it is the baseline every figure is paired with.

**Per method** (see [`summarize_comparison`]): success rate; the paired difference to greedy with a 95% bootstrap
interval over seeds and the discordant counts; mean episode length; median ms per policy call (one action, or one
chunk of actions for a chunked policy) and the speed-up vs greedy (median over seeds of the ratio of the two
episodes' median ms per call); target forwards per call and per action (env step);
tokens per target forward; for relaxed methods the bin deviation from greedy's action *on the same observation*
(greedy decoded off the clock at every step); for lossless methods how many episodes were identical to greedy's.

**Folder**: ``run.json`` (policy and draft-head weights, env, seeds, methods), one ``episodes.worker-<i>.jsonl``
log per worker (a finished (task, seed, method) episode is never run again: resumable, and more tasks or episodes
continue a folder), ``summary.json``, ``compare.md`` and PNG plots.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import random
import statistics
import threading
import time
from collections import Counter
from concurrent.futures import FIRST_EXCEPTION, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import torch

from .envs.metaworld import EnvConfig, MetaWorldEnv, resolve_tasks
from .envs.seeds import EVAL_SEED_START
from .policy import VLAPolicy
from .progress import progress_bar
from .run_folder import RunRecord, claim_run_folder, fingerprint, read_jsonl, write_json_atomic
from .speculative import DraftHead, DraftHeadDrafter, DraftTreeConfig

logger = logging.getLogger(__name__)

DRAFTER_CHOICES = ("greedy", "head", "tree", "prior", "prior+head", "prior+tree")
METHOD_KEYS = {"r": "bin tolerance (relaxed acceptance; 0 = lossless)", "k": "draft-head chain length (head only)"}
DEFAULT_METHODS = ("greedy", "head", "tree", "tree:r=4", "prior", "prior:r=2", "prior:r=4", "prior:r=8",
                   "prior+tree:r=4")  # fmt: skip
BOOTSTRAP_RESAMPLES = 10_000
LOG_PATTERN = "episodes.worker-*.jsonl"
PLOTS = ("speedup_vs_r.png", "success_vs_r.png", "accept_lengths.png")


# ----------------------------------------------------------------------------- methods
@dataclass(frozen=True)
class DecodingMethod:
    """One decoding method of a comparison (see module docstring for the names)."""

    drafters: str = "greedy"
    bin_tolerance: int = 0
    num_draft_tokens: int | None = None

    @classmethod
    def parse(cls, text: str) -> DecodingMethod:
        """``"prior+tree:r=4"`` -> DecodingMethod("prior+tree", 4).

        Raises:
            ValueError: naming the bad part and listing what is valid.
        """
        valid = f"valid: {', '.join(DRAFTER_CHOICES)}, optionally followed by :r=<int>[,k=<int>] (e.g. prior+tree:r=4)"
        drafters, _, options = text.strip().partition(":")
        if drafters not in DRAFTER_CHOICES:
            raise ValueError(f"unknown decoding method {text!r}: {drafters!r} is not a drafter; {valid}")
        values: dict[str, int] = {}
        for option in filter(None, options.split(",")):
            key, _, value = option.partition("=")
            if key in METHOD_KEYS and value.strip().lstrip("-").isdigit() and int(value) < 0:
                raise ValueError(f"decoding method {text!r}: {key} must be an integer >= 0 ({METHOD_KEYS[key]}), "
                                 f"got {int(value)}")  # fmt: skip
            if key not in METHOD_KEYS or not value.strip().isdigit():
                raise ValueError(
                    f"decoding method {text!r}: bad option {option!r}; options are "
                    + ", ".join(f"{k}=<int> ({v})" for k, v in METHOD_KEYS.items())
                )
            values[key] = int(value)
        if options and not values:
            raise ValueError(f"decoding method {text!r}: empty options after ':'; {valid}")
        method = cls(drafters, values.get("r", 0), values.get("k"))
        if method.drafters == "greedy" and (method.bin_tolerance or method.num_draft_tokens):
            raise ValueError(f"decoding method {text!r}: greedy drafts nothing, so it takes no r or k")
        if method.num_draft_tokens is not None and "head" not in method.drafters.split("+"):
            raise ValueError(f"decoding method {text!r}: k (a chain length) needs the head chain (head, prior+head)")
        if method.num_draft_tokens == 0:
            raise ValueError(f"decoding method {text!r}: k must be >= 1")
        return method

    @property
    def name(self) -> str:
        """Canonical name (``prior+tree:r=4``; ``r=0`` is left out)."""
        options = [f"r={self.bin_tolerance}"] if self.bin_tolerance else []
        options += [f"k={self.num_draft_tokens}"] if self.num_draft_tokens is not None else []
        return self.drafters + (":" + ",".join(options) if options else "")

    @property
    def uses_draft_head(self) -> bool:
        return any(part in ("head", "tree") for part in self.drafters.split("+"))

    @property
    def lossless(self) -> bool:
        return self.bin_tolerance == 0

    def generate_kwargs(self, draft_head: DraftHead | None) -> dict:
        """``predict_action`` options for this method."""
        parts = self.drafters.split("+")
        kwargs: dict = {}
        if self.uses_draft_head:
            if draft_head is None:
                raise ValueError(f"decoding method {self.name!r} needs a draft head (--draft-head)")
            if "tree" in parts:
                kwargs["assistant_model"] = DraftHeadDrafter(draft_head, tree=DraftTreeConfig())
            else:
                kwargs["assistant_model"] = draft_head
                if self.num_draft_tokens is not None:
                    kwargs["num_draft_tokens"] = self.num_draft_tokens
        if "prior" in parts:
            kwargs["action_prior"] = True
        if self.bin_tolerance:
            kwargs["bin_tolerance"] = self.bin_tolerance
        return kwargs


GREEDY = DecodingMethod()


def parse_methods(names: list[str]) -> list[DecodingMethod]:
    """Parsed, de-duplicated methods, greedy first (added when missing: it is the baseline)."""
    methods = [GREEDY]
    for name in names:
        method = DecodingMethod.parse(name)
        if method not in methods:
            methods.append(method)
    return methods


@dataclass
class CompareConfig:
    """What a comparison runs.

    Args:
        tasks: Meta-World tasks (names or suites).
        episodes_per_task: seeds per task (``seed_start``, +1, ...); every method runs every seed.
        methods: method names (see module docstring); greedy is added first when missing.
        seed_start: first seed (evaluation seeds start at 100000; the second fidelity range at 200000).
        max_episode_steps: step limit of an episode.
        workers: processes the seeds are split between.
        threads: torch CPU threads per worker.
        order_seed: seeds the random method order of every seed.
    """

    tasks: str | list[str] = "MT10"
    episodes_per_task: int = 20
    methods: list[str] | tuple[str, ...] = DEFAULT_METHODS
    seed_start: int = EVAL_SEED_START
    max_episode_steps: int = EnvConfig.max_episode_steps
    workers: int = 1
    threads: int = 1
    order_seed: int = 0

    def __post_init__(self):
        self.tasks = resolve_tasks(self.tasks)
        for name in ("episodes_per_task", "workers", "threads"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.seed_start < 0:
            raise ValueError(f"seed_start must be >= 0, got {self.seed_start}")
        self.methods = [m.name for m in parse_methods(list(self.methods))]

    def decoding_methods(self) -> list[DecodingMethod]:
        return [DecodingMethod.parse(name) for name in self.methods]

    def pairs(self) -> list[tuple[str, int]]:
        """Every (task, seed), seed-major (each task's first seed, then each task's second, ...): a run stopped
        part-way has covered every task alike, and workers that take every n-th pair share the load."""
        return [(task, self.seed_start + i) for i in range(self.episodes_per_task) for task in self.tasks]


# ----------------------------------------------------------------------------- episodes
def _greedy_action_ids(policy: VLAPolicy, obs: dict) -> list[int]:
    """Greedy's action ids on ``obs``, leaving the policy's episode memory as it was."""
    memory = policy.previous_action_ids
    try:
        _, output = policy.predict_action(obs["image"], obs["instruction"], obs["state"], return_output=True)
    finally:
        policy.previous_action_ids = memory
    return output.sequences[0, -policy.config.action_tokens :].tolist()


def run_method_episode(
    policy: VLAPolicy, env: MetaWorldEnv, seed: int, method: DecodingMethod, draft_head: DraftHead | None
) -> dict:
    """One episode of ``method`` from ``env.reset(seed)``: the record a comparison log holds."""
    kwargs = method.generate_kwargs(draft_head)
    action_dim = policy.config.action_tokens  # tokens per call (a chunk's, for a chunked policy)
    obs = env.reset(seed)
    policy.reset()
    latencies, accept_counts, digest = [], Counter(), hashlib.sha256()
    target_forwards = new_tokens = length = 0
    distances: list[int] = []
    while True:
        start = time.perf_counter()
        action, output = policy.predict_action(
            obs["image"], obs["instruction"], obs["state"], return_output=True, **kwargs
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
        if not method.lossless:  # off the clock: how far is this from greedy's action on the same observation?
            reference = _greedy_action_ids(policy, obs)
            distances.extend(abs(a - b) for a, b in zip(action_ids, reference))
        digest.update(np.asarray(action_ids, np.int64).tobytes())
        for step_action in policy.action_steps(action):
            obs, _, done, info = env.step(step_action)
            length += 1
            if done:
                break
        if done:
            break
    return {
        "task": env.task, "seed": seed, "method": method.name, "success": bool(info["success"]),
        "length": length, "latencies_ms": latencies, "target_forwards": target_forwards,
        "new_tokens": new_tokens, "accept_length_counts": {str(k): v for k, v in sorted(accept_counts.items())},
        "bin_distance_sum": sum(distances), "bin_distance_count": len(distances),
        "bin_distance_max": max(distances, default=0), "actions_digest": digest.hexdigest()[:16],
    }  # fmt: skip


def _run_shard(
    policy: VLAPolicy,
    draft_head: DraftHead | None,
    config: CompareConfig,
    pairs: list[tuple[str, int]],
    log_path: Path,
    done: set[tuple[str, int, str]],
    bar=None,
) -> None:
    """Runs every method not yet ``done`` on each (task, seed) of ``pairs``, seed by seed, appending to
    ``log_path``."""
    env_config = EnvConfig(policy.config.image_size, policy.config.camera, config.max_episode_steps)
    methods = config.decoding_methods()
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
            random.Random(f"{config.order_seed}:{task}:{seed}").shuffle(todo)
            for method in todo:
                record = run_method_episode(policy, env, seed, method, draft_head)
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


def _worker_main(policy_dir: str, draft_head_dir: str | None, config: dict, pairs: list, log_path: str,
                 done: list) -> None:  # fmt: skip
    """Entry point of a worker process (spawned: loads its own policy and head)."""
    from transformers.utils import logging as transformers_logging

    _exit_with_parent()
    transformers_logging.disable_progress_bar()  # a worker's weight loading draws no bars of its own
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    config = CompareConfig(**config)
    torch.set_num_threads(config.threads)
    policy = VLAPolicy.from_pretrained(policy_dir)
    draft_head = None if draft_head_dir is None else DraftHead.from_pretrained(draft_head_dir).eval()
    _run_shard(policy, draft_head, config, [tuple(p) for p in pairs], Path(log_path), {tuple(d) for d in done})


def _count_log_lines(output_dir: Path) -> int:
    return sum(path.read_bytes().count(b"\n") for path in output_dir.glob(LOG_PATTERN))


def read_episode_logs(output_dir: Path) -> list[dict]:
    """Every episode record of a comparison folder (all workers' logs)."""
    return [record for path in sorted(output_dir.glob(LOG_PATTERN)) for record in read_jsonl(path)]


def run_comparison(
    policy: VLAPolicy,
    config: CompareConfig,
    output_dir: str | Path,
    draft_head: DraftHead | None = None,
    policy_dir: str | None = None,
    draft_head_dir: str | None = None,
    overwrite: bool = False,
    progress: bool = True,
) -> dict:
    """Runs (or resumes) a comparison into ``output_dir`` and writes its summary, table and plots.

    ``workers > 1`` spawns processes that load the policy (and head) from ``policy_dir`` (``draft_head_dir``);
    with one worker everything runs in this process on ``policy``.

    Raises:
        ValueError: a method needs a draft head and none was given, or the head was made for another policy.
        FileExistsError: ``output_dir`` holds another comparison (other weights, env, seeds or methods).
    """
    methods = config.decoding_methods()
    needs_head = [m.name for m in methods if m.uses_draft_head]
    if needs_head and draft_head is None:
        raise ValueError(f"methods {needs_head} need a draft head (--draft-head)")
    if draft_head is not None:
        policy.check_draft_head(draft_head)
    if config.workers > 1 and policy_dir is None:
        raise ValueError("workers > 1 load the policy in each process: pass policy_dir (and draft_head_dir)")
    widest = policy.action_tokenizer.n_bins - 1
    too_wide = [m.name for m in methods if m.bin_tolerance > widest]
    if too_wide:
        raise ValueError(
            f"methods {too_wide}: r is wider than the action range (the policy's {widest + 1} bins are at most "
            f"{widest} apart; r={widest} already accepts any action token); use r in 0..{widest}"
        )
    output_dir = Path(output_dir)
    env_config = EnvConfig(policy.config.image_size, policy.config.camera, config.max_episode_steps)
    settings = {
        "policy": policy.weights_fingerprint(),
        "draft_head": None if draft_head is None else fingerprint(draft_head),
        "env": asdict(env_config), "seed_start": config.seed_start, "methods": sorted(config.methods),
        "order_seed": config.order_seed,
    }  # fmt: skip
    with claim_run_folder(output_dir, RunRecord("compare", settings), overwrite) as run:
        output_dir = run.bound  # writes stay in the claimed folder, renamed or not
        done = {(r["task"], r["seed"], r["method"]) for r in read_episode_logs(output_dir)}
        pairs = config.pairs()
        total = len(pairs) * len(methods)
        remaining = sum((t, s, m.name) not in done for t, s in pairs for m in methods)
        logger.info("compare: %d episodes (%d methods x %d seeds), %d to run", total, len(methods), len(pairs),
                    remaining)  # fmt: skip
        bar = progress_bar(total=total, initial=total - remaining, desc="compare", unit="episode", disable=not progress)
        if config.workers == 1:
            _run_shard(policy, draft_head, config, pairs, output_dir / "episodes.worker-0.jsonl", done, bar)
        else:
            _run_in_workers(config, pairs, done, output_dir, policy_dir, draft_head_dir, bar)
        bar.close()
        records = read_episode_logs(output_dir)
        wanted = {(t, s) for t, s in pairs}
        in_folder = len(records)
        records = [r for r in records if (r["task"], r["seed"]) in wanted and r["method"] in config.methods]
        if len(records) < in_folder:
            logger.warning(
                "summary.json and compare.md cover the %d episodes this run asked for (%d tasks x %d seeds x %d "
                "methods); the folder holds %d, and a run with more --episodes summarises them all",
                len(records), len(config.tasks), config.episodes_per_task, len(methods), in_folder,
            )  # fmt: skip
        summary = summarize_comparison(records, config.methods)
        summary["settings"] = {**settings, "tasks": config.tasks, "episodes_per_task": config.episodes_per_task,
                               "workers": config.workers, "threads": config.threads}  # fmt: skip
        write_json_atomic(output_dir / "summary.json", summary)
        (output_dir / "compare.md").write_text(format_comparison(summary) + "\n")
        plot_comparison(summary, output_dir)
        return summary


def _run_in_workers(config: CompareConfig, pairs: list, done: set, output_dir: Path, policy_dir: str | None,
                    draft_head_dir: str | None, bar) -> None:  # fmt: skip
    """Splits ``pairs`` between ``config.workers`` spawned processes (a seed never spans two) and follows their
    logs on ``bar``."""
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
            )  # fmt: skip
            for i, shard in enumerate(shards)
            if shard
        }
        while pending:
            finished, pending = wait(pending, timeout=10, return_when=FIRST_EXCEPTION)
            for future in finished:
                future.result()  # a worker's exception surfaces here
            # new finished lines only (workers write only wanted episodes; repairing a log with read_jsonl while
            # its worker appends would race); update() keeps the bar's redraw interval
            written = min(bar.total, bar_start + _count_log_lines(output_dir) - lines_at_start)
            if written > bar.n:
                bar.update(written - bar.n)


# ----------------------------------------------------------------------------- statistics
def paired_difference(
    method_success: list[bool], greedy_success: list[bool], resamples: int = BOOTSTRAP_RESAMPLES, seed: int = 0
) -> dict:
    """Success difference (method - greedy) over paired episodes, with a 95% percentile-bootstrap interval
    (pairs resampled with replacement) and the discordant counts.

    Returns:
        ``difference``, ``ci_low``, ``ci_high``, ``pairs``, ``greedy_only`` (greedy succeeded, the method failed),
        ``method_only`` (the reverse).
    """
    if len(method_success) != len(greedy_success) or not method_success:
        raise ValueError(
            f"paired outcomes must be two equally long, non-empty lists, got {len(method_success)} and "
            f"{len(greedy_success)}"
        )
    method = np.asarray(method_success, dtype=float)
    greedy = np.asarray(greedy_success, dtype=float)
    differences = method - greedy
    rng = np.random.default_rng(seed)
    means = differences[rng.integers(0, len(differences), (resamples, len(differences)))].mean(axis=1)
    low, high = np.percentile(means, [2.5, 97.5])
    return {
        "difference": float(differences.mean()), "ci_low": float(low), "ci_high": float(high),
        "pairs": len(differences), "greedy_only": int(((greedy == 1) & (method == 0)).sum()),
        "method_only": int(((method == 1) & (greedy == 0)).sum()),
    }  # fmt: skip


def summarize_comparison(records: list[dict], methods: list[str]) -> dict:
    """Per-method figures (see module docstring) from episode records; ``methods[0]`` must be greedy."""
    if not methods or methods[0] != GREEDY.name:
        raise ValueError(f"the first method must be greedy (the baseline), got {methods[:1]}")
    by_method: dict[str, dict[tuple[str, int], dict]] = {m: {} for m in methods}
    for record in records:
        if record["method"] in by_method:
            by_method[record["method"]][(record["task"], record["seed"])] = record
    greedy = by_method[GREEDY.name]
    summary: dict = {"methods": {}}
    for name in methods:
        episodes = by_method[name]
        if not episodes:
            continue
        method = DecodingMethod.parse(name)
        paired = sorted(key for key in episodes if key in greedy)
        latencies = [x for r in episodes.values() for x in r["latencies_ms"]]
        ratios = [
            statistics.median(greedy[key]["latencies_ms"]) / statistics.median(episodes[key]["latencies_ms"])
            for key in paired
        ]
        accept_counts: Counter = Counter()
        for record in episodes.values():
            accept_counts.update({int(k): v for k, v in record["accept_length_counts"].items()})
        forwards = sum(r["target_forwards"] for r in episodes.values())
        actions = sum(r["length"] for r in episodes.values())
        distance_count = sum(r["bin_distance_count"] for r in episodes.values())
        tasks = sorted({task for task, _ in episodes})
        row = {
            "drafters": method.drafters,
            "bin_tolerance": method.bin_tolerance,
            "episodes": len(episodes),
            "success_rate": statistics.mean(r["success"] for r in episodes.values()),
            "task_success_rates": {
                t: statistics.mean(r["success"] for (task, _), r in episodes.items() if task == t) for t in tasks
            },
            "mean_episode_length": statistics.mean(r["length"] for r in episodes.values()),
            "median_ms_per_call": statistics.median(latencies),  # one call decides one action, or one chunk
            "speedup": statistics.median(ratios) if ratios else None,
            "target_forwards_per_action": forwards / actions,  # per env step
            "target_forwards_per_call": forwards / len(latencies),
            "tokens_per_target_forward": sum(r["new_tokens"] for r in episodes.values()) / forwards,
            "accept_length_counts": {str(k): v for k, v in sorted(accept_counts.items())},
            "mean_bin_deviation": (
                sum(r["bin_distance_sum"] for r in episodes.values()) / distance_count if distance_count else 0.0
            ),  # fmt: skip
            "max_bin_deviation": max(r["bin_distance_max"] for r in episodes.values()),
            "identical_to_greedy": sum(episodes[k]["actions_digest"] == greedy[k]["actions_digest"] for k in paired),
        }
        if paired:
            row["vs_greedy"] = paired_difference(
                [episodes[k]["success"] for k in paired], [greedy[k]["success"] for k in paired]
            )
        summary["methods"][name] = row
    return summary


def format_comparison(summary: dict) -> str:
    """The markdown table of a comparison summary."""
    lines = [
        "| method | episodes | success | vs greedy (95% CI) | greedy-only / method-only | mean length "
        "| median ms/call | speed-up | target fwd/call | tokens/target fwd | bin dev. mean / max "
        "| identical to greedy |",
        "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---|---:|",
    ]
    for name, row in summary["methods"].items():
        paired = row.get("vs_greedy")
        if paired is None:
            versus, discordant = "-", "-"
        else:
            versus = f"{paired['difference']:+.1%} [{paired['ci_low']:+.1%}, {paired['ci_high']:+.1%}]"
            discordant = f"{paired['greedy_only']} / {paired['method_only']}"
        speedup = "-" if row["speedup"] is None else f"{row['speedup']:.2f}x"
        deviation = "-" if not row["bin_tolerance"] else f"{row['mean_bin_deviation']:.2f} / {row['max_bin_deviation']}"
        identical = f"{row['identical_to_greedy']}/{paired['pairs'] if paired else 0}"
        lines.append(
            f"| {name} | {row['episodes']} | {row['success_rate']:.1%} | {versus} | {discordant} "
            f"| {row['mean_episode_length']:.0f} | {row['median_ms_per_call']:.2f} | {speedup} "
            f"| {row['target_forwards_per_call']:.2f} | {row['tokens_per_target_forward']:.2f} | {deviation} "
            f"| {identical} |"
        )
    return "\n".join(lines)


# ----------------------------------------------------------------------------- plots
def _finish_plot(plt, figure, axis, baseline: float, ylabel: str, title: str, path: Path) -> None:
    """Greedy's level as a grey line, labels, legend; saves and closes the figure."""
    axis.axhline(baseline, color="grey", linewidth=0.8)
    axis.set(xlabel="bin tolerance r", ylabel=ylabel, title=title)
    axis.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def plot_comparison(summary: dict, output_dir: str | Path) -> list[Path]:
    """Writes the PNG plots of [`PLOTS`]: speed-up vs r and success difference vs r (95% CI) per drafter family,
    and each method's histogram of tokens per target forward."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    output_dir = Path(output_dir)
    rows = summary["methods"]
    families: dict[str, list[tuple[int, dict]]] = {}
    for row in rows.values():
        families.setdefault(row["drafters"], []).append((row["bin_tolerance"], row))
    paths = [output_dir / name for name in PLOTS]

    figure, axis = plt.subplots(figsize=(6, 4))
    for family, points in families.items():
        points = sorted((r, row["speedup"]) for r, row in points if row["speedup"] is not None)
        axis.plot([p[0] for p in points], [p[1] for p in points], marker="o", label=family)
    _finish_plot(plt, figure, axis, 1.0, "speed-up vs greedy (per action)", "Speed-up", paths[0])

    figure, axis = plt.subplots(figsize=(6, 4))
    for offset, (family, points) in enumerate(families.items()):
        points = sorted((r, row["vs_greedy"]) for r, row in points if "vs_greedy" in row)
        x = [p[0] + 0.08 * offset for p in points]
        y = [100 * p[1]["difference"] for p in points]
        errors = [[100 * (p[1]["difference"] - p[1]["ci_low"]) for p in points],
                  [100 * (p[1]["ci_high"] - p[1]["difference"]) for p in points]]  # fmt: skip
        axis.errorbar(x, y, yerr=errors, marker="o", capsize=3, label=family)
    _finish_plot(plt, figure, axis, 0.0, "success - greedy's (points, 95% CI)", "Success, paired", paths[1])

    columns = min(3, len(rows))
    lines = -(-len(rows) // columns)
    figure, axes = plt.subplots(lines, columns, figsize=(3.2 * columns, 2.4 * lines), squeeze=False)
    for axis, (name, row) in zip(axes.flat, rows.items()):
        counts = {int(k): v for k, v in row["accept_length_counts"].items()}
        total = sum(counts.values())
        axis.bar(list(counts), [v / total for v in counts.values()])
        axis.set_title(name, fontsize=9)
        axis.set_xlabel("tokens per target forward", fontsize=8)
    for axis in list(axes.flat)[len(rows) :]:
        axis.set_visible(False)
    figure.tight_layout()
    figure.savefig(paths[2], dpi=120)
    plt.close(figure)
    return paths
