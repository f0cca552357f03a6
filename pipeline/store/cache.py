"""The decoded chunks of the maps stores a process reads, kept in one LRU cache bounded in bytes
(``AUV_PIPELINE_CHUNK_CACHE_MB``, 1 GiB by default) that every store of the process shares.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict

import numpy as np

from .paths import exists, join
from .schema import damaged
from .zarr_direct import MappedLayer, assemble_window, decoded_buffer, direct_reader


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
            from ..runtime.env import setting

            self._budget = setting("AUV_PIPELINE_CHUNK_CACHE_MB") * 2**20
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
        return assemble_window(
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
        chunks cost fresh memory, whose page faults took longer than the decoding."""
        arr = self.array(store, var)
        kc, ch, cw = arr.chunks
        read = self.readers.get((store, var))
        ci, cj = r // ch, c // cw
        values = np.empty(arr.shape[0], dtype=arr.dtype)
        for k in range(-(-arr.shape[0] // kc)):  # chunks along the layer axis
            block = None
            if read is not None:
                block = read(
                    (k, ci, cj), decoded_buffer(math.prod(read.chunks) * read.dtype.itemsize)
                )
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
