"""Proven lower bounds on the shortest safe path that the planners and the certificate use
(docs/certified-bound.md): the Lagrangian planner's off-ridge distances to the goal and its
bound, raised by the exact distances where the search did not settle them.
"""

from __future__ import annotations

import math

import numpy as np

from ..runtime.jit import njit
from .grid import DC, DR, flat_offsets, inside
from .heap import grown, heap_reserve
from .search import LANDMARK_MARGIN, edge_length, heuristic
from .sweep import (
    FIXED_UNREACHED,
    METRES,
    cell_error,
    fixed_units,
    flat_mask,
    grid_shape,
    height_at,
    lowered,
    passable_flat,
    whole_units,
)

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
    from the goal is Dial's algorithm (:func:`_dial_to_goal`: its time is the moves it scans,
    about half a binary heap's of exact lengths; CHANGELOG.md, "Measurements").

    With a start (sr, sc) in the window (``-1, -1``: none) the search stops once it has settled
    the start, and every cell's bound is the smaller of its distance and the start's: a cell not
    settled then is at least as far as the start, and the smaller of two consistent bounds is
    consistent. A search from the start needs no more: the backward search is shorter, its
    searches expand hardly more cells, and the paths are the same (CHANGELOG.md,
    "Measurements").

    Its lengths are integers, turned into metres in place at the end, in the same buffer (the
    frame dropped): faster, the same bounds bit for bit, in the same memory (9 bytes a
    cell)."""
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
# move BOUND_SPAN units: few buckets whatever the weight (weights span orders of magnitude on
# the benchmark missions), a bound under the horizontal one by less than one unit a move. A
# floor on a straight move on the ridge network cut the weighted searches' expansions by a
# quarter but made the bound's search many times slower (CHANGELOG.md, "Measurements").
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

    On the benchmark missions' weighted searches it cuts A*'s expansions about tenfold and,
    served to the searches of smaller weights too, the time of the bounds and searches by a
    sixth, with the same paths, lengths and bounds (CHANGELOG.md, "Measurements"). The planner
    takes it only on gentle ground (``lagrangian.BOUND_SLACK``)."""
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


@njit(cache=True)
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

    A pass over the window instead of a search (over twenty times faster): the planner computes
    one bound a window, at twice its first weighted search's weight, and raises it for the
    larger weights that follow (``lagrangian.JOINT``)."""
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


@njit(nogil=True, cache=True)
def dijkstra(surface, passable, a, sources):
    """Exact shortest path lengths (float64, ``inf`` where unreached) from the cells
    ``sources`` (flat indices, distance 0) to every cell, on the planners' graph
    (:func:`_dijkstra_into`)."""
    rows, cols = surface.shape
    dist = np.full(rows * cols, np.inf)
    _dijkstra_into(surface, passable, a, METRES, sources, dist)
    return dist.reshape(rows, cols)


@njit(nogil=True, cache=True)
def fixed_point_dijkstra(surface, a, source, bits):
    """The distances of :func:`~.planners.sweep.fixed_point_distances` (whole units of ``a *
    2^-bits``, uint32) by :func:`_dijkstra_into`, for a map where the sweeps give up: from the
    cell ``source`` of ``surface`` (quantised, :func:`quantised`; or float32 with NaN on its
    impassable cells). The same values (both are the one solution of ``D(v) = min(cap, min_u
    D(u) + c'(u, v))`` in integers), in 5 bytes a cell besides the surface."""
    rows, cols = grid_shape(surface)
    dist = np.full(rows * cols, FIXED_UNREACHED, dtype=np.uint32)
    units, u = fixed_units(a, bits)
    start = np.array([source[0] * cols + source[1]], dtype=np.int64)
    _dijkstra_into(surface, surface, units, u, start, dist)
    return dist.reshape(rows, cols)


@njit(nogil=True, cache=True)
def _dijkstra_into(surface, passable, a, un, sources, dist):
    """Shortest path lengths from the cells ``sources`` (flat indices, distance 0) into
    ``dist`` (flat, all not reached), in the units ``un`` of the row sweeps
    (:data:`~.planners.sweep.METRES`: float64 metres; the fixed point of
    :func:`~.planners.sweep.fixed_point_distances`: each move's cost rounded down to whole
    units, values held at the cap); ``passable`` a mask, or the surface with NaN on its
    impassable cells.

    A bucket queue (Dial's algorithm with buckets narrower than the shortest edge, ``a``): a
    cell taken from the lowest bucket cannot be improved by any other cell of that bucket, so
    its distance is final, as in Dijkstra's algorithm, at O(1) a queue operation. The buckets
    are circular, as many as the longest edge spans; each is a contiguous array of cells
    (entries made stale by a later improvement are skipped when taken), so that the wavefront
    is read and written in order. An edge costs its 3-D length along the surface, as the
    planners' ``edge_cost`` (``edge_length`` of the same squared horizontal length and rise)."""
    rows, cols = grid_shape(surface)
    n = rows * cols
    okf = flat_mask(passable)
    done = np.zeros(n, dtype=np.bool_)
    lo = np.inf
    hi = -np.inf
    for i in range(n):
        if passable_flat(okf, i):
            r = i // cols
            z = height_at(surface, r, i - r * cols) * un[0]
            lo = min(lo, z)
            hi = max(hi, z)
    w = a * (1.0 - 1e-7)
    longest = math.sqrt(2.0 * a * a + (hi - lo) ** 2) if hi >= lo else a
    nb = int(longest / w) + 2
    # each bucket's array made when a cell first goes into it: with a relief of many cells'
    # lengths most buckets stay empty (30 x 40 cells of 2 cm and 17.7 km of relief: 884,000
    # buckets, 7 GB of arrays made up front)
    cap = np.zeros(nb, dtype=np.int64)
    fill = np.zeros(nb, dtype=np.int64)
    buckets = [np.empty(0, dtype=np.int64) for _ in range(nb)]
    off = flat_offsets(cols)
    h2 = np.empty(8)  # each move's squared horizontal length, as edge_cost computes it
    for k in range(8):
        h2[k] = a * a * (DR[k] * DR[k] + DC[k] * DC[k])
    queued = 0
    for s in sources:
        dist[s] = 0.0
        bk = buckets[0]
        if fill[0] == cap[0]:
            cap[0] = max(2 * cap[0], 1024)
            bk = grown(bk, fill[0], cap[0])
            buckets[0] = bk
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
            du = np.float64(dist[u])
            r = u // cols
            c = u - r * cols
            zu = height_at(surface, r, c) * un[0]
            inner = 0 < r < rows - 1 and 0 < c < cols - 1
            for k in range(8):
                if not inner and not inside(r, c, k, rows, cols):
                    continue
                v = u + off[k]
                if done[v] or not passable_flat(okf, v):
                    continue
                if k & 1 and not (
                    passable_flat(okf, u + DC[k]) and passable_flat(okf, u + DR[k] * cols)
                ):
                    continue  # no corner cutting
                vr = r + DR[k]
                vc = c + DC[k]
                zv = height_at(surface, vr, vc) * un[0]
                # the planners' edge (its rise lowered on a Quantised surface)
                loss = (cell_error(surface, r, c) + cell_error(surface, vr, vc)) * un[0]
                nd = du + whole_units(edge_length(h2[k], lowered(zv - zu, loss, surface)), dist)
                if nd < dist[v]:
                    dist[v] = min(nd, un[1])
                    b = max(int(nd / w), cur) % nb
                    if fill[b] == cap[b]:
                        cap[b] = max(2 * cap[b], 1024)
                        buckets[b] = grown(buckets[b], fill[b], cap[b])
                    buckets[b][fill[b]] = v
                    fill[b] += 1
                    queued += 1
        fill[cb] = 0
        cur += 1


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
    b = np.abs(ds[both] - dg[both]) - LANDMARK_MARGIN * (ds[both] + dg[both])
    return float(max(b.max(), 0.0))
