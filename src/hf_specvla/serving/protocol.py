"""The policy server's wire format: a superset of OpenVLA's ``vla-scripts/deploy.py`` API. No torch, no pickle.

**Arrays** travel as json_numpy writes them: ``{"__numpy__": <base64 of the C-order bytes>, "dtype": "<u1",
"shape": [64, 64, 3]}``. Only boolean and numeric dtypes are read (an object or structured dtype is refused: numpy
would unpickle or misread it), at most ``MAX_ARRAY_DIMS`` dimensions, and the byte count must match the shape. A
request's arrays are decoded field by field, so an error names the field (``image``, ``state``, ``draft_state``).

**``POST /act``** takes a JSON object:

| field | type | |
|---|---|---|
| ``image`` | uint8 array ``[S, S, 3]`` (``GET /info``'s S; null: any ``[H, W, 3]``) | required (OpenVLA's) |
| ``instruction`` | string | required (OpenVLA's); at most 1000 characters and ``GET /info``'s ``max_prompt_tokens`` |
| ``unnorm_key`` | string | an OpenVLA checkpoint's dataset (``GET /info``'s ``unnorm_keys``) (OpenVLA's) |
| ``state`` | numbers ``[state_dim]`` (an array or a list) | required when the policy reads the proprio state |
| ``session`` | string, at most 128 characters | the robot's id: the server keeps its previous actions as drafts |
| ``reset`` | bool | a new episode: forget the session's previous actions |
| ``draft_state`` | lists of ints | this robot's last reply's ``draft_state``, echoed: drafts whatever replica answers |
| ``api_key`` | string | when the server was started with an API key (or send ``Authorization: Bearer <key>``) |

``unnorm_key`` defaults to the server's (``GET /info``'s ``unnorm_key``: the checkpoint's only dataset, or
``serve --unnorm-key``); a Meta-World policy has one set of statistics and ignores it. Or OpenVLA's double-encoded
form ``{"encoded": "<json_numpy text of the object above>"}`` (its ``api_key`` inside). An
``instruction`` is words: special-token text in it (``<image>``, ``<pad>``) is tokenized as text, never as the token.

The reply is the action array itself (float64 ``[action_dim]``, ``[chunk, action_dim]`` for a chunked policy), so an
OpenVLA client that calls ``json_numpy.patch()`` and ``requests.post(url, json=...).json()`` gets its action
unchanged. The same JSON object also carries ``"served"``: the method used, the target forwards, the time spent in
the server and the robot's new ``draft_state`` ([`ActReply`]); json_numpy's decoder ignores it. A double-encoded
request gets OpenVLA's double-encoded reply (a JSON string) and no figures.

Errors are JSON objects ``{"error": <message>, "field": <the field at fault or null>}`` with a 4xx status
(5xx for the server's own faults).
"""

from __future__ import annotations

import base64
import binascii
import json
import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

#: numpy dtype kinds read from the wire: bool, signed and unsigned ints, floats
ARRAY_KINDS = "biuf"
#: the longest session id
MAX_SESSION_LENGTH = 128
#: the longest instruction, in characters
MAX_INSTRUCTION_LENGTH = 1000
#: the most dimensions an array on the wire may have (a request's have at most 3)
MAX_ARRAY_DIMS = 8
#: the longest side of an image of a policy that takes any size (an OpenVLA checkpoint's processor resizes it)
MAX_IMAGE_SIDE = 4096
#: the largest token id ``draft_state`` may hold (token ids are int64 on the policy's side)
MAX_TOKEN_ID = 2**63 - 1
#: the fields of ``POST /act``
REQUEST_FIELDS = ("image", "instruction", "unnorm_key", "state", "session", "reset", "draft_state", "api_key")


class RequestError(ValueError):
    """A request the server refuses: its HTTP status, the field at fault (None: the request as a whole) and why."""

    def __init__(self, message: str, field: str | None = None, status: int = 422):
        super().__init__(message)
        self.message, self.field, self.status = message, field, status

    def to_payload(self) -> dict:
        return {"error": self.message, "field": self.field}


class Overloaded(RuntimeError):
    """The server cannot take the request now: retry after ``retry_after_s`` seconds (HTTP 503 + Retry-After)."""

    def __init__(self, message: str, retry_after_s: int):
        super().__init__(message)
        self.retry_after_s = retry_after_s


# ----------------------------------------------------------------------------- arrays
def encode_array(array) -> dict:
    """A numpy array (or scalar) as json_numpy encodes it."""
    array = np.ascontiguousarray(array)
    return {
        "__numpy__": base64.b64encode(array.tobytes()).decode("ascii"),
        "dtype": np.lib.format.dtype_to_descr(array.dtype),
        "shape": list(array.shape),
    }


def decode_array(payload: dict, name: str = "array") -> np.ndarray:
    """json_numpy's array object -> a numpy array, reading only bool / int / float dtypes.

    Raises:
        RequestError: a dtype that is not plain numbers, a bad shape, bad base64, or bytes that do not fill the shape.
    """
    descr, shape = payload.get("dtype"), payload.get("shape")
    try:
        dtype = np.dtype(descr) if isinstance(descr, str) else None
    except Exception:  # noqa: BLE001 (numpy raises TypeError, ValueError, SyntaxError... for text it cannot read)
        dtype = None
    if dtype is None or dtype.kind not in ARRAY_KINDS or dtype.fields is not None or dtype.subdtype is not None:
        raise RequestError(f"{name}: dtype {str(descr)[:40]!r} is not read here; send bool, int or float arrays", name)
    if (
        not isinstance(shape, list | tuple)
        or len(shape) > MAX_ARRAY_DIMS
        or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)
    ):
        raise RequestError(
            f"{name}: shape must be a list of at most {MAX_ARRAY_DIMS} non-negative ints, got {str(shape)[:80]}", name
        )
    data = payload.get("__numpy__")
    try:
        raw = base64.b64decode(data, validate=True) if isinstance(data, str) else None
    except (binascii.Error, ValueError):
        raw = None
    if raw is None:
        raise RequestError(f"{name}: '__numpy__' must be base64 text", name)
    if max(shape, default=0) > len(raw):  # also an empty array's: numpy refuses absurd dimensions (>= 2**63)
        raise RequestError(f"{name}: shape {str(shape)[:80]} has a dimension larger than its {len(raw)} bytes", name)
    expected = math.prod(shape) * dtype.itemsize
    if len(raw) != expected:
        raise RequestError(
            f"{name}: {len(raw)} bytes do not fill shape {list(shape)} of {dtype} ({expected} bytes)", name
        )
    return np.frombuffer(raw, dtype).reshape(shape) if shape else np.frombuffer(raw, dtype)[0]


def _json_default(value: Any):
    if isinstance(value, np.ndarray | np.generic):
        return encode_array(value)
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


def dumps(value: Any) -> bytes:
    """JSON bytes, numpy arrays in json_numpy's form."""
    return json.dumps(value, default=_json_default).encode()


def loads(body: bytes | str, arrays: bool = True) -> Any:
    """JSON text -> Python values, json_numpy's array objects as numpy arrays (see [`decode_array`]; ``arrays``
    False: left as the dicts they are, for [`ActRequest.parse`] to decode field by field).

    Raises:
        RequestError: not JSON (400), nested too deeply for the parser (400), or an array object that
            [`decode_array`] refuses.
    """
    try:
        return json.loads(body, object_hook=_array_hook if arrays else None)
    except ValueError as error:  # not JSON, not UTF-8, or a number past Python's 4300 digits
        raise RequestError(f"the body is not JSON: {error}", None, 400) from None
    except RecursionError:
        raise RequestError("the body is JSON nested too deeply to read (a request nests 3 levels)", None, 400) from None


def _array_hook(payload: dict):
    return decode_array(payload) if "__numpy__" in payload else payload


def _field_array(value, name: str):
    """A field's value with a json_numpy array object decoded (errors name the field)."""
    return decode_array(value, name) if isinstance(value, dict) and "__numpy__" in value else value


def _check_text(value: str, name: str) -> None:
    """Refuses text that is not valid Unicode (a lone surrogate, as JSON's ``\\ud800`` writes it): no tokenizer
    reads it."""
    try:
        value.encode("utf-8")
    except UnicodeEncodeError as error:
        raise RequestError(
            f"{name} is not valid Unicode text: {error.reason} at character {error.start}", name
        ) from None


# ----------------------------------------------------------------------------- requests
def unwrap(payload: Any) -> tuple[Any, bool]:
    """A decoded body -> (the request's fields, whether it came double-encoded): OpenVLA's ``{"encoded": <json_numpy
    text>}`` is read inside (arrays left as dicts), any other body is its own fields.

    Raises:
        RequestError: a double-encoded body with other keys beside ``encoded``, or text that is not JSON.
    """
    if not (isinstance(payload, dict) and "encoded" in payload):
        return payload, False
    if len(payload) != 1 or not isinstance(payload["encoded"], str):
        raise RequestError("a double-encoded request holds only 'encoded': json_numpy text", "encoded")
    return loads(payload["encoded"], arrays=False), True


@dataclass
class ActRequest:
    """One robot's ``POST /act``, checked ([`parse`]).

    Attributes:
        image: uint8 ``[S, S, 3]`` (``[H, W, 3]`` for a policy that takes any size).
        instruction: the task in words.
        state: float64 ``[state_dim]``, or None.
        session: the robot's id (None: no memory between its requests).
        reset: a new episode (the session's previous actions are forgotten).
        draft_state: the previous actions' token ids (one list per action) the robot echoed (None: the server's own
            memory of the session).
        double_encoded: sent in OpenVLA's ``{"encoded": ...}`` form (answered the same way).
        received: ``time.perf_counter()`` once its body was read and checked (None: it did not come over HTTP).
        unnorm_key: the dataset whose statistics un-normalise the action, as sent (the service resolves it: None for
            a policy with one set of statistics).
    """

    image: np.ndarray
    instruction: str
    state: np.ndarray | None = None
    session: str | None = None
    reset: bool = False
    draft_state: list[list[int]] | None = None
    double_encoded: bool = False
    received: float | None = None
    unnorm_key: str | None = None

    @classmethod
    def parse(cls, payload: Any, image_size: int | None, state_dim: int, needs_state: bool) -> ActRequest:
        """A decoded request body (``loads(body, arrays=False)``, or with its arrays decoded) -> an ActRequest, for a
        policy that takes ``image_size``-pixel images (None: any ``[H, W, 3]`` up to ``MAX_IMAGE_SIDE``) and
        ``state_dim`` proprio numbers (``needs_state``: the state is required).

        Raises:
            RequestError: naming the field at fault and what it must be.
        """
        payload, double_encoded = unwrap(payload)
        if not isinstance(payload, dict):
            raise RequestError(
                f"the body must be a JSON object with {', '.join(REQUEST_FIELDS)}, got {type(payload).__name__}",
                None,
                400,
            )
        image = _image(_field_array(payload.get("image"), "image"), image_size)
        instruction = payload.get("instruction")
        if not isinstance(instruction, str) or not instruction.strip():
            raise RequestError("instruction is required: the task in words (a non-empty string)", "instruction")
        if len(instruction) > MAX_INSTRUCTION_LENGTH:
            raise RequestError(
                f"instruction has {len(instruction)} characters, at most {MAX_INSTRUCTION_LENGTH}", "instruction"
            )
        _check_text(instruction, "instruction")
        unnorm_key = payload.get("unnorm_key")
        if unnorm_key is not None and not isinstance(unnorm_key, str):
            raise RequestError(f"unnorm_key must be a string, got {type(unnorm_key).__name__}", "unnorm_key")
        state = _state(_field_array(payload.get("state"), "state"), state_dim, needs_state)
        draft_state = _draft_state(_field_array(payload.get("draft_state"), "draft_state"))
        return cls(
            image,
            instruction,
            state,
            _session(payload.get("session")),
            _flag(payload.get("reset", False), "reset"),
            draft_state,
            double_encoded,
            unnorm_key=unnorm_key,
        )


def _image(image, image_size: int | None) -> np.ndarray:
    expected = "[H, W, 3]" if image_size is None else str([image_size, image_size, 3])
    if not isinstance(image, np.ndarray):
        raise RequestError(f"image is required: a json_numpy uint8 array of shape {expected}", "image")
    if image_size is None:
        fits = image.ndim == 3 and image.shape[2] == 3 and all(1 <= side <= MAX_IMAGE_SIDE for side in image.shape[:2])
        expected += f" (sides 1..{MAX_IMAGE_SIDE})"
    else:
        fits = image.shape == (image_size, image_size, 3)
    if image.dtype != np.uint8 or not fits:
        raise RequestError(f"image must be uint8 of shape {expected}, got {image.dtype} {list(image.shape)}", "image")
    return image


def _state(value, state_dim: int, needs_state: bool) -> np.ndarray | None:
    if value is None:
        if needs_state:
            raise RequestError(f"state is required by this policy: {state_dim} numbers (the proprio reading)", "state")
        return None
    if isinstance(value, list) and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value):
        try:
            value = np.asarray(value, dtype=np.float64)
        except OverflowError:  # an int past float64's range
            raise RequestError(
                f"state must hold finite numbers, got an integer of {max(len(str(v)) for v in value)} digits", "state"
            ) from None
    if not isinstance(value, np.ndarray) or value.dtype.kind not in "iuf" or value.shape != (state_dim,):
        shown = f"{value.dtype} {list(value.shape)}" if isinstance(value, np.ndarray) else type(value).__name__
        raise RequestError(f"state must be {state_dim} numbers (a list or a numeric array), got {shown}", "state")
    with np.errstate(over="ignore"):  # float128 past float64's range: inf, refused below
        state = value.astype(np.float64)
    if not np.isfinite(state).all():
        raise RequestError(f"state must hold finite numbers, got {state.tolist()}", "state")
    return state


def _session(value) -> str | None:
    if value is None:
        return None
    if not isinstance(value, str) or not 0 < len(value) <= MAX_SESSION_LENGTH:
        raise RequestError(
            f"session must be a string of 1..{MAX_SESSION_LENGTH} characters (the robot's id), got "
            f"{type(value).__name__} {str(value)[:40]!r}",
            "session",
        )
    _check_text(value, "session")
    return value


def _flag(value, name: str) -> bool:
    if not isinstance(value, bool):
        raise RequestError(f"{name} must be true or false, got {type(value).__name__} {value!r}", name)
    return value


def _draft_state(value) -> list[list[int]] | None:
    if value is None:
        return None
    if isinstance(value, np.ndarray) and value.dtype.kind in "iu" and value.ndim == 2:
        value = value.tolist()
    if not isinstance(value, list) or not all(
        isinstance(row, list) and all(isinstance(v, int) and not isinstance(v, bool) for v in row) for row in value
    ):
        raise RequestError(
            "draft_state must be what the last reply's 'served.draft_state' held: a list of actions, "
            "each a list of token ids (ints)",
            "draft_state",
        )
    if not all(0 <= v <= MAX_TOKEN_ID for row in value for v in row):
        raise RequestError(
            f"draft_state must hold token ids 0..{MAX_TOKEN_ID} (as the last reply sent), got {str(value)[:80]}",
            "draft_state",
        )
    return value


# ----------------------------------------------------------------------------- replies
@dataclass
class ServedFigures:
    """What the server did for one request (the reply's ``served`` object).

    Attributes:
        method: the decoding that ran: the speculative method's name, or the greedy baseline's.
        speculative: whether the request was decoded speculatively (False: the batch's size pays better greedy).
        target_forwards: target forwards this row took part in.
        batch_size: requests decoded together (the robots' rows; idle rows filling the bucket not counted).
        bucket: the batch size the call ran at (a compiled shape).
        queue_ms: from the request's arrival to its batch's start.
        decode_ms: from the batch's start to this row's action (the whole call for the batch's last row).
        server_ms: from the request's arrival to its reply.
        session: the robot's id, as sent.
        draft_state: the robot's previous actions as token ids (one list per action): echo it as the next
            request's ``draft_state``.
        batch_forwards: target forwards the batch ran (its slowest row's count; for a reply that left before its
            batch's call returned, those the batch had run when the row finished: its own).
        early: whether the reply left before its batch's call returned (its row finished while the rest of the
            batch still decoded).
        intake_ms: the part of ``queue_ms`` before the request could join a batch: from its arrival to its body
            read and checked (0 for a request that did not come over HTTP).
    """

    method: str
    speculative: bool
    target_forwards: int
    batch_size: int
    bucket: int
    queue_ms: float
    decode_ms: float
    server_ms: float = 0.0
    session: str | None = None
    draft_state: list[list[int]] = field(default_factory=list)
    batch_forwards: int = 0
    early: bool = False
    intake_ms: float = 0.0


@dataclass
class ActReply:
    """An action and how it was served."""

    action: np.ndarray
    served: ServedFigures

    def to_payload(self) -> dict:
        """The reply body: the action in json_numpy's form (what OpenVLA's clients read) plus ``served``."""
        return {**encode_array(self.action), "served": asdict(self.served)}

    @classmethod
    def from_payload(cls, payload: dict) -> ActReply:
        """A reply body parsed with plain ``json.loads`` -> the action and the figures."""
        figures = payload.get("served")
        if not isinstance(figures, dict):
            raise ValueError("the reply carries no 'served' figures: not an hf_specvla server (an OpenVLA deploy.py?)")
        return cls(decode_array(payload, "action"), ServedFigures(**figures))
