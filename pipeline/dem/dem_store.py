"""DEM stores: a canonical DEM written to a Zarr v3 store atomically and in bands (never the
whole map in memory), its chunks listed as written, and read back through a guard that
says which chunk is missing or damaged.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import dask.array as da
import numpy as np
import xarray as xr

from .._types import Chunks
from ..exceptions import InvalidDEMError
from ..params import DEFAULT_CHUNK, chunks2d
from ..store.bands import store_in_bands
from ..store.paths import atomic_path
from ..store.schema import GRID_MAPPING, grid_mapping, layer_codec
from .canonical import _check_canonical, construction_figures, warp_figures
from .readers import reading
from .reproject import combine_stats

log = logging.getLogger(__name__)

CANONICAL_ATTR = "pipeline_dem_version"


CANONICAL_VERSION = 1


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
    figures = warp_figures(dem)
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
            parts = store_in_bands(data, grid, progress=_band_log(store), also=figures or ())
        if figures:  # the resample's raise and coverage, recorded with the store
            row = construction_figures(combine_stats(parts), dem.attrs.get("source", store))
            zarr.open_array(str(tmp / "elevation"), mode="r+").attrs.update(row)
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
