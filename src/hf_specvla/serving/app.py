"""The policy server's HTTP API (a Starlette app; the wire format is in ``protocol``):

| route | |
|---|---|
| ``POST /act`` | an observation -> the action (OpenVLA's ``deploy.py`` API and ours on top, see ``protocol``) |
| ``GET /info`` | the policy (name, fingerprint, image size, camera, dims), the method, buckets, calibration |
| ``GET /stats`` | what the server did: requests, batches per bucket and mode, median decode times, queue |
| ``GET /health`` | ``{"status": "ok"}``, or 503 ``{"status": "unavailable", "error": ...}`` when it cannot serve |

**Security.** With an API key, every route but ``/health`` needs it, as ``Authorization: Bearer <key>``,
``X-API-Key: <key>`` or the body's ``api_key`` field (401 otherwise, whatever the body: the key is checked before
the request is). A body larger than ``max_request_bytes`` is refused (413) before it is read whole. A malformed
request gets a 4xx JSON error naming the field (``{"error": ..., "field": ...}``) before it reaches a batch, so it
never fails or delays the others.

**Faults.** A robot that disconnects before its batch starts is dropped from it, and its queue slot is free at once;
one that disconnects later does not hold the batch up (its reply is discarded). A robot that hangs up (mid-body or
while it waits) is counted in ``/stats`` (``client_hangups``) and logged at INFO, not as an error. A full queue (of
live requests) answers 503 with ``Retry-After``. A body must arrive whole within ``body_timeout_s`` (10 s) of its
request, else 408: a client holding a half-sent body never holds a worker, or a shutdown's drain, longer than that.

The routes are served the same way by the server on one machine (``server``) and by each Ray Serve replica
(``ray_deployment``): a *backend* ([`Backend`]) decodes, the app only speaks HTTP.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import logging
import time
from typing import Protocol

from starlette.applications import Starlette
from starlette.requests import ClientDisconnect, Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route

from .config import BODY_TIMEOUT_S, DEFAULT_MAX_REQUEST_BYTES, check_body_timeout
from .protocol import ActReply, ActRequest, Overloaded, RequestError, dumps, encode_array, loads, unwrap

logger = logging.getLogger(__name__)

#: how often a waiting request checks whether its robot is still connected
DISCONNECT_POLL_S = 0.05
#: the status logged for a request whose robot went away before its reply (nginx's convention)
CLIENT_CLOSED_REQUEST = 499


class Backend(Protocol):
    """What decodes behind the HTTP routes."""

    def info(self) -> dict: ...

    def stats(self) -> dict: ...

    def unhealthy(self) -> str | None:
        """Why the backend cannot serve now (None: it can)."""
        ...

    def parse(self, payload) -> ActRequest: ...

    async def act(self, request: ActRequest, arrived: float) -> ActReply: ...


class PolicyRoutes:
    """The routes over a backend (``api_key``: None for an open server)."""

    def __init__(
        self,
        backend: Backend,
        api_key: str | None = None,
        max_request_bytes: int = DEFAULT_MAX_REQUEST_BYTES,
        body_timeout_s: float = BODY_TIMEOUT_S,
    ):
        check_body_timeout(body_timeout_s)
        self.backend, self.api_key, self.max_request_bytes = backend, api_key, max_request_bytes
        self.body_timeout_s = body_timeout_s
        self.client_hangups = 0  # robots that hung up before their reply (mid-body, or while their request waited)
        self.routes = {
            ("POST", "/act"): self.act,
            ("GET", "/info"): self.info,
            ("GET", "/stats"): self.stats,
            ("GET", "/health"): self.health,
        }

    async def dispatch(self, request: Request) -> Response:
        """Any request -> its response (Ray Serve replicas call this from ``__call__``)."""
        path, method = request.url.path.rstrip("/") or "/", request.method
        routes = self.routes
        handler = routes.get((method, path))
        if handler is None:
            known = ", ".join(f"{m} {p}" for m, p in routes)
            status = 405 if any(p == path for _, p in routes) else 404
            return _error(RequestError(f"no route {method} {path}; the routes are {known}", None, status))
        try:
            return await handler(request)
        except RequestError as error:
            return _error(error)
        except ClientDisconnect:  # the robot hung up mid-body: nobody to answer, nothing wrong here
            self.client_hangups += 1
            logger.info("a robot hung up before its request's body arrived (%s %s)", method, path)
            return Response(status_code=CLIENT_CLOSED_REQUEST)
        except Overloaded as error:
            return JSONResponse(
                {"error": str(error), "field": None}, 503, headers={"Retry-After": str(error.retry_after_s)}
            )
        except Exception as error:  # noqa: BLE001 (the robot gets a 500; the server goes on)
            logger.exception("%s %s failed", method, path)
            return JSONResponse({"error": f"internal error: {type(error).__name__}: {error}", "field": None}, 500)

    def app(self, lifespan=None) -> Starlette:
        """A Starlette app of these routes (``lifespan``: Starlette's start-up / shut-down context)."""
        methods = ["GET", "POST", "PUT", "DELETE", "PATCH"]
        return Starlette(routes=[Route("/{path:path}", self.dispatch, methods=methods)], lifespan=lifespan)

    async def health(self, request: Request) -> Response:
        problem = self.backend.unhealthy()
        if problem is not None:
            return JSONResponse({"status": "unavailable", "error": problem}, 503)
        return JSONResponse({"status": "ok"})

    async def info(self, request: Request) -> Response:
        self._authorize(request)
        return JSONResponse(self.backend.info())

    async def stats(self, request: Request) -> Response:
        self._authorize(request)
        return JSONResponse({**self.backend.stats(), "client_hangups": self.client_hangups})

    async def act(self, request: Request) -> Response:
        arrived = time.perf_counter()
        header_key = self._header_key(request)
        if self.api_key is not None and header_key is not None:
            self._check_key(header_key)
        key_in_body = self.api_key is not None and header_key is None
        try:
            payload = loads(await self._body(request), arrays=False)  # arrays: decoded field by field in parse
        except RequestError:
            if key_in_body:  # a body that is not JSON carries no key: refused as such, not for its form
                self._check_key(None)
            raise
        if key_in_body:  # the body's own field, or inside OpenVLA's double-encoded form
            try:
                fields = unwrap(payload)[0]
            except RequestError:  # a malformed double-encoded body carries no key either
                fields = None
            self._check_key(fields.get("api_key") if isinstance(fields, dict) else None)
        act_request = self.backend.parse(payload)
        act_request.received = time.perf_counter()  # the intake (body and checks) ends: ServedFigures.intake_ms
        task = asyncio.ensure_future(self.backend.act(act_request, arrived))
        try:
            while not task.done():
                await asyncio.wait({task}, timeout=DISCONNECT_POLL_S)
                if not task.done() and await request.is_disconnected():
                    task.cancel()
                    self.client_hangups += 1
                    logger.info("a robot (session %s) disconnected before its action", act_request.session)
                    return Response(status_code=CLIENT_CLOSED_REQUEST)
        except asyncio.CancelledError:  # the server gave up on the request (Ray Serve's proxy: the robot hung up)
            task.cancel()
            raise
        reply = task.result()
        if act_request.double_encoded:  # OpenVLA's double-encoded reply: the json_numpy text as a JSON string
            return JSONResponse(json.dumps(encode_array(reply.action)))
        return Response(dumps(reply.to_payload()), media_type="application/json")

    # ----------------------------------------------------------------------------- checks
    async def _body(self, request: Request) -> bytes:
        declared = request.headers.get("content-length")
        if declared is not None and (not declared.isdigit() or int(declared) > self.max_request_bytes):
            raise RequestError(
                f"the body ({declared} bytes) exceeds this server's limit of {self.max_request_bytes} bytes", None, 413
            )
        chunks: list[bytes] = []

        async def read() -> None:
            size = 0
            async for chunk in request.stream():
                size += len(chunk)
                if size > self.max_request_bytes:
                    raise RequestError(
                        f"the body exceeds this server's limit of {self.max_request_bytes} bytes", None, 413
                    )
                chunks.append(chunk)

        try:
            await asyncio.wait_for(read(), self.body_timeout_s)
        except asyncio.TimeoutError:
            raise RequestError(
                f"the body did not arrive whole within {self.body_timeout_s:g} s of the request (this server's limit: "
                f"send the whole body at once)",
                None,
                408,
            ) from None
        return b"".join(chunks)

    @staticmethod
    def _header_key(request: Request) -> str | None:
        authorization = request.headers.get("authorization", "")
        if authorization.lower().startswith("bearer "):
            return authorization[7:].strip()
        return request.headers.get("x-api-key")

    def _authorize(self, request: Request) -> None:
        if self.api_key is not None:
            self._check_key(self._header_key(request))

    def _check_key(self, key) -> None:
        if not isinstance(key, str) or not hmac.compare_digest(key.encode(), self.api_key.encode()):
            shown = "no API key" if key is None else "a wrong API key"
            raise RequestError(
                f"{shown}: send 'Authorization: Bearer <key>' (or X-API-Key, or the body's api_key)", "api_key", 401
            )


def _error(error: RequestError) -> Response:
    headers = {"WWW-Authenticate": "Bearer"} if error.status == 401 else None
    return JSONResponse(error.to_payload(), error.status, headers=headers)
