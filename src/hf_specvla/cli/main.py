"""``hf-specvla``: the dispatcher. Each command is a module of this package with ``NAME``, ``HELP``, ``EXAMPLES``,
``add_arguments(parser)`` and ``run(args, parser)``; heavy libraries (accelerate, MuJoCo, the data and training
code) load inside ``run``, so ``--help`` and usage errors come back before any of them loads."""

from __future__ import annotations

import argparse
import sys

from . import bench_episodes, benchmark, collect, compare, demo, eval, robots, rollouts, serve, train_draft, train_vla
from .common import HelpFormatter, configure_logging

#: in the order ``--help`` lists them
COMMANDS = (demo, benchmark, bench_episodes, collect, train_vla, eval, rollouts, train_draft, compare, serve, robots)
EXAMPLES = "".join(command.EXAMPLES for command in COMMANDS)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hf-specvla",
        description="Draft-head speculative decoding with relaxed action acceptance for VLA models.",
        epilog="examples:" + EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    commands = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        sub = commands.add_parser(
            command.NAME,
            help=command.HELP,
            description=command.__doc__,
            epilog="examples:" + command.EXAMPLES,
            formatter_class=HelpFormatter,
        )
        command.add_arguments(sub)
        sub.set_defaults(command_module=command, command_parser=sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(argv)
    args.argv = argv
    configure_logging(args.verbose)
    if getattr(args, "threads", None) is not None:
        import torch

        torch.set_num_threads(args.threads)
    return args.command_module.run(args, args.command_parser)
