"""The vehicle a mission is flown by (:class:`Vehicle`: speed, pitch limit, turn radius, the
waypoint band, power and battery) and what its flight is (:class:`Flight`: the flown track,
the waypoints, timing, energy and the figures of the flight against the seabed).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from ..exceptions import InvalidParameterError
from ..params import VEHICLE

DEFAULT_TURN_RADIUS_MAX_M = 50.0


@dataclass(frozen=True)
class Vehicle:
    """The vehicle's limits and, optionally, its energy model ([vehicle] in job files)."""

    speed_m_s: float = VEHICLE.speed_m_s.default
    max_pitch_deg: float = VEHICLE.max_pitch_deg.default
    min_turn_radius_m: float | None = None  # default: min(cell side, 50 m)
    waypoint_band_m: float | None = None  # default: R/4, R/2 or R (fly)
    hotel_power_w: float | None = None
    propulsion_power_w: float | None = None
    battery_wh: float | None = None
    max_depth_m: float | None = None  # the rated depth (metres, positive down)
    max_leg_m: float | None = None  # the longest leg between two waypoints

    def __post_init__(self):
        for p in VEHICLE:
            v = getattr(self, p.name)
            if v is None and p.default is None:
                continue
            object.__setattr__(self, p.name, p.check(v, f"vehicle.{p.name}"))
        power = (self.hotel_power_w, self.propulsion_power_w)
        if self.battery_wh is not None and all(v is None for v in power):
            raise InvalidParameterError(
                "vehicle.battery_wh is given without a power: give hotel_power_w and/or "
                "propulsion_power_w (W) so that the mission's energy can be computed"
            )

    @classmethod
    def of(cls, value) -> Vehicle:
        """A Vehicle from None (the defaults), a Vehicle or a dict of VEHICLE's keys."""
        if value is None:
            return cls()
        if isinstance(value, Vehicle):
            return value
        if isinstance(value, dict):
            unknown = sorted(set(value) - VEHICLE.names())
            if unknown:
                raise InvalidParameterError(
                    f"unknown vehicle key {unknown[0]!r}; allowed: {sorted(VEHICLE.names())}"
                )
            return cls(**value)
        raise InvalidParameterError(
            f"`vehicle` must be a Vehicle or a dict of {sorted(VEHICLE.names())}, got {value!r}"
        )

    def turn_radius(self, cell_size: float) -> float:
        """The minimum turn radius in metres (the default: one cell side, at most 50 m)."""
        if self.min_turn_radius_m is not None:
            return float(self.min_turn_radius_m)
        return float(min(cell_size, DEFAULT_TURN_RADIUS_MAX_M))

    @property
    def power_w(self) -> float | None:
        """Hotel plus propulsion power at cruise speed, None when no power is given."""
        p = [v for v in (self.hotel_power_w, self.propulsion_power_w) if v is not None]
        return float(sum(p)) if p else None

    def to_dict(self) -> dict:
        return {k: v for k, v in asdict(self).items() if v is not None}


@dataclass
class Flight:
    """The track a vehicle flies for one mission; lengths in metres, heights positive up.

    Dense samples (no two more than half a cell apart): ``x``, ``y`` (map coordinates),
    ``z`` (vehicle height), ``s`` (horizontal distance along the track), ``time_s``,
    ``seabed_m`` (DEM interpolated bilinearly under the vehicle), ``required_m`` (the lowest
    height keeping the clearance there), ``altitude_m`` (``z - seabed_m``). Waypoints:
    ``waypoints`` (k x 4: x, y, z, time_s) and ``waypoint_index`` (their sample indices)."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    s: np.ndarray
    time_s: np.ndarray
    seabed_m: np.ndarray
    required_m: np.ndarray
    waypoints: np.ndarray
    waypoint_index: np.ndarray
    vehicle: Vehicle
    turn_radius_m: float  # the minimum the vehicle was given
    flown_length_m: float
    route_length_m: float  # the waypoints' straight 3-D legs
    waypoint_band_m: float  # how far above their route's lowest profile the legs may fly
    grid_length_m: float
    duration_s: float
    max_pitch_deg: float  # the steepest flown
    min_turn_radius_m: float  # the tightest turn flown (inf: no turn)
    ridge_ratio: float  # share of the flown track's length over ridge cells (horizontally)
    energy_wh: float | None
    surface_limit_m: float
    smoothing: str  # "shortcuts", "loose shortcuts", "straight shortcuts", "path vertices", ...
    problems: list = field(default_factory=list)
    over_bound: str = ""  # the problem saying the flown length exceeds the bound, if it does
    seconds: float = 0.0
    route: np.ndarray | None = None  # the waypoint route sampled: x, y, z (waypoints' legs)
    route_seabed_m: np.ndarray | None = None
    altitude_median_m: float = math.nan  # above the seabed along the flown track
    altitude_p90_m: float = math.nan
    altitude_min_m: float = math.nan
    reversals_per_km: float = math.nan  # climb to descent or back, per km flown
    # samples (of the track and the route) within R of a grid square with a no-data corner
    unknown_seabed_samples: int = 0
    short_legs: int = 0  # waypoint legs shorter than the minimum turn radius
    # the least clearance of the route and the track from the continuous seabed (the maps'
    # elevation layer), measured at every sample on a lattice of each grid square
    # (:func:`seabed_clearance`)
    min_clearance_m: float = math.nan
    # the rated depth kept (metres, positive down; None: no rating), and the horizontal length
    # where it binds (the lowest safe height lies deeper: the vehicle flies no deeper than it)
    max_depth_m: float | None = None
    at_rated_depth_m: float = 0.0
    # for each via point (its cell's centre a waypoint), the flown track's closest approach
    via_miss_m: list = field(default_factory=list)
    # where the flight broke a limit it can place (map x, y; rows): samples over unknown
    # seabed or above the surface limit, corners turning tighter than the vehicle can
    trouble_xy: np.ndarray | None = None
    # where the smoothing that keeps the ridges broke such a limit, when another was flown
    ridge_trouble_xy: np.ndarray | None = None

    @property
    def altitude_m(self) -> np.ndarray:
        return self.z - self.seabed_m

    @property
    def ok(self) -> bool:
        return not self.problems

    def __repr__(self) -> str:
        """One line: flyable or the number of problems, flown length and duration,
        waypoints, the least clearance and altitude; the arrays are in the fields."""
        state = "ok" if self.ok else f"{len(self.problems)} problems"
        return (
            f"Flight({state}, {self.flown_length_m / 1e3:.3f} km in "
            f"{self.duration_s / 3600:.2f} h, {len(self.waypoints)} waypoints, min clearance "
            f"{self.min_clearance_m:.1f} m, altitude median {self.altitude_median_m:.0f} m)"
        )

    def to_dataframe(self):
        """The flown track as a pandas DataFrame, a row a sample: ``x``, ``y``, ``z``,
        ``s_m``, ``time_s``, ``seabed_m``, ``required_m``, ``altitude_m``."""
        import pandas as pd

        return pd.DataFrame(
            {
                "x": self.x,
                "y": self.y,
                "z": self.z,
                "s_m": self.s,
                "time_s": self.time_s,
                "seabed_m": self.seabed_m,
                "required_m": self.required_m,
                "altitude_m": self.altitude_m,
            }
        )
