"""The planners, each on one window of arrays (docs/method.md sections 4, 5): the grid search
they share (:mod:`.search`: graph, edge cost, heuristic, A*), proven lower bounds
(:mod:`.bounds`), endpoint checks (:mod:`.endpoints`), path tracing and metrics (:mod:`.paths`),
one module per planner (:mod:`.astar`: dijkstra, astar, wastar; :mod:`.ra_star`;
:mod:`.lagrangian`), each registered in :data:`.registry.PLANNERS` (a :class:`.base.Planner`);
:mod:`.sweep`: the exact search by row sweeps over a bounded region, ``astar``'s engine on
large windows and the landmark layers'; :mod:`.window`: any of them on one window.
``dijkstra`` and ``astar`` are optimal; ``wastar``, ``ra_star`` and ``lagrangian`` keep
``length <= omega * L*``.
"""

from .._lazy import submodules

__getattr__ = submodules(__name__)
