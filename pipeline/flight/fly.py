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
   a tolerance of, ``ROUTE_SIMPLIFICATIONS``), with more waypoints where fewer would keep less
   than ``RIDGE_KEPT`` of the path's ridge share: the waypoints' horizontal positions.
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
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .._types import Maps, VehicleLike

if TYPE_CHECKING:
    from ..trajectory import Trajectory
from ..exceptions import InvalidParameterError
from ..methods import METHODS
from ..trajectory import Status
from .geometry import (
    _LEVELS,
    RIDGE_SLACK,
    Corridor,
    _corner_vertices,
    _line_usable,
    _path_off_ridge,
    _polyline_off_ridge,
    _route_samples,
    _route_vertices,
    _shortcuts,
    _tight_turns,
    _too_tight,
    arc_sagitta,
    arcs,
    ridge_share,
    widen_turns,
)
from .profile import (
    CHECK_LATTICE,
    CLEARANCE_SLACK,
    LEG_MARGIN,
    SAMPLE_STEP,
    _bilinear,
    _closest,
    _required_threaded,
    clearance_blocks,
    profile_figures,
    seabed_clearance,
    subdivisions,
    vertical_profile,
)
from .vehicle import Flight, Vehicle

# waypoint legs may fly above the lowest profile of their route by up to a band: by default the
# narrowest of these shares of the clearance that needs at most WAYPOINT_SHARE waypoints per
# grid path cell (fewer waypoints for a little more altitude); [vehicle] waypoint_band_m fixes it
WAYPOINT_BANDS = (0.25, 0.5, 1.0)


WAYPOINT_SHARE = 0.1

# the share of the planned path's ridge cover (the length over ridge cells) a smoothing keeps:
# the waypoint route takes more waypoints (these multiples of the count wanted, then every
# corner) rather than cut across more of the ridges
RIDGE_KEPT = 0.9
ROUTE_WAYPOINTS = (0.75, 1.5, 3.0)


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
    t0 = time.perf_counter()
    ctx = _flight_context(maps, traj, Vehicle.of(vehicle))
    results = []
    for name, make, rad in _smoothings(ctx):
        results.append(_attempt(ctx, name, make(), rad))
        if not results[-1]["problems"]:
            break
    pick = _pick(results)
    flight = _flight(ctx, traj, pick, t0)
    first = results[0]  # the smoothing that keeps the ridges, when another is flown
    if pick is not first and len(first["trouble"]) and not first["zones"]:
        flight.ridge_trouble_xy = first["trouble"]
    return flight


def _flight_context(maps: Maps, traj: Trajectory, veh: Vehicle) -> _Context:
    """The :class:`_Context` of flying ``traj`` on the maps store ``maps`` for ``veh``."""
    from ..constraints.store import constrained
    from ..store.maps_store import open_store

    # the zones it was planned to avoid; the rating it was planned for, or the vehicle's
    depth = veh.max_depth_m if veh.max_depth_m is not None else traj.max_depth_m
    m = constrained(open_store(maps), traj.keep_out, None, depth)
    if not traj.planned or len(traj.cells) < 2:
        raise InvalidParameterError("fly needs a planned trajectory of at least two cells")
    return _context(m, traj, veh)


@dataclass(frozen=True)
class _Context:
    """What every smoothing of one flight shares: the store, the vehicle and the maps'
    clearances, the sampling, the corridor of cells around the path, its corners, the length
    limit and the waypoint bands."""

    m: object  # the MapsStore
    veh: Vehicle
    a: float  # cell size (m)
    clearance: float
    top: float  # the highest height allowed (sea level less the surface clearance)
    turn_m: float
    slope: float  # tan(max pitch)
    step: float
    terrain: tuple
    top_ok: float
    cor: Corridor
    usable: tuple
    cells: np.ndarray
    verts: np.ndarray  # the path's corners and via points (indices into cells)
    fixed: np.ndarray  # which of ``verts`` are via points (every smoothing keeps them)
    limit: float  # the flown length allowed: omega x the proven lower bound
    bands: tuple
    want: int  # waypoints wanted at most
    ridge_share: float  # the grid path's share over ridge cells (a polyline through its cells)


def _context(m, traj: Trajectory, veh: Vehicle) -> _Context:
    p = m.parameters
    a = m.cell_size
    turn_m = veh.turn_radius(a)
    slope = math.tan(math.radians(veh.max_pitch_deg))
    step, terrain, top_ok = _sampling(
        p.method, a, p.clearance_m, p.radius_m, slope, turn_m, p.top_m
    )
    rows, cols = m.shape
    elem = int(math.ceil((terrain[1] + terrain[4]) / a + math.sqrt(2.0))) + 1
    pad = elem + int(math.ceil(turn_m / a)) + 2
    cells = np.asarray(traj.cells, dtype=np.int64)
    via = np.asarray(traj.extra.get("via_index", []), dtype=np.int64)
    verts = np.union1d(_corner_vertices(cells), via)
    cor = Corridor(m, cells, pad)
    limit = traj.omega * traj.lower_bound_m if traj.lower_bound_m > 0 else traj.length_m
    if traj.status != Status.OK:
        limit = max(limit, traj.length_m)
    bands = (
        (veh.waypoint_band_m,)
        if veh.waypoint_band_m is not None
        else tuple(f * p.clearance_m for f in WAYPOINT_BANDS)
    )
    return _Context(
        m=m,
        veh=veh,
        a=a,
        clearance=p.clearance_m,
        top=p.top_m,
        turn_m=turn_m,
        slope=slope,
        step=step,
        terrain=terrain,
        top_ok=top_ok,
        cor=cor,
        usable=(cor.pas, cor.slot, cor.tr, cor.tc, rows, cols, elem),
        cells=cells,
        verts=verts,
        fixed=np.isin(verts, via),
        limit=limit,
        bands=bands,
        want=max(2, int(WAYPOINT_SHARE * len(cells))),
        ridge_share=ridge_share(
            cor.rdg, cor.slot, cor.tr, cor.tc, *cells.T.astype(np.float64)
        ),  # fmt: skip
    )


def _smoothings(ctx: _Context) -> tuple:
    """``(name, make, turn radius in cells)`` of each smoothing to try, in order: ``make()``
    gives its corners. When the flight along shortcuts that keep the ridge cover is longer
    than the bound allows, shortcuts free of that rule (the shortest), then the path's own
    corners (each made only when needed)."""
    cor, usable, cells, verts, fixed = ctx.cor, ctx.usable, ctx.cells, ctx.verts, ctx.fixed
    rows, cols = ctx.m.shape
    vr = cells[verts, 0].astype(np.float64)
    vc = cells[verts, 1].astype(np.float64)
    off, along = _path_off_ridge(cells, cor)
    off, along = off[verts], along[verts]
    r_turn = ctx.turn_m / ctx.a
    most = 4 * max(rows, cols)

    def shortcuts(offs, slack=RIDGE_SLACK):
        def pulled(a, b):
            k = _shortcuts(
                vr[a:b], vc[a:b], offs[a:b], along[a:b], cor.pas, cor.rdg, *usable[1:], most,
                slack,
            )  # fmt: skip
            if offs is off and slack == RIDGE_SLACK:  # (the shortcuts that keep the ridges)
                k = _ridge_restored(k, vr[a:b], vc[a:b], off[a:b], along[a:b], cor)
            return k

        return _widened(*_by_leg(vr, vc, fixed, pulled), r_turn, usable)

    return (
        ("shortcuts", lambda: shortcuts(off), r_turn),
        # the ridge rule without its cap (they may cut where the ridge runs shallow)
        ("loose shortcuts", lambda: shortcuts(off, math.inf), r_turn),
        ("straight shortcuts", lambda: shortcuts(along * 2.0), r_turn),
        ("path vertices", lambda: _widened(vr, vc, fixed, r_turn, usable), r_turn),
        ("grid path", lambda: (vr, vc, fixed), 0.0),
    )


def _ridge_restored(k, vr, vc, off, along, cor) -> np.ndarray:
    """The kept corners ``k`` of the polyline ``v`` (the path's corners; ``off``, ``along``:
    the path's off-ridge length and length up to each) with the path's own corners put back
    between the two ends of the legs that lost the most ridge length, leg by leg, until the
    polyline keeps ``RIDGE_KEPT`` of the path's ridge share: a shortcut keeps its legs' share,
    but one across a winding ridge shortens the ridge more than the rest."""
    span = along[-1] - along[0]
    share = 1.0 - (off[-1] - off[0]) / span if span > 0 else 0.0
    if share <= 0 or len(k) < 2:
        return k
    a, b = k[:-1], k[1:]
    kept_off, kept_along = _polyline_off_ridge(
        vr[k], vc[k], True, cor.rdg, cor.slot, cor.tr, cor.tc
    )
    ln, leg_off = np.diff(kept_along), np.diff(kept_off)
    path_len = along[b] - along[a]
    path_ridge = path_len - (off[b] - off[a])
    lost = path_ridge - (ln - leg_off)
    total, ridge = float(ln.sum()), float((ln - leg_off).sum())
    back = np.zeros(len(a), dtype=bool)
    for q in np.argsort(-lost):
        if ridge >= RIDGE_KEPT * share * total or lost[q] <= 0:
            break
        back[q] = True
        total += path_len[q] - ln[q]
        ridge += lost[q]
    if not back.any():
        return k
    out = [np.arange(i, j) if put else np.array([i]) for i, j, put in zip(a, b, back, strict=True)]
    return np.concatenate([*out, k[-1:]]).astype(k.dtype)


def _legs(fixed) -> list:
    """``(a, b)``: the first and last corner of each stretch of a polyline between two of its
    ``fixed`` corners (the via points), or its ends."""
    bounds = [0, *(np.flatnonzero(fixed[1:-1]) + 1).tolist(), len(fixed) - 1]
    return list(zip(bounds[:-1], bounds[1:], strict=True))


def _by_leg(wr, wc, fixed, kept) -> tuple:
    """The polyline ``w`` with, between each two of its ``fixed`` corners (the via points,
    and the ends), the corners ``kept(a, b)`` keeps of ``w[a:b]`` (indices from ``a``, its
    first and last among them): a smoothing that never skips a via point."""
    idx = []
    for a, b in _legs(fixed):
        k = np.asarray(kept(a, b + 1), dtype=np.int64) + a
        idx.append(k if not idx else k[1:])
    idx = np.concatenate(idx)
    return wr[idx], wc[idx], fixed[idx]


def _widened(wr, wc, fixed, radius, usable) -> tuple:
    """:func:`widen_turns` between each two fixed corners (via points kept)."""
    pr, pc, pf = [], [], []
    for a, b in _legs(fixed):
        r, c = widen_turns(wr[a : b + 1], wc[a : b + 1], radius, usable)
        f = np.zeros(len(r), dtype=bool)
        f[-1] = b != len(wr) - 1
        first = 0 if not pr else 1
        pr.append(r[first:])
        pc.append(c[first:])
        pf.append(f[first:])
    return np.concatenate(pr), np.concatenate(pc), np.concatenate(pf)


def _attempt(ctx: _Context, name: str, corners: tuple, rad: float) -> dict:
    """One smoothing flown: its route, turns, required heights and depth profile, and the
    limits it breaks (``problems``; ``over``: the flown length above the bound, if so)."""
    a, cor, usable = ctx.a, ctx.cor, ctx.usable
    wr, wc, fixed = corners
    # the waypoint route: the corners, a leg skipping those it passes within a tolerance
    # of; the flown track: the route with its turns rounded (via points kept: ``fixed``)
    if rad > 0:
        keep_ridge = name != "straight shortcuts"
        woff, walong = _polyline_off_ridge(wr, wc, keep_ridge, cor.rdg, *usable[1:4])
        # the closest route with few corners that keeps RIDGE_KEPT of the corners' ridge share
        # or the path's, the larger (more waypoints where fewer would cut across the ridges'
        # bends)
        hug = name in ("shortcuts", "path vertices")  # (the smoothings that keep the ridges)
        if hug:
            share = max(ridge_share(cor.rdg, cor.slot, cor.tr, cor.tc, wr, wc), ctx.ridge_share)
        for enough in ROUTE_WAYPOINTS if hug else ROUTE_WAYPOINTS[:1]:

            def route(i, j, enough=enough):  # (a leg between via points: its share)
                most = enough * ctx.want * (j - i) / len(wr)
                return _route_vertices(
                    wr[i:j], wc[i:j], woff[i:j], walong[i:j], _LEVELS, most, cor.rdg, *usable
                )

            sr, sc, sf = _widened(*_by_leg(wr, wc, fixed, route), rad, usable)
            if not hug:
                break
            if ridge_share(cor.rdg, cor.slot, cor.tr, cor.tc, sr, sc) >= RIDGE_KEPT * share:
                break
        else:  # no simplification keeps the ridges: every corner is a waypoint
            sr, sc, sf = wr, wc, fixed
        # a simplified route whose corners come too close together where no straight leg
        # can part them: every corner of the smoothing kept instead (more waypoints)
        if not (_tight_turns(sr, sc, rad) and not _tight_turns(wr, wc, rad)):
            wr, wc, fixed = sr, sc, sf
    wr, wc, fixed = _fly_over(wr, wc, fixed, rad, usable)
    pr, pc, leg, radii, tan_d = arcs(wr, wc, rad, ctx.step)
    grid = cor.grid()  # the elevation decoded meanwhile
    qr, qc, shared, vi = _route_samples(wr, wc, pr, pc, leg, tan_d, ctx.step)
    h_track, unsure = _required_threaded(grid, ctx.terrain, pr, pc)
    hq = np.empty(len(qr))
    new = shared < 0
    hq[~new] = h_track[shared[~new]]
    hq[new], unsure_q = _required_threaded(grid, ctx.terrain, qr[new], qc[new])
    sea = float(ctx.m.parameters.sea_level_m)  # depths are measured from the sea surface
    floor = ctx.m.floor_m
    if floor is not None:  # no deeper than the rating: there the vehicle flies at it
        h_track, hq = np.maximum(h_track, floor), np.maximum(hq, floor)
    unsure = int(unsure.sum() + unsure_q.sum())
    prof = vertical_profile(
        wr, wc, qr, qc, vi, pr, pc, leg, radii, tan_d, hq, h_track, a, ctx.slope, ctx.bands,
        ctx.top_ok, ctx.want, ctx.turn_m * (1 + LEG_MARGIN),
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
    from ..constraints.zones import entered

    problems = []
    # the track's arcs lie up to a sagitta outside its samples' polyline; the waypoint legs
    # are straight
    zones = entered(
        ctx.m.keep_out,
        _map_xy(ctx.m, pr, pc),
        _map_xy(ctx.m, qr, qc),
        slack=(a * arc_sagitta(radii, ctx.step), 0.0),
    )
    if zones:
        problems.append(f"the flown route enters keep-out zone {', '.join(map(repr, zones))}")
    if not track["known"]:
        problems.append("the terrain near the track is unknown (no-data) at some samples")
    elif (need := max(h_track.max(), hq.max())) > ctx.top_ok:
        problems.append(
            f"the clearance from the seabed needs {sea - need:.1f} m depth on the route, above "
            f"the surface limit ({sea - ctx.top:.0f} m)"
        )
    elif max(z_t.max(), zq.max()) > ctx.top_ok:
        problems.append(
            f"the pitch limit forces the vehicle to {sea - max(z_t.max(), zq.max()):.1f} m "
            f"depth, above the surface limit ({sea - ctx.top:.0f} m)"
        )
    else:
        low = min(float(np.min(z_t - h_track)), float(np.min(zq - hq)))
        if low < -1e-6:  # never by construction: a check of what is written
            problems.append(f"the route passes {-low:.2f} m below its required height")
        deepest = sea - min(float(z_t.min()), float(zq.min()))  # (below the sea surface)
        rated = ctx.m.max_depth_m
        if rated is not None and deepest > rated + 1e-6:  # never by construction, as above
            problems.append(f"the route reaches {deepest:.1f} m, below the rated {rated:g} m")
    route_length = float(np.hypot(np.diff(route["s"]), np.diff(zq)).sum())
    longest = max(track["length"], route_length)
    over = ""
    if longest > ctx.limit * (1 + 1e-9):
        over = (
            f"the flown length {longest:.0f} m exceeds omega x the proven lower "
            f"bound ({ctx.limit:.0f} m)"
        )
        problems.append(over)
    turns = radii[np.isfinite(radii)] * a
    tight = int(np.sum(_too_tight(turns, ctx.turn_m)))
    # where a limit broke (the seabed unknown, a height above the surface limit, a turn too
    # tight): the places a mission planned again keeps away from (jobs.missions)
    bad_t = ~(h_track <= ctx.top_ok) | (z_t > ctx.top_ok)
    bad_q = ~(hq <= ctx.top_ok) | (zq > ctx.top_ok)
    sharp = _too_tight(radii, rad) if rad > 0 else np.zeros(len(wr), dtype=bool)
    trouble = np.column_stack(
        [
            np.concatenate(v)
            for v in zip(
                _map_xy(ctx.m, pr[bad_t], pc[bad_t]),
                _map_xy(ctx.m, qr[bad_q], qc[bad_q]),
                _map_xy(ctx.m, wr[sharp], wc[sharp]),
                strict=True,
            )
        ]
    )
    if rad == 0:
        problems.append("turns are not rounded (the smoothed tracks broke a limit)")
    elif tight:  # corners that widen_turns could not part: the next smoothing may
        problems.append(
            f"{tight} turns are tighter than the minimum turn radius {ctx.turn_m:g} m "
            f"(tightest {turns.min():.1f} m): the corners are too close together"
        )
    return dict(
        name=name,
        via=(wr[fixed], wc[fixed]),
        pr=pr,
        pc=pc,
        radii=radii,
        track=track,
        route=route,
        qr=qr,
        shared=shared,
        qc=qc,
        zq=zq,
        wi=wi,
        band=band,
        route_length=route_length,
        problems=problems,
        over=over,
        zones=zones,
        unsure=unsure,
        grid=grid,
        trouble=trouble,
    )


def _pick(results: list) -> dict:
    """The first smoothing that keeps every limit; else the first whose only fault is a
    length above the proven bound (the mission is then "uncertified", as a planned path would
    be); else the first with the fewest faults, of those that enter no keep-out zone when
    there are such."""
    clear = [r for r in results if not r["zones"]]
    results = clear or results
    pick = next((r for r in results if not r["problems"]), None)
    pick = pick or next((r for r in results if r["problems"] == [r["over"]]), None)
    return pick or min(results, key=lambda r: len(r["problems"]))


def _flight(ctx: _Context, traj: Trajectory, pick: dict, t0: float) -> Flight:
    """The picked smoothing measured as it is flown: the track's samples, pitch, timing,
    ridge share and energy, the waypoints, and its clearance from the continuous seabed."""
    m, veh, a, cor, grid = ctx.m, ctx.veh, ctx.a, ctx.cor, pick["grid"]
    name, pr, pc, radii = pick["name"], pick["pr"], pick["pc"], pick["radii"]
    track, route, qr, qc = pick["track"], pick["route"], pick["qr"], pick["qc"]
    zq, wi, band, route_length = pick["zq"], pick["wi"], pick["band"], pick["route_length"]
    problems = list(pick["problems"])
    z, s, h = track["z"], track["s"], track["h"]
    # a leg used up by its two arcs leaves a sample where the next arc starts (up to rounding:
    # a micrometre): one sample each
    once = np.concatenate(([True], np.diff(s) > 1e-6))
    pr, pc, z, s, h = pr[once], pc[once], z[once], s[once], h[once]
    turns = radii[np.isfinite(radii)] * a
    min_turn = 0.0 if name == "grid path" else float(turns.min()) if turns.size else math.inf
    dz, ds = np.diff(z), np.diff(s)
    pitch = np.degrees(np.arctan2(np.abs(dz), ds))
    seg = np.hypot(ds, dz)
    t = np.concatenate(([0.0], np.cumsum(seg))) / veh.speed_m_s
    total = float(seg.sum())
    x, y = _map_xy(m, pr, pc)
    # legs short enough that the map line, the geodesic and the rhumb line between their
    # waypoints are one (docs/flyable-missions.md, "Legs"), each checked as flown
    qx, qy = _map_xy(m, qr, qc)
    # the route's samples that are the track's own (place and height) measured once
    rest = _not_on_track(pick["shared"], once, (pr, pc, z), (qr, qc, zq))
    least = _least_clearance(
        ctx, grid, ((pr, pc, z, h), (qr[rest], qc[rest], zq[rest], route["h"][rest]))
    )
    # the legs' other lines measured only for less than what is flown on the map line keeps
    known = max(least, ctx.clearance)
    wi, other, where, entered_by = _autopilot_legs(ctx, grid, qx, qy, zq, wi, known)
    if other < ctx.clearance * (1 - 1e-6):
        problems.append(
            f"the {where} comes {other:.1f} m from the seabed, under the clearance "
            f"{ctx.clearance:g} m"
        )
    if entered_by:
        problems.append(f"the {entered_by}")
    # waypoints: every corner of the route and every break of its height profile (wi), and
    # the middles of legs split for the autopilot
    wx, wy = _map_xy(m, qr[wi], qc[wi])
    rt = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(route["s"]), np.diff(zq)))))
    duration = float(t[-1])
    seabed = _bilinear(*grid, pr, pc)
    if least < ctx.clearance * (1 - 1e-6):
        problems.append(
            f"the flown route comes {least:.1f} m from the seabed between grid points, under "
            f"the clearance {ctx.clearance:g} m"
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
        turn_radius_m=ctx.turn_m,
        flown_length_m=float(track["length"]),
        route_length_m=route_length,
        grid_length_m=float(traj.length_m),
        duration_s=duration,
        max_pitch_deg=float(pitch.max()) if pitch.size else 0.0,
        min_turn_radius_m=min_turn,
        ridge_ratio=ridge_share(cor.rdg, cor.slot, cor.tr, cor.tc, pr, pc) if total > 0 else 0.0,
        energy_wh=veh.power_w * duration / 3600.0 if veh.power_w is not None else None,
        surface_limit_m=ctx.top,
        waypoint_band_m=float(band),
        smoothing=name,
        problems=problems,
        over_bound=pick["over"],
        seconds=time.perf_counter() - t0,
        route=np.column_stack([*_map_xy(m, qr, qc), zq]),
        route_seabed_m=_bilinear(*grid, qr, qc),
        unknown_seabed_samples=pick["unsure"],
        min_clearance_m=float(min(least, other)),
        via_miss_m=_via_miss(_given_via(m, traj, pick["via"]), x, y),
        max_depth_m=m.max_depth_m,
        at_rated_depth_m=_at_rated_depth(m.floor_m, s, h),
        short_legs=int(np.sum(np.hypot(np.diff(wx), np.diff(wy)) < ctx.turn_m * (1 - 1e-9))),
        trouble_xy=pick["trouble"],
        **profile_figures(s, z, seabed),
    )


def _fly_over(wr, wc, fixed, rad: float, usable) -> tuple:
    """The polyline ``w`` with a turn flown over each via point (``fixed``) whose rounded
    corner would pass it further than half a cell: the route goes straight on through the via
    point for ``1.05 rad``, turns square to the side of the next leg for ``2.1 rad`` and then
    heads for the next corner, so that the track crosses the via point itself (the two square
    turns need legs of ``rad`` on each side). Kept only where the new legs are usable and no
    turn near it is tighter than before (the other side tried too); else the corner stays as
    it was. Grid units."""
    if rad <= 0 or not fixed[1:-1].any():
        return wr, wc, fixed
    out = [(wr[0], wc[0], fixed[0])]
    for k in range(1, len(wr) - 1):
        v = np.array([wr[k], wc[k]])
        out.append((wr[k], wc[k], fixed[k]))
        if not fixed[k]:
            continue
        prev = np.array(out[-2][:2])
        d1 = v - prev
        d2 = np.array([wr[k + 1], wc[k + 1]]) - v
        n1, n2 = np.hypot(*d1), np.hypot(*d2)
        if n1 == 0 or n2 == 0:
            continue
        d1, d2 = d1 / n1, d2 / n2
        half = 0.5 * math.acos(float(np.clip(d1 @ d2, -1.0, 1.0)))
        if half < math.pi / 2 - 1e-9 and rad * (1 / math.cos(half) - 1) <= 0.5:
            continue  # the rounded corner passes within half a cell
        turn = 1.0 if d1[0] * d2[1] - d1[1] * d2[0] >= 0 else -1.0
        after = [np.array([wr[j], wc[j]]) for j in range(k + 1, min(k + 3, len(wr)))]
        before = _tight_turns(*np.array([prev, v, *after]).T, rad)
        for side in (turn, -turn):
            p1 = v + 1.05 * rad * d1
            p2 = p1 + 2.1 * rad * side * np.array([-d1[1], d1[0]])
            legs = ((v, p1), (p1, p2), (p2, after[0]))
            # no turn there tighter than before (the next corner too close to the loop)
            if _tight_turns(*np.array([prev, v, p1, p2, *after]).T, rad) > before:
                continue
            if all(_line_usable(*usable, *a, *b) for a, b in legs):
                out += [(p1[0], p1[1], False), (p2[0], p2[1], False)]
                break
    r, c, f = zip(*[*out, (wr[-1], wc[-1], fixed[-1])], strict=True)
    return np.array(r, dtype=np.float64), np.array(c, dtype=np.float64), np.array(f, dtype=bool)


def _via_miss(via, x, y) -> list:
    """For each via point ``via`` (xs, ys in map coordinates: as the user gave them), how
    close the flown track comes to it (metres)."""
    return [float(np.hypot(x - px, y - py).min()) for px, py in zip(*via, strict=True)]


def _given_via(m, traj, snapped) -> tuple:
    """The via points as the user gave them (map coordinates), else their cells' centres."""
    given = traj.extra.get("via_given_xy")
    if given:
        g = np.asarray(given, dtype=np.float64)
        return g[:, 0], g[:, 1]
    return _map_xy(m, *snapped)


def _autopilot_legs(ctx: _Context, grid, qx, qy, zq, wi, known: float) -> tuple:
    """The waypoint indices with legs split until the map line, the geodesic and the rhumb
    line of each lie within :func:`leg_tolerance` of each other (closer, a quarter at a time,
    while one of them breaks the clearance or enters a zone; three times at most), and the
    least clearance of the geodesics and rhumb lines of the legs where they part from the map
    line by more than a millionth of the clearance (elsewhere the map line's own check holds
    for them: a clearance moves no more than the point does), where it is, and the zone one
    of them enters ("" for none). ``known``: a clearance the route keeps, at least the
    clearance: the lines are measured for less only (what is at least it is reported as it)."""
    from ..constraints.zones import entered
    from .legs import leg_points, leg_tolerance, split_legs

    m, veh = ctx.m, ctx.veh
    tol = leg_tolerance(ctx.clearance)
    for _ in range(4):
        wi, dev = split_legs(m.crs_wkt, qx, qy, wi, tol, veh.max_leg_m, deviations=True)
        least, where, zone = math.inf, "", ""
        if not m.crs_wkt or len(wi) < 2:
            break
        a, b = wi[:-1], wi[1:]
        legs = np.flatnonzero(dev > 1e-6 * ctx.clearance)
        if not legs.size:
            break
        # every leg's lines sampled as the route is, all legs at once
        a, b = a[legs], b[legs]
        length = np.hypot(qx[b] - qx[a], qy[b] - qy[a])
        count = np.ceil(length / (ctx.step * ctx.a)).astype(np.int64) + 2
        leg = np.repeat(np.arange(legs.size), count)
        first = np.concatenate(([0], np.cumsum(count)[:-1]))
        f = (np.arange(leg.size) - first[leg]) / (count[leg] - 1)
        z = zq[a][leg] + (zq[b] - zq[a])[leg] * f
        lines = leg_points(m.crs_wkt, qx[a], qy[a], qx[b], qy[b], leg, f)
        parts = None  # each leg's samples, where a leg must be named
        for name, (lx, ly) in lines.items():
            r, c = _grid_rc(m, lx, ly)
            got = _least_clearance(ctx, grid, ((r, c, z, z),), known)
            if got < least:
                least = got
                if got < ctx.clearance * (1 - 1e-6):  # which leg: measured leg by leg
                    parts = parts or np.split(np.arange(leg.size), first[1:])
                    each = [
                        _least_clearance(ctx, grid, ((r[at], c[at], z[at], z[at]),), known)
                        for at in parts
                    ]
                    j = legs[int(np.argmin(each))]
                    where = f"{name} between waypoints {j + 1} and {j + 2}"
            if m.keep_out is None or zone:
                continue
            parts = parts or np.split(np.arange(leg.size), first[1:])
            if entered(m.keep_out, *((lx[at], ly[at]) for at in parts)):
                for k, at in enumerate(parts):
                    hit = entered(m.keep_out, (lx[at], ly[at]))
                    if hit:
                        j = legs[k]
                        zone = (
                            f"{name} between waypoints {j + 1} and {j + 2} enters keep-out "
                            f"zone {', '.join(map(repr, hit))}"
                        )
                        break
        if least >= ctx.clearance * (1 - 1e-6) and not zone:
            break
        tol /= 4.0
    return wi, least, where, zone


def check_leg_lines(
    maps: Maps,
    traj: Trajectory,
    flight: Flight,
    vehicle: VehicleLike = None,
    clearance: float | None = None,
) -> tuple:
    """The check a flight makes of its legs' geodesics and rhumb lines, on its own: for the
    flown ``flight`` of ``traj`` on ``maps`` (flown for ``vehicle``), the least clearance of
    the lines (each measured fully, not only for less than the route keeps) and the line and
    leg where it is, measured against ``clearance`` (default the maps'): ``(waypoint indices,
    least clearance, where, the zone a line enters)``. Legs are split further where a line
    comes under it, as in :func:`fly`."""
    import dataclasses

    ctx = _flight_context(maps, traj, Vehicle.of(vehicle))
    if clearance is not None:
        ctx = dataclasses.replace(ctx, clearance=float(clearance))
    q = flight.route
    return _autopilot_legs(
        ctx, ctx.cor.grid(), q[:, 0], q[:, 1], q[:, 2], flight.waypoint_index, math.inf
    )


def _at_rated_depth(floor: float | None, s: np.ndarray, h: np.ndarray) -> float:
    """The horizontal length of the track where the rating binds: its lowest allowed height
    ``h`` is the rating's ``floor`` (within 1 cm), as the lowest safe height lies deeper; each
    step counted by halves at its two samples."""
    if floor is None or len(s) < 2:
        return 0.0
    at = h <= floor + 0.01
    step = np.diff(s)
    return float(0.5 * (step * at[:-1]).sum() + 0.5 * (step * at[1:]).sum())


def _not_on_track(shared, once, track, route) -> np.ndarray:
    """Which samples of the ``route`` (rows, cols, heights) are not samples of the ``track``
    (the same, after its samples ``once`` were kept): those :func:`_route_samples` took from
    the track (``shared``: the track sample, or -1) at the same place and height are."""
    keep = np.ones(len(shared), dtype=bool)
    at = np.flatnonzero(shared >= 0)
    at = at[once[shared[at]]]
    j = (np.cumsum(once) - 1)[shared[at]]
    same = np.ones(len(at), dtype=bool)
    for t, r in zip(track, route, strict=True):
        same &= r[at] == t[j]
    keep[at[same]] = False
    return keep


def _least_clearance(ctx: _Context, grid, lines, start: float = math.inf) -> float:
    """What is flown, measured anew against the continuous seabed at every sample of each of
    ``lines`` (``(rows, cols, heights, required heights)``): the least clearance of the track
    and of the waypoint legs, never under the clearance by construction (a mission whose route
    came under it would fail here). The samples nearest their required heights are measured
    first, so that the others' searches stop early (:func:`seabed_clearance`). ``start``: as
    there."""
    p = ctx.m.parameters
    lattice = int(min(32, max(CHECK_LATTICE, math.ceil(8 * ctx.a / ctx.clearance))))
    r, c, z, h = (np.concatenate(v) for v in zip(*lines, strict=True))
    first = _closest(z - h)
    rest = np.ones(len(z), dtype=bool)
    rest[first] = False
    order = np.concatenate((first, np.flatnonzero(rest)))
    if ctx.cor.check_blocks is None:
        ctx.cor.check_blocks = clearance_blocks(grid[0])
    return seabed_clearance(
        *grid, r[order], c[order], z[order], ctx.a, p.reach_m, METHODS[p.method].code, lattice,
        start, ctx.cor.check_blocks,
    )  # fmt: skip


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
    of a step is as high as one of its two ends). The surface limit ``top`` is kept as it is
    (``R'`` only raises the lowest heights; a sample whose lowest height ``R'`` puts above the
    limit is a flight problem, however close)."""
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
        terrain = (a, r, METHODS[method].code, clearance, 0.0, k)
    else:
        r = METHODS[method].reach_m(clearance, radius)
        terrain = (a, r, METHODS[method].code, clearance, chord + sag, k)
    return step, terrain, top + 1e-6


def _map_steps(m) -> tuple:
    """The maps' steps (metres) along columns and rows."""
    dx = m.x[1] - m.x[0] if len(m.x) > 1 else m.cell_size
    dy = m.y[1] - m.y[0] if len(m.y) > 1 else -m.cell_size
    return dx, dy


def _map_xy(m, pr, pc):
    """Map coordinates of the grid positions (rows ``pr``, columns ``pc``)."""
    dx, dy = _map_steps(m)
    return m.x[0] + pc * dx, m.y[0] + pr * dy


def _grid_rc(m, x, y):
    """Grid positions (rows, columns) of the map coordinates ``x, y``: :func:`_map_xy`'s
    inverse."""
    dx, dy = _map_steps(m)
    return (y - m.y[0]) / dy, (x - m.x[0]) / dx


def with_flight(maps, traj, vehicle=None):
    """``traj`` with its flown track (``traj.flight``) and the status it implies: a flight
    that breaks a vehicle limit, or needs more energy than the battery holds, fails the
    mission with the reason (its track is kept for inspection). A mission whose start is its
    goal has nothing to fly: its message says so, and it has no track or waypoints."""
    if not traj.planned:
        return traj
    if len(traj.cells) < 2:
        _note(traj, "start and goal are the same cell: nothing to fly, no waypoints")
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
    from ..store.maps_store import open_store

    half = 0.5 * open_store(maps).cell_size
    for k, d in enumerate(f.via_miss_m):
        if d > half:
            _note(
                traj,
                f"the flown track passes {d:.0f} m from via {k + 1} as given, more than half "
                "a cell (the point's cell centre, where the waypoint route turns, is up to half "
                "a cell from it; a turn sharper than the turn radius rounds off more)",
            )
    if f.unknown_seabed_samples:
        _note(
            traj,
            f"the seabed is unknown (a no-data grid point's squares) within the clearance of "
            f"{f.unknown_seabed_samples} route samples: there the clearance is kept from the "
            "known seabed only",
        )
    if reasons == [f.over_bound]:  # only the bound: not proven, as for a planned path
        if traj.status == Status.OK:
            traj.status = Status.UNCERTIFIED
        traj.message = f"{traj.message}; flight: {f.over_bound}" if traj.message else f.over_bound
    elif reasons:
        traj.status = Status.FAILED
        _note(traj, "flight: " + "; ".join(reasons))
    return traj


def _note(traj, text: str) -> None:
    """``text`` added to the trajectory's message (after what it says already)."""
    traj.message = f"{traj.message}; {text}" if traj.message else text
