"""Settings a process reads from its environment (``AUV_PIPELINE_*``): a number, checked."""

from __future__ import annotations

import math
import os

from ..exceptions import InvalidParameterError


def env_number(name: str, default: float, *, integer: bool = False, minimum: float = 0.0):
    """The number in the environment variable ``name`` (``default`` when it is not set), or
    one :class:`InvalidParameterError` naming the variable where it is not a finite number of
    at least ``minimum``."""
    text = os.environ.get(name)
    if text is None or not text.strip():
        return default
    try:
        value = int(text) if integer else float(text)
    except ValueError:
        value = None
    if value is None or not math.isfinite(value) or value < minimum:
        kind = "an integer" if integer else "a number"
        raise InvalidParameterError(
            f"the environment variable {name}={text!r} must be {kind} of at least {minimum:g}; "
            "set it so, or unset it for the default"
        )
    return value
