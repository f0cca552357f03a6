"""DEM files read as they are: GeoTIFF, BAG and ESRI ASCII through rasterio, NetCDF (and old GMT
.grd) through xarray, Zarr stores; the elevation (and uncertainty) variable found, the
file's chunks, and the readers' errors turned into one line naming the file.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import xarray as xr

from ..exceptions import InvalidDEMError
from ..params import DEFAULT_CHUNK

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


@dataclass(frozen=True)
class Reader:
    """One family of DEM files: how a file of it is recognised and read.

    ``read(path, chunks, variable, uncertainty)`` returns the elevation and the uncertainty
    (or None) as lazy DataArrays in the file's own coordinates; ``chunks(path)`` the sides of
    the file's own chunks or tiles (None when it has none). A file is recognised by its suffix,
    else by its first bytes (``magic``); a directory by a file inside it (``inside``).
    """

    name: str
    formats: str  # as the message for an unknown file lists them
    read: Callable[..., tuple[xr.DataArray, xr.DataArray | None]]
    chunks: Callable[[Path], tuple[int, int] | None]
    suffixes: tuple[str, ...] = ()
    magic: tuple[bytes, ...] = ()
    inside: tuple[str, ...] = ()
    tiled: bool = False  # a region is best read in the file's own tiles


def reader_of(path: Path) -> Reader:
    """The reader of the DEM file or directory ``path``; an :class:`InvalidDEMError` naming
    the formats read when it is none of them."""
    suffix = path.suffix.lower()
    if path.is_dir():
        for reader in READERS.values():
            if reader.inside and (
                suffix in reader.suffixes or any((path / f).exists() for f in reader.inside)
            ):
                return reader
        raise InvalidDEMError(
            f"DEM path {path} is a directory but not a Zarr store (no zarr.json or .zgroup inside)"
        )
    files = [r for r in READERS.values() if not r.inside]
    for reader in files:
        if suffix in reader.suffixes:
            return reader
    with open(path, "rb") as fh:
        opening = fh.read(8)
    for reader in files:
        if any(opening.startswith(m) for m in reader.magic):
            return reader
    *most, last = (r.formats for r in READERS.values())
    known = f"{', '.join(most)} or {last}"
    raise InvalidDEMError(f"DEM file {path}: unknown format (suffix {suffix!r}); use {known}")


def read(
    path: Path, reader: Reader, chunks, variable: str | None, uncertainty: str | None = None
) -> tuple[xr.DataArray, xr.DataArray | None]:
    """The elevation of the file, and its uncertainty band or variable when it has one; what
    the reader cannot open is one :class:`InvalidDEMError` naming the file. Read in chunks,
    never a whole large file at once (``chunks`` None: in memory)."""
    try:
        return reader.read(path, chunks, variable, uncertainty)
    except InvalidDEMError:
        raise
    except Exception as exc:  # the readers raise many types; one clear message for all
        raise InvalidDEMError(f"cannot read DEM file {path}: {reader_message(exc)}") from exc


def _read_gdal(path: Path, chunks, variable, uncertainty):
    """GeoTIFF, BAG and ESRI ASCII through rasterio, in chunks of the requested side."""
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


def _gdal_chunks(path: Path):
    import rasterio

    with rasterio.open(path) as src:
        return tuple(int(v) for v in src.block_shapes[0])


def _read_netcdf(path: Path, chunks, variable, uncertainty):
    """NetCDF and GMT grids through xarray, in dask's automatic chunks (about 128 MiB)."""
    ds = xr.open_dataset(path, chunks=None if chunks is None else "auto")
    return _from_dataset(ds, path, variable, uncertainty)


def _netcdf_chunks(path: Path):
    import netCDF4

    with netCDF4.Dataset(path) as nc:
        for var in nc.variables.values():
            if var.ndim >= 2:
                ch = var.chunking()
                return None if ch == "contiguous" else tuple(int(v) for v in ch[-2:])
    return None


def _read_zarr(path: Path, chunks, variable, uncertainty):
    """A Zarr store in its own chunks; a DEM store this tool wrote keeps its record of the
    chunks it left unwritten (all no-data), older ones are read as they are."""
    from .dem_store import EMPTY_CHUNKS_ATTR, _guarded

    ds = xr.open_zarr(path, chunks=None if chunks is None else {}, consolidated=False)
    elev, sigma = _from_dataset(ds, path, variable, uncertainty)
    unstored = ds.attrs.get(EMPTY_CHUNKS_ATTR)
    if unstored is not None and elev.name == "elevation":
        elev = _guarded(path, elev, unstored)
    return elev, sigma


def _zarr_chunks(path: Path):
    import zarr

    group = zarr.open_group(path, mode="r")
    name = "elevation" if "elevation" in group else next(iter(group.array_keys()))
    return tuple(int(v) for v in group[name].chunks[-2:])


def _from_dataset(ds: xr.Dataset, path: Path, variable, uncertainty):
    if _is_old_gmt(ds):
        if uncertainty is not None:
            raise InvalidDEMError(f"DEM file {path} (a 1-D GMT grid) has no {uncertainty!r}")
        return _from_old_gmt(ds, path), None
    gridded = [str(k) for k, v in ds.data_vars.items() if v.ndim >= 2]
    name = _uncertainty_name(gridded, uncertainty, path, "variable")
    elev = _pick_variable(ds, path, variable, exclude=name)
    return elev, (None if name is None else ds[name])


# the DEM formats read, by name; a new format is a reader function and one line here
READERS = {
    # GDAL reads these through rasterio: GeoTIFF, BAG (the Bathymetric Attributed Grid, HDF5:
    # an elevation band and an uncertainty band) and the ESRI ASCII grid (EMODnet's and many
    # survey offices' exchange format; its CRS from the .prj beside it)
    "gdal": Reader(
        "gdal",
        "a GeoTIFF (.tif), a BAG (.bag), an ESRI ASCII grid (.asc)",
        _read_gdal,
        _gdal_chunks,
        suffixes=(".tif", ".tiff", ".gtiff", ".geotiff", ".bag", ".asc"),
        magic=(b"II", b"MM"),
        tiled=True,
    ),
    "netcdf": Reader(
        "netcdf",
        "a NetCDF or GMT grid (.nc, .grd)",
        _read_netcdf,
        _netcdf_chunks,
        suffixes=(".nc", ".nc4", ".cdf", ".grd", ".netcdf"),
        magic=(b"CDF", b"\x89HDF"),
    ),
    "zarr": Reader(
        "zarr",
        "a Zarr store",
        _read_zarr,
        _zarr_chunks,
        suffixes=(".zarr",),
        inside=("zarr.json", ".zgroup"),
    ),
}


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
        return reader_of(path).chunks(path)
    except Exception:  # noqa: BLE001 - only for the description; open_dem says what is wrong
        return None


def _pick_variable(
    ds: xr.Dataset, path: Path, variable: str | None, exclude: str | None = None
) -> xr.DataArray:
    """The elevation variable of ``ds`` (``variable``, else its one 2-D variable, else the one
    of an elevation's name), with the dataset's CRS when that lies in a variable of its own
    (:func:`_with_grid_mapping`)."""
    return _with_grid_mapping(ds, _choose_variable(ds, path, variable, exclude))


def _with_grid_mapping(ds: xr.Dataset, arr: xr.DataArray) -> xr.DataArray:
    """``arr`` with the CRS of a lone grid-mapping variable of ``ds`` (a 0-D variable holding
    ``crs_wkt`` or ``spatial_ref``, as rioxarray writes ``spatial_ref``) when ``arr`` names
    none: a store written by ``to_zarr`` keeps the variable but may lose the link to it."""
    if any(k in arr.attrs for k in ("crs_wkt", "crs", "spatial_ref", "grid_mapping")):
        return arr
    if "grid_mapping" in arr.encoding or any(
        "crs_wkt" in arr[c].attrs or "spatial_ref" in arr[c].attrs for c in arr.coords
    ):
        return arr
    found = [
        v.attrs.get("crs_wkt") or v.attrs.get("spatial_ref")
        for v in ds.variables.values()
        if v.ndim == 0 and (v.attrs.get("crs_wkt") or v.attrs.get("spatial_ref"))
    ]
    if len(found) != 1:
        return arr
    return arr.assign_attrs(crs_wkt=str(found[0]))


def _choose_variable(
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
