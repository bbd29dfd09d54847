"""Speed benchmark: plain greedy vs speculative decoding, in one process, interleaved.

For every repeat and prompt, the methods run in a freshly shuffled order, so drift in machine load hits them
alike. Reported per method: median per-action latency, speed-up = median(greedy) / median(method), mean accept
length (tokens per target forward), where the time goes (target forwards / draft forwards / the rest), and how
far the actions moved from greedy's (mean and max bin distance; 0 for lossless methods).
"""

from __future__ import annotations

import random
import statistics
import time
from dataclasses import dataclass, field

import torch

from ..actions.tokenizer import ActionTokenizer
from ..progress import heartbeat, progress_bar
from ..speculative import ActionPriorDrafter, SpeculationStats


@dataclass
class Method:
    """One decoding configuration: a name and the extra ``generate`` keyword arguments it uses."""

    name: str
    generate_kwargs: dict = field(default_factory=dict)


@dataclass
class MethodResult:
    name: str
    latencies: list[float] = field(default_factory=list)
    stats: SpeculationStats | None = None
    bin_distances: list[int] = field(default_factory=list)

    @property
    def median_latency(self) -> float:
        return statistics.median(self.latencies)


#: the first transformers release whose own assisted generation runs on a static cache (its compiled peer)
ASSISTED_STATIC_SINCE = "5.24"


def assisted_generation_compiles() -> bool:
    """Whether the installed transformers runs its own assisted generation on a static cache (>= 5.24)."""
    import transformers
    from packaging.version import Version

    return Version(transformers.__version__).release >= Version(ASSISTED_STATIC_SINCE).release


def speculative_methods(
    draft_head,
    chain_lengths=(2, 4, 6),
    bin_tolerances=(1, 2, 4),
    relaxed_chain=6,
    compiled_on: str | None = None,
    assistant_model=None,
) -> list[Method]:
    """Greedy, strict chains of several lengths k, Jacobi drafts (the target's own guesses, no model), and relaxed
    acceptance at several r (chain ``relaxed_chain``). With ``compiled_on`` (a device type) also transformers'
    compiled greedy (``greedy:compile``) and the strict methods compiled (``:compile``: a static cache, compiled
    verification). With ``assistant_model`` (a small transformers model sharing the target's vocabulary) also
    transformers' own assisted generation, the peer: eagerly, and compiled on a static cache where the installed
    release supports it ([`assisted_generation_compiles`])."""
    from ..speculative import JacobiDrafter

    methods = [Method("greedy")]
    if assistant_model is not None:
        methods.append(Method("assisted (transformers)", dict(assistant_model=assistant_model)))
    for k in chain_lengths:
        methods.append(Method(f"spec k={k} r=0", dict(assistant_model=draft_head, num_draft_tokens=k)))
    methods.append(Method("jacobi r=0", dict(assistant_model=JacobiDrafter())))
    for r in bin_tolerances:
        kwargs = dict(assistant_model=draft_head, num_draft_tokens=relaxed_chain, bin_tolerance=r)
        methods.append(Method(f"spec k={relaxed_chain} r={r}", kwargs))
    if compiled_on is None:
        return methods
    from ..speculative import compiled_decoding_kwargs

    compiled = compiled_decoding_kwargs(compiled_on)
    methods.insert(1, Method("greedy:compile", dict(compiled)))
    for k in chain_lengths:
        methods.append(
            Method(f"spec k={k} r=0:compile", dict(assistant_model=draft_head, num_draft_tokens=k, **compiled))
        )
    methods.append(Method("jacobi r=0:compile", dict(assistant_model=JacobiDrafter(), **compiled)))
    if assistant_model is not None and assisted_generation_compiles():
        methods.append(Method("assisted (transformers):compile", dict(assistant_model=assistant_model, **compiled)))
    return methods


@torch.no_grad()
def run_benchmark(
    target,
    prompts: list[dict],
    methods: list[Method],
    max_new_tokens: int,
    action_tokenizer: ActionTokenizer,
    repeats: int = 3,
    warmup: int = 2,
    seed: int = 0,
    progress: bool = True,
) -> list[MethodResult]:
    """Times every method on every prompt ``repeats`` times, interleaved. The first method is the baseline."""
    results = {m.name: MethodResult(m.name) for m in methods}
    base = dict(max_new_tokens=max_new_tokens, min_new_tokens=max_new_tokens, do_sample=False)
    by_length = {prompt["input_ids"].shape[1]: prompt for prompt in prompts}  # compiled graphs: one per prompt length
    warm_up = prompts[:warmup] + [p for p in by_length.values() if not any(p is q for q in prompts[:warmup])]
    with heartbeat("warm-up (compiles the :compile rows, off the clock)") as beat:
        for index, method in enumerate(methods):  # warm-up: allocator, lazy init, every prompt length's compiled graphs
            beat.begin(f"{method.name} ({index + 1}/{len(methods)})")
            for prompt in warm_up:
                target.generate(**prompt, **base, **method.generate_kwargs)
    rng = random.Random(seed)
    order = list(methods)
    bar = progress_bar(total=repeats * len(prompts), desc="benchmark", disable=not progress)  # a tick a prompt
    with bar:
        for _ in range(repeats):
            for prompt in prompts:
                rng.shuffle(order)
                outputs = {}
                for method in order:
                    start = time.perf_counter()
                    out = target.generate(**prompt, **base, **method.generate_kwargs, return_dict_in_generate=True)
                    results[method.name].latencies.append(time.perf_counter() - start)
                    outputs[method.name] = out.sequences[:, -max_new_tokens:]
                    spec = getattr(out, "speculation", None)
                    if spec is not None:
                        prev = results[method.name].stats
                        results[method.name].stats = spec if prev is None else prev.merge(spec)
                reference = outputs[methods[0].name]
                for name, tokens in outputs.items():
                    distance = action_tokenizer.bin_distance(tokens, reference)
                    results[name].bin_distances.extend(distance.flatten().tolist())
                bar.update(1)
    return [results[m.name] for m in methods]


def fastest_greedy(results: list) -> object:
    """The fastest greedy row (eager ``greedy`` or transformers' ``greedy:compile``): what speed-ups are quoted
    against; the first row when there is no greedy row."""
    rows = [r for r in results if r.name.split(":")[0] == "greedy"] or results[:1]
    return min(rows, key=lambda r: r.median_latency)


def format_report(results: list[MethodResult]) -> str:
    """Markdown table of [`run_benchmark`] results: speed-ups against the fastest greedy row and the first row (eager
    greedy)."""
    eager, fastest = results[0], fastest_greedy(results)
    lines = [
        f"| method | median ms/action | speed-up vs {fastest.name} | vs {eager.name} | mean accept length | target / "
        "draft / other time | bin distance to greedy (mean / max) |",
        "|---|---:|---:|---:|---:|---|---|",
    ]
    for result in results:
        stats = result.stats
        if stats is None and result.name.split(":")[0] != "greedy":  # transformers' own assisted generation
            accept, split = "-", "-"  # it reports no statistics
        elif stats is None:
            accept, split = "1.00", "100% / 0% / 0%"
        else:
            total = stats.total_seconds or 1.0
            target_share, draft_share = stats.target_seconds / total, stats.draft_seconds / total
            accept = f"{stats.mean_accept_length:.2f}"
            split = f"{target_share:.0%} / {draft_share:.0%} / {1 - target_share - draft_share:.0%}"
        distances = result.bin_distances or [0]
        lines.append(
            f"| {result.name} | {1000 * result.median_latency:.2f} | "
            f"{fastest.median_latency / result.median_latency:.2f}x | "
            f"{eager.median_latency / result.median_latency:.2f}x | "
            f"{accept} | {split} | {statistics.mean(distances):.2f} / {max(distances)} |"
        )
    return "\n".join(lines)


# ----------------------------------------------------------------------------- the verdict
@dataclass(frozen=True)
class VerdictRow:
    """One row of the demo's verdict, read from one measured method.

    Attributes:
        role: what a newcomer calls it (``"compiled greedy"``, ``"`exact`"``, ``"relaxed r=1"``).
        method: the measured row it reads (its name in the full tables).
        median_latency: seconds per action (median over calls).
        target_forwards: target forwards per action, the mean over calls.
        identical: actions whose every token is eager greedy's; ``actions``: actions compared.
    """

    role: str
    method: str
    median_latency: float
    target_forwards: float
    identical: int
    actions: int

    def __post_init__(self):
        if not 0 <= self.identical <= self.actions or self.actions < 1:
            raise ValueError(f"{self.method}: {self.identical} identical of {self.actions} actions (need 0..actions)")

    @property
    def lossless(self) -> bool:
        return self.identical == self.actions


#: The verdict's rows: (role, the measured rows it may read as (name pattern, what it is); the first found is read).
#: The episode table has them all (the previous action drafts there); the held-out scene table stands in for it
#: with ``--episodes 0`` (Jacobi drafts and the head's chains, no previous action).
VERDICT_ROLES = (
    ("greedy", ((r"greedy", "plain greedy decoding, eager"),)),
    ("compiled greedy", ((r"greedy:compile", "transformers' static cache + CompileConfig"),)),
    (
        "`exact`",
        (
            (r"prior\+jacobi r=0:compile", "previous action + Jacobi drafts, compiled, r=0"),
            (r"prior\+jacobi r=0", "previous action + Jacobi drafts, eager, r=0"),
            (r"jacobi r=0:compile", "Jacobi drafts, compiled, r=0 (no previous action here)"),
            (r"jacobi r=0", "Jacobi drafts, eager, r=0 (no previous action here)"),
        ),
    ),
    (
        "draft head",
        (
            (r"prior\+jacobi\+tree r=0:compile", "`exact` + the draft head's EAGLE-2 tree, compiled"),
            (r"prior\+jacobi\+tree r=0", "`exact` + the draft head's EAGLE-2 tree, eager"),
            (r"spec k=\d+ r=0:compile", "the draft head's chain, compiled, r=0"),
            (r"spec k=\d+ r=0", "the draft head's chain, eager, r=0"),
        ),
    ),
    (
        "relaxed",
        (
            (r"prior\+jacobi r=[1-9]\d*(:compile)?", "`exact` accepting draft tokens up to r bins off"),
            (r"spec k=\d+ r=[1-9]\d*(:compile)?", "the head's chain accepting tokens up to r bins off"),
        ),
    ),
)


def verdict_rows(results: list, action_dim: int) -> list[tuple[VerdictRow, str]]:
    """(row, what it is) for each [`VERDICT_ROLES`] role found in ``results`` ([`run_episode_benchmark`]'s or
    [`run_benchmark`]'s; the first result is eager greedy, what "identical" compares with)."""
    import re

    rows = []
    for role, candidates in VERDICT_ROLES:
        found = next(
            ((r, what) for pattern, what in candidates for r in results if re.fullmatch(pattern, r.name)), None
        )
        if found is None or any(row.method == found[0].name for row, _ in rows):
            continue
        result, what = found
        tolerance = re.search(r"r=(\d+)", result.name)
        if role == "relaxed" and tolerance:
            role = f"relaxed r={tolerance.group(1)}"
        distances = result.bin_distances or [0] * action_dim
        actions = [distances[i : i + action_dim] for i in range(0, len(distances), action_dim)]
        identical = sum(not any(action) for action in actions)
        rows.append(
            (
                VerdictRow(
                    role,
                    result.name,
                    result.median_latency,
                    _forwards_per_action(result, action_dim),
                    identical,
                    len(actions),
                ),
                what,
            )
        )
    return rows


def _forwards_per_action(result, action_dim: int) -> float:
    if isinstance(result, EpisodeMethodResult):
        return statistics.mean(result.target_forwards)
    if result.stats is None:  # greedy: one forward a token
        return float(action_dim)
    return result.stats.num_target_forwards / len(result.latencies)


def format_verdict(results: list, action_dim: int) -> str:
    """The demo's last screen: the rows a newcomer needs (greedy, compiled greedy, `exact`, the draft head, a relaxed
    setting; those measured) as a table against the fastest greedy row, then one sentence saying what it means, every
    figure read from ``results`` (see [`verdict_rows`])."""
    rows = verdict_rows(results, action_dim)
    if not rows:
        return "No verdict: none of the verdict's rows (greedy, greedy:compile, `exact`, ...) was measured."
    greedy = [row for row, _ in rows if row.method.split(":")[0] == "greedy"]
    baseline = min(greedy or [rows[0][0]], key=lambda row: row.median_latency)
    lines = [
        f"| | method | what it is | ms/action | speed-up vs {baseline.role} | target forwards/action | identical to "
        "greedy |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    for row, what in rows:
        lines.append(
            f"| {row.role} | {row.method} | {what} | {1000 * row.median_latency:.1f} | "
            f"{baseline.median_latency / row.median_latency:.2f}x | {row.target_forwards:.2f} | "
            f"{row.identical}/{row.actions} |"
        )
    return "\n".join(lines) + "\n\n" + verdict_sentence([row for row, _ in rows], baseline)


def verdict_sentence(rows: list[VerdictRow], baseline: VerdictRow) -> str:
    """One sentence from the verdict's rows: the fastest lossless speculative row against ``baseline`` (faster or
    not, in how many target forwards), then whether the relaxed row buys speed with changed actions."""
    speculative = [row for row in rows if row.method.split(":")[0] != "greedy"]
    lossless = [row for row in speculative if row.lossless]
    best = min(lossless, key=lambda row: row.median_latency) if lossless else None
    parts = []
    if best is not None:
        speedup = baseline.median_latency / best.median_latency
        forwards = f"{best.target_forwards:.1f} target forwards per action instead of {baseline.target_forwards:.0f}"
        if speedup > 1:
            parts.append(
                f"{best.role} ({best.method}) gives greedy's actions, all {best.actions}, {speedup:.2f}x as "
                f"fast as {baseline.role} ({forwards})"
            )
        else:
            parts.append(
                f"no lossless setting beat {baseline.role} on this machine: the best, {best.role} "
                f"({best.method}), gives greedy's actions at {speedup:.2f}x its speed "
                f"({forwards})"
            )
    elif speculative:
        parts.append(
            f"no speculative row gave all of greedy's actions here (a lossless row should: see the full "
            f"tables), against {baseline.role}"
        )
    else:
        parts.append(f"only greedy rows were measured: the fastest is {baseline.role}")
    for row in [row for row in speculative if row.role.startswith("relaxed")][:1]:
        speedup, changed = baseline.median_latency / row.median_latency, 1 - row.identical / row.actions
        if not changed:
            parts.append(f"{row.role} changed no action here ({speedup:.2f}x)")
        elif best is None or row.median_latency < best.median_latency:
            parts.append(
                f"{row.role} is faster still ({speedup:.2f}x) but changes {changed:.0%} of the actions: "
                f"fidelity traded for speed"
            )
        else:
            parts.append(
                f"{row.role} changes {changed:.0%} of the actions and is no faster ({speedup:.2f}x): keep {best.role}"
            )
    text = "; ".join(parts)
    return f"In one sentence: {text[0].lower()}{text[1:]}."


# ----------------------------------------------------------------------------- episodes (previous actions are real)
@dataclass
class EpisodeMethod:
    """One decoding configuration for [`run_episode_benchmark`]: ``generate`` options, and whether the episode's
    previous actions are drafted ([`ActionPriorDrafter`], verified inside the prefill)."""

    name: str
    generate_kwargs: dict = field(default_factory=dict)
    action_prior: bool = False


@dataclass
class EpisodeMethodResult:
    """Per-action measurements of one method over every replayed step."""

    name: str
    latencies: list[float] = field(default_factory=list)
    target_forwards: list[int] = field(default_factory=list)
    draft_forwards: list[int] = field(default_factory=list)
    new_tokens: list[int] = field(default_factory=list)
    bin_distances: list[int] = field(default_factory=list)
    target_seconds: float = 0.0
    draft_seconds: float = 0.0
    total_seconds: float = 0.0
    split_seconds: dict[str, float] = field(default_factory=dict)  # where the time goes, summed over calls
    guesses: SpeculationStats = field(default_factory=SpeculationStats)  # the Jacobi guesses' counts, summed
    accepted_by_position: list[int] = field(default_factory=list)  # per token position: calls that took a draft

    @property
    def median_latency(self) -> float:
        return statistics.median(self.latencies)


#: where a policy call's time goes (see [`ForwardClock`]): the image encoder, the target's first forward (the
#: prefill, drafts verified inside it included), its later forwards (verifications, or greedy's decoding steps),
#: drafting (the drafter's own work: head forwards, tree building), and the rest (preprocessing, generate's
#: preparation, the loop's own steps: acceptance, cache surgery, logits processors, stopping criteria)
TIME_SPLIT = ("vision", "prefill", "later forwards", "drafting", "rest")


class ForwardClock:
    """Wall time spent inside a VLM's image encoder and language model during one call, from forward hooks.

    A compiled model call (transformers' ``get_compiled_call``: its compiled greedy decoding, our compiled
    verifications) runs the hooks only while it is traced, so the clock also times every call of the compiled
    function from outside (``model.get_compiled_call`` is wrapped on this instance, and so is the engine's compiled
    round whose graph holds the acceptance too, ``speculative.CALL_WRAPPER_ATTRIBUTE``); such a call counts
    as a language forward (it is the whole model call: the language model and its head, and that acceptance). The
    engine's compiled image encoder (``speculative.vision``) is timed from outside too, as vision.

    Args:
        model: a Llava-style model (``model.model.vision_tower`` / ``.language_model``, or the same on ``model``).
    """

    def __init__(self, model):
        inner = getattr(model, "model", model)
        self.vision_tower = getattr(inner, "vision_tower", None)
        self.language_model = getattr(inner, "language_model", None)
        if self.language_model is None:
            raise ValueError(f"{type(model).__name__} has no language_model to time")
        self.reset()
        self._starts: dict[str, float] = {}
        self._inside_compiled_encoder = False
        for name, module in (("vision", self.vision_tower), ("language", self.language_model)):
            if module is not None:
                module.register_forward_pre_hook(self._enter(name))
                module.register_forward_hook(self._leave(name))
        self._time_compiled_calls(model)

    def _time_compiled_calls(self, model) -> None:
        from ..speculative import CALL_WRAPPER_ATTRIBUTE, ENCODER_WRAPPER_ATTRIBUTE

        original = model.get_compiled_call

        def timed(compiled):
            def timed_call(*args, **kwargs):
                start = time.perf_counter()
                output = compiled(*args, **kwargs)
                self.language_seconds.append(time.perf_counter() - start)
                return output

            return timed_call

        def timed_encoder(compiled):
            def timed_encoding(*args, **kwargs):
                start, self._inside_compiled_encoder = time.perf_counter(), True
                try:
                    return compiled(*args, **kwargs)
                finally:
                    self._inside_compiled_encoder = False
                    self.vision_seconds += time.perf_counter() - start

            return timed_encoding

        model.get_compiled_call = lambda compile_config: timed(original(compile_config))
        setattr(model, CALL_WRAPPER_ATTRIBUTE, timed)  # the engine's own compiled rounds (forward + acceptance)
        setattr(model, ENCODER_WRAPPER_ATTRIBUTE, timed_encoder)  # ... and its compiled image encoder

    def reset(self) -> None:
        self.vision_seconds, self.language_seconds = 0.0, []  # one entry per language-model forward

    def _timed_from_outside(self) -> bool:
        """Inside a compiled call (or the compiled image encoder, whose graph breaks may run a hook): timed from
        outside it."""
        return torch.compiler.is_compiling() or self._inside_compiled_encoder

    def _enter(self, name: str):
        def hook(module, args):
            if not self._timed_from_outside():
                self._starts[name] = time.perf_counter()

        return hook

    def _leave(self, name: str):
        def hook(module, args, output):
            if self._timed_from_outside():
                return
            elapsed = time.perf_counter() - self._starts.pop(name)
            if name == "vision":
                self.vision_seconds += elapsed
            else:
                self.language_seconds.append(elapsed)

        return hook

    def split(self, call_seconds: float, draft_seconds: float) -> dict[str, float]:
        """One call's seconds per [`TIME_SPLIT`] part (``rest`` = the call's wall time minus the others)."""
        prefill = self.language_seconds[0] if self.language_seconds else 0.0
        later = sum(self.language_seconds[1:])
        parts = {"vision": self.vision_seconds, "prefill": prefill, "later forwards": later, "drafting": draft_seconds}
        parts["rest"] = call_seconds - sum(parts.values())
        return parts


def run_episode_benchmark(
    act,
    episodes: list[list],
    methods: list[EpisodeMethod],
    action_dim: int,
    repeats: int = 1,
    warmup: int = 3,
    seed: int = 0,
    progress: bool = True,
    clock: ForwardClock | None = None,
) -> list[EpisodeMethodResult]:
    """Replays observation sequences with every method, interleaved; the first method is the baseline.

    Args:
        act: ``act(observation, previous_action_ids, action_prior, **generate_kwargs) -> (action_ids, output)``;
            ``previous_action_ids`` is this method's own episode memory (its earlier actions in this episode,
            oldest first), so each method drafts from the actions it produced itself.
        episodes: lists of observations (whatever ``act`` reads).
        clock: a [`ForwardClock`] on the target: each result's ``split_seconds`` then says where the time went.
    At every step the methods run in a fresh random order on the same observation, so machine-load drift hits
    them alike; bin distances compare each action token with the baseline's at the same step.
    """
    results = {m.name: EpisodeMethodResult(m.name, accepted_by_position=[0] * action_dim) for m in methods}
    with heartbeat("warm-up (compiles the :compile rows, off the clock)") as beat:
        for number, method in enumerate(methods):  # warm-up: allocator, lazy init, both code paths, compiled graphs
            beat.begin(f"{method.name} ({number + 1}/{len(methods)})")
            for index, episode in enumerate(episodes):
                history: list[list[int]] = []
                for observation in episode[: warmup if index == 0 else 1]:
                    ids, _ = act(observation, history, method.action_prior, **method.generate_kwargs)
                    history = [*history, ids][-ActionPriorDrafter.history_length :]
    rng = random.Random(seed)
    order = list(methods)
    total = repeats * sum(len(e) for e in episodes)
    with progress_bar(total=total, desc="episode benchmark", disable=not progress, mininterval=10) as bar:
        for _ in range(repeats):
            for episode in episodes:
                histories: dict[str, list[list[int]]] = {m.name: [] for m in methods}
                for observation in episode:
                    rng.shuffle(order)
                    actions = {}
                    for method in order:
                        if clock is not None:
                            clock.reset()
                        start = time.perf_counter()
                        ids, output = act(
                            observation, histories[method.name], method.action_prior, **method.generate_kwargs
                        )
                        elapsed = time.perf_counter() - start
                        result = results[method.name]
                        result.latencies.append(elapsed)
                        spec = getattr(output, "speculation", None)
                        result.target_forwards.append(spec.num_target_forwards if spec else action_dim)
                        result.draft_forwards.append(spec.num_draft_forwards if spec else 0)
                        result.new_tokens.append(spec.num_new_tokens if spec else action_dim)
                        taken = spec.accepted_positions(action_dim) if spec else [False] * action_dim
                        result.accepted_by_position = [n + t for n, t in zip(result.accepted_by_position, taken)]
                        if spec is not None:
                            result.guesses.add_guesses(spec)
                            result.target_seconds += spec.target_seconds
                            result.draft_seconds += spec.draft_seconds
                            result.total_seconds += spec.total_seconds
                        if clock is not None:
                            for part, seconds in clock.split(elapsed, spec.draft_seconds if spec else 0.0).items():
                                result.split_seconds[part] = result.split_seconds.get(part, 0.0) + seconds
                        histories[method.name] = [*histories[method.name], ids][-ActionPriorDrafter.history_length :]
                        actions[method.name] = ids
                    reference = actions[methods[0].name]
                    for name, ids in actions.items():
                        results[name].bin_distances.extend(abs(a - b) for a, b in zip(ids, reference))
                    bar.update(1)
    return [results[m.name] for m in methods]


def format_jacobi_report(results: list[EpisodeMethodResult]) -> str:
    """Markdown table: how often the methods' Jacobi guesses were right, by position after the bonus token (empty
    when no method drafted Jacobi tails)."""
    rows = [r for r in results if r.guesses.jacobi_guesses_per_position]
    if not rows:
        return ""
    width = max(len(r.guesses.jacobi_guesses_per_position) for r in rows)
    lines = [
        "Jacobi guesses right (the target's argmax past a rejection, by position after the bonus token; "
        "right / checked):",
        "",
        "| method | " + " | ".join(f"+{j + 1}" for j in range(width)) + " |",
        "|---|" + "---:|" * width,
    ]
    for r in rows:
        rights, guessed = r.guesses.jacobi_right_per_position, r.guesses.jacobi_guesses_per_position
        cells = [
            f"{right / guesses:.0%} ({guesses})" if guesses else "-"
            for right, guesses in zip(rights + [0] * width, guessed + [0] * width)
        ]
        lines.append(f"| {r.name} | " + " | ".join(cells[:width]) + " |")
    return "\n".join(lines)


def format_episode_report(results: list[EpisodeMethodResult]) -> str:
    """Markdown table of [`run_episode_benchmark`] results. Speed-ups are against the fastest greedy row (eager
    ``greedy`` or transformers' compiled ``greedy:compile``) and, in a second column, against the first row (eager
    greedy); bin distances against the first row."""
    eager, fastest = results[0].median_latency, fastest_greedy(results)
    lines = [
        f"| method | median ms/action | speed-up vs {fastest.name} | vs {results[0].name} | target forwards/action | "
        "one-forward actions | tokens/target forward | draft forwards/action | target / draft / other time | bin "
        "distance to greedy (mean / max) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---|---|",
    ]
    for r in results:
        forwards = statistics.mean(r.target_forwards)
        one_forward = sum(f == 1 for f in r.target_forwards) / len(r.target_forwards)
        tokens = sum(r.new_tokens) / sum(r.target_forwards)
        if r.total_seconds:
            t, d = r.target_seconds / r.total_seconds, r.draft_seconds / r.total_seconds
            split = f"{t:.0%} / {d:.0%} / {1 - t - d:.0%}"
        else:
            split = "-"
        lines.append(
            f"| {r.name} | {1000 * r.median_latency:.2f} | {fastest.median_latency / r.median_latency:.2f}x | "
            f"{eager / r.median_latency:.2f}x | {forwards:.2f} | "
            f"{one_forward:.0%} | {tokens:.2f} | {statistics.mean(r.draft_forwards):.2f} | {split} | "
            f"{statistics.mean(r.bin_distances):.2f} / {max(r.bin_distances)} |"
        )
    if all(r.split_seconds for r in results):
        lines += [
            "",
            "Where the time goes (mean ms per call; rest = preprocessing, generate's preparation and the "
            "loop's own steps):",
            "",
            "| method | " + " | ".join(TIME_SPLIT) + " | total |",
            "|---|" + "---:|" * (len(TIME_SPLIT) + 1),
        ]
        for r in results:
            calls = len(r.latencies)
            cells = [f"{1000 * r.split_seconds[part] / calls:.1f}" for part in TIME_SPLIT]
            lines.append(f"| {r.name} | " + " | ".join(cells) + f" | {1000 * sum(r.latencies) / calls:.1f} |")
    jacobi = format_jacobi_report(results)
    lines += ["", jacobi] if jacobi else []
    positions = len(results[0].accepted_by_position)
    lines += [
        "",
        "Accepted drafts by token position of a call (share of calls; the rest are the target's own tokens):",
        "",
        "| method | " + " | ".join(f"t{p}" for p in range(positions)) + " |",
        "|---|" + "---:|" * positions,
    ]
    for r in results:
        cells = [f"{n / len(r.latencies):.0%}" for n in r.accepted_by_position]
        lines.append(f"| {r.name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def episode_methods(
    draft_head, bin_tolerances=(0, 1, 2, 4, 8), tree=None, chain_length: int = 3, compiled_on: str | None = None
) -> list[EpisodeMethod]:
    """Greedy; the action prior at every r; the draft head's chain and EAGLE-2 tree at r=0 and the largest r <= 4;
    the prior followed by the tree at the same two r. With ``compiled_on`` (a device type), also transformers'
    compiled greedy (``greedy:compile``) and every method but the chain compiled (``<name>:compile``: a static cache,
    compiled verification)."""
    methods = _episode_methods(draft_head, bin_tolerances, tree, chain_length)
    if compiled_on is None:
        return methods
    from ..speculative import compiled_decoding_kwargs

    compile_kwargs = compiled_decoding_kwargs(compiled_on)
    compiled = [
        EpisodeMethod(f"{m.name}:compile", {**m.generate_kwargs, **compile_kwargs}, m.action_prior)
        for m in methods
        if not m.name.startswith("head chain")
    ]
    return methods[:1] + compiled[:1] + methods[1:] + compiled[1:]


def _episode_methods(draft_head, bin_tolerances, tree, chain_length: int) -> list[EpisodeMethod]:
    from ..speculative import ComposedDrafter, DraftHeadDrafter, JacobiDrafter

    methods = [EpisodeMethod("greedy")]
    for r in bin_tolerances:
        methods.append(EpisodeMethod(f"prior r={r}", dict(bin_tolerance=r), action_prior=True))
    relaxed = max([r for r in bin_tolerances if 0 < r <= 4], default=None)
    tolerances = [0] + ([relaxed] if relaxed else [])
    jacobi = JacobiDrafter()
    methods.append(EpisodeMethod("jacobi r=0", dict(assistant_model=jacobi)))
    for r in tolerances:
        methods.append(EpisodeMethod(f"prior+jacobi r={r}", dict(assistant_model=jacobi, bin_tolerance=r), True))
    if draft_head is None:
        return methods
    chain = DraftHeadDrafter(draft_head, num_draft_tokens=chain_length)
    tree_drafter = DraftHeadDrafter(draft_head, tree=tree) if tree is not None else None
    methods.append(EpisodeMethod(f"head chain k={chain_length} r=0", dict(assistant_model=chain)))
    if tree_drafter is not None:
        jacobi_tree = ComposedDrafter([JacobiDrafter(fill=False), tree_drafter])
        for name, drafter, prior in (
            ("head tree", tree_drafter, False),
            ("prior+tree", tree_drafter, True),
            ("prior+jacobi+tree", jacobi_tree, True),
        ):
            for r in tolerances:
                methods.append(EpisodeMethod(f"{name} r={r}", dict(assistant_model=drafter, bin_tolerance=r), prior))
    return methods


def policy_actor(policy):
    """``act`` for [`run_episode_benchmark`] over a [`VLAPolicy`]; observations are dicts with ``image``,
    ``instruction`` and ``state``."""

    dim = policy.config.action_dim

    def act(observation, previous_action_ids, action_prior, **generate_kwargs):
        # the benchmark remembers each call's tokens (a chunk: H actions), the policy one list per action
        actions = [call[i : i + dim] for call in previous_action_ids for i in range(0, len(call), dim)]
        policy.previous_action_ids = actions[-policy.HISTORY_LENGTH :]
        _, output = policy.predict_action(
            observation["image"],
            observation["instruction"],
            observation["state"],
            return_output=True,
            action_prior=action_prior,
            **generate_kwargs,
        )
        return output.sequences[0, -policy.config.action_tokens :].tolist(), output

    return act


def toy_actor(pipeline):
    """``act`` for [`run_episode_benchmark`] over the toy target; observations are [`DotScene`]s."""
    from ..actions.tokenizer import ActionLayout
    from ..speculative import SPECULATION_KWARGS, as_drafter, with_action_prior
    from .toy import ACTION_DIM, toy_inputs

    layout = ActionLayout(pipeline.action_tokenizer, ACTION_DIM)

    def act(scene, previous_action_ids, action_prior, **generate_kwargs):
        kwargs = dict(generate_kwargs)
        drafter = as_drafter(kwargs.pop("assistant_model", None), None)
        if action_prior:
            drafter = with_action_prior(drafter, previous_action_ids, layout)
        if drafter is None:  # nothing to draft from (an episode's first step): plain greedy, as the policy does
            kwargs = {k: v for k, v in kwargs.items() if k not in SPECULATION_KWARGS}
        else:
            kwargs.update(assistant_model=drafter, action_layout=layout)
        inputs = toy_inputs([scene], pipeline.tokenizer)
        output = pipeline.target.generate(
            **{name: value.to(pipeline.target.device) for name, value in inputs.items()},  # the target's device
            max_new_tokens=ACTION_DIM,
            min_new_tokens=ACTION_DIM,
            do_sample=False,
            return_dict_in_generate=True,
            **kwargs,
        )
        return output.sequences[0, -ACTION_DIM:].tolist(), output

    return act


def toy_episodes(num_episodes: int) -> list[list]:
    """Toy "episodes": a dot moving one grid cell per step along a row (held-out scenes included), so that
    consecutive actions are close, as a robot's are."""
    from .toy import COLOURS, GRID_SIZE, TASKS, DotScene

    episodes = []
    for i in range(num_episodes):
        colour, task = list(COLOURS)[i % len(COLOURS)], list(TASKS)[(i // len(COLOURS)) % len(TASKS)]
        row = (3 * i) % GRID_SIZE
        episodes.append([DotScene(col, row, colour, task) for col in range(GRID_SIZE)])
    return episodes
