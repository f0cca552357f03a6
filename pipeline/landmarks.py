"""Landmark distance layers: a proven lower bound on the shortest safe path between any two
cells of a maps store, and a strong A* heuristic (ALT: A*, landmarks, triangle inequality;
Goldberg & Harrelson 2005).

For a landmark cell ``l`` let ``d_l(v)`` be the exact length of the shortest path from ``l``
to ``v`` on the planners' fine graph (8-connected over passable cells, no corner cutting, an
edge costs its 3-D length along the safety surface; the graph is symmetric). For any two cells
``s``, ``g`` of the landmark's component the triangle inequality gives

    L*(s, g) >= |d_l(s) - d_l(g)|

so ``max_l |d_l(s) - d_l(g)|`` is a lower bound on the optimum ``L*(s, g)``; as a function of
``s`` it is also a consistent A* heuristic (it changes along an edge by at most the edge's
cost). Landmarks are placed farthest-point: the first is the cell farthest (in graph distance)
from an arbitrary cell of the largest component, every next one the cell farthest from all the
landmarks placed so far; a component that no landmark has reached is farther than any reached
cell, so every large component gets its own landmarks. Components of fewer than
``MIN_COMPONENT_FRACTION`` of the passable cells get none (their missions fall back on the
octile distance).

Distances are computed in float64 and stored as float32, rounded to nearest; every value then
carries a relative error of at most 2^-24 plus the float64 summation error (at most
``n * 2^-53`` relative for a path of ``n`` edges, ``n < 2^32``), so
:func:`lower_bound` takes ``|d_l(s) - d_l(g)| - REL_MARGIN * (d_l(s) + d_l(g))`` with
``REL_MARGIN = 2^-22`` (``LANDMARK_MARGIN`` of the planners' core, which uses the same bound as
its A* heuristic), a margin that covers both with room to spare.

A layer's search runs on the whole map in one process: row sweeps (the exact search of
:mod:`pipeline.planners.sweep` with the whole map as its region), or where they give up
Dijkstra's algorithm with a bucket queue; either holds the safety surface (float32), the
passable mask, a float64 distance per cell and its working state, at most 14 bytes a cell
(:func:`memory_per_landmark`).
"""

from __future__ import annotations

import math

import numpy as np

from ._grid8 import DC, DR, flat_offsets, inside
from ._heap import grown
from ._io import inner_chunks, layer_codec, storage_chunks
from ._jit import njit
from .planners.core import LANDMARK_MARGIN, edge_length

MIN_COMPONENT_FRACTION = 0.01
REL_MARGIN = LANDMARK_MARGIN
DEFAULT_LANDMARKS = 8


@njit(nogil=True, cache=True)
def dijkstra(surface, passable, a, sources):
    """Exact shortest path lengths (float64, ``inf`` where unreached) from the cells
    ``sources`` (flat indices, distance 0) to every cell, on the planners' graph.

    A bucket queue (Dial's algorithm with buckets narrower than the shortest edge, ``a``): a
    cell taken from the lowest bucket cannot be improved by any other cell of that bucket, so
    its distance is final, as in Dijkstra's algorithm, at O(1) a queue operation. The buckets
    are circular, as many as the longest edge spans; each is a contiguous array of cells
    (entries made stale by a later improvement are skipped when taken), so that the wavefront
    is read and written in order. An edge costs its 3-D length along the surface, as the
    planners' ``edge_cost`` (``edge_length`` of the same squared horizontal length and rise)."""
    rows, cols = surface.shape
    n = rows * cols
    zf = surface.ravel()
    okf = passable.ravel()
    dist = np.full(n, np.inf)
    done = np.zeros(n, dtype=np.bool_)
    lo = np.inf
    hi = -np.inf
    for i in range(n):
        if okf[i]:
            z = np.float64(zf[i])
            lo = min(lo, z)
            hi = max(hi, z)
    w = a * (1.0 - 1e-7)
    longest = math.sqrt(2.0 * a * a + (hi - lo) ** 2) if hi >= lo else a
    nb = int(longest / w) + 2
    cap = np.full(nb, 1024, dtype=np.int64)
    fill = np.zeros(nb, dtype=np.int64)
    buckets = [np.empty(1024, dtype=np.int64) for _ in range(nb)]
    off = flat_offsets(cols)
    h2 = np.empty(8)  # each move's squared horizontal length, as edge_cost computes it
    for k in range(8):
        h2[k] = a * a * (DR[k] * DR[k] + DC[k] * DC[k])
    queued = 0
    for s in sources:
        dist[s] = 0.0
        bk = buckets[0]
        if fill[0] == cap[0]:
            bk = grown(bk, fill[0], 2 * cap[0])
            buckets[0] = bk
            cap[0] *= 2
        bk[fill[0]] = s
        fill[0] += 1
        queued += 1
    cur = 0  # the bucket index (not wrapped) being emptied
    while queued > 0:
        cb = cur % nb
        if fill[cb] > 64:  # taken in memory order: the wavefront's rows are read in sequence
            buckets[cb][: fill[cb]].sort()
        i = 0
        while i < fill[cb]:  # cells pushed into this bucket meanwhile are taken too
            u = buckets[cb][i]
            i += 1
            queued -= 1
            if done[u]:
                continue
            done[u] = True
            du = dist[u]
            zu = np.float64(zf[u])
            r = u // cols
            c = u - r * cols
            inner = 0 < r < rows - 1 and 0 < c < cols - 1
            for k in range(8):
                if not inner and not inside(r, c, k, rows, cols):
                    continue
                v = u + off[k]
                if done[v] or not okf[v]:
                    continue
                if k & 1 and not (okf[u + DC[k]] and okf[u + DR[k] * cols]):
                    continue  # no corner cutting
                nd = du + edge_length(h2[k], np.float64(zf[v]) - zu)  # the planners' edge
                if nd < dist[v]:
                    dist[v] = nd
                    b = max(int(nd / w), cur) % nb
                    if fill[b] == cap[b]:
                        buckets[b] = grown(buckets[b], fill[b], 2 * cap[b])
                        cap[b] *= 2
                    buckets[b][fill[b]] = v
                    fill[b] += 1
                    queued += 1
        fill[cb] = 0
        cur += 1
    return dist.reshape(rows, cols)


# --------------------------------------------------------------------------- placement

PLACEMENT_SIDE = 512  # landmarks are placed on a coarse grid of at most this many cells a side


def placement_factor(shape) -> int:
    """The block side of the coarse grid landmarks are placed on."""
    return max(1, math.ceil(max(shape) / PLACEMENT_SIDE))


def large_components(component: np.ndarray | None, counts: np.ndarray) -> np.ndarray:
    """The labels of the components that get landmarks: at least ``MIN_COMPONENT_FRACTION``
    of the passable cells (``counts[label]`` cells each, ``counts[0]`` the impassable)."""
    counts = np.asarray(counts, dtype=np.int64)
    total = counts[1:].sum()
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    return np.flatnonzero((counts >= MIN_COMPONENT_FRACTION * total) & (np.arange(counts.size) > 0))


def place_coarse(surface, ok, a: float, k: int) -> list[tuple[int, int]]:
    """Farthest-point placement of ``k`` landmarks on a coarse grid (``ok`` its passable cells,
    ``surface`` its mean safety surface, ``a`` its cell size): the first is the cell farthest
    from the first passable cell, each next the cell farthest from those placed; a cell no
    landmark reaches counts as farthest of all, so each separate region gets landmarks."""
    surface = np.ascontiguousarray(surface, dtype=np.float32)
    ok = np.ascontiguousarray(ok, dtype=np.bool_)
    cells = np.flatnonzero(ok.ravel())
    if cells.size == 0 or k <= 0:
        return []
    cols = ok.shape[1]
    far = distances_from(surface, ok, a, divmod(int(cells[0]), cols)).ravel()
    nearest = np.full(ok.size, np.inf)  # distance to the nearest landmark placed
    out: list[tuple[int, int]] = []
    score = np.where(np.isfinite(far), far, -1.0)
    for _ in range(min(k, cells.size)):
        cand = np.where(ok.ravel(), np.where(np.isfinite(nearest), nearest, np.inf), -1.0)
        if out:
            v = int(np.argmax(cand))
        else:
            v = int(np.argmax(np.where(ok.ravel(), score, -1.0)))
        if out and cand[v] <= 0.0:
            break  # every cell is a landmark already
        out.append((v // cols, v % cols))
        d = distances_from(surface, ok, a, (v // cols, v % cols)).ravel()
        nearest = np.minimum(nearest, d)
    return out


def coarse_grid(surface, passable, keep, factor: int):
    """Block means of ``surface`` over the ``keep`` cells (those of large components) and a
    coarse passable mask (at least half of a block's cells kept), for placement."""
    return coarse_mean(*block_sums(surface, keep, factor), factor)


def block_sums(surface, keep, factor: int):
    """Per block of ``factor`` x ``factor`` cells (the last row and column of blocks padded):
    how many cells are kept, and the sum of ``surface`` (float64, NaN as 0) over them. A part
    of a map whose first row and column are multiples of ``factor`` gives its own blocks'
    sums, as the maps build's placement pass reads it."""
    rows, cols = keep.shape
    pr, pc = -rows % factor, -cols % factor
    keep = np.asarray(keep, bool)
    z = np.where(keep, np.nan_to_num(np.asarray(surface, np.float64)), 0.0)
    keep = np.pad(keep, ((0, pr), (0, pc)))
    z = np.pad(z, ((0, pr), (0, pc)))
    shp = (keep.shape[0] // factor, factor, keep.shape[1] // factor, factor)
    return keep.reshape(shp).sum(axis=(1, 3)), z.reshape(shp).sum(axis=(1, 3))


def coarse_mean(n, zs, factor: int):
    """The coarse grid of :func:`coarse_grid` from its :func:`block_sums`."""
    ok = n >= (factor * factor) / 2
    mean = np.where(n > 0, zs / np.maximum(n, 1), 0.0).astype(np.float32)
    return mean, ok


def fine_cell(keep_block: np.ndarray, r0: int, c0: int) -> tuple[int, int] | None:
    """The kept cell of a block (its first cell ``(r0, c0)``) nearest the block's centre."""
    idx = np.argwhere(keep_block)
    if idx.size == 0:
        return None
    centre = (np.array(keep_block.shape) - 1) / 2
    r, c = idx[int(np.argmin(((idx - centre) ** 2).sum(axis=1)))]
    return int(r) + r0, int(c) + c0


def place_landmarks(surface, passable, a: float, k: int = DEFAULT_LANDMARKS, component=None):
    """The landmark cells of an in-memory map (see the module doc)."""
    passable = np.asarray(passable, dtype=bool)
    if component is None:
        from .components import label_components  # dask and scipy.ndimage: not on a mission's path

        component, _ = label_components(passable)
    keep = np.isin(component, large_components(component, np.bincount(component.ravel())))
    f = placement_factor(passable.shape)
    mean, ok = coarse_grid(surface, passable, keep, f)
    out = []
    for cr, cc in place_coarse(mean, ok, a * f, k):
        cell = fine_cell(keep[cr * f : (cr + 1) * f, cc * f : (cc + 1) * f], cr * f, cc * f)
        if cell is not None and cell not in out:
            out.append(cell)
    return out


def distances_from(surface, passable, a: float, cell) -> np.ndarray:
    """The exact shortest distances (float64, ``inf`` where unreached) from the passable
    ``cell`` to every cell: by the row sweeps of :func:`pipeline.planners.sweep.distances`
    (the same values as :func:`dijkstra`, bit for bit, 12-20x faster at 10000^2), by
    :func:`dijkstra` where they give up (a maze that turns back on itself many times)."""
    from .planners import sweep

    surface = np.ascontiguousarray(surface)
    if surface.dtype != np.float32:
        surface = surface.astype(np.float32)
    passable = np.ascontiguousarray(passable, dtype=np.bool_)
    r, c = int(cell[0]), int(cell[1])
    d = sweep.distances(surface, passable, float(a), (r, c)) if passable[r, c] else None
    if d is None:
        d = dijkstra(surface, passable, float(a), np.array([r * passable.shape[1] + c]))
    return d


def landmark_layer(surface, passable, a: float, cell) -> np.ndarray:
    """The float32 distance layer of one landmark (``inf`` outside its component)."""
    return distances_from(surface, passable, a, cell).astype(np.float32)


def lower_bound(ds: np.ndarray, dg: np.ndarray) -> float:
    """The proven lower bound on the shortest path between two cells from their landmark
    distances ``ds``, ``dg`` (one value per landmark; ``inf`` where a landmark does not reach):
    ``max_l |d_l(s) - d_l(g)|`` less the rounding margin (module doc); 0 with no common
    landmark."""
    ds = np.asarray(ds, dtype=np.float64)
    dg = np.asarray(dg, dtype=np.float64)
    both = np.isfinite(ds) & np.isfinite(dg)
    if not both.any():
        return 0.0
    b = np.abs(ds[both] - dg[both]) - REL_MARGIN * (ds[both] + dg[both])
    return float(max(b.max(), 0.0))


# --------------------------------------------------------------------------- the maps store

# the layers are sharded as the maps' other layers are, with inner chunks of at most this side:
# a mission reads one value per landmark at each end, which decodes one inner chunk each.
# Measured on a 4000^2 layer (chunks of 1024^2 inner 128^2 against 256^2 chunks unsharded):
# the 16 chunks of a mission's bound decode in 1.0 ms against 3.1 ms (4 ms on the client, more
# while the workers run its sections), writing a layer takes 0.29 s against 0.16 s and reading
# it whole 0.27 s against 0.11 s; inner chunks of 64^2 saved 0.6 ms more a mission for 3.3x
# the write time
LANDMARK_CHUNK = 128
VARIABLE = "landmark_distance"  # (landmark, y, x), float32, shards (1, *the maps' chunks)


def memory_per_landmark(shape) -> int:
    """Bytes one landmark's task holds: the safety surface (float32), the passable mask, the
    float64 distances and a byte a cell of the search's state (Dijkstra's settled flags; the
    row sweeps keep a few values a row). The float32 layer is rounded shard by shard as it is
    written. Measured on 2 workers, 10000^2: 1.61 GiB a worker at the peak (14 bytes a cell
    is 1.30 GiB)."""
    return 14 * int(shape[0]) * int(shape[1])


def _layers_task(store: str, items: list, a: float) -> None:
    """The layers of the landmarks ``items`` (``(index, cell)`` pairs) computed in turn, each
    written shard by shard (:func:`~.store.block_writer`: on a local store the shards' bytes
    written directly, 1.2 s for a 10000^2 layer where zarr's own write of it took 6.4 s) and
    rounded to float32 shard by shard as it is written (no float32 copy of the map). The
    safety and passable layers are read once for all of them, as :func:`whole_layer` reads
    them (1.1 s at 10000^2)."""
    import zarr

    from .store import block_writer

    g = zarr.open_group(store, mode="r", zarr_format=3)
    surface = whole_layer(store, g, "safety")
    passable = whole_layer(store, g, "passable")
    _, bh, bw = storage_chunks(g[VARIABLE])
    write = block_writer(store, VARIABLE)
    for i, cell in items:
        d = distances_from(surface, passable, a, cell)
        for si in range(-(-d.shape[0] // bh)):
            for sj in range(-(-d.shape[1] // bw)):
                part = (slice(si * bh, (si + 1) * bh), slice(sj * bw, (sj + 1) * bw))
                write((i, si, sj), d[None, *part].astype(np.float32))
        del d  # (no view of it left) before the next search allocates its own


def search_slots() -> int:
    """How many landmark searches run at once: the worker threads of the distributed client
    dask computes on, else two (this process's threads, half of its memory each)."""
    from .cluster import computing_client

    client = computing_client()
    if client is None:
        return 2
    return max(1, sum(client.nthreads().values()))


def component_sizes(parts) -> np.ndarray:
    """The cells of each component label (index 0: not passable), from the ``np.bincount`` of
    each part of the component layer (the parts tiling the map)."""
    counts = np.zeros(max((p.size for p in parts), default=1), dtype=np.int64)
    for p in parts:
        counts[: p.size] += p
    return counts


def whole_layer(store: str, group, var: str) -> np.ndarray:
    """Layer ``var`` of the maps store ``store`` (its zarr ``group``) in memory: copied from its
    memory-mapped shards where it is local, sharded and uncompressed
    (:class:`~.store.MappedLayer`; a 10000^2 safety layer in 0.99 s against 1.71 s through
    zarr, the passable mask 0.10 s against 0.64 s), else through zarr. The mapping is dropped
    once copied."""
    from .store import MappedLayer

    arr = group[var]
    layer = MappedLayer.of(arr, store, var)
    out = None
    if layer is not None:
        out = layer.window(0, arr.shape[0], 0, arr.shape[1])  # None: a chunk not written
        del layer
    return arr[:] if out is None else out


# the placement passes' tasks read about one storage chunk each, in whole blocks of the coarse
# grid, so that each coarse block is summed by one task, as the in-memory placement sums it
def placement_regions(shape, chunks, factor: int) -> list[tuple[int, int, int, int]]:
    """``(r0, r1, c0, c1)`` spans tiling a map of ``shape``: about ``chunks`` cells a side,
    their first row and column multiples of ``factor``."""
    steps = [factor * max(1, round(c / factor)) for c in chunks]
    return [
        (r0, min(r0 + steps[0], shape[0]), c0, min(c0 + steps[1], shape[1]))
        for r0 in range(0, shape[0], steps[0])
        for c0 in range(0, shape[1], steps[1])
    ]


def _region(store: str, var: str, region) -> np.ndarray:
    """Cells ``region`` ``(r0, r1, c0, c1)`` of layer ``var`` of the store, through zarr."""
    import zarr

    r0, r1, c0, c1 = region
    return zarr.open_array(f"{store}/{var}", mode="r", zarr_format=3)[r0:r1, c0:c1]


def _region_counts(store: str, region) -> np.ndarray:
    """The cells of each component label in ``region`` of the store's component layer."""
    return np.bincount(_region(store, "component", region).ravel())


def _region_sums(store: str, region, factor: int, big) -> tuple:
    """:func:`block_sums` of ``region`` (its first cell's coarse block, the sums), the kept
    cells those of the components ``big``."""
    keep = np.isin(_region(store, "component", region), big)
    n, zs = block_sums(_region(store, "safety", region), keep, factor)
    return region[0] // factor, region[2] // factor, n, zs


def assembled(shape, factor: int, parts) -> tuple:
    """The :func:`block_sums` of a map of ``shape`` from those of its parts (each as
    :func:`_region_sums` returns it: its first block's row and column, then its sums)."""
    n = np.zeros((-(-shape[0] // factor), -(-shape[1] // factor)), dtype=np.int64)
    zs = np.zeros(n.shape, dtype=np.float64)
    for br, bc, rn, rz in parts:
        n[br : br + rn.shape[0], bc : bc + rn.shape[1]] = rn
        zs[br : br + rz.shape[0], bc : bc + rz.shape[1]] = rz
    return n, zs


def landmarks_staged(store, k: int, a: float, log=None, counts=None) -> list[tuple[int, int]]:
    """Place ``k`` landmarks on the maps store being built at ``store`` (its safety, passable
    and component layers written) and write their distance layers into it: the variable
    ``landmark_distance`` (landmark, y, x). ``counts``: the cells of each component label,
    when the caller has them (:func:`component_sizes`; the maps build's component pass).

    Placement reads the store in two passes of tasks over parts of about a storage chunk, in
    whole blocks of its coarse grid (:func:`placement_regions`): the components' sizes (unless
    given), then the block sums of the coarse grid of at most ``PLACEMENT_SIDE`` cells a side
    (:func:`block_sums`, as :func:`coarse_grid` computes them in memory). On the 10000^2
    benchmark map (2 workers) the two passes took 5.3-5.6 s (the sums 3.3-3.7 s; the maps
    build counts the sizes in its component pass) where dask's ``bincount`` of the raveled
    layer and xarray's ``coarsen`` (which rechunked it to the blocks) took 10.2 s. The
    layers are computed by one task per search slot (:func:`search_slots`), each holding the
    whole map (:func:`memory_per_landmark`), which reads the map once and computes its share
    of the landmarks in turn (every slot-th one). Returns the landmark cells."""
    import dask
    import zarr

    if k <= 0:
        return []
    store = str(store)
    comp_arr = zarr.open_array(f"{store}/component", mode="r", zarr_format=3)
    shape = tuple(int(n) for n in comp_arr.shape)
    f = placement_factor(shape)
    regions = placement_regions(shape, storage_chunks(comp_arr), f)
    if counts is None:
        task = dask.delayed(_region_counts, pure=False)  # it reads the store
        counts = component_sizes(dask.compute(*[task(store, r) for r in regions]))
    if counts.size <= 1:
        return []  # no passable cell
    big = large_components(None, counts)
    task = dask.delayed(_region_sums, pure=False)
    parts = dask.compute(*[task(store, r, f, big) for r in regions])
    mean, ok = coarse_mean(*assembled(shape, f, parts), f)
    cells: list[tuple[int, int]] = []
    for cr, cc in place_coarse(mean, ok, a * f, k):
        block = np.isin(comp_arr[cr * f : (cr + 1) * f, cc * f : (cc + 1) * f], big)
        cell = fine_cell(block, cr * f, cc * f)
        if cell is not None and cell not in cells:
            cells.append(cell)
    if log:
        log("placing %d landmarks: %s", len(cells), cells)
    group = zarr.open_group(store, mode="r+", zarr_format=3)
    if not cells:
        return cells
    group.create_array(
        VARIABLE,
        shape=(len(cells),) + shape,
        shards=(1,) + storage_chunks(comp_arr),
        chunks=(1,) + inner_chunks(storage_chunks(comp_arr), LANDMARK_CHUNK),
        dtype="float32",
        # no distance is negative, so no chunk equals the fill value and every chunk is
        # written (also those all inf, outside the landmark's component)
        fill_value=-1.0,
        compressors=layer_codec(),
        dimension_names=("landmark", "y", "x"),
        attributes={
            "long_name": "shortest safe path length from each landmark (inf: not reached)",
            "units": "m",
            "landmark_cells": [list(c) for c in cells],
        },
        overwrite=True,
    )
    items = list(enumerate(cells))
    slots = min(len(items), search_slots())
    task = dask.delayed(_layers_task, pure=False)
    dask.compute(*[task(store, items[j::slots], a) for j in range(slots)])
    return cells
