"""An OpenVLA checkpoint served through ``/act`` to K robots: a speculative server against a compiled-greedy one
(issue 85), in one process, interleaved.

The policy: ``--checkpoint`` (an OpenVLA checkpoint folder: its weights, processor and tokenizer files), or a random
OpenVLA built in code (``--shapes tiny``: tiny towers and 2 Llama layers of 64, the CPU's; ``--shapes 7b``:
openvla/openvla-7b's shapes, for a GPU) with the real openvla-7b tokenizer and processor files
(``--processor-files``, default the shared reference's ``hub-openvla-7b``; ``--shapes tiny`` resizes to 28 pixels).
Two embedded servers over the one policy (graphs compiled once each, warm-up timed): the speculative method
(``--method``, default ``exact``, speculating at every batch size) and ``greedy:compile`` (transformers' compiled
greedy: what a plain server does; ``greedy`` for an eager method). For each K in ``--robots`` and each repeat, both
are driven in turn (order rotated per repeat) by K robot threads with OpenVLA's client fields (an image, an
instruction, an ``unnorm_key``; a session, so each robot drafts from its own previous actions), each sending
``--steps`` observations of its own slowly moving synthetic scene (the random weights' actions follow the image: how
often a robot's previous action is right depends on this scene, not on a task; with a real checkpoint send real
observations for real figures).

Reported per K and server (medians over repeats, ``[min-max]`` for actions/s, the speculative server's ratio to the
same repeat's greedy run): actions per second (all robots' actions / wall time), ms per action at the client,
the batch's decode ms, target forwards per call, batch sizes formed, and the tokens of each action unlike the
greedy server's for the same observation (at r = 0 none may differ: the script fails if one does in float32).

    python examples/benchmarks/openvla_serving.py --shapes tiny --robots 1 4 --output runs/openvla_serving.json
    python examples/benchmarks/openvla_serving.py --method prior+jacobi --robots 1 2 --repeats 1 --steps 3 \\
        --output /tmp/openvla_serving.json       # eager, no compile: a minute (what CI runs)
    python examples/benchmarks/openvla_serving.py --shapes 7b --device cuda --robots 1 4 --output gpu_serving.json
    python examples/benchmarks/openvla_serving.py --checkpoint ~/openvla-7b --unnorm-key bridge_orig --device cuda \\
        --output runs/openvla_7b_serving.json
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import sys
import threading
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from gpu_openvla import openvla_7b_config, tiny_config  # noqa: E402 (the models of the one-call benchmark)

logger = logging.getLogger("openvla_serving")
PROCESSOR_FILES = ROOT.parent / "shared" / "openvla-reference" / "hub-openvla-7b"
INSTRUCTIONS = ("pick up the red block", "put the carrot in the pot", "open the drawer", "wipe the table")
#: the tiny model's image processor: resize-naive to 28 pixels for both towers
TINY_PREPROCESSOR = {
    "image_resize_strategy": "resize-naive",
    "tvf_resize_params": [{"size": [28, 28], "interpolation": 3}] * 2,
    "tvf_crop_params": [{"output_size": [28, 28]}] * 2,
    "tvf_normalize_params": [{"mean": [0.5] * 3, "std": [0.5] * 3}] * 2,
}


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)  # fmt: skip
    parser.add_argument("--checkpoint", default=None, help="an OpenVLA checkpoint folder (default: random weights)")
    parser.add_argument("--shapes", choices=("tiny", "7b"), default="tiny", help="the random model's shapes")
    parser.add_argument("--processor-files", default=str(PROCESSOR_FILES), help="the tokenizer / processor files")
    parser.add_argument("--unnorm-key", default=None, help="the dataset the robots name (default: the first)")
    parser.add_argument("--method", default="exact", help="the speculative server's method or preset")
    parser.add_argument("--robots", type=int, nargs="+", default=[1, 4], help="the K values")
    parser.add_argument("--buckets", type=int, nargs="+", default=None, help="default: 1 2 4 ... up to the largest K")
    parser.add_argument("--steps", type=int, default=12, help="observations per robot per run")
    parser.add_argument("--repeats", type=int, default=3, help="rounds over the two servers, order rotated")
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N")
    parser.add_argument("--dtype", default="auto", help="auto (bfloat16 on CUDA, else float32), bfloat16, float32")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument("--max-wait-ms", type=float, default=5.0)
    parser.add_argument("--output", required=True, help="the JSON of every run and the table")
    args = parser.parse_args(argv)
    if min(args.robots) < 1 or args.steps < 2 or args.repeats < 1:
        parser.error("--robots must be >= 1, --steps >= 2, --repeats >= 1")
    return args


def build_policy(args, placement):
    """The served [`OpenVLAPolicy`]: the checkpoint, or a random model with the real tokenizer and processor."""
    from hf_specvla.openvla import OpenVLAForActionPrediction, OpenVLAImageProcessor, OpenVLAProcessor
    from hf_specvla.policies import OpenVLAPolicy, load_policy

    if args.checkpoint:
        policy = load_policy(args.checkpoint, args.unnorm_key, dtype=placement.dtype)
        placement.move(policy.model)
        return policy
    processor = OpenVLAProcessor.from_pretrained(args.processor_files)
    if args.shapes == "tiny":
        processor = OpenVLAProcessor(OpenVLAImageProcessor.from_dict(TINY_PREPROCESSOR), processor.tokenizer)
    config = tiny_config() if args.shapes == "tiny" else openvla_7b_config()
    torch.manual_seed(0)  # the same random weights every run
    with torch.device(placement.device):
        torch.set_default_dtype(placement.dtype)
        model = OpenVLAForActionPrediction(config).eval()
        torch.set_default_dtype(torch.float32)
    with torch.no_grad():  # random weights: greedy decoding emits action tokens, as a trained OpenVLA's does
        model.get_output_embeddings().weight[31744:32000] *= 4
    return OpenVLAPolicy(model, processor, args.unnorm_key)


def scene(robot: int, steps: int) -> list[np.ndarray]:
    """A robot's camera images: its own random scene, drifting a few pixels a step (224 x 224 uint8)."""
    rng = np.random.default_rng(robot)
    world = rng.integers(0, 256, (224 + 2 * steps, 224 + 2 * steps, 3), dtype=np.uint8)
    return [np.ascontiguousarray(world[2 * t : 2 * t + 224, t : t + 224]) for t in range(steps)]


def drive(url: str, robots: int, steps: int, key: str) -> dict:
    """K robot threads, ``steps`` requests each (a session per robot, reset at its first): their replies, times."""
    from hf_specvla.serving import PolicyClient

    replies: dict = {}
    latency: list[float] = []
    images = [scene(robot, steps) for robot in range(robots)]

    def robot(i: int) -> None:
        client = PolicyClient(url)
        for step in range(steps):
            start = time.perf_counter()
            replies[i, step] = client.act(images[i][step], INSTRUCTIONS[i % len(INSTRUCTIONS)], session=f"r{i}",
                                          reset=step == 0, unnorm_key=key)  # fmt: skip
            latency.append(1000 * (time.perf_counter() - start))

    threads = [threading.Thread(target=robot, args=(i,)) for i in range(robots)]
    start = time.perf_counter()
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    wall = time.perf_counter() - start
    served = [r.served for r in replies.values()]
    return {
        "actions_per_s": len(replies) / wall,
        "ms_per_action": statistics.median(latency),
        "decode_ms": statistics.median(s.decode_ms for s in served),
        "forwards_per_call": statistics.mean(s.batch_forwards for s in served),
        "batch_sizes": sorted({s.batch_size for s in served}),
        "actions": {f"{i}/{step}": reply.action.tolist() for (i, step), reply in replies.items()},
    }


def unlike(run: dict, greedy: dict, policy) -> int:
    """Action tokens of ``run`` unlike the greedy run's for the same (robot, step)."""
    count = 0
    for name, action in run["actions"].items():
        ids = np.asarray(policy.model.action_token_ids(np.asarray(action)).cpu())
        ids_greedy = np.asarray(policy.model.action_token_ids(np.asarray(greedy["actions"][name])).cpu())
        count += int((ids != ids_greedy).sum())
    return count


def main(argv=None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    from hf_specvla.policies.devices import Placement
    from hf_specvla.serving import PolicyService, ServeConfig
    from hf_specvla.serving.server import PolicyServer

    if args.threads:
        torch.set_num_threads(args.threads)
    placement = Placement.resolve(args.device, args.dtype)
    policy = build_policy(args, placement)
    key = args.unnorm_key or policy.default_unnorm_key or policy.unnorm_keys[0]
    buckets = tuple(args.buckets or [b for b in (1, 2, 4, 8, 16, 32) if b < max(args.robots)] + [max(args.robots)])
    settings = dict(buckets=buckets, calibration_calls=0, max_wait_ms=args.max_wait_ms, device=placement.device)
    servers, warm_up_s = {}, {}
    from hf_specvla.policies.decoding_methods import serving_methods

    compiled = serving_methods(args.method, False, policy.config.action_dim)[0].compiled
    greedy_method = "greedy:compile" if compiled else "greedy"  # the plain server an eager method is measured against
    for name, method in (("speculative", args.method), ("greedy", greedy_method)):
        speculate = buckets if name == "speculative" else ()
        service = PolicyService(policy, ServeConfig(method=method, speculate_buckets=speculate, **settings))
        start = time.perf_counter()
        service.warm_up()
        warm_up_s[name] = round(time.perf_counter() - start, 1)
        logger.info("%s server (%s): warmed up in %.1f s", name, service.methods_name, warm_up_s[name])
        servers[name] = PolicyServer(service, port=0).__enter__()
    runs = []
    try:
        for repeat in range(args.repeats):
            for robots in args.robots:
                order = list(servers)[repeat % 2 :] + list(servers)[: repeat % 2]
                results = {name: drive(servers[name].url, robots, args.steps, key) for name in order}
                for name, result in results.items():
                    result.update(repeat=repeat, robots=robots, server=name,
                                  unlike_greedy=unlike(result, results["greedy"], policy))  # fmt: skip
                    runs.append(result)
                    logger.info(
                        "K=%d %s: %.1f actions/s, %.1f forwards a call, %d tokens unlike greedy's",
                        robots,
                        name,
                        result["actions_per_s"],
                        result["forwards_per_call"],
                        result["unlike_greedy"],
                    )
    finally:
        for server in servers.values():
            server.__exit__(None, None, None)
    for run in runs:  # compared above; the report keeps the counts, not every action
        run.pop("actions")
    table = summarise(runs, args.robots)
    print_table(table)
    report = {"args": vars(args), "device": placement.device, "dtype": str(placement.dtype), "buckets": buckets,
              "warm_up_s": warm_up_s, "table": table, "runs": runs, "torch": torch.__version__,
              "threads": torch.get_num_threads()}  # fmt: skip
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    Path(args.output).write_text(json.dumps(report, indent=1))
    if placement.dtype == torch.float32 and any(run["unlike_greedy"] for run in runs):
        logger.error("float32 at r=0: a served action differs from the greedy server's")
        return 1
    return 0


def summarise(runs: list[dict], robot_counts: list[int]) -> list[dict]:
    rows = []
    for robots in robot_counts:
        for name in ("greedy", "speculative"):
            mine = [r for r in runs if r["robots"] == robots and r["server"] == name]
            greedy = {r["repeat"]: r for r in runs if r["robots"] == robots and r["server"] == "greedy"}
            rate = [r["actions_per_s"] for r in mine]
            rows.append({
                "robots": robots, "server": name,
                "actions_per_s": round(statistics.median(rate), 2), "range": [round(min(rate), 2), round(max(rate), 2)],
                "vs_greedy": round(statistics.median(r["actions_per_s"] / greedy[r["repeat"]]["actions_per_s"]
                                                     for r in mine), 2),
                "ms_per_action": round(statistics.median(r["ms_per_action"] for r in mine), 1),
                "decode_ms": round(statistics.median(r["decode_ms"] for r in mine), 1),
                "forwards_per_call": round(statistics.median(r["forwards_per_call"] for r in mine), 2),
                "batch_sizes": sorted({b for r in mine for b in r["batch_sizes"]}),
                "unlike_greedy": sum(r["unlike_greedy"] for r in mine),
            })  # fmt: skip
    return rows


def print_table(rows: list[dict]) -> None:
    print("| K | server | actions/s [min-max] | vs greedy | ms/action | decode ms | forwards/call | batches | unlike |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['robots']} | {r['server']} | {r['actions_per_s']} [{r['range'][0]}-{r['range'][1]}] | "
              f"{r['vs_greedy']}x | {r['ms_per_action']} | {r['decode_ms']} | {r['forwards_per_call']} | "
              f"{r['batch_sizes']} | {r['unlike_greedy']} |")  # fmt: skip


if __name__ == "__main__":
    raise SystemExit(main())
