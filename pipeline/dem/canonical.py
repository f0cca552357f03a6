"""Open, validate, reproject and write digital elevation models (docs/method.md section 1).

The canonical DEM is an ``xarray.DataArray`` named ``elevation``: dims ``(y, x)``, float32
metres positive up (seabed negative), NaN for no-data, square cells in a metric CRS, with
``cell_size`` (metres) and, when known, ``crs_wkt`` in its attributes. ``open_dem`` turns a
GeoTIFF, a NetCDF / GMT grid or a Zarr store into that form; ``write_dem`` writes it as the
canonical chunked Zarr (v3) store, atomically.
"""

from __future__ import annotations

import functools
import logging
import math
import os
from pathlib import Path

import dask.array as da
import numpy as np
import xarray as xr

from .._types import Chunks, DEMLike
from ..exceptions import InvalidDEMError, InvalidParameterError, notice
from ..params import CELL_SIZE, DEFAULT_CHUNK, chunks2d
from ..store.schema import GRID_MAPPING
from .readers import _X_NAMES, _Y_NAMES, _pick_variable
from .reproject import (
    _mean_step,
    _reproject_geographic,
    _resample_square,
    _spacing,
    _step,
    combine_stats,
)

log = logging.getLogger(__name__)


def cell_size(dem: xr.DataArray) -> float:
    """Side of a (square) cell of ``dem`` in metres.

    Examples
    --------
    >>> cell_size(synthetic_dem((64, 64), cell_size=30.0))  # doctest: +SKIP
    30.0
    """
    if not isinstance(dem, xr.DataArray):
        raise InvalidParameterError(f"`dem` must be an xarray.DataArray, got {type(dem).__name__}")
    if "cell_size" in dem.attrs:
        return float(dem.attrs["cell_size"])
    dx, dy = _spacing(dem, "x"), _spacing(dem, "y")
    crs = _crs_of(dem)
    if crs is not None and crs.is_geographic:
        raise InvalidDEMError(
            "the DEM is in geographic coordinates (longitude and latitude, not metres); "
            "open it with pipeline.open_dem (or pipeline.import_dem), which reprojects it to "
            "square cells in metres"
        )
    if not math.isclose(abs(dx), abs(dy), rel_tol=1e-6):
        raise InvalidDEMError(
            f"cells are not square (dx={abs(dx)}, dy={abs(dy)}); "
            "open the DEM with pipeline.open_dem to resample it"
        )
    return abs(dx)


def as_dem(dem: DEMLike, chunks: Chunks = DEFAULT_CHUNK) -> xr.DataArray:
    """``dem`` as the DEM the pipeline's stages take: a path is opened with :func:`open_dem`;
    an xarray DataArray (or a Dataset's elevation variable), such as ``rioxarray.open_rasterio``
    gives, keeps its no-data and its CRS: the no-data value of ``rio.nodata``, ``_FillValue``
    or ``missing_value`` (attributes or encoding), and a masked array's mask, become NaN; the
    CRS of ``rio.crs`` (a ``spatial_ref`` or ``grid_mapping`` variable) becomes its
    ``crs_wkt``; a band dimension of one band is dropped. Anything else (a bare numpy array,
    several bands) is one :class:`InvalidDEMError` naming what to pass."""
    from .open import open_dem

    if isinstance(dem, str | os.PathLike):
        return open_dem(dem, chunks=chunks)
    if isinstance(dem, xr.Dataset):
        dem = _pick_variable(dem, Path("<Dataset>"), None)
    if not isinstance(dem, xr.DataArray):
        return open_dem(dem)  # (its one line names what to pass)
    extra = [d for d in dem.dims if d not in ("y", "x")]
    if any(dem.sizes[d] != 1 for d in extra) or set(dem.dims) - set(extra) != {"y", "x"}:
        raise InvalidDEMError(
            f"a DEM is one 2-D grid with dims ('y', 'x'), got dims {dem.dims} of sizes "
            f"{tuple(dem.shape)}; select one band or time step (dem.sel(band=1)), or open "
            "the file with pipeline.open_dem"
        )
    if extra:
        dem = dem.squeeze(extra, drop=True)
    dem = dem.transpose("y", "x")
    if dem.dtype.kind not in "iuf":  # (bool or complex values are no elevations)
        raise InvalidDEMError(
            f"a DEM holds elevations in metres (numbers), got values of type {dem.dtype}; "
            "give the elevation grid"
        )
    attrs = dict(dem.attrs)
    if str(attrs.get("positive", "")).lower() == "down":  # depths, as a file's are read
        notice(log, "DEM has positive='down' (depths): negating to elevation, positive up")
        dem = -dem
        attrs["positive"] = "up"
    crs = _crs_of(dem)  # (rio.crs: a spatial_ref or grid_mapping variable; or an attribute)
    data = dem.data
    if isinstance(data, np.ma.MaskedArray):
        dem = dem.copy(data=np.ma.filled(data.astype(np.float32), np.nan))
    nodata = _nodata_of(dem)
    try:  # NaN (a float of any width) is no-data already
        real = nodata is not None and not math.isnan(float(nodata))
    except (TypeError, ValueError):
        real = nodata is not None
    if real:
        dem = dem.where(dem != nodata)
        notice(log, "DEM: its no-data value %g read as NaN", nodata)
    if dem.dtype.kind != "f":
        dem = dem.astype(np.float32)
    for key in ("_FillValue", "missing_value", "nodata"):
        attrs.pop(key, None)
    dem.attrs = attrs
    dem.encoding = {}
    if crs is not None and "crs_wkt" not in attrs:
        dem.attrs["crs_wkt"] = crs.to_wkt()
    dem = dem.drop_vars([c for c in (GRID_MAPPING, "crs") if c in dem.coords])
    return dem


def _nodata_of(dem: xr.DataArray):
    """The no-data value a DataArray declares, or None."""
    try:
        import rioxarray  # noqa: F401

        value = dem.rio.nodata
        if value is not None:
            return value
    except Exception:  # noqa: BLE001 - no rioxarray, or coordinates it cannot read
        pass
    for where in (dem.attrs, dem.encoding):
        for key in ("_FillValue", "missing_value", "nodata"):
            if where.get(key) is not None:
                return np.asarray(where[key]).ravel()[0].item()
    return None


def _shoal_surface(elev: xr.DataArray, sigma: xr.DataArray, k: float, path) -> xr.DataArray:
    """``elevation + k * sigma`` (positive up), lazily; sigma must lie on the same grid and be
    non-negative (checked chunk by chunk as the grid is read)."""
    try:
        elev, sigma = xr.align(elev, sigma, join="exact")
    except ValueError:
        raise InvalidDEMError(
            f"DEM file {path}: the uncertainty {sigma.name!r} is not on the elevation's grid "
            f"({dict(sigma.sizes)} against {dict(elev.sizes)})"
        ) from None
    sign = _depth_sign(elev, path)
    s = sigma.astype(np.float32)
    check = functools.partial(_nonnegative_sigma, path=str(path), name=str(sigma.name))
    s = s.copy(data=s.data.map_blocks(check) if isinstance(s.data, da.Array) else check(s.data))
    out = elev.astype(np.float32) * np.float32(sign) + np.float32(k) * s
    out.attrs = {**elev.attrs, "positive": "up"}
    return out


def _nonnegative_sigma(block: np.ndarray, path: str, name: str) -> np.ndarray:
    if np.any(block < 0):
        raise InvalidDEMError(
            f"DEM file {path}: the uncertainty {name!r} holds negative values (down to "
            f"{float(np.nanmin(block)):g}); sigma is a standard deviation, >= 0"
        )
    return block


def _located(arr: xr.DataArray, path: Path, cell_size: float | None = None) -> tuple:
    """A file's grid with dims ``(y, x)`` and 1-D coordinates, its CRS (or None) and
    whether it is a lon/lat grid; nothing read yet."""
    if arr.dtype.kind not in "iuf":
        raise InvalidDEMError(f"DEM file {path}: values are of type {arr.dtype}, not numbers")
    arr = _squeeze_to_2d(arr, path)
    crs = _crs_of(arr)
    ydim, xdim = _spatial_dims(arr, path)
    arr = arr.transpose(ydim, xdim).rename({ydim: "y", xdim: "x"})
    arr = arr.drop_vars([c for c in arr.coords if c not in ("x", "y")])
    if min(arr.shape) < 2:
        raise InvalidDEMError(
            f"DEM file {path} is {arr.shape[0]} x {arr.shape[1]} cells; at least 2 x 2 are needed"
        )
    if "x" not in arr.coords or "y" not in arr.coords:
        arr = _synthesise_coords(arr, path, cell_size)
    geographic = _is_geographic(arr, crs, xdim, ydim)
    if not geographic and crs is None and (cell := _degree_cell(arr)) is not None:
        notice(
            log,
            "DEM %s has no coordinate reference system, and its cells of %g units with "
            "coordinates within longitude and latitude ranges are no metres: read as lon/lat "
            "(WGS84); give the file its CRS (a .prj beside an .asc, or gdal_edit.py -a_srs) "
            "if it is another",
            path,
            cell,
        )
        geographic = True
    if geographic:
        arr = _unwrapped(arr)
    return arr, crs, geographic


def source_grid(arr: xr.DataArray, path: Path) -> tuple:
    """A file's grid as it is (no resample): float64 metres positive up, NaN no-data, dims
    ``(y, x)`` in its own coordinates, lazily; and its CRS (pyproj; a lon/lat grid without
    one is WGS84; None for a projected grid without one)."""
    from pyproj import CRS

    arr, crs, geographic = _located(arr, path)
    if geographic and crs is None:
        crs = CRS.from_epsg(4326)
    for dim in ("y", "x"):
        _step(arr, dim, path)  # (a repeated or unordered axis is refused, named)
    sign = _depth_sign(arr, path)
    values = arr.astype(np.float64) * sign
    return values.where(np.isfinite(values)), crs


def _canonicalise(
    arr: xr.DataArray,
    path: Path,
    *,
    chunks,
    cell_size: float | None,
    resolution: float | None = None,
    region: tuple | None = None,
) -> xr.DataArray:
    arr, crs, geographic = _located(arr, path, cell_size)
    # a region is read with a margin of source cells beyond it: the target nodes at its edges
    # take the highest of the source over a target cell around them (docs/method.md section 1)
    margin = _resample_margin(arr, path, geographic, resolution)
    arr, bounds = _crop(arr, path, crs, geographic, region, margin)  # before a value is read
    if geographic:
        lat, lon = np.asarray(arr["y"].values, float), np.asarray(arr["x"].values, float)
        if np.abs(lat).max() > 90 or lon.min() < -360 or lon.max() > 360:
            raise InvalidDEMError(
                f"DEM file {path} is a lon/lat grid with latitudes beyond +-90 or longitudes "
                f"beyond +-360 (latitudes {lat.min():g} to {lat.max():g}, longitudes "
                f"{lon.min():g} to {lon.max():g}); fix its coordinates"
            )
        _check_geographic_extent(path, lat, lon)
    sign = _depth_sign(arr, path)
    attrs = {k: v for k, v in arr.attrs.items() if k in ("long_name", "standard_name", "title")}
    values = arr.astype(np.float32) * np.float32(sign) if sign != 1 else arr.astype(np.float32)
    values = values.where(np.isfinite(values))
    stats = None
    if geographic:
        values, crs, stats = _reproject_geographic(values, path, crs, resolution, chunks, bounds)
    elif margin > 1:
        dx, dy = _mean_step(values["x"].values), _mean_step(values["y"].values)
        values, stats = _resample_square(values, path, dx, dy, resolution, chunks, bounds)
    a = abs(_spacing(values, "x", path))
    attrs.update(cell_size=float(a), units="m", positive="up", source=str(path))
    attrs["seabed_surface"] = SURFACES["upper" if stats is not None else "source"]
    if crs is not None:
        attrs["crs_wkt"] = crs.to_wkt()
    out = values.astype(np.float32)
    out.name = "elevation"
    out.attrs = attrs
    out.encoding = {}
    if chunks is None:
        if isinstance(out.data, da.Array):
            import dask

            data, stats = dask.compute(out.data, stats)
            out = out.copy(data=data)
        if stats is not None:
            out.attrs.update(construction_figures(combine_stats(stats), path))
        return out
    out = out.chunk(dict(zip(("y", "x"), chunks2d(chunks, out.shape), strict=True)))
    if stats is not None:
        _FIGURES[out.data.name] = stats
        while len(_FIGURES) > 64:
            _FIGURES.pop(next(iter(_FIGURES)))
    return out


# how the seabed a DEM store holds was made from the file (its attribute ``seabed_surface``)
SURFACES = {
    "source": "the source grid's own points (no resample)",
    "upper": (
        "upper envelope: each node the highest of the source's bilinear surface within one "
        "cell of it, so the grid's bilinear surface lies on or above the source's"
    ),
}


# the figures of the resamples of DEMs opened lazily and not written yet (the warp's blocks
# give them as they are computed, in the write: warp_figures), by the dask name of the grid
_FIGURES: dict = {}


def warp_figures(dem: xr.DataArray):
    """The per-block figures (delayed) of the resample that made ``dem`` (:func:`open_dem`
    lazily), or None when it was not resampled or was changed since."""
    data = dem.data
    return _FIGURES.get(data.name) if isinstance(data, da.Array) else None


def construction_figures(row, path) -> dict:
    """A resample's figures (:func:`pipeline.dem.reproject.combine_stats`) as the DEM's
    attributes, logged: the raise of the planning seabed over the source's bilinear surface
    at the nodes (mean and greatest, metres) and the nodes beyond the source's coverage."""
    total, count, most, beyond = (float(v) for v in row)
    mean = total / count if count else 0.0
    log.info(
        "DEM %s: the planning seabed (upper envelope of the source) lies above the source's "
        "bilinear surface by %.2f m on average at the grid points, %.2f m at most",
        path,
        mean,
        most if count else 0.0,
    )
    if beyond:
        notice(
            log,
            "DEM %s: %d grid points lie beyond the source's coverage (no-data, never passable)",
            path,
            int(beyond),
        )
    return {
        "seabed_raise_mean_m": round(mean, 4),
        "seabed_raise_max_m": round(most if count else 0.0, 4),
        "cells_beyond_source": int(beyond),
    }


def _resample_margin(arr: xr.DataArray, path: Path, geographic: bool, resolution) -> int:
    """The source cells read beyond a region: 1 when the grid is not resampled (one cell
    each side), else enough for a target cell around the region's edge nodes (its square
    of half-side one target cell, with slack)."""
    # (an axis repeated or unordered is refused here, named)
    even = {dim: _step(arr, dim, path)[1] for dim in ("y", "x")}
    if geographic:
        from .reproject import degree_cell_metres, natural_cell

        lat = np.asarray(arr["y"].values, dtype=np.float64)
        a = resolution or natural_cell(arr)
        dx_m, dy_m = degree_cell_metres(arr)
        # (the cells of longitude narrow towards the poles: counted at the farthest latitude)
        k = math.cos(math.radians(float(np.abs(lat).mean()))) / max(
            math.cos(math.radians(min(float(np.abs(lat).max()), 89.0))), 1e-3
        )
        return 2 + math.ceil(a / min(dx_m / k, dy_m))
    for dim in (d for d, ok in even.items() if not ok):
        steps = np.abs(np.diff(np.asarray(arr[dim].values, dtype=np.float64)))
        notice(
            log,
            "DEM %s: %s coordinates are unevenly spaced (steps %.6g to %.6g): "
            "resampling onto an even grid",
            path,
            dim,
            steps.min(),
            steps.max(),
        )
    dx, dy = _mean_step(arr["x"].values), _mean_step(arr["y"].values)
    square = math.isclose(dx, dy, rel_tol=1e-4)
    same = resolution is None or math.isclose(dx, resolution, rel_tol=1e-4)
    if all(even.values()) and square and same:
        return 1
    a = resolution or math.sqrt(dx * dy)
    return 2 + math.ceil(a / min(dx, dy))


def _crop(
    arr: xr.DataArray, path: Path, crs, geographic: bool, region, margin: int = 1
) -> tuple[xr.DataArray, tuple | None]:
    """The cells of ``arr`` (dims y, x with 1-D coordinates) whose centres lie in the region,
    and ``margin`` more on each side, selected lazily (only their chunks are ever read); and
    the region's box in the grid's coordinates (None without a region)."""
    if region is None:
        return arr, None
    form, box = region
    x = np.asarray(arr["x"].values, dtype=np.float64)
    y = np.asarray(arr["y"].values, dtype=np.float64)
    name = "bbox_xy" if form == "xy" else "bbox"
    if form == "lonlat" and geographic:
        lon0, lat0, lon1, lat1 = box
        if x.max() > 180 and lon1 <= 0:  # a grid of longitudes 0..360: the same meridians
            lon0, lon1 = lon0 + 360, lon1 + 360
        elif x.max() > 180 and lon0 < 0:
            raise InvalidParameterError(
                f"`bbox` {list(box)} crosses longitude 0, where DEM file {path} (longitudes "
                f"{x.min():g} to {x.max():g}) wraps; give longitudes from 0 to 360"
            )
        box = (lon0, lat0, lon1, lat1)
    elif form == "lonlat":
        if crs is None:
            raise InvalidParameterError(
                f"`bbox` is longitude and latitude, but DEM file {path} has no coordinate "
                "reference system; give the region in the file's coordinates (bbox_xy)"
            )
        from pyproj import CRS, Transformer

        tr = Transformer.from_crs("EPSG:4326", CRS.from_user_input(crs), always_xy=True)
        box = tr.transform_bounds(*box, densify_pts=21)
    cols = _covering(x, box[0], box[2], margin)
    rows = _covering(y, box[1], box[3], margin)
    if len(cols) < 2 or len(rows) < 2:
        raise InvalidParameterError(
            f"`{name}` {[round(v, 6) for v in box]} does not overlap DEM file {path} by 2 x 2 "
            f"cells: its cell centres span x {x.min():g} to {x.max():g}, y {y.min():g} to "
            f"{y.max():g}"
        )
    out = arr.isel(x=slice(cols[0], cols[-1] + 1), y=slice(rows[0], rows[-1] + 1))
    log.info(
        "DEM %s: reading the region %s = %s, %d x %d of %d x %d cells",
        path,
        name,
        list(region[1]),
        out.shape[0],
        out.shape[1],
        arr.shape[0],
        arr.shape[1],
    )
    return out, tuple(float(v) for v in box)


def _covering(c: np.ndarray, lo: float, hi: float, margin: int) -> np.ndarray:
    """The indices of the coordinates ``c`` (monotonic) within ``lo..hi`` and ``margin``
    more each side; a centre on a bound (to a millionth of a step) is within."""
    step = abs(c[1] - c[0]) if len(c) > 1 else 0.0
    tol = 1e-6 * step
    inside = np.nonzero((c >= lo - tol) & (c <= hi + tol))[0]
    if not inside.size:  # a region between two centres: the two around it
        inside = np.nonzero((c >= lo - step) & (c <= hi + step))[0]
        if not inside.size:
            return inside
        margin = max(margin - 1, 0)
    first, last = max(int(inside[0]) - margin, 0), min(int(inside[-1]) + margin, len(c) - 1)
    return np.arange(first, last + 1)


def _squeeze_to_2d(arr: xr.DataArray, path: Path) -> xr.DataArray:
    extra = [d for d in arr.dims if arr.sizes[d] == 1 and d not in _X_NAMES + _Y_NAMES]
    if extra:
        arr = arr.isel({d: 0 for d in extra}, drop=True)
    if arr.ndim != 2:
        shape = " x ".join(f"{d}={n}" for d, n in arr.sizes.items())
        raise InvalidDEMError(
            f"DEM file {path} is {arr.ndim}-D ({shape}); a DEM is one 2-D "
            "grid: select one band or time step and save that"
        )
    return arr


def _spatial_dims(arr: xr.DataArray, path: Path) -> tuple[str, str]:
    names = [str(d) for d in arr.dims]
    lower = [n.lower() for n in names]
    x = next((names[i] for i, n in enumerate(lower) if n in _X_NAMES), None)
    y = next((names[i] for i, n in enumerate(lower) if n in _Y_NAMES), None)
    if x is None and y is None:
        return names[0], names[1]  # row-major convention: (rows, cols)
    if x is None or y is None or x == y:
        raise InvalidDEMError(f"DEM file {path}: cannot tell the x and y dimensions of {names}")
    return y, x


def _synthesise_coords(arr: xr.DataArray, path: Path, cell_size: float | None) -> xr.DataArray:
    a = cell_size
    if a is None:
        for key in ("cell_size", "spacing", "resolution", "res", "dx"):
            if key in arr.attrs:
                try:
                    a = CELL_SIZE.check(float(np.atleast_1d(arr.attrs[key])[0]), key)
                except (InvalidParameterError, TypeError, ValueError):
                    a = None
                break
    if a is None:
        raise InvalidDEMError(
            f"DEM file {path} has no coordinates and no cell size; pass "
            "cell_size=... (--cell-size) in metres"
        )
    rows, cols = arr.shape
    log.info("DEM %s has no coordinates: using cells of %g m from (0, 0)", path, a)
    return arr.assign_coords(x=(np.arange(cols) + 0.5) * a, y=(rows - np.arange(rows) - 0.5) * a)


def _crs_of(arr: xr.DataArray):
    from pyproj import CRS

    try:
        crs = arr.rio.crs
    except Exception:  # rioxarray may not know this array's layout
        crs = None
    if crs is not None:
        return _horizontal(CRS.from_user_input(crs))
    for key in ("crs_wkt", "crs", "spatial_ref"):
        if key in arr.attrs:
            try:
                return _horizontal(CRS.from_user_input(arr.attrs[key]))
            except Exception:
                continue
    return None


def _horizontal(crs):
    """The horizontal part of a compound CRS (a BAG's is projected + a vertical datum)."""
    if crs.is_compound:
        return next((c for c in crs.sub_crs_list if not c.is_vertical), crs)
    return crs


def _is_geographic(arr: xr.DataArray, crs, xdim: str, ydim: str) -> bool:
    if crs is not None:
        return bool(crs.is_geographic)
    if xdim.lower() in ("lon", "longitude") or ydim.lower() in ("lat", "latitude"):
        return True
    units = str(arr["x"].attrs.get("units", "")).lower()
    return units.startswith("degree")


# a grid without a CRS whose cells are smaller than this (in its own units) and whose
# coordinates are longitudes and latitudes is a lon/lat grid: no seabed grid has cells of a
# centimetre, and an ESRI ASCII grid in degrees often comes without its .prj
DEGREE_CELL_BELOW = 0.01


def _degree_cell(arr: xr.DataArray) -> float | None:
    """The cell side of a grid without a CRS that is a lon/lat grid (:data:`DEGREE_CELL_BELOW`),
    else None."""
    x = np.asarray(arr["x"].values, dtype=np.float64)
    y = np.asarray(arr["y"].values, dtype=np.float64)
    if len(x) < 2 or len(y) < 2:
        return None
    cell = float(max(abs(x[1] - x[0]), abs(y[1] - y[0])))
    lonlat = np.abs(y).max() <= 90.0 and x.min() >= -180.0 and x.max() <= 360.0
    return cell if cell < DEGREE_CELL_BELOW and lonlat else None


def _depth_sign(arr: xr.DataArray, path: Path) -> int:
    if str(arr.attrs.get("positive", "")).lower() == "down":
        notice(log, "DEM %s has positive='down' (depths): negating to elevation, positive up", path)
        return -1
    return 1


# a lon/lat grid is projected onto one azimuthal equidistant grid around its centre: beyond
# this angle from the centre (degrees of arc) its distortion grows past a few per cent
MAX_GEOGRAPHIC_RADIUS = 30.0


def _unwrapped(arr: xr.DataArray) -> xr.DataArray:
    """A lon/lat grid whose longitudes cross the antimeridian as ``..., 179.9, -179.9, ...``
    with longitudes continuing past 180 instead (one drop of more than 180 degrees)."""
    lon = np.asarray(arr["x"].values, dtype=np.float64)
    d = np.diff(lon)
    drops = np.flatnonzero(d < -180.0)
    if lon.size < 3 or drops.size != 1 or np.sum(d > 0) != d.size - 1:
        return arr
    fixed = lon.copy()
    fixed[drops[0] + 1 :] += 360.0
    return arr.assign_coords(x=fixed)


def _check_geographic_extent(path: Path, lat: np.ndarray, lon: np.ndarray) -> None:
    """Refuse a lon/lat grid reaching farther than :data:`MAX_GEOGRAPHIC_RADIUS` from its
    centre: one projected grid cannot hold it without great distortion (a whole globe has no
    such grid at all)."""
    lat0, lon0 = math.radians(float(lat.mean())), math.radians(float(lon.mean()))
    far = 0.0
    for la in (lat.min(), lat.max()):
        for lo in (lon.min(), lon.max()):
            p, q = math.radians(float(la)), math.radians(float(lo))
            c = math.sin(lat0) * math.sin(p) + math.cos(lat0) * math.cos(p) * math.cos(q - lon0)
            far = max(far, math.degrees(math.acos(min(1.0, max(-1.0, c)))))
    if far > MAX_GEOGRAPHIC_RADIUS or float(np.ptp(lon)) > 2 * MAX_GEOGRAPHIC_RADIUS / max(
        math.cos(lat0), 0.05
    ):
        raise InvalidDEMError(
            f"DEM file {path} is a lon/lat grid reaching {far:.0f} degrees of arc from its "
            f"centre (latitudes {lat.min():g} to {lat.max():g}, longitudes {lon.min():g} to "
            f"{lon.max():g}): one projected grid holds at most {MAX_GEOGRAPHIC_RADIUS:g} without "
            "great distortion; give a bbox around the region to plan on"
        )


def check_dem(dem, *, floating: bool = False) -> float:
    """Validate a canonical DEM argument (before any graph is built); return its cell size."""
    if not isinstance(dem, xr.DataArray):
        raise InvalidParameterError(
            f"`dem` must be an xarray.DataArray, got {type(dem).__name__}; "
            "open it with pipeline.open_dem"
        )
    if dem.ndim != 2 or dem.dims != ("y", "x"):
        raise InvalidDEMError(
            f"`dem` must be 2-D with dims ('y', 'x'), got dims {dem.dims}; "
            "open it with pipeline.open_dem"
        )
    if floating and dem.dtype.kind != "f":
        raise InvalidDEMError(f"`dem` must hold floating-point elevations, got {dem.dtype}")
    return cell_size(dem)


def require_valid_cells(dem: xr.DataArray, message: str) -> None:
    """Raise InvalidDEMError(message) when every cell of ``dem`` is NaN. A lazy DEM is read
    chunk by chunk only as far as needed: its first chunk, then (only when that one is all
    NaN) the rest in one pass."""
    data = dem.data
    if isinstance(data, da.Array):
        first = data.blocks[(0,) * data.ndim]
        if bool(np.isfinite(first).any().compute()):
            return
        anyvalid = np.isfinite(data).any().compute()
    else:
        anyvalid = np.isfinite(data).any()
    if not bool(anyvalid):
        raise InvalidDEMError(message)


def _check_canonical(dem) -> None:
    check_dem(dem)
    if "cell_size" not in dem.attrs:
        raise InvalidDEMError(
            "`dem` has no 'cell_size' attribute; open it with pipeline.open_dem "
            "or pipeline.synthetic_dem"
        )
