"""Target forwards: the prefill and every verification, each over pending tokens followed by a draft tree.

One function serves both: the prefill's pending tokens are the whole prompt (images included: the model's own
input preparation runs once and the image features are computed once), a later round's pending token is the
last emitted one. Tree nodes get depth-based position ids and a 4D tree mask; without a tree the model builds
its own causal mask (the cheapest path, identical to a plain decoding step).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from transformers import LogitsProcessorList, PreTrainedModel
from transformers.generation.logits_process import PrefixConstrainedLogitsProcessor

from .masks import sequence_key_padding, to_additive_mask, tree_verification_allowed
from .tree import DraftTree


class TargetOutput(NamedTuple):
    """What a verification forward returns.

    Attributes:
        logits: ``[B, 1 + N, V]`` float32 logits after the root (the last pending token) and after each node.
        hidden: ``[B, P + N, H]`` the last hidden state at every pending token and node, or None if not asked.
    """

    logits: torch.Tensor
    hidden: torch.Tensor | None


def prefill_inputs(model: PreTrainedModel, input_ids: torch.Tensor, model_kwargs: dict) -> dict:
    """The model's own inputs for a first forward over ``input_ids`` ``[B, S]`` (cache, position ids, encoded
    images), as ``generate`` would build them."""
    return model.prepare_inputs_for_generation(input_ids, is_first_iteration=True, **model_kwargs)


def verify_tree(
    model: PreTrainedModel,
    model_inputs: dict,
    pending_ids: torch.Tensor,
    pending_positions: torch.Tensor,
    tree: DraftTree,
    past_length: int,
    prompt_padding: torch.Tensor | None,
    output_hidden: bool,
) -> TargetOutput:
    """One target forward over ``[pending tokens ; tree nodes]`` on top of a cache of ``past_length`` entries.

    Args:
        model_inputs: the other forward inputs (the cache, and at the prefill the model's prepared inputs).
        pending_ids / pending_positions: ``[B, P]`` tokens not yet in the cache and their position ids.
        tree: the draft tree below the last pending token (node at depth d gets position ``last + 1 + d``).
        prompt_padding: ``[B, S]`` the prompt's 2D attention mask, or None when unpadded.
    """
    num_pending, num_nodes = pending_ids.shape[1], tree.num_nodes
    inputs = dict(model_inputs)
    inputs["input_ids"] = torch.cat([pending_ids, tree.token_ids[None]], dim=1) if num_nodes else pending_ids
    root_position = pending_positions[:, -1:]
    if num_nodes:
        inputs["position_ids"] = torch.cat([pending_positions, root_position + 1 + tree.depths[None]], dim=1)
        if tree.is_chain and prompt_padding is None:
            # A chain's tree mask is the causal mask: the model runs its own causal path (the kernels a plain
            # forward uses; in bf16 an explicit mask selects other kernels, whose rounding can flip a near-tied
            # argmax away from plain greedy decoding's).
            inputs["attention_mask"] = None
        else:
            padding = sequence_key_padding(prompt_padding, past_length + num_pending)
            allowed = tree_verification_allowed(past_length, num_pending, tree.ancestor_or_self, padding)
            inputs["attention_mask"] = to_additive_mask(allowed, model.dtype)
    else:
        inputs["position_ids"] = pending_positions
        padding = sequence_key_padding(prompt_padding, past_length + num_pending)
        inputs["attention_mask"] = None if padding is None else padding.long()
    inputs["logits_to_keep"] = num_nodes + 1
    inputs["use_cache"] = True
    outputs = model(**inputs, output_hidden_states=output_hidden, return_dict=True)
    hidden = outputs.hidden_states[-1] if output_hidden else None
    return TargetOutput(outputs.logits.float(), hidden)


def apply_processors(logits_processor: LogitsProcessorList, input_ids: torch.Tensor, scores: torch.Tensor):
    """``logits_processor(input_ids, scores)`` without the list's per-call ``inspect.signature`` of every processor
    (the list only needs it to forward extra kwargs, and none are passed here)."""
    for processor in logits_processor:
        scores = processor(input_ids, scores)
    return scores


def target_greedy_ids(
    logits_processor: LogitsProcessorList, sequence: torch.Tensor, tree: DraftTree, logits: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The target's greedy token after the root and after each node, with the logits processors applied.

    The processors at node i see ``sequence`` + the tokens on node i's path: exactly what plain greedy decoding
    would pass them had that path been generated. Nodes of one depth have prefixes of one length, so they are
    processed as one batch (one call per depth), except under processors that read the batch index
    (``prefix_allowed_tokens_fn``), which see each node alone as batch row 0.

    Args:
        sequence: ``[1, L]`` emitted so far (ending with the root); logits: ``[1, 1 + N, V]``.
    Returns:
        (target_ids ``[1 + N]``, scores ``[1 + N, V]``)
    """
    if len(logits_processor) == 0:
        return logits[0].argmax(dim=-1), logits[0]
    by_row = any(isinstance(p, PrefixConstrainedLogitsProcessor) for p in logits_processor)
    scores = torch.empty_like(logits[0])  # [1 + N, V]
    scores[:1] = apply_processors(logits_processor, sequence, logits[:, 0])
    for depth in range(tree.max_depth):
        nodes = (tree.depths == depth).nonzero()[:, 0]  # [n] nodes at this depth
        # their paths: ancestors (and self) in index order, which is depth order (parents first)
        path_nodes = tree.ancestor_or_self[nodes].nonzero()[:, 1].view(len(nodes), depth + 1)
        input_ids = torch.cat([sequence.expand(len(nodes), -1), tree.token_ids[path_nodes]], dim=1)  # [n, L + d + 1]
        groups = [[i] for i in range(len(nodes))] if by_row else [list(range(len(nodes)))]
        for group in groups:
            rows = nodes[group] + 1
            scores[rows] = apply_processors(logits_processor, input_ids[group], logits[0, rows])
    return scores.argmax(dim=-1), scores
