"""``hf-specvla robots``: K concurrent Meta-World robots drive a policy server (``hf-specvla serve``): each robot
renders what the server's ``GET /info`` names, sends its observation, executes the returned action (a chunk whole)
and repeats until its episode ends. Writes per-episode results as ``eval`` does plus the serving figures (actions
per second, request latency p50 / p95 / p99, the batch sizes the server formed, the method it used) (resumable)."""

from __future__ import annotations

import argparse
import os

from ..metaworld.fleet import RobotsConfig
from ..serving.config import API_KEY_VARIABLE
from .common import NON_NEGATIVE, POSITIVE, check_output_dir_flag, check_tasks, usage_errors

NAME = "robots"
HELP = "concurrent Meta-World robots driving a policy server: success, actions/s, latency, batching (resumable)"
EXAMPLES = """
    # Robots against a policy server (start it first: hf-specvla serve --policy policies/mt10_vla3 --method exact)
    hf-specvla robots --server http://127.0.0.1:8000 --tasks reach-v3 --episodes 2 --robots 4 \\
        --output-dir runs/robots_reach
    hf-specvla robots --tasks MT10 --episodes 5 --robots 8 --output-dir runs/robots_mt10
"""


def add_arguments(parser) -> None:
    defaults = RobotsConfig
    parser.add_argument("--server", default=defaults.server, help="the policy server's address")
    parser.add_argument(
        "--api-key", default=argparse.SUPPRESS, help=f"the server's API key (default: ${API_KEY_VARIABLE})"
    )
    parser.add_argument("--tasks", nargs="+", default=["MT10"], help="suites and/or task names")
    parser.add_argument("--episodes", type=POSITIVE, default=defaults.episodes_per_task, help="episodes per task")
    parser.add_argument(
        "--robots",
        type=POSITIVE,
        default=defaults.robots,
        help="concurrent robots, each its own environment and server session",
    )
    parser.add_argument("--seed-start", type=NON_NEGATIVE, default=defaults.seed_start, help="first seed")
    parser.add_argument("--max-episode-steps", type=POSITIVE, default=defaults.max_episode_steps, help="step limit")
    parser.add_argument("--output-dir", required=True, help="episodes.jsonl + summary.json go here (resumes)")
    parser.add_argument(
        "--overwrite-output-dir", action="store_true", help="move a folder holding another run aside, start over"
    )


def _fail(parser, message: str):
    """A one-line error (exit code 1): the server, not the command line, is at fault."""
    parser.exit(1, f"{parser.prog}: error: {message}\n")


def _check_server(config: RobotsConfig, parser) -> None:
    """Reads the server's ``/info`` before anything is written: an unreachable server, a refusal (a missing API key)
    or a server that is not an hf-specvla policy server for Meta-World robots is a one-line error naming it."""
    from ..metaworld.fleet import ServerInfo
    from ..serving.client import PolicyClient, ServerError

    url = config.server
    try:  # few retries: a server that is not there is said at once
        ServerInfo.from_payload(PolicyClient(url, config.api_key, timeout_s=10.0, retries=2).info())
    except ConnectionError as error:
        _fail(
            parser,
            f"cannot reach the policy server at {url} ({error}); start one with `hf-specvla serve` or "
            f"give its address with --server",
        )
    except ServerError as error:
        hint = f"; give its key with --api-key or {API_KEY_VARIABLE}" if error.status in (401, 403) else ""
        _fail(parser, f"the policy server at {url} refused GET /info: {error}{hint}")
    except ValueError as error:  # a ServerReplyError, or /info is not JSON
        _fail(parser, f"the server at {url} cannot drive Meta-World robots: {error}")


def run(args, parser) -> int:
    from ..metaworld.fleet import ServerReplyError, format_summary, run_robots
    from ..serving.client import ServerError

    check_output_dir_flag(args.output_dir, parser)
    check_tasks(args.tasks, parser)
    api_key = getattr(args, "api_key", None) or os.environ.get(API_KEY_VARIABLE) or None
    with usage_errors(parser, errors=(ValueError,)):
        config = RobotsConfig(
            args.tasks, args.episodes, args.robots, args.seed_start, args.max_episode_steps, args.server, api_key
        )
    _check_server(config, parser)
    resume = f"the finished episodes stay in {args.output_dir}: the same command continues them"
    try:
        with usage_errors(parser, errors=(FileExistsError,)):
            summary = run_robots(config, args.output_dir, overwrite=args.overwrite_output_dir)
    except ConnectionError as error:
        _fail(parser, f"lost the policy server at {config.server} ({error}); {resume}")
    except (ServerError, ServerReplyError) as error:
        _fail(parser, f"the policy server at {config.server}: {error}; {resume}")
    print(format_summary(summary))
    print(f"episodes.jsonl and summary.json in {args.output_dir}")
    return 0
