"""The planners, by name: a new planner is one module with a :class:`~.core.Planner` and one
line here."""

from __future__ import annotations

from . import astar, lagrangian, ra_star
from .base import Planner

PLANNERS: dict[str, Planner] = {
    p.name: p
    for p in (
        astar.DIJKSTRA,
        astar.ASTAR,
        astar.WASTAR,
        ra_star.RA_STAR,
        lagrangian.LAGRANGIAN,
    )
}
