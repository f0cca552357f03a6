"""RA* (the paper's Algorithms 1-2) as the focal search docs/method.md section 5 makes precise.

- OPEN_cost is plain A* (``f = g + h``, its own ``g`` and best predecessor); its smallest
  ``f``, ``f_min``, never decreases and is a lower bound on the optimum ``L*``.
- The ridge search keeps its own record per state: ``g_incons`` (the length of its path so
  far), ``Nor`` (ridge cells on that path) and predecessor. OPEN_nor is split into FOCAL, the
  admissible states (``g_incons + h < limit``, ``limit = omega * f_min``) ordered by the largest
  ``Nor``, then the smallest ``f_incons = g_incons + h``, and WAIT, the others ordered by
  ``f_incons``; as ``f_min`` grows, WAIT states move to FOCAL (the admissible set only grows).
  The paper leaves ties of ``Nor`` open. Taking the least ``g_incons`` among them (as this
  module once did) floods every state of equal ``Nor`` nearer the start than the goal, as
  Dijkstra does; the least ``f_incons`` heads for the goal between ridge cells, as A* does.
  On the MCPC missions of the benchmarks that took 4.8-6.3x fewer expansions and gave more
  ridge at a shorter length (docs/method.md section 5).
- Each iteration expands the FOCAL top if there is one (and, when it is also the OPEN_cost top,
  performs the A* expansion too), else the OPEN_cost top.
- The ridge search relaxes a successor when ``g_incons(s) + c(s, s') < limit`` (the paper's
  test, with ``g_incons`` where it prints ``g``) and the successor is new to the ridge search or
  its ``Nor`` improves (on a tie, a smaller ``g_incons`` wins). Each state is expanded at most
  once by the ridge search (CLOSE_nor), and a record changes only while the state has not been
  expanded, i.e. has no children: the ridge tree stays a tree, the returned path is simple and
  its length is exactly the ``g_incons`` that was checked against the limit.

Guarantee: a path returned by the ridge search has ``length = g_incons(goal) < omega * f_min <=
omega * L*``; one returned by OPEN_cost is optimal. With ``omega = 1`` nothing is ever strictly
below the limit, so RA* is A*.
"""

from __future__ import annotations

import numpy as np

from ..runtime.jit import njit
from .base import Planner, Search
from .grid import DC, DR
from .heap import heap_pop, heap_push, heap_reserve
from .search import CLOSED, INWAIT, PARENT, SEEN, edge_cost, heuristic, relax_successors


@njit(cache=True)
def _focal_key(nor, f, gscale):
    # largest Nor first; among equals the smallest f_incons = g_incons + h (f / gscale < 1)
    return -np.float64(nor) + f / gscale


@njit(nogil=True, cache=True)
def _ra_star(surface, ridge, passable, a, sr, sc, gr, gc, omega):
    rows, cols = surface.shape
    n = rows * cols
    s = sr * cols + sc
    # status returned: 0 unreachable, 1 goal expanded by A* (optimal path, st_cost),
    # 2 goal expanded by the ridge search (st_nor); the states as in ``grid.PARENT``
    t = gr * cols + gc
    # A* (OPEN_cost)
    g = np.empty(n)
    st_cost = np.zeros(n, dtype=np.int8)
    ck = np.empty(1024)
    ci = np.empty(1024, dtype=np.int64)
    cn = 0
    # ridge search (OPEN_nor = FOCAL + WAIT)
    gi = np.empty(n)
    nor = np.empty(n, dtype=np.int32)
    st_nor = np.zeros(n, dtype=np.int8)  # a ridge record exists where PARENT or SEEN
    fk = np.empty(1024)
    fi = np.empty(1024, dtype=np.int64)
    fn = 0
    wk = np.empty(1024)
    wi = np.empty(1024, dtype=np.int64)
    wn = 0
    h0 = heuristic(a, sr, sc, gr, gc, False)
    gscale = 1e6 * (h0 + a) * (1.0 + omega) + 1.0  # > any f_incons that can pass the limit
    g[s] = 0.0
    st_cost[s] = SEEN
    cn = heap_push(ck, ci, cn, h0, s)
    gi[s] = 0.0
    nor[s] = 0
    st_nor[s] = SEEN
    f_min = h0
    limit = omega * f_min
    if h0 < limit:
        fn = heap_push(fk, fi, fn, _focal_key(0, h0, gscale), s)
    else:
        wn = heap_push(wk, wi, wn, h0, s)
        st_nor[s] |= INWAIT
    expansions = 0
    while True:  # makes room in the heaps; the inner loop never reassigns them (heap_reserve)
        # one pass of the inner loop pushes at most 8 entries to OPEN_cost, moves WAIT entries
        # (each to FOCAL or back to WAIT) and pushes at most 8 to FOCAL or WAIT
        ck, ci = heap_reserve(ck, ci, cn, 8)
        fk, fi = heap_reserve(fk, fi, fn, wn + 8)
        wk, wi = heap_reserve(wk, wi, wn, 8)
        while cn + 8 <= ck.size and fn + wn + 8 <= fk.size and wn + 8 <= wk.size:
            # the OPEN_cost top (drop stale entries) gives f_min and the limit
            top = -1
            while cn > 0:
                u = ci[0]
                if st_cost[u] & CLOSED or ck[0] != g[u] + heuristic(
                    a, u // cols, u % cols, gr, gc, False
                ):
                    heap_pop(ck, ci, cn)
                    cn -= 1
                    continue
                top = u
                if ck[0] > f_min:
                    f_min = ck[0]
                break
            limit = omega * f_min
            # WAIT states that the grown limit admits move to FOCAL
            while wn > 0 and wk[0] < limit:
                _, v = heap_pop(wk, wi, wn)
                wn -= 1
                st_nor[v] &= ~INWAIT
                if st_nor[v] & CLOSED:
                    continue
                fv = gi[v] + heuristic(a, v // cols, v % cols, gr, gc, False)
                if fv < limit:
                    fn = heap_push(fk, fi, fn, _focal_key(nor[v], fv, gscale), v)
                else:  # the record changed while it waited: wait again under its own key
                    wn = heap_push(wk, wi, wn, fv, v)
                    st_nor[v] |= INWAIT
            # the FOCAL top (drop stale entries)
            pick = -1
            while fn > 0:
                v = fi[0]
                if st_nor[v] & CLOSED or fk[0] != _focal_key(
                    nor[v], gi[v] + heuristic(a, v // cols, v % cols, gr, gc, False), gscale
                ):
                    heap_pop(fk, fi, fn)
                    fn -= 1
                    continue
                pick = v
                break
            if pick < 0 and top < 0:
                return st_cost, st_nor, expansions, 0, f_min  # nothing left: unreachable
            if pick >= 0:
                heap_pop(fk, fi, fn)
                fn -= 1
                st_nor[pick] |= CLOSED
                expansions += 1
                if pick == t:
                    return st_cost, st_nor, expansions, 2, f_min
                r = pick // cols
                c = pick - r * cols
                gp = gi[pick]
                np_ = nor[pick]
                for k in range(8):
                    nr = r + DR[k]
                    nc = c + DC[k]
                    if nr < 0 or nr >= rows or nc < 0 or nc >= cols:
                        continue
                    v = nr * cols + nc
                    sv = st_nor[v]
                    if sv & CLOSED or not passable[nr, nc]:
                        continue
                    if k % 2 == 1 and not (passable[r, nc] and passable[nr, c]):
                        continue  # no corner cutting
                    ng = gp + edge_cost(surface, a, r, c, nr, nc)
                    if ng >= limit:
                        continue
                    nn = np_ + (1 if ridge[nr, nc] else 0)
                    if sv & (PARENT | SEEN) and not (nn > nor[v] or (nn == nor[v] and ng < gi[v])):
                        continue
                    # INWAIT: the state has a WAIT entry no later than its record (an early one
                    # rereads the record when it pops), so a record that waits longer needs no
                    # push. A record that goes to FOCAL clears it: the entries still in WAIT may
                    # then be later than a later record of the state, which must push its own
                    early = (sv & INWAIT) != 0 and ng >= gi[v]
                    gi[v] = ng
                    nor[v] = nn
                    hv = heuristic(a, nr, nc, gr, gc, False)
                    if ng + hv < limit:
                        st_nor[v] = PARENT | k
                        fn = heap_push(fk, fi, fn, _focal_key(nn, ng + hv, gscale), v)
                        continue
                    st_nor[v] = (sv & INWAIT) | PARENT | k
                    if not early:
                        wn = heap_push(wk, wi, wn, ng + hv, v)
                        st_nor[v] |= INWAIT
                if pick != top:
                    continue
                # the picked state is also the OPEN_cost top: do the A* update as well
            u = top
            heap_pop(ck, ci, cn)
            cn -= 1
            st_cost[u] |= CLOSED
            if pick < 0:
                expansions += 1
            if u == t:
                return st_cost, st_nor, expansions, 1, f_min
            cn = relax_successors(
                surface, ridge, passable, a, u, g, st_cost, ck, ci, cn, gr, gc, 1.0, 0.0, False
            )


def _search(surface, ridge, passable, a, s, t, omega, landmarks=None) -> Search:
    # the landmark bound is not used: RA*'s two lists keep the straight-line heuristic
    # (docs/method.md section 4)
    st_cost, st_nor, expansions, status, f_min = _ra_star(
        surface, ridge, passable, a, s[0], s[1], t[0], t[1], float(omega)
    )
    # status 2: the ridge search reached the goal (length < omega f_min); 1: A* did (optimal)
    return Search(
        st_nor if status == 2 else st_cost,
        expansions,
        status > 0,
        lambda length: min(f_min, length),
    )


RA_STAR = Planner("ra_star", _search, "the paper's RA*: most ridge first within omega * f_min")
