"""The vertical profile of a flight (docs/flyable-missions.md): the lowest height that keeps the
clearance of the maps' method from the continuous (bilinear) seabed along the route, the
pitch-limited profile over it, the waypoints' band and the breaks kept a turn radius apart,
and the check of the flown track against the seabed.
"""

from __future__ import annotations

import math

import numpy as np

from ..runtime.jit import njit
from ..runtime.threads import shared_pool
from .geometry import _cell, _tile_of

# the flown track and the waypoint legs are sampled (and checked) every SAMPLE_STEP cells at
# most, closer where the clearance is small against the cell (CLEARANCE_SLACK)
SAMPLE_STEP = 0.5


CLEARANCE_SLACK = 2e-3


# the profile's breaks are kept this share beyond a turn radius apart, so that the legs stay
# at least a turn radius long as their files write them (coordinates rounded)
LEG_MARGIN = 0.01


# the maps' clearance methods, as the kernels know them


# (the helpers below called once a sample are inlined in numba's IR: see flight.geometry)
@njit(inline="always", cache=True)
def _least_term(p, lo, hi, a):
    """The least ``(i - p)^2 a^2`` over the grid lines ``lo..hi``, computed as each line's own
    term is (the terms grow with the distance on either side of ``p``: the least is next to
    it)."""
    near = min(max(int(math.floor(p + 0.5)), lo), hi)
    least = (near - p) * (near - p) * a * a
    for i in range(max(near - 1, lo), min(near + 1, hi) + 1):
        least = min(least, (i - p) * (i - p) * a * a)
    return least


# required_heights reads the corridor's elevation in square blocks of up to this side (a divisor
# of the tiles' side), each with its highest value: a block whose highest value cannot raise
# the height found so far is passed over unread (measured on the 10000^2 benchmark missions)
HEIGHT_BLOCK = 4


@njit(inline="always", cache=True)
def _dome(d2, rr, reach):
    """How far above a grid point ``sqrt(d2)`` away a sphere of squared radius ``rr`` must be
    to clear the grid square (at most ``reach`` from the point) the point is the highest
    corner of: ``sqrt(rr - max(0, d - reach)^2)``, 0 beyond the sphere (monotone in ``d2``)."""
    d = max(math.sqrt(d2) - reach, 0.0)
    return math.sqrt(max(rr - d * d, 0.0))


@njit(cache=True, nogil=True)
def required_heights(
    el, slot, tr, tc, rows, cols, pr, pc, a, radius, method, clearance, reach, partial
):
    """The lowest height at each point (grid units) that keeps the clearance from the
    continuous seabed (bilinear between the DEM's grid points), conservatively: the seabed over
    a grid square is at most its highest corner, and a point of the square is at least ``d -
    reach`` (metres) from ``p`` for a corner ``d`` away (``reach``: the square's diagonal, more
    for the methods that cover the step between samples). Spherical (``radius`` the
    clearance): ``max z(q) + sqrt(radius^2 - max(0, d - reach)^2)`` over the grid points ``q``
    within ``radius + reach``; horizontal and vertical: ``max z(q) + clearance`` within
    ``radius + reach`` (docs/method.md section 2). NaN where the terrain it needs is unknown: a
    no-data grid point within ``radius + reach - a sqrt(2)`` (the reach without the squares'
    diagonal; within ``radius + reach`` for the vertical method, whose squares are under the
    point), or a grid point within reach not loaded; ``-inf`` where no grid point is near
    enough. Where only the squares around a no-data grid point farther away come that close,
    the seabed there is unknown but no grid point the planner kept the clearance from: the
    height keeps the clearance from the known squares, and ``partial`` (a uint8 array of one
    flag a point, or empty) marks the point.

    Exactly the maximum over every grid point within reach: the grid points are taken in
    blocks (``HEIGHT_BLOCK``), and a block is read only when its highest elevation, at the
    block's least distance, could exceed the best value so far (computed with the same floating
    point operations as each point's own value, which are monotone: so a block passed over
    holds no larger value), or when it holds unknown elevation; the best value starts at the
    previous point's highest grid point, usually near the answer."""
    n = pr.size
    out = np.empty(n)
    spherical = method == 2
    rr = radius * radius  # the clearance's square (spherical)
    far = radius + reach  # the farthest grid point that can constrain a point
    r2 = far * far
    rc = far / a
    # an unknown grid point within this makes the height unknown; farther, one whose grid
    # squares come within the reach less the squares' diagonal (which the highest-corner bound
    # adds) marks the point partly unknown
    unknown = max(far - a * math.sqrt(2.0), 0.0)
    unknown2 = unknown * unknown
    missing2 = r2 if method == 0 else unknown2
    flags = partial.size > 0
    b = HEIGHT_BLOCK
    while b > 1 and (tr % b or tc % b):
        b //= 2
    nbr = tr // b
    nbc = tc // b
    bs = 0  # b is a power of two: divisions by it are shifts
    while (1 << bs) < b:
        bs += 1
    top = np.empty((el.shape[0], nbr, nbc), dtype=np.float64)  # a block's highest elevation
    seen = np.zeros((el.shape[0], nbr, nbc), dtype=np.uint8)
    colterm = np.empty(int(2 * rc) // b + 3)  # per block column: its least column term,
    coltile = np.empty(colterm.size, dtype=np.int64)  # its tile column, its block in the tile
    colblock = np.empty(colterm.size, dtype=np.int64)
    cap = radius if spherical else 0.0
    mi = -1  # the previous point's highest grid point
    mj = -1
    for k in range(n):
        p = pr[k]
        q = pc[k]
        best = -np.inf
        bad = False
        ilo = max(0, int(math.ceil(p - rc)))
        ihi = min(rows - 1, int(math.floor(p + rc)))
        jlo = max(0, int(math.ceil(q - rc)))
        jhi = min(cols - 1, int(math.floor(q + rc)))
        if mi >= 0:
            d2 = (mi - p) * (mi - p) * a * a + (mj - q) * (mj - q) * a * a
            if d2 <= r2:
                z = np.float64(_cell(slot, el, tr, tc, mi, mj, np.nan))
                if z == z:
                    best = z + _dome(d2, rr, reach) if spherical else z
        bj0 = jlo >> bs
        nbj = (jhi >> bs) + 1 - bj0
        for bj in range(bj0, bj0 + nbj):  # each block column's least column term
            colterm[bj - bj0] = _least_term(q, max(bj * b, jlo), min(bj * b + b - 1, jhi), a)
            t = _tile_of(bj * b, tc)  # (32-bit divisions: a 64-bit one costs several times more)
            coltile[bj - bj0] = t
            colblock[bj - bj0] = (bj * b - t * tc) >> bs
        for bi in range(ilo >> bs, (ihi >> bs) + 1):
            i0 = max(bi * b, ilo)
            i1 = min(bi * b + b - 1, ihi)
            di2 = _least_term(p, i0, i1, a)
            ti = _tile_of(bi * b, tr)
            lbi = (bi * b - ti * tr) >> bs
            for bj in range(bj0, bj0 + nbj):
                dj2 = colterm[bj - bj0]
                if di2 + dj2 > r2:
                    continue  # no grid point of the block is within the radius
                j0 = max(bj * b, jlo)
                j1 = min(bj * b + b - 1, jhi)
                s = slot[ti, coltile[bj - bj0]]
                if s >= 0:
                    lbj = colblock[bj - bj0]
                    if not seen[s, lbi, lbj]:
                        hi = -np.inf
                        r0 = bi * b - ti * tr
                        c0 = bj * b - coltile[bj - bj0] * tc
                        for ii in range(r0, r0 + b):
                            for jj in range(c0, c0 + b):
                                z = np.float64(el[s, ii, jj])
                                if z != z:
                                    hi = np.nan
                                    break
                                if z > hi:
                                    hi = z
                            if hi != hi:
                                break
                        top[s, lbi, lbj] = hi
                        seen[s, lbi, lbj] = 1
                    hi = top[s, lbi, lbj]
                    if hi == hi:  # no unknown elevation in the block
                        if hi + cap <= best:  # cap: no block's square root is larger
                            continue
                        if spherical and hi + _dome(di2 + dj2, rr, reach) <= best:
                            continue
                if s < 0:  # its tile is not loaded: the grid point within reach is unknown
                    bad = True
                    break
                # the block lies in one tile: its cells by their place in it (no division)
                oi = -ti * tr
                oj = -coltile[bj - bj0] * tc
                for i in range(i0, i1 + 1):
                    ri2 = (i - p) * (i - p) * a * a
                    for j in range(j0, j1 + 1):
                        d2 = ri2 + (j - q) * (j - q) * a * a
                        if d2 > r2:
                            continue
                        z = np.float64(el[s, i + oi, j + oj])
                        if z != z:
                            if d2 < missing2:
                                bad = True
                                break
                            # the seabed of the four squares around it is unknown
                            bi2 = max(abs(i - p) - 1.0, 0.0) * a
                            bj2 = max(abs(j - q) - 1.0, 0.0) * a
                            if flags and bi2 * bi2 + bj2 * bj2 < unknown2:
                                partial[k] = 1
                            continue
                        v = z + _dome(d2, rr, reach) if spherical else z
                        if v > best:
                            best = v
                            mi = i
                            mj = j
                    if bad:
                        break
                if bad:
                    break
            if bad:
                break
        out[k] = _height(bad, best, spherical, clearance)
    return out


# where the clearance is under FINE_BELOW cells the required heights bound the seabed over
# parts of each grid square (:func:`required_heights_fine`): the highest corner of a whole
# square raises a height by up to the square's rise, which on a coarse grid is a good part of
# the clearance (on real bathymetry at 150 m cells, R = 100 m: shallow straits no longer
# passable under the surface limit)
FINE_BELOW = 4.0


FINE_MOST = 8


def subdivisions(a: float, clearance: float) -> int:
    """Parts a grid square's side is cut in for the required heights: 1 (the whole square,
    :func:`required_heights`) where the clearance is at least ``FINE_BELOW`` cells, else
    enough for parts of at most an eighth of the clearance, at most ``FINE_MOST``."""
    if clearance >= FINE_BELOW * a:
        return 1
    return int(min(FINE_MOST, max(2, math.ceil(8.0 * a / clearance))))


@njit(cache=True, nogil=True)
def required_heights_fine(
    el, slot, tr, tc, rows, cols, pr, pc, a, radius, method, clearance, extra, k, partial
):
    """:func:`required_heights` with each grid square cut into ``k`` x ``k`` parts: the
    bilinear seabed over a part is at most the highest of its four corners (bilinear values),
    and a part lies exactly its box distance from the point. Spherical: ``max Z + sqrt(radius^2
    - d^2)`` over the parts less than ``radius`` away; horizontal and vertical: ``max Z +
    clearance`` over the parts less than ``radius + extra`` away (``extra``: the step between
    samples). A square whose highest corner cannot beat the best so far is passed over. NaN
    where a no-data corner lies within the reach (the vertical method: of the point's own
    square too) or a tile within reach is not loaded; a square with a no-data corner farther
    only flags the point in ``partial`` (a uint8 array, or empty)."""
    n = pr.size
    out = np.empty(n)
    spherical = method == 2
    lim = radius + (0.0 if spherical else extra)
    lim2 = lim * lim
    rr = radius * radius
    missing = lim + (a * math.sqrt(2.0) if method == 0 else 0.0)
    missing2 = missing * missing
    flags = partial.size > 0
    span = missing / a
    # no square or part yet: typed int64, so that numba compiles _parts_max once (not also
    # for the literal -1 while it types these variables)
    none = np.int64(-1)
    mi = none  # the previous point's highest square, and its highest part there
    mj = none
    mu = none
    mv = none
    stack = np.empty((64, 4), dtype=np.int64)
    for s in range(n):
        p = pr[s]
        q = pc[s]
        best = -np.inf
        bad = False
        first_i = -1
        first_j = -1
        if mi >= 0:  # the previous point's highest square first: most others then pass
            z00, z01, z10, z11 = _corners(slot, el, tr, tc, mi, mj, np.inf)
            if np.isfinite(z00 + z01 + z10 + z11):
                best, mu, mv = _parts_max(
                    z00, z01, z10, z11, mi, mj, p, q, a, k, lim2, rr, spherical, best, stack,
                    mu, mv,
                )  # fmt: skip
                first_i = mi
                first_j = mj
        i0 = max(0, int(math.floor(p - span)) - 1)
        i1 = min(rows - 2, int(math.floor(p + span)) + 1)
        j0 = max(0, int(math.floor(q - span)) - 1)
        j1 = min(cols - 2, int(math.floor(q + span)) + 1)
        for i in range(i0, i1 + 1):
            di = max(0.0, i - p, p - (i + 1)) * a
            if di * di >= max(lim2, missing2):
                continue
            for j in range(j0, j1 + 1):
                dj = max(0.0, j - q, q - (j + 1)) * a
                d2 = di * di + dj * dj
                if d2 >= max(lim2, missing2):
                    continue
                z00, z01, z10, z11 = _corners(slot, el, tr, tc, i, j, np.inf)
                if np.inf in (z00, z01, z10, z11):
                    bad = True  # a tile not loaded
                    break
                if z00 != z00 or z01 != z01 or z10 != z10 or z11 != z11:
                    # a no-data corner: unknown within the clearance, else noted
                    for ci in range(i, i + 2):
                        for cj in range(j, j + 2):
                            z = _cell(slot, el, tr, tc, ci, cj, np.inf)
                            if z == z:
                                continue
                            dc2 = ((ci - p) * (ci - p) + (cj - q) * (cj - q)) * a * a
                            if dc2 < missing2:
                                bad = True
                            elif flags and d2 < lim2:
                                partial[s] = 1
                    if bad:
                        break
                    continue
                if d2 >= lim2:
                    continue
                top = max(z00, z01, z10, z11)
                if top + (math.sqrt(rr - d2) if spherical else 0.0) <= best:
                    continue  # no part of the square can raise the height
                if i == first_i and j == first_j:
                    continue  # measured first
                v, u, w = _parts_max(
                    z00, z01, z10, z11, i, j, p, q, a, k, lim2, rr, spherical, best, stack,
                    none, none,
                )  # fmt: skip
                if v > best:
                    best = v
                    mi = i
                    mj = j
                    mu = u
                    mv = w
            if bad:
                break
        out[s] = _height(bad, best, spherical, clearance)
    return out


@njit(inline="always", cache=True)
def _corners(slot, el, tr, tc, i, j, missing):
    """The four corners of grid square ``(i, j)``: ``(i, j)``, ``(i, j + 1)``, ``(i + 1,
    j)``, ``(i + 1, j + 1)`` (``missing`` where a tile is not loaded)."""
    return (
        np.float64(_cell(slot, el, tr, tc, i, j, missing)),
        np.float64(_cell(slot, el, tr, tc, i, j + 1, missing)),
        np.float64(_cell(slot, el, tr, tc, i + 1, j, missing)),
        np.float64(_cell(slot, el, tr, tc, i + 1, j + 1, missing)),
    )


@njit(inline="always", cache=True)
def _height(bad, best, spherical, clearance):
    """A point's required height from the best value found: NaN where the terrain it needs is
    unknown, the value itself (spherical, or no constraint), else the value plus the
    clearance."""
    if bad:
        return np.nan
    if spherical or best == -np.inf:
        return best
    return best + clearance


@njit(inline="always", cache=True)
def _part_bound(z00, z01, z10, z11, i, j, p, q, a, inv, u0, u1, v0, v1, lim2, rr, spherical):
    """The highest value the parts ``u0..u1-1`` x ``v0..v1-1`` of square ``(i, j)`` can give
    the point ``(p, q)``: the highest bilinear corner of the rectangle they make (a bilinear
    surface is highest at a corner of any rectangle), plus the sphere's rise at the
    rectangle's box distance (spherical); ``-inf`` where it lies ``sqrt(lim2)`` or farther."""
    a0 = u0 * inv
    a1 = u1 * inv
    b0 = v0 * inv
    b1 = v1 * inv
    du = max(0.0, i + a0 - p, p - (i + a1)) * a
    dv = max(0.0, j + b0 - q, q - (j + b1)) * a
    e2 = du * du + dv * dv
    if e2 >= lim2:
        return -np.inf
    zm = max(
        _bilin(z00, z01, z10, z11, a0, b0),
        _bilin(z00, z01, z10, z11, a0, b1),
        _bilin(z00, z01, z10, z11, a1, b0),
        _bilin(z00, z01, z10, z11, a1, b1),
    )
    return zm + (math.sqrt(rr - e2) if spherical else 0.0)


@njit(cache=True, nogil=True)
def _parts_max(z00, z01, z10, z11, i, j, p, q, a, k, lim2, rr, spherical, best, stack, hu, hv):
    """The highest of ``best`` and the values over the ``k`` x ``k`` parts of square ``(i,
    j)`` (corners ``z``) less than ``sqrt(lim2)`` from ``(p, q)``: a part's highest bilinear
    corner, plus the sphere's rise at its box distance (spherical); and the part that gave it
    (``-1, -1`` where none beat ``best``). Branch and bound: the part ``(hu, hv)`` first (the
    previous point's best, when given), then the square halved until single parts, a block of
    parts passed over where its bound (:func:`_part_bound`, at least the value of each of its
    parts) cannot beat the best; the result is that of every part measured. ``stack``: scratch
    rows ``(u0, u1, v0, v1)``, at least ``4 log2(k) + 4``."""
    inv = 1.0 / k
    bu = -1
    bv = -1
    if hu >= 0:
        v = _part_bound(
            z00, z01, z10, z11, i, j, p, q, a, inv, hu, hu + 1, hv, hv + 1, lim2, rr, spherical
        )
        if v > best:
            best = v
            bu = hu
            bv = hv
    stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3] = 0, k, 0, k
    top = 1
    while top > 0:
        top -= 1
        u0, u1, v0, v1 = stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3]
        bound = _part_bound(
            z00, z01, z10, z11, i, j, p, q, a, inv, u0, u1, v0, v1, lim2, rr, spherical
        )
        if bound <= best:
            continue
        if u1 - u0 == 1 and v1 - v0 == 1:
            best = bound
            bu = u0
            bv = v0
            continue
        um = (u0 + u1 + 1) // 2 if u1 - u0 > 1 else u1
        vm = (v0 + v1 + 1) // 2 if v1 - v0 > 1 else v1
        # the halves, the one nearest the point pushed last (measured first: the best rises
        # early and the others pass over)
        nu = 1 if um == u1 else 2
        nv = 1 if vm == v1 else 2
        fu = 1 if (nu == 2 and p >= i + um * inv) else 0
        fv = 1 if (nv == 2 and q >= j + vm * inv) else 0
        for c in range(nu * nv - 1, -1, -1):  # the farthest from the point first onto the stack
            cu = (c // nv) ^ fu if nu == 2 else 0
            cv = (c % nv) ^ fv if nv == 2 else 0
            stack[top, 0] = u0 if cu == 0 else um
            stack[top, 1] = um if cu == 0 else u1
            stack[top, 2] = v0 if cv == 0 else vm
            stack[top, 3] = vm if cv == 0 else v1
            top += 1
    return best, bu, bv


@njit(inline="always", cache=True)
def _bilin(z00, z01, z10, z11, u, v):
    """The bilinear surface of a square's corners at ``u`` (rows) and ``v`` (columns) in
    [0, 1]."""
    return (z00 * (1 - v) + z01 * v) * (1 - u) + (z10 * (1 - v) + z11 * v) * u


# the flown route's own check samples each grid square's bilinear seabed on a lattice of this
# many parts a side at least (more where the clearance is under sixteen cells)
CHECK_LATTICE = 2


# the flight's own check passes over blocks of up to this many grid squares a side at once
# (their highest grid point kept, found once per flight: :func:`clearance_blocks`)
CHECK_BLOCK = 8


def clearance_blocks(el: np.ndarray) -> np.ndarray:
    """The highest grid point of each block of grid squares of the elevation tiles ``el``
    (``CHECK_BLOCK`` squares a side, from each tile's first row and column), not found yet
    (NaN): :func:`seabed_clearance` finds each block's the first time it needs it."""
    _, tr, tc = el.shape
    return np.full((el.shape[0], -(-tr // CHECK_BLOCK), -(-tc // CHECK_BLOCK)), np.nan)


@njit(cache=True, nogil=True)
def _block_top(el, slot, tr, tc, rows, cols, blocks, s, lbi, lbj, r0, r1, c0, c1):
    """The highest known grid point of the corners of squares ``r0..r1`` x ``c0..c1`` (the
    block ``(lbi, lbj)`` of the tile in slot ``s``; the map's ``rows`` x ``cols`` points);
    -inf for none."""
    top = blocks[s, lbi, lbj]
    if top == top:
        return top
    top = -np.inf
    for i in range(r0, min(r1 + 1, rows - 1) + 1):
        for j in range(c0, min(c1 + 1, cols - 1) + 1):
            v = np.float64(_cell(slot, el, tr, tc, i, j, np.nan))
            if v > top:
                top = v
    blocks[s, lbi, lbj] = top
    return top


@njit(cache=True, nogil=True)
def seabed_clearance(el, slot, tr, tc, rows, cols, pr, pc, z, a, radius, method, m, start, blocks):
    """The least clearance of the points ``(pr, pc)`` (grid units) at heights ``z`` from the
    continuous seabed, measured anew (not from the required heights): the bilinear seabed of
    every grid square near a point sampled on an ``(m + 1)`` x ``(m + 1)`` lattice. Spherical:
    the least 3-D distance to the samples within ``1.25 radius`` and to the seabed under the
    point (``1.25 radius``, where none is that near); horizontal: the height above the highest
    sample within ``radius`` horizontally; vertical: the height above the seabed under the
    point; a point under the seabed: the (negative) height above it. Each point's search
    starts from the least clearance found so far (a point that cannot come under it is not
    measured further), so the points are best given nearest the seabed first: a block of
    squares (``blocks``: :func:`clearance_blocks`), then a square, is passed over where even
    its highest grid point, at its box distance, is farther than that; a square with a no-data
    corner is not measured. ``start``: the least clearance known already (inf for none): the
    result is the lesser of it and the points' own, found the sooner."""
    n = pr.size
    least = start
    # spherical: searched a quarter beyond the clearance, for the least distance itself
    far = 1.25 * radius if method == 2 else radius
    lim = far * far
    span = far / a + 1.0
    bs = CHECK_BLOCK
    for s in range(n):
        p = pr[s]
        q = pc[s]
        h = z[s]
        if method == 0:
            i = min(max(int(math.floor(p)), 0), rows - 2)
            j = min(max(int(math.floor(q)), 0), cols - 2)
            z00, z01, z10, z11 = _corners(slot, el, tr, tc, i, j, np.nan)
            v = h - _bilin(z00, z01, z10, z11, p - i, q - j)
            if v == v:
                least = min(least, v)
            continue
        # the seabed under the point: a point under it has a negative clearance
        ui = min(max(int(math.floor(p)), 0), rows - 2)
        uj = min(max(int(math.floor(q)), 0), cols - 2)
        z00, z01, z10, z11 = _corners(slot, el, tr, tc, ui, uj, np.nan)
        under = _bilin(z00, z01, z10, z11, p - ui, q - uj)
        if h < under:  # (a no-data corner under it: measured from the squares around only)
            least = min(least, h - under)
            continue
        # squared distance (at most to the seabed under the point, or the least clearance
        # found so far), or the highest seabed (at least the height that would give that)
        if method == 2:
            best = min(lim, (h - under) * (h - under), least * least)
            if best != best:
                best = min(lim, least * least)
        else:
            best = h - least
        i0 = max(0, int(math.floor(p - span)))
        i1 = min(rows - 2, int(math.floor(p + span)))
        j0 = max(0, int(math.floor(q - span)))
        j1 = min(cols - 2, int(math.floor(q + span)))
        bi = i0
        while bi <= i1:  # the blocks of squares the search reaches, then their squares
            ti = _tile_of(bi, tr)
            lbi = (bi - ti * tr) // bs
            r0 = ti * tr + lbi * bs  # the block's squares: rows r0..r1, columns c0..c1
            r1 = ti * tr + min((lbi + 1) * bs, tr) - 1
            ie = min(r1, i1)
            dbi = max(0.0, bi - p, p - (ie + 1)) * a
            bj = j0
            while bj <= j1 and dbi * dbi < (best if method == 2 else lim):
                tj = _tile_of(bj, tc)
                lbj = (bj - tj * tc) // bs
                c0 = tj * tc + lbj * bs
                c1 = tj * tc + min((lbj + 1) * bs, tc) - 1
                je = min(c1, j1)
                dbj = max(0.0, bj - q, q - (je + 1)) * a
                db2 = dbi * dbi + dbj * dbj
                sl = slot[ti, tj]
                enter = sl >= 0 and db2 < (best if method == 2 else lim)
                if enter:
                    btop = _block_top(
                        el, slot, tr, tc, rows, cols, blocks, sl, lbi, lbj, r0, r1, c0, c1
                    )
                    if method == 2:
                        gap = max(h - btop, 0.0)
                        enter = db2 + gap * gap < best
                    else:
                        enter = btop > best
                for i in range(bi, ie + 1 if enter else bi):
                    di = max(0.0, i - p, p - (i + 1)) * a
                    if di * di >= (best if method == 2 else lim):
                        continue
                    for j in range(bj, je + 1):
                        dj = max(0.0, j - q, q - (j + 1)) * a
                        d2 = di * di + dj * dj
                        # (spherical: no sample of a square farther than the least so far counts)
                        if d2 >= (best if method == 2 else lim):
                            continue
                        z00, z01, z10, z11 = _corners(slot, el, tr, tc, i, j, np.nan)
                        if z00 != z00 or z01 != z01 or z10 != z10 or z11 != z11:
                            continue  # no seabed to measure (the flight says where it is unknown)
                        top = max(z00, z01, z10, z11)
                        if method == 2:
                            gap = max(h - top, 0.0)
                            if d2 + gap * gap >= best:
                                continue
                        elif top <= best:
                            continue
                        for u in range(m + 1):
                            fu = u / m
                            for v in range(m + 1):
                                fv = v / m
                                dy = (i + fu - p) * a
                                dx = (j + fv - q) * a
                                e2 = dx * dx + dy * dy
                                if e2 >= lim:
                                    continue
                                b = _bilin(z00, z01, z10, z11, fu, fv)
                                if method == 2:
                                    best = min(best, e2 + (h - b) * (h - b))
                                else:
                                    best = max(best, b)
                bj = je + 1
            bi = ie + 1
        if method == 2:
            least = min(least, math.sqrt(best))
        else:
            least = min(least, h - best)
    return least


@njit(cache=True, nogil=True)
def _bilinear(el, slot, tr, tc, rows, cols, pr, pc):
    n = pr.size
    out = np.empty(n)
    for k in range(n):
        p = min(max(pr[k], 0.0), rows - 1.0)
        q = min(max(pc[k], 0.0), cols - 1.0)
        i0 = min(int(math.floor(p)), max(rows - 2, 0))
        j0 = min(int(math.floor(q)), max(cols - 2, 0))
        fi = p - i0
        fj = q - j0
        ti = _tile_of(i0, tr)
        tj = _tile_of(j0, tc)
        ri = i0 - ti * tr
        rj = j0 - tj * tc
        s = slot[ti, tj]
        # the four grid points in one loaded tile (most samples): read by their place in it
        one = s >= 0 and ri + 1 < tr and rj + 1 < tc and i0 + 1 < rows and j0 + 1 < cols
        acc = 0.0
        for di in range(2):
            for dj in range(2):
                wgt = (fi if di else 1.0 - fi) * (fj if dj else 1.0 - fj)
                if wgt == 0.0:
                    continue
                if one:
                    z = np.float64(el[s, ri + di, rj + dj])
                else:
                    i = min(i0 + di, rows - 1)
                    j = min(j0 + dj, cols - 1)
                    z = np.float64(_cell(slot, el, tr, tc, i, j, np.nan))
                acc += wgt * z
        out[k] = acc
    return out


def pitch_envelope(h, s, slope):
    """The lowest profile ``z >= h`` with ``|dz/ds| <= slope``: ``z_i = max_j (h_j - slope
    |s_i - s_j|)`` by a forward and a backward pass (``-inf`` in ``h``: no constraint)."""
    return pitch_envelope_var(h, s, np.full(max(len(h) - 1, 0), float(slope)))


@njit(cache=True, nogil=True)
def pitch_envelope_var(h, s, slopes):
    """:func:`pitch_envelope` with a slope limit per interval (``slopes[k]`` between samples
    ``k`` and ``k + 1``): the lowest profile ``z >= h`` keeping each."""
    n = h.size
    z = h.copy()
    for k in range(1, n):
        v = z[k - 1] - slopes[k - 1] * (s[k] - s[k - 1])
        if v > z[k]:
            z[k] = v
    for k in range(n - 2, -1, -1):
        v = z[k + 1] - slopes[k] * (s[k + 1] - s[k])
        if v > z[k]:
            z[k] = v
    return z


@njit(cache=True, nogil=True)
def band_profile(s, env, band, top, slopes):
    """Few straight pieces inside the band ``[env, min(env + band, top)]``, each no steeper
    than the ``slopes`` of the intervals it spans (one per interval): greedy, each piece as
    long as a line from its start stays in the band (the feasible slopes narrowed sample by
    sample), at the slope nearest the previous piece's (level first). Returns the heights at
    every sample and the indices where pieces meet."""
    n = s.size
    zr = np.empty(n)
    brk = np.empty(n, dtype=np.int64)
    nb = 0
    brk[nb] = 0
    nb += 1
    i = 0
    zi = env[0]
    zr[0] = zi
    lo = -np.inf
    hi = np.inf
    prev = 0.0
    k = 1
    while k < n:
        ds = s[k] - s[i]
        if ds <= 0.0:
            zr[k] = zi
            k += 1
            continue
        if env[k] != env[k]:  # unknown terrain (reported by the caller): hold the height
            zr[k] = zi
            k += 1
            continue
        up = min(env[k] + band, top)
        if up < env[k]:
            up = env[k]
        sl = slopes[k - 1]
        nlo = max(lo, -sl, (env[k] - zi) / ds)
        nhi = min(hi, sl, (up - zi) / ds)
        if nlo <= nhi + 1e-12:  # (a profile at the pitch limit meets it up to rounding)
            lo = min(nlo, nhi)
            hi = nhi
            k += 1
            continue
        if k == i + 1:
            # not even the next sample: only rounding at the pitch limit does this; step to it
            zr[k] = max(env[k], zi + max(-sl, min(sl, (env[k] - zi) / ds)) * ds)
            i = k
            zi = zr[k]
            brk[nb] = i
            nb += 1
            lo = -np.inf
            hi = np.inf
            k += 1
            continue
        # the piece from i ends at k - 1: the slope the last piece had, or the nearest the band
        # allows (a climb or a descent goes on, a level stays level: few reversals)
        m = min(max(prev, lo), hi)
        prev = m
        for q in range(i + 1, k):
            zr[q] = zi + m * (s[q] - s[i])
        i = k - 1
        zi = zr[i]
        brk[nb] = i
        nb += 1
        lo = -np.inf
        hi = np.inf
    m = min(max(prev, lo), hi) if lo <= hi else 0.0
    for q in range(i + 1, n):
        zr[q] = zi + m * (s[q] - s[i])
    if brk[nb - 1] != n - 1:
        brk[nb] = n - 1
        nb += 1
    return zr, brk[:nb]


@njit(cache=True, nogil=True)
def turn_slopes(sig, zones, slope, min_leg):
    """The pitch limit of each interval of the route's profile (``slope`` as a rise per metre)
    lowered over each turn: ``zones`` rows ``(first interval, end interval, slope)`` in route
    order. Zones less than ``min_leg`` apart (or from either end) are joined, each at its least
    slope (and one shorter than ``min_leg`` made that long), so that a profile held at the limit
    breaks no closer than ``min_leg`` to a turn, to another break or to an end (a waypoint an
    autopilot can tell from the next)."""
    n = sig.size
    out = np.full(n - 1, slope)
    runs = np.empty((zones.shape[0], 3))
    m = 0
    for z in range(zones.shape[0]):
        j0, j1, sl = int(zones[z, 0]), int(zones[z, 1]), zones[z, 2]
        while j1 < n - 1 and sig[j1] - sig[j0] < min_leg:  # (never so over a turn)
            j1 += 1
        while j0 > 0 and sig[j1] - sig[j0] < min_leg:
            j0 -= 1
        while m > 0 and sig[j0] - sig[int(runs[m - 1, 1])] < min_leg:  # (a long arc may reach back)
            m -= 1
            j0 = min(int(runs[m, 0]), j0)
            j1 = max(int(runs[m, 1]), j1)
            sl = min(runs[m, 2], sl)
        runs[m, 0], runs[m, 1], runs[m, 2] = j0, j1, sl
        m += 1
    if m > 0 and sig[int(runs[0, 0])] - sig[0] < min_leg:
        runs[0, 0] = 0
    if m > 0 and sig[n - 1] - sig[int(runs[m - 1, 1])] < min_leg:
        runs[m - 1, 1] = n - 1
    for r in range(m):
        for t in range(int(runs[r, 0]), int(runs[r, 1])):
            out[t] = min(out[t], runs[r, 2])
    return out


def vertical_profile(
    wr, wc, qr, qc, vi, pr, pc, leg, radii, tan_d, hq, h_track, a, slope, bands, top, want,
    min_leg=0.0,
) -> dict:  # fmt: skip
    """The heights of the waypoint route and its waypoints (docs/flyable-missions.md): one
    profile along the route's straight legs (``sigma``, metres), linear between waypoints
    (what an autopilot flies), and the flown track's heights read from it at each sample's
    place along the route (:func:`_track_sigma`). Every sample of either keeps its required
    height (``hq``; ``h_track``: an arc sample's binds the two route samples around it);
    the pitch holds on the legs and on the arcs (the route's slope limited over a turn by the
    ratio of the arc's chords to the route they stand for); the profile is a few straight
    pieces inside a band above the lowest such profile (:func:`band_profile`), the narrowest of
    ``bands`` that needs at most ``want`` waypoints. Its breaks stay ``min_leg`` from turns,
    from each other and from the ends where the limits allow: the slope lowered over a turn
    reaches ``min_leg`` either side of it (:func:`turn_slopes`), and a break still ending a
    shorter leg is removed or moved (:func:`resolve_short_legs`)."""
    sig = np.concatenate(([0.0], np.cumsum(a * np.hypot(np.diff(qr), np.diff(qc)))))
    sig_corner = sig[vi]
    arcs = _arcs_of(leg)
    sig_t = _track_sigma(wr, wc, pr, pc, leg, arcs, tan_d, sig_corner, a)
    h = np.where(np.isnan(hq), -np.inf, hq)
    ht = np.where(np.isnan(h_track), -np.inf, h_track)
    j = np.clip(np.searchsorted(sig, sig_t, side="right") - 1, 0, len(sig) - 2)
    np.maximum.at(h, j, ht)
    np.maximum.at(h, j + 1, ht)
    arc_n = np.zeros(len(wr), dtype=np.int64)
    for b, e, corner in arcs:
        arc_n[corner] = e - b
    k = np.flatnonzero(np.isfinite(radii) & (tan_d > 0))  # the turns
    theta = 2.0 * np.arctan(tan_d[k] / radii[k])
    na = np.maximum(arc_n[k], 1)
    factor = na * np.sin(theta / (2 * na)) / np.tan(theta / 2)
    t = np.maximum(tan_d[k] * a, min_leg)  # a break where the slope changes: min_leg from it
    zones = np.column_stack(
        [
            np.maximum(np.searchsorted(sig, sig_corner[k] - t, side="right") - 1, 0),
            np.minimum(np.searchsorted(sig, sig_corner[k] + t, side="left"), len(sig) - 1),
            slope * factor * (1 - 1e-9),
        ]
    )  # (first interval, end, slope) over each turn
    slopes = turn_slopes(sig, zones, float(slope), float(min_leg))
    if not np.isfinite(h).any():
        h[:] = 0.0
    env = pitch_envelope_var(h, sig, slopes)
    corners = np.asarray(vi, dtype=np.int64)
    for band in bands:  # the narrowest band that needs few waypoints (linear time each)
        z, brk = band_profile(sig, env, band, top, slopes)
        wi = resolve_short_legs(
            sig, z, np.union1d(corners, brk), corners, h, slopes, top, float(min_leg)
        )
        if len(wi) <= want:
            break
    z = np.interp(sig, sig[wi], z[wi])  # exactly linear between waypoints
    return {"sigma": sig, "z": z, "h": h, "waypoints": wi, "band": band, "sigma_track": sig_t}


@njit(cache=True, nogil=True)
def _knot_range(sig, z, h, slopes, top, a, j, b):
    """The heights a knot at sample ``j`` may take between the fixed knots ``a < j < b``: the
    two straight lines ``a -> j -> b`` keep every required height ``h`` of the samples they
    span, the pitch limit of every interval and the surface limit ``top``. Returns
    ``(lo, hi)``, empty when ``lo > hi``."""
    lo = -np.inf
    hi = top
    da = sig[j] - sig[a]
    db = sig[b] - sig[j]
    if da <= 0.0 or db <= 0.0:
        return np.inf, -np.inf
    sl = np.inf
    for t in range(a, j):
        sl = min(sl, slopes[t])
    lo = max(lo, z[a] - sl * da)
    hi = min(hi, z[a] + sl * da)
    for t in range(a + 1, j + 1):  # z_a + (z_j - z_a) u >= h_t, u in (0, 1]
        if h[t] > -np.inf:
            u = (sig[t] - sig[a]) / da
            if u > 0.0:
                lo = max(lo, z[a] + (h[t] - z[a]) / u)
    sl = np.inf
    for t in range(j, b):
        sl = min(sl, slopes[t])
    lo = max(lo, z[b] - sl * db)
    hi = min(hi, z[b] + sl * db)
    for t in range(j, b):
        if h[t] > -np.inf:
            u = (sig[b] - sig[t]) / db
            if u > 0.0:
                lo = max(lo, z[b] + (h[t] - z[b]) / u)
    return lo, hi


@njit(cache=True, nogil=True)
def _line_fits(sig, z, h, slopes, top, a, b):
    """Whether the straight line between the knots at samples ``a < b`` keeps every required
    height, the pitch limit of every interval it spans (up to rounding: two pieces at the limit
    may meet a part in 1e12 steeper) and the surface limit."""
    rise = (z[b] - z[a]) / (sig[b] - sig[a])
    for t in range(a, b):
        if abs(rise) > slopes[t] * (1 + 1e-9):
            return False
    for t in range(a, b + 1):
        v = z[a] + rise * (sig[t] - sig[a])
        if v < h[t] or v > top:
            return False
    return True


@njit(cache=True, nogil=True)
def _draw(sig, z, a, b):
    """The profile between the knots at samples ``a < b`` made the straight line between them."""
    rise = (z[b] - z[a]) / (sig[b] - sig[a])
    for t in range(a + 1, b):
        z[t] = z[a] + rise * (sig[t] - sig[a])


@njit(cache=True, nogil=True)
def _set_knot(sig, z, h, slopes, top, a, j, b):
    """Sets the knot at ``j`` between the fixed knots ``a < j < b`` to the height nearest its
    present one that keeps the limits (:func:`_knot_range`) and draws the two lines; False
    (nothing changed) where no height does."""
    lo, hi = _knot_range(sig, z, h, slopes, top, a, j, b)
    if lo > hi:
        return False
    z[j] = min(max(z[j], lo), hi)
    _draw(sig, z, a, j)
    _draw(sig, z, j, b)
    return True


@njit(cache=True, nogil=True)
def resolve_short_legs(sig, z, wi, corners, h, slopes, top, min_leg):
    """The waypoints ``wi`` with no leg shorter than ``min_leg`` that a break of the height
    profile (a waypoint that is not one of the route's ``corners``) ends, where the limits allow
    (every required height ``h``, the pitch limit of every interval, the surface limit ``top``):
    an autopilot takes a waypoint as reached within about its turn radius and would pass over
    one closer. Each such break, in turn: removed, the line between its neighbours straight;
    else removed and a neighbour's height set anew (not the route's first or last waypoint);
    else moved along the route (never past its neighbours) to a place ``min_leg`` from both,
    its height set anew. ``z`` is changed to the new profile (straight between waypoints)."""
    m = wi.size
    keep = wi.copy()
    fixed = np.zeros(m, dtype=np.bool_)
    c = 0
    for w in range(m):  # both sorted
        while c < corners.size and corners[c] < wi[w]:
            c += 1
        fixed[w] = c < corners.size and corners[c] == wi[w]
    fixed[0] = True
    fixed[m - 1] = True
    n = m
    k = 1
    while k < n - 1:
        b, i0, i1 = keep[k], keep[k - 1], keep[k + 1]
        if fixed[k] or min(sig[b] - sig[i0], sig[i1] - sig[b]) >= min_leg:
            k += 1
            continue
        done = False
        if _line_fits(sig, z, h, slopes, top, i0, i1):  # the break removed
            _draw(sig, z, i0, i1)
            done = True
        if not done and k >= 2:  # removed, the knot before it set anew
            done = _set_knot(sig, z, h, slopes, top, keep[k - 2], i0, i1)
        if not done and k + 2 < n:  # or the knot after it
            done = _set_knot(sig, z, h, slopes, top, i0, i1, keep[k + 2])
        if done:
            for t in range(k, n - 1):  # drop waypoint k
                keep[t] = keep[t + 1]
                fixed[t] = fixed[t + 1]
            n -= 1
            k = max(k - 1, 1)  # the leg before may now be long enough, or still short
            continue
        # moved: the places min_leg from both neighbours, nearest its own first
        best = -1
        if sig[i1] - sig[i0] >= 2.0 * min_leg:
            p = b
            while p > i0 and sig[i1] - sig[p] < min_leg:
                p -= 1
            while p < i1 and sig[p] - sig[i0] < min_leg:
                p += 1
            q = p
            for _ in range(16):  # a few places past it (the first is usually taken)
                if q <= i0 or q >= i1 or sig[q] - sig[i0] < min_leg or sig[i1] - sig[q] < min_leg:
                    break
                if _set_knot(sig, z, h, slopes, top, i0, q, i1):  # from its present height
                    best = q
                    break
                q += 1 if p >= b else -1
        if best >= 0:
            keep[k] = best
        k += 1
    return keep[:n]


# the flown route's own check measures every sample, first the samples nearest their required
# heights (this share of them, and at least CHECK_LEAST), whose least clearance lets the
# others' searches stop early
CHECK_SHARE = 0.01


CHECK_LEAST = 32


def _closest(margin: np.ndarray) -> np.ndarray:
    """The indices of the samples with the least ``margin`` (``CHECK_SHARE`` of them, at least
    ``CHECK_LEAST``; NaN margins, of unknown terrain, last)."""
    k = min(len(margin), max(CHECK_LEAST, int(CHECK_SHARE * len(margin))))
    m = np.where(np.isnan(margin), np.inf, margin)
    return np.sort(np.argpartition(m, k - 1)[:k]) if k < len(m) else np.arange(len(m))


def profile_figures(s, z, seabed) -> dict:
    """Near-bottom figures of a flown profile: the altitude above the seabed (median, 90th
    percentile, least) and the vertical reversals (climb to descent or back, level pieces
    passed over) per km of horizontal distance."""
    alt = z - seabed
    d = np.sign(np.round(np.diff(z) / np.maximum(np.diff(s), 1e-300), 9))
    d = d[d != 0]
    rev = int(np.count_nonzero(d[1:] != d[:-1])) if d.size > 1 else 0
    km = max(float(s[-1] - s[0]) / 1000.0, 1e-9)
    ok = np.isfinite(alt)
    return {
        "altitude_median_m": float(np.median(alt[ok])) if ok.any() else math.nan,
        "altitude_p90_m": float(np.percentile(alt[ok], 90)) if ok.any() else math.nan,
        "altitude_min_m": float(alt[ok].min()) if ok.any() else math.nan,
        "reversals_per_km": rev / km,
    }


def _required_threaded(grid, terrain, pr, pc, parts: int = 2) -> tuple:
    """``required_heights`` over the samples and their flags of a partly unknown seabed, in
    ``parts`` threads (the kernel releases the GIL): the mission's other work waits for it,
    the cores do not."""
    n = len(pr)
    partial = np.zeros(n, dtype=np.uint8)
    cut = np.linspace(0, n, parts + 1).astype(int) if n >= 4096 and parts >= 2 else [0, n]

    a, radius, method, clearance, extra, k = terrain

    def part(q):
        lo, hi = cut[q], cut[q + 1]
        args = (*grid, pr[lo:hi], pc[lo:hi], a, radius, method, clearance)
        if k == 1:  # the squares' diagonal added to every distance, blocks passed over
            return required_heights(*args, extra + a * math.sqrt(2.0), partial[lo:hi])
        return required_heights_fine(*args, extra, k, partial[lo:hi])

    if len(cut) == 2:
        return part(0), partial
    out = shared_pool(f"heights-{parts}", parts).map(part, range(parts))
    return np.concatenate(list(out)), partial


def _arcs_of(leg: np.ndarray) -> list:
    """``(first, end, corner)`` of each arc of the flown track: its samples (``leg`` -1)
    ``first:end``, and the corner it turns, the one after the leg whose samples precede it."""
    on_arc = np.flatnonzero(leg < 0)
    if not on_arc.size:
        return []
    gap = np.diff(on_arc) > 1
    first = on_arc[np.concatenate(([True], gap))]
    end = on_arc[np.concatenate((gap, [True]))] + 1
    return [(b, e, int(leg[b - 1]) + 1) for b, e in zip(first.tolist(), end.tolist(), strict=True)]


def _track_sigma(wr, wc, pr, pc, leg, arcs, tan_d, sig_corner, a) -> np.ndarray:
    """Where each sample of the flown track (the corners' arcs) lies along the waypoint route
    (metres from the start, along the straight legs): a straight sample at its own place; the
    samples of the arc at corner ``k`` (``arcs``, :func:`_arcs_of`) spread evenly over
    ``[sigma_k - t, sigma_k + t]`` (``t`` the arc's tangent length), in turn."""
    out = np.empty(len(pr))
    straight = leg >= 0
    k = leg[straight]
    out[straight] = sig_corner[k] + a * np.hypot(pr[straight] - wr[k], pc[straight] - wc[k])
    for b, e, corner in arcs:
        t = tan_d[corner] * a
        out[b:e] = sig_corner[corner] - t + 2.0 * t * np.arange(e - b) / (e - b)
    return out
