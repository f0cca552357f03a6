"""Connected components of the passable graph, chunk-wise and exact (docs/method.md section 9:
"unreachable" is said only when proven).

The planners' graph joins passable cells by the 8 moves, a diagonal only when both cells it
passes between are passable. Such a diagonal step is then also two orthogonal steps, so two
cells are joined in that graph exactly when they are joined by orthogonal steps: the
components are those of 4-connectivity, and ``scipy.ndimage.label`` with the cross element
labels a tile.

Chunked input is labelled in two streaming passes, bounded in memory like the ridge build:
(1) every tile is labelled on its own, its labels go to a scratch tile and only its border
rows and columns come back; (2) a small global solve joins the labels that touch across tile
borders (``scipy.sparse.csgraph.connected_components`` on that graph), and every tile is
relabelled through the resulting table. Labels are 1..N in the order of each component's
first cell in row-major order, 0 where a cell is not passable: ``scipy.ndimage.label``'s
numbering, so the result is the same for any chunking and in memory.
"""

from __future__ import annotations

import dask
import dask.array as da
import numpy as np
from scipy import ndimage

from ..runtime.jit import njit
from .scratch import load_tile, save_tile

CROSS = ndimage.generate_binary_structure(2, 1)


def label_components(passable: np.ndarray) -> tuple[np.ndarray, int]:
    """(labels, count) of an in-memory passable array: int32, 1..count, 0 not passable."""
    labels, n = ndimage.label(np.asarray(passable, dtype=bool), structure=CROSS)
    return labels.astype(np.int32), int(n)


def label_tile(block, r0: int, c0: int, ncols: int, scratch: str, tile: tuple):
    """Pass 1 for one tile (``tile``: its place in the tile grid): label it, keep the labels as
    a scratch tile (uint16 when they fit: half the bytes); return its count, the global
    row-major index of each label's first cell, and its borders."""
    labels, n = label_components(block)
    rows, cols = labels.shape
    save_tile(scratch, "labels", tile, labels.astype(np.uint16) if n <= 65535 else labels)
    first = _first_cells(labels, n)  # local row-major indices
    first = (r0 + first // cols) * ncols + (c0 + first % cols)
    return (
        n,
        first,
        (labels[0].copy(), labels[-1].copy(), labels[:, 0].copy(), labels[:, -1].copy()),
    )


@njit(nogil=True, cache=True)
def _first_cells(labels, n):
    """The row-major index of the first cell of each label 1..n: ``scipy.ndimage.label``
    numbers labels in the order their first cells come in that order, so label ``k``'s first
    cell is the first cell holding ``k`` once ``1..k-1`` have all been seen."""
    flat = labels.ravel()
    first = np.empty(n, dtype=np.int64)
    want = 1
    for i in range(flat.size):
        if flat[i] == want:
            first[want - 1] = i
            want += 1
            if want > n:
                break
    return first


def join_tiles(counts, firsts, borders, nbr: int, nbc: int) -> tuple[np.ndarray, np.ndarray]:
    """(table, offsets): the global label of tile t's local label k is ``table[offsets[t] +
    k]``, with ``table[offsets[t]] == 0`` for k == 0."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    counts = np.asarray(counts, dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts + 1)[:-1]])  # slot 0 of a tile: label 0
    total = int((counts + 1).sum())
    src, dst = [], []

    def join(a, oa, b, ob):
        both = (a > 0) & (b > 0)
        src.append(a[both].astype(np.int64) + oa)
        dst.append(b[both].astype(np.int64) + ob)

    for bi in range(nbr):
        for bj in range(nbc):
            t = bi * nbc + bj
            if bi + 1 < nbr:  # this tile's last row against the first row of the one below
                join(borders[t][1], offsets[t], borders[t + nbc][0], offsets[t + nbc])
            if bj + 1 < nbc:  # its last column against the first column of the one right
                join(borders[t][3], offsets[t], borders[t + 1][2], offsets[t + 1])
    src = np.concatenate(src) if src else np.zeros(0, np.int64)
    dst = np.concatenate(dst) if dst else np.zeros(0, np.int64)
    graph = coo_matrix((np.ones(src.size, np.int8), (src, dst)), shape=(total, total))
    _, comp = connected_components(graph, directed=False)
    # number the components 1..N by their first cell in row-major order (scipy's numbering);
    # slot 0 of every tile maps to 0
    zero = np.zeros(total, dtype=bool)
    zero[offsets] = True
    slot_first = np.full(total, np.iinfo(np.int64).max)
    slot_first[~zero] = (
        np.concatenate([np.asarray(f, np.int64) for f in firsts])
        if len(firsts)
        else np.zeros(0, np.int64)
    )
    keys, inverse = np.unique(comp[~zero], return_inverse=True)
    comp_first = np.full(keys.size, np.iinfo(np.int64).max)
    np.minimum.at(comp_first, inverse, slot_first[~zero])
    rank = np.empty(keys.size, dtype=np.int64)
    rank[np.argsort(comp_first)] = np.arange(1, keys.size + 1)
    table = np.zeros(total, dtype=np.int32)
    table[~zero] = rank[inverse]
    return table, offsets


def relabel_tile(scratch: str, tile: tuple, table, offsets, nbc: int) -> np.ndarray:
    """Pass 2 for one tile: its global labels, from the local labels :func:`label_tile` kept
    and the table :func:`join_tiles` solved."""
    local = load_tile(scratch, "labels", tile)
    return table[offsets[tile[0] * nbc + tile[1]] + local.astype(np.int64)]


def _relabel_block(scratch: str, table, offsets, nbc: int, block_info=None):
    """:func:`relabel_tile` as a dask block of the tile grid."""
    return relabel_tile(scratch, tuple(block_info[None]["chunk-location"]), table, offsets, nbc)


def components_staged(passable: da.Array, scratch) -> tuple[da.Array, int]:
    """``(labels, count)``: the component labels of a chunked passable array (see the module
    doc) and how many components there are (known once the labels are joined, before the
    labels are written). ``scratch`` is a directory for the scratch tiles that the returned
    array reads, so it must live until the result is written."""
    ok = passable.astype(bool)
    ok = ok.rechunk((ok.chunks[0][0], ok.chunks[1][0]))  # regular tiles
    scratch = str(scratch)
    r_off = np.concatenate([[0], np.cumsum(ok.chunks[0])])
    c_off = np.concatenate([[0], np.cumsum(ok.chunks[1])])
    nbr, nbc = len(ok.chunks[0]), len(ok.chunks[1])
    blocks = ok.to_delayed()
    parts = dask.compute(
        *[
            dask.delayed(label_tile, pure=False)(
                blocks[bi, bj], int(r_off[bi]), int(c_off[bj]), ok.shape[1], scratch, (bi, bj)
            )
            for bi in range(nbr)
            for bj in range(nbc)
        ]
    )
    table, offsets = join_tiles(
        [p[0] for p in parts], [p[1] for p in parts], [p[2] for p in parts], nbr, nbc
    )
    # the tables travel as graph keys (sent once to each worker), not in closures
    table_key = dask.delayed(table, pure=True)
    offsets_key = dask.delayed(offsets, pure=True)
    labels = da.map_blocks(
        _relabel_block,
        scratch,
        table_key,
        offsets_key,
        nbc,
        chunks=ok.chunks,
        dtype=np.int32,
        meta=np.empty((0, 0), np.int32),
    )
    return labels, int(table.max(initial=0))
