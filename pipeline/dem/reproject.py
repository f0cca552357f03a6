"""Exact reprojection of a DEM (docs/method.md): each target cell centre transformed by pyproj
and the source grid sampled bilinearly there (a lon/lat grid onto an azimuthal equidistant
projection centred on it), and resampling to square cells.
"""

from __future__ import annotations

import functools
import logging
import math
from pathlib import Path

import dask.array as da
import numpy as np
import xarray as xr

from ..exceptions import InvalidDEMError, notice
from ..params import DEFAULT_CHUNK, chunks2d
from ..runtime.jit import njit

log = logging.getLogger(__name__)


def _reproject_geographic(
    values: xr.DataArray, path: Path, crs, resolution: float | None = None, chunks=None
):
    """Reproject a lon/lat grid to an azimuthal equidistant projection centred on the grid,
    bilinearly and exactly (:func:`exact_warp`), chunk by chunk when ``values`` is a dask
    array. The output grid is rasterio's default one for that projection and cell."""
    from pyproj import CRS
    from rasterio.warp import calculate_default_transform

    src_crs = crs if crs is not None else CRS.from_epsg(4326)
    lon = np.asarray(values["x"].values, dtype=np.float64)
    lat = np.asarray(values["y"].values, dtype=np.float64)
    if lon.min() >= 180.0:
        values = values.assign_coords(x=lon - 360.0)
        lon = lon - 360.0
    lon0, lat0 = float(lon.mean()), float(lat.mean())
    dlon, dlat = abs(_spacing(values, "x", path)), abs(_spacing(values, "y", path))
    metres_per_degree = 111_320.0
    dx_m = dlon * metres_per_degree * math.cos(math.radians(lat0))
    dy_m = dlat * metres_per_degree
    a = resolution or float(f"{math.sqrt(dx_m * dy_m):.3g}")
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
        left=lon.min() - dlon / 2,
        bottom=lat.min() - dlat / 2,
        right=lon.max() + dlon / 2,
        top=lat.max() + dlat / 2,
        resolution=a,
    )
    lazy = isinstance(values.data, da.Array)
    side = chunks2d(chunks if chunks is not None else DEFAULT_CHUNK, (height, width))
    out = exact_warp(values, src_crs, dst, transform, (height, width), side if lazy else None)
    return out, dst


def exact_warp(values: xr.DataArray, src_crs, dst_crs, transform, shape, chunks=None):
    """``values`` (dims ``(y, x)`` on a regular grid of ``src_crs``) sampled at the cell
    centres of the grid ``transform``, ``shape`` of ``dst_crs``: each centre transformed
    exactly by pyproj (not GDAL's approximate transformer, whose error of up to an eighth of
    a source cell moves terrain by tens of metres on coarse grids), then bilinear in the
    source grid, the source's outer half cells holding their edge points' values (its cells
    are areas, as GDAL reads them); NaN beyond them, or where a source point with a weight is
    NaN. With ``chunks`` (a (rows, cols) side) the result is a dask array whose each block
    reads only the source window it needs (memory bounded by the block), equal to the
    in-memory result (each centre is computed alone)."""
    from pyproj import Transformer

    # the exact operation as a PROJ pipeline: a thread makes its own copy of a transformer, and
    # one made from a pipeline does not read PROJ's database again (2 MB a thread)
    tr = _pipeline(Transformer.from_crs(dst_crs, src_crs, always_xy=True).definition)
    height, width = shape
    xs = transform.c + (np.arange(width) + 0.5) * transform.a
    ys = transform.f + (np.arange(height) + 0.5) * transform.e
    sx = np.asarray(values["x"].values, dtype=np.float64)
    sy = np.asarray(values["y"].values, dtype=np.float64)
    grid = (sx[0], _spacing(values, "x"), sy[0], _spacing(values, "y"), len(sy), len(sx))

    def block(src, y, x, off):
        llon, llat, fy, fx = _lattice(tr, x, y, grid)
        src = np.ascontiguousarray(src, dtype=np.float32)
        return _warp_kernel(src, off[0], off[1], *grid, llon, llat, fy, fx)

    if chunks is None:
        data = block(values.values, ys, xs, (0, 0))
    else:
        rows = []
        for i0 in range(0, height, chunks[0]):
            row = []
            for j0 in range(0, width, chunks[1]):
                y, x = ys[i0 : i0 + chunks[0]], xs[j0 : j0 + chunks[1]]
                (r0, r1), (c0, c1) = _source_window(tr, x, y, grid)
                src = values.data[max(r0, 0) : max(r1, 1), max(c0, 0) : max(c1, 1)]
                src = src.rechunk(src.shape)  # the window as one block
                part = src.map_blocks(
                    block, y, x, (r0, c0), chunks=(len(y), len(x)), dtype=np.float32,
                    meta=np.empty((0, 0), dtype=np.float32),
                )  # fmt: skip
                row.append(part)
            rows.append(row)
        data = da.block(rows)
    return xr.DataArray(data, dims=("y", "x"), coords={"y": ys, "x": xs}, name=values.name)


# the source coordinates of a block's cell centres: transformed exactly on a lattice of every
# WARP_LATTICE-th centre and interpolated bilinearly between (8^2 times fewer transforms), where
# the lattice cells' midpoints, transformed exactly too, are within WARP_TOLERANCE source cells
# of the interpolation (else every centre of the block is transformed)
WARP_LATTICE = 8


WARP_TOLERANCE = 1e-4


def _lattice(tr, x, y, grid) -> tuple:
    """The source coordinates (lon, lat as ``tr`` gives them) of the centres ``x`` by ``y``
    as a lattice and the fractional lattice row of each ``y`` and column of each ``x``: every
    ``WARP_LATTICE``-th centre when interpolating between them is close enough, else all."""
    k = WARP_LATTICE
    every = np.arange(len(y), dtype=np.float64), np.arange(len(x), dtype=np.float64)
    if len(x) > 2 * k and len(y) > 2 * k:
        ix = np.unique(np.append(np.arange(0, len(x), k), len(x) - 1))
        iy = np.unique(np.append(np.arange(0, len(y), k), len(y) - 1))
        llon, llat = _transform_grid(tr, x[ix], y[iy])
        # the midpoints of the lattice cells: exact against interpolated
        clon, clat = _transform_grid(
            tr, 0.5 * (x[ix[:-1]] + x[ix[1:]]), 0.5 * (y[iy[:-1]] + y[iy[1:]])
        )
        ilon = 0.25 * (llon[:-1, :-1] + llon[1:, :-1] + llon[:-1, 1:] + llon[1:, 1:])
        ilat = 0.25 * (llat[:-1, :-1] + llat[1:, :-1] + llat[:-1, 1:] + llat[1:, 1:])
        with np.errstate(invalid="ignore"):
            dev = max(
                np.max(np.abs(ilon - clon)) / abs(grid[1]),
                np.max(np.abs(ilat - clat)) / abs(grid[3]),
            )
        if dev <= WARP_TOLERANCE:  # (not NaN: every lattice point in the projection's domain)
            fy = np.interp(every[0], iy, np.arange(len(iy), dtype=np.float64))
            fx = np.interp(every[1], ix, np.arange(len(ix), dtype=np.float64))
            return llon, llat, fy, fx
    llon, llat = _transform_grid(tr, x, y)
    return llon, llat, *every


def _transform_grid(tr, x, y) -> tuple:
    xx, yy = np.meshgrid(x, y)
    lon, lat = tr.transform(xx, yy)
    return np.asarray(lon, dtype=np.float64), np.asarray(lat, dtype=np.float64)


@njit(cache=True, nogil=True)
def _warp_kernel(src, r0, c0, x0, dx, y0, dy, ny, nx, llon, llat, fy, fx):
    """The bilinear sample of the source window ``src`` (its first point source row ``r0``,
    column ``c0``; the source grid's first coordinates, steps and size ``x0, dx, y0, dy, ny,
    nx``) at the source coordinates interpolated bilinearly in the lattice ``llon``, ``llat``
    at fractional rows ``fy`` by columns ``fx`` (integers: the lattice's own values); the
    outer half cells take their edge's values. NaN beyond them or where a point with a weight
    is NaN; a neighbour of weight 0 (on a grid line)
    is the point itself, so its NaN does not count."""
    out = np.empty((fy.size, fx.size), dtype=np.float32)
    h, w = src.shape
    li, lj = llon.shape
    for r in range(fy.size):
        a0 = min(int(math.floor(fy[r])), li - 1)
        ta = fy[r] - a0
        a1 = min(a0 + 1, li - 1)
        for c in range(fx.size):
            b0 = min(int(math.floor(fx[c])), lj - 1)
            tb = fx[c] - b0
            b1 = min(b0 + 1, lj - 1)
            lon = (llon[a0, b0] * (1 - tb) + llon[a0, b1] * tb) * (1 - ta)
            lon += (llon[a1, b0] * (1 - tb) + llon[a1, b1] * tb) * ta
            lat = (llat[a0, b0] * (1 - tb) + llat[a0, b1] * tb) * (1 - ta)
            lat += (llat[a1, b0] * (1 - tb) + llat[a1, b1] * tb) * ta
            fi = (lat - y0) / dy
            fj = (lon - x0) / dx
            # the source's cells are areas: its outer half cells hold their points' values
            if not (-0.5 <= fi <= ny - 0.5 and -0.5 <= fj <= nx - 0.5):
                out[r, c] = np.nan  # (NaN coordinates too)
                continue
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
            if i0 < 0 or j0 < 0 or i1 >= h or j1 >= w:
                raise AssertionError("a reprojected block's source window misses a point")
            v = (src[i0, j0] * (1 - tj) + src[i0, j1] * tj) * (1 - ti)
            v += (src[i1, j0] * (1 - tj) + src[i1, j1] * tj) * ti
            out[r, c] = v
    return out


@functools.lru_cache(maxsize=8)
def _pipeline(definition: str):
    from pyproj import Transformer

    return Transformer.from_pipeline(definition)


def _source_window(tr, x, y, grid) -> tuple:
    """The rows and columns of the source grid that the bilinear sampling of the centres
    ``x`` by ``y`` can weigh: the block's outline transformed densely (a projected block's
    outline holds its extremes in lon/lat away from the poles), one source point of margin."""
    x0, dx, y0, dy, ny, nx = grid
    edge_x = np.concatenate([x, x, np.full(len(y), x[0]), np.full(len(y), x[-1])])
    edge_y = np.concatenate([np.full(len(x), y[0]), np.full(len(x), y[-1]), y, y])
    lon, lat = tr.transform(edge_x, edge_y)
    fi = (np.asarray(lat) - y0) / dy
    fj = (np.asarray(lon) - x0) / dx
    fi, fj = fi[np.isfinite(fi)], fj[np.isfinite(fj)]
    if not fi.size:
        return (0, 0), (0, 0)
    r0 = int(np.clip(np.floor(fi.min()) - 1, 0, ny))
    r1 = int(np.clip(np.ceil(fi.max()) + 2, 0, ny))
    c0 = int(np.clip(np.floor(fj.min()) - 1, 0, nx))
    c1 = int(np.clip(np.ceil(fj.max()) + 2, 0, nx))
    return (r0, r1), (c0, c1)


def _resample_square(
    values: xr.DataArray, path: Path, dx: float, dy: float, crs, resolution: float | None = None
):
    """Bilinear resample onto square cells (of ``resolution``, by default of the geometric-mean
    size), keeping the extent."""
    a = resolution or float(f"{math.sqrt(dx * dy):.4g}")
    notice(log, "DEM %s has cells of %g x %g m: resampling to square %g m cells", path, dx, dy, a)
    x = np.asarray(values["x"].values)
    y = np.asarray(values["y"].values)
    x0, x1 = x.min() - dx / 2, x.max() + dx / 2
    y0, y1 = y.min() - dy / 2, y.max() + dy / 2
    nx, ny = max(2, int(round((x1 - x0) / a))), max(2, int(round((y1 - y0) / a)))
    new_x = x0 + (np.arange(nx) + 0.5) * a
    new_y = y1 - (np.arange(ny) + 0.5) * a
    if y[0] < y[-1]:
        new_y = new_y[::-1]
    out = values.load().interp(x=new_x, y=new_y, method="linear", kwargs={"fill_value": None})
    return out


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
