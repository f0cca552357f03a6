"""Clearance from a DEM file's own seabed: the bilinear surface through the file's grid points,
in its own coordinates (lon/lat or projected), never a resample of it (docs/method.md
section 1). :class:`SourceSeabed` opens the file once; :meth:`SourceSeabed.clearances` gives
each point's clearance, by branch and bound over the grid's cells to a stated tolerance.

Distances are ground metres: around each group of points, one source row and one column are
measured on the ellipsoid (pyproj's Geod) as metres north and east, so a lon/lat grid's cells
of a tenth of a degree are the metres they are at that latitude; the points themselves come
from the mission's own map coordinates through pyproj.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..exceptions import InvalidDEMError
from ..methods import METHODS
from ..runtime.jit import njit

# a clearance is found to this many metres (the least over a cell's parts is refined until
# no part could come closer by more)
TOLERANCE_M = 1e-3


# points measured together: one window of the file read and one local scale for them
GROUP = 256

# the points' whole window of the file is read at once up to this many cells (else a window a
# group); a grid read lazily costs tens of milliseconds a read
WINDOW_CELLS = 2**22

# with ``least_only``, the search of every point is bounded from the start by the least height
# of a point above the seabed under it plus this margin (metres; above the tolerance, so that
# the point whose clearance is that height is measured)
MARGIN_M = 1.0


@dataclass
class SourceSeabed:
    """A DEM file's grid as the file holds it (metres, positive up; NaN no-data), read a
    window at a time. ``path`` is any file :func:`pipeline.open_dem` reads (its ``variable``
    and ``uncertainty_k`` the same way); ``values`` is the lazy grid in the file's own
    coordinates, ``crs`` its CRS (None: it has none, and its coordinates are the map's)."""

    path: Path
    values: object
    crs: object
    # the last whole window read (:meth:`_window`; all of a file of at most WINDOW_CELLS): a
    # mission's track and route, and the checks of its rounds, lie in the same window of it
    _last: object = field(default=None, init=False, repr=False, compare=False)
    _from_map: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @classmethod
    def open(cls, path, *, variable=None, uncertainty_k=None, uncertainty=None) -> SourceSeabed:
        from ..dem.canonical import source_grid
        from ..dem.open import read_source

        path = Path(path)
        raw = read_source(path, variable, uncertainty_k, uncertainty)
        values, crs = source_grid(raw, path)
        return cls(path, values, crs)

    def clearances(
        self,
        x,
        y,
        z,
        crs_wkt: str | None,
        radius: float,
        method: str = "spherical",
        *,
        least_only: bool = False,
    ) -> np.ndarray:
        """The clearance (metres) of each point ``x, y`` (the map CRS ``crs_wkt``), height
        ``z`` (metres, positive up) from this seabed: ``spherical``, the least 3-D distance
        to it (``inf`` beyond ``1.25 radius``, searched no farther); ``horizontal``, the
        height above its highest point within ``radius`` horizontally; ``vertical``, the
        height above it. Negative under the seabed; NaN where the point is off the grid or
        over no-data (nothing known to measure). ``least_only``: a point whose clearance is not
        below the least found before it, nor below the least height of a point above the seabed
        under it (plus :data:`MARGIN_M`), reads ``inf``, unmeasured: the least, and where it
        is, stay those of every point measured."""
        x, y, z = (np.asarray(v, dtype=np.float64).ravel() for v in (x, y, z))
        code = METHODS[method].code
        fi, fj = self._index(x, y, crs_wkt)
        reach = (1.25 * radius if code == 2 else radius) if code else 0.0
        si, sj = self._scales(fi, fj)
        window = self._window(fi, fj, reach, si, sj)
        pts = (fi, fj, z, si, sj)
        if not least_only or code == 0:
            return self._measure(pts, window, reach, radius, code, math.inf)
        # a point's clearance is at most its height above the seabed under it (the seabed
        # there is within reach; the highest within reach at least that high): the least is
        # below the least such height and a margin, and the search of every point bounded by it
        under = self._measure(pts, window, 0.0, radius, 0, math.inf)
        if np.isfinite(under).any():
            out = self._measure(
                pts, window, reach, radius, code, float(np.nanmin(under)) + MARGIN_M
            )
            if np.isfinite(out).any() or not np.isinf(out).any():
                return out
            # (every point below the bound is over no-data within its reach: measured in full)
        return self._measure(pts, window, reach, radius, code, math.inf)

    def _scales(self, fi, fj) -> tuple:
        """Ground metres per source row and per column at each point: those of its group of
        :data:`GROUP` points (:meth:`_scale` around their middle; NaN off the grid)."""
        si, sj = np.full(fi.size, np.nan), np.full(fi.size, np.nan)
        for g in range(0, fi.size, GROUP):
            sl = slice(g, g + GROUP)
            ok = np.isfinite(fi[sl]) & np.isfinite(fj[sl])
            if ok.any():
                si[sl], sj[sl] = self._scale(fi[sl][ok], fj[sl][ok])
        return si, sj

    def _window(self, fi, fj, reach: float, si, sj):
        """The points' whole window of the file, read once (or the last one read, where it
        holds it), when it is at most :data:`WINDOW_CELLS` cells: ``(array, r0, c0)``; else
        None (a window a group)."""
        bounds = self._bounds(fi, fj, reach, si, sj)
        if bounds is None:
            return None
        r0, r1, c0, c1 = bounds
        if (r1 - r0) * (c1 - c0) > WINDOW_CELLS:
            return None
        if _within(self._last, r0, r1, c0, c1) is None:
            ny, nx = self.values.shape
            if ny * nx <= WINDOW_CELLS:  # a small file: all of it, once
                r0, r1, c0, c1 = 0, ny, 0, nx
            win = np.ascontiguousarray(self.values[r0:r1, c0:c1].values, dtype=np.float64)
            self._last = (win, r0, c0)
        return self._last

    def _bounds(self, fi, fj, reach: float, si, sj):
        """The rows ``r0:r1`` and columns ``c0:c1`` of the file within ``reach`` (metres) of
        the points at fractional rows ``fi`` and columns ``fj`` (``si``, ``sj`` metres per row
        and column at each), and a cell more; None where no point is on the grid or fewer than
        two rows or columns."""
        ok = np.isfinite(fi) & np.isfinite(fj)
        if not ok.any():
            return None
        fi, fj, di, dj = fi[ok], fj[ok], reach / si[ok], reach / sj[ok]
        ny, nx = self.values.shape
        r0 = max(int(math.floor(np.min(fi - di))) - 1, 0)
        r1 = min(int(math.ceil(np.max(fi + di))) + 2, ny)
        c0 = max(int(math.floor(np.min(fj - dj))) - 1, 0)
        c1 = min(int(math.ceil(np.max(fj + dj))) + 2, nx)
        if r1 - r0 < 2 or c1 - c0 < 2:
            return None
        return r0, r1, c0, c1

    def _measure(self, pts, window, reach, radius, code, below) -> np.ndarray:
        """:meth:`clearances` of the points ``pts`` (fractional rows and columns of the file,
        heights, metres per row and column at each), :data:`GROUP` at a time, each searched for
        less than ``below`` and than the least before it (``inf`` where none is found) but
        where ``below`` is ``inf``."""
        fi, fj, z, si, sj = pts
        out = np.full(fi.size, np.nan)
        ny, nx = self.values.shape
        bounded = math.isfinite(below)
        for g in range(0, fi.size, GROUP):
            sl = slice(g, g + GROUP)
            bounds = self._bounds(fi[sl], fj[sl], reach, si[sl], sj[sl])
            if bounds is None:
                continue
            r0, r1, c0, c1 = bounds
            part = _within(window, r0, r1, c0, c1)
            if part is None:
                part = self.values[r0:r1, c0:c1].values
            part = np.ascontiguousarray(part, dtype=np.float64)
            out[sl] = _clearances(
                part, r0, c0, ny, nx, fi[sl], fj[sl], z[sl], si[sl], sj[sl], radius, code,
                TOLERANCE_M, below,
            )  # fmt: skip
            if bounded:
                got = out[sl][np.isfinite(out[sl])]
                if got.size:
                    below = min(below, float(got.min()))
        return out

    @functools.cached_property
    def _to_lonlat(self):
        """The file's coordinates to WGS84 longitude and latitude (made once: pyproj takes
        milliseconds to make a transformer, and the scale is measured every group)."""
        from pyproj import Transformer

        return Transformer.from_crs(self.crs, "EPSG:4326", always_xy=True)

    def cell_m(self) -> float:
        """The smaller side of the grid's cells in ground metres, at its middle."""
        ny, nx = self.values.shape
        return min(self._scale(np.array([ny / 2]), np.array([nx / 2])))

    def _index(self, x, y, crs_wkt):
        """The file's fractional rows and columns of the map points ``x, y``."""
        from ..dem.reproject import GridAxes

        sx, sy = x, y
        if self.crs is not None and crs_wkt:
            from pyproj import CRS, Transformer

            tr = self._from_map.get(crs_wkt)
            if tr is None:  # made once a map (pyproj takes milliseconds to make one)
                tr = Transformer.from_crs(CRS.from_wkt(crs_wkt), self.crs, always_xy=True)
                self._from_map[crs_wkt] = tr
            sx, sy = tr.transform(x, y)
            if self.crs.is_geographic:
                lon = np.asarray(self.values["x"].values, dtype=np.float64)
                sx = np.asarray(sx)
                if lon.max() > 180.0:  # a grid of longitudes 0..360
                    sx = np.where(sx < lon.min(), sx + 360.0, sx)
        axes = GridAxes(self.values)
        fi, fj = axes.rows(np.asarray(sy)), axes.cols(np.asarray(sx))
        ny, nx = self.values.shape
        off = (fi < -0.5) | (fi > ny - 0.5) | (fj < -0.5) | (fj > nx - 0.5)
        fi, fj = np.where(off, np.nan, fi), np.where(off, np.nan, fj)
        return fi, fj

    def _scale(self, gi, gj) -> tuple[float, float]:
        """Ground metres per source row and per column around the points (their middle)."""
        ci, cj = float(np.median(gi)), float(np.median(gj))
        yv = np.asarray(self.values["y"].values, dtype=np.float64)
        xv = np.asarray(self.values["x"].values, dtype=np.float64)
        i = min(max(int(round(ci)), 0), len(yv) - 2)
        j = min(max(int(round(cj)), 0), len(xv) - 2)
        dy, dx = abs(yv[i + 1] - yv[i]), abs(xv[j + 1] - xv[j])
        if self.crs is None:
            return dy, dx
        px = np.array([xv[j], xv[j], xv[j + 1]])
        py = np.array([yv[i], yv[i + 1], yv[i]])
        from pyproj import Geod

        lon, lat = self._to_lonlat.transform(px, py)
        geod = Geod(ellps="WGS84")
        _, _, d_row = geod.inv(lon[0], lat[0], lon[1], lat[1])
        _, _, d_col = geod.inv(lon[0], lat[0], lon[2], lat[2])
        if not (d_row > 0 and d_col > 0):
            raise InvalidDEMError(f"DEM file {self.path}: cannot measure its cells in metres")
        return float(d_row), float(d_col)


def _within(window, r0: int, r1: int, c0: int, c1: int):
    """Rows ``r0:r1`` and columns ``c0:c1`` of the file from ``window`` (``(array, first row,
    first column)`` or None), or None where it does not hold them all (a group's own scale may
    reach farther than the window's, measured at the points' middle)."""
    if window is None:
        return None
    win, w0, v0 = window
    if r0 < w0 or c0 < v0 or r1 > w0 + win.shape[0] or c1 > v0 + win.shape[1]:
        return None
    return win[r0 - w0 : r1 - w0, c0 - v0 : c1 - v0]


@njit(cache=True, nogil=True)
def _clearances(win, r0, c0, ny, nx, fi, fj, z, ssi, ssj, radius, method, tol, below):
    """:meth:`SourceSeabed.clearances` for one group: ``win`` the file's window from row
    ``r0``, column ``c0``; ``ssi``, ``ssj`` metres per row and column at each point (NaN off
    the grid). A point whose clearance is not below ``below`` and the least before it in the
    group reads ``inf`` (``below`` inf: every point measured)."""
    n = fi.size
    out = np.full(n, np.nan)
    h, w = win.shape
    stack = np.empty((256, 4))
    bounded = below < np.inf
    for s in range(n):
        p = fi[s]
        q = fj[s]
        if p != p or q != q:
            continue
        si = ssi[s]
        sj = ssj[s]
        p = min(max(p, 0.0), ny - 1.0)  # (the outer half cells hold their edge values)
        q = min(max(q, 0.0), nx - 1.0)
        under = _value(win, r0, c0, p, q)
        if method == 0 or under != under or z[s] < under:
            out[s] = z[s] - under
            continue
        if method == 2:
            far = 1.25 * radius
            best = min(z[s] - under, far)  # (the seabed under the point is at that distance)
            if bounded:
                best = min(best, below)
        else:
            far = radius
            best = under  # the highest seabed within reach, at least that under the point
            if bounded:
                best = max(best, z[s] - below)
        i0 = max(int(math.floor(p - far / si)), r0, 0)
        i1 = min(int(math.floor(p + far / si)), r0 + h - 2, ny - 2)
        j0 = max(int(math.floor(q - far / sj)), c0, 0)
        j1 = min(int(math.floor(q + far / sj)), c0 + w - 2, nx - 2)
        bad = False
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                z00 = win[i - r0, j - c0]
                z01 = win[i - r0, j + 1 - c0]
                z10 = win[i + 1 - r0, j - c0]
                z11 = win[i + 1 - r0, j + 1 - c0]
                if z00 != z00 or z01 != z01 or z10 != z10 or z11 != z11:
                    if _box_d2(p, q, i, i + 1.0, j, j + 1.0, si, sj) < far * far:
                        bad = True  # no-data within reach: nothing known there
                    continue
                best = _cell(
                    z00, z01, z10, z11, i, j, p, q, z[s], si, sj, far, method, best, tol, stack
                )
        if bad:
            out[s] = np.nan
        else:
            c = best if method == 2 else z[s] - best
            if bounded:
                if c >= below:
                    c = np.inf  # nothing below the least so far: unmeasured
                else:
                    below = c
            out[s] = c
    return out


@njit(cache=True)
def _value(win, r0, c0, p, q):
    i = min(int(math.floor(p)), r0 + win.shape[0] - 2)
    j = min(int(math.floor(q)), c0 + win.shape[1] - 2)
    u = p - i
    v = q - j
    i -= r0
    j -= c0
    return (win[i, j] * (1 - v) + win[i, j + 1] * v) * (1 - u) + (
        win[i + 1, j] * (1 - v) + win[i + 1, j + 1] * v
    ) * u


@njit(cache=True)
def _box_d2(p, q, a0, a1, b0, b1, si, sj):
    """Squared ground distance from the point (row ``p``, column ``q``) to the rectangle of
    rows ``a0..a1`` and columns ``b0..b1``."""
    du = max(0.0, a0 - p, p - a1) * si
    dv = max(0.0, b0 - q, q - b1) * sj
    return du * du + dv * dv


@njit(cache=True)
def _bil(z00, z01, z10, z11, u, v):
    return (z00 * (1 - v) + z01 * v) * (1 - u) + (z10 * (1 - v) + z11 * v) * u


@njit(cache=True)
def _cell(z00, z01, z10, z11, i, j, p, q, h, si, sj, far, method, best, tol, stack):
    """``best`` improved by the cell ``(i, j)``: spherical, the least 3-D distance from the
    point to its bilinear surface (``best`` the least so far); horizontal, its highest within
    ``far`` (``best`` the highest so far). Branch and bound on the cell's parts: a part's
    bilinear surface lies within its corners' range, so the distance to the box of its rows,
    columns and that range bounds it below (its highest corner, above); a part is halved until
    it cannot beat ``best`` by more than ``tol``; its corners are points of the surface."""
    stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3] = 0.0, 1.0, 0.0, 1.0
    top = 1
    lim = far * far
    while top > 0:
        top -= 1
        u0, u1, v0, v1 = stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3]
        a = _bil(z00, z01, z10, z11, u0, v0)
        b = _bil(z00, z01, z10, z11, u0, v1)
        c = _bil(z00, z01, z10, z11, u1, v0)
        d = _bil(z00, z01, z10, z11, u1, v1)
        lo = min(a, b, c, d)
        hi = max(a, b, c, d)
        e2 = _box_d2(p, q, i + u0, i + u1, j + v0, j + v1, si, sj)
        if e2 >= lim:
            continue
        gap = max(0.0, lo - h, h - hi)
        if method == 2:
            if math.sqrt(e2 + gap * gap) >= best - tol:
                continue
            # the corners are points of the surface: distances reached
            for uu, vv, zz in ((u0, v0, a), (u0, v1, b), (u1, v0, c), (u1, v1, d)):
                du = (i + uu - p) * si
                dv = (j + vv - q) * sj
                best = min(best, math.sqrt(du * du + dv * dv + (h - zz) * (h - zz)))
        else:
            if hi <= best + tol:
                continue
            for uu, vv, zz in ((u0, v0, a), (u0, v1, b), (u1, v0, c), (u1, v1, d)):
                du = (i + uu - p) * si
                dv = (j + vv - q) * sj
                if du * du + dv * dv < lim:
                    best = max(best, zz)
            if hi <= best + tol:
                continue
        if top + 4 > stack.shape[0] or (u1 - u0) * max(si, sj) < tol:
            # a part smaller than the tolerance: its bound counts (on the safe side)
            if method == 2:
                best = min(best, math.sqrt(e2 + gap * gap))
            else:
                best = max(best, hi)
            continue
        um = 0.5 * (u0 + u1)
        vm = 0.5 * (v0 + v1)
        stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3] = u0, um, v0, vm
        stack[top + 1, 0], stack[top + 1, 1], stack[top + 1, 2], stack[top + 1, 3] = u0, um, vm, v1
        stack[top + 2, 0], stack[top + 2, 1], stack[top + 2, 2], stack[top + 2, 3] = um, u1, v0, vm
        stack[top + 3, 0], stack[top + 3, 1], stack[top + 3, 2], stack[top + 3, 3] = um, u1, vm, v1
        top += 4
    return best
