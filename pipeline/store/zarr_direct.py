"""Zarr v3 shards read and written directly: a layer's shard index decoded and its inner chunks
read into a window without zarr-python's per-chunk machinery (:func:`direct_reader`), an
uncompressed local layer's shards mapped into memory (:class:`MappedLayer`), and a layer's
blocks written as whole shards (:class:`ShardWriter`, else zarr's own writes,
:class:`ZarrBlockWriter`).
"""

from __future__ import annotations

import array
import math
import os
import sys
import threading
from collections import OrderedDict

import numpy as np

from .paths import filesystem, is_url, join
from .schema import damaged, storage_chunks

_SCRATCH = threading.local()


# shard files a direct reader keeps open, per layer (a 10000^2 layer of 1024^2 shards has 100)
OPEN_FILES = 64


def _scratch(size: int) -> memoryview:
    """A view of ``size`` bytes of this thread's reusable read buffer (grown as needed)."""
    buf = getattr(_SCRATCH, "buf", None)
    if buf is None or len(buf) < size:
        buf = _SCRATCH.buf = bytearray(max(size, 2**20))
    return memoryview(buf)[:size]


def decoded_buffer(size: int) -> np.ndarray:
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
    """The "compressor" of a layer stored without one
    (:data:`pipeline.store.schema.WINDOW_LAYERS` of a local store): its bytes copied (out of
    the thread's scratch buffer they were read into) into ``out`` or a new buffer."""

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
    full passes over a process that has imported dask and xarray made mapping a store's shards
    several times slower."""
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
    its index at the end of each shard). zarr-python's own read costs several times the decode
    itself (CHANGELOG.md, "Measurements"): a mission reads 16 landmark chunks for its bound and
    a few per section.

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

        return assemble_window(r0, r1, c0, c1, self.chunks, self.dtype, block)

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


def assemble_window(r0: int, r1: int, c0: int, c1: int, chunks, dtype, block):
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

    zarr's own write of a shard took many times the encodings themselves (its codec pipeline,
    the region's indexing, a task per inner chunk; CHANGELOG.md, "Measurements"), and the maps
    build's layers pass writes 5 layers of a shard a tile.
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
