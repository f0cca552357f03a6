"""Job files (TOML) -> DEM store -> maps store -> missions -> results catalog.

A job file is validated completely before any compute: an unknown key, a wrong type or a
missing file is one :class:`~pipeline.exceptions.JobFileError` naming the key and the file.
A job file::

    name = "demo"
    [dem]                       # path = "survey.tif" (+ variable, cell_size, resolution), or:
    chunks = 512
    [dem.synthetic]
    shape = [2000, 2000]        # cell_size, seed, islands
    [maps]                      # method, clearance, horizontal_clearance, sea_level,
    clearance = 300.0           # surface_clearance, min_accumulation
    [planning]                  # defaults of every mission: planner, omega, mcpc, rho,
    planner = "ra_star"         # section_size, margin
    omega = 2.0
    [[missions]]
    name = "north-ridge"
    start = [100, 120]          # a cell (row, col); or start_xy = [x, y] in map
    goal = [1800, 1700]         # coordinates, or start_lonlat = [lon, lat]
    omega = 1.5                 # any [planning] key, for this mission
    [output]
    catalog = "catalogs/demo"
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from .exceptions import JobFileError, PipelineError

log = logging.getLogger(__name__)

_TOP_KEYS = {"name", "dem", "maps", "planning", "missions", "output"}
_MAPS_KEYS = {"method", "clearance", "horizontal_clearance", "sea_level", "surface_clearance",
              "min_accumulation"}
_PLANNING_KEYS = {"planner", "omega", "mcpc", "rho", "section_size", "margin"}
_ENDPOINT_KEYS = {f"{w}{form}" for w in ("start", "goal") for form in ("", "_xy", "_lonlat")}
_MISSION_KEYS = {"name"} | _PLANNING_KEYS | _ENDPOINT_KEYS
_DEM_KEYS = {"path", "synthetic", "chunks", "variable", "cell_size", "resolution"}
_SYNTH_KEYS = {"shape", "cell_size", "seed", "islands"}
_OUTPUT_KEYS = {"catalog"}


@dataclass
class Job:
    """A validated job file."""

    path: Path
    name: str
    catalog: Path
    chunks: int = 1024
    dem_path: Path | None = None
    variable: str | None = None
    cell_size: float | None = None
    resolution: float | None = None
    synthetic: dict = field(default_factory=dict)
    maps: dict = field(default_factory=lambda: {"method": "spherical", "clearance": 300.0})
    planning: dict = field(default_factory=dict)
    missions: list = field(default_factory=list)

    def maps_fingerprint(self) -> str:
        """A hash of the DEM definition and the maps parameters (reuse the maps store)."""
        what = {"dem": self.dem_fingerprint(), "maps": self.maps}
        return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:16]

    def dem_fingerprint(self) -> str:
        """A hash of what defines the DEM: re-running with the same inputs reuses the store."""
        if self.dem_path is not None:
            st = self.dem_path.stat()
            what = {"path": str(self.dem_path.resolve()), "size": st.st_size,
                    "mtime_ns": st.st_mtime_ns, "variable": self.variable,
                    "cell_size": self.cell_size}
            if self.resolution is not None:
                what["resolution"] = self.resolution
        else:
            from .synthetic import GENERATOR_VERSION

            what = {"synthetic": self.synthetic, "version": GENERATOR_VERSION}
        what["chunks"] = self.chunks
        return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:16]


def _fail(path: Path, msg: str):
    raise JobFileError(f"job file {path}: {msg}")


def _check_keys(path: Path, table: dict, allowed: set[str], where: str) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        _fail(path, f"unknown key {where}{unknown[0]!r}; allowed keys here: {sorted(allowed)}")


def _typed(path: Path, table: dict, key: str, types, where: str, what: str):
    value = table[key]
    if isinstance(value, bool) or not isinstance(value, types):
        _fail(path, f"{where}{key} must be {what}, got {value!r}")
    return value


def load_job(path: str | os.PathLike) -> Job:
    """Read and validate a job file without computing anything."""
    path = Path(path)
    if not path.is_file():
        raise JobFileError(f"job file {path} does not exist")
    try:
        with open(path, "rb") as fh:
            doc = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise JobFileError(f"job file {path} is not valid TOML: {exc}") from exc
    _check_keys(path, doc, _TOP_KEYS, "")
    name = doc.get("name", path.stem)
    if not isinstance(name, str) or not name or "/" in name or name.startswith("."):
        _fail(path, f"name must be a non-empty file-name-safe string, got {name!r}")
    dem = doc.get("dem")
    if not isinstance(dem, dict):
        _fail(path, "a [dem] table is required, with path = '...' or a [dem.synthetic] table")
    _check_keys(path, dem, _DEM_KEYS, "dem.")
    if ("path" in dem) == ("synthetic" in dem):
        _fail(path, "[dem] needs exactly one of path = '...' or a [dem.synthetic] table")
    job = Job(path=path, name=name, catalog=Path("catalogs") / name)
    if "chunks" in dem:
        job.chunks = _typed(path, dem, "chunks", int, "dem.", "a positive integer")
        if job.chunks < 1:
            _fail(path, f"dem.chunks must be a positive integer, got {job.chunks}")
    if "path" in dem:
        p = Path(_typed(path, dem, "path", str, "dem.", "a file path"))
        p = p if p.is_absolute() else (path.parent / p)
        if not p.exists():
            _fail(path, f"dem.path {dem['path']!r} does not exist (resolved to {p})")
        job.dem_path = p
        if "variable" in dem:
            job.variable = _typed(path, dem, "variable", str, "dem.", "a string")
        for key in ("cell_size", "resolution"):
            if key in dem:
                setattr(job, key, float(_number(path, dem, key, "dem.", above=0, unit="metres")))
    else:
        syn = dem["synthetic"]
        if not isinstance(syn, dict):
            _fail(path, "dem.synthetic must be a table")
        _check_keys(path, syn, _SYNTH_KEYS, "dem.synthetic.")
        if "shape" not in syn:
            _fail(path, "dem.synthetic.shape is required, e.g. shape = [2000, 2000]")
        shape = syn["shape"]
        if (not isinstance(shape, list) or len(shape) != 2
                or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 2
                           for v in shape)):
            _fail(path, f"dem.synthetic.shape must be [rows, cols] of integers >= 2, got {shape!r}")
        job.synthetic = {"shape": shape, "cell_size": 30.0, "seed": 0, "islands": 2}
        for key, types, what in (("cell_size", int | float, "a number > 0"),
                                 ("seed", int, "an integer >= 0"),
                                 ("islands", int, "an integer from 0 to 10")):
            if key in syn:
                job.synthetic[key] = _typed(path, syn, key, types, "dem.synthetic.", what)
    _load_maps(path, doc, job)
    _load_planning(path, doc, job)
    _load_missions(path, doc, job)
    out = doc.get("output", {})
    if not isinstance(out, dict):
        _fail(path, "[output] must be a table")
    _check_keys(path, out, _OUTPUT_KEYS, "output.")
    if "catalog" in out:
        job.catalog = Path(_typed(path, out, "catalog", str, "output.", "a directory path"))
    return job


def _number(path, table, key, where, *, minimum=None, above=None, integer=False, unit=""):
    """``table[key]`` if it is a finite number (an integer) >= ``minimum`` / > ``above``."""
    v = table[key]
    ok = isinstance(v, int if integer else int | float) and not isinstance(v, bool)
    if (not ok or (minimum is not None and v < minimum) or (above is not None and v <= above)
            or (not integer and not math.isfinite(v))):
        what = ("an integer" if integer else "a number") + (f" of {unit}" if unit else "")
        bound = (f" >= {minimum}" if minimum is not None else "") + (
            f" > {above}" if above is not None else "")
        _fail(path, f"{where}{key} must be {what}{bound}, got {v!r}")
    return v


def _load_maps(path, doc, job):
    t = doc.get("maps", {})
    if not isinstance(t, dict):
        _fail(path, "[maps] must be a table")
    _check_keys(path, t, _MAPS_KEYS, "maps.")
    if "method" in t and t["method"] not in ("spherical", "horizontal", "vertical"):
        _fail(path, f"maps.method must be 'spherical', 'horizontal' or 'vertical', got "
                    f"{t['method']!r}")
    for k in ("clearance", "horizontal_clearance", "surface_clearance"):
        if k in t:
            _number(path, t, k, "maps.", minimum=0)
    if "sea_level" in t:
        _number(path, t, "sea_level", "maps.")
    if "min_accumulation" in t:
        _number(path, t, "min_accumulation", "maps.", minimum=1, integer=True)
    job.maps = {"method": "spherical", "clearance": 300.0, **t}


def _check_planning(path, t, where):
    from .planners.grid import PLANNERS

    if "planner" in t and t["planner"] not in PLANNERS:
        _fail(path, f"{where}planner must be one of {', '.join(map(repr, PLANNERS))}, got "
                    f"{t['planner']!r}")
    if "omega" in t:
        _number(path, t, "omega", where, minimum=1)
    if "mcpc" in t and not isinstance(t["mcpc"], bool):
        _fail(path, f"{where}mcpc must be true or false, got {t['mcpc']!r}")
    for k, lo in (("rho", 1), ("section_size", 2), ("margin", 0)):
        if k in t:
            _number(path, t, k, where, minimum=lo, integer=True)


def _load_planning(path, doc, job):
    t = doc.get("planning", {})
    if not isinstance(t, dict):
        _fail(path, "[planning] must be a table")
    _check_keys(path, t, _PLANNING_KEYS, "planning.")
    _check_planning(path, t, "planning.")
    job.planning = dict(t)


def _load_missions(path, doc, job):
    ms = doc.get("missions", [])
    if not isinstance(ms, list) or not all(isinstance(m, dict) for m in ms):
        _fail(path, "missions must be an array of tables ([[missions]])")
    seen = set()
    for i, m in enumerate(ms):
        where = f"missions[{i}]."
        _check_keys(path, m, _MISSION_KEYS, where)
        name = m.get("name", f"mission-{i + 1:03d}")
        if not isinstance(name, str) or not name or "/" in name or name.startswith("."):
            _fail(path, f"{where}name must be a non-empty file-name-safe string, got {name!r}")
        if name in seen:
            _fail(path, f"{where}name {name!r} is used twice; mission names must be unique")
        seen.add(name)
        mission = {"name": name}
        for end in ("start", "goal"):
            forms = [k for k in (end, f"{end}_xy", f"{end}_lonlat") if k in m]
            if len(forms) != 1:
                _fail(path, f"{where} needs exactly one of {end} = [row, col], {end}_xy = [x, y] "
                            f"or {end}_lonlat = [lon, lat]; got {forms or 'none'}")
            key = forms[0]
            v = m[key]
            integer = key == end
            if (not isinstance(v, list) or len(v) != 2 or not all(
                    isinstance(x, int if integer else int | float) and not isinstance(x, bool)
                    for x in v)):
                what = "[row, col] of integers" if integer else "a pair of numbers"
                _fail(path, f"{where}{key} must be {what}, got {v!r}")
            mission[f"{end}_form"] = key[len(end):].lstrip("_") or "cell"
            mission[f"{end}_input"] = list(v)
        plan = {k: m[k] for k in _PLANNING_KEYS if k in m}
        _check_planning(path, plan, where)
        mission.update(plan)
        job.missions.append(mission)


@dataclass
class JobResult:
    """What a job run did."""

    job: Job
    dem_store: Path
    reused: bool
    seconds: float
    maps_store: Path | None = None
    catalog: Path | None = None
    planned: int = 0
    skipped: int = 0
    failed: list = field(default_factory=list)  # names of failed missions (this run or before)
    dashboard: str | None = None

    @property
    def ok(self) -> bool:
        return not self.failed


def _cell_of(end: str, mission: dict, maps, crs_wkt: str | None):
    """The cell of a mission's start or goal given as a cell, map coordinates or lon/lat."""
    from .exceptions import InvalidParameterError

    form, v = mission[f"{end}_form"], mission[f"{end}_input"]
    if form == "cell":
        return int(v[0]), int(v[1])
    x, y = float(v[0]), float(v[1])
    if form == "lonlat":
        if not crs_wkt:
            raise InvalidParameterError(f"{end}_lonlat {v} given, but the DEM has no coordinate "
                                        f"reference system; give {end} as a cell or in map "
                                        f"coordinates ({end}_xy)")
        from pyproj import CRS, Transformer

        tr = Transformer.from_crs("EPSG:4326", CRS.from_wkt(crs_wkt), always_xy=True)
        x, y = tr.transform(x, y)
    xs, ys, a = maps.x, maps.y, maps.a
    col = int(round((x - xs[0]) / (xs[1] - xs[0])))
    row = int(round((y - ys[0]) / (ys[1] - ys[0])))
    if not (0 <= row < len(ys) and 0 <= col < len(xs)):
        from .planners.grid import InvalidEndpointError

        raise InvalidEndpointError(
            f"{end} {v} ({form}) is off the map: x spans {min(xs[0], xs[-1]) - a / 2:.1f} to "
            f"{max(xs[0], xs[-1]) + a / 2:.1f}, y {min(ys[0], ys[-1]) - a / 2:.1f} to "
            f"{max(ys[0], ys[-1]) + a / 2:.1f}")
    return row, col


def run_job(path: str | os.PathLike, scheduler: str | None = None, overwrite: bool = False,
            dry_run: bool = False) -> JobResult:
    """Run a job file: DEM store, maps store, every mission, the results catalog.

    The stores are ``<catalog>/dem-<hash>.zarr`` and ``<catalog>/maps-<hash>.zarr``, reused
    while the DEM definition and the maps parameters are unchanged. Finished missions (their
    Item exists) are skipped unless ``overwrite``; each mission is written atomically as it
    finishes, so a killed job loses at most the missions in flight. With no ``scheduler``, a
    LocalCluster of 2 single-threaded workers. A performance report (HTML) is saved as
    ``<catalog>/performance-report.html``.

    Examples
    --------
    >>> res = pipeline.run_job("tasks/demo.toml")             # doctest: +SKIP
    >>> res.ok, res.catalog                                  # doctest: +SKIP
    (True, PosixPath('catalogs/demo/catalog.json'))
    """
    job = load_job(path)
    dem_store = job.catalog / f"dem-{job.dem_fingerprint()}.zarr"
    maps_store = job.catalog / f"maps-{job.maps_fingerprint()}.zarr"
    t0 = time.perf_counter()
    if dry_run:
        log.info("dry run: job %s is valid: %d missions; DEM store %s, maps store %s, catalog "
                 "%s", job.name, len(job.missions), dem_store, maps_store, job.catalog)
        return JobResult(job, dem_store, dem_store.exists(), 0.0, maps_store=maps_store)
    job.catalog.mkdir(parents=True, exist_ok=True)
    from distributed import performance_report

    with _scheduler(scheduler) as client:
        res = JobResult(job, dem_store, False, 0.0, maps_store=maps_store,
                        dashboard=client.dashboard_link)
        log.info("dask dashboard: %s", client.dashboard_link)
        report = job.catalog / "performance-report.html"
        tmp_report = job.catalog / f".performance-report.tmp-{os.getpid()}.html"
        with performance_report(filename=str(tmp_report)):
            res.reused = _dem_store(job, dem_store, overwrite)
            _maps_store(job, dem_store, maps_store, overwrite or not res.reused)
            crs = _missions(job, maps_store, client, overwrite, res)
        os.replace(tmp_report, report)
    from .catalog import write_catalog

    res.catalog = write_catalog(job.catalog, job.name, [m["name"] for m in job.missions],
                                description=f"Missions of job {job.name} ({job.path})",
                                lonlat=bool(crs))
    res.seconds = time.perf_counter() - t0
    log.info("job %s: %d planned, %d skipped (finished before), %d failed; catalog %s "
             "(%.1f s)", job.name, res.planned, res.skipped, len(res.failed), res.catalog,
             res.seconds)
    return res


def _dem_store(job: Job, store: Path, overwrite: bool) -> bool:
    from .dem import open_dem, write_dem
    from .synthetic import synthetic_dem

    if store.exists() and not overwrite:
        log.info("DEM store %s is up to date: reusing it", store)
        return True
    try:
        if job.dem_path is not None:
            dem = open_dem(job.dem_path, chunks=job.chunks, variable=job.variable,
                           cell_size=job.cell_size, resolution=job.resolution)
        else:
            dem = synthetic_dem(chunks=job.chunks, **job.synthetic)
    except PipelineError as exc:
        raise JobFileError(f"job file {job.path}: {exc}") from exc
    log.info("writing the DEM store %s", store)
    write_dem(dem, store, chunks=job.chunks, overwrite=True)
    return False


def _maps_store(job: Job, dem_store: Path, store: Path, rebuild: bool) -> None:
    from .dem import open_dem
    from .maps import build_maps

    if store.exists() and not rebuild:
        log.info("maps store %s is up to date: reusing it", store)
        return
    log.info("building the maps store %s (%s)", store, job.maps)
    try:
        build_maps(open_dem(dem_store, chunks=job.chunks), store, overwrite=True,
                   chunks=job.chunks, **job.maps)
    except PipelineError as exc:
        if isinstance(exc, JobFileError):
            raise
        raise JobFileError(f"job file {job.path}: [maps]: {exc}") from exc


def _missions(job: Job, maps_store: Path, client, overwrite: bool, res: JobResult):
    """Plan the missions not finished yet, writing each as it ends; returns the DEM's CRS."""
    import uuid

    from .catalog import finished, write_mission
    from .mcpc import _maps
    from .missions import failed_trajectory, min_clearance, plan_missions

    maps = _maps(maps_store)
    crs = maps.ds["elevation"].attrs.get("crs_wkt")
    run_id = uuid.uuid4().hex[:12]
    import shutil

    for stale in (job.catalog / "missions").glob(".*.tmp-*"):  # a killed run's half-written
        shutil.rmtree(stale, ignore_errors=True)
    todo = []
    for m in job.missions:
        done = None if overwrite else finished(job.catalog, m["name"])
        if done is None:
            todo.append(m)
        else:
            res.skipped += 1
            if done["properties"].get("auv:status") != "ok":
                res.failed.append(m["name"])
    if res.skipped:
        log.info("%d missions finished before: skipped (--overwrite plans them again)",
                 res.skipped)
    clearance = float(job.maps.get("clearance", 300.0))
    ready, bad = [], []
    for m in todo:
        try:
            ready.append({**m, "start": _cell_of("start", m, maps, crs),
                          "goal": _cell_of("goal", m, maps, crs)})
        except PipelineError as exc:
            bad.append((m, str(exc)))
    count = [0]
    total = len(todo)

    def record(mission, traj):
        count[0] += 1
        clr = min_clearance(maps, traj, clearance) if traj.status == "ok" else float("nan")
        write_mission(job.catalog, mission["name"], mission, traj, maps=maps, crs_wkt=crs,
                      min_clearance_m=clr, run_id=run_id)
        res.planned += 1
        if traj.status == "ok":
            log.info("[%d/%d] %s: ok, %.1f km, %.0f %% ridge, min clearance %.0f m (%.2f s)",
                     count[0], total, mission["name"], traj.length_m / 1e3,
                     100 * traj.ridge_ratio, clr, traj.runtime_s)
        else:
            res.failed.append(mission["name"])
            log.warning("[%d/%d] %s: FAILED: %s", count[0], total, mission["name"],
                        traj.message)

    for m, msg in bad:
        record(m, failed_trajectory({**job.planning, **m}, msg))
    if ready:
        plan_missions(maps, ready, client=client, defaults=job.planning,
                      on_done=lambda i, mission, traj: record(mission, traj))
    return crs


class _scheduler:
    """The dask cluster at ``address`` if given, else a LocalCluster of 2 single-threaded
    workers (dashboard on port 8787, or a free one); its client is the default meanwhile."""

    def __init__(self, address: str | None):
        self.address = address
        self.client = None
        self.cluster = None

    def __enter__(self):
        from distributed import Client, LocalCluster

        if self.address:
            try:
                self.client = Client(self.address, timeout=30)
            except OSError as exc:
                raise PipelineError(f"cannot reach the dask scheduler at {self.address}: "
                                    f"{exc}; start it (`dask scheduler`) or run without "
                                    "--scheduler for a local cluster") from None
        else:
            import socket

            with socket.socket() as sk:
                busy = sk.connect_ex(("127.0.0.1", 8787)) == 0
            self.cluster = LocalCluster(n_workers=2, threads_per_worker=1,
                                        dashboard_address=":0" if busy else ":8787")
            self.client = Client(self.cluster)
        return self.client

    def __exit__(self, *exc):
        if self.client is not None:
            self.client.close()
        if self.cluster is not None:
            self.cluster.close()
