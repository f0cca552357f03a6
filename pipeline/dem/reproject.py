"""Exact reprojection of a DEM (docs/method.md): each target cell centre transformed by pyproj
and the source grid sampled bilinearly there (a lon/lat grid onto an azimuthal equidistant
projection centred on it), and resampling to square cells.
"""

from __future__ import annotations

import functools
import logging
import math
from pathlib import Path

import dask
import dask.array as da
import numpy as np
import xarray as xr

from ..exceptions import InvalidDEMError, notice
from ..params import DEFAULT_CHUNK, chunks2d
from ..runtime.jit import njit

log = logging.getLogger(__name__)


def _reproject_geographic(
    values: xr.DataArray,
    path: Path,
    crs,
    resolution: float | None = None,
    chunks=None,
    bounds: tuple | None = None,
):
    """Reproject a lon/lat grid to an azimuthal equidistant projection centred on the grid
    (:func:`warp`: the upper envelope of its bilinear surface), chunk by chunk when ``values``
    is a dask array. The output grid is rasterio's default one for that projection and cell,
    over ``bounds`` (lon, lat) when a region was asked for, else over the grid's own cells."""
    from pyproj import CRS
    from rasterio.warp import calculate_default_transform

    src_crs = crs if crs is not None else CRS.from_epsg(4326)
    lon = np.asarray(values["x"].values, dtype=np.float64)
    lat = np.asarray(values["y"].values, dtype=np.float64)
    if lon.min() >= 180.0:
        values = values.assign_coords(x=lon - 360.0)
        lon = lon - 360.0
        if bounds is not None:
            bounds = (bounds[0] - 360.0, bounds[1], bounds[2] - 360.0, bounds[3])
    a = resolution or natural_cell(values)
    dlon, dlat = _mean_step(lon), _mean_step(lat)
    cover = (lon.min() - dlon / 2, lat.min() - dlat / 2, lon.max() + dlon / 2, lat.max() + dlat / 2)
    if bounds is not None:  # the region asked for, where the grid covers it
        cover = (
            max(cover[0], bounds[0]),
            max(cover[1], bounds[1]),
            min(cover[2], bounds[2]),
            min(cover[3], bounds[3]),
        )
    lon0, lat0 = 0.5 * (cover[0] + cover[2]), 0.5 * (cover[1] + cover[3])
    dst = CRS.from_proj4(f"+proj=aeqd +lat_0={lat0:.6f} +lon_0={lon0:.6f} +datum=WGS84 +units=m")
    notice(
        log,
        "DEM %s is in geographic coordinates: reprojecting to a local azimuthal "
        "equidistant projection centred at (%.4f E, %.4f N) with %.3g m cells",
        path,
        lon0,
        lat0,
        a,
    )
    transform, width, height = calculate_default_transform(
        src_crs,
        dst,
        values.sizes["x"],
        values.sizes["y"],
        left=cover[0],
        bottom=cover[1],
        right=cover[2],
        top=cover[3],
        resolution=a,
    )
    lazy = isinstance(values.data, da.Array)
    side = chunks2d(chunks if chunks is not None else DEFAULT_CHUNK, (height, width))
    out, stats = warp(values, src_crs, dst, transform, (height, width), side if lazy else None)
    return out, dst, stats


METRES_PER_DEGREE = 111_320.0


def natural_cell(values: xr.DataArray) -> float:
    """The square cell (metres, three figures) a lon/lat grid is reprojected at by default:
    the geometric mean of its cells' sides at its mean latitude."""
    lat = np.asarray(values["y"].values, dtype=np.float64)
    return lonlat_cell(_mean_step(values["x"].values), _mean_step(lat), float(lat.mean()))


def lonlat_cell(dlon: float, dlat: float, lat: float) -> float:
    """:func:`natural_cell` of a grid of steps ``dlon`` by ``dlat`` degrees at latitude
    ``lat`` (what a file's header tells, before its values are read)."""
    dx_m = abs(dlon) * METRES_PER_DEGREE * math.cos(math.radians(lat))
    return float(f"{math.sqrt(dx_m * (abs(dlat) * METRES_PER_DEGREE)):.3g}")


def degree_cell_metres(values: xr.DataArray) -> tuple[float, float]:
    """The sides (metres, east and north) of a lon/lat grid's cells at its mean latitude."""
    lon = np.asarray(values["x"].values, dtype=np.float64)
    lat = np.asarray(values["y"].values, dtype=np.float64)
    k = math.cos(math.radians(float(lat.mean())))
    return _mean_step(lon) * METRES_PER_DEGREE * k, _mean_step(lat) * METRES_PER_DEGREE


def _mean_step(c) -> float:
    """The mean step (its size) of a monotonic coordinate axis."""
    c = np.asarray(c, dtype=np.float64)
    return float(abs(c[-1] - c[0]) / max(c.size - 1, 1))


def exact_warp(values: xr.DataArray, src_crs, dst_crs, transform, shape, chunks=None):
    """``values`` sampled bilinearly at the cell centres of the grid ``transform``, ``shape``
    of ``dst_crs`` (:func:`warp` with ``upper=False``): the exact resample, for a display or
    a comparison; planning takes the upper envelope."""
    return warp(values, src_crs, dst_crs, transform, shape, chunks, upper=False)[0]


def warp(values: xr.DataArray, src_crs, dst_crs, transform, shape, chunks=None, *, upper=True):
    """``values`` (dims ``(y, x)`` on a grid of ``src_crs``, its axes monotonic, evenly spaced
    or not) onto the cell centres of the grid ``transform``, ``shape`` of ``dst_crs``; with
    ``src_crs`` None the two grids share their coordinates (a resample, no reprojection).

    Each target centre is transformed exactly by pyproj (not GDAL's approximate transformer,
    whose error of up to an eighth of a source cell moves terrain by tens of metres on coarse
    grids) into the source grid's fractional rows and columns. ``upper`` (planning): each
    target node takes the highest value of the source's bilinear surface over the square of
    half-side one target cell around it (the highest over each of the four target cells that
    make it: the box of the source rows and columns the cell's corners reach), so that the
    target's own bilinear surface lies on or above the source's everywhere (docs/method.md
    section 1); else the source's bilinear value at the node. The source's cells are areas:
    its outer half cells hold their edge points' values; a node beyond them is NaN (no
    source), as is one whose surface weighs a NaN source point.

    Returns the DataArray and the figures of the construction: a float64 array ``(sum of the
    raise over the nodes, nodes counted, greatest raise, nodes beyond the source)``, where the
    raise is the node's value less the source's bilinear value there (0 without ``upper``);
    with ``chunks``, a list of one delayed such row per tile (:func:`combine_stats`). With
    ``chunks`` (a (rows, cols) side) each block reads only the source window it needs (memory
    bounded by the block) and equals the in-memory result (each node is computed alone)."""
    from pyproj import Transformer

    tr = definition = None
    if src_crs is not None:  # the exact operation as a PROJ pipeline (made once per process)
        definition = Transformer.from_crs(dst_crs, src_crs, always_xy=True).definition
        tr = _pipeline(definition)
    height, width = shape
    a = abs(transform.a)
    xs = transform.c + (np.arange(width) + 0.5) * transform.a
    ys = transform.f + (np.arange(height) + 0.5) * transform.e
    grid = GridAxes(values)
    eps = UPPER_SLACK if tr is not None else 1e-9

    block = functools.partial(
        _warp_block, definition=definition, step=(transform.e, transform.a), grid=grid,
        upper=upper, eps=eps,
    )  # fmt: skip

    if chunks is None:
        data, stats = block(values.values, ys, xs, (0, 0))
        return _named(data, ys, xs, values), stats
    rows, parts = [], []
    for i0 in range(0, height, chunks[0]):
        row = []
        for j0 in range(0, width, chunks[1]):
            y, x = ys[i0 : i0 + chunks[0]], xs[j0 : j0 + chunks[1]]
            # a block whose source window is large (a coarse target) is warped in tiles
            window = _source_window(tr, x, y, grid, a)
            (r0, r1), (c0, c1) = window
            k = max(1, math.ceil(math.sqrt((r1 - r0) * (c1 - c0) / WARP_WINDOW_CELLS)))
            ty, tx = max(1, -(-len(y) // k)), max(1, -(-len(x) // k))
            tiles = []
            for a0 in range(0, len(y), ty):
                trow = []
                for b0 in range(0, len(x), tx):
                    yy, xx = y[a0 : a0 + ty], x[b0 : b0 + tx]
                    (r0, r1), (c0, c1) = window if k == 1 else _source_window(tr, xx, yy, grid, a)
                    src = values.data[max(r0, 0) : max(r1, 1), max(c0, 0) : max(c1, 1)]
                    # the window as one block, its tasks kept as they are (not fused into
                    # new ones, which would read a source chunk once for each window)
                    src = src.rechunk(src.shape).to_delayed(optimize_graph=False)[0, 0]
                    # (not pure: tokenizing the partial pickles its grid axes, 0.2 s a grid)
                    pair = dask.delayed(block, pure=False, nout=2)(src, yy, xx, (r0, c0))
                    trow.append(da.from_delayed(pair[0], (len(yy), len(xx)), dtype=np.float32))
                    parts.append(pair[1])
                tiles.append(trow)
            piece = da.block(tiles)
            row.append(piece if k == 1 else piece.rechunk(piece.shape))
        rows.append(row)
    return _named(da.block(rows), ys, xs, values), parts


def _warp_block(src, y, x, off, *, definition, step, grid, upper, eps):
    """One block of :func:`warp`: the source window ``src`` (its first point at source row and
    column ``off``) onto the nodes ``y`` by ``x``. At module level, so that a worker imports it
    and its kernel (compiled once, cached on disk) rather than being sent a copy of the kernel
    to compile again in every process of every job."""
    tr = _pipeline(definition) if definition is not None else None
    # the nodes one target cell around the block too: the squares of its edge nodes
    yp = np.concatenate(([y[0] - step[0]], y, [y[-1] + step[0]]))
    xp = np.concatenate(([x[0] - step[1]], x, [x[-1] + step[1]]))
    lfi, lfj, fy, fx = _lattice(tr, xp, yp, grid)
    src = np.ascontiguousarray(src, dtype=np.float32)
    return _warp_kernel(src, off[0], off[1], grid.ny, grid.nx, lfi, lfj, fy, fx, upper, eps)


def _named(data, ys, xs, values) -> xr.DataArray:
    return xr.DataArray(data, dims=("y", "x"), coords={"y": ys, "x": xs}, name=values.name)


def combine_stats(parts) -> np.ndarray:
    """The figures of a warp's blocks (rows of :func:`warp`'s four) as one row."""
    p = np.asarray(parts, dtype=np.float64).reshape(-1, 4)
    if not len(p):
        return np.zeros(4)
    return np.array([p[:, 0].sum(), p[:, 1].sum(), p[:, 2].max(), p[:, 3].sum()])


# a block whose source window holds more cells than this is warped in tiles, each reading its
# own window (a target a tenth as fine as its source would otherwise read 100 source cells for
# every cell it writes at once)
WARP_WINDOW_CELLS = 2048 * 2048


# the slack (source cells) added each way to a target cell's box of source rows and columns
# when the grids are reprojected: the box is that of its four corners' transforms (each within
# WARP_TOLERANCE of exact), and the cell's sides between them bend from straight lines by far
# less
UPPER_SLACK = 1e-3


class GridAxes:
    """A source grid's axes as fractional rows and columns: exact steps for an evenly spaced
    axis, piecewise linear for an uneven one (the bilinear surface of a rectilinear grid is
    bilinear in its rows and columns), extrapolated with the end steps."""

    def __init__(self, values: xr.DataArray):
        self.y = np.asarray(values["y"].values, dtype=np.float64)
        self.x = np.asarray(values["x"].values, dtype=np.float64)
        self.ny, self.nx = len(self.y), len(self.x)
        self.even_y, self.even_x = _step(values, "y", "DEM")[1], _step(values, "x", "DEM")[1]

    def rows(self, v):
        return _index(self.y, v, self.even_y)

    def cols(self, v):
        return _index(self.x, v, self.even_x)


def _index(c: np.ndarray, v, even: bool):
    """The fractional index of the coordinates ``v`` on the monotonic axis ``c``."""
    v = np.asarray(v, dtype=np.float64)
    n = c.size
    if even:
        return (v - c[0]) / ((c[-1] - c[0]) / (n - 1))
    if c[0] > c[-1]:
        return (n - 1) - _index(c[::-1], v, False)
    out = np.interp(v, c, np.arange(n, dtype=np.float64))
    lo, hi = v < c[0], v > c[-1]
    out = np.where(lo, (v - c[0]) / (c[1] - c[0]), out)
    return np.where(hi, (n - 1) + (v - c[-1]) / (c[-1] - c[-2]), out)


# the source coordinates of a block's cell centres: transformed exactly on a lattice of every
# WARP_LATTICE-th centre and interpolated bilinearly between (16^2 times fewer transforms), where
# the lattice cells' midpoints, transformed exactly too, are within WARP_TOLERANCE source cells
# of the interpolation (else every centre of the block is transformed)
WARP_LATTICE = 16


WARP_TOLERANCE = 2.5e-4


def _lattice(tr, x, y, grid: GridAxes) -> tuple:
    """The source rows and columns of the centres ``x`` by ``y`` as a lattice and the
    fractional lattice row of each ``y`` and column of each ``x``: every ``WARP_LATTICE``-th
    centre when interpolating between them is close enough, else all."""
    k = WARP_LATTICE
    every = np.arange(len(y), dtype=np.float64), np.arange(len(x), dtype=np.float64)
    if len(x) > 2 * k and len(y) > 2 * k:
        ix = np.unique(np.append(np.arange(0, len(x), k), len(x) - 1))
        iy = np.unique(np.append(np.arange(0, len(y), k), len(y) - 1))
        li, lj = _transform_grid(tr, x[ix], y[iy], grid)
        # the midpoints of the lattice cells: exact against interpolated
        ci, cj = _transform_grid(
            tr, 0.5 * (x[ix[:-1]] + x[ix[1:]]), 0.5 * (y[iy[:-1]] + y[iy[1:]]), grid
        )
        ii = 0.25 * (li[:-1, :-1] + li[1:, :-1] + li[:-1, 1:] + li[1:, 1:])
        jj = 0.25 * (lj[:-1, :-1] + lj[1:, :-1] + lj[:-1, 1:] + lj[1:, 1:])
        with np.errstate(invalid="ignore"):
            dev = max(np.max(np.abs(ii - ci)), np.max(np.abs(jj - cj)))
        if dev <= WARP_TOLERANCE:  # (not NaN: every lattice point in the projection's domain)
            fy = np.interp(every[0], iy, np.arange(len(iy), dtype=np.float64))
            fx = np.interp(every[1], ix, np.arange(len(ix), dtype=np.float64))
            return li, lj, fy, fx
    li, lj = _transform_grid(tr, x, y, grid)
    return li, lj, *every


def _transform_grid(tr, x, y, grid: GridAxes) -> tuple:
    """The source rows and columns of the centres ``x`` by ``y`` (``tr`` None: the same
    coordinates)."""
    xx, yy = np.meshgrid(x, y)
    if tr is not None:
        xx, yy = tr.transform(xx, yy)
    return grid.rows(yy), grid.cols(xx)


@njit(cache=True, nogil=True)
def _warp_kernel(src, r0, c0, ny, nx, li, lj, fy, fx, upper, eps):
    """The warp of the source window ``src`` (its first point source row ``r0``, column
    ``c0``; the source grid ``ny`` x ``nx``) onto the nodes whose source rows and columns are
    interpolated bilinearly in the lattice ``li``, ``lj`` at fractional rows ``fy`` by columns
    ``fx``: the nodes of a block and one ring around it, whose values are not returned.
    ``upper``: a node's value is the highest of the source's bilinear surface over its four
    dual cells (:func:`_dual_row`; ``eps`` each way, clipped to the source's points: its outer
    half cells hold their edge values); else the bilinear value at the node. NaN
    beyond the outer half cells, where a point with a weight is NaN, or (upper) where a
    neighbour has no source coordinates. Returns the block and its figures (:func:`warp`)."""
    h = fy.size - 2
    w = fx.size - 2
    # the nodes' source rows and columns, three rows of them at a time (row k at k % 3),
    # and the highest over each dual cell (between four nodes), two rows at a time
    pi = np.empty((3, fx.size))
    pj = np.empty((3, fx.size))
    cell = np.empty((2, w + 1))
    _lattice_row(li, lj, fy[0], fx, pi[0], pj[0])
    _lattice_row(li, lj, fy[1], fx, pi[1], pj[1])
    if upper:
        _dual_row(src, r0, c0, ny, nx, pi[0], pi[1], pj[0], pj[1], eps, cell[0])
    out = np.empty((h, w), dtype=np.float32)
    stats = np.zeros(4)
    for r in range(h):
        _lattice_row(li, lj, fy[r + 2], fx, pi[(r + 2) % 3], pj[(r + 2) % 3])
        node_i, node_j = pi[(r + 1) % 3], pj[(r + 1) % 3]
        if upper:
            ri, rj = pi[(r + 2) % 3], pj[(r + 2) % 3]
            _dual_row(src, r0, c0, ny, nx, node_i, ri, node_j, rj, eps, cell[(r + 1) % 2])
        above = cell[r % 2]
        below = cell[(r + 1) % 2]
        for c in range(w):
            fi = node_i[c + 1]
            fj = node_j[c + 1]
            # the source's cells are areas: its outer half cells hold their points' values
            if not (-0.5 <= fi <= ny - 0.5 and -0.5 <= fj <= nx - 0.5):
                out[r, c] = np.nan  # (NaN coordinates too)
                stats[3] += 1
                continue
            base = _bilinear_at(src, r0, c0, ny, nx, fi, fj)
            if not upper or base != base:
                out[r, c] = base
                continue
            # the four dual cells around the node: the square of half-side one cell
            a = above[c]
            b = below[c]
            d = above[c + 1]
            e = below[c + 1]
            if a != a or b != b or d != d or e != e:
                out[r, c] = np.nan
                continue
            top = max(max(a, b), max(d, e))
            # the value stored is float32: rounded up, never below the highest
            v32 = np.float32(top)
            if np.float64(v32) < top:
                v32 = np.nextafter(v32, np.float32(np.inf))
            out[r, c] = v32
            raise_m = np.float64(v32) - base
            stats[0] += raise_m
            stats[1] += 1
            stats[2] = max(stats[2], raise_m)
    return out, stats


@njit(cache=True)
def _lattice_row(li, lj, fy, fx, pi, pj):
    """The source rows ``pi`` and columns ``pj`` of a row of nodes: the lattice ``li``,
    ``lj`` interpolated bilinearly at fractional row ``fy`` and columns ``fx``."""
    n_i, n_j = li.shape
    a0 = min(int(math.floor(fy)), n_i - 1)
    ta = fy - a0
    a1 = min(a0 + 1, n_i - 1)
    for c in range(fx.size):
        b0 = min(int(math.floor(fx[c])), n_j - 1)
        tb = fx[c] - b0
        b1 = min(b0 + 1, n_j - 1)
        pi[c] = (li[a0, b0] * (1 - tb) + li[a0, b1] * tb) * (1 - ta) + (
            li[a1, b0] * (1 - tb) + li[a1, b1] * tb
        ) * ta
        pj[c] = (lj[a0, b0] * (1 - tb) + lj[a0, b1] * tb) * (1 - ta) + (
            lj[a1, b0] * (1 - tb) + lj[a1, b1] * tb
        ) * ta


@njit(cache=True)
def _dual_row(src, r0, c0, ny, nx, pi0, pi1, pj0, pj1, eps, out):
    """The highest of the source's bilinear surface over each dual cell between two rows of
    nodes (source rows ``pi0``, ``pi1``, columns ``pj0``, ``pj1``): over the box of its four
    corners, ``eps`` each way (NaN where a corner has no source coordinates)."""
    for c in range(out.size):
        u0 = pi0[c]
        u1 = pi1[c]
        u2 = pi0[c + 1]
        u3 = pi1[c + 1]
        v0 = pj0[c]
        v1 = pj1[c]
        v2 = pj0[c + 1]
        v3 = pj1[c + 1]
        lo_i = min(min(u0, u1), min(u2, u3)) - eps
        hi_i = max(max(u0, u1), max(u2, u3)) + eps
        lo_j = min(min(v0, v1), min(v2, v3)) - eps
        hi_j = max(max(v0, v1), max(v2, v3)) + eps
        if not (lo_i == lo_i and hi_i == hi_i and lo_j == lo_j and hi_j == hi_j):
            out[c] = np.nan
            continue
        # within the source's points (its outer half cells hold their edge values)
        out[c] = small_box_max(
            src, r0, c0,
            min(max(lo_i, 0.0), ny - 1.0), min(max(hi_i, 0.0), ny - 1.0),
            min(max(lo_j, 0.0), nx - 1.0), min(max(hi_j, 0.0), nx - 1.0),
        )  # fmt: skip


@njit(cache=True)
def _bilinear_at(src, r0, c0, ny, nx, fi, fj):
    """The source's bilinear value at fractional row ``fi``, column ``fj`` (clamped to its
    points); a neighbour of weight 0 (on a grid line) is the point itself, so its NaN does
    not count."""
    fi = min(max(fi, 0.0), ny - 1.0)
    fj = min(max(fj, 0.0), nx - 1.0)
    i0 = int(math.floor(fi))
    j0 = int(math.floor(fj))
    ti = fi - i0
    tj = fj - j0
    i0 -= r0
    j0 -= c0
    i1 = i0 + 1 if ti > 0 else i0
    j1 = j0 + 1 if tj > 0 else j0
    h, w = src.shape
    if i0 < 0 or j0 < 0 or i1 >= h or j1 >= w:
        raise AssertionError("a warped block's source window misses a point")
    v = (src[i0, j0] * (1 - tj) + src[i0, j1] * tj) * (1 - ti)
    v += (src[i1, j0] * (1 - tj) + src[i1, j1] * tj) * ti
    return v


@njit(cache=True)
def _row_breaks(src, k, jj, s, t0, th):
    """Row ``k`` of ``src`` at the column breakpoints of a box over ``s`` (1-3) cells from
    column ``jj``: its left side (at ``t0`` in the first cell), the grid points inside and
    its right side (at ``th`` in the last cell), padded with repeats; and the points' sum."""
    w0 = np.float64(src[k, jj])
    w1 = np.float64(src[k, jj + 1])
    g0 = w0 + (w1 - w0) * t0
    if s == 1:
        gh = w0 + (w1 - w0) * th
        return g0, gh, gh, gh, w0 + w1
    w2 = np.float64(src[k, jj + 2])
    if s == 2:
        return g0, w1, w1 + (w2 - w1) * th, g0, w0 + w1 + w2
    w3 = np.float64(src[k, jj + 3])
    return g0, w1, w2, w2 + (w3 - w2) * th, (w0 + w1) + (w2 + w3)


@njit(cache=True)
def _lerp_max(a0, a1, a2, a3, b0, b1, b2, b3, t):
    return max(
        max(a0 + (b0 - a0) * t, a1 + (b1 - a1) * t), max(a2 + (b2 - a2) * t, a3 + (b3 - a3) * t)
    )


@njit(cache=True)
def small_box_max(src, r0, c0, lo_i, hi_i, lo_j, hi_j):
    """:func:`box_max`, in straight lines for a box over 1-2 source cells by 1-3 (a target
    cell about as fine as the source's; others go to :func:`box_max`): the surface's highest
    is at a breakpoint of both axes (the box's sides and the grid lines between them), so
    each row the box touches is taken at the column breakpoints, then the rows at the row
    breakpoints."""
    i0 = int(math.floor(lo_i))
    i1 = int(math.ceil(hi_i))
    j0 = int(math.floor(lo_j))
    j1 = int(math.ceil(hi_j))
    r = i1 - i0
    s = j1 - j0
    if r > 2 or s > 3 or r == 0 or s == 0:
        return box_max(src, r0, c0, lo_i, hi_i, lo_j, hi_j)
    t0 = lo_j - j0
    th = hi_j - (j1 - 1)
    jj = j0 - c0
    k = i0 - r0
    a0, a1, a2, a3, s0 = _row_breaks(src, k, jj, s, t0, th)
    b0, b1, b2, b3, s1 = _row_breaks(src, k + 1, jj, s, t0, th)
    top = _lerp_max(a0, a1, a2, a3, b0, b1, b2, b3, lo_i - i0)
    if r == 1:
        top = max(top, _lerp_max(a0, a1, a2, a3, b0, b1, b2, b3, hi_i - i0))
        total = s0 + s1
    else:  # row i0 + 1 inside the box
        d0, d1, d2, d3, s2 = _row_breaks(src, k + 2, jj, s, t0, th)
        top = max(top, max(max(b0, b1), max(b2, b3)))
        top = max(top, _lerp_max(b0, b1, b2, b3, d0, d1, d2, d3, hi_i - (i0 + 1)))
        total = s0 + s1 + s2
    if total != total:  # (a NaN among the points: source values are finite or NaN)
        return np.nan
    return top


@njit(cache=True)
def box_max(src, r0, c0, lo_i, hi_i, lo_j, hi_j):
    """The highest value of the source's bilinear surface over the box of fractional rows
    ``lo_i..hi_i`` and columns ``lo_j..hi_j`` (within its points); NaN where a point with a
    weight is NaN. The surface is bilinear on each source cell's part of the box, highest at
    one of its corners: the grid points inside the box, the crossings of its sides with the
    grid lines (linear between two points) and the box's corners. A crossing (or corner) is
    measured only where one of its points is higher than every point inside: its value lies
    between theirs."""
    i0 = int(math.floor(lo_i))
    i1 = int(math.ceil(hi_i))
    j0 = int(math.floor(lo_j))
    j1 = int(math.ceil(hi_j))
    ia = int(math.ceil(lo_i))
    ib = int(math.floor(hi_i))
    ja = int(math.ceil(lo_j))
    jb = int(math.floor(hi_j))
    # the grid points inside, then those of the cells the box touches outside it (a NaN
    # among them makes the sum NaN: source values are finite or NaN)
    top = -np.inf
    total = 0.0
    for i in range(ia, ib + 1):
        for j in range(ja, jb + 1):
            z = np.float64(src[i - r0, j - c0])
            total += z
            top = max(top, z)
    out = -np.inf
    for i in (i0, i1):
        if i < ia or i > ib:
            for j in range(j0, j1 + 1):
                z = np.float64(src[i - r0, j - c0])
                total += z
                out = max(out, z)
    for j in (j0, j1):
        if j < ja or j > jb:
            for i in range(ia, ib + 1):
                z = np.float64(src[i - r0, j - c0])
                total += z
                out = max(out, z)
    if total != total:
        return np.nan
    if out <= top:
        return top
    # the sides along rows (between rows k and k + 1, at t), then along columns, where they
    # lie between two grid lines
    for k, t, on in ((i0, lo_i - i0, i0 < ia), (i1 - 1, hi_i - (i1 - 1), i1 > ib)):
        if on:
            for j in range(ja, jb + 1):
                a = np.float64(src[k - r0, j - c0])
                b = np.float64(src[k + 1 - r0, j - c0])
                if max(a, b) > top:
                    top = max(top, a * (1 - t) + b * t)
    for m, t, on in ((j0, lo_j - j0, j0 < ja), (j1 - 1, hi_j - (j1 - 1), j1 > jb)):
        if on:
            for i in range(ia, ib + 1):
                a = np.float64(src[i - r0, m - c0])
                b = np.float64(src[i - r0, m + 1 - c0])
                if max(a, b) > top:
                    top = max(top, a * (1 - t) + b * t)
    for u in (lo_i, hi_i):  # the box's corners
        k = min(int(math.floor(u)), i1 - 1) if i1 > i0 else i0
        for v in (lo_j, hi_j):
            m = min(int(math.floor(v)), j1 - 1) if j1 > j0 else j0
            k1 = k + 1 if i1 > i0 else k
            m1 = m + 1 if j1 > j0 else m
            z00 = np.float64(src[k - r0, m - c0])
            z01 = np.float64(src[k - r0, m1 - c0])
            z10 = np.float64(src[k1 - r0, m - c0])
            z11 = np.float64(src[k1 - r0, m1 - c0])
            if max(z00, z01, z10, z11) <= top:
                continue
            t = u - k
            w = v - m
            top = max(top, (z00 * (1 - w) + z01 * w) * (1 - t) + (z10 * (1 - w) + z11 * w) * t)
    return top


@functools.lru_cache(maxsize=8)
def _pipeline(definition: str):
    from pyproj import Transformer

    return Transformer.from_pipeline(definition)


def _source_window(tr, x, y, grid: GridAxes, a: float = 0.0) -> tuple:
    """The rows and columns of the source grid that the warp of the centres ``x`` by ``y``
    can weigh, with the squares of side ``2 a`` around them: the outline of the block grown
    by ``a`` transformed densely (a projected block's outline holds its extremes in lon/lat
    away from the poles), one source point of margin."""
    x = np.concatenate(([np.min(x) - a], x, [np.max(x) + a]))
    y = np.concatenate(([np.min(y) - a], y, [np.max(y) + a]))
    edge_x = np.concatenate([x, x, np.full(len(y), x[0]), np.full(len(y), x[-1])])
    edge_y = np.concatenate([np.full(len(x), y[0]), np.full(len(x), y[-1]), y, y])
    if tr is not None:
        edge_x, edge_y = tr.transform(edge_x, edge_y)
    fi = grid.rows(edge_y)
    fj = grid.cols(edge_x)
    fi, fj = fi[np.isfinite(fi)], fj[np.isfinite(fj)]
    if not fi.size:
        return (0, 0), (0, 0)
    r0 = int(np.clip(np.floor(fi.min()) - 1, 0, grid.ny))
    r1 = int(np.clip(np.ceil(fi.max()) + 2, 0, grid.ny))
    c0 = int(np.clip(np.floor(fj.min()) - 1, 0, grid.nx))
    c1 = int(np.clip(np.ceil(fj.max()) + 2, 0, grid.nx))
    return (r0, r1), (c0, c1)


def _resample_square(
    values: xr.DataArray,
    path: Path,
    dx: float,
    dy: float,
    resolution: float | None = None,
    chunks=None,
    bounds: tuple | None = None,
):
    """Resample onto square cells (of ``resolution``, by default of the geometric-mean size)
    over the grid's extent (or ``bounds``, x0, y0, x1, y1, where the grid covers them): the
    upper envelope of its bilinear surface (:func:`warp`)."""
    from rasterio.transform import from_origin

    a = resolution or float(f"{math.sqrt(dx * dy):.4g}")
    notice(log, "DEM %s has cells of %g x %g m: resampling to square %g m cells", path, dx, dy, a)
    x = np.asarray(values["x"].values, dtype=np.float64)
    y = np.asarray(values["y"].values, dtype=np.float64)
    x0, x1 = x.min() - dx / 2, x.max() + dx / 2
    y0, y1 = y.min() - dy / 2, y.max() + dy / 2
    if bounds is not None:
        x0, y0 = max(x0, bounds[0]), max(y0, bounds[1])
        x1, y1 = min(x1, bounds[2]), min(y1, bounds[3])
    nx, ny = max(2, int(round((x1 - x0) / a))), max(2, int(round((y1 - y0) / a)))
    transform = from_origin(x0, y1, a, a)
    lazy = isinstance(values.data, da.Array)
    side = chunks2d(chunks if chunks is not None else DEFAULT_CHUNK, (ny, nx))
    out, stats = warp(values, None, None, transform, (ny, nx), side if lazy else None)
    if y[0] < y[-1]:  # a south-up grid stays south-up
        out = out.isel(y=slice(None, None, -1))
    return out, stats


def _spacing(arr: xr.DataArray, dim: str, path: Path | str = "DEM") -> float:
    """The (signed) step of an evenly spaced coordinate; refuse an uneven one."""
    step, even = _step(arr, dim, path)
    if not even:
        raise InvalidDEMError(
            f"{path}: {dim} coordinates are not evenly spaced; "
            "open the DEM with pipeline.open_dem to resample it"
        )
    return step


def _step(arr: xr.DataArray, dim: str, path: Path | str) -> tuple[float, bool]:
    """Mean step of coordinate ``dim`` and whether it is even up to the storage precision."""
    raw = np.asarray(arr[dim].values)
    c = raw.astype(np.float64)
    if c.size < 2:
        raise InvalidDEMError(f"{path}: dimension {dim} has fewer than 2 coordinates")
    d = np.diff(c)
    if not (np.all(d > 0) or np.all(d < 0)):
        raise InvalidDEMError(
            f"{path}: {dim} coordinates are not strictly increasing or "
            "decreasing (repeated or unordered values); fix the grid's "
            "coordinates"
        )
    step = (c[-1] - c[0]) / (c.size - 1)
    eps = np.finfo(raw.dtype).eps if raw.dtype.kind == "f" else 0.0
    tol = max(1e-6 * abs(step), 4.0 * eps * float(np.abs(c).max()))
    return float(step), bool(np.all(np.abs(d - step) <= tol))
