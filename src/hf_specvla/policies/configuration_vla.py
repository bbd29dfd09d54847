"""The Meta-World VLA policy's configuration: what a policy is built from and how it reads observations.

A plain dataclass saved as ``policy_config.json`` beside the transformers model; it names its camera as a string
and imports nothing of the simulator.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from .._validation import check_ranges

POLICY_CONFIG_NAME = "policy_config.json"


def check_policy_folder(folder: str | Path) -> None:
    """Raises ``FileNotFoundError`` naming what is missing when ``folder`` holds no saved policy (read without torch:
    a command's usage error comes before the seconds its imports take)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"policy folder {str(folder)!r} does not exist")
    if not (folder / POLICY_CONFIG_NAME).exists():
        raise FileNotFoundError(
            f"{str(folder)!r} has no {POLICY_CONFIG_NAME}: not a policy saved by VLAPolicy.save_pretrained "
            f"(or hf-specvla train-vla)"
        )


@dataclass
class VLAPolicyConfig:
    """What a policy is built from and how it reads observations. Saved as ``policy_config.json``.

    Args:
        image_size: side of the square RGB image the vision encoder takes (pixels).
        camera: the name of the camera the training images came from; evaluation renders from it (the simulator
            checks the name: a policy knows no simulator).
        patch_size: ViT patch size; the image becomes ``(image_size / patch_size) ** 2`` tokens.
        action_dim / state_dim: action tokens per action, proprio numbers per observation.
        chunk_length: actions predicted per call (an action chunk, H): the model generates
            ``chunk_length * action_dim`` tokens, the next H actions in order; ``predict_action`` returns them as
            ``[H, action_dim]`` when H > 1.
        use_state: put the discretised proprio state in the prompt.
        vision_hidden_size, vision_layers, text_hidden_size, text_layers, text_heads: model sizes.
        scene_state_dim: 0, or the number of scene-state values (object and goal xyz: 6) that training asks the
            model to predict after the action tokens, an auxiliary target that makes the vision encoder locate
            the object and the goal. Acting is unchanged: only the action tokens are generated.
        action_stats / state_stats / scene_stats: ``ActionNormalizer.to_dict()`` of the training data.
    """

    image_size: int = 64
    camera: str = "corner"
    patch_size: int = 16
    action_dim: int = 4
    state_dim: int = 4
    use_state: bool = True
    vision_hidden_size: int = 128
    vision_layers: int = 3
    text_hidden_size: int = 192
    text_layers: int = 3
    text_heads: int = 6
    scene_state_dim: int = 0
    chunk_length: int = 1
    action_stats: dict = field(default_factory=dict)
    state_stats: dict = field(default_factory=dict)
    scene_stats: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.image_size % self.patch_size:
            raise ValueError(f"image_size {self.image_size} must be a multiple of patch_size {self.patch_size}")
        if not isinstance(self.camera, str) or not self.camera:
            raise ValueError(f"VLAPolicyConfig.camera must be a camera name (a non-empty string), got {self.camera!r}")
        if self.vision_layers < 1 or self.vision_hidden_size < 4 or self.vision_hidden_size % 4:
            raise ValueError(
                "vision_hidden_size must be a positive multiple of 4 (the encoder's attention heads) and "
                f"vision_layers >= 1, got {self.vision_hidden_size} and {self.vision_layers}"
            )
        check_ranges(
            self,
            at_least_one=("text_hidden_size", "text_layers", "text_heads", "chunk_length"),
            integers=("text_hidden_size", "text_layers", "text_heads", "chunk_length"),
        )
        if self.text_hidden_size % self.text_heads:
            raise ValueError(
                f"text_hidden_size {self.text_hidden_size} must be a multiple of text_heads {self.text_heads}"
            )
        if self.action_dim < 1 or self.state_dim < 0 or self.scene_state_dim < 0:
            raise ValueError(
                f"action_dim must be >= 1, state_dim and scene_state_dim >= 0, got {self.action_dim}, "
                f"{self.state_dim}, {self.scene_state_dim}"
            )

    @property
    def num_image_tokens(self) -> int:
        return (self.image_size // self.patch_size) ** 2

    @property
    def action_tokens(self) -> int:
        """Tokens one call generates: ``chunk_length * action_dim``."""
        return self.chunk_length * self.action_dim
