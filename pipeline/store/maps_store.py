"""The maps store as the planners see it: ``MapsStore``, its window reads through a per-process
chunk cache, its coarse (compressed) maps, and the conversion of map or lon/lat coordinates to
cells.

A ``MapsStore`` pickles as its path, so a dask task receives it cheaply and reopens it on the
worker, where :func:`open_store` keeps one per store and process (and the chunks it decoded,
``AUV_PIPELINE_CHUNK_CACHE_MB``, 1 GiB by default).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import sys
import threading
import uuid
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .._types import Chunks, Maps
from .paths import exists, is_url, join, location, stamp, store_exists, unreachable
from .schema import MapsParameters, storage_chunks

if TYPE_CHECKING:
    import xarray as xr
from ..exceptions import InvalidEndpointError, InvalidParameterError, PipelineError
from ..params import LATITUDE, LONGITUDE, PLANNING
from .cache import CACHE
from .schema import COARSE_RIDGE_FRACTION, LAYERS, MAPS_VERSION, attrs_signature, damaged


class MapsStore:
    """A maps store (:func:`pipeline.build_maps`): shape, cell size, coordinates, CRS and
    parameters, windows of its layers, its coarse maps, cells of map or lon/lat coordinates.

    Open it with :func:`open_store` (one per store and process)."""

    # a mission's constraints (constraints.store.ConstrainedStore): none on the store itself
    keep_out = None  # keep-out zones (pipeline.constraints.zones.KeepOut)
    max_depth_m = None  # the vehicle's rated depth (metres)
    floor_m = None  # the lowest height the rating allows (ConstrainedStore.floor_m)

    def __init__(self, path: str | os.PathLike):
        import zarr

        path = location(path)
        _require_store(path)
        try:
            group = zarr.open_group(path, mode="r", zarr_format=3)
        except Exception as exc:  # noqa: BLE001 - object storage raises its own errors
            raise unreachable(path, exc) from None
        attrs = dict(group.attrs)
        _require_version(path, attrs)
        self.path = path
        try:
            self.parameters = MapsParameters.from_attrs(attrs.get("parameters"))
            self.crs_wkt = attrs.get("crs_wkt")
            # the count of passable cells (stores built before it was kept: None)
            self.passable_cells = attrs.get("passable_cells")
            self.shape = tuple(int(v) for v in group["safety"].shape)
            self.cell_size = float(attrs["cell_size"])
            self.x = np.asarray(group["x"][:], dtype=np.float64)
            self.y = np.asarray(group["y"][:], dtype=np.float64)
            for var in LAYERS:
                if tuple(group[var].shape) != self.shape:
                    raise ValueError(f"layer {var} has shape {group[var].shape}")
        except (KeyError, ValueError, TypeError) as exc:
            raise damaged(path, f"it is incomplete or malformed ({exc})") from None
        if "signature" in attrs and attrs_signature(attrs) != attrs["signature"]:
            raise damaged(
                path,
                "its attributes (parameters, cell size, DEM hash, landmarks) were changed after it "
                "was built",
            )
        spacing = (
            abs(self.x[1] - self.x[0]) if len(self.x) > 1 else self.cell_size,
            abs(self.y[1] - self.y[0]) if len(self.y) > 1 else self.cell_size,
        )
        if not all(math.isclose(d, self.cell_size, rel_tol=1e-6) for d in spacing):
            raise damaged(
                path,
                f"its cell_size attribute ({self.cell_size:g} m) disagrees with "
                f"its coordinates ({spacing[0]:g} x {spacing[1]:g} m)",
            )
        self.all_chunks_written = bool(attrs.get("all_chunks_written"))
        # what the store holds, as a hash (:func:`attrs_signature`; None: built before it)
        self.signature = attrs.get("signature")
        # stores built before the components layer have none: reachability then is not known
        self.has_components = "component" in group
        try:
            self.landmarks = [tuple(int(v) for v in c) for c in json.loads(attrs["landmarks"])]
        except KeyError:
            self.landmarks = []  # a store built before the landmark layers
        except (TypeError, ValueError):
            raise damaged(path, "its landmarks attribute is malformed") from None
        from .schema import VARIABLE

        if self.landmarks:
            want = (len(self.landmarks),) + self.shape
            if VARIABLE not in group or tuple(group[VARIABLE].shape) != want:
                raise damaged(path, f"its landmark layers ({VARIABLE!r}, {want}) are missing")
        self._dataset = None
        self._coarse: dict = {}
        self._lock = threading.Lock()
        # a store opened anew (open_store does so when its zarr.json changed: rebuilt in place)
        # must not be read through chunks decoded from what was there before
        CACHE.forget(path)

    def __reduce__(self):
        return open_store, (self.path,)

    def __repr__(self) -> str:
        return f"MapsStore({self.path!r}, shape={self.shape}, cell_size={self.cell_size:g})"

    @property
    def dataset(self):
        """The store as a lazy ``xarray.Dataset`` (:func:`open_maps`)."""
        if self._dataset is None:
            self._dataset = open_maps(self.path)
        return self._dataset

    def window(self, var: str, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """Rows ``r0:r1`` and columns ``c0:c1`` of layer ``var``, through the chunk cache. A
        chunk missing from a store that wrote every chunk is an error, not NaN."""
        return CACHE.window(self.path, var, r0, r1, c0, c1, complete=self.all_chunks_written)

    def values(self, var: str, cells) -> np.ndarray:
        """Layer ``var`` at ``cells`` (pairs of row and column, on the map), through the chunk
        cache (:meth:`ChunkCache.values`)."""
        return CACHE.values(self.path, var, cells, complete=self.all_chunks_written)

    def component(self, cell) -> int | None:
        """The connected component of a cell (0: not passable), or None for a store without
        the components layer."""
        return self.components(cell)[0]

    def components(self, *cells) -> list:
        """The connected components of the cells (:meth:`component`), in one lookup."""
        if not self.has_components:
            return [None] * len(cells)
        got = self.values("component", [(int(r), int(c)) for r, c in cells])
        return [int(v) for v in got]

    def landmark_distances(self, cell) -> np.ndarray:
        """The distances of ``cell`` from every landmark (metres, ``inf`` where a landmark does
        not reach it): the cell's value in every layer (:meth:`ChunkCache.stack_values`)."""
        from .schema import VARIABLE

        r, c = int(cell[0]), int(cell[1])
        values = CACHE.stack_values(self.path, VARIABLE, r, c, self.all_chunks_written)
        return values.astype(np.float64)

    def landmark_window(self, i: int, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """Rows ``r0:r1`` and columns ``c0:c1`` of landmark ``i``'s distance layer (read
        directly, not cached: the whole-map search reads large windows once)."""
        from .schema import VARIABLE

        return CACHE.array(self.path, VARIABLE)[i, r0:r1, c0:c1]

    def active_landmarks(self, start, goal, k: int) -> list[int]:
        """The ``k`` landmarks whose bound is largest for this pair of cells (the most useful
        as an A* heuristic towards ``goal``); none without landmark layers."""
        if not self.landmarks or k <= 0:
            return []
        ds, dg = self.landmark_distances(start), self.landmark_distances(goal)
        both = np.isfinite(ds) & np.isfinite(dg)
        gain = np.full(ds.shape, -1.0)
        gain[both] = np.abs(ds[both] - dg[both])
        return [int(i) for i in np.argsort(-gain, kind="stable")[:k] if both[i]]

    def lower_bound(self, start, goal) -> float:
        """A proven lower bound (metres) on the shortest safe path from ``start`` to ``goal``
        on the whole map: the landmark bound (:func:`pipeline.planners.bounds.lower_bound`), or 0
        with no landmark layers."""
        from ..planners.bounds import lower_bound

        if not self.landmarks:
            return 0.0
        return lower_bound(self.landmark_distances(start), self.landmark_distances(goal))

    def coarse(self, rho: int) -> dict:
        """The maps compressed by ``rho`` (docs/method.md section 6 step 1), as numpy arrays.

        ``safety`` is the block mean of the finite fine values, ``ridge`` the fraction of ridge
        cells, ``passable`` true where at least half the fine cells are passable (and the mean
        is finite), ``ridge_cells`` true where at least ``COARSE_RIDGE_FRACTION`` of the fine
        cells are ridge cells. The arrays are checked once (a damaged level is refused). Blocks
        at the right and bottom edges may be partial. The result is written once into the store
        (group ``coarse-rho{rho}``) and read from there afterwards, so that many missions and
        processes share it.
        """
        rho = PLANNING.rho.check(rho)
        name = f"coarse-rho{rho}"

        def build():
            import xarray as xr

            ds = self.dataset[["safety", "ridge", "passable"]]
            cs = ds.astype("float32").coarsen(y=rho, x=rho, boundary="pad").mean()
            out = xr.Dataset(
                {
                    "safety": cs["safety"].astype("float32"),
                    "ridge": cs["ridge"].astype("float32"),
                    "passable": (cs["passable"] >= 0.5) & np.isfinite(cs["safety"]),
                }
            ).compute()
            out.attrs.update(
                rho=rho, source="block means of the fine maps (docs/method.md section 6)"
            )
            return out

        def finish(ds):
            from ..planners.endpoints import check_arrays

            try:  # once: every mission searches these arrays (planners.window.search_window)
                safety, ridge_cells, passable = check_arrays(
                    ds["safety"], ds["ridge"] >= COARSE_RIDGE_FRACTION, ds["passable"]
                )
            except InvalidParameterError as exc:
                what = f"its coarse level {name} does not hold together ({exc})"
                raise damaged(self.path, what) from None
            return {
                "safety": safety,
                "ridge": ds["ridge"],
                "passable": passable,
                "ridge_cells": ridge_cells,
            }

        return self._reduced(rho, name, build, finish)

    def overview(self, factor: int) -> dict:
        """The elevation and ridge layers reduced by ``factor`` for pictures, as numpy arrays:
        ``elevation`` the block mean of the known (finite) elevations (NaN where a block has
        none), ``ridge`` true where a block holds a ridge cell. Blocks at the right and bottom
        edges may be partial. Written once into the store (group ``overview-f{factor}``) and
        read from there afterwards: a mission's quick-look draws its plan view from it instead
        of reading every chunk of the elevation under the mission's extent."""
        factor = int(factor)
        if factor < 2:
            raise InvalidParameterError(f"an overview factor must be 2 or more, got {factor}")

        def build():
            import xarray as xr

            # as float32: coarsen pads the partial blocks with NaN (a bool layer becomes an
            # object array), which the block mean and maximum pass over
            ds = self.dataset[["elevation", "ridge"]].astype("float32")
            blocks = ds.coarsen(y=factor, x=factor, boundary="pad")
            out = xr.Dataset(
                {
                    "elevation": blocks.mean()["elevation"],
                    "ridge": blocks.max()["ridge"] > 0,
                }
            ).compute()
            out.attrs.update(factor=factor, source="block mean of the elevation, ridge if any")
            return out

        def finish(ds):
            return {"elevation": ds["elevation"], "ridge": ds["ridge"].astype(bool)}

        return self._reduced(("overview", factor), f"overview-f{factor}", build, finish)

    def _reduced(self, key, name: str, build, finish) -> dict:
        """A reduced level of the maps (:meth:`coarse`, :meth:`overview`), kept by this object
        under ``key``: ``finish`` of group ``name`` of the store, read as numpy arrays in the
        caller's thread (a mission task's), after writing it there once from ``build()`` when
        it is not there yet (so that many missions and processes share it). ``finish`` gets the
        group's arrays by name, read through zarr: a mission's task then needs neither xarray
        nor dask.array, whose imports slowed a worker's first mission (the arrays are
        float32 with NaN as the fill value, and bool: nothing for xarray to decode)."""
        import zarr

        with self._lock:
            got = self._coarse.get(key)
        if got is not None:
            return got
        if not _coarse_written(self.path, name):
            _write_coarse(build(), self.path, name)
        group = zarr.open_group(join(self.path, name), mode="r", zarr_format=3)
        res = finish({var: arr[...] for var, arr in group.arrays()})
        with self._lock:
            self._coarse[key] = res
        return res

    def cell_of(self, name: str, form: str, value) -> tuple[int, int]:
        """The cell of a point given as a cell (``form="cell"``), map coordinates (``"xy"``) or
        lon/lat (``"lonlat"``, the DEM needs a CRS); ``name`` (start, goal) goes into errors."""
        if form == "cell":
            return int(value[0]), int(value[1])
        try:
            if len(value) != 2:
                raise ValueError
            x, y = float(value[0]), float(value[1])
            if not (math.isfinite(x) and math.isfinite(y)):
                raise ValueError
        except (TypeError, ValueError, IndexError):
            raise InvalidParameterError(
                f"{name}_{form} must be a pair of finite numbers, got {value!r}"
            ) from None
        if form == "lonlat":
            try:  # the job loader's bounds
                LONGITUDE.check(x)
                LATITUDE.check(y)
            except InvalidParameterError:
                raise InvalidParameterError(
                    f"{name}_lonlat {value} is not a longitude and latitude (lon "
                    f"{LONGITUDE.minimum:g}..{LONGITUDE.maximum:g}, lat "
                    f"{LATITUDE.minimum:g}..{LATITUDE.maximum:g})"
                ) from None
            if not self.crs_wkt:
                raise InvalidParameterError(
                    f"{name}_lonlat {value} given, but the DEM has no coordinate reference "
                    f"system; give {name} as a cell or in map coordinates ({name}_xy)"
                )
            from pyproj import CRS, Transformer

            tr = Transformer.from_crs("EPSG:4326", CRS.from_wkt(self.crs_wkt), always_xy=True)
            x, y = tr.transform(x, y)
        elif form != "xy":
            raise InvalidParameterError(
                f"unknown form {form!r} of {name}: 'cell', 'xy' or 'lonlat'"
            )
        xs, ys, a = self.x, self.y, self.cell_size
        # the cell whose square holds the point; a point on the map's outer edge is in its
        # edge cell (the map spans its cells' squares, as the message says)
        fc = (x - xs[0]) / (xs[1] - xs[0])
        fr = (y - ys[0]) / (ys[1] - ys[0])
        inside = (
            -0.5 - 1e-9 <= fc <= len(xs) - 0.5 + 1e-9 and -0.5 - 1e-9 <= fr <= len(ys) - 0.5 + 1e-9
        )
        col = min(max(int(math.floor(fc + 0.5)), 0), len(xs) - 1)
        row = min(max(int(math.floor(fr + 0.5)), 0), len(ys) - 1)
        if not inside:
            raise InvalidEndpointError(
                f"{name} {value} ({form}) is off the map: x spans "
                f"{min(xs[0], xs[-1]) - a / 2:.1f} to {max(xs[0], xs[-1]) + a / 2:.1f}, y "
                f"{min(ys[0], ys[-1]) - a / 2:.1f} to {max(ys[0], ys[-1]) + a / 2:.1f}"
            )
        return row, col


def _write_coarse(out, store: str, name: str) -> None:
    """Write the coarse maps ``out`` as group ``name`` of ``store``: locally beside it and
    renamed into place; on object storage (no rename) in place, then marked complete."""
    if is_url(store):
        out.to_zarr(join(store, name), mode="w", zarr_format=3, consolidated=False)
        import zarr

        zarr.open_group(join(store, name), mode="r+", zarr_format=3).attrs["complete"] = True
        return
    tmp = Path(store) / f".{name}.tmp-{uuid.uuid4().hex[:8]}"
    out.to_zarr(tmp, mode="w", zarr_format=3, consolidated=False)
    try:
        os.rename(tmp, Path(store) / name)
    except OSError:  # another process wrote it first: keep theirs
        shutil.rmtree(tmp, ignore_errors=True)


def _coarse_written(store: str, name: str) -> bool:
    """Whether group ``name`` is there, and on object storage also marked complete."""
    if not exists(join(store, name, "zarr.json")):
        return False
    if not is_url(store):
        return True  # renamed into place whole
    import zarr

    return bool(zarr.open_group(join(store, name), mode="r", zarr_format=3).attrs.get("complete"))


def _require_store(path) -> None:
    if is_url(path):
        if not store_exists(path):
            raise PipelineError(
                f"maps store {path} does not exist (no zarr.json there); build it with "
                "pipeline.build_maps or `pipeline build-maps`"
            )
        return
    path = Path(path)
    if not (path / "zarr.json").is_file():
        what = "is not a Zarr store" if path.exists() else "does not exist"
        raise PipelineError(
            f"maps store {path} {what}; build it with pipeline.build_maps or `pipeline build-maps`"
        )


def _require_version(path, attrs) -> None:
    if is_url(path) and "maps_version" not in attrs:
        raise PipelineError(
            f"maps store {path} is incomplete (its build did not finish: the attributes a "
            "build writes last are missing); rebuild it with overwrite=True (--overwrite)"
        )
    if "maps_version" not in attrs and "pipeline_dem_version" in attrs:
        raise InvalidParameterError(
            f"{path} is a DEM store, not a maps store: build its maps with pipeline.build_maps "
            "or `pipeline build-maps`, and plan on those"
        )
    if attrs.get("maps_version") != MAPS_VERSION:
        raise InvalidParameterError(
            f"{path} is not a maps store of this version "
            f"(maps_version={attrs.get('maps_version')!r}); rebuild it"
        )


_STORES: dict = {}


_STORES_LOCK = threading.Lock()


def open_store(maps: Maps) -> MapsStore:
    """The :class:`MapsStore` of a path, of a Dataset from :func:`open_maps`, or ``maps``
    itself; one per store and process while the store is unchanged."""
    if isinstance(maps, MapsStore):
        return maps
    xr = sys.modules.get("xarray")  # not imported: ``maps`` is no Dataset (a mission's task)
    if xr is not None and isinstance(maps, xr.Dataset):
        path = maps.attrs.get("store")
        if not path:
            raise InvalidParameterError(
                "`maps` must be a maps store path, a MapsStore or a "
                "Dataset from pipeline.open_maps (planning reads "
                "windows from the store)"
            )
        maps = path
    if not isinstance(maps, str | os.PathLike):
        raise InvalidParameterError(
            "`maps` must be a maps store path, a MapsStore or a Dataset"
            f" from pipeline.open_maps, got {type(maps).__name__}"
        )
    p = location(maps)
    when = stamp(join(p, "zarr.json"))
    if when is None:
        return MapsStore(maps)  # it says what is wrong
    with _STORES_LOCK:
        got = _STORES.get(p)
    if got is None or got[0] != when:
        got = (when, MapsStore(p))
        with _STORES_LOCK:
            _STORES[p] = got
    return got[1]


def open_maps(store: str | os.PathLike, chunks: Chunks = "store") -> xr.Dataset:
    """Open a maps store lazily as an ``xarray.Dataset``; ``chunks="store"`` keeps the blocks
    the store was written in (its shards: a dask chunk per shard, not per inner chunk).

    The Dataset is a view of the store's :class:`MapsStore` (:func:`open_store`, which checks
    the store's version, layers and attributes; its ``dataset`` is this view):
    ``attrs["store"]`` holds the path, so every function that takes a maps store takes the
    Dataset too."""
    import xarray as xr
    import zarr

    store = open_store(store).path  # a store that is missing, outdated or damaged says so
    try:
        opts = dict(consolidated=False, zarr_format=3)
        shards = None
        if chunks == "store":
            group = zarr.open_group(store, mode="r", zarr_format=3)
            if "safety" in group and getattr(group["safety"], "shards", None) is not None:
                shards = dict(zip(("y", "x"), storage_chunks(group["safety"]), strict=True))
        if shards is None:
            ds = xr.open_zarr(store, chunks={} if chunks == "store" else chunks, **opts)
        else:  # the layers by their shards; the landmark layers (not sharded) by their chunks
            from .schema import VARIABLE

            ds = xr.open_zarr(store, chunks=shards, drop_variables=[VARIABLE], **opts)
            if VARIABLE in group:
                ds[VARIABLE] = xr.open_zarr(store, chunks={}, **opts)[VARIABLE]
    except Exception as exc:  # noqa: BLE001 - object storage raises its own errors
        if not is_url(store):
            raise
        raise unreachable(store, exc) from None
    ds.attrs["store"] = store
    ds.attrs["parameters"] = (
        json.loads(ds.attrs["parameters"])
        if isinstance(ds.attrs.get("parameters"), str)
        else ds.attrs.get("parameters")
    )
    return ds
