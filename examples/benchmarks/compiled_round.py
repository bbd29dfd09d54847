"""The compiled round's acceptance inside its graph (issue 66, ``speculative.fused``), before / after in one process:
every speculative method runs twice per step, once with the acceptance inside the verification's graph (and the
guards skipped after a key's first round: the engine's default) and once accepting after transformers' compiled
model call (as before), interleaved in a fresh random order with transformers' compiled greedy; one thread; medians.

* ``--tiny`` (default): ``host_overhead.py``'s tiny Llama, whose forwards cost almost nothing (the host's time):
  Jacobi (about one token a round), right drafts (one forward: the prefill, unchanged) and Jacobi at B = 4.
* ``--policy DIR``: a Meta-World policy (policy v3: ``policies/mt10_vla3``) replaying its own greedy episodes
  (MT10's first ``--tasks``, ``--steps`` steps, ``--repeats`` passes), ``exact`` against ``greedy:compile`` and
  eager greedy, with where the time goes (``ForwardClock``: vision, prefill, later forwards, drafting, rest).
  ``--call-work`` switches instead what a compiled call does once (the image encoder compiled,
  ``speculative.vision``; the r=0 acceptance of host-drafted trees on the host), each off in turn.

    python examples/benchmarks/compiled_round.py --json round_tiny.json                     # ~2 min
    python examples/benchmarks/compiled_round.py --policy policies/mt10_vla3 --json round_v3.json   # ~2 min
    PYTHONPATH=<checkout of another commit>/src python examples/benchmarks/compiled_round.py --policy \
        policies/mt10_vla3 --plain --json before.json      # greedy, greedy:compile, exact on that engine
    python examples/benchmarks/compiled_round.py --policy policies/mt10_vla3 --call-work --json work.json  # ~4 min

Both variants' tokens are checked against greedy's (bin distance 0 on the policy).
"""

from __future__ import annotations

import argparse
import json
import random
import statistics
import sys
import time
from pathlib import Path

import torch
import transformers

import hf_specvla.speculative.call as speculative_call

sys.path.insert(0, str(Path(__file__).resolve().parent))

ORIGINAL = getattr(speculative_call, "accepts_in_graph", None)  # None: an engine from before the compiled round
IN_GRAPH = {"on": True}


def _call_work_switch():
    """(set(vision, host) -> None): switches the compiled image encoder (``speculative.vision``) and the r=0
    acceptance of host-drafted trees on the host (``acceptance.exact_paths_on_host``, off: the device search) for the
    calls that follow."""
    import hf_specvla.speculative.acceptance as acceptance
    from hf_specvla.speculative.decoder import SpeculativeDecoder

    encoder, on_host = SpeculativeDecoder.encode_images, acceptance.exact_paths_on_host

    def device_search(trees, target_ids):
        packed = acceptance.search_paths(trees.token_ids, trees.ancestor_or_self, trees.parents, trees.depths,
                                         trees.is_real, target_ids, None, None, None, acceptance.ExactMatch(),
                                         None)  # fmt: skip
        return acceptance.read_paths(packed.tolist(), trees)

    def switch(vision: bool, host: bool) -> None:
        SpeculativeDecoder.encode_images = encoder if vision else (lambda decoder, kwargs: kwargs)
        acceptance.exact_paths_on_host = on_host if host else device_search

    return switch


def _switchable(*args) -> bool:
    """The engine's choice, or False while the "after" variant runs."""
    return IN_GRAPH["on"] and ORIGINAL(*args)


def tiny(rounds: int) -> dict:
    import host_overhead

    model = host_overhead.tiny_llama()
    table = host_overhead.methods(model, small=False)
    names = ["greedy:compile 8", "jacobi", "drafts right", "jacobi B=4"]
    runs = [(name, on) for name in names for on in ((True, False) if name != names[0] else (True,))]
    expected = {name: table[name]().sequences for name in names}
    for name, on in runs:  # warm-up: both variants' graphs compiled
        IN_GRAPH["on"] = on
        output = table[name]()
        assert torch.equal(output.sequences, expected[names[0]] if "B=4" not in name else expected[name]), name
    times: dict[tuple, list[float]] = {run: [] for run in runs}
    rng = random.Random(0)
    for _ in range(rounds):
        rng.shuffle(runs)
        for name, on in runs:
            IN_GRAPH["on"] = on
            start = time.perf_counter()
            table[name]()
            times[(name, on)].append(1000 * (time.perf_counter() - start))
    rows = []
    greedy = statistics.median(times[(names[0], True)])
    for name in names[1:]:
        inside, after = statistics.median(times[(name, True)]), statistics.median(times[(name, False)])
        rows.append({"method": name, "ms_in_graph": inside, "ms_after": after, "saved_ms": after - inside,
                     "greedy_compile_8_ms": greedy})  # fmt: skip
    return {"rows": rows}


def policy(path: str, tasks: list[str], steps: int, repeats: int, plain: bool, call_work: bool = False) -> dict:
    from hf_specvla.benchmarks.speed import EpisodeMethod, ForwardClock, policy_actor, run_episode_benchmark
    from hf_specvla.metaworld.evaluation import record_observations
    from hf_specvla.policies import DecodingMethod, VLAPolicy
    from hf_specvla.speculative import compiled_decoding_kwargs

    target = VLAPolicy.from_pretrained(path)
    episodes = record_observations(target, tasks, [300000], steps)
    base = policy_actor(target)

    switch = _call_work_switch() if call_work else None

    def act(observation, history, prior, _in_graph=True, _vision=True, _host=True, **kwargs):
        IN_GRAPH["on"] = _in_graph
        if switch is not None:
            switch(_vision, _host)
        return base(observation, history, prior, **kwargs)

    exact = DecodingMethod.parse("exact", False, target.config.action_dim).generate_kwargs(draft_head=None)
    prior = bool(exact.pop("action_prior", True))
    methods = [EpisodeMethod("greedy"), EpisodeMethod("greedy:compile", compiled_decoding_kwargs("cpu"))]
    if plain:
        methods.append(EpisodeMethod("exact", exact, prior))
    elif call_work:
        for name, vision, host in (("exact", True, True), ("exact, eager image encoder", False, True),
                                   ("exact, acceptance on the device", True, False),
                                   ("exact, both off (before)", False, False)):  # fmt: skip
            methods.append(EpisodeMethod(name, {**exact, "_vision": vision, "_host": host}, prior))
    else:
        for name, in_graph in (("in the graph", True), ("after the forward", False)):
            methods.append(EpisodeMethod(f"exact, acceptance {name}", {**exact, "_in_graph": in_graph}, prior))
    results = run_episode_benchmark(act, episodes, methods, target.config.action_tokens, repeats=repeats,
                                    clock=ForwardClock(target.model), progress=False)  # fmt: skip
    compiled = next(r for r in results if r.name == "greedy:compile")
    rows = []
    for result in results:
        calls = len(result.latencies)
        rows.append({
            "method": result.name, "median_ms": 1000 * statistics.median(result.latencies),
            "vs_greedy_compile_median": statistics.median(compiled.latencies) / statistics.median(result.latencies),
            "vs_greedy_compile_total": sum(compiled.latencies) / sum(result.latencies),
            "vs_greedy_total": sum(results[0].latencies) / sum(result.latencies),
            "target_forwards_per_call": statistics.mean(result.target_forwards),
            "max_bin_distance": max(result.bin_distances, default=0),
            "split_ms": {part: 1000 * seconds / calls for part, seconds in result.split_seconds.items()},
        })  # fmt: skip
    assert all(row["max_bin_distance"] == 0 for row in rows), rows
    return {"tasks": tasks, "steps": steps, "repeats": repeats, "calls": len(compiled.latencies), "rows": rows}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", default=None, help="a policy folder (default: the tiny Llama)")
    parser.add_argument("--tasks", nargs="+", default=["reach-v3", "push-v3", "pick-place-v3", "door-open-v3"])
    parser.add_argument("--steps", type=int, default=20, help="steps recorded per task (policy)")
    parser.add_argument("--repeats", type=int, default=3, help="passes over the episodes (policy)")
    parser.add_argument("--rounds", type=int, default=300, help="interleaved rounds (tiny)")
    parser.add_argument("--plain", action="store_true",
                        help="policy: greedy, greedy:compile and exact only, no switch (runs on any engine version: "
                             "PYTHONPATH=<another checkout>/src for a before / after across commits)")  # fmt: skip
    parser.add_argument("--call-work", action="store_true",
                        help="policy: exact with the compiled image encoder and the r=0 acceptance on the host "
                             "switched off in turn, interleaved (what each saves a call)")  # fmt: skip
    parser.add_argument("--json", default=None, help="also write the results here")
    args = parser.parse_args()
    for name in ("steps", "repeats", "rounds"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if (args.plain or args.call_work) and args.policy is None:
        parser.error("--plain and --call-work need --policy")
    if args.plain and args.call_work:
        parser.error("--plain and --call-work are two different runs: pick one")
    if ORIGINAL is None and not args.plain:
        parser.error("this engine has no compiled round's acceptance to switch: run with --policy ... --plain")
    torch.set_num_threads(1)
    if not args.plain and not args.call_work:
        speculative_call.accepts_in_graph = _switchable
    result = (tiny(args.rounds) if args.policy is None
              else policy(args.policy, args.tasks, args.steps, args.repeats, args.plain, args.call_work))  # fmt: skip
    result.update(torch=torch.__version__, transformers=transformers.__version__, settings=vars(args))
    print(json.dumps(result["rows"], indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
