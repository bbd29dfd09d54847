"""A light client of the policy server (the standard library and numpy only: no torch, no HTTP package).

    from hf_specvla.serving import PolicyClient

    client = PolicyClient("http://127.0.0.1:8000")
    info = client.info()                                   # image size, state dim, the policy's fingerprint
    reply = client.act(image, "open the drawer", state, session="robot-1", reset=True)
    reply.action, reply.served.target_forwards             # the action, how it was served

The client echoes each session's ``draft_state`` (the robot's previous actions) with its next request, so the
drafts do not depend on which server replica answers. Connection failures, 502/503/504 (overload: after its
``Retry-After``) and a proxy's plain 500 (a Ray Serve replica that died under the request) are retried; a robot's
retried request gets the same action (decoding is deterministic).
"""

from __future__ import annotations

import json
import logging
import time
import urllib.error
import urllib.request
from typing import Any

import numpy as np

from .protocol import ActReply, dumps

logger = logging.getLogger(__name__)

#: statuses worth retrying: a proxy's or a restarting replica's, and overload
RETRY_STATUSES = (502, 503, 504)


class ServerError(RuntimeError):
    """The server refused a request: ``status``, its message and the field at fault (None: the request)."""

    def __init__(self, status: int, message: str, field: str | None = None):
        super().__init__(f"HTTP {status}: {message}" + (f" (field {field!r})" if field else ""))
        self.status, self.message, self.field = status, message, field


class PolicyClient:
    """Talks to ``hf-specvla serve`` (or its Ray Serve deployment).

    Args:
        url: the server's address, e.g. ``http://127.0.0.1:8000``.
        api_key: sent as ``Authorization: Bearer <key>`` (a server started with ``--api-key`` needs it).
        timeout_s: per attempt.
        retries: attempts after the first on connection failures and 502 / 503 / 504.
        backoff_s: the first wait between attempts (doubled each time; a 503's ``Retry-After`` wins).
    """

    def __init__(
        self, url: str, api_key: str | None = None, timeout_s: float = 60.0, retries: int = 8, backoff_s: float = 0.25
    ):
        if not url.startswith(("http://", "https://")):
            raise ValueError(f"url must start with http:// or https://, got {url!r}")
        self.url = url.rstrip("/")
        self.api_key, self.timeout_s, self.retries, self.backoff_s = api_key, timeout_s, retries, backoff_s
        self.draft_states: dict[str, list[list[int]]] = {}  # session -> the draft_state of its last reply
        self.retried = 0  # attempts repeated, over the client's life

    def info(self) -> dict:
        """``GET /info``: the policy (name, fingerprint, image size, camera, state and action dims), the method and
        the batch buckets."""
        return json.loads(self._request("GET", "/info"))

    def act(
        self,
        image: np.ndarray,
        instruction: str,
        state=None,
        session: str | None = None,
        reset: bool = False,
        unnorm_key: str | None = None,
    ) -> ActReply:
        """One action: ``POST /act``. ``session`` names the robot (its drafts); ``reset`` starts its new episode;
        ``unnorm_key``: an OpenVLA checkpoint's dataset (None: the server's default)."""
        payload: dict[str, Any] = {"image": np.asarray(image), "instruction": instruction}
        if unnorm_key is not None:
            payload["unnorm_key"] = unnorm_key
        if state is not None:
            payload["state"] = np.asarray(state, dtype=np.float64)
        if session is not None:
            payload["session"] = session
            if reset:
                payload["reset"] = True
                self.draft_states.pop(session, None)
            elif session in self.draft_states:
                payload["draft_state"] = self.draft_states[session]
        reply = ActReply.from_payload(json.loads(self._request("POST", "/act", dumps(payload))))
        if session is not None:
            self.draft_states[session] = reply.served.draft_state
        return reply

    def _request(self, method: str, path: str, body: bytes | None = None) -> bytes:
        headers = {"Content-Type": "application/json"}
        if self.api_key:
            headers["Authorization"] = f"Bearer {self.api_key}"
        wait = self.backoff_s
        for attempt in range(self.retries + 1):
            request = urllib.request.Request(self.url + path, body, headers, method=method)
            try:
                with urllib.request.urlopen(request, timeout=self.timeout_s) as response:
                    return response.read()
            except urllib.error.HTTPError as error:
                text = error.read()
                if not _retryable(error.code, text) or attempt == self.retries:
                    raise _server_error(error.code, text) from None
                retry_after = error.headers.get("Retry-After")
                pause = float(retry_after) if retry_after and retry_after.isdigit() else wait
                logger.debug("%s %s: HTTP %d, retrying in %.2f s", method, path, error.code, pause)
            except (urllib.error.URLError, ConnectionError, TimeoutError) as error:
                if attempt == self.retries:
                    message = f"{method} {self.url}{path} failed after {attempt + 1} attempts: {error}"
                    raise ConnectionError(message) from None
                pause = wait
                logger.debug("%s %s: %s, retrying in %.2f s", method, path, error, pause)
            self.retried += 1
            time.sleep(pause)
            wait = min(2 * wait, 5.0)
        raise AssertionError("unreachable")


def _retryable(status: int, body: bytes) -> bool:
    """A 502 / 503 / 504, or a 500 that is not the server's own JSON error (a proxy's: e.g. Ray Serve's replica
    died under the request, which another replica answers)."""
    if status in RETRY_STATUSES:
        return True
    if status != 500:
        return False
    try:
        return not isinstance(json.loads(body), dict)
    except ValueError:
        return True


def _server_error(status: int, body: bytes) -> ServerError:
    try:
        payload = json.loads(body)
        return ServerError(status, str(payload.get("error", body[:200])), payload.get("field"))
    except (ValueError, AttributeError):
        return ServerError(status, body[:200].decode(errors="replace"))
