"""Planners on one in-memory window (SPEC sections 4, 5): the grid core and the searches.

Available now: ``dijkstra``, ``astar`` (optimal) and ``wastar`` (weighted A*, bound omega).
``ra_star`` and ``lagrangian`` (issue 5) are not implemented yet and raise a clear error.
"""

from .grid import PLANNERS, Trajectory, plan_window

__all__ = ["PLANNERS", "Trajectory", "plan_window"]
