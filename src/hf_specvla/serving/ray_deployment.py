"""The policy server as a Ray Serve application, deployed the way Ray users deploy: an application builder that
``serve run`` and a Serve config file start (``build_app``), with the policy, the method, the buckets and the key as
its arguments. The same HTTP API as the server on one machine (``app``: ``POST /act``, ``GET /info``, ``GET /stats``,
``GET /health``), served by replicas that each hold their own [`PolicyService`] (the policy loaded, every bucket
compiled and calibrated before it takes a request).

    serve run hf_specvla.serving.ray_deployment:build_app policy=policies/mt10_vla3 method=exact num_replicas=2
    serve run examples/serving/serve_config.yaml       # replicas, max_ongoing_requests, autoscaling, ray_actor_options
    hf-specvla serve --policy policies/mt10_vla3 --method exact --ray --replicas 2   # writes such a file, serve runs it

Serve does the rest: it starts or joins the Ray cluster, starts the HTTP proxy, replaces a replica that dies, scales
with ``autoscaling_config``, and on Ctrl-C deletes the application (``serve run``'s own handling). A config file's
``deployments:`` entry for ``PolicyDeployment`` overrides the options this module sets from the arguments
(``num_replicas``, ``max_ongoing_requests``, ``max_queued_requests``, ``ray_actor_options``...).

**Batching.** Each replica forms its batches by the one-machine server's rule, with its [`Batcher`]: a batch is
formed when the decoding thread is free, from every request waiting then (up to the largest bucket), waiting at most
``max_wait_ms`` for the robots seen recently. Its event loop only hands requests over, so it keeps reading them,
answering health checks and noticing robots that went away (their requests leave the batch). Ray Serve's own
``serve.batch`` is not used: it forms the next batch while the current one decodes (the batch waits for the
decoding only after it is formed, ``max_concurrent_batches``), so robots whose replies leave at different times
(each row answered when done) each start a batch of their own, and a loaded replica decoded one request at a time
(1.15 robots a batch at K = 8, ~575 ms queued behind batches of one; docs/serving.md).

**Overload.** A replica takes at most ``2 x`` the largest bucket at once (``max_ongoing_requests``: the batch being
decoded and the next one filling); beyond that each Ray Serve proxy queues up to ``max_queue`` requests
(``max_queued_requests``), and refuses the rest itself. On Ray 2.60 the refusal is HTTP 503 with ``Retry-After: 1``
(``BackpressureConfig``; Ray releases without it send the 503 with no ``Retry-After``) and a plain-text body
("Request dropped due to backpressure ..."), not the JSON error of the one-machine server; [`PolicyClient`] retries
it either way.

**Each robot's drafts.** A reply carries the robot's ``draft_state`` (its previous actions) and [`PolicyClient`]
echoes it with the robot's next request, so the drafts, hence the speed, do not depend on which replica answers; a
client that does not echo it gets the drafts of whichever replica last served its session, if any. Whatever
happens, the action is the policy's: at ``r = 0`` drafts change how fast an action comes, never which.

**Faults.** Ray replaces a replica that dies (its process killed, its node lost): its health check (every
``HEALTH_CHECK_PERIOD_S``) notices, and a new replica loads the policy and warms up; meanwhile the other replicas
serve (Ray 2.60 on 2 busy CPU cores, the small ``mt10_vla``: about 1 s to notice, 6 to 10 s to start). New requests
are routed around the dead replica at once. A request in flight on it fails: Ray 2.60's proxy answers it with HTTP
500 and a plain-text body ``Internal Server Error`` (not this API's JSON error); retrying it gives the same action.
The robot's drafts survive in its ``draft_state``; a robot that does not echo it gets its next action without prior
drafts (one step at the method's speed without the previous action), the same action.

**The key.** ``api_key`` among the arguments, else ``HF_SPECVLA_API_KEY`` in the replicas' environment (a local
cluster inherits the environment of the process that started it; on a cluster set it on the nodes or in the
``runtime_env``'s ``env_vars``): arguments are shown by ``serve config``, the environment is not. The builder cannot
see Serve's ``http_options``: serving on a host other than loopback without a key is refused by ``hf-specvla serve``,
not by a config file.

Needs Ray Serve (``pip install 'hf_specvla[ray]'``). This module imports Ray (and starlette, torch) only inside its
functions: it imports without them, and [`require_ray`] says what to install.
"""

from __future__ import annotations

import _thread
import asyncio
import dataclasses
import logging
import os
import signal
import threading
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..policies.devices import is_cuda
from .config import API_KEY_VARIABLE, BODY_TIMEOUT_S, DEFAULT_MAX_REQUEST_BYTES, ServeConfig, check_body_timeout
from .protocol import ActReply, ActRequest

if TYPE_CHECKING:
    from .service import PolicyService

logger = logging.getLogger(__name__)

#: the Ray Serve application's name (``serve status`` shows it)
APP_NAME = "hf_specvla"
#: the deployment's name within the application (a config file's ``deployments:`` entry names it)
DEPLOYMENT_NAME = "PolicyDeployment"
#: what ``serve run`` / a config file's ``import_path`` names
IMPORT_PATH = "hf_specvla.serving.ray_deployment:build_app"
#: the Retry-After (seconds) of Ray's own 503 on overload
OVERLOAD_RETRY_AFTER_S = 1
#: how often Ray checks that each replica is alive (Ray's default, 10 s, leaves a dead replica unnoticed that long)
HEALTH_CHECK_PERIOD_S = 2.0
#: what to install when Ray Serve is missing
RAY_EXTRA = "pip install 'hf_specvla[ray]'"


def require_ray():
    """``(ray, ray.serve)``.

    Raises:
        ImportError: Ray Serve is not installed (the message says how to install it).
    """
    try:
        import ray
        from ray import serve
    except ImportError as error:
        raise ImportError(f"serving on Ray needs Ray Serve ({error}): {RAY_EXTRA}") from error
    return ray, serve


def max_ongoing_requests(config: ServeConfig) -> int:
    """The requests a replica holds at once: the batch being decoded and the next one filling."""
    return 2 * config.max_batch_size


# ----------------------------------------------------------------------------- the builder's arguments
@dataclass
class PolicyAppArgs:
    """The application's arguments, as ``serve run ... key=value`` or a config file's ``args:`` give them.

    Args:
        policy: the policy's folder (a relative path is read from the directory the local cluster was started in;
            on a cluster of several machines, a path that exists on every node).
        serve: the service's [`ServeConfig`]; its fields are arguments of their own (``method``, ``buckets``,
            ``max_wait_ms``, ``max_queue``, ``calibration_calls``, ``speculate_buckets``, ``explore_every``,
            ``max_sessions``, ``max_prompt_tokens``, ``compile_cache``: a folder every replica's node can write,
            where a replica started later, or again, finds the graphs of the first: a warm start; ``device``,
            ``dtype``: each replica's, resolved in the replica: ``cuda`` asks its actor for one GPU, which Ray makes
            the replica's ``cuda:0``; ``auto`` asks for none, so it resolves to ``cpu`` unless a config file's
            ``ray_actor_options`` gives the replica a GPU).
        draft_head: a draft head's folder, for methods that draft with one.
        api_key: every request but ``/health`` must carry it (None: ``HF_SPECVLA_API_KEY`` in the replica's
            environment, else an open server).
        threads: torch CPU threads per replica (and its ``ray_actor_options.num_cpus`` unless the config file
            sets them).
        num_replicas: replicas (None: Serve's default, 1, or what the config file sets: ``num_replicas`` or
            ``autoscaling_config``, which the code's own ``num_replicas`` would clash with).
        max_request_bytes: the largest request body.
        body_timeout_s: the longest a request's body may take to arrive whole (408 past it; seconds in (0, 600]).
    """

    policy: str
    serve: ServeConfig = field(default_factory=ServeConfig)
    draft_head: str | None = None
    api_key: str | None = None
    threads: int = 1
    num_replicas: int | None = None
    max_request_bytes: int = DEFAULT_MAX_REQUEST_BYTES
    body_timeout_s: float = BODY_TIMEOUT_S

    def __post_init__(self):
        for name in ("threads", "num_replicas", "max_request_bytes"):
            value = getattr(self, name)
            if value is None and name == "num_replicas":
                continue
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        check_body_timeout(self.body_timeout_s)
        if is_cuda(self.serve.device) and self.serve.device not in ("cuda", "cuda:0"):
            raise ValueError(
                f"device {self.serve.device!r}: a Ray replica sees only the GPU Ray gives it (its cuda:0); give "
                f"device=cuda"
            )

    @classmethod
    def from_args(cls, args: dict[str, Any]) -> PolicyAppArgs:
        """Reads the builder's arguments: text (``serve run``'s ``key=value``) or typed values (YAML); lists as
        YAML lists or ``"1,2,4"`` (``method``: one, or a YAML list of several); ``speculate_buckets=""`` never
        speculates. Checks the policy's folder and the
        method against it (cheap: the weights are not loaded).

        Raises:
            ValueError: an unknown argument, a value of the wrong kind or out of range, no ``policy``, a folder
                without a policy, an unknown method, a method that needs a draft head without one.
        """
        from ..policies.loading import is_hub_id

        known = {f.name for f in dataclasses.fields(cls) if f.name != "serve"}
        serve_fields = {f.name: f for f in dataclasses.fields(ServeConfig)}
        unknown = sorted(set(args) - known - set(serve_fields))
        if unknown:
            raise ValueError(f"unknown argument(s) {unknown}; the arguments are {sorted(known | set(serve_fields))}")
        if not args.get("policy"):
            raise ValueError("the argument policy is required: policy=<a policy folder>")
        values = {name: _read_arg(name, value, _ARG_KINDS.get(name, "text")) for name, value in args.items()}
        serve = ServeConfig(**{k: v for k, v in values.items() if k in serve_fields})
        if serve.compile_cache is not None:  # the replicas' working directory may not be this one
            serve.compile_cache = str(Path(serve.compile_cache).expanduser().resolve())
        kept = {k: v for k, v in values.items() if k in known}
        if not is_hub_id(kept["policy"]):  # an OpenVLA hub id is loaded by each replica as it is
            kept["policy"] = _existing_folder(kept["policy"], "policy")
        if kept.get("draft_head") is not None:
            kept["draft_head"] = _existing_folder(kept["draft_head"], "draft_head")
        app_args = cls(serve=serve, **kept)
        app_args.check_method()
        return app_args

    def check_method(self) -> None:
        """The method is one this policy decodes with (and has its draft head if it drafts with one).

        Raises:
            ValueError: the folder holds no policy (neither a Meta-World policy nor an OpenVLA checkpoint); an
                ``unnorm_key`` it does not have; an unknown method; a head missing.
        """
        from ..policies.decoding_methods import serving_methods
        from ..policies.loading import read_policy_layout

        try:
            layout = read_policy_layout(self.policy, self.serve.unnorm_key)
        except FileNotFoundError as error:
            raise ValueError(f"policy {self.policy!r}: {error}") from None
        for method in serving_methods(self.serve.method, self.draft_head is not None, layout.action_dim):
            if method.uses_draft_head and self.draft_head is None:
                raise ValueError(f"method {method.name} drafts with the draft head: give draft_head=<its folder>")

    def to_args(self) -> dict[str, Any]:
        """The arguments that [`from_args`] reads back to this (a config file's ``args:``); the key is left out."""
        serve = {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self.serve).items()}
        mine = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in ("serve", "api_key")}
        return {k: v for k, v in {**mine, **serve}.items() if v is not None}


#: how each argument is read (the rest are text)
_ARG_KINDS = {
    "method": "texts",
    "buckets": "ints",
    "speculate_buckets": "ints",
    "max_wait_ms": "number",
    "max_queue": "int",
    "calibration_calls": "int",
    "explore_every": "int",
    "max_sessions": "int",
    "max_prompt_tokens": "int",
    "threads": "int",
    "num_replicas": "int",
    "max_request_bytes": "int",
    "body_timeout_s": "number",
}


def _read_arg(name: str, value: Any, kind: str) -> Any:
    """One argument as ``kind`` (``text``, ``texts``: one text or a list of them, ``int``, ``number``, ``ints``);
    None stays None."""
    if value is None:
        return None
    if kind == "texts" and isinstance(value, list | tuple):
        return tuple(_read_arg(name, item, "text") for item in value)
    try:
        if kind == "ints":
            items = value if isinstance(value, list | tuple) else str(value).replace(",", " ").split()
            return tuple(_read_arg(name, item, "int") for item in items)
        if kind == "int":
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError
            return int(value)
        if kind == "number":
            if isinstance(value, bool):
                raise ValueError
            return float(value)
    except (TypeError, ValueError):
        wanted = {"ints": "integers (a list, or '1,2,4')", "int": "an integer", "number": "a number"}[kind]
        raise ValueError(f"argument {name} must be {wanted}, got {value!r}") from None
    if not isinstance(value, str):
        raise ValueError(f"argument {name} must be text, got {value!r}")
    return value


def _existing_folder(folder: str, name: str) -> str:
    """``folder`` as an absolute path (the replicas' working directory may not be this one)."""
    path = Path(folder).expanduser()
    if not path.is_dir():
        raise ValueError(
            f"argument {name}: no folder {folder!r} (looked in {os.getcwd()}; give an absolute path, one "
            f"that exists on the machine that builds the application)"
        )
    return str(path.resolve())


# ----------------------------------------------------------------------------- the application
def build_app(args: dict[str, Any]):
    """The application builder that ``serve run`` and a Serve config file call: the [`PolicyDeployment`] bound to
    its arguments ([`PolicyAppArgs.from_args`]), with its options set from them (``num_replicas``,
    ``ray_actor_options.num_cpus = threads`` and ``num_gpus = 1`` on a CUDA ``device``, ``max_ongoing_requests`` =
    2 x the largest bucket, ``max_queued_requests`` = ``max_queue``, the health check's period and the overload's
    Retry-After); a config file's ``deployments:`` entry overrides any of them.

    Raises:
        ValueError: a bad argument (see [`PolicyAppArgs.from_args`]), before any replica starts.
        ImportError: Ray Serve is not installed.
    """
    return policy_app(PolicyAppArgs.from_args(args))


def policy_app(app_args: PolicyAppArgs):
    """[`build_app`] for arguments already read."""
    return policy_deployment(app_args).bind(app_args)


def policy_deployment(app_args: PolicyAppArgs):
    """The Ray Serve ``Deployment`` of [`PolicyDeployment`] with the options [`build_app`] names (unbound)."""
    _, serve = require_ray()
    options = {}
    try:  # Ray >= 2.5x: the 503's Retry-After
        from ray.serve.config import BackpressureConfig

        options["backpressure_config"] = BackpressureConfig(status_code=503, retry_after_s=OVERLOAD_RETRY_AFTER_S)
    except ImportError:
        pass
    if app_args.num_replicas is not None:
        options["num_replicas"] = app_args.num_replicas
    config = app_args.serve
    gpus = {"num_gpus": 1} if is_cuda(config.device) else {}  # the replica's cuda device, given by Ray
    return serve.deployment(
        PolicyDeployment,
        name=DEPLOYMENT_NAME,
        ray_actor_options={"num_cpus": app_args.threads, **gpus},
        max_ongoing_requests=max_ongoing_requests(config),
        max_queued_requests=config.max_queue,
        health_check_period_s=HEALTH_CHECK_PERIOD_S,
        **options,
    )


class PolicyDeployment:
    """One Ray Serve replica: a [`PolicyService`] behind the routes of ``app`` (this object is their backend).

    Built by Ray in the replica's process from [`PolicyAppArgs`]: loads the policy (and draft head), warms the
    service up (compiles every bucket, calibrates), then answers HTTP. Each robot's reply leaves as soon as its row
    is decoded (``PolicyService.act_each``), while the rest of its batch may still decode.
    """

    def __init__(self, app_args: PolicyAppArgs):
        ray, serve = require_ray()
        from .app import PolicyRoutes
        from .batching import Batcher
        from .service import PolicyService

        context = serve.get_replica_context()
        #: this replica's id (unique within the deployment) and its Ray actor's name (namespace ``serve``)
        self.replica, self.replica_actor = context.replica_id.unique_id, context.replica_id.to_full_id_str()
        self.world_size = getattr(context, "world_size", None)  # Ray >= 2.5x
        self.node = ray.get_runtime_context().get_node_id()  #: the Ray node this replica runs on
        started = time.perf_counter()
        config = app_args.serve
        self.service: PolicyService = PolicyService.from_pretrained(
            app_args.policy, config, app_args.draft_head, app_args.threads
        )
        self.service.warm_up()
        logger.info(
            "replica %s: %s (%s) ready in %.1f s (%s)",
            self.replica,
            app_args.policy,
            self.service.methods_name,
            time.perf_counter() - started,
            ", ".join(f"{k} {v}" for k, v in self.service.startup.items()),
        )
        api_key = app_args.api_key if app_args.api_key is not None else os.environ.get(API_KEY_VARIABLE) or None
        self.routes = PolicyRoutes(self, api_key, app_args.max_request_bytes, app_args.body_timeout_s)
        self.batcher = Batcher(self.service).start()  # the one-machine server's batching (module docstring)
        self.started = time.time()

    async def __call__(self, request):
        """Ray Serve hands every HTTP request (a Starlette ``Request``) here: the routes answer it."""
        return await self.routes.dispatch(request)

    # ----------------------------------------------------------------------------- the routes' backend
    def info(self) -> dict:
        """The service's info, plus ``deployment: "ray"``, this replica and the batching / overload limits."""
        config = self.service.config
        return {
            **self.service.info(),
            "deployment": "ray",
            "replica": self.replica,
            "node": self.node,
            "replica_actor": self.replica_actor,
            "replicas": self.world_size,
            "max_wait_ms": config.max_wait_ms,
            "max_queue": config.max_queue,
            "max_ongoing_requests": max_ongoing_requests(config),
        }

    def stats(self) -> dict:
        """This replica's figures (each replica counts its own; ``replica`` says which answered)."""
        batcher = self.batcher
        return {
            **self.service.stats(),
            "deployment": "ray",
            "replica": self.replica,
            "node": self.node,
            "batches": batcher.batches,
            "waiting": batcher.waiting,
            "dropped": batcher.dropped,
            "uptime_s": round(time.time() - self.started, 1),
        }

    def unhealthy(self) -> str | None:
        """Why this replica cannot serve (its batching thread died), else None."""
        return self.batcher.unhealthy()

    def check_health(self) -> None:
        """Ray Serve's health check (every ``HEALTH_CHECK_PERIOD_S``): a replica whose batching thread died is
        reported unhealthy, and Ray replaces it.

        Raises:
            RuntimeError: why it cannot serve.
        """
        problem = self.unhealthy()
        if problem is not None:
            raise RuntimeError(problem)

    def parse(self, payload) -> ActRequest:
        return self.service.parse(payload)

    async def act(self, request: ActRequest, arrived: float) -> ActReply:
        """The request's reply, decoded in a batch with the requests waiting with it; it comes as soon as its row is
        done, not when the batch's call returns. A cancelled wait (the robot went away) drops the request from its
        batch if the batch has not started.

        Raises:
            Overloaded: the replica's queue is full (HTTP 503 + Retry-After).
        """
        return await asyncio.wrap_future(self.batcher.submit(request, arrived))


# ----------------------------------------------------------------------------- serve run, for hf-specvla serve --ray
def serve_config(app_args: PolicyAppArgs, host: str, port: int) -> dict:
    """A Serve config (what ``serve run`` / ``serve deploy`` read) serving ``app_args`` on ``host:port``: the
    application [`build_app`] builds, at ``/``, named ``APP_NAME``."""
    application = {"name": APP_NAME, "route_prefix": "/", "import_path": IMPORT_PATH, "args": app_args.to_args()}
    return {"http_options": {"host": host, "port": port}, "applications": [application]}


def serve_run(
    config_file: str | Path,
    address: str | None = None,
    on_ready: Callable[[str], None] | None = None,
    url: str | None = None,
) -> int:
    """Runs Ray Serve's own ``serve run <config_file>`` in this process (it starts or joins the Ray cluster, deploys,
    blocks, and on Ctrl-C / SIGINT shuts Serve down); ``on_ready(url)`` once the application is running. Returns the
    exit status: 0 after Ctrl-C or SIGTERM, 1 when the application failed to deploy (its message logged).

    SIGTERM (what a supervisor, systemd or Kubernetes sends) is made a Ctrl-C: Ray installs its own SIGTERM handlers
    when it starts or joins a cluster (they exit at once: on Ray 2.60 the process aborts, status -6, before Serve has
    shut down), so while ``serve run`` runs, Python's SIGINT handler takes SIGTERM again once Ray has started
    ([`_sigterm_as_ctrl_c`]), and ``serve run``'s own Ctrl-C path shuts Serve down.

    Raises:
        ImportError: Ray Serve is not installed.
    """
    require_ray()
    from ray.serve.scripts import run

    failure: list[str] = []
    watcher = threading.Thread(target=_watch, args=(on_ready, url, failure), daemon=True, name="hf-specvla-ready")
    watcher.start()
    command = [str(config_file)] + (["--address", address] if address else [])
    try:
        with _sigterm_as_ctrl_c():
            run.main(command, prog_name="serve run", standalone_mode=False)
    except SystemExit as stop:  # Ctrl-C: serve run shut Serve down and exits
        status = stop.code if isinstance(stop.code, int) else 0
    else:
        status = 0
    ray, _ = require_ray()
    if ray.is_initialized():  # the cluster serve run started (or joined), left here rather than at exit
        ray.shutdown()
    if failure:
        logger.error("the Ray Serve application %s failed to deploy: %s", APP_NAME, failure[0])
        return 1
    return status


@contextmanager
def _sigterm_as_ctrl_c():
    """Within the block, SIGTERM raises ``KeyboardInterrupt`` in the main thread, as Ctrl-C does: Python's SIGINT
    handler is installed for it now and again right after every ``ray.init`` (which ``serve run`` calls there), as
    Ray installs SIGTERM handlers of its own while it starts (Python ones, and its core worker's C++ failure handler,
    which aborts); the handlers and ``ray.init`` are put back after. Outside the main thread nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    ray, _ = require_ray()
    previous, init = signal.getsignal(signal.SIGTERM), ray.init

    def init_then_sigterm_as_ctrl_c(*args, **kwargs):
        try:
            return init(*args, **kwargs)
        finally:
            signal.signal(signal.SIGTERM, signal.default_int_handler)

    signal.signal(signal.SIGTERM, signal.default_int_handler)
    ray.init = init_then_sigterm_as_ctrl_c
    try:
        yield
    finally:
        ray.init = init
        signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)


def _watch(on_ready: Callable[[str], None] | None, url: str | None, failure: list[str], poll_s: float = 0.5) -> None:
    """On a thread beside ``serve run``: once the application runs, ``on_ready(url)``; if it fails to deploy, the
    failure noted and ``serve run`` interrupted as by Ctrl-C (so that it shuts Serve down)."""
    ray, serve = require_ray()
    while True:
        time.sleep(poll_s)
        if not ray.is_initialized():
            continue
        try:
            application = serve.status().applications.get(APP_NAME)
        except Exception:  # noqa: BLE001 (Serve not started yet)
            continue
        status = str(getattr(application, "status", ""))
        if status.endswith("RUNNING"):
            if on_ready is not None:
                on_ready(url)
            return
        if status.endswith(("DEPLOY_FAILED", "UNHEALTHY")):
            failure.append(application.message or status)
            _thread.interrupt_main()
            return
