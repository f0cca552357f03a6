"""Many missions at once on one maps store.

``plan_missions`` on a cluster runs each mission within one task (its coarse search, bound,
sections and flight in one worker, the sections in turn), as many at once as the cluster has
threads: missions run side by side instead of one mission's sections, which keeps every
worker busy with no round trip per section (about 1.4x the missions per second of a section
task each, `benchmarks/bench_jobs.py`). Large batches go a few missions to a task (see
``missions_per_task``), the last missions one to a task. A single mission, or
``client="synchronous"`` or ``"threads"``, runs in client threads, each mission's sections
where :func:`pipeline.plan` runs them (tasks on a cluster, or in this process). A mission
that cannot be planned comes back as a ``Trajectory`` with ``status="failed"`` and its
reason; the others complete.
"""

from __future__ import annotations

import difflib
import logging
import math
import threading
import uuid
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass

import numpy as np

from .._types import ClientLike, Maps, VehicleLike
from ..exceptions import InvalidParameterError, PipelineError
from ..flight.fly import with_flight
from ..flight.vehicle import Vehicle
from ..mcpc.algorithm import coarse_rho
from ..mcpc.certify import certified
from ..mcpc.plan import plan
from ..params import (
    ENDPOINT_FORMS,
    MISSIONS_PER_TASK,
    PLANNING,
    VIA_KEYS,
    endpoint_cells,
    endpoint_form,
    endpoint_key,
)
from ..runtime.cluster import IN_PROCESS, get_client
from ..runtime.threads import cores
from ..store.maps_store import open_store
from ..trajectory import Status, Trajectory

log = logging.getLogger(__name__)


_PLAN_KEYS = PLANNING.names()


# the keys a mission's dict is read for; any other is kept for the caller (a name, a tag),
# unless it is a near miss of one of these (``omgea``), which would be planned as if absent
_ENDPOINT_KEYS = {endpoint_key(end, f) for end in ("start", "goal") for f in ENDPOINT_FORMS}


_MISSION_KEYS = sorted(
    _PLAN_KEYS | _ENDPOINT_KEYS | set(VIA_KEYS) | {"vehicle", "name", "max_depth_m"}
)


def failed_trajectory(mission: dict, message: str) -> Trajectory:
    """The record of a mission that could not be planned."""
    omega = mission.get("omega", PLANNING.omega.default)
    return Trajectory(
        cells=np.zeros((0, 2), dtype=np.int64),
        points=np.zeros((0, 3)),
        length_m=math.nan,
        ridge_length_m=math.nan,
        ridge_ratio=math.nan,
        lower_bound_m=math.nan,
        expansions=0,
        runtime_s=0.0,
        planner=str(mission.get("planner", PLANNING.planner.default)),
        omega=float(omega) if isinstance(omega, int | float) else math.nan,
        status=Status.FAILED,
        message=message,
    )


def _normalise(m) -> dict:
    if isinstance(m, dict):
        mission = dict(m)
    else:
        try:
            start, goal = m
        except (TypeError, ValueError):
            raise InvalidParameterError(
                f"a mission must be a dict with start and goal, or a (start, goal) pair, got {m!r}"
            ) from None
        mission = {"start": start, "goal": goal}
    for end in ("start", "goal"):
        endpoint_form(mission, end)  # exactly one of the three forms
    for key in mission:
        if key in _MISSION_KEYS:
            continue
        near = difflib.get_close_matches(str(key).lower(), _MISSION_KEYS, n=1, cutoff=0.75)
        if near:
            raise InvalidParameterError(
                f"mission key {key!r} is no option of a mission: did you mean {near[0]!r}? "
                f"(options: {', '.join(_MISSION_KEYS)}; other keys are kept as they are)"
            )
    return mission


def plan_missions(
    maps: Maps,
    missions: Sequence,
    *,
    client: ClientLike = None,
    defaults: dict | None = None,
    max_concurrent: int = 4,
    on_done: Callable[[int, dict, Trajectory], None] | None = None,
    vehicle: VehicleLike = None,
    quicklooks: bool = False,
    missions_per_task: int | None = None,
) -> list[Trajectory]:
    """Plan many missions on one maps store; trajectories come back in mission order.

    Parameters
    ----------
    maps : path, xarray.Dataset or MapsStore
        The maps store (:func:`pipeline.build_maps`).
    missions : sequence
        Each a ``(start, goal)`` pair of cells or a dict with ``start``, ``goal`` and any of
        :func:`pipeline.plan`'s options (``planner``, ``omega``, ``mcpc``, ``rho``,
        ``section_size``, ``margin``, ``keep_out``, ``max_depth_m``: the rating, as the
        vehicle's) and ``vehicle``; other keys (a ``name``, a tag of the
        caller's) are kept for ``on_done``, but a near miss of an option (``omgea``) fails
        its mission with the reason, as it would be planned as if it were absent.
    client : as :func:`pipeline.plan`
    defaults : dict, optional
        Options for every mission that does not set them.
    max_concurrent : int
        Missions in flight at once when they run in client threads (one mission, or
        ``client="synchronous"`` or ``"threads"``); on a cluster the scheduler runs one
        mission per worker thread at a time. With ``"threads"`` a mission's sections are
        shared by the cores only while fewer missions than cores are in flight; else each
        mission plans its sections in turn.
    on_done : callable, optional
        ``on_done(index, mission, trajectory)`` as each mission finishes (in finishing order),
        e.g. to write its result at once.
    vehicle : Vehicle or dict, optional
        When given (or when a mission has a ``vehicle`` dict of its own, laid over it), each
        planned trajectory gets its flown track and waypoints (``trajectory.flight``,
        :func:`pipeline.fly`); a flight that breaks a vehicle limit or needs more energy than
        the battery holds fails the mission with the reason.
    quicklooks : bool
        Draw each planned mission's quick-look PNG
        (:func:`pipeline.outputs.plots.mission_quicklook`, titled with the mission's
        ``name``) where the mission was planned, on the worker that planned it: its bytes are
        ``trajectory.extra["quicklook_png"]`` (about 1 MB each; a caller that keeps many
        trajectories should take them out in ``on_done``).
    missions_per_task : int, optional
        On a cluster, how many missions one task plans, in turn. dask costs the scheduler and
        this client some CPU a task, a sizeable share of a small machine at many missions a
        second; grouping pays it once for several missions. Default:
        1 up to 8 missions per cluster thread, then one eighth of a thread's missions, up to 8
        (faster, for less of the client's CPU, than the smaller groups tried; CHANGELOG.md,
        "Measurements"); the last ``2 x threads``
        missions run one per task either way, so that no worker waits for another's group at
        the end. 1: every mission its own task.

    Returns
    -------
    list of Trajectory
        Certified missions have ``status == "ok"``; planned but not certified ones
        ``"uncertified"`` (the proven ratio in ``message``, see :func:`pipeline.plan`); failed
        missions ``"failed"`` and the reason in ``message``, a malformed one (not a pair of
        cells, no goal) included: the others are planned.

    Examples
    --------
    >>> ts = pipeline.plan_missions("maps.zarr", [((5, 5), (900, 950)),
    ...                                          {"start": (10, 900), "goal": (950, 20),
    ...                                           "planner": "lagrangian", "omega": 1.5}])
    ... # doctest: +SKIP
    """
    if isinstance(missions, str | bytes | dict) or not isinstance(missions, Iterable):
        raise InvalidParameterError(
            "`missions` must be a sequence of missions (each a (start, goal) pair of cells or "
            f"a dict with start and goal), got {type(missions).__name__}"
        )
    missions = list(missions)
    m = open_store(maps)
    run_on = get_client(client)
    items, invalid = _read_missions(m, missions)
    todo = [i for i in range(len(items)) if i not in invalid]
    defaults = dict(defaults or {})
    unknown = set(defaults) - _PLAN_KEYS
    if unknown:
        raise InvalidParameterError(
            f"unknown planning option {sorted(unknown)[0]!r}; allowed: {sorted(_PLAN_KEYS)}"
        )

    missions_per_task = MISSIONS_PER_TASK.check_optional(missions_per_task)
    batch = _Batch(
        defaults, vehicle.to_dict() if isinstance(vehicle, Vehicle) else vehicle, quicklooks
    )
    out: list[Trajectory | None] = [None] * len(items)
    if len(todo) > 1:
        _prepare_coarse(m, [items[i] for i in todo], defaults)

    def done(i: int, t: Trajectory) -> None:
        out[i] = t
        if on_done is not None:
            on_done(i, items[i], t)

    for i, message in invalid.items():
        done(i, failed_trajectory(items[i], message))
    if run_on not in IN_PROCESS and len(todo) > 1:
        _on_cluster(run_on, m, items, batch, done, missions_per_task, todo)
        return out  # type: ignore[return-value]
    _in_threads(m, items, todo, batch, run_on, max_concurrent, done)
    return out  # type: ignore[return-value]


def _read_missions(m, missions) -> tuple[list, dict]:
    """``(items, invalid)``: each mission as a dict with its ends as cells of ``m``, and the
    reason of each that cannot be read (by index): it fails alone, the batch goes on."""
    items, invalid = [], {}
    for i, x in enumerate(missions):
        try:
            items.append(endpoint_cells(m, _normalise(x)))
        except PipelineError as exc:  # (an end or a via point off the map, on land: its own)
            items.append(dict(x) if isinstance(x, dict) else {"mission": x})
            invalid[i] = str(exc)
    return items, invalid


def _in_threads(m, items, todo, batch: _Batch, run_on, max_concurrent: int, done) -> None:
    """The missions ``todo`` in this process, up to ``max_concurrent`` at once in threads,
    ``done(i, trajectory)`` for each as it finishes; a mission that raises (a bug) fails
    alone."""
    workers = max(1, min(int(max_concurrent), len(todo)))
    if run_on == "threads" and workers >= cores():
        # the missions' threads keep every core busy: a mission's sections in turn, as
        # sharing them between threads too cost time (CHANGELOG.md, "Measurements")
        run_on = "synchronous"
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="mission") as pool:
        futures = {pool.submit(_plan_one, m, items[i], batch, run_on, i): i for i in todo}
        for fut in as_completed(futures):
            i = futures[fut]
            try:
                t = fut.result()
            except Exception as exc:  # noqa: BLE001 - a crash in one mission must not stop the batch
                log.exception("mission %d crashed", i)
                t = failed_trajectory(items[i], f"{type(exc).__name__}: {exc}")
            done(i, t)


def _prepare_coarse(m, items, defaults) -> None:
    """Write the coarse levels the MCPC missions use into the store once, here, before the
    missions start: otherwise every mission of the first wave finds none and computes the same
    one at once (seconds added to each of them, and to their recorded runtimes). A level that
    cannot be made is left to the missions, which report why."""
    rhos = set()
    for mission in items:
        opts = {**defaults, **mission}
        if not opts.get("mcpc", PLANNING.mcpc.default):
            continue
        try:
            rhos.add(coarse_rho(m, opts.get("rho")))
        except PipelineError:  # the mission says why
            continue
    for rho in sorted(rhos):
        try:
            m.coarse(rho)
        except Exception as exc:  # noqa: BLE001 - the missions then meet it and say why
            log.debug("coarse level rho=%r not prepared: %s", rho, exc)


@dataclass(frozen=True)
class _Batch:
    """What every mission of one :func:`plan_missions` call shares, as its tasks take it: the
    planning defaults, the vehicle (a dict of its keys, or None: no flight) and whether to
    draw each mission's quick-look."""

    defaults: dict
    vehicle: dict | None
    quicklooks: bool


def _plan_one(m, mission: dict, batch: _Batch, run_on, i: int = 0) -> Trajectory:
    """One mission of :func:`plan_missions`: planned (its sections on ``run_on``), then flown
    when a vehicle is given, then drawn (``batch.quicklooks``); a mission that cannot be
    planned or flown comes back failed with the reason."""
    t = _plan_and_fly(m, mission, batch, run_on, i)
    if batch.quicklooks and len(t.cells) > 1:
        try:
            t.extra["quicklook_png"] = _quicklook_png(m, t, mission.get("name", f"mission {i}"))
        except Exception as exc:  # noqa: BLE001 - the mission stands; its writer draws it again
            log.warning("mission %d: its quick-look could not be drawn here: %s", i, exc)
    return t


# matplotlib makes no promise for figures drawn in several threads of a process at once (the
# missions' threads here, the threads of a multi-threaded worker): one at a time per process
_DRAWING = threading.Lock()


def _quicklook_png(m, t: Trajectory, name) -> bytes:
    import io

    from ..outputs.plots import mission_quicklook

    with _DRAWING:
        return mission_quicklook(m, t, io.BytesIO(), title=name, crs_wkt=m.crs_wkt).getvalue()


def _plan_and_fly(m, mission: dict, batch: _Batch, run_on, i: int) -> Trajectory:
    opts = {**batch.defaults, **{k: v for k, v in mission.items() if k in _PLAN_KEYS}}
    opts.update({k: mission[k] for k in VIA_KEYS if k in mission})
    vehicle = {**(batch.vehicle or {}), **mission.get("vehicle", {})}
    rated = mission.get("max_depth_m")  # plan's own keyword, or the vehicle's rating
    if rated is not None and vehicle.get("max_depth_m") not in (None, rated):
        return failed_trajectory(
            {**opts},
            f"max_depth_m is {rated!r} for the mission and {vehicle['max_depth_m']!r} for its "
            "vehicle; give the rating once",
        )
    if rated is not None:
        vehicle["max_depth_m"] = rated
    if vehicle.get("max_depth_m") is not None:  # the rating: its path is planned for it too
        opts["max_depth_m"] = vehicle["max_depth_m"]
    try:
        t = plan(m, mission["start"], mission["goal"], client=run_on, **opts)
    except PipelineError as exc:
        return failed_trajectory({**opts}, str(exc))
    if batch.vehicle is None and "vehicle" not in mission:
        return t

    def again(keep) -> Trajectory:  # the mission planned again under the zones ``keep``
        o = {**opts, "keep_out": keep, "keep_out_margin_m": None}
        return plan(m, mission["start"], mission["goal"], client=run_on, **o)

    try:
        return fly_or_plan_again(m, t, vehicle, again, mission.get("name", f"mission {i}"))
    except PipelineError as exc:
        t.status = Status.FAILED
        t.message = f"its flown track could not be made: {exc}"
        return t
    except Exception as exc:  # noqa: BLE001 - a fault in one flight keeps the planned path
        log.exception("mission %d: the flight failed", i)
        t.status = Status.FAILED
        t.message = (
            f"its flown track could not be made ({type(exc).__name__}: {exc}); the "
            "planned path is kept; this is a bug, please report it with the log"
        )
        return t


# how many times a mission whose flight breaks a limit at places it can name (a height above
# the surface limit, unknown seabed, a turn too tight) is planned again around them
FLIGHT_ROUNDS = 3
# a round's zone at these shares of its radius, the next where one closes every way around
ZONE_SCALES = (1.0, 0.5, 0.25)
# below this share of the grid path's ridge share kept by its flight (where the route along
# the ridges broke a limit) the mission is planned again around the places; if it still is,
# its message says so
RIDGE_SAID = 0.75


def fly_or_plan_again(m, t: Trajectory, vehicle, again, name) -> Trajectory:
    """``t`` flown (:func:`~pipeline.flight.fly.with_flight`), then planned again by
    ``again(zones)`` around the places its flight names and flown again, up to
    :data:`FLIGHT_ROUNDS` rounds, each logged and recorded (``extra["flight_rounds"]``):
    while the flight fails at places (``Flight.trouble_xy``), or flies but keeps less than
    :data:`RIDGE_SAID` of the planned ridge share because the smoothing that keeps the ridges
    broke a limit at places (``Flight.ridge_trouble_xy``); the best flight of the rounds is
    kept (a better status, or the same over more ridge). Round ``k``'s zone is a disc of ``k``
    times the turn radius and a cell round each place, less the mission's own points; every
    round's zone is kept.

    A path planned again is certified against the original problem: its length against
    ``omega`` times the lower bound proven in the first round (the zones only lengthen the
    shortest path, so that bound still holds; the bound proven under the zones need not):
    ok where it holds, else uncertified (docs/certified-bound.md, "Planning around the
    flight")."""
    from ..constraints.zones import KeepOut

    t = with_flight(m, t, vehicle)
    lower, user, rounds, zones = t.lower_bound_m, t.keep_out, [], []
    margin = user.margin_m if user is not None else 0.0
    best, best_round = t, 0  # the best flight so far (status, then ridge share flown)
    while t.flight is not None and len(rounds) < FLIGHT_ROUNDS:
        why = _why_again(t)
        if why is None:
            break
        problem, places, kind = why
        k = len(rounds) + 1
        zone, end = _around(m, t, places, k, margin)
        if end is not None:  # no route to plan can help
            if kind == "fail":
                t.message = (
                    f"{t.message}; it breaks in the {end}'s own cell, which no route avoids: "
                    f"move the {end}"
                )
            break
        if zone is None:
            break
        rounds.append({"round": k, "problem": problem})
        log.info("%s: flight round %d: %s; planning again around it", name, k, problem)
        nxt, failure = None, None
        for scale in ZONE_SCALES:  # a zone that closes the way (a narrow strait): smaller
            zone = _around(m, t, places, k, margin, scale)[0] if scale != 1 else zone
            if zone is None:  # nothing left of it beside the mission's own points
                break
            keep = KeepOut(
                (*(user.zones if user is not None else ()), *zones, (f"flight round {k}", zone)),
                margin,
            )
            try:
                nxt = again(keep)
                break
            except PipelineError as exc:
                failure = exc
        if nxt is None:
            rounds[-1]["result"] = f"no path around it ({failure})"
            break
        zones.append((f"flight round {k}", zone))
        t = with_flight(m, _against_original(nxt, lower), vehicle)
        rounds[-1]["result"] = str(t.status)
        if t.flight is not None and t.status != Status.FAILED:
            rounds[-1]["result"] += f", {_ridge_kept(t):.0%} of its ridge share flown"
        if _flies_better(t, best):
            best, best_round = t, k
    if rounds:
        if best_round != len(rounds):
            which = f"round {best_round}'s" if best_round else "the first"
            rounds[-1]["result"] += f"; {which} route flown"
        t = best
        t.extra["flight_rounds"] = rounds
        tried = "; ".join(
            f"round {r['round']}: "
            + (r["problem"] if j == 0 or r["problem"] != rounds[j - 1]["problem"] else "the same")
            + f" -> {r['result']}"
            for j, r in enumerate(rounds)
        )
        lead = (
            f"no flyable route within {len(rounds)} round{'s' * (len(rounds) > 1)} of "
            "planning around the flight"
            if t.status == Status.FAILED
            else "planned again around its flight's problems"
            if best_round
            else "planning again around its flight's problems flew no better"
        )
        t.message = f"{lead} ({tried})" + (f"; {t.message}" if t.message else "")
    if t.flight is not None and t.status != Status.FAILED and _ridge_kept(t) < RIDGE_SAID:
        f = t.flight
        note = (
            f"the flown route keeps {_ridge_kept(t):.0%} of the grid path's ridge share "
            f"({f.ridge_ratio:.0%} against {t.ridge_ratio:.0%}): with turns of at least "
            f"{f.turn_radius_m:g} m and its pitch and surface limits the vehicle cannot follow "
            "the ridges closer"
        )
        t.message = f"{t.message}; {note}" if t.message else note
    return t


def _why_again(t: Trajectory) -> tuple | None:
    """``(problem, places, kind)`` when the flight of ``t`` asks for another round: it fails
    at places it names (``"fail"``), or it keeps too little of the ridges where the smoothing
    that keeps them broke a limit at places (``"ridge"``); else None."""
    f = t.flight
    if t.status == Status.FAILED:
        if f.trouble_xy is not None and len(f.trouble_xy):
            return "; ".join(f.problems), f.trouble_xy, "fail"
        return None
    kept = _ridge_kept(t)
    if f.ridge_trouble_xy is not None and kept < RIDGE_SAID:
        return (
            f"the flown route keeps {kept:.0%} of the planned ridge share (a route along the "
            "ridges breaks a limit)",
            f.ridge_trouble_xy,
            "ridge",
        )
    return None


def _ridge_kept(t: Trajectory) -> float:
    """The share of the grid path's ridge share its flight keeps (1 without ridge)."""
    return t.flight.ridge_ratio / t.ridge_ratio if t.ridge_ratio > 0 else 1.0


_RANK = {Status.OK: 0, Status.UNCERTIFIED: 1, Status.FAILED: 2}


def _flies_better(new: Trajectory, old: Trajectory) -> bool:
    """Whether ``new`` flies better than ``old``: a better status, or the same over more
    ridge (of two failures, the later)."""
    a, b = _RANK[Status(new.status)], _RANK[Status(old.status)]
    if a != b or a == _RANK[Status.FAILED]:
        return a <= b
    return new.flight is not None and new.flight.ridge_ratio > old.flight.ridge_ratio


def _against_original(t: Trajectory, lower: float) -> Trajectory:
    """``t``, planned under added zones, certified against ``lower``, the bound proven for
    the mission as given (:func:`fly_or_plan_again`)."""
    t.extra["lower_bound_under_zones_m"] = t.lower_bound_m
    t.lower_bound_m = lower
    if t.status == Status.OK and not certified(t.length_m, lower, t.omega):
        t.status = Status.UNCERTIFIED
        t.message = (
            f"planned around the flight's problems, its length {t.length_m:.0f} m is above "
            f"omega x the proven lower bound of the mission as given ({t.omega * lower:.0f} "
            "m): flyable, the bound not proven"
        )
    return t


def _around(m, t: Trajectory, places: np.ndarray, k: int, margin: float, scale=1.0) -> tuple:
    """``(zone, end)``: the zone round ``k`` keeps the mission away from, a disc of ``k``
    times the turn radius and a cell (times ``scale``) round each of the ``places`` (map x,
    y), less a disc round
    each of the mission's own points (start, via points, goal: a point in a zone is refused),
    None when nothing is left; ``end`` names the point ("start", "via 2", "goal") in whose own
    cell a place lies (no route can help), else None."""
    import shapely

    from ..constraints.zones import SLACK

    a = m.cell_size
    via = np.asarray(t.extra.get("via_index", []), dtype=np.int64)
    own = [0, *via, len(t.cells) - 1]
    names = ["start", *(f"via {j + 1}" for j in range(len(via))), "goal"]
    cells = t.cells[own]
    ends = np.column_stack([np.asarray(m.x)[cells[:, 1]], np.asarray(m.y)[cells[:, 0]]])
    for name, (x, y) in zip(names, ends, strict=True):
        if np.any(np.maximum(*np.abs(places - (x, y)).T) <= 0.5 * a):
            return None, name
    radius = scale * k * (t.flight.turn_radius_m + a)
    # the places a quarter cell apart at least (a flight names hundreds of samples along a
    # stretch; a disc each took most of a round's time): the zone a little wider instead
    snapped = np.unique(np.round(places / (0.25 * a)), axis=0) * (0.25 * a)
    zone = shapely.MultiPoint(snapped).buffer(radius + 0.18 * a, quad_segs=4)
    zone = zone.difference(shapely.MultiPoint(ends).buffer(margin + (SLACK + 1.0) * a))
    return (None if zone.is_empty else zone), None


def _mission_task(path: str, mission: dict, batch: _Batch, i: int) -> Trajectory:
    """A whole mission as one task on a worker, its sections in turn in this process.

    Any dask computation inside it (a coarse level not in the store yet) runs here too: in a
    task, dask's default scheduler is the worker's client, whose computations secede the task
    from the worker's thread limit, so that every queued mission would start at once and each
    record the others' time as its own."""
    import dask

    with dask.config.set(scheduler="synchronous"):
        return _plan_one(open_store(path), mission, batch, "synchronous", i)


def _missions_task(path: str, group: list, batch: _Batch) -> list:
    """Several missions (``(index, mission)`` pairs) as one task, in turn, each as
    :func:`_mission_task`; a mission that raises (a bug) fails alone, with the reason."""
    out = []
    for i, mission in group:
        try:
            out.append(_mission_task(path, mission, batch, i))
        except Exception as exc:  # noqa: BLE001 - a crash in one mission must not stop the group
            log.exception("mission %d crashed", i)
            out.append(failed_trajectory(mission, f"{type(exc).__name__}: {exc}"))
    return out


def mission_groups(n: int, threads: int, per_task: int | None) -> list[list[int]]:
    """Mission indices in task order: groups of ``per_task`` (default: 1 up to 8 missions a
    thread, then an eighth of a thread's missions, up to 8), the last ``2 * threads`` missions
    alone."""
    threads = max(1, threads)
    per = per_task if per_task is not None else max(1, min(8, n // (8 * threads)))
    if per == 1:
        return [[i] for i in range(n)]
    head = max(0, n - 2 * threads)
    return [list(range(k, min(k + per, head))) for k in range(0, head, per)] + [
        [i] for i in range(head, n)
    ]


def _on_cluster(client, m, items, batch: _Batch, done, per_task=None, todo=None) -> None:
    """Every mission of ``todo`` (indices into ``items``; default: all) in a task (alone, or in
    a group of ``per_task``, see :func:`mission_groups`); ``done(i, trajectory)`` for each as
    its task finishes. A task that raises (a bug) or whose workers keep dying fails its
    missions only."""
    from distributed import as_completed as finished

    token = uuid.uuid4().hex[:8]
    try:
        threads = sum(client.nthreads().values())
    except Exception:  # noqa: BLE001 - an adaptive cluster with no worker yet: one thread
        threads = 1
    todo = list(range(len(items))) if todo is None else todo
    groups = [[todo[j] for j in g] for g in mission_groups(len(todo), threads, per_task)]
    # one map per kind of task, one message each to the scheduler (a submit each would cost it
    # a graph update each before the workers are fed); the groups go first, then the tail
    futures = {}
    multi = [g for g in groups if len(g) > 1]
    if multi:
        futs = client.map(
            _missions_task,
            [m.path] * len(multi),
            [[(i, items[i]) for i in g] for g in multi],
            [batch] * len(multi),
            pure=False,
            key=[f"missions-{g[0]}-{g[-1]}-{token}" for g in multi],
        )
        futures.update(zip(futs, multi, strict=True))
    single = [g[0] for g in groups if len(g) == 1]
    if single:
        futs = client.map(
            _mission_task,
            [m.path] * len(single),
            [items[i] for i in single],
            [batch] * len(single),
            single,
            pure=False,
            key=[f"mission-{i}-{token}" for i in single],
        )
        futures.update((f, [i]) for f, i in zip(futs, single, strict=True))
    for fut in finished(futures, loop=client.loop):
        group = futures[fut]
        try:
            got = fut.result()
            ts = got if isinstance(got, list) else [got]
        except Exception as exc:  # noqa: BLE001 - a crash in one task must not stop the batch
            log.error("missions %s crashed: %s: %s", group, type(exc).__name__, exc)
            ts = [failed_trajectory(items[i], f"{type(exc).__name__}: {exc}") for i in group]
        for i, t in zip(group, ts, strict=True):
            done(i, t)
