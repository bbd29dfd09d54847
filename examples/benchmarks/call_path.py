"""How much of hf_specvla one robot's call passes through (issue 86's target): from ``VLAPolicy.predict_action
(decoding=plan)`` to the target's forward, the distinct hf_specvla functions that run, the files they are in, and the
hf_specvla frames on the stack when the target's forward starts.

A random tiny policy (seconds) decodes one episode's first calls with one method (``exact`` by default: the previous
action drafted, Jacobi guesses, compiled), through the policy's decoder session as ``predict_action`` runs by
default; the call measured is ``--call``'s (the third: an episode's calls from there on repeat its path), counted
with ``sys.setprofile`` (Python calls only: comprehensions, generator expressions and lambdas are reported apart).

Spans counted:

* ``to the forward``: from ``predict_action`` to the prefill's verification (``verify.py``'s ``verify``: the target's
  forward, compiled or not, is its next step);
* ``whole call``: everything ``predict_action`` runs (the rounds and the end too).

    python examples/benchmarks/call_path.py
    python examples/benchmarks/call_path.py --method exact --files       # each file's functions
    python examples/benchmarks/call_path.py --method none:compile --json runs/call_path.json
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
from session_path import tiny_policy  # this folder's: the random tiny policy of its --tiny mode

import hf_specvla
from hf_specvla.metaworld.env import TASK_INSTRUCTIONS
from hf_specvla.policies.decoding_methods import DecodingMethod

#: the package's folder: a function counts when its file is under it
PACKAGE = str(Path(hf_specvla.__file__).parent)
#: code objects Python makes inside a function (counted apart)
INNER = ("<listcomp>", "<dictcomp>", "<setcomp>", "<genexpr>", "<lambda>")


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog=__doc__.split("\n\n")[-1],
        formatter_class=argparse.RawTextHelpFormatter,
    )
    parser.add_argument("--method", default="exact", help="a decoding method (default: %(default)s)")
    parser.add_argument("--call", type=int, default=3, help="which call of the episode to count (default: 3)")
    parser.add_argument("--no-session", action="store_true", help="every call through model.generate")
    parser.add_argument("--files", action="store_true", help="list each file's functions")
    parser.add_argument("--json", type=Path, help="write the counts here")
    args = parser.parse_args(argv)
    if args.call < 1:
        parser.error(f"--call must be >= 1, got {args.call}")
    try:
        DecodingMethod.parse(args.method)
    except ValueError as error:
        parser.error(str(error))
    if args.json is not None and args.json.exists():
        parser.error(f"--json {args.json} exists: nothing a run wrote is overwritten; pass a new path")
    return args


class CallTrace:
    """Records the hf_specvla code objects entered while it is installed (``sys.setprofile``), and where the first
    prefill verification starts."""

    def __init__(self):
        self.entered: list = []  # code objects in order of first entry
        self.seen: set = set()
        self.forward_at: int | None = None  # len(entered) when the prefill's verify started
        self.frames_at_forward: int | None = None

    def __call__(self, frame, event, arg):
        if event != "call":
            return
        code = frame.f_code
        if not code.co_filename.startswith(PACKAGE):
            return
        if self.forward_at is None and code.co_name == "verify" and code.co_filename.endswith("verify.py"):
            self.forward_at = len(self.entered)
            depth, f = 0, frame
            while f is not None:
                depth += f.f_code.co_filename.startswith(PACKAGE)
                f = f.f_back
            self.frames_at_forward = depth
        if code not in self.seen:
            self.seen.add(code)
            self.entered.append(code)


def summary(codes: list) -> dict:
    """Counts of ``codes``: functions (named ones), inner code objects, files; each file's functions."""
    named = [c for c in codes if c.co_name not in INNER]
    by_file: dict[str, list[str]] = defaultdict(list)
    for code in named:
        by_file[str(Path(code.co_filename).relative_to(PACKAGE))].append(code.co_qualname)
    return {
        "functions": len(named),
        "inner": len(codes) - len(named),
        "files": len(by_file),
        "by_file": dict(sorted(by_file.items(), key=lambda item: -len(item[1]))),
    }


def run(args: argparse.Namespace) -> dict:
    torch.manual_seed(0)
    torch.set_num_threads(1)
    policy = tiny_policy()
    policy.decoder_sessions = not args.no_session
    plan = DecodingMethod.parse(args.method).plan(None, policy.model.device.type, None, policy.config.action_dim)
    rng = np.random.default_rng(0)
    size = policy.config.image_size
    instruction = next(iter(TASK_INSTRUCTIONS.values()))
    policy.reset()
    trace = CallTrace()
    for call in range(1, args.call + 1):
        image = rng.integers(0, 256, (size, size, 3), dtype=np.uint8)
        state = rng.standard_normal(policy.config.state_dim) if policy.config.use_state else None
        if call == args.call:
            sys.setprofile(trace)
        try:
            policy.predict_action(image, instruction, state, decoding=plan)
        finally:
            sys.setprofile(None)
    if trace.forward_at is None:
        raise RuntimeError("the call ran no prefill verification (verify.py's verify): nothing to count to")
    return {
        "method": args.method,
        "call": args.call,
        "session": not args.no_session,
        "to the forward": summary(trace.entered[: trace.forward_at]),
        "whole call": summary(trace.entered),
        "hf_specvla frames at the forward": trace.frames_at_forward,
    }


def main(argv=None) -> None:
    args = parse_args(argv)
    result = run(args)
    print(f"{args.method}, call {args.call}, {'session' if result['session'] else 'model.generate'}:")
    print("| span | functions | files | + comprehensions, lambdas |")
    print("|---|---:|---:|---:|")
    for span in ("to the forward", "whole call"):
        counts = result[span]
        print(f"| {span} | {counts['functions']} | {counts['files']} | {counts['inner']} |")
    print(f"hf_specvla frames on the stack at the prefill's verification: {result['hf_specvla frames at the forward']}")
    if args.files:
        for name, functions in result["to the forward"]["by_file"].items():
            print(f"{name} ({len(functions)}): {', '.join(functions)}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
