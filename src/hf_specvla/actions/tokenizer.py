"""OpenVLA's discretisation of continuous actions into the tail of a language model's vocabulary.

Mirrors ``prismatic/vla/action_tokenizer.py`` of openvla/openvla exactly:

* ``bins = linspace(-1, 1, n_bins)``; ``bin_centers`` are the ``n_bins - 1`` midpoints.
* An action value is clipped to [-1, 1], ``d = digitize(value, bins)`` (1..n_bins) and becomes token id
  ``vocab_size - d``: the action ids are the last ``n_bins`` ids below ``vocab_size`` and a *higher*
  value gets a *lower* id.
* Decoding: ``bin_centers[clip(vocab_size - id - 1, 0, n_bins - 2)]``.

``vocab_size`` is where the action range *ends*. For OpenVLA it is 32000 although the embedding matrix
is padded to 32064; ids at or above ``vocab_size`` are never action tokens.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

DEFAULT_N_BINS = 256


class ActionTokenizer:
    """Maps continuous actions in [-1, 1] to token ids and back, OpenVLA-style.

    Args:
        vocab_size: one past the last action token id (OpenVLA: 32000).
        n_bins: number of uniform bins over [-1, 1] (OpenVLA: 256).

    Token ids may be Python ints, numpy arrays or torch tensors; the id arithmetic works on all three.
    """

    def __init__(self, vocab_size: int, n_bins: int = DEFAULT_N_BINS):
        if isinstance(vocab_size, bool) or not isinstance(vocab_size, (int, np.integer)):
            raise TypeError(f"vocab_size must be an int, got {vocab_size!r}")
        if isinstance(n_bins, bool) or not isinstance(n_bins, (int, np.integer)) or n_bins < 2:
            raise ValueError(f"n_bins must be an int >= 2, got {n_bins!r}")
        if vocab_size <= n_bins:
            raise ValueError(
                f"vocab_size={vocab_size} must be larger than n_bins={n_bins}: the action tokens are the last "
                f"n_bins ids below vocab_size, and ids below them are needed for text"
            )
        self.vocab_size = int(vocab_size)
        self.n_bins = int(n_bins)
        self.bins = np.linspace(-1.0, 1.0, self.n_bins)
        self.bin_centers = (self.bins[:-1] + self.bins[1:]) / 2.0

    # ----------------------------------------------------------------- layout
    @property
    def action_token_begin(self) -> int:
        """Smallest action token id (the id of the highest bin)."""
        return self.vocab_size - self.n_bins

    @property
    def action_token_ids(self) -> range:
        """All action token ids, ascending."""
        return range(self.action_token_begin, self.vocab_size)

    def is_action_token(self, token_ids):
        """Whether each id is an action token. Same type and shape as ``token_ids``."""
        return (token_ids >= self.action_token_begin) & (token_ids < self.vocab_size)

    def token_to_bin(self, token_ids):
        """Bin index (0..n_bins-1, 0 = lowest action value) of each action token id.

        Only meaningful for action tokens; see :meth:`is_action_token`.
        """
        return self.vocab_size - 1 - token_ids

    def bin_distance(self, token_ids_a, token_ids_b):
        """``|bin(a) - bin(b)|``; equal to the id distance since action ids are consecutive."""
        if isinstance(token_ids_a, torch.Tensor) or isinstance(token_ids_b, torch.Tensor):
            return (torch.as_tensor(token_ids_a) - torch.as_tensor(token_ids_b)).abs()
        return np.abs(np.asarray(token_ids_a) - np.asarray(token_ids_b))

    # ------------------------------------------------------------ conversion
    def encode(self, actions) -> np.ndarray:
        """Continuous actions (any shape, values clipped to [-1, 1]) -> int64 token ids of the same shape."""
        actions = np.clip(np.asarray(actions, dtype=np.float64), -1.0, 1.0)
        discretized = np.digitize(actions, self.bins)  # 1..n_bins
        return (self.vocab_size - discretized).astype(np.int64)

    def decode(self, token_ids) -> np.ndarray:
        """Token ids (any shape) -> bin-center actions in [-1, 1] of the same shape (float64)."""
        if isinstance(token_ids, torch.Tensor):
            token_ids = token_ids.detach().cpu().numpy()
        discretized = self.vocab_size - np.asarray(token_ids, dtype=np.int64)
        indices = np.clip(discretized - 1, 0, self.bin_centers.shape[0] - 1)
        return self.bin_centers[indices]

    def __repr__(self) -> str:
        return f"ActionTokenizer(vocab_size={self.vocab_size}, n_bins={self.n_bins})"

    def __eq__(self, other) -> bool:
        return (
            isinstance(other, ActionTokenizer) and other.vocab_size == self.vocab_size and other.n_bins == self.n_bins
        )

    def __hash__(self) -> int:
        return hash((self.vocab_size, self.n_bins))


@dataclass(frozen=True)
class ActionLayout:
    """Where a model's actions live in its output: the action-token range and the tokens per action.

    The speculative engine needs it for relaxed acceptance (which tokens are actions, which action dimension a
    token belongs to) and for bin-distance statistics. It comes from the call (``generate(action_layout=...)``),
    the policy or processor, or a draft head's config, so that a model-free drafter can be verified relaxed too.

    Args:
        tokenizer: the [`ActionTokenizer`] (action ids ``vocab_size - n_bins .. vocab_size - 1``).
        action_dim: action tokens per action (OpenVLA: 7; the Meta-World policy: 4).
        units: what a bin is in the policy's own units, per dimension ([`ActionUnits`]); needed only by acceptance
            rules that scale with the motion or bound the deviation in action space. None: unknown.
    """

    tokenizer: ActionTokenizer
    action_dim: int
    units: ActionUnits | None = None

    def __post_init__(self):
        if not isinstance(self.tokenizer, ActionTokenizer):
            raise TypeError(f"ActionLayout.tokenizer must be an ActionTokenizer, got {type(self.tokenizer).__name__}")
        if (
            isinstance(self.action_dim, bool)
            or not isinstance(self.action_dim, (int, np.integer))
            or self.action_dim < 1
        ):
            raise ValueError(
                f"ActionLayout.action_dim must be an int >= 1 (tokens per action), got {self.action_dim!r}"
            )
        if self.units is not None:
            if not isinstance(self.units, ActionUnits):
                raise TypeError(f"ActionLayout.units must be an ActionUnits or None, got {type(self.units).__name__}")
            if len(self.units.zero_bins) != self.action_dim:
                raise ValueError(
                    f"ActionLayout.units describes {len(self.units.zero_bins)} dimensions, but an action has "
                    f"{self.action_dim}"
                )


@dataclass(frozen=True)
class ActionUnits:
    """What the bins of each action dimension mean in the policy's own (un-normalised) units.

    Args:
        zero_bins: per dimension, the bin (0 = lowest value) whose action is closest to 0 in the policy's units: no
            motion, for a delta action.
        bin_widths: per dimension, the distance in the policy's units between the actions of two neighbouring bins
            (the un-normalised bin spacing; > 0).
    """

    zero_bins: tuple[int, ...]
    bin_widths: tuple[float, ...]

    def __post_init__(self):
        zero_bins, widths = tuple(int(b) for b in self.zero_bins), tuple(float(w) for w in self.bin_widths)
        if not zero_bins or len(zero_bins) != len(widths):
            raise ValueError(
                f"ActionUnits needs one zero bin and one bin width per dimension, got {len(zero_bins)} zero bins and "
                f"{len(widths)} widths"
            )
        if not all(np.isfinite(w) and w > 0 for w in widths):
            raise ValueError(f"ActionUnits.bin_widths must be finite and > 0, got {list(widths)}")
        object.__setattr__(self, "zero_bins", zero_bins)
        object.__setattr__(self, "bin_widths", widths)

    @classmethod
    def from_normalizer(cls, tokenizer: ActionTokenizer, normalizer: ActionNormalizer | None, action_dim: int):
        """The units of ``tokenizer``'s bins once un-normalised by ``normalizer`` (None: actions are already in
        [-1, 1], e.g. a policy without statistics)."""
        normalizer = normalizer or ActionNormalizer(-np.ones(action_dim), np.ones(action_dim))
        if normalizer.action_dim != action_dim:
            raise ValueError(f"the action statistics have {normalizer.action_dim} dimensions, an action {action_dim}")
        zero = np.clip(normalizer.normalize(np.zeros(action_dim)), -1.0, 1.0)  # [D] no motion, normalised
        zero_bins = np.abs(tokenizer.bin_centers[None, :] - zero[:, None]).argmin(axis=1)  # [D]
        spacing = 2.0 / (tokenizer.n_bins - 1)  # between neighbouring bin centers in [-1, 1]
        scale = np.where(normalizer.mask, (normalizer.q99 - normalizer.q01) / 2.0, 1.0)  # [D] unnormalize's slope
        widths = np.maximum(spacing * scale, np.finfo(np.float64).tiny)  # a constant dimension: any r is 0 units
        return cls(tuple(zero_bins.tolist()), tuple(widths.tolist()))


@dataclass
class ActionNormalizer:
    """OpenVLA's ``BOUNDS_Q99`` normalisation of raw actions to [-1, 1].

    ``normalize``: ``clip(2 (x - q01) / (q99 - q01 + 1e-8) - 1, -1, 1)`` on the dimensions where ``mask``
    is True; the others (e.g. an already-binary gripper) pass through unchanged.
    ``unnormalize``: ``0.5 (a + 1) (q99 - q01) + q01`` on the masked dimensions.

    Args:
        q01, q99: per-dimension 1st / 99th percentiles of the raw actions, shape [action_dim].
        mask: per-dimension flag, True = normalise; defaults to all True.
    """

    q01: np.ndarray
    q99: np.ndarray
    mask: np.ndarray | None = field(default=None)

    def __post_init__(self):
        self.q01 = np.asarray(self.q01, dtype=np.float64)
        self.q99 = np.asarray(self.q99, dtype=np.float64)
        if self.q01.ndim != 1 or self.q01.shape != self.q99.shape:
            raise ValueError(
                f"q01 and q99 must be 1-D of the same length, got shapes {self.q01.shape} and {self.q99.shape}"
            )
        if np.any(self.q99 < self.q01):
            raise ValueError(f"q99 must be >= q01 in every dimension, got q01={self.q01}, q99={self.q99}")
        self.mask = np.ones_like(self.q01, dtype=bool) if self.mask is None else np.asarray(self.mask, dtype=bool)
        if self.mask.shape != self.q01.shape:
            raise ValueError(f"mask must have shape {self.q01.shape}, got {self.mask.shape}")

    @classmethod
    def from_actions(cls, actions, mask=None) -> ActionNormalizer:
        """Statistics of raw actions of shape [N, action_dim]."""
        actions = np.asarray(actions, dtype=np.float64)
        if actions.ndim != 2 or len(actions) == 0:
            raise ValueError(f"actions must have shape [N, action_dim] with N > 0, got {actions.shape}")
        return cls(np.quantile(actions, 0.01, axis=0), np.quantile(actions, 0.99, axis=0), mask)

    @property
    def action_dim(self) -> int:
        return self.q01.shape[0]

    def _check(self, actions: np.ndarray) -> np.ndarray:
        actions = np.asarray(actions, dtype=np.float64)
        if actions.shape[-1] != self.action_dim:
            raise ValueError(f"actions have {actions.shape[-1]} dimensions, the statistics have {self.action_dim}")
        return actions

    def normalize(self, actions) -> np.ndarray:
        actions = self._check(actions)
        scaled = np.clip(2.0 * (actions - self.q01) / (self.q99 - self.q01 + 1e-8) - 1.0, -1.0, 1.0)
        return np.where(self.mask, scaled, actions)

    def unnormalize(self, normalized_actions) -> np.ndarray:
        normalized_actions = self._check(normalized_actions)
        raw = 0.5 * (normalized_actions + 1.0) * (self.q99 - self.q01) + self.q01
        return np.where(self.mask, raw, normalized_actions)

    def to_dict(self) -> dict:
        return {"q01": self.q01.tolist(), "q99": self.q99.tolist(), "mask": self.mask.tolist()}

    @classmethod
    def from_dict(cls, data: dict) -> ActionNormalizer:
        return cls(data["q01"], data["q99"], data.get("mask"))
