"""The 8-neighbourhood in one fixed order (E, SE, S, SW, W, NW, N, NE), shared by the D8 flow
directions and the planners' moves: odd codes are the diagonals. Kernels over flat indices take
a neighbour as ``c + flat_offsets(cols)[k]`` once ``inside`` says it is on the grid (a cell off
the border needs no check)."""

from __future__ import annotations

import math

import numpy as np

from ..runtime.jit import njit

DR = np.array([0, 1, 1, 1, 0, -1, -1, -1], dtype=np.int64)
DC = np.array([1, 1, 0, -1, -1, -1, 0, 1], dtype=np.int64)
DIST = np.array([1.0, math.sqrt(2.0)] * 4)  # step length in cells


@njit(cache=True)
def flat_offsets(cols):
    """The flat-index step to each neighbour on a grid of ``cols`` columns."""
    off = np.empty(8, dtype=np.int64)
    for k in range(8):
        off[k] = DR[k] * cols + DC[k]
    return off


@njit(cache=True)
def inside(r, c, k, rows, cols):
    """Whether neighbour ``k`` of cell (r, c) is on the ``rows x cols`` grid."""
    nr = r + DR[k]
    nc = c + DC[k]
    return 0 <= nr < rows and 0 <= nc < cols
