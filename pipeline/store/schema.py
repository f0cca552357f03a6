"""The maps store's format, written down once: its version, its layers, the attributes whose
signature proves the store complete and unchanged, and how its layers are chunked and
compressed.

A maps store is a Zarr v3 group: one 2-D array a layer (``elevation``, ``safety``,
``passable``, ``accumulation``, ``ridge``, ``component``; ``landmark_distance`` is 3-D), every
layer sharded by the store's chunks into inner chunks of at most :data:`INNER_CHUNK` cells a
side, the CRS as a CF grid-mapping variable (``spatial_ref``), and the build's parameters,
the DEM's content hash and a signature of them in the group's attributes.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

import numpy as np

from ..exceptions import PipelineError
from ..methods import METHODS

# raised whenever the layers of a store built from the same DEM and parameters change (a job's
# maps store is named by a hash that holds it, so a new version builds a new store): 2 is the
# safety surface rounded up to float32
MAPS_VERSION = 2


LAYERS = ("elevation", "safety", "passable", "accumulation", "ridge")


_SIGNED = ("maps_version", "parameters", "cell_size", "dem_hash", "crs_wkt", "all_chunks_written")


def attrs_signature(attrs: dict) -> str:
    """A hash of the attributes that define what a maps store holds: a store whose attributes
    were edited after it was built no longer matches it."""
    what = {k: attrs.get(k) for k in _SIGNED}
    if "landmarks" in attrs:  # stores built before the landmark layers have none
        what["landmarks"] = attrs["landmarks"]
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:32]


def damaged(path, what: str) -> PipelineError:
    return PipelineError(
        f"maps store {path} is damaged: {what}; rebuild it (build_maps overwrite=True, "
        "`pipeline build-maps --overwrite`, or `pipeline run --overwrite`)"
    )


COARSE_RIDGE_FRACTION = 0.5  # a coarse cell is a ridge cell when half its fine cells are


def layer_codec():
    """The codec of every Zarr layer the pipeline keeps (DEM stores, maps layers, landmark
    distances): blosc LZ4 with byte shuffle. Builds read the DEM several times and missions
    read windows of the maps layers and the landmark chunks at both ends: it decodes and
    encodes several times faster than zarr's default (zstd) and than blosc zstd with bit
    shuffle, at the same or a better ratio (CHANGELOG.md, "Measurements")."""
    from zarr.codecs import BloscCodec

    return (BloscCodec(cname="lz4", clevel=5, shuffle="shuffle"),)


INNER_CHUNK = 256  # the largest side of a maps layer's inner chunk (the unit a window reads)


def inner_chunks(chunks, largest: int = INNER_CHUNK) -> tuple[int, ...]:
    """The inner chunk of a maps layer whose shards are ``chunks``: on each side the largest
    divisor of the shard's side that is at most ``largest`` (:data:`INNER_CHUNK`: 1024 -> 256,
    300 -> 150, 89 -> 89)."""
    return tuple(
        next(d for d in range(min(int(c), largest), 0, -1) if int(c) % d == 0) for c in chunks
    )


# The layers a mission's sections read window by window. In a local store they are kept
# uncompressed: a window is then copied straight out of the shard files, memory-mapped
# (pipeline.store.cache.ChunkCache.window), with no decoding and no decoded chunk held: the
# decoding and the fresh memory of decoded chunks made a mission's reads longer than its
# searches, mapped they take less than half that (CHANGELOG.md, "Measurements"). The cost is
# disk: 4 + 1 + 1 bytes a cell (a 10000^2 store's three layers 600 MB, against 245 MB
# compressed). On object storage, where bytes travel, they stay compressed.
WINDOW_LAYERS = ("safety", "ridge", "passable")


def layer_encoding(chunks, compress: bool = True) -> dict:
    """The Zarr encoding of a maps layer written in blocks of ``chunks``: shards of ``chunks``
    (what a dask task writes, what dask reads the layer by) holding inner chunks of
    :func:`inner_chunks` (what a mission reads), each compressed with :func:`layer_codec`
    unless ``compress`` is false (:data:`WINDOW_LAYERS` of a local store).
    A section's window (about 150^2 cells) covers a few 256^2 inner chunks; with 1024^2
    chunks it decoded whole chunks: 11.5 M cells a layer for a mission across the 10000^2 map
    against 3.4 M (benchmarks/bench_latency.py)."""
    shards = tuple(int(c) for c in chunks)
    return {
        "chunks": inner_chunks(shards),
        "shards": shards,
        "compressors": layer_codec() if compress else None,
    }


def storage_chunks(arr) -> tuple[int, ...]:
    """The blocks a Zarr array was written in: its shards, or its chunks without sharding (the
    dask chunks to read it with)."""
    shards = getattr(arr, "shards", None)
    return tuple(int(v) for v in (shards if shards is not None else arr.chunks))


# the variable of a store that holds its CRS, as CF conventions and rioxarray have it
GRID_MAPPING = "spatial_ref"


def grid_mapping(crs_wkt: str | None) -> tuple | None:
    """How a store holds the CRS ``crs_wkt`` (None without one): ``(variable, attrs)``, the CF
    grid-mapping variable as rioxarray writes it (a 0-d variable whose attributes are the CRS's
    CF parameters, ``crs_wkt`` and GDAL's ``spatial_ref``; named :data:`GRID_MAPPING`) and the
    attributes each layer takes: ``grid_mapping`` naming it, and GDAL's Zarr ``_CRS``."""
    if not crs_wkt:
        return None
    import xarray as xr
    from pyproj import CRS

    crs = CRS.from_wkt(crs_wkt)
    try:
        attrs = crs.to_cf()
    except Exception:  # noqa: BLE001 - a CRS without a CF form: its WKT only
        attrs = {}
    attrs.update(crs_wkt=crs_wkt, spatial_ref=crs_wkt)
    layer = {"grid_mapping": GRID_MAPPING, "_CRS": {"wkt": crs_wkt}}
    return xr.DataArray(np.int32(0), attrs=attrs), layer


# the layers are sharded as the maps' other layers are, with inner chunks of at most this side:
# a mission reads one value per landmark at each end, which decodes one inner chunk each: a
# mission's bound decodes three times faster than from unsharded chunks, for slower writes and
# whole reads of a layer; smaller inner chunks saved little for much longer writes
# (CHANGELOG.md, "Measurements")
LANDMARK_CHUNK = 128


VARIABLE = "landmark_distance"  # (landmark, y, x), float32, shards (1, *the maps' chunks)


@dataclass(frozen=True)
class MapsParameters:
    """The parameters a maps store was built with (its ``parameters`` attribute), read once:
    every stage that needs the safety method, the clearances or the sea level takes them from
    here, with the defaults of stores built before a key was kept."""

    method: str
    clearance_m: float
    horizontal_clearance_m: float | None = None
    sea_level_m: float = 0.0
    surface_clearance_m: float | None = None
    min_accumulation: int | None = None
    landmarks: int = 0

    @classmethod
    def from_attrs(cls, params) -> MapsParameters:
        """The parameters of a store's ``parameters`` attribute (a dict, or its JSON text)."""
        if isinstance(params, str):
            params = json.loads(params)
        p = dict(params or {})

        def number(key):
            return None if p.get(key) is None else float(p[key])

        return cls(
            method=str(p.get("method", "spherical")),
            clearance_m=float(p["clearance_m"]),
            horizontal_clearance_m=number("horizontal_clearance_m"),
            sea_level_m=float(p.get("sea_level_m", 0.0)),
            surface_clearance_m=number("surface_clearance_m"),
            min_accumulation=None
            if p.get("min_accumulation") is None
            else int(p["min_accumulation"]),
            landmarks=int(p.get("landmarks", 0)),
        )

    @property
    def radius_m(self) -> float:
        """The clearance's horizontal radius: ``horizontal_clearance_m`` for the
        ``horizontal`` method where it was given, else ``clearance_m``."""
        if self.method == "horizontal" and self.horizontal_clearance_m:
            return self.horizontal_clearance_m
        return self.clearance_m

    @property
    def reach_m(self) -> float:
        """How far the clearance reaches sideways from a point: R for the spherical method,
        the horizontal radius for the horizontal one, none for the vertical one."""
        return METHODS[self.method].reach_m(self.clearance_m, self.radius_m)

    @property
    def top_m(self) -> float:
        """The highest the vehicle may fly: the sea level less the surface clearance (R when
        none was given)."""
        surface = self.clearance_m if self.surface_clearance_m is None else self.surface_clearance_m
        return self.sea_level_m - surface
