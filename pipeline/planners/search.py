"""The grid search every planner shares (docs/method.md section 4): the graph, the edge cost,
the heuristic (with landmark distances where a window has them), the search state, and A*'s
relaxation and search (a binary heap, or buckets on large windows).

Graph: 8-connected over passable cells; a diagonal move only when both orthogonal cells it
passes between are passable (no corner cutting). Edge cost: the 3-D length along the safety
surface ``sqrt(a^2 (dr^2 + dc^2) + (S(q) - S(p))^2)``; heuristic: the horizontal straight-line
distance to the goal (admissible and consistent, since every edge is at least as long as its
horizontal projection).
"""

from __future__ import annotations

import math
import threading

import numpy as np

from ..exceptions import InvalidParameterError
from ..runtime.jit import njit
from .grid import DC, DR
from .heap import grown, heap_pop, heap_push, heap_reserve


@njit(cache=True)
def edge_length(h2, dz):
    """The 3-D length of a move: ``h2`` its squared horizontal length, ``dz`` its rise."""
    return math.sqrt(h2 + dz * dz)


@njit(cache=True)
def edge_cost(surface, a, r, c, nr, nc):
    """The cost of the move (r, c) -> (nr, nc): its 3-D length along the surface."""
    dr = nr - r
    dc = nc - c
    dz = np.float64(surface[nr, nc]) - np.float64(surface[r, c])
    return edge_length(a * a * (dr * dr + dc * dc), dz)


# ties in f go to the state nearer the goal: the heap key is g + weight * (1 + TIE) * h. A* with
# it is weighted A* of weight 1 + TIE, so its path is within a factor 1 + TIE of the optimum
TIE = 1e-10


@njit(cache=True)
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


@njit(cache=True)
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
    updates on every expansion, and A* took a quarter longer (CHANGELOG.md,
    "Measurements")."""
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
    cache by, so every new process compiled the search again (seconds).
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
    map's open list holds a million entries, a heap of them misses the caches at every level:
    faster on whole 10000^2 maps, no faster at 4000^2 (CHANGELOG.md, "Measurements"): hence
    only from :data:`BUCKET_CELLS`; with the successors pushed inline instead of through
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
    first touches them, which took as long as a small coarse search itself."""
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
