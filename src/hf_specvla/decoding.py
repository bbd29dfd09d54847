"""The speculative decode loop: draft a chain of tokens with a [`DraftHead`], verify them in one target forward.

Reads as a ladder (gpt-fast style):

    prefill_target -> draft_catch_up -> draft_chain -> verify_drafts -> target_greedy_ids -> accept -> repeat

Invariants kept between rounds (B = 1 in this version):

* ``sequence`` holds the prompt and every emitted token; its last token ``sequence[:, -1]`` has *not* been fed
  to the target yet. The target cache covers ``sequence[:, :-1]``.
* The draft cache has exactly as many entries as the target cache, all computed from true target hidden
  states (drafted-feature entries are dropped after each verification).
* ``catch_up_features[:, -1]`` is the draft head's estimate of the hidden state that will follow the last
  emitted token, from which the next chain starts.

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
from transformers.cache_utils import Cache, DynamicCache

from .acceptance import AcceptanceRule, accepted_prefix_length, action_dimensions, make_acceptance_rule
from .action_tokenizer import ActionTokenizer
from .attention_masks import causal_mask
from .kv_cache import truncate_cache
from .modeling_draft_head import DraftHead, DraftScorer, TargetHandles
from .outputs import SpeculativeDecoderOnlyOutput
from .stats import SpeculationStats

logger = logging.getLogger(__name__)


@dataclass
class SpeculationConfig:
    """Runtime settings of one speculative ``generate`` call (passed as ``generate`` keyword arguments).

    Args:
        bin_tolerance: the paper's r: accept a drafted action token within this many bins of the target's greedy
            token. An int, or one int per action dimension. 0 = lossless (identical to greedy decoding).
        num_draft_tokens: chain length k per verification; None = the draft head's ``config.num_draft_tokens``.
        profile_speculation: synchronise the device around timed forwards so the time breakdown is exact.
    """

    bin_tolerance: int | Sequence[int] = 0
    num_draft_tokens: int | None = None
    profile_speculation: bool = False

    def __post_init__(self):
        k = self.num_draft_tokens
        if k is not None and (isinstance(k, bool) or not isinstance(k, int) or k < 1):
            raise ValueError(f"num_draft_tokens must be an int >= 1 (tokens drafted per verification), got {k!r}")


# ----------------------------------------------------------------------------- state
@dataclass
class DecodeState:
    """Everything one speculative decode carries between rounds (one explicit object, nothing on the models)."""

    sequence: torch.Tensor  # [B, S] prompt + emitted tokens; the last one is not in the target cache yet
    target_cache: Cache
    draft_cache: Cache
    next_position: torch.Tensor  # [B, 1] position id of sequence[:, -1]
    attention_mask: torch.Tensor | None  # [B, S] 2D padding mask, or None when there is no padding
    catch_up_features: torch.Tensor  # [B, q, H] draft features of the last catch-up
    num_prior_action_tokens: torch.Tensor  # [B] action tokens emitted so far
    stats: SpeculationStats


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


# ----------------------------------------------------------------------------- steps
def key_padding(attention_mask: torch.Tensor | None, length: int) -> torch.Tensor | None:
    """Bool ``[B, length]`` "is a real token" mask for the first ``length`` positions; positions past the
    2D ``attention_mask`` (drafted tokens) are real. None when there is no padding at all."""
    if attention_mask is None:
        return None
    if length <= attention_mask.shape[1]:
        return attention_mask[:, :length].bool()
    extra = attention_mask.new_ones(attention_mask.shape[0], length - attention_mask.shape[1])
    return torch.cat([attention_mask, extra], dim=1).bool()


def embed_tokens(handles: TargetHandles, token_ids: torch.Tensor) -> torch.Tensor:
    """Target embeddings ``[B, q, H]`` of ``token_ids`` ``[B, q]``; ids past the embedding (e.g. image
    placeholders of some VLMs) embed as id 0: the hidden state at that position carries the content."""
    num_embeddings = handles.embed_tokens.weight.shape[0]
    safe_ids = torch.where(token_ids < num_embeddings, token_ids, torch.zeros_like(token_ids))
    return handles.embed_tokens(safe_ids)


def prefill_target(model: PreTrainedModel, input_ids: torch.Tensor, model_kwargs: dict):
    """First target forward over the prompt (images included, via the model's own input preparation).

    Returns:
        (cache, last_logits ``[B, V]``, hidden ``[B, S, H]``, position_ids ``[B, S]``)
    """
    model_inputs = model.prepare_inputs_for_generation(input_ids, is_first_iteration=True, **model_kwargs)
    model_inputs["logits_to_keep"] = 1
    outputs = model(**model_inputs, output_hidden_states=True, return_dict=True)
    position_ids = model_inputs.get("position_ids")
    if position_ids is None:
        position_ids = torch.arange(input_ids.shape[1], device=input_ids.device)[None].expand(input_ids.shape[0], -1)
    return outputs.past_key_values, outputs.logits[:, -1].float(), outputs.hidden_states[-1], position_ids


def draft_catch_up(
    draft_head: DraftHead,
    handles: TargetHandles,
    state_cache: Cache,
    next_token_ids: torch.Tensor,
    target_hidden: torch.Tensor,
    position_ids: torch.Tensor,
    padding: torch.Tensor | None,
) -> torch.Tensor:
    """Feeds the draft head the pairs (token x[p+1], true hidden h[p]) for new positions p.

    Args:
        next_token_ids: ``[B, q]`` tokens x[p+1]; target_hidden: ``[B, q, H]`` h[p]; position_ids: ``[B, q]`` p.
    Returns:
        features ``[B, q, H]``; the last one predicts the hidden state after the last emitted token.
    """
    past_len = state_cache.get_seq_length()
    q_len = next_token_ids.shape[1]
    mask = causal_mask(q_len, past_len, target_hidden.dtype, target_hidden.device, padding)
    return draft_head(embed_tokens(handles, next_token_ids), target_hidden, position_ids, mask, state_cache)


def draft_chain(
    draft_head: DraftHead,
    handles: TargetHandles,
    scorer: DraftScorer,
    state: DecodeState,
    num_draft_tokens: int,
) -> tuple[torch.Tensor, int]:
    """Drafts ``num_draft_tokens`` tokens greedily, each from the previous drafted token and feature.

    Returns:
        (draft_ids ``[B, k]``, number of draft forwards run)
    """
    feature = state.catch_up_features[:, -1:]  # [B, 1, H]
    draft_ids = [scorer.token_ids(feature)]  # k x [B, 1]
    position = state.next_position  # drafted token j is fed at the position of the token before it
    for step in range(1, num_draft_tokens):
        past_len = state.draft_cache.get_seq_length()
        padding = key_padding(state.attention_mask, past_len + 1)
        mask = causal_mask(1, past_len, feature.dtype, feature.device, padding)
        feature = draft_head(
            embed_tokens(handles, draft_ids[-1]), feature, position + step - 1, mask, state.draft_cache
        )
        draft_ids.append(scorer.token_ids(feature))
    return torch.cat(draft_ids, dim=1), num_draft_tokens - 1


def verify_drafts(
    model: PreTrainedModel, state: DecodeState, draft_ids: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """One target forward over ``[last emitted token, drafts...]``.

    Returns:
        (target_logits ``[B, 1+k, V]`` float32, target_hidden ``[B, 1+k, H]``)
    """
    verify_ids = torch.cat([state.sequence[:, -1:], draft_ids], dim=1)  # [B, 1+k]
    q_len = verify_ids.shape[1]
    position_ids = state.next_position + torch.arange(q_len, device=verify_ids.device)
    inputs = dict(input_ids=verify_ids, position_ids=position_ids, past_key_values=state.target_cache, use_cache=True)
    if state.attention_mask is not None:
        inputs["attention_mask"] = key_padding(state.attention_mask, state.sequence.shape[1] + q_len - 1).long()
    outputs = model(**inputs, output_hidden_states=True, return_dict=True)
    return outputs.logits.float(), outputs.hidden_states[-1]


def target_greedy_ids(
    logits_processor: LogitsProcessorList, sequence: torch.Tensor, draft_ids: torch.Tensor, target_logits: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The target's greedy token at each verified position, after the logits processors.

    Position j's processors see ``sequence + draft_ids[:, :j]``, exactly what plain greedy decoding would pass
    them if the drafted prefix had been generated.

    Returns:
        (target_ids ``[B, 1+k]``, scores ``[B, 1+k, V]``)
    """
    if len(logits_processor) == 0:
        return target_logits.argmax(dim=-1), target_logits
    candidate = torch.cat([sequence, draft_ids], dim=1)
    cur_len = sequence.shape[1]
    scores = torch.stack(
        [logits_processor(candidate[:, : cur_len + j], target_logits[:, j]) for j in range(target_logits.shape[1])],
        dim=1,
    )
    return scores.argmax(dim=-1), scores


# ----------------------------------------------------------------------------- validation
def _validate_call(model, input_ids, generation_config: GenerationConfig, draft_head) -> None:
    if not isinstance(draft_head, DraftHead):
        raise TypeError(f"draft_head must be a hf_specvla.DraftHead, got {type(draft_head).__name__}")
    if generation_config.do_sample:
        raise ValueError(
            "speculative decoding with a DraftHead is greedy only (do_sample=False); got do_sample=True. Drop "
            "do_sample / temperature, or generate without assistant_model to sample"
        )
    if (generation_config.num_beams or 1) > 1 or (generation_config.num_return_sequences or 1) > 1:
        raise ValueError(
            f"speculative decoding with a DraftHead needs num_beams=1 and num_return_sequences=1, got "
            f"num_beams={generation_config.num_beams}, num_return_sequences={generation_config.num_return_sequences}"
        )
    batch_size = input_ids.shape[0]
    if batch_size != 1:
        raise ValueError(
            f"speculative decoding with a DraftHead supports batch size 1 in this version, got {batch_size} "
            f"sequences; call generate once per sequence, or without assistant_model for batched greedy decoding"
        )
    if generation_config.output_attentions or generation_config.output_hidden_states:
        raise ValueError(
            "output_attentions / output_hidden_states are not returned by speculative decoding; set them to False "
            "(return_dict_in_generate=True still returns sequences, scores, logits and .speculation)"
        )
    if model.config.is_encoder_decoder:
        raise ValueError(f"speculative decoding needs a decoder-only target, got {type(model).__name__}")


# ----------------------------------------------------------------------------- the loop
@torch.no_grad()
def speculative_generate(
    model: PreTrainedModel,
    input_ids: torch.LongTensor,
    logits_processor: LogitsProcessorList,
    stopping_criteria: StoppingCriteriaList,
    generation_config: GenerationConfig,
    draft_head: DraftHead | None = None,
    bin_tolerance: int | Sequence[int] = SpeculationConfig.bin_tolerance,
    num_draft_tokens: int | None = SpeculationConfig.num_draft_tokens,
    profile_speculation: bool = SpeculationConfig.profile_speculation,
    **model_kwargs,
) -> SpeculativeDecoderOnlyOutput | torch.LongTensor:
    """Greedy speculative decoding with a draft head; a ``custom_generate`` callable for ``model.generate``.

    ``generate`` has already prepared ``input_ids`` ``[1, S]``, the logits processors, stopping criteria and
    ``model_kwargs`` (cache, position ids, encoded images). Extra keyword arguments of ``generate`` named like
    the parameters below arrive here (see [`SpeculationConfig`] for their meaning).

    Returns:
        ``[1, S + new]`` token ids, or with ``return_dict_in_generate=True`` a [`SpeculativeDecoderOnlyOutput`]
        whose ``.speculation`` is a [`SpeculationStats`].
    """
    if draft_head is None:
        raise ValueError("speculative_generate needs draft_head=DraftHead(...) (or generate(assistant_model=...))")
    _validate_call(model, input_ids, generation_config, draft_head)
    settings = SpeculationConfig(bin_tolerance, num_draft_tokens, profile_speculation)
    config = draft_head.config
    action_tokenizer: ActionTokenizer = config.action_tokenizer()
    rule: AcceptanceRule = make_acceptance_rule(settings.bin_tolerance, action_tokenizer, config.action_dim)
    max_drafts = settings.num_draft_tokens or config.num_draft_tokens
    handles = draft_head.target_handles(model)
    eos_ids = generation_config.eos_token_id
    eos_ids = [] if eos_ids is None else ([eos_ids] if isinstance(eos_ids, int) else list(eos_ids))
    scorer = draft_head.scorer(handles.lm_head, eos_ids)

    stats = SpeculationStats()
    stopwatch = _Stopwatch(stats, input_ids.device, settings.profile_speculation)
    return_dict = generation_config.return_dict_in_generate
    scores_out = [] if return_dict and generation_config.output_scores else None
    logits_out = [] if return_dict and generation_config.output_logits else None
    total_start = time.perf_counter()

    # 1. Prefill the target on the prompt: it emits the first token.
    with stopwatch.section("target_seconds"):
        target_cache, last_logits, prompt_hidden, prompt_positions = prefill_target(model, input_ids, model_kwargs)
    first_scores = logits_processor(input_ids, last_logits) if len(logits_processor) else last_logits
    first_token = first_scores.argmax(dim=-1, keepdim=True)  # [1, 1]
    sequence = torch.cat([input_ids, first_token], dim=1)
    stats.accept_lengths.append(1)
    if scores_out is not None:
        scores_out.append(first_scores)
    if logits_out is not None:
        logits_out.append(last_logits)
    finished = bool(stopping_criteria(sequence, None).any())

    attention_mask = model_kwargs.get("attention_mask")  # [1, S] or None (no padding)
    if attention_mask is not None:
        attention_mask = torch.cat([attention_mask, attention_mask.new_ones(1, 1)], dim=1)  # covers `sequence`

    # 2. Prefill the draft head on (x[p+1], h[p]) for every prompt position.
    draft_cache = DynamicCache()
    if not finished:
        with stopwatch.section("draft_seconds"):
            features = draft_catch_up(
                draft_head,
                handles,
                draft_cache,
                sequence[:, 1:],
                prompt_hidden,
                prompt_positions,
                key_padding(attention_mask, input_ids.shape[1]),
            )
        stats.num_draft_forwards += 1
    else:
        features = prompt_hidden[:, -1:]
    state = DecodeState(
        sequence=sequence,
        target_cache=target_cache,
        draft_cache=draft_cache,
        next_position=prompt_positions[:, -1:] + 1,
        attention_mask=attention_mask,
        catch_up_features=features,
        num_prior_action_tokens=action_tokenizer.is_action_token(first_token[:, 0]).long(),
        stats=stats,
    )

    max_length = generation_config.max_length
    while not finished:
        # 3. Draft a chain, never past max_length (the bonus token takes the last slot).
        remaining = max_length - state.sequence.shape[1]
        num_drafts = max(0, min(max_drafts, remaining - 1))
        cache_len = state.target_cache.get_seq_length()
        if num_drafts > 0:
            with stopwatch.section("draft_seconds"):
                draft_ids, num_forwards = draft_chain(draft_head, handles, scorer, state, num_drafts)
            stats.num_draft_forwards += num_forwards
        else:
            draft_ids = state.sequence.new_empty(1, 0)

        # 4. Verify every drafted token in one target forward.
        with stopwatch.section("target_seconds"):
            target_logits, verify_hidden = verify_drafts(model, state, draft_ids)
        target_ids, target_scores = target_greedy_ids(logits_processor, state.sequence, draft_ids, target_logits)

        # 5. Accept the longest prefix that passes the rule; the bonus token is the target's greedy choice there.
        dims = action_dimensions(draft_ids, action_tokenizer, state.num_prior_action_tokens, config.action_dim)
        accepted = rule(draft_ids, target_ids[:, :num_drafts], dims)
        num_accepted = int(accepted_prefix_length(accepted)[0])
        emitted = torch.cat([draft_ids[:, :num_accepted], target_ids[:, num_accepted : num_accepted + 1]], dim=1)
        stats.record_verification(num_drafts, num_accepted)

        # 6. Emit token by token so that EOS / max_length / custom criteria stop exactly where greedy would.
        num_emitted = 0
        for i in range(emitted.shape[1]):
            state.sequence = torch.cat([state.sequence, emitted[:, i : i + 1]], dim=1)
            num_emitted += 1
            if scores_out is not None:
                scores_out.append(target_scores[:, i])
            if logits_out is not None:
                logits_out.append(target_logits[:, i])
            if bool(stopping_criteria(state.sequence, None).any()):
                finished = True
                break
        stats.accept_lengths.append(num_emitted)
        if state.attention_mask is not None:
            state.attention_mask = key_padding(state.attention_mask, state.sequence.shape[1]).long()
        state.num_prior_action_tokens += action_tokenizer.is_action_token(emitted[:, :num_emitted]).long().sum(-1)

        # 7. Roll both caches back to the accepted inputs: [last token, accepted drafts].
        kept = num_accepted + 1
        truncate_cache(state.target_cache, cache_len + kept)
        truncate_cache(state.draft_cache, cache_len)
        if finished:
            break
        # 8. Catch the draft head up on the true hidden states of the accepted inputs.
        catch_up_positions = state.next_position + torch.arange(kept, device=draft_ids.device)
        with stopwatch.section("draft_seconds"):
            state.catch_up_features = draft_catch_up(
                draft_head,
                handles,
                state.draft_cache,
                emitted,  # x[p+1] for the accepted inputs = accepted drafts + bonus
                verify_hidden[:, :kept],
                catch_up_positions,
                key_padding(state.attention_mask, cache_len + kept),
            )
        stats.num_draft_forwards += 1
        state.next_position = state.next_position + kept

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
