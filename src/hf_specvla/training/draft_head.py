"""Draft-head training by self-distillation from a frozen target, on accelerate.

Recipe (Spec-VLA section 3.2, following EAGLE):

1. [`build_distillation_dataset`]: run the target greedily over the prompts (images + text); keep the full
   sequence (prompt + the target's *own* action tokens) and the target's last hidden state at every position.
2. [`train_draft_head`]: teacher-forced draft forward over ``(x[p+1], h[p] + noise)``; loss on the positions whose
   next token is a generated action token:

       loss = feature_loss_weight * SmoothL1(features[p], h[p+1])
            + token_loss_weight   * CE(softmax(lm_head(h[p+1])), log_softmax(lm_head(features[p])))

   With ``unroll_steps`` n > 1, training-time test (EAGLE-3): the head then runs n - 1 more steps in which the input
   at position p + j is the head's own feature from step j - 1 (as when it drafts a chain from root p), attending to
   the teacher-forced entries up to p and to its own earlier steps from the same root; each step adds the same loss
   against ``h[p+j+1]``, averaged over the steps. A head v2 reads several of the target's layers
   (``feature_layers``) and the robot's previous action (each example's ``previous_action``).

   AdamW (betas 0.9/0.95), gradient clipping, uniform feature noise, in the one training loop
   (``training.loop``: checkpoints with the full accelerate state, exact resume, one CPU or many GPUs with
   ``accelerate launch``).
3. [`distil_draft_head`]: the whole recipe for a target (a policy, OpenVLA): head, record, folder check, data,
   validation by the engine, training.
"""

from __future__ import annotations

import json
import logging
import resource
import sys
from collections.abc import Callable, Iterable
from pathlib import Path

import torch
from accelerate import Accelerator
from torch.utils.data import Dataset
from transformers import PreTrainedModel
from transformers.cache_utils import DynamicCache

from ..progress import progress_bar
from ..run_folder import fingerprint, fingerprint_arrays, write_json_atomic
from ..speculative import (
    DraftHead,
    DraftHeadDrafter,
    SpeculationStats,
    TargetHandles,
    embed_tokens,
    encode_images,
    prompt_input_embeddings,
    read_hidden_states,
    reads_encoded_images,
    softcap_logits,
    speculative_generate,
    to_additive_mask,
)
from .checkpoints import check_output_dir, latest_checkpoint, prepare_output_dir, training_record
from .configuration import HEAD_VERSIONS, DraftTrainingConfig, check_draft_chain
from .loop import TrainingJob, run_training
from .processes import is_main_process, mean_over_processes

logger = logging.getLogger(__name__)

__all__ = [
    "DraftTrainingConfig",
    "accuracy_by_position",
    "build_distillation_dataset",
    "head_settings",
    "head_v2_settings",
    "head_v3_settings",
    "latest_checkpoint",
    "speculative_acceptance",
    "train_draft_head",
]


# ----------------------------------------------------------------------------- data
#: The batch key of each example's index in its dataset ``[B]`` (the training loss seeds its noise by it).
EXAMPLE_INDEX = "example_index"


class DistillationDataset(Dataset):
    """Sequences the target generated, with its hidden states.

    Each item: ``input_ids`` ``[L]`` (prompt + generated tokens), ``hidden`` ``[L, n H]`` (the target's hidden states
    at each position: the head's ``feature_layers``, then the last one when they do not include it: the loss's
    targets), ``loss_mask`` ``[L]`` (True at positions p whose token x[p+2] is a generated action token, i.e. where
    the draft head's prediction is used), ``first_position`` (0-dim: the first generated token's position) and
    ``previous_action`` ``[D]`` (the robot's previous action as token ids, -1 where there was none).
    """

    def __init__(self, examples: list[dict[str, torch.Tensor]]):
        if not examples:
            raise ValueError("a DistillationDataset needs at least one example")
        self.examples = examples

    def __len__(self) -> int:
        return len(self.examples)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        return {**self.examples[index], EXAMPLE_INDEX: torch.tensor(index)}

    def save(self, path: str | Path) -> None:
        torch.save(self.examples, path)

    @classmethod
    def load(cls, path: str | Path) -> DistillationDataset:
        return cls(torch.load(path, weights_only=True))


def dataset_hidden_layers(hidden_state_layers: tuple[int, ...]) -> tuple[int, ...]:
    """The target hidden states a distillation set stores for a head reading ``hidden_state_layers``: those, then the
    last one (what the loss's targets are made of) when they do not include it."""
    layers = tuple(hidden_state_layers)
    return layers if -1 in layers else (*layers, -1)


#: a prompt dict's optional key: each example's previous action (``[B, D]`` token ids, -1: none), not a model input
PREVIOUS_ACTION = "previous_action"
#: how [`distil_draft_head`] stores the target's hidden states: half of float32's memory (the set is most of a large
#: run's memory); float16 keeps 11 significant bits (relative error < 5e-4), far below the training's feature noise
STORED_HIDDEN_DTYPE = torch.float16
#: the file in a run's folder that records its distillation set (what a resumed run's rebuilt set must equal)
DATA_RECORD = "distillation_set.json"


@torch.no_grad()
def build_distillation_dataset(
    target: PreTrainedModel,
    prompts: Iterable[dict[str, torch.Tensor]],
    max_new_tokens: int,
    action_tokenizer,
    progress: bool = True,
    hidden_state_layers: tuple[int, ...] = (-1,),
    action_dim: int | None = None,
    hidden_dtype: torch.dtype = torch.float32,
    image_features: bool = False,
) -> DistillationDataset:
    """Runs the target greedily on each prompt and records its sequence and hidden states.

    The prompts are read one at a time (a lazy sequence such as ``policy_draft.PolicyPrompts`` builds each batch's
    images only when it is read), so that only the distillation set itself grows with the frames.

    Args:
        target: the frozen target (any model ``generate`` works on; images go in the prompt dicts).
        prompts: model inputs, e.g. ``{"input_ids": [B, S], "pixel_values": [B, 3, H, W]}``, and optionally
            ``previous_action`` ``[B, D]`` (each example's previous action as token ids, -1: none; not a model
            input). A dict may hold several examples (batched generation) when it has no padding; with an
            ``attention_mask`` that has padding, give one example per dict. The progress bar counts examples, of
            ``prompts.num_examples`` (or, for a list, of its dicts' examples).
        max_new_tokens: tokens the target generates (an action's worth: OpenVLA 7).
        action_tokenizer: which generated tokens count for the loss.
        hidden_state_layers: the target hidden states the head reads (its ``config.hidden_state_layers``).
        action_dim: D, the previous action's length when no prompt gives one (default: 1).
        hidden_dtype: how the hidden states are stored (the loss casts each batch back to the head's dtype):
            ``torch.float16`` halves the set ([`STORED_HIDDEN_DTYPE`], what [`distil_draft_head`] stores).
        image_features: also record what the target's language model reads at each prompt image token (the encoded
            image: ``image_positions`` ``[n]``, ``image_embeddings`` ``[n, H]`` in ``hidden_dtype``), for a head with
            ``prefill_image_features``.

    Raises:
        ValueError: a hidden state too large for ``hidden_dtype`` (naming the largest; store float32).
    """
    target.eval()
    examples = []
    layers = dataset_hidden_layers(hidden_state_layers)
    total = getattr(prompts, "num_examples", None)  # examples done / total (unknown for an iterator)
    if total is None and isinstance(prompts, list | tuple):
        total = sum(int(inputs["input_ids"].shape[0]) for inputs in prompts)
    bar = progress_bar(total=total, desc="self-distillation data", unit="example", disable=not progress)
    for inputs in prompts:
        batch = _distil_prompt(
            target, inputs, max_new_tokens, action_tokenizer, layers, action_dim, hidden_dtype, image_features
        )
        examples.extend(batch)
        del inputs  # this prompt's images: only one prompt's are alive at a time
        bar.update(len(batch))
    bar.close()
    return DistillationDataset(examples)


def _distil_prompt(
    target: PreTrainedModel,
    inputs: dict,
    max_new_tokens: int,
    action_tokenizer,
    layers: tuple[int, ...],
    action_dim: int | None,
    hidden_dtype: torch.dtype,
    image_features: bool = False,
) -> list[dict]:
    """[`build_distillation_dataset`]'s examples of one prompt dict (see there)."""
    inputs = {k: v.to(target.device) if isinstance(v, torch.Tensor) else v for k, v in inputs.items()}
    batch_size = inputs["input_ids"].shape[0]
    previous = inputs.pop(PREVIOUS_ACTION, None)
    if previous is None:
        previous = torch.full((batch_size, action_dim or 1), -1, dtype=torch.long)
    mask = inputs.get("attention_mask")
    if inputs["input_ids"].shape[0] != 1 and mask is not None and not bool(mask.all()):
        raise ValueError("prompts with padding must be given one example per dict (batch size 1)")
    # Greedy to exactly max_new_tokens tokens, so every example has the same layout.
    sequences = target.generate(
        **inputs, max_new_tokens=max_new_tokens, min_new_tokens=max_new_tokens, do_sample=False
    )  # [B, L]
    forward_inputs = dict(inputs, input_ids=sequences)
    if mask is not None:
        forward_inputs["attention_mask"] = torch.cat([mask, mask.new_ones(mask.shape[0], max_new_tokens)], 1)
    hidden = read_hidden_states(target(**forward_inputs, output_hidden_states=True).hidden_states, layers)
    stored = _narrowed(hidden, hidden_dtype).cpu()  # [B, L, n H]
    prompt_len, length = inputs["input_ids"].shape[1], sequences.shape[1]
    images = _prompt_images(target, inputs, hidden_dtype) if image_features else [{}] * batch_size
    positions = torch.arange(length)
    examples = []
    for ids, row_states, row_previous, row_images in zip(sequences.cpu(), stored, previous.cpu(), images):
        generated_action = (positions >= prompt_len) & action_tokenizer.is_action_token(ids)
        loss_mask = torch.zeros(length, dtype=torch.bool)
        loss_mask[: length - 2] = generated_action[2:]  # position p predicts token p+2
        examples.append(
            {
                "input_ids": ids,
                "hidden": row_states,
                "loss_mask": loss_mask,
                "first_position": torch.tensor(prompt_len),
                PREVIOUS_ACTION: row_previous.long(),
                **row_images,
            }
        )
    return examples


def _prompt_images(target: PreTrainedModel, inputs: dict, dtype: torch.dtype) -> list[dict]:
    """Per example of ``inputs``: ``image_positions`` ``[n]`` (the prompt's image tokens) and ``image_embeddings``
    ``[n, H]`` (what the target's language model reads there: the encoded image), as a ``generate`` call gives a
    drafter ([`prompt_input_embeddings`])."""
    encoded = encode_images(target, inputs)
    embeddings = prompt_input_embeddings(target, inputs["input_ids"], {"mm_encoder_outputs": {"image": encoded}})
    image_token_id = getattr(target.config, "image_token_id", None)
    rows = []
    for ids, row in zip(inputs["input_ids"], embeddings):
        where = (ids == image_token_id).nonzero()[:, 0] if image_token_id is not None else ids.new_zeros(0)
        rows.append({"image_positions": where.cpu(), "image_embeddings": _narrowed(row[where], dtype).cpu()})
    return rows


def _narrowed(hidden: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``hidden`` as ``dtype``, refused where that overflows (float16's largest value is 65504)."""
    narrowed = hidden.to(dtype)
    if narrowed.dtype != hidden.dtype and not bool(torch.isfinite(narrowed).all()) and bool(hidden.isfinite().all()):
        raise ValueError(
            f"the target's hidden states reach {hidden.abs().max().item():.4g}, more than {dtype} holds: build the "
            f"distillation set with hidden_dtype=torch.float32"
        )
    return narrowed


def collate_distillation(batch: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Right-pads a list of dataset items to ``input_ids`` ``[B, L]``, ``hidden`` ``[B, L, n H]``,
    ``loss_mask`` ``[B, L]``, ``padding_mask`` ``[B, L]`` (True = real token), ``first_position`` ``[B, 1]`` and
    ``previous_action`` ``[B, D]`` (items saved before head v2, without them: their prompt's end unknown, -1, and no
    previous action); from a set built with ``image_features``, ``image_embeddings`` ``[B, L, H]`` and ``image_mask``
    ``[B, L]`` (True at the prompts' image tokens)."""
    length = max(item["input_ids"].shape[0] for item in batch)
    hidden_size = batch[0]["hidden"].shape[-1]
    out = {
        "input_ids": torch.zeros(len(batch), length, dtype=torch.long),
        "hidden": torch.zeros(len(batch), length, hidden_size, dtype=batch[0]["hidden"].dtype),
        "loss_mask": torch.zeros(len(batch), length, dtype=torch.bool),
        "padding_mask": torch.zeros(len(batch), length, dtype=torch.bool),
    }
    for i, item in enumerate(batch):
        n = item["input_ids"].shape[0]
        out["input_ids"][i, :n] = item["input_ids"]
        out["hidden"][i, :n] = item["hidden"]
        out["loss_mask"][i, :n] = item["loss_mask"]
        out["padding_mask"][i, :n] = True
    out["first_position"] = torch.tensor([[int(item.get("first_position", -1))] for item in batch])
    out[EXAMPLE_INDEX] = torch.tensor([int(item.get(EXAMPLE_INDEX, -1)) for item in batch])
    dims = {item[PREVIOUS_ACTION].shape[0] for item in batch if PREVIOUS_ACTION in item} or {1}
    out[PREVIOUS_ACTION] = torch.full((len(batch), max(dims)), -1, dtype=torch.long)
    for i, item in enumerate(batch):
        if PREVIOUS_ACTION in item:
            out[PREVIOUS_ACTION][i, : item[PREVIOUS_ACTION].shape[0]] = item[PREVIOUS_ACTION]
    if all("image_embeddings" in item for item in batch):  # a set built with image_features
        width = batch[0]["image_embeddings"].shape[-1]
        out["image_embeddings"] = torch.zeros(len(batch), length, width, dtype=batch[0]["image_embeddings"].dtype)
        out["image_mask"] = torch.zeros(len(batch), length, dtype=torch.bool)
        for i, item in enumerate(batch):
            out["image_embeddings"][i, item["image_positions"]] = item["image_embeddings"]
            out["image_mask"][i, item["image_positions"]] = True
    return out


# ----------------------------------------------------------------------------- loss
def unrolled_features(
    draft_head: DraftHead,
    handles: TargetHandles,
    batch: dict[str, torch.Tensor],
    inputs_hidden: torch.Tensor,
    num_steps: int,
) -> list[torch.Tensor]:
    """The head's features over a batch, unrolled ``num_steps`` draft steps (training-time test).

    Step 0 is teacher-forced: the input at position p is ``(x[p+1], h[p])``. At step j >= 1 the query of root r (one
    per position, r = 0..T-1) is fed at position ``r + j`` with token ``x[r+j+1]`` and the head's own step-(j-1)
    feature of root r, seeing the step-0 entries 0..r and its own entries of steps 1..j: exactly what a chain drafted
    from root r computes when its drafts were right.

    Args:
        batch: a [`collate_distillation`] batch (``input_ids`` ``[B, L]``, ``padding_mask``, ``first_position``,
            ``previous_action``).
        inputs_hidden: ``[B, T, n H]`` (T = L - 1) the step-0 hidden inputs h[p] (noise added by the caller).
    Returns:
        ``num_steps`` tensors ``[B, T, H]``: step j's feature of root r estimates ``h[r+j+1]`` (predicts x[r+j+2]).
    """
    input_ids = batch["input_ids"]
    batch_size, steps = input_ids.shape[0], input_ids.shape[1] - 1
    dtype = inputs_hidden.dtype
    positions = torch.arange(steps, device=input_ids.device)[None].expand(batch_size, -1)
    previous = _previous_bins(draft_head, batch) if draft_head.config.previous_action_input else None
    first_position = batch["first_position"].to(input_ids.device)
    valid_keys = batch["padding_mask"][:, :-1]  # [B, T]
    cache = DynamicCache() if num_steps > 1 else None
    features, outputs = inputs_hidden, []
    for step in range(num_steps):
        # the token of root r's step: x[r+step+1] (past the sequence: padding, never scored)
        token_ids = input_ids[:, step + 1 :]
        token_ids = torch.cat([token_ids, token_ids.new_zeros(batch_size, step)], dim=1)
        step_positions = positions + step
        mask = _unrolled_mask(valid_keys, step, dtype)
        bins = None if previous is None else draft_head.slot_bins(previous, first_position, step_positions)
        features = draft_head(embed_tokens(handles, token_ids).to(dtype), features, step_positions, mask, cache, bins)
        outputs.append(features)
    return outputs


def block_features(
    draft_head: DraftHead,
    handles: TargetHandles,
    batch: dict[str, torch.Tensor],
    inputs_hidden: torch.Tensor | None,
    roots: torch.Tensor,
    num_queries: int,
) -> torch.Tensor:
    """The head's block from one root per example, in one forward (head v3; what ``head_block.block_round`` drafts):
    the teacher-forced pairs ``(x[p+1], h[p])`` at p = 0..r, then ``num_queries`` mask queries at r + 1 .., each
    seeing the pairs and the queries before it.

    Args:
        batch: a [`collate_distillation`] batch (right-padded).
        inputs_hidden: ``[B, T, n H]`` the pairs' hidden inputs h[p] (noise added by the caller), or None: missing (the
            block drafted before the prefill).
        roots: ``[B]`` int64, each example's root r (its last pair).
    Returns:
        ``[B, N, H]`` (N = the longest row's pairs + M) the feature of every slot, slot n at position n: a pair's
        (teacher-forced, as a chain's first step from root n) or a query's; [`block_entries`] reads a block's.
    """
    input_ids = batch["input_ids"]
    batch_size, device = input_ids.shape[0], input_ids.device
    num_pairs = roots[:, None] + 1  # [B, 1]
    length = int(num_pairs.max()) + num_queries
    slots = torch.arange(length, device=device)[None]  # [1, N]: slot n holds position n
    is_pair = slots < num_pairs
    token_ids = torch.cat([input_ids[:, 1:], input_ids.new_zeros(batch_size, length)], dim=1)[:, :length]
    query_embeds, missing = draft_head.mask_query_inputs(batch_size, length)
    pair_embeds = embed_tokens(handles, token_ids).to(query_embeds.dtype)
    if inputs_hidden is None and draft_head.config.prefill_image_features:  # the prompt as the target's LM reads it
        pair_embeds = _with_image_embeddings(batch, pair_embeds)
    embeds = torch.where(is_pair[..., None], pair_embeds, query_embeds)
    if inputs_hidden is None:
        hidden = missing
    else:
        fused = draft_head.fuse_features(inputs_hidden)[:, :length]
        fused = torch.cat([fused, missing[:, : length - fused.shape[1]]], dim=1)
        hidden = torch.where(is_pair[..., None], fused.to(missing.dtype), missing)
    valid_keys = slots < num_pairs + num_queries  # [B, N]
    allowed = (slots.T >= slots)[None] & valid_keys[:, None, :]  # [B, N, N] causal over the row's slots
    mask = to_additive_mask(allowed, embeds.dtype)
    positions = slots.expand(batch_size, -1)
    bins = None
    if draft_head.config.previous_action_input:
        first_position = batch["first_position"].to(device)
        bins = draft_head.slot_bins(_previous_bins(draft_head, batch), first_position, positions)
    return draft_head(embeds, hidden, positions, mask, None, bins)  # [B, N, H]


def _with_image_embeddings(batch: dict[str, torch.Tensor], pair_embeds: torch.Tensor) -> torch.Tensor:
    """``pair_embeds`` ``[B, N, H]`` (slot n: token x[n+1]) with the slots whose token is an image token holding the
    encoded image there (the batch's ``image_embeddings``), as ``head_block.block_round`` reads them before the
    prefill.

    Raises:
        ValueError: a batch without image embeddings (a set built without ``image_features``).
    """
    if "image_embeddings" not in batch:
        raise ValueError(
            "this draft head reads the prompt's encoded images before the prefill (prefill_image_features): build "
            "its distillation set with build_distillation_dataset(..., image_features=True)"
        )
    length = pair_embeds.shape[1]
    images = batch["image_embeddings"][:, 1 : length + 1].to(pair_embeds)
    is_image = batch["image_mask"][:, 1 : length + 1].to(pair_embeds.device)
    width = min(images.shape[1], length)
    images = torch.cat([images, images.new_zeros(images.shape[0], length - width, images.shape[-1])], dim=1)
    is_image = torch.cat([is_image, is_image.new_zeros(is_image.shape[0], length - width)], dim=1)
    return torch.where(is_image[..., None], images, pair_embeds)


def block_entries(features: torch.Tensor, roots: torch.Tensor, num_queries: int) -> torch.Tensor:
    """[`block_features`]' ``[B, N, H]`` -> the blocks' ``[B, 1 + M, H]``: the last pair's feature (entry 0), then the
    queries'; entry j estimates ``h[r+j+1]`` (drafts x[r+j+2])."""
    drafting = roots[:, None] + torch.arange(num_queries + 1, device=features.device)[None]
    return features.gather(1, drafting[..., None].expand(-1, -1, features.shape[-1]))


def _uniform_rows(
    generators: list[torch.Generator] | None, lengths: list[int], width: int, batch: int, length: int
) -> torch.Tensor:
    """``[batch, length, width]`` uniform [0, 1) numbers: row i's first ``lengths[i]`` positions from
    ``generators[i]`` (the rest 0: padding); without generators, the whole from torch's global generator."""
    if generators is None:
        return torch.rand(batch, length, width)
    out = torch.zeros(batch, length, width)
    for row, (generator, n) in enumerate(zip(generators, lengths, strict=True)):
        out[row, :n] = torch.rand(n, width, generator=generator)
    return out


def _block_roots(batch: dict[str, torch.Tensor], generators: list[torch.Generator] | None) -> torch.Tensor:
    """``[B]`` one root per example for block training: drawn uniformly among the roots a block is drafted from after
    the prefill (the last pair at or after the prompt's end - 1, with a token left to draft)."""
    first = batch["first_position"][:, 0]
    last = batch["padding_mask"].sum(1) - 3  # the last root with a token x[r+2] to draft
    low = (first - 1).clamp(min=0).minimum(last)
    draw = _uniform_rows(generators, [1] * len(first), 1, len(first), 1).view(-1)
    return (low + (draw * (last - low + 1)).long()).minimum(last)


def example_generators(batch: dict[str, torch.Tensor], seed: int, step: int) -> list[torch.Generator]:
    """One generator per example of ``batch``, seeded by ``(seed, step, its index in the dataset)``: an example draws
    the same noise whichever batch, process or resumed run it is in."""
    return [torch.Generator().manual_seed(hash((seed, step, int(index))) % 2**63) for index in batch[EXAMPLE_INDEX]]


def distillation_loss(
    draft_head: DraftHead,
    handles: TargetHandles,
    batch: dict[str, torch.Tensor],
    config: DraftTrainingConfig,
    generators: list[torch.Generator] | None = None,
) -> dict[str, torch.Tensor]:
    """EAGLE objective on one batch (see module docstring), unrolled ``config.unroll_steps`` draft steps
    ([`unrolled_features`]; a block head's steps are its mask queries). Returns ``loss``, ``feature_loss``,
    ``token_loss`` and ``token_accuracy`` (draft argmax == target argmax on the loss positions), each averaged over the
    steps, and ``step_accuracy`` ``[n]`` (each step's accuracy). A head that drafts before the prefill
    (``prefill_drafts``) adds the same objective on its pre-prefill block (the prompt's tokens with missing hidden
    states, scored from the root before the first action token only) to ``loss``, and reports
    ``prefill_token_accuracy`` and ``prefill_step_accuracy`` ``[n]`` (step j: the action's token j)."""
    input_ids, hidden = batch["input_ids"], batch["hidden"]  # [B, L], [B, L, n H (+ H)]
    dtype = next(draft_head.parameters()).dtype
    hidden = hidden.to(dtype)
    head_config = draft_head.config
    width, layers = head_config.hidden_size, head_config.hidden_state_layers
    stored = dataset_hidden_layers(layers)
    if hidden.shape[-1] != len(stored) * width:
        raise ValueError(
            f"the distillation set holds {hidden.shape[-1] // width} hidden states per position, but this head reads "
            f"layers {list(layers)} (and the loss the last one): {len(stored)}; build the set for this head "
            f"(build_distillation_dataset(..., hidden_state_layers=head.config.hidden_state_layers))"
        )
    top = stored.index(-1)
    target_top = hidden[..., top * width : (top + 1) * width]  # [B, L, H] the target's last hidden state
    inputs_hidden = hidden[:, :-1, : len(layers) * width]  # h[p], p = 0..L-2
    if config.feature_noise > 0:  # each example's own noise (``generators``: one per example, see example_generators)
        lengths = (batch["padding_mask"].sum(1) - 1).tolist()
        noise = _uniform_rows(generators, lengths, inputs_hidden.shape[-1], *inputs_hidden.shape[:2])
        inputs_hidden = (
            inputs_hidden + (noise.to(inputs_hidden.device, inputs_hidden.dtype) - 0.5) * config.feature_noise
        )
    positions = torch.arange(input_ids.shape[1] - 1, device=input_ids.device)[None]
    cap = head_config.final_logit_softcapping  # the target caps its logits (Gemma-2): so does the loss
    target_features_all = target_top[:, 1:]  # [B, T, H]: h[p+1], what input p's feature estimates
    with torch.no_grad():
        target_logits_all = softcap_logits(handles.lm_head(target_features_all).float(), cap)  # [B, T, V]
    targets = (target_features_all, target_logits_all, batch["loss_mask"][:, :-1])
    queries = config.unroll_steps - 1
    if head_config.draft_mode == "block":  # one block from one root per example (no training-time test to do)
        roots = _block_roots(batch, generators).to(input_ids.device)
        features = block_features(draft_head, handles, batch, inputs_hidden, roots, queries)
        # the first draft from every pair up to the root, teacher-forced (as a chain's first step), then the queries
        pairs = min(features.shape[1], target_features_all.shape[1])
        before_root = torch.arange(pairs, device=roots.device)[None] <= roots[:, None]
        target_features, target_logits, loss_mask = (values[:, :pairs] for values in targets)
        first = (features[:, :pairs], target_features, target_logits, loss_mask & before_root)
        block = _block_steps(block_entries(features, roots, queries), roots, targets)
        losses = _step_losses(handles, [first, *block[1:]], config, cap)
    else:
        all_features = unrolled_features(draft_head, handles, batch, inputs_hidden, config.unroll_steps)
        # root r's step predicts x[r+step+2], the target's h[r+step+1]; scored where that is a generated action
        # token (and, past step 0, where r is a root a chain is drafted from: at or after the prompt's end - 2)
        roots = positions + 2 >= batch["first_position"].to(positions.device)
        steps = []
        for step, features in enumerate(all_features):
            target_features, target_logits, loss_mask = (_shifted(values, step) for values in targets)
            steps.append((features, target_features, target_logits, loss_mask & roots if step else loss_mask))
        losses = _step_losses(handles, steps, config, cap)
    if head_config.prefill_drafts:  # the block drafted before the prefill: from the prompt's last pair
        roots = (batch["first_position"][:, 0] - 2).to(input_ids.device)
        features = block_entries(block_features(draft_head, handles, batch, None, roots, queries), roots, queries)
        prefill = _step_losses(handles, _block_steps(features, roots, targets), config, cap)
        losses["loss"] = losses["loss"] + prefill.pop("loss")
        losses["prefill_token_accuracy"] = prefill["token_accuracy"]
        losses["prefill_step_accuracy"] = prefill["step_accuracy"]
    return losses


def _block_steps(features: torch.Tensor, roots: torch.Tensor, targets: tuple) -> list[tuple]:
    """A block's ``[B, 1 + M, H]`` features (entry j of root r drafts x[r+j+2]) as [`_step_losses`]' steps: each
    ``(features [B, 1, H], target features, target logits, loss mask [B, 1])``, the targets (``[B, T, ...]`` each, at
    input p: h[p+1], its logits, whether x[p+2] is a generated action token) read at r + j."""
    steps = []
    for step in range(features.shape[1]):
        index = roots[:, None] + step  # [B, 1]
        inside = index < targets[0].shape[1]
        index = index.clamp(max=targets[0].shape[1] - 1)
        read = []
        for values in targets:
            spread = index.reshape(index.shape + (1,) * (values.ndim - 2)).expand(-1, -1, *values.shape[2:])
            read.append(values.gather(1, spread))
        steps.append((features[:, step : step + 1], read[0], read[1], read[2] & inside))
    return steps


def _step_losses(handles: TargetHandles, steps: list[tuple], config: DraftTrainingConfig, cap: float | None) -> dict:
    """The objective over draft steps, each ``(features [B, X, H], target features [B, X, H], target logits
    [B, X, V], loss mask [B, X])``: SmoothL1 on the features and soft cross-entropy on the logits where the mask is
    True, each averaged over ``config.unroll_steps``; ``step_accuracy`` ``[n]`` each step's top-1.

    Each mean is over the step's positions in the *global* batch: under n launched processes, a process divides its
    sum by the positions of every process over n (``processes.mean_over_processes``), so that the gradients, which
    ``DistributedDataParallel`` averages, are one process's on the whole batch, whatever each process's share held."""
    totals = {"feature_loss": 0.0, "token_loss": 0.0, "token_accuracy": 0.0}
    step_accuracy = []
    for features, target_features, target_logits, loss_mask in steps:
        n = mean_over_processes(loss_mask.sum().float()).clamp(min=1e-6)
        feature_loss = torch.nn.functional.smooth_l1_loss(features, target_features, reduction="none").mean(-1)
        feature_loss = (feature_loss * loss_mask).sum() / n
        target_logits = target_logits[loss_mask]
        target_probs = target_logits.softmax(-1)
        draft_logits = softcap_logits(handles.lm_head(features[loss_mask]).float(), cap)
        token_loss = -(target_probs * draft_logits.log_softmax(-1)).sum(-1).sum() / n
        accuracy = (draft_logits.argmax(-1) == target_logits.argmax(-1)).float().sum() / n
        totals["feature_loss"] = totals["feature_loss"] + feature_loss / config.unroll_steps
        totals["token_loss"] = totals["token_loss"] + token_loss / config.unroll_steps
        totals["token_accuracy"] = totals["token_accuracy"] + accuracy.detach() / config.unroll_steps
        step_accuracy.append(accuracy.detach())
    loss = config.feature_loss_weight * totals["feature_loss"] + config.token_loss_weight * totals["token_loss"]
    return {"loss": loss, **totals, "step_accuracy": torch.stack(step_accuracy)}


@torch.no_grad()
def accuracy_by_position(
    draft_head: DraftHead, target: PreTrainedModel, dataset: DistillationDataset, batch_size: int = 32
) -> dict[str, list[float]]:
    """Top-1 of the head's drafts at each token of the action on ``dataset`` (its tokens are the target's own greedy
    ones), computed as the head drafts: no feature noise, the tokens its drafting scores (``draft_action_tokens_only``).

    Returns:
        ``after_prefill``: ``[n]`` (n = ``num_draft_tokens``) from the root after a prefill that emitted the action's
        token 0: entry j is the action's token j + 1 (a chain's step j given right drafts before it, a block's entry
        j); and for a head with ``prefill_drafts`` ``before_prefill``: ``[n]``, the pre-prefill block's token j.
    """
    handles = draft_head.target_handles(target)
    scorer = draft_head.scorer(handles.lm_head, _eos_ids(target))
    steps, config = draft_head.config.num_draft_tokens, draft_head.config
    width, layers = config.hidden_size, config.hidden_state_layers
    modes = ["after_prefill"] + (["before_prefill"] if config.prefill_drafts else [])
    right, counted = torch.zeros(len(modes), steps), torch.zeros(len(modes), steps)
    for start in range(0, len(dataset), batch_size):
        batch = collate_distillation([dataset[i] for i in range(start, min(start + batch_size, len(dataset)))])
        batch = {name: value.to(draft_head.device) for name, value in batch.items()}
        input_ids, first = batch["input_ids"], batch["first_position"][:, 0]
        inputs_hidden = batch["hidden"][:, :-1, : len(layers) * width].to(next(draft_head.parameters()).dtype)
        for m, mode in enumerate(modes):
            roots = first - (1 if mode == "after_prefill" else 2)  # [B]
            if mode == "after_prefill" and config.draft_mode == "chain":
                unrolled = unrolled_features(draft_head, handles, batch, inputs_hidden, steps)  # every root
                index = roots[:, None, None].expand(-1, 1, width)
                features = torch.cat([f.gather(1, index) for f in unrolled], dim=1)  # [B, n, H]
            else:
                hidden = inputs_hidden if mode == "after_prefill" else None
                features = block_features(draft_head, handles, batch, hidden, roots, steps - 1)
                features = block_entries(features, roots, steps - 1)  # [B, n, H]
            label_at = roots[:, None] + torch.arange(steps, device=input_ids.device)[None] + 2  # [B, n]
            valid = label_at < batch["padding_mask"].sum(1, keepdim=True)
            labels = input_ids.gather(1, label_at.clamp(max=input_ids.shape[1] - 1))
            right[m] += ((scorer.token_ids(features) == labels) & valid).sum(0).float().cpu()
            counted[m] += valid.sum(0).float().cpu()
    return {mode: [round(x, 4) for x in (right[m] / counted[m].clamp(min=1)).tolist()] for m, mode in enumerate(modes)}


def _eos_ids(target: PreTrainedModel) -> list[int]:
    """The target's EOS ids (what a drafting scorer scores beside the action tokens)."""
    eos = getattr(target.generation_config, "eos_token_id", None)
    return [] if eos is None else [eos] if isinstance(eos, int) else list(eos)


def _shifted(values: torch.Tensor, step: int) -> torch.Tensor:
    """``values`` ``[B, T, ...]`` moved ``step`` positions left (root r gets position r + step's), zeros past the
    end."""
    return torch.cat([values[:, step:], values[:, :step].new_zeros(values[:, :step].shape)], dim=1)


def _previous_bins(draft_head: DraftHead, batch: dict[str, torch.Tensor]) -> torch.Tensor:
    """``[B, D]`` the examples' previous-action bins (``n_action_bins`` where an example has none)."""
    ids = batch[PREVIOUS_ACTION]
    action_dim = draft_head.config.action_dim
    if bool((ids < 0).all()):  # no example has one
        return draft_head.no_previous_action(ids.device).expand(ids.shape[0], -1)
    if ids.shape[1] != action_dim:
        raise ValueError(
            f"the distillation set's previous actions have {ids.shape[1]} tokens, the head's actions "
            f"{action_dim}: build the set with the policy's previous actions"
        )
    tokenizer = draft_head.config.action_tokenizer()
    known = tokenizer.is_action_token(ids).all(dim=1, keepdim=True)  # [B, 1]: a whole previous action
    none = torch.full_like(ids, draft_head.config.n_action_bins)
    return torch.where(known, tokenizer.token_to_bin(ids), none)


def _unrolled_mask(valid_keys: torch.Tensor, step: int, dtype: torch.dtype) -> torch.Tensor:
    """``[B, 1, T, (step + 1) T]`` additive mask of unrolled step ``step``: query r sees the teacher-forced entries
    0..r (valid ones) and its own entries of steps 1..step (the same r), as a chain drafted from root r does."""
    batch_size, steps = valid_keys.shape
    causal = torch.ones(steps, steps, dtype=torch.bool, device=valid_keys.device).tril()
    blocks = [causal[None] & valid_keys[:, None, :]]
    diagonal = torch.eye(steps, dtype=torch.bool, device=valid_keys.device)[None].expand(batch_size, -1, -1)
    blocks += [diagonal] * step
    return to_additive_mask(torch.cat(blocks, dim=-1), dtype)


# ----------------------------------------------------------------------------- training
def train_draft_head(
    draft_head: DraftHead,
    target: PreTrainedModel,
    dataset: DistillationDataset,
    config: DraftTrainingConfig,
    accelerator: Accelerator | None = None,
    progress: bool = True,
    validate: Callable[[DraftHead], dict] | None = None,
    inputs: dict | None = None,
    target_fingerprint: str | None = None,
    paths: dict | None = None,
    data_record: dict | None = None,
) -> DraftHead:
    """Trains ``draft_head`` against the frozen ``target`` on a [`DistillationDataset`].

    Only the draft head is optimised; the target's embedding and lm_head are used frozen. Checkpoints
    (``output_dir/checkpoint-<step>/``: the head via ``save_pretrained`` plus the accelerate state) are written
    every ``save_every`` steps and after the last one; with ``resume=True`` training continues from the newest
    one (so a finished run can be continued with a larger ``max_steps``). The final head is
    saved to ``output_dir`` and returned (unwrapped, in eval mode).

    Args:
        validate: called with the head (in eval mode, without gradients) every ``eval_every`` steps and after the
            last one, e.g. ``lambda head: speculative_acceptance(target, head, held_out_prompts, 7)``; its numbers
            are logged and appended to ``output_dir/validation.jsonl`` with the step.
        inputs: what the data is, for the folder's ``run.json`` (so that ``resume`` refuses a run fed from elsewhere):
            by default a fingerprint of the dataset's token ids; a caller whose data is a deterministic recipe
            (e.g. a policy's rollouts on given seeds) passes the recipe, and can check the folder with
            [`draft_training_record`] and ``checkpoints.check_output_dir`` before building the data (as
            [`distil_draft_head`] does).
        target_fingerprint: ``run_folder.fingerprint(target)`` when the caller already has it (hashed otherwise).
        paths: where the inputs were read from, recorded in ``run.json`` for people (never compared).
        data_record: what the set built from ``inputs`` is ([`distillation_set_record`]): written to
            ``output_dir/distillation_set.json`` by a new run; a resumed run whose rebuilt set differs is refused.
    """
    output_dir = Path(config.output_dir)
    if inputs is None:
        inputs = {"data": fingerprint_arrays(*[example["input_ids"] for example in dataset.examples])}
    record = draft_training_record(draft_head, target_fingerprint or fingerprint(target), config, inputs, paths)
    with prepare_output_dir(output_dir, record, config.resume, config.overwrite_output_dir) as run:
        if data_record is not None:
            _check_data_record(run.bound, data_record, run.continued)
        handles = draft_head.target_handles(target)
        for module in handles:
            module.requires_grad_(False)

        def loss(objective: DistillationObjective, batch: dict, step: int):
            # noise seeded per step and example: a resumed run, or one on n processes, draws what one run would
            losses = objective(batch, example_generators(batch, config.seed, step))
            return losses["loss"], {name: value.detach() for name, value in losses.items()}

        job = TrainingJob(
            DistillationObjective(draft_head, handles, config),
            dataset,
            loss,
            save=lambda objective, folder: objective.head.save_pretrained(folder),
            validate=None if validate is None else lambda objective: validate(objective.head),
            collate_fn=collate_distillation,
            checkpoint_name="draft_head",
            description="train draft head",
        )
        objective, _ = run_training(job, config, run.bound, accelerator, progress)  # run.bound: the claimed folder
        return objective.head


class DistillationObjective(torch.nn.Module):
    """A draft head and its [`distillation_loss`] as one module, the one the training loop optimises: under several
    processes accelerate wraps it in ``DistributedDataParallel``, which averages the gradients of what a *forward*
    computed, and the loss reads the head through more than its forward (its fused features, mask queries, slot
    bins). Its state is the head's own (checkpoints hold the head's parameter names, as before it existed); the
    target's frozen embedding and lm_head are held, not registered (never broadcast, never saved)."""

    def __init__(self, head: DraftHead, handles: TargetHandles, config: DraftTrainingConfig):
        super().__init__()
        self.head, self.handles, self.training_config = head, handles, config  # handles: a tuple, not a submodule

    def forward(self, batch: dict[str, torch.Tensor], generators: list[torch.Generator] | None = None) -> dict:
        return distillation_loss(self.head, self.handles, batch, self.training_config, generators)

    def state_dict(self, *args, **kwargs):
        return self.head.state_dict(*args, **kwargs)

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        return self.head.load_state_dict(state_dict, strict=strict, assign=assign)


def distil_draft_head(
    target: PreTrainedModel,
    training_config: DraftTrainingConfig,
    recipe: dict,
    prompts: Callable[[], tuple[Iterable[dict], Iterable[dict]]],
    tokens_per_call: int,
    *,
    action_tokenizer=None,
    action_dim: int,
    num_draft_tokens: int,
    action_layout=None,
    target_name_or_path: str | None = None,
    target_fingerprint: str | None = None,
    paths: dict | None = None,
    progress: bool = True,
    head_settings: dict | None = None,
    hidden_dtype: torch.dtype | None = None,
) -> DraftHead:
    """The draft-head recipe every target shares (a Meta-World policy, OpenVLA): an untrained head sized for
    ``target`` (seeded by ``training_config.seed``) that records what it was distilled from; the folder's
    ``run.json`` (target weights, ``recipe``, settings) checked *before* ``prompts()`` builds the data (rollouts are
    slow); the target's own greedy ``tokens_per_call`` tokens on the training prompts as the distillation set (hidden
    states in ``hidden_dtype``; its size and the peak memory logged and recorded with its token ids' fingerprint in
    ``distillation_set.json``, which a resumed run's rebuilt set must match); the engine at r=0 on the held-out
    prompts as validation; [`train_draft_head`].

    Args:
        recipe: what the data is, for the record (a fingerprint, or the settings of a deterministic recipe).
        prompts: builds ``(training prompts, held-out prompts)``, each a list or a re-iterable lazy sequence of
            ``generate`` inputs (such as ``policy_draft.PolicyPrompts``: each batch built when read).
        action_tokenizer / action_dim / num_draft_tokens: the head's action layout (default: the target's
            ``action_tokenizer``) and default chain length.
        action_layout: the target's ``ActionLayout`` for validation (which ids are actions, tokens per action).
        target_name_or_path: recorded in the head's config (for people; never compared).
        head_settings: more [`DraftHeadConfig`] fields of the head (e.g. head v2's ``feature_layers`` and
            ``previous_action_input``; see [`head_v2_settings`]).
        hidden_dtype: how the set stores the target's hidden states (recorded in ``run.json``); None: float16 for a
            float32 target ([`STORED_HIDDEN_DTYPE`]), a half-precision target's own dtype.
    """
    settings = head_settings or {}
    uses_blocks = settings.get("draft_mode") == "block" or settings.get("prefill_drafts", False)
    check_draft_chain(num_draft_tokens, tokens_per_call, training_config.unroll_steps, uses_blocks)
    target_fingerprint = target_fingerprint or fingerprint(target)
    torch.manual_seed(training_config.seed)  # the head's initialisation
    head = DraftHead.from_target(
        target,
        action_tokenizer,
        action_dim=action_dim,
        num_draft_tokens=num_draft_tokens,
        target_name_or_path=target_name_or_path,
        target_fingerprint=target_fingerprint,
        **(head_settings or {}),
    )
    if hidden_dtype is None:  # half of a float32 target's; a half-precision target's stay as they are
        hidden_dtype = STORED_HIDDEN_DTYPE if target.dtype == torch.float32 else target.dtype
    recipe = {**recipe, "distillation": {"hidden_dtype": str(hidden_dtype).removeprefix("torch.")}}
    record = draft_training_record(head, target_fingerprint, training_config, recipe, paths)
    check_output_dir(
        Path(training_config.output_dir), record, training_config.resume, training_config.overwrite_output_dir
    )
    training_prompts, held_out_prompts = prompts()
    action_tokenizer = action_tokenizer or target.action_tokenizer  # the labels' action ids, as the head's default
    build = dict(
        max_new_tokens=tokens_per_call,
        action_tokenizer=action_tokenizer,
        action_dim=action_dim,
        hidden_state_layers=head.config.hidden_state_layers,
        hidden_dtype=hidden_dtype,
        image_features=head.config.prefill_image_features,
    )
    dataset = build_distillation_dataset(target, training_prompts, progress=progress, **build)
    data_record = distillation_set_record(dataset)
    logger.info(
        "distillation set: %d examples, %.2f GB of hidden states (%s); peak memory so far %.2f GB",
        len(dataset),
        data_record["measured"]["hidden_bytes"] / 1e9,
        data_record["data"]["hidden_dtype"],
        data_record["measured"]["peak_rss_gb"],
    )

    by_position = {}  # head v3: top-1 by token position on training and held-out frames, so overfitting shows
    if head.config.uses_mask_queries:
        held_out = build_distillation_dataset(target, held_out_prompts, progress=False, **build)
        spread = torch.linspace(0, len(dataset) - 1, min(len(held_out), len(dataset))).round().long().tolist()
        by_position = {"train": DistillationDataset([dataset[i] for i in spread]), "held_out": held_out}

    def validate(draft_head: DraftHead) -> dict:
        metrics = speculative_acceptance(
            target, draft_head, held_out_prompts, tokens_per_call, action_layout=action_layout
        )
        if by_position:
            metrics["accuracy_by_position"] = {
                name: accuracy_by_position(draft_head, target, frames) for name, frames in by_position.items()
            }
        return metrics

    return train_draft_head(
        head,
        target,
        dataset,
        training_config,
        progress=progress,
        validate=validate,
        inputs=recipe,
        target_fingerprint=target_fingerprint,
        paths=paths,
        data_record=data_record,
    )


def distillation_set_record(dataset: DistillationDataset) -> dict:
    """What [`distil_draft_head`] records of its set in ``distillation_set.json``: ``data`` (compared when a run is
    resumed: the examples, their token ids' fingerprint, the hidden states' dtype) and ``measured`` (for people: the
    hidden states' size in bytes and the process's peak memory when the set was built, in GB)."""
    hidden = [example["hidden"] for example in dataset.examples]
    data = {
        "examples": len(dataset),
        "token_ids": fingerprint_arrays(*[example["input_ids"] for example in dataset.examples]),
        "hidden_dtype": str(hidden[0].dtype).removeprefix("torch."),
    }
    hidden_bytes = sum(h.numel() * h.element_size() for h in hidden)
    return {"data": data, "measured": {"hidden_bytes": hidden_bytes, "peak_rss_gb": round(peak_rss_gb(), 3)}}


def peak_rss_gb() -> float:
    """This process's peak resident memory so far, in GB (``getrusage``: kilobytes on Linux, bytes on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 1e9 if sys.platform == "darwin" else peak * 1024 / 1e9


def _check_data_record(folder: Path, data_record: dict, continued: bool) -> None:
    """A new run writes ``data_record`` to ``folder/distillation_set.json``; a continued one checks that the set it
    rebuilt is the one it was trained on.

    Raises:
        FileExistsError: the folder's run was trained on another set (as for a folder of another run), naming what
            differs.
    """
    path = folder / DATA_RECORD
    if continued and path.is_file():
        saved = json.loads(path.read_text())["data"]
        differences = [
            f"{key}: {data_record['data'].get(key)!r} here vs {value!r} there"
            for key, value in saved.items()
            if data_record["data"].get(key) != value
        ]
        if differences:
            raise FileExistsError(
                f"{str(folder)!r} was trained on another distillation set than the one rebuilt to resume it "
                f"({'; '.join(differences)}): the policy or the frames changed; pass --overwrite-output-dir to train "
                f"from scratch, or choose another folder"
            )
        return
    if is_main_process():  # the other processes of a launched run write nothing of the run's own
        write_json_atomic(path, data_record)


def head_v2_settings(target: PreTrainedModel) -> dict:
    """Head v2's [`DraftHeadConfig`] fields for ``target``: a low, a middle and the top layer of its decoder
    (EAGLE-3: the outputs of layer 2, of the middle layer and the last hidden state; fewer on a shallower decoder) and
    the robot's previous action as input."""
    num_layers = target.config.get_text_config().num_hidden_layers
    layers = list(dict.fromkeys(i for i in (min(2, num_layers), num_layers // 2) if 0 < i < num_layers))
    return {"feature_layers": [*layers, -1], "previous_action_input": True}


def head_v3_settings(target: PreTrainedModel, image_features: bool = False) -> dict:
    """Head v3's [`DraftHeadConfig`] fields for ``target``: head v2's ([`head_v2_settings`]) and its new modes: a block
    per forward after the prefill (``draft_mode="block"``) and the whole action drafted before the prefill
    (``prefill_drafts``); with ``image_features``, from the encoded image too (``prefill_image_features``: it paid on
    the demo's toy target, not on policy v3, docs/training.md).

    Raises:
        ValueError: ``image_features`` for a target whose ``generate`` does not encode its images before the prefill
            ([`reads_encoded_images`]).
    """
    if image_features and not reads_encoded_images(target):
        raise ValueError(
            f"{type(target).__name__}'s generate does not encode its images before the prefill (a Llava-style VLM's "
            f"does): a head cannot draft from them there; train it without image features"
        )
    settings = {**head_v2_settings(target), "draft_mode": "block", "prefill_drafts": True}
    return {**settings, "prefill_image_features": True} if image_features else settings


def head_settings(version: str, target: PreTrainedModel, image_features: bool = False) -> dict:
    """The [`DraftHeadConfig`] fields of head ``version`` (one of ``training.configuration.HEAD_VERSIONS``) for
    ``target``: none for v1 (the last hidden state, a chain), [`head_v2_settings`], [`head_v3_settings`] (with
    ``image_features``: drafts before the prefill from the encoded image too).

    Raises:
        ValueError: an unknown version, naming the valid ones; ``image_features`` for a head before v3 or a target
            that does not encode its images before the prefill.
    """
    if version not in HEAD_VERSIONS:
        raise ValueError(f"head_version must be one of {HEAD_VERSIONS}, got {version!r}")
    if image_features and version != "v3":
        raise ValueError(f"image features are read by a head v3's drafts before the prefill, not by a {version} head")
    if version == "v3":
        return head_v3_settings(target, image_features)
    return head_v2_settings(target) if version == "v2" else {}


def draft_training_record(
    draft_head: DraftHead, target_fingerprint: str, config: DraftTrainingConfig, inputs: dict, paths: dict | None = None
):
    """The ``run.json`` record of a draft-head training: its settings, the target's weights (``fingerprint``) and
    the head's identity, and ``inputs`` (what the data is). The target's path is recorded under ``paths`` (a copy of
    the same target elsewhere continues the run)."""
    head_config = {k: v for k, v in draft_head.config.to_dict().items() if k != "transformers_version"}
    target_path = head_config.pop("target_name_or_path", None)
    identity = {"target": target_fingerprint, "draft_head_config": head_config}
    return training_record("train-draft", config, {**identity, **inputs}, {"target": target_path, **(paths or {})})


@torch.no_grad()
def speculative_acceptance(
    target: PreTrainedModel,
    draft_head: DraftHead,
    prompts: Iterable[dict[str, torch.Tensor]],
    max_new_tokens: int,
    **generate_kwargs,
) -> dict:
    """What speculative decoding with ``draft_head`` does on held-out ``prompts``, at ``bin_tolerance=0`` unless
    ``generate_kwargs`` say otherwise: the engine itself runs, so these are the numbers a user will see.

    Args:
        prompts: model inputs of one example each (``input_ids`` ``[1, S]``, images...), and optionally its
            ``previous_action`` (``[1, D]`` token ids, -1: none), which a head with ``previous_action_input`` reads.
        generate_kwargs: more speculation settings (``num_draft_tokens``, ``action_layout``...).

    Returns:
        ``acceptance_per_position`` (``[d]``: of the verifications that drafted a token at depth d, the fraction
        that accepted it), ``tokens_per_target_forward``, ``target_forwards_per_sequence`` and ``sequences``.
    """
    stats, sequences = SpeculationStats(), 0
    chain = DraftHeadDrafter(draft_head, num_draft_tokens=generate_kwargs.pop("num_draft_tokens", None))
    for inputs in prompts:
        if inputs["input_ids"].shape[0] != 1:
            raise ValueError(f"speculative_acceptance takes prompts of one example, got {inputs['input_ids'].shape}")
        inputs = {k: v.to(target.device) if isinstance(v, torch.Tensor) else v for k, v in inputs.items()}
        previous = inputs.pop(PREVIOUS_ACTION, None)
        drafter = chain
        if previous is not None and bool((previous >= 0).all()):
            drafter = chain.with_previous_action(previous[0].tolist())
        output = target.generate(
            **inputs,
            max_new_tokens=max_new_tokens,
            min_new_tokens=max_new_tokens,
            do_sample=False,
            custom_generate=speculative_generate,
            drafter=drafter,
            return_dict_in_generate=True,
            **{"bin_tolerance": 0, **generate_kwargs},
        )
        stats = stats.merge(output.speculation)
        sequences += 1
    if not sequences:
        raise ValueError("speculative_acceptance needs at least one prompt")
    return {
        "acceptance_per_position": [round(x, 4) for x in stats.acceptance_rate_per_position],
        "tokens_per_target_forward": round(stats.tokens_per_target_forward, 4),
        "target_forwards_per_sequence": round(stats.num_target_forwards / sequences, 4),
        "sequences": sequences,
    }
