"""From a planned grid path to a track a vehicle can fly (``fly``): any-angle shortcuts, turns
rounded to the vehicle's radius, a pitch-limited near-bottom depth profile clear of the
continuous seabed, waypoints, timing and energy (docs/flyable-missions.md).

The planned path is a chain of grid cells on the safety surface. A vehicle flies neither cell
centres nor 45-degree staircases, and it cannot climb at 70 degrees. ``fly`` turns the path
into a track in steps, every one checked against the terrain itself (the DEM, not the safety
layer):

1. **Shortcuts** (string pulling): from each kept corner of the path, the farthest later one
   that a straight leg reaches over usable cells (passable, no corner cutting, terrain known
   around them) without flying more off the ridge cells than the path did.
2. **Route**: the corners simplified once more (a leg may skip corners it passes within
   a tolerance of, ``ROUTE_SIMPLIFICATIONS``): the waypoints' horizontal positions.
3. **Turns**: corners too close for the turn radius are cut where a straight leg between
   their neighbours is usable; every other corner is rounded by a circular arc of the
   vehicle's minimum turn radius (never tighter), tangent to both legs: the flown track.
4. **Required heights**: along the waypoint route and the flown track, sampled every half
   cell at most, the lowest height ``h(p)`` that keeps the clearance of the maps' method from
   the continuous seabed (bilinear between the DEM's grid points), conservatively: a grid
   square's seabed is at most its highest corner, within the square's diagonal of any of its
   points (:func:`required_heights`); the samples' spacing and ``R'`` slightly above ``R``
   make it hold between samples and on the arcs too (:func:`_sampling`).
5. **Depth profile and waypoints**: one profile along the route's straight legs, linear
   between waypoints (what an autopilot flies): few straight pieces inside a band above the
   lowest pitch-limited profile over ``h`` (``band_profile``; the arcs' samples bind the route
   around them, and over a turn the slope is limited so that the arc keeps the pitch); the
   waypoints are the route's corners and the pieces' ends, and the flown track (the route
   with its turns) takes its heights from the route (:func:`vertical_profile`).

If the smoothed track breaks a limit (terrain unknown near a shortcut, the profile forced
above the surface clearance, or a flown length above ``omega`` times the proven lower bound),
``fly`` falls back to the path's own corners, then to the grid path without arcs; what still
breaks a limit is listed in ``Flight.problems``.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from .._types import Maps, VehicleLike
from ..runtime.jit import njit
from ..runtime.threads import shared_pool

if TYPE_CHECKING:
    from ..trajectory import Trajectory
from ..exceptions import InvalidParameterError
from ..params import VEHICLE

# -------------------------------------------------------------------------- the vehicle

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


# -------------------------------------------------------------------------- the flown track


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
    ridge_ratio: float  # share of the flown 3-D length over ridge cells
    energy_wh: float | None
    surface_limit_m: float
    smoothing: str  # "shortcuts", "path vertices" or "grid path"
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
    # the least clearance of the route and the track from the continuous seabed, measured on
    # a lattice of each grid square (:func:`seabed_clearance`)
    min_clearance_m: float = math.nan

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


# the flown track and the waypoint legs are sampled (and checked) every SAMPLE_STEP cells at
# most, closer where the clearance is small against the cell (CLEARANCE_SLACK)
SAMPLE_STEP = 0.5
CLEARANCE_SLACK = 2e-3
# the profile's breaks are kept this share beyond a turn radius apart, so that the legs stay
# at least a turn radius long as their files write them (coordinates rounded)
LEG_MARGIN = 0.01
# waypoint legs may fly above the lowest profile of their route by up to a band: by default the
# narrowest of these shares of the clearance that needs at most WAYPOINT_SHARE waypoints per
# grid path cell (fewer waypoints for a little more altitude); [vehicle] waypoint_band_m fixes it
WAYPOINT_BANDS = (0.25, 0.5, 1.0)
WAYPOINT_SHARE = 0.1
# the waypoint route may leave the shortcut path by up to a tolerance (cells) to skip small
# wiggles, its legs flying off the ridge cells for up to a share of their length more than the
# path: the first of these that leaves at most three quarters of the waypoints to corners, and
# never more than the last (the ridge cover then drops by about ten points at most, measured)
ROUTE_SIMPLIFICATIONS = ((2.0, 0.02), (2.0, 0.05), (3.0, 0.1), (4.0, 0.2), (4.0, 0.3))
_LEVELS = np.array(ROUTE_SIMPLIFICATIONS, dtype=np.float64)

# the maps' clearance methods, as the kernels know them
_METHOD = {"vertical": 0, "horizontal": 1, "spherical": 2}


@njit(inline="always", cache=True)
def _tile_of(i, t):
    """``i // t`` for ``0 <= i < 2^32``, ``t > 0`` (a row or column and the tiles' side): a
    32-bit unsigned division, which costs the flight's kernels several times less than
    Python's 64-bit floor division (with its sign fix-up)."""
    return np.int64(np.uint32(i) // np.uint32(t))


@njit(inline="always", cache=True)
def _cell(slot, tiles, tr, tc, i, j, missing):
    if i < 0 or j < 0:  # (a 32-bit division of a negative row would index far off the table)
        return missing
    ti = _tile_of(i, tr)
    tj = _tile_of(j, tc)
    s = slot[ti, tj]
    if s < 0:
        return missing
    return tiles[s, i - ti * tr, j - tj * tc]


@njit(cache=True, _nrt=False)
def _usable(pas, slot, tr, tc, rows, cols, pad, i, j):
    """Passable, and the terrain known within ``pad`` cells (its tiles are loaded).

    Compiled on its own (``_nrt=False``: it allocates nothing), not inlined: :func:`_walk`
    calls it three times, and numba's inlining typed its body at each call, for each of the
    walk's two signatures: the walk took 9.9 s to compile on a new machine, now 4.4 s with this
    (2.2 s), and ``fly`` takes the same time (29 ms a mission across 4000^2)."""
    if i < 0 or j < 0 or i >= rows or j >= cols:
        return False
    ti = _tile_of(i, tr)
    tj = _tile_of(j, tc)
    s = slot[ti, tj]
    ri = i - ti * tr
    rj = j - tj * tc
    if s < 0 or not pas[s, ri, rj]:
        return False
    if pad <= ri < tr - pad and pad <= rj < tc - pad:
        return True  # the cells within pad all lie in this tile (most cells: 4 lookups saved)
    i0 = max(i - pad, 0)
    i1 = min(i + pad, rows - 1)
    j0 = max(j - pad, 0)
    j1 = min(j + pad, cols - 1)
    return (
        slot[_tile_of(i0, tr), _tile_of(j0, tc)] >= 0
        and slot[_tile_of(i0, tr), _tile_of(j1, tc)] >= 0
        and slot[_tile_of(i1, tr), _tile_of(j0, tc)] >= 0
        and slot[_tile_of(i1, tr), _tile_of(j1, tc)] >= 0
    )


@njit(inline="always", cache=True)
def _samples(dr, dc):
    """How many pieces a segment of ``dr`` rows and ``dc`` columns is walked in: 4 a cell along
    its longer side (one count for :func:`_walk` and :func:`_off_ridge`, so that
    :func:`leg_allowed` measures the off-ridge length as :func:`_off_ridge` does)."""
    return max(1, int(math.ceil(max(abs(dr), abs(dc)) * 4.0)))


@njit(cache=True, _nrt=False)
def _walk(pas, rdg, slot, tr, tc, rows, cols, pad, ar, ac, br, bc, most, rate, count):
    """``(ok, off)``: whether the straight segment between two points (grid units: row, col)
    crosses only usable cells, without cutting a corner between two cells it passes diagonally
    (samples 4 a cell), and, with ``count``, its off-ridge length (:func:`_off_ridge`'s samples,
    in turn with those) stays at most ``most`` and at most ``rate`` times its length; ``off``
    the off-ridge length summed so far. It stops at the first unusable cell or once the
    off-ridge length so far is over a limit (it only grows, and is compared after every piece,
    the last included: with infinite limits the walk sums it all, and ``ok and not (off >
    most or off / length > rate)`` is then the answer for any limits)."""
    dr = br - ar
    dc = bc - ac
    n = _samples(dr, dc)
    ln = math.hypot(dr, dc)
    piece = ln / n
    seg = 0.0
    pi = -(10**9)
    pj = -(10**9)
    poi = -(10**9)  # the cell of the last off-ridge sample, and whether it is off the ridge
    poj = -(10**9)
    off = True
    for k in range(n + 1):
        t = k / n
        i = int(math.floor(ar + t * dr + 0.5))
        j = int(math.floor(ac + t * dc + 0.5))
        if i != pi or j != pj:
            if not _usable(pas, slot, tr, tc, rows, cols, pad, i, j):
                return False, seg
            if k > 0 and i != pi and j != pj:
                if not (
                    _usable(pas, slot, tr, tc, rows, cols, pad, pi, j)
                    and _usable(pas, slot, tr, tc, rows, cols, pad, i, pj)
                ):
                    return False, seg
            pi = i
            pj = j
        if k == n or not count:
            continue
        oi, oj = _off_point(ar, ac, dr, dc, k, n)
        if oi != poi or oj != poj:  # the ridge looked up once a cell, not once a piece
            off = _off_cell(rdg, slot, tr, tc, oi, oj)
            poi = oi
            poj = oj
        if not off:
            continue
        seg += piece
        if seg > most or seg / ln > rate:
            return False, seg
    return True, seg


@njit(inline="always", cache=True)
def _off_point(ar, ac, dr, dc, k, n):
    """The cell of the middle of the ``k``-th of ``n`` pieces of a segment."""
    t = (k + 0.5) / n
    return int(math.floor(ar + t * dr + 0.5)), int(math.floor(ac + t * dc + 0.5))


@njit(cache=True, _nrt=False)
def _off_cell(rdg, slot, tr, tc, i, j):
    """Whether cell ``(i, j)`` lies off the ridge cells (or off the loaded tiles). Compiled on
    its own without reference counting (``_nrt=False``): inlined, the arrays it takes cost the
    shortcuts' walk 1.6x its time."""
    if i < 0 or j < 0 or i >= slot.shape[0] * tr or j >= slot.shape[1] * tc:
        return True
    return not _cell(slot, rdg, tr, tc, i, j, 0)


@njit(cache=True, nogil=True)
def _line_usable(pas, slot, tr, tc, rows, cols, pad, ar, ac, br, bc):
    """Whether the straight segment between two points (grid units: row, col) crosses only
    usable cells, without cutting a corner between two cells it passes diagonally."""
    return _walk(pas, pas, slot, tr, tc, rows, cols, pad, ar, ac, br, bc, np.inf, np.inf, False)[0]


@njit(cache=True, nogil=True)
def _off_ridge(rdg, slot, tr, tc, ar, ac, br, bc):
    """The length (grid units) of the straight segment lying over cells that are not ridge."""
    dr = br - ar
    dc = bc - ac
    n = _samples(dr, dc)
    piece = math.hypot(dr, dc) / n
    off = 0.0
    for k in range(n):
        if _off_cell(rdg, slot, tr, tc, *_off_point(ar, ac, dr, dc, k, n)):
            off += piece
    return off


@njit(inline="always", cache=True)
def _leg_limits(off, along, i, j, ln, share):
    """``(most, rate)``: the off-ridge length and share a leg of length ``ln`` from vertex ``i``
    to ``j`` may fly (``off``, ``along``: the path's, :func:`_polyline_off_ridge`)."""
    path = off[j] - off[i]
    return path + 0.5 + share * ln, path / (along[j] - along[i]) + share


@njit(inline="always", cache=True)
def leg_allowed(pr, pc, off, along, i, j, pas, rdg, slot, tr, tc, rows, cols, pad, share=0.02):
    """Whether the straight leg from vertex ``i`` to ``j`` crosses only usable cells
    (:func:`_line_usable`) and flies no more off the ridge cells (:func:`_off_ridge`) than the
    path between them (half a cell of slack, more with a larger ``share``), nor an off-ridge
    share larger by more than ``share``: one walk along the leg (:func:`_walk`), which stops
    at the first unusable cell or once the off-ridge length is over a limit, sooner than the
    two functions when the answer is no (most probes of a leg too long)."""
    ln = math.hypot(pr[j] - pr[i], pc[j] - pc[i])
    most, rate = _leg_limits(off, along, i, j, ln, share)
    ar, ac, br, bc = pr[i], pc[i], pr[j], pc[j]
    return _walk(pas, rdg, slot, tr, tc, rows, cols, pad, ar, ac, br, bc, most, rate, True)[0]


@njit(cache=True, nogil=True)
def _shortcuts(pr, pc, off, along, pas, rdg, slot, tr, tc, rows, cols, pad, max_leg):
    """Indices of the vertices kept by string pulling: from each kept vertex, the farthest
    later one (probed at doubling steps, then refined) reached by a usable straight leg that
    flies no more off the ridge cells than the path between them does (``off``: the path's
    off-ridge length up to each vertex, grid units; half a cell of slack)."""
    n = pr.size
    keep = np.empty(n, dtype=np.int64)
    m = 0
    keep[m] = 0
    m += 1
    i = 0
    while i < n - 1:
        best = i + 1
        step = 1
        fails = 0
        nxt = n - 1
        while True:
            j = min(i + step, n - 1)
            if j - i > max_leg:
                nxt = j
                break
            if leg_allowed(pr, pc, off, along, i, j, pas, rdg, slot, tr, tc, rows, cols, pad):
                best = j
                nxt = min(i + 2 * step, n - 1)
            else:
                fails += 1
                if fails >= 3:
                    break
            if j == n - 1:
                break
            step *= 2
        lo = best
        hi = max(nxt, best)
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if mid - i <= max_leg and leg_allowed(
                pr, pc, off, along, i, mid, pas, rdg, slot, tr, tc, rows, cols, pad
            ):
                lo = mid
            else:
                hi = mid
        i = lo
        keep[m] = i
        m += 1
    return keep[:m]


@njit(cache=True, nogil=True)
def _arcs_radii(wr, wc, radius):
    """The radius of the arc at each corner (inf where straight) and ``tan(theta / 2)``."""
    m = wr.size
    tan_d = np.zeros(m)  # tangent length at each corner
    rad = np.full(m, np.inf)
    half = np.zeros(m)  # tan(theta / 2) at each corner
    for k in range(1, m - 1):
        ur = wr[k] - wr[k - 1]
        uc = wc[k] - wc[k - 1]
        vr = wr[k + 1] - wr[k]
        vc = wc[k + 1] - wc[k]
        cosang = (ur * vr + uc * vc) / (math.hypot(ur, uc) * math.hypot(vr, vc))
        theta = math.acos(min(1.0, max(-1.0, cosang)))
        if theta >= 1e-9:
            half[k] = math.tan(theta / 2.0)
    # each leg shared by two corners: both arcs at full radius when their tangent lengths fit
    # in it, else both shrunk in proportion
    scale = np.ones(m)
    for k in range(m - 1):
        need = radius * (half[k] + half[k + 1])
        ln = math.hypot(wr[k + 1] - wr[k], wc[k + 1] - wc[k])
        if need > ln:
            f = ln / need
            scale[k] = min(scale[k], f)
            scale[k + 1] = min(scale[k + 1], f)
    for k in range(1, m - 1):
        if half[k] > 0:
            rad[k] = radius * scale[k]
            tan_d[k] = rad[k] * half[k]
    return tan_d, rad


@njit(cache=True, nogil=True)
def arcs(wr, wc, radius, step):
    """Dense samples (grid units) of the polyline ``w`` with every corner rounded by an arc of
    ``radius`` (grid units; narrower where two corners share a leg too short for both).
    Returns rows, cols, the leg of each sample (-1 on an arc), the radius used at each corner
    (inf where straight) and the tangent lengths."""
    m = wr.size
    tan_d, rad = _arcs_radii(wr, wc, radius)
    total = 2
    for k in range(m - 1):
        total += int(math.ceil(math.hypot(wr[k + 1] - wr[k], wc[k + 1] - wc[k]) / step)) + 2
        if rad[k] < np.inf:
            total += int(math.ceil(rad[k] * math.pi / step)) + 2
    outr = np.empty(total)
    outc = np.empty(total)
    leg = np.empty(total, dtype=np.int64)
    n = 0
    for k in range(m - 1):
        lr = wr[k + 1] - wr[k]
        lc = wc[k + 1] - wc[k]
        ln = math.hypot(lr, lc)
        ur = lr / ln
        uc = lc / ln
        a0 = tan_d[k]
        a1 = ln - tan_d[k + 1]
        ns = max(1, int(math.ceil((a1 - a0) / step)))
        for q in range(ns):
            t = a0 + (a1 - a0) * q / ns
            outr[n] = wr[k] + ur * t
            outc[n] = wc[k] + uc * t
            leg[n] = k
            n += 1
        kk = k + 1
        if kk < m - 1 and rad[kk] < np.inf:
            # arc from the tangent point on leg k to the one on leg k + 1
            vr = wr[kk + 1] - wr[kk]
            vc = wc[kk + 1] - wc[kk]
            lv = math.hypot(vr, vc)
            vr /= lv
            vc /= lv
            t1r = wr[kk] - ur * tan_d[kk]
            t1c = wc[kk] - uc * tan_d[kk]
            cross = ur * vc - uc * vr
            side = 1.0 if cross > 0 else -1.0
            # normal of leg k towards the inside of the turn
            nr = -uc * side
            nc = ur * side
            r = rad[kk]
            cr = t1r + nr * r
            cc = t1c + nc * r
            a_start = math.atan2(t1c - cc, t1r - cr)
            theta = math.acos(min(1.0, max(-1.0, ur * vr + uc * vc)))
            na = max(1, int(math.ceil(r * theta / step)))
            for q in range(na):
                ang = a_start + side * theta * q / na
                outr[n] = cr + r * math.cos(ang)
                outc[n] = cc + r * math.sin(ang)
                leg[n] = -1
                n += 1
    outr[n] = wr[m - 1]
    outc[n] = wc[m - 1]
    leg[n] = m - 1
    n += 1
    return outr[:n], outc[:n], leg[:n], rad, tan_d


@njit(cache=True)
def _fill_route(
    rows, cols, shared, vi, wr, wc, u, ln, tan_d, head, own, tail, order, starts, pr, pc
):
    """``_route_samples``' legs: each the new samples from its first corner to where its arc
    meets it, the track's straight samples, the new samples to its last corner."""
    for k in range(wr.size - 1):
        o = vi[k]
        for q in range(head[k]):
            t = q / head[k] * tan_d[k]
            rows[o + q] = wr[k] + u[k, 0] * t
            cols[o + q] = wc[k] + u[k, 1] * t
        o += head[k]
        for q in range(own[k]):
            idx = order[starts[k] + q]
            rows[o + q] = pr[idx]
            cols[o + q] = pc[idx]
            shared[o + q] = idx
        o += own[k]
        for q in range(tail[k]):
            t = ln[k] - tan_d[k + 1] + q / tail[k] * tan_d[k + 1]
            rows[o + q] = wr[k] + u[k, 0] * t
            cols[o + q] = wc[k] + u[k, 1] * t


def _route_samples(wr, wc, pr, pc, leg, tan_d, step):
    """Samples of the straight legs between the corners ``w`` that share the flown track's
    samples where the two coincide (a leg's straight part between its arcs); the rest (from a
    corner to where its arc leaves the legs) sampled anew. Returns rows, cols, the track sample
    each shares (-1: new) and each corner's sample index."""
    m = len(wr)
    u = np.column_stack([np.diff(wr), np.diff(wc)])
    ln = np.hypot(u[:, 0], u[:, 1])
    u /= ln[:, None]
    head = np.ceil(tan_d[:-1] / step).astype(np.int64)  # corner k -> where its arc meets leg k
    tail = np.ceil(tan_d[1:] / step).astype(np.int64)  # where arc k + 1 leaves leg k -> corner
    tail[-1] = 0
    order = np.argsort(leg, kind="stable")  # the straight samples of each leg, in order
    legs_sorted = leg[order]
    starts = np.searchsorted(legs_sorted, np.arange(m))
    own = np.diff(starts)[: m - 1]  # straight samples per leg
    count = head + own + tail
    vi = np.concatenate(([0], np.cumsum(count)))
    n = int(vi[-1]) + 1
    rows, cols = np.empty(n), np.empty(n)
    shared = np.full(n, -1, dtype=np.int64)
    _fill_route(
        rows, cols, shared, vi, wr, wc, u, ln, tan_d, head, own, tail, order, starts, pr, pc
    )
    rows[-1], cols[-1] = wr[-1], wc[-1]
    shared[-1] = len(pr) - 1
    return rows, cols, shared, vi


@njit(inline="always", cache=True)
def _least_term(p, lo, hi, a):
    """The least ``(i - p)^2 a^2`` over the grid lines ``lo..hi``, computed as each line's own
    term is (the terms grow with the distance on either side of ``p``: the least is next to
    it)."""
    near = min(max(int(math.floor(p + 0.5)), lo), hi)
    least = (near - p) * (near - p) * a * a
    for i in range(max(near - 1, lo), min(near + 1, hi) + 1):
        least = min(least, (i - p) * (i - p) * a * a)
    return least


# required_heights reads the corridor's elevation in square blocks of up to this side (a divisor
# of the tiles' side), each with its highest value: a block whose highest value cannot raise
# the height found so far is passed over unread (measured on the 10000^2 benchmark missions)
HEIGHT_BLOCK = 4


@njit(inline="always", cache=True)
def _dome(d2, rr, reach):
    """How far above a grid point ``sqrt(d2)`` away a sphere of squared radius ``rr`` must be
    to clear the grid square (at most ``reach`` from the point) the point is the highest
    corner of: ``sqrt(rr - max(0, d - reach)^2)``, 0 beyond the sphere (monotone in ``d2``)."""
    d = max(math.sqrt(d2) - reach, 0.0)
    return math.sqrt(max(rr - d * d, 0.0))


@njit(cache=True, nogil=True)
def required_heights(
    el, slot, tr, tc, rows, cols, pr, pc, a, radius, method, clearance, reach, partial
):
    """The lowest height at each point (grid units) that keeps the clearance from the
    continuous seabed (bilinear between the DEM's grid points), conservatively: the seabed over
    a grid square is at most its highest corner, and a point of the square is at least ``d -
    reach`` (metres) from ``p`` for a corner ``d`` away (``reach``: the square's diagonal, more
    for the methods that cover the step between samples). Spherical (``radius`` the
    clearance): ``max z(q) + sqrt(radius^2 - max(0, d - reach)^2)`` over the grid points ``q``
    within ``radius + reach``; horizontal and vertical: ``max z(q) + clearance`` within
    ``radius + reach`` (docs/method.md section 2). NaN where the terrain it needs is unknown: a
    no-data grid point within ``radius + reach - a sqrt(2)`` (the reach without the squares'
    diagonal; within ``radius + reach`` for the vertical method, whose squares are under the
    point), or a grid point within reach not loaded; ``-inf`` where no grid point is near
    enough. Where only the squares around a no-data grid point farther away come that close,
    the seabed there is unknown but no grid point the planner kept the clearance from: the
    height keeps the clearance from the known squares, and ``partial`` (a uint8 array of one
    flag a point, or empty) marks the point.

    Exactly the maximum over every grid point within reach: the grid points are taken in
    blocks (``HEIGHT_BLOCK``), and a block is read only when its highest elevation, at the
    block's least distance, could exceed the best value so far (computed with the same floating
    point operations as each point's own value, which are monotone: so a block passed over
    holds no larger value), or when it holds unknown elevation; the best value starts at the
    previous point's highest grid point, usually near the answer."""
    n = pr.size
    out = np.empty(n)
    spherical = method == 2
    rr = radius * radius  # the clearance's square (spherical)
    far = radius + reach  # the farthest grid point that can constrain a point
    r2 = far * far
    rc = far / a
    # an unknown grid point within this makes the height unknown; farther, one whose grid
    # squares come within the reach less the squares' diagonal (which the highest-corner bound
    # adds) marks the point partly unknown
    unknown = max(far - a * math.sqrt(2.0), 0.0)
    unknown2 = unknown * unknown
    missing2 = r2 if method == 0 else unknown2
    flags = partial.size > 0
    b = HEIGHT_BLOCK
    while b > 1 and (tr % b or tc % b):
        b //= 2
    nbr = tr // b
    nbc = tc // b
    bs = 0  # b is a power of two: divisions by it are shifts
    while (1 << bs) < b:
        bs += 1
    top = np.empty((el.shape[0], nbr, nbc), dtype=np.float64)  # a block's highest elevation
    seen = np.zeros((el.shape[0], nbr, nbc), dtype=np.uint8)
    colterm = np.empty(int(2 * rc) // b + 3)  # per block column: its least column term,
    coltile = np.empty(colterm.size, dtype=np.int64)  # its tile column, its block in the tile
    colblock = np.empty(colterm.size, dtype=np.int64)
    cap = radius if spherical else 0.0
    mi = -1  # the previous point's highest grid point
    mj = -1
    for k in range(n):
        p = pr[k]
        q = pc[k]
        best = -np.inf
        bad = False
        ilo = max(0, int(math.ceil(p - rc)))
        ihi = min(rows - 1, int(math.floor(p + rc)))
        jlo = max(0, int(math.ceil(q - rc)))
        jhi = min(cols - 1, int(math.floor(q + rc)))
        if mi >= 0:
            d2 = (mi - p) * (mi - p) * a * a + (mj - q) * (mj - q) * a * a
            if d2 <= r2:
                z = np.float64(_cell(slot, el, tr, tc, mi, mj, np.nan))
                if z == z:
                    best = z + _dome(d2, rr, reach) if spherical else z
        bj0 = jlo >> bs
        nbj = (jhi >> bs) + 1 - bj0
        for bj in range(bj0, bj0 + nbj):  # each block column's least column term
            colterm[bj - bj0] = _least_term(q, max(bj * b, jlo), min(bj * b + b - 1, jhi), a)
            t = _tile_of(bj * b, tc)  # (32-bit divisions: a 64-bit one costs several times more)
            coltile[bj - bj0] = t
            colblock[bj - bj0] = (bj * b - t * tc) >> bs
        for bi in range(ilo >> bs, (ihi >> bs) + 1):
            i0 = max(bi * b, ilo)
            i1 = min(bi * b + b - 1, ihi)
            di2 = _least_term(p, i0, i1, a)
            ti = _tile_of(bi * b, tr)
            lbi = (bi * b - ti * tr) >> bs
            for bj in range(bj0, bj0 + nbj):
                dj2 = colterm[bj - bj0]
                if di2 + dj2 > r2:
                    continue  # no grid point of the block is within the radius
                j0 = max(bj * b, jlo)
                j1 = min(bj * b + b - 1, jhi)
                s = slot[ti, coltile[bj - bj0]]
                if s >= 0:
                    lbj = colblock[bj - bj0]
                    if not seen[s, lbi, lbj]:
                        hi = -np.inf
                        r0 = bi * b - ti * tr
                        c0 = bj * b - coltile[bj - bj0] * tc
                        for ii in range(r0, r0 + b):
                            for jj in range(c0, c0 + b):
                                z = np.float64(el[s, ii, jj])
                                if z != z:
                                    hi = np.nan
                                    break
                                if z > hi:
                                    hi = z
                            if hi != hi:
                                break
                        top[s, lbi, lbj] = hi
                        seen[s, lbi, lbj] = 1
                    hi = top[s, lbi, lbj]
                    if hi == hi:  # no unknown elevation in the block
                        if hi + cap <= best:  # cap: no block's square root is larger
                            continue
                        if spherical and hi + _dome(di2 + dj2, rr, reach) <= best:
                            continue
                if s < 0:  # its tile is not loaded: the grid point within reach is unknown
                    bad = True
                    break
                # the block lies in one tile: its cells by their place in it (no division)
                oi = -ti * tr
                oj = -coltile[bj - bj0] * tc
                for i in range(i0, i1 + 1):
                    ri2 = (i - p) * (i - p) * a * a
                    for j in range(j0, j1 + 1):
                        d2 = ri2 + (j - q) * (j - q) * a * a
                        if d2 > r2:
                            continue
                        z = np.float64(el[s, i + oi, j + oj])
                        if z != z:
                            if d2 < missing2:
                                bad = True
                                break
                            # the seabed of the four squares around it is unknown
                            bi2 = max(abs(i - p) - 1.0, 0.0) * a
                            bj2 = max(abs(j - q) - 1.0, 0.0) * a
                            if flags and bi2 * bi2 + bj2 * bj2 < unknown2:
                                partial[k] = 1
                            continue
                        v = z + _dome(d2, rr, reach) if spherical else z
                        if v > best:
                            best = v
                            mi = i
                            mj = j
                    if bad:
                        break
                if bad:
                    break
            if bad:
                break
        out[k] = _height(bad, best, spherical, clearance)
    return out


# where the clearance is under FINE_BELOW cells the required heights bound the seabed over
# parts of each grid square (:func:`required_heights_fine`): the highest corner of a whole
# square raises a height by up to the square's rise, which on a coarse grid is a good part of
# the clearance (on real bathymetry at 150 m cells, R = 100 m: shallow straits no longer
# passable under the surface limit)
FINE_BELOW = 4.0
FINE_MOST = 8


def subdivisions(a: float, clearance: float) -> int:
    """Parts a grid square's side is cut in for the required heights: 1 (the whole square,
    :func:`required_heights`) where the clearance is at least ``FINE_BELOW`` cells, else
    enough for parts of at most an eighth of the clearance, at most ``FINE_MOST``."""
    if clearance >= FINE_BELOW * a:
        return 1
    return int(min(FINE_MOST, max(2, math.ceil(8.0 * a / clearance))))


@njit(cache=True, nogil=True)
def required_heights_fine(
    el, slot, tr, tc, rows, cols, pr, pc, a, radius, method, clearance, extra, k, partial
):
    """:func:`required_heights` with each grid square cut into ``k`` x ``k`` parts: the
    bilinear seabed over a part is at most the highest of its four corners (bilinear values),
    and a part lies exactly its box distance from the point. Spherical: ``max Z + sqrt(radius^2
    - d^2)`` over the parts less than ``radius`` away; horizontal and vertical: ``max Z +
    clearance`` over the parts less than ``radius + extra`` away (``extra``: the step between
    samples). A square whose highest corner cannot beat the best so far is passed over. NaN
    where a no-data corner lies within the reach (the vertical method: of the point's own
    square too) or a tile within reach is not loaded; a square with a no-data corner farther
    only flags the point in ``partial`` (a uint8 array, or empty)."""
    n = pr.size
    out = np.empty(n)
    spherical = method == 2
    lim = radius + (0.0 if spherical else extra)
    lim2 = lim * lim
    rr = radius * radius
    missing = lim + (a * math.sqrt(2.0) if method == 0 else 0.0)
    missing2 = missing * missing
    flags = partial.size > 0
    span = missing / a
    mi = -1  # the previous point's highest square, and its highest part there
    mj = -1
    mu = -1
    mv = -1
    stack = np.empty((64, 4), dtype=np.int64)
    for s in range(n):
        p = pr[s]
        q = pc[s]
        best = -np.inf
        bad = False
        first_i = -1
        first_j = -1
        if mi >= 0:  # the previous point's highest square first: most others then pass
            z00, z01, z10, z11 = _corners(slot, el, tr, tc, mi, mj, np.inf)
            if np.isfinite(z00 + z01 + z10 + z11):
                best, mu, mv = _parts_max(
                    z00, z01, z10, z11, mi, mj, p, q, a, k, lim2, rr, spherical, best, stack,
                    mu, mv,
                )  # fmt: skip
                first_i = mi
                first_j = mj
        i0 = max(0, int(math.floor(p - span)) - 1)
        i1 = min(rows - 2, int(math.floor(p + span)) + 1)
        j0 = max(0, int(math.floor(q - span)) - 1)
        j1 = min(cols - 2, int(math.floor(q + span)) + 1)
        for i in range(i0, i1 + 1):
            di = max(0.0, i - p, p - (i + 1)) * a
            if di * di >= max(lim2, missing2):
                continue
            for j in range(j0, j1 + 1):
                dj = max(0.0, j - q, q - (j + 1)) * a
                d2 = di * di + dj * dj
                if d2 >= max(lim2, missing2):
                    continue
                z00, z01, z10, z11 = _corners(slot, el, tr, tc, i, j, np.inf)
                if np.inf in (z00, z01, z10, z11):
                    bad = True  # a tile not loaded
                    break
                if z00 != z00 or z01 != z01 or z10 != z10 or z11 != z11:
                    # a no-data corner: unknown within the clearance, else noted
                    for ci in range(i, i + 2):
                        for cj in range(j, j + 2):
                            z = _cell(slot, el, tr, tc, ci, cj, np.inf)
                            if z == z:
                                continue
                            dc2 = ((ci - p) * (ci - p) + (cj - q) * (cj - q)) * a * a
                            if dc2 < missing2:
                                bad = True
                            elif flags and d2 < lim2:
                                partial[s] = 1
                    if bad:
                        break
                    continue
                if d2 >= lim2:
                    continue
                top = max(z00, z01, z10, z11)
                if top + (math.sqrt(rr - d2) if spherical else 0.0) <= best:
                    continue  # no part of the square can raise the height
                if i == first_i and j == first_j:
                    continue  # measured first
                v, u, w = _parts_max(
                    z00, z01, z10, z11, i, j, p, q, a, k, lim2, rr, spherical, best, stack, -1, -1
                )
                if v > best:
                    best = v
                    mi = i
                    mj = j
                    mu = u
                    mv = w
            if bad:
                break
        out[s] = _height(bad, best, spherical, clearance)
    return out


@njit(inline="always", cache=True)
def _corners(slot, el, tr, tc, i, j, missing):
    """The four corners of grid square ``(i, j)``: ``(i, j)``, ``(i, j + 1)``, ``(i + 1,
    j)``, ``(i + 1, j + 1)`` (``missing`` where a tile is not loaded)."""
    return (
        np.float64(_cell(slot, el, tr, tc, i, j, missing)),
        np.float64(_cell(slot, el, tr, tc, i, j + 1, missing)),
        np.float64(_cell(slot, el, tr, tc, i + 1, j, missing)),
        np.float64(_cell(slot, el, tr, tc, i + 1, j + 1, missing)),
    )


@njit(inline="always", cache=True)
def _height(bad, best, spherical, clearance):
    """A point's required height from the best value found: NaN where the terrain it needs is
    unknown, the value itself (spherical, or no constraint), else the value plus the
    clearance."""
    if bad:
        return np.nan
    if spherical or best == -np.inf:
        return best
    return best + clearance


@njit(inline="always", cache=True)
def _part_bound(z00, z01, z10, z11, i, j, p, q, a, inv, u0, u1, v0, v1, lim2, rr, spherical):
    """The highest value the parts ``u0..u1-1`` x ``v0..v1-1`` of square ``(i, j)`` can give
    the point ``(p, q)``: the highest bilinear corner of the rectangle they make (a bilinear
    surface is highest at a corner of any rectangle), plus the sphere's rise at the
    rectangle's box distance (spherical); ``-inf`` where it lies ``sqrt(lim2)`` or farther."""
    a0 = u0 * inv
    a1 = u1 * inv
    b0 = v0 * inv
    b1 = v1 * inv
    du = max(0.0, i + a0 - p, p - (i + a1)) * a
    dv = max(0.0, j + b0 - q, q - (j + b1)) * a
    e2 = du * du + dv * dv
    if e2 >= lim2:
        return -np.inf
    zm = max(
        _bilin(z00, z01, z10, z11, a0, b0),
        _bilin(z00, z01, z10, z11, a0, b1),
        _bilin(z00, z01, z10, z11, a1, b0),
        _bilin(z00, z01, z10, z11, a1, b1),
    )
    return zm + (math.sqrt(rr - e2) if spherical else 0.0)


@njit(inline="always", cache=True)
def _parts_max(z00, z01, z10, z11, i, j, p, q, a, k, lim2, rr, spherical, best, stack, hu, hv):
    """The highest of ``best`` and the values over the ``k`` x ``k`` parts of square ``(i,
    j)`` (corners ``z``) less than ``sqrt(lim2)`` from ``(p, q)``: a part's highest bilinear
    corner, plus the sphere's rise at its box distance (spherical); and the part that gave it
    (``-1, -1`` where none beat ``best``). Branch and bound: the part ``(hu, hv)`` first (the
    previous point's best, when given), then the square halved until single parts, a block of
    parts passed over where its bound (:func:`_part_bound`, at least the value of each of its
    parts) cannot beat the best; the result is that of every part measured. ``stack``: scratch
    rows ``(u0, u1, v0, v1)``, at least ``4 log2(k) + 4``."""
    inv = 1.0 / k
    bu = -1
    bv = -1
    if hu >= 0:
        v = _part_bound(
            z00, z01, z10, z11, i, j, p, q, a, inv, hu, hu + 1, hv, hv + 1, lim2, rr, spherical
        )
        if v > best:
            best = v
            bu = hu
            bv = hv
    stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3] = 0, k, 0, k
    top = 1
    while top > 0:
        top -= 1
        u0, u1, v0, v1 = stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3]
        bound = _part_bound(
            z00, z01, z10, z11, i, j, p, q, a, inv, u0, u1, v0, v1, lim2, rr, spherical
        )
        if bound <= best:
            continue
        if u1 - u0 == 1 and v1 - v0 == 1:
            best = bound
            bu = u0
            bv = v0
            continue
        um = (u0 + u1 + 1) // 2 if u1 - u0 > 1 else u1
        vm = (v0 + v1 + 1) // 2 if v1 - v0 > 1 else v1
        # the halves, the one nearest the point pushed last (measured first: the best rises
        # early and the others pass over)
        nu = 1 if um == u1 else 2
        nv = 1 if vm == v1 else 2
        fu = 1 if (nu == 2 and p >= i + um * inv) else 0
        fv = 1 if (nv == 2 and q >= j + vm * inv) else 0
        for c in range(nu * nv - 1, -1, -1):  # the farthest from the point first onto the stack
            cu = (c // nv) ^ fu if nu == 2 else 0
            cv = (c % nv) ^ fv if nv == 2 else 0
            stack[top, 0] = u0 if cu == 0 else um
            stack[top, 1] = um if cu == 0 else u1
            stack[top, 2] = v0 if cv == 0 else vm
            stack[top, 3] = vm if cv == 0 else v1
            top += 1
    return best, bu, bv


@njit(inline="always", cache=True)
def _bilin(z00, z01, z10, z11, u, v):
    """The bilinear surface of a square's corners at ``u`` (rows) and ``v`` (columns) in
    [0, 1]."""
    return (z00 * (1 - v) + z01 * v) * (1 - u) + (z10 * (1 - v) + z11 * v) * u


# the flown route's own check samples each grid square's bilinear seabed on a lattice of this
# many parts a side at least (more where the clearance is under sixteen cells)
CHECK_LATTICE = 2


@njit(cache=True, nogil=True)
def seabed_clearance(el, slot, tr, tc, rows, cols, pr, pc, z, a, radius, method, m):
    """The least clearance of the points ``(pr, pc)`` (grid units) at heights ``z`` from the
    continuous seabed, measured anew (not from the required heights): the bilinear seabed of
    every grid square near a point sampled on an ``(m + 1)`` x ``(m + 1)`` lattice. Spherical:
    the least 3-D distance to the samples within ``1.25 radius`` and to the seabed under the
    point (``1.25 radius``, where none is that near); horizontal: the height above the highest
    sample within ``radius`` horizontally; vertical: the height above the seabed under the
    point; a point under the seabed: the (negative) height above it. A square is passed over
    where even its highest corner, at its box distance, is farther than the least found; one
    with a no-data corner is not measured."""
    n = pr.size
    least = np.inf
    # spherical: searched a quarter beyond the clearance, for the least distance itself
    far = 1.25 * radius if method == 2 else radius
    lim = far * far
    span = far / a + 1.0
    for s in range(n):
        p = pr[s]
        q = pc[s]
        h = z[s]
        if method == 0:
            i = min(max(int(math.floor(p)), 0), rows - 2)
            j = min(max(int(math.floor(q)), 0), cols - 2)
            z00, z01, z10, z11 = _corners(slot, el, tr, tc, i, j, np.nan)
            v = h - _bilin(z00, z01, z10, z11, p - i, q - j)
            if v == v:
                least = min(least, v)
            continue
        # the seabed under the point: a point under it has a negative clearance
        ui = min(max(int(math.floor(p)), 0), rows - 2)
        uj = min(max(int(math.floor(q)), 0), cols - 2)
        z00, z01, z10, z11 = _corners(slot, el, tr, tc, ui, uj, np.nan)
        under = _bilin(z00, z01, z10, z11, p - ui, q - uj)
        if h < under:  # (a no-data corner under it: measured from the squares around only)
            least = min(least, h - under)
            continue
        # squared distance (at most to the seabed under the point), or the highest seabed
        best = min(lim, (h - under) * (h - under)) if method == 2 else -np.inf
        if best != best:
            best = lim
        i0 = max(0, int(math.floor(p - span)))
        i1 = min(rows - 2, int(math.floor(p + span)))
        j0 = max(0, int(math.floor(q - span)))
        j1 = min(cols - 2, int(math.floor(q + span)))
        for i in range(i0, i1 + 1):
            di = max(0.0, i - p, p - (i + 1)) * a
            if di * di >= lim:
                continue
            for j in range(j0, j1 + 1):
                dj = max(0.0, j - q, q - (j + 1)) * a
                d2 = di * di + dj * dj
                if d2 >= lim:
                    continue
                z00, z01, z10, z11 = _corners(slot, el, tr, tc, i, j, np.nan)
                if z00 != z00 or z01 != z01 or z10 != z10 or z11 != z11:
                    continue  # no seabed to measure (the flight says where it is unknown)
                top = max(z00, z01, z10, z11)
                if method == 2:
                    gap = max(h - top, 0.0)
                    if d2 + gap * gap >= best:
                        continue
                elif top <= best:
                    continue
                for u in range(m + 1):
                    fu = u / m
                    for v in range(m + 1):
                        fv = v / m
                        dy = (i + fu - p) * a
                        dx = (j + fv - q) * a
                        e2 = dx * dx + dy * dy
                        if e2 >= lim:
                            continue
                        b = _bilin(z00, z01, z10, z11, fu, fv)
                        if method == 2:
                            best = min(best, e2 + (h - b) * (h - b))
                        else:
                            best = max(best, b)
        if method == 2:
            least = min(least, math.sqrt(best))
        else:
            least = min(least, h - best)
    return least


@njit(cache=True, nogil=True)
def _bilinear(el, slot, tr, tc, rows, cols, pr, pc):
    n = pr.size
    out = np.empty(n)
    for k in range(n):
        p = min(max(pr[k], 0.0), rows - 1.0)
        q = min(max(pc[k], 0.0), cols - 1.0)
        i0 = min(int(math.floor(p)), max(rows - 2, 0))
        j0 = min(int(math.floor(q)), max(cols - 2, 0))
        fi = p - i0
        fj = q - j0
        ti = _tile_of(i0, tr)
        tj = _tile_of(j0, tc)
        ri = i0 - ti * tr
        rj = j0 - tj * tc
        s = slot[ti, tj]
        # the four grid points in one loaded tile (most samples): read by their place in it
        one = s >= 0 and ri + 1 < tr and rj + 1 < tc and i0 + 1 < rows and j0 + 1 < cols
        acc = 0.0
        for di in range(2):
            for dj in range(2):
                wgt = (fi if di else 1.0 - fi) * (fj if dj else 1.0 - fj)
                if wgt == 0.0:
                    continue
                if one:
                    z = np.float64(el[s, ri + di, rj + dj])
                else:
                    i = min(i0 + di, rows - 1)
                    j = min(j0 + dj, cols - 1)
                    z = np.float64(_cell(slot, el, tr, tc, i, j, np.nan))
                acc += wgt * z
        out[k] = acc
    return out


def pitch_envelope(h, s, slope):
    """The lowest profile ``z >= h`` with ``|dz/ds| <= slope``: ``z_i = max_j (h_j - slope
    |s_i - s_j|)`` by a forward and a backward pass (``-inf`` in ``h``: no constraint)."""
    return pitch_envelope_var(h, s, np.full(max(len(h) - 1, 0), float(slope)))


@njit(cache=True, nogil=True)
def pitch_envelope_var(h, s, slopes):
    """:func:`pitch_envelope` with a slope limit per interval (``slopes[k]`` between samples
    ``k`` and ``k + 1``): the lowest profile ``z >= h`` keeping each."""
    n = h.size
    z = h.copy()
    for k in range(1, n):
        v = z[k - 1] - slopes[k - 1] * (s[k] - s[k - 1])
        if v > z[k]:
            z[k] = v
    for k in range(n - 2, -1, -1):
        v = z[k + 1] - slopes[k] * (s[k + 1] - s[k])
        if v > z[k]:
            z[k] = v
    return z


@njit(cache=True, nogil=True)
def band_profile(s, env, band, top, slopes):
    """Few straight pieces inside the band ``[env, min(env + band, top)]``, each no steeper
    than the ``slopes`` of the intervals it spans (one per interval): greedy, each piece as
    long as a line from its start stays in the band (the feasible slopes narrowed sample by
    sample), at the slope nearest the previous piece's (level first). Returns the heights at
    every sample and the indices where pieces meet."""
    n = s.size
    zr = np.empty(n)
    brk = np.empty(n, dtype=np.int64)
    nb = 0
    brk[nb] = 0
    nb += 1
    i = 0
    zi = env[0]
    zr[0] = zi
    lo = -np.inf
    hi = np.inf
    prev = 0.0
    k = 1
    while k < n:
        ds = s[k] - s[i]
        if ds <= 0.0:
            zr[k] = zi
            k += 1
            continue
        if env[k] != env[k]:  # unknown terrain (reported by the caller): hold the height
            zr[k] = zi
            k += 1
            continue
        up = min(env[k] + band, top)
        if up < env[k]:
            up = env[k]
        sl = slopes[k - 1]
        nlo = max(lo, -sl, (env[k] - zi) / ds)
        nhi = min(hi, sl, (up - zi) / ds)
        if nlo <= nhi + 1e-12:  # (a profile at the pitch limit meets it up to rounding)
            lo = min(nlo, nhi)
            hi = nhi
            k += 1
            continue
        if k == i + 1:
            # not even the next sample: only rounding at the pitch limit does this; step to it
            zr[k] = max(env[k], zi + max(-sl, min(sl, (env[k] - zi) / ds)) * ds)
            i = k
            zi = zr[k]
            brk[nb] = i
            nb += 1
            lo = -np.inf
            hi = np.inf
            k += 1
            continue
        # the piece from i ends at k - 1: the slope the last piece had, or the nearest the band
        # allows (a climb or a descent goes on, a level stays level: few reversals)
        m = min(max(prev, lo), hi)
        prev = m
        for q in range(i + 1, k):
            zr[q] = zi + m * (s[q] - s[i])
        i = k - 1
        zi = zr[i]
        brk[nb] = i
        nb += 1
        lo = -np.inf
        hi = np.inf
    m = min(max(prev, lo), hi) if lo <= hi else 0.0
    for q in range(i + 1, n):
        zr[q] = zi + m * (s[q] - s[i])
    if brk[nb - 1] != n - 1:
        brk[nb] = n - 1
        nb += 1
    return zr, brk[:nb]


@njit(cache=True, nogil=True)
def _polyline_off_ridge(wr, wc, ridge, rdg, slot, tr, tc):
    """The off-ridge length and the length of the polyline ``w`` up to each corner (grid
    units); without ``ridge`` an off-ridge length no leg can exceed (no ridge rule)."""
    n = wr.size
    off = np.zeros(n)
    along = np.zeros(n)
    for k in range(1, n):
        along[k] = along[k - 1] + math.hypot(wr[k] - wr[k - 1], wc[k] - wc[k - 1])
        if ridge:
            off[k] = off[k - 1] + _off_ridge(rdg, slot, tr, tc, wr[k - 1], wc[k - 1], wr[k], wc[k])
        else:
            off[k] = 2.0 * along[k]
    return off, along


# legs of up to this many corners are walked once for all the route's simplifications
# (:func:`_route_vertices`): the levels probe mostly the same short legs
ROUTE_CACHED_LEG = 8


@njit(cache=True, nogil=True)
def _route_vertices(wr, wc, off, along, levels, enough, rdg, pas, slot, tr, tc, rows, cols, pad):
    """Indices of the corners kept for the waypoint route: greedy, each leg the longest usable
    one that passes within ``tol`` (grid units) of every corner it skips and flies no more off
    the ridge cells than the legs it replaces but for ``share`` of its length (as the
    shortcuts do; ``off``, ``along``: ``_polyline_off_ridge``). ``levels``: ``(tol, share)``
    rows, tried in turn until one keeps at most ``enough`` corners (else the last one's). A leg
    is walked to its end (:func:`_walk` without limits) and each level's limits compared with
    its whole off-ridge length, which is what the early-stopping walk decides; the legs of up
    to ``ROUTE_CACHED_LEG`` corners are walked once for every level (the 5 levels of a
    10000^2 mission's route took 7.4 ms walked anew, 2.3 ms so)."""
    n = wr.size
    cap = ROUTE_CACHED_LEG
    known = np.zeros((n, cap), dtype=np.uint8)  # 0 not walked, 1 usable, 2 not
    offs = np.empty((n, cap))
    keep = np.empty(n, dtype=np.int64)
    m = 0
    for li in range(levels.shape[0]):
        tol = levels[li, 0]
        share = levels[li, 1]
        m = 0
        keep[m] = 0
        m += 1
        i = 0
        while i < n - 1:
            j = i + 1
            while j + 1 < n:
                c = j + 1
                dr = wr[c] - wr[i]
                dc = wc[c] - wc[i]
                ln = math.hypot(dr, dc)
                ok = ln > 0.0
                for q in range(i + 1, c):
                    if not ok:
                        break
                    t = ((wr[q] - wr[i]) * dr + (wc[q] - wc[i]) * dc) / (ln * ln)
                    t = min(1.0, max(0.0, t))
                    if math.hypot(wr[i] + t * dr - wr[q], wc[i] + t * dc - wc[q]) > tol:
                        ok = False
                if ok:  # leg_allowed, from the leg's one walk (kept for the next levels)
                    d = c - i - 1
                    if d >= cap or known[i, d] == 0:
                        usable, seg = _walk(
                            pas, rdg, slot, tr, tc, rows, cols, pad,
                            wr[i], wc[i], wr[c], wc[c], np.inf, np.inf, True,
                        )  # fmt: skip
                        if d < cap:
                            known[i, d] = 1 if usable else 2
                            offs[i, d] = seg
                    else:
                        usable, seg = known[i, d] == 1, offs[i, d]
                    most, rate = _leg_limits(off, along, i, c, ln, share)
                    ok = usable and not (seg > most or seg / ln > rate)
                if not ok:
                    break
                j = c
            i = j
            keep[m] = i
            m += 1
        if m <= enough:
            break
    return keep[:m]


def _corner_vertices(cells: np.ndarray) -> np.ndarray:
    """Indices of the path's cells where its direction changes (and both ends)."""
    if len(cells) <= 2:
        return np.arange(len(cells))
    d = np.diff(cells, axis=0)
    turn = np.any(d[1:] != d[:-1], axis=1)
    return np.concatenate(([0], np.nonzero(turn)[0] + 1, [len(cells) - 1]))


class Corridor:
    """The store chunks (elevation, passable, ridge) around a path, as stacked tiles with a
    slot table, so that the kernels read the terrain near the track and nothing else.

    The passable and ridge tiles are read here; the elevation tiles, which only the heights
    need, are decoded by the pool's threads meanwhile and waited for by :meth:`grid`: the
    shortcuts and the route, which need the others only, are computed in the meantime (a
    10000^2 mission's corridor decodes 37 tiles of each layer; its elevation is 80 % of the
    bytes)."""

    def __init__(self, m, cells: np.ndarray, pad: int):
        from ..store.cache import CACHE

        rows, cols = m.shape
        tr, tc = (int(v) for v in CACHE.array(m.path, "elevation").chunks)
        self.tr, self.tc, self.rows, self.cols = tr, tc, rows, cols
        nti, ntj = -(-rows // tr), -(-cols // tc)
        want = np.zeros((nti, ntj), dtype=bool)
        r, c = cells[:, 0].astype(np.int64), cells[:, 1].astype(np.int64)
        steps = range(-pad, pad + 1, max(1, min(tr, tc) - 1))
        offs = sorted(set(list(steps) + [pad]))
        for dr in offs:
            for dc in offs:
                rr = np.clip(r + dr, 0, rows - 1) // tr
                cc = np.clip(c + dc, 0, cols - 1) // tc
                want[rr, cc] = True
        ti, tj = np.nonzero(want)
        self.slot = np.full((nti, ntj), -1, dtype=np.int64)
        self.slot[ti, tj] = np.arange(len(ti))
        complete = m.all_chunks_written
        self._el = np.empty((len(ti), tr, tc), dtype=np.float32)
        self.pas = np.empty((len(ti), tr, tc), dtype=np.uint8)
        self.rdg = np.empty((len(ti), tr, tc), dtype=np.uint8)

        def load(job):
            k, i, j, var, dst, fill = job
            # decoded into the tile (the chunks a planning process holds are copied from it)
            h, w = CACHE.chunk_into(m.path, var, i, j, dst[k], complete=complete)
            dst[k, h:, :] = fill  # a tile at the map's edge: the rest is no terrain
            dst[k, :h, w:] = fill

        def jobs(var, dst, fill):
            tiles = zip(ti.tolist(), tj.tolist(), strict=True)
            return [(k, i, j, var, dst, fill) for k, (i, j) in enumerate(tiles)]

        # decoding releases the GIL: read the chunks a few at a time
        pool = shared_pool("corridor", 4)
        first = jobs("passable", self.pas, 0) + jobs("ridge", self.rdg, 0)
        first = [pool.submit(load, x) for x in first]
        self._elevation = [pool.submit(load, x) for x in jobs("elevation", self._el, np.nan)]
        try:
            for f in first:
                f.result()
        except BaseException:
            for f in first + self._elevation:
                f.cancel()
            for f in self._elevation:
                if not f.cancelled():
                    f.exception()  # waits: no decoding left running behind the error
            raise
        self.tiles = len(ti)

    def grid(self) -> tuple:
        """``(elevation tiles, slot, tr, tc, rows, cols)``, the elevation read by then."""
        pending, self._elevation = self._elevation, []
        errors = [f.exception() for f in pending]
        if any(errors):
            raise next(e for e in errors if e is not None)
        return self._el, self.slot, self.tr, self.tc, self.rows, self.cols

    @property
    def el(self) -> np.ndarray:
        """The elevation tiles (waits for their decoding)."""
        return self.grid()[0]


def fly(maps: Maps, traj: Trajectory, vehicle: VehicleLike = None) -> Flight:
    """The track a vehicle flies for ``traj`` (a planned :class:`Trajectory`) on the maps store
    ``maps``, and its waypoints: see the module's description. ``vehicle``: a
    :class:`Vehicle`, a dict of its keys, or None (the defaults).

    Examples
    --------
    >>> t = pipeline.plan("maps.zarr", (120, 150), (1850, 1800))          # doctest: +SKIP
    >>> f = pipeline.fly("maps.zarr", t, {"max_pitch_deg": 15})         # doctest: +SKIP
    >>> f.flown_length_m <= t.omega * t.lower_bound_m, len(f.waypoints)  # doctest: +SKIP
    (True, 41)
    """
    from ..store.maps_store import open_store

    t0 = time.perf_counter()
    m = open_store(maps)
    veh = Vehicle.of(vehicle)
    if not traj.planned or len(traj.cells) < 2:
        raise InvalidParameterError("fly needs a planned trajectory of at least two cells")
    p = m.parameters
    a = m.cell_size
    method = p.get("method", "spherical")
    clearance = float(p["clearance_m"])
    radius = clearance
    if method == "horizontal" and p.get("horizontal_clearance_m"):
        radius = float(p["horizontal_clearance_m"])
    surface = p.get("surface_clearance_m")
    top = float(p.get("sea_level_m", 0.0)) - float(clearance if surface is None else surface)
    turn_m = veh.turn_radius(a)
    slope = math.tan(math.radians(veh.max_pitch_deg))
    step, terrain, top_ok = _sampling(method, a, clearance, radius, slope, turn_m, top)
    rows, cols = m.shape
    elem = int(math.ceil((terrain[1] + terrain[4]) / a + math.sqrt(2.0))) + 1
    pad = elem + int(math.ceil(turn_m / a)) + 2
    cells = np.asarray(traj.cells, dtype=np.int64)
    cor = Corridor(m, cells, pad)
    usable = (cor.pas, cor.slot, cor.tr, cor.tc, rows, cols, elem)
    verts = _corner_vertices(cells)
    vr = cells[verts, 0].astype(np.float64)
    vc = cells[verts, 1].astype(np.float64)
    if traj.lower_bound_m > 0:
        limit = traj.omega * traj.lower_bound_m
    else:
        limit = traj.length_m
    if traj.status != "ok":
        limit = max(limit, traj.length_m)
    off, along = _path_off_ridge(cells, cor)
    keep = _shortcuts(
        vr, vc, off[verts], along[verts], cor.pas, cor.rdg, *usable[1:], 4 * max(rows, cols)
    )
    r_turn = turn_m / a

    # when the flight along shortcuts that keep the ridge cover is longer than the bound
    # allows, shortcuts free of that rule (the shortest), then the path's own corners (each
    # made only when needed)
    def free():
        kf = _shortcuts(
            vr, vc, along[verts] * 2.0, along[verts], cor.pas, cor.rdg, *usable[1:],
            4 * max(rows, cols),
        )  # fmt: skip
        return widen_turns(vr[kf], vc[kf], r_turn, usable)

    tries = (
        ("shortcuts", lambda: widen_turns(vr[keep], vc[keep], r_turn, usable), r_turn),
        ("straight shortcuts", free, r_turn),
        ("path vertices", lambda: widen_turns(vr, vc, r_turn, usable), r_turn),
        ("grid path", lambda: (vr, vc), 0.0),
    )
    bands = (
        (veh.waypoint_band_m,)
        if veh.waypoint_band_m is not None
        else tuple(f * clearance for f in WAYPOINT_BANDS)
    )
    want = max(2, int(WAYPOINT_SHARE * len(cells)))
    results = []
    for name, make, rad in tries:
        wr, wc = make()
        # the waypoint route: the corners, a leg skipping those it passes within a tolerance
        # of; the flown track: the route with its turns rounded
        if rad > 0:
            keep_ridge = name != "straight shortcuts"
            woff, walong = _polyline_off_ridge(wr, wc, keep_ridge, cor.rdg, *usable[1:4])
            # the closest route with few corners
            rk = _route_vertices(wr, wc, woff, walong, _LEVELS, 0.75 * want, cor.rdg, *usable)
            sr, sc = widen_turns(wr[rk], wc[rk], rad, usable)
            # a simplified route whose corners come too close together where no straight leg
            # can part them: every corner of the smoothing kept instead (more waypoints)
            if not (_tight_turns(sr, sc, rad) and not _tight_turns(wr, wc, rad)):
                wr, wc = sr, sc
        pr, pc, leg, radii, tan_d = arcs(wr, wc, rad, step)
        grid = cor.grid()  # the elevation decoded meanwhile
        qr, qc, shared, vi = _route_samples(wr, wc, pr, pc, leg, tan_d, step)
        h_track, unsure = _required_threaded(grid, terrain, pr, pc)
        hq = np.empty(len(qr))
        new = shared < 0
        hq[~new] = h_track[shared[~new]]
        hq[new], unsure_q = _required_threaded(grid, terrain, qr[new], qc[new])
        unsure = int(unsure.sum() + unsure_q.sum())
        prof = vertical_profile(
            wr, wc, qr, qc, vi, pr, pc, leg, radii, tan_d, hq, h_track, a, slope, bands,
            top_ok, want, turn_m * (1 + LEG_MARGIN),
        )  # fmt: skip
        zq, wi, band, sig_t = prof["z"], prof["waypoints"], prof["band"], prof["sigma_track"]
        route = {"s": prof["sigma"], "z": zq, "h": prof["h"]}
        z_t = np.interp(sig_t, prof["sigma"], zq)
        s_t = np.concatenate(([0.0], np.cumsum(a * np.hypot(np.diff(pr), np.diff(pc)))))
        track = {
            "h": h_track,
            "s": s_t,
            "z": z_t,
            "length": float(np.hypot(np.diff(s_t), np.diff(z_t)).sum()),
        }
        track["known"] = not (np.isnan(h_track).any() or np.isnan(hq).any())
        problems = []
        if not track["known"]:
            problems.append("the terrain near the track is unknown (no-data) at some samples")
        elif max(z_t.max(), zq.max()) > top_ok:
            problems.append(
                f"the pitch limit forces the vehicle to {-max(z_t.max(), zq.max()):.0f} m depth, "
                f"above the surface limit ({-top:.0f} m)"
            )
        else:
            low = min(float(np.min(z_t - h_track)), float(np.min(zq - hq)))
            if low < -1e-6:  # never by construction: a check of what is written
                problems.append(f"the route passes {-low:.2f} m below its required height")
        route_length = float(np.hypot(np.diff(route["s"]), np.diff(zq)).sum())
        longest = max(track["length"], route_length)
        over = ""
        if longest > limit * (1 + 1e-9):
            over = (
                f"the flown length {longest:.0f} m exceeds omega x the proven lower "
                f"bound ({limit:.0f} m)"
            )
            problems.append(over)
        turns = radii[np.isfinite(radii)] * a
        tight = int(np.sum(_too_tight(turns, turn_m)))
        if rad == 0:
            problems.append("turns are not rounded (the smoothed tracks broke a limit)")
        elif tight:  # corners that widen_turns could not part: the next smoothing may
            problems.append(
                f"{tight} turns are tighter than the minimum turn radius {turn_m:g} m "
                f"(tightest {turns.min():.1f} m): the corners are too close together"
            )
        results.append(
            dict(
                name=name,
                pr=pr,
                pc=pc,
                radii=radii,
                track=track,
                route=route,
                qr=qr,
                qc=qc,
                zq=zq,
                wi=wi,
                band=band,
                route_length=route_length,
                problems=problems,
                over=over,
                unsure=unsure,
            )
        )
        if not problems:
            break
    # the first smoothing that keeps every limit; else the first whose only fault is a length
    # above the proven bound (the mission is then "uncertified", as a planned path would be);
    # else the first with the fewest faults
    pick = next((r for r in results if not r["problems"]), None)
    pick = pick or next((r for r in results if r["problems"] == [r["over"]]), None)
    pick = pick or min(results, key=lambda r: len(r["problems"]))
    name, pr, pc, radii = pick["name"], pick["pr"], pick["pc"], pick["radii"]
    track, route, qr, qc = pick["track"], pick["route"], pick["qr"], pick["qc"]
    zq, wi, band, route_length = pick["zq"], pick["wi"], pick["band"], pick["route_length"]
    problems = list(pick["problems"])
    z, s, h = track["z"], track["s"], track["h"]
    # a leg used up by its two arcs leaves a sample where the next arc starts: one sample each
    once = np.concatenate(([True], np.diff(s) > 0))
    pr, pc, z, s, h = pr[once], pc[once], z[once], s[once], h[once]
    turns = radii[np.isfinite(radii)] * a
    min_turn = 0.0 if name == "grid path" else float(turns.min()) if turns.size else math.inf
    dz, ds = np.diff(z), np.diff(s)
    pitch = np.degrees(np.arctan2(np.abs(dz), ds))
    seg = np.hypot(ds, dz)
    t = np.concatenate(([0.0], np.cumsum(seg))) / veh.speed_m_s
    mid_r = np.rint(0.5 * (pr[1:] + pr[:-1])).astype(np.int64)
    mid_c = np.rint(0.5 * (pc[1:] + pc[:-1])).astype(np.int64)
    on_ridge = _lookup(cor.rdg, cor.slot, cor.tr, cor.tc, mid_r, mid_c).astype(bool)
    total = float(seg.sum())
    x, y = _map_xy(m, pr, pc)
    # waypoints: every corner of the route and every break of its height profile (wi)
    wx, wy = _map_xy(m, qr[wi], qc[wi])
    rt = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(route["s"]), np.diff(zq)))))
    duration = float(t[-1])
    seabed = _bilinear(*grid, pr, pc)
    near = profile_figures(s, z, seabed)
    # what is flown, measured anew against the continuous seabed where it comes closest to its
    # required heights: never under the clearance by construction, and a mission whose route
    # came under it would fail here
    reach = clearance if method == "spherical" else radius if method == "horizontal" else 0.0
    lattice = int(min(32, max(CHECK_LATTICE, math.ceil(8 * a / clearance))))
    least = np.inf
    for r_, c_, z_, h_ in ((pr, pc, z, h), (qr, qc, zq, route["h"])):
        k = _closest(z_ - h_)
        least = min(
            least, seabed_clearance(*grid, r_[k], c_[k], z_[k], a, reach, _METHOD[method], lattice)
        )
    if least < clearance * (1 - 1e-6):
        problems.append(
            f"the flown route comes {least:.1f} m from the seabed between grid points, under "
            f"the clearance {clearance:g} m"
        )
    return Flight(
        x=x,
        y=y,
        z=z,
        s=s,
        time_s=t,
        seabed_m=seabed,
        required_m=h,
        waypoints=np.column_stack([wx, wy, zq[wi], rt[wi] / veh.speed_m_s]),
        waypoint_index=wi,
        vehicle=veh,
        turn_radius_m=turn_m,
        flown_length_m=float(track["length"]),
        route_length_m=route_length,
        grid_length_m=float(traj.length_m),
        duration_s=duration,
        max_pitch_deg=float(pitch.max()) if pitch.size else 0.0,
        min_turn_radius_m=min_turn,
        ridge_ratio=float(seg[on_ridge].sum() / total) if total > 0 else 0.0,
        energy_wh=veh.power_w * duration / 3600.0 if veh.power_w is not None else None,
        surface_limit_m=top,
        waypoint_band_m=float(band),
        smoothing=name,
        problems=problems,
        over_bound=pick["over"],
        seconds=time.perf_counter() - t0,
        route=np.column_stack([*_map_xy(m, qr, qc), zq]),
        route_seabed_m=_bilinear(*grid, qr, qc),
        unknown_seabed_samples=pick["unsure"],
        min_clearance_m=float(least),
        short_legs=int(np.sum(np.hypot(np.diff(wx), np.diff(wy)) < turn_m * (1 - 1e-9))),
        **near,
    )


def _sampling(method, a, clearance, radius, slope, turn_m, top) -> tuple:
    """The sample step (grid units), the ``required_heights`` terrain arguments and the
    highest height allowed, such that a route whose samples keep their required heights keeps
    the clearance from the continuous seabed everywhere between them too (docs/method.md
    section 2): the seabed over a grid square, or over each of its ``k`` x ``k`` parts
    (:func:`subdivisions`), is at most its highest corner; on an arc the vehicle is within the
    sagitta
    ``c^2 / (8 r)`` of the chord between samples ``c`` apart; spherical: the samples clear of
    the seabed by ``R' = sqrt((R + sagitta)^2 + (L/2)^2)``, ``L`` the longest 3-D step between
    samples, keep every point of the step ``R`` away (samples close enough that the step's
    share of ``R' - R`` is at most ``CLEARANCE_SLACK * R``; the sagitta adds to it);
    horizontal and vertical: a sample's heights cover every point within a step of it (a point
    of a step is as high as one of its two ends)."""
    grade = math.sqrt(1.0 + slope * slope)
    step = SAMPLE_STEP
    if method == "spherical":
        eps = CLEARANCE_SLACK * clearance
        longest = 2.0 * math.sqrt(2.0 * clearance * eps + eps * eps)
        step = min(SAMPLE_STEP, longest / (a * grade))
    chord = step * a
    sag = chord * chord / (8.0 * turn_m) if turn_m > 0 else 0.0
    k = subdivisions(a, clearance)
    if method == "spherical":
        r = math.sqrt((clearance + sag) ** 2 + 0.25 * (chord * grade) ** 2)
        terrain = (a, r, _METHOD[method], clearance, 0.0, k)
        top_ok = top + (r - clearance) + 1e-6  # the surface limit is R's, not R''s
    else:
        r = radius if method == "horizontal" else 0.0
        terrain = (a, r, _METHOD[method], clearance, chord + sag, k)
        top_ok = top + 1e-6
    return step, terrain, top_ok


def _arcs_of(leg: np.ndarray) -> list:
    """``(first, end, corner)`` of each arc of the flown track: its samples (``leg`` -1)
    ``first:end``, and the corner it turns, the one after the leg whose samples precede it."""
    on_arc = np.flatnonzero(leg < 0)
    if not on_arc.size:
        return []
    gap = np.diff(on_arc) > 1
    first = on_arc[np.concatenate(([True], gap))]
    end = on_arc[np.concatenate((gap, [True]))] + 1
    return [(b, e, int(leg[b - 1]) + 1) for b, e in zip(first.tolist(), end.tolist(), strict=True)]


def _track_sigma(wr, wc, pr, pc, leg, arcs, tan_d, sig_corner, a) -> np.ndarray:
    """Where each sample of the flown track (the corners' arcs) lies along the waypoint route
    (metres from the start, along the straight legs): a straight sample at its own place; the
    samples of the arc at corner ``k`` (``arcs``, :func:`_arcs_of`) spread evenly over
    ``[sigma_k - t, sigma_k + t]`` (``t`` the arc's tangent length), in turn."""
    out = np.empty(len(pr))
    straight = leg >= 0
    k = leg[straight]
    out[straight] = sig_corner[k] + a * np.hypot(pr[straight] - wr[k], pc[straight] - wc[k])
    for b, e, corner in arcs:
        t = tan_d[corner] * a
        out[b:e] = sig_corner[corner] - t + 2.0 * t * np.arange(e - b) / (e - b)
    return out


@njit(cache=True, nogil=True)
def turn_slopes(sig, zones, slope, min_leg):
    """The pitch limit of each interval of the route's profile (``slope`` as a rise per metre)
    lowered over each turn: ``zones`` rows ``(first interval, end interval, slope)`` in route
    order. Zones less than ``min_leg`` apart (or from either end) are joined, each at its least
    slope (and one shorter than ``min_leg`` made that long), so that a profile held at the limit
    breaks no closer than ``min_leg`` to a turn, to another break or to an end (a waypoint an
    autopilot can tell from the next)."""
    n = sig.size
    out = np.full(n - 1, slope)
    runs = np.empty((zones.shape[0], 3))
    m = 0
    for z in range(zones.shape[0]):
        j0, j1, sl = int(zones[z, 0]), int(zones[z, 1]), zones[z, 2]
        while j1 < n - 1 and sig[j1] - sig[j0] < min_leg:  # (never so over a turn)
            j1 += 1
        while j0 > 0 and sig[j1] - sig[j0] < min_leg:
            j0 -= 1
        while m > 0 and sig[j0] - sig[int(runs[m - 1, 1])] < min_leg:  # (a long arc may reach back)
            m -= 1
            j0 = min(int(runs[m, 0]), j0)
            j1 = max(int(runs[m, 1]), j1)
            sl = min(runs[m, 2], sl)
        runs[m, 0], runs[m, 1], runs[m, 2] = j0, j1, sl
        m += 1
    if m > 0 and sig[int(runs[0, 0])] - sig[0] < min_leg:
        runs[0, 0] = 0
    if m > 0 and sig[n - 1] - sig[int(runs[m - 1, 1])] < min_leg:
        runs[m - 1, 1] = n - 1
    for r in range(m):
        for t in range(int(runs[r, 0]), int(runs[r, 1])):
            out[t] = min(out[t], runs[r, 2])
    return out


def vertical_profile(
    wr, wc, qr, qc, vi, pr, pc, leg, radii, tan_d, hq, h_track, a, slope, bands, top, want,
    min_leg=0.0,
) -> dict:  # fmt: skip
    """The heights of the waypoint route and its waypoints (docs/flyable-missions.md): one
    profile along the route's straight legs (``sigma``, metres), linear between waypoints
    (what an autopilot flies), and the flown track's heights read from it at each sample's
    place along the route (:func:`_track_sigma`). Every sample of either keeps its required
    height (``hq``; ``h_track``: an arc sample's binds the two route samples around it);
    the pitch holds on the legs and on the arcs (the route's slope limited over a turn by the
    ratio of the arc's chords to the route they stand for); the profile is a few straight
    pieces inside a band above the lowest such profile (:func:`band_profile`), the narrowest of
    ``bands`` that needs at most ``want`` waypoints. Its breaks stay ``min_leg`` from turns,
    from each other and from the ends where the limits allow: the slope lowered over a turn
    reaches ``min_leg`` either side of it (:func:`turn_slopes`), and a break still ending a
    shorter leg is removed or moved (:func:`resolve_short_legs`)."""
    sig = np.concatenate(([0.0], np.cumsum(a * np.hypot(np.diff(qr), np.diff(qc)))))
    sig_corner = sig[vi]
    arcs = _arcs_of(leg)
    sig_t = _track_sigma(wr, wc, pr, pc, leg, arcs, tan_d, sig_corner, a)
    h = np.where(np.isnan(hq), -np.inf, hq)
    ht = np.where(np.isnan(h_track), -np.inf, h_track)
    j = np.clip(np.searchsorted(sig, sig_t, side="right") - 1, 0, len(sig) - 2)
    np.maximum.at(h, j, ht)
    np.maximum.at(h, j + 1, ht)
    arc_n = np.zeros(len(wr), dtype=np.int64)
    for b, e, corner in arcs:
        arc_n[corner] = e - b
    k = np.flatnonzero(np.isfinite(radii) & (tan_d > 0))  # the turns
    theta = 2.0 * np.arctan(tan_d[k] / radii[k])
    na = np.maximum(arc_n[k], 1)
    factor = na * np.sin(theta / (2 * na)) / np.tan(theta / 2)
    t = np.maximum(tan_d[k] * a, min_leg)  # a break where the slope changes: min_leg from it
    zones = np.column_stack(
        [
            np.maximum(np.searchsorted(sig, sig_corner[k] - t, side="right") - 1, 0),
            np.minimum(np.searchsorted(sig, sig_corner[k] + t, side="left"), len(sig) - 1),
            slope * factor * (1 - 1e-9),
        ]
    )  # (first interval, end, slope) over each turn
    slopes = turn_slopes(sig, zones, float(slope), float(min_leg))
    if not np.isfinite(h).any():
        h[:] = 0.0
    env = pitch_envelope_var(h, sig, slopes)
    corners = np.asarray(vi, dtype=np.int64)
    for band in bands:  # the narrowest band that needs few waypoints (linear time each)
        z, brk = band_profile(sig, env, band, top, slopes)
        wi = resolve_short_legs(
            sig, z, np.union1d(corners, brk), corners, h, slopes, top, float(min_leg)
        )
        if len(wi) <= want:
            break
    z = np.interp(sig, sig[wi], z[wi])  # exactly linear between waypoints
    return {"sigma": sig, "z": z, "h": h, "waypoints": wi, "band": band, "sigma_track": sig_t}


@njit(cache=True, nogil=True)
def _knot_range(sig, z, h, slopes, top, a, j, b):
    """The heights a knot at sample ``j`` may take between the fixed knots ``a < j < b``: the
    two straight lines ``a -> j -> b`` keep every required height ``h`` of the samples they
    span, the pitch limit of every interval and the surface limit ``top``. Returns
    ``(lo, hi)``, empty when ``lo > hi``."""
    lo = -np.inf
    hi = top
    da = sig[j] - sig[a]
    db = sig[b] - sig[j]
    if da <= 0.0 or db <= 0.0:
        return np.inf, -np.inf
    sl = np.inf
    for t in range(a, j):
        sl = min(sl, slopes[t])
    lo = max(lo, z[a] - sl * da)
    hi = min(hi, z[a] + sl * da)
    for t in range(a + 1, j + 1):  # z_a + (z_j - z_a) u >= h_t, u in (0, 1]
        if h[t] > -np.inf:
            u = (sig[t] - sig[a]) / da
            if u > 0.0:
                lo = max(lo, z[a] + (h[t] - z[a]) / u)
    sl = np.inf
    for t in range(j, b):
        sl = min(sl, slopes[t])
    lo = max(lo, z[b] - sl * db)
    hi = min(hi, z[b] + sl * db)
    for t in range(j, b):
        if h[t] > -np.inf:
            u = (sig[b] - sig[t]) / db
            if u > 0.0:
                lo = max(lo, z[b] + (h[t] - z[b]) / u)
    return lo, hi


@njit(cache=True, nogil=True)
def _line_fits(sig, z, h, slopes, top, a, b):
    """Whether the straight line between the knots at samples ``a < b`` keeps every required
    height, the pitch limit of every interval it spans (up to rounding: two pieces at the limit
    may meet a part in 1e12 steeper) and the surface limit."""
    rise = (z[b] - z[a]) / (sig[b] - sig[a])
    for t in range(a, b):
        if abs(rise) > slopes[t] * (1 + 1e-9):
            return False
    for t in range(a, b + 1):
        v = z[a] + rise * (sig[t] - sig[a])
        if v < h[t] or v > top:
            return False
    return True


@njit(cache=True, nogil=True)
def _draw(sig, z, a, b):
    """The profile between the knots at samples ``a < b`` made the straight line between them."""
    rise = (z[b] - z[a]) / (sig[b] - sig[a])
    for t in range(a + 1, b):
        z[t] = z[a] + rise * (sig[t] - sig[a])


@njit(cache=True, nogil=True)
def _set_knot(sig, z, h, slopes, top, a, j, b):
    """Sets the knot at ``j`` between the fixed knots ``a < j < b`` to the height nearest its
    present one that keeps the limits (:func:`_knot_range`) and draws the two lines; False
    (nothing changed) where no height does."""
    lo, hi = _knot_range(sig, z, h, slopes, top, a, j, b)
    if lo > hi:
        return False
    z[j] = min(max(z[j], lo), hi)
    _draw(sig, z, a, j)
    _draw(sig, z, j, b)
    return True


@njit(cache=True, nogil=True)
def resolve_short_legs(sig, z, wi, corners, h, slopes, top, min_leg):
    """The waypoints ``wi`` with no leg shorter than ``min_leg`` that a break of the height
    profile (a waypoint that is not one of the route's ``corners``) ends, where the limits allow
    (every required height ``h``, the pitch limit of every interval, the surface limit ``top``):
    an autopilot takes a waypoint as reached within about its turn radius and would pass over
    one closer. Each such break, in turn: removed, the line between its neighbours straight;
    else removed and a neighbour's height set anew (not the route's first or last waypoint);
    else moved along the route (never past its neighbours) to a place ``min_leg`` from both,
    its height set anew. ``z`` is changed to the new profile (straight between waypoints)."""
    m = wi.size
    keep = wi.copy()
    fixed = np.zeros(m, dtype=np.bool_)
    c = 0
    for w in range(m):  # both sorted
        while c < corners.size and corners[c] < wi[w]:
            c += 1
        fixed[w] = c < corners.size and corners[c] == wi[w]
    fixed[0] = True
    fixed[m - 1] = True
    n = m
    k = 1
    while k < n - 1:
        b, i0, i1 = keep[k], keep[k - 1], keep[k + 1]
        if fixed[k] or min(sig[b] - sig[i0], sig[i1] - sig[b]) >= min_leg:
            k += 1
            continue
        done = False
        if _line_fits(sig, z, h, slopes, top, i0, i1):  # the break removed
            _draw(sig, z, i0, i1)
            done = True
        if not done and k >= 2:  # removed, the knot before it set anew
            done = _set_knot(sig, z, h, slopes, top, keep[k - 2], i0, i1)
        if not done and k + 2 < n:  # or the knot after it
            done = _set_knot(sig, z, h, slopes, top, i0, i1, keep[k + 2])
        if done:
            for t in range(k, n - 1):  # drop waypoint k
                keep[t] = keep[t + 1]
                fixed[t] = fixed[t + 1]
            n -= 1
            k = max(k - 1, 1)  # the leg before may now be long enough, or still short
            continue
        # moved: the places min_leg from both neighbours, nearest its own first
        best = -1
        if sig[i1] - sig[i0] >= 2.0 * min_leg:
            p = b
            while p > i0 and sig[i1] - sig[p] < min_leg:
                p -= 1
            while p < i1 and sig[p] - sig[i0] < min_leg:
                p += 1
            q = p
            for _ in range(16):  # a few places past it (the first is usually taken)
                if q <= i0 or q >= i1 or sig[q] - sig[i0] < min_leg or sig[i1] - sig[q] < min_leg:
                    break
                if _set_knot(sig, z, h, slopes, top, i0, q, i1):  # from its present height
                    best = q
                    break
                q += 1 if p >= b else -1
        if best >= 0:
            keep[k] = best
        k += 1
    return keep[:n]


# the flown route's own check measures the samples nearest their required heights: this share
# of them, and at least CHECK_LEAST
CHECK_SHARE = 0.01
CHECK_LEAST = 32


def _closest(margin: np.ndarray) -> np.ndarray:
    """The indices of the samples with the least ``margin`` (``CHECK_SHARE`` of them, at least
    ``CHECK_LEAST``; NaN margins, of unknown terrain, last)."""
    k = min(len(margin), max(CHECK_LEAST, int(CHECK_SHARE * len(margin))))
    m = np.where(np.isnan(margin), np.inf, margin)
    return np.sort(np.argpartition(m, k - 1)[:k]) if k < len(m) else np.arange(len(m))


def profile_figures(s, z, seabed) -> dict:
    """Near-bottom figures of a flown profile: the altitude above the seabed (median, 90th
    percentile, least) and the vertical reversals (climb to descent or back, level pieces
    passed over) per km of horizontal distance."""
    alt = z - seabed
    d = np.sign(np.round(np.diff(z) / np.maximum(np.diff(s), 1e-300), 9))
    d = d[d != 0]
    rev = int(np.count_nonzero(d[1:] != d[:-1])) if d.size > 1 else 0
    km = max(float(s[-1] - s[0]) / 1000.0, 1e-9)
    ok = np.isfinite(alt)
    return {
        "altitude_median_m": float(np.median(alt[ok])) if ok.any() else math.nan,
        "altitude_p90_m": float(np.percentile(alt[ok], 90)) if ok.any() else math.nan,
        "altitude_min_m": float(alt[ok].min()) if ok.any() else math.nan,
        "reversals_per_km": rev / km,
    }


def _required_threaded(grid, terrain, pr, pc, parts: int = 2) -> tuple:
    """``required_heights`` over the samples and their flags of a partly unknown seabed, in
    ``parts`` threads (the kernel releases the GIL): the mission's other work waits for it,
    the cores do not."""
    n = len(pr)
    partial = np.zeros(n, dtype=np.uint8)
    cut = np.linspace(0, n, parts + 1).astype(int) if n >= 4096 and parts >= 2 else [0, n]

    a, radius, method, clearance, extra, k = terrain

    def part(q):
        lo, hi = cut[q], cut[q + 1]
        args = (*grid, pr[lo:hi], pc[lo:hi], a, radius, method, clearance)
        if k == 1:  # the squares' diagonal added to every distance, blocks passed over
            return required_heights(*args, extra + a * math.sqrt(2.0), partial[lo:hi])
        return required_heights_fine(*args, extra, k, partial[lo:hi])

    if len(cut) == 2:
        return part(0), partial
    out = shared_pool(f"heights-{parts}", parts).map(part, range(parts))
    return np.concatenate(list(out)), partial


@njit(cache=True)
def _lookup(tiles, slot, tr, tc, r, c):
    out = np.zeros(r.size, dtype=np.uint8)
    for k in range(r.size):
        out[k] = _cell(slot, tiles, tr, tc, r[k], c[k], 0)
    return out


def widen_turns(wr, wc, radius, usable, passes: int = 8):
    """Remove corners too close together for the turn radius where a straight leg between
    their neighbours is usable (an out-and-back spur, two short zigzags), tightest first."""
    wr, wc = _distinct(np.asarray(wr, dtype=np.float64), np.asarray(wc, dtype=np.float64))
    for _ in range(passes):
        if len(wr) <= 2:
            break
        rad = _arcs_radii(wr, wc, radius)[1]
        tight = np.nonzero(_too_tight(rad, radius))[0]
        if tight.size == 0:
            break
        drop = _cut_corners(wr, wc, tight[np.argsort(rad[tight])], *usable)
        if not drop.any():
            break
        wr, wc = _distinct(wr[~drop], wc[~drop])
    return wr, wc


@njit(cache=True, nogil=True)
def _cut_corners(wr, wc, order, pas, slot, tr, tc, rows, cols, pad):
    """Which corners ``widen_turns`` drops, taken in ``order`` (the tightest first): a corner
    whose neighbours are both kept, where the straight leg between those is usable."""
    drop = np.zeros(wr.size, dtype=np.bool_)
    for k in order:
        if drop[k - 1] or drop[k + 1] or drop[k]:
            continue
        ar, ac, br, bc = wr[k - 1], wc[k - 1], wr[k + 1], wc[k + 1]
        if _line_usable(pas, slot, tr, tc, rows, cols, pad, ar, ac, br, bc):
            drop[k] = True
    return drop


def _tight_turns(wr, wc, radius) -> int:
    """How many corners of the polyline turn tighter than ``radius`` (grid units)."""
    if len(wr) <= 2:
        return 0
    return int(np.sum(_too_tight(_arcs_radii(wr, wc, radius)[1], radius)))


def _too_tight(radii, radius):
    """Which turn radii are below ``radius`` (beyond rounding)."""
    return radii < radius * (1 - 1e-9)


def _distinct(wr, wc):
    """The polyline without repeated consecutive vertices (an out-and-back spur cut at its
    tip returns to where it left)."""
    keep = np.ones(len(wr), dtype=bool)
    keep[1:] = (np.diff(wr) != 0) | (np.diff(wc) != 0)
    return wr[keep], wc[keep]


def _path_off_ridge(cells: np.ndarray, cor: Corridor) -> np.ndarray:
    """The path's off-ridge horizontal length up to each cell, and its horizontal length
    (grid units): each move counted by halves at its two cells, as ``_off_ridge`` counts a
    straight leg."""
    on = _lookup(cor.rdg, cor.slot, cor.tr, cor.tc, cells[:, 0], cells[:, 1]).astype(bool)
    step = np.hypot(*np.diff(cells, axis=0).T.astype(np.float64))
    half = 0.5 * step
    move = half * ~on[:-1] + half * ~on[1:]
    return np.concatenate(([0.0], np.cumsum(move))), np.concatenate(([0.0], np.cumsum(step)))


def _map_xy(m, pr, pc):
    dx = m.x[1] - m.x[0] if len(m.x) > 1 else m.cell_size
    dy = m.y[1] - m.y[0] if len(m.y) > 1 else -m.cell_size
    return m.x[0] + pc * dx, m.y[0] + pr * dy


def with_flight(maps, traj, vehicle=None):
    """``traj`` with its flown track (``traj.flight``) and the status it implies: a flight
    that breaks a vehicle limit, or needs more energy than the battery holds, fails the
    mission with the reason (its track is kept for inspection). A mission whose start is its
    goal has nothing to fly: its message says so, and it has no track or waypoints."""
    if not traj.planned:
        return traj
    if len(traj.cells) < 2:
        note = "start and goal are the same cell: nothing to fly, no waypoints"
        traj.message = f"{traj.message}; {note}" if traj.message else note
        return traj
    f = fly(maps, traj, vehicle)
    traj.flight = f
    veh = f.vehicle
    reasons = list(f.problems)
    if veh.battery_wh is not None and f.energy_wh is not None and f.energy_wh > veh.battery_wh:
        reasons.append(
            f"the flown track needs {f.energy_wh:.0f} Wh ({f.duration_s / 3600:.1f} h at "
            f"{veh.speed_m_s:g} m/s and {veh.power_w:g} W), more than the battery's "
            f"{veh.battery_wh:g} Wh: raise battery_wh or lower the powers, or split the mission"
        )
    if f.unknown_seabed_samples:
        note = (
            f"the seabed is unknown (a no-data grid point's squares) within the clearance of "
            f"{f.unknown_seabed_samples} route samples: there the clearance is kept from the "
            "known seabed only"
        )
        traj.message = f"{traj.message}; {note}" if traj.message else note
    if reasons == [f.over_bound]:  # only the bound: not proven, as for a planned path
        if traj.status == "ok":
            traj.status = "uncertified"
        traj.message = f"{traj.message}; flight: {f.over_bound}" if traj.message else f.over_bound
    elif reasons:
        traj.status = "failed"
        msg = "; ".join(reasons)
        traj.message = f"{traj.message}; flight: {msg}" if traj.message else f"flight: {msg}"
    return traj
