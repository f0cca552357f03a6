"""The grid core shared by every planner: the graph, the edge cost, the heuristic, the search
state, A*'s relaxation and search, path tracing and metrics, endpoint checks, ``Trajectory``.

Graph (docs/method.md section 4): 8-connected over passable cells; a diagonal move only when both
orthogonal cells it passes between are passable (no corner cutting). Edge cost: the 3-D length
along the safety surface ``sqrt(a^2 (dr^2 + dc^2) + (S(q) - S(p))^2)``; heuristic: the
horizontal straight-line distance to the goal (admissible and consistent, since every edge is
at least as long as its horizontal projection).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..exceptions import InvalidEndpointError, InvalidParameterError
from ..runtime.jit import njit
from .grid import DC, DR, flat_offsets
from .heap import grown, heap_pop, heap_push, heap_reserve


@dataclass
class Trajectory:
    """A planned path and its metrics (docs/method.md section 8); lengths in metres."""

    cells: np.ndarray
    points: np.ndarray
    length_m: float
    ridge_length_m: float
    ridge_ratio: float
    lower_bound_m: float
    expansions: int
    runtime_s: float
    planner: str
    omega: float
    status: str = "ok"  # "ok" (certified), "uncertified" or "failed"
    message: str = ""
    extra: dict = field(default_factory=dict)
    flight: object = None  # the flown track (pipeline.flight.Flight), when computed

    @property
    def certified_ratio(self) -> float:
        """``length_m / lower_bound_m``: the path is proven within this factor of the shortest
        safe path (NaN without a path, 1 for a path of one cell)."""
        if not (self.length_m == self.length_m) or not (self.lower_bound_m > 0):
            return 1.0 if self.length_m == 0 else math.nan
        return self.length_m / self.lower_bound_m

    @property
    def planned(self) -> bool:
        """Whether there is a path (status "ok" or "uncertified")."""
        return self.status in ("ok", "uncertified")

    def __repr__(self) -> str:
        """One line: status, planner, length, the proven bound and ratio, ridge share, cells
        (and the flight's, when flown); the arrays are in ``cells``, ``points``."""
        if not self.planned:
            return f"Trajectory(failed, {self.planner}: {self.message})"
        flown = ""
        if self.flight is not None:
            flown = f", {self.flight!r}"
        return (
            f"Trajectory({self.status}, {self.planner} omega {self.omega:g}, "
            f"{self.length_m / 1e3:.3f} km <= {self.certified_ratio:.3f} x the proven bound "
            f"{self.lower_bound_m / 1e3:.3f} km, ridge {100 * self.ridge_ratio:.0f} %, "
            f"{len(self.cells)} cells{flown})"
        )

    def to_geodataframe(self):
        """The grid path as a GeoDataFrame (a point a cell: ``row``, ``col``, ``z`` on the
        safety surface) and, when flown, the flown route's waypoints (``waypoint``, ``z``,
        ``time_s``), in the maps' CRS when the trajectory knows it (``extra["crs_wkt"]``,
        which :func:`pipeline.plan` sets), with a ``kind`` column telling them apart."""
        import geopandas as gpd
        import pandas as pd

        crs = self.extra.get("crs_wkt")
        pts = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        grid = gpd.GeoDataFrame(
            {
                "kind": "grid path",
                "row": np.asarray(self.cells)[:, 0] if len(self.cells) else [],
                "col": np.asarray(self.cells)[:, 1] if len(self.cells) else [],
                "z": pts[:, 2],
            },
            geometry=gpd.points_from_xy(pts[:, 0], pts[:, 1]),
            crs=crs,
        )
        f = self.flight
        if f is None:
            return grid
        w = np.asarray(f.waypoints, dtype=np.float64)
        route = gpd.GeoDataFrame(
            {"kind": "waypoint", "waypoint": np.arange(len(w)), "z": w[:, 2], "time_s": w[:, 3]},
            geometry=gpd.points_from_xy(w[:, 0], w[:, 1]),
            crs=crs,
        )
        return gpd.GeoDataFrame(pd.concat([grid, route], ignore_index=True), crs=crs)


@njit(inline="always", cache=True)
def edge_length(h2, dz):
    """The 3-D length of a move: ``h2`` its squared horizontal length, ``dz`` its rise."""
    return math.sqrt(h2 + dz * dz)


@njit(inline="always", cache=True)
def edge_cost(surface, a, r, c, nr, nc):
    """The cost of the move (r, c) -> (nr, nc): its 3-D length along the surface."""
    dr = nr - r
    dc = nc - c
    dz = np.float64(surface[nr, nc]) - np.float64(surface[r, c])
    return edge_length(a * a * (dr * dr + dc * dc), dz)


# ties in f go to the state nearer the goal: the heap key is g + weight * (1 + TIE) * h. A* with
# it is weighted A* of weight 1 + TIE, so its path is within a factor 1 + TIE of the optimum
TIE = 1e-10


@njit(inline="always", cache=True)
def heuristic(a, r, c, gr, gc, octile):
    """A lower bound on the length from (r, c) to the goal: the octile distance (the exact
    horizontal length on the open 8-connected grid) or the straight line of docs/method.md
    section 4; both are admissible and consistent, since no edge is shorter than its
    horizontal projection."""
    dr = abs(r - gr)
    dc = abs(c - gc)
    if octile:
        return a * (max(dr, dc) + (math.sqrt(2.0) - 1.0) * min(dr, dc))
    return a * math.sqrt(dr * dr + dc * dc)


# landmark distances (ALT, :mod:`pipeline.maps.landmarks`) are float32: a bound from them is taken
# less this relative margin (float32 rounding and float64 summation), so that it never exceeds
# the true distance
LANDMARK_MARGIN = 2.0**-22
NO_LANDMARKS = np.zeros((0, 0), dtype=np.float32)
NO_GOAL = np.zeros(0)


@njit(cache=True)
def landmark_shrink(lm, a):
    """The factor ``1 - delta`` that makes the landmark heuristic consistent: stored as float32,
    a distance ``D`` is off by up to ``2^-24 D``, so ``|d_l(u) - d_l(g)|`` may change along an
    edge by its cost plus ``2^-23 D_max``; every edge costs at least ``a``, so shrinking by
    ``delta = 2 LANDMARK_MARGIN + 2^-22 D_max / a`` absorbs that (and the margin's own change)
    with room to spare. ``D_max``: the largest finite distance of the window's layers."""
    dmax = 0.0
    for k in range(lm.shape[0]):
        for v in range(lm.shape[1]):
            d = np.float64(lm[k, v])
            if d != np.inf and d > dmax:
                dmax = d
    return 1.0 - (2.0 * LANDMARK_MARGIN + 2.0**-22 * dmax / a)


@njit(inline="always", cache=True)
def landmark_heuristic(lm, lg, shrink, v, h):
    """``max(h, shrink * max_l |d_l(v) - d_l(goal)|)`` less the rounding margin: a lower bound
    on the length from flat cell ``v`` of the window to the goal, by the triangle inequality,
    and consistent (``landmark_shrink``); ``lm[l, v]`` the distances from landmark ``l`` (inf:
    it does not reach), ``lg`` the goal's."""
    for k in range(lm.shape[0]):
        d = np.float64(lm[k, v])
        if d == np.inf or lg[k] == np.inf:
            continue
        b = shrink * abs(d - lg[k]) - LANDMARK_MARGIN * (d + lg[k])
        if b > h:
            h = b
    return h


def landmark_rows(landmarks, shape) -> np.ndarray:
    """Landmark layers of a window, ``(k, rows, cols)``, as the ``(k, cells)`` float32 array the
    searches take (none: an empty array)."""
    if landmarks is None or len(landmarks) == 0:
        return NO_LANDMARKS
    lm = np.ascontiguousarray(landmarks, dtype=np.float32)
    if lm.ndim != 3 or lm.shape[1:] != tuple(shape):
        raise InvalidParameterError(
            f"`landmarks` must be k layers of the window's shape {tuple(shape)}, got {lm.shape}"
        )
    return lm.reshape(lm.shape[0], -1)


# Search state, one byte a cell: bits 0-2 the neighbour index (``_grid8``) of the move that
# entered the cell, PARENT when it has one, CLOSED once expanded, SEEN for the root. ``g`` is
# valid only where PARENT or SEEN is set, so it needs no initialisation pass (np.empty).
PARENT = 8
CLOSED = 16
SEEN = 32
INWAIT = 64  # RA*'s ridge search: the state has an entry in WAIT


@njit(cache=True, _nrt=False)
def relax_successors(
    surface,
    ridge,
    passable,
    a,
    u,
    g,
    state,
    hk,
    hi,
    hn,
    gr,
    gc,
    weight,
    off_weight,
    octile,
    lm=NO_LANDMARKS,
    lg=NO_GOAL,
    shrink=1.0,
    hoff=NO_GOAL,
    hw=0.0,
):
    """A*'s expansion of ``u``: improve ``g`` of its open successors and push them with key
    ``g + weight * h`` (weight 0: Dijkstra). An edge costs its 3-D length, times
    ``1 + off_weight`` when it ends off the ridge network (the Lagrangian objective
    ``length + off_ridge / lambda``; 0 for plain length). With landmark layers ``lm`` (goal
    distances ``lg``, consistency factor ``shrink``) ``h`` is the larger of the octile and the
    landmark bound, both consistent; with ``hw > 0``, ``hw`` times ``hoff``
    (:func:`off_ridge_to_goal`, flat) is added, a bound on the off-ridge term. The heap must
    have room for 8 more entries (``heap_reserve``, outside the caller's inner loop). Returns
    the heap's new size.

    Compiled on its own without numba's reference counting (``_nrt=False``: it allocates
    nothing), not inlined: inlined into A*'s loop, the arrays it takes cost reference-count
    updates on every expansion, and A* took 1.27x the time (the Lagrangian planner's searches
    of the 4000^2 benchmark, the same paths and expansions)."""
    rows, cols = surface.shape
    r = u // cols
    c = u - r * cols
    gu = g[u]
    for k in range(8):
        nr = r + DR[k]
        nc = c + DC[k]
        if nr < 0 or nr >= rows or nc < 0 or nc >= cols:
            continue
        v = nr * cols + nc
        sv = state[v]
        if sv & CLOSED or not passable[nr, nc]:
            continue
        if k % 2 == 1 and not (passable[r, nc] and passable[nr, c]):
            continue  # a diagonal must not cut a corner
        cost = edge_cost(surface, a, r, c, nr, nc)
        if off_weight > 0.0 and not ridge[nr, nc]:
            cost *= 1.0 + off_weight
        ng = gu + cost
        if (sv & (PARENT | SEEN)) == 0 or ng < g[v]:
            g[v] = ng
            state[v] = PARENT | k
            h = heuristic(a, nr, nc, gr, gc, octile)
            if lm.shape[0] > 0:
                h = landmark_heuristic(lm, lg, shrink, v, h)
            if hw > 0.0:
                h += hw * hoff[v]
            hn = heap_push(hk, hi, hn, ng + weight * h, v)
    return hn


@njit(cache=True)
def _search_start(surface, a, sr, sc, gr, gc, weight, off_weight, octile, lm, hoff, g, state):
    """An A* search's start: ``g`` and ``state`` cut to the window's cells, the start marked;
    returns them, the start's and goal's flat indices, the key's weight (with the tie factor),
    the goal's landmark distances, the landmark bound's consistency factor, the off-ridge
    bound's weight (0: not used) and the start's key."""
    rows, cols = surface.shape
    g = g[: rows * cols]
    state = state[: rows * cols]
    s = sr * cols + sc
    t = gr * cols + gc
    g[s] = 0.0
    state[s] = SEEN
    weight = weight * (1.0 + TIE)
    lg = np.empty(lm.shape[0])
    for k in range(lm.shape[0]):
        lg[k] = lm[k, t]
    shrink = landmark_shrink(lm, a) if lm.shape[0] > 0 else 1.0
    h0 = heuristic(a, sr, sc, gr, gc, octile)
    if lm.shape[0] > 0:
        h0 = landmark_heuristic(lm, lg, shrink, s, h0)
    hw = off_weight * (1.0 - 1e-9) if off_weight > 0.0 and hoff.size > 0 else 0.0
    if hw > 0.0:
        h0 += hw * hoff[s]
    return g, state, s, t, weight, lg, shrink, hw, weight * h0


@njit(nogil=True, cache=True)
def astar_search(
    surface,
    ridge,
    passable,
    a,
    sr,
    sc,
    gr,
    gc,
    weight,
    off_weight,
    octile,
    lm,
    hoff,
    g,
    state,
    hk,
    hi,
):
    """(Weighted) A* from (sr, sc) to (gr, gc); weight 1 is A*, weight 0 is Dijkstra.

    No re-expansions: the heuristic is consistent, and weighted A* without reopening still
    returns a path within ``weight`` of the optimum (Likhachev et al. 2003). With landmark
    layers ``lm`` (k x cells of the window, float32) the heuristic is the larger of the octile
    distance and the landmark bound, made consistent by ``landmark_shrink``. With ``hoff``
    (:func:`off_ridge_to_goal` of this goal, flat) and ``off_weight > 0``, ``off_weight`` times
    it (less a relative ``1e-9`` for rounding) is added to the heuristic: the off-ridge term of
    the Lagrangian cost has a bound of its own, and the sum of two consistent bounds on the two
    terms of a cost is a consistent bound on the cost.
    Every argument is given by the callers (``NO_LANDMARKS``, ``NO_GOAL`` for none): an
    omitted array argument types as its default object, which numba cannot key its on-disk
    cache by, so every new process compiled the search again (1-3 s).
    ``g``, ``state`` (float64 and int8, at least a cell each, ``state`` zero on its first
    cells) and the heap's first arrays ``hk``, ``hi`` (float64 and int64, of one size, grown
    here when short) are the search's own, written here (:func:`search_arrays`).
    Returns the state (see ``PARENT``; ``trace_path`` reads the path from it), g, expansions,
    found flag.
    """
    g, state, s, t, weight, lg, shrink, hw, key = _search_start(
        surface, a, sr, sc, gr, gc, weight, off_weight, octile, lm, hoff, g, state
    )
    hn = heap_push(hk, hi, 0, key, s)
    expansions = 0
    while hn > 0:  # makes room in the heap; the inner loop never reassigns it (heap_reserve)
        hk, hi = heap_reserve(hk, hi, hn, 8)
        while hn > 0 and hn + 8 <= hk.size:
            _, u = heap_pop(hk, hi, hn)
            hn -= 1
            if state[u] & CLOSED:
                continue
            state[u] |= CLOSED
            expansions += 1
            if u == t:
                return state, g, expansions, True
            hn = relax_successors(
                surface,
                ridge,
                passable,
                a,
                u,
                g,
                state,
                hk,
                hi,
                hn,
                gr,
                gc,
                weight,
                off_weight,
                octile,
                lm,
                lg,
                shrink,
                hoff,
                hw,
            )
    return state, g, expansions, False


# Searches over windows of at least this many cells (whole large maps: ``plan(mcpc=False)``)
# keep their open list in two levels (:func:`astar_search_bucketed`): buckets of f this many
# cells wide, this many of them ahead of the current one, and a heap beyond
BUCKET_CELLS = 2**22
BUCKET_WIDTH = 0.25
BUCKETS = 4096


def search_kernel(cells: int):
    """The A* kernel for a window of ``cells`` cells: :func:`astar_search`, or
    :func:`astar_search_bucketed` from :data:`BUCKET_CELLS` on (the same arguments, the same
    optimal lengths)."""
    return astar_search_bucketed if cells >= BUCKET_CELLS else astar_search


@njit(cache=True, _nrt=False)
def _bucket_put(pk, pi, pn, head, free, top, nfree, b, key, item):
    """Link (key, item) into bucket ``b`` of the pool (``pk``, ``pi``, ``pn`` the keys, items
    and links; ``free`` the free list's first node): returns (free, top, nfree)."""
    if free >= 0:
        node = free
        free = pn[node]
        nfree -= 1
    else:
        node = top
        top += 1
    pk[node] = key
    pi[node] = item
    pn[node] = head[b]
    head[b] = node
    return free, top, nfree


@njit(cache=True)
def _pool_reserve(pk, pi, pn, top, nfree, extra):
    """The bucket pool's arrays with room for ``extra`` more nodes (its free list's ``nfree``
    first, then the slots from ``top``), grown as
    :func:`~pipeline.planners.heap.heap_reserve` grows a heap; outside a search's inner loop,
    for the same reason."""
    if nfree >= extra or top + extra <= pk.size:
        return pk, pi, pn
    size = max(2 * pk.size, top + extra)
    return grown(pk, top, size), grown(pi, top, size), grown(pn, top, size)


@njit(nogil=True, cache=True)
def astar_search_bucketed(
    surface,
    ridge,
    passable,
    a,
    sr,
    sc,
    gr,
    gc,
    weight,
    off_weight,
    octile,
    lm,
    hoff,
    g,
    state,
    hk,
    hi,
):
    """:func:`astar_search` (the same arguments and result) with its open list in two levels,
    for searches over large maps: the heap ``hk, hi`` holds only the entries of the current
    bucket of keys (``BUCKET_WIDTH`` cells wide) and below; the next ``BUCKETS`` buckets are
    linked lists in a pool, pushed and emptied in O(1); entries further ahead wait in a second
    heap. The heap's top is the smallest key of all (every other entry lies in a later
    bucket), so the pops are A*'s: the same optimal length (ties may go another way). A whole
    map's open list holds 0.2-1 M entries, a heap of them misses the caches at every level:
    exact A* over the benchmark's 10000^2 map 1.17-1.32x faster (3 missions, the best of two
    runs each, in one process), over 4000^2 0.94-1.10x (5 missions): hence only from
    :data:`BUCKET_CELLS`; with the successors pushed inline instead of through
    :func:`relax_successors`, 1.2-1.5x at 4000^2 too, for a second copy of the relaxation."""
    g, state, s, t, weight, lg, shrink, hw, base = _search_start(
        surface, a, sr, sc, gr, gc, weight, off_weight, octile, lm, hoff, g, state
    )
    inv = 1.0 / (BUCKET_WIDTH * a)
    mask = BUCKETS - 1
    head = np.full(BUCKETS, -1, dtype=np.int64)
    bcount = np.zeros(BUCKETS, dtype=np.int64)
    pk = np.empty(1 << 16)
    pi = np.empty(1 << 16, dtype=np.int64)
    pn = np.empty(1 << 16, dtype=np.int64)
    top = 0
    free = -1
    nfree = 0
    fk = np.empty(64)  # the far heap
    fi = np.empty(64, dtype=np.int64)
    fn = 0
    sk = np.empty(8)  # one expansion's successors (relax_successors pushes them here)
    si = np.empty(8, dtype=np.int64)
    cur = 0  # the current bucket; ``count`` entries wait in the later ones
    count = 0
    hn = heap_push(hk, hi, 0, base, s)
    expansions = 0
    while True:
        if hn == 0:  # the next bucket that holds entries, and the far ones now within reach
            if count == 0 and fn == 0:
                break
            if count == 0:
                cur = max(cur, int((fk[0] - base) * inv) - BUCKETS)
            while True:
                cur += 1
                if bcount[cur & mask] > 0 or (fn > 0 and int((fk[0] - base) * inv) < cur + BUCKETS):
                    break
            hk, hi = heap_reserve(hk, hi, hn, bcount[cur & mask] + fn + 8)
            pk, pi, pn = _pool_reserve(pk, pi, pn, top, nfree, fn)
            while fn > 0 and int((fk[0] - base) * inv) < cur + BUCKETS:
                key, v = heap_pop(fk, fi, fn)
                fn -= 1
                b = int((key - base) * inv)
                if b <= cur:
                    hn = heap_push(hk, hi, hn, key, v)
                else:
                    free, top, nfree = _bucket_put(
                        pk, pi, pn, head, free, top, nfree, b & mask, key, v
                    )
                    bcount[b & mask] += 1
                    count += 1
            node = head[cur & mask]
            head[cur & mask] = -1
            count -= bcount[cur & mask]
            bcount[cur & mask] = 0
            while node >= 0:
                nxt = pn[node]
                hn = heap_push(hk, hi, hn, pk[node], pi[node])
                pn[node] = free
                free = node
                nfree += 1
                node = nxt
        # room for one expansion's 8 pushes, made outside the inner loop (heap_reserve)
        hk, hi = heap_reserve(hk, hi, hn, 8)
        fk, fi = heap_reserve(fk, fi, fn, 8)
        pk, pi, pn = _pool_reserve(pk, pi, pn, top, nfree, 8)
        while (
            hn > 0
            and hn + 8 <= hk.size
            and fn + 8 <= fk.size
            and (nfree >= 8 or top + 8 <= pk.size)
        ):
            _, u = heap_pop(hk, hi, hn)
            hn -= 1
            if state[u] & CLOSED:
                continue
            state[u] |= CLOSED
            expansions += 1
            if u == t:
                return state, g, expansions, True
            m = relax_successors(
                surface,
                ridge,
                passable,
                a,
                u,
                g,
                state,
                sk,
                si,
                0,
                gr,
                gc,
                weight,
                off_weight,
                octile,
                lm,
                lg,
                shrink,
                hoff,
                hw,
            )
            for j in range(m):
                b = int((sk[j] - base) * inv)
                if b <= cur:
                    hn = heap_push(hk, hi, hn, sk[j], si[j])
                elif b < cur + BUCKETS:
                    free, top, nfree = _bucket_put(
                        pk, pi, pn, head, free, top, nfree, b & mask, sk[j], si[j]
                    )
                    bcount[b & mask] += 1
                    count += 1
                else:
                    fn = heap_push(fk, fi, fn, sk[j], si[j])
    return state, g, expansions, False


# searches of at most this many cells reuse arrays kept by their thread (search_arrays)
REUSED_CELLS = 2**21
REUSED_HEAP = 2**16
_ARRAYS = threading.local()


def search_arrays(n: int, reuse: bool = False) -> tuple:
    """``g``, ``state`` and the heap's first arrays for :func:`astar_search` on ``n`` cells:
    new ones, or with ``reuse`` (a caller done with the search's state before its thread's
    next search) the ones this thread keeps, grown as needed, for up to :data:`REUSED_CELLS`
    cells (a heap of :data:`REUSED_HEAP` entries). A new array's pages fault in as the search
    first touches them: 100-1200 faults, 0.1-1 ms, in each mission's coarse search on the
    1000^2 coarse level of a 2000^2 map (the search itself 0.1-4 ms)."""
    if not reuse or n > REUSED_CELLS:  # zeros: pages the search does not touch stay unmapped
        return np.empty(n), np.zeros(n, dtype=np.int8), np.empty(1024), np.empty(1024, np.int64)
    got = getattr(_ARRAYS, "arrays", None)
    if got is None or got[0].size < n:
        # written once here, so that later searches touch no page for the first time
        got = _ARRAYS.arrays = (
            np.full(n, 0.0),
            np.full(n, 0, np.int8),
            np.full(REUSED_HEAP, 0.0),
            np.full(REUSED_HEAP, 0, np.int64),
        )
    got[1][:n] = 0  # the last search's marks
    return got


# ``off_ridge_to_goal`` counts lengths in units of a / OFF_UNITS: a straight move OFF_UNITS
# units, a diagonal OFF_DIAGONAL = floor(OFF_UNITS sqrt 2) (41 / 29 = 1.41379, 0.03 % under
# sqrt 2), so that its search is Dial's bucket queue (integer lengths) instead of a heap
OFF_UNITS = 29
OFF_DIAGONAL = 41


@njit(nogil=True, cache=True)
def off_ridge_to_goal(ridge, passable, a, gr, gc, sr, sc):
    """Per cell (flat), a lower bound on the off-ridge length of any path from it to the goal
    (gr, gc): the least horizontal length of the moves that end off the ridge network, over
    the paths of the planners' graph, a diagonal move counted as ``OFF_DIAGONAL / OFF_UNITS``
    cells (just under sqrt 2; ``inf`` where the goal is out of reach). A move's 3-D length is
    at least that, so this bounds the Lagrangian cost's off-ridge term, consistently (it is a
    shortest distance). The lengths are whole units (a / ``OFF_UNITS``), so the search backwards
    from the goal is Dial's algorithm (:func:`_dial_to_goal`; 2.1 -> 1.0 ms on the benchmark's
    windows of 22000 cells, against a binary heap of exact lengths: its time is the moves it
    scans).

    With a start (sr, sc) in the window (``-1, -1``: none) the search stops once it has settled
    the start, and every cell's bound is the smaller of its distance and the start's: a cell not
    settled then is at least as far as the start, and the smaller of two consistent bounds is
    consistent. A search from the start needs no more; on the 2000^2 benchmark's Lagrangian
    sections the backward search took 330 instead of 475 us a window and its searches expanded
    1 % more cells; the same paths on 50 missions at 2000^2, 4000^2 and 10000^2.

    Its lengths are integers, turned into metres in place at the end, in the same buffer (the
    frame dropped). 0.77 -> 0.48 ms a window of the 2000^2 benchmark's Lagrangian sections,
    the same bounds bit for bit, in the same memory (9 bytes a cell)."""
    rows, cols = passable.shape
    w = cols + 2  # the framed grid's row
    stop = (sr + 1) * w + sc + 1 if 0 <= sr < rows and 0 <= sc < cols else -1
    d, reach, far = _dial_to_goal(ridge, passable, gr, gc, 0, 0, OFF_UNITS, OFF_DIAGONAL, stop)
    unit = a / OFF_UNITS * (1.0 - 1e-13)  # never above the length it bounds, after rounding
    out = d.view(np.float64)  # in place: cell v of the window is read from slot >= v first
    v = 0
    for r in range(rows):
        row = (r + 1) * w + 1
        for c in range(cols):
            dv = min(d[row + c], reach)  # reach: far unless the search stopped at the start
            out[v] = np.inf if dv == far else dv * unit
            v += 1
    return out[: rows * cols]


# :func:`lagrangian_bound` counts in whole units, each move's cost rounded down, the longest
# move BOUND_SPAN units: few buckets whatever the weight (the searches' weights went up to 4e5
# on the 10000^2 benchmark missions, median 12), a bound under the horizontal one by less than
# one unit a move. A straight move on the ridge network kept at least 64 units instead (1.6 %
# at most) cut the expansions of the weighted searches there from 604 to 437 a search, and
# made the bound's search 8x slower.
BOUND_SPAN = 400


@njit(nogil=True, cache=True)
def lagrangian_bound(ridge, passable, a, sr, sc, gr, gc, off_weight, hoff):
    """The heuristic of the Lagrangian search of weight ``off_weight`` from (sr, sc) to the goal
    (gr, gc), as :func:`astar_search` takes it in ``hoff`` (flat; with no landmark layers): per
    cell ``v``, ``(B(v) - octile(v)) / off_weight``, where ``B`` is the larger of

    - the least cost to the goal on the horizontal plane: every move costing its horizontal
      length (a diagonal ``41 / 29`` cells), times ``1 + off_weight`` when it ends off the ridge
      network, in whole units (Dial's search backwards from the goal, :func:`_dial_to_goal`,
      each move's cost rounded down); a move's 3-D cost is at least that. The search stops once
      it has settled the start: a cell it has not settled is at least as far as the start, so
      that distance bounds it (the smaller of two consistent bounds is consistent);
    - the octile distance plus ``off_weight`` times the off-ridge bound ``hoff``
      (:func:`off_ridge_to_goal`), a bound on each of the two terms of the cost.

    Both are consistent, hence their maximum; :func:`astar_search` adds
    ``(1 - 1e-9) off_weight`` times this to the octile distance, a mean of two consistent
    bounds. The first is the tighter where the shortest and the least off-ridge routes part
    (an obstacle, a ridge away from the straight line).

    It also serves a search of a smaller weight ``w``: ``octile + w x this`` is then the larger
    of ``octile + w x hoff`` and ``(w / off_weight) B1 + (1 - w / off_weight) octile``, with
    ``B1`` the first bound above: a mean of two consistent bounds on ``length + w off_ridge``
    (``B1`` bounds ``length + off_weight off_ridge``, the octile distance bounds ``length``).

    On the weighted searches of 20
    Lagrangian missions (omega 2) across the benchmarks' 10000^2 map, in one process, A*
    expanded 604 cells a search instead of 6173, and took with this search 1.04 ms instead of
    1.31 (2000^2: 1422 instead of 5997 cells, 1.21 ms instead of 1.38); the same paths, lengths
    and bounds on all 40 missions. Served to the searches of smaller weights too, it ran 65
    times a mission instead of 97 there, for 1293 expansions a search instead of 604: the
    bounds and searches 84.9-87.8 ms a mission instead of 99.0-99.5. The planner takes it only
    on gentle ground (``lagrangian.BOUND_SLACK``)."""
    rows, cols = passable.shape
    q = BOUND_SPAN / (OFF_DIAGONAL * (1.0 + off_weight))  # units a 1/OFF_UNITS cell
    s_on = np.int64(math.floor(OFF_UNITS * q))
    d_on = np.int64(math.floor(OFF_DIAGONAL * q))
    s_off = np.int64(math.floor(OFF_UNITS * q * (1.0 + off_weight)))
    d_off = np.int64(math.floor(OFF_DIAGONAL * q * (1.0 + off_weight)))
    w = cols + 2
    d, reach, far = _dial_to_goal(
        ridge, passable, gr, gc, s_on, d_on, s_off, d_off, (sr + 1) * w + sc + 1
    )
    unit = a / (OFF_UNITS * q) * (1.0 - 1e-12)
    out = np.empty(rows * cols)
    v = 0
    for r in range(rows):
        row = (r + 1) * w + 1
        for c in range(cols):
            dv = d[row + c]
            h = np.inf if dv == far and reach == far else min(dv, reach) * unit
            out[v] = _per_weight(h, heuristic(a, r, c, gr, gc, True), hoff[v], off_weight)
            v += 1
    return out


@njit(inline="always", cache=True)
def _per_weight(h, octile, hoff, off_weight):
    """A cell's entry of :func:`lagrangian_bound` from a bound ``h`` on its cost to the goal:
    the larger of ``h`` and ``octile + off_weight hoff``, less the octile distance, over the
    weight (0 where the octile distance is larger)."""
    b = octile + off_weight * hoff
    if b > h:
        h = b
    return (h - octile) / off_weight if h > octile else 0.0


@njit(nogil=True, cache=True)
def raised_bound(bound, hoff, w0, off_weight, rows, cols, gr, gc, a):
    """:func:`lagrangian_bound` of weight ``w0`` (``bound``) raised to a larger weight
    ``off_weight``, in the same form (per cell ``(B(v) - octile(v)) / off_weight``), without a
    search: ``B`` is the larger of

    - ``B0 + (off_weight - w0) hoff``, with ``B0 = octile + w0 bound`` the bound of weight
      ``w0`` on ``length + w0 off_ridge`` and ``hoff`` (:func:`off_ridge_to_goal`) one on
      ``off_ridge``: a path's cost of weight ``off_weight`` is the sum of those two terms, so
      the sum of their bounds bounds it, consistently (each is consistent on its own term);
    - the octile distance plus ``off_weight`` times ``hoff``, as in :func:`lagrangian_bound`.

    A pass over the window (19 us on the 2000^2 benchmark's windows of 15625 cells) instead of
    a search (440 us): the planner computes one bound a window, at twice its first weighted
    search's weight, and raises it for the larger weights that follow (``lagrangian.JOINT``)."""
    out = np.empty(rows * cols)
    rise = off_weight - w0
    v = 0
    for r in range(rows):
        for c in range(cols):
            octile = heuristic(a, r, c, gr, gc, True)
            out[v] = _per_weight(
                octile + w0 * bound[v] + rise * hoff[v], octile, hoff[v], off_weight
            )
            v += 1
    return out


@njit(nogil=True, cache=True)
def _dial_to_goal(ridge, passable, gr, gc, s_on, d_on, s_off, d_off, stop):
    """Dial's search backwards from the goal (gr, gc) over the planners' graph, a move into a
    cell costing ``s_on`` / ``d_on`` (straight / diagonal) on the ridge network and ``s_off`` /
    ``d_off`` off it, whole units: a circular array of buckets, one per distance modulo the
    longest move plus one, each a stack of cells. It runs on the window framed by one cell that
    is not passable, one byte a cell (passable, off the ridge network, settled), so that a move
    needs no bounds check. Returns the distances (framed, int64, ``far`` where not reached),
    the distance at which it settled the framed cell ``stop`` (where it stopped; ``far``: it
    ran to the end) and ``far``."""
    rows, cols = passable.shape
    w = cols + 2  # the framed grid's row
    flag = np.zeros((rows + 2) * w, dtype=np.uint8)  # 1 passable, 2 off the ridge, 4 settled
    for r in range(rows):
        row = (r + 1) * w + 1
        for c in range(cols):
            if passable[r, c]:
                flag[row + c] = 1 if ridge[r, c] else 3
    step = flat_offsets(w)  # to each neighbour, in the framed grid
    nb = max(s_on, d_on, s_off, d_off) + 1  # no two live distances share a bucket
    far = np.int64(2**62)  # not reached (yet)
    d = np.full(flag.size, far, dtype=np.int64)
    head = np.full(nb, -1, dtype=np.int64)  # per bucket, its last entry
    cells = np.empty(1024, dtype=np.int64)  # entries: a cell and the entry below it
    nxt = np.empty(1024, dtype=np.int64)
    t = (gr + 1) * w + gc + 1
    d[t] = 0
    cells[0] = t
    nxt[0] = -1
    head[0] = 0
    m = 1  # entries made
    live = 1  # entries not popped yet
    cur = 0  # the distance of the bucket being emptied
    b = 0  # its bucket: cur % nb
    while live > 0:
        cells, nxt = heap_reserve(cells, nxt, m, 8 * 64)  # two parallel arrays, as a heap's
        budget = 64  # cells settled in this pass: 8 entries each at most
        while live > 0 and budget > 0:
            e = head[b]
            if e < 0:
                cur += 1
                b = b + 1 if b + 1 < nb else 0
                continue
            head[b] = nxt[e]
            live -= 1
            x = cells[e]
            fx = flag[x]
            if fx & 4:
                continue  # settled already (an entry at a smaller distance came first)
            if x == stop:
                return d, cur, far
            flag[x] = fx | 4
            budget -= 1
            # a move into x costs by whether x is off the ridge network
            straight = s_off if fx & 2 else s_on
            diagonal = d_off if fx & 2 else d_on
            for k in range(8):  # p, a cell with a move p -> x (the moves are symmetric)
                p = x + step[k]
                if (flag[p] & 5) != 1:
                    continue  # not passable (the frame is not), or settled
                if k % 2 == 1:
                    if not (flag[x + DC[k]] & 1 and flag[x + DR[k] * w] & 1):
                        continue  # no corner cutting
                    nd = cur + diagonal
                else:
                    nd = cur + straight
                if nd < d[p]:
                    d[p] = nd
                    bp = b + (nd - cur)
                    if bp >= nb:
                        bp -= nb
                    cells[m] = p
                    nxt[m] = head[bp]
                    head[bp] = m
                    m += 1
                    live += 1
    return d, far, far


# --------------------------------------------------------------------------- validation


def nearest_passable(passable: np.ndarray, cell, origin=(0, 0)) -> tuple[int, int] | None:
    """The passable cell of ``passable`` nearest ``cell``, or None; ``passable`` may be a window
    whose first cell is ``origin`` (cells in and out are then in map coordinates)."""
    r, c = int(cell[0]) - origin[0], int(cell[1]) - origin[1]
    if 0 <= r < passable.shape[0] and 0 <= c < passable.shape[1] and passable[r, c]:
        return int(cell[0]), int(cell[1])  # itself, the only cell at distance 0
    idx = np.argwhere(passable)
    if idx.size == 0:
        return None
    d = ((idx + np.asarray(origin) - np.asarray(cell)) ** 2).sum(axis=1)
    r, c = idx[int(np.argmin(d))] + np.asarray(origin)
    return int(r), int(c)


def off_map_error(name: str, r: int, c: int, shape) -> InvalidEndpointError:
    return InvalidEndpointError(
        f"{name} ({r}, {c}) is off the map (rows 0..{shape[0] - 1}, cols 0..{shape[1] - 1})"
    )


# said where a maps store has no passable cell: the likeliest cause is a DEM of depths
NO_PASSABLE = (
    "no cell of the maps is passable: the DEM lies above the surface limit (sea level less "
    "the surface clearance) everywhere; if its values are depths, positive down, negate them "
    "(or give the variable the attribute positive = 'down') and build the maps again"
)


def not_passable_error(name: str, r: int, c: int, near, none_hint: str) -> InvalidEndpointError:
    hint = f"nearest passable cell: {near}" if near else none_hint
    return InvalidEndpointError(
        f"{name} ({r}, {c}) is on land or inside the clearance zone; {hint}"
    )


def check_endpoint(name: str, cell, passable: np.ndarray) -> tuple[int, int]:
    try:
        r, c = (int(v) for v in cell)
    except (TypeError, ValueError):
        raise InvalidParameterError(f"`{name}` must be a cell (row, col), got {cell!r}") from None
    rows, cols = passable.shape
    if not (0 <= r < rows and 0 <= c < cols):
        raise off_map_error(name, r, c, passable.shape)
    if not passable[r, c]:
        raise not_passable_error(name, r, c, nearest_passable(passable, (r, c)), NO_PASSABLE)
    return r, c


def check_arrays(surface, ridge, passable):
    surface = np.asarray(surface)
    if surface.dtype not in (np.float32, np.float64):  # float32 maps stay float32: no copy
        surface = surface.astype(np.float64)
    ridge = np.asarray(ridge, dtype=bool)
    passable = np.asarray(passable, dtype=bool)
    if surface.ndim != 2 or ridge.shape != surface.shape or passable.shape != surface.shape:
        raise InvalidParameterError(
            f"surface, ridge and passable must be 2-D arrays of one "
            f"shape; got {surface.shape}, {ridge.shape}, "
            f"{passable.shape}"
        )
    count, first = _unusable(surface, passable)
    if count:
        r, c = divmod(first, surface.shape[1])
        raise InvalidParameterError(
            f"the surface is NaN or infinite at passable cell "
            f"({r}, {c}) ({count} such cells); mark no-data "
            "cells impassable"
        )
    return surface, ridge, passable


@njit(nogil=True, cache=True)
def _unusable(surface, passable):
    """How many passable cells have a surface that is NaN or infinite, and the first of them
    (flat index, row-major; -1 for none): one pass, no temporaries (numpy's ``passable &
    ~isfinite(surface)`` made two window-sized arrays for every section)."""
    rows, cols = surface.shape
    count = 0
    for r in range(rows):
        for c in range(cols):
            x = surface[r, c]
            count += passable[r, c] and not (x - x == 0)  # x - x is NaN for NaN and inf
    if count == 0:
        return 0, -1
    for r in range(rows):
        for c in range(cols):
            x = surface[r, c]
            if passable[r, c] and not (x - x == 0):
                return count, r * cols + c
    return count, -1


@njit(cache=True)
def _trace(state, cols, gr, gc):
    n = 1
    r, c = gr, gc
    while state[r * cols + c] & PARENT:
        k = state[r * cols + c] & 7
        r -= DR[k]
        c -= DC[k]
        n += 1
    out = np.empty((n, 2), dtype=np.int64)
    r, c = gr, gc
    for i in range(n - 1, -1, -1):
        out[i, 0] = r
        out[i, 1] = c
        if i:
            k = state[r * cols + c] & 7
            r -= DR[k]
            c -= DC[k]
    return out


def trace_path(state: np.ndarray, cols: int, goal) -> np.ndarray:
    """The cells (k x 2) from the root of a search tree to ``goal``, read from the search state
    (per flat cell the move that entered it: one byte a cell, not eight for a predecessor)."""
    return _trace(state, cols, int(goal[0]), int(goal[1]))


def path_steps(cells: np.ndarray, z: np.ndarray, a: float) -> np.ndarray:
    """The 3-D length of every step of a path (step i ends at ``cells[i + 1]``), from its cells
    and the heights ``z`` of the surface along it: the one place path lengths are computed,
    ``sqrt(a^2 (dr^2 + dc^2) + dz^2)`` in float64 (in one kernel pass: numpy's seven array
    operations took 25 us a section)."""
    cells = np.asarray(cells, dtype=np.int64)
    return _steps(cells.reshape(-1, 2), np.asarray(z, dtype=np.float64).ravel(), float(a))


@njit(nogil=True, cache=True)
def _steps(cells, z, a):
    n = max(cells.shape[0] - 1, 0)
    out = np.empty(n)
    aa = a * a
    for i in range(n):
        dr = cells[i + 1, 0] - cells[i, 0]
        dc = cells[i + 1, 1] - cells[i, 1]
        dz = z[i + 1] - z[i]
        out[i] = math.sqrt(aa * (dr * dr + dc * dc) + dz * dz)
    return out


@njit(cache=True)
def _trace_measured(state, cols, gr, gc, surface, ridge, a, r0, c0):
    """:func:`_trace` and the path's heights (float64), ridge flags and steps (:func:`_steps`),
    and the steps that end on the ridge network, in one pass; the cells offset by (r0, c0).

    It keeps the GIL (a section's path: 5-30 us): in one process a helper thread reads the
    next windows meanwhile, and a kernel that lets the GIL go waits for it to come back, up to
    the switch interval (in turn, mission by mission, 30 missions at 10000^2 three and four
    times: the missions' fixed cost 0.4 and 0.8 ms lower)."""
    return _measured(_trace(state, cols, gr, gc), surface, ridge, a, r0, c0)


@njit(nogil=True, cache=True)
def _measured(cells, surface, ridge, a, r0, c0):
    """What :func:`_trace_measured` returns for a path's ``cells`` (written in place)."""
    n = cells.shape[0]
    z = np.empty(n)
    on = np.empty(n, dtype=np.bool_)
    for i in range(n):
        r, c = cells[i, 0], cells[i, 1]
        z[i] = surface[r, c]
        on[i] = ridge[r, c]
    steps = _steps(cells, z, a)
    k = 0
    for i in range(n - 1):
        k += on[i + 1]
    on_steps = np.empty(k)
    k = 0
    for i in range(n - 1):
        if on[i + 1]:
            on_steps[k] = steps[i]
            k += 1
    if r0 or c0:
        for i in range(n):
            cells[i, 0] += r0
            cells[i, 1] += c0
    return cells, z, on, steps, on_steps


def traced_path(state, cols: int, goal, surface, ridge, a: float, offset=(0, 0)):
    """The path to ``goal`` in a search state (:func:`trace_path`) with what a section keeps of
    it: ``(cells + offset, heights as float64, ridge flags, length, ridge length, ridge
    ratio)``, the metrics as :func:`path_metrics` computes them (the steps' sums by numpy, bit
    for bit the same). One kernel pass instead of the trace, two gathers, path_metrics' numpy
    calls, and a section's copy of its cells and heights: 21 -> 13 us a section of the
    10000^2 benchmark's missions (62 a mission), the same results on 80 missions (2000^2 and
    10000^2, ra_star and lagrangian: cells, points, lengths, bounds, bit for bit)."""
    cells, z, on, steps, on_steps = _trace_measured(
        state, cols, int(goal[0]), int(goal[1]), surface, ridge, float(a), *offset
    )
    return _summed(cells, z, on, steps, on_steps)


def measured_path(cells, surface, ridge, a: float, offset=(0, 0)):
    """:func:`traced_path` for a path given as its cells (k x 2, int64; offset in place)."""
    return _summed(*_measured(cells, surface, ridge, float(a), *offset))


def _summed(cells, z, on, steps, on_steps):
    if len(cells) < 2:
        return cells, z, on, 0.0, 0.0, 0.0
    length = float(steps.sum())
    ridge_len = float(on_steps.sum())
    return cells, z, on, length, ridge_len, ridge_len / length if length > 0 else 0.0


def path_metrics(cells: np.ndarray, z: np.ndarray, on_ridge: np.ndarray, a: float):
    """length, ridge length (steps whose end cell is a ridge cell), ridge ratio of a path with
    heights ``z`` and ridge flags ``on_ridge`` along it."""
    if len(cells) < 2:
        return 0.0, 0.0, 0.0
    step = path_steps(cells, z, a)
    length = float(step.sum())
    ridge_len = float(step[np.asarray(on_ridge, dtype=bool)[1:]].sum())
    return length, ridge_len, ridge_len / length if length > 0 else 0.0


# --------------------------------------------------------------------------- the registry's types


@dataclass(frozen=True)
class Search:
    """What a planner's search returns to :func:`pipeline.plan_window`."""

    state: np.ndarray | None  # the search state the path is traced from (``trace_path``)
    expansions: int
    found: bool
    lower_bound: Callable[[float], float]  # a proven lower bound on L*, given the path length
    extra: dict = field(default_factory=dict)
    cells: np.ndarray | None = None  # the path itself (k x 2), for a search without a state


@dataclass(frozen=True)
class Planner:
    """A planner of the registry: ``search(surface, ridge, passable, a, start, goal, omega,
    landmarks=None)`` returns a :class:`Search`; ``landmarks`` (k layers of landmark distances
    over the window) may strengthen its heuristic, never its result's bound."""

    name: str
    search: Callable[..., Search]
    summary: str
    uses_landmarks: bool = False  # whether ``landmarks`` serves its heuristic
    optimal: bool = False  # whether it returns a shortest path (omega plays no part)
