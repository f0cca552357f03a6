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
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import dask.array as da
import numpy as np
import xarray as xr

from .._types import Box, Chunks, DEMLike
from ..exceptions import InvalidDEMError, InvalidParameterError, notice
from ..params import CELL_SIZE, DEFAULT_CHUNK, DEM, check_region, chunks2d
from ..runtime.jit import njit
from ..store.bands import store_in_bands
from ..store.paths import atomic_path, has_scheme
from ..store.schema import GRID_MAPPING, grid_mapping, layer_codec

log = logging.getLogger(__name__)

CANONICAL_ATTR = "pipeline_dem_version"
CANONICAL_VERSION = 1

_X_NAMES = ("x", "lon", "longitude", "easting", "east", "xc")
_Y_NAMES = ("y", "lat", "latitude", "northing", "north", "yc")
_ELEVATION_NAMES = (
    "elevation",
    "z",
    "band_data",
    "Band1",
    "topo",
    "bathymetry",
    "height",
    "depth",
    "altitude",
    "elev",
)
# names of a survey's vertical uncertainty (one standard deviation, metres), matched
# case-insensitively: a BAG's second band is "uncertainty"
_UNCERTAINTY_NAMES = ("uncertainty", "sigma", "stdev", "std", "tvu", "elevation_uncertainty")
_NETCDF_SUFFIXES = (".nc", ".nc4", ".cdf", ".grd", ".netcdf")
# GDAL reads these through rasterio: GeoTIFF, BAG (the Bathymetric Attributed Grid, HDF5: an
# elevation band and an uncertainty band) and the ESRI ASCII grid (EMODnet's and many survey
# offices' exchange format; its CRS from the .prj beside it)
_TIFF_SUFFIXES = (".tif", ".tiff", ".gtiff", ".geotiff", ".bag", ".asc")


# --------------------------------------------------------------------------- public API


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
    attrs = dict(dem.attrs)
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


def open_dem(
    path: str | os.PathLike,
    chunks: Chunks = DEFAULT_CHUNK,
    *,
    variable: str | None = None,
    cell_size: float | None = None,
    resolution: float | None = None,
    validate: bool = True,
    bbox: Box | None = None,
    bbox_xy: Box | None = None,
    uncertainty_k: float | None = None,
    uncertainty: str | None = None,
) -> xr.DataArray:
    """Open a DEM file as the canonical elevation DataArray.

    Parameters
    ----------
    path : str or path
        A GeoTIFF (``.tif``), a BAG (``.bag``), an ESRI ASCII grid (``.asc``, its CRS from the
        ``.prj`` beside it), a NetCDF or GMT grid (``.nc``, ``.grd``), or a Zarr store (a
        directory, usually ``.zarr``).
    chunks : int, (int, int) or None
        Dask chunk sides; ``None`` loads the grid into memory as numpy.
    variable : str, optional
        The data variable to use in a NetCDF or Zarr file with several.
    cell_size : float, optional
        Cell side in metres for a grid that has no coordinates.
    resolution : float, optional
        Resample (bilinear) to square cells of this side in metres, keeping the extent: to
        plan a coarse survey grid at a finer step, or to choose the step a lon/lat grid is
        reprojected at (by default the geometric mean of its cells). A clearance needs cells
        of at most twice its size.
    validate : bool
        Check that the grid holds at least one valid cell (one pass over the data). Stores
        written by :func:`write_dem` were checked when written and skip this pass.
    bbox : (lon_min, lat_min, lon_max, lat_max), optional
        Read only this region (WGS84 degrees; a projected file needs a CRS): the cells whose
        centres lie within it, and one more on each side. Nothing outside it is read, as the
        file is read in chunks (a GeoTIFF in tiles, a NetCDF or Zarr file in its chunks).
    bbox_xy : (x_min, y_min, x_max, y_max), optional
        The same in the file's own coordinates (its units: metres, or degrees for a lon/lat
        grid). At most one of ``bbox`` and ``bbox_xy``.
    uncertainty_k : float, optional
        Plan on the shoal side of the survey's uncertainty band: the grid returned is
        ``elevation + k * sigma``, the highest the seabed can be at ``k`` standard deviations,
        so a clearance kept from it is at least ``clearance + k * sigma`` above the surveyed
        seabed at every cell. ``sigma`` is a BAG's uncertainty band, a GeoTIFF band or a
        NetCDF / Zarr variable named ``uncertainty`` (or sigma, stdev, std, tvu), or the one
        named by ``uncertainty``; a cell without sigma is no-data (never passable).
    uncertainty : str, optional
        The band description or variable name of sigma, when it is not one of those.

    Examples
    --------
    >>> dem = open_dem("seabed.tif", chunks=1024)  # doctest: +SKIP
    >>> dem.dims, dem.dtype, dem.attrs["cell_size"]  # doctest: +SKIP
    (('y', 'x'), dtype('float32'), 30.0)
    """
    if not isinstance(path, str | os.PathLike):
        raise InvalidDEMError(
            f"a DEM is a file path or an xarray DataArray with y and x coordinates in metres, "
            f"not a {type(path).__module__}.{type(path).__qualname__}; wrap an array as "
            "xr.DataArray(z, dims=('y', 'x'), coords={'y': ..., 'x': ...})"
        )
    if has_scheme(path):
        raise InvalidDEMError(
            f"DEM {path} is a URL: DEMs are read from local files (GeoTIFF, NetCDF, Zarr, BAG, "
            "ASCII grid); download it first (maps stores may live on object storage)"
        )
    path = Path(path)
    if not path.exists():
        raise InvalidDEMError(f"DEM file {path} does not exist")
    if not path.is_file() and not path.is_dir():  # a FIFO would block the read for ever
        raise InvalidDEMError(
            f"DEM file {path} is not a regular file (a device, a pipe or a socket); give the "
            "DEM file itself"
        )
    if cell_size is not None:
        cell_size = DEM.cell_size.check(cell_size)
    if resolution is not None:
        resolution = DEM.resolution.check(resolution)
    region = check_region(bbox, bbox_xy)
    if uncertainty_k is not None:
        uncertainty_k = DEM.uncertainty_k.check(uncertainty_k)
    if uncertainty is not None:
        uncertainty = DEM.uncertainty.check(uncertainty)
    kind = _kind_of(path)
    read_chunks = chunks
    if region is not None and chunks is not None and kind == "tiff":
        # a region is read in the file's own tiles (rechunked to ``chunks`` afterwards): a
        # dask chunk is read whole, so chunks of 1024^2 would read up to four times the tiles
        # a small region touches
        tile = file_chunks(path)
        if tile is not None and max(tile) < max(chunks2d(chunks, (2**31, 2**31))):
            read_chunks = max(tile)
    raw, sigma = _read(path, kind, read_chunks, variable, uncertainty)
    canonical = raw.attrs.get(CANONICAL_ATTR) == CANONICAL_VERSION
    if canonical and uncertainty_k is not None:
        raise InvalidParameterError(
            f"DEM store {path} is already a pipeline DEM store (one elevation layer): apply "
            "uncertainty_k when importing the survey file that holds the uncertainty band"
        )
    if uncertainty_k is not None:
        if sigma is None:
            raise InvalidDEMError(
                f"DEM file {path} has no uncertainty band or variable (looked for "
                f"{', '.join(_UNCERTAINTY_NAMES)}): name it with uncertainty=... "
                "(--uncertainty), or drop uncertainty_k"
            )
        raw = _shoal_surface(raw, sigma, uncertainty_k, path)
    elif sigma is not None:
        log.info(
            "DEM %s has an uncertainty band %r, not used: set uncertainty_k to plan on "
            "elevation + k * sigma",
            path,
            sigma.name,
        )
    if canonical and resolution is None:
        dem = _crop(raw, path, _crs_of(raw), False, region)
        if chunks is None:
            dem = dem.load()
        else:
            dem = dem.chunk(dict(zip(("y", "x"), chunks2d(chunks, dem.shape), strict=True)))
        return dem
    with reading(path):
        dem = _canonicalise(
            raw, path, chunks=chunks, cell_size=cell_size, resolution=resolution, region=region
        )
        if validate:
            require_valid_cells(dem, _no_valid_cells(path))
    if uncertainty_k is not None:
        dem.attrs.update(
            uncertainty_k=uncertainty_k,
            surface=f"elevation + {uncertainty_k:g} * {sigma.name} (the shoal side of the survey)",
        )
    return dem


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


def _holds_a_valid_cell(array: Path, stored: set) -> bool:
    """Whether the Zarr array just written holds a valid (non-NaN) cell: written without its
    empty chunks and with NaN as its fill value, it does exactly when a chunk was stored
    (``stored``, :func:`_stored_chunks`: no pass over the data); otherwise it is read back."""
    import zarr

    fill = zarr.open_array(array, mode="r").metadata.fill_value
    if fill is None or not np.isnan(fill):
        return bool(np.isfinite(da.from_zarr(str(array))).any().compute())
    return bool(stored)


# the root attribute of a DEM store listing the chunks not stored because all their cells
# are no-data (the fill value): any other chunk absent is damage
EMPTY_CHUNKS_ATTR = "unstored_chunks"


def _stored_chunks(array: Path) -> set:
    """The chunk indices ``(row, col)`` stored under the Zarr v3 array ``array`` (its
    ``c/<row>/<col>`` files)."""
    out = set()
    base = array / "c"
    for root, _dirs, files in os.walk(base):
        rel = Path(root).relative_to(base).parts
        for f in files:
            parts = (*rel, f)
            if len(parts) == 2 and all(p.isdigit() for p in parts):
                out.add((int(parts[0]), int(parts[1])))
    return out


def _guarded(path: Path, elev: xr.DataArray, unstored) -> xr.DataArray:
    """The elevation of this tool's DEM store ``path`` read so that damage is named: a chunk
    missing that held data (not among ``unstored``), or one that cannot be decoded, is one
    :class:`InvalidDEMError` naming the chunk (the reader would take the first for no-data
    and fail deep in a computation on the second)."""
    import zarr

    array = path / "elevation"
    rows, cols = zarr.open_array(str(array), mode="r").cdata_shape
    expected = {(i, j) for i in range(rows) for j in range(cols)}
    expected -= {tuple(c) for c in unstored}
    missing = sorted(expected - _stored_chunks(array))
    if missing:
        i, j = missing[0]
        more = f" and {len(missing) - 1} more" if len(missing) > 1 else ""
        raise InvalidDEMError(
            f"DEM store {path} is damaged: chunk c/{i}/{j} of its elevation is missing{more} "
            "(it held data); import the DEM again (pipeline dem import ... --overwrite, or "
            "pipeline run --overwrite)"
        )
    data = elev.data
    if not isinstance(data, da.Array):
        return elev
    guarded = da.map_blocks(
        _read_block,
        str(array),
        dtype=data.dtype,
        chunks=data.chunks,
        meta=np.empty((0, 0), data.dtype),
    )
    return elev.copy(data=guarded)


def _read_block(array: str, block_info=None):
    import zarr

    (r0, r1), (c0, c1) = block_info[None]["array-location"]
    try:
        return zarr.open_array(array, mode="r")[r0:r1, c0:c1]
    except Exception as exc:  # noqa: BLE001 - the codecs raise their own types
        i, j = block_info[None]["chunk-location"]
        what = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        store = str(Path(array).parent)
        raise InvalidDEMError(
            f"DEM store {store} is damaged: chunk c/{i}/{j} of its elevation cannot be decoded "
            f"({type(exc).__name__}: {what}); import the DEM again (pipeline dem import ... "
            "--overwrite, or pipeline run --overwrite)"
        ) from None


def _no_valid_cells(path) -> str:
    return (
        f"DEM file {path} holds no valid elevation: every cell is no-data (NaN or the file's "
        "nodata value)"
    )


def write_dem(
    dem: xr.DataArray,
    store: str | os.PathLike,
    *,
    chunks: Chunks = DEFAULT_CHUNK,
    overwrite: bool = False,
) -> Path:
    """Write ``dem`` as the canonical chunked Zarr (v3) store, atomically.

    The store is written beside ``store`` and moved into place only when complete. Chunk sides
    default to 1024 (a multiple of 64, so that coarsening by 2, 4, 8, 16, 32 or 64 needs no
    rechunk). Computation streams chunk by chunk on the current dask scheduler.
    """
    return _write_dem(dem, store, chunks, overwrite)


def _write_dem(dem, store, chunks, overwrite: bool, empty: str | None = None) -> Path:
    """:func:`write_dem`; with ``empty``, the grid written is also checked to hold a valid cell
    (from the chunks stored: no second pass over the file), else InvalidDEMError(empty) and
    nothing is left behind."""
    import zarr

    _check_canonical(dem)
    ch = chunks2d(chunks if chunks is not None else DEFAULT_CHUNK, dem.shape)
    for side in ch:
        if side % 64 and side not in dem.shape:
            log.warning(
                "chunk side %d is not a multiple of 64: coarsening may need a rechunk", side
            )
    data = dem.data if isinstance(dem.data, da.Array) else da.from_array(dem.data, chunks=ch)
    data = data.astype(np.float32).rechunk(ch)
    out = dem.copy(data=data)
    out.attrs[CANONICAL_ATTR] = CANONICAL_VERSION
    out.encoding = {}
    mapping = grid_mapping(out.attrs.get("crs_wkt"))
    if mapping is not None:  # the CRS the CF way too (rioxarray, GDAL), and GDAL's Zarr way
        out.attrs.update(mapping[1])
        out = out.assign_coords({GRID_MAPPING: mapping[0]})
    ds = out.to_dataset(name="elevation")
    ds.attrs = {"title": "pipeline DEM store", CANONICAL_ATTR: CANONICAL_VERSION}
    encoding = {"elevation": {"chunks": ch, "compressors": layer_codec()}}
    with atomic_path(store, kind="DEM", overwrite=overwrite) as tmp:
        with reading(dem.attrs.get("source", "")):
            # the metadata and coordinates, then the grid a band of chunk rows at a time (its
            # memory follows the band: store_in_bands); chunks that are all no-data (the fill
            # value, NaN) are not stored
            ds.to_zarr(
                tmp,
                mode="w",
                zarr_format=3,
                consolidated=False,
                encoding=encoding,
                write_empty_chunks=False,
                compute=False,
            )
            grid = zarr.open_array(
                str(tmp / "elevation"), mode="r+", config={"write_empty_chunks": False}
            )
            store_in_bands(data, grid, progress=_band_log(store))
        stored = _stored_chunks(tmp / "elevation")
        if empty is not None and not _holds_a_valid_cell(tmp / "elevation", stored):
            raise InvalidDEMError(empty)
        # the chunks left unstored (all no-data): any other found missing later is damage
        rows, cols = grid.cdata_shape
        unstored = [[i, j] for i in range(rows) for j in range(cols) if (i, j) not in stored]
        group = zarr.open_group(str(tmp), mode="r+", zarr_format=3)
        group.attrs[EMPTY_CHUNKS_ATTR] = unstored
    log.info(
        "wrote DEM store %s (%d x %d cells of %.6g m, chunks %s)",
        store,
        *dem.shape,
        dem.attrs["cell_size"],
        ch,
    )
    return Path(store)


def _band_log(store):
    """A progress callback of :func:`store_in_bands` for a DEM store's long writes: a log line
    each tenth of the bands, from 10 bands up."""

    def progress(done: int, total: int) -> None:
        if total >= 10 and done * 10 // total > (done - 1) * 10 // total:
            log.info("writing DEM store %s: %d of %d bands of chunk rows", store, done, total)

    return progress


@contextmanager
def reading(source) -> Iterator[None]:
    """Turn an error of the file readers raised inside the block (a damaged or truncated
    GeoTIFF or NetCDF file, found when its chunks are read lazily) into one
    :class:`InvalidDEMError` naming ``source``; errors of writing pass unchanged."""
    try:
        yield
    except Exception as exc:
        from rasterio.errors import RasterioError

        netcdf = isinstance(exc, RuntimeError) and ("NetCDF" in str(exc) or "HDF" in str(exc))
        if isinstance(exc, RasterioError) or netcdf:
            raise InvalidDEMError(f"cannot read DEM file {source}: {reader_message(exc)}") from exc
        raise


def reader_message(exc: BaseException) -> str:
    """A reader's error with what caused it (GDAL's own words come as the cause of rasterio's
    "Read failed. See previous exception for details.")."""
    parts, seen = [], set()
    while exc is not None and id(exc) not in seen and len(parts) < 3:
        seen.add(id(exc))
        text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        if text and "See previous exception" not in text:
            parts.append(text)
        elif text:
            parts.append(text.split(". See previous exception")[0])
        exc = exc.__cause__ or exc.__context__
    kept = [p for k, p in enumerate(parts) if not any(p in q for q in parts[:k])]
    return ": ".join(kept) or "unreadable"


def import_dem(
    source: str | os.PathLike,
    store: str | os.PathLike,
    *,
    chunks: Chunks = DEFAULT_CHUNK,
    variable: str | None = None,
    cell_size: float | None = None,
    resolution: float | None = None,
    overwrite: bool = False,
    bbox: Box | None = None,
    bbox_xy: Box | None = None,
    uncertainty_k: float | None = None,
    uncertainty: str | None = None,
) -> Path:
    """Open ``source`` with :func:`open_dem` (``bbox`` or ``bbox_xy``: only that region;
    ``uncertainty_k``: the shoal side of its uncertainty band) and write it as the canonical
    Zarr store, in one pass over the file (the check that it holds a valid cell is made on the
    chunks as they are written)."""
    dem = open_dem(
        source,
        chunks=chunks,
        variable=variable,
        cell_size=cell_size,
        resolution=resolution,
        bbox=bbox,
        bbox_xy=bbox_xy,
        uncertainty_k=uncertainty_k,
        uncertainty=uncertainty,
        validate=False,
    )
    return _write_dem(dem, store, chunks, overwrite, _no_valid_cells(source))


# --------------------------------------------------------------------------- reading


def _kind_of(path: Path) -> str:
    suffix = path.suffix.lower()
    if path.is_dir():
        if (path / "zarr.json").exists() or (path / ".zgroup").exists() or suffix == ".zarr":
            return "zarr"
        raise InvalidDEMError(
            f"DEM path {path} is a directory but not a Zarr store (no zarr.json or .zgroup inside)"
        )
    if suffix in _TIFF_SUFFIXES:
        return "tiff"
    if suffix in _NETCDF_SUFFIXES:
        return "netcdf"
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if magic[:2] in (b"II", b"MM"):
        return "tiff"
    if magic[:3] == b"CDF" or magic == b"\x89HDF":
        return "netcdf"
    raise InvalidDEMError(
        f"DEM file {path}: unknown format (suffix {suffix!r}); use a GeoTIFF (.tif), a BAG "
        "(.bag), an ESRI ASCII grid (.asc), a NetCDF or GMT grid (.nc, .grd) or a Zarr store"
    )


def _read(
    path: Path, kind: str, chunks, variable: str | None, uncertainty: str | None = None
) -> tuple[xr.DataArray, xr.DataArray | None]:
    """The elevation of the file, and its uncertainty band or variable when it has one."""
    # read in chunks, never a whole large file at once: a GeoTIFF in chunks of the requested
    # side, a NetCDF file in dask's automatic chunks (about 128 MiB), a Zarr store in its own
    dask_chunks = None if chunks is None else {}
    unstored = None
    try:
        if kind == "tiff":
            import rioxarray

            side = chunks if isinstance(chunks, int) else DEFAULT_CHUNK
            tif_chunks = None if chunks is None else {"band": 1, "y": side, "x": side}
            arr = rioxarray.open_rasterio(path, masked=True, chunks=tif_chunks)
            if isinstance(arr, list | xr.Dataset):
                raise InvalidDEMError(
                    f"DEM file {path} holds several subdatasets; "
                    "export the elevation band to its own GeoTIFF"
                )
            _north_up(arr, path)
            return _split_bands(arr, path, variable, uncertainty)
        if kind == "netcdf":
            ds = xr.open_dataset(path, chunks=None if chunks is None else "auto")
        else:
            ds = xr.open_zarr(path, chunks=dask_chunks, consolidated=False)
            unstored = ds.attrs.get(EMPTY_CHUNKS_ATTR)
    except InvalidDEMError:
        raise
    except Exception as exc:  # the readers raise many types; one clear message for all
        raise InvalidDEMError(f"cannot read DEM file {path}: {reader_message(exc)}") from exc
    if _is_old_gmt(ds):
        if uncertainty is not None:
            raise InvalidDEMError(f"DEM file {path} (a 1-D GMT grid) has no {uncertainty!r}")
        return _from_old_gmt(ds, path), None
    gridded = [str(k) for k, v in ds.data_vars.items() if v.ndim >= 2]
    name = _uncertainty_name(gridded, uncertainty, path, "variable")
    elev = _pick_variable(ds, path, variable, exclude=name)
    if kind == "zarr" and unstored is not None and elev.name == "elevation":
        elev = _guarded(path, elev, unstored)  # a store this tool wrote (older ones: as read)
    return elev, (None if name is None else ds[name])


def _north_up(arr: xr.DataArray, path: Path) -> None:
    """Refuse a raster whose grid is not north-up: a geotransform with rotation or skew terms,
    or georeferencing by ground control points only. Its cells have no x and y coordinates
    of their own, and a cell size given in their place would put it kilometres off."""
    t = arr.rio.transform(recalc=False)
    warp = "warp it to a north-up grid first (gdalwarp -t_srs <its CRS> in.tif out.tif)"
    if t.b != 0.0 or t.d != 0.0:
        raise InvalidDEMError(
            f"DEM file {path} is rotated or skewed (its geotransform's rotation terms are "
            f"{t.b:g} and {t.d:g}); {warp}"
        )
    gcps = None
    try:
        gcps = arr.rio.get_gcps()
    except Exception:  # noqa: BLE001 - no GCPs: rioxarray raises or returns None by version
        gcps = None
    if gcps is not None and len(getattr(gcps, "features", gcps) or []) and t.is_identity:
        raise InvalidDEMError(
            f"DEM file {path} is georeferenced by ground control points only; {warp}"
        )


def _uncertainty_name(names, wanted: str | None, path: Path, what: str) -> str | None:
    """Which of ``names`` (bands or variables) holds sigma: ``wanted`` (it must exist), else
    the first of the usual names, else None."""
    if wanted is not None:
        if wanted not in names:
            raise InvalidDEMError(
                f"DEM file {path} has no {what} {wanted!r} (uncertainty); it has {list(names)}"
            )
        return wanted
    lower = {n.lower(): n for n in names if n}
    return next((lower[n] for n in _UNCERTAINTY_NAMES if n in lower), None)


def _split_bands(arr: xr.DataArray, path: Path, variable, uncertainty):
    """The elevation band of a raster and its uncertainty band (by their descriptions: a BAG's
    are "elevation" and "uncertainty"); a one-band raster is its elevation."""
    if "band" not in arr.dims or arr.sizes["band"] == 1:
        if uncertainty is not None:
            raise InvalidDEMError(
                f"DEM file {path} has one band, so no uncertainty band {uncertainty!r}"
            )
        return arr, None
    desc = arr.attrs.get("long_name")
    names = [str(d) for d in desc] if isinstance(desc, tuple | list) else []
    names += [""] * (arr.sizes["band"] - len(names))
    names = [n or f"band{i + 1}" for i, n in enumerate(names)]  # undescribed bands
    su = _uncertainty_name(names, uncertainty, path, "band")
    if variable is not None:
        if variable not in names:
            raise InvalidDEMError(f"DEM file {path} has no band {variable!r}; it has {names}")
        ei = names.index(variable)
    else:
        lower = [n.lower() for n in names]
        ei = next((lower.index(n) for n in _ELEVATION_NAMES if n in lower), None)
        if ei is None:
            raise InvalidDEMError(
                f"DEM file {path} has {len(names)} bands (described {names}) and none is "
                "named elevation: name the elevation band with variable=... (--variable)"
            )

    def band(i):
        out = arr.isel(band=i, drop=True)
        out.attrs = {**arr.attrs, "long_name": names[i]}
        return out.rename(names[i])

    return band(ei), (None if su is None else band(names.index(su)))


def file_chunks(path: str | os.PathLike) -> tuple[int, int] | None:
    """The chunk (or tile) sides a DEM file is stored in, or None when it has none."""
    path = Path(path)
    try:
        kind = _kind_of(path)
        if kind == "tiff":
            import rasterio

            with rasterio.open(path) as src:
                return tuple(int(v) for v in src.block_shapes[0])
        if kind == "zarr":
            import zarr

            group = zarr.open_group(path, mode="r")
            name = "elevation" if "elevation" in group else next(iter(group.array_keys()))
            return tuple(int(v) for v in group[name].chunks[-2:])
        import netCDF4

        with netCDF4.Dataset(path) as nc:
            for var in nc.variables.values():
                if var.ndim >= 2:
                    ch = var.chunking()
                    return None if ch == "contiguous" else tuple(int(v) for v in ch[-2:])
    except Exception:  # noqa: BLE001 - only for the description; open_dem says what is wrong
        return None
    return None


def _pick_variable(
    ds: xr.Dataset, path: Path, variable: str | None, exclude: str | None = None
) -> xr.DataArray:
    if variable is not None:
        if variable not in ds.data_vars:
            raise InvalidDEMError(
                f"DEM file {path} has no variable {variable!r}; "
                f"it has {sorted(map(str, ds.data_vars))}"
            )
        return ds[variable]
    gridded = [k for k, v in ds.data_vars.items() if v.ndim >= 2 and k != exclude]
    if not gridded:
        raise InvalidDEMError(
            f"DEM file {path} has no 2-D variable "
            f"(variables: {sorted(map(str, ds.data_vars)) or 'none'})"
        )
    if len(gridded) == 1:
        return ds[gridded[0]]
    for name in _ELEVATION_NAMES:
        if name in gridded:
            return ds[name]
    raise InvalidDEMError(
        f"DEM file {path} has several 2-D variables {sorted(map(str, gridded))}; "
        "name the elevation with variable=... (--variable)"
    )


def _is_old_gmt(ds: xr.Dataset) -> bool:
    return {"x_range", "y_range", "dimension", "z"} <= set(ds.variables) and ds["z"].ndim == 1


def _from_old_gmt(ds: xr.Dataset, path: Path) -> xr.DataArray:
    """The 1-D GMT grid format (GMT 4 ``=cf``): z is a flat row-major array, top row first."""
    nx, ny = (int(v) for v in np.asarray(ds["dimension"].values))
    x0, x1 = (float(v) for v in np.asarray(ds["x_range"].values))
    y0, y1 = (float(v) for v in np.asarray(ds["y_range"].values))
    pixel = int(ds["z"].attrs.get("node_offset", 0)) == 1
    z = np.asarray(ds["z"].values, dtype=np.float64)
    if z.size != nx * ny:
        raise InvalidDEMError(f"GMT grid {path}: z has {z.size} values, dimension says {nx} x {ny}")
    if pixel:  # cell-centre (pixel) registration: ranges are the outer edges
        x = x0 + (np.arange(nx) + 0.5) * (x1 - x0) / nx
        y = y1 - (np.arange(ny) + 0.5) * (y1 - y0) / ny
    else:  # gridline registration: ranges are the outer nodes
        x = np.linspace(x0, x1, nx)
        y = np.linspace(y1, y0, ny)
    arr = xr.DataArray(
        z.reshape(ny, nx), dims=("y", "x"), coords={"x": x, "y": y}, attrs=dict(ds["z"].attrs)
    )
    xunits = str(ds["x_range"].attrs.get("units", "")).lower()
    if "deg" in xunits:
        arr = arr.rename(y="lat", x="lon")
    return arr


# --------------------------------------------------------------------------- canonical form


def _canonicalise(
    arr: xr.DataArray,
    path: Path,
    *,
    chunks,
    cell_size: float | None,
    resolution: float | None = None,
    region: tuple | None = None,
) -> xr.DataArray:
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
    arr = _crop(arr, path, crs, geographic, region)  # before anything reads a value
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
    values = _regularise(values.where(np.isfinite(values)), path)
    if geographic:
        values, crs = _reproject_geographic(values, path, crs, resolution, chunks)
    else:
        dx, dy = abs(_spacing(values, "x", path)), abs(_spacing(values, "y", path))
        if not math.isclose(dx, dy, rel_tol=1e-4) or (
            resolution is not None and not math.isclose(dx, resolution, rel_tol=1e-4)
        ):
            values = _resample_square(values, path, dx, dy, crs, resolution)
    a = abs(_spacing(values, "x", path))
    attrs.update(cell_size=float(a), units="m", positive="up", source=str(path))
    if crs is not None:
        attrs["crs_wkt"] = crs.to_wkt()
    out = values.astype(np.float32)
    out.name = "elevation"
    out.attrs = attrs
    out.encoding = {}
    if chunks is None:
        return out.load() if isinstance(out.data, da.Array) else out
    return out.chunk(dict(zip(("y", "x"), chunks2d(chunks, out.shape), strict=True)))


def _crop(arr: xr.DataArray, path: Path, crs, geographic: bool, region) -> xr.DataArray:
    """The cells of ``arr`` (dims y, x with 1-D coordinates) whose centres lie in the region,
    and one more on each side, selected lazily (only their chunks are ever read)."""
    if region is None:
        return arr
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
    ax = abs(x[1] - x[0]) if len(x) > 1 else 0.0
    ay = abs(y[1] - y[0]) if len(y) > 1 else 0.0
    cols = np.nonzero((x >= box[0] - ax) & (x <= box[2] + ax))[0]
    rows = np.nonzero((y >= box[1] - ay) & (y <= box[3] + ay))[0]
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
    return out


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


def _regularise(values: xr.DataArray, path: Path) -> xr.DataArray:
    """Resample monotonic but unevenly spaced axes (e.g. Mercator latitudes) to even steps."""
    for dim in ("y", "x"):
        step, even = _step(values, dim, path)
        c = np.asarray(values[dim].values, dtype=np.float64)
        if even:
            values = values.assign_coords({dim: c[0] + step * np.arange(c.size)})
            continue
        d = np.diff(c)
        notice(
            log,
            "DEM %s: %s coordinates are unevenly spaced (steps %.6g to %.6g): "
            "resampling linearly onto an even grid",
            path,
            dim,
            d.min(),
            d.max(),
        )
        values = values.load().interp({dim: c[0] + step * np.arange(c.size)}, method="linear")
    return values


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
