"""What a planner is to the registry (:class:`Planner`) and what its search returns
(:class:`Search`): a new planner is one module that defines a :class:`Planner`, and one line
in :mod:`.registry`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Search:
    """What a planner's search returns to :func:`pipeline.plan_window`."""

    state: np.ndarray | None  # the search state the path is traced from (``trace_path``)
    expansions: int
    found: bool
    lower_bound: Callable[[float], float]  # a proven lower bound on L*, given the path length
    extra: dict = field(default_factory=dict)
    cells: np.ndarray | None = None  # the path itself (k x 2), for a search without a state


@dataclass(frozen=True)
class Planner:
    """A planner of the registry: ``search(surface, ridge, passable, a, start, goal, omega,
    landmarks=None)`` returns a :class:`Search`; ``landmarks`` (k layers of landmark distances
    over the window) may strengthen its heuristic, never its result's bound."""

    name: str
    search: Callable[..., Search]
    summary: str
    uses_landmarks: bool = False  # whether ``landmarks`` serves its heuristic
    optimal: bool = False  # whether it returns a shortest path (omega plays no part)
