"""Paired side-by-side evaluation of decoding methods on Meta-World: ``hf-specvla compare``.

**Pairing.** Every method runs the same (task, seed) starts. For each seed, every method runs its episode before
the next seed starts, in a fresh random order per seed, in one process: each method's speed is measured next to
greedy's under the same load, and success is compared on identical starts. With ``workers > 1`` the seeds are
split between processes (one CPU thread each by default); a seed's methods always run in one worker, so every
timing ratio is taken within a worker.

**Methods** are named ``<drafters>[:<option>,...][:compile]`` (see ``methods``) with drafters such as
``greedy``, ``head`` (the draft head's chain), ``tree`` (its EAGLE-2 tree), ``prior`` (the episode's previous
actions), ``jacobi`` (the target's own guesses) and their ``+`` compositions, options the relaxed acceptance rule
(``r``, ``rl``, ``m``, ``gate``) and the chain length ``k``: e.g. ``greedy``, ``head:k=3``, ``tree:r=4``,
``prior+jacobi:r=4/4/4/0,m=1:compile``; or the presets ``exact`` and ``fast``. Greedy is always run: it is the
baseline every figure is paired with.

**Per method** (see [`summarize_comparison`]): success rate; the paired difference to greedy with a 95% bootstrap
interval over seeds and the discordant counts; mean episode length; median ms per policy call (one action, or one
chunk of actions for a chunked policy); the speed-up vs greedy as the **mean per call** (greedy's mean ms per call
over the paired episodes / the method's: the ratio of total decode times only when both make the same calls) with a
95% paired bootstrap interval over episodes, and as the **median of ratios** (median over seeds of the ratio of the two
episodes' median ms per call, the figure reported first), both also vs ``greedy:compile`` when it ran; target
forwards per call and per action (env step);
tokens per target forward; for relaxed methods the bin deviation from greedy's action *on the same observation*
(greedy decoded off the clock at every step), overall and per action dimension; for lossless methods how many
episodes were identical to greedy's.

**Folder**: ``run.json`` (policy and draft-head weights, env, seeds, methods), one ``episodes.worker-<i>.jsonl``
log per worker (a finished (task, seed, method) episode is never run again: resumable, and more tasks or episodes
continue a folder), ``timing.json`` (the conditions the speed figures are of), ``summary.json`` (with every timed
episode's ms per call, ``per_call_ms``), ``compare.md`` and PNG plots.

**Timing conditions**: each episode record names the conditions it was timed under (workers, threads, torch's
threads, the machine: OS, CPU model and count, torch version). A resume under other conditions is refused, naming
both, unless ``--restart-timing``: the finished episodes are kept for success and every other column, and only the
episodes timed under the new conditions enter the speed columns (the earlier timings stay in the logs). Episodes
logged before conditions were recorded are taken as timed under the conditions of the run that first continues the
folder, unless its ``summary.json`` names other workers or threads (refused the same way) or the timing restarts
(then they are left out of the speed columns).

**A worker that dies** (``kill -9``, out of memory) ends the run with a logged error naming its exit signal; the
finished episodes are saved and rerunning the same command resumes.
"""

from ..._lazy import lazy_exports

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        ".methods": (
            "COMPILED_GREEDY",
            "DEFAULT_METHODS",
            "DRAFTER_CHOICES",
            "GREEDY",
            "METHOD_KEYS",
            "PRESETS",
            "CompareConfig",
            "DecodingMethod",
            "parse_methods",
            "resolve_preset",
        ),
        ".runner": (
            "LOG_PATTERN",
            "RESTART_TIMING_FLAG",
            "WorkerDiedError",
            "check_method_rule",
            "check_timing",
            "read_episode_logs",
            "run_comparison",
            "run_method_episode",
        ),
        ".statistics": (
            "BOOTSTRAP_RESAMPLES",
            "PLOTS",
            "SPEEDUP_RESAMPLES",
            "format_comparison",
            "paired_difference",
            "paired_speedup",
            "per_call_latencies",
            "plot_comparison",
            "summarize_comparison",
        ),
    },
    globals(),
)
