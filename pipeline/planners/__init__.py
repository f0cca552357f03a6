"""Planners on one in-memory window (docs/method.md sections 4, 5).

``core``: the graph, edge cost, heuristic, search state, A*, tracing, path metrics, endpoint
checks and ``Trajectory``; one module per planner (``astar``: dijkstra, astar, wastar;
``ra_star``; ``lagrangian``), each registered in ``registry.PLANNERS``; ``sweep``: the exact
search by row sweeps over a bounded region, ``astar``'s engine on large windows and the
landmark layers'; ``window``: ``plan_window``, which runs any of them. ``dijkstra`` and
``astar`` are optimal; ``wastar``, ``ra_star`` and ``lagrangian`` keep ``length <= omega * L*``.
"""

from ..trajectory import Trajectory
from .registry import PLANNERS
from .window import plan_window

__all__ = ["PLANNERS", "Trajectory", "plan_window"]
