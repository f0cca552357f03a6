"""MCPC: map compression and parallel computing (docs/method.md section 6, the paper's Algorithm 3).

``plan`` compresses the maps by ``rho`` (block means, cached in the maps store), plans a coarse
path, restores it to fine cells, cuts it into square sections with a margin, snaps the joints
to passable cells, plans every section as one dask task that reads only its own window from the
Zarr store, and stitches the sections into one continuous, simple trajectory.

Defaults (all in fine cells; ``a`` is the cell size in metres):

- ``rho = max(2, ceil(max(rows, cols) / 1000))``: a coarse grid of at most about 1000 cells a
  side, so the coarse search is a few tens of milliseconds at any map size (10 at 10000^2, the
  paper's value).
- ``section_size = max(4 * rho, ceil(3000 / a))``: sections of about 3 km (100 cells at 30 m).
  The planning work of a mission grows as its length times the section side (a window's area
  per section); larger sections give the ridge search more room, but on the benchmark maps
  5 km sections reached the same ridge ratio as 3 km ones (44-45 %) at 1.4x the work.
- ``margin = max(rho, section_size // 8)``: room on each side of a section's bounding square
  for the fine path to leave the coarse one (to follow a ridge, or round an obstacle the coarse
  map smoothed away). A failing section is retried with the margin doubled. A window's area per
  section is ``(1 + 2 margin / section_size)^2`` section squares, and a section's searches
  cover much of its window (the Lagrangian planner's off-ridge bound all of it): a quarter
  (2.25 squares, the default until results revision 3) against an eighth (1.56) took 0.9-1.2x
  the time with RA* and 1.4-1.5x with the Lagrangian planner, for at most 0.6 points more
  ridge on the benchmark maps, with the same missions certified (benchmarks/RESULTS.md, "One
  mission against pyastar2d").
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from numbers import Integral

import numpy as np

from .._types import Cell, ClientLike, Maps, Pair, ZonesLike
from ..exceptions import InvalidEndpointError, InvalidParameterError, UnreachableGoalError
from ..params import PLANNING, check_planner
from ..planners.endpoints import (
    NO_PASSABLE,
    nearest_passable,
    not_passable_error,
    off_map_error,
)
from ..planners.paths import path_metrics
from ..planners.registry import PLANNERS
from ..planners.search import heuristic
from ..planners.window import search_window
from ..runtime.cluster import get_client
from ..store.maps_store import MapsStore, open_store
from ..trajectory import Trajectory
from .algorithm import (
    _coarse_endpoint,
    _snapped_joints,
    coarse_rho,
    default_margin,
    default_parameters,
    remove_loops,
    restore,
    segment,
)
from .certify import _Bound, _done, _Reach, certified
from .runners import Section, _ReadAhead, _run, _section_summary, plan_sections


def _check_args(planner, omega, m: MapsStore, rho, section_size, margin):
    planner, omega = check_planner(planner, omega)
    d = default_parameters(m.shape, m.cell_size)
    rho = coarse_rho(m, rho)
    if section_size is None:
        section_size = max(4 * rho, d["section_size"])
    section_size = PLANNING.section_size.check(section_size)
    if section_size < 2 * rho:
        raise InvalidParameterError(
            f"`section_size` ({section_size}) must be at least 2 * rho "
            f"({2 * rho}): a section spans at least two coarse cells"
        )
    if margin is None:
        margin = default_margin(rho, section_size)
    margin = PLANNING.margin.check(margin)
    return planner, omega, rho, section_size, margin


def _cell(name, value) -> tuple[int, int]:
    try:
        r, c = value
        if not all(isinstance(v, Integral) and not isinstance(v, bool) for v in (r, c)):
            raise TypeError
    except (TypeError, ValueError):
        raise InvalidParameterError(
            f"`{name}` must be a cell (row, col) of integers, got {value!r}"
        ) from None
    return int(r), int(c)


def _check_endpoints(m: MapsStore, cells, names=("start", "goal"), given: dict | None = None):
    """``cells`` (a start, via points, a goal: ``names``) checked: on the map and passable,
    else one error naming the first that is not and the nearest passable cell (in the form
    the point was ``given``: map coordinates or longitude and latitude, with its cell)."""
    rows, cols = m.shape
    out = []
    for name, cell in zip(names, cells, strict=True):
        r, c = _cell(name, cell)
        if not (0 <= r < rows and 0 <= c < cols):
            raise off_map_error(name, r, c, m.shape)
        out.append((r, c))
    passable = m.values("passable", out)
    if passable.all():  # one lookup; a window only to name the nearest cell
        return out
    for name, (r, c), here in zip(names, out, passable, strict=True):
        if here:
            continue  # passable: no window read for it
        h = 64
        r0, r1, c0, c1 = max(r - h, 0), min(r + h + 1, rows), max(c - h, 0), min(c + h + 1, cols)
        ok = m.window("passable", r0, r1, c0, c1)
        if not ok[r - r0, c - c0]:
            near = nearest_passable(ok, (r, c), (r0, c0))
            none = NO_PASSABLE if m.passable_cells == 0 else f"no passable cell within {h} cells"
            form, value = _given_form(given or {}, name)
            if form == "cell":
                raise not_passable_error(name, r, c, near, none)
            hint = f"nearest passable point: {_as_given(m, form, near)}" if near else none
            raise InvalidEndpointError(
                f"{name}_{form} {tuple(value)} (cell ({r}, {c})) is on land or inside the "
                f"clearance zone; {hint}"
            )
    return out


def _given_form(given: dict, name: str) -> tuple[str, object]:
    """How the point ``name`` (start, goal, via k) was given: ``(form, value)``."""
    from ..params import ENDPOINT_FORMS, endpoint_key, via_form

    if name.startswith("via "):
        form, points = via_form(given)
        k = int(name.split()[1]) - 1
        return (form or "cell"), (points[k] if form else None)
    for form in ENDPOINT_FORMS:
        if endpoint_key(name, form) in given:
            return form, given[endpoint_key(name, form)]
    return "cell", None


def _as_given(m, form: str, cell) -> str:
    """The centre of ``cell`` in map coordinates or longitude and latitude, with the cell."""
    r, c = cell
    x, y = float(m.x[c]), float(m.y[r])
    if form == "lonlat":
        from pyproj import CRS, Transformer

        to_ll = Transformer.from_crs(CRS.from_wkt(m.crs_wkt), "EPSG:4326", always_xy=True)
        lon, lat = to_ll.transform(x, y)
        return f"({lon:.6f}, {lat:.6f}) (cell ({r}, {c}))"
    return f"({x:.1f}, {y:.1f}) (cell ({r}, {c}))"


def _finish(
    m: MapsStore, results: list, planner, omega, start, goal, expansions, t0, extra, lower: float
) -> Trajectory:
    """Stitch section results (dropping the duplicated joints), cut any loops, measure;
    ``lower`` is the proven lower bound on the whole map's optimum known so far."""
    cells = np.vstack([r.cells if k == 0 else r.cells[1:] for k, r in enumerate(results)])
    z = np.concatenate([r.z if k == 0 else r.z[1:] for k, r in enumerate(results)])
    rdg = np.concatenate([r.ridge if k == 0 else r.ridge[1:] for k, r in enumerate(results)])
    keep = remove_loops(cells)
    extra["loop_cells_removed"] = int(len(cells) - len(keep))
    cells, z, rdg = cells[keep], z[keep], rdg[keep]
    length, ridge_len, ratio = path_metrics(cells, z, rdg, m.cell_size)
    a = m.cell_size
    h0 = heuristic(a, start[0], start[1], goal[0], goal[1], True)
    points = np.column_stack([m.x[cells[:, 1]], m.y[cells[:, 0]], z])
    return Trajectory(
        cells=cells,
        points=points,
        length_m=length,
        ridge_length_m=ridge_len,
        ridge_ratio=ratio,
        lower_bound_m=float(max(h0, lower)),
        expansions=int(expansions),
        runtime_s=time.perf_counter() - t0,
        planner=planner,
        omega=float(omega),
        extra=extra,
    )


def plan(
    maps: Maps,
    start: Cell | None = None,
    goal: Cell | None = None,
    *,
    start_xy: Pair | None = None,
    goal_xy: Pair | None = None,
    start_lonlat: Pair | None = None,
    goal_lonlat: Pair | None = None,
    planner: str = PLANNING.planner.default,
    omega: float = PLANNING.omega.default,
    mcpc: bool = PLANNING.mcpc.default,
    rho: int | None = None,
    section_size: int | None = None,
    margin: int | None = None,
    coarse_planner: str = PLANNING.coarse_planner.default,
    coarse_weight: float = PLANNING.coarse_weight.default,
    repair_max_cells: int = PLANNING.repair_max_cells.default,
    via: list[Cell] | None = None,
    via_xy: list[Pair] | None = None,
    via_lonlat: list[Pair] | None = None,
    keep_out: ZonesLike = None,
    keep_out_margin_m: float | None = None,
    max_depth_m: float | None = None,
    client: ClientLike = None,
) -> Trajectory:
    """Plan a mission on a maps store, coarse to fine (MCPC) or in one window, and certify it.

    Certification: ``lower_bound_m`` is a proven lower bound on the shortest safe path ``L*``
    between start and goal on the whole map (the larger of the octile distance, the landmark
    bound of the store and, for a search of the whole map, the planner's own bound). The
    status is ``"ok"`` only when ``length_m <= omega * lower_bound_m`` (up to a relative
    ``CERTIFY_TOLERANCE`` for floating point), which proves ``length_m <= omega * L*``. A
    stitched MCPC path that is not certified is planned again on the whole map (whose search
    proves its own bound) when the map has at most ``repair_max_cells`` cells; otherwise it is
    returned with status ``"uncertified"`` and the proven ratio in ``message``.

    Parameters
    ----------
    maps : path, xarray.Dataset or MapsStore
        A maps store (:func:`pipeline.build_maps`), the Dataset :func:`pipeline.open_maps`
        returned for it, or its :class:`pipeline.store.maps_store.MapsStore`.
    start, goal : (row, col)
        Fine cells; or, instead of either, as a job file gives them:
    start_xy, goal_xy : (x, y)
        Map coordinates (metres, the maps' CRS).
    start_lonlat, goal_lonlat : (lon, lat)
        WGS84 longitude and latitude (the maps need a CRS). Each end in exactly one form.
    planner : str
        The planner of every section (and of the whole map with ``mcpc=False``): a name of
        :data:`pipeline.planners.PLANNERS`.
    omega : float
        The length bound of the bounded planners, kept per section.
    mcpc : bool
        False plans the whole map in one window (one task).
    rho, section_size, margin : int, optional
        Compression factor, section side and window margin in fine cells; defaults from the
        map (module documentation).
    coarse_planner : str
        Planner of the coarse path (A*, the paper's choice). Coarse ridge cells are those whose
        block is at least half ridge.
    coarse_weight : float
        For the bounded planners (wastar, ra_star, lagrangian) the coarse A* is weighted A* of
        weight ``min(coarse_weight, omega)`` (1: exact A*, as in the paper): the coarse path
        only guides the sections, and at 1.1 it expands a small fraction of the exact search's
        cells for a path at most 10 % longer than the coarse optimum (a few tenths of a
        percent longer on the benchmark maps); at 1.05, on coarse grids whose 3-D lengths
        exceed the horizontal ones by more than 5 %, it took several times as long, with the
        same ridge and length after the sections (CHANGELOG.md, "Measurements"). The optimal
        planners (astar, dijkstra) keep the exact coarse A*: their stitched paths follow the
        coarse route, and a 5 % detour there is 5 % on the result. Other coarse planners run
        with the mission's omega.
    repair_max_cells : int
        The largest map (rows x cols) on which an uncertified MCPC path is planned again on
        the whole map; 0 never does.
    via, via_xy, via_lonlat : list of pairs, optional
        Points the mission visits in order between start and goal, in one form (cells, map
        coordinates, longitude and latitude). Each leg is planned as a mission of its own with
        these options; the trajectory joins them, its bound is the sum of the legs' bounds
        (a lower bound on the sum of their optima, the shortest path through the points in
        order), and ``extra["legs"]`` records each leg.
    keep_out : path, list of paths, GeoDataFrame, shapely polygons or KeepOut, optional
        Keep-out zones the path never enters (:mod:`pipeline.constraints.zones`): vector files
        geopandas reads (GeoJSON, GeoPackage, Shapefile; any CRS), a GeoDataFrame, or polygons in
        map coordinates. The trajectory keeps them (``keep_out``) for :func:`pipeline.fly`.
    keep_out_margin_m : float, optional
        The distance kept from every zone (default 0).
    max_depth_m : float, optional
        The vehicle's rated depth (metres below the sea surface, as the vehicle files measure
        depth): the path is planned and measured on the safety surface raised to the sea level
        less ``max_depth_m`` where it lies deeper, and certified
        against the octile distance (:mod:`pipeline.constraints.store`). :func:`pipeline.fly` keeps
        the rating the trajectory records (``max_depth_m``).
    client : None, "synchronous", "threads", scheduler address or distributed.Client
        Where the sections run (see :func:`pipeline.runtime.cluster.get_client`). None: the dask
        client this process made current, if there is one, else this process's threads (no
        cluster is started for one mission: a plain script needs no main guard).

    Returns
    -------
    Trajectory
        ``status`` "ok" (certified) or "uncertified"; ``certified_ratio`` is ``length_m /
        lower_bound_m``. ``extra`` holds the parameters, the coarse path, every section
        (window, attempts, times), the timings of the stages and, when the path was repaired,
        ``extra["repair"]``.

    Examples
    --------
    >>> t = pipeline.plan("maps.zarr", (120, 80), (9800, 9900), omega=2.0)  # doctest: +SKIP
    """
    t0 = time.perf_counter()
    m = open_store(maps)
    planner, omega, rho, section_size, margin = _check_args(
        planner, omega, m, rho, section_size, margin
    )
    check_planner(coarse_planner, omega, "coarse_planner")
    coarse_weight = PLANNING.coarse_weight.check(coarse_weight)
    mcpc = PLANNING.mcpc.check(mcpc)
    repair_max_cells = PLANNING.repair_max_cells.check(repair_max_cells)
    given = {
        k: v
        for k, v in dict(
            start=start,
            goal=goal,
            start_xy=start_xy,
            goal_xy=goal_xy,
            start_lonlat=start_lonlat,
            goal_lonlat=goal_lonlat,
            via=via,
            via_xy=via_xy,
            via_lonlat=via_lonlat,
        ).items()
        if v is not None
    }
    from ..constraints.store import constrained

    margin_m = PLANNING.keep_out_margin_m.check_optional(keep_out_margin_m)
    m = constrained(m, keep_out, margin_m, max_depth_m)
    points, names = _points(m, given)
    if len(points) > 2:  # via points: each leg a mission of its own
        _check_endpoints(m, points, names, given)
        legs = dict(
            planner=planner, omega=omega, mcpc=mcpc, rho=rho, section_size=section_size,
            margin=margin, coarse_planner=coarse_planner, coarse_weight=coarse_weight,
            repair_max_cells=repair_max_cells, client=client,
        )  # fmt: skip
        traj = _plan_legs(m, points, names, legs, t0)
        traj.extra["via_given_xy"] = _given_via_xy(m, given)  # the flight's via_miss_m
        return traj
    start, goal = _check_endpoints(m, points, names, given)
    # the components layer proves reachability at once, either way (_Reach)
    reach = _Reach(m, start, goal)
    run_on = get_client(client, own="threads")  # no cluster of its own for one mission
    extra: dict = {
        "mcpc": bool(mcpc),
        "rho": rho,
        "section_size": section_size,
        "margin": margin,
        "coarse_planner": coarse_planner,
        "coarse_weight": coarse_weight,
    }
    req = _Request(
        m,
        run_on,
        planner,
        omega,
        start,
        goal,
        t0,
        extra,
        rho,
        section_size,
        margin,
        coarse_planner,
        coarse_weight,
        _Bound(m, start, goal, extra),
        reach,
    )
    return _plan_request(req, mcpc, repair_max_cells)


def _points(m, given: dict) -> tuple[list, list]:
    """The mission's points as cells (start, via points, goal) and their names, from the
    forms they were ``given`` in, each outside the zones (:func:`check_outside`)."""
    from ..constraints.store import check_outside
    from ..params import endpoint_cells

    ends = endpoint_cells(m, given)  # as a job file gives them
    vias = [_cell(f"via {k + 1}", v) for k, v in enumerate(ends.get("via", []))]
    names = ["start", *(f"via {k + 1}" for k in range(len(vias))), "goal"]
    points = [_cell("start", ends["start"]), *vias, _cell("goal", ends["goal"])]
    for name, cell in zip(names, points, strict=True):
        check_outside(m, name, cell)
    return points, names


def _plan_request(req: _Request, mcpc: bool, repair_max_cells: int) -> Trajectory:
    """One mission's search: the whole map (``mcpc`` False), or MCPC, falling back to the whole
    map when MCPC finds no path though start and goal share a component, and repaired by a
    search of the whole map (up to ``repair_max_cells``) when its bound is not proven."""
    m, omega, reach, extra = req.m, req.omega, req.reach, req.extra
    if not mcpc:
        reach.check()
        return _done(m, _plan_whole(req))
    try:
        t = _plan_mcpc(req)
    except UnreachableGoalError as exc:
        if not reach.check():  # reachability unknown (a store without components): as it says
            raise
        # start and goal share a component, so a path exists that the coarse map or the
        # sections missed (a passage narrower than rho cells): plan the whole map
        extra["fallback"] = f"MCPC found no path ({exc}); planned on the whole map instead"
        return _done(m, _plan_whole(req))
    if certified(t.length_m, t.lower_bound_m, omega):
        return _done(m, t)
    cells = m.shape[0] * m.shape[1]
    if cells > repair_max_cells:
        return _done(m, t, repair=f"the map's {cells} cells exceed repair_max_cells")
    # repair: one search over the whole map, whose planner proves its own bound
    tr = time.perf_counter()
    repair = {
        "reason": f"the stitched path ({t.length_m:.1f} m) is {t.length_m / t.lower_bound_m:.4f}"
        f" x the proven lower bound ({t.lower_bound_m:.1f} m), above omega = {omega:g}",
        "stitched_length_m": t.length_m,
        "stitched_ridge_ratio": t.ridge_ratio,
    }
    whole = _plan_whole(req, {**t.extra, "repair": repair})
    repair["seconds"] = time.perf_counter() - tr
    return _done(m, whole)


def _plan_legs(m, points: list, names: list, options: dict, t0: float) -> Trajectory:
    """A mission through via points: each leg planned in turn as a mission of its own on the
    constrained store ``m``, the legs joined (the joints once), its length and ridge the legs'
    sums, its lower bound the sum of theirs, certified as one mission (docs/certified-bound.md,
    "Via points")."""
    legs = []
    # each leg under the mission's constraints (plan() takes the store's own, unconstrained)
    options = {**options, "keep_out": m.keep_out, "max_depth_m": m.max_depth_m}
    for k in range(len(points) - 1):
        try:
            leg = plan(m, points[k], points[k + 1], **options)
        except UnreachableGoalError as exc:
            raise UnreachableGoalError(
                f"leg {k + 1} ({names[k]} to {names[k + 1]}): {exc}"
            ) from None
        legs.append(leg)
    first = [leg.cells if k == 0 else leg.cells[1:] for k, leg in enumerate(legs)]
    cells = np.vstack(first)
    points_xyz = np.vstack([leg.points if k == 0 else leg.points[1:] for k, leg in enumerate(legs)])
    length = float(sum(leg.length_m for leg in legs))
    ridge = float(sum(leg.ridge_length_m for leg in legs))
    joints = np.cumsum([0] + [len(c) for c in first])[1:-1] - 1  # via points' indices in cells
    extra = {
        "via_index": joints.astype(np.int64),
        "legs": [
            {
                "from": names[k],
                "to": names[k + 1],
                "status": str(leg.status),
                "length_m": leg.length_m,
                "lower_bound_m": leg.lower_bound_m,
                "ridge_ratio": leg.ridge_ratio,
                "cells": len(leg.cells),
                "message": leg.message,
            }
            for k, leg in enumerate(legs)
        ],
        "sections": [s for leg in legs for s in leg.extra.get("sections", [])],
    }
    t = Trajectory(
        cells=cells,
        points=points_xyz,
        length_m=length,
        ridge_length_m=ridge,
        ridge_ratio=ridge / length if length > 0 else 0.0,
        lower_bound_m=float(sum(leg.lower_bound_m for leg in legs)),
        expansions=int(sum(leg.expansions for leg in legs)),
        runtime_s=time.perf_counter() - t0,
        planner=legs[0].planner,
        omega=legs[0].omega,
        extra=extra,
    )
    return _done(m, t)


# landmark layers the whole-map search reads for its heuristic (those that bound the mission
# best). None by default: on the benchmark maps reading a whole-map layer takes longer than the
# landmark heuristic saves A* there (CHANGELOG.md, "Measurements"); on maze-like maps it saves
# far more. plan_window takes layers directly (``landmarks=``).
ACTIVE_LANDMARKS = 0


@dataclass(frozen=True)
class _Request:
    """A mission's arguments once :func:`plan` has checked them, as its steps take them."""

    m: MapsStore
    run_on: object  # where sections run (cluster.get_client)
    planner: str
    omega: float
    start: tuple[int, int]
    goal: tuple[int, int]
    t0: float  # when plan() started (perf_counter)
    extra: dict  # what the trajectory's ``extra`` records of the planning
    rho: int
    section_size: int
    margin: int
    coarse_planner: str
    coarse_weight: float
    bound: _Bound
    reach: _Reach  # the components layer's proof of reachability

    @property
    def ends(self) -> tuple:
        """``(start, goal)``."""
        return self.start, self.goal


def _plan_whole(req: _Request, extra: dict | None = None) -> Trajectory:
    """One search over the whole map (its planner proves its own bound); ``extra`` (default
    the request's) is kept with the trajectory."""
    m, planner = req.m, req.planner
    extra = req.extra if extra is None else extra
    k = min(ACTIVE_LANDMARKS, len(m.landmarks)) if PLANNERS[planner].uses_landmarks else 0
    whole = Section((0, m.shape[0], 0, m.shape[1]), req.start, req.goal, landmarks=k)
    res = _run(req.run_on, m, [whole], planner, req.omega)[0]
    if not res.ok:
        raise UnreachableGoalError(
            f"no path on the whole map: {res.message}{_zones_cause(m, req.start, req.goal)}"
        )
    extra["sections"] = [_section_summary(res, whole)]
    # a search of the whole map proves its own bound on L*
    lower = max(req.bound.value(), res.lower_bound_m)
    return _finish(
        m, [res], planner, req.omega, req.start, req.goal, res.expansions, req.t0, extra, lower
    )


def _zones_cause(m, start, goal) -> str:
    """What to add to a mission's 'no path' when its keep-out zones are the cause: the store
    without them holds start and goal in one passable region (its components layer)."""
    zones = getattr(m, "keep_out", None)
    base = getattr(m, "base", None)
    if zones is None or base is None:
        return ""
    try:
        a, b = base.components(start, goal)
    except Exception:  # noqa: BLE001 - a store without the layer: nothing to add
        return ""
    if a is None or a != b:
        return ""
    return (
        f"; without the keep-out zones ({', '.join(zones.names)}, kept {zones.margin_m:g} m "
        "off) the two are connected: the zones close the way between them"
    )


def _plan_mcpc(req: _Request) -> Trajectory:
    """Algorithm 3 for one mission: the coarse path, its sections planned where ``req.run_on``
    runs them, the stitched path measured and bounded."""
    m, run_on, planner, omega, start, goal = req.m, req.run_on, req.planner, req.omega, *req.ends
    t0, extra, rho, section_size, margin = req.t0, req.extra, req.rho, req.section_size, req.margin
    coarse_planner, coarse_weight, bound = req.coarse_planner, req.coarse_weight, req.bound
    reach = req.reach
    # 1-2: compression (cached) and the coarse path
    tc = time.perf_counter()
    co = m.coarse(rho)
    cs = _coarse_endpoint(co["passable"], (start[0] // rho, start[1] // rho))
    cg = _coarse_endpoint(co["passable"], (goal[0] // rho, goal[1] // rho))
    if cs is None or cg is None:
        which = "start" if cs is None else "goal"
        raise UnreachableGoalError(
            f"no passable coarse cell near the {which} at rho={rho}; "
            "try a smaller rho or mcpc=False"
        )
    # the coarse A* is weighted A* (see ``coarse_weight``); other planners take omega
    weight = 1.0 if PLANNERS[planner].optimal else min(coarse_weight, omega)
    if coarse_planner == "astar" and weight > 1.0:
        coarse_planner, coarse_omega = "wastar", weight
    else:
        coarse_omega = omega
    try:
        ct = search_window(  # the coarse level's arrays are checked when it is read
            co["safety"],
            co["ridge_cells"],
            co["passable"],
            cs,
            cg,
            m.cell_size * rho,
            coarse_planner,
            coarse_omega,
        )
    except UnreachableGoalError:
        cause = _zones_cause(m, start, goal)
        raise UnreachableGoalError(
            f"no coarse path from {start} to {goal} at rho={rho}: the goal is unreachable, or "
            "reachable only through passages narrower than rho cells; try a smaller rho or "
            f"mcpc=False{cause}"
        ) from None
    extra["coarse_cells"] = ct.cells.astype(np.int32)  # an array: quick to send back
    extra["coarse_s"] = time.perf_counter() - tc
    reach.check()  # before any section: a goal in another region is no mission

    # 3-5: restore, segment, snap the joints
    pts = restore(ct.cells, rho, m.shape, start, goal)
    secs = segment(pts, section_size, margin, m.shape)
    # in one process the windows are read from now on, while the joints are snapped
    ahead = _ReadAhead.start(run_on, m, [w for _, _, w in secs])
    try:
        joints = _snapped_joints(m, pts, secs, goal, rho, margin)
        sections = [Section(w, joints[k], joints[k + 1]) for k, (_, _, w) in enumerate(secs)]

        # 6: plan the sections as tasks; retry failures with a doubled margin, then merged
        tp = time.perf_counter()
        sections, results = plan_sections(ahead or run_on, m, sections, planner, omega, margin)
        extra["sections_s"] = time.perf_counter() - tp
    finally:
        if ahead is not None:
            ahead.close()  # a mission that failed before its sections: its reads dropped

    # 7: stitch, then cut any loops
    extra["sections"] = [_section_summary(r, sec) for r, sec in zip(results, sections, strict=True)]
    expansions = ct.expansions + sum(r.expansions for r in results)
    # the sections' own bounds hold on their windows only: the landmark bound is the proof
    return _finish(m, results, planner, omega, start, goal, expansions, t0, extra, bound.value())


def _given_via_xy(m, given: dict) -> list:
    """A mission's via points as the user gave them, in map coordinates (a cell: its
    centre)."""
    from ..params import via_form

    form, points = via_form(given)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if form == "cell":
        return [[float(m.x[int(c)]), float(m.y[int(r)])] for r, c in pts]
    if form == "lonlat":
        from pyproj import CRS, Transformer

        tr = Transformer.from_crs("EPSG:4326", CRS.from_wkt(m.crs_wkt), always_xy=True)
        x, y = tr.transform(pts[:, 0], pts[:, 1])
        return np.column_stack([x, y]).tolist()
    return pts.tolist()
