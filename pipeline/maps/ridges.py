"""Ridge maps by flow accumulation on the inverted DEM (docs/method.md section 3; the paper's
4.2.2).

Esri's ridge-line recipe, made exact and chunk-wise:

1. fill the depressions of ``z`` (what priority-flood computes, Barnes et al. 2014); map edges
   and cells next to no-data are outlets;
2. invert: ``w = -filled`` (not filled again: flow ends at summits);
3. D8 on ``w``: the neighbour with the steepest strictly positive drop per distance, ties to
   the first in a fixed neighbour order (E, SE, S, SW, W, NW, N, NE); no lower neighbour means a
   sink (summits, flats left by filling, and outlets with nothing lower);
4. accumulation: the number of cells draining through a cell, itself included;
5. ``ridge = accumulation >= min_accumulation``.

Steps 1 and 4 are global. For chunked input they follow R. Barnes' tiled algorithms (parallel
Priority-Flood, 2016; parallel flow accumulation, 2017), reimplemented from the papers:

- fill: every tile fills itself towards its perimeter cells (each a terminal labelled with its
  global cell index) and its true outlets (``_basin_fill``): each cell gets its local fill and
  the terminal its water reaches at that level, and the tile records the minimax height
  between its terminals (a spanning tree of them) and across its borders. One small global
  minimax search over those labels gives each label's spill level; each tile then finishes
  with ``max(local fill, spill[label])`` (exact: the label's local minimax is the cell's, and
  the spanning tree keeps every minimax between the tile's terminals).
- accumulation: every tile computes D8 (with a one-cell halo of the filled DEM) and its local
  accumulation, the links where flow leaves it, and for each border cell the link its flow
  leaves through (walked downstream, each cell once). A global pass over the links (a forest
  of chains) gives the inflow at every entry cell; each tile re-accumulates with weights
  ``1 + inflow``.

Only perimeter data crosses between tiles, and the results equal the single-array ones cell
for cell (integer accumulation, fill values copied from the input).

One algorithm, driven three ways over the same kernels (the tile fill, D8, the accumulation
walk and the two global solves): in memory (``fill_single``, ``accumulation_single``: a numpy
array, no dask), as a lazy dask graph (``fill_depressions`` and ``flow_accumulation`` of a
chunked DEM: the tiles' summaries are tasks of the graph, so nothing is written to disk and
the caller owns no scratch), and staged (``flood_and_solve``: the maps build, each tile
flooded once and kept in scratch tiles, which the build's per-tile pass reads beside the
other layers). All three equal the in-memory result cell for cell for any tiling.

Fills, whole-array and per tile, use descent basins and a minimax over the basins that touch
(no priority queue over cells, ``_basin_fill``); accumulations walk each flow chain once from
its sources (``_accumulate_single`` for a whole array in memory, ``_accumulate`` per tile).
"""

from __future__ import annotations

import math
import time
from typing import NamedTuple

import dask
import dask.array as da
import numpy as np
import xarray as xr

from ..dem.canonical import cell_size as _cell_size
from ..dem.canonical import check_dem, require_valid_cells
from ..params import MAPS
from ..planners.grid import DC, DIST, DR, flat_offsets, inside
from ..planners.heap import grown
from ..runtime.cluster import compute_told, prefixed
from ..runtime.jit import njit
from ..runtime.threads import shared_pool
from .scratch import load_tile, load_window, save_tile, tile_array

OUTLET = -1


# --------------------------------------------------------------------------- fill


@njit(nogil=True, cache=True)
def _outlets(z, top, left, bottom, right, at_top, at_left, at_bottom, at_right):
    """True outlets among the cells of ``z`` (a block with halos of the given widths): valid
    cells on the map edge or with a no-data 8-neighbour. ``at_*`` say whether a side of the
    block is the map edge. Cells whose neighbourhood is not fully inside the block are only
    marked when that can be decided (the result is used for the inner block and one ring)."""
    rows, cols = z.shape
    out = np.zeros((rows, cols), dtype=np.bool_)
    for i in range(rows):
        for j in range(cols):
            if z[i, j] != z[i, j]:
                continue
            if (
                (at_top and i == 0)
                or (at_bottom and i == rows - 1)
                or (at_left and j == 0)
                or (at_right and j == cols - 1)
            ):
                out[i, j] = True
                continue
            for k in range(8):
                ni = i + DR[k]
                nj = j + DC[k]
                if 0 <= ni < rows and 0 <= nj < cols and z[ni, nj] != z[ni, nj]:
                    out[i, j] = True
                    break
    return out


@njit(cache=True)
def _slot(keys, key):
    """The slot of ``key`` in an open-addressing table (linear probing; -1 marks empty)."""
    mask = keys.size - 1
    h = (key * np.int64(0x9E3779B97F4A7C15)) & mask
    while keys[h] != -1 and keys[h] != key:
        h = (h + 1) & mask
    return h


_CACHE = 4096  # entries of the basin fill's pair cache (48 KiB: it stays in L2)


@njit(cache=True)
def _new_table(cap):
    return np.full(cap, np.int64(-1), dtype=np.int64), np.empty(cap, dtype=np.float32)


@njit(cache=True)
def _table_min(keys, vals, used, key, w):
    """``table[key] = min(table[key], w)`` in the open-addressing table (keys, vals), grown
    (doubled) when half full; returns the table and its count."""
    if 2 * (used + 1) > keys.size:
        old_k, old_v = keys, vals
        keys, vals = _new_table(2 * keys.size)
        for t in range(old_k.size):
            if old_k[t] != -1:
                h = _slot(keys, old_k[t])
                keys[h] = old_k[t]
                vals[h] = old_v[t]
    h = _slot(keys, key)
    if keys[h] == -1:
        keys[h] = key
        vals[h] = w
        used += 1
    elif w < vals[h]:
        vals[h] = w
    return keys, vals, used


@njit(nogil=True, cache=True)
def _basin_fill(z, seed, want_labels):
    """Depression filling (NaN = no-data) towards the terminal cells marked in ``seed``: each
    cell's lowest level at which water from it reaches a terminal (the minimax height of its
    paths to one), what Priority-Flood (Barnes et al., 2014) computes, without a priority
    queue over cells. ``seed``: -1 an outlet (all outlets are one terminal), ``p >= 0`` the
    terminal ``p`` (a tile's perimeter cell), -2 any other cell; every non-terminal valid cell
    must have 8 valid neighbours in the array (cells next to no-data are outlets).

    1. Every non-terminal cell descends to its lowest strictly lower neighbour; a cell with
       none is a pit. Descending, every cell reaches a pit or a terminal: its basin.
    2. Basins that touch get an edge weighted by the lowest ``max(z_a, z_b)`` over their
       touching cell pairs (8-neighbours).
    3. Kruskal: edges by weight, joined with a union-find. A pit basin's level is the weight
       at which its component first holds a terminal (its minimax to the nearest terminal),
       and that terminal is its label; when two components that hold terminals join at
       weight ``w``, the edge (label a, label b, w) is recorded: these edges keep the minimax
       between any two terminals (they are a minimum spanning tree of the terminals).
    4. ``filled = max(z, level[basin])`` (a terminal's basin has level -inf).

    Why it is exact: inside a basin, every cell is reached from its root by its descent path
    reversed, whose highest cell is that cell, so crossing between basins costs at least and
    at most the edge weight; the pit's minimax is therefore its basin's level, and a cell's
    minimax is the larger of its own height (its descent reaches the root) and that level.

    Returns the filled surface, each cell's label (the terminal its water reaches at its
    level: -1 outlet, ``p``, -3 no-data; an empty array unless ``want_labels``), and the
    terminal edges ``(a, b, w)``.
    """
    rows, cols = z.shape
    n = rows * cols
    zf = z.ravel()
    sf = seed.ravel()
    NONE = np.int64(-1)
    # 1: descent and basins. Nodes: 0 the outlets, 1 + p terminal p, then the pits
    nterm = 0
    for c in range(n):
        if sf[c] >= nterm:
            nterm = sf[c] + 1
    off = flat_offsets(cols)
    down = np.full(n, -1, dtype=np.int8)  # the neighbour (D8 code) a cell descends to
    node = np.full(n, np.int32(-1), dtype=np.int32)
    npit = 0
    for c in range(n):
        zc = zf[c]
        if zc != zc:
            continue
        if sf[c] >= -1:
            node[c] = sf[c] + 1
            continue
        low = zc
        best = -1
        for k in range(8):
            m = c + off[k]
            if zf[m] < low:
                low = zf[m]
                best = k
        if best < 0:
            node[c] = 1 + nterm + npit
            npit += 1
        else:
            down[c] = best
    # most cells descend to a neighbour already labelled in a raster pass one way or the
    # other: two sequential passes label those (fewer cache misses), the walks the rest
    for c in range(n):
        d = down[c]
        if d >= 0:
            b = node[c + off[d]]
            if b >= 0:
                node[c] = b
    for c in range(n - 1, -1, -1):
        d = down[c]
        if d >= 0 and node[c] < 0:
            b = node[c + off[d]]
            if b >= 0:
                node[c] = b
    path = np.empty(1024, dtype=np.int64)
    for c in range(n):
        if node[c] >= 0 or zf[c] != zf[c]:
            continue
        np_ = 0
        x = c
        while node[x] < 0:
            if np_ == path.size:
                path = grown(path, np_, 2 * path.size)
            path[np_] = x
            np_ += 1
            x = x + off[down[x]]
        b = node[x]
        for t in range(np_):
            node[path[t]] = b
    # 2: the lowest crossing between touching basins, in a hash table keyed by the node pair.
    # The table is far larger than the processor's caches and most crossings repeat a pair
    # met a few cells or a row before, so a small direct-mapped table (a write-back cache)
    # takes them first: a pair goes to the big table only when evicted, and at the end
    nodes = np.int64(1 + nterm + npit)
    keys, vals = _new_table(1024)
    used = 0
    ck = np.full(_CACHE, NONE, dtype=np.int64)
    cv = np.empty(_CACHE, dtype=np.float32)
    for ci in range(rows):
        for cj in range(cols):
            c = ci * cols + cj
            a = node[c]
            if a < 0:
                continue
            for k in range(4):  # E, SE, S, SW: each pair once
                ni = ci + DR[k]
                nj = cj + DC[k]
                if ni >= rows or nj < 0 or nj >= cols:
                    continue
                m = ni * cols + nj
                bnode = node[m]
                if bnode < 0 or bnode == a:
                    continue
                lo, hi = (a, bnode) if a < bnode else (bnode, a)
                w = max(zf[c], zf[m])
                key = np.int64(lo) * nodes + hi
                h = ((key * np.int64(0x9E3779B97F4A7C15)) >> 40) & (_CACHE - 1)
                if ck[h] == key:
                    if w < cv[h]:
                        cv[h] = w
                    continue
                if ck[h] != NONE:
                    keys, vals, used = _table_min(keys, vals, used, ck[h], cv[h])
                ck[h] = key
                cv[h] = w
    for h in range(_CACHE):
        if ck[h] != NONE:
            keys, vals, used = _table_min(keys, vals, used, ck[h], cv[h])
    # 3: Kruskal; a component's terminal label (-2: none yet) and, while it has none, its
    # members in a linked list
    ek = np.empty(used, dtype=np.int64)
    ew = np.empty(used, dtype=np.float32)
    e = 0
    for t in range(keys.size):
        if keys[t] != NONE:
            ek[e] = keys[t]
            ew[e] = vals[t]
            e += 1
    order = np.argsort(ew, kind="mergesort")
    parent = np.arange(nodes)
    first = np.arange(nodes)
    nxt = np.full(nodes, NONE, dtype=np.int64)
    last = np.arange(nodes)
    label = np.full(nodes, -2, dtype=np.int64)
    label[0] = -1
    for p in range(nterm):
        label[1 + p] = p
    level = np.full(nodes, -np.inf, dtype=np.float32)
    ta = np.empty(nterm + 1, dtype=np.int64)
    tb = np.empty(nterm + 1, dtype=np.int64)
    tw = np.empty(nterm + 1, dtype=np.float32)
    nt = 0
    for t in order:
        a = ek[t] // nodes
        u = _find(parent, a)
        v = _find(parent, ek[t] - a * nodes)
        if u == v:
            continue
        if label[v] == -1 or (label[u] == -2 and label[v] != -2):
            u, v = v, u  # u keeps a terminal if either has one, the outlets if either has
        if label[v] >= 0:  # both hold terminals: record the edge
            ta[nt] = label[u]
            tb[nt] = label[v]
            tw[nt] = ew[t]
            nt += 1
        elif label[u] != -2:  # v's pits reach a terminal at this level
            x = first[v]
            while x != NONE:
                level[x] = ew[t]
                label[x] = label[u]
                x = nxt[x]
        else:  # two components without a terminal merge
            nxt[last[u]] = first[v]
            last[u] = last[v]
        parent[v] = u
    # 4: filled, and each cell's terminal
    filled = np.empty(n, dtype=np.float32)
    lab2 = np.empty((rows, cols) if want_labels else (0, 0), dtype=np.int32)
    lab = lab2.reshape(-1)
    for c in range(n):
        b = node[c]
        if b < 0:
            filled[c] = np.nan
            if want_labels:
                lab[c] = -3
            continue
        filled[c] = max(zf[c], level[b])
        if want_labels:
            lab[c] = label[b]
    return filled.reshape(rows, cols), lab2, ta[:nt], tb[:nt], tw[:nt]


def fill_single(z: np.ndarray) -> np.ndarray:
    """The depression fill of a whole array in memory (the reference for the tiled version)."""
    z = np.ascontiguousarray(z, dtype=np.float32)
    if z.size >= 2**32 - 1:
        raise ValueError(
            f"fill_single takes fewer than 2^32 - 1 cells, got {z.size}; use the "
            "chunked fill (fill_depressions on a dask-backed DEM)"
        )
    outlet = _outlets(z, 0, 0, 0, 0, True, True, True, True)
    return _basin_fill(z, np.where(outlet, np.int32(-1), np.int32(-2)), False)[0]


def _halo(bi, bj, nbr, nbc, depth):
    return (
        depth if bi > 0 else 0,
        depth if bj > 0 else 0,
        depth if bi < nbr - 1 else 0,
        depth if bj < nbc - 1 else 0,
    )


def _perimeter_glabels(r0, c0, rows, cols, ncols):
    """Global labels (cell indices) of a tile's perimeter cells, in row-major order: the first
    row, then each middle row's first and last cell, then the last row (built from the
    perimeter alone: a mask of the tile cost the maps build's client noticeable time)."""
    rows, cols = int(rows), int(cols)
    if rows <= 2 or cols <= 2:  # every cell is on the perimeter
        pi, pj = np.divmod(np.arange(rows * cols, dtype=np.int64), cols)
    else:
        mid = np.arange(1, rows - 1, dtype=np.int64)
        side = np.arange(cols, dtype=np.int64)
        pi = np.concatenate([np.zeros(cols, np.int64), np.repeat(mid, 2), np.full(cols, rows - 1)])
        pj = np.concatenate([side, np.tile(np.array([0, cols - 1], np.int64), rows - 2), side])
    return pi, pj, (r0 + pi) * ncols + (c0 + pj)


def _to_global(local, glabels):
    """Tile-local labels (perimeter index, -1 outlet, -3 no-data) to global labels."""
    local = np.asarray(local, dtype=np.int64)
    return np.where(local >= 0, glabels[np.maximum(local, 0)], np.where(local == -1, OUTLET, -3))


def _tile_flood(zh, r0, c0, ncols, halo, want_edges):
    """Fill one tile towards its perimeter and outlets: ``zh`` is the tile with a halo of 2
    (none at map edges).

    Returns the local fill, the tile-local label of every cell (int32: the index of its
    perimeter seed in row-major order, -1 for a true outlet, -3 for no-data), the perimeter's
    global labels, and (if ``want_edges``) the spill edges between global labels.
    """
    top, left, bottom, right = halo
    zh = np.ascontiguousarray(zh, dtype=np.float32)
    outlet_h = _outlets(zh, top, left, bottom, right, top == 0, left == 0, bottom == 0, right == 0)
    rows = zh.shape[0] - top - bottom
    cols = zh.shape[1] - left - right
    z = np.ascontiguousarray(zh[top : top + rows, left : left + cols])
    outlet = outlet_h[top : top + rows, left : left + cols]
    pi, pj, glabels = _perimeter_glabels(r0, c0, rows, cols, ncols)
    seed_label = np.full((rows, cols), -2, dtype=np.int32)
    seed_label[pi, pj] = np.arange(pi.size, dtype=np.int32)
    seed_label[outlet] = -1
    filled, label, ea, eb, ew = _basin_fill(z, seed_label, True)
    if not want_edges:
        return filled, label, glabels, None
    # edges across the tile border: perimeter cell c and neighbour n in the next tile
    a_list, b_list = [_to_global(ea, glabels)], [_to_global(eb, glabels)]
    w_list = [ew.astype(np.float64)]
    hr, hc = zh.shape
    ok = np.isfinite(z[pi, pj])
    qi, qj = pi[ok], pj[ok]
    for k in range(8):
        ni, nj = qi + top + DR[k], qj + left + DC[k]
        ok = (ni >= 0) & (ni < hr) & (nj >= 0) & (nj < hc)
        ok &= ~((ni >= top) & (ni < top + rows) & (nj >= left) & (nj < left + cols))
        ci, cj, ni, nj = qi[ok], qj[ok], ni[ok], nj[ok]
        ok = np.isfinite(zh[ni, nj])
        ci, cj, ni, nj = ci[ok], cj[ok], ni[ok], nj[ok]
        nlabel = np.where(outlet_h[ni, nj], OUTLET, (r0 + ni - top) * ncols + (c0 + nj - left))
        a_list.append(_to_global(label[ci, cj], glabels))
        b_list.append(nlabel.astype(np.int64))
        w_list.append(np.maximum(zh[ci + top, cj + left], zh[ni, nj]).astype(np.float64))
    return (
        filled,
        label,
        glabels,
        _lowest_edges(np.concatenate(a_list), np.concatenate(b_list), np.concatenate(w_list)),
    )


def _tile_fill_summary(zh, r0, c0, ncols, halo):
    return _tile_flood(zh, r0, c0, ncols, halo, True)[3]


def _lowest_edges(a, b, w):
    """One edge per unordered label pair, at the lowest spill height (all the solve needs)."""
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    keep = lo != hi
    lo, hi, w = lo[keep], hi[keep], w[keep]
    order = np.lexsort((w, hi, lo))
    lo, hi, w = lo[order], hi[order], w[order]
    first = np.ones(lo.size, dtype=bool)
    first[1:] = (lo[1:] != lo[:-1]) | (hi[1:] != hi[:-1])
    return lo[first], hi[first], w[first]


@njit(cache=True)
def _find(parent, x):
    while parent[x] != x:
        parent[x] = parent[parent[x]]
        x = parent[x]
    return x


@njit(cache=True)
def _spill_levels(n, start, ia, ib, w):
    """Spill level of every node: the least, over the paths to ``start``, of the highest edge
    on the path (``inf`` where none reaches it). Kruskal's order: edges by height, joined with
    a union-find; a node's level is the height of the edge that first joins its component to
    the one holding ``start`` (the bottleneck of its minimax path). Memory: the edges once and
    a few arrays of ``n``, no adjacency lists."""
    order = np.argsort(w, kind="mergesort")
    parent = np.arange(n, dtype=np.int32)
    size = np.ones(n, dtype=np.int32)
    nxt = np.full(n, -1, dtype=np.int32)  # each component's members, as a linked list
    tail = np.arange(n, dtype=np.int32)
    spill = np.full(n, np.inf)
    spill[start] = -np.inf
    reached = np.zeros(n, dtype=np.bool_)
    reached[start] = True
    for e in order:
        ru = _find(parent, ia[e])
        rv = _find(parent, ib[e])
        if ru == rv:
            continue
        if reached[ru] != reached[rv]:  # a component joins the outlet's: its level is w[e]
            x = rv if reached[ru] else ru
            while x >= 0:
                spill[x] = w[e]
                x = nxt[x]
        if size[ru] < size[rv]:
            ru, rv = rv, ru
        parent[rv] = ru
        size[ru] += size[rv]
        nxt[tail[ru]] = rv
        tail[ru] = tail[rv]
        reached[ru] = reached[ru] or reached[rv]
    return spill


def _solve_fill(*summaries):
    """The spill level of every perimeter label: ``(ids, spill)``, ``ids`` sorted. The edges
    of every tile are held once as compact arrays (int32 node indices, float32 heights: the
    DEM's own values, so exact), about 40 bytes an edge at the peak, not 150: this solve runs
    in the client and its edges grow with the number of tiles times the tile side."""
    count = sum(sm[0].size for sm in summaries)
    ab = np.empty(2 * count + 1, dtype=np.int64)
    k = 0
    for sm in summaries:
        m = sm[0].size
        ab[k : k + m] = sm[0]
        ab[count + k : count + k + m] = sm[1]
        k += m
    ab[-1] = OUTLET
    ab.sort()  # then the distinct values: several times faster than np.unique here
    keep = np.empty(ab.size, dtype=bool)
    keep[0] = True
    np.not_equal(ab[1:], ab[:-1], out=keep[1:])
    ids = ab[keep]
    del ab, keep
    ia = np.empty(count, dtype=np.int32)
    ib = np.empty(count, dtype=np.int32)
    w = np.empty(count, dtype=np.float32)
    k = 0
    for sm in summaries:
        m = sm[0].size
        ia[k : k + m] = np.searchsorted(ids, sm[0])
        ib[k : k + m] = np.searchsorted(ids, sm[1])
        w[k : k + m] = sm[2]
        k += m
    start = int(np.searchsorted(ids, OUTLET))
    spill = _spill_levels(ids.size, start, ia, ib, w)
    spill[~np.isfinite(spill) & (spill > 0)] = -np.inf  # unreachable: nothing to raise
    return ids, spill


def _fill_finish(zh, solution, block_info=None):
    ids, spill = solution
    (bi, bj) = block_info[0]["chunk-location"]
    nbr, nbc = block_info[0]["num-chunks"]
    (r0, _), (c0, _) = block_info[None]["array-location"]
    ncols = block_info[None]["shape"][1]
    filled, local, glabels, _ = _tile_flood(zh, r0, c0, ncols, _halo(bi, bj, nbr, nbc, 2), False)
    label = _to_global(local, glabels)
    pos = np.clip(np.searchsorted(ids, label), 0, ids.size - 1)
    lev = np.where(ids[pos] == label, spill[pos], -np.inf).astype(np.float32)
    return np.where(np.isnan(filled), filled, np.maximum(filled, lev)).astype(np.float32)


def _tiles(z: da.Array, depth: int):
    """(overlapped array, [(delayed block, r0, c0, halo)]) for a tile-by-tile pass."""
    z = z.rechunk(_min_chunks(z.chunks, depth))
    zo = da.overlap.overlap(z, depth={0: depth, 1: depth}, boundary="none")
    blocks = zo.to_delayed()
    r_off = np.concatenate([[0], np.cumsum(z.chunks[0])])
    c_off = np.concatenate([[0], np.cumsum(z.chunks[1])])
    nbr, nbc = len(z.chunks[0]), len(z.chunks[1])
    tiles = [
        (blocks[bi, bj], int(r_off[bi]), int(c_off[bj]), _halo(bi, bj, nbr, nbc, depth))
        for bi in range(nbr)
        for bj in range(nbc)
    ]
    return z, zo, tiles


def _min_chunks(chunks, depth):
    """Merge chunks thinner than ``depth`` into their neighbours (same values, fewer tiles)."""
    out = []
    for dim in chunks:
        merged = []
        for c in dim:
            if merged and (merged[-1] < depth or c < depth):
                merged[-1] += c
            else:
                merged.append(c)
        if len(merged) > 1 and merged[-1] < depth:
            merged[-2] += merged.pop()
        out.append(tuple(merged))
    return tuple(out)


def _fill_dask(z: da.Array, *, eager_solve: bool) -> da.Array:
    ncols = z.shape[1]
    z, zo, tiles = _tiles(z.astype(np.float32), 2)
    summaries = [
        dask.delayed(_tile_fill_summary, pure=True)(blk, r0, c0, ncols, halo)
        for blk, r0, c0, halo in tiles
    ]
    solution = dask.delayed(_solve_fill, pure=True)(*summaries)
    if eager_solve:
        solution = solution.compute()
    return da.map_blocks(
        _fill_finish,
        zo,
        solution,
        chunks=z.chunks,
        dtype=np.float32,
        meta=np.empty((0, 0), np.float32),
    )


# --------------------------------------------------------------------------- D8 + accumulation


@njit(cache=True)
def _drop(wc, wv, k):
    """D8's drop per distance from a cell of height ``wc`` to its neighbour ``k`` of height
    ``wv`` (float32 values, computed in float64)."""
    return (np.float64(wc) - np.float64(wv)) / DIST[k]


@njit(nogil=True, cache=True)
def _d8(w, top, left, rows, cols):
    """D8 codes (0..7, -1 sink/no-data) of the ``rows x cols`` cells of ``w`` starting at
    (top, left); ``w`` holds them plus a halo (the neighbours outside are in the halo)."""
    hr, hc = w.shape
    out = np.full((rows, cols), -1, dtype=np.int8)
    for i in range(rows):
        for j in range(cols):
            wi = i + top
            wj = j + left
            c = w[wi, wj]
            if c != c:
                continue
            best = 0.0
            code = -1
            for k in range(8):
                ni = wi + DR[k]
                nj = wj + DC[k]
                if ni < 0 or ni >= hr or nj < 0 or nj >= hc:
                    continue
                v = w[ni, nj]
                if v != v:
                    continue
                drop = _drop(c, v, k)
                if drop > best:
                    best = drop
                    code = k
            out[i, j] = code
    return out


@njit(nogil=True, cache=True)
def _accumulate(dirs, weights):
    """Weighted accumulation inside a block (flow leaving it is dropped): in-degrees, then
    each chain walked downstream from its sources, a cell passing its total on once all its
    upstream cells have (as :func:`_accumulate_single`)."""
    acc = weights.copy()
    _walk(dirs, acc)
    return acc


@njit(nogil=True, cache=True)
def _walk(dirs, acc):
    """:func:`_accumulate`'s walk, on the weights ``acc`` in place."""
    rows, cols = dirs.shape
    indeg = np.zeros((rows, cols), dtype=np.uint8)
    for i in range(rows):
        for j in range(cols):
            k = dirs[i, j]
            if k >= 0 and inside(i, j, k, rows, cols):
                indeg[i + DR[k], j + DC[k]] += 1
    for i in range(rows):
        for j in range(cols):
            if indeg[i, j] != 0:
                continue
            x, y = i, j
            while True:
                k = dirs[x, y]
                if k < 0 or not inside(x, y, k, rows, cols):
                    break
                nx = x + DR[k]
                ny = y + DC[k]
                acc[nx, ny] += acc[x, y]
                indeg[nx, ny] -= 1
                if indeg[nx, ny] != 0:
                    break
                indeg[nx, ny] = 255  # walked from here on: not a source for the raster loop
                x, y = nx, ny


@njit(nogil=True, cache=True)
def _accumulate_single(filled):
    """D8 on ``w = -filled`` (as :func:`_d8`) and the accumulation of every cell (valid cells
    count 1), in two passes: directions with in-degrees, then each chain walked downstream
    from its sources, a cell passing its total on once all its upstream cells have."""
    rows, cols = filled.shape
    n = rows * cols
    f = filled.ravel()
    dirs = np.full(n, -1, dtype=np.int8)
    indeg = np.zeros(n, dtype=np.uint8)
    off = flat_offsets(cols)
    for ci in range(rows):
        inner_row = 0 < ci < rows - 1
        for cj in range(cols):
            c = ci * cols + cj
            fc = f[c]
            if fc != fc:
                continue
            best = 0.0
            code = -1
            inner = inner_row and 0 < cj < cols - 1
            for k in range(8):
                if not inner and not inside(ci, cj, k, rows, cols):
                    continue
                v = f[c + off[k]]
                if v != v:
                    continue
                drop = _drop(-fc, -v, k)  # on w = -f
                if drop > best:
                    best = drop
                    code = k
            if code >= 0:
                dirs[c] = code
                indeg[c + off[code]] += 1
    acc = np.zeros(n, dtype=np.int64)
    for c in range(n):
        if f[c] == f[c]:
            acc[c] = 1
    for c in range(n):
        if indeg[c] != 0:
            continue
        x = c
        while dirs[x] >= 0:
            y = x + off[dirs[x]]
            acc[y] += acc[x]
            indeg[y] -= 1
            if indeg[y] != 0:
                break
            indeg[y] = 255  # walked from here on: not a source for the raster loop
            x = y
    return acc.reshape(rows, cols)


def accumulation_single(filled: np.ndarray) -> np.ndarray:
    """D8 accumulation of ``-filled`` for a whole array in memory (the reference)."""
    return _accumulate_single(np.ascontiguousarray(filled, dtype=np.float32))


def _tile_dirs(fh, halo):
    top, left, bottom, right = halo
    rows = fh.shape[0] - top - bottom
    cols = fh.shape[1] - left - right
    w = -np.ascontiguousarray(fh, dtype=np.float32)
    return _d8(w, top, left, rows, cols), np.isnan(w[top : top + rows, left : left + cols])


def _tile_flow_summary(fh, r0, c0, ncols, halo):
    """Links leaving the tile, with local amounts, and the link each border cell exits by."""
    dirs, nodata = _tile_dirs(fh, halo)
    return _dirs_flow_summary(dirs, nodata, r0, c0, ncols)


def _dirs_flow_summary(dirs, nodata, r0, c0, ncols):
    """:func:`_tile_flow_summary` from the tile's D8 codes and no-data mask."""
    acc = _accumulate(dirs, (~nodata).astype(np.int64))
    return _flow_links(dirs, acc, nodata, r0, c0, ncols)


@njit(nogil=True, cache=True)
def _flow_links(dirs, acc, nodata, r0, c0, ncols):
    """A tile's flow summary: the links where flow leaves it (a cell whose D8 move ends
    outside: its global index, the target's, its local accumulation; in row-major order) and,
    for each valid border cell in row-major order, its global index and the id of the link its
    flow leaves by (-1: it ends inside)."""
    rows, cols = dirs.shape
    link_id = np.full((rows, cols), -1, dtype=np.int32)
    nl = 0
    for i in range(rows):
        for j in range(cols):
            k = dirs[i, j]
            if k >= 0 and not inside(i, j, k, rows, cols):
                link_id[i, j] = nl
                nl += 1
    src = np.empty(nl, dtype=np.int64)
    dst = np.empty(nl, dtype=np.int64)
    amount = np.empty(nl, dtype=np.int64)
    for i in range(rows):
        for j in range(cols):
            e = link_id[i, j]
            if e >= 0:
                k = dirs[i, j]
                src[e] = (r0 + i) * ncols + (c0 + j)
                dst[e] = (r0 + i + DR[k]) * ncols + (c0 + j + DC[k])
                amount[e] = acc[i, j]
    memo = np.full((rows, cols), -2, dtype=np.int32)
    path = np.empty(rows * cols, dtype=np.int64)
    nb = 0
    cell = np.empty(2 * (rows + cols), dtype=np.int64)
    exits = np.empty(2 * (rows + cols), dtype=np.int64)
    for i in range(rows):
        # the border's cells in row-major order: whole first and last rows, else both ends
        step = 1 if i == 0 or i == rows - 1 else max(cols - 1, 1)
        for j in range(0, cols, step):
            if not nodata[i, j]:
                cell[nb] = (r0 + i) * ncols + (c0 + j)
                exits[nb] = _exit_link(dirs, link_id, memo, path, i, j)
                nb += 1
    return src, dst, amount, cell[:nb], exits[:nb]


@njit(cache=True)
def _exit_link(dirs, link_id, memo, path, i, j):
    """The id of the link the flow from cell (i, j) leaves its block by (-1: it ends inside),
    walking downstream and remembering the answer for every cell walked (``memo``, -2 where
    not known yet; ``path`` a scratch array of the block's size)."""
    rows, cols = dirs.shape
    n = 0
    while memo[i, j] == -2:
        if link_id[i, j] >= 0:
            memo[i, j] = link_id[i, j]
            break
        k = dirs[i, j]
        if k < 0:
            memo[i, j] = -1
            break
        path[n] = i * cols + j
        n += 1
        i += DR[k]
        j += DC[k]
    out = memo[i, j]
    for t in range(n):
        memo[path[t] // cols, path[t] % cols] = out
    return out


@njit(cache=True)
def _chain_totals(amount, nxt):
    """total[L] = amount[L] + sum of total[L'] over links L' whose next link is L."""
    n = amount.size
    indeg = np.zeros(n, dtype=np.int64)
    for i in range(n):
        if nxt[i] >= 0:
            indeg[nxt[i]] += 1
    total = amount.copy()
    queue = np.empty(n, dtype=np.int64)
    head = 0
    tail = 0
    for i in range(n):
        if indeg[i] == 0:
            queue[tail] = i
            tail += 1
    while head < tail:
        u = queue[head]
        head += 1
        v = nxt[u]
        if v >= 0:
            total[v] += total[u]
            indeg[v] -= 1
            if indeg[v] == 0:
                queue[tail] = v
                tail += 1
    return total


def _solve_flow(*summaries):
    src, dst, amount = [], [], []
    cells, exits = [], []
    base = 0
    for s_src, s_dst, s_amt, b_cell, b_exit in summaries:
        src.append(s_src)
        dst.append(s_dst)
        amount.append(s_amt)
        cells.append(b_cell)
        exits.append(np.where(b_exit >= 0, b_exit + base, -1))
        base += s_src.size
    src = np.concatenate(src)
    dst = np.concatenate(dst)
    amount = np.concatenate(amount).astype(np.int64)
    cells = np.concatenate(cells)
    exits = np.concatenate(exits)
    order = np.argsort(cells)
    cells, exits = cells[order], exits[order]
    # the link a link's flow continues by: the exit of the border cell it flows into
    nxt = np.full(dst.size, -1, dtype=np.int64)
    if cells.size:
        pos = np.clip(np.searchsorted(cells, dst), 0, cells.size - 1)
        found = cells[pos] == dst
        nxt[found] = exits[pos[found]]
    total = _chain_totals(amount, nxt)
    targets, inv = np.unique(dst, return_inverse=True)
    inflow = np.zeros(targets.size, dtype=np.int64)
    np.add.at(inflow, inv, total)
    return targets, inflow


def _flow_finish(fh, solution, block_info=None):
    (bi, bj) = block_info[0]["chunk-location"]
    nbr, nbc = block_info[0]["num-chunks"]
    dirs, nodata = _tile_dirs(fh, _halo(bi, bj, nbr, nbc, 1))
    return _flow_finish_dirs(dirs, nodata, solution, block_info)


def _inflow_into(solution, block_info):
    """The cells of a block (rows, columns in the block) that the global solve sends flow
    into, and the amounts."""
    (r0, r1), (c0, c1) = block_info[None]["array-location"]
    return _inflow_rect(solution, r0, r1, c0, c1, block_info[None]["shape"][1])


def _inflow_rect(solution, r0, r1, c0, c1, ncols):
    """:func:`_inflow_into` the block of rows ``r0:r1`` and columns ``c0:c1`` of a map of
    ``ncols`` columns."""
    targets, inflow = solution
    r0, r1, c0, c1 = int(r0), int(r1), int(c0), int(c1)
    lo = np.searchsorted(targets, r0 * ncols)
    hi = np.searchsorted(targets, (r1 - 1) * ncols + c1)
    r, c = np.divmod(targets[lo:hi], ncols)
    mine = (c >= c0) & (c < c1)
    return r[mine] - r0, c[mine] - c0, inflow[lo:hi][mine].astype(np.int64)


def _flow_finish_dirs(dirs, nodata, solution, block_info):
    """A block's accumulation from its D8 codes and no-data mask, with the inflow the global
    solve sends into it."""
    weights = (~nodata).astype(np.int64)
    r, c, amount = _inflow_into(solution, block_info)
    np.add.at(weights, (r, c), amount)
    return _accumulate(dirs, weights)


@njit(nogil=True, cache=True)
def _accumulate_codes(dirs, r, c, amount):
    """:func:`_flow_finish_dirs` on stored codes (``NO_DATA_DIR`` where no-data) as int32, in
    one kernel: the weights (1 a valid cell, plus the inflow) built and walked in place, no
    mask, weight copy or conversion pass."""
    rows, cols = dirs.shape
    acc = np.empty((rows, cols), dtype=np.int64)
    for i in range(rows):
        for j in range(cols):
            acc[i, j] = 0 if dirs[i, j] == NO_DATA_DIR else 1
    for k in range(r.size):
        acc[r[k], c[k]] += amount[k]
    _walk(dirs, acc)
    return acc.astype(np.int32)


def _accumulation_dask(filled: da.Array, *, eager_solve: bool) -> da.Array:
    ncols = filled.shape[1]
    f, fo, tiles = _tiles(filled, 1)
    summaries = [
        dask.delayed(_tile_flow_summary, pure=True)(blk, r0, c0, ncols, halo)
        for blk, r0, c0, halo in tiles
    ]
    solution = dask.delayed(_solve_flow, pure=True)(*summaries)
    if eager_solve:
        solution = solution.compute()
    return da.map_blocks(
        _flow_finish, fo, solution, chunks=f.chunks, dtype=np.int64, meta=np.empty((0, 0), np.int64)
    )


# --------------------------------------------------------------------------- public API


def _wrap(data, dem, name, attrs):
    return xr.DataArray(data, dims=dem.dims, coords=dem.coords, name=name, attrs=attrs)


def fill_depressions(dem: xr.DataArray, *, eager_solve: bool = False) -> xr.DataArray:
    """Depression fill of ``dem`` (map edges and cells next to no-data are outlets): the
    minimal surface without pits, what priority-flood computes.

    Exact for any chunking; lazy for dask input (the small global step is a task of the graph,
    or computed at once with ``eager_solve=True`` so that the graph left holds no summaries).
    """
    check_dem(dem)
    require_valid_cells(
        dem, "the DEM is entirely no-data (NaN): there is no terrain to derive ridges from"
    )
    z = dem.data
    if isinstance(z, da.Array):
        data = _fill_dask(z, eager_solve=eager_solve)
    else:
        data = fill_single(np.asarray(z))
    return _wrap(data, dem, "filled", {"long_name": "depression-filled elevation", "units": "m"})


def flow_accumulation(
    dem: xr.DataArray, *, filled: xr.DataArray | None = None, eager_solve: bool = False
) -> xr.DataArray:
    """Cells draining through each cell (itself included) on the inverted filled DEM.

    This is the ridge network of docs/method.md section 3: high accumulation of ``-filled``
    marks ridge lines of ``z``. Exact, cell for cell, for any chunking; lazy for dask input.

    Examples
    --------
    >>> acc = flow_accumulation(pipeline.synthetic_dem((500, 500), chunks=128))  # doctest: +SKIP
    >>> int(acc.min())                                                             # doctest: +SKIP
    1
    """
    check_dem(dem)
    if filled is None:
        filled = fill_depressions(dem, eager_solve=eager_solve)
    f = filled.data
    if isinstance(f, da.Array):
        data = _accumulation_dask(f.astype(np.float32), eager_solve=eager_solve)
    else:
        data = accumulation_single(np.asarray(f))
    return _wrap(
        data,
        dem,
        "accumulation",
        {
            "long_name": "flow accumulation of the inverted filled DEM (cells)",
            "units": "cells",
            "cell_size": _cell_size(dem),
        },
    )


def flow_directions(filled: np.ndarray) -> np.ndarray:
    """D8 codes of ``-filled`` (in memory): 0..7 index ``DR``/``DC`` (E, SE, S, SW, W, NW, N,
    NE), -1 for sinks and no-data."""
    w = -np.ascontiguousarray(filled, dtype=np.float32)
    return _d8(w, 0, 0, *w.shape)


def default_min_accumulation(a: float) -> int:
    """Cells of a 1 km^2 contributing area, at least 8 (docs/method.md section 3)."""
    return max(8, int(math.ceil(1e6 / (a * a))))


def ridge_map(
    dem: xr.DataArray,
    min_accumulation: int | None = None,
    *,
    accumulation: xr.DataArray | None = None,
) -> xr.DataArray:
    """Ridge cells: ``accumulation >= min_accumulation`` (default: a 1 km^2 area, >= 8 cells).

    Examples
    --------
    >>> rdg = ridge_map(pipeline.synthetic_dem((500, 500), chunks=128))  # doctest: +SKIP
    """
    a = check_dem(dem)
    if min_accumulation is None:
        min_accumulation = default_min_accumulation(a)
    min_accumulation = MAPS.min_accumulation.check(min_accumulation)
    if accumulation is None:
        accumulation = flow_accumulation(dem)
    ridge = accumulation >= min_accumulation
    ridge.name = "ridge"
    ridge.attrs = {
        "long_name": "ridge cells",
        "min_accumulation": int(min_accumulation),
        "cell_size": a,
    }
    return ridge


# --------------------------------------------------------------------------- staged build
# For maps built into a store (build_maps), each tile is filled once: its local fill and, for
# every cell, the index of its label in the tile's perimeter list go to scratch tiles, one file
# a tile and layer (:func:`pipeline.maps.scratch.save_tile`).
# The flow pass finishes the fill elementwise (max(local fill, spill[label])) on a tile plus
# a one-cell halo, takes its D8 codes and flow summary, and stores the codes as scratch tiles
# too; the accumulation pass reads a tile's codes alone. No tile is filled twice, and
# no D8 code is computed twice.


def _keep_dem(block, scratch, block_info=None):
    """Pass 0 for one tile: the DEM's tile kept in the scratch as ``"dem"`` (float32)."""
    save_tile(scratch, "dem", tuple(block_info[0]["chunk-location"]), block)
    return np.zeros((1, 1), dtype=np.int8)


def _scratch_flood(scratch, tile, r_off, c_off):
    """Pass 1 for one tile (``tile``: its place in the tile grid of offsets ``r_off``,
    ``c_off``): its DEM with a halo of 2 read from the scratch, filled; its local fill and
    label indices and the four sides of both (the flow pass's one-cell halos, see
    :func:`_haloed_from_scratch`) kept as scratch tiles; returns the spill edges."""
    bi, bj = tile
    halo = _halo(bi, bj, len(r_off) - 1, len(c_off) - 1, 2)
    top, left, bottom, right = halo
    r0, c0, ncols = int(r_off[bi]), int(c_off[bj]), int(c_off[-1])
    zh = load_window(
        scratch,
        "dem",
        r_off,
        c_off,
        r0 - top,
        int(r_off[bi + 1]) + bottom,
        c0 - left,
        int(c_off[bj + 1]) + right,
        np.float32,
    )
    filled, label, _, edges = _tile_flood(zh, r0, c0, ncols, halo, True)
    label = _narrow_labels(label)
    save_tile(scratch, "floc", tile, filled)
    save_tile(scratch, "plab", tile, label)
    for name, a in (("fside", filled), ("pside", label)):
        rows, cols = a.shape
        sides = np.zeros((4, max(rows, cols)), dtype=a.dtype)
        sides[0, :cols], sides[1, :cols] = a[0], a[-1]  # top, bottom rows
        sides[2, :rows], sides[3, :rows] = a[:, 0], a[:, -1]  # left, right columns
        save_tile(scratch, name, tile, sides)
    return edges


def _narrow_labels(label: np.ndarray) -> np.ndarray:
    """A tile's label indices as int16 when they fit (a 1024^2 tile's perimeter has 4092
    cells): half the scratch bytes written and read."""
    info = np.iinfo(np.int16)
    if label.size and (label.max() > info.max or label.min() < info.min):
        return label
    return label.astype(np.int16)


def _haloed_from_scratch(scratch, name, bi, bj, geometry):
    """Tile ``(bi, bj)`` of the scratch layer ``name`` ("floc" or "plab") with a one-cell halo
    on each side that has a neighbour: the tile read from its own file, the halo from the
    neighbours' stored sides (``fside``, ``pside``: a few KiB each), so that a flow task needs
    no other tile (dask's overlap of the scratch layers moved the neighbours' chunks between
    the workers and left them idle for much of that pass)."""
    _, _, r_off, c_off, nbr, nbc, _ = geometry
    top, left, bottom, right = _halo(bi, bj, nbr, nbc, 1)
    own = load_tile(scratch, name, (bi, bj))
    rows, cols = own.shape
    sides = {}
    for i in range(bi - top, bi + bottom + 1):
        for j in range(bj - left, bj + right + 1):
            if (i, j) != (bi, bj):
                sides[i, j] = load_tile(scratch, name[0] + "side", (i, j))
    dtype = np.result_type(own, *sides.values())
    out = np.empty((top + rows + bottom, left + cols + right), dtype=dtype)
    out[top : top + rows, left : left + cols] = own
    if top:
        out[0, left : left + cols] = sides[bi - 1, bj][1, :cols]  # the bottom row above
    if bottom:
        out[-1, left : left + cols] = sides[bi + 1, bj][0, :cols]  # the top row below
    if left:
        out[top : top + rows, 0] = sides[bi, bj - 1][3, :rows]  # the right column to the left
    if right:
        out[top : top + rows, -1] = sides[bi, bj + 1][2, :rows]  # the left column to the right
    width = int(c_off[bj] - c_off[bj - 1]) if left else 0  # the tile to the left
    if top and left:
        out[0, 0] = sides[bi - 1, bj - 1][1, width - 1]
    if top and right:
        out[0, -1] = sides[bi - 1, bj + 1][1, 0]
    if bottom and left:
        out[-1, 0] = sides[bi + 1, bj - 1][0, width - 1]
    if bottom and right:
        out[-1, -1] = sides[bi + 1, bj + 1][0, 0]
    return out


def _spill_tables(ids, spill, r_off, c_off, ncols):
    """Concatenated per-tile spill tables (indexed by perimeter index) and each tile's base."""
    tables, bases, base = [], [], 0
    for bi in range(len(r_off) - 1):
        for bj in range(len(c_off) - 1):
            rows, cols = r_off[bi + 1] - r_off[bi], c_off[bj + 1] - c_off[bj]
            _, _, glabels = _perimeter_glabels(r_off[bi], c_off[bj], rows, cols, ncols)
            pos = np.clip(np.searchsorted(ids, glabels), 0, ids.size - 1)
            tables.append(np.where(ids[pos] == glabels, spill[pos], -np.inf))
            bases.append(base)
            base += glabels.size
    return np.concatenate(tables).astype(np.float32), np.array(bases, dtype=np.int64)


def _finish_from_scratch(floc, plab, tables, bases, r_off, c_off, gr0, gc0):
    """Final fill of a block (with halo) whose first cell is global (gr0, gc0)."""
    rows, cols = floc.shape
    ti = np.searchsorted(r_off, gr0 + np.arange(rows), side="right") - 1
    tj = np.searchsorted(c_off, gc0 + np.arange(cols), side="right") - 1
    return _raise_to_levels(
        np.ascontiguousarray(floc, dtype=np.float32),
        np.ascontiguousarray(plab, dtype=np.int32),
        tables,
        bases,
        ti,
        tj,
        len(c_off) - 1,
    )


@njit(nogil=True, cache=True)
def _raise_to_levels(floc, plab, tables, bases, ti, tj, ntc):
    """``max(floc, level of the cell's terminal)``: the terminal ``plab`` (-1 or less: none)
    of the tile ``(ti[i], tj[j])`` has its level at ``tables[bases[tile] + plab]``; NaN stays
    NaN (as numpy's ``maximum``)."""
    rows, cols = floc.shape
    out = np.empty((rows, cols), dtype=np.float32)
    for i in range(rows):
        row_base = ti[i] * ntc
        for j in range(cols):
            f = floc[i, j]
            p = plab[i, j]
            if f != f or p < 0:
                out[i, j] = f
                continue
            lev = tables[bases[row_base + tj[j]] + p]
            out[i, j] = lev if (lev > f or lev != lev) else f
    return out


class Staged(NamedTuple):
    """What the first two passes of the staged build leave (:func:`flood_and_solve`): the
    scratch tiles under ``scratch`` on the tile grid ``chunks``, and the two global solves
    as dask keys (persisted on a cluster): ``geometry`` (the fill's spill tables and the tile
    grid) and ``solution`` (the flow solve's inflow into the tiles)."""

    chunks: tuple
    geometry: object
    solution: object
    scratch: str

    @property
    def offsets(self) -> tuple:
        """The tile grid's row and column offsets (each ends with the map's side)."""
        return _offsets(self.chunks)


def _offsets(chunks) -> tuple:
    """The row and column offsets of a grid of ``chunks`` (each ends with the map's side)."""
    return tuple(np.concatenate([[0], np.cumsum(c)]).astype(np.int64) for c in chunks)


def flood_and_solve(z: da.Array, scratch, log=None) -> Staged:
    """Passes 1 and 2 of the staged build of the DEM ``z`` (see the section comment): every
    tile flooded once, the fill's spill edges solved, every tile's D8 codes and flow summary,
    the flow solved. Each tile's DEM is kept in the scratch as ``"dem"`` (float32) first.
    ``scratch`` is a directory (a path or a URL) for the scratch tiles."""
    t0 = time.perf_counter()
    # the two solves run here, in the caller's process: their compiled code is loaded from
    # numba's cache meanwhile (a fraction of a second in a new process, after the tiles
    # otherwise)
    solves = shared_pool("solver-load", 1).submit(_load_solvers)
    # regular tiles (only the last may be larger, when a thin last chunk is merged into it)
    z = z.astype(np.float32).rechunk((z.chunks[0][0], z.chunks[1][0]))
    z = z.rechunk(_min_chunks(z.chunks, 2))
    scratch = str(scratch)
    ncols = z.shape[1]
    nbr, nbc = len(z.chunks[0]), len(z.chunks[1])
    r_off, c_off = _offsets(z.chunks)
    # pass 0: the DEM's tiles kept in the scratch, where each later pass reads a tile with the
    # halo it needs (dask's overlap of the source took 9 tasks a tile, slices moved between
    # the workers, and the scheduler's time for them on the same two cores)
    z.map_blocks(
        _keep_dem,
        scratch,
        chunks=((1,) * nbr, (1,) * nbc),
        dtype=np.int8,
        meta=np.empty((0, 0), np.int8),
    ).compute()
    edges = compute_told(
        [
            dask.delayed(_scratch_flood, pure=False)(scratch, (bi, bj), r_off, c_off)
            for bi in range(nbr)
            for bj in range(nbc)
        ],
        prefixed(log, "fill: "),
        "tiles flooded",
    )
    solves.result()
    ids, spill = _solve_fill(*edges)
    tables, bases = _spill_tables(ids, spill, r_off, c_off, ncols)
    if log:
        log("fill: tiles flooded and solved (%.1f s)", time.perf_counter() - t0)
    # large constants travel as single graph keys (sent once to each worker), not in closures;
    # on a cluster they are kept there (persisted), so that each later computation that reads
    # them names them instead of carrying them again (12.6 MiB at 20000^2, and distributed's
    # "Sending large graph" warning each time)
    (geometry,) = dask.persist(
        dask.delayed((tables, bases, r_off, c_off, nbr, nbc, ncols), pure=True)
    )
    flow = compute_told(
        [
            dask.delayed(_scratch_flow_summary, pure=False)(bi, bj, geometry, scratch)
            for bi in range(nbr)
            for bj in range(nbc)
        ],
        prefixed(log, "flow: "),
        "tiles summarised",
    )
    (solution,) = dask.persist(dask.delayed(_solve_flow(*flow), pure=True))
    if log:
        log("flow: tiles summarised and solved (%.1f s)", time.perf_counter() - t0)
    return Staged(z.chunks, geometry, solution, scratch)


def ridge_layers_staged(z: da.Array, scratch, min_accumulation: int, log=None):
    """(filled, accumulation, ridge) dask arrays of the DEM ``z``, computing the two small
    global solves eagerly and flooding each tile once (see the section comment).

    ``scratch`` is a directory (a path or a URL) for the scratch tiles; the returned arrays read
    it, so it must live until they are written.
    """
    st = flood_and_solve(z, scratch, log)
    floc = tile_array(st.scratch, "floc", st.chunks, np.float32)
    plab = tile_array(st.scratch, "plab", st.chunks, np.int32)
    fo = da.overlap.overlap(floc, depth={0: 1, 1: 1}, boundary="none")
    po = da.overlap.overlap(plab, depth={0: 1, 1: 1}, boundary="none")
    acc = da.map_blocks(
        _accumulate_block,
        st.scratch,
        *st.offsets,
        st.solution,
        chunks=st.chunks,
        dtype=np.int32,
        meta=np.empty((0, 0), np.int32),
    )
    filled = da.map_blocks(
        _scratch_inner_fill,
        fo,
        po,
        st.geometry,
        chunks=st.chunks,
        dtype=np.float32,
        meta=np.empty((0, 0), np.float32),
    )
    return filled, acc, acc >= min_accumulation


def _load_solvers() -> None:
    """Compile (in a new process: load from numba's cache) the global solves' kernels, on the
    argument types the solves give them."""
    i32, i64 = np.zeros(1, np.int32), np.zeros(1, np.int64)
    _spill_levels(1, 0, i32, i32, np.zeros(1, np.float32))
    _chain_totals(i64, np.full(1, -1, np.int64))


def _scratch_finished(fblk, pblk, bi, bj, geometry):
    tables, bases, r_off, c_off, nbr, nbc, _ = geometry
    top, left, _, _ = _halo(bi, bj, nbr, nbc, 1)
    return _finish_from_scratch(
        fblk, pblk, tables, bases, r_off, c_off, r_off[bi] - top, c_off[bj] - left
    )


NO_DATA_DIR = -2  # the scratch D8 code of a no-data cell (-1: a sink)


def _scratch_flow_summary(bi, bj, geometry, scratch):
    """Pass 2 for one tile: its flow summary; its D8 codes go to the scratch tiles."""
    _, _, r_off, c_off, nbr, nbc, ncols = geometry
    fblk = _haloed_from_scratch(scratch, "floc", bi, bj, geometry)
    pblk = _haloed_from_scratch(scratch, "plab", bi, bj, geometry)
    fh = _scratch_finished(fblk, pblk, bi, bj, geometry)
    dirs, nodata = _tile_dirs(fh, _halo(bi, bj, nbr, nbc, 1))
    r0, c0 = int(r_off[bi]), int(c_off[bj])
    save_tile(scratch, "dirs", (bi, bj), np.where(nodata, np.int8(NO_DATA_DIR), dirs))
    return _dirs_flow_summary(dirs, nodata, r0, c0, ncols)


def tile_accumulation(scratch: str, r_off, c_off, bi: int, bj: int, solution) -> np.ndarray:
    """The accumulation of tile ``(bi, bj)`` of a staged build on the tile grid of offsets
    ``r_off``, ``c_off`` (:attr:`Staged.offsets`; pass 3 for one tile): its D8 codes stored
    under ``scratch`` walked with the inflow that the flow solve (``solution``, the value of
    :attr:`Staged.solution`) sends into it."""
    dirs = load_tile(scratch, "dirs", (bi, bj))
    ncols = int(c_off[-1])
    return _accumulate_codes(
        np.ascontiguousarray(dirs),
        *_inflow_rect(solution, r_off[bi], r_off[bi + 1], c_off[bj], c_off[bj + 1], ncols),
    )


def _accumulate_block(scratch, r_off, c_off, solution, block_info=None):
    """:func:`tile_accumulation` as a dask block of the tile grid."""
    return tile_accumulation(scratch, r_off, c_off, *block_info[None]["chunk-location"], solution)


def _scratch_inner_fill(fblk, pblk, geometry, block_info=None):
    bi, bj = block_info[0]["chunk-location"]
    nbr, nbc = geometry[4], geometry[5]
    top, left, _, _ = _halo(bi, bj, nbr, nbc, 1)
    rows, cols = block_info[None]["chunk-shape"]
    return _scratch_finished(fblk, pblk, bi, bj, geometry)[top : top + rows, left : left + cols]
