"""``OpenVLAConfig``: reads the official OpenVLA ``config.json`` as it is (``model_type: "openvla"``)."""

from __future__ import annotations

from typing import Any

from transformers import LlamaConfig, PretrainedConfig

from .vision import BUILTIN_VISION_TOWERS, VisionTowerSpec, vision_tower_spec

#: The vision backbones of the official Prismatic/OpenVLA config and the timm ids and image sizes they imply
#: (a config.json's own ``timm_model_ids`` / ``image_sizes`` override these, as in the official code).
VISION_BACKBONES: dict[str, tuple[list[str], list[int]]] = {
    "dinosiglip-vit-so-224px": (["vit_large_patch14_reg4_dinov2.lvd142m", "vit_so400m_patch14_siglip_224"], [224, 224]),
    "dinosiglip-vit-so-384px": (["vit_large_patch14_reg4_dinov2.lvd142m", "vit_so400m_patch14_siglip_384"], [384, 384]),
    "dinov2-vit-l": (["vit_large_patch14_reg4_dinov2.lvd142m"], [224]),
    "siglip-vit-so400m": (["vit_so400m_patch14_siglip_224"], [224]),
    "siglip-vit-so400m-384px": (["vit_so400m_patch14_siglip_384"], [384]),
}

#: LLM backbones whose language model is a Llama (the only family this port builds), with their hub ids.
LLM_BACKBONES: dict[str, str] = {
    "llama2-7b-pure": "meta-llama/Llama-2-7b-hf",
    "llama2-13b-pure": "meta-llama/Llama-2-13b-hf",
    "llama2-7b-chat": "meta-llama/Llama-2-7b-chat-hf",
    "llama2-13b-chat": "meta-llama/Llama-2-13b-chat-hf",
    "vicuna-v15-7b": "lmsys/vicuna-7b-v1.5",
    "vicuna-v15-13b": "lmsys/vicuna-13b-v1.5",
}

#: The projectors the official HF code builds: ``gelu-mlp`` for one tower, ``fused-gelu-mlp`` for two.
ARCH_SPECIFIERS = ("gelu-mlp", "no-align+gelu-mlp", "fused-gelu-mlp", "no-align+fused-gelu-mlp")

#: transformers 4.40's ``LlamaConfig()`` defaults. The official config.json stores ``text_config`` as a diff against
#: them (the 7B's holds only model_type, pad_token_id, torch_dtype and vocab_size), so they are pinned here rather
#: than read from whatever LlamaConfig defaults the installed transformers has.
LLAMA_DEFAULTS_OF_OFFICIAL_CONFIG: dict[str, Any] = {
    "vocab_size": 32000,
    "hidden_size": 4096,
    "intermediate_size": 11008,
    "num_hidden_layers": 32,
    "num_attention_heads": 32,
    "num_key_value_heads": None,
    "hidden_act": "silu",
    "max_position_embeddings": 2048,
    "initializer_range": 0.02,
    "rms_norm_eps": 1e-6,
    "rope_theta": 10000.0,
    "attention_bias": False,
    "tie_word_embeddings": False,
    "bos_token_id": 1,
    "eos_token_id": 2,
}


def _check_type(name: str, value, expected: type | tuple[type, ...], description: str, optional: bool = False) -> None:
    """Raises TypeError naming the field, the value and the expected type (bools are not ints here)."""
    if value is None and optional:
        return
    is_bool = isinstance(value, bool)
    wants_bool = expected is bool or (isinstance(expected, tuple) and bool in expected)
    if not isinstance(value, expected) or (is_bool and not wants_bool):
        raise TypeError(
            f"OpenVLAConfig.{name} must be {description}{' or null' if optional else ''}, got {value!r} "
            f"({type(value).__name__}); fix it in config.json"
        )


def _check_list(name: str, value, item_type: type, description: str) -> None:
    if value is None:
        return
    if not isinstance(value, (list, tuple)) or not all(
        isinstance(item, item_type) and not isinstance(item, bool) for item in value
    ):
        raise TypeError(
            f"OpenVLAConfig.{name} must be a list of {description} or null, got {value!r} ({type(value).__name__}); "
            f"fix it in config.json"
        )


class OpenVLAConfig(PretrainedConfig):
    r"""Configuration of an [`OpenVLAForActionPrediction`], field for field the official one.

    Args:
        norm_stats: per-dataset statistics, ``{unnorm_key: {"action": {"q01", "q99", "mask", ...}, ...}}``.
        n_action_bins: bins per action dimension (256: 255 bin centres over [-1, 1]).
        vision_backbone_id: the Prismatic backbone name (sets the default ``timm_model_ids`` / ``image_sizes``).
        llm_backbone_id: the Prismatic LLM name; Llama-family ones are supported.
        arch_specifier: the projector, one of ``ARCH_SPECIFIERS``.
        use_fused_vision_backbone: two towers on a 6-channel input; default: the backbone id starts with
            ``dinosiglip`` / ``dinoclip``.
        image_resize_strategy: what the processor does to images (``resize-naive`` for OpenVLA-7B).
        text_config: the Llama config (dict or [`LlamaConfig`]); missing fields take
            ``LLAMA_DEFAULTS_OF_OFFICIAL_CONFIG``.
        llm_max_length, pad_token_id, pad_to_multiple_of, output_projector_states: as in the official config
            (``pad_to_multiple_of``: the embedding rows added after the tokenizer's vocabulary).
        timm_model_ids / image_sizes: the towers (override the backbone id's defaults, as config.json does).
        image_token_id: the placeholder id that marks the image's rows in a prompt prepared for generation;
            default: the last padded vocabulary row (``text_config.vocab_size - 1``), which no tokenizer produces.
        vision_towers: ``{timm id: VisionTowerSpec fields}`` for towers this package does not know
            (``BUILTIN_VISION_TOWERS``): a checkpoint carries them, so a fine-tune with other towers (or a small test
            checkpoint) loads in any process without ``register_vision_tower``. Filled on its own for any such tower
            that was registered, so ``save_pretrained`` writes them.
    """

    model_type = "openvla"
    sub_configs = {"text_config": LlamaConfig}

    def __init__(
        self,
        norm_stats: dict | None = None,
        n_action_bins: int = 256,
        vision_backbone_id: str = "dinosiglip-vit-so-224px",
        llm_backbone_id: str = "llama2-7b-pure",
        arch_specifier: str = "no-align+fused-gelu-mlp",
        use_fused_vision_backbone: bool | None = None,
        image_resize_strategy: str = "resize-naive",
        text_config: dict | LlamaConfig | None = None,
        llm_max_length: int = 2048,
        pad_token_id: int = 32000,
        pad_to_multiple_of: int = 64,
        output_projector_states: bool = False,
        timm_model_ids: list[str] | None = None,
        image_sizes: list[int] | None = None,
        timm_override_act_layers: list[str | None] | None = None,
        image_token_id: int | None = None,
        vision_towers: dict[str, dict] | None = None,
        **kwargs,
    ):
        for name, value, expected, description, optional in (
            ("norm_stats", norm_stats, dict, "a dict of per-dataset statistics", True),
            ("n_action_bins", n_action_bins, int, "an int", False),
            ("vision_backbone_id", vision_backbone_id, str, "a string", False),
            ("llm_backbone_id", llm_backbone_id, str, "a string", False),
            ("arch_specifier", arch_specifier, str, "a string", False),
            ("use_fused_vision_backbone", use_fused_vision_backbone, bool, "true or false", True),
            ("image_resize_strategy", image_resize_strategy, str, "a string", False),
            ("text_config", text_config, (dict, LlamaConfig), "a dict (the Llama config)", True),
            ("llm_max_length", llm_max_length, int, "an int", False),
            ("pad_token_id", pad_token_id, int, "an int", True),
            ("pad_to_multiple_of", pad_to_multiple_of, int, "an int", False),
            ("output_projector_states", output_projector_states, bool, "true or false", False),
            ("image_token_id", image_token_id, int, "an int (a token id)", True),
            ("vision_towers", vision_towers, dict, "a dict {timm id: VisionTowerSpec fields}", True),
        ):
            _check_type(name, value, expected, description, optional)
        _check_list("timm_model_ids", timm_model_ids, str, "timm model ids (strings)")
        _check_list("image_sizes", image_sizes, int, "ints (pixels)")
        if vision_backbone_id not in VISION_BACKBONES and timm_model_ids is None:
            raise ValueError(
                f"vision_backbone_id={vision_backbone_id!r} is not supported by the OpenVLA port; supported: "
                f"{sorted(VISION_BACKBONES)} (or pass timm_model_ids and image_sizes)"
            )
        if llm_backbone_id not in LLM_BACKBONES:
            raise ValueError(
                f"llm_backbone_id={llm_backbone_id!r} is not supported by the OpenVLA port (it builds Llama-family "
                f"language models); supported: {sorted(LLM_BACKBONES)}"
            )
        if arch_specifier not in ARCH_SPECIFIERS:
            raise ValueError(
                f"arch_specifier={arch_specifier!r} is not supported by the OpenVLA port; supported: "
                f"{list(ARCH_SPECIFIERS)}"
            )
        default_ids, default_sizes = VISION_BACKBONES.get(vision_backbone_id, (None, None))
        self.vision_backbone_id = vision_backbone_id
        self.llm_backbone_id = llm_backbone_id
        self.hf_llm_id = kwargs.pop("hf_llm_id", LLM_BACKBONES[llm_backbone_id])
        self.arch_specifier = arch_specifier
        self.use_fused_vision_backbone = (
            use_fused_vision_backbone
            if use_fused_vision_backbone is not None
            else vision_backbone_id.startswith(("dinosiglip", "dinoclip"))
        )
        if ("fused" in arch_specifier) != self.use_fused_vision_backbone:
            raise ValueError(
                f"arch_specifier={arch_specifier!r} does not match use_fused_vision_backbone="
                f"{self.use_fused_vision_backbone} (a fused backbone takes a fused-gelu-mlp projector)"
            )
        self.timm_model_ids = list(timm_model_ids if timm_model_ids is not None else default_ids)
        self.image_sizes = list(image_sizes if image_sizes is not None else default_sizes)
        carried = {name: VisionTowerSpec.from_dict(name, values) for name, values in (vision_towers or {}).items()}
        #: the towers' specs beyond the built-in ones, as config.json carries them
        self.vision_towers = {
            name: vision_tower_spec(name, carried).to_dict()  # unsupported towers fail here, naming the id
            for name in self.timm_model_ids
            if name not in BUILTIN_VISION_TOWERS or name in carried
        }
        if any(act is not None for act in timm_override_act_layers or []):
            raise ValueError(
                f"timm_override_act_layers={timm_override_act_layers} is not supported by the OpenVLA port "
                f"(its towers use GELU)"
            )
        self.timm_override_act_layers = list(timm_override_act_layers or [None] * len(self.timm_model_ids))
        self.image_resize_strategy = image_resize_strategy
        self.norm_stats = norm_stats
        self.n_action_bins = n_action_bins
        self.llm_max_length = llm_max_length
        self.pad_to_multiple_of = pad_to_multiple_of
        self.output_projector_states = output_projector_states
        if isinstance(text_config, LlamaConfig):
            self.text_config = text_config
        else:
            text_config = dict(text_config or {})
            text_config.pop("model_type", None)
            self.text_config = LlamaConfig(**{**LLAMA_DEFAULTS_OF_OFFICIAL_CONFIG, **text_config})
        self.image_token_id = self.text_config.vocab_size - 1 if image_token_id is None else image_token_id
        super().__init__(pad_token_id=pad_token_id, **kwargs)

    def tower_specs(self) -> dict[str, VisionTowerSpec]:
        """The towers' specs this config carries (``vision_towers``), by timm id."""
        return {name: VisionTowerSpec(**values) for name, values in self.vision_towers.items()}

    @property
    def action_vocab_end(self) -> int:
        """One past the last action token id: the tokenizer's vocabulary size (the embedding rows minus the
        padding; 32000 for OpenVLA-7B)."""
        return self.text_config.vocab_size - self.pad_to_multiple_of
