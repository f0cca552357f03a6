"""The horizontal route of a flight (docs/flyable-missions.md): any-angle shortcuts over usable
cells that keep the path's ridge cover, the route simplified, corners too close for the turn
radius cut, the rest rounded by arcs of the vehicle's turn radius, and the samples along it.
"""

from __future__ import annotations

import math

import numpy as np

from ..runtime.jit import njit
from ..runtime.threads import shared_pool

# the waypoint route may leave the shortcut path by up to a tolerance (cells) to skip small
# wiggles, its legs flying off the ridge cells for up to a share of their length more than the
# path: the first of these that leaves at most three quarters of the waypoints to corners, and
# never more than the last (the ridge cover then drops by about ten points at most, measured)
ROUTE_SIMPLIFICATIONS = ((2.0, 0.02), (2.0, 0.05), (3.0, 0.1), (4.0, 0.2), (4.0, 0.3))


_LEVELS = np.array(ROUTE_SIMPLIFICATIONS, dtype=np.float64)


# the flight's helpers called once a grid cell or sample are inlined in numba's own IR
# (``inline="always"``): called across compiled functions instead, the flight was measurably
# slower (CHANGELOG.md); elsewhere LLVM's inlining does as well and compiles in less time
@njit(inline="always", cache=True)
def _tile_of(i, t):
    """``i // t`` for ``0 <= i < 2^32``, ``t > 0`` (a row or column and the tiles' side): a
    32-bit unsigned division, which costs the flight's kernels several times less than
    Python's 64-bit floor division (with its sign fix-up)."""
    return np.int64(np.uint32(i) // np.uint32(t))


@njit(inline="always", cache=True)
def _cell(slot, tiles, tr, tc, i, j, missing):
    if i < 0 or j < 0:  # (a 32-bit division of a negative row would index far off the table)
        return missing
    ti = _tile_of(i, tr)
    tj = _tile_of(j, tc)
    s = slot[ti, tj]
    if s < 0:
        return missing
    return tiles[s, i - ti * tr, j - tj * tc]


@njit(cache=True, _nrt=False)
def _usable(pas, slot, tr, tc, rows, cols, pad, i, j):
    """Passable, and the terrain known within ``pad`` cells (its tiles are loaded).

    Compiled on its own (``_nrt=False``: it allocates nothing), not inlined: :func:`_walk`
    calls it three times, and numba's inlining typed its body at each call, for each of the
    walk's two signatures: the walk compiles in half the time on a new machine, and ``fly``
    takes the same time."""
    if i < 0 or j < 0 or i >= rows or j >= cols:
        return False
    ti = _tile_of(i, tr)
    tj = _tile_of(j, tc)
    s = slot[ti, tj]
    ri = i - ti * tr
    rj = j - tj * tc
    if s < 0 or not pas[s, ri, rj]:
        return False
    if pad <= ri < tr - pad and pad <= rj < tc - pad:
        return True  # the cells within pad all lie in this tile (most cells: 4 lookups saved)
    i0 = max(i - pad, 0)
    i1 = min(i + pad, rows - 1)
    j0 = max(j - pad, 0)
    j1 = min(j + pad, cols - 1)
    return (
        slot[_tile_of(i0, tr), _tile_of(j0, tc)] >= 0
        and slot[_tile_of(i0, tr), _tile_of(j1, tc)] >= 0
        and slot[_tile_of(i1, tr), _tile_of(j0, tc)] >= 0
        and slot[_tile_of(i1, tr), _tile_of(j1, tc)] >= 0
    )


@njit(inline="always", cache=True)
def _samples(dr, dc):
    """How many pieces a segment of ``dr`` rows and ``dc`` columns is walked in: 4 a cell along
    its longer side (one count for :func:`_walk` and :func:`_off_ridge`, so that
    :func:`leg_allowed` measures the off-ridge length as :func:`_off_ridge` does)."""
    return max(1, int(math.ceil(max(abs(dr), abs(dc)) * 4.0)))


@njit(cache=True, _nrt=False)
def _walk(pas, rdg, slot, tr, tc, rows, cols, pad, ar, ac, br, bc, most, rate, count):
    """``(ok, off)``: whether the straight segment between two points (grid units: row, col)
    crosses only usable cells, without cutting a corner between two cells it passes diagonally
    (samples 4 a cell), and, with ``count``, its off-ridge length (:func:`_off_ridge`'s samples,
    in turn with those) stays at most ``most`` and at most ``rate`` times its length; ``off``
    the off-ridge length summed so far. It stops at the first unusable cell or once the
    off-ridge length so far is over a limit (it only grows, and is compared after every piece,
    the last included: with infinite limits the walk sums it all, and ``ok and not (off >
    most or off / length > rate)`` is then the answer for any limits)."""
    dr = br - ar
    dc = bc - ac
    n = _samples(dr, dc)
    ln = math.hypot(dr, dc)
    piece = ln / n
    seg = 0.0
    pi = -(10**9)
    pj = -(10**9)
    poi = -(10**9)  # the cell of the last off-ridge sample, and whether it is off the ridge
    poj = -(10**9)
    off = True
    for k in range(n + 1):
        t = k / n
        i = int(math.floor(ar + t * dr + 0.5))
        j = int(math.floor(ac + t * dc + 0.5))
        if i != pi or j != pj:
            if not _usable(pas, slot, tr, tc, rows, cols, pad, i, j):
                return False, seg
            if k > 0 and i != pi and j != pj:
                if not (
                    _usable(pas, slot, tr, tc, rows, cols, pad, pi, j)
                    and _usable(pas, slot, tr, tc, rows, cols, pad, i, pj)
                ):
                    return False, seg
            pi = i
            pj = j
        if k == n or not count:
            continue
        oi, oj = _off_point(ar, ac, dr, dc, k, n)
        if oi != poi or oj != poj:  # the ridge looked up once a cell, not once a piece
            off = _off_cell(rdg, slot, tr, tc, oi, oj)
            poi = oi
            poj = oj
        if not off:
            continue
        seg += piece
        if seg > most or seg / ln > rate:
            return False, seg
    return True, seg


@njit(inline="always", cache=True)
def _off_point(ar, ac, dr, dc, k, n):
    """The cell of the middle of the ``k``-th of ``n`` pieces of a segment."""
    t = (k + 0.5) / n
    return int(math.floor(ar + t * dr + 0.5)), int(math.floor(ac + t * dc + 0.5))


@njit(cache=True, _nrt=False)
def _off_cell(rdg, slot, tr, tc, i, j):
    """Whether cell ``(i, j)`` lies off the ridge cells (or off the loaded tiles). Compiled on
    its own without reference counting (``_nrt=False``): inlined, the arrays it takes cost the
    shortcuts' walk 1.6x its time."""
    if i < 0 or j < 0 or i >= slot.shape[0] * tr or j >= slot.shape[1] * tc:
        return True
    return not _cell(slot, rdg, tr, tc, i, j, 0)


@njit(cache=True, nogil=True)
def _line_usable(pas, slot, tr, tc, rows, cols, pad, ar, ac, br, bc):
    """Whether the straight segment between two points (grid units: row, col) crosses only
    usable cells, without cutting a corner between two cells it passes diagonally."""
    return _walk(pas, pas, slot, tr, tc, rows, cols, pad, ar, ac, br, bc, np.inf, np.inf, False)[0]


@njit(cache=True, nogil=True)
def _off_ridge(rdg, slot, tr, tc, ar, ac, br, bc):
    """The length (grid units) of the straight segment lying over cells that are not ridge."""
    dr = br - ar
    dc = bc - ac
    n = _samples(dr, dc)
    piece = math.hypot(dr, dc) / n
    off = 0.0
    for k in range(n):
        if _off_cell(rdg, slot, tr, tc, *_off_point(ar, ac, dr, dc, k, n)):
            off += piece
    return off


# a shortcut gives up at most this share of the ridge share of the path it replaces (so that
# on a path with little ridge the allowance ``share`` does not take what there is)
RIDGE_SLACK = 0.1


@njit(inline="always", cache=True)
def _leg_limits(off, along, i, j, ln, share, slack):
    """``(most, rate)``: the off-ridge length and share a leg of length ``ln`` from vertex ``i``
    to ``j`` may fly (``off``, ``along``: the path's, :func:`_polyline_off_ridge`): the path's
    own, plus half a cell and ``share`` of the leg but no more than ``slack`` (a share) of the
    path's ridge length there, at a share of the leg no more than the path's plus ``share``
    but at most ``slack`` of the path's ridge share (``slack`` inf: no such cap)."""
    path = off[j] - off[i]
    span = along[j] - along[i]
    rate = path / span
    most = path + min(0.5 + share * ln, slack * max(span - path, 0.0))
    return most, rate + min(share, slack * max(1.0 - rate, 0.0))


@njit(inline="always", cache=True)
def leg_allowed(
    pr, pc, off, along, i, j, pas, rdg, slot, tr, tc, rows, cols, pad, share=0.02,
    slack=RIDGE_SLACK,
):  # fmt: skip
    """Whether the straight leg from vertex ``i`` to ``j`` crosses only usable cells
    (:func:`_line_usable`) and flies no more off the ridge cells (:func:`_off_ridge`) than the
    path between them (half a cell of slack, more with a larger ``share``), nor an off-ridge
    share larger by more than ``share``: one walk along the leg (:func:`_walk`), which stops
    at the first unusable cell or once the off-ridge length is over a limit, sooner than the
    two functions when the answer is no (most probes of a leg too long)."""
    ln = math.hypot(pr[j] - pr[i], pc[j] - pc[i])
    most, rate = _leg_limits(off, along, i, j, ln, share, slack)
    ar, ac, br, bc = pr[i], pc[i], pr[j], pc[j]
    return _walk(pas, rdg, slot, tr, tc, rows, cols, pad, ar, ac, br, bc, most, rate, True)[0]


@njit(cache=True, nogil=True)
def _shortcuts(pr, pc, off, along, pas, rdg, slot, tr, tc, rows, cols, pad, max_leg, slack):
    """Indices of the vertices kept by string pulling: from each kept vertex, the farthest
    later one (probed at doubling steps, then refined) reached by a usable straight leg that
    flies no more off the ridge cells than the path between them does (``off``: the path's
    off-ridge length up to each vertex, grid units; :func:`_leg_limits`'s slack, ``slack``
    its cap: ``RIDGE_SLACK``, or inf for none)."""
    n = pr.size
    keep = np.empty(n, dtype=np.int64)
    m = 0
    keep[m] = 0
    m += 1
    i = 0
    while i < n - 1:
        best = i + 1
        step = 1
        fails = 0
        nxt = n - 1
        while True:
            j = min(i + step, n - 1)
            if j - i > max_leg:
                nxt = j
                break
            if leg_allowed(
                pr, pc, off, along, i, j, pas, rdg, slot, tr, tc, rows, cols, pad, 0.02, slack
            ):
                best = j
                nxt = min(i + 2 * step, n - 1)
            else:
                fails += 1
                if fails >= 3:
                    break
            if j == n - 1:
                break
            step *= 2
        lo = best
        hi = max(nxt, best)
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if mid - i <= max_leg and leg_allowed(
                pr, pc, off, along, i, mid, pas, rdg, slot, tr, tc, rows, cols, pad, 0.02, slack
            ):
                lo = mid
            else:
                hi = mid
        i = lo
        keep[m] = i
        m += 1
    return keep[:m]


@njit(cache=True, nogil=True)
def _arcs_radii(wr, wc, radius):
    """The radius of the arc at each corner (inf where straight) and ``tan(theta / 2)``."""
    m = wr.size
    tan_d = np.zeros(m)  # tangent length at each corner
    rad = np.full(m, np.inf)
    half = np.zeros(m)  # tan(theta / 2) at each corner
    for k in range(1, m - 1):
        ur = wr[k] - wr[k - 1]
        uc = wc[k] - wc[k - 1]
        vr = wr[k + 1] - wr[k]
        vc = wc[k + 1] - wc[k]
        cosang = (ur * vr + uc * vc) / (math.hypot(ur, uc) * math.hypot(vr, vc))
        theta = math.acos(min(1.0, max(-1.0, cosang)))
        if theta >= 1e-9:
            half[k] = math.tan(theta / 2.0)
    # each leg shared by two corners: both arcs at full radius when their tangent lengths fit
    # in it, else both shrunk in proportion
    scale = np.ones(m)
    for k in range(m - 1):
        need = radius * (half[k] + half[k + 1])
        ln = math.hypot(wr[k + 1] - wr[k], wc[k + 1] - wc[k])
        if need > ln:
            f = ln / need
            scale[k] = min(scale[k], f)
            scale[k + 1] = min(scale[k + 1], f)
    for k in range(1, m - 1):
        if half[k] > 0:
            rad[k] = radius * scale[k]
            tan_d[k] = rad[k] * half[k]
    return tan_d, rad


def arc_sagitta(radii: np.ndarray, step: float) -> float:
    """How far (grid units) the arcs of :func:`arcs` (``radii``: as it returns them) lie at
    most outside the polyline through their samples: an arc of radius ``r`` is sampled in
    pieces of at most ``step`` along it, so a piece's angle is at most ``step / r`` (and half
    a turn) and the arc lies at most ``r (1 - cos(angle / 2))`` from its chord."""
    r = radii[np.isfinite(radii) & (radii > 0)]
    if not r.size:
        return 0.0
    half = np.minimum(step / (2.0 * r), math.pi / 2.0)
    return float(np.max(r * (1.0 - np.cos(half))))


@njit(cache=True, nogil=True)
def arcs(wr, wc, radius, step):
    """Dense samples (grid units) of the polyline ``w`` with every corner rounded by an arc of
    ``radius`` (grid units; narrower where two corners share a leg too short for both).
    Returns rows, cols, the leg of each sample (-1 on an arc), the radius used at each corner
    (inf where straight) and the tangent lengths."""
    m = wr.size
    tan_d, rad = _arcs_radii(wr, wc, radius)
    total = 2
    for k in range(m - 1):
        total += int(math.ceil(math.hypot(wr[k + 1] - wr[k], wc[k + 1] - wc[k]) / step)) + 2
        if rad[k] < np.inf:
            total += int(math.ceil(rad[k] * math.pi / step)) + 2
    outr = np.empty(total)
    outc = np.empty(total)
    leg = np.empty(total, dtype=np.int64)
    n = 0
    for k in range(m - 1):
        lr = wr[k + 1] - wr[k]
        lc = wc[k + 1] - wc[k]
        ln = math.hypot(lr, lc)
        ur = lr / ln
        uc = lc / ln
        a0 = tan_d[k]
        a1 = ln - tan_d[k + 1]
        ns = max(1, int(math.ceil((a1 - a0) / step)))
        for q in range(ns):
            t = a0 + (a1 - a0) * q / ns
            outr[n] = wr[k] + ur * t
            outc[n] = wc[k] + uc * t
            leg[n] = k
            n += 1
        kk = k + 1
        if kk < m - 1 and rad[kk] < np.inf:
            # arc from the tangent point on leg k to the one on leg k + 1
            vr = wr[kk + 1] - wr[kk]
            vc = wc[kk + 1] - wc[kk]
            lv = math.hypot(vr, vc)
            vr /= lv
            vc /= lv
            t1r = wr[kk] - ur * tan_d[kk]
            t1c = wc[kk] - uc * tan_d[kk]
            cross = ur * vc - uc * vr
            side = 1.0 if cross > 0 else -1.0
            # normal of leg k towards the inside of the turn
            nr = -uc * side
            nc = ur * side
            r = rad[kk]
            cr = t1r + nr * r
            cc = t1c + nc * r
            a_start = math.atan2(t1c - cc, t1r - cr)
            theta = math.acos(min(1.0, max(-1.0, ur * vr + uc * vc)))
            na = max(1, int(math.ceil(r * theta / step)))
            for q in range(na):
                ang = a_start + side * theta * q / na
                outr[n] = cr + r * math.cos(ang)
                outc[n] = cc + r * math.sin(ang)
                leg[n] = -1
                n += 1
    outr[n] = wr[m - 1]
    outc[n] = wc[m - 1]
    leg[n] = m - 1
    n += 1
    return outr[:n], outc[:n], leg[:n], rad, tan_d


@njit(cache=True)
def _fill_route(
    rows, cols, shared, vi, wr, wc, u, ln, tan_d, head, own, tail, order, starts, pr, pc
):
    """``_route_samples``' legs: each the new samples from its first corner to where its arc
    meets it, the track's straight samples, the new samples to its last corner."""
    for k in range(wr.size - 1):
        o = vi[k]
        for q in range(head[k]):
            t = q / head[k] * tan_d[k]
            rows[o + q] = wr[k] + u[k, 0] * t
            cols[o + q] = wc[k] + u[k, 1] * t
        o += head[k]
        for q in range(own[k]):
            idx = order[starts[k] + q]
            rows[o + q] = pr[idx]
            cols[o + q] = pc[idx]
            shared[o + q] = idx
        o += own[k]
        for q in range(tail[k]):
            t = ln[k] - tan_d[k + 1] + q / tail[k] * tan_d[k + 1]
            rows[o + q] = wr[k] + u[k, 0] * t
            cols[o + q] = wc[k] + u[k, 1] * t


def _route_samples(wr, wc, pr, pc, leg, tan_d, step):
    """Samples of the straight legs between the corners ``w`` that share the flown track's
    samples where the two coincide (a leg's straight part between its arcs); the rest (from a
    corner to where its arc leaves the legs) sampled anew. Returns rows, cols, the track sample
    each shares (-1: new) and each corner's sample index."""
    m = len(wr)
    u = np.column_stack([np.diff(wr), np.diff(wc)])
    ln = np.hypot(u[:, 0], u[:, 1])
    u /= ln[:, None]
    head = np.ceil(tan_d[:-1] / step).astype(np.int64)  # corner k -> where its arc meets leg k
    tail = np.ceil(tan_d[1:] / step).astype(np.int64)  # where arc k + 1 leaves leg k -> corner
    tail[-1] = 0
    order = np.argsort(leg, kind="stable")  # the straight samples of each leg, in order
    legs_sorted = leg[order]
    starts = np.searchsorted(legs_sorted, np.arange(m))
    own = np.diff(starts)[: m - 1]  # straight samples per leg
    count = head + own + tail
    vi = np.concatenate(([0], np.cumsum(count)))
    n = int(vi[-1]) + 1
    rows, cols = np.empty(n), np.empty(n)
    shared = np.full(n, -1, dtype=np.int64)
    _fill_route(
        rows, cols, shared, vi, wr, wc, u, ln, tan_d, head, own, tail, order, starts, pr, pc
    )
    rows[-1], cols[-1] = wr[-1], wc[-1]
    shared[-1] = len(pr) - 1
    return rows, cols, shared, vi


@njit(cache=True, nogil=True)
def _polyline_off_ridge(wr, wc, ridge, rdg, slot, tr, tc):
    """The off-ridge length and the length of the polyline ``w`` up to each corner (grid
    units); without ``ridge`` an off-ridge length no leg can exceed (no ridge rule)."""
    n = wr.size
    off = np.zeros(n)
    along = np.zeros(n)
    for k in range(1, n):
        along[k] = along[k - 1] + math.hypot(wr[k] - wr[k - 1], wc[k] - wc[k - 1])
        if ridge:
            off[k] = off[k - 1] + _off_ridge(rdg, slot, tr, tc, wr[k - 1], wc[k - 1], wr[k], wc[k])
        else:
            off[k] = 2.0 * along[k]
    return off, along


@njit(cache=True, nogil=True)
def ridge_share(rdg, slot, tr, tc, pr, pc) -> float:
    """The share of the polyline ``(pr, pc)`` (grid units) whose length lies over ridge cells,
    each segment walked as :func:`_off_ridge` walks a leg (the rule the shortcuts and the route
    keep); 1 for a polyline of no length."""
    off = 0.0
    along = 0.0
    for k in range(1, pr.size):
        along += math.hypot(pr[k] - pr[k - 1], pc[k] - pc[k - 1])
        off += _off_ridge(rdg, slot, tr, tc, pr[k - 1], pc[k - 1], pr[k], pc[k])
    return 1.0 - off / along if along > 0 else 1.0


# legs of up to this many corners are walked once for all the route's simplifications
# (:func:`_route_vertices`): the levels probe mostly the same short legs
ROUTE_CACHED_LEG = 8


@njit(cache=True, nogil=True)
def _route_vertices(wr, wc, off, along, levels, enough, rdg, pas, slot, tr, tc, rows, cols, pad):
    """Indices of the corners kept for the waypoint route: greedy, each leg the longest usable
    one that passes within ``tol`` (grid units) of every corner it skips and flies no more off
    the ridge cells than the legs it replaces but for ``share`` of its length (as the
    shortcuts do; ``off``, ``along``: ``_polyline_off_ridge``). ``levels``: ``(tol, share)``
    rows, tried in turn until one keeps at most ``enough`` corners (else the last one's). A leg
    is walked to its end (:func:`_walk` without limits) and each level's limits compared with
    its whole off-ridge length, which is what the early-stopping walk decides; the legs of up
    to ``ROUTE_CACHED_LEG`` corners are walked once for every level, not anew at each."""
    n = wr.size
    cap = ROUTE_CACHED_LEG
    known = np.zeros((n, cap), dtype=np.uint8)  # 0 not walked, 1 usable, 2 not
    offs = np.empty((n, cap))
    keep = np.empty(n, dtype=np.int64)
    m = 0
    for li in range(levels.shape[0]):
        tol = levels[li, 0]
        share = levels[li, 1]
        m = 0
        keep[m] = 0
        m += 1
        i = 0
        while i < n - 1:
            j = i + 1
            while j + 1 < n:
                c = j + 1
                dr = wr[c] - wr[i]
                dc = wc[c] - wc[i]
                ln = math.hypot(dr, dc)
                ok = ln > 0.0
                for q in range(i + 1, c):
                    if not ok:
                        break
                    t = ((wr[q] - wr[i]) * dr + (wc[q] - wc[i]) * dc) / (ln * ln)
                    t = min(1.0, max(0.0, t))
                    if math.hypot(wr[i] + t * dr - wr[q], wc[i] + t * dc - wc[q]) > tol:
                        ok = False
                if ok:  # leg_allowed, from the leg's one walk (kept for the next levels)
                    d = c - i - 1
                    if d >= cap or known[i, d] == 0:
                        usable, seg = _walk(
                            pas, rdg, slot, tr, tc, rows, cols, pad,
                            wr[i], wc[i], wr[c], wc[c], np.inf, np.inf, True,
                        )  # fmt: skip
                        if d < cap:
                            known[i, d] = 1 if usable else 2
                            offs[i, d] = seg
                    else:
                        usable, seg = known[i, d] == 1, offs[i, d]
                    most, rate = _leg_limits(off, along, i, c, ln, share, np.inf)
                    ok = usable and not (seg > most or seg / ln > rate)
                if not ok:
                    break
                j = c
            i = j
            keep[m] = i
            m += 1
        if m <= enough:
            break
    return keep[:m]


def _corner_vertices(cells: np.ndarray) -> np.ndarray:
    """Indices of the path's cells where its direction changes (and both ends)."""
    if len(cells) <= 2:
        return np.arange(len(cells))
    d = np.diff(cells, axis=0)
    turn = np.any(d[1:] != d[:-1], axis=1)
    return np.concatenate(([0], np.nonzero(turn)[0] + 1, [len(cells) - 1]))


class Corridor:
    """The store chunks (elevation, passable, ridge) around a path, as stacked tiles with a
    slot table, so that the kernels read the terrain near the track and nothing else.

    The passable and ridge tiles are read here; the elevation tiles, which only the heights
    need, are decoded by the pool's threads meanwhile and waited for by :meth:`grid`: the
    shortcuts and the route, which need the others only, are computed in the meantime (the
    elevation is most of a corridor's bytes)."""

    def __init__(self, m, cells: np.ndarray, pad: int):
        from ..store.cache import CACHE

        rows, cols = m.shape
        tr, tc = (int(v) for v in CACHE.array(m.path, "elevation").chunks)
        self.tr, self.tc, self.rows, self.cols = tr, tc, rows, cols
        nti, ntj = -(-rows // tr), -(-cols // tc)
        want = np.zeros((nti, ntj), dtype=bool)
        r, c = cells[:, 0].astype(np.int64), cells[:, 1].astype(np.int64)
        steps = range(-pad, pad + 1, max(1, min(tr, tc) - 1))
        offs = sorted(set(list(steps) + [pad]))
        for dr in offs:
            for dc in offs:
                rr = np.clip(r + dr, 0, rows - 1) // tr
                cc = np.clip(c + dc, 0, cols - 1) // tc
                want[rr, cc] = True
        ti, tj = np.nonzero(want)
        self.slot = np.full((nti, ntj), -1, dtype=np.int64)
        self.slot[ti, tj] = np.arange(len(ti))
        complete = m.all_chunks_written
        self._el = np.empty((len(ti), tr, tc), dtype=np.float32)
        self.pas = np.empty((len(ti), tr, tc), dtype=np.uint8)
        self.rdg = np.empty((len(ti), tr, tc), dtype=np.uint8)

        def load(job):
            k, i, j, var, dst, fill = job
            # decoded into the tile (the chunks a planning process holds are copied from it)
            h, w = CACHE.chunk_into(m.path, var, i, j, dst[k], complete=complete)
            dst[k, h:, :] = fill  # a tile at the map's edge: the rest is no terrain
            dst[k, :h, w:] = fill

        def jobs(var, dst, fill):
            tiles = zip(ti.tolist(), tj.tolist(), strict=True)
            return [(k, i, j, var, dst, fill) for k, (i, j) in enumerate(tiles)]

        # decoding releases the GIL: read the chunks a few at a time
        pool = shared_pool("corridor", 4)
        first = jobs("passable", self.pas, 0) + jobs("ridge", self.rdg, 0)
        first = [pool.submit(load, x) for x in first]
        self._elevation = [pool.submit(load, x) for x in jobs("elevation", self._el, np.nan)]
        try:
            for f in first:
                f.result()
            if m.keep_out is not None:  # its cells removed (pipeline.constraints.store)
                for k, (i, j) in enumerate(zip(ti.tolist(), tj.tolist(), strict=True)):
                    r0, c0 = i * tr, j * tc
                    r1, c1 = min(r0 + tr, rows), min(c0 + tc, cols)
                    self.pas[k, : r1 - r0, : c1 - c0] &= ~m.removed(r0, r1, c0, c1)
        except BaseException:
            for f in first + self._elevation:
                f.cancel()
            for f in self._elevation:
                if not f.cancelled():
                    f.exception()  # waits: no decoding left running behind the error
            raise
        self.tiles = len(ti)
        # the highest grid point of blocks of squares, for the flight's own clearance check
        # (pipeline.flight.profile.clearance_blocks), made when it first runs
        self.check_blocks = None

    def grid(self) -> tuple:
        """``(elevation tiles, slot, tr, tc, rows, cols)``, the elevation read by then."""
        pending, self._elevation = self._elevation, []
        errors = [f.exception() for f in pending]
        if any(errors):
            raise next(e for e in errors if e is not None)
        return self._el, self.slot, self.tr, self.tc, self.rows, self.cols

    @property
    def el(self) -> np.ndarray:
        """The elevation tiles (waits for their decoding)."""
        return self.grid()[0]


@njit(cache=True)
def _lookup(tiles, slot, tr, tc, r, c):
    out = np.zeros(r.size, dtype=np.uint8)
    for k in range(r.size):
        out[k] = _cell(slot, tiles, tr, tc, r[k], c[k], 0)
    return out


def widen_turns(wr, wc, radius, usable, passes: int = 8):
    """Remove corners too close together for the turn radius where a straight leg between
    their neighbours is usable (an out-and-back spur, two short zigzags), tightest first."""
    wr, wc = _distinct(np.asarray(wr, dtype=np.float64), np.asarray(wc, dtype=np.float64))
    for _ in range(passes):
        if len(wr) <= 2:
            break
        rad = _arcs_radii(wr, wc, radius)[1]
        tight = np.nonzero(_too_tight(rad, radius))[0]
        if tight.size == 0:
            break
        drop = _cut_corners(wr, wc, tight[np.argsort(rad[tight])], *usable)
        if not drop.any():
            break
        wr, wc = _distinct(wr[~drop], wc[~drop])
    return wr, wc


@njit(cache=True, nogil=True)
def _cut_corners(wr, wc, order, pas, slot, tr, tc, rows, cols, pad):
    """Which corners ``widen_turns`` drops, taken in ``order`` (the tightest first): a corner
    whose neighbours are both kept, where the straight leg between those is usable."""
    drop = np.zeros(wr.size, dtype=np.bool_)
    for k in order:
        if drop[k - 1] or drop[k + 1] or drop[k]:
            continue
        ar, ac, br, bc = wr[k - 1], wc[k - 1], wr[k + 1], wc[k + 1]
        if _line_usable(pas, slot, tr, tc, rows, cols, pad, ar, ac, br, bc):
            drop[k] = True
    return drop


def _tight_turns(wr, wc, radius) -> int:
    """How many corners of the polyline turn tighter than ``radius`` (grid units)."""
    if len(wr) <= 2:
        return 0
    return int(np.sum(_too_tight(_arcs_radii(wr, wc, radius)[1], radius)))


def _too_tight(radii, radius):
    """Which turn radii are below ``radius`` (beyond rounding)."""
    return radii < radius * (1 - 1e-9)


def _distinct(wr, wc):
    """The polyline without repeated consecutive vertices (an out-and-back spur cut at its
    tip returns to where it left)."""
    keep = np.ones(len(wr), dtype=bool)
    keep[1:] = (np.diff(wr) != 0) | (np.diff(wc) != 0)
    return wr[keep], wc[keep]


def _path_off_ridge(cells: np.ndarray, cor: Corridor) -> np.ndarray:
    """The path's off-ridge horizontal length up to each cell, and its horizontal length
    (grid units): each move counted by halves at its two cells, as ``_off_ridge`` counts a
    straight leg."""
    on = _lookup(cor.rdg, cor.slot, cor.tr, cor.tc, cells[:, 0], cells[:, 1]).astype(bool)
    step = np.hypot(*np.diff(cells, axis=0).T.astype(np.float64))
    half = 0.5 * step
    move = half * ~on[:-1] + half * ~on[1:]
    return np.concatenate(([0.0], np.cumsum(move))), np.concatenate(([0.0], np.cumsum(step)))
