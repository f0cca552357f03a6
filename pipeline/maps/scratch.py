"""The maps build's scratch tiles: plain ``.npy`` files, one a tile and quantity, beside the store
(on the same storage, so every worker reads and writes them), which the build's passes read
back with the halo each needs.
"""

from __future__ import annotations

import os
import threading

from ..store.paths import filesystem, is_url, join

# np.load parses a .npy file's header with ast.literal_eval, and CPython 3.11's AST
# constructor is not safe in several threads at once (python/cpython#106905): tiles read in
# dask's threads raised "SystemError: AST constructor recursion depth mismatch" at random.
# Their headers are parsed one at a time; the data is read outside the lock.
_HEADERS = threading.Lock()


def save_tile(scratch, name: str, tile: tuple, array) -> None:
    """Tile ``tile`` (its place in the tile grid) of the build scratch layer ``name``, kept as
    one ``.npy`` file under ``scratch`` (a path or a URL): each tile has one writer and is read
    whole, so no chunk grid constrains the tiles. As a file a tile reads in half the time of an
    uncompressed zarr chunk and writes in what the page cache costs (CHANGELOG.md,
    "Measurements")."""
    import io

    import numpy as np

    key = f"{tile[0]}.{tile[1]}.npy"
    buf = io.BytesIO()
    np.save(buf, np.asarray(array), allow_pickle=False)
    if is_url(scratch):
        fs, path = filesystem(join(str(scratch), name, key))
        fs.pipe_file(path, buf.getvalue())
        return
    folder = os.path.join(scratch, name)
    os.makedirs(folder, exist_ok=True)
    # written by Python's file, not numpy's tofile: a full disk then raises the OSError with
    # its errno (ENOSPC, EFBIG), which the command line turns into its one line
    with open(os.path.join(folder, key), "wb") as f:
        f.write(buf.getbuffer())


def load_tile(scratch, name: str, tile: tuple, mapped: bool = False):
    """The tile :func:`save_tile` kept; with ``mapped``, a local tile is memory-mapped (read
    only: a caller that copies part of it reads only that part's pages)."""
    import io

    import numpy as np

    key = f"{tile[0]}.{tile[1]}.npy"
    if is_url(scratch):
        fs, path = filesystem(join(str(scratch), name, key))
        data = fs.cat_file(path)
        with _HEADERS:  # the bytes are in memory: the header and a copy
            return np.load(io.BytesIO(data), allow_pickle=False)
    with _HEADERS:
        tile_map = np.load(os.path.join(scratch, name, key), mmap_mode="r", allow_pickle=False)
    return tile_map if mapped else np.array(tile_map)


def load_window(scratch, name: str, r_off, c_off, r0: int, r1: int, c0: int, c1: int, dtype):
    """Rows ``r0:r1`` and columns ``c0:c1`` of the scratch layer ``name`` whose tiles
    :func:`save_tile` kept on the grid of row and column offsets ``r_off`` and ``c_off``
    (tile ``(i, j)`` covers rows ``r_off[i]:r_off[i + 1]``): a window across as many tiles as
    it spans, so a halo of any width is read from the tiles that hold it, with no dask task
    that slices one tile for another."""
    import numpy as np

    out = np.empty((r1 - r0, c1 - c0), dtype=dtype)
    remote = is_url(scratch)
    i0 = int(np.searchsorted(r_off, r0, side="right")) - 1
    i1 = int(np.searchsorted(r_off, r1, side="left"))
    j0 = int(np.searchsorted(c_off, c0, side="right")) - 1
    j1 = int(np.searchsorted(c_off, c1, side="left"))
    for i in range(i0, i1):
        a0, a1 = max(r0, int(r_off[i])), min(r1, int(r_off[i + 1]))
        for j in range(j0, j1):
            b0, b1 = max(c0, int(c_off[j])), min(c1, int(c_off[j + 1]))
            top = a0 - int(r_off[i])
            if remote:  # only the rows wanted, in one range request
                tile = _tile_rows(scratch, name, (i, j), top, a1 - int(r_off[i]))
                top = 0
            else:
                tile = load_tile(scratch, name, (i, j), mapped=True)
            out[a0 - r0 : a1 - r0, b0 - c0 : b1 - c0] = tile[
                top : top + a1 - a0, b0 - int(c_off[j]) : b1 - int(c_off[j])
            ]
            del tile
    return out


def _tile_rows(scratch: str, name: str, tile: tuple, a: int, b: int):
    """Rows ``a:b`` of a 2-D tile :func:`save_tile` kept on object storage: its ``.npy``
    header, then those rows' bytes (C order), each in one range request."""
    import io

    import numpy as np

    fs, path = filesystem(join(str(scratch), name, f"{tile[0]}.{tile[1]}.npy"))
    head = io.BytesIO(fs.cat_file(path, start=0, end=4096))
    fmt = np.lib.format
    version = fmt.read_magic(head)
    read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
    shape, fortran, dtype = read(head)
    if fortran:  # rows not contiguous: the whole tile
        return load_tile(scratch, name, tile)[a:b]
    row = shape[1] * dtype.itemsize
    start = head.tell() + a * row
    data = fs.cat_file(path, start=start, end=start + (b - a) * row)
    return np.frombuffer(data, dtype=dtype).reshape(b - a, shape[1])


def tile_array(scratch, name: str, chunks, dtype):
    """The scratch layer ``name`` that :func:`save_tile` kept, as a dask array of ``chunks`` (a
    tile a block, the block's place in the grid its tile's)."""
    import dask.array as da
    import numpy as np

    return da.map_blocks(
        _load_block, scratch, name, chunks=chunks, dtype=dtype, meta=np.empty((0, 0), dtype)
    )


def _load_block(scratch, name: str, block_info=None):
    return load_tile(scratch, name, tuple(block_info[None]["chunk-location"]))
