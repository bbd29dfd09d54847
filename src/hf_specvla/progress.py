"""Progress bars for long jobs: redrawn freely on a terminal, and at most every ``REDIRECTED_INTERVAL`` seconds
when the output goes to a file or a pipe (a log then gets a few lines, not hundreds of redraws)."""

from __future__ import annotations

import logging
import sys

from tqdm.auto import tqdm

#: Seconds between updates of a bar whose output is not a terminal.
REDIRECTED_INTERVAL = 30.0


class _ProgressBar(tqdm):
    """A tqdm whose ``set_postfix`` never forces a redraw (tqdm's default would redraw at every call, whatever
    ``mininterval`` says); the postfix shows at the next timed redraw."""

    def set_postfix(self, ordered_dict=None, refresh=True, **kwargs):
        super().set_postfix(ordered_dict, refresh=False, **kwargs)


def progress_bar(*args, **kwargs) -> tqdm:
    """``tqdm(*args, **kwargs)``, slowed down when stderr is not a terminal (see module docstring)."""
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
