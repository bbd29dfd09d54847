"""The arithmetic floor of batched verification: what one decoder forward of T new tokens per row costs against a
greedy step (T = 1), per batch size, on a cache of a prompt's length; plain causal forwards (no tree mask, no
speculation loop), interleaved, medians.

    python examples/benchmarks/batch_forward_cost.py --policy policies/mt10_vla3 --threads 1
    python examples/benchmarks/batch_forward_cost.py --tiny   # a random 2-layer Llama, seconds (plumbing, no speed)

A speculative batch forward verifies 1 + N tokens per row (the root and N drafts); if a plain forward of that many
tokens already costs more than 1.2x a greedy step at batch size B, no mask layout or loop change brings batched
verification to 1.2x there: only fewer drafted tokens per row can.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from compile_strategies import load_model  # the same --policy / --tiny model (this script's folder is on sys.path)
from transformers import DynamicCache

from hf_specvla.run_folder import write_json_atomic
from hf_specvla.speculative.cache import truncate_cache


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--policy", help="a VLAPolicy folder (its language model is measured)")
    source.add_argument("--tiny", action="store_true", help="a random 2-layer Llama instead (seconds)")
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 4, 8, 16], help="(default: 1 4 8 16)")
    parser.add_argument("--tokens", type=int, nargs="+", default=[1, 2, 3, 5, 9],
                        help="new tokens per row per forward; 1 = a greedy step (default: 1 2 3 5 9)")  # fmt: skip
    parser.add_argument("--prompt-length", type=int, default=41, help="cached tokens per row (default: 41)")
    parser.add_argument("--repeats", type=int, default=20, help="interleaved rounds (default: 20)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default: 1)")
    parser.add_argument("--output", default=None, help="also write the figures as JSON here")
    args = parser.parse_args(argv)
    numbers = [*args.batch_sizes, *args.tokens, args.prompt_length, args.repeats, args.threads]
    if min(numbers) < 1:
        parser.error(f"batch sizes, tokens, --prompt-length, --repeats and --threads must be >= 1, got {numbers}")
    if 1 not in args.tokens:
        parser.error(f"--tokens must include 1 (the greedy step every width is compared with), got {args.tokens}")
    if args.tiny:
        args.batch_sizes, args.tokens, args.repeats = [1, 4], [1, 3], 2
    return args


@torch.no_grad()
def main(argv=None) -> dict:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    model = load_model(args)
    vocab = model.get_output_embeddings().weight.shape[0]
    generator = torch.Generator().manual_seed(0)
    caches = {}
    for batch_size in args.batch_sizes:  # one prefilled cache per batch size, rolled back after every forward
        prompt = torch.randint(3, min(vocab, 1000), (batch_size, args.prompt_length), generator=generator)
        cache = DynamicCache()
        model(input_ids=prompt, past_key_values=cache, use_cache=True)
        caches[batch_size] = cache
    shapes = [(b, t) for b in args.batch_sizes for t in args.tokens]
    times = {shape: [] for shape in shapes}
    for _ in range(args.repeats):
        for batch_size, tokens in shapes:
            cache = caches[batch_size]
            ids = torch.randint(3, min(vocab, 1000), (batch_size, tokens), generator=generator)
            positions = torch.arange(args.prompt_length, args.prompt_length + tokens)[None].expand(batch_size, -1)
            start = time.perf_counter()
            model(input_ids=ids, position_ids=positions, past_key_values=cache, use_cache=True, logits_to_keep=tokens)
            times[(batch_size, tokens)].append(time.perf_counter() - start)
            truncate_cache(cache, args.prompt_length)
    rows = []
    for batch_size in args.batch_sizes:
        step = statistics.median(times[(batch_size, 1)])
        for tokens in args.tokens:
            median = statistics.median(times[(batch_size, tokens)])
            rows.append({"batch_size": batch_size, "tokens_per_row": tokens, "ms": median * 1000,
                         "over_greedy_step": median / step})  # fmt: skip
    print(f"plain causal forwards on a {args.prompt_length}-token cache, median of {args.repeats}, "
          f"{args.threads} thread(s)")  # fmt: skip
    print("| B | new tokens per row | ms | / greedy step (1 token) |")
    print("|---:|---:|---:|---:|")
    for row in rows:
        print(f"| {row['batch_size']} | {row['tokens_per_row']} | {row['ms']:.2f} | {row['over_greedy_step']:.2f} |")
    result = {"prompt_length": args.prompt_length, "repeats": args.repeats, "threads": args.threads, "rows": rows}
    if args.output:
        write_json_atomic(args.output, result)
    return result


if __name__ == "__main__":
    main()
