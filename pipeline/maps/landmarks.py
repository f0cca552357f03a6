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

A layer's search holds the safety surface quantised (:func:`quantised`, 2 bytes a cell): in
blocks of 8 x 8 cells, each passable cell's height is one of 65 535 steps between its block's
lowest and highest heights (``IMPASSABLE`` marks the others), so it lies within the block's
error ``e`` (half a step, measured as the search computes the height, with a margin for
rounding) of its true height: 0.5 mm in the median block of the 2000^2 benchmark map, 9.7 mm
in the worst. A move's rise is taken less the errors of its two cells (never below 0), which
is at most its true rise: every move of the search's graph costs at most what it costs the
planners, by at most ``e_u + e_v`` (times the move's slope) less.

A layer's distances are computed in whole units of ``unit = a * 2^-b`` (``a`` the cell size;
``b`` from 16 to 24 bits as the map's size allows, :func:`fixed_point_bits`), 4 bytes a cell:
each move's cost (its rise lowered as above) is rounded down to whole units, so the layer holds
the exact shortest distances ``D_l`` (integer arithmetic, which float64 carries exactly) of a
graph whose every edge is at most as long as the planners'. A path of the planners' graph is
no shorter in it, so ``|D_l(s) - D_l(g)| unit <= L*(s, g)`` by the triangle inequality in that
graph: neither the rounding nor the quantised heights ever make the bound exceed the optimum,
they only loosen it, by less than one unit and the two cells' errors a move (a relative
``2^-b``, 1.5e-5 at most where rows and columns add up to more than 4096, and ``2 e / a``:
measured against float32 heights, a median of 6e-6 and at most 4e-5 of the distances on the
2000^2 benchmark map, 5e-7 and 8e-6 at 10000^2, 3e-5 and 6e-5 on the serpentine corridor
map, 5e-5 and 3.3e-4 on the certify benchmark's wall with one gap). Values are held at
``2^31`` units (``2^(31 - b)`` cells' lengths, four times the way round the map where ``b`` is
above 16, 32 768 where it is 16): ``min(D, cap)`` keeps the triangle inequality. Where a
distance reaches the cap (a maze whose paths wind further), the layer is computed again in
units 16 times as long, down to ``2^-8`` of a cell (0.4 %); where a move could cost ``2^30``
units (a relief of more than ``2^(30 - b)`` cells' lengths), in coarser units from the start;
only a relief of ``2^30`` cells' lengths would leave float64 (:func:`distances_from` on the
float32 heights, exact up to the float64 summation, ``n * 2^-53`` for a path of ``n`` moves).

The layer stores ``D_l unit`` as float32, rounded to nearest: a relative error of at most
2^-24 (plus 2^-53 for the product and for the float64 rounding of each move's cost), so
:func:`lower_bound` takes ``|d_l(s) - d_l(g)| - REL_MARGIN * (d_l(s) + d_l(g))`` with
``REL_MARGIN = 2^-22`` (``LANDMARK_MARGIN`` of the planners' core, which uses the same bound
as its A* heuristic), a margin that covers it with room to spare.

A layer's search runs on the whole map in one process: row sweeps (the exact search of
:mod:`pipeline.planners.sweep` with the whole map as its region), or where they give up
Dijkstra's algorithm with a bucket queue in the same fixed point (:func:`fixed_point_dijkstra`:
the same integers), holding the quantised surface and the distances, 6.2 bytes a cell
(10000^2: 0.58 GiB), 7.2 with Dijkstra's settled flags (:func:`memory_per_landmark`).
"""

from __future__ import annotations

import math

import numpy as np

from ..planners.bounds import dijkstra, fixed_point_dijkstra
from ..planners.search import LANDMARK_MARGIN
from ..planners.sweep import (
    FIXED_CAP,
    FIXED_UNREACHED,
    IMPASSABLE,
    Quantised,
)
from ..runtime.cluster import compute_told, prefixed
from ..runtime.jit import njit
from ..store.schema import LANDMARK_CHUNK, VARIABLE, inner_chunks, layer_codec, storage_chunks

MIN_COMPONENT_FRACTION = 0.01


REL_MARGIN = LANDMARK_MARGIN


DEFAULT_LANDMARKS = 8


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
    (the same values as :func:`dijkstra`, bit for bit, an order of magnitude faster), by
    :func:`dijkstra` where they give up (a maze that turns back on itself many times)."""
    from ..planners import sweep

    surface = np.ascontiguousarray(surface)
    if surface.dtype != np.float32:
        surface = surface.astype(np.float32)
    passable = np.ascontiguousarray(passable, dtype=np.bool_)
    r, c = int(cell[0]), int(cell[1])
    d = sweep.distances(surface, passable, float(a), (r, c)) if passable[r, c] else None
    if d is None:
        d = dijkstra(surface, passable, float(a), np.array([r * passable.shape[1] + c]))
    return d


MIN_BITS = 16  # the unit the map's size asks for: at most 2^-16 of a cell (a bound 1.5e-5 looser)


MAX_BITS = 24  # at least 2^-24 of a cell: finer is below the float32 layer's resolution


CAPPED_BITS = 8  # where distances pass the cap, coarser units down to 2^-8 of a cell (0.4 %)


def fixed_point_bits(shape, relief_m: float, a: float) -> int | None:
    """The ``b`` of the layer's first unit ``a * 2^-b`` (module doc) for a map of ``shape``: the
    finest (at most :data:`MAX_BITS`) whose cap ``2^31`` units holds four times the way round
    the map (a path across it and back, twice), at least :data:`MIN_BITS`; coarser where the
    longest move (its rise ``relief_m``) would cost ``2^30`` units or more (a relief of more
    than ``2^14`` cells' lengths); None where even whole cells would not do (the layer is then
    computed in float64)."""
    extent = 4.0 * (int(shape[0]) + int(shape[1]))
    bits = min(MAX_BITS, max(MIN_BITS, math.floor(math.log2(FIXED_CAP / extent))))
    longest = math.sqrt(2.0 + (float(relief_m) / a) ** 2)  # in cells' lengths
    while bits >= 0 and longest * 2.0**bits >= 2.0**30:
        bits -= 1
    return bits if bits >= 0 else None


@njit(nogil=True, cache=True)
def _reaches_cap(d) -> bool:
    """Whether a fixed-point distance is held at the cap."""
    for v in d.ravel():
        if v == FIXED_CAP:
            return True
    return False


def layer_distances(surface, passable, a: float, cell):
    """One landmark's distances as its layer is computed (module doc): ``(D, unit)``, ``D`` the
    whole units of ``unit`` metres (uint32; ``FIXED_UNREACHED`` where not reached), or, where
    the fixed point does not serve, float64 metres with ``unit`` None. Convert a part of it
    with :func:`layer_values`. ``surface`` float32 heights with the mask ``passable`` (None:
    NaN on the impassable cells), quantised here (:func:`quantised`), or a
    :class:`~.planners.sweep.Quantised` surface already (:func:`_layers_task`, which gives the
    float32 heights where no fixed point serves).

    The row sweeps compute it, or Dijkstra's algorithm where they give up; where a distance
    reaches the cap (a maze whose paths run more than four times round the map), again in
    units 16 times as long, down to :data:`CAPPED_BITS`."""
    from ..planners import sweep

    r, c = int(cell[0]), int(cell[1])
    if isinstance(surface, Quantised):
        q = surface
    else:
        surface = np.ascontiguousarray(surface, dtype=np.float32)
        if passable is None:
            passable = ~np.isnan(surface)
        passable = np.ascontiguousarray(passable, dtype=np.bool_)
        q = quantised(surface, passable)
    shape = q.codes.shape
    bits = fixed_point_bits(shape, q.relief, float(a))
    if bits is None:  # float64 metres, on the float32 heights
        if isinstance(surface, Quantised):
            raise ValueError("no fixed point serves this relief: give the float32 heights")
        del q
        return distances_from(surface, passable, a, cell), None
    if q.codes[r, c] == IMPASSABLE:  # reaches nothing
        return np.full(shape, FIXED_UNREACHED, dtype=np.uint32), float(a) * 2.0**-bits
    while True:
        d = sweep.fixed_point_distances(q, q, float(a), (r, c), bits)
        if d is None:
            d = fixed_point_dijkstra(q, float(a), (r, c), bits)
        if bits <= CAPPED_BITS or not _reaches_cap(d):
            return d, float(a) * 2.0**-bits
        del d  # before the next search allocates its own
        bits = max(CAPPED_BITS, bits - 4)


# quantised surfaces (:func:`quantised`) are quantised in blocks of 2^QUANT_SHIFT cells a side,
# whose values take 12 bytes a block, 3/16 byte a cell. On the 2000^2 benchmark map (30 m
# cells) a block's largest error is 0.5 mm in the median block, 9.7 mm in the worst (4 x 4
# blocks: 0.2 and 5.4 mm, 16 x 16: about twice 8 x 8)
QUANT_SHIFT = 3


QUANT_STEPS = 65534.0  # codes 0 .. 65534; IMPASSABLE (65535) marks a cell not passable


@njit(nogil=True, cache=True)
def _quantise_rows(z, ok, r0, codes, base, quantum, error, shift):
    """Rows ``r0 ..`` of a quantised surface from the heights ``z`` (float32) and mask ``ok``
    of those rows (``r0`` a multiple of the block side; the rows end at a block's or the
    map's end): per block its lowest passable height (``base``, float32: exact), a step
    ``quantum`` (float32) of its relief over :data:`QUANT_STEPS` and the largest difference
    between a cell's height and its quantised one (``height_at``'s float64 arithmetic), with a
    margin for the rounding of float64 sums of heights (``error``, float32, rounded up); per
    cell the nearest step (:data:`IMPASSABLE` where not passable, or where its height is not
    finite: no move reaches it). Returns the lowest and highest passable heights and the
    largest error."""
    rows, cols = z.shape
    side = 1 << shift
    lowest = np.inf
    highest = -np.inf
    worst = 0.0
    for i0 in range(0, rows, side):
        bi = (r0 + i0) >> shift
        i1 = min(i0 + side, rows)
        for j0 in range(0, cols, side):
            bj = j0 >> shift
            j1 = min(j0 + side, cols)
            lo = np.inf
            hi = -np.inf
            for i in range(i0, i1):
                for j in range(j0, j1):
                    if ok[i, j] and np.isfinite(z[i, j]):
                        h = np.float64(z[i, j])
                        lo = min(lo, h)
                        hi = max(hi, h)
            base[bi, bj] = np.float32(lo) if hi >= lo else 0.0
            quantum[bi, bj] = np.float32((hi - lo) / QUANT_STEPS) if hi >= lo else 0.0
            b = np.float64(base[bi, bj])
            step = np.float64(quantum[bi, bj])
            # the nearest step (or, by the reciprocal's rounding, one beside it: the error is
            # measured on the code taken)
            inv = 1.0 / step if step > 0.0 else 0.0
            err = 0.0
            for i in range(i0, i1):
                for j in range(j0, j1):
                    if not (ok[i, j] and np.isfinite(z[i, j])):
                        codes[r0 + i, j] = IMPASSABLE
                        continue
                    h = np.float64(z[i, j])
                    k = min(max(np.floor((h - b) * inv + 0.5), 0.0), QUANT_STEPS)
                    codes[r0 + i, j] = np.uint16(k)
                    err = max(err, abs(h - (b + k * step)))
            if hi >= lo:
                lowest = min(lowest, lo)
                highest = max(highest, hi)
                # margins: float32 rounds the error to within 2^-24 of it; the searches' float64
                # heights and their differences are exact to within 2^-52 of the heights
                err = err * (1.0 + 2.0**-20) + 2.0**-40 * (max(abs(lo), abs(hi)) + 1.0)
            error[bi, bj] = np.float32(err)
            worst = max(worst, np.float64(error[bi, bj]))
    return lowest, highest, worst


def _quantised_parts(shape, shift: int = QUANT_SHIFT):
    """The arrays of a quantised surface of ``shape``: codes, blocks' bases, steps, errors."""
    nb = (-(-shape[0] // (1 << shift)), -(-shape[1] // (1 << shift)))
    codes = np.empty(shape, dtype=np.uint16)
    return codes, *(np.empty(nb, dtype=np.float32) for _ in range(3))


def _finished(arrays, shift, parts) -> Quantised:
    """The :class:`~.planners.sweep.Quantised` surface of its ``arrays``, from the
    :func:`_quantise_rows` results of its row bands: its ``relief`` the passable heights'
    span plus twice the largest error (a bound on the quantised heights')."""
    lo = min((p[0] for p in parts), default=np.inf)
    hi = max((p[1] for p in parts), default=-np.inf)
    worst = max((p[2] for p in parts), default=0.0)
    relief = (hi - lo) + 2.0 * worst if hi >= lo else 0.0
    return Quantised(*arrays, shift, float(relief))


def quantised(surface, passable, shift: int = QUANT_SHIFT) -> Quantised:
    """The float32 safety ``surface`` with its ``passable`` mask as a quantised surface, 2
    bytes a cell (:class:`~.planners.sweep.Quantised`; module doc): what a landmark's search
    holds."""
    surface = np.ascontiguousarray(surface, dtype=np.float32)
    passable = np.ascontiguousarray(passable, dtype=np.bool_)
    arrays = _quantised_parts(surface.shape, shift)
    part = _quantise_rows(surface, passable, 0, *arrays, shift)
    return _finished(arrays, shift, [part])


def layer_values(d: np.ndarray, unit: float | None) -> np.ndarray:
    """Distances of :func:`layer_distances` (any part of them) as the layer stores them:
    float32 metres, ``inf`` where not reached."""
    if unit is None:
        return d.astype(np.float32)
    return _in_metres(d, unit)


@njit(nogil=True, cache=True)
def _in_metres(d, unit):
    """Fixed-point distances ``d`` (rows x cols) as float32 metres (each ``d * unit`` in
    float64, then rounded to nearest), ``inf`` where not reached, with no temporary array."""
    out = np.empty(d.shape, dtype=np.float32)
    for i in range(d.shape[0]):
        for j in range(d.shape[1]):
            v = d[i, j]
            out[i, j] = np.inf if v == FIXED_UNREACHED else np.float32(np.float64(v) * unit)
    return out


def landmark_layer(surface, passable, a: float, cell) -> np.ndarray:
    """The float32 distance layer of one landmark (``inf`` outside its component)."""
    return layer_values(*layer_distances(surface, passable, a, cell))


def memory_per_landmark(shape) -> int:
    """Bytes one landmark's task may hold: the quantised safety surface (2 bytes a cell and 12
    a block of 8 x 8) and the fixed-point distances (uint32), 6.2 bytes a cell, and where the
    row sweeps give up (a maze) Dijkstra's settled flags besides: 7.2 bytes a cell (the row
    sweeps keep a few values a row; the surface is quantised a row of shards at a time, the
    float32 layer converted shard by shard as it is written). Only a relief of 2^30 cells'
    lengths (float32 heights, a mask and float64 distances: 13 bytes a cell) would need more.
    The workers' measured peaks against this estimate: CHANGELOG.md, "Measurements"."""
    side = 1 << QUANT_SHIFT
    blocks = -(-int(shape[0]) // side) * -(-int(shape[1]) // side)
    return 7 * int(shape[0]) * int(shape[1]) + 12 * blocks


def _layers_task(store: str, items: list, a: float) -> None:
    """The layers of the landmarks ``items`` (``(index, cell)`` pairs) computed in turn, each
    written shard by shard (:func:`~.store.block_writer`: on a local store the shards' bytes
    written directly, five times faster than zarr's own write) and
    converted to float32 metres shard by shard as it is written (:func:`layer_values`; no
    float32 copy of the map). The safety and passable layers are read once for all of them,
    as a quantised surface (:func:`quantised_surface`, 2 bytes a cell)."""
    import zarr

    from ..store.zarr_direct import block_writer

    g = zarr.open_group(store, mode="r", zarr_format=3)
    surface, mask = quantised_surface(store, g), None
    if fixed_point_bits(surface.codes.shape, surface.relief, a) is None:
        # a relief of 2^30 cells' lengths: float64 distances on the float32 heights (module doc)
        surface = whole_layer(store, g, "safety").astype(np.float32, copy=False)
        mask = whole_layer(store, g, "passable").astype(bool)
    _return_freed_memory()
    _, bh, bw = storage_chunks(g[VARIABLE])
    write = block_writer(store, VARIABLE)
    for i, cell in items:
        d, unit = layer_distances(surface, mask, a, cell)
        for si in range(-(-d.shape[0] // bh)):
            for sj in range(-(-d.shape[1] // bw)):
                part = (slice(si * bh, (si + 1) * bh), slice(sj * bw, (sj + 1) * bw))
                write((i, si, sj), layer_values(d[part], unit)[None])
        del d  # (no view of it left) before the next search allocates its own


def _return_freed_memory() -> None:
    """Hand the memory this process has freed back to the system (glibc's ``malloc_trim``,
    which dask's documentation suggests for a worker's unmanaged memory), before a landmark
    search takes the most: what the maps build's earlier tasks left in the worker's heap
    (0.03 GiB of a worker's 0.09 after the placement passes at 10000^2) would otherwise add
    to its peak. Nothing where there is no glibc."""
    import ctypes
    import ctypes.util
    import gc

    gc.collect()
    name = ctypes.util.find_library("c")
    try:
        ctypes.CDLL(name).malloc_trim(0)
    except (OSError, AttributeError, TypeError):
        pass


def search_slots() -> int:
    """How many landmark searches run at once: the worker threads of the distributed client
    dask computes on, else two (this process's threads, half of its memory each)."""
    from ..runtime.cluster import computing_client

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


def whole_layer(store: str, group, var: str, rows=None) -> np.ndarray:
    """Layer ``var`` of the maps store ``store`` (its zarr ``group``) in memory, or its rows
    ``rows`` (``(r0, r1)``): copied from its memory-mapped shards where it is local, sharded
    and uncompressed (:class:`~.store.MappedLayer`, faster than through zarr), else through
    zarr. One row
    of shards is mapped at a time (the mapped pages count in the process's memory: the whole
    layer mapped at once made its copy's peak twice the layer)."""
    from ..store.zarr_direct import MappedLayer

    arr = group[var]
    r0, r1 = rows if rows is not None else (0, arr.shape[0])
    layer = MappedLayer.of(arr, store, var)
    out = None
    if layer is not None:
        layer.keep = -(-arr.shape[1] // arr.shards[1])
        out = layer.window(r0, r1, 0, arr.shape[1])  # None: a chunk not written
        del layer
    return arr[r0:r1] if out is None else out


def quantised_surface(store: str, group) -> Quantised:
    """The store's safety layer with its passable layer as a quantised surface (:func:`quantised`,
    2 bytes a cell): the landmark searches' one whole-map input, read a row of shards at a
    time (the rows of a band rounded down to whole blocks)."""
    shape = tuple(group["safety"].shape)
    arrays = _quantised_parts(shape)
    side = 1 << QUANT_SHIFT
    step = storage_chunks(group["safety"])[0]
    step = max(side, step - step % side)
    parts = []
    for r0 in range(0, shape[0], step):
        r1 = min(r0 + step, shape[0])
        z = whole_layer(store, group, "safety", (r0, r1))
        ok = whole_layer(store, group, "passable", (r0, r1)).astype(bool)
        z = z.astype(np.float32, copy=False)
        parts.append(_quantise_rows(z, ok, r0, *arrays, QUANT_SHIFT))
        del z, ok
    return _finished(arrays, QUANT_SHIFT, parts)


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
    (:func:`block_sums`, as :func:`coarse_grid` computes them in memory), in about half the
    time of dask's ``bincount`` of the raveled layer and xarray's ``coarsen`` (which rechunked
    it to the blocks; the maps build counts the sizes in its component pass). The
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
    parts = compute_told(
        [task(store, r, f, big) for r in regions],
        prefixed(log, "placing: "),
        "regions summed",
    )
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
            # the searches' heights: 65 535 steps of each block's relief (module doc)
            "quantised_blocks": 1 << QUANT_SHIFT,
        },
        overwrite=True,
    )
    items = list(enumerate(cells))
    slots = min(len(items), search_slots())
    task = dask.delayed(_layers_task, pure=False)
    dask.compute(*[task(store, items[j::slots], a) for j in range(slots)])
    return cells
