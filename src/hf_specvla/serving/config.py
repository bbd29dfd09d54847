"""What a policy server is configured with: [`ServeConfig`] (how the service decodes and batches) and the HTTP
defaults, each defined once; [`check_exposure`], the rule for serving beyond this machine. Imports nothing heavy:
the CLI reads its defaults here."""

from __future__ import annotations

import ipaddress
import math
from dataclasses import dataclass

from .._validation import check_ranges
from ..policies.devices import DEFAULT_DEVICE, DEFAULT_DTYPE, check_device, check_dtype

DEFAULT_BUCKETS = (1, 2, 4, 8, 16)
#: the largest bucket (batch size) and batching window accepted: beyond them a setting is a typo, not a plan (a
#: bucket's graphs and caches are built at start-up; a window past the timeout of any robot's client serves no one)
MAX_BUCKET, MAX_WAIT_MS = 1024, 60_000.0
#: the most timed calls per bucket and mode at start-up (more only delays the start: the chooser's figures stay current
#: by exploring, ``explore_every``)
MAX_CALIBRATION_CALLS = 100
DEFAULT_HOST, DEFAULT_PORT = "127.0.0.1", 8000
#: the largest request body read (an OpenVLA 224 x 224 image is ~200 KB as json_numpy)
DEFAULT_MAX_REQUEST_BYTES = 4 * 2**20
#: the environment variable an API key may come from (so that it stays out of shell histories and process lists)
API_KEY_VARIABLE = "HF_SPECVLA_API_KEY"


@dataclass
class ServeConfig:
    """How the service decodes and batches.

    Args:
        method: the speculative decoding method or preset (``exact``, ``prior+jacobi:compile``, ...; see
            ``policies.decoding_methods``), or several: each bucket decodes with whichever of them and the greedy
            baseline is fastest (measured). A preset given a draft head stands for its methods with and without the
            head (``exact``: ``prior+jacobi:compile`` and ``prior+jacobi+tree:compile``). ``greedy`` /
            ``greedy:compile`` serves greedy only.
        buckets: the batch sizes decoding runs at (a batch is padded up to the next); the largest is the most
            requests decoded together.
        max_wait_ms: how long a batch waits for more requests after its first arrived (0: decode what is there).
        max_queue: requests waiting beyond the batch being decoded; more are refused (HTTP 503, Retry-After).
        calibration_calls: interleaved timed calls per bucket and mode at start-up (0: no calibration: speculate
            wherever ``speculate_buckets`` says, or everywhere).
        speculate_buckets: the buckets to decode speculatively, fixed (None: measured).
        explore_every: every n-th batch of a bucket runs the mode not chosen, to keep its timing current (0: never).
        max_sessions: robots whose drafts are kept.
        max_prompt_tokens: the longest prompt served (tokens: image, instruction and state), for a compiled method:
            start-up compiles graphs for every prompt length up to it (None: as long as the shortest prompt's
            verification cache holds, and at least ``service.MIN_INSTRUCTION_TOKENS`` for the instruction: 54 tokens
            on policy v3. Longer costs start-up time, more graphs per bucket every 64 tokens, and every speculative
            call then runs on the longest prompt's cache).
            ``GET /info`` states the limit in force; a longer request is refused (422, field ``instruction``) before
            any forward. An eager method has no such limit.
        compile_cache: a folder for the compiled graphs (``serving.compile_cache``): the engine's graph files in
            ``DIR/graphs`` and torch's Inductor caches beside them; a later start loads them instead of compiling
            (None: the graph folder of ``HF_SPECVLA_GRAPH_CACHE`` or its default, and torch's default Inductor
            folder, which a new machine or container starts without).
        device: where the policy and its draft head run: ``auto`` (``cuda`` when torch sees a GPU, else ``cpu``),
            ``cpu``, ``cuda``, ``cuda:N`` (``policies.devices``; whether it is there is asked when the policy loads).
            On Ray Serve a CUDA device asks each replica's actor for one GPU (``ray_actor_options.num_gpus``).
        dtype: the weights' precision: ``auto`` (``bfloat16`` on a CUDA device, ``float32`` on the CPU),
            ``bfloat16``, ``float16``, ``float32``. A draft head is checked against the policy as saved, then cast.
        unnorm_key: an OpenVLA checkpoint's dataset whose statistics un-normalise the actions of a request that
            names none (a request's own ``unnorm_key`` wins). None: the checkpoint's only dataset; with several, each
            request must name one. A Meta-World policy has one set of statistics and takes none.
    """

    method: str | tuple[str, ...] = "exact"
    buckets: tuple[int, ...] = DEFAULT_BUCKETS
    max_wait_ms: float = 2.0
    max_queue: int = 64
    calibration_calls: int = 3
    speculate_buckets: tuple[int, ...] | None = None
    explore_every: int = 16
    max_sessions: int = 10_000
    max_prompt_tokens: int | None = None
    compile_cache: str | None = None
    device: str = DEFAULT_DEVICE
    dtype: str = DEFAULT_DTYPE
    unnorm_key: str | None = None

    def __post_init__(self):
        if isinstance(self.method, list | tuple):
            self.method = self.method[0] if len(self.method) == 1 else tuple(self.method)
        texts = (self.method,) if isinstance(self.method, str) else self.method
        if not texts or not all(isinstance(text, str) and text.strip() for text in texts):
            raise ValueError(
                f"ServeConfig.method must be a decoding method or preset (e.g. exact, "
                f"prior+jacobi:compile), or a list of them, got {self.method!r}"
            )
        self.buckets = tuple(self.buckets)
        if not self.buckets or any(
            isinstance(b, bool) or not isinstance(b, int) or not 1 <= b <= MAX_BUCKET for b in self.buckets
        ):
            raise ValueError(f"buckets must be batch sizes 1..{MAX_BUCKET}, got {list(self.buckets)}")
        if list(self.buckets) != sorted(set(self.buckets)):
            raise ValueError(f"buckets must be increasing without repeats, got {list(self.buckets)} (e.g. 1,2,4,8,16)")
        check_ranges(
            self,
            at_least_one=("max_queue", "max_sessions"),
            non_negative=("max_wait_ms", "calibration_calls", "explore_every"),
            integers=("max_queue", "max_sessions", "calibration_calls", "explore_every"),
        )
        if not math.isfinite(self.max_wait_ms) or self.max_wait_ms > MAX_WAIT_MS:
            raise ValueError(
                f"ServeConfig.max_wait_ms must be a finite number of milliseconds 0..{MAX_WAIT_MS:g}, "
                f"got {self.max_wait_ms!r}"
            )
        if self.calibration_calls > MAX_CALIBRATION_CALLS:
            raise ValueError(
                f"ServeConfig.calibration_calls must be 0..{MAX_CALIBRATION_CALLS} (timed calls per "
                f"bucket and mode at start-up), got {self.calibration_calls}"
            )
        for name, check in (("device", check_device), ("dtype", check_dtype)):
            try:
                check(getattr(self, name))
            except ValueError as error:
                raise ValueError(f"ServeConfig.{name}: {error}") from None
        if self.compile_cache is not None and (not isinstance(self.compile_cache, str) or not self.compile_cache):
            raise ValueError(f"ServeConfig.compile_cache must be a folder (a path), got {self.compile_cache!r}")
        if self.unnorm_key is not None and (not isinstance(self.unnorm_key, str) or not self.unnorm_key.strip()):
            raise ValueError(f"ServeConfig.unnorm_key must be a dataset's name (a string), got {self.unnorm_key!r}")
        if self.max_prompt_tokens is not None:
            check_ranges(self, at_least_one=("max_prompt_tokens",), integers=("max_prompt_tokens",))
        if self.speculate_buckets is not None:
            self.speculate_buckets = tuple(self.speculate_buckets)
            unknown = sorted(set(self.speculate_buckets) - set(self.buckets))
            if unknown:
                raise ValueError(f"speculate_buckets {unknown} are not buckets; the buckets are {list(self.buckets)}")

    @property
    def max_batch_size(self) -> int:
        return self.buckets[-1]


def is_loopback(host: str) -> bool:
    """Whether ``host`` is reachable only from this machine (127.0.0.0/8, ::1, localhost)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_exposure(host: str, api_key: str | None) -> None:
    """Refuses to serve beyond this machine without an API key.

    Raises:
        ValueError: a non-loopback ``host`` and no ``api_key``.
    """
    if not is_loopback(host) and not api_key:
        raise ValueError(
            f"host {host!r} is reachable from other machines: pass --api-key (or set "
            f"{API_KEY_VARIABLE}) so that every request must carry it, or serve on 127.0.0.1"
        )


#: the longest a request's body may take to arrive whole by default (a robot's observation arrives in milliseconds;
#: 10 s carries a 4 MiB body at 3.2 Mbit/s): past it the request is answered 408, so that a client holding a half-sent
#: body delays a shutdown's drain at most this long (``serve --body-timeout-s``)
BODY_TIMEOUT_S = 10.0
#: the longest ``body_timeout_s`` may be set to
MAX_BODY_TIMEOUT_S = 600.0


def check_body_timeout(body_timeout_s) -> None:
    """Refuses a body timeout that is not seconds in (0, ``MAX_BODY_TIMEOUT_S``].

    Raises:
        ValueError: naming the value and what is valid.
    """
    if (
        isinstance(body_timeout_s, bool)
        or not isinstance(body_timeout_s, int | float)
        or not 0 < body_timeout_s <= MAX_BODY_TIMEOUT_S
    ):
        raise ValueError(
            f"body_timeout_s must be seconds in (0, {MAX_BODY_TIMEOUT_S:g}] (how long a request's body may take to "
            f"arrive whole), got {body_timeout_s!r}"
        )
