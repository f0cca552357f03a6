"""A search's path traced back from its state, and measured: its cells, its 3-D steps along the
safety surface, its length and the share of it on ridge cells.
"""

from __future__ import annotations

import math

import numpy as np

from ..runtime.jit import njit
from .grid import DC, DR
from .search import PARENT


@njit(cache=True)
def _trace(state, cols, gr, gc):
    n = 1
    r, c = gr, gc
    while state[r * cols + c] & PARENT:
        k = state[r * cols + c] & 7
        r -= DR[k]
        c -= DC[k]
        n += 1
    out = np.empty((n, 2), dtype=np.int64)
    r, c = gr, gc
    for i in range(n - 1, -1, -1):
        out[i, 0] = r
        out[i, 1] = c
        if i:
            k = state[r * cols + c] & 7
            r -= DR[k]
            c -= DC[k]
    return out


def trace_path(state: np.ndarray, cols: int, goal) -> np.ndarray:
    """The cells (k x 2) from the root of a search tree to ``goal``, read from the search state
    (per flat cell the move that entered it: one byte a cell, not eight for a predecessor)."""
    return _trace(state, cols, int(goal[0]), int(goal[1]))


def path_steps(cells: np.ndarray, z: np.ndarray, a: float) -> np.ndarray:
    """The 3-D length of every step of a path (step i ends at ``cells[i + 1]``), from its cells
    and the heights ``z`` of the surface along it: the one place path lengths are computed,
    ``sqrt(a^2 (dr^2 + dc^2) + dz^2)`` in float64 (in one kernel pass, not numpy's seven
    array operations)."""
    cells = np.asarray(cells, dtype=np.int64)
    return _steps(cells.reshape(-1, 2), np.asarray(z, dtype=np.float64).ravel(), float(a))


@njit(nogil=True, cache=True)
def _steps(cells, z, a):
    n = max(cells.shape[0] - 1, 0)
    out = np.empty(n)
    aa = a * a
    for i in range(n):
        dr = cells[i + 1, 0] - cells[i, 0]
        dc = cells[i + 1, 1] - cells[i, 1]
        dz = z[i + 1] - z[i]
        out[i] = math.sqrt(aa * (dr * dr + dc * dc) + dz * dz)
    return out


@njit(cache=True)
def _trace_measured(state, cols, gr, gc, surface, ridge, a, r0, c0):
    """:func:`_trace` and the path's heights (float64), ridge flags and steps (:func:`_steps`),
    and the steps that end on the ridge network, in one pass; the cells offset by (r0, c0).

    It keeps the GIL (a section's path takes microseconds): in one process a helper thread
    reads the next windows meanwhile, and a kernel that lets the GIL go waits for it to come
    back, up to the switch interval, which cost the missions more than it saved."""
    return _measured(_trace(state, cols, gr, gc), surface, ridge, a, r0, c0)


@njit(nogil=True, cache=True)
def _measured(cells, surface, ridge, a, r0, c0):
    """What :func:`_trace_measured` returns for a path's ``cells`` (written in place)."""
    n = cells.shape[0]
    z = np.empty(n)
    on = np.empty(n, dtype=np.bool_)
    for i in range(n):
        r, c = cells[i, 0], cells[i, 1]
        z[i] = surface[r, c]
        on[i] = ridge[r, c]
    steps = _steps(cells, z, a)
    k = 0
    for i in range(n - 1):
        k += on[i + 1]
    on_steps = np.empty(k)
    k = 0
    for i in range(n - 1):
        if on[i + 1]:
            on_steps[k] = steps[i]
            k += 1
    if r0 or c0:
        for i in range(n):
            cells[i, 0] += r0
            cells[i, 1] += c0
    return cells, z, on, steps, on_steps


def traced_path(state, cols: int, goal, surface, ridge, a: float, offset=(0, 0)):
    """The path to ``goal`` in a search state (:func:`trace_path`) with what a section keeps of
    it: ``(cells + offset, heights as float64, ridge flags, length, ridge length, ridge
    ratio)``, the metrics as :func:`path_metrics` computes them (the steps' sums by numpy, bit
    for bit the same). One kernel pass instead of the trace, two gathers, path_metrics' numpy
    calls, and a section's copy of its cells and heights: faster, with the same results on 80
    missions (2000^2 and 10000^2, ra_star and lagrangian: cells, points, lengths, bounds, bit
    for bit; CHANGELOG.md, "Measurements")."""
    cells, z, on, steps, on_steps = _trace_measured(
        state, cols, int(goal[0]), int(goal[1]), surface, ridge, float(a), *offset
    )
    return _summed(cells, z, on, steps, on_steps)


def measured_path(cells, surface, ridge, a: float, offset=(0, 0)):
    """:func:`traced_path` for a path given as its cells (k x 2, int64; offset in place)."""
    return _summed(*_measured(cells, surface, ridge, float(a), *offset))


def _summed(cells, z, on, steps, on_steps):
    if len(cells) < 2:
        return cells, z, on, 0.0, 0.0, 0.0
    length = float(steps.sum())
    ridge_len = float(on_steps.sum())
    return cells, z, on, length, ridge_len, ridge_len / length if length > 0 else 0.0


def path_metrics(cells: np.ndarray, z: np.ndarray, on_ridge: np.ndarray, a: float):
    """length, ridge length (steps whose end cell is a ridge cell), ridge ratio of a path with
    heights ``z`` and ridge flags ``on_ridge`` along it."""
    if len(cells) < 2:
        return 0.0, 0.0, 0.0
    step = path_steps(cells, z, a)
    length = float(step.sum())
    ridge_len = float(step[np.asarray(on_ridge, dtype=bool)[1:]].sum())
    return length, ridge_len, ridge_len / length if length > 0 else 0.0
