"""Reduced precision: keeping r=0 speculative decoding with greedy decoding in bf16 / fp16.

A verification feeds the root and its drafts in one forward, greedy decoding one token per forward. In fp32 each
token's argmax comes out the same either way. In bf16 / fp16 it does only where every kernel computes a token's row
the same whatever the number of tokens in the forward. Measured on the CPU (docs/benchmarks.md, "r=0 in bf16 on the
CPU"): the linear layers of policy v2 do, and PyTorch's fused ``scaled_dot_product_attention`` does not (a prompt's
keys differ in the last layers when drafts are appended to it, a chain's from one-token steps), so r=0 departed from
greedy at near-ties in 3.5-10.5% of policy v2's actions; with transformers' ``eager`` attention (matmul, fp32
softmax, matmul) none of 1000 did. Not bit for bit in general: a matmul's accumulation order can still depend on the
forward's token count, and where it flips a rounding at a near-tie the tokens part (a random 4-layer Llama: 6 of 1056
generations, against 137 with sdpa).

So a reduced-precision target whose generate is speculation-enabled runs ``eager`` attention, for greedy and
speculative calls alike (both go through the mixin's ``generate``): logged once, turned off with
``enable_speculation(model, exact_reduced_precision=False)``.

**Compiled forwards.** Inductor fuses a chain of operations into one kernel and, by default, keeps its intermediate
values in fp32 where eager decoding rounds each to bf16: which chains fuse depends on the graph, so the one-token
graph and a verification's k-token graph round differently, and at near-ties compiled r=0 speculation parted from
compiled greedy (a tiny random OpenVLA in bf16 on the CPU, 6 calls of 4 left-padded rows, drafts = compiled greedy's
own tokens: 5 of 168 tokens unlike, 7 forwards for 6 calls, where compiled greedy itself parted from eager greedy in
2). With inductor's ``emulate_precision_casts`` every graph rounds where eager decoding does, whatever its width:
1 of 168 unlike, one forward a call ([`exact_compile_config`]: the engine's own graphs of a reduced-precision model,
unless ``exact_reduced_precision=False``). GPU matmuls (cuBLAS may choose kernels by the number of rows) are not
measured here.
"""

from __future__ import annotations

import copy
import logging

import torch
from transformers import PreTrainedModel

logger = logging.getLogger(__name__)

#: dtypes whose rounding makes a forward's shape matter
REDUCED_PRECISION = (torch.bfloat16, torch.float16)
#: the attention implementation whose per-token result depends least on the forward's token count (measured)
STABLE_ATTENTION = "eager"
#: the model attribute ``enable_speculation`` records its ``exact_reduced_precision`` choice in
EXACT_ATTRIBUTE = "_speculation_exact_reduced_precision"


def attention_implementation(model: PreTrainedModel) -> str | None:
    """The model's attention implementation (``config._attn_implementation``), or None when it records none."""
    return getattr(model.config, "_attn_implementation", None)


def keep_greedy_exact(model: PreTrainedModel) -> None:
    """Switches a reduced-precision ``model`` to eager attention, unless its owner turned that off
    (``enable_speculation(model, exact_reduced_precision=False)``) or it already runs it. Logs the switch once."""
    if not getattr(model, EXACT_ATTRIBUTE, True) or model.dtype not in REDUCED_PRECISION:
        return
    current = attention_implementation(model)
    if current == STABLE_ATTENTION:
        return
    try:
        model.set_attn_implementation(STABLE_ATTENTION)
    except (ValueError, NotImplementedError) as error:
        setattr(model, EXACT_ATTRIBUTE, False)  # asked once: the model keeps its attention
        logger.warning(
            "%s runs in %s with %s attention, which rounds a multi-token forward differently from a one-token step, "
            "and it could not switch to %s attention (%s): r=0 speculative decoding may depart from greedy decoding "
            "at near-ties",
            type(model).__name__,
            model.dtype,
            current,
            STABLE_ATTENTION,
            error,
        )
        return
    logger.warning(
        "%s runs in %s: its attention is switched from %s to %s, for greedy and speculative generate alike, so that "
        "r=0 speculative decoding keeps greedy decoding's tokens at near-ties (%s attention rounds a multi-token "
        "forward differently from a one-token step). enable_speculation(model, exact_reduced_precision=False) keeps "
        "%s attention",
        type(model).__name__,
        model.dtype,
        current,
        STABLE_ATTENTION,
        current,
        current,
    )


def exact_compile_config(model: PreTrainedModel, compile_config):
    """The ``CompileConfig`` the engine compiles ``model``'s graphs with: ``compile_config`` itself, or, for a model in
    bf16 / fp16 whose owner kept ``exact_reduced_precision`` (the default), a copy whose inductor options add
    ``emulate_precision_casts`` (its ``mode`` turned into the options it stands for: torch takes one or the other),
    so that graphs of every width round as eager decoding does (the module docstring). Unchanged for another backend,
    or a torch without the option."""
    if compile_config is None or model.dtype not in REDUCED_PRECISION or not getattr(model, EXACT_ATTRIBUTE, True):
        return compile_config
    import torch._inductor.config as inductor_config

    if getattr(compile_config, "backend", "inductor") != "inductor" or not hasattr(
        inductor_config, "emulate_precision_casts"
    ):
        return compile_config
    from torch._inductor import list_mode_options

    options = dict(getattr(compile_config, "options", None) or {})
    if compile_config.mode not in (None, "default"):
        options = {**list_mode_options(compile_config.mode), **options}
    adjusted = copy.copy(compile_config)
    adjusted.mode, adjusted.options = None, {**options, "emulate_precision_casts": True}
    return adjusted
