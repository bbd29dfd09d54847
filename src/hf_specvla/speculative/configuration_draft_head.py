"""Configuration of an EAGLE-style draft head: what it is, and what target it was built for."""

from __future__ import annotations

from transformers import LlamaConfig, PretrainedConfig

from ..actions.tokenizer import DEFAULT_N_BINS, ActionLayout, ActionTokenizer

#: how a head drafts after the prefill: autoregressive levels (heads v1, v2) or one block per forward (head v3)
DRAFT_MODES = ("chain", "block")


class DraftHeadConfig(PretrainedConfig):
    r"""Configuration of a [`DraftHead`].

    The head is one Llama decoder layer, so most fields mirror [`LlamaConfig`]; the rest record the target the
    head was built for (so that attaching it to another model fails loudly) and OpenVLA's action-token layout.

    Args:
        hidden_size: the target's hidden size H (the head's width must equal it: it reads the target's hidden
            states and reuses the target's embedding and lm_head).
        intermediate_size, num_attention_heads, num_key_value_heads, head_dim, hidden_act, rms_norm_eps,
        max_position_embeddings, rope_parameters, attention_bias, mlp_bias: the decoder layer, as in LlamaConfig.
        vocab_size: number of logits the target's lm_head produces (OpenVLA: 32064, padded).
        action_vocab_size: one past the last action token id (OpenVLA: 32000); see [`ActionTokenizer`].
        n_action_bins: number of action bins, i.e. action tokens (OpenVLA: 256).
        action_dim: action tokens per action (OpenVLA: 7); the position of a token within its action is its
            "action dimension", used by per-dimension bin tolerances.
        num_draft_tokens: default number of tokens drafted per target verification (chain length k).
        draft_action_tokens_only: score only action tokens (and EOS) when drafting. This makes each draft step's
            lm_head product n_action_bins+1 wide instead of vocab_size, and the head can then only draft actions.
        final_logit_softcapping: the target's cap on its output logits (Gemma-2: ``logits = cap * tanh(logits /
            cap)``), applied to the head's logits too, so that drafting and training see the target's distribution;
            None (most models): no cap.
        feature_layers: which of the target's hidden states the head reads (indices into the ``hidden_states`` a
            forward with ``output_hidden_states=True`` returns: 0 the embeddings, -1 the last, post-norm), fused by a
            linear layer into one H-wide feature (EAGLE-3 reads a low, a middle and a top layer). None: the last
            hidden state alone (EAGLE-1/2; every head saved before head v2).
        previous_action_input: the head also reads the robot's previous action: the input that predicts the
            generated token k carries the previous action's bin at the same dimension (``k mod action_dim``), or a
            learned "no previous action" vector (prompt positions, an episode's first step). False: heads before v2.
        draft_mode: how the head drafts after the prefill: ``"chain"`` (autoregressive: one head forward per drafted
            level, EAGLE; every head before v3) or ``"block"`` (head v3, DFlash-style: one head forward feeds the
            target's committed pairs and ``num_draft_tokens - 1`` mask queries after them, and drafts every
            remaining token of the action in parallel; a round costs one head forward whatever its depth).
        prefill_drafts: head v3: the head also drafts before the target's prefill (the whole action, its first
            token included) from what is known then: the prompt's tokens (instruction, state) and the previous
            action, in one head forward; verified inside the prefill. False: heads before v3 draft nothing there.
        prefill_image_features: with ``prefill_drafts``: the pre-prefill block reads the prompt as the target's
            language model does, its image tokens replaced by the encoded image (the input embeddings ``generate``
            builds from the vision tower's output, which it computes before the prefill): the current frame, not
            only the previous action, informs the drafts. Needs a VLM whose ``generate`` encodes images first
            (``mm_encoder_outputs``, e.g. Llava). False: the image tokens stand as their placeholder's embedding.
        target_model_type, target_name_or_path: what the head was built for (informational + compatibility check).
        target_fingerprint: content fingerprint of the target weights the head was distilled from (set by
            ``hf-specvla train-draft``); a head whose fingerprint differs from a target's was trained for another
            model and is refused by [`DraftHead.check_target`] (it would still be lossless, only slow).
    """

    model_type = "specvla_draft_head"

    def __init__(
        self,
        hidden_size: int = 4096,
        intermediate_size: int = 11008,
        num_attention_heads: int = 32,
        num_key_value_heads: int | None = None,
        head_dim: int | None = None,
        hidden_act: str = "silu",
        rms_norm_eps: float = 1e-6,
        max_position_embeddings: int = 4096,
        rope_parameters: dict | None = None,
        attention_bias: bool = False,
        mlp_bias: bool = False,
        initializer_range: float = 0.02,
        vocab_size: int = 32064,
        action_vocab_size: int = 32000,
        n_action_bins: int = DEFAULT_N_BINS,
        action_dim: int = 7,
        num_draft_tokens: int = 6,
        draft_action_tokens_only: bool = True,
        final_logit_softcapping: float | None = None,
        feature_layers: list[int] | None = None,
        previous_action_input: bool = False,
        draft_mode: str = "chain",
        prefill_drafts: bool = False,
        prefill_image_features: bool = False,
        target_model_type: str | None = None,
        target_name_or_path: str | None = None,
        target_fingerprint: str | None = None,
        **kwargs,
    ):
        self.hidden_size = hidden_size
        self.intermediate_size = intermediate_size
        self.num_attention_heads = num_attention_heads
        self.num_key_value_heads = num_attention_heads if num_key_value_heads is None else num_key_value_heads
        self.head_dim = hidden_size // num_attention_heads if head_dim is None else head_dim
        self.hidden_act = hidden_act
        self.rms_norm_eps = rms_norm_eps
        self.max_position_embeddings = max_position_embeddings
        self.rope_parameters = rope_parameters or {"rope_type": "default", "rope_theta": 10000.0}
        self.attention_bias = attention_bias
        self.mlp_bias = mlp_bias
        self.initializer_range = initializer_range
        self.vocab_size = vocab_size
        self.action_vocab_size = action_vocab_size
        self.n_action_bins = n_action_bins
        self.action_dim = action_dim
        self.num_draft_tokens = num_draft_tokens
        self.draft_action_tokens_only = draft_action_tokens_only
        self.final_logit_softcapping = final_logit_softcapping
        self.feature_layers = None if feature_layers is None else list(feature_layers)
        self.previous_action_input = previous_action_input
        self.draft_mode = draft_mode
        self.prefill_drafts = prefill_drafts
        self.prefill_image_features = prefill_image_features
        self.target_model_type = target_model_type
        self.target_name_or_path = target_name_or_path
        self.target_fingerprint = target_fingerprint
        super().__init__(**kwargs)
        self._validate()

    def _validate(self) -> None:
        for name in ("hidden_size", "intermediate_size", "num_attention_heads", "vocab_size", "action_dim"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
                raise ValueError(f"DraftHeadConfig.{name} must be a positive int, got {value!r}")
        if isinstance(self.num_draft_tokens, bool) or not isinstance(self.num_draft_tokens, int):
            raise ValueError(f"DraftHeadConfig.num_draft_tokens must be an int >= 1, got {self.num_draft_tokens!r}")
        if self.num_draft_tokens < 1:
            raise ValueError(f"DraftHeadConfig.num_draft_tokens must be an int >= 1, got {self.num_draft_tokens!r}")
        cap = self.final_logit_softcapping
        if cap is not None and (isinstance(cap, bool) or not isinstance(cap, (int, float)) or cap <= 0):
            raise ValueError(f"DraftHeadConfig.final_logit_softcapping must be a number > 0 or None, got {cap!r}")
        if self.action_vocab_size > self.vocab_size:
            raise ValueError(
                f"action_vocab_size={self.action_vocab_size} exceeds vocab_size={self.vocab_size}: the action tokens "
                f"must be ids the target's lm_head can produce"
            )
        layers = self.feature_layers
        if layers is not None and (
            not layers
            or any(isinstance(i, bool) or not isinstance(i, int) for i in layers)
            or len(set(layers)) != len(layers)
        ):
            raise ValueError(
                f"DraftHeadConfig.feature_layers must be None (the last hidden state) or distinct ints indexing the "
                f"target's hidden_states (e.g. [2, 8, -1]), got {layers!r}"
            )
        if not isinstance(self.previous_action_input, bool):
            raise ValueError(
                f"DraftHeadConfig.previous_action_input must be True or False, got {self.previous_action_input!r}"
            )
        if self.draft_mode not in DRAFT_MODES:
            raise ValueError(
                f"DraftHeadConfig.draft_mode must be one of {DRAFT_MODES} (autoregressive levels, or one forward per "
                f"block), got {self.draft_mode!r}"
            )
        if not isinstance(self.prefill_drafts, bool):
            raise ValueError(f"DraftHeadConfig.prefill_drafts must be True or False, got {self.prefill_drafts!r}")
        if not isinstance(self.prefill_image_features, bool):
            raise ValueError(
                f"DraftHeadConfig.prefill_image_features must be True or False, got {self.prefill_image_features!r}"
            )
        if self.prefill_image_features and not self.prefill_drafts:
            raise ValueError(
                "DraftHeadConfig.prefill_image_features=True needs prefill_drafts=True (the image features are read by "
                "the block drafted before the prefill)"
            )
        # Delegates the action-layout checks (n_bins >= 2, room for text ids) to the tokenizer.
        self.action_tokenizer()

    @property
    def uses_mask_queries(self) -> bool:
        """Whether the head drafts positions whose token or hidden state it does not know (block mode, drafts
        before the prefill): it then has learned inputs for them (``DraftHead.mask_embedding``, ``missing_hidden``)."""
        return self.draft_mode == "block" or self.prefill_drafts

    @property
    def hidden_state_layers(self) -> tuple[int, ...]:
        """The target hidden states the head reads (see ``feature_layers``), in order: ``(-1,)`` before head v2."""
        return (-1,) if self.feature_layers is None else tuple(self.feature_layers)

    def action_tokenizer(self) -> ActionTokenizer:
        """The [`ActionTokenizer`] this head was built for."""
        return ActionTokenizer(self.action_vocab_size, self.n_action_bins)

    def action_layout(self) -> ActionLayout:
        """The [`ActionLayout`] (action tokens and tokens per action) this head was built for."""
        return ActionLayout(self.action_tokenizer(), self.action_dim)

    def to_llama_config(self) -> LlamaConfig:
        """The [`LlamaConfig`] of the head's single decoder layer."""
        config = LlamaConfig(
            vocab_size=self.vocab_size,
            hidden_size=self.hidden_size,
            intermediate_size=self.intermediate_size,
            num_hidden_layers=1,
            num_attention_heads=self.num_attention_heads,
            num_key_value_heads=self.num_key_value_heads,
            head_dim=self.head_dim,
            hidden_act=self.hidden_act,
            rms_norm_eps=self.rms_norm_eps,
            max_position_embeddings=self.max_position_embeddings,
            rope_parameters=dict(self.rope_parameters),
            attention_bias=self.attention_bias,
            mlp_bias=self.mlp_bias,
            initializer_range=self.initializer_range,
        )
        # The head always passes an explicit additive float mask, which eager and sdpa both read correctly.
        config._attn_implementation = "sdpa"
        return config
