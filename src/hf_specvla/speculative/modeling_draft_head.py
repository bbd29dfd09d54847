"""EAGLE-style draft head: one decoder layer that drafts action tokens from the target's own hidden states.

Architecture (EAGLE, Li et al. 2024; Spec-VLA, arXiv 2507.22424, section 3):

    features[p] = norm( decoder_layer( fuse( [embed(x[p+1]) ; h[p]] ) ) )      # ~ h[p+1]
    draft token x[p+2] = argmax lm_head(features[p])

where ``h[p]`` is the target's last hidden state (after its final norm) at position p, ``embed`` and ``lm_head``
are the *target's* modules (reused, frozen, never stored in the draft checkpoint), ``fuse`` is Linear(2H -> H).
Deviation from EAGLE-1: a final RMSNorm, because the target's last hidden state is itself post-norm.

Head v2 (config options, each off in every head saved before it):

* ``feature_layers`` (EAGLE-3, Li et al. 2025): ``h[p]`` is several of the target's hidden states (a low, a middle
  and the top layer), concatenated and fused by ``feature_fuse`` (Linear(nH -> H)); they come from the same target
  forward the verification runs. At later draft steps the head's own H-wide output stands in for them.
* ``previous_action_input``: ``fuse`` reads a third input, ``previous_embedding[b]`` (Linear(3H -> H)), where b is
  the robot's previous action's bin at the dimension of the token being predicted, or a learned "none" row (a
  prompt position, or no previous action): the head drafts "the last action, corrected" ([`slot_bins`]).
* trained with training-time test (``training.draft_head``): later draft steps see the head's own outputs.

Head v3 (config options ``draft_mode="block"`` and ``prefill_drafts``; DFlash, Chen et al. 2026, drafts a block per
forward): positions whose token or target hidden state is not known yet are fed as *mask queries*, two learned
vectors (``mask_inputs``: row 0 stands for an unknown token, row 1 for a missing target hidden state) with their own
positions (rotary) and previous-action bins. A block round feeds the committed pairs and ``num_draft_tokens - 1``
mask queries after them in one forward (causal): the last pair's feature drafts depth 0, query j drafts depth j.
Before the prefill, the prompt's tokens stand as pairs with a missing hidden state, followed by the mask queries:
the whole action drafted from the prompt (instruction, state) and the previous action. Deviation from DFlash: the
target's context reaches the block through the head's own KV cache (EAGLE's pairs), not through injected target
keys, and the block attends causally.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import NamedTuple

import torch
from torch import nn
from transformers import AutoConfig, AutoModel, PreTrainedModel
from transformers.cache_utils import Cache
from transformers.models.llama.modeling_llama import LlamaDecoderLayer, LlamaRMSNorm, LlamaRotaryEmbedding

from ..actions.tokenizer import DEFAULT_N_BINS, ActionTokenizer
from .compat import CACHE_KEY, NOT_ENABLED_HINT
from .configuration_draft_head import DraftHeadConfig
from .masks import causal_mask
from .weights import named_weight_errors


def is_local_path(name_or_path: str | os.PathLike) -> bool:
    """Whether ``name_or_path`` means a local file or folder rather than a hub repo id (see
    [`DraftHead.from_pretrained`])."""
    if isinstance(name_or_path, os.PathLike):
        return True
    text = str(name_or_path)
    first = text.split("/", 1)[0]
    return (
        Path(text).expanduser().exists()
        or text.startswith(("/", "./", "../", "~", "."))
        or "\\" in text
        or text.count("/") > 1
        or ("/" in text and Path(first).is_dir())
    )


def check_draft_head_folder(name_or_path: str | os.PathLike) -> None:
    """Raises when a local ``name_or_path`` is not a saved draft head; does nothing for a hub repo id."""
    if not is_local_path(name_or_path):
        return
    folder = Path(name_or_path).expanduser()
    if not folder.is_dir():
        raise FileNotFoundError(
            f"draft head folder {str(name_or_path)!r} does not exist (a local path: it is not looked up on the hub)"
        )
    config_file = folder / "config.json"
    if not config_file.is_file():
        raise FileNotFoundError(
            f"{str(name_or_path)!r} has no config.json: not a draft head saved by DraftHead.save_pretrained"
        )
    try:
        model_type = json.loads(config_file.read_text()).get("model_type")
    except json.JSONDecodeError as error:
        raise ValueError(f"{str(config_file)!r} is not valid JSON ({error}): a damaged draft head folder") from None
    if model_type != DraftHeadConfig.model_type:
        raise ValueError(
            f"{str(name_or_path)!r} holds a {model_type!r} model, not a hf_specvla draft head (whose config.json says "
            f"model_type {DraftHeadConfig.model_type!r}); pass a folder written by DraftHead.save_pretrained"
        )


class TargetHandles(NamedTuple):
    """The target modules a draft head borrows: its input embedding and its lm_head."""

    embed_tokens: nn.Embedding
    lm_head: nn.Linear


def softcap_logits(logits: torch.Tensor, cap: float | None) -> torch.Tensor:
    """``cap * tanh(logits / cap)`` (Gemma-2's final logit soft-capping), or ``logits`` when ``cap`` is None."""
    return logits if cap is None else torch.tanh(logits / cap) * cap


class DraftScorer:
    """Turns draft features into draft token ids with the target's lm_head.

    With ``draft_action_tokens_only`` only the action tokens (+ EOS) are scored: the lm_head rows are gathered
    once here, so each draft step multiplies by ``[n_bins + n_eos, H]`` instead of ``[vocab_size, H]``.
    """

    def __init__(self, lm_head: nn.Linear, candidate_ids: torch.Tensor | None, softcap: float | None = None):
        self.candidate_ids = candidate_ids  # [C] or None for the full vocabulary
        self.softcap = softcap
        weight = lm_head.weight
        bias = getattr(lm_head, "bias", None)
        if candidate_ids is not None:
            weight = weight.index_select(0, candidate_ids)
            bias = None if bias is None else bias.index_select(0, candidate_ids)
        self.weight, self.bias = weight, bias

    def logits(self, features: torch.Tensor) -> torch.Tensor:
        """features ``[..., H]`` -> logits ``[..., C]`` over the scored tokens (capped as the target caps them)."""
        return softcap_logits(nn.functional.linear(features, self.weight, self.bias), self.softcap)

    def token_ids(self, features: torch.Tensor) -> torch.Tensor:
        """features ``[..., H]`` -> greedy draft token ids ``[...]`` (vocabulary ids)."""
        return self.vocab_ids(self.logits(features).argmax(dim=-1))

    def vocab_ids(self, scored_index: torch.Tensor) -> torch.Tensor:
        """Indices into the scored tokens (the last dimension of [`logits`]) -> vocabulary ids."""
        return scored_index if self.candidate_ids is None else self.candidate_ids[scored_index]


def _full_attention_rope(rope_parameters: dict | None) -> dict | None:
    """The target's rotary settings for the head's one (full-attention, 1-D position) layer: models that mix layer
    types (Gemma-3) key them by layer type; multimodal rotary sections (Qwen2-VL's ``mrope_section``) are dropped, the
    head's positions being the text positions."""
    if rope_parameters and "full_attention" in rope_parameters:
        rope_parameters = rope_parameters["full_attention"]
    if rope_parameters is None:
        return None
    return {key: value for key, value in rope_parameters.items() if key != "mrope_section"}


class DraftHead(PreTrainedModel):
    """EAGLE-style draft head (see module docstring). Create one for a target with [`DraftHead.from_target`].

    Used as ``target.generate(..., assistant_model=draft_head)`` once the target has speculation enabled
    (see [`hf_specvla.enable_speculation`]).
    """

    config_class = DraftHeadConfig
    base_model_prefix = "draft_head"
    main_input_name = "token_embeds"
    _no_split_modules = ["LlamaDecoderLayer"]
    _supports_sdpa = True

    def __init__(self, config: DraftHeadConfig):
        super().__init__(config)
        hidden = config.hidden_size
        layer_config = config.to_llama_config()
        num_features = len(config.hidden_state_layers)
        #: fuses the target's hidden states of several layers into one (EAGLE-3); None: the last one alone
        self.feature_fuse = nn.Linear(num_features * hidden, hidden, bias=False) if num_features > 1 else None
        #: the previous action's bins (+ a last "none" row); None: a head that does not read it
        self.previous_embedding = (
            nn.Embedding(config.n_action_bins + 1, hidden) if config.previous_action_input else None
        )
        self.fuse = nn.Linear((3 if config.previous_action_input else 2) * hidden, hidden, bias=True)
        #: head v3's mask-query inputs (row 0: an unknown token, row 1: a missing target hidden state); None before v3
        self.mask_inputs = nn.Embedding(2, hidden) if config.uses_mask_queries else None
        self.layer = LlamaDecoderLayer(layer_config, layer_idx=0)
        self.norm = LlamaRMSNorm(hidden, eps=config.rms_norm_eps)
        self.rotary_emb = LlamaRotaryEmbedding(layer_config)
        self.post_init()

    def __getattr__(self, name: str):
        try:
            return super().__getattr__(name)  # nn.Module: parameters, buffers, submodules
        except AttributeError as error:
            if name == "generation_config":  # transformers' assisted generation, on a target without the mixin
                raise AttributeError(f"{error}: {NOT_ENABLED_HINT}") from None
            raise

    # ------------------------------------------------------------------ building
    @classmethod
    def from_pretrained(cls, pretrained_model_name_or_path, *model_args, **kwargs) -> DraftHead:
        """``PreTrainedModel.from_pretrained``, after checking a local folder: it must exist and hold a draft-head
        ``config.json``. A local path (an existing file or folder, ``/``, ``./``, ``~``, or a first component that is
        a local folder, like ``runs/draft``) is never sent to the hub; anything else is a hub repo id.

        Raises:
            FileNotFoundError / ValueError naming the path and what it holds instead.
        """
        check_draft_head_folder(pretrained_model_name_or_path)
        with named_weight_errors(pretrained_model_name_or_path, "draft head"):
            try:
                return super().from_pretrained(pretrained_model_name_or_path, *model_args, **kwargs)
            except OSError as error:
                if is_local_path(pretrained_model_name_or_path):
                    raise
                raise OSError(
                    f"no local folder {str(pretrained_model_name_or_path)!r} exists, so it was taken for a hub repo "
                    f"id, and the hub could not provide it ({error}). For a local draft head, check the path (a path "
                    f"written as ./{pretrained_model_name_or_path} is never sent to the hub)"
                ) from error

    @classmethod
    def from_target(
        cls,
        target: PreTrainedModel,
        action_tokenizer: ActionTokenizer | None = None,
        action_dim: int = 7,
        **config_overrides,
    ) -> DraftHead:
        """An untrained draft head sized for ``target`` (its text config), on the target's device and dtype.

        Args:
            target: a causal LM or a VLM with a language model (e.g. Llama, Llava).
            action_tokenizer: the target's action layout; defaults to the target's own ``action_tokenizer`` attribute
                (e.g. OpenVLA's: the 256 ids below 32000), else the last 256 ids of the text vocabulary.
            action_dim: action tokens per action.
            config_overrides: any other [`DraftHeadConfig`] field (e.g. ``num_draft_tokens=4``,
                ``intermediate_size=...``).
        """
        text_config = target.config.get_text_config()
        lm_head = target.get_output_embeddings()
        if lm_head is None:
            raise ValueError(f"{type(target).__name__} has no lm_head (get_output_embeddings() is None)")
        if action_tokenizer is None:
            action_tokenizer = getattr(target, "action_tokenizer", None)
        if action_tokenizer is None:
            action_tokenizer = ActionTokenizer(text_config.vocab_size, DEFAULT_N_BINS)
        settings = dict(
            hidden_size=text_config.hidden_size,
            intermediate_size=text_config.intermediate_size,
            num_attention_heads=text_config.num_attention_heads,
            num_key_value_heads=getattr(text_config, "num_key_value_heads", None),
            head_dim=getattr(text_config, "head_dim", None),
            hidden_act=getattr(text_config, "hidden_act", "silu"),
            rms_norm_eps=getattr(text_config, "rms_norm_eps", 1e-6),
            max_position_embeddings=getattr(text_config, "max_position_embeddings", 4096),
            rope_parameters=_full_attention_rope(getattr(text_config, "rope_parameters", None)),
            vocab_size=lm_head.weight.shape[0],
            action_vocab_size=action_tokenizer.vocab_size,
            n_action_bins=action_tokenizer.n_bins,
            action_dim=action_dim,
            eos_token_id=getattr(text_config, "eos_token_id", None),
            final_logit_softcapping=getattr(text_config, "final_logit_softcapping", None),
            target_model_type=target.config.model_type,
            target_name_or_path=getattr(target.config, "_name_or_path", None) or None,
        )
        settings.update(config_overrides)
        head = cls(DraftHeadConfig(**settings))
        with torch.no_grad():
            if head.feature_fuse is not None:  # starts as a head of the last listed layer alone
                hidden = head.config.hidden_size
                head.feature_fuse.weight.zero_()
                head.feature_fuse.weight[:, -hidden:] = torch.eye(hidden)
            if head.previous_embedding is not None:  # bin b starts as the lm_head row that scores it
                token_ids = action_tokenizer.token_to_bin(torch.arange(action_tokenizer.n_bins))  # bin b's id
                rows = lm_head.weight.detach().index_select(0, token_ids.to(lm_head.weight.device))
                head.previous_embedding.weight[:-1] = rows.to(head.previous_embedding.weight)
        return head.to(device=target.device, dtype=target.dtype)

    def target_handles(self, target: PreTrainedModel) -> TargetHandles:
        """Checks that this head fits ``target`` and returns the target modules it borrows.

        Raises:
            ValueError: naming the mismatching field when the head was built for another target.
        """
        text_config = target.config.get_text_config()
        embed_tokens, lm_head = target.get_input_embeddings(), target.get_output_embeddings()
        problems = []
        if text_config.hidden_size != self.config.hidden_size:
            problems.append(f"hidden_size: draft {self.config.hidden_size}, target {text_config.hidden_size}")
        if lm_head is None or lm_head.weight.shape[0] != self.config.vocab_size:
            found = None if lm_head is None else lm_head.weight.shape[0]
            problems.append(f"lm_head vocabulary: draft {self.config.vocab_size}, target {found}")
        if embed_tokens is None or embed_tokens.weight.shape[1] != self.config.hidden_size:
            problems.append("the target's input embedding width differs from the draft's hidden_size")
        if problems:
            built_for = self.config.target_name_or_path or self.config.target_model_type or "another model"
            raise ValueError(
                f"This DraftHead was built for {built_for!r} and does not fit {type(target).__name__}: "
                + "; ".join(problems)
                + ". Build one for this target with DraftHead.from_target(target) and train it."
            )
        if self.fuse.weight.device != lm_head.weight.device or self.fuse.weight.dtype != lm_head.weight.dtype:
            raise ValueError(
                f"DraftHead is on {self.fuse.weight.device}/{self.fuse.weight.dtype} but the target's lm_head is on "
                f"{lm_head.weight.device}/{lm_head.weight.dtype}; move it with "
                f"draft_head.to(device=target.device, dtype=target.dtype)"
            )
        return TargetHandles(embed_tokens, lm_head)

    def check_target(self, target: PreTrainedModel, target_fingerprint: str | None = None) -> None:
        """Refuses a target this head was not made for, before any decoding: shapes (as [`target_handles`]) and,
        when both are known, the weights the head was distilled from (``config.target_fingerprint``) against
        ``target_fingerprint`` (the caller's fingerprint of ``target``'s weights).

        Raises:
            ValueError: naming both sides.
        """
        self.target_handles(target)
        trained_for = self.config.target_fingerprint
        if trained_for and target_fingerprint and trained_for != target_fingerprint:
            built_for = self.config.target_name_or_path or "another model"
            raise ValueError(
                f"this DraftHead was distilled from the weights of {built_for!r} (fingerprint {trained_for}), but the "
                f"target's weights have fingerprint {target_fingerprint}: it was trained for another model. Train one "
                f"for this target (hf-specvla train-draft --policy <this policy>)"
            )

    def scorer(self, lm_head: nn.Linear, eos_token_ids: list[int] | None = None) -> DraftScorer:
        """A [`DraftScorer`] over the tokens this head drafts (all, or actions + EOS)."""
        if not self.config.draft_action_tokens_only:
            return DraftScorer(lm_head, None, self.config.final_logit_softcapping)
        action_ids = list(self.config.action_tokenizer().action_token_ids)
        extra = [i for i in (eos_token_ids or []) if i not in action_ids]
        candidate_ids = torch.tensor(extra + action_ids, device=lm_head.weight.device)
        return DraftScorer(lm_head, candidate_ids, self.config.final_logit_softcapping)

    # ------------------------------------------------------------------ previous action
    def no_previous_action(self, device: torch.device | None = None) -> torch.Tensor:
        """``[D]`` int64: the "no previous action" bins (an episode's first step) for [`slot_bins`]."""
        return torch.full((self.config.action_dim,), self.config.n_action_bins, dtype=torch.long, device=device)

    def previous_action_bins(self, previous_action, device: torch.device | None = None) -> torch.Tensor:
        """The robot's previous action (``action_dim`` action token ids, or None) -> ``[D]`` int64 bins for
        [`slot_bins`] (None: [`no_previous_action`]).

        Args:
            previous_action: a flat sequence of ``action_dim`` integer token ids: a list or tuple of ints, or a 1-D
                integer tensor or array. Floats (a bin is not truncated from them), bools and nested sequences are
                refused, not flattened.

        Raises:
            ValueError: not a flat sequence of ``action_dim`` integer ids, or an id that is not an action token of
                the head's layout.
        """
        if previous_action is None:
            return self.no_previous_action(device)
        tokenizer = self.config.action_tokenizer()
        valid = (
            f"this draft head reads the previous action as {self.config.action_dim} action token ids (ids "
            f"{tokenizer.action_token_begin}..{tokenizer.vocab_size - 1}), a flat sequence of ints"
        )
        try:
            ids = torch.as_tensor(previous_action, device=device)
        except (TypeError, ValueError, RuntimeError) as error:  # ragged, strings, objects
            raise ValueError(f"{valid}, got {previous_action!r}") from error
        if ids.ndim != 1 or ids.dtype == torch.bool or ids.is_floating_point() or ids.is_complex():
            shown = previous_action if isinstance(previous_action, (list, tuple)) else ids.tolist()  # as given
            kind = (
                "nested"
                if ids.ndim > 1
                else "not a sequence"
                if ids.ndim == 0
                else "bools"
                if ids.dtype == torch.bool
                else f"{ids.dtype} values, not ints"
            )
            raise ValueError(f"{valid}, got {shown} ({kind})")
        ids = ids.long()
        if ids.shape[0] != self.config.action_dim or not bool(tokenizer.is_action_token(ids).all()):
            raise ValueError(f"{valid}, got {ids.tolist()}")
        return tokenizer.token_to_bin(ids)

    def slot_bins(self, previous_bins: torch.Tensor, first_position, position_ids: torch.Tensor) -> torch.Tensor:
        """Which previous-action bin each input reads: the input at position p predicts the token at ``p + 2``,
        the generated token ``k = p + 2 - first_position``, which reads the previous action's bin at dimension
        ``k mod action_dim``; ``k < 0`` (a prompt token) reads the "none" row.

        Args:
            previous_bins: ``[D]`` or ``[B, D]`` int64 (``n_action_bins`` = none; see [`previous_action_bins`]).
            first_position: the position of the first generated token: an int, 0-dim or ``[B, 1]`` tensor.
            position_ids: ``[B, q]`` the inputs' positions p.
        Returns:
            ``[B, q]`` int64 rows of ``previous_embedding``.
        """
        generated = position_ids + 2 - first_position  # [B, q]
        dim = generated.clamp(min=0) % previous_bins.shape[-1]
        rows = previous_bins.reshape(-1, previous_bins.shape[-1]).expand(position_ids.shape[0], -1)
        bins = rows.gather(1, dim)
        return torch.where(generated >= 0, bins, torch.full_like(bins, self.config.n_action_bins))

    # ------------------------------------------------------------------ mask queries (head v3)
    def fuse_features(self, target_hidden: torch.Tensor) -> torch.Tensor:
        """``[..., n H]`` the target's hidden states of the ``feature_layers`` -> ``[..., H]`` the head's hidden input
        (fused by ``feature_fuse``; H-wide inputs, the head's own features, pass unchanged)."""
        if self.feature_fuse is not None and target_hidden.shape[-1] != self.config.hidden_size:
            return self.feature_fuse(target_hidden)
        return target_hidden

    def mask_query_inputs(self, batch_size: int, count: int, unknown_token: bool = True):
        """Inputs of ``count`` positions the head knows nothing of: ``(token_embeds [B, count, H], hidden [B, count,
        H])``, the learned "unknown token" (``unknown_token``; else None: the caller embeds known tokens) and
        "missing hidden state" vectors.

        Raises:
            ValueError: a head without mask queries (``draft_mode="chain"`` and no ``prefill_drafts``).
        """
        if self.mask_inputs is None:
            raise ValueError(
                "this draft head has no mask queries: it drafts autoregressively (draft_mode='chain') and not before "
                "the prefill (prefill_drafts=False); build a head v3 (draft_mode='block' or prefill_drafts=True)"
            )
        width = self.config.hidden_size
        token = self.mask_inputs.weight[0].expand(batch_size, count, width) if unknown_token else None
        return token, self.mask_inputs.weight[1].expand(batch_size, count, width)

    # ------------------------------------------------------------------ forward
    def forward(
        self,
        token_embeds: torch.Tensor,
        target_hidden: torch.Tensor,
        position_ids: torch.Tensor,
        attention_mask: torch.Tensor | None = None,
        cache: Cache | None = None,
        previous_bins: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Predicts the target's next hidden states.

        Args:
            token_embeds: ``[B, q, H]`` target embeddings of tokens ``x[p+1]``.
            target_hidden: ``[B, q, n H]`` the target's hidden states ``h[p]`` of the ``feature_layers`` (n of them,
                concatenated), or ``[B, q, H]`` features the head drafted itself.
            position_ids: ``[B, q]`` positions p.
            attention_mask: additive float ``[B, 1, q, past + q]``; default causal over the cache + new tokens.
            cache: the head's own KV cache (one layer), updated in place.
            previous_bins: ``[B, q]`` int64, the previous action's bin each input reads ([`slot_bins`]); required
                by a head with ``previous_action_input``, refused by one without.

        Returns:
            features ``[B, q, H]``, estimates of ``h[p+1]``.
        """
        past_len = 0 if cache is None else cache.get_seq_length()
        if attention_mask is None:
            attention_mask = causal_mask(token_embeds.shape[1], past_len, token_embeds.dtype, token_embeds.device)
        target_hidden = self.fuse_features(target_hidden)  # the target's layers -> [B, q, H]
        inputs = [token_embeds, target_hidden]
        if (previous_bins is None) != (self.previous_embedding is None):
            raise ValueError(
                "this draft head reads the robot's previous action: pass previous_bins (DraftHead.slot_bins)"
                if previous_bins is None
                else "this draft head does not read a previous action (config.previous_action_input is False)"
            )
        if previous_bins is not None:
            inputs.append(self.previous_embedding(previous_bins))
        fused = self.fuse(torch.cat(inputs, dim=-1))  # [B, q, H]
        position_embeddings = self.rotary_emb(fused, position_ids=position_ids)
        hidden = self.layer(
            fused,
            attention_mask=attention_mask,
            position_ids=position_ids,
            use_cache=cache is not None,
            **{CACHE_KEY: cache},
            position_embeddings=position_embeddings,
        )
        if isinstance(hidden, tuple):  # older decoder layers return (hidden_states, ...)
            hidden = hidden[0]
        return self.norm(hidden)


AutoConfig.register(DraftHeadConfig.model_type, DraftHeadConfig)
AutoModel.register(DraftHeadConfig, DraftHead)
