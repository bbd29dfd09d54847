"""The Meta-World VLA's processing: observations and actions to the model's inputs and targets, as a transformers
processor does (images to pixel values, the prompt with the discretised proprio state, actions to action-bin ids,
teacher-forcing batches). No model, no device: [`VLAPolicy`] moves what it builds to the model.

Prompt (OpenVLA's, plus the proprio state):

    <s> <image> x N  "in: what action should the robot take to {instruction}?"  "state:" s1 s2 s3 s4  "out:"

The image enters as N placeholder tokens that Llava replaces with projected patch features. The proprio state
(hand xyz + gripper, 4 numbers) is q01/q99-normalised and discretised with the *action* tokenizer, i.e. it
reuses the 256 bin tokens, so no new vocabulary is needed.

The prompt's fixed part per instruction (``<s>``, the image tokens, the prompt's words) is cached for the last
``PROMPT_CACHE_SIZE`` distinct instructions (least recently used first out): a policy server's robots resend the same
few, and one sending a new instruction every call cannot grow the server's memory without bound.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np
import torch
from transformers import PreTrainedTokenizerFast

from ..actions.tokenizer import ActionNormalizer, ActionTokenizer
from .configuration_vla import VLAPolicyConfig

#: the distinct instructions whose prompt prefix [`VLAProcessor.prompt_ids`] keeps (least recently used first out)
PROMPT_CACHE_SIZE = 1024


class VLAProcessor:
    """Observations and actions <-> model inputs for one policy (its tokenizer, config and statistics).

    Attributes:
        tokenizer, config, action_tokenizer, action_normalizer, state_normalizer, scene_normalizer.
    """

    def __init__(self, tokenizer: PreTrainedTokenizerFast, config: VLAPolicyConfig):
        self.tokenizer = tokenizer
        self.config = config
        self.action_tokenizer = ActionTokenizer(len(tokenizer))
        self.action_normalizer = ActionNormalizer.from_dict(config.action_stats) if config.action_stats else None
        self.state_normalizer = ActionNormalizer.from_dict(config.state_stats) if config.state_stats else None
        self.scene_normalizer = ActionNormalizer.from_dict(config.scene_stats) if config.scene_stats else None
        # instruction -> [<s>, <image> x N, prompt text], the last PROMPT_CACHE_SIZE distinct instructions
        self._prefix_cache: OrderedDict[str, list[int]] = OrderedDict()
        # the special tokens no text may tokenize to (<unk> is how a tokenizer reads words it does not know)
        self._special_ids = set(tokenizer.all_special_ids) - {tokenizer.unk_token_id}
        self._state_word, self._out_words = self._encode("\nState:"), self._encode("\nOut:")

    def preprocess_images(self, images) -> torch.Tensor:
        """uint8 images ``[S, S, 3]`` or ``[B, S, S, 3]`` -> pixel_values float32 ``[B, 3, S, S]`` in [-1, 1], on the
        CPU.

        Raises:
            ValueError / TypeError: wrong size, channel count or dtype, naming what was expected.
        """
        images = np.asarray(images)
        if images.dtype != np.uint8:
            raise TypeError(f"images must be uint8 RGB (0..255), got dtype {images.dtype}")
        if images.ndim == 3:
            images = images[None]
        size = self.config.image_size
        if images.ndim != 4 or images.shape[1:] != (size, size, 3):
            raise ValueError(
                f"images must have shape [{size}, {size}, 3] (or [B, {size}, {size}, 3]), got {images.shape}"
            )
        pixels = torch.tensor(images).permute(0, 3, 1, 2).float() / 127.5 - 1.0  # a copy: read-only arrays welcome
        return pixels

    def state_token_ids(self, state) -> list[int]:
        """The discretised proprio state as action-bin token ids."""
        state = np.asarray(state, dtype=np.float64).reshape(-1)
        if state.shape[0] != self.config.state_dim:
            raise ValueError(f"state must have {self.config.state_dim} numbers, got {state.shape[0]}")
        if not np.isfinite(state).all():  # NaN would discretise to an arbitrary bin, silently
            raise ValueError(
                f"state must hold finite numbers, got {state.tolist()} (NaN or inf at dimension(s) "
                f"{np.flatnonzero(~np.isfinite(state)).tolist()}): check the robot's proprio reading"
            )
        normalized = self.state_normalizer.normalize(state) if self.state_normalizer else np.clip(state, -1, 1)
        return self.action_tokenizer.encode(normalized).tolist()

    def _encode(self, text: str) -> list[int]:
        """``text`` (lower-cased) as words: special-token text in it (``<image>``, ``<pad>``, ``</s>``) is split into
        ordinary tokens (``split_special_tokens``), so a robot's instruction can never add an image placeholder, a
        padding token or an end of sequence to the prompt.

        Raises:
            ValueError: a tokenizer that made special tokens of it anyway (one that ignores ``split_special_tokens``).
        """
        ids = self.tokenizer(text.lower(), add_special_tokens=False, split_special_tokens=True)["input_ids"]
        found = [self.tokenizer.convert_ids_to_tokens(i) for i in ids if i in self._special_ids]
        if found:
            raise ValueError(
                f"{text[:80]!r} tokenizes to special tokens {found[:5]} with this tokenizer "
                f"({type(self.tokenizer).__name__}): remove them from the instruction"
            )
        return ids

    def prompt_ids(self, instruction: str, state=None) -> list[int]:
        """Token ids of the prompt (see module docstring)."""
        ids = list(self._prompt_prefix(instruction))
        if self.config.use_state:
            if state is None:
                raise ValueError("this policy was built with use_state=True: pass state=[x, y, z, gripper]")
            ids += self._state_word + self.state_token_ids(state)
        return ids + self._out_words

    def _prompt_prefix(self, instruction: str) -> list[int]:
        """``[<s>, <image> x N, prompt text]`` for ``instruction``, from the cache of the last ``PROMPT_CACHE_SIZE``
        distinct instructions (callers copy it). Safe from several threads (a server's HTTP and decoding threads):
        each step is one ``OrderedDict`` operation, and an entry evicted meanwhile is only recomputed."""
        cache = self._prefix_cache
        prefix = cache.get(instruction)
        if prefix is not None:
            try:
                cache.move_to_end(instruction)
            except KeyError:  # evicted by another thread since: it stays out
                pass
            return prefix
        text = f"In: What action should the robot take to {instruction.lower().strip().rstrip('.')}?"
        image_id = self.tokenizer.convert_tokens_to_ids("<image>")
        prefix = [self.tokenizer.bos_token_id] + [image_id] * self.config.num_image_tokens + self._encode(text)
        cache[instruction] = prefix
        while len(cache) > PROMPT_CACHE_SIZE:
            try:
                cache.popitem(last=False)
            except KeyError:  # emptied by another thread meanwhile
                break
        return prefix

    def action_token_ids(self, actions) -> np.ndarray:
        """Raw actions ``[..., action_dim]`` -> their token ids (normalised with the policy's statistics)."""
        return self.action_tokenizer.encode(self.action_normalizer.normalize(actions))

    def training_batch(
        self, images, states, actions, instructions: list[str], scene_states=None
    ) -> dict[str, torch.Tensor]:
        """Teacher-forcing inputs for behaviour cloning: ``input_ids`` ``[B, L]`` (right-padded), ``attention_mask``,
        ``pixel_values``, ``labels`` (-100 except on the target tokens: the ``chunk_length * action_dim`` action
        tokens, then, when ``config.scene_state_dim``, the discretised ``scene_states`` ``[B, scene_state_dim]``).

        ``actions``: ``[B, action_dim]`` for a policy without chunks, ``[B, chunk_length, action_dim]`` (the frame's
        action and the next ones) for any policy.
        """
        target_ids = self.action_token_ids(self._check_action_chunks(np.asarray(actions)))  # [B, H, A]
        target_ids = target_ids.reshape(len(target_ids), -1)  # [B, H * A]
        if self.config.scene_state_dim:
            if scene_states is None:
                raise ValueError(
                    f"this policy learns scene_state_dim={self.config.scene_state_dim} scene targets: pass "
                    "scene_states (demonstrations with the scene_state column)"
                )
            scene_ids = self.action_tokenizer.encode(self.scene_normalizer.normalize(np.asarray(scene_states)))
            target_ids = np.concatenate([target_ids, scene_ids], axis=1)  # [B, A + scene_state_dim]
        targets = target_ids.shape[1]
        sequences = [
            self.prompt_ids(instruction, state) + ids.tolist()
            for instruction, state, ids in zip(instructions, states, target_ids)
        ]
        length = max(len(s) for s in sequences)
        input_ids = torch.full((len(sequences), length), self.tokenizer.pad_token_id, dtype=torch.long)
        attention_mask = torch.zeros_like(input_ids)
        labels = torch.full_like(input_ids, -100)
        for i, seq in enumerate(sequences):
            input_ids[i, : len(seq)] = torch.tensor(seq)
            attention_mask[i, : len(seq)] = 1
            labels[i, len(seq) - targets : len(seq)] = input_ids[i, len(seq) - targets : len(seq)]
        return {
            "input_ids": input_ids,
            "attention_mask": attention_mask,
            "pixel_values": self.preprocess_images(images),
            "labels": labels,
        }

    def _check_action_chunks(self, actions: np.ndarray) -> np.ndarray:
        """``actions`` as ``[B, chunk_length, action_dim]``; a clear error for another layout."""
        chunk, dim = self.config.chunk_length, self.config.action_dim
        if actions.ndim == 2 and chunk == 1:
            actions = actions[:, None]
        if actions.ndim != 3 or actions.shape[1:] != (chunk, dim):
            expected = f"[B, {chunk}, {dim}]" + (f" or [B, {dim}]" if chunk == 1 else "")
            raise ValueError(
                f"this policy predicts chunks of chunk_length={chunk} actions of action_dim={dim}: training actions "
                f"must have shape {expected}, got {list(actions.shape)}"
            )
        return actions
