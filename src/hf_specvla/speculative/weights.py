"""Loading errors that name the file: a damaged weights file, a folder that is not there."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

from safetensors import SafetensorError


class DamagedWeightsError(OSError):
    """A weights file that cannot be read (truncated, damaged): the message names the file and what to do."""


@contextlib.contextmanager
def named_weight_errors(name_or_path: str | os.PathLike, what: str):
    """Re-raises a ``safetensors`` error of a ``from_pretrained`` inside the block as a [`DamagedWeightsError`] (an
    ``OSError``) that names the weights file and what to do; other errors pass unchanged.

    Args:
        name_or_path: the folder (or hub id) being loaded.
        what: what it is, for the message ("draft head", "policy", "OpenVLA checkpoint").
    """
    try:
        yield
    except SafetensorError as error:
        folder = Path(name_or_path)
        files = sorted(folder.glob("*.safetensors")) if folder.is_dir() else []
        named = ", ".join(f"{str(f)!r} ({f.stat().st_size:,} bytes)" for f in files)
        named = named or f"the weights of {name_or_path!r}"
        raise DamagedWeightsError(
            f"could not read the {what}'s weights {named}: {error}. The file is damaged or truncated (an interrupted "
            f"download, copy or save): download or save it again"
        ) from error
