"""``hf-specvla serve``: serve a policy to robots over HTTP — OpenVLA's ``POST /act`` API and more (sessions with
each robot's drafts, per-request figures), batching the requests that arrive together, decoding each batch size
speculatively or greedily, whichever this machine does faster (measured at start-up, kept current on traffic).
One machine by default; ``--ray`` runs the same API as a Ray Serve deployment (``--replicas``). Runs until SIGTERM
or Ctrl-C; the requests in flight get their actions first."""

from __future__ import annotations

import importlib.util
import logging
import os
import time

from .common import (
    POSITIVE,
    add_device_arguments,
    check_draft_head_flag,
    load_draft_head_for,
    positive_number,
    read_policy_config,
    resolve_placement,
    usage_errors,
)

logger = logging.getLogger(__name__)

NAME = "serve"
HELP = "serve a policy to robots over HTTP (OpenVLA's /act API; batched, speculative where it pays)"
EXAMPLES = """
    # Serve policy v3 on 127.0.0.1:8000 with the lossless preset; drive it with 4 robots from another shell
    hf-specvla serve --policy policies/mt10_vla3 --method exact
    hf-specvla robots --server http://127.0.0.1:8000 --tasks reach-v3 --episodes 2 --robots 4 \\
        --output-dir runs/robots_reach
    # With the shipped draft head: each batch size decodes with exact, exact + the head or greedy, the fastest
    hf-specvla serve --policy policies/mt10_vla3 --method exact --draft-head policies/mt10_vla3_draft_v3 --port 8004
    # Quick start-up (eager decoding, no compile), small batches; a greedy-only server (the baseline)
    hf-specvla serve --policy policies/mt10_vla3 --method prior+jacobi --buckets 1 2 4 --port 8001
    hf-specvla serve --policy policies/mt10_vla3 --method greedy:compile --port 8002
    # Instructions longer than the default limit (GET /info: max_prompt_tokens): their graphs compiled at start-up
    hf-specvla serve --policy policies/mt10_vla3 --method exact --max-prompt-tokens 240 --port 8003
    # Reachable from other machines: an API key is required (from the environment, not the command line)
    HF_SPECVLA_API_KEY=change-me hf-specvla serve --policy policies/mt10_vla3 --host 0.0.0.0
    # A warm start: the second start with the same settings reuses the first one's compile (docs/serving.md)
    hf-specvla serve --policy policies/mt10_vla3 --method exact --buckets 1 2 4 --compile-cache runs/compile_cache
    # Ray Serve: 2 replicas on a local Ray cluster (or --ray-address auto for a running one)
    hf-specvla serve --policy policies/mt10_vla3 --method exact --ray --replicas 2
    # On the CPU in float32 (default: auto, a GPU in bfloat16 when torch sees one; GET /info says which)
    hf-specvla serve --policy policies/mt10_vla3 --method prior+jacobi --buckets 1 2 --device cpu --dtype float32 \\
        --port 8005
    # An OpenVLA checkpoint (a folder or a hub id) on a GPU in bfloat16; OpenVLA's deploy.py client works unchanged
    hf-specvla serve --policy openvla/openvla-7b --unnorm-key bridge_orig --method exact --buckets 1 4 --device cuda \\
        --port 8006
"""


def add_arguments(parser) -> None:
    from ..serving.config import (
        API_KEY_VARIABLE,
        BODY_TIMEOUT_S,
        DEFAULT_HOST,
        DEFAULT_MAX_REQUEST_BYTES,
        DEFAULT_PORT,
        MAX_WAIT_MS,
        ServeConfig,
    )

    defaults = ServeConfig()
    parser.add_argument(
        "--policy",
        required=True,
        help="a policy folder (train-vla output), or an OpenVLA checkpoint: a folder holding config.json, the "
        "weights, preprocessor_config.json and the tokenizer files (as the hub's openvla/openvla-7b does), or a hub id",
    )
    parser.add_argument(
        "--unnorm-key",
        default=None,
        metavar="DATASET",
        help="an OpenVLA checkpoint's dataset whose statistics un-normalise the actions of a request that names none "
        "(default: the checkpoint's only one; with several, each request names its own)",
    )
    parser.add_argument(
        "--method",
        nargs="+",
        default=[defaults.method],
        help="the speculative method or preset, as `compare` names it (exact, fast, "
        "prior+jacobi:compile, ...), or several: each batch size decodes with the fastest of them "
        "and greedy (measured); a preset with --draft-head stands for its methods with and "
        "without the head; greedy / greedy:compile serve greedy only",
    )
    parser.add_argument(
        "--draft-head",
        default=None,
        help="a DraftHead folder, for methods that draft with one (with a preset: measured beside "
        "the preset's head-less method)",
    )
    parser.add_argument(
        "--host",
        default=DEFAULT_HOST,
        help=f"address to listen on; other than loopback needs --api-key (or {API_KEY_VARIABLE})",
    )
    parser.add_argument("--port", type=_port, default=DEFAULT_PORT, help="TCP port (0: any free port)")
    parser.add_argument(
        "--api-key",
        default=os.environ.get(API_KEY_VARIABLE),
        help=f"every request must carry it (default: ${API_KEY_VARIABLE})",
    )
    parser.add_argument(
        "--buckets",
        type=POSITIVE,
        nargs="+",
        default=list(defaults.buckets),
        help="batch sizes decoding runs at (one compiled shape each); the largest is the most "
        "requests decoded together",
    )
    parser.add_argument(
        "--max-wait-ms",
        type=float,
        default=defaults.max_wait_ms,
        help=f"ms a batch waits for more after its first request (0..{MAX_WAIT_MS:g})",
    )
    parser.add_argument(
        "--max-prompt-tokens",
        type=POSITIVE,
        default=defaults.max_prompt_tokens,
        help="the longest prompt served, in tokens, for a compiled method: start-up compiles graphs "
        "for every length up to it (default: what the shortest prompt's cache holds; GET /info "
        "states it); longer requests get 422",
    )
    parser.add_argument(
        "--max-queue",
        type=POSITIVE,
        default=defaults.max_queue,
        help="requests waiting beyond the batch in decoding; more get 503 + Retry-After",
    )
    parser.add_argument(
        "--calibration-calls",
        type=int,
        default=defaults.calibration_calls,
        help="timed calls per bucket and mode at start-up (0: no calibration)",
    )
    parser.add_argument(
        "--speculate-buckets",
        type=int,
        nargs="*",
        default=None,
        help="fix the buckets that decode speculatively (the others greedily), instead of measuring; "
        "no values: never speculate",
    )
    parser.add_argument(
        "--explore-every",
        type=int,
        default=defaults.explore_every,
        help="every n-th batch of a bucket runs the mode not chosen, keeping its timing current (0: never)",
    )
    parser.add_argument(
        "--compile-cache",
        default=None,
        metavar="DIR",
        help="keep the compiled graphs in this folder (the engine's graph files in DIR/graphs, torch's "
        "Inductor caches beside them): a later start loads them instead of compiling (a warm start; "
        "with --ray, a folder every replica's node can write)",
    )
    parser.add_argument(
        "--max-request-bytes", type=POSITIVE, default=DEFAULT_MAX_REQUEST_BYTES, help="the largest request body"
    )
    parser.add_argument(
        "--body-timeout-s",
        type=positive_number,
        default=BODY_TIMEOUT_S,
        help="the longest a request's body may take to arrive whole, in seconds (408 past it; a half-sent body holds "
        "a shutdown at most this long; at most 600)",
    )
    parser.add_argument("--threads", type=POSITIVE, default=None, help="torch CPU threads (per replica with --ray)")
    add_device_arguments(parser)
    parser.add_argument("--ray", action="store_true", help="serve as a Ray Serve deployment")
    parser.add_argument("--replicas", type=POSITIVE, default=None, help="Ray Serve replicas, with --ray (unset: 1)")
    parser.add_argument(
        "--ray-address", default=None, help="a running Ray cluster (auto, ray://host:port); default: start a local one"
    )


def _port(text: str) -> int:
    import argparse

    if not text.isascii() or not text.isdigit() or int(text) > 65535:
        raise argparse.ArgumentTypeError(f"must be a TCP port 0..65535, got {text!r}")
    return int(text)


def serve_config(args, parser):
    """The [`ServeConfig`] the flags name (usage errors for bad values)."""
    from ..serving.config import ServeConfig

    with usage_errors(parser, "--buckets", (ValueError, TypeError)):  # the flag named, as every other one is
        ServeConfig(buckets=tuple(args.buckets))
    with usage_errors(parser, errors=(ValueError, TypeError)):
        speculate = None if args.speculate_buckets is None else tuple(args.speculate_buckets)
        return ServeConfig(
            method=tuple(args.method),
            buckets=tuple(args.buckets),
            max_wait_ms=args.max_wait_ms,
            max_queue=args.max_queue,
            calibration_calls=args.calibration_calls,
            speculate_buckets=speculate,
            explore_every=args.explore_every,
            max_prompt_tokens=args.max_prompt_tokens,
            compile_cache=args.compile_cache and os.path.abspath(args.compile_cache),
            device=args.device,
            dtype=args.dtype,
            unnorm_key=args.unnorm_key,
        )


def run(args, parser) -> int:
    from ..policies.decoding_methods import serving_methods
    from ..serving.config import check_body_timeout, check_exposure

    if (args.replicas is not None or args.ray_address is not None) and not args.ray:
        parser.error("--replicas / --ray-address are for Ray Serve: add --ray")
    missing = [name for name in ("starlette", "uvicorn") if importlib.util.find_spec(name) is None]
    if missing:
        parser.error(f"serving needs {' and '.join(missing)}: pip install 'hf_specvla[serve]'")
    with usage_errors(parser, "--host", (ValueError,)):
        check_exposure(args.host, args.api_key)
    with usage_errors(parser, "--body-timeout-s", (ValueError,)):
        check_body_timeout(args.body_timeout_s)
    config = serve_config(args, parser)
    if args.compile_cache is not None:
        from .common import check_output_dir_flag

        check_output_dir_flag(args.compile_cache, parser, "--compile-cache")
    check_draft_head_flag(args.draft_head, parser)
    policy_config = read_policy_config(args.policy, parser, unnorm_key=args.unnorm_key)  # cheap: no weights loaded
    given = " ".join(text.strip() for text in args.method)
    with usage_errors(parser, "--method", (ValueError,)):
        methods = serving_methods(args.method, bool(args.draft_head), policy_config.action_dim)
    for method in methods:
        if method.uses_draft_head and not args.draft_head:
            parser.error(f"--method {method.name} drafts with the draft head: give --draft-head")
    if args.draft_head and not any(m.uses_draft_head for m in methods):  # as compare does: said, not dropped silently
        logger.warning(
            "--draft-head %s is not used: --method %s does not draft with a head (head, tree, prior+head, "
            "prior+tree and the presets do); it is ignored",
            args.draft_head,
            given,
        )
        args.draft_head = None
    names = " ".join(method.name for method in methods)
    if given != names:
        logger.info("--method %s = %s", given, names)
    if args.ray:
        return _run_ray(args, parser, config)
    placement = resolve_placement(args, parser)  # before the port is taken and the policy loads
    return _run_local(args, parser, config, methods, placement)


def _run_local(args, parser, config, methods, placement) -> int:
    from ..metaworld.comparison.runner import check_method_rule
    from ..serving.server import PolicyServer, bind
    from ..serving.service import PolicyService
    from .common import load_policy

    with usage_errors(parser, "--port", (OSError,)):
        sock = bind(args.host, args.port)  # a taken port is refused before the policy loads
    started = time.perf_counter()
    policy = load_policy(args.policy, parser, unnorm_key=args.unnorm_key, dtype=placement.dtype)
    with usage_errors(parser, "--method", (ValueError, TypeError)):
        for method in methods:
            check_method_rule(method, policy)
    uses_head = any(method.uses_draft_head for method in methods)
    draft_head = load_draft_head_for(policy, args.draft_head, parser) if uses_head else None
    placement.place_policy(policy, draft_head)  # after the head's check: it compares the weights as saved
    logger.info(
        "loaded %s%s onto %s in %.1f s",
        args.policy,
        f" and {args.draft_head}" if draft_head is not None else "",
        placement,
        time.perf_counter() - started,
    )
    with usage_errors(parser, errors=(ValueError,)):  # e.g. --max-prompt-tokens shorter than any prompt
        service = PolicyService(policy, config, draft_head)
    server = PolicyServer(
        service,
        args.host,
        args.port,
        args.api_key,
        args.max_request_bytes,
        sock=sock,
        body_timeout_s=args.body_timeout_s,
    )
    compiled = any(method.compiled for method in methods)
    logger.info(
        "%s buckets %s%s",
        "compiling and calibrating" if compiled else "calibrating",
        list(config.buckets),
        " (a compiled method: ~30 s per bucket on 2 CPU cores)" if compiled else "",
    )
    service.warm_up()
    print(
        f"serving {args.policy} ({service.methods_name}) on {server.url}: POST /act, GET /info, GET /stats", flush=True
    )
    server.run()
    return 0


def _run_ray(args, parser, config) -> int:
    """A thin wrapper over Ray Serve's own ``serve run``: the flags become a Serve config file (the application
    ``serving.ray_deployment:build_app`` and its arguments, the HTTP host and port), which ``serve run`` deploys."""
    import json
    import tempfile
    from pathlib import Path

    from ..policies.loading import is_hub_id
    from ..serving.config import API_KEY_VARIABLE
    from ..serving.ray_deployment import PolicyAppArgs, require_ray, serve_config, serve_run

    with usage_errors(parser, "--ray", (ImportError,)):
        require_ray()
    if args.port == 0:
        parser.error("--port 0 (any free port) is for the server on one machine: give Ray Serve's proxy a port")
    replicas, threads = args.replicas or 1, args.threads or 1
    local = args.ray_address is None and not os.environ.get("RAY_ADDRESS")
    if local and replicas * threads > (os.cpu_count() or 1):
        parser.error(
            f"--replicas {replicas} x --threads {threads} need {replicas * threads} CPUs; this machine has "
            f"{os.cpu_count()}: fewer --replicas or --threads (or a --ray-address)"
        )
    if local:  # the replicas run on this machine: its devices are theirs (auto resolved here, so GPUs are asked for)
        from dataclasses import replace

        from ..policies.devices import is_cuda

        config = replace(config, device=resolve_placement(args, parser).device)
        if is_cuda(config.device):
            import torch

            if replicas > torch.cuda.device_count():
                parser.error(
                    f"--replicas {replicas} on --device {args.device} ask one GPU each; this machine has "
                    f"{torch.cuda.device_count()}: fewer --replicas, --device cpu (or a --ray-address)"
                )
    with usage_errors(parser, errors=(ValueError,)):
        app_args = PolicyAppArgs(
            policy=args.policy if is_hub_id(args.policy) else str(Path(args.policy).resolve()),
            serve=config,
            threads=threads,
            draft_head=str(Path(args.draft_head).resolve()) if args.draft_head else None,
            num_replicas=replicas,
            max_request_bytes=args.max_request_bytes,
            body_timeout_s=args.body_timeout_s,
        )
    settings = serve_config(app_args, args.host, args.port)
    if args.api_key and local:  # the local cluster inherits this environment: the key stays out of Serve's config
        os.environ[API_KEY_VARIABLE] = args.api_key
    elif args.api_key:
        logger.warning(
            "--api-key with --ray-address: the key travels in the application's arguments (`serve config` "
            "shows it); set %s on the cluster's nodes instead to keep it out",
            API_KEY_VARIABLE,
        )
        settings["applications"][0]["args"]["api_key"] = args.api_key
    host = f"[{args.host}]" if ":" in args.host else args.host
    url = f"http://{host}:{args.port}"

    given = " ".join(text.strip() for text in args.method)

    def ready(url: str) -> None:
        print(
            f"serving {args.policy} ({given}) on {url}: POST /act, GET /info, GET /stats "
            f"(Ray Serve, {replicas} replicas)",
            flush=True,
        )

    with tempfile.TemporaryDirectory(prefix="hf-specvla-serve-") as folder:
        config_file = Path(folder) / "serve_config.yaml"  # JSON is YAML: serve run reads it as such
        config_file.write_text(json.dumps(settings, indent=2))
        logger.info("serve run %s:\n%s", config_file, config_file.read_text())
        status = serve_run(config_file, args.ray_address, on_ready=ready, url=url)
    logger.info("Ray Serve application on %s stopped", url)
    return status
