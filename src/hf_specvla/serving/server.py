"""The policy server on one machine: ``hf-specvla serve`` without ``--ray``. A uvicorn server runs the HTTP app
(``app``) over a [`LocalBackend`]: a [`Batcher`] that forms batches for one [`PolicyService`].

    service = PolicyService.from_pretrained("policies/mt10_vla3", ServeConfig(method="exact"))
    service.warm_up()                                  # compiles every bucket, calibrates
    PolicyServer(service, port=8000).run()             # until SIGTERM / Ctrl-C

    with PolicyServer(service, port=0) as server:      # in a background thread (tests, notebooks)
        PolicyClient(server.url).act(...)

It binds 127.0.0.1 unless told otherwise; a host reachable from other machines needs an API key
([`check_exposure`]). SIGTERM (and Ctrl-C) stop accepting connections, let the requests in flight get their actions
(up to ``drain_timeout_s``), then stop the batcher. A request whose body is still arriving holds the drain at most
until its body timeout (``body_timeout_s``, 10 s after its arrival by default: then it is answered 408), not the whole
``drain_timeout_s``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import socket
import threading
import time

from .app import PolicyRoutes
from .batching import Batcher
from .config import BODY_TIMEOUT_S, DEFAULT_HOST, DEFAULT_MAX_REQUEST_BYTES, DEFAULT_PORT, check_exposure
from .protocol import ActReply, ActRequest
from .service import PolicyService

logger = logging.getLogger(__name__)

#: the longest drain SIGTERM may be given (a finite wait: its thread joins and uvicorn's timer need a number)
MAX_DRAIN_TIMEOUT_S = 3600.0


class LocalBackend:
    """The app's backend on one machine: requests -> [`Batcher`] -> [`PolicyService`]."""

    def __init__(self, service: PolicyService):
        self.service, self.batcher = service, Batcher(service)
        self.started = time.time()

    def info(self) -> dict:
        config = self.service.config
        return {
            **self.service.info(),
            "deployment": "local",
            "max_wait_ms": config.max_wait_ms,
            "max_queue": config.max_queue,
        }

    def stats(self) -> dict:
        return {
            **self.service.stats(),
            "batches": self.batcher.batches,
            "waiting": self.batcher.waiting,
            "dropped": self.batcher.dropped,
            "uptime_s": round(time.time() - self.started, 1),
        }

    def unhealthy(self) -> str | None:
        return self.batcher.unhealthy()

    def parse(self, payload) -> ActRequest:
        return self.service.parse(payload)

    async def act(self, request: ActRequest, arrived: float) -> ActReply:
        return await asyncio.wrap_future(self.batcher.submit(request, arrived))


class PolicyServer:
    """Serves a [`PolicyService`] over HTTP on one machine ([`run`], or ``with`` for a background thread).

    Args:
        service: the policy service (warmed up, or not: then the first request of each bucket compiles).
        host / port: where to listen (port 0: any free port; see ``url``).
        api_key: every request must carry it (None: an open server; refused off loopback).
        max_request_bytes: the largest request body.
        drain_timeout_s: how long SIGTERM waits for the requests in flight (one whose body is still arriving: at most
            ``routes.body_timeout_s``, 10 s after its arrival).
        sock: a socket already listening ([`bind`]: e.g. taken before the policy loads), instead of host / port.
        body_timeout_s: the longest a request's body may take to arrive whole (408 past it; seconds in (0, 600]).
    """

    def __init__(
        self,
        service: PolicyService,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        api_key: str | None = None,
        max_request_bytes: int = DEFAULT_MAX_REQUEST_BYTES,
        drain_timeout_s: float = 30.0,
        sock: socket.socket | None = None,
        body_timeout_s: float = BODY_TIMEOUT_S,
    ):
        check_exposure(host, api_key)
        if isinstance(max_request_bytes, bool) or not isinstance(max_request_bytes, int) or max_request_bytes < 1:
            raise ValueError(f"max_request_bytes must be an integer >= 1, got {max_request_bytes!r}")
        if (
            isinstance(drain_timeout_s, bool)
            or not isinstance(drain_timeout_s, int | float)
            or not (0 <= drain_timeout_s <= MAX_DRAIN_TIMEOUT_S)
        ):
            raise ValueError(f"drain_timeout_s must be seconds 0..{MAX_DRAIN_TIMEOUT_S:g}, got {drain_timeout_s!r}")
        self.backend = LocalBackend(service)
        self.routes = PolicyRoutes(self.backend, api_key, max_request_bytes, body_timeout_s)
        self.host, self.drain_timeout_s = host, drain_timeout_s
        self._socket = sock if sock is not None else bind(host, port)
        self.port = self._socket.getsockname()[1]
        self._server = None
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}"

    @contextlib.asynccontextmanager
    async def _lifespan(self, app):
        self.backend.batcher.start()
        logger.info(
            "serving %s (%s) on %s",
            self.backend.service.policy.name_or_path,
            self.backend.service.methods_name,
            self.url,
        )
        yield
        self.backend.batcher.stop()
        logger.info("stopped: %d batches served", self.backend.batcher.batches)

    def _uvicorn(self, log_level: str = "warning"):
        import uvicorn

        config = uvicorn.Config(
            self.routes.app(self._lifespan),
            log_level=log_level,
            access_log=False,
            timeout_graceful_shutdown=self.drain_timeout_s,
            lifespan="on",
        )
        self._server = uvicorn.Server(config)
        return self._server

    def run(self, log_level: str = "warning") -> None:
        """Serves until SIGTERM or Ctrl-C, then drains the requests in flight and returns (from the main thread;
        uvicorn re-raises the signal it stopped on to the handler that was there before: here, one that notes it,
        so that a drained server exits normally)."""
        stopped_by: list[int] = []
        main = threading.current_thread() is threading.main_thread()
        previous = (
            {
                sig: signal.signal(sig, lambda number, frame: stopped_by.append(number))
                for sig in (signal.SIGTERM, signal.SIGINT)
            }
            if main
            else {}
        )
        try:
            self._uvicorn(log_level).run(sockets=[self._socket])
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        if stopped_by:
            logger.info("stopped by %s after draining the requests in flight", signal.Signals(stopped_by[0]).name)

    def __enter__(self) -> PolicyServer:
        server = self._uvicorn()
        self._thread = threading.Thread(
            target=server.run, kwargs={"sockets": [self._socket]}, daemon=True, name="hf-specvla-server"
        )
        self._thread.start()
        deadline = time.time() + 30
        while not server.started:
            if not self._thread.is_alive() or time.time() > deadline:
                raise RuntimeError(f"the policy server on {self.url} did not start")
            time.sleep(0.01)
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stops a server started with ``with`` (the requests in flight finish first)."""
        if self._server is not None:
            self._server.should_exit = True
        if self._thread is not None:
            self._thread.join(self.drain_timeout_s + 10)
        self._socket.close()


def bind(host: str, port: int) -> socket.socket:
    """A listening socket on ``host:port`` (the error names the address when it is taken)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as error:
        sock.close()
        raise OSError(f"cannot listen on {host}:{port}: {error.strerror} (another server there? pass --port)") from None
    sock.listen(2048)
    sock.set_inheritable(True)
    return sock
