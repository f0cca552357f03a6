"""The paper's Algorithm 3 on cells (docs/method.md section 6): a coarse path restored to fine
cells, cut into square sections with a margin, the joints snapped to passable cells, and the
sections' paths stitched into one simple path (loops removed).
"""

from __future__ import annotations

import math

import numpy as np

from ..exceptions import InvalidParameterError, UnreachableGoalError
from ..params import PLANNING
from ..planners.endpoints import (
    nearest_passable,
)
from ..runtime.jit import njit
from ..store.maps_store import MapsStore


def default_parameters(shape, a: float) -> dict:
    """The default ``rho``, ``section_size`` and ``margin`` for a map (see the module doc)."""
    rho = max(2, math.ceil(max(shape) / 1000))
    section = max(4 * rho, math.ceil(3000.0 / a))
    return {"rho": rho, "section_size": section, "margin": default_margin(rho, section)}


def default_margin(rho: int, section_size: int) -> int:
    """The default window margin of sections of ``section_size`` at ``rho`` (the module doc)."""
    return max(rho, section_size // 8)


def restore(coarse_cells: np.ndarray, rho: int, shape, start, goal) -> np.ndarray:
    """Coarse cells to fine points (docs/method.md section 6 step 3): ``(i, j) -> (i rho + rho // 2,
    j rho + rho // 2)`` clipped to the map; the real start and goal replace the first and last
    point (a path of one coarse cell becomes start, goal)."""
    pts = np.asarray(coarse_cells, dtype=np.int64) * rho + rho // 2
    pts[:, 0] = np.clip(pts[:, 0], 0, shape[0] - 1)
    pts[:, 1] = np.clip(pts[:, 1], 0, shape[1] - 1)
    if len(pts) == 1:
        pts = np.vstack([pts, pts])
    pts[0] = start
    pts[-1] = goal
    return pts


def _window(rmin, rmax, cmin, cmax, margin, shape):
    """The bounding square of the box, centred on it, grown by ``margin``, clipped:
    half-open ``(r0, r1, c0, c1)``."""
    side = max(rmax - rmin, cmax - cmin)
    r0 = math.floor((rmin + rmax - side) / 2) - margin
    c0 = math.floor((cmin + cmax - side) / 2) - margin
    r1 = r0 + side + 2 * margin + 1
    c1 = c0 + side + 2 * margin + 1
    r0, c0 = min(r0, rmin), min(c0, cmin)
    r1, c1 = max(r1, rmax + 1), max(c1, cmax + 1)
    return max(r0, 0), min(r1, shape[0]), max(c0, 0), min(c1, shape[1])


def segment(points: np.ndarray, section_size: int, margin: int, shape) -> list:
    """Cut a restored path into sections (docs/method.md section 6 step 4).

    Points are added to a section until its bounding box has a side ``>= section_size``; the
    section spans those points and the next section starts at its last point. Returns a list
    of ``(i0, i1, (r0, r1, c0, c1))``: the indices of the section's first and last point in
    ``points`` and its window (half-open, clipped to the map).
    """
    cuts = _cuts(np.ascontiguousarray(points, dtype=np.int64).reshape(-1, 2), int(section_size))
    return [
        (i0, i1, _window(rmin, rmax, cmin, cmax, margin, shape))
        for i0, i1, rmin, rmax, cmin, cmax in cuts.tolist()
    ]


@njit(cache=True)
def _cuts(pts, section_size):
    """:func:`segment`'s sections as rows ``(i0, i1, rmin, rmax, cmin, cmax)``: their first and
    last point and their points' bounding box (compiled: a Python loop over the points took a
    noticeable share of a mission)."""
    n = pts.shape[0]
    out = np.empty((max(n - 1, 0), 6), dtype=np.int64)
    k = 0
    i0 = 0
    while i0 < n - 1:
        rmin = rmax = pts[i0, 0]
        cmin = cmax = pts[i0, 1]
        j = i0
        while j < n - 1:
            j += 1
            r = pts[j, 0]
            c = pts[j, 1]
            rmin, rmax = min(rmin, r), max(rmax, r)
            cmin, cmax = min(cmin, c), max(cmax, c)
            if max(rmax - rmin, cmax - cmin) >= section_size:
                break
        out[k, 0] = i0
        out[k, 1] = j
        out[k, 2] = rmin
        out[k, 3] = rmax
        out[k, 4] = cmin
        out[k, 5] = cmax
        k += 1
        i0 = j
    return out[:k]


_GOLDEN = np.int64(-7046029254386353131)  # 0x9E3779B97F4A7C15 as a signed 64-bit integer


@njit(cache=True)
def _remove_loops(flat):
    """The kept indices of :func:`remove_loops`. Each cell's last position in ``keep`` sits in
    an open-addressing table (nothing is ever deleted from it): a position is the cell's
    current one when it lies in the kept prefix and ``keep`` still holds that cell there (a
    cut, then later cells, reuse the positions), not numba's typed Dict with a deletion per
    cell of each loop cut, which was slower."""
    size = 1
    while size < 2 * flat.size:
        size *= 2
    mask = size - 1
    keys = np.full(size, -1, dtype=np.int64)
    vals = np.empty(size, dtype=np.int64)
    keep = np.empty(flat.size, dtype=np.int64)
    n = 0
    for i in range(flat.size):
        key = flat[i]
        h = (key * _GOLDEN) & mask  # Fibonacci hashing of the flat cell index (wraps)
        while keys[h] != -1 and keys[h] != key:
            h = (h + 1) & mask
        if keys[h] == key:
            p = vals[h]
            if p < n and flat[keep[p]] == key:  # a loop back to position p: cut it out
                n = p + 1
                continue
        keys[h] = key
        vals[h] = n
        keep[n] = i
        n += 1
    return keep[:n]


def remove_loops(cells: np.ndarray) -> np.ndarray:
    """Indices that keep ``cells`` simple: where a cell recurs, the loop between its first and
    its last visit is cut out (the path stays 8-connected and only gets shorter)."""
    cells = np.asarray(cells, dtype=np.int64)
    if len(cells) == 0:
        return np.zeros(0, dtype=np.int64)
    flat = cells[:, 0] * (int(cells[:, 1].max()) + 1) + cells[:, 1]
    return _remove_loops(flat)


def _snapped_joints(m: MapsStore, pts, secs: list, goal, rho: int, margin: int) -> list:
    """The cells where the sections ``secs`` (:func:`segment` of the restored points
    ``pts``) meet, from the start to ``goal``: each inner joint, a restored point, moved to the
    passable cell nearest it in both windows it joins (within ``rho``, else ``4 rho``, else
    ``margin`` cells); UnreachableGoalError where there is none."""
    joints = [(int(pts[i0][0]), int(pts[i0][1])) for i0, _, _ in secs] + [goal]
    # a passable joint is its own snap: it lies in both windows (each holds its section's
    # points); one lookup for all, not one a joint
    passable = m.values("passable", joints[1:-1])
    for k in range(1, len(secs)):
        if passable[k - 1]:
            continue
        wins = (secs[k - 1][2], secs[k][2])
        snapped = None
        for radius in (rho, 4 * rho, margin):
            snapped = _snap(m, joints[k], wins, radius)
            if snapped is not None:
                break
        if snapped is None:
            raise UnreachableGoalError(
                f"no passable cell near the joint {joints[k]} between "
                f"sections {k - 1} and {k}; try mcpc=False"
            )
        joints[k] = snapped
    return joints


def _snap(m: MapsStore, cell, wins, radius: int):
    """The passable cell nearest ``cell`` inside every window of ``wins`` (within
    ``radius``), or None."""
    r0 = max(max(w[0] for w in wins), cell[0] - radius)
    r1 = min(min(w[1] for w in wins), cell[0] + radius + 1)
    c0 = max(max(w[2] for w in wins), cell[1] - radius)
    c1 = min(min(w[3] for w in wins), cell[1] + radius + 1)
    if r0 >= r1 or c0 >= c1:
        return None
    return nearest_passable(m.window("passable", r0, r1, c0, c1), cell, (r0, c0))


def coarse_rho(m: MapsStore, rho=None) -> int:
    """The compression factor a mission on ``m`` uses: ``rho``, checked, or the map's default
    (:func:`default_parameters`)."""
    rho = (
        default_parameters(m.shape, m.cell_size)["rho"] if rho is None else PLANNING.rho.check(rho)
    )
    if rho > min(m.shape):
        raise InvalidParameterError(
            f"`rho` ({rho}) must not exceed the map's shorter side ({min(m.shape)} cells)"
        )
    return rho


def _grow(win, by: int, shape):
    r0, r1, c0, c1 = win
    by = max(by, 1)
    return max(r0 - by, 0), min(r1 + by, shape[0]), max(c0 - by, 0), min(c1 + by, shape[1])


def _coarse_endpoint(passable: np.ndarray, cell):
    r = min(cell[0], passable.shape[0] - 1)
    c = min(cell[1], passable.shape[1] - 1)
    if passable[r, c]:
        return r, c
    for radius in (1, 2, 4):
        r0, c0 = max(r - radius, 0), max(c - radius, 0)
        near = nearest_passable(
            passable[r0 : r + radius + 1, c0 : c + radius + 1], (r, c), (r0, c0)
        )
        if near is not None:
            return near
    return None
