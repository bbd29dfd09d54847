"""Output type of speculative ``generate`` calls."""

from __future__ import annotations

from dataclasses import dataclass

from transformers.generation.utils import GenerateDecoderOnlyOutput

from .stats import SpeculationStats


@dataclass
class SpeculativeDecoderOnlyOutput(GenerateDecoderOnlyOutput):
    """[`GenerateDecoderOnlyOutput`] plus ``speculation``: the [`SpeculationStats`] of the call.

    ``sequences`` is ``[B, S + new]``; ``scores`` / ``logits`` (when requested) hold one ``[B, V]`` tensor per new
    token, the processed / raw target logits at the position that emitted it (zeros in a row that had already
    stopped). The target cache (``.cache`` from transformers 5.24, ``.past_key_values`` before) is returned for
    B = 1, None for a batch (its cache has holes).
    """

    speculation: SpeculationStats | None = None
