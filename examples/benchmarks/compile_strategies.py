"""What compiling a verification costs and gives, three ways: eager, the whole model compiled (one graph per width,
what ``speculative.compiled`` does) and regional compilation (each decoder layer compiled, one graph shared by
every layer), at a few verification widths and a prefill; interleaved, medians.

    python examples/benchmarks/compile_strategies.py --policy policies/mt10_vla3 --repeats 20 --threads 1
    python examples/benchmarks/compile_strategies.py --tiny --backend eager   # a random 2-layer Llama, seconds

The verifications run through the engine's own ``CompiledVerification`` on a static cache (the pending token, filler
draft nodes padded to the width, the explicit tree mask), rolled back after each call, exactly as a compiled round
runs.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from hf_specvla.run_folder import write_json_atomic

#: (drafted nodes, pending tokens) per measured forward: a decode step, two verifications, a prefill-sized forward
SHAPES = ((0, 1), (2, 1), (8, 1), (8, 41))


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--policy", help="a VLAPolicy folder (its language model is measured)")
    source.add_argument("--tiny", action="store_true", help="a random 2-layer Llama instead (seconds)")
    parser.add_argument("--repeats", type=int, default=20, help="interleaved rounds (default: 20)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default: 1)")
    parser.add_argument(
        "--backend",
        default="inductor",
        help="torch.compile backend (default: inductor; the tests use eager: plumbing, no speed)",
    )
    parser.add_argument("--output", default=None, help="also write the figures as JSON here")
    args = parser.parse_args(argv)
    if args.repeats < 1 or args.threads < 1:
        parser.error(f"--repeats and --threads must be >= 1, got {args.repeats} and {args.threads}")
    return args


def load_model(args):
    if args.tiny:
        from transformers import LlamaConfig, LlamaForCausalLM

        torch.manual_seed(0)
        config = LlamaConfig(vocab_size=320, hidden_size=64, intermediate_size=128, num_hidden_layers=2,
                             num_attention_heads=4, num_key_value_heads=2, max_position_embeddings=256)  # fmt: skip
        return LlamaForCausalLM(config).eval()
    from hf_specvla.policies import VLAPolicy

    return VLAPolicy.from_pretrained(args.policy).model.eval()


def decoder_layers(model) -> torch.nn.ModuleList:
    """The decoder's layer list (the longest ``layers`` ModuleList: a VLM's language model, not its vision tower)."""
    lists = [m for name, m in model.named_modules() if name.endswith("layers") and isinstance(m, torch.nn.ModuleList)]
    return max(lists, key=len)


def main(argv=None) -> dict:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    from transformers import StaticCache

    from hf_specvla.speculative import CACHE_KEY
    from hf_specvla.speculative.cache import cache_length, truncate_cache
    from hf_specvla.speculative.compiled import allow_graphs
    from hf_specvla.speculative.tree import DraftTree, TreeBatch
    from hf_specvla.speculative.verify import CompiledVerification, Pending

    model = load_model(args)
    slots = 128
    cache = StaticCache(config=getattr(model.config, "text_config", model.config), max_cache_len=slots)
    with torch.no_grad():  # a 40-token context already in the cache
        model(input_ids=torch.randint(0, 100, (1, 40)), use_cache=True, **{CACHE_KEY: cache})
    length = cache_length(cache)
    allow_graphs(4 * len(SHAPES))

    def verify(forward, nodes: int, pending: int) -> None:
        pending_ids = torch.full((1, pending), 5)
        positions = torch.arange(length, length + pending)[None]
        trees = TreeBatch([DraftTree.empty(torch.device("cpu"))], min_nodes=nodes)
        with torch.no_grad():
            CompiledVerification(forward, None, key_length=slots).verify(
                model, Pending({CACHE_KEY: cache}, pending_ids, positions), trees
            )
        truncate_cache(cache, length)

    compile_seconds = {}
    whole = torch.compile(model.__call__, fullgraph=True, dynamic=False, backend=args.backend)
    start = time.perf_counter()
    for nodes, pending in SHAPES:
        verify(whole, nodes, pending)
    compile_seconds["whole"] = time.perf_counter() - start
    layers = decoder_layers(model)
    for layer in layers:
        layer.compile(fullgraph=True, dynamic=False, backend=args.backend)
    compiled_calls = [layer._compiled_call_impl for layer in layers]
    start = time.perf_counter()
    for nodes, pending in SHAPES:
        verify(model, nodes, pending)
    compile_seconds["regional"] = time.perf_counter() - start

    def regional(on: bool) -> None:  # the layers' compiled call, on or off (eager)
        for layer, call in zip(layers, compiled_calls):
            layer._compiled_call_impl = call if on else None

    times: dict[tuple, list[float]] = {}
    for _ in range(args.repeats):
        for nodes, pending in SHAPES:
            for strategy in ("eager", "regional", "whole"):
                regional(strategy == "regional")
                start = time.perf_counter()
                verify(whole if strategy == "whole" else model, nodes, pending)
                times.setdefault((nodes, pending, strategy), []).append(1000 * (time.perf_counter() - start))
    regional(True)
    rows = [{"pending": pending, "nodes": nodes,
             **{s: statistics.median(times[nodes, pending, s]) for s in ("eager", "regional", "whole")}}
            for nodes, pending in SHAPES]  # fmt: skip
    print(f"{len(layers)} decoder layers, {args.threads} thread(s), medians of {args.repeats} interleaved rounds (ms)")
    print("| width (pending + nodes) | eager | regional | whole model |")
    print("|---|---:|---:|---:|")
    for row in rows:
        figures = " | ".join(f"{row[s]:.2f}" for s in ("eager", "regional", "whole"))
        print(f"| {row['pending']} + {row['nodes']} | {figures} |")
    print(f"compile time for the {len(SHAPES)} shapes: whole model {compile_seconds['whole']:.1f} s, regional "
          f"{compile_seconds['regional']:.1f} s (warm or cold as the inductor cache is)")  # fmt: skip
    result = {"rows": rows, "compile_seconds": compile_seconds, "layers": len(layers), "threads": args.threads}
    if args.output:
        write_json_atomic(args.output, result)
    return result


if __name__ == "__main__":
    main()
