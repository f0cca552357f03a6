"""Any registered planner on one window of arrays (:func:`search_window`, :func:`search_path`):
the search and its path, traced and measured, for a mission planned in one window and for
each MCPC section.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..exceptions import UnreachableGoalError
from ..trajectory import Trajectory
from .endpoints import check_endpoint
from .paths import measured_path, traced_path
from .registry import PLANNERS
from .search import heuristic


@dataclass(frozen=True)
class PathSearch:
    """What :func:`search_path` found: the path's cells, the surface height and ridge flag on
    each, its metrics and the search's bound, expansions, time and extra."""

    cells: np.ndarray
    z: np.ndarray
    on_ridge: np.ndarray
    length_m: float
    ridge_length_m: float
    ridge_ratio: float
    lower_bound_m: float
    expansions: int
    runtime_s: float
    extra: dict


def search_path(
    surface,
    ridge,
    passable,
    start,
    goal,
    a,
    planner,
    omega,
    landmarks=None,
    offset=(0, 0),
    bound: bool = True,
) -> PathSearch:
    """The search of :func:`search_window` and the path's metrics, without the path's
    coordinates: an MCPC section needs the heights only (the coordinates were a fifth of a
    section's time outside its search). The cells
    come offset by ``offset`` (a section's window's first row and column: the map's cells),
    the heights as float64. Without ``bound`` (an MCPC section, whose mission has a bound of
    its own) ``lower_bound_m`` is the octile distance: the planner's own bound may cost a
    search (the Lagrangian planner's shortest path, where it did not need it)."""
    s = check_endpoint("start", start, passable)
    t = check_endpoint("goal", goal, passable)
    t0 = time.perf_counter()
    search = PLANNERS[planner].search(surface, ridge, passable, a, s, t, omega, landmarks)
    runtime = time.perf_counter() - t0
    if not search.found:
        raise UnreachableGoalError(
            f"no path from start {s} to goal {t} through passable "
            "cells: they lie in separate regions"
        )
    if search.cells is not None:
        cells, z, on_ridge, length, ridge_len, ratio = measured_path(
            search.cells, surface, ridge, a, offset
        )
    else:
        cells, z, on_ridge, length, ridge_len, ratio = traced_path(
            search.state, surface.shape[1], t, surface, ridge, a, offset
        )
    # the planner's proven bound, or the octile distance when that is larger
    lower = heuristic(a, s[0], s[1], t[0], t[1], True)
    if bound:
        lower = max(search.lower_bound(length), lower)
    return PathSearch(
        cells=cells,
        z=z,
        on_ridge=on_ridge,
        length_m=length,
        ridge_length_m=ridge_len,
        ridge_ratio=ratio,
        lower_bound_m=float(lower),
        expansions=int(search.expansions),
        runtime_s=runtime,
        extra=search.extra,
    )


def search_window(
    surface, ridge, passable, start, goal, a, planner, omega, x=None, y=None, landmarks=None
) -> Trajectory:
    """:func:`plan_window` on arrays :func:`check_arrays` returned (2-D, of one shape, bool
    masks, the surface finite where passable) with a checked cell size, planner and omega:
    for arrays checked once and searched many times (a maps store's coarse level, which
    every mission searches: the check of its million cells is not free)."""
    p = search_path(surface, ridge, passable, start, goal, a, planner, omega, landmarks)
    cells = p.cells
    xs = np.asarray(x, dtype=np.float64) if x is not None else np.arange(surface.shape[1]) * a
    ys = np.asarray(y, dtype=np.float64) if y is not None else np.arange(surface.shape[0]) * a
    points = np.column_stack([xs[cells[:, 1]], ys[cells[:, 0]], p.z])
    return Trajectory(
        cells=cells,
        points=points,
        length_m=p.length_m,
        ridge_length_m=p.ridge_length_m,
        ridge_ratio=p.ridge_ratio,
        lower_bound_m=p.lower_bound_m,
        expansions=p.expansions,
        runtime_s=p.runtime_s,
        planner=planner,
        omega=float(omega),
        extra=p.extra,
    )
