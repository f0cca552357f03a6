"""Small argument checks shared by the public functions (validate before building a graph)."""

from __future__ import annotations

import math
from numbers import Integral, Real

from .exceptions import InvalidParameterError


def positive_int(name: str, value, *, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, Integral):
        raise InvalidParameterError(f"`{name}` must be an integer >= {minimum}, got {value!r}")
    if value < minimum:
        raise InvalidParameterError(f"`{name}` must be an integer >= {minimum}, got {value}")
    return int(value)


def positive_float(name: str, value, *, allow_zero: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, Real):
        raise InvalidParameterError(f"`{name}` must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise InvalidParameterError(f"`{name}` must be a finite number {bound}, got {value}")
    return value


def shape2d(name: str, value) -> tuple[int, int]:
    try:
        rows, cols = value
    except (TypeError, ValueError):
        raise InvalidParameterError(
            f"`{name}` must be a pair (rows, cols), got {value!r}"
        ) from None
    return positive_int(f"{name}[0] (rows)", rows), positive_int(f"{name}[1] (cols)", cols)


def chunks2d(value, shape: tuple[int, int]) -> tuple[int, int] | None:
    """Normalise ``chunks`` (None, an int, or a (rows, cols) pair) to a pair of chunk sides."""
    if value is None:
        return None
    if isinstance(value, Integral) and not isinstance(value, bool):
        pair = (value, value)
    else:
        try:
            pair = tuple(value)
        except TypeError:
            raise InvalidParameterError(
                f"`chunks` must be None, an integer or a (rows, cols) pair, got {value!r}"
            ) from None
        if len(pair) != 2:
            raise InvalidParameterError(
                f"`chunks` must be None, an integer or a (rows, cols) pair, got {value!r}"
            )
    r = positive_int("chunks[0]", pair[0])
    c = positive_int("chunks[1]", pair[1])
    return min(r, shape[0]), min(c, shape[1])
