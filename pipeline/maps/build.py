"""The maps store: one Zarr (v3) store per DEM and parameter set (docs/method.md section 1).

It holds ``elevation``, ``safety``, ``passable``, ``accumulation``, ``ridge`` and
``component``, chunked identically, every chunk written, with the parameters, a content hash
of the input DEM and a signature of those attributes. It is written once, atomically, and read
by every mission (:mod:`pipeline.store`).

The build runs as streaming passes over the tiles (the store's chunks; a last chunk thinner
than two cells joins the tile before it), one dask task a tile in each pass, no task depending
on another: each reads what it needs from the scratch tiles (plain files beside the store), so
that no worker holds more than a tile with its halo plus perimeter data. (0) Every DEM tile is
kept in the scratch; (1) every tile is filled once with a halo of 2 read from there, its local
fill and label indices go to scratch tiles, and the spill edges to a small global solve; (2)
the fill is finished elementwise per tile (plus a one-cell halo), its D8 codes go to the
scratch tiles and the flow summaries to the second global solve; (3) every layer of a tile is
written (its safety surface from its DEM with the structuring element's halo read from the
scratch tiles, the accumulation from its stored codes and the flow solve) and its passable
cells labelled; (4) the labels that touch across tile borders are joined in a third small
solve and the component layer written (:mod:`pipeline.maps.components`); (5) the landmark layers.
The scratch stores are removed at the end. With dask's overlap of the source instead, the
halos took 9 tasks a tile and moved slices between the workers: the 10000^2 build ran 3807
tasks, and the scheduler's time for them shared the workers' 2 cores.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

import dask
import dask.array as da
import numpy as np
import xarray as xr
import zarr

from .._types import Chunks, DEMLike
from ..dem.canonical import as_dem, cell_size, require_valid_cells
from ..exceptions import InvalidParameterError
from ..params import DEFAULT_CHUNK, MAPS, chunks2d
from ..planners.endpoints import NO_PASSABLE
from ..runtime.cluster import compute_told, computing_client, prefixed
from ..runtime.jit import njit
from ..store.maps_store import open_maps
from ..store.paths import check_replaceable, is_url, location, remove_settled, remove_tree, target
from ..store.schema import (
    GRID_MAPPING,
    MAPS_VERSION,
    WINDOW_LAYERS,
    attrs_signature,
    grid_mapping,
    layer_encoding,
)
from ..store.zarr_direct import block_writer
from .components import join_tiles, label_tile, relabel_tile
from .landmarks import component_sizes, landmarks_staged, memory_per_landmark
from .ridges import default_min_accumulation, flood_and_solve, tile_accumulation
from .safety import block_kernel, passable, passable_cells, safety_map
from .scratch import load_window

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


def dem_hash(dem: xr.DataArray) -> str | da.Array:
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
    return np.array([[_hash_tile(block, r0, c0, ncols)]], dtype=np.uint64)


def _hash_tile(block, r0: int, c0: int, ncols: int) -> np.uint64:
    """The hash partial of ``block``, whose first cell is ``(r0, c0)`` of a DEM of ``ncols``
    columns (NaN payloads made one)."""
    b = np.ascontiguousarray(np.where(np.isnan(block), np.float32(np.nan), block), dtype=np.float32)
    return _block_hash(b, r0, c0, ncols)


def _hex(partials) -> str:
    total = int(np.asarray(partials, dtype=np.uint64).sum(dtype=np.uint64))
    return f"{total:016x}"


def build_maps(
    dem: DEMLike,
    store: str | os.PathLike,
    *,
    method: str = MAPS.method.default,
    clearance: float = MAPS.clearance.default,
    horizontal_clearance: float | None = None,
    sea_level: float = MAPS.sea_level.default,
    surface_clearance: float | None = None,
    min_accumulation: int | None = None,
    landmarks: int = MAPS.landmarks.default,
    chunks: Chunks = None,
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
        Landmark distance layers to store (:mod:`pipeline.maps.landmarks`): the proven lower bound
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
    t0 = time.perf_counter()

    def say(msg, *args) -> None:
        log.info(f"maps {store}: " + msg, *args)

    with target(store, kind="maps", overwrite=overwrite) as tmp:
        # beside the store, on the same storage: every worker reads and writes them
        scratch, labels = tmp + "-scratch", tmp + "-components"
        try:
            partials, sizes = _tile_passes(dem, S, ok, tmp, scratch, labels, ch, params, say)
            # the scratch tiles (about 13 bytes a cell) go before the landmark searches,
            # which read the store's layers back through the page cache
            remove_tree(scratch)
            remove_tree(labels)
            # pass 5: landmark distance layers (the proven lower bound)
            tl = time.perf_counter()
            cells = landmarks_staged(tmp, landmarks, a, log=say, counts=component_sizes(sizes))
            landmarks_s = time.perf_counter() - tl
            say("%d landmarks written (%.1f s)", len(cells), landmarks_s)
        except BaseException:
            for p in (scratch, labels):  # tasks still running may write after a failure
                remove_settled(p)
            raise
        passable_cells = int(component_sizes(sizes)[1:].sum())
        if passable_cells == 0:
            log.warning("maps %s: %s", store, NO_PASSABLE)
        _finish_attributes(
            tmp,
            dem,
            params,
            passable_cells=passable_cells,
            dem_hash=_hex(partials),
            landmarks=cells,
            seconds={
                "total": round(time.perf_counter() - t0, 2),
                "landmarks": round(landmarks_s, 2),
            },
        )
    log.info(
        "built maps store %s (%s, R = %g m, ridge >= %d cells) in %.1f s",
        store,
        method,
        params["clearance_m"],
        min_accumulation,
        time.perf_counter() - t0,
    )
    return open_maps(store)


def _tile_passes(dem, S, ok, tmp: str, scratch: str, labels: str, ch, params: dict, say):
    """Passes 1-4 of the build into the store ``tmp``: the tiles flooded and the fill and
    flow solved (1-2), every layer of every tile written and its components labelled (3), the
    labels joined across tiles and the component layer written (4). Returns the tiles' DEM
    hash partials and their component sizes."""
    a, method = params["cell_size"], params["method"]
    # passes 1-2: tiles flooded once (each keeping its DEM tile in the scratch), the fill and
    # flow summaries solved globally
    st = flood_and_solve(dem.data, scratch, log=say)
    # pass 3: every layer of every tile written and its components labelled, one task a tile
    # that reads its haloed DEM from the scratch tiles
    kernel, depth = block_kernel(
        method, S.attrs["clearance_m"], S.attrs.get("horizontal_clearance_m"), a
    )
    tiles = _Tiles(
        scratch,
        labels,
        *st.offsets,
        ch,
        dem.shape,
        kernel,
        depth,
        ok.attrs["sea_level_m"],
        ok.attrs["surface_clearance_m"],
        params["min_accumulation"],
    )
    elev = dem.copy()
    elev.attrs = {k: v for k, v in dem.attrs.items() if k not in ("pipeline_dem_version",)}
    writers = _create(
        {
            "elevation": elev,
            "safety": S,
            "passable": ok,
            "accumulation": (
                np.int32,
                {"long_name": "flow accumulation of the inverted filled DEM", "units": "cells"},
            ),
            "ridge": (
                bool,
                {"long_name": "ridge cells", "min_accumulation": params["min_accumulation"]},
            ),
        },
        dem,
        tmp,
        ch,
    )
    parts = tiles.run(_layers_tile, st.solution, writers, prefixed(say, "layers: "))
    say("layers written (elevation, safety, passable, accumulation, ridge)")
    # pass 4: the labels that touch across tiles joined, the component layer written
    table, offsets = join_tiles(
        *([p[2][k] for p in parts] for k in range(3)), len(tiles.r_off) - 1, tiles.nbc
    )
    (joined,) = dask.persist(dask.delayed((table, offsets), pure=True))
    writers = _create(
        {
            "component": (
                np.int32,
                {"long_name": "connected component of the passable graph (0: none)"},
            )
        },
        dem,
        tmp,
        ch,
        mode="a",
    )
    sizes = tiles.run(_component_tile, joined, writers, prefixed(say, "components: "))
    say("components labelled")
    return [p[0] for p in parts], sizes


def _finish_attributes(tmp: str, dem, params: dict, **facts) -> None:
    """The store's attributes, written last (a store without them is incomplete): its
    format's version, the build's parameters, the DEM's hash and CRS, the landmarks, what the
    build took, and the signature of them (:func:`pipeline.store.schema.attrs_signature`)."""
    group = zarr.open_group(tmp, mode="r+", zarr_format=3)
    attrs = {
        "passable_cells": facts["passable_cells"],
        "title": "pipeline maps store",
        "maps_version": MAPS_VERSION,
        "parameters": json.dumps(params),
        "cell_size": params["cell_size"],
        "dem_hash": facts["dem_hash"],
        "all_chunks_written": True,
        "landmarks": json.dumps(facts["landmarks"]),
        "build_seconds": facts["seconds"],
    }
    if "crs_wkt" in dem.attrs:
        attrs["crs_wkt"] = dem.attrs["crs_wkt"]
    attrs["signature"] = attrs_signature(attrs)
    group.attrs.update(attrs)


def check_build_arguments(dem, store, **kwargs) -> None:
    """Raise what :func:`build_maps` would raise for its arguments before it computes anything
    (a store that exists, cells that are not square, a clearance, sea level, threshold or
    landmark count out of range), without a cluster: the command line checks them before it
    starts one (the workers took seconds to start before a mistyped clearance was reported).
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
    dem = as_dem(dem, chunks=chunks or DEFAULT_CHUNK)
    store = location(store) if is_url(store) else Path(store)
    check_replaceable(store, "maps", overwrite)
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
    each search holds the map (:func:`pipeline.maps.landmarks.memory_per_landmark`) and would
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
            f"exact search of the whole {shape[0]} x {shape[1]} map, 7.2 bytes a cell), more "
            f"than the {have / 2**30:.1f} GiB one search can have here; set landmarks = 0 "
            "(--landmarks 0): missions are then certified by the octile bound or say they "
            "are not"
        )


@dataclass(frozen=True)
class _Tiles:
    """The tile grid of a build's passes 3 and 4 (the scratch tiles' grid: the store's chunks,
    a last one thinner than the fill's halo merged into the one before) and what a tile's
    task needs besides its scratch tiles."""

    scratch: str
    labels: str
    r_off: np.ndarray
    c_off: np.ndarray
    ch: tuple
    shape: tuple
    kernel: object
    depth: int
    sea_level: float
    surface_clearance: float
    min_accumulation: int

    @property
    def nbc(self) -> int:
        return len(self.c_off) - 1

    def extent(self, bi: int, bj: int) -> tuple:
        """Rows ``r0:r1`` and columns ``c0:c1`` of tile ``(bi, bj)``."""
        return (
            int(self.r_off[bi]),
            int(self.r_off[bi + 1]),
            int(self.c_off[bj]),
            int(self.c_off[bj + 1]),
        )

    def run(self, task, shared, writers, tell=None, what: str = "tiles") -> list:
        """``task(self, bi, bj, shared, writers)`` for every tile, one dask task each (no task
        depends on another: each reads its tiles from the scratch), in the tile grid's order;
        ``shared`` is a dask key (persisted on a cluster). ``tell`` hears of the progress
        (:func:`pipeline.runtime.cluster.compute_told`)."""
        return list(
            compute_told(
                [
                    dask.delayed(task, pure=False)(self, bi, bj, shared, writers)
                    for bi in range(len(self.r_off) - 1)
                    for bj in range(self.nbc)
                ],
                tell,
                what,
            )
        )

    def put(self, writer, bi: int, bj: int, array) -> int:
        """Write the store's blocks (its shards) that tile ``(bi, bj)`` holds, of ``array`` (the
        tile's values of one layer): one block, or two or four where a thin last chunk was
        merged into the tile; the bytes written."""
        r0, r1, c0, c1 = self.extent(bi, bj)
        h, w = self.ch
        return sum(
            writer((i // h, j // w), array[i - r0 : i - r0 + h, j - c0 : j - c0 + w])
            for i in range(r0, r1, h)
            for j in range(c0, c1, w)
        )


def _layers_tile(t: _Tiles, bi: int, bj: int, solution, writers) -> tuple:
    """Pass 3 for one tile: its DEM with the safety kernel's halo read from the scratch tiles,
    its elevation, safety, passable, accumulation and ridge blocks written, its components
    labelled (kept in the labels scratch); returns ``(its DEM hash partial, the bytes written,
    (label count, first cells, borders))``."""
    r0, r1, c0, c1 = t.extent(bi, bj)
    n, m = t.shape
    d = t.depth
    w0, v0 = max(0, r0 - d), max(0, c0 - d)
    zw = load_window(
        t.scratch, "dem", t.r_off, t.c_off, w0, min(n, r1 + d), v0, min(m, c1 + d), np.float32
    )
    inner = (slice(r0 - w0, r1 - w0), slice(c0 - v0, c1 - v0))
    z = zw[inner]
    safety = t.kernel(zw)[inner]
    ok = passable_cells(z, safety, t.sea_level, t.surface_clearance)
    acc = tile_accumulation(t.scratch, t.r_off, t.c_off, bi, bj, solution)
    layers = (z, safety, ok, acc, acc >= t.min_accumulation)
    written = sum(t.put(w, bi, bj, v) for w, v in zip(writers, layers, strict=True))
    parts = label_tile(ok, r0, c0, m, t.labels, (bi, bj))
    return _hash_tile(z, r0, c0, m), written, parts


def _component_tile(t: _Tiles, bi: int, bj: int, joined, writers) -> np.ndarray:
    """Pass 4 for one tile: its component block(s) from its local labels and the join
    written; returns the cells of each component label in the tile (the landmarks' placement
    needs the components' sizes)."""
    table, offsets = joined
    (writer,) = writers
    block = relabel_tile(t.labels, (bi, bj), table, offsets, t.nbc)
    t.put(writer, bi, bj, block)
    return np.bincount(block.ravel())


def _create(layers: dict, dem: xr.DataArray, path, ch, *, mode: str = "w") -> tuple:
    """Create the 2-D ``layers`` (each a DataArray on the DEM's grid, or ``(dtype, attrs)``)
    in the Zarr store ``path`` (``mode`` "w": a new store; "a": layers added) in blocks of
    ``ch``, with no values yet (xarray writes the metadata and the coordinates); return
    their block writers (:func:`pipeline.store.zarr_direct.block_writer`: the bytes zarr
    writes, in half its time for a 1024^2 float32 shard and a fifth for a bool one), in
    ``layers``' order."""
    ds = xr.Dataset(coords=dem.coords)
    mapping = grid_mapping(dem.attrs.get("crs_wkt"))
    if mapping is not None and mode == "w":
        ds = ds.assign_coords({GRID_MAPPING: mapping[0]})
    for k, v in layers.items():
        dtype, attrs = (v.dtype, v.attrs) if isinstance(v, xr.DataArray) else v
        if mapping is not None:  # the CF way (rioxarray, GDAL's netCDF) and GDAL's Zarr way
            attrs = {**attrs, **mapping[1]}
        ds[k] = (("y", "x"), da.empty(dem.shape, chunks=ch, dtype=dtype), attrs)
    ds.to_zarr(  # the metadata and the coordinates now; the blocks by the passes' tasks
        path,
        mode=mode,
        zarr_format=3,
        consolidated=False,
        encoding={
            k: layer_encoding(ch, compress=k not in WINDOW_LAYERS or is_url(path)) for k in layers
        },
        compute=False,
        write_empty_chunks=True,  # every chunk on disk: a missing one means damage
    )
    return tuple(block_writer(str(path), k) for k in layers)
