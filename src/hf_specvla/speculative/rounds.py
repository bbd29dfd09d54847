"""A speculative call's rounds: the prefill and every later round run the same ladder, each step a short function
(propose -> fit -> one target forward -> settle: accept -> emit -> commit_paths -> observe -> drop finished rows)."""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable

import torch
from transformers import LogitsProcessorList, PreTrainedModel, StoppingCriteriaList
from transformers.generation.stopping_criteria import EosTokenCriteria, MaxLengthCriteria, MaxTimeCriteria

from .acceptance import AcceptedPath, accept_trees, read_paths, sample_trees
from .cache import (
    cache_length,
    compact_rows,
    keep_cache_path,
    select_cache_positions,
    select_cache_rows,
    truncate_cache,
)
from .compat import CACHE_KEY
from .compiled import verification_width
from .drafter import Commit, DraftRound
from .state import DecodeState, RoundPlan, RowState, SpeculativeCall, in_cache_batch
from .stats import SpeculationStats
from .tree import DraftTree, TreeBatch
from .verify import Pending, TargetOutput, target_greedy_ids


def commit_paths(
    state: DecodeState,
    trees: TreeBatch,
    paths: list[AcceptedPath],
    hidden: torch.Tensor | None,
    target_ids: torch.Tensor | None = None,
) -> list[Commit]:
    """Keeps, for every row, its pending tokens and its accepted path in the target cache; says so to drafters.

    A row whose path is shorter than the longest one keeps invalid entries up to that length (``key_valid``), so
    that the cache stays rectangular; when every row's path is leftmost (always for chains) the cache is simply
    truncated (a shorter row's rejected entries stay, as invalid keys), else each row's path is gathered.
    Updates ``state`` (pending tokens, positions, key validity).

    Args:
        hidden: ``[B, P + N, H]`` the target's hidden states of the verification, or None.
        target_ids: ``[B, 1 + N]`` the target's greedy token after each row's root and each node, or None.
    Returns:
        one [`Commit`] per row: kept inputs = pending tokens + path nodes; the token after each; hidden states; the
        verified tree, the target's tokens on it and the accepted path.
    """
    batch_size, num_pending = state.pending_ids.shape
    base = cache_length(state.target_cache) - trees.num_nodes  # cache entries before the tree's
    device = state.pending_ids.device
    longest = max(len(p.nodes) for p in paths)
    node_index = None  # [B, A] each row's path nodes, padded; None when every path is its tree's first nodes
    if all(p.nodes == list(range(len(p.nodes))) for p in paths):  # leftmost paths (chains): a prefix, truncate
        truncate_cache(state.target_cache, base + longest)  # a shorter row's extra entries become invalid keys
    else:
        node_index = torch.tensor([p.nodes + [0] * (longest - len(p.nodes)) for p in paths], device=device).long()
        keep_cache_path(state.target_cache, base, in_cache_batch(state, node_index, 0))
    # every key valid: known on the host when no key was invalid before and every path has one length (else the
    # device says); the mask of valid keys is built only when some key may be invalid
    same_length = all(len(p.nodes) == longest for p in paths)
    key_valid = None  # [B, base + A]
    if not same_length or state.key_valid is not None:
        path_valid = torch.tensor(
            [[i < len(p.nodes) for i in range(longest)] for p in paths], dtype=torch.bool, device=device
        )  # [B, A]
        valid_before = state.key_valid
        if valid_before is None:
            valid_before = torch.ones(batch_size, base, dtype=torch.bool, device=device)
        key_valid = torch.cat([valid_before, path_valid], dim=1)
    all_valid = same_length and (state.key_valid is None or bool(key_valid.all()))
    commits = []
    for b, (row, path) in enumerate(zip(state.rows, paths)):
        accepted = len(path.nodes)
        kept_hidden = None
        if node_index is None:  # the path is the tree's first nodes: slices, no gather
            path_tokens = trees.token_ids[b : b + 1, :accepted]  # [1, A_b]
            if hidden is not None:  # the pending tokens' hidden states, then the path's, as they are laid out
                kept_hidden = hidden[b : b + 1, : num_pending + accepted]
        else:
            nodes = node_index[b, :accepted]
            path_tokens = trees.token_ids[b, nodes][None]  # [1, A_b]
            if hidden is not None:
                kept_hidden = torch.cat([hidden[b : b + 1, :num_pending], hidden[b : b + 1, num_pending + nodes]], 1)
        row.committed_length += num_pending + accepted
        commits.append(
            Commit(
                None,
                None,
                target_hidden=kept_hidden,
                cache_length=row.committed_length,
                tree=trees.trees[b],
                tree_target_ids=None if target_ids is None else target_ids[b, : 1 + trees.trees[b].num_nodes],
                path_nodes=path.nodes,
                tree_target_list=path.target_ids,
                kept_inputs=_kept_inputs(
                    state.pending_ids[b : b + 1], state.pending_positions[b : b + 1], path_tokens, path.bonus_id
                ),
            )
        )
    # [B, 1] the bonus tokens, at the position after each row's path
    state.pending_ids = torch.tensor([[p.bonus_id] for p in paths], dtype=state.pending_ids.dtype, device=device)
    advance = torch.tensor([[len(p.nodes) + 1] for p in paths], dtype=state.pending_positions.dtype, device=device)
    state.pending_positions = state.pending_positions[:, -1:] + advance
    state.key_valid = None if all_valid else torch.cat([key_valid, key_valid.new_ones(batch_size, 1)], 1)
    return commits


def _kept_inputs(pending_ids, pending_positions, path_tokens, bonus_id: int):
    """A [`Commit`]'s ``kept_inputs``: ``() -> (next_token_ids [1, K], positions [1, K])`` of one row's pending
    tokens ``[1, P]`` (at ``pending_positions``) and its accepted path's tokens ``[1, A]``, made when a drafter reads
    them."""

    def make() -> tuple[torch.Tensor, torch.Tensor]:
        bonus = path_tokens.new_full((1, 1), bonus_id)
        steps = torch.arange(1, path_tokens.shape[1] + 1, device=pending_positions.device)[None]
        return (
            torch.cat([pending_ids[:, 1:], path_tokens, bonus], dim=1),
            torch.cat([pending_positions, pending_positions[:, -1:] + steps], dim=1),
        )

    return make


def drop_finished_rows(state: DecodeState, fixed_batch: bool = False) -> None:
    """Removes finished rows from the batch tensors, and from the target cache with the cache columns no row needs;
    with ``fixed_batch`` (a static cache) the cache keeps its rows and columns: the finished ones become idle rows
    (``state.cache_rows`` maps the rows still generating to theirs)."""
    active = [b for b, row in enumerate(state.rows) if not row.finished]
    if len(active) == len(state.rows):
        return
    state.rows = [state.rows[b] for b in active]
    if not active:
        return
    index = torch.tensor(active, device=state.pending_ids.device)
    state.pending_ids, state.pending_positions = state.pending_ids[index], state.pending_positions[index]
    if state.position_offsets is not None:
        state.position_offsets = state.position_offsets[:, index]
    if fixed_batch:
        state.cache_rows = index if state.cache_rows is None else state.cache_rows[index]
        if state.key_valid is not None:
            state.key_valid = state.key_valid[index]
        return
    select_cache_rows(state.target_cache, index)
    if state.key_valid is not None:
        key_valid = state.key_valid[index]
        needed = key_valid[:, :-1].any(dim=0)  # cached columns some remaining row attends to
        if not bool(needed.all()):
            select_cache_positions(state.target_cache, needed.nonzero()[:, 0])
            key_valid = torch.cat([key_valid[:, :-1][:, needed], key_valid[:, -1:]], dim=1)
        state.key_valid = None if bool(key_valid.all()) else key_valid


class CallStopping:
    """A call's stopping criteria, and (read once a call) their answer on the host when they are transformers' own
    length, EOS and time criteria (what ``generate`` builds): the EOS ids read once from the device, not once a
    round, and nothing written onto the criteria."""

    def __init__(self, criteria: StoppingCriteriaList):
        self.criteria, self.on_host = criteria, _host_stopping(criteria)

    @classmethod
    def of(cls, stopping: CallStopping | StoppingCriteriaList) -> CallStopping:
        return stopping if isinstance(stopping, CallStopping) else cls(stopping)


def emit_tokens(
    rows: list[RowState], emitted: list[list[int]], stopping: CallStopping | StoppingCriteriaList
) -> list[int]:
    """Appends each row's ``emitted`` tokens up to where the stopping criteria first fire, as greedy decoding (which
    asks them after every token) would stop, and marks those rows finished.

    The criteria see exactly the prefixes greedy decoding shows them; prefixes of one length (across rows) are
    asked in one call.

    Returns:
        per row, how many of its tokens were kept.
    """
    lengths = [row.sequence.shape[1] for row in rows]
    extended = [torch.cat([row.sequence[0], row.sequence.new_tensor(tokens)]) for row, tokens in zip(rows, emitted)]
    by_length: dict[int, list[int]] = {}  # prefix length -> rows that reach it
    for b, tokens in enumerate(emitted):
        for count in range(1, len(tokens) + 1):
            by_length.setdefault(lengths[b] + count, []).append(b)
    stop_length: list[int | None] = [None] * len(rows)  # the shortest prefix the criteria stop at
    asked = [(length, by_length[length]) for length in sorted(by_length)]
    stopping = CallStopping.of(stopping)
    on_host, stopping_criteria = stopping.on_host, stopping.criteria
    if on_host is not None:  # generate's own criteria (length, EOS, time), answered from the host's tokens
        for length, group in asked:
            for b in group:
                if stop_length[b] is None and on_host(length, emitted[b][length - lengths[b] - 1]):
                    stop_length[b] = length
    elif asked:  # every prefix asked (the criteria are functions of the ids), then one read of all the answers
        answers = torch.cat(
            [
                stopping_criteria(torch.stack([extended[b][:length] for b in group]), None).reshape(-1)
                for length, group in asked
            ]
        ).tolist()
        for (length, group), start in zip(asked, itertools.accumulate([0] + [len(g) for _, g in asked])):
            for b, stop in zip(group, answers[start : start + len(group)]):
                if stop and stop_length[b] is None:
                    stop_length[b] = length
    num_kept = []
    for b, row in enumerate(rows):
        end = lengths[b] + len(emitted[b]) if stop_length[b] is None else stop_length[b]
        row.finished = stop_length[b] is not None
        row.sequence = extended[b][None, :end]
        row.num_generated += end - lengths[b]
        num_kept.append(end - lengths[b])
    return num_kept


def _host_stopping(stopping_criteria: StoppingCriteriaList) -> Callable[[int, int], bool] | None:
    """``stop(prefix_length, last_token)`` answering ``stopping_criteria`` on the host, exactly as they answer on the
    ids, when they are all transformers' length, EOS and time criteria (what ``generate`` builds); None otherwise."""
    known = (MaxLengthCriteria, EosTokenCriteria, MaxTimeCriteria)
    if not all(type(criteria) in known for criteria in stopping_criteria):
        return None
    max_lengths = [c.max_length for c in stopping_criteria if type(c) is MaxLengthCriteria]
    eos_ids = set()
    for criteria in stopping_criteria:
        if type(criteria) is EosTokenCriteria:
            eos_ids.update(criteria.eos_token_id.reshape(-1).tolist())
    timers = [c for c in stopping_criteria if type(c) is MaxTimeCriteria]

    def stop(length: int, last_token: int) -> bool:
        return (
            any(length >= m for m in max_lengths)
            or last_token in eos_ids
            or any(time.time() - c.initial_timestamp > c.max_time for c in timers)
        )

    return stop


def propose(state: DecodeState, plan: RoundPlan) -> list[DraftTree]:
    """1. Each row's drafter proposes a tree below its root (at the prefill: before any token of the call was emitted);
    no path drafts past ``max_length`` (the bonus token takes the last slot)."""
    trees = []
    for b, row in enumerate(state.rows):
        round_ = next_draft_round(state, plan, b)
        trees.append(row.session.propose(round_).truncate_depth(round_.max_depth))
    return trees


def next_draft_round(state: DecodeState, plan: RoundPlan, b: int) -> DraftRound:
    """What row ``b``'s drafter sees in the round that comes next ([`DraftRound`]): its tokens, the deepest path that
    fits ``max_length``, its root's position."""
    row = state.rows[b]
    return DraftRound(
        sequence=row.sequence,
        num_generated=row.num_generated,
        max_depth=max(0, plan.max_length - row.sequence.shape[1] - 1),
        at_prefill=row.num_generated == 0,  # the prefill emits at least its bonus token
        root_position=state.pending_positions[b : b + 1, -1:],
    )


def fit_prefill_trees(trees: list[DraftTree], state: DecodeState, plan: RoundPlan) -> TreeBatch:
    """The prefill's trees as one [`TreeBatch`]: a prefix-LM prompt keeps one chain; ``max_drafts_per_row`` and, on a
    static cache, its free slots cut each tree to its first nodes (the prefill's width is free: its compiled graph
    has a dynamic length)."""
    if plan.prefix_attention:
        trees = [tree.first_path() for tree in trees]
    if plan.max_drafts is not None:
        trees = [tree.truncate_nodes(plan.max_drafts) for tree in trees]
    if plan.capacity is not None:
        trees = [tree.truncate_nodes(_free_slots(state, plan)) for tree in trees]
    return TreeBatch(trees, structures=plan.tree_structures)


def _free_slots(state: DecodeState, plan: RoundPlan) -> int:
    """A static cache's slots left for a tree after its entries and the pending tokens."""
    return plan.capacity - cache_length(state.target_cache) - state.pending_ids.shape[1]


def fit_trees(trees: list[DraftTree], state: DecodeState, plan: RoundPlan, stats: SpeculationStats) -> TreeBatch:
    """A round's trees as one [`TreeBatch`]: ``max_drafts_per_row`` cuts every tree to its first nodes; on a static
    cache the pending token and the tree fit in the free slots (a batch's rows are compacted first when invalid
    entries take the slots the trees need), and a compiled round is padded (or cut) to its width bucket."""
    if plan.max_drafts is not None:
        trees = [tree.truncate_nodes(plan.max_drafts) for tree in trees]
    width = 0  # the node count a compiled verification is padded to
    if plan.capacity is not None:
        free = _free_slots(state, plan)
        widest = max(tree.num_nodes for tree in trees)
        buckets = plan.verifier.buckets
        wanted = verification_width(widest, buckets[-1], buckets) if plan.verifier.compiled else widest
        if free < wanted and state.key_valid is not None:
            _compact(state)
            free = _free_slots(state, plan)
        if plan.verifier.compiled:  # one width per bucket: padded, or cut to fit
            free = width = verification_width(widest, free, buckets)
            stats.compiled_widths.append(width)
        trees = [tree.truncate_nodes(free) for tree in trees]
    return TreeBatch(trees, min_nodes=width, structures=plan.tree_structures)


def _compact(state: DecodeState) -> None:
    """[`compact_rows`] on a static cache's batch: each row's valid entries moved to the front (idle rows keep none)."""
    cached = cache_length(state.target_cache)
    valid = in_cache_batch(state, state.key_valid[:, :cached], False)  # [B_cache, C]
    if int(valid.sum(dim=1).max()) == cached:  # some row keeps every entry: nothing to free
        return
    compacted = compact_rows(state.target_cache, valid)  # [B_cache, C']
    if state.cache_rows is not None:
        compacted = compacted[state.cache_rows]
    key_valid = torch.cat([compacted, state.key_valid[:, cached:]], dim=1)  # [B, C' + P]
    state.key_valid = None if bool(key_valid.all()) else key_valid


def verify(model: PreTrainedModel, state: DecodeState, plan: RoundPlan, trees: TreeBatch) -> TargetOutput:
    """2. Every row's tree in one target forward on the cache (the plan's [`Verification`]: eager, compiled, or with
    the acceptance in the graph). A static cache's idle rows (finished, kept in its batch) are fed a filler token and
    an empty tree, their outputs dropped."""
    pending_ids, positions, key_valid, offsets = (
        state.pending_ids,
        state.pending_positions,
        state.key_valid,
        state.position_offsets,
    )
    if state.cache_rows is not None:
        pending_ids, positions = in_cache_batch(state, pending_ids, 0), in_cache_batch(state, positions, 0)
        if key_valid is None:
            columns = cache_length(state.target_cache) + state.pending_ids.shape[1]
            key_valid = torch.ones(state.pending_ids.shape[0], columns, dtype=torch.bool, device=pending_ids.device)
        key_valid = in_cache_batch(state, key_valid, False)
        key_valid[:, -1] = True  # an idle row's filler attends to itself
        if offsets is not None:
            offsets = in_cache_batch(state, offsets.transpose(0, 1), 0).transpose(0, 1)
        rows = [DraftTree.empty(pending_ids.device)] * pending_ids.shape[0]
        for tree, b in zip(trees.trees, state.cache_rows.tolist()):
            rows[b] = tree
        trees = TreeBatch(rows, min_nodes=trees.num_nodes, structures=plan.tree_structures)
    lengths = None  # the rows' sequence lengths, for an acceptance in the graph (it hides EOS by them)
    if plan.verifier.fused:
        lengths = in_cache_batch(
            state, torch.tensor([[row.sequence.shape[1]] for row in state.rows], device=pending_ids.device), 0
        )
    pending = Pending({CACHE_KEY: state.target_cache}, pending_ids, positions, key_valid, offsets, lengths)
    output = plan.verifier.round(model, pending, trees)
    if state.cache_rows is None:
        return output
    return TargetOutput(*(None if value is None else value[state.cache_rows] for value in output))


def accept(
    state: DecodeState, plan: RoundPlan, trees: TreeBatch, output: TargetOutput, logits_processor: LogitsProcessorList
) -> tuple[list[AcceptedPath], torch.Tensor, torch.Tensor]:
    """3. Per row, the longest passing path; its bonus token is the target's greedy choice after it (sampling: the path
    and bonus token drawn by speculative sampling, [`sample_trees`]).

    Returns:
        (the accepted paths, the target's greedy ids ``[B, 1 + N]``, the processed scores ``[B, 1 + N, V]``, None
        when the acceptance ran inside the forward's graph)."""
    if output.accepted is not None:  # decided in the verification's graph: one read of its packed rows
        num_nodes = trees.num_nodes
        paths = read_paths(output.accepted.tolist(), trees)
        return paths, output.accepted[:, 3 * num_nodes + 1 : 4 * num_nodes + 2], None
    target_ids, target_scores = target_greedy_ids(
        logits_processor, [row.sequence for row in state.rows], trees, output.logits
    )
    if plan.sampling:  # the target's distribution, exactly: every draft a point mass, recursive rejection sampling
        return sample_trees(trees, target_scores), target_ids, target_scores
    action_counts = [row.num_action_tokens for row in state.rows]
    top1_probs = target_scores.softmax(dim=-1).amax(dim=-1) if plan.rule.needs_probabilities else None  # [B, 1 + N]
    budgeted = plan.rule.max_relaxed_per_action is not None and plan.layout is not None  # counted per action
    dim = plan.layout.action_dim if plan.layout is not None else 1
    relaxed = [row.relaxed_in_action if row.num_action_tokens % dim else 0 for row in state.rows] if budgeted else None
    paths = accept_trees(trees, target_ids, plan.rule, plan.layout, action_counts, top1_probs, relaxed)
    return paths, target_ids, target_scores


def emit(
    state: DecodeState,
    plan: RoundPlan,
    trees: TreeBatch,
    paths: list[AcceptedPath],
    output: TargetOutput,
    target_scores: torch.Tensor,
    stopping_criteria: CallStopping | StoppingCriteriaList,
) -> None:
    """4. Appends each row's accepted tokens and bonus token, stopping it exactly where greedy would (EOS,
    ``max_length``, custom criteria); books statistics, scores and logits."""
    emitted = []
    for row, tree, path in zip(state.rows, trees.trees, paths):
        row.stats.record_verification(tree.max_depth, tree.num_nodes, [tree.sources[n] for n in path.nodes])
        emitted.append([tree.host_tokens[n] for n in path.nodes] + [path.bonus_id])
    num_kept = emit_tokens(state.rows, emitted, stopping_criteria)
    for b, (row, tree, path, count) in enumerate(zip(state.rows, trees.trees, paths, num_kept)):
        parents = tree.parent_list
        logit_rows = [parents[n] + 1 for n in path.nodes] + [path.nodes[-1] + 1 if path.nodes else 0]
        for token, logit_row, distance in zip(emitted[b][:count], logit_rows, path.distances + [0]):
            if plan.layout is not None and plan.layout.tokenizer.is_action_token(token):
                if row.num_action_tokens % plan.layout.action_dim == 0:  # the first token of an action
                    row.relaxed_in_action = 0
                row.num_action_tokens += 1
                row.relaxed_in_action += distance > 0
                row.stats.action_bin_distances.append(distance)
            if plan.keep_scores:
                row.scores.append(target_scores[b, logit_row])
            if plan.keep_logits:
                row.logits.append(output.logits[b, logit_row])
        row.stats.accept_lengths.append(count)


def observe(state: DecodeState, commits: list[Commit]) -> None:
    """5b. Tells the drafter of every row still generating what its round kept (after [`commit_paths`], 5a)."""
    for row, kept in zip(state.rows, commits):
        if not row.finished:
            row.session.observe(kept)


def settle(call: SpeculativeCall, trees: TreeBatch, output: TargetOutput, logits_processor, stopping_criteria) -> None:
    """A verification's outcome: accept, emit, commit each row's path, tell the drafters (the prefill's and every
    round's)."""
    state, plan = call.state, call.plan
    call.stats.num_batch_forwards += 1
    paths, target_ids, target_scores = accept(state, plan, trees, output, logits_processor)
    emit(state, plan, trees, paths, output, target_scores, stopping_criteria)
    if call.on_row_finished is not None:
        for row in state.rows:
            if row.finished:  # finished this round: finished rows leave the batch at the end of every round
                new_tokens = row.sequence[0, row.sequence.shape[1] - row.num_generated :]
                call.on_row_finished(row.index, new_tokens, row.stats)
    commits = commit_paths(state, trees, paths, output.hidden, target_ids)
    with call.stopwatch.section("draft_seconds"):
        observe(state, commits)


def prefill(model, call: SpeculativeCall, logits_processor, stopping_criteria) -> TreeBatch:
    """2. The prompt and the drafts known up front, verified in one forward (the model's prepared inputs, images
    included; compiled when an earlier call compiled its graph). Finished rows stay in the batch (a compiled call's
    graphs are compiled next, for the whole batch: ``SpeculativeDecoder.warm_up``); the caller drops them.

    Returns:
        the prefill's trees (what a compiled call feeds once more to compile the next call's prefill graph).
    """
    state, plan, stats = call.state, call.plan, call.stats
    with call.stopwatch.section("draft_seconds"):
        proposed = propose(state, plan)
    trees = fit_prefill_trees(proposed, state, plan)
    with call.stopwatch.section("target_seconds"):
        prompt = Pending(
            call.model_inputs, state.pending_ids, state.pending_positions, state.key_valid, state.position_offsets
        )
        output = plan.verifier.prefill(model, prompt, trees)
    stats.compiled_prefills += plan.verifier.compiled_prefill
    settle(call, trees, output, logits_processor, stopping_criteria)
    return trees


def decode_round(model, call: SpeculativeCall, logits_processor, stopping_criteria) -> None:
    """3. One round after the prefill: the rows' trees verified in one (compiled) forward; finished rows leave."""
    state, plan = call.state, call.plan
    with call.stopwatch.section("draft_seconds"):
        proposed = propose(state, plan)
    trees = fit_trees(proposed, state, plan, call.stats)
    with call.stopwatch.section("target_seconds"):
        output = verify(model, state, plan, trees)
    settle(call, trees, output, logits_processor, stopping_criteria)
    drop_finished_rows(call.state, fixed_batch=call.plan.capacity is not None)
