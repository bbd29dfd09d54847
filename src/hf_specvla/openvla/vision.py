"""OpenVLA's vision towers: ViTs laid out like timm's, so the official checkpoints load with their own key names.

OpenVLA-7B's checkpoint stores its two towers (DINOv2 ViT-L/14 with 4 registers, SigLIP So400m/14) under timm's
module names (``blocks.N.attn.qkv``, ``ls1.scale_factor``, ``attn_pool.kv``...). timm itself cannot be a dependency
here (it needs torchvision, which has no CPU build for current torch), and transformers' DINOv2 / SigLIP modules would
need a key mapping that splits the fused qkv, pads the position table and renames every block, so that
``state_dict()`` would no longer match the checkpoint. These modules reproduce timm 0.9's semantics for the two
tower kinds OpenVLA uses, and nothing more:

* ``no_embed_class`` (DINOv2-reg): the position table covers the patches only; the class and register tokens are
  prepended afterwards, with no position embedding.
* OpenVLA reads the output of the **second-to-last** block (timm's ``get_intermediate_layers(n={depth - 2})``), with
  no final norm and without the prefix tokens; the last block, ``norm`` and ``attn_pool`` are stored in the
  checkpoint but unused, so [`VisionTransformer.forward`] stops before the last block.
* erf GELU in both towers, LayerNorm eps 1e-6, LayerScale stored as ``scale_factor`` (OpenVLA renamed timm's
  ``gamma``, which old transformers rewrote to ``weight`` on load).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import torch
import torch.nn.functional as F
from torch import nn


@dataclass(frozen=True)
class VisionTowerSpec:
    """The architecture behind a timm model id, as far as OpenVLA uses it.

    Attributes:
        embed_dim / depth / num_heads: the ViT's width, number of blocks and attention heads.
        mlp_hidden_size: the MLP's inner width (timm: ``int(embed_dim * mlp_ratio)``).
        patch_size: the square patch side in pixels.
        class_token: whether a class token is prepended.
        num_register_tokens: DINOv2 register tokens (prepended after the class token).
        no_embed_class: True when the position table covers the patches only (DINOv2); False adds it to every
            token (SigLIP, which has no prefix tokens anyway).
        layer_scale: whether blocks scale their residual branches (``ls1`` / ``ls2``).
        attention_pool: whether the checkpoint holds a MAP attention-pool head (``attn_pool.*``; unused by OpenVLA).
    """

    embed_dim: int
    depth: int
    num_heads: int
    mlp_hidden_size: int
    patch_size: int = 14
    class_token: bool = False
    num_register_tokens: int = 0
    no_embed_class: bool = False
    layer_scale: bool = False
    attention_pool: bool = False

    @property
    def num_prefix_tokens(self) -> int:
        return int(self.class_token) + self.num_register_tokens

    def to_dict(self) -> dict:
        """The fields, as a checkpoint's ``config.json`` carries them (``OpenVLAConfig.vision_towers``)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, timm_model_id: str, values) -> VisionTowerSpec:
        """The spec a ``config.json`` carries for ``timm_model_id``.

        Raises:
            ValueError: not a dict, a field that is not a spec's, a missing size, or a value of the wrong type; each
                named with the tower's id.
        """
        where = f"vision_towers[{timm_model_id!r}]"
        if not isinstance(values, dict):
            raise ValueError(f"{where} must be a dict of VisionTowerSpec fields, got {type(values).__name__}")
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise ValueError(f"{where} has fields {unknown} that a vision tower does not; valid: {sorted(known)}")
        missing = [name for name in ("embed_dim", "depth", "num_heads", "mlp_hidden_size") if name not in values]
        if missing:
            raise ValueError(f"{where} needs {missing} (the ViT's sizes)")
        for name, value in values.items():
            flag = known[name].type in ("bool", bool)
            least = 0 if name == "num_register_tokens" else 1
            if type(value) is not (bool if flag else int) or (not flag and value < least):
                wanted = "true or false" if flag else f"an int >= {least}"
                raise ValueError(f"{where}.{name} must be {wanted}, got {value!r}")
        return cls(**values)


def _dinov2_reg4(embed_dim: int, depth: int, num_heads: int) -> VisionTowerSpec:
    return VisionTowerSpec(
        embed_dim,
        depth,
        num_heads,
        4 * embed_dim,
        class_token=True,
        num_register_tokens=4,
        no_embed_class=True,
        layer_scale=True,
    )


_SIGLIP_SO400M = VisionTowerSpec(1152, 27, 16, 4304, attention_pool=True)

#: timm ids OpenVLA checkpoints name in ``config.timm_model_ids``, and the towers they stand for (a checkpoint with
#: other towers carries their specs in its ``config.json``: ``OpenVLAConfig.vision_towers``).
VISION_TOWERS: dict[str, VisionTowerSpec] = {
    "vit_large_patch14_reg4_dinov2.lvd142m": _dinov2_reg4(1024, 24, 16),
    "vit_base_patch14_reg4_dinov2.lvd142m": _dinov2_reg4(768, 12, 12),
    "vit_small_patch14_reg4_dinov2.lvd142m": _dinov2_reg4(384, 12, 6),
    "vit_so400m_patch14_siglip_224": _SIGLIP_SO400M,
    "vit_so400m_patch14_siglip_384": _SIGLIP_SO400M,
}


#: the timm ids this package knows without being told (a checkpoint need not carry their specs)
BUILTIN_VISION_TOWERS = frozenset(VISION_TOWERS)


def register_vision_tower(timm_model_id: str, spec: VisionTowerSpec, exist_ok: bool = False) -> None:
    """Makes ``timm_model_id`` loadable (e.g. a custom timm architecture a fine-tune was built with).

    Raises:
        ValueError: if the id is already registered with another spec and ``exist_ok`` is False.
    """
    if not isinstance(spec, VisionTowerSpec):
        raise TypeError(f"spec must be a VisionTowerSpec, got {type(spec).__name__}")
    known = VISION_TOWERS.get(timm_model_id)
    if known is not None and known != spec and not exist_ok:
        raise ValueError(f"vision tower {timm_model_id!r} is already registered as {known}")
    VISION_TOWERS[timm_model_id] = spec


def vision_tower_spec(timm_model_id: str, carried: dict[str, VisionTowerSpec] | None = None) -> VisionTowerSpec:
    """The spec of a timm id: the one a checkpoint ``carried`` in its config, else the registered one.

    Raises:
        ValueError: naming the id and listing the supported ones.
    """
    if carried and timm_model_id in carried:
        return carried[timm_model_id]
    if timm_model_id not in VISION_TOWERS:
        raise ValueError(
            f"vision tower {timm_model_id!r} is not supported by the OpenVLA port; supported timm ids: "
            f"{sorted(VISION_TOWERS)} (register another with hf_specvla.openvla.register_vision_tower, or give its "
            f"shapes in config.json's vision_towers)"
        )
    return VISION_TOWERS[timm_model_id]


class PatchEmbed(nn.Module):
    def __init__(self, patch_size: int, embed_dim: int):
        super().__init__()
        self.proj = nn.Conv2d(3, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """``[B, 3, H, W]`` -> ``[B, (H / patch) * (W / patch), D]``, row-major patches."""
        return self.proj(images).flatten(2).transpose(1, 2)


class Attention(nn.Module):
    """Multi-head self-attention with a fused ``qkv`` projection (timm's layout)."""

    def __init__(self, embed_dim: int, num_heads: int):
        super().__init__()
        if embed_dim % num_heads:
            raise ValueError(f"embed_dim={embed_dim} is not divisible by num_heads={num_heads}")
        self.num_heads = num_heads
        self.qkv = nn.Linear(embed_dim, 3 * embed_dim)
        self.proj = nn.Linear(embed_dim, embed_dim)

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:
        batch, length, width = hidden.shape
        qkv = self.qkv(hidden).reshape(batch, length, 3, self.num_heads, width // self.num_heads)
        query, key, value = qkv.permute(2, 0, 3, 1, 4).unbind(0)
        attended = F.scaled_dot_product_attention(query, key, value)
        return self.proj(attended.transpose(1, 2).reshape(batch, length, width))


class Mlp(nn.Module):
    def __init__(self, embed_dim: int, hidden_size: int):
        super().__init__()
        self.fc1 = nn.Linear(embed_dim, hidden_size)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden_size, embed_dim)

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(hidden)))


class LayerScale(nn.Module):
    """Per-channel residual scale, stored as ``scale_factor`` as in OpenVLA's checkpoints."""

    def __init__(self, embed_dim: int, init_value: float = 1e-5):
        super().__init__()
        self.scale_factor = nn.Parameter(torch.full((embed_dim,), init_value))

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:
        return hidden * self.scale_factor


class VisionBlock(nn.Module):
    """Pre-norm transformer block: ``x + ls1(attn(norm1(x)))``, then ``x + ls2(mlp(norm2(x)))``."""

    def __init__(self, spec: VisionTowerSpec):
        super().__init__()
        self.norm1 = nn.LayerNorm(spec.embed_dim, eps=1e-6)
        self.attn = Attention(spec.embed_dim, spec.num_heads)
        self.ls1 = LayerScale(spec.embed_dim) if spec.layer_scale else nn.Identity()
        self.norm2 = nn.LayerNorm(spec.embed_dim, eps=1e-6)
        self.mlp = Mlp(spec.embed_dim, spec.mlp_hidden_size)
        self.ls2 = LayerScale(spec.embed_dim) if spec.layer_scale else nn.Identity()

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:
        hidden = hidden + self.ls1(self.attn(self.norm1(hidden)))
        return hidden + self.ls2(self.mlp(self.norm2(hidden)))


class AttentionPoolLatent(nn.Module):
    """SigLIP's MAP head (one learned query attending over the tokens). OpenVLA never calls it; it exists so that
    the checkpoint's ``attn_pool.*`` weights load and save unchanged."""

    def __init__(self, spec: VisionTowerSpec):
        super().__init__()
        width = spec.embed_dim
        self.num_heads = spec.num_heads
        self.latent = nn.Parameter(torch.zeros(1, 1, width))
        self.q = nn.Linear(width, width)
        self.kv = nn.Linear(width, 2 * width)
        self.proj = nn.Linear(width, width)
        self.norm = nn.LayerNorm(width, eps=1e-6)
        self.mlp = Mlp(width, spec.mlp_hidden_size)

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:
        """``[B, N, D]`` -> ``[B, D]``."""
        batch, length, width = hidden.shape
        head_dim = width // self.num_heads
        query = self.q(self.latent.expand(batch, -1, -1)).reshape(batch, 1, self.num_heads, head_dim).transpose(1, 2)
        key, value = self.kv(hidden).reshape(batch, length, 2, self.num_heads, head_dim).permute(2, 0, 3, 1, 4)
        pooled = F.scaled_dot_product_attention(query, key, value).transpose(1, 2).reshape(batch, 1, width)
        pooled = self.proj(pooled)
        pooled = pooled + self.mlp(self.norm(pooled))
        return pooled[:, 0]


class VisionTransformer(nn.Module):
    """One tower. ``forward`` returns OpenVLA's features: the patch tokens after the second-to-last block.

    Args:
        spec: the architecture.
        image_size: the square input side in pixels (sets the position table: ``(image_size / patch)**2`` rows).
    """

    def __init__(self, spec: VisionTowerSpec, image_size: int):
        super().__init__()
        if image_size % spec.patch_size:
            raise ValueError(f"image_size={image_size} is not a multiple of the patch size {spec.patch_size}")
        if spec.depth < 2:
            raise ValueError(f"a tower needs at least 2 blocks (OpenVLA reads the second-to-last), got {spec.depth}")
        self.spec = spec
        self.num_patches = (image_size // spec.patch_size) ** 2
        width = spec.embed_dim
        self.cls_token = nn.Parameter(torch.zeros(1, 1, width)) if spec.class_token else None
        self.reg_token = (
            nn.Parameter(torch.zeros(1, spec.num_register_tokens, width)) if spec.num_register_tokens else None
        )
        table_length = self.num_patches + (0 if spec.no_embed_class else spec.num_prefix_tokens)
        self.pos_embed = nn.Parameter(torch.zeros(1, table_length, width))
        self.patch_embed = PatchEmbed(spec.patch_size, width)
        self.blocks = nn.ModuleList(VisionBlock(spec) for _ in range(spec.depth))
        self.norm = nn.LayerNorm(width, eps=1e-6)
        self.attn_pool = AttentionPoolLatent(spec) if spec.attention_pool else None

    @property
    def embed_dim(self) -> int:
        return self.spec.embed_dim

    def embed(self, images: torch.Tensor) -> torch.Tensor:
        """``[B, 3, H, W]`` -> ``[B, prefix + patches, D]``: patches, position table, prefix tokens."""
        patches = self.patch_embed(images)
        if patches.shape[1] != self.num_patches:
            raise ValueError(
                f"the image gives {patches.shape[1]} patches, the position table has {self.num_patches}: pass images "
                f"of the size the checkpoint was built for"
            )
        batch = patches.shape[0]
        prefix = [token.expand(batch, -1, -1) for token in (self.cls_token, self.reg_token) if token is not None]
        if self.spec.no_embed_class:
            return torch.cat([*prefix, patches + self.pos_embed], dim=1)
        return torch.cat([*prefix, patches], dim=1) + self.pos_embed

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """``[B, 3, H, W]`` -> ``[B, num_patches, D]`` (output of block ``depth - 2``, no norm, no prefix tokens)."""
        hidden = self.embed(images)
        for block in self.blocks[:-1]:
            hidden = block(hidden)
        return hidden[:, self.spec.num_prefix_tokens :]


class OpenVLAVisionBackbone(nn.Module):
    """The featurizer (and, fused, the second tower): 3 or 6 input channels -> ``[B, patches, D1 (+ D2)]``.

    A fused backbone reads channels 0-2 with ``featurizer`` and 3-5 with ``fused_featurizer`` and concatenates the
    two token sequences on the feature axis (so both towers must give the same patch grid).
    """

    def __init__(
        self,
        timm_model_ids: list[str],
        image_sizes: list[int],
        use_fused_vision_backbone: bool,
        carried: dict[str, VisionTowerSpec] | None = None,
    ):
        super().__init__()
        num_towers = 2 if use_fused_vision_backbone else 1
        if len(timm_model_ids) < num_towers or len(image_sizes) < num_towers:
            raise ValueError(
                f"a {'fused' if use_fused_vision_backbone else 'single'} vision backbone needs {num_towers} timm ids "
                f"and image sizes, got timm_model_ids={timm_model_ids}, image_sizes={image_sizes}"
            )
        self.use_fused_vision_backbone = use_fused_vision_backbone
        self.featurizer = VisionTransformer(vision_tower_spec(timm_model_ids[0], carried), image_sizes[0])
        self.fused_featurizer = None
        if use_fused_vision_backbone:
            self.fused_featurizer = VisionTransformer(vision_tower_spec(timm_model_ids[1], carried), image_sizes[1])
            if self.fused_featurizer.num_patches != self.featurizer.num_patches:
                raise ValueError(
                    f"the fused towers give {self.featurizer.num_patches} and {self.fused_featurizer.num_patches} "
                    f"patches; OpenVLA concatenates them per patch, so they must match"
                )

    @property
    def embed_dim(self) -> int:
        return self.featurizer.embed_dim + (self.fused_featurizer.embed_dim if self.fused_featurizer else 0)

    @property
    def num_patches(self) -> int:
        return self.featurizer.num_patches

    @property
    def in_channels(self) -> int:
        return 6 if self.use_fused_vision_backbone else 3

    def forward(self, pixel_values: torch.Tensor) -> torch.Tensor:
        """``[B, 3 or 6, H, W]`` -> ``[B, num_patches, embed_dim]``."""
        if pixel_values.ndim != 4 or pixel_values.shape[1] != self.in_channels:
            raise ValueError(
                f"pixel_values must have shape [B, {self.in_channels}, H, W] for this backbone, got "
                f"{tuple(pixel_values.shape)}"
            )
        if self.fused_featurizer is None:
            return self.featurizer(pixel_values)
        images, fused_images = pixel_values.split([3, 3], dim=1)
        return torch.cat([self.featurizer(images), self.fused_featurizer(fused_images)], dim=2)


class OpenVLAProjector(nn.Module):
    """Patch features -> LLM embeddings. ``gelu-mlp``: fc1, GELU, fc2. ``fused-gelu-mlp``: fc1 (to 4x the vision
    width), GELU, fc2, GELU, fc3."""

    def __init__(self, vision_dim: int, llm_dim: int, fused: bool):
        super().__init__()
        self.fused = fused
        if fused:
            self.fc1 = nn.Linear(vision_dim, 4 * vision_dim)
            self.fc2 = nn.Linear(4 * vision_dim, llm_dim)
            self.fc3 = nn.Linear(llm_dim, llm_dim)
        else:
            self.fc1 = nn.Linear(vision_dim, llm_dim)
            self.fc2 = nn.Linear(llm_dim, llm_dim)
        self.act = nn.GELU()

    def forward(self, patch_features: torch.Tensor) -> torch.Tensor:
        """``[B, N, vision_dim]`` -> ``[B, N, llm_dim]``."""
        projected = self.fc2(self.act(self.fc1(patch_features)))
        return self.fc3(self.act(projected)) if self.fused else projected
