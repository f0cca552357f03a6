"""Opening a DEM (:func:`open_dem`) from a file or a store, as the canonical DEM every later
stage takes, and importing it into a DEM store (:func:`import_dem`).
"""

from __future__ import annotations

import inspect
import logging
import os
from pathlib import Path

import xarray as xr

from .._types import Box, Chunks
from ..exceptions import InvalidDEMError, InvalidParameterError
from ..params import DEFAULT_CHUNK, DEM, check_region, chunks2d
from ..store.paths import has_scheme
from .canonical import _canonicalise, _crop, _crs_of, _shoal_surface, require_valid_cells
from .dem_store import CANONICAL_ATTR, CANONICAL_VERSION, _no_valid_cells, _write_dem
from .readers import _UNCERTAINTY_NAMES, file_chunks, read, reader_of, reading

log = logging.getLogger(__name__)


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
    reader = reader_of(path)
    read_chunks = chunks
    if region is not None and chunks is not None and reader.tiled:
        # a region is read in the file's own tiles (rechunked to ``chunks`` afterwards): a
        # dask chunk is read whole, so chunks of 1024^2 would read up to four times the tiles
        # a small region touches
        tile = file_chunks(path)
        if tile is not None and max(tile) < max(chunks2d(chunks, (2**31, 2**31))):
            read_chunks = max(tile)
    raw, canonical, sigma_name = _surface(
        path, reader, read_chunks, variable, uncertainty_k, uncertainty
    )
    if canonical and resolution is None:
        dem, _ = _crop(raw, path, _crs_of(raw), False, region)
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
            surface=f"elevation + {uncertainty_k:g} * {sigma_name} (the shoal side of the survey)",
        )
    return dem


def read_source(path: Path, variable=None, uncertainty_k=None, uncertainty=None):
    """The grid of the DEM file ``path`` as read (its own coordinates, no resample), with the
    shoal side of its uncertainty band when ``uncertainty_k`` is given."""
    if not path.exists():
        raise InvalidDEMError(f"DEM file {path} does not exist")
    if uncertainty_k is not None:
        uncertainty_k = DEM.uncertainty_k.check(uncertainty_k)
    return _surface(path, reader_of(path), DEFAULT_CHUNK, variable, uncertainty_k, uncertainty)[0]


def _surface(path, reader, chunks, variable, uncertainty_k, uncertainty):
    """The file's elevation (or elevation + k sigma) as read, whether it is a DEM store of
    this tool's, and the name of its uncertainty (or None)."""
    raw, sigma = read(path, reader, chunks, variable, uncertainty)
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
    return raw, canonical, None if sigma is None else sigma.name


def import_dem(
    source: str | os.PathLike, store: str | os.PathLike, *, overwrite: bool = False, **options
) -> Path:
    """Open ``source`` with :func:`open_dem` and write it as the canonical Zarr store, in one
    pass over the file (the check that it holds a valid cell is made on the chunks as they are
    written).

    ``options`` are :func:`open_dem`'s keywords (``chunks``, ``bbox`` or ``bbox_xy``: only
    that region, ``uncertainty_k``: the shoal side of its uncertainty band, ...); the store is
    written in ``chunks``. ``overwrite`` replaces a DEM store this tool wrote, never another
    path."""
    known = [p for p in inspect.signature(open_dem).parameters if p not in ("path", "validate")]
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise InvalidParameterError(
            f"import_dem has no option {', '.join(map(repr, unknown))}; "
            f"it takes overwrite and open_dem's {', '.join(known)}"
        )
    dem = open_dem(source, **options, validate=False)
    chunks = options.get("chunks", DEFAULT_CHUNK)
    return _write_dem(dem, store, chunks, overwrite, _no_valid_cells(source))
