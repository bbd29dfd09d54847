"""The speculative decode loop: drafters propose trees, the target verifies each in one forward.

[`speculative_generate`] folds a call's loose settings into one [`SpeculationConfig`] and hands the call to the
model's ``SpeculativeDecoder`` (``decoder.py``), which runs it as five steps (gpt-fast style):

    prepare (every argument checked, the rows' drafter sessions, the [`RoundPlan`]) -> prefill -> warm up (a compiled
    call's graphs compiled, the one place that triggers it) -> decode_round until every row has stopped -> finish
    (the cache left as greedy leaves it, statistics, the output)

``call.py`` holds the call's set-up and end (validation, ``prepare``, ``finish``), ``rounds.py`` the rounds,
``state.py`` the state they share. The prefill and every round run the same ladder, each step a short function of
``rounds.py``:

    propose (drafters) -> fit (fit_prefill_trees / fit_trees) -> one target forward (the prefill's over the model's
    prepared inputs; a round's [`verify`], compiled at a fixed width) -> settle: accept -> emit -> commit_paths ->
    observe (drafters) -> drop finished rows

What every round reads is decided once, before the prefill ([`RoundPlan`]: the acceptance rule, the static cache's
slots, the compiled model call when ``compile_config`` asks for one); the compiled widths are compiled right after the
prefill, outside the round loop (``SpeculativeDecoder.warm_up``).

Invariants kept between rounds, per batch row (each row has its own drafter session, tree, accepted path):

* a row's ``sequence`` holds its prompt and every token it emitted. ``pending`` tokens are not in the target cache yet:
  the whole prompt before the prefill, afterwards exactly the last emitted token (the previous bonus token).
* The tree proposed in a round hangs below the last pending token (the root). Drafts known before the target has
  run (``draft_ids``, the action prior) are proposed in round 0 and so verified *inside the prefill*: when all of
  them pass, the action costs exactly one target forward.
* After a round the target cache holds, for each row, the pending tokens and the accepted path as valid entries
  (an accepted node need not be leftmost in the tree: then the path is gathered). The cache is one rectangle for
  the batch: entries a row did not keep are invalid keys, masked like prompt padding (``DecodeState.key_valid``).
  Finished rows leave the batch; a static cache keeps its batch (compiled graphs hold its shape): finished rows stay
  in it as idle rows, fed filler and never read (``DecodeState.cache_rows``), and when its free slots run short every
  row's valid entries are moved to the front ([`compact_rows`]).

Entry point: [`speculative_generate`], a ``custom_generate`` callable for ``model.generate``.
"""

from __future__ import annotations

import inspect
import os
import sys
import warnings
from collections.abc import Callable

import torch
from transformers import GenerationConfig, LogitsProcessorList, PreTrainedModel, StoppingCriteriaList

from .compat import check_transformers_support
from .config import SPECULATION_KWARGS, SpeculationConfig
from .decoder import SpeculativeDecoder
from .outputs import SpeculativeDecoderOnlyOutput
from .rounds import emit_tokens
from .state import RowState
from .stats import SpeculationStats

#: the loop's parts that tests and benchmarks reach through it
__all__ = ["speculative_generate", "RowState", "emit_tokens"]


def speculative_generate(
    model: PreTrainedModel,
    input_ids: torch.LongTensor,
    logits_processor: LogitsProcessorList,
    stopping_criteria: StoppingCriteriaList,
    generation_config: GenerationConfig,
    speculation: SpeculationConfig | None = None,
    draft_ids: torch.LongTensor | None = None,
    on_row_finished: Callable[[int, torch.Tensor, SpeculationStats], None] | None = None,
    **model_kwargs,
) -> SpeculativeDecoderOnlyOutput | torch.LongTensor:
    """Greedy speculative decoding of a batch; a ``custom_generate`` callable for ``model.generate``.

    ``generate`` has already prepared ``input_ids`` ``[B, S]`` (left-padded when rows differ in length, with the
    2D ``attention_mask`` in ``model_kwargs``), the logits processors, stopping criteria and ``model_kwargs``
    (cache, position ids, encoded images). The settings come whole as ``speculation`` (a [`SpeculationConfig`]: what
    drafts, how drafts count, limits), or as loose keywords of ``generate`` (``drafter=``, ``bin_tolerance=``, ...:
    its fields, which this function's signature lists for ``generate`` to route here), folded into one here.

    Each row drafts with its own drafter session, accepts its own number of tokens per target forward and stops on
    its own (EOS, ``max_length``, stopping criteria); finished rows leave the batch. With ``bin_tolerance=0`` every
    row's tokens are plain (batched) greedy decoding's.

    Args:
        speculation: the settings; its ``drafter`` is a [`Drafter`] (the same for every row, or a [`PerRowDrafter`])
            or a [`DraftHead`] (loose: ``drafter=``; ``draft_head=`` is the same, deprecated: a ``FutureWarning``).
        draft_ids: ``[B, k]`` or ``[B, C, k]`` drafts of the first generated tokens of each row, known up front:
            verified inside the prefill forward, with or without a drafter.
        on_row_finished: called as ``on_row_finished(row, new_tokens, stats)`` the moment a row stops (EOS, its
            length, a stopping criterion), while the rest of the batch may still be decoding: ``row`` its index in
            the batch, ``new_tokens`` ``[n]`` its generated tokens (final: what the returned row holds after the
            prompt, without the right padding), ``stats`` the row's [`SpeculationStats`] (final: its forwards,
            accepted lengths; no times). Once per row, in the calling thread, in finishing order (rows that
            stop in one round in batch order). A server answers each request from it without waiting for the
            batch's slowest row; an exception raised by it ends the call.
    Returns:
        ``[B, S + new]`` token ids (rows that stopped early right-padded with ``pad_token_id``), or with
        ``return_dict_in_generate=True`` a [`SpeculativeDecoderOnlyOutput`] whose ``.speculation`` is a
        [`SpeculationStats`] (summed over rows; ``.rows`` per row when B > 1).
    """
    check_transformers_support()
    speculation = SpeculationConfig.fold(speculation, _loose_settings(model_kwargs))
    return SpeculativeDecoder.of(model).decode(
        input_ids,
        logits_processor,
        stopping_criteria,
        generation_config,
        speculation,
        draft_ids,
        model_kwargs,
        on_row_finished,
    )


def _loose_settings(model_kwargs: dict) -> dict:
    """The loose settings among ``model_kwargs`` (taken out): [`SpeculationConfig`]'s fields as ``generate``
    keywords, ``drafter=`` and its deprecated name ``draft_head=`` (a ``FutureWarning``).

    Raises:
        ValueError: both ``drafter`` and ``draft_head``.
    """
    loose = {name: model_kwargs.pop(name) for name in (*SPECULATION_KWARGS, "drafter") if name in model_kwargs}
    draft_head = model_kwargs.pop("draft_head", None)
    if draft_head is not None:
        warnings.warn(
            "speculative_generate(draft_head=...) is deprecated and will be removed: pass drafter= (or "
            "model.generate(assistant_model=...)), which takes a DraftHead too",
            FutureWarning,
            stacklevel=_caller_stacklevel(),
        )
        if loose.get("drafter") is not None:
            raise ValueError("pass drafter= or draft_head=, not both")
        loose["drafter"] = draft_head
    if loose.get("drafter", ...) is None:
        del loose["drafter"]
    return loose


#: what ``generate`` reads to route its keywords to a ``custom_generate`` callable: the settings' loose forms beside
#: the parameters (``drafter=``, ``draft_head=``, ``bin_tolerance=``, ...), keyword-only, all defaulting to unset
speculative_generate.__signature__ = inspect.signature(speculative_generate).replace(
    parameters=[
        *list(inspect.signature(speculative_generate).parameters.values())[:-1],
        *(
            inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=None)
            for name in ("drafter", "draft_head", *SPECULATION_KWARGS)
        ),
        inspect.Parameter("model_kwargs", inspect.Parameter.VAR_KEYWORD),
    ]
)


def _caller_stacklevel() -> int:
    """The ``stacklevel`` that makes a warning raised in [`speculative_generate`] name its caller's line: the first
    frame outside this package's engine, transformers (whose ``generate`` calls us through ``custom_generate``) and
    torch (its ``no_grad`` wrapper)."""
    import transformers

    skip = tuple(
        os.path.dirname(module.__file__) + os.sep for module in (sys.modules[__package__], transformers, torch)
    )
    frame, level = sys._getframe(2), 2  # the frame that called speculative_generate
    while frame.f_back is not None and frame.f_code.co_filename.startswith(skip):
        frame, level = frame.f_back, level + 1
    return level
