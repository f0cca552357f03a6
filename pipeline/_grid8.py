"""The 8-neighbourhood in one fixed order (E, SE, S, SW, W, NW, N, NE), shared by the D8 flow
directions and the planners' moves: odd codes are the diagonals."""

from __future__ import annotations

import math

import numpy as np

DR = np.array([0, 1, 1, 1, 0, -1, -1, -1], dtype=np.int64)
DC = np.array([1, 1, 0, -1, -1, -1, 0, 1], dtype=np.int64)
DIST = np.array([1.0, math.sqrt(2.0)] * 4)  # step length in cells
