"""A planned mission as every stage after the planners sees it: :class:`Trajectory`, its cells
and points, its length against the proven lower bound, its status and its flight.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np


class Status(StrEnum):
    """A mission's status: planned and proven within its bound (``OK``), planned but not
    proven (``UNCERTIFIED``, the proven ratio in the message) or not planned (``FAILED``, the
    reason in the message). Each is its string too (``Status.OK == "ok"``), as files and
    catalogs write it."""

    OK = "ok"
    UNCERTIFIED = "uncertified"
    FAILED = "failed"


@dataclass
class Trajectory:
    """A planned path and its metrics (docs/method.md section 8); lengths in metres."""

    cells: np.ndarray
    points: np.ndarray
    length_m: float
    ridge_length_m: float
    ridge_ratio: float
    lower_bound_m: float
    expansions: int
    runtime_s: float
    planner: str
    omega: float
    status: Status = Status.OK
    message: str = ""
    extra: dict = field(default_factory=dict)
    flight: object = None  # the flown track (pipeline.flight.vehicle.Flight), when computed
    keep_out: object = (
        None  # the keep-out zones it avoids (pipeline.constraints.zones.KeepOut), if any
    )
    max_depth_m: float | None = None  # the rated depth it was planned for, if any (metres)

    @property
    def certified_ratio(self) -> float:
        """``length_m / lower_bound_m``: the path is proven within this factor of the shortest
        safe path (NaN without a path, 1 for a path of one cell)."""
        if not (self.length_m == self.length_m) or not (self.lower_bound_m > 0):
            return 1.0 if self.length_m == 0 else math.nan
        return self.length_m / self.lower_bound_m

    @property
    def planned(self) -> bool:
        """Whether there is a path (status "ok" or "uncertified")."""
        return self.status in (Status.OK, Status.UNCERTIFIED)

    def __repr__(self) -> str:
        """One line: status, planner, length, the proven bound and ratio, ridge share, cells
        (and the flight's, when flown); the arrays are in ``cells``, ``points``."""
        if not self.planned:
            return f"Trajectory(failed, {self.planner}: {self.message})"
        flown = ""
        if self.flight is not None:
            flown = f", {self.flight!r}"
        return (
            f"Trajectory({self.status}, {self.planner} omega {self.omega:g}, "
            f"{self.length_m / 1e3:.3f} km <= {self.certified_ratio:.3f} x the proven bound "
            f"{self.lower_bound_m / 1e3:.3f} km, ridge {100 * self.ridge_ratio:.0f} %, "
            f"{len(self.cells)} cells{flown})"
        )

    def to_geodataframe(self):
        """The grid path as a GeoDataFrame (a point a cell: ``row``, ``col``, ``z`` on the
        safety surface) and, when flown, the flown route's waypoints (``waypoint``, ``z``,
        ``time_s``), in the maps' CRS when the trajectory knows it (``extra["crs_wkt"]``,
        which :func:`pipeline.plan` sets), with a ``kind`` column telling them apart."""
        import geopandas as gpd
        import pandas as pd

        crs = self.extra.get("crs_wkt")
        pts = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        grid = gpd.GeoDataFrame(
            {
                "kind": "grid path",
                "row": np.asarray(self.cells)[:, 0] if len(self.cells) else [],
                "col": np.asarray(self.cells)[:, 1] if len(self.cells) else [],
                "z": pts[:, 2],
            },
            geometry=gpd.points_from_xy(pts[:, 0], pts[:, 1]),
            crs=crs,
        )
        f = self.flight
        if f is None:
            return grid
        w = np.asarray(f.waypoints, dtype=np.float64)
        route = gpd.GeoDataFrame(
            {"kind": "waypoint", "waypoint": np.arange(len(w)), "z": w[:, 2], "time_s": w[:, 3]},
            geometry=gpd.points_from_xy(w[:, 0], w[:, 1]),
            crs=crs,
        )
        return gpd.GeoDataFrame(pd.concat([grid, route], ignore_index=True), crs=crs)
