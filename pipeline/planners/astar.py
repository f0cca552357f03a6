"""Dijkstra, A* and weighted A* (docs/method.md section 5): the grid core's A* search with
weight 0, 1 and ``omega`` on the octile heuristic (or the landmark bound where it is larger),
ties broken towards the goal."""

from __future__ import annotations

from . import sweep
from .base import Planner, Search
from .search import NO_GOAL, TIE, landmark_rows, search_arrays, search_kernel

# A* (weight 1) over windows of at least this many cells (a whole map, ``mcpc=False``, and the
# exact coarse search of astar and dijkstra missions) runs as row sweeps over a bounded region
# (:mod:`.sweep`): the same optimal length, faster than the two-level A* and than pyastar2d
# on the large benchmark maps (benchmarks/RESULTS.md, "The exact search over the whole map").
# From 2^16 cells on the sweeps are the faster, below A* (an MCPC section's window: 125^2 cells
# at 30 m). Not on flat ground between the two ends (:func:`.sweep.flat_between`), where A*
# follows the straight line and is the faster (CHANGELOG.md, "Measurements")
SWEEP_CELLS = 2**16


def _weighted(weight_of):
    def search(surface, ridge, passable, a, s, t, omega, landmarks=None) -> Search:
        """The search's state is read (``trace_path``) before this thread searches again: its
        arrays are the thread's own (:func:`~.core.search_arrays`), kept for the next search
        (the coarse search of every mission on a map). A* from :data:`SWEEP_CELLS` cells on is
        the sweeps' search, which needs no heuristic (the landmark layers go unused), but on
        flat ground; A* runs only there and where they give up (:data:`.sweep.BUDGET`)."""
        weight = weight_of(omega)
        if (
            weight == 1.0
            and surface.size >= SWEEP_CELLS
            and not sweep.flat_between(surface, passable, a, s, t)
        ):
            got = sweep.search(surface, passable, a, s, t)
            if got is not None:
                cells, relaxed, extra = got
                return Search(
                    None, relaxed, len(cells) > 0, lambda length: length / (1.0 + TIE), extra, cells
                )
        state, _, expansions, found = search_kernel(surface.size)(
            surface,
            ridge,
            passable,
            a,
            s[0],
            s[1],
            t[0],
            t[1],
            weight,
            0.0,
            True,
            landmark_rows(landmarks, surface.shape),
            NO_GOAL,
            *search_arrays(surface.size, reuse=True),
        )
        # A* (tie-broken) is within 1 + TIE of L*, weighted A* within omega (1 + TIE)
        w = max(weight, 1.0)
        return Search(state, expansions, found, lambda length: length / (w * (1.0 + TIE)))

    return search


DIJKSTRA = Planner("dijkstra", _weighted(lambda omega: 0.0), "optimal, no heuristic", optimal=True)
ASTAR = Planner(
    "astar",
    _weighted(lambda omega: 1.0),
    "optimal, octile or landmark heuristic",
    True,
    optimal=True,
)
WASTAR = Planner("wastar", _weighted(float), "weighted A*: length <= omega * L*", True)
