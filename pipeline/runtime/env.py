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


# the numbers the package reads from its environment: default, integer, least value
SETTINGS = {
    "AUV_PIPELINE_CHUNK_CACHE_MB": (1024, True, 0.0),
    "AUV_PIPELINE_CONNECT_TIMEOUT_S": (30.0, False, 0.001),
}


def setting(name: str):
    """The value of the package's environment setting ``name`` (:data:`SETTINGS`), checked."""
    default, integer, minimum = SETTINGS[name]
    return env_number(name, default, integer=integer, minimum=minimum)


def check_environment() -> None:
    """Every setting of :data:`SETTINGS` checked at once (the command line does it as it
    starts: a bad value is one line before any work, not after a cluster has started)."""
    for name in SETTINGS:
        setting(name)
