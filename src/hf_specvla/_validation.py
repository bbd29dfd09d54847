"""Field checks shared by the config dataclasses (training, comparison, policy): one wording for every refusal."""

from __future__ import annotations

import math


def check_ranges(config, at_least_one=(), positive=(), non_negative=(), integers=()) -> None:
    """Raises ValueError naming the first field of ``config`` out of its range: ``<Config>.<name> must be >= 1, got 0``
    (or ``must be an integer`` / ``a number`` when the type is wrong, ``a finite number`` for inf and NaN).
    ``integers``: fields that must be ints."""
    kind = type(config).__name__
    rules = (
        (at_least_one, lambda v: v >= 1, ">= 1"),
        (positive, lambda v: v > 0, "> 0"),
        (non_negative, lambda v: v >= 0, ">= 0"),
    )
    for names, ok, rule in rules:
        for name in names:
            value = getattr(config, name)
            integer = name in integers
            if isinstance(value, bool) or not isinstance(value, int if integer else (int, float)):
                raise ValueError(
                    f"{kind}.{name} must be {'an integer' if integer else 'a number'} {rule}, got {value!r}"
                )
            if not math.isfinite(value):  # inf passes >= 0 and > 0: a weight, rate or count is never infinite
                raise ValueError(f"{kind}.{name} must be a finite number {rule}, got {value!r}")
            if not ok(value):
                raise ValueError(f"{kind}.{name} must be {rule}, got {value!r}")
