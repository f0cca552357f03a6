"""The maps store: one Zarr (v3) store per DEM and parameter set (docs/method.md section 1).

It holds ``elevation``, ``safety``, ``passable``, ``accumulation``, ``ridge`` and
``component``, chunked identically, every chunk written, with the parameters, a content hash
of the input DEM and a signature of those attributes. It is written once, atomically, and read
by every mission (:mod:`pipeline.store`).

The build runs as streaming passes, each a dask computation that reads its input chunk by
chunk, so that no worker holds more than a chunk or two plus perimeter data: (1) every tile
is filled once, its local fill and label indices go to scratch tiles, and the spill edges
to a small global solve; (2) the fill is finished elementwise per tile (plus a one-cell halo),
its D8 codes go to the scratch tiles and the flow summaries to the second global solve; (3)
every layer is written (the accumulation from the stored codes and the flow solve); (4) the
passable layer is labelled tile by tile, the labels that touch across tile borders joined in a
third small solve, and the component layer written (:mod:`pipeline.components`). The scratch
stores are removed at the end.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import time
from pathlib import Path

import dask
import dask.array as da
import numpy as np
import xarray as xr
import zarr
from numba import njit

from ._io import (
    WINDOW_LAYERS,
    is_url,
    join,
    layer_encoding,
    location,
    remove_settled,
    remove_tree,
    store_exists,
    target,
)
from .cluster import computing_client
from .components import components_staged
from .dem import cell_size, open_dem, require_valid_cells
from .exceptions import InvalidParameterError, StoreExistsError
from .landmarks import landmarks_staged, memory_per_landmark
from .params import DEFAULT_CHUNK, MAPS, chunks2d
from .ridges import default_min_accumulation, ridge_layers_staged
from .safety import passable, safety_map
from .store import MAPS_VERSION, attrs_signature, block_writer, open_maps

log = logging.getLogger(__name__)


@njit(nogil=True, cache=True)
def _mix64(x):
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


@njit(nogil=True, cache=True)
def _block_hash(block, r0, c0, ncols):
    """Sum over cells of mix(value bits, global index): order-free, so any chunking agrees."""
    bits = block.view(np.uint32)
    h = np.uint64(0)
    for i in range(block.shape[0]):
        for j in range(block.shape[1]):
            idx = np.uint64((r0 + i) * ncols + (c0 + j))
            h += _mix64(np.uint64(bits[i, j]) ^ _mix64(idx + np.uint64(0x9E3779B97F4A7C15)))
    return h


def dem_hash(dem: xr.DataArray):
    """A 64-bit content hash of the DEM's float32 values (NaN-normalised), independent of how
    it is chunked. Returns a hex string, or a dask array of per-chunk partials when lazy."""
    ncols = dem.shape[1]
    z = dem.data
    part = functools.partial(_hash_part, ncols=ncols)
    if isinstance(z, da.Array):
        return z.map_blocks(part, chunks=(1, 1), dtype=np.uint64)
    return _hex(part(np.asarray(z, np.float32), {0: {"array-location": [(0, 0), (0, 0)]}}))


def _hash_part(block, block_info=None, *, ncols):
    (r0, _), (c0, _) = block_info[0]["array-location"]
    b = np.ascontiguousarray(np.where(np.isnan(block), np.float32(np.nan), block), dtype=np.float32)
    return np.array([[_block_hash(b, r0, c0, ncols)]], dtype=np.uint64)


def _hex(partials) -> str:
    total = int(np.asarray(partials, dtype=np.uint64).sum(dtype=np.uint64))
    return f"{total:016x}"


def build_maps(
    dem,
    store: str | os.PathLike,
    *,
    method: str = MAPS.method.default,
    clearance: float = MAPS.clearance.default,
    horizontal_clearance: float | None = None,
    sea_level: float = MAPS.sea_level.default,
    surface_clearance: float | None = None,
    min_accumulation: int | None = None,
    landmarks: int = MAPS.landmarks.default,
    chunks=None,
    overwrite: bool = False,
) -> xr.Dataset:
    """Build the maps of ``dem`` chunk-wise and write them to the Zarr store ``store``.

    Parameters
    ----------
    dem : xarray.DataArray or path
        The canonical DEM, or a file :func:`pipeline.open_dem` can read.
    store : path
        Destination Zarr store, written atomically.
    method, clearance, horizontal_clearance
        As :func:`pipeline.safety_map`.
    sea_level, surface_clearance
        As :func:`pipeline.passable`.
    min_accumulation : int, optional
        Ridge threshold in cells, as :func:`pipeline.ridge_map` (default: a 1 km^2 area).
    landmarks : int
        Landmark distance layers to store (:mod:`pipeline.landmarks`): the proven lower bound
        every mission is certified against. 0 stores none (missions are then certified only
        when planned on the whole map).
    chunks : int or (int, int), optional
        Chunk sides of the store; default the DEM's chunks, else 1024.
    overwrite : bool
        Replace an existing store.

    Returns
    -------
    xarray.Dataset
        The store, opened lazily (:func:`open_maps`).

    Examples
    --------
    >>> dem = pipeline.synthetic_dem((2000, 2000), chunks=512)           # doctest: +SKIP
    >>> maps = build_maps(dem, "maps.zarr", clearance=300.0)             # doctest: +SKIP
    >>> sorted(maps.data_vars)                                           # doctest: +SKIP
    ['accumulation', 'elevation', 'passable', 'ridge', 'safety']
    """
    dem, store, ch, a, S, ok, min_accumulation, landmarks = _checked(
        dem,
        store,
        method=method,
        clearance=clearance,
        horizontal_clearance=horizontal_clearance,
        sea_level=sea_level,
        surface_clearance=surface_clearance,
        min_accumulation=min_accumulation,
        landmarks=landmarks,
        chunks=chunks,
        overwrite=overwrite,
    )
    if landmarks:
        _check_landmark_memory(dem.shape)
    require_valid_cells(dem, "the DEM is entirely no-data (NaN); nothing to build maps from")
    params = {
        "method": method,
        "clearance_m": S.attrs["clearance_m"],
        "horizontal_clearance_m": S.attrs.get("horizontal_clearance_m"),
        "sea_level_m": ok.attrs["sea_level_m"],
        "surface_clearance_m": ok.attrs["surface_clearance_m"],
        "min_accumulation": min_accumulation,
        "landmarks": landmarks,
        "cell_size": a,
        "chunks": list(ch),
    }
    elev = dem.copy()
    elev.attrs = {k: v for k, v in dem.attrs.items() if k not in ("pipeline_dem_version",)}
    t0 = time.perf_counter()
    with target(store, overwrite=overwrite) as tmp:
        # beside the store, on the same storage: every worker reads and writes them
        scratch, labels = tmp + "-scratch", tmp + "-components"
        try:
            # passes 1-2: tiles flooded once, fill and flow summaries solved globally
            _, acc, ridge = ridge_layers_staged(
                dem.data,
                scratch,
                min_accumulation,
                log=lambda msg, *a: log.info(f"maps {store}: " + msg, *a),
            )
            # pass 3: every layer written, a band of chunk rows at a time (+ the DEM hash)
            ds = xr.Dataset(
                {
                    "elevation": elev,
                    "safety": S,
                    "passable": ok,
                    "accumulation": (
                        ("y", "x"),
                        acc,
                        {
                            "long_name": "flow accumulation of the inverted filled DEM",
                            "units": "cells",
                        },
                    ),
                    "ridge": (
                        ("y", "x"),
                        ridge,
                        {"long_name": "ridge cells", "min_accumulation": min_accumulation},
                    ),
                }
            )
            partials = _write(ds, tmp, ch, also=dem_hash(dem))
            log.info(
                "maps %s: layers written (elevation, safety, passable, accumulation, ridge)",
                store,
            )
            # pass 4: connected components of the passable layer just written
            component, count = components_staged(
                da.from_zarr(join(tmp, "passable"), chunks=ch), labels
            )
            _write(
                xr.Dataset(
                    {
                        "component": (
                            ("y", "x"),
                            component,
                            {"long_name": "connected component of the passable graph (0: none)"},
                        )
                    }
                ),
                tmp,
                ch,
                mode="a",
            )
            log.info("maps %s: components labelled", store)
            # pass 5: landmark distance layers (the proven lower bound)
            tl = time.perf_counter()
            cells = landmarks_staged(
                tmp,
                landmarks,
                a,
                log=lambda msg, *a: log.info(f"maps {store}: " + msg, *a),
                components=count,
            )
            landmarks_s = time.perf_counter() - tl
            log.info("maps %s: %d landmarks written (%.1f s)", store, len(cells), landmarks_s)
        except BaseException:
            for p in (scratch, labels):  # tasks still running may write after a failure
                remove_settled(p)
            raise
        remove_tree(scratch)
        remove_tree(labels)
        group = zarr.open_group(tmp, mode="r+", zarr_format=3)
        attrs = {
            "title": "pipeline maps store",
            "maps_version": MAPS_VERSION,
            "parameters": json.dumps(params),
            "cell_size": a,
            "dem_hash": _hex(partials),
            "all_chunks_written": True,
            "landmarks": json.dumps(cells),
            "build_seconds": {
                "total": round(time.perf_counter() - t0, 2),
                "landmarks": round(landmarks_s, 2),
            },
        }
        if "crs_wkt" in dem.attrs:
            attrs["crs_wkt"] = dem.attrs["crs_wkt"]
        attrs["signature"] = attrs_signature(attrs)
        group.attrs.update(attrs)
    log.info(
        "built maps store %s (%s, R = %g m, ridge >= %d cells) in %.1f s",
        store,
        method,
        params["clearance_m"],
        min_accumulation,
        time.perf_counter() - t0,
    )
    return open_maps(store)


def check_build_arguments(dem, store, **kwargs) -> None:
    """Raise what :func:`build_maps` would raise for its arguments before it computes anything
    (a store that exists, cells that are not square, a clearance, sea level, threshold or
    landmark count out of range), without a cluster: the command line checks them before it
    starts one (the workers took 3-5 s to start before a mistyped clearance was reported).
    The landmark layers' memory is checked by :func:`build_maps` only, against the workers'
    memory limits."""
    import inspect

    args = inspect.signature(build_maps).bind(dem, store, **kwargs)  # its defaults, its errors
    args.apply_defaults()
    _checked(**args.arguments)


def _checked(
    dem,
    store,
    *,
    method,
    clearance,
    horizontal_clearance,
    sea_level,
    surface_clearance,
    min_accumulation,
    landmarks,
    chunks,
    overwrite,
):
    """:func:`build_maps`' arguments checked, before any compute: ``(dem as float32 in the
    store's chunks, store, chunks, cell size, safety map, passable map (both lazy),
    min_accumulation, landmarks)``."""
    if not isinstance(dem, xr.DataArray):
        dem = open_dem(dem, chunks=chunks or DEFAULT_CHUNK)
    store = location(store) if is_url(store) else Path(store)
    if store_exists(store) and not overwrite:
        raise StoreExistsError(
            f"maps store {store} exists already; pass overwrite=True (--overwrite) to rebuild it"
        )
    if chunks is None:
        chunks = dem.data.chunksize if isinstance(dem.data, da.Array) else DEFAULT_CHUNK
    ch = chunks2d(chunks, dem.shape)
    dem = dem.chunk(dict(zip(("y", "x"), ch, strict=True))).astype(np.float32)
    a = cell_size(dem)  # checks the cells are square
    S = safety_map(
        dem, method=method, clearance=clearance, horizontal_clearance=horizontal_clearance
    )
    ok = passable(dem, S, sea_level=sea_level, surface_clearance=surface_clearance)
    if min_accumulation is None:
        min_accumulation = default_min_accumulation(a)
    min_accumulation = MAPS.min_accumulation.check(min_accumulation)
    landmarks = MAPS.landmarks.check(landmarks)
    return dem, store, ch, a, S, ok, min_accumulation, landmarks


def _check_landmark_memory(shape) -> None:
    """Refuse, before any compute, landmark layers whose exact whole-map searches cannot fit:
    each search holds the map (:func:`pipeline.landmarks.memory_per_landmark`) and would
    otherwise fail only after every other layer was built. A search runs on one dask worker
    (the smallest worker's memory limit counts) or, without a distributed client, two at a
    time in this process (half of this machine's memory each)."""
    import psutil

    need = memory_per_landmark(shape)
    have = psutil.virtual_memory().total // 2
    client = computing_client()
    if client is not None:
        workers = client.scheduler_info()["workers"].values()
        limits = [w.get("memory_limit") or 0 for w in workers]
        if limits and min(limits) > 0:
            have = min(limits)
    if need > 0.9 * have:
        raise InvalidParameterError(
            f"the landmark layers need about {need / 2**30:.1f} GiB per landmark search (an "
            f"exact search of the whole {shape[0]} x {shape[1]} map, 18 bytes a cell), more "
            f"than the {have / 2**30:.1f} GiB one search can have here; set landmarks = 0 "
            "(--landmarks 0): missions are then certified by the octile bound or say they "
            "are not"
        )


BAND_CHUNKS = 64  # pass 3 writes bands of whole chunk rows of at least this many chunks


def _write(ds: xr.Dataset, path, ch, *, also=None, mode: str = "w"):
    """Write ``ds`` (dask-backed 2-D layers in blocks of ``ch``) into the Zarr store ``path``
    (``mode`` "w": a new store; "a": layers added), band by band (whole block rows, at least
    :data:`BAND_CHUNKS` blocks a band); ``also`` (per-block partials of a dask collection
    sharing its inputs, one per block) is computed with each band and returned.

    One computation of the whole map let the workers hold intermediate chunks of every layer
    (the shared DEM chunks, their halos, the flow tiles) across much of the map: 1.50 GiB per
    worker at 20000^2 and growing with the map. A band at a time bounds that by the band
    (0.81 GiB at 20000^2, the same 2.3 min); each band rereads the DEM chunks of its halo rows
    from the source.

    xarray writes the metadata and the coordinates; each block is then written as its shard by
    :func:`pipeline.store.block_writer` (the bytes zarr writes, in half its time for a 1024^2
    float32 shard and a fifth for a bool one: the 10000^2 build's layers pass, 5 layers of 100
    shards, took 15.2 s through xarray's region writes, 11.3 s this way)."""
    for v in ds.data_vars.values():
        v.encoding = {}
    ds.to_zarr(  # the metadata and the coordinates now, the layers band by band
        path,
        mode=mode,
        zarr_format=3,
        consolidated=False,
        encoding={
            k: layer_encoding(ch, compress=k not in WINDOW_LAYERS or is_url(path))
            for k in ds.data_vars
        },
        compute=False,
        write_empty_chunks=True,  # every chunk on disk: a missing one means damage
    )
    writers = {k: block_writer(str(path), k) for k in ds.data_vars}
    ny, per_row = ds.sizes["y"], -(-ds.sizes["x"] // ch[1])
    step = ch[0] * max(1, -(-BAND_CHUNKS // per_row))
    # blocks of the shards (dask's overlap merges a last chunk thinner than its depth into the
    # one before: a no-op where the chunks are the shards already)
    layers = {k: v.data.rechunk(da.core.normalize_chunks(ch, v.shape)) for k, v in ds.items()}
    parts = []
    for r0 in range(0, ny, step):
        r1 = min(ny, r0 + step)
        # one task a block writes every layer's shard: the layers' own steps (the passable
        # test, the ridge threshold, the accumulation) fuse into it, and a block computed for
        # two layers (the safety surface: its own and the passable layer) is held by none
        writes = da.map_blocks(
            _put_blocks,
            *(data[r0:r1] for data in layers.values()),
            writers=tuple(writers[k] for k in layers),
            first_row=r0 // ch[0],
            chunks=tuple((1,) * len(c) for c in layers[next(iter(layers))][r0:r1].chunks),
            dtype=np.int64,
            meta=np.empty((0, 0), np.int64),
        )
        band = [] if also is None else also[r0 // ch[0] : -(-r1 // ch[0])]
        _, part = dask.compute(writes, band)
        parts.append(np.asarray(part))
    return None if also is None else np.concatenate(parts)


def _put_blocks(*blocks, writers, first_row: int, block_info=None):
    """Write one block of each layer of a band through its writer (the block row in the band
    offset by the band's ``first_row``); the bytes written, as a 1x1 block."""
    bi, bj = block_info[0]["chunk-location"]
    n = sum(w((first_row + bi, bj), b) for w, b in zip(writers, blocks, strict=True))
    return np.full((1, 1), n, dtype=np.int64)
