"""A mission planned in one in-memory window (:func:`plan_window`): any registered planner on
numpy arrays, its arguments checked, its result measured and certified by the planner's own
bound.
"""

from __future__ import annotations

import numpy as np

from .._types import Cell
from ..params import CELL_SIZE, PLANNING, check_planner
from ..planners.endpoints import check_arrays
from ..planners.window import search_window
from ..trajectory import Trajectory


def plan_window(
    surface: np.ndarray,
    ridge: np.ndarray,
    passable: np.ndarray,
    start: Cell,
    goal: Cell,
    *,
    cell_size: float,
    planner: str = PLANNING.planner.default,
    omega: float = PLANNING.omega.default,
    x: np.ndarray | None = None,
    y: np.ndarray | None = None,
    landmarks: np.ndarray | None = None,
) -> Trajectory:
    """Plan on one in-memory window.

    Parameters
    ----------
    surface : 2-D array
        The safety surface ``S`` (metres) the vehicle flies on.
    ridge, passable : 2-D bool arrays
        Ridge cells and passable cells.
    start, goal : (row, col)
    cell_size : float
        Metres.
    planner : str
        A name of the registry (:data:`pipeline.planners.PLANNERS`): ``"dijkstra"``,
        ``"astar"``, ``"wastar"``, ``"ra_star"``, ``"lagrangian"``.
    omega : float
        Length bound (>= 1) for the bounded planners.
    x, y : 1-D arrays, optional
        Map coordinates of the columns and rows for ``points`` (default: ``col * a``,
        ``row * a``).
    landmarks : array (k, rows, cols), optional
        Exact shortest-path distances from k landmark cells over this window's graph
        (:mod:`pipeline.maps.landmarks`; ``inf`` where a landmark does not reach): A*, weighted A*
        and the Lagrangian planner then use the landmark bound (made consistent) as their
        heuristic where it beats the octile distance. Distances over a larger map bound this
        window's too (a window's paths are paths of the map), so a window of a maps store may
        take its layers.

    Examples
    --------
    >>> t = plan_window(S, rdg, ok, (5, 5), (90, 120), cell_size=30.0, planner="astar")
    ... # doctest: +SKIP
    """
    planner, omega = check_planner(planner, omega)
    a = CELL_SIZE.check(cell_size)
    surface, ridge, passable = check_arrays(surface, ridge, passable)
    return search_window(surface, ridge, passable, start, goal, a, planner, omega, x, y, landmarks)
