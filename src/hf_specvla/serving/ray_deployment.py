"""The policy server as a Ray Serve deployment: ``hf-specvla serve --ray --replicas N``. The same HTTP API as the server
on one machine (``app``: ``POST /act``, ``GET /info``, ``GET /stats``, ``GET /health``), served by N replicas, each
with its own [`PolicyService`] (the policy loaded, every bucket compiled and calibrated before it takes a request).

    from hf_specvla.serving import PolicyClient, ServeConfig
    from hf_specvla.serving.ray_deployment import deploy

    url = deploy("policies/mt10_vla3", ServeConfig(method="exact"), replicas=2, blocking=False)
    PolicyClient(url).act(...)                         # any replica answers; the drafts travel with the robot

**Batching.** Each replica forms its batches with Ray Serve's own ``serve.batch`` (up to the largest bucket, waiting
at most ``max_wait_ms`` after the first request) and decodes them in a worker thread, so its event loop keeps
reading requests, answering health checks and noticing robots that went away (their requests leave the batch).

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

Needs Ray Serve (``pip install 'hf_specvla[ray]'``). This module imports Ray (and starlette, torch) only inside its
functions: it imports without them, and [`deploy`] says what to install.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from .config import DEFAULT_HOST, DEFAULT_MAX_REQUEST_BYTES, DEFAULT_PORT, ServeConfig, check_exposure
from .protocol import ActReply, ActRequest

if TYPE_CHECKING:
    from .service import PolicyService

logger = logging.getLogger(__name__)

#: the Ray Serve application's name (``serve status`` shows it)
APP_NAME = "hf_specvla"
#: the deployment's name within the application
DEPLOYMENT_NAME = "PolicyDeployment"
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


class PolicyDeployment:
    """One Ray Serve replica: a [`PolicyService`] behind the routes of ``app`` (this object is their backend).

    Built by Ray in the replica's process ([`policy_deployment`] makes the deployment, [`deploy`] runs it): loads the
    policy (and draft head), warms the service up (compiles every bucket, calibrates), then answers HTTP.

    Args:
        policy_folder: the policy's folder (readable on every node that runs a replica).
        config: the service's [`ServeConfig`]: the method, the buckets (the largest is ``serve.batch``'s
            ``max_batch_size``), ``max_wait_ms`` (its ``batch_wait_timeout_s``).
        api_key: every request but ``/health`` must carry it (None: open).
        draft_head_folder: for methods that draft with a head.
        threads: torch CPU threads of this replica.
        max_request_bytes: the largest request body.
    """

    def __init__(self, policy_folder: str, config: ServeConfig, api_key: str | None = None,
                 draft_head_folder: str | None = None, threads: int | None = 1,
                 max_request_bytes: int = DEFAULT_MAX_REQUEST_BYTES):  # fmt: skip
        _, serve = require_ray()
        from .app import PolicyRoutes
        from .service import PolicyService

        context = serve.get_replica_context()
        #: this replica's id (unique within the deployment) and its Ray actor's name (namespace ``serve``)
        self.replica, self.replica_actor = context.replica_id.unique_id, context.replica_id.to_full_id_str()
        self.world_size = getattr(context, "world_size", None)  # Ray >= 2.5x
        started = time.perf_counter()
        self.service: PolicyService = PolicyService.from_pretrained(policy_folder, config, draft_head_folder, threads)
        self.service.warm_up()
        logger.info("replica %s: %s (%s) ready in %.1f s", self.replica, policy_folder, self.service.method.name,
                    time.perf_counter() - started)  # fmt: skip
        self.routes = PolicyRoutes(self, api_key, max_request_bytes)
        # built here, not with a decorator, so that the batch size follows this deployment's config
        batch = serve.batch(max_batch_size=config.max_batch_size, batch_wait_timeout_s=config.max_wait_ms / 1000)
        self._batched = batch(self._decode_batch)
        self.batches = 0  # batches decoded by this replica
        self.failed_batches = 0  # batches whose call failed (then decoded one request at a time)
        self.started = time.time()

    async def __call__(self, request):
        """Ray Serve hands every HTTP request (a Starlette ``Request``) here: the routes answer it."""
        return await self.routes.dispatch(request)

    # ----------------------------------------------------------------------------- the routes' backend
    def info(self) -> dict:
        """The service's info, plus ``deployment: "ray"``, this replica and the batching / overload limits."""
        config = self.service.config
        return {**self.service.info(), "deployment": "ray", "replica": self.replica,
                "replica_actor": self.replica_actor, "replicas": self.world_size, "max_wait_ms": config.max_wait_ms,
                "max_queue": config.max_queue, "max_ongoing_requests": max_ongoing_requests(config)}  # fmt: skip

    def stats(self) -> dict:
        """This replica's figures (each replica counts its own; ``replica`` says which answered)."""
        return {**self.service.stats(), "deployment": "ray", "replica": self.replica, "batches": self.batches,
                "failed_batches": self.failed_batches, "uptime_s": round(time.time() - self.started, 1)}  # fmt: skip

    def unhealthy(self) -> str | None:
        """None: a replica that answers is serving (Ray replaces one that is not, see ``HEALTH_CHECK_PERIOD_S``)."""
        return None

    def parse(self, payload) -> ActRequest:
        return self.service.parse(payload)

    async def act(self, request: ActRequest, arrived: float) -> ActReply:
        """The request's reply, decoded in a batch with the requests that arrived with it."""
        result = await self._batched((request, arrived))
        if isinstance(result, BaseException):
            raise result
        return result

    # ----------------------------------------------------------------------------- decoding
    async def _decode_batch(self, items: list[tuple[ActRequest, float]]) -> list[ActReply | Exception]:
        """``serve.batch``'s function: one batch, decoded in a worker thread (the event loop stays free)."""
        return await asyncio.to_thread(self._decode, items)

    def _decode(self, items: list[tuple[ActRequest, float]]) -> list[ActReply | Exception]:
        """Replies (or, for a request that fails alone, its exception) in order: a failing batch is decoded one
        request at a time, so one request's failure never fails the others (as the local batcher does)."""
        requests, arrived = [r for r, _ in items], [a for _, a in items]
        self.batches += 1
        try:
            results: list[ActReply | Exception] = list(self.service.act(requests, arrived))
        except Exception:
            self.failed_batches += 1
            logger.exception("a batch of %d failed; decoding its requests one at a time", len(items))
            results = []
            for request, at in items:
                try:
                    results += self.service.act([request], [at])
                except Exception as error:  # noqa: BLE001 (reported to that request's robot)
                    results.append(error)
        done = time.perf_counter()
        for result, at in zip(results, arrived):
            if isinstance(result, ActReply):
                result.served.server_ms = 1000 * (done - at)
        return results


def policy_deployment(config: ServeConfig, *, replicas: int = 1, threads_per_replica: int = 1):
    """The Ray Serve ``Deployment`` of [`PolicyDeployment`]: ``replicas`` replicas of ``threads_per_replica`` CPUs
    each, overload limits from ``config`` (see the module's docstring). Bind it to the replicas' arguments
    (``.bind(policy_folder, config, api_key, draft_head_folder, threads, max_request_bytes)``) or use
    [`policy_app`].

    Raises:
        ValueError: ``replicas`` or ``threads_per_replica`` below 1.
        ImportError: Ray Serve is not installed.
    """
    for name, value in (("replicas", replicas), ("threads_per_replica", threads_per_replica)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    _, serve = require_ray()
    options = {}
    try:  # Ray >= 2.5x: the 503's Retry-After
        from ray.serve.config import BackpressureConfig

        options["backpressure_config"] = BackpressureConfig(status_code=503, retry_after_s=OVERLOAD_RETRY_AFTER_S)
    except ImportError:
        pass
    return serve.deployment(
        PolicyDeployment, name=DEPLOYMENT_NAME, num_replicas=replicas,
        ray_actor_options={"num_cpus": threads_per_replica},
        max_ongoing_requests=max_ongoing_requests(config), max_queued_requests=config.max_queue,
        health_check_period_s=HEALTH_CHECK_PERIOD_S, **options,
    )  # fmt: skip


def policy_app(policy_folder, config: ServeConfig, *, replicas: int = 1, api_key: str | None = None,
               draft_head_folder=None, threads_per_replica: int = 1,
               max_request_bytes: int = DEFAULT_MAX_REQUEST_BYTES):  # fmt: skip
    """The Ray Serve application (``serve.run(policy_app(...), route_prefix="/")``): [`policy_deployment`] bound to
    its replicas' arguments. A folder that exists here is passed as an absolute path (the replicas' working
    directory is not this one); on a cluster of several machines it must exist at that path on each."""
    return policy_deployment(config, replicas=replicas, threads_per_replica=threads_per_replica).bind(
        _absolute(policy_folder), config, api_key, _absolute(draft_head_folder), threads_per_replica, max_request_bytes
    )


def deploy(policy_folder, config: ServeConfig, *, replicas: int = 1, host: str = DEFAULT_HOST,
           port: int = DEFAULT_PORT, api_key: str | None = None, draft_head_folder=None,
           threads_per_replica: int = 1, max_request_bytes: int = DEFAULT_MAX_REQUEST_BYTES,
           ray_address: str | None = None, blocking: bool = True,
           on_ready: Callable[[str], None] | None = None) -> str:  # fmt: skip
    """Serves the policy on Ray Serve: ``replicas`` replicas behind Ray's HTTP proxy on ``host:port``; returns the
    URL once every replica has loaded the policy and warmed up.

    Connects to Ray when this process has not already (``ray_address``: None is Ray's default: ``RAY_ADDRESS``, else
    a cluster started with ``ray start`` on this machine, else a new local one; ``"local"`` always a new local one;
    ``"auto"`` or ``"ray://host:10001"`` a running one), starts Serve there if it
    is not running (with ``host:port``; a Serve already running keeps its own HTTP options) and runs the application
    (``APP_NAME``) at ``/``. With ``blocking``, serves until SIGTERM or Ctrl-C, then deletes the application (its
    replicas finish the requests in flight), shuts Serve down if this call started it and Ray if this call started it.

    Raises:
        ValueError: a host reachable from other machines without an API key; ``replicas`` or
            ``threads_per_replica`` below 1; a local cluster with fewer CPUs than the replicas need.
        ImportError: Ray Serve is not installed.
    """
    check_exposure(host, api_key)
    application = policy_app(policy_folder, config, replicas=replicas, api_key=api_key,
                             draft_head_folder=draft_head_folder, threads_per_replica=threads_per_replica,
                             max_request_bytes=max_request_bytes)  # fmt: skip
    ray, serve = require_ray()
    started_ray = not ray.is_initialized()
    if started_ray:
        ray.init(address=ray_address)
    if started_ray and ray_address in (None, "local"):
        cpus = ray.cluster_resources().get("CPU", 0)
        needed = replicas * threads_per_replica
        if needed > cpus:
            ray.shutdown()
            raise ValueError(f"{replicas} replicas x {threads_per_replica} threads need {needed} CPUs; this machine's "
                             f"Ray cluster has {cpus:g}: fewer --replicas or --threads")  # fmt: skip
    status = serve.status()
    started_serve = not status.proxies and not status.applications
    if not started_serve:
        logger.warning("Ray Serve is already running on this cluster: it keeps its HTTP options (host %s, port %s "
                       "ignored)", host, port)  # fmt: skip
    try:
        serve.start(http_options={"host": host, "port": port})
        logger.info("starting %d replica(s) of %s (%s): each loads the policy and warms up", replicas, policy_folder,
                    config.method)  # fmt: skip
        serve.run(application, name=APP_NAME, route_prefix="/")
    except BaseException:
        _stop(ray, serve, started_serve, started_ray)
        raise
    url = f"http://[{host}]:{port}" if ":" in host else f"http://{host}:{port}"
    logger.info("serving %s (%s) on Ray Serve, %d replica(s), at %s", policy_folder, config.method, replicas, url)
    if on_ready is not None:
        on_ready(url)
    if not blocking:
        return url
    try:
        _wait_for_a_signal()
    finally:
        logger.info("stopping the Ray Serve application %s", APP_NAME)
        _stop(ray, serve, started_serve, started_ray)
    return url


def _stop(ray, serve, started_serve: bool, started_ray: bool) -> None:
    """Deletes the application; shuts Serve and Ray down where [`deploy`] started them."""
    try:
        serve.delete(APP_NAME)
    except Exception as error:  # noqa: BLE001 (stopping anyway)
        logger.warning("could not delete the Ray Serve application %s: %s", APP_NAME, error)
    if started_serve:
        serve.shutdown()
    if started_ray:
        ray.shutdown()


def _wait_for_a_signal() -> None:
    """Returns on SIGTERM or Ctrl-C (SIGINT)."""
    stop = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        stop.wait()  # signals reach the main thread only: wait for the process to end
        return
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        while not stop.wait(1.0):
            pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _absolute(folder) -> str | None:
    if folder is None:
        return None
    path = Path(folder).expanduser()
    return str(path.resolve()) if path.exists() else str(folder)
