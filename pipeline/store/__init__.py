"""The maps store as the planners see it: ``MapsStore``, its window reads through a per-process
chunk cache, its coarse (compressed) maps, and the conversion of map or lon/lat coordinates to
cells.

A ``MapsStore`` pickles as its path, so a dask task receives it cheaply and reopens it on the
worker, where :func:`open_store` keeps one per store and process (and the chunks it decoded,
``AUV_PIPELINE_CHUNK_CACHE_MB``, 1 GiB by default).
"""

from __future__ import annotations

import array
import hashlib
import json
import math
import os
import shutil
import sys
import threading
import uuid
from collections import OrderedDict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .._io import (
    exists,
    filesystem,
    is_url,
    join,
    location,
    stamp,
    storage_chunks,
    store_exists,
    unreachable,
)
from .._types import Chunks, Maps

if TYPE_CHECKING:
    import xarray as xr
from ..exceptions import InvalidEndpointError, InvalidParameterError, PipelineError
from ..params import LATITUDE, LONGITUDE, PLANNING

MAPS_VERSION = 1
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


_SCRATCH = threading.local()

# shard files a direct reader keeps open, per layer (a 10000^2 layer of 1024^2 shards has 100)
OPEN_FILES = 64


def _scratch(size: int) -> memoryview:
    """A view of ``size`` bytes of this thread's reusable read buffer (grown as needed)."""
    buf = getattr(_SCRATCH, "buf", None)
    if buf is None or len(buf) < size:
        buf = _SCRATCH.buf = bytearray(max(size, 2**20))
    return memoryview(buf)[:size]


def _decoded(size: int) -> np.ndarray:
    """This thread's reusable buffer of ``size`` bytes for a decoded chunk read once (apart
    from :func:`_scratch`, which holds the encoded bytes being decoded)."""
    buf = getattr(_SCRATCH, "decoded", None)
    if buf is None or buf.size != size:
        buf = _SCRATCH.decoded = np.empty(size, dtype=np.uint8)
    return buf


def _numcodecs_takes_typesize() -> bool:
    """Whether numcodecs' Blosc takes a ``typesize`` (0.16 and later; zarr passes it then)."""
    import re

    import numcodecs

    major_minor = re.match(r"(\d+)\.(\d+)", numcodecs.__version__)
    return major_minor is None or tuple(map(int, major_minor.groups())) >= (0, 16)


def _layout(arr):
    """``(the sharding codec or None, the compressor as numcodecs configures it)`` of a Zarr 3
    array laid out as the pipeline writes its layers: the ``bytes`` codec (little-endian)
    then one blosc or zstd compressor, either as the array's codecs or inside a sharding codec
    whose index (little-endian, CRC32C-checked) ends each shard; None for any other layout.
    The compressor is built as zarr builds it for encoding (blosc with the array's typesize),
    so that what it encodes is what zarr would write."""
    import numcodecs
    from zarr.codecs import BloscCodec, BytesCodec, Crc32cCodec, ShardingCodec, ZstdCodec
    from zarr.codecs.sharding import ShardingCodecIndexLocation

    codecs = tuple(getattr(arr.metadata, "codecs", ()))
    sharding = None
    if len(codecs) == 1 and isinstance(codecs[0], ShardingCodec):
        sharding = codecs[0]
        index_codecs = tuple(sharding.index_codecs)
        if (
            sharding.index_location != ShardingCodecIndexLocation.end
            or len(index_codecs) != 2
            or not isinstance(index_codecs[0], BytesCodec)
            or getattr(index_codecs[0].endian, "value", "little") != "little"
            or not isinstance(index_codecs[1], Crc32cCodec)
        ):
            return None
        codecs = tuple(sharding.codecs)
    if (
        len(codecs) not in (1, 2)
        or not isinstance(codecs[0], BytesCodec)
        or getattr(codecs[0].endian, "value", "little") != "little"
        or arr.dtype.byteorder == ">"
        or arr.dtype.hasobject
    ):
        return None
    if len(codecs) == 1:
        return sharding, _Uncompressed()
    c = codecs[1]
    if isinstance(c, BloscCodec):
        shuffle = {"noshuffle": 0, "shuffle": 1, "bitshuffle": 2}[
            getattr(c.shuffle, "value", c.shuffle)
        ]
        config = {
            "cname": getattr(c.cname, "value", c.cname),
            "clevel": c.clevel,
            "shuffle": shuffle,
            "blocksize": c.blocksize,
        }
        if _numcodecs_takes_typesize():  # as zarr does: older numcodecs take the item size
            config["typesize"] = c.typesize
        compressor = numcodecs.Blosc.from_config(config)
    elif isinstance(c, ZstdCodec):
        compressor = numcodecs.Zstd(level=c.level, checksum=c.checksum)
    else:
        return None
    return sharding, compressor


class _Uncompressed:
    """The "compressor" of a layer stored without one (:data:`pipeline._io.WINDOW_LAYERS` of
    a local store): its bytes copied (out of the thread's scratch buffer they were read into)
    into ``out`` or a new buffer."""

    @staticmethod
    def encode(buf) -> bytes:
        return bytes(memoryview(buf).cast("B"))

    @staticmethod
    def decode(buf, out=None):
        if out is None:
            return bytes(buf)
        out = np.frombuffer(out, dtype=np.uint8) if not isinstance(out, np.ndarray) else out
        view = out.reshape(-1).view(np.uint8)
        if len(buf) != view.size:
            raise ValueError(f"{len(buf)} bytes where {view.size} were expected")
        view[:] = np.frombuffer(buf, dtype=np.uint8)
        return out


NOT_WRITTEN = 2**64 - 1  # a shard index's offset and size of an inner chunk never written


def _shard_index(raw, entries: int, store, key: str, var: str) -> array.array:
    """The index at the end of a shard (``raw``: its last ``16 entries + 4`` bytes, the
    offsets and sizes then their CRC32C) as :func:`_index_table`; damage when it is short or
    its checksum differs."""
    from numcodecs.checksum32 import CRC32C

    try:
        if len(raw) != 16 * entries + 4:
            raise ValueError(f"{len(raw)} bytes, not the {16 * entries + 4} of its index")
        return _index_table(CRC32C(location="end").decode(raw))
    except Exception as exc:  # noqa: BLE001 - a short file, a checksum that differs
        raise damaged(
            store, f"chunk {key} of its layer {var!r} cannot be decoded (its shard index: {exc})"
        ) from None


def _index_table(index) -> array.array:
    """A shard's index (offset, size of each inner chunk, little-endian uint64) as one flat
    ``array.array``: its items read as Python ints, and it is a single object. As a list of
    pairs (``tolist``), the 257 objects of each shard set off the garbage collector, whose
    full passes over a process that has imported dask and xarray made mapping a 10000^2
    store's 300 shards 0.5-0.8 ms a shard instead of 0.13."""
    table = array.array("Q")
    table.frombytes(bytes(index))
    if sys.byteorder != "little":
        table.byteswap()
    return table


def direct_reader(arr, store: str, var: str):
    """A reader of whole chunks of ``arr`` (``read(index, out=None) -> ndarray``, clipped to the
    array; decoded into ``out``, a buffer of the chunk's bytes, when given)
    that fetches the chunk's bytes from its file or object and decodes them with numcodecs
    (None for a chunk that is not there), or None when the array is not laid out the way the
    maps stores are (Zarr 3 on a local directory or object storage, the ``bytes`` codec then
    one blosc or zstd compressor, either as the array's codecs or inside a sharding codec with
    its index at the end of each shard). zarr-python's own read costs about 1.5-2 ms a chunk
    more than the decode itself (benchmarks/RESULTS.md, "one mission"): a mission reads 16
    landmark chunks for its bound and a few per section.

    In a sharded array ``index`` is an inner chunk's: the reader reads the shard's index (the
    offset and size of each inner chunk, checked against its CRC32C) once, then each inner
    chunk's own bytes, so a window decodes the inner chunks it covers, not whole shards."""
    from zarr.storage import FsspecStore, LocalStore

    meta = arr.metadata
    if isinstance(arr.store, LocalStore):
        root = os.path.join(str(arr.store.root), arr.path)
        files: OrderedDict = OrderedDict()  # key -> its open file, the oldest first
        files_lock = threading.Lock()

        def handle(key: str):
            """The file of ``key``, kept open (the last ``OPEN_FILES`` of the layer): opening
            and closing a shard's file took as long as reading an inner chunk of it. A file
            dropped from the table closes when no thread reads it any more."""
            f = files.get(key)
            if f is None:
                f = open(os.path.join(root, key), "rb", buffering=0)  # noqa: SIM115 - kept
                with files_lock:
                    files[key] = f
                    while len(files) > OPEN_FILES:
                        files.popitem(last=False)
            return f

        def fetch(key: str, start: int | None = None, size: int | None = None):
            """The object's bytes; ``start`` (negative: from the end) and ``size`` a range.
            A range of known size is read into this thread's scratch buffer (a view of it,
            valid until the thread's next fetch): a new bytes object of a chunk's size is
            fresh memory, whose page faults cost more than the read itself."""
            if start is None or size is None:
                with open(os.path.join(root, key), "rb", buffering=0) as f:
                    if start is not None:
                        f.seek(start, os.SEEK_END if start < 0 else os.SEEK_SET)
                    return f.read()
            view = _scratch(size)
            if hasattr(os, "preadv"):  # no shared file position: one kept file for all threads
                f = handle(key)  # held while read: a file dropped by another thread stays open
                return view[: os.preadv(f.fileno(), [view], start)]
            with open(os.path.join(root, key), "rb", buffering=0) as f:
                f.seek(start)
                return view[: f.readinto(view)]

    elif isinstance(arr.store, FsspecStore) and is_url(store):
        fs, root = filesystem(join(store, var))  # a synchronous instance, for this thread

        def fetch(key: str, start: int | None = None, size: int | None = None) -> bytes:
            end = None if start is None or size is None else start + size
            return fs.cat_file(f"{root}/{key}", start=start, end=end)

    else:
        return None
    layout = _layout(arr)
    if layout is None:
        return None
    sharding, decoder = layout  # a compressor decodes whatever its settings
    chunks, shape, dtype = tuple(arr.chunks), tuple(arr.shape), arr.dtype

    def decode(raw: bytes, key: str, index: tuple, out):
        try:
            block = np.frombuffer(decoder.decode(raw, out=out), dtype=dtype).reshape(chunks)
        except Exception as exc:  # noqa: BLE001 - numcodecs raises RuntimeError, ValueError, ...
            where = key if sharding is None else f"{key} (inner chunk {index})"
            raise damaged(
                store, f"chunk {where} of its layer {var!r} cannot be decoded ({exc})"
            ) from None
        clip = zip(index, chunks, shape, strict=True)
        return block[tuple(slice(0, min(c, n - i * c)) for i, c, n in clip)]

    if sharding is None:

        def read(index: tuple, out=None):
            key = meta.encode_chunk_key(index)
            try:
                raw = fetch(key)
            except FileNotFoundError:
                return None
            return decode(raw, key, index, out)

        read.chunks, read.dtype = chunks, dtype
        return read

    per = tuple(s // c for s, c in zip(arr.shards, chunks, strict=True))  # inner chunks a shard
    entries = math.prod(per)
    tables: dict = {}  # shard key -> its index, offset and size of each inner chunk in turn

    def read(index: tuple, out=None):
        key = meta.encode_chunk_key(tuple(i // p for i, p in zip(index, per, strict=True)))
        table = tables.get(key)
        if table is None:
            try:
                raw = fetch(key, -(16 * entries + 4))
            except FileNotFoundError:
                return None
            except OSError:  # a file shorter than its index: the seek before its start fails
                raw = b""
            table = tables[key] = _shard_index(raw, entries, store, key, var)
        k = 0
        for i, p in zip(index, per, strict=True):  # the inner chunk's place in the shard, C order
            k = k * p + i % p
        offset, size = table[2 * k], table[2 * k + 1]
        if offset == size == NOT_WRITTEN:
            return None
        return decode(fetch(key, offset, size), key, index, out)

    read.chunks, read.dtype = chunks, dtype
    return read


class MappedLayer:
    """Windows of a local, sharded, uncompressed layer copied straight out of its shard files,
    memory-mapped: no read into a buffer, no decoding, no decoded chunk kept (the page cache
    is the cache). A shard is mapped when first read (its index checked against its CRC32C
    then), and each inner chunk read is kept as a view of its mapping (a window then costs a
    dictionary lookup and a copy a chunk); the last :data:`MAPPED_SHARDS` shards of the layer
    stay mapped (``keep``). The store's files are never rewritten in place (a rebuild writes a
    new store and renames it): a mapping holds the file it mapped. ``window`` returns None
    where a chunk is not there, for the caller to read through zarr (the fill value) or to
    report the damage."""

    def __init__(self, root: str, arr, store: str, var: str):
        self.root, self.store, self.var = root, store, var
        self.chunks = tuple(int(c) for c in arr.chunks)
        self.per = tuple(s // c for s, c in zip(arr.shards, self.chunks, strict=True))
        self.dtype = np.dtype(arr.dtype)
        self.keys = arr.metadata
        self.chunk_bytes = math.prod(self.chunks) * self.dtype.itemsize
        self.shards: OrderedDict = OrderedDict()  # shard index -> (bytes as uint8, its index)
        self.blocks: dict = {}  # inner chunk index -> its 2-D view of the mapped shard
        self.lock = threading.Lock()
        self.keep = MAPPED_SHARDS  # shards kept mapped (a whole layer's copy: a row of them)

    @classmethod
    def of(cls, arr, store: str, var: str):
        """The mapped layer of ``arr``, or None when it is not local, sharded, uncompressed."""
        from zarr.storage import LocalStore

        layout = _layout(arr)
        if (
            layout is None
            or layout[0] is None
            or not isinstance(layout[1], _Uncompressed)
            or not isinstance(arr.store, LocalStore)
            or arr.ndim != 2
        ):
            return None
        return cls(os.path.join(str(arr.store.root), arr.path), arr, store, var)

    def _shard(self, index: tuple):
        """Shard ``index`` mapped, with its index; None when its file is not there."""
        with self.lock:
            got = self.shards.get(index)
            if got is not None:
                self.shards.move_to_end(index)
                return got
        import mmap

        key = self.keys.encode_chunk_key(index)
        try:
            with open(os.path.join(self.root, key), "rb") as f:
                size = os.fstat(f.fileno()).st_size
                buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) if size else b""
        except FileNotFoundError:
            return None
        n = math.prod(self.per)
        table = _shard_index(buf[max(0, len(buf) - 16 * n - 4) :], n, self.store, key, self.var)
        got = (np.frombuffer(buf, dtype=np.uint8), table)
        (ph, pw) = self.per
        with self.lock:
            self.shards[index] = got
            while len(self.shards) > self.keep:  # unmapped once no window reads it
                (si, sj), _ = self.shards.popitem(last=False)
                for i in range(si * ph, si * ph + ph):
                    for j in range(sj * pw, sj * pw + pw):
                        self.blocks.pop((i, j), None)
        return got

    def _block(self, ci: int, cj: int):
        """Inner chunk ``(ci, cj)`` as a view of its mapped shard (kept), or None where it is
        not there (its shard, or its entry in the shard's index)."""
        (ph, pw) = self.per
        shard = self._shard((ci // ph, cj // pw))
        if shard is None:
            return None
        buf, table = shard
        k = 2 * ((ci % ph) * pw + cj % pw)
        offset, size = table[k], table[k + 1]
        if size != self.chunk_bytes or offset + size > buf.size:
            if offset == size == NOT_WRITTEN:
                return None
            where = f"{self.keys.encode_chunk_key((ci // ph, cj // pw))} (inner chunk "
            raise damaged(
                self.store,
                f"chunk {where}{(ci, cj)}) of its layer {self.var!r} cannot be decoded "
                f"({size} bytes at {offset}, {self.chunk_bytes} expected)",
            )
        block = buf[offset : offset + size].view(self.dtype).reshape(self.chunks)
        self.blocks[(ci, cj)] = block
        return block

    def window(self, r0: int, r1: int, c0: int, c1: int):
        blocks = self.blocks

        def block(ci, cj):
            got = blocks.get((ci, cj))
            return got if got is not None else self._block(ci, cj)

        return _assemble(r0, r1, c0, c1, self.chunks, self.dtype, block)

    def values(self, cells) -> np.ndarray | None:
        """The layer's values at ``cells`` (pairs of row and column), or None where a chunk
        is not there (as :meth:`window`)."""
        ch, cw = self.chunks
        blocks = self.blocks
        out = np.empty(len(cells), dtype=self.dtype)
        for k, (r, c) in enumerate(cells):
            ci, cj = r // ch, c // cw
            blk = blocks.get((ci, cj))
            if blk is None:
                blk = self._block(ci, cj)
                if blk is None:
                    return None
            out[k] = blk[r - ci * ch, c - cj * cw]
        return out


def _assemble(r0: int, r1: int, c0: int, c1: int, chunks, dtype, block):
    """Rows ``r0:r1`` and columns ``c0:c1`` of a layer of ``chunks``, copied from the chunks
    ``block(ci, cj)`` returns (each a chunk's array, which may be clipped at the layer's last
    row and column), or None as soon as one returns None."""
    ch, cw = chunks
    out = np.empty((r1 - r0, c1 - c0), dtype=dtype)
    for ci in range(r0 // ch, (r1 - 1) // ch + 1):
        b0 = ci * ch
        for cj in range(c0 // cw, (c1 - 1) // cw + 1):
            blk = block(ci, cj)
            if blk is None:
                return None
            d0 = cj * cw
            a0, a1 = max(r0, b0), min(r1, b0 + blk.shape[0])
            e0, e1 = max(c0, d0), min(c1, d0 + blk.shape[1])
            out[a0 - r0 : a1 - r0, e0 - c0 : e1 - c0] = blk[a0 - b0 : a1 - b0, e0 - d0 : e1 - d0]
    return out


MAPPED_SHARDS = 4096  # shard files a mapped layer keeps mapped (a 40000^2 layer has 1600)


def _morton(place: tuple, per: tuple) -> int:
    """The compressed Z-order code of an inner chunk's ``place`` in a shard of ``per`` inner
    chunks (zarr's order of the inner chunks in a shard's bytes): the axes' bits interleaved,
    the first axis lowest, each axis giving only the bits its count needs."""
    bits = [(int(n) - 1).bit_length() for n in per]
    code, out = 0, 0
    for b in range(max(bits, default=0)):
        for axis, i in enumerate(place):
            if b < bits[axis]:
                code |= ((int(i) >> b) & 1) << out
                out += 1
    return code


class ShardWriter:
    """Writes whole shards of a local sharded layer laid out as :func:`_layout` reads (what
    every maps layer is): ``writer(index, block)`` encodes the inner chunks of ``block`` (the
    shard at ``index`` of the shard grid, clipped to the layer) with the layer's compressor,
    lays them out in zarr's order after one another, appends their index and its CRC32C, and
    writes the shard's file, the same bytes zarr writes. Pickles as its few fields: a build
    sends it with each write task.

    zarr's own write of a shard took 15-26 ms a 1024^2 float32 shard of the 10000^2 benchmark
    map (its codec pipeline, the region's indexing, a task per inner chunk), against 2.4 ms for
    the 16 encodings themselves: the maps build's layers pass wrote 5 layers of 100 shards.
    Inner chunks wholly outside the layer (at its right and bottom edges) are left out, and
    parts of one are filled with the layer's fill value, as zarr does."""

    def __init__(self, root: str, arr, compressor):
        self.root = root
        self.shape = tuple(int(n) for n in arr.shape)
        self.shards = tuple(int(c) for c in arr.shards)
        self.inner = tuple(int(c) for c in arr.chunks)
        self.dtype = np.dtype(arr.dtype)
        self.fill = np.array(arr.metadata.fill_value, dtype=self.dtype)
        self.keys = arr.metadata.chunk_key_encoding
        self.compressor = compressor

    def __call__(self, index: tuple, block) -> int:
        """Write shard ``index`` holding ``block``; returns the bytes written."""
        from numcodecs.checksum32 import CRC32C

        block = np.asarray(block)
        want = tuple(
            min(s, n - i * s) for i, s, n in zip(index, self.shards, self.shape, strict=True)
        )
        if block.shape != want:
            raise ValueError(f"shard {index} of shape {want} given a block of {block.shape}")
        per = tuple(s // c for s, c in zip(self.shards, self.inner, strict=True))
        table = np.full((math.prod(per), 2), NOT_WRITTEN, dtype="<u8")
        parts, offset = [], 0
        for place in sorted(np.ndindex(*per), key=lambda p: _morton(p, per)):
            lo = tuple(p * c for p, c in zip(place, self.inner, strict=True))
            if any(a >= n for a, n in zip(lo, block.shape, strict=True)):
                continue  # wholly outside the layer
            piece = block[tuple(slice(a, a + c) for a, c in zip(lo, self.inner, strict=True))]
            if piece.shape != self.inner:
                full = np.full(self.inner, self.fill, dtype=self.dtype)
                full[tuple(slice(0, n) for n in piece.shape)] = piece
                piece = full
            raw = np.ascontiguousarray(piece, dtype=self.dtype).reshape(-1).view(np.uint8)
            data = self.compressor.encode(raw)
            k = np.ravel_multi_index(place, per)
            table[k] = (offset, len(data))
            offset += len(data)
            parts.append(data)
        parts.append(CRC32C(location="end").encode(table.tobytes()))
        path = os.path.join(self.root, self.keys.encode_chunk_key(tuple(int(i) for i in index)))
        os.makedirs(os.path.dirname(path), exist_ok=True)
        data = b"".join(parts)
        with open(path, "wb") as f:
            f.write(data)
        return len(data)


class ZarrBlockWriter:
    """``writer(index, block)`` through zarr: block ``index`` of the layer's storage blocks
    (its shards, else its chunks), for the layouts and storages :class:`ShardWriter` does not
    write (object storage)."""

    def __init__(self, store: str, var: str, blocks: tuple):
        self.store, self.var, self.blocks = store, var, blocks

    def __call__(self, index: tuple, block) -> int:
        import zarr

        arr = zarr.open_array(join(self.store, self.var), mode="r+", zarr_format=3)
        block = np.asarray(block)
        arr[
            tuple(
                slice(i * b, i * b + n)
                for i, b, n in zip(index, self.blocks, block.shape, strict=True)
            )
        ] = block
        return block.nbytes


def block_writer(store: str, var: str):
    """The writer of ``var``'s storage blocks in the Zarr store ``store`` (created already):
    a :class:`ShardWriter` where the layer is sharded on a local directory, else a
    :class:`ZarrBlockWriter`."""
    import zarr
    from zarr.storage import LocalStore

    arr = zarr.open_array(join(store, var), mode="r", zarr_format=3)
    layout = _layout(arr)
    if isinstance(arr.store, LocalStore) and layout is not None and layout[0] is not None:
        return ShardWriter(os.path.join(str(arr.store.root), arr.path), arr, layout[1])
    return ZarrBlockWriter(store, var, storage_chunks(arr))


class ChunkCache:
    """Decoded Zarr chunks of the maps stores this process has read (LRU, bounded in bytes).

    Sections of one mission, and missions on one map, read overlapping windows: each worker
    decodes a chunk once and keeps it while it fits in the budget. The windows of a local
    store's uncompressed layers are copied from their mapped shards instead
    (:class:`MappedLayer`) and hold nothing here."""

    def __init__(self, budget: int | None = None):
        self._budget = budget
        self.used = 0
        self.items: OrderedDict = OrderedDict()
        self.arrays: dict = {}
        self.readers: dict = {}
        self.layouts: dict = {}  # (store, var) -> (chunk shape, dtype) of a 2-D layer
        self.mapped: dict = {}  # (store, var) -> its MappedLayer, or None
        self.lock = threading.Lock()

    @property
    def budget(self) -> int:
        """Bytes kept at most: ``AUV_PIPELINE_CHUNK_CACHE_MB`` (default 1024) MiB, read at
        first use (a bad value is then one line, not an error at import)."""
        if self._budget is None:
            from ..params import env_number

            self._budget = env_number("AUV_PIPELINE_CHUNK_CACHE_MB", 1024, integer=True) * 2**20
        return self._budget

    def array(self, store: str, var: str):
        key = (store, var)
        arr = self.arrays.get(key)
        if arr is None:
            import zarr

            arr = zarr.open_array(join(store, var), mode="r", zarr_format=3)
            self.arrays[key] = arr
            self.readers[key] = direct_reader(arr, store, var)
        return arr

    def _read(self, store: str, var: str, index: tuple, complete: bool):
        """The chunk ``index`` of ``var``, decoded directly where the layout allows, else
        through zarr; a missing chunk of a complete store is damage."""
        arr = self.array(store, var)
        read = self.readers.get((store, var))
        block = read(index) if read is not None else None
        if block is not None:
            return block
        # the direct reader found no chunk there; else ask the storage (a chunk's key names its
        # file only without sharding; zarr reads other sharded layouts as they are)
        if complete and (
            read is not None
            or (
                getattr(arr, "shards", None) is None
                and not exists(join(store, var, arr.metadata.encode_chunk_key(index)))
            )
        ):
            what = ", ".join(str(i) for i in index)
            raise damaged(store, f"chunk ({what}) of its layer {var!r} is missing")
        return arr[tuple(slice(i * c, (i + 1) * c) for i, c in zip(index, arr.chunks, strict=True))]

    def _cached(self, key, load) -> np.ndarray:
        """The block under ``key``, or ``load()`` kept under it (least recently used first
        out while over the budget)."""
        with self.lock:
            got = self.items.get(key)
            if got is not None:
                self.items.move_to_end(key)
                return got
        block = load()
        with self.lock:
            self.items[key] = block
            self.used += block.nbytes
            while self.used > self.budget and len(self.items) > 1:
                _, old = self.items.popitem(last=False)
                self.used -= old.nbytes
        return block

    def chunk(self, store: str, var: str, ci: int, cj: int, complete: bool = False) -> np.ndarray:
        def load():
            return self._read(store, var, (ci, cj), complete)

        return self._cached((store, var, ci, cj), load)

    def chunk_into(
        self, store: str, var: str, ci: int, cj: int, out: np.ndarray, complete: bool = False
    ) -> tuple[int, int]:
        """Chunk ``(ci, cj)`` of ``var`` written into ``out`` (an array of the chunk's full
        shape): copied from the cache when it holds the chunk, else decoded straight into
        ``out`` and not kept (a read used once, such as the flight's corridor: no copy, no
        memory of the cache's own). Returns the chunk's shape within the layer (smaller at its
        right and bottom edges, where the rest of ``out`` holds what the store padded with)."""
        with self.lock:
            got = self.items.get((store, var, ci, cj))
        if got is None:
            self.array(store, var)
            read = self.readers.get((store, var))
            if (
                read is not None
                and out.flags.c_contiguous
                and tuple(out.shape) == tuple(read.chunks)
                and out.dtype.itemsize == read.dtype.itemsize
                and out.dtype.kind in (read.dtype.kind, "u" if read.dtype.kind == "b" else "")
            ):
                block = read((ci, cj), out.reshape(-1).view(np.uint8))
                if block is not None:
                    return block.shape
            got = self.chunk(store, var, ci, cj, complete)  # zarr's read, or the damage
        out[: got.shape[0], : got.shape[1]] = got
        return got.shape

    def _layer(self, store: str, var: str) -> tuple:
        """``((chunk shape, dtype), its MappedLayer or None)`` of the 2-D layer ``var``."""
        layout = self.layouts.get((store, var))
        if layout is None:  # zarr's metadata properties cost microseconds a call
            arr = self.array(store, var)
            layout = self.layouts[(store, var)] = (tuple(arr.chunks), arr.dtype)
            self.mapped[(store, var)] = MappedLayer.of(arr, store, var)
        return layout, self.mapped.get((store, var))

    def window(
        self, store: str, var: str, r0: int, r1: int, c0: int, c1: int, complete: bool = False
    ) -> np.ndarray:
        layout, mapped = self._layer(store, var)
        if mapped is not None:
            got = mapped.window(r0, r1, c0, c1)
            if got is not None:
                return got  # else a chunk is not there: its fill value, or the damage, below
        chunks, dtype = layout
        return _assemble(
            r0, r1, c0, c1, chunks, dtype, lambda ci, cj: self.chunk(store, var, ci, cj, complete)
        )

    def values(self, store: str, var: str, cells, complete: bool = False) -> np.ndarray:
        """The values of the 2-D layer ``var`` at ``cells`` (pairs of row and column): looked
        up in the mapped shards or the cached chunks, with no window copied around each."""
        ((ch, cw), dtype), mapped = self._layer(store, var)
        got = mapped.values(cells) if mapped is not None else None
        if got is not None:
            return got
        out = np.empty(len(cells), dtype=dtype)
        for k, (r, c) in enumerate(cells):
            ci, cj = r // ch, c // cw
            out[k] = self.chunk(store, var, ci, cj, complete)[r - ci * ch, c - cj * cw]
        return out

    def stack_values(
        self, store: str, var: str, r: int, c: int, complete: bool = False
    ) -> np.ndarray:
        """The values at cell ``(r, c)`` of every layer of a 3-D ``var`` (layer, y, x), read
        past the cache: each chunk that holds the cell is decoded into this thread's scratch
        buffer and only the cell's values are kept. A mission's landmark bound needs 8 values
        at each end, and a new mission's ends lie in chunks not read before: keeping those
        chunks cost fresh memory, whose page faults took longer than the decoding (a new
        mission's bound: 1.2 -> 0.8 ms at 2000^2, 2.0 -> 1.5 ms at 10000^2)."""
        arr = self.array(store, var)
        kc, ch, cw = arr.chunks
        read = self.readers.get((store, var))
        ci, cj = r // ch, c // cw
        values = np.empty(arr.shape[0], dtype=arr.dtype)
        for k in range(-(-arr.shape[0] // kc)):  # chunks along the layer axis
            block = None
            if read is not None:
                block = read((k, ci, cj), _decoded(math.prod(read.chunks) * read.dtype.itemsize))
            if block is None:  # zarr's read, a chunk not written, or the damage
                block = self._read(store, var, (k, ci, cj), complete)
            # copied out before the next chunk is decoded into the same buffer
            values[k * kc : k * kc + block.shape[0]] = block[:, r - ci * ch, c - cj * cw]
        return values

    def forget(self, store: str) -> None:
        """Drop what this cache holds of ``store``: its decoded chunks and open arrays."""
        with self.lock:
            for key in [k for k in self.items if k[0] == store]:
                self.used -= self.items.pop(key).nbytes
            for d in (self.arrays, self.readers, self.layouts, self.mapped):
                for key in [k for k in d if k[0] == store]:
                    del d[key]

    def clear(self) -> None:
        with self.lock:
            self.items.clear()
            self.arrays.clear()
            self.readers.clear()
            self.layouts.clear()
            self.mapped.clear()
            self.used = 0


CACHE = ChunkCache()  # its budget: AUV_PIPELINE_CHUNK_CACHE_MB, read when first needed


class MapsStore:
    """A maps store (:func:`pipeline.build_maps`): shape, cell size, coordinates, CRS and
    parameters, windows of its layers, its coarse maps, cells of map or lon/lat coordinates.

    Open it with :func:`open_store` (one per store and process)."""

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
            params = attrs.get("parameters")
            self.parameters = json.loads(params) if isinstance(params, str) else params
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
        from ..maps.landmarks import VARIABLE

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
        from ..maps.landmarks import VARIABLE

        r, c = int(cell[0]), int(cell[1])
        values = CACHE.stack_values(self.path, VARIABLE, r, c, self.all_chunks_written)
        return values.astype(np.float64)

    def landmark_window(self, i: int, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """Rows ``r0:r1`` and columns ``c0:c1`` of landmark ``i``'s distance layer (read
        directly, not cached: the whole-map search reads large windows once)."""
        from ..maps.landmarks import VARIABLE

        return CACHE.array(self.path, VARIABLE)[i, r0:r1, c0:c1]

    def active_landmarks(self, start, goal, k: int) -> list[int]:
        """The ``k`` landmarks whose bound is largest for this pair of cells (the most useful
        as an A* heuristic towards ``goal``)."""
        ds, dg = self.landmark_distances(start), self.landmark_distances(goal)
        both = np.isfinite(ds) & np.isfinite(dg)
        gain = np.full(ds.shape, -1.0)
        gain[both] = np.abs(ds[both] - dg[both])
        return [int(i) for i in np.argsort(-gain, kind="stable")[:k] if both[i]]

    def lower_bound(self, start, goal) -> float:
        """A proven lower bound (metres) on the shortest safe path from ``start`` to ``goal``
        on the whole map: the landmark bound (:func:`pipeline.maps.landmarks.lower_bound`), or 0
        with no landmark layers."""
        from ..maps.landmarks import lower_bound

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
            from ..planners.core import check_arrays

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
        of reading every chunk of the elevation under the mission's extent (at 10000^2, 0.2 s
        of each quick-look)."""
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
        nor dask.array, whose imports took a worker 0.6 s at its first mission (the arrays are
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
        col = int(round((x - xs[0]) / (xs[1] - xs[0])))
        row = int(round((y - ys[0]) / (ys[1] - ys[0])))
        if not (0 <= row < len(ys) and 0 <= col < len(xs)):
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
    ``attrs["store"]`` holds its path, so :func:`pipeline.plan` accepts the Dataset too."""
    import xarray as xr
    import zarr

    store = location(store)
    _require_store(store)
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
            from ..maps.landmarks import VARIABLE

            ds = xr.open_zarr(store, chunks=shards, drop_variables=[VARIABLE], **opts)
            if VARIABLE in group:
                ds[VARIABLE] = xr.open_zarr(store, chunks={}, **opts)[VARIABLE]
    except Exception as exc:  # noqa: BLE001 - object storage raises its own errors
        if not is_url(store):
            raise
        raise unreachable(store, exc) from None
    _require_version(store, ds.attrs)
    ds.attrs["store"] = store
    ds.attrs["parameters"] = (
        json.loads(ds.attrs["parameters"])
        if isinstance(ds.attrs.get("parameters"), str)
        else ds.attrs.get("parameters")
    )
    return ds
