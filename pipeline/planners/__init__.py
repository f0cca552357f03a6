"""Planners on one in-memory window (SPEC sections 4, 5): the grid core and the searches.

``dijkstra`` and ``astar`` (optimal), ``wastar`` (weighted A*), ``ra_star`` (the paper's RA*)
and ``lagrangian`` (LARAC on off-ridge length under the length bound), the last three within
``length <= omega * L*``.
"""

from .grid import PLANNERS, Trajectory, plan_window

__all__ = ["PLANNERS", "Trajectory", "plan_window"]
