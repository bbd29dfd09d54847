"""The speculative decode loop: drafters propose trees, the target verifies each in one forward.

Reads as a ladder (gpt-fast style), the same steps every round, the prefill included:

    propose (drafter) -> verify_tree (one target forward) -> target_greedy_ids -> accept_tree -> emit -> commit
    -> observe (drafter) -> repeat until a stopping criterion

Invariants kept between rounds (B = 1 in this version):

* ``sequence`` holds the prompt and every emitted token. ``pending`` tokens are not in the target cache yet:
  the whole prompt before the prefill, afterwards exactly the last emitted token (the previous bonus token).
* The tree proposed in a round hangs below the last pending token (the root). Drafts known before the target has
  run (``draft_ids``, the action prior) are proposed in round 0 and so verified *inside the prefill*: when all of
  them pass, the action costs exactly one target forward.
* After a round the target cache holds the pending tokens and the accepted path only: the path's entries are
  gathered (not truncated), since an accepted node need not be leftmost in the tree.

Entry point: [`speculative_generate`], a ``custom_generate`` callable for ``model.generate``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import torch
from transformers import GenerationConfig, LogitsProcessorList, PreTrainedModel, StoppingCriteriaList
from transformers.cache_utils import Cache

from ..action_tokenizer import ActionLayout
from .acceptance import AcceptanceRule, AcceptedPath, accept_tree, make_acceptance_rule
from .cache import select_cache_positions, truncate_cache
from .config import SpeculationConfig
from .drafter import CandidateDrafter, Commit, ComposedDrafter, DraftContext, Drafter, DraftRound
from .drafters.draft_head import DraftHeadDrafter
from .modeling_draft_head import DraftHead
from .outputs import SpeculativeDecoderOnlyOutput
from .stats import SpeculationStats
from .tree import DraftTree
from .verify import prefill_inputs, target_greedy_ids, verify_tree

logger = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- state
@dataclass
class DecodeState:
    """Everything one speculative decode carries between rounds (one explicit object, nothing on the models)."""

    sequence: torch.Tensor  # [1, L] prompt + emitted tokens
    pending_ids: torch.Tensor  # [1, P] tokens not yet in the target cache (their last one is the tree's root)
    pending_positions: torch.Tensor  # [1, P] their position ids
    target_cache: Cache
    num_generated: int  # tokens emitted in this call
    num_action_tokens: int  # action tokens emitted in this call (for action dimensions)


class _Stopwatch:
    """Accumulates wall time of labelled sections into the stats, optionally device-synchronised."""

    def __init__(self, stats: SpeculationStats, device: torch.device, synchronize: bool):
        self.stats, self.device, self.synchronize = stats, device, synchronize

    def _sync(self):
        if self.synchronize and self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    @contextmanager
    def section(self, attribute: str):
        self._sync()
        start = time.perf_counter()
        yield
        self._sync()
        setattr(self.stats, attribute, getattr(self.stats, attribute) + time.perf_counter() - start)


# ----------------------------------------------------------------------------- inputs
def as_drafter(assistant, num_draft_tokens: int | None) -> Drafter | None:
    """The [`Drafter`] behind an ``assistant_model`` / ``draft_head`` argument (a bare DraftHead drafts a chain).

    Raises:
        TypeError: for anything that is neither a DraftHead nor a Drafter.
    """
    if assistant is None:
        return None
    if isinstance(assistant, DraftHead):
        return DraftHeadDrafter(assistant, num_draft_tokens=num_draft_tokens)
    if isinstance(assistant, Drafter):
        if num_draft_tokens is not None:
            raise ValueError(
                "num_draft_tokens applies to a bare DraftHead assistant; a Drafter carries its own settings "
                "(e.g. DraftHeadDrafter(head, num_draft_tokens=k))"
            )
        return assistant
    raise TypeError(
        f"the assistant must be a hf_specvla DraftHead or Drafter (DraftHeadDrafter, ActionPriorDrafter, "
        f"ComposedDrafter, ...), got {type(assistant).__name__}"
    )


def draft_id_candidates(draft_ids, batch_size: int, vocab_size: int) -> list[list[int]]:
    """Validates ``generate(draft_ids=...)``: a LongTensor ``[B, k]`` or ``[B, C, k]`` -> C candidate lists (B = 1).

    Raises:
        TypeError / ValueError naming the shape, dtype or id that is wrong and what is valid.
    """
    if not isinstance(draft_ids, torch.Tensor):
        raise TypeError(f"draft_ids must be a LongTensor [B, k] or [B, C, k], got {type(draft_ids).__name__}")
    if draft_ids.dtype not in (torch.int64, torch.int32, torch.int16, torch.uint8):
        raise TypeError(f"draft_ids must hold integer token ids, got dtype {draft_ids.dtype}")
    if draft_ids.ndim not in (2, 3):
        raise ValueError(
            f"draft_ids must have shape [B, k] (one continuation) or [B, C, k] (C candidates), got "
            f"{tuple(draft_ids.shape)}"
        )
    if draft_ids.shape[0] != batch_size:
        raise ValueError(f"draft_ids has batch size {draft_ids.shape[0]}, input_ids has {batch_size}")
    if draft_ids.shape[-1] == 0:
        raise ValueError(f"draft_ids has no tokens (shape {tuple(draft_ids.shape)}); pass k >= 1 or leave it out")
    if draft_ids.numel() and (int(draft_ids.min()) < 0 or int(draft_ids.max()) >= vocab_size):
        raise ValueError(
            f"draft_ids must be token ids in 0..{vocab_size - 1}, got values "
            f"{int(draft_ids.min())}..{int(draft_ids.max())}"
        )
    candidates = draft_ids[0].reshape(-1, draft_ids.shape[-1])
    return candidates.tolist()


def _validate_call(model, input_ids, generation_config: GenerationConfig) -> None:
    if generation_config.do_sample:
        raise ValueError(
            "speculative decoding is greedy only (do_sample=False); got do_sample=True. Drop do_sample / "
            "temperature, or generate without assistant_model / draft_ids to sample"
        )
    if (generation_config.num_beams or 1) > 1 or (generation_config.num_return_sequences or 1) > 1:
        raise ValueError(
            f"speculative decoding needs num_beams=1 and num_return_sequences=1, got "
            f"num_beams={generation_config.num_beams}, num_return_sequences={generation_config.num_return_sequences}"
        )
    batch_size = input_ids.shape[0]
    if batch_size != 1:
        raise ValueError(
            f"speculative decoding supports batch size 1 in this version, got {batch_size} sequences; call "
            f"generate once per sequence, or without assistant_model / draft_ids for batched greedy decoding"
        )
    if generation_config.output_attentions or generation_config.output_hidden_states:
        raise ValueError(
            "output_attentions / output_hidden_states are not returned by speculative decoding; set them to False "
            "(return_dict_in_generate=True still returns sequences, scores, logits and .speculation)"
        )
    if model.config.is_encoder_decoder:
        raise ValueError(f"speculative decoding needs a decoder-only target, got {type(model).__name__}")


def _check_draft_ids_are_actions(candidates: list[list[int]], rule: AcceptanceRule, layout: ActionLayout | None):
    if rule.is_lossless or layout is None:
        return
    tokenizer = layout.tokenizer
    bad = sorted({t for c in candidates for t in c if not tokenizer.is_action_token(t)})
    if bad:
        raise ValueError(
            f"draft_ids holds non-action token ids {bad[:8]} but relaxed acceptance (bin_tolerance > 0) compares "
            f"action bins: draft only action ids {tokenizer.action_token_begin}..{tokenizer.vocab_size - 1}, or use "
            f"bin_tolerance=0"
        )


# ----------------------------------------------------------------------------- steps
def commit_path(
    state: DecodeState,
    tree: DraftTree,
    path: AcceptedPath,
    past_length: int,
    hidden: torch.Tensor | None,
) -> Commit:
    """Keeps the pending tokens and the accepted path in the target cache (gathered) and says so to drafters.

    Returns:
        the [`Commit`]: kept inputs = pending tokens + path nodes; the token after each; their hidden states.
    """
    num_pending = state.pending_ids.shape[1]
    base = past_length + num_pending
    path_nodes = torch.tensor(path.nodes, dtype=torch.long, device=state.sequence.device)
    if path.nodes == list(range(len(path.nodes))):  # a leftmost path (always for a chain): a prefix, truncate
        truncate_cache(state.target_cache, base + len(path.nodes))
    else:
        keep = torch.cat([torch.arange(base, device=path_nodes.device), base + path_nodes])
        select_cache_positions(state.target_cache, keep)
    path_tokens = tree.token_ids[path_nodes][None]  # [1, A]
    bonus = path_tokens.new_full((1, 1), path.bonus_id)
    root_position = state.pending_positions[:, -1:]
    kept_hidden = None
    if hidden is not None:
        kept_hidden = torch.cat([hidden[:, :num_pending], hidden[:, num_pending + path_nodes]], dim=1)
    return Commit(
        next_token_ids=torch.cat([state.pending_ids[:, 1:], path_tokens, bonus], dim=1),
        positions=torch.cat(
            [state.pending_positions, root_position + 1 + torch.arange(len(path.nodes), device=bonus.device)[None]],
            dim=1,
        ),
        target_hidden=kept_hidden,
        cache_length=base + len(path.nodes),
    )


# ----------------------------------------------------------------------------- the loop
@torch.no_grad()
def speculative_generate(
    model: PreTrainedModel,
    input_ids: torch.LongTensor,
    logits_processor: LogitsProcessorList,
    stopping_criteria: StoppingCriteriaList,
    generation_config: GenerationConfig,
    drafter: Drafter | DraftHead | None = None,
    draft_head: DraftHead | None = None,
    draft_ids: torch.LongTensor | None = None,
    bin_tolerance: int | Sequence[int] = SpeculationConfig.bin_tolerance,
    num_draft_tokens: int | None = SpeculationConfig.num_draft_tokens,
    action_layout: ActionLayout | None = SpeculationConfig.action_layout,
    profile_speculation: bool = SpeculationConfig.profile_speculation,
    **model_kwargs,
) -> SpeculativeDecoderOnlyOutput | torch.LongTensor:
    """Greedy speculative decoding; a ``custom_generate`` callable for ``model.generate``.

    ``generate`` has already prepared ``input_ids`` ``[1, S]``, the logits processors, stopping criteria and
    ``model_kwargs`` (cache, position ids, encoded images). Extra keyword arguments of ``generate`` named like
    the parameters below arrive here (see [`SpeculationConfig`] for the settings).

    Args:
        drafter: a [`Drafter`] or a [`DraftHead`] (``draft_head=`` is the same, kept for older callers).
        draft_ids: ``[1, k]`` or ``[1, C, k]`` drafts of the first generated tokens, known up front: verified
            inside the prefill forward, with or without a drafter.
    Returns:
        ``[1, S + new]`` token ids, or with ``return_dict_in_generate=True`` a [`SpeculativeDecoderOnlyOutput`]
        whose ``.speculation`` is a [`SpeculationStats`].
    """
    if drafter is not None and draft_head is not None:
        raise ValueError("pass drafter= or draft_head=, not both")
    settings = SpeculationConfig(bin_tolerance, num_draft_tokens, action_layout, profile_speculation)
    drafter = as_drafter(drafter if drafter is not None else draft_head, settings.num_draft_tokens)
    _validate_call(model, input_ids, generation_config)
    candidates = None
    if draft_ids is not None:
        vocab_size = model.get_output_embeddings().weight.shape[0]
        candidates = draft_id_candidates(draft_ids, input_ids.shape[0], vocab_size)
        known = CandidateDrafter(candidates)
        drafter = known if drafter is None else ComposedDrafter([known, drafter])
    if drafter is None:
        raise ValueError(
            "speculative_generate needs something to draft with: drafter= (or generate(assistant_model=...)) "
            "and/or draft_ids="
        )
    layout = settings.action_layout or drafter.action_layout
    rule = make_acceptance_rule(settings.bin_tolerance, layout)
    if candidates is not None:
        _check_draft_ids_are_actions(candidates, rule, layout)
    eos_ids = generation_config.eos_token_id
    eos_ids = [] if eos_ids is None else ([eos_ids] if isinstance(eos_ids, int) else list(eos_ids))
    prompt_padding = model_kwargs.get("attention_mask")  # [1, S] or None (no padding)
    session = drafter.start(DraftContext(model, layout, eos_ids, prompt_padding))

    stats = SpeculationStats()
    stopwatch = _Stopwatch(stats, input_ids.device, settings.profile_speculation)
    return_dict = generation_config.return_dict_in_generate
    scores_out = [] if return_dict and generation_config.output_scores else None
    logits_out = [] if return_dict and generation_config.output_logits else None
    total_start = time.perf_counter()

    model_inputs = prefill_inputs(model, input_ids, model_kwargs)
    prompt_positions = model_inputs.get("position_ids")
    if prompt_positions is None:
        prompt_positions = torch.arange(input_ids.shape[1], device=input_ids.device)[None]
    state = DecodeState(
        sequence=input_ids,
        pending_ids=input_ids,
        pending_positions=prompt_positions,
        target_cache=model_inputs["past_key_values"],
        num_generated=0,
        num_action_tokens=0,
    )
    max_length = generation_config.max_length
    finished = False
    while not finished:
        at_prefill = state.num_generated == 0
        # 1. Propose a tree below the root; no path may draft past max_length (the bonus takes the last slot).
        draft_round = DraftRound(
            sequence=state.sequence,
            num_generated=state.num_generated,
            max_depth=max(0, max_length - state.sequence.shape[1] - 1),
            at_prefill=at_prefill,
            root_position=state.pending_positions[:, -1:],
        )
        with stopwatch.section("draft_seconds"):
            tree = session.propose(draft_round).truncate_depth(draft_round.max_depth)

        # 2. Verify every node in one target forward (the prefill's forward when at_prefill).
        past_length = state.target_cache.get_seq_length()
        with stopwatch.section("target_seconds"):
            output = verify_tree(
                model,
                model_inputs if at_prefill else {"past_key_values": state.target_cache},
                state.pending_ids,
                state.pending_positions,
                tree,
                past_length,
                prompt_padding,
                output_hidden=drafter.needs_hidden_states,
            )
        target_ids, target_scores = target_greedy_ids(logits_processor, state.sequence, tree, output.logits)

        # 3. Accept the longest passing path; the bonus token is the target's greedy choice after it.
        path = accept_tree(tree, target_ids, rule, layout, state.num_action_tokens)
        stats.record_verification(tree.max_depth, tree.num_nodes, [tree.sources[n] for n in path.nodes])
        emitted = [int(tree.token_ids[n]) for n in path.nodes] + [path.bonus_id]
        rows = [tree.parents[n].item() + 1 for n in path.nodes] + [path.nodes[-1] + 1 if path.nodes else 0]
        distances = path.distances + [0]

        # 4. Emit token by token so that EOS / max_length / custom criteria stop exactly where greedy would.
        num_emitted = 0
        for token, row, distance in zip(emitted, rows, distances):
            state.sequence = torch.cat([state.sequence, state.sequence.new_full((1, 1), token)], dim=1)
            num_emitted += 1
            if layout is not None and layout.tokenizer.is_action_token(token):
                state.num_action_tokens += 1
                stats.action_bin_distances.append(distance)
            if scores_out is not None:
                scores_out.append(target_scores[row][None])
            if logits_out is not None:
                logits_out.append(output.logits[:, row])
            if bool(stopping_criteria(state.sequence, None).any()):
                finished = True
                break
        state.num_generated += num_emitted
        stats.accept_lengths.append(num_emitted)

        # 5. Commit: keep the pending tokens and the path in the cache; tell the drafters.
        commit = commit_path(state, tree, path, past_length, output.hidden)
        state.pending_ids = commit.next_token_ids[:, -1:]
        state.pending_positions = commit.positions[:, -1:] + 1
        if finished:
            break
        with stopwatch.section("draft_seconds"):
            session.observe(commit)

    stats.num_draft_forwards = session.num_forwards
    stats.total_seconds = time.perf_counter() - total_start
    logger.debug("speculation: %s", stats)
    if not return_dict:
        return state.sequence
    return SpeculativeDecoderOnlyOutput(
        sequences=state.sequence,
        scores=None if scores_out is None else tuple(scores_out),
        logits=None if logits_out is None else tuple(logits_out),
        past_key_values=state.target_cache,
        speculation=stats,
    )
