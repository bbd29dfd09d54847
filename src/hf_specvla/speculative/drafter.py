"""The drafter seam: anything that proposes draft trees to the decode loop.

The loop never looks inside a drafter. Per call and batch row it asks ``drafter.start(context)`` for a
[`DraftSession`] (all per-call state lives there, nothing is stuck onto models; a session sees one row, so every
tensor it is handed has batch size 1), then each round

    tree = session.propose(draft_round)      # before the target's forward; at the prefill too (drafts known up front)
    ... the target verifies the tree in one forward, the loop keeps the accepted path ...
    session.observe(commit)            # what was kept: tokens, positions, and the target's hidden states

transformers has the same split (``CandidateGenerator.get_candidates`` / ``update_candidate_strategy``); here the
proposal is a tree, and drafts known before the target has run are verified inside the prefill itself.

Built in: [`DraftHeadDrafter`] (EAGLE chain and EAGLE-2 dynamic tree), [`ActionPriorDrafter`] (previous actions, no
model), [`JacobiDrafter`] (the target's own guesses past a rejection, no model), [`CandidateDrafter`]
(``generate(draft_ids=...)``), and [`ComposedDrafter`] (several at once: their trees are merged, so drafts known up
front are verified at the prefill and a draft head continues from wherever they stop being accepted).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import torch
from transformers import CompileConfig, PreTrainedModel

from ..actions.tokenizer import ActionLayout
from .compat import NOT_ENABLED_HINT
from .stats import SpeculationStats
from .tree import DraftTree


@dataclass
class DraftContext:
    """What a drafter may read about one ``generate`` call (fixed for the call).

    Attributes:
        model: the target.
        action_layout: the action layout used for acceptance, or None (no relaxed acceptance possible).
        eos_token_ids: the call's EOS ids.
        prompt_padding: ``[1, S]`` 2D attention mask of the row's prompt (0 = padding), or None when there is none.
        row: the batch row the session drafts for (0 .. B-1).
        max_length: the longest sequence the call can reach (prompt + ``max_new_tokens``), or None when unknown.
        graphs: the call's compiled graphs (``speculative.compiled.CompiledGraphs``) when its verifications run
            compiled, else None (eager): a drafter then compiles its own work through them (its functions, its
            up-front compiles, their graph files), under their ``CompileConfig`` ([`compile_config`]), instead of
            looking the model's graphs up or deciding to compile itself.
        decoder: the target's ``SpeculativeDecoder`` when ``graphs`` are given (the static caches a compiled
            drafter reuses across calls: ``static_cache``), else None.
        cached_tokens: the row's first tokens the target cache already held when the call began (a continued
            conversation or episode on one cache): the prefill feeds only the tokens after them, so no hidden states
            exist for them and a drafter's own cache starts empty there (``prompt_padding`` covers the fed ones).
        prompt_embeddings: ``[1, S, H]`` what the target's language model reads for the row's prompt (token
            embeddings, image tokens replaced by the encoded images: ``speculative.vision.prompt_input_embeddings``),
            given when the drafter ``needs_prompt_embeddings``, else None.
    """

    model: PreTrainedModel
    action_layout: ActionLayout | None
    eos_token_ids: list[int]
    prompt_padding: torch.Tensor | None
    row: int = 0
    max_length: int | None = None
    graphs: Any = None  # a CompiledGraphs (not imported: compiled.py imports this module's importers)
    decoder: Any = None  # the target's SpeculativeDecoder (not imported, as graphs), given with graphs
    cached_tokens: int = 0
    prompt_embeddings: torch.Tensor | None = None

    def __post_init__(self):
        if self.graphs is not None and self.max_length is None:
            raise ValueError("DraftContext.graphs needs max_length (a compiled drafter sizes its cache by it)")
        if self.graphs is not None and self.decoder is None:
            raise ValueError("DraftContext.graphs needs decoder (a compiled drafter's static cache is kept by it)")

    @property
    def compile_config(self) -> CompileConfig | None:
        """The ``CompileConfig`` the call compiles with (its [`graphs`]'), None when it runs eagerly."""
        return None if self.graphs is None else self.graphs.compile_config


@dataclass
class DraftRound:
    """What a drafter sees when it proposes.

    Attributes:
        sequence: ``[1, L]`` the row's prompt + emitted tokens (its last token is the root of the tree to propose).
        num_generated: tokens emitted in this row so far.
        max_depth: the deepest path the loop will verify (so that path + bonus token fit ``max_length``).
        at_prefill: True before the target's first forward (no hidden states exist yet).
        root_position: ``[1, 1]`` position id of the root; a node at depth d is fed at ``root_position + 1 + d``.
        proposed: what the drafters before this one in a [`ComposedDrafter`] proposed this round (None: none did, or
            the drafter drafts alone).
    """

    sequence: torch.Tensor
    num_generated: int
    max_depth: int
    at_prefill: bool
    root_position: torch.Tensor
    proposed: DraftTree | None = None


@dataclass
class Commit:
    """What one verification kept, told to every drafter.

    The kept inputs are the tokens fed to the target in that forward and kept in its cache: the pending tokens
    (the whole prompt at the prefill, else the previous bonus token) and the accepted path.

    Attributes:
        next_token_ids: ``[1, K]`` the token that follows each kept input (the last one is the new bonus token).
        positions: ``[1, K]`` position ids of the kept inputs.
        target_hidden: ``[1, K, n H]`` the target's hidden states at each kept input (the n layers of
            ``Drafter.hidden_state_layers``, concatenated; the last one alone by default), or None when no drafter
            asked for hidden states (``Drafter.needs_hidden_states``).
        cache_length: the row's tokens in the target cache so far (its prompt, padding included, and its emitted
            tokens but the last): an index into the row's sequence. A drafter's own cache of the row holds
            ``cache_length - DraftContext.cached_tokens`` entries once it has seen this commit.
        tree: the row's verified tree (N nodes; the prompt's tree at the prefill).
        tree_target_ids: ``[1 + N]`` the target's greedy token after the root (0) and after each node (1 + i), each
            given that node's own path: past the accepted path these are the target's guesses on rejected prefixes
            (what [`JacobiDrafter`] drafts next).
        path_nodes: the accepted path's node indices in ``tree`` (root's child first).
        tree_target_list: ``tree_target_ids`` on the host (read with the accepted path: no read of its own), or None.
        kept_inputs: ``() -> (next_token_ids, positions)``, to make them when first read instead (the engine's
            commits: most drafters never read them, and each is a few device ops a round); then pass None for both.
    """

    next_token_ids: torch.Tensor | None
    positions: torch.Tensor | None
    target_hidden: torch.Tensor | None
    cache_length: int
    tree: DraftTree | None = None
    tree_target_ids: torch.Tensor | None = None
    path_nodes: list[int] = field(default_factory=list)
    tree_target_list: list[int] | None = None
    kept_inputs: Callable[[], tuple[torch.Tensor, torch.Tensor]] | None = field(default=None, repr=False)

    def __getattribute__(self, name: str):
        if name in ("next_token_ids", "positions"):
            kept = object.__getattribute__(self, "kept_inputs")
            if kept is not None:  # made on first read
                self.next_token_ids, self.positions = kept()
                self.kept_inputs = None
        return object.__getattribute__(self, name)


class DraftSession:
    """Per-call drafting state (see module docstring). ``num_forwards`` counts the model forwards it ran;
    ``compile_seconds`` the time it spent compiling (reported apart from drafting)."""

    num_forwards: int = 0
    compile_seconds: float = 0.0

    def propose(self, draft_round: DraftRound) -> DraftTree:
        """A draft tree below the root (may be empty)."""
        raise NotImplementedError

    def observe(self, commit: Commit) -> None:
        """Told what the verification kept. Default: nothing to update."""

    def warm_up(self, draft_round: DraftRound) -> None:
        """Compiles, now, every graph this session's later rounds run (a compiled call's drafter, through the
        call's ``DraftContext.graphs``): called once by the target's ``SpeculativeDecoder.warm_up`` right after the
        prefill was observed, with the round that comes next (``draft_round``, as [`propose`] will get it), so that
        nothing compiles mid-call. Default: nothing to compile."""

    def report(self, stats: SpeculationStats, sequence: torch.Tensor) -> None:
        """Adds what the session alone knows to the row's statistics, once the call has ended (``sequence``
        ``[1, L]``: the row's final tokens). Default: nothing to add."""


class Drafter:
    """Proposes draft trees; stateless across calls (``start`` returns the per-call [`DraftSession`]).

    Attributes:
        name: how statistics name the drafter's accepted tokens.
        needs_hidden_states: whether [`Commit`] must carry the target's hidden states (draft heads do).
        needs_prompt_embeddings: whether [`DraftContext`] must carry the prompt's input embeddings, images encoded
            (a draft head with ``prefill_image_features``).
        hidden_state_layers: which of them (indices into the target's ``hidden_states``; -1 the last, post-norm).
        action_layout: the action layout the drafter knows of (a draft head's config), or None.
        batch_size: the batch size the drafter is made for ([`PerRowDrafter`]), or None for any.
    """

    name: str = "drafter"
    needs_hidden_states: bool = False
    needs_prompt_embeddings: bool = False
    hidden_state_layers: tuple[int, ...] = (-1,)
    action_layout: ActionLayout | None = None
    batch_size: int | None = None

    def start(self, context: DraftContext) -> DraftSession:
        raise NotImplementedError

    def as_drafter(self, num_draft_tokens: int | None = None) -> Drafter:
        """What ``generate`` drafts with when this is the ``assistant_model``: itself (a bare [`DraftHead`] drafts
        its chain, ``speculative.assistant.as_drafter``). ``num_draft_tokens`` is a bare head's option: a drafter
        carries its own settings.

        Raises:
            ValueError: ``num_draft_tokens`` given to a drafter.
        """
        if num_draft_tokens is not None:
            raise ValueError(
                "num_draft_tokens applies to a bare DraftHead assistant; a Drafter carries its own settings "
                "(e.g. DraftHeadDrafter(head, num_draft_tokens=k))"
            )
        return self

    def with_previous_action(self, previous_action: Sequence[int] | None) -> Drafter:
        """This drafter for a robot whose previous action was ``previous_action`` (its action token ids, or None at
        an episode's first step): a drafter that reads it (a draft head with ``previous_action_input``) returns a
        copy that does; every other drafter returns ``self``."""
        return self

    def max_tree_nodes(self, max_depth: int) -> int | None:
        """The most nodes a session proposes in one round after the prefill when no path may be deeper than
        ``max_depth``, or None when unknown (compiled verification then compiles every width; see
        ``speculative.compiled``). A larger tree is cut to the widest compiled width, so a bound is a promise of
        speed, not of correctness."""
        return None

    def settings_key(self) -> tuple | None:
        """What the drafter drafts from, as a hashable value: drafters of equal keys (and class) are equal and hash
        alike (a [`DecodingPlan`] of equal settings is equal); None (the default): compared by identity."""
        return None

    def __eq__(self, other) -> bool:
        if self is other:
            return True
        key = self.settings_key()
        return key is not None and type(other) is type(self) and key == other.settings_key()

    def __hash__(self) -> int:
        key = self.settings_key()
        return id(self) if key is None else hash((type(self).__qualname__, key))

    def __getattr__(self, name: str):
        # Only reached for missing attributes: e.g. transformers' assisted generation probing ``.config`` because
        # the target's generate was never speculation-enabled. Say how to fix it.
        if name.startswith("__"):
            raise AttributeError(name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}: {NOT_ENABLED_HINT}")


class _NoDraftSession(DraftSession):
    def propose(self, draft_round: DraftRound) -> DraftTree:
        return DraftTree.empty(draft_round.root_position.device)


class NoDrafter(Drafter):
    """Drafts nothing: every round verifies its root alone, one token a target forward, so a call is greedy decoding
    run by the engine (its compiled calls, static caches and host path): the baseline that tells a speed-up from
    speculation apart from one from the engine's own path (a [`DecoderSession`] call without drafts)."""

    name = "none"

    def start(self, context: DraftContext) -> DraftSession:
        return _NoDraftSession()

    def max_tree_nodes(self, max_depth: int) -> int | None:
        return 0

    def settings_key(self) -> tuple:
        return ()

    def __repr__(self) -> str:
        return "NoDrafter()"


# ----------------------------------------------------------------------------- drafts known up front
class PathSession(DraftSession):
    """Proposes fixed token paths, aligned with the first generated token: after m tokens were emitted, each
    path's remaining part ``path[m:]`` is proposed (a guess for the tokens still to come), or with
    ``prefill_only`` nothing after the prefill. Paths are taken in order while the tree stays within ``max_nodes``
    nodes (shared prefixes count once)."""

    def __init__(
        self,
        paths: list[list[int]],
        source: str,
        device: torch.device,
        max_nodes: int | None = None,
        prefill_only: bool = False,
    ):
        self.paths, self.source, self.device, self.max_nodes = paths, source, device, max_nodes
        self.prefill_only = prefill_only

    def propose(self, draft_round: DraftRound) -> DraftTree:
        if self.prefill_only and not draft_round.at_prefill:
            return DraftTree.empty(self.device)
        m = draft_round.num_generated
        kept, prefixes = [], set()
        for path in self.paths:
            suffix = tuple(path[m : m + draft_round.max_depth])
            new = {suffix[: d + 1] for d in range(len(suffix))} - prefixes
            if not new or (self.max_nodes is not None and len(prefixes) + len(new) > self.max_nodes):
                continue
            prefixes |= new
            kept.append(suffix)
        return DraftTree.from_paths(kept, self.source, self.device)


class CandidateDrafter(Drafter):
    """Drafts given token sequences (``generate(draft_ids=...)``), no model.

    Args:
        candidates: ``C`` sequences of token ids, each a guess of the first generated tokens. They are verified
            inside the prefill (one tree, shared prefixes merged); after a partial acceptance their remaining
            tokens are proposed again for the positions still to come.
        name: the statistics' name for them.
    """

    def __init__(self, candidates: Sequence[Sequence[int]], name: str = "draft_ids"):
        self.candidates = [[int(t) for t in c] for c in candidates]
        self.name = name

    def start(self, context: DraftContext) -> DraftSession:
        return PathSession(self.candidates, self.name, context.model.device)

    def max_tree_nodes(self, max_depth: int) -> int | None:
        return sum(min(len(c), max_depth) for c in self.candidates)  # their remaining parts, shared prefixes merged


# ----------------------------------------------------------------------------- composition
class _ComposedSession(DraftSession):
    def __init__(self, sessions: list[DraftSession]):
        self.sessions = sessions

    @property
    def num_forwards(self) -> int:  # type: ignore[override]
        return sum(s.num_forwards for s in self.sessions)

    @property
    def compile_seconds(self) -> float:  # type: ignore[override]
        return sum(s.compile_seconds for s in self.sessions)

    def propose(self, draft_round: DraftRound) -> DraftTree:
        tree = DraftTree.empty(draft_round.sequence.device)
        for session in self.sessions:
            tree = tree.merge(session.propose(replace(draft_round, proposed=tree)))
        return tree

    def observe(self, commit: Commit) -> None:
        for session in self.sessions:
            session.observe(commit)

    def warm_up(self, draft_round: DraftRound) -> None:
        for session in self.sessions:
            session.warm_up(draft_round)

    def report(self, stats: SpeculationStats, sequence: torch.Tensor) -> None:
        for session in self.sessions:
            session.report(stats, sequence)


class ComposedDrafter(Drafter):
    """Several drafters at once: each round their trees are merged (nodes on the same token path become one,
    credited to the earlier drafter). With an [`ActionPriorDrafter`] first and a [`DraftHeadDrafter`] second,
    the prior's candidates are verified in the prefill and the head drafts from wherever they stop being accepted.
    """

    def __init__(self, drafters: Sequence[Drafter]):
        flat: list[Drafter] = []
        for drafter in drafters:
            if not isinstance(drafter, Drafter):
                raise TypeError(f"ComposedDrafter takes Drafters, got {type(drafter).__name__}")
            flat.extend(drafter.drafters if isinstance(drafter, ComposedDrafter) else [drafter])
        if not flat:
            raise ValueError("ComposedDrafter needs at least one drafter")
        self.drafters = flat
        self.name = "+".join(d.name for d in flat)
        self.needs_hidden_states = any(d.needs_hidden_states for d in flat)
        self.needs_prompt_embeddings = any(d.needs_prompt_embeddings for d in flat)
        self.hidden_state_layers = _common_hidden_state_layers(flat)
        self.action_layout = next((d.action_layout for d in flat if d.action_layout is not None), None)
        self.batch_size = _common_batch_size(flat)

    def start(self, context: DraftContext) -> DraftSession:
        return _ComposedSession([d.start(context) for d in self.drafters])

    def with_previous_action(self, previous_action: Sequence[int] | None) -> Drafter:
        drafters = [d.with_previous_action(previous_action) for d in self.drafters]
        return self if all(a is b for a, b in zip(drafters, self.drafters)) else ComposedDrafter(drafters)

    def max_tree_nodes(self, max_depth: int) -> int | None:
        bounds = [d.max_tree_nodes(max_depth) for d in self.drafters]
        return None if None in bounds else sum(bounds)

    def settings_key(self) -> tuple | None:
        keys = [d.settings_key() for d in self.drafters]
        return None if None in keys else tuple(zip((type(d).__qualname__ for d in self.drafters), keys))

    def __repr__(self) -> str:
        return f"ComposedDrafter({self.drafters!r})"


class PerRowDrafter(Drafter):
    """A different drafter for each batch row (e.g. each robot's own previous actions): row b drafts with
    ``drafters[b]``. A drafter used for every row (a draft head) needs no wrapping.

    Example:
        ```python
        drafter = PerRowDrafter([ActionPriorDrafter(history, layout) for history in histories_per_robot])
        model.generate(input_ids, attention_mask=mask, assistant_model=drafter, max_new_tokens=7)
        ```
    """

    def __init__(self, drafters: Sequence[Drafter]):
        drafters = list(drafters)
        if not drafters:
            raise ValueError("PerRowDrafter needs one drafter per batch row, got none")
        for row, drafter in enumerate(drafters):
            if not isinstance(drafter, Drafter) or isinstance(drafter, PerRowDrafter):
                raise TypeError(f"PerRowDrafter takes one Drafter per row, got {type(drafter).__name__} at row {row}")
        self.drafters = drafters
        self.batch_size = len(drafters)
        self.name = "+".join(dict.fromkeys(d.name for d in drafters))
        self.needs_hidden_states = any(d.needs_hidden_states for d in drafters)
        self.needs_prompt_embeddings = any(d.needs_prompt_embeddings for d in drafters)
        self.hidden_state_layers = _common_hidden_state_layers(drafters)
        self.action_layout = next((d.action_layout for d in drafters if d.action_layout is not None), None)

    def start(self, context: DraftContext) -> DraftSession:
        return self.drafters[context.row].start(context)

    def max_tree_nodes(self, max_depth: int) -> int | None:
        bounds = [d.max_tree_nodes(max_depth) for d in self.drafters]
        return None if None in bounds else max(bounds)


def _common_hidden_state_layers(drafters: Sequence[Drafter]) -> tuple[int, ...]:
    """The target hidden states the drafters that read them read (one set: each Commit carries one)."""
    layers = {tuple(d.hidden_state_layers) for d in drafters if d.needs_hidden_states}
    if len(layers) > 1:
        raise ValueError(
            f"these drafters read different target hidden states {sorted(layers)} (draft heads of "
            f"different feature_layers); one call serves one set"
        )
    return layers.pop() if layers else (-1,)


def read_hidden_states(hidden_states: Sequence[torch.Tensor], layers: Sequence[int]) -> torch.Tensor:
    """A forward's ``hidden_states`` (one ``[B, q, H]`` per layer) -> ``[B, q, n H]``: the n ``layers`` asked for
    ([`Drafter.hidden_state_layers`]), concatenated in that order."""
    if len(layers) == 1:
        return hidden_states[layers[0]]
    return torch.cat([hidden_states[i] for i in layers], dim=-1)


def _common_batch_size(drafters: Sequence[Drafter]) -> int | None:
    sizes = {d.batch_size for d in drafters if d.batch_size is not None}
    if len(sizes) > 1:
        raise ValueError(f"these drafters are made for different batch sizes {sorted(sizes)}; use one per row count")
    return sizes.pop() if sizes else None
