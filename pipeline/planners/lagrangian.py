"""The Lagrangian ridge planner (docs/method.md section 5, beyond the paper).

Maximising ridge length under ``length <= omega * L*`` is a constrained shortest path problem:
minimise the off-ridge length subject to the length bound. Lagrangian relaxation turns it into
a sequence of plain shortest paths on ``off_ridge + lambda * length`` (no negative weights),
solved as A* on ``length + off_ridge / lambda`` (the same order for lambda > 0, and the plain
length heuristic stays admissible and consistent). ``lambda`` follows the LARAC rule (Juettner
et al. 2001): keep the best feasible path P_d and the best infeasible one P_c, set
``lambda = (off(P_d) - off(P_c)) / (len(P_c) - len(P_d))`` and stop when the relaxed optimum no
longer improves on P_c. Every path found is a shortest path for some weighting, hence
Pareto-optimal between length and off-ridge length. The feasible one with the most ridge is
returned, with the dual lower bound on the off-ridge length in ``extra``.
"""

from __future__ import annotations

import math

import numpy as np

from ..runtime.jit import njit
from .astar import ASTAR
from .base import Planner, Search
from .bounds import lagrangian_bound, off_ridge_to_goal, raised_bound
from .paths import trace_path
from .search import NO_GOAL, TIE, edge_cost, heuristic, landmark_rows, search_arrays, search_kernel

# lambda -> 0 end: off-ridge length first, length only as a tie-break
_OFF_FIRST = 1e7


@njit(nogil=True, cache=True)
def _horizontal(cells, a):
    """The horizontal length of a path: its straight and diagonal moves counted, the sum as
    numpy's diff, abs, sum and masks formed it (equal to the last bit on 900 random paths, and
    many times faster, once a section)."""
    straight = 0
    diagonal = 0
    for i in range(cells.shape[0] - 1):
        d = abs(cells[i + 1, 0] - cells[i, 0]) + abs(cells[i + 1, 1] - cells[i, 1])
        if d == 1:
            straight += 1
        elif d == 2:
            diagonal += 1
    return a * (straight + math.sqrt(2.0) * diagonal)


@njit(nogil=True, cache=True)
def _measure(cells, surface, ridge, a):
    """(length, off-ridge length) of a path: its steps' costs (``edge_cost``, the planners' own
    3-D length of a move) summed in one pass, a step off the ridge network where it ends off
    it, several paths a section: numpy's version (gather the heights, the steps, the mask, two
    sums) took about ten times as long (CHANGELOG.md, "Measurements")."""
    length = 0.0
    off = 0.0
    for i in range(cells.shape[0] - 1):
        r, c = cells[i + 1, 0], cells[i + 1, 1]
        step = edge_cost(surface, a, cells[i, 0], cells[i, 1], r, c)
        length += step
        if not ridge[r, c]:
            off += step
    return length, off


# A weighted search whose off-ridge weight is below this (length counts more than off-ridge
# length) bounds the length term by the exact length to the goal (:func:`goal_layer`), from
# then on in the mission's window: such a search expands far fewer cells, for a backward
# search costing about two of them, which pays at omega 1 and costs nothing at larger omegas
# only below this weight (CHANGELOG.md, "Measurements"). Memory: 4 bytes a cell of the window
# kept, 13 while the backward search runs (each weighted search keeps 9 of its own).
EXACT_BELOW = 1.0


# The weighted searches take bounds of their own (lagrangian_bound) only where the shortest
# path's 3-D length exceeds its horizontal length by at most this fraction: the bound is one on
# the horizontal plane, and its search settles most of the window at about a quarter of an
# expansion's cost a cell, so it pays only where the ground's rise and fall leaves little
# slack: on the benchmark missions' sections the slack is small and the bound cuts a search
# tenfold; on whole windows of steep ground it is large and the bound cost more than it saved
# (CHANGELOG.md, "Measurements").
BOUND_SLACK = 0.05


# The weighted searches of a window take one lagrangian_bound, of this many times the first
# weighted search's weight: it serves the smaller weights as it is, the larger raised
# (:func:`raised_bound`, a pass over the window instead of a search), rather than one bound per
# weight above the largest so far: faster, with the same lengths and off-ridge lengths on every
# window; twice the first weight was the best of the factors tried (CHANGELOG.md,
# "Measurements").
JOINT = 2.0


def goal_layer(lm, surface, passable, a, t):
    """The landmark rows ``lm`` and one more: the exact length from every cell of the window to
    the goal ``t`` (:func:`pipeline.planners.bounds.dijkstra` from it; the graph is symmetric), the
    goal as its own landmark. Its bound ``|d(v) - d(t)| = d(v)`` is the exact length to the goal,
    made consistent as every landmark's (``landmark_shrink``), where the octile distance ignores
    the terrain's rise and fall."""
    from .bounds import dijkstra

    rows, cols = surface.shape
    dg = dijkstra(surface, passable, a, np.array([t[0] * cols + t[1]], dtype=np.int64))
    out = np.empty((lm.shape[0] + 1, rows * cols), dtype=np.float32)
    if lm.shape[0]:
        out[: lm.shape[0]] = lm
    out[lm.shape[0]] = dg.reshape(-1)
    return out


def larac(surface, ridge, passable, a, s, t, omega, max_iter: int = 30, landmarks=None):
    """(search state of the chosen path, expansions, found, extra) for ``plan_window``.
    Every search may use the landmark bound: a bound on the length bounds every weighted
    cost too (an edge costs at least its length). The weighted searches add the off-ridge
    bound to the goal (:func:`off_ridge_to_goal`, one backward search for all of them): on the
    benchmark sections they expand 2.3x fewer cells, in half the time."""
    cols = surface.shape[1]
    expansions = 0
    lm = landmark_rows(landmarks, surface.shape)
    hoff = None  # the off-ridge bound to the goal, for the weighted searches' heuristic
    exact = False  # whether ``lm`` holds the lengths to the goal (:func:`goal_layer`)
    joint = None  # (a weight, its lagrangian_bound)
    fresh = False  # whether the weighted searches take a lagrangian_bound (BOUND_SLACK)

    def search(off_weight):
        nonlocal expansions, hoff, lm, exact, joint, fresh
        if off_weight > 0 and hoff is None:  # one backward search serves every weighting
            hoff = off_ridge_to_goal(ridge, passable, a, t[0], t[1], s[0], s[1])
        if 0 < off_weight < EXACT_BELOW and not exact:
            lm = goal_layer(lm, surface, passable, a, t)
            exact = True
        h = hoff if off_weight > 0 else NO_GOAL
        if fresh and off_weight > 0 and off_weight != _OFF_FIRST and lm.shape[0] == 0:
            # a bound on both terms at once (:func:`lagrangian_bound`; the off-first search has
            # hoff's), one a window (JOINT): it serves every smaller weight, raised to a larger
            if joint is None:
                w0 = JOINT * off_weight
                joint = (w0, lagrangian_bound(ridge, passable, a, s[0], s[1], t[0], t[1], w0, hoff))
            if off_weight <= joint[0]:
                h = joint[1]
            else:
                h = raised_bound(joint[1], hoff, joint[0], off_weight, *surface.shape, *t, a)
        parent, _, exp, found = search_kernel(surface.size)(
            surface,
            ridge,
            passable,
            a,
            s[0],
            s[1],
            t[0],
            t[1],
            1.0,
            off_weight,
            True,
            lm,
            h,
            *search_arrays(surface.size),  # new ones: the searches' states are kept
        )
        expansions += exp
        if not found:
            return None
        cells = trace_path(parent, cols, t)
        return parent, cells, *_measure(cells, surface, ridge, a)

    # the least off-ridge path first: where its length is within omega times the octile
    # distance (a lower bound on L*) it is the answer, and the shortest path is not searched;
    # the same answer as with L* (such a path is feasible for any L* at least the octile
    # distance). On the benchmark missions' sections that is most windows whose answer it is,
    # a search saved each time (CHANGELOG.md, "Measurements")
    off_first = search(_OFF_FIRST)
    if off_first is None:
        return None, expansions, False, {}
    extra = {"searches": 1, "lambda": None}
    if off_first[2] <= omega * heuristic(a, s[0], s[1], t[0], t[1], True):
        extra.update(dual_bound_off_ridge_m=off_first[3], lambda_=0.0)
        return off_first[0], expansions, True, extra
    shortest = search(0.0)
    optimum = shortest[2]
    fresh = optimum - _horizontal(shortest[1], a) <= BOUND_SLACK * optimum
    bound = omega * optimum
    feasible = shortest
    extra.update(optimum_m=optimum, searches=2)
    if off_first[2] <= bound:
        extra.update(dual_bound_off_ridge_m=off_first[3], lambda_=0.0)
        return off_first[0], expansions, True, extra
    infeasible = off_first
    dual = 0.0
    for _ in range(max_iter):
        # P_d (feasible) is shorter with more off-ridge, P_c (infeasible) the reverse
        dlen = infeasible[2] - feasible[2]
        doff = feasible[3] - infeasible[3]
        if dlen <= 0 or doff <= 0:
            break
        lam = doff / dlen  # the weighting under which P_c and P_d cost the same
        r = search(1.0 / lam)
        extra["searches"] += 1
        value_r = r[3] + lam * r[2]
        value_c = infeasible[3] + lam * infeasible[2]
        dual = max(dual, value_r - lam * bound)
        extra["lambda"] = lam
        if value_r >= value_c * (1.0 - 1e-12):
            break  # no weighting improves on the bracket: LARAC's stop
        if r[2] <= bound:
            if r[3] < feasible[3]:
                feasible = r
        else:
            infeasible = r
    extra["dual_bound_off_ridge_m"] = max(dual, 0.0)
    return feasible[0], expansions, True, extra


def _search(surface, ridge, passable, a, s, t, omega, landmarks=None) -> Search:
    state, expansions, found, extra = larac(
        surface, ridge, passable, a, s, t, float(omega), landmarks=landmarks
    )
    cols = surface.shape[1]

    def lower_bound(length):
        # the shortest path's A* length is within 1 + TIE of L*; where the planner did not
        # need it (the least off-ridge path was short enough), it is searched now, when a
        # caller asks for the bound (not counted in the expansions, which chose the path: in
        # ``bound_expansions``)
        if found and "optimum_m" not in extra:
            got = ASTAR.search(surface, ridge, passable, a, s, t, 1.0, landmarks)
            cells = got.cells if got.cells is not None else trace_path(got.state, cols, t)
            extra["optimum_m"] = _measure(cells, surface, ridge, a)[0]
            extra["bound_expansions"] = int(got.expansions)
        return extra.get("optimum_m", 0.0) / (1.0 + TIE)

    return Search(state, expansions, found, lower_bound, extra)


LAGRANGIAN = Planner(
    "lagrangian",
    _search,
    "most ridge under length <= omega * L* (Lagrangian relaxation, LARAC)",
    True,
)
