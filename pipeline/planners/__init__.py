"""Planners on one in-memory window (SPEC sections 4, 5): the grid core and the searches.

Available now: ``dijkstra``, ``astar`` (optimal), ``wastar`` (weighted A*, bound omega) and
``ra_star`` (the paper's RA*, bound omega). ``lagrangian`` (issue 5) is not implemented yet and
raises a clear error.
"""

from .grid import PLANNERS, Trajectory, plan_window

__all__ = ["PLANNERS", "Trajectory", "plan_window"]
