"""How long a fresh server process takes to be ready with the engine's compiled graphs as files (issue 84): the same
start three times, each in a process of its own, one after the other:

* ``in memory``: ``HF_SPECVLA_GRAPH_CACHE=off``, every graph traced and compiled by dynamo, as before;
* ``files, first start``: an empty graph folder (the graphs compiled ahead of time and saved);
* ``files, later start``: the same folder again (the graphs loaded, not traced).

Inductor's cache (``TORCHINDUCTOR_CACHE_DIR``) starts empty: one for the start in memory, one the two file starts share
(a graph file holds its kernels' code; their C++ compile is Inductor's cache, which a later start on the same machine
finds): a cold start is a machine's first (``--inductor-cache machine``: the machine's own cache instead).

Each start builds a ``PolicyService`` (``--method`` on ``--buckets``, no calibration) and times its warm-up, which
compiles every bucket's graphs for every mode, then decodes one observation per bucket row and compares its actions
with the policy's own greedy ``predict_action`` (eager), and counts the graphs dynamo traced in the process (a later
start loads every graph from its file: none). Prints the table; ``--json`` writes its rows.

    python examples/benchmarks/start_time.py --policy policies/mt10_vla3 --buckets 1 2 4 --json runs/start.json
    python examples/benchmarks/start_time.py --tiny      # a random tiny policy, bucket 1: what CI runs
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: start name -> the graph folder setting of its process (None: a fresh folder shared by the two file starts)
STARTS = {"in memory": "off", "files, first start": None, "files, later start": None}


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n")[-1],
                                     formatter_class=argparse.RawTextHelpFormatter)  # fmt: skip
    parser.add_argument("--policy", default="policies/mt10_vla3", help="a policy folder (default: %(default)s)")
    parser.add_argument("--method", default="exact", help="the served method (default: %(default)s)")
    parser.add_argument("--buckets", type=int, nargs="+", default=[1], help="batch sizes (default: 1)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default: %(default)s)")
    parser.add_argument("--json", type=Path, help="write the table's rows here")
    parser.add_argument("--tiny", action="store_true", help="a random tiny policy (saved to a temporary folder)")
    parser.add_argument(
        "--inductor-cache",
        choices=("empty", "machine"),
        default="empty",
        help="empty: every start from empty Inductor caches (a machine's first start); machine: the machine's own "
        "(TORCHINDUCTOR_CACHE_DIR or torch's default) (default: %(default)s)",
    )
    parser.add_argument("--child", help=argparse.SUPPRESS)  # one start, in this process: the policy folder
    args = parser.parse_args(argv)
    if args.threads < 1 or any(b < 1 for b in args.buckets):
        parser.error(f"--threads and --buckets must be >= 1, got {args.threads} and {args.buckets}")
    if args.json is not None and args.json.exists():
        parser.error(f"--json {args.json} exists: nothing a run wrote is overwritten; pass a new path")
    if not args.tiny and args.child is None and not Path(args.policy).is_dir():
        parser.error(f"--policy {args.policy}: no such folder")
    return args


def save_tiny_policy(folder: Path) -> None:
    import numpy as np

    from hf_specvla.actions.tokenizer import ActionNormalizer
    from hf_specvla.metaworld.env import TASK_INSTRUCTIONS
    from hf_specvla.policies import VLAPolicy, VLAPolicyConfig

    unit = ActionNormalizer(-np.ones(4), np.ones(4))
    config = VLAPolicyConfig(text_layers=2, text_hidden_size=48, vision_layers=1, vision_hidden_size=32)
    VLAPolicy.build(list(TASK_INSTRUCTIONS.values()), unit, unit, config, seed=0).save_pretrained(folder)


def one_start(args: argparse.Namespace) -> dict:
    """A start in this process: import, load, warm up, then one batch a bucket against greedy."""
    start = time.perf_counter()
    import numpy as np
    import torch

    from hf_specvla.serving.config import ServeConfig
    from hf_specvla.serving.service import PolicyService

    torch.set_num_threads(args.threads)
    buckets = tuple(args.buckets)
    config = ServeConfig(method=args.method, buckets=buckets, calibration_calls=0, speculate_buckets=buckets,
                         device="cpu", dtype="float32")  # fmt: skip
    service = PolicyService.from_pretrained(args.child, config)
    loaded = time.perf_counter()
    service.warm_up(calibrate=False)
    warm = time.perf_counter()
    policy, layout = service.policy, service.policy.config
    rng = np.random.default_rng(0)
    unlike = total = 0
    for bucket in buckets:
        images = rng.integers(0, 255, (bucket, layout.image_size, layout.image_size, 3), dtype=np.uint8)
        states = rng.normal(size=(bucket, layout.state_dim)).astype(np.float32) if layout.use_state else None
        rows = [{"image": images[row], "instruction": "reach the goal"} for row in range(bucket)]
        for row, request in enumerate(rows):
            if states is not None:
                request["state"] = states[row]
        replies = service.act([service.parse(request) for request in rows])
        for request, reply in zip(rows, replies):
            policy.reset()
            greedy = policy.predict_action(request["image"], request["instruction"], state=request.get("state"))
            unlike += not np.allclose(np.asarray(reply.action), np.asarray(greedy))
            total += 1
    service.close()
    from torch._dynamo.utils import counters

    seconds = {"import_and_load_s": loaded - start, "warm_up_s": warm - loaded, "ready_from_launch_s": warm - start}
    traced = counters["stats"]["unique_graphs"]  # graphs dynamo traced in this process (a loaded file: none)
    return {**{k: round(v, 1) for k, v in seconds.items()}, "actions": total, "actions_unlike_greedy": unlike,
            "graphs_traced": traced}  # fmt: skip


def main(argv=None) -> list[dict]:
    args = parse_args(argv)
    if args.child is not None:
        print(json.dumps(one_start(args)))
        return []
    rows = []
    with tempfile.TemporaryDirectory(prefix="hf_specvla-start-") as scratch:
        policy = args.policy
        if args.tiny:
            policy = str(Path(scratch) / "policy")
            save_tiny_policy(Path(policy))
        for name, folder in STARTS.items():
            env = {**os.environ, "HF_SPECVLA_GRAPH_CACHE": folder or str(Path(scratch) / "graphs")}
            if args.inductor_cache == "empty":
                env["TORCHINDUCTOR_CACHE_DIR"] = str(Path(scratch) / f"inductor-{folder or 'files'}")
            command = [sys.executable, __file__, "--child", policy, "--method", args.method, "--threads",
                       str(args.threads), "--buckets", *map(str, args.buckets)]  # fmt: skip
            done = subprocess.run(command, capture_output=True, text=True, env=env)
            if done.returncode != 0:
                sys.exit(f"the {name!r} start failed:\n{done.stderr[-3000:]}")
            rows.append({"start": name, "buckets": args.buckets, **json.loads(done.stdout.strip().splitlines()[-1])})
    print("| start | ready from launch | warm-up | graphs traced | actions unlike greedy |")
    print("|---|---:|---:|---:|---:|")
    for row in rows:
        print(f"| {row['start']} | {row['ready_from_launch_s']:.1f} s | {row['warm_up_s']:.1f} s | "
              f"{row['graphs_traced']} | {row['actions_unlike_greedy']}/{row['actions']} |")  # fmt: skip
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"rows": rows}, indent=1))
    return rows


if __name__ == "__main__":
    main()
