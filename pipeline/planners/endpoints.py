"""A mission's ends checked against a window's passable cells: off the map, not passable (with
the nearest passable cell in the message), or a map with no passable cell at all.
"""

from __future__ import annotations

import numpy as np

from ..exceptions import InvalidEndpointError, InvalidParameterError
from ..runtime.jit import njit


def nearest_passable(passable: np.ndarray, cell, origin=(0, 0)) -> tuple[int, int] | None:
    """The passable cell of ``passable`` nearest ``cell``, or None; ``passable`` may be a window
    whose first cell is ``origin`` (cells in and out are then in map coordinates)."""
    r, c = int(cell[0]) - origin[0], int(cell[1]) - origin[1]
    if 0 <= r < passable.shape[0] and 0 <= c < passable.shape[1] and passable[r, c]:
        return int(cell[0]), int(cell[1])  # itself, the only cell at distance 0
    idx = np.argwhere(passable)
    if idx.size == 0:
        return None
    d = ((idx + np.asarray(origin) - np.asarray(cell)) ** 2).sum(axis=1)
    r, c = idx[int(np.argmin(d))] + np.asarray(origin)
    return int(r), int(c)


def off_map_error(name: str, r: int, c: int, shape) -> InvalidEndpointError:
    return InvalidEndpointError(
        f"{name} ({r}, {c}) is off the map (rows 0..{shape[0] - 1}, cols 0..{shape[1] - 1})"
    )


# said where a maps store has no passable cell: the likeliest cause is a DEM of depths
NO_PASSABLE = (
    "no cell of the maps is passable: the DEM lies above the surface limit (sea level less "
    "the surface clearance) everywhere; if its values are depths, positive down, negate them "
    "(or give the variable the attribute positive = 'down') and build the maps again"
)


def not_passable_error(name: str, r: int, c: int, near, none_hint: str) -> InvalidEndpointError:
    hint = f"nearest passable cell: {near}" if near else none_hint
    return InvalidEndpointError(
        f"{name} ({r}, {c}) is on land or inside the clearance zone; {hint}"
    )


def check_endpoint(name: str, cell, passable: np.ndarray) -> tuple[int, int]:
    try:
        r, c = (int(v) for v in cell)
    except (TypeError, ValueError):
        raise InvalidParameterError(f"`{name}` must be a cell (row, col), got {cell!r}") from None
    rows, cols = passable.shape
    if not (0 <= r < rows and 0 <= c < cols):
        raise off_map_error(name, r, c, passable.shape)
    if not passable[r, c]:
        raise not_passable_error(name, r, c, nearest_passable(passable, (r, c)), NO_PASSABLE)
    return r, c


def check_arrays(surface, ridge, passable):
    surface = np.asarray(surface)
    if surface.dtype not in (np.float32, np.float64):  # float32 maps stay float32: no copy
        surface = surface.astype(np.float64)
    ridge = np.asarray(ridge, dtype=bool)
    passable = np.asarray(passable, dtype=bool)
    if surface.ndim != 2 or ridge.shape != surface.shape or passable.shape != surface.shape:
        raise InvalidParameterError(
            f"surface, ridge and passable must be 2-D arrays of one "
            f"shape; got {surface.shape}, {ridge.shape}, "
            f"{passable.shape}"
        )
    count, first = _unusable(surface, passable)
    if count:
        r, c = divmod(first, surface.shape[1])
        raise InvalidParameterError(
            f"the surface is NaN or infinite at passable cell "
            f"({r}, {c}) ({count} such cells); mark no-data "
            "cells impassable"
        )
    return surface, ridge, passable


@njit(nogil=True, cache=True)
def _unusable(surface, passable):
    """How many passable cells have a surface that is NaN or infinite, and the first of them
    (flat index, row-major; -1 for none): one pass, no temporaries (numpy's ``passable &
    ~isfinite(surface)`` made two window-sized arrays for every section)."""
    rows, cols = surface.shape
    count = 0
    for r in range(rows):
        for c in range(cols):
            x = surface[r, c]
            count += passable[r, c] and not (x - x == 0)  # x - x is NaN for NaN and inf
    if count == 0:
        return 0, -1
    for r in range(rows):
        for c in range(cols):
            x = surface[r, c]
            if passable[r, c] and not (x - x == 0):
                return count, r * cols + c
    return count, -1
