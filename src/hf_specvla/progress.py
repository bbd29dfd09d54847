"""Progress bars for long jobs: redrawn freely on a terminal, and at most every ``REDIRECTED_INTERVAL`` seconds
when the output goes to a file or a pipe (a log then gets a few lines, not hundreds of redraws); and a heartbeat, a
log line every ``HEARTBEAT_INTERVAL`` seconds through work that says nothing while it runs (compiling)."""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from contextlib import contextmanager

from tqdm.auto import tqdm

logger = logging.getLogger(__name__)

#: Seconds between updates of a bar whose output is not a terminal.
REDIRECTED_INTERVAL = 30.0


class _ProgressBar(tqdm):
    """A tqdm whose ``set_postfix`` never forces a redraw (tqdm's default would redraw at every call, whatever
    ``mininterval`` says); the postfix shows at the next timed redraw."""

    def set_postfix(self, ordered_dict=None, refresh=True, **kwargs):
        super().set_postfix(ordered_dict, refresh=False, **kwargs)


def is_secondary_process() -> bool:
    """A process other than the first of a launched group (``accelerate launch`` / ``torchrun`` set ``RANK``): it
    draws no bar and logs only warnings, so that a run of n processes reads as a run of one."""
    return int(os.environ.get("RANK", "0")) > 0


def progress_bar(*args, **kwargs) -> tqdm:
    """``tqdm(*args, **kwargs)``, slowed down when stderr is not a terminal (see module docstring); none in a
    secondary process."""
    if is_secondary_process():
        kwargs["disable"] = True
    stream = kwargs.get("file") or sys.stderr
    if not getattr(stream, "isatty", lambda: False)():
        kwargs["mininterval"] = max(kwargs.get("mininterval", 0.1), REDIRECTED_INTERVAL)
        kwargs.setdefault("maxinterval", 2 * REDIRECTED_INTERVAL)
    return _ProgressBar(*args, **kwargs)


class ProgressAwareHandler(logging.Handler):
    """A logging handler that writes through ``tqdm.write``: a log line goes on its own line, above any live bar,
    instead of being glued onto the bar's line."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            tqdm.write(self.format(record), file=sys.stderr)
        except Exception:  # logging must never raise
            self.handleError(record)


#: Seconds between the lines [`heartbeat`] logs while a step that reports nothing runs (compiling).
HEARTBEAT_INTERVAL = 30.0


class Heartbeat:
    """What [`heartbeat`] reports; the block calls ``begin(step)`` as the work moves on."""

    def __init__(self, description: str):
        self.description, self.step = description, ""
        self.started = self.step_started = time.perf_counter()

    def begin(self, step: str) -> None:
        """A new step (``"greedy:compile (2/25)"``), timed from now."""
        self.step, self.step_started = step, time.perf_counter()

    def line(self) -> str:
        """``"<description>: <step>, 45 s on it, 2 min 10 s in all"``."""
        now = time.perf_counter()
        on_step = f"{self.step}, {now - self.step_started:.0f} s on it, " if self.step else ""
        minutes, seconds = divmod(round(now - self.started), 60)
        return f"{self.description}: {on_step}{minutes} min {seconds} s in all"


@contextmanager
def heartbeat(description: str, interval: float = HEARTBEAT_INTERVAL, log: logging.Logger | None = None):
    """Logs a line every ``interval`` seconds (INFO, from a background thread) until the block ends, for work that
    says nothing while it runs: e.g. a first ``generate`` call that compiles its graphs for a minute. Yields a
    [`Heartbeat`]: the block calls its ``begin(step)`` as it goes; a block shorter than ``interval`` logs nothing.

    Raises:
        ValueError: ``interval`` is not a positive number of seconds.
    """
    if not interval > 0:
        raise ValueError(f"heartbeat interval must be a positive number of seconds, got {interval!r}")
    log = log or logger
    beat, stop = Heartbeat(description), threading.Event()

    def run() -> None:
        while not stop.wait(interval):
            log.info("%s", beat.line())

    thread = threading.Thread(target=run, name=f"heartbeat: {description}", daemon=True)
    thread.start()
    try:
        yield beat
    finally:
        stop.set()
        thread.join()
