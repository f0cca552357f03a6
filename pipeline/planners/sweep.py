"""The exact shortest path over a large window by row sweeps over a bounded region: the engine of
the ``astar`` planner from :data:`SWEEP_CELLS` cells on (a whole large map, ``mcpc=False``),
with the same optimal length (docs/method.md section 5).

Why not A* there: every octile-monotone path between two cells has the same horizontal length,
and the terrain adds only 0.1-3 % to it, so every cell of the parallelogram the mission spans
has ``f = g + h`` below the optimum ``L*``, and A* must expand all of them (millions at
10000^2) through a heap whose entries miss the caches: about a microsecond an expansion.

The sweeps visit the same cells in memory order instead, a few nanoseconds each:

1. **Region.** The octile distance is a lower bound on the length between two cells, so a path
   of length at most ``U`` from ``s`` to ``g`` stays in ``R(U) = {v : oct(s, v) + oct(v, g) <=
   U}``. The left side is a convex function of ``v``, so ``R(U)`` is one interval of columns
   per row (:func:`region_rows`).
2. **Distances in the region** (:func:`sweep_distances`): Gauss-Seidel relaxation (Bellman-Ford
   in row order). A row is relaxed from the row before it in the sweep's direction (its three
   neighbours above or below: one pass the compiler vectorises), then along itself from left to
   right and back. Sweeps go down and up in turn; a row is relaxed again only when the row it
   pulls from has changed since it last did, and only over the columns where a neighbour of
   that row lies within one cell's length ``a`` of its value (no move is shorter, so nowhere
   else can it lower anything). It stops when no row waits for a pull: then no move of the
   region can shorten any distance, and every distance is the length of a path, so each is the
   shortest within the region (the fixpoint of Bellman-Ford).
3. **Proof and growth.** With ``L`` the goal's distance in ``R(U)``: if ``L <= U``, any path that
   leaves the region is longer than ``U >= L``, so ``L = L*``. Otherwise the region grows to
   ``R(L)``, which holds the path found, so the next round proves its optimum (or, without a
   path in the region, ``U - oct(s, g)`` grows fourfold, up to the whole map). The first
   ``U`` is ``(1 + SLACK)`` times the octile distance.
4. **Path.** From the goal back to the start, each cell's predecessor is the neighbour ``u``
   that minimises ``d(u) + c(u, v)``: at the fixpoint that minimum is ``d(v)`` itself, computed
   with the same floating-point operations as the sweeps, and ``d`` strictly falls along the
   way (every move is at least ``a`` long), so the walk ends at the start.

Work is bounded: a round that has relaxed more than :data:`BUDGET` times its region's cells, or
taken :data:`MAX_SWEEPS` sweeps (a maze that turns back on itself needs a sweep per turn),
gives up, and the caller runs A* instead.
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import types
from numba.extending import overload

from ..runtime.jit import njit
from .grid import DC, DR
from .search import edge_cost, heuristic

# the first bound is (1 + SLACK) times the octile distance, which the benchmark maps' optima
# lie just above (benchmarks/bench_certify.py); a larger slack widens the region, a smaller one
# asks more missions for a second round (CHANGELOG.md, "Measurements")
SLACK = 0.015
BUDGET = 8.0  # cell relaxations per region cell before a round gives up (A* then)
MAX_SWEEPS = 64  # and sweeps
# sweeps of the distances to every cell of a map (:func:`distances`): each turn of a path
# around land needs one, but only the rows that changed are relaxed again
WHOLE_MAP_SWEEPS = 4096
INF = np.inf


@njit(cache=True)
def _f(a, i, j, sr, sc, gr, gc):
    return heuristic(a, i, j, sr, sc, True) + heuristic(a, i, j, gr, gc, True)


@njit(cache=True)
def region_rows(rows, cols, a, sr, sc, gr, gc, bound):
    """Per row ``i`` the columns ``lo[i] .. hi[i]`` of the cells ``v`` with ``oct(s, v) + oct(v,
    g) <= bound`` (``lo[i] > hi[i]``: none). ``f(j) = oct(s, (i, j)) + oct((i, j), g)`` is
    convex in ``j``: its minimum is where its forward difference first stops falling, and the
    interval grows from there both ways (binary searches, O(rows log cols))."""
    lo = np.ones(rows, dtype=np.int64)
    hi = np.zeros(rows, dtype=np.int64)
    for i in range(rows):
        # the first j whose step to j + 1 does not fall
        x, y = 0, cols - 1
        while x < y:
            mid = (x + y) // 2
            if _f(a, i, mid + 1, sr, sc, gr, gc) - _f(a, i, mid, sr, sc, gr, gc) >= 0.0:
                y = mid
            else:
                x = mid + 1
        jm = x
        if _f(a, i, jm, sr, sc, gr, gc) > bound:
            continue
        x, y = 0, jm  # the first j <= jm inside
        while x < y:
            mid = (x + y) // 2
            if _f(a, i, mid, sr, sc, gr, gc) <= bound:
                y = mid
            else:
                x = mid + 1
        lo[i] = x
        x, y = jm, cols - 1  # the last j >= jm inside
        while x < y:
            mid = (x + y + 1) // 2
            if _f(a, i, mid, sr, sc, gr, gc) <= bound:
                x = mid
            else:
                y = mid - 1
        hi[i] = x
    return lo, hi


@njit(cache=True)
def _along(surface, ok, a, u, d, i, j0, j1):
    """The move (i, j0) -> (i, j1) along a row, inf where a cell is not passable: with the
    heights scaled by ``u[0]``, in the units of ``d`` (:func:`whole_units`; in :data:`METRES` the
    operations of ``edge_cost`` in its order, as every relaxation here repeats them)."""
    if not (passable_at(ok, i, j0) and passable_at(ok, i, j1)):
        return INF
    dz = height_at(surface, i, j1) * u[0] - height_at(surface, i, j0) * u[0]
    dz = lowered(dz, (cell_error(surface, i, j0) + cell_error(surface, i, j1)) * u[0], surface)
    return whole_units(math.sqrt(a * a + dz * dz), d)


# A safety surface held in 2 bytes a cell (the landmark layers' searches,
# :func:`pipeline.maps.landmarks.quantised`): ``codes`` (uint16, rows x cols; :data:`IMPASSABLE` on
# the cells that are not passable), steps of ``quantum`` above ``base`` in blocks of ``2^shift``
# cells a side (float32, a value a block). A cell's height ``base + code * quantum`` in float64
# (:func:`height_at`) lies within its block's ``error`` (float32, metres, a margin for float64
# rounding in it) of its float32 safety height, so a move's rise less the errors of its two
# cells (:func:`lowered`) is at most its true rise: the move costs at most what the planners'
# ``edge_cost`` makes it. ``relief``: a bound on the span of the quantised heights
Quantised = namedtuple("Quantised", "codes base quantum error shift relief")
IMPASSABLE = 65535


def height_at(surface, i, j):
    """The height of cell (i, j) in float64: of a float surface, or of a :class:`Quantised`
    one. Compiled for the surface's type (:func:`_height_typed`)."""
    if isinstance(surface, Quantised):
        b = (i >> surface.shift, j >> surface.shift)
        return float(surface.base[b]) + float(surface.codes[i, j]) * float(surface.quantum[b])
    return np.float64(surface[i, j])


@overload(height_at)
def _height_typed(surface, i, j):
    if isinstance(surface, types.BaseTuple):

        def quantised(surface, i, j):
            bi = i >> surface.shift
            bj = j >> surface.shift
            step = np.float64(surface.quantum[bi, bj])
            return np.float64(surface.base[bi, bj]) + np.float64(surface.codes[i, j]) * step

        return quantised
    return lambda surface, i, j: np.float64(surface[i, j])


def cell_error(surface, i, j):
    """How far the height of cell (i, j) may lie from its true one, metres: 0 on a float
    surface, its block's ``error`` on a :class:`Quantised` one."""
    if isinstance(surface, Quantised):
        return float(surface.error[i >> surface.shift, j >> surface.shift])
    return 0.0


@overload(cell_error)
def _cell_error_typed(surface, i, j):
    if isinstance(surface, types.BaseTuple):
        return lambda surface, i, j: np.float64(
            surface.error[i >> surface.shift, j >> surface.shift]
        )
    return lambda surface, i, j: 0.0


def grid_shape(surface):
    """``(rows, cols)`` of a float surface or of a :class:`Quantised` one."""
    return surface.codes.shape if isinstance(surface, Quantised) else surface.shape


@overload(grid_shape)
def _grid_shape_typed(surface):
    if isinstance(surface, types.BaseTuple):
        return lambda surface: surface.codes.shape
    return lambda surface: surface.shape


def lowered(dz, loss, surface):
    """A move's rise ``dz`` as the searches take it: as it is on a float surface; on a
    :class:`Quantised` one its size less ``loss`` (its two cells' errors, in the units of
    ``dz``; at least 0), so that the move never costs more than its true 3-D length. Compiled
    for the surface's type: nothing for the planners' float surfaces."""
    if isinstance(surface, Quantised):
        return max(abs(dz) - loss, 0.0)
    return dz


@overload(lowered)
def _lowered_typed(dz, loss, surface):
    if isinstance(surface, types.BaseTuple):
        return lambda dz, loss, surface: max(abs(dz) - loss, 0.0)
    return lambda dz, loss, surface: dz


def whole_units(x, d):
    """A move's cost ``x`` in the units of the distances ``d``: rounded down to a whole unit
    where ``d`` holds integers (:func:`fixed_point_distances`), else as it is. Compiled for
    the type of ``d`` (:func:`_whole_typed`), so that the planners' searches pay nothing."""
    return np.floor(x) if np.issubdtype(d.dtype, np.integer) else x


@overload(whole_units)
def _whole_typed(x, d):
    if isinstance(d.dtype, types.Integer):
        return lambda x, d: np.floor(x)
    return lambda x, d: x


def passable_at(ok, i, j):
    """Whether cell (i, j) is passable: ``ok`` the passable mask, a float surface whose
    impassable cells are NaN, or a :class:`Quantised` surface (the landmark layers' search,
    which then holds no mask). Compiled for the type of ``ok`` (:func:`_passable_typed`)."""
    if isinstance(ok, Quantised):
        return ok.codes[i, j] != IMPASSABLE
    v = ok[i, j]
    return bool(v) if ok.dtype == np.bool_ else v == v


@overload(passable_at)
def _passable_typed(ok, i, j):
    if isinstance(ok, types.BaseTuple):
        return lambda ok, i, j: ok.codes[i, j] != IMPASSABLE
    if isinstance(ok.dtype, types.Boolean):
        return lambda ok, i, j: ok[i, j]
    return lambda ok, i, j: ok[i, j] == ok[i, j]


def flat_mask(ok):
    """``ok`` of :func:`passable_at` as the flat array :func:`passable_flat` reads: raveled,
    the codes of a :class:`Quantised` surface."""
    return ok.codes.ravel() if isinstance(ok, Quantised) else ok.ravel()


@overload(flat_mask)
def _flat_mask_typed(ok):
    if isinstance(ok, types.BaseTuple):
        return lambda ok: ok.codes.ravel()
    return lambda ok: ok.ravel()


def passable_flat(ok, i):
    """:func:`passable_at` of :func:`flat_mask` at index ``i``."""
    v = ok[i]
    if ok.dtype == np.uint16:
        return v != IMPASSABLE
    return bool(v) if ok.dtype == np.bool_ else v == v


@overload(passable_flat)
def _passable_flat_typed(ok, i):
    if isinstance(ok.dtype, types.Boolean):
        return lambda ok, i: ok[i]
    if ok.dtype == types.uint16:  # a Quantised surface's codes
        return lambda ok, i: ok[i] != IMPASSABLE
    return lambda ok, i: ok[i] == ok[i]


@njit(cache=True)
def _lowest_of_three(d, pbase, lp, hp, j):
    """The least distance of row ``p``'s columns ``j - 1 .. j + 1`` (inf outside its span)."""
    m = INF
    for k in range(j - 1, j + 2):
        if lp <= k <= hp:
            v = d[pbase + k]
            if v < m:
                m = v
    return m


@njit(cache=True)
def _lowered(d, base, pbase, lp, hp, low, j):
    """Whether a pull from row ``p`` may lower column ``j``: a neighbour there within ``low``
    (a lower bound on every move) of its distance."""
    return _lowest_of_three(d, pbase, lp, hp, j) + low < d[base + j]


@njit(cache=True)
def _inner_lowest(d, pbase, j):
    """:func:`_lowest_of_three` where all three columns lie in row ``p``'s span, without a
    branch (so that the loops over them vectorise)."""
    x = d[pbase + j - 1]
    y = d[pbase + j]
    z = d[pbase + j + 1]
    m = x if x < y else y
    return m if m < z else z


@njit(cache=True)
def _first_lowered(d, base, pbase, lp, hp, low, j0, j1):
    """The first column of ``j0 .. j1`` whose distance a neighbour in row ``p`` comes within
    ``low`` of (``j1 + 1``: none). Most rows a sweep revisits have none: the columns whose three
    neighbours all lie in row ``p``'s span are tested 16 at a time without a branch (which
    the compiler vectorises), and the block that holds one is searched again one by one."""
    j = j0
    while j <= j1 and (j - 1 < lp or j + 1 > hp):
        if _lowered(d, base, pbase, lp, hp, low, j):
            return j
        j += 1
    inner = min(j1, hp - 1)
    while j + 16 <= inner + 1:
        hit = False
        for q in range(j, j + 16):
            hit |= _inner_lowest(d, pbase, q) + low < d[base + q]
        if hit:
            break
        j += 16
    while j <= j1:
        if _lowered(d, base, pbase, lp, hp, low, j):
            return j
        j += 1
    return j1 + 1


@njit(cache=True)
def _held(d, i, u):
    """Distance ``d[i]`` as the scratch rows hold it: inf where not reached (``u[2]``)."""
    v = d[i]
    return INF if v == u[2] else np.float64(v)


@njit(cache=True)
def _stored(x, u):
    """A scratch row's distance ``x`` as ``d`` stores it in the units ``u``: held at the cap
    (``u[1]``), not reached (inf) as ``u[2]``."""
    return u[2] if x == INF else min(x, u[1])


def _float_heights(surface, ok, r, j0, n, z, pen, e, u):
    """:func:`_load_heights` of a float surface (no errors to load)."""
    cols = surface.shape[1]
    for q in range(n):
        j = j0 + q
        if 0 <= j < cols and passable_at(ok, r, j):
            z[q] = np.float64(surface[r, j]) * u[0]
            pen[q] = 0.0
        else:
            z[q] = 0.0
            pen[q] = INF


def _quantised_heights(surface, ok, r, j0, n, z, pen, e, u):
    """:func:`_load_heights` of a :class:`Quantised` surface: its codes say which cells are
    passable (the searches' ``ok`` is the surface itself), and a block's values are read once
    a cell, for its height and its error."""
    codes, base = surface.codes, surface.base
    quantum, error = surface.quantum, surface.error
    cols = codes.shape[1]
    bi = r >> surface.shift
    for q in range(n):
        j = j0 + q
        if 0 <= j < cols and codes[r, j] != IMPASSABLE:
            bj = j >> surface.shift
            step = np.float64(quantum[bi, bj])
            z[q] = (np.float64(base[bi, bj]) + np.float64(codes[r, j]) * step) * u[0]
            e[q] = np.float64(error[bi, bj]) * u[0]
            pen[q] = 0.0
        else:
            z[q] = 0.0
            e[q] = 0.0
            pen[q] = INF


def _load_heights(surface, ok, r, j0, n, z, pen, e, u):
    """Columns ``j0 .. j0 + n - 1`` of row ``r`` into scratch rows: heights (scaled by
    ``u[0]``; 0 where not passable, so that no NaN of a no-data cell enters a sum), penalties
    (inf where not passable) and, on a :class:`Quantised` surface, the heights' errors
    (:func:`cell_error`, scaled alike; untouched on a float surface, which has none).
    Compiled for the surface's type (:func:`_load_heights_typed`)."""
    load = _quantised_heights if isinstance(surface, Quantised) else _float_heights
    load(surface, ok, r, j0, n, z, pen, e, u)


@overload(_load_heights)
def _load_heights_typed(surface, ok, r, j0, n, z, pen, e, u):
    return _quantised_heights if isinstance(surface, types.BaseTuple) else _float_heights


@njit(cache=True)
def _load(surface, ok, d, r, base, first, last, j0, n, z, pen, dist, e, u):
    """Columns ``j0 .. j0 + n - 1`` of row ``r`` into scratch rows: heights, penalties and
    errors (:func:`_load_heights`) and distances (inf outside the row's span ``first ..
    last``)."""
    _load_heights(surface, ok, r, j0, n, z, pen, e, u)
    for q in range(n):
        j = j0 + q
        dist[q] = _held(d, base + j, u) if first <= j <= last else INF


# candidates of a pull at most this many columns apart are relaxed as one span; a row whose
# candidates lie further apart (a maze's parallel corridors) is relaxed span by span
GAP = 8


@njit(cache=True, nogil=True)
def _relax_row(surface, ok, a, u, i, p, lo, hi, off, d, s):
    """Relax row ``i`` from row ``p`` (``p < 0``: from nothing, the start's row) and along
    itself; returns the cells relaxed and whether any distance fell. ``s``: scratch rows (11 x
    the widest row + 2); ``u`` the units (:data:`METRES`, :func:`fixed_point_distances`).
    The pull is computed only over the spans of columns it can lower (a neighbour in row p
    within a move of the cell: no move is shorter than ``a``, though computed,
    ``sqrt(a*a + dz*dz)`` may fall an ulp below it)."""
    if p < 0:
        return _relax_span(surface, ok, a, u, i, p, lo, hi, off, d, s, lo[i], hi[i])
    first, last = lo[i], hi[i]
    base = off[i] - first
    lp, hp = lo[p], hi[p]
    pbase = off[p] - lp
    j1 = min(last, hp + 1)
    low = a * (1.0 - 1e-12)
    j0 = max(first, lp - 1)
    kmin = _first_lowered(d, base, pbase, lp, hp, low, j0, j1)
    if kmin > j1:
        return 0, False
    kmax = j1
    while not _lowered(d, base, pbase, lp, hp, low, kmax):
        kmax -= 1
    if 2 * _count_lowered(d, base, pbase, lp, hp, low, kmin, kmax) >= kmax - kmin + 1:
        # dense (a row the sweeps reach for the first time): one span
        return _relax_span(surface, ok, a, u, i, p, lo, hi, off, d, s, kmin, kmax)
    relaxed = 0
    changed = False
    start = kmin
    while True:  # sparse: span by span, split where GAP columns in turn have no candidate
        kmin = _first_lowered(d, base, pbase, lp, hp, low, start, j1)
        if kmin > j1:
            return relaxed, changed
        end = kmin
        j = kmin + 1
        while j <= j1 and j - end <= GAP:
            if _lowered(d, base, pbase, lp, hp, low, j):
                end = j
            j += 1
        n, fell = _relax_span(surface, ok, a, u, i, p, lo, hi, off, d, s, kmin, end)
        relaxed += n
        changed |= fell
        start = j


@njit(cache=True)
def _count_lowered(d, base, pbase, lp, hp, low, j0, j1):
    """How many columns of ``j0 .. j1`` a pull from row ``p`` may lower (as
    :func:`_first_lowered` tests them; without a branch where all three neighbours lie in
    row ``p``'s span)."""
    count = 0
    inner0 = max(j0, lp + 1)
    inner1 = min(j1, hp - 1)
    for j in range(j0, min(j1, inner0 - 1) + 1):
        count += _lowered(d, base, pbase, lp, hp, low, j)
    for q in range(inner0, inner1 + 1):
        count += _inner_lowest(d, pbase, q) + low < d[base + q]
    for j in range(max(j0, inner1 + 1), j1 + 1):
        count += _lowered(d, base, pbase, lp, hp, low, j)
    return count


@njit(cache=True)
def _extend(surface, ok, a, u, i, d, base, j, end, step):
    """Carry row ``i``'s distances on from column ``j`` towards ``end`` (``step`` +1 or -1)
    while each move along the row lowers the next; returns the last column lowered (``j``:
    none)."""
    while j != end:
        c = d[base + j] + _along(surface, ok, a, u, d, i, j, j + step)
        if not c < d[base + j + step]:
            break
        j += step
        d[base + j] = min(c, u[1])
    return j


@njit(cache=True, nogil=True)
def _relax_span(surface, ok, a, u, i, p, lo, hi, off, d, s, kmin, kmax):
    """:func:`_relax_row` over columns ``kmin .. kmax``: the pull (none with ``p < 0``), then
    along the row over the span and on past its ends while that lowers the distances."""
    a2 = a * a
    d2 = 2.0 * a2
    zi, zp, pi, pp, dp, best, hz, wv, wd = s[0], s[1], s[2], s[3], s[4], s[5], s[6], s[7], s[8]
    ei, ep = s[9], s[10]  # the heights' errors (Quantised surfaces only)
    first, last = lo[i], hi[i]
    base = off[i] - first
    changed = False
    lp = hp = pbase = 0
    if p >= 0:
        lp, hp = lo[p], hi[p]
        pbase = off[p] - lp
    n = kmax - kmin + 1
    _load(surface, ok, d, i, base, first, last, kmin - 1, n + 2, zi, pi, best, ei, u)
    if p >= 0:
        _load(surface, ok, d, p, pbase, lp, hp, kmin - 1, n + 2, zp, pp, dp, ep, u)
        for q in range(1, n + 1):
            dz = lowered(zi[q] - zp[q], ei[q] + ep[q], surface)
            wv[q] = whole_units(math.sqrt(a2 + dz * dz), d)
        for q in range(1, n + 1):  # from (p, j - 1): it passes between (p, j) and (i, j - 1)
            dz = lowered(zi[q] - zp[q - 1], ei[q] + ep[q - 1], surface)
            wd[q] = dp[q - 1] + whole_units(math.sqrt(d2 + dz * dz), d) + pi[q - 1]
        for q in range(1, n + 1):
            dz = lowered(zi[q] - zp[q + 1], ei[q] + ep[q + 1], surface)
            c = dp[q + 1] + whole_units(math.sqrt(d2 + dz * dz), d) + pi[q + 1]
            c = c if c < wd[q] else wd[q]
            v = dp[q] + wv[q]
            c = (c if c < v else v) + pp[q] + pi[q]
            b = best[q]
            changed |= c < b
            best[q] = c if c < b else b
        if not changed:
            return n, False
    for q in range(1, n + 2):
        dz = lowered(zi[q] - zi[q - 1], ei[q] + ei[q - 1], surface)
        hz[q] = whole_units(math.sqrt(a2 + dz * dz), d) + pi[q] + pi[q - 1]
    # along the row, left to right, on past kmax while it lowers
    for q in range(1, n + 1):
        c = best[q - 1] + hz[q]
        if c < best[q]:
            best[q] = c
            changed = True
    for q in range(1, n + 1):
        d[base + kmin - 1 + q] = _stored(best[q], u)
    right = _extend(surface, ok, a, u, i, d, base, kmax, last, 1)
    changed |= right > kmax
    # and back, right to left, on past kmin while it lowers
    for j in range(right - 1, kmax, -1):
        c = d[base + j + 1] + _along(surface, ok, a, u, d, i, j + 1, j)
        if c < d[base + j]:
            d[base + j] = min(c, u[1])
    if kmax < last:
        best[n + 1] = _held(d, base + kmax + 1, u)
    for q in range(n, 0, -1):
        c = best[q + 1] + hz[q + 1]
        if c < best[q]:
            best[q] = c
            changed = True
    for q in range(1, n + 1):
        d[base + kmin - 1 + q] = _stored(best[q], u)
    left = _extend(surface, ok, a, u, i, d, base, kmin, first, -1)
    changed |= left < kmin
    return n + (right - kmax) + (kmin - left), changed


@njit(cache=True, nogil=True)
def sweep_distances(surface, ok, a, sr, sc, lo, hi, budget, max_sweeps):
    """The shortest distances from (sr, sc) within the region ``lo``/``hi`` (step 2 of the
    module's method): ``(d, off, relaxed, sweeps, done)``, ``d[off[i] + j - lo[i]]`` the
    distance of cell (i, j) (inf: not reached; ``off[-1]`` the region's cells), ``done`` False
    when the relaxations passed ``budget`` times the region's cells or the sweeps
    ``max_sweeps`` (the distances are then upper bounds only)."""
    rows = surface.shape[0]
    off = np.zeros(rows + 1, dtype=np.int64)
    for i in range(rows):
        off[i + 1] = off[i] + max(hi[i] - lo[i] + 1, 0)
    d = np.full(off[rows], INF)
    relaxed, sweeps, done = _sweeps(
        surface, ok, a, METRES, sr, sc, lo, hi, off, d, budget, max_sweeps
    )
    return d, off, relaxed, sweeps, done


# the units of the planners' searches: heights as they are (scale 1), distances in float64
# stored as computed (no cap), inf where not reached
METRES = (1.0, INF, INF)


@njit(cache=True, nogil=True)
def _sweeps(surface, ok, a, u, sr, sc, lo, hi, off, d, budget, max_sweeps):
    """:func:`sweep_distances` into the distances ``d`` (all not reached but the start's, set
    here to 0) in the units ``u``: ``(heights' scale, cap, not reached)`` (:data:`METRES`;
    :func:`fixed_point_distances`). Returns ``(relaxed, sweeps, done)``."""
    rows = grid_shape(surface)[0]
    width = 0
    for i in range(rows):
        width = max(width, hi[i] - lo[i] + 1)
    budget = budget * off[rows]
    scratch = np.empty((11, width + 2))
    d[off[sr] + sc - lo[sr]] = 0
    # stamps: when a row last changed, and last pulled from the row above / below
    stamp = 1
    changed = np.zeros(rows, dtype=np.int64)
    from_above = np.zeros(rows, dtype=np.int64)
    from_below = np.zeros(rows, dtype=np.int64)
    # the first row has no row to pull from: -1 as an int64, not the literal -1, whose own
    # compiled copies of _relax_row and _relax_span cost seconds of compilation per surface type
    relaxed, _ = _relax_row(surface, ok, a, u, sr, np.int64(-1), lo, hi, off, d, scratch)
    changed[sr] = stamp
    sweeps = 0
    while True:
        waiting = False
        for i in range(rows):
            if lo[i] <= hi[i] and (
                (i > 0 and changed[i - 1] > from_above[i])
                or (i < rows - 1 and changed[i + 1] > from_below[i])
            ):
                waiting = True
                break
        if not waiting:
            return relaxed, sweeps, True
        for step in (1, -1):
            sweeps += 1
            for k in range(rows):
                i = k if step == 1 else rows - 1 - k
                p = i - step
                if lo[i] > hi[i] or p < 0 or p >= rows or lo[p] > hi[p]:
                    continue
                last = from_above if step == 1 else from_below
                if changed[p] <= last[i]:
                    continue
                stamp += 1
                last[i] = stamp
                n, fell = _relax_row(surface, ok, a, u, i, p, lo, hi, off, d, scratch)
                relaxed += n
                if fell:
                    stamp += 1
                    changed[i] = stamp
            if relaxed > budget or sweeps >= max_sweeps:
                return relaxed, sweeps, False


@njit(cache=True, nogil=True)
def _backtrack(surface, ok, a, sr, sc, gr, gc, lo, hi, off, d):
    """Step 4: the path's cells (k x 2, start to goal), or an empty array if a cell has no
    neighbour that gives its distance (not a fixpoint: never, but the caller then runs A*)."""
    rows, cols = surface.shape
    moves = np.empty(1024, dtype=np.int8)
    n = 0
    r, c = gr, gc
    while r != sr or c != sc:
        if n == off[rows]:  # longer than the region: not a fixpoint
            return np.empty((0, 2), dtype=np.int64)
        here = d[off[r] + c - lo[r]]
        best = INF
        move = -1
        for k in range(8):
            pr = r - DR[k]  # the neighbour the move k leaves from
            pc = c - DC[k]
            if pr < 0 or pr >= rows or pc < lo[pr] or pc > hi[pr] or not ok[pr, pc]:
                continue
            if k % 2 == 1 and not (ok[pr, c] and ok[r, pc]):
                continue  # a diagonal must not cut a corner
            v = d[off[pr] + pc - lo[pr]] + edge_cost(surface, a, pr, pc, r, c)
            if v < best:
                best = v
                move = k
        if move < 0 or not best <= here:
            return np.empty((0, 2), dtype=np.int64)
        if n == moves.size:
            grown = np.empty(2 * n, dtype=np.int8)
            grown[:n] = moves
            moves = grown
        moves[n] = move
        n += 1
        r -= DR[move]
        c -= DC[move]
    cells = np.empty((n + 1, 2), dtype=np.int64)
    cells[0, 0] = sr
    cells[0, 1] = sc
    for i in range(n):  # the moves were found goal first
        k = moves[n - 1 - i]
        cells[i + 1, 0] = cells[i, 0] + DR[k]
        cells[i + 1, 1] = cells[i, 1] + DC[k]
    return cells


def flat_between(surface, passable, a: float, s, t):
    """Whether every passable cell of the sweeps' first region between ``s`` and ``t`` (the
    cells within ``(1 + SLACK)`` times the octile distance of the two, where the optimum of an
    open seabed lies) has one height: a flat seabed, as the planners' benchmark obstacle map.
    There the octile distance is the exact length wherever no obstacle stands in the way, every
    cell of the parallelogram a mission spans ties on ``f`` with the optimum, and A*, its ties
    broken towards the goal, walks the straight line, expanding a few cells a step of the path.
    What decides between A* and the sweeps for a mission; it stops at the first cell that
    differs (at once on real relief), a fraction of a check of the whole window."""
    rows, cols = surface.shape
    bound = heuristic(a, s[0], s[1], t[0], t[1], True) * (1.0 + SLACK) * (1.0 + 1e-9)
    lo, hi = region_rows(rows, cols, a, s[0], s[1], t[0], t[1], bound)
    return _flat_rows(surface, passable, lo, hi)


@njit(nogil=True, cache=True)
def _flat_rows(surface, passable, lo, hi):
    """Whether the passable cells of columns ``lo[i] .. hi[i]`` of each row ``i`` have one
    height, stopping at the first that differs."""
    z0 = np.float32(0.0)
    seen = False
    for i in range(surface.shape[0]):
        for j in range(lo[i], hi[i] + 1):
            if passable[i, j]:
                if not seen:
                    z0 = surface[i, j]
                    seen = True
                elif surface[i, j] != z0:
                    return False
    return True


def search(surface, passable, a: float, s, t):
    """The shortest path from ``s`` to ``t`` by the module's method: ``(cells, relaxed,
    extra)``, ``cells`` the path (k x 2; none: no path), ``relaxed`` the cell relaxations,
    ``extra`` the region's cells, the sweeps and rounds; or None when a round ran out of its
    budget (the caller then runs A*)."""
    rows, cols = surface.shape
    octile = heuristic(a, s[0], s[1], t[0], t[1], True)
    bound = octile * (1.0 + SLACK)
    relaxed = rounds = sweeps = 0
    while True:
        # a hair wider than the bound: the floating point of oct(s, v) + oct(v, g)
        lo, hi = region_rows(rows, cols, a, s[0], s[1], t[0], t[1], bound * (1.0 + 1e-9))
        d, off, n, k, done = sweep_distances(
            surface, passable, a, s[0], s[1], lo, hi, BUDGET, MAX_SWEEPS
        )
        cells = int(off[-1])
        rounds += 1
        relaxed += int(n)
        sweeps += int(k)
        if not done:
            return None
        length = d[off[t[0]] + t[1] - lo[t[0]]] if lo[t[0]] <= t[1] <= hi[t[0]] else INF
        if length <= bound or cells == rows * cols:
            break
        # the path found lies in R(length): the next round proves its optimum
        bound = length if length < INF else octile + 4.0 * (bound - octile)
    extra = {"engine": "sweep", "region_cells": cells, "sweeps": sweeps, "rounds": rounds}
    if length == INF:
        return np.empty((0, 2), dtype=np.int64), relaxed, extra
    path = _backtrack(surface, passable, a, s[0], s[1], t[0], t[1], lo, hi, off, d)
    return (path, relaxed, extra) if len(path) else None


def distances(surface, passable, a: float, source):
    """The exact shortest distances from the passable cell ``source`` to every cell of the map
    (float64, rows x cols, inf where it does not reach): step 2 of the module's method with the
    whole map as the region, so no bound is needed. The same values, bit for bit, as Dijkstra's
    algorithm computes with the same edge lengths (both are the one solution of ``d(v) = min_u
    d(u) + c(u, v)``, ``d(source) = 0``, in the same floating point), an order of magnitude
    faster on the large benchmark maps (CHANGELOG.md, "Measurements"). None when the
    relaxations passed :data:`BUDGET` times the map's cells (the caller then runs Dijkstra)."""
    rows, cols = surface.shape
    lo = np.zeros(rows, dtype=np.int64)
    hi = np.full(rows, cols - 1, dtype=np.int64)
    d, _, _, _, done = sweep_distances(
        surface, passable, a, int(source[0]), int(source[1]), lo, hi, BUDGET, WHOLE_MAP_SWEEPS,
    )  # fmt: skip
    return d.reshape(rows, cols) if done else None


# fixed-point distances (:func:`fixed_point_distances`): values at or above FIXED_CAP are held
# at it; FIXED_UNREACHED marks a cell not reached. A move must cost less than FIXED_UNREACHED -
# FIXED_CAP units (the caller's choice of units: pipeline.maps.landmarks.fixed_point_bits keeps it
# under 2^30), so that a cell next to a capped one is reached, and capped
FIXED_CAP = 2.0**31
FIXED_UNREACHED = 2**32 - 1


@njit(cache=True)
def fixed_units(a, bits):
    """The fixed point of whole units of ``a * 2^-bits``: a cell's length in units and the
    units ``(heights' scale, cap, not reached)`` the searches take (:data:`METRES` their float64
    metres)."""
    units = 2.0**bits
    return units, (units / a, FIXED_CAP, np.float64(FIXED_UNREACHED))


@njit(cache=True, nogil=True)
def fixed_point_distances(surface, passable, a: float, source, bits: int):
    """Distances from the passable cell ``source`` to every cell of the map in whole units of
    ``a * 2^-bits`` (uint32, rows x cols; :data:`FIXED_UNREACHED` where it does not reach), by
    the whole-map sweeps of :func:`distances` with each move's cost rounded down to a whole unit
    (:func:`whole_units`) and each distance held at :data:`FIXED_CAP`: 4 bytes a cell where
    float64 takes 8, for the landmark layers (:mod:`pipeline.maps.landmarks`, whose module doc has
    the bound's proof), on their :class:`Quantised` surface (``passable`` the same: each move's
    rise lowered by its cells' errors) or on a float32 one with NaN on its impassable cells.
    The sums are whole units, exact in float64: the distances are the exact ones, capped, of a
    graph whose every move is at most the planners' cost. None when the relaxations passed
    :data:`BUDGET` times the map's cells (the caller then runs Dijkstra)."""
    rows, cols = grid_shape(surface)
    lo = np.zeros(rows, dtype=np.int64)
    hi = np.full(rows, cols - 1, dtype=np.int64)
    off = np.arange(rows + 1) * np.int64(cols)
    d = np.full(rows * cols, FIXED_UNREACHED, dtype=np.uint32)
    units, u = fixed_units(a, bits)
    _, _, done = _sweeps(
        surface, passable, units, u, source[0], source[1], lo, hi, off, d, BUDGET, WHOLE_MAP_SWEEPS
    )
    return d.reshape(rows, cols) if done else None
