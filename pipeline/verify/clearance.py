"""The independent clearance check on the maps: each point of a planned track against the
DEM store's grid points, read from the elevation layer alone (never the safety map the planner
used). A job records its least value as ``auv:min_clearance_m`` for a mission planned without a
flight (a flown mission is measured along what it flies: from the DEM file's own seabed,
:mod:`pipeline.verify.seabed`, or the flight's continuous seabed).
"""

from __future__ import annotations

import math

import numpy as np

from ..runtime.jit import njit
from ..store.maps_store import open_store
from ..trajectory import Trajectory


def clearances(maps, traj: Trajectory, radius_m: float) -> np.ndarray:
    """For each point of the trajectory, its 3-D distance to the nearest DEM grid point.

    Independent of the safety map: it reads the elevation layer only and measures, for every
    point of the track, its distance to every grid point within ``radius_m`` horizontally
    (farther grid points are farther than ``radius_m`` anyway); a point with no grid point that
    close gets ``inf``.
    """
    m = open_store(maps)
    out = np.full(len(traj.cells), np.inf)
    if len(traj.cells) == 0:
        return out
    a = m.cell_size
    r = int(math.ceil(radius_m / a))
    off = np.arange(-r, r + 1)
    dr, dc = np.meshgrid(off, off, indexing="ij")
    h2 = (a * a) * (dr**2 + dc**2).ravel()
    keep = h2 <= radius_m * radius_m
    dr, dc, h2 = dr.ravel()[keep], dc.ravel()[keep], h2[keep]
    rows, cols = m.shape
    cells = traj.cells
    z = traj.points[:, 2].astype(np.float64)
    for k in range(0, len(cells), 512):
        cc, zz = cells[k : k + 512], z[k : k + 512]
        r0, r1 = max(int(cc[:, 0].min()) - r, 0), min(int(cc[:, 0].max()) + r + 1, rows)
        c0, c1 = max(int(cc[:, 1].min()) - r, 0), min(int(cc[:, 1].max()) + r + 1, cols)
        elev = m.window("elevation", r0, r1, c0, c1)
        rc = np.ascontiguousarray(cc, dtype=np.int64)
        out[k : k + 512] = _nearest_grid_point(rc, zz, elev, r0, c0, dr, dc, h2, rows, cols)
    return out


@njit(nogil=True, cache=True)
def _nearest_grid_point(cells, z, elev, r0, c0, dr, dc, h2, rows, cols):
    """For each cell ``(row, col)`` with height ``z``: the 3-D distance to the nearest grid
    point among its offsets ``(dr, dc)`` (squared horizontal distances ``h2``) inside the map;
    ``elev`` is the elevation window whose corner is ``(r0, c0)``; no-data is skipped, and a
    cell with no grid point gets ``inf``."""
    out = np.empty(cells.shape[0])
    for i in range(cells.shape[0]):
        best = np.inf
        for k in range(dr.shape[0]):
            r = cells[i, 0] + dr[k]
            c = cells[i, 1] + dc[k]
            if r < 0 or r >= rows or c < 0 or c >= cols:
                continue
            d = z[i] - np.float64(elev[r - r0, c - c0])
            d2 = h2[k] + d * d
            if d2 < best:  # False for NaN (no-data)
                best = d2
        out[i] = math.sqrt(best)
    return out


def min_clearance(maps, traj: Trajectory, radius_m: float) -> float:
    """The smallest 3-D distance from the trajectory's points to the DEM's grid points
    (:func:`clearances`); ``inf`` when no grid point is within ``radius_m``, NaN for an empty
    track."""
    if len(traj.cells) == 0:
        return math.nan
    return float(clearances(maps, traj, radius_m).min())
