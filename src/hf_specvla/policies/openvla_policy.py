"""An OpenVLA checkpoint (the port, [`OpenVLAForActionPrediction`]) as a policy: what ``hf-specvla serve --policy
openvla/openvla-7b`` loads, with the batched, speculative ``predict_action`` of [`ActionPolicy`].

A batch's prompts are OpenVLA's own (``In: What action should the robot take to {instruction}?\\nOut:``, the image's
rows after BOS, the ``29871`` that ends a prompt), left-padded with the tokenizer's pad token; each row is the
one-robot call's, so at ``r = 0`` every row's action is the one the port's ``predict_action`` gives that robot alone.
Each row un-normalises with its own dataset (``unnorm_key``: OpenVLA's clients send it per request).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import torch

from ..actions.tokenizer import ActionLayout
from ..openvla.processing_openvla import PROMPT_TEMPLATE
from .acting import ActionPolicy


@dataclass(frozen=True)
class OpenVLAPolicyLayout:
    """What a server and a robot need to know of an OpenVLA policy (the counterpart of [`VLAPolicyConfig`]'s
    layout fields).

    Attributes:
        action_dim: action tokens per action (the datasets' ``q01`` length: 7 for OpenVLA-7B's).
        image_size: None: images of any size (the processor resizes them, as OpenVLA's ``deploy.py`` does).
        camera: None: the robot's own camera.
        state_dim / use_state: 0 / False (OpenVLA reads no proprio state).
        chunk_length: 1 (one action per call).
    """

    action_dim: int
    image_size: int | None = None
    camera: str | None = None
    state_dim: int = 0
    use_state: bool = False
    chunk_length: int = 1

    @property
    def action_tokens(self) -> int:
        """Tokens one call generates."""
        return self.chunk_length * self.action_dim

    @staticmethod
    def datasets(norm_stats: dict | None, unnorm_key: str | None = None) -> tuple[str | None, int, tuple[str, ...]]:
        """A checkpoint's ``norm_stats`` -> the default dataset (``unnorm_key``, the only one, or None), the action
        length served and the datasets a call may name (those of that length). Reads no weights.

        Raises:
            ValueError: no statistics; an unknown ``unnorm_key`` (naming the valid keys); datasets whose actions
                differ in length and no default chosen among them.
        """
        keys = sorted(norm_stats or {})
        if not keys:
            raise ValueError("this OpenVLA checkpoint has no norm_stats, so it cannot un-normalise actions")
        if unnorm_key is not None and unnorm_key not in keys:
            raise ValueError(f"unnorm_key={unnorm_key!r} is not in this checkpoint's norm_stats; valid keys: {keys}")
        default = unnorm_key if unnorm_key is not None else (keys[0] if len(keys) == 1 else None)
        dims = {key: len(norm_stats[key]["action"]["q01"]) for key in keys}
        if default is None and len(set(dims.values())) > 1:
            raise ValueError(
                f"this checkpoint's datasets have actions of different lengths {dims}: pass unnorm_key, one of {keys}"
            )
        action_dim = dims[default if default is not None else keys[0]]
        return default, action_dim, tuple(key for key in keys if dims[key] == action_dim)


class OpenVLAPolicy(ActionPolicy):
    """An OpenVLA checkpoint as a policy: ``predict_action(images, instructions, unnorm_key=...)``, one robot or a
    batch in one ``generate``.

    Args:
        model: the port's model (on its device and dtype).
        processor: the checkpoint's [`OpenVLAProcessor`] (its tokenizer and image transforms).
        unnorm_key: the default dataset (a call's or request's own wins); None: the checkpoint's only one, or none
            when it has several (each call must then name one).

    Raises:
        ValueError: an ``unnorm_key`` the checkpoint does not have, naming the valid ones; a checkpoint without
            statistics; datasets whose actions differ in length and no default chosen among them.
    """

    def __init__(self, model, processor, unnorm_key: str | None = None):
        super().__init__()
        self.model, self.processor, self.tokenizer = model, processor, processor.tokenizer
        keys = sorted(model.norm_stats or {})
        if not keys:
            raise ValueError("this OpenVLA checkpoint has no norm_stats, so it cannot un-normalise actions")
        self.default_unnorm_key = (
            model.check_unnorm_key(unnorm_key) if unnorm_key is not None or len(keys) == 1 else None
        )
        dims = {key: model.get_action_dim(key) for key in keys}
        if self.default_unnorm_key is not None:
            action_dim = dims[self.default_unnorm_key]
        elif len(set(dims.values())) == 1:
            action_dim = next(iter(dims.values()))
        else:
            raise ValueError(
                f"this checkpoint's datasets have actions of different lengths {dims}: pass unnorm_key, one of {keys}"
            )
        self.config = OpenVLAPolicyLayout(action_dim)
        self.action_tokenizer = model.action_tokenizer
        #: the datasets a call may name: those whose actions have the served length
        self._keys = tuple(key for key in keys if dims[key] == action_dim)
        self._layouts: dict[str, ActionLayout] = {}

    @classmethod
    def from_pretrained(cls, name_or_path: str | os.PathLike, unnorm_key: str | None = None, **model_kwargs):
        """Loads the checkpoint (a folder or a hub id: the model through the port, the processor from its
        ``preprocessor_config.json`` and tokenizer files); ``model_kwargs`` go to ``from_pretrained`` (``dtype=``,
        ``device_map=``...).

        Raises:
            FileNotFoundError / ValueError: as [`OpenVLAForActionPrediction.from_pretrained`] and
                [`OpenVLAProcessor.from_pretrained`] name them; an unknown ``unnorm_key`` (before the weights load).
        """
        from ..openvla import OpenVLAConfig, OpenVLAForActionPrediction, OpenVLAProcessor

        OpenVLAPolicyLayout.datasets(OpenVLAConfig.from_pretrained(name_or_path).norm_stats, unnorm_key)  # no weights
        processor = OpenVLAProcessor.from_pretrained(name_or_path)
        model = OpenVLAForActionPrediction.from_pretrained(name_or_path, **model_kwargs).eval()
        policy = cls(model, processor, unnorm_key)
        policy.name_or_path = str(name_or_path)
        return policy

    # ----------------------------------------------------------------------------- datasets
    @property
    def unnorm_keys(self) -> tuple[str, ...]:
        """The datasets a call may name (those whose actions have ``config.action_dim`` numbers)."""
        return self._keys

    def check_unnorm_key(self, unnorm_key: str | None) -> str:
        """The dataset a call un-normalises with: ``unnorm_key``, or the default.

        Raises:
            ValueError: an unknown key, none where there is no default, or a dataset of another action length; each
                naming the valid keys.
        """
        if unnorm_key is None:
            if self.default_unnorm_key is None:
                raise ValueError(
                    f"this checkpoint was trained on {len(self._keys)} datasets and the policy has no default: pass "
                    f"unnorm_key, one of {list(self._keys)}"
                )
            return self.default_unnorm_key
        if unnorm_key not in self._keys:
            known = sorted(self.model.norm_stats or {})
            why = (
                "is not in this checkpoint's norm_stats" if unnorm_key not in known else "has actions of another length"
            )
            raise ValueError(f"unnorm_key={unnorm_key!r} {why}; valid keys: {list(self._keys)}")
        return unnorm_key

    @property
    def action_layout(self) -> ActionLayout:
        """What relaxed acceptance and the action prior read: the action tokens, ``action_dim`` and the bins' size
        in the default dataset's units (or the first's)."""
        key = self.default_unnorm_key or self._keys[0]
        if key not in self._layouts:
            self._layouts[key] = self.model.action_layout(key)
        return self._layouts[key]

    # ----------------------------------------------------------------------------- inputs and outputs
    def prompt_ids(self, instruction: str, state=None) -> list[int]:
        """OpenVLA's prompt for ``instruction``: BOS, the image's ``num_patches`` rows (``config.image_token_id``),
        the prompt's words and ``29871``, as the port's ``generate`` lays them out.

        Raises:
            ValueError: a ``state`` (OpenVLA reads none), an instruction of white space.
        """
        if state is not None:
            raise ValueError("OpenVLA reads no proprio state: pass state=None")
        # (an empty instruction gives the shortest prompt: what a server's prompt limits start from)
        text = self.processor.prompt(instruction) if instruction else PROMPT_TEMPLATE.format(instruction="")
        ids = torch.as_tensor(self.tokenizer(text, return_tensors="pt")["input_ids"]).reshape(1, -1)
        ids, _ = self.model.add_image_tokens(ids)
        ids, _ = self.model.end_prompt(ids)
        return ids[0].tolist()

    def preprocess_images(self, images) -> torch.Tensor:
        """Images (``[B, H, W, 3]`` uint8, or a list of ``[H, W, 3]`` arrays or PIL images of any size) ->
        ``pixel_values`` ``[B, 6, 224, 224]`` (the checkpoint's transforms) on the model's device and dtype."""
        pixel_values = self.processor.image_processor(list(images))
        return pixel_values.to(self.model.device, self.model.dtype)

    def actions_from_token_ids(self, action_ids, unnorm_key: str | None = None) -> np.ndarray:
        """Token ids ``[..., action_dim]`` -> actions un-normalised with ``unnorm_key``'s statistics (where its mask
        says so), float64."""
        normalized = self.action_tokenizer.decode(np.asarray(action_ids))
        return self.model.action_normalizer(self.check_unnorm_key(unnorm_key)).unnormalize(normalized)
