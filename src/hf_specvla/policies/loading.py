"""One loader for every policy a command or a server runs: a Meta-World policy folder ([`VLAPolicy`]) or an OpenVLA
checkpoint, a folder or a hub id ([`OpenVLAPolicy`]), told apart by what the folder holds."""

from __future__ import annotations

import json
import os
from pathlib import Path

from .acting import ActionPolicy
from .configuration_vla import POLICY_CONFIG_NAME

#: what ``config.json``'s ``model_type`` says in an OpenVLA checkpoint (the official and the port's)
OPENVLA_MODEL_TYPES = ("openvla",)


def is_hub_id(name_or_path: str | os.PathLike) -> bool:
    """Whether ``name_or_path`` reads as a hub id (``owner/name``) rather than a local path: nothing there, one slash,
    and no local folder of the owner's name (``policies/missing`` is a missing folder, not a hub id)."""
    text = str(name_or_path)
    owner, _, name = text.partition("/")
    return (
        not Path(text).exists()
        and text.count("/") == 1
        and bool(owner)
        and bool(name)
        and not text.startswith((".", "~"))
        and not Path(owner).is_dir()
    )


def policy_kind(name_or_path: str | os.PathLike) -> str:
    """``"vla"`` for a folder holding ``policy_config.json``, ``"openvla"`` for an OpenVLA checkpoint (a folder whose
    ``config.json`` says ``model_type: openvla``, or a name that is not a local path: a hub id). Reads no weights.

    Raises:
        FileNotFoundError: a local path that is not a folder, or a folder that is neither, naming what it lacks.
    """
    path = Path(name_or_path)
    if is_hub_id(name_or_path):
        return "openvla"
    if not path.exists():
        raise FileNotFoundError(f"policy {str(name_or_path)!r}: no such folder (nor an owner/name hub id)")
    if not path.is_dir():
        raise FileNotFoundError(f"policy {str(path)!r} is a file; pass the policy's folder")
    if (path / POLICY_CONFIG_NAME).is_file():
        return "vla"
    config = path / "config.json"
    model_type = None
    if config.is_file():
        try:
            model_type = json.loads(config.read_text()).get("model_type")
        except (ValueError, AttributeError):
            raise ValueError(f"{config} is not a JSON object: not a checkpoint's config") from None
    if model_type in OPENVLA_MODEL_TYPES:
        return "openvla"
    raise FileNotFoundError(
        f"policy folder {str(path)!r} holds neither {POLICY_CONFIG_NAME} (a Meta-World policy: hf-specvla train-vla "
        f"writes one) nor an OpenVLA checkpoint's config.json (model_type {OPENVLA_MODEL_TYPES[0]!r}; its "
        f"config.json says {model_type!r})"
    )


def load_policy(name_or_path: str | os.PathLike, unnorm_key: str | None = None, **model_kwargs) -> ActionPolicy:
    """The policy at ``name_or_path`` (see [`policy_kind`]); ``unnorm_key`` is an OpenVLA checkpoint's default
    dataset; ``model_kwargs`` go to the model's ``from_pretrained`` (``dtype=``...).

    Raises:
        FileNotFoundError: see [`policy_kind`]; ValueError: an ``unnorm_key`` for a Meta-World policy (one set of
            statistics), or one the checkpoint does not have (naming the valid ones).
    """
    if policy_kind(name_or_path) == "openvla":
        from .openvla_policy import OpenVLAPolicy

        return OpenVLAPolicy.from_pretrained(name_or_path, unnorm_key=unnorm_key, **model_kwargs)
    if unnorm_key is not None:
        raise ValueError(
            f"unnorm_key={unnorm_key!r}: {str(name_or_path)!r} is a Meta-World policy with one set of action "
            f"statistics; unnorm_key names an OpenVLA checkpoint's dataset"
        )
    from .modeling_vla import VLAPolicy

    return VLAPolicy.from_pretrained(name_or_path, **model_kwargs)


def read_policy_layout(name_or_path: str | os.PathLike, unnorm_key: str | None = None):
    """What a command checks before the slow load, read from the configuration files alone: a Meta-World policy's
    [`VLAPolicyConfig`], or an OpenVLA checkpoint's [`OpenVLAPolicyLayout`] (its action length from ``norm_stats``).

    Raises:
        FileNotFoundError: see [`policy_kind`]; ValueError: an unreadable configuration, an ``unnorm_key`` that does
            not apply (naming the valid ones).
    """
    if policy_kind(name_or_path) == "openvla":
        from ..openvla import OpenVLAConfig
        from .openvla_policy import OpenVLAPolicyLayout

        norm_stats = OpenVLAConfig.from_pretrained(name_or_path).norm_stats
        return OpenVLAPolicyLayout(OpenVLAPolicyLayout.datasets(norm_stats, unnorm_key)[1])
    if unnorm_key is not None:
        load_policy(name_or_path, unnorm_key)  # refused, naming why
    from .configuration_vla import VLAPolicyConfig

    return VLAPolicyConfig(**json.loads((Path(name_or_path) / POLICY_CONFIG_NAME).read_text()))
