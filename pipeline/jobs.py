"""Job files (TOML) -> DEM store -> maps store -> missions -> results catalog.

A job file is validated completely before any compute: an unknown key, a wrong type or a
missing file is one :class:`~pipeline.exceptions.JobFileError` naming the key and the file.
A job file::

    name = "demo"
    [dem]                       # path = "survey.tif" (+ variable, cell_size, resolution, and
                                # bbox = [lon_min, lat_min, lon_max, lat_max] or bbox_xy = [...]
                                # in the file's coordinates: read only that region;
                                # uncertainty_k = 2: plan on elevation + 2 sigma), or:
    chunks = 512
    [dem.synthetic]
    shape = [2000, 2000]        # cell_size, seed, islands
    [maps]                      # method, clearance, horizontal_clearance, sea_level,
    clearance = 300.0           # surface_clearance, min_accumulation
    [planning]                  # defaults of every mission: planner, omega, mcpc, rho,
    planner = "ra_star"         # section_size, margin, coarse_planner, coarse_weight,
                                # repair_max_cells
    omega = 2.0
    [vehicle]                   # speed_m_s, max_pitch_deg, min_turn_radius_m, waypoint_band_m,
    speed_m_s = 1.5             # hotel_power_w, propulsion_power_w, battery_wh
    [[missions]]
    name = "north-ridge"
    start = [100, 120]          # a cell (row, col); or start_xy = [x, y] in map
    goal = [1800, 1700]         # coordinates, or start_lonlat = [lon, lat]
    omega = 1.5                 # any [planning] key, for this mission
    vehicle = { max_pitch_deg = 15 }   # any [vehicle] key, for this mission
    [output]
    catalog = "catalogs/demo"
    quicklooks = true           # a plan view and depth profile PNG per mission (~0.4 s each)
    performance_report = true   # dask's performance report of each run (~1 s, a few MB)
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import shutil
import socket
import time
import tomllib
import uuid
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path

from ._types import ClientLike
from .exceptions import (
    CatalogBusyError,
    InvalidDEMError,
    InvalidParameterError,
    JobFileError,
    PipelineError,
)
from .params import (
    DEFAULT_CHUNK,
    DEM,
    GENERATOR_VERSION,
    LATITUDE,
    LONGITUDE,
    MAPS,
    PERFORMANCE_REPORT,
    PLANNING,
    QUICKLOOKS,
    SYNTHETIC,
    VEHICLE,
    Param,
    Schema,
    check_clearance,
    check_region,
    endpoint_forms,
    endpoint_key,
    shape2d,
)
from .store.paths import TEMPORARY, has_scheme

log = logging.getLogger(__name__)

_TOP_KEYS = {"name", "dem", "maps", "planning", "vehicle", "missions", "output"}
_ENDPOINT_KEYS = {f"{w}{form}" for w in ("start", "goal") for form in ("", "_xy", "_lonlat")}
_MISSION_KEYS = {"name", "vehicle"} | PLANNING.names() | _ENDPOINT_KEYS
_DEM_KEYS = {"path", "synthetic"} | DEM.names()
_SYNTH_KEYS = {"shape"} | SYNTHETIC.names()
_OUTPUT_KEYS = {"catalog", "quicklooks", "performance_report"}

# Raised whenever a change of the code makes a mission's result differ for the same inputs (the
# planners' paths, the flight), so that a job plans its finished missions again instead of
# keeping results the code would no longer give: 2 is RA*'s ties of Nor by g_incons + h, 3 the
# default window margin of MCPC's sections halved (section_size // 8), 4 the flight's heights
# against the continuous seabed and its profile's breaks a turn radius apart.
RESULTS_REVISION = 4

_COORD = Param("coordinate", "float", None, "")


@dataclass
class Job:
    """A validated job file."""

    path: Path
    name: str
    catalog: Path
    chunks: int = DEFAULT_CHUNK
    dem_path: Path | None = None
    variable: str | None = None
    cell_size: float | None = None
    resolution: float | None = None
    bbox: tuple | None = None  # [dem] bbox (lon/lat) or bbox_xy: the region read
    bbox_xy: tuple | None = None
    uncertainty_k: float | None = None  # [dem] uncertainty_k: plan on elevation + k sigma
    uncertainty: str | None = None
    synthetic: dict = field(default_factory=dict)
    maps: dict = field(default_factory=lambda: _maps_defaults({}))
    planning: dict = field(default_factory=dict)
    vehicle: dict = field(default_factory=dict)  # the [vehicle] keys given
    quicklooks: bool = QUICKLOOKS.default  # [output] quicklooks: a PNG per mission
    # [output] performance_report: dask's performance report of each run that computed
    performance_report: bool = PERFORMANCE_REPORT.default
    missions: list = field(default_factory=list)

    def maps_fingerprint(self) -> str:
        """A hash of the DEM definition and the maps parameters (reuse the maps store)."""
        what = {"dem": self.dem_fingerprint(), "maps": self.maps}
        return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:16]

    def mission_fingerprint(self, mission: dict) -> str:
        """A hash of what defines a mission's result: its endpoints, its planning options (the
        library's defaults, under the job's, under the mission's), the vehicle, the maps (hence
        the DEM) and :data:`RESULTS_REVISION`. A re-run plans a finished mission again when this
        changed: a new default or a planner that now returns other paths included."""
        plan = {
            **PLANNING.defaults(),
            **self.planning,
            **{k: mission[k] for k in PLANNING.names() if k in mission},
        }
        what = {
            "ends": {k: mission[k] for k in sorted(mission) if k.startswith(("start", "goal"))},
            "planning": plan,
            "vehicle": self.vehicle_of(mission),
            "maps": self.maps_fingerprint(),
            "revision": RESULTS_REVISION,
        }
        return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:16]

    def vehicle_of(self, mission: dict) -> dict:
        """The vehicle of a mission: the job's [vehicle] with the mission's own keys over it."""
        return {**self.vehicle, **mission.get("vehicle", {})}

    def dem_fingerprint(self) -> str:
        """A hash of what defines the DEM: re-running with the same inputs reuses the store."""
        if self.dem_path is not None:
            st = self.dem_path.stat()
            what = {
                "path": str(self.dem_path.resolve()),
                "size": st.st_size,
                "mtime_ns": st.st_mtime_ns,
                "variable": self.variable,
                "cell_size": self.cell_size,
            }
            if self.resolution is not None:
                what["resolution"] = self.resolution
            for key in ("bbox", "bbox_xy"):
                if getattr(self, key) is not None:
                    what[key] = list(getattr(self, key))
            for key in ("uncertainty_k", "uncertainty"):
                if getattr(self, key) is not None:
                    what[key] = getattr(self, key)
        else:
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


def _checked(path: Path, schema: Schema, table: dict, where: str) -> dict:
    """``table``'s values checked by the library's own schema: the same bounds and messages
    as the library, the key named as the job file names it."""
    try:
        return schema.check(table, where)
    except InvalidParameterError as exc:
        _fail(path, str(exc))


def _maps_defaults(table: dict) -> dict:
    # method, clearance and landmarks always, the rest as given: the maps store's fingerprint
    return {
        "method": MAPS.method.default,
        "clearance": MAPS.clearance.default,
        "landmarks": MAPS.landmarks.default,
        **table,
    }


def load_job(path: str | os.PathLike) -> Job:
    """Read and validate a job file without computing anything."""
    path = Path(path)
    if not path.is_file():
        what = (
            "is a directory, not a file"
            if path.is_dir()
            else "is not a regular file (a device, a pipe or a socket); give a TOML file"
            if path.exists()
            else "does not exist"
        )
        raise JobFileError(f"job file {path} {what}")
    try:
        raw = path.read_bytes()
        # a byte-order mark, as some editors on Windows write, is not TOML but means UTF-8
        doc = tomllib.loads(raw.removeprefix(b"\xef\xbb\xbf").decode("utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise JobFileError(f"job file {path} is not valid TOML: {exc}") from exc
    except UnicodeDecodeError as exc:
        raise JobFileError(
            f"job file {path} is not UTF-8 text (byte {exc.start}); save it as UTF-8"
        ) from exc
    except OSError as exc:
        raise JobFileError(f"job file {path} cannot be read: {exc.strerror}") from exc
    _check_keys(path, doc, _TOP_KEYS, "")
    name = doc.get("name", path.stem)
    if (
        not isinstance(name, str)
        or not name
        or "/" in name
        or name.startswith(".")
        or any(ord(c) < 32 or ord(c) == 127 for c in name)
    ):
        _fail(
            path,
            f"name must be a non-empty file-name-safe string (no '/', no leading '.', no "
            f"control characters), got {name!r}",
        )
    dem = doc.get("dem")
    if not isinstance(dem, dict):
        _fail(path, "a [dem] table is required, with path = '...' or a [dem.synthetic] table")
    _check_keys(path, dem, _DEM_KEYS, "dem.")
    if ("path" in dem) == ("synthetic" in dem):
        _fail(path, "[dem] needs exactly one of path = '...' or a [dem.synthetic] table")
    job = Job(path=path, name=name, catalog=path.parent / "catalogs" / name)
    given = _checked(path, DEM, {k: v for k, v in dem.items() if k in DEM}, "dem.")
    job.chunks = given.get("chunks", DEFAULT_CHUNK)
    if "path" in dem:
        given_path = _typed(path, dem, "path", str, "dem.", "a file path")
        if has_scheme(given_path):
            _fail(
                path,
                f"dem.path {given_path!r} is a URL: DEMs are read from local files (GeoTIFF, "
                "NetCDF, Zarr, BAG, ASCII grid); download it first",
            )
        p = Path(given_path)
        p = p if p.is_absolute() else (path.parent / p)
        if not p.exists():
            _fail(path, f"dem.path {dem['path']!r} does not exist (resolved to {p})")
        if not p.is_file() and not p.is_dir():  # a FIFO would block the read for ever
            _fail(
                path,
                f"dem.path {dem['path']!r} is not a regular file (a device, a pipe or a socket)",
            )
        job.dem_path = p
        job.variable = given.get("variable")
        job.cell_size = given.get("cell_size")
        job.resolution = given.get("resolution")
        job.bbox, job.bbox_xy = given.get("bbox"), given.get("bbox_xy")
        job.uncertainty_k, job.uncertainty = given.get("uncertainty_k"), given.get("uncertainty")
        try:  # the library's own check, so that --dry-run refuses what a run would
            check_region(job.bbox, job.bbox_xy, "dem.")
        except InvalidParameterError as exc:
            _fail(path, str(exc))
        cell = job.resolution  # the cell side the maps are built on, when the job says it
    else:
        for key in ("bbox", "bbox_xy"):
            if key in dem:
                _fail(
                    path,
                    f"dem.{key} selects a region of a DEM file (dem.path), not of a "
                    "synthetic DEM: set dem.synthetic.shape instead",
                )
        for key in ("uncertainty_k", "uncertainty"):
            if key in dem:
                _fail(
                    path,
                    f"dem.{key} reads a survey's uncertainty band from a DEM file (dem.path); "
                    "a synthetic DEM has none",
                )
        syn = dem["synthetic"]
        if not isinstance(syn, dict):
            _fail(path, "dem.synthetic must be a table")
        _check_keys(path, syn, _SYNTH_KEYS, "dem.synthetic.")
        if "shape" not in syn:
            _fail(path, "dem.synthetic.shape is required, e.g. shape = [2000, 2000]")
        try:
            shape = list(shape2d("shape", syn["shape"], label="dem.synthetic.shape"))
        except InvalidParameterError as exc:
            _fail(path, str(exc))
        job.synthetic = {
            "shape": shape,
            **SYNTHETIC.defaults(),
            **_checked(
                path, SYNTHETIC, {k: v for k, v in syn.items() if k != "shape"}, "dem.synthetic."
            ),
        }
        cell = job.synthetic["cell_size"]
    _load_maps(path, doc, job, cell)
    _load_planning(path, doc, job)
    job.vehicle = _load_vehicle(path, doc.get("vehicle", {}), "vehicle.")
    _load_missions(path, doc, job)
    out = doc.get("output", {})
    if not isinstance(out, dict):
        _fail(path, "[output] must be a table")
    _check_keys(path, out, _OUTPUT_KEYS, "output.")
    if "catalog" in out:
        p = Path(_typed(path, out, "catalog", str, "output.", "a directory path"))
        job.catalog = p if p.is_absolute() else path.parent / p
    for key, param in (("quicklooks", QUICKLOOKS), ("performance_report", PERFORMANCE_REPORT)):
        if key in out:
            try:
                setattr(job, key, param.check(out[key], f"output.{key}"))
            except InvalidParameterError as exc:
                _fail(path, str(exc))
    # relative paths are the job file's (a cron job run from elsewhere finds its results), made
    # absolute so that workers in other directories or on other machines write where the
    # client reads
    job.catalog = Path(os.path.abspath(job.catalog))
    if job.dem_path is None and "shape" in (job.synthetic or {}):
        _check_size(path, job, job.synthetic["shape"])
    return job


# a grid cut into more chunks than this is refused: each is a task of every layer and pass,
# and the graphs of so many grow the client by gigabytes before anything is written
MAX_CHUNKS = 10_000
# bytes a cell of the DEM and maps stores take before compression: the DEM (4), the maps'
# elevation, safety and accumulation (4 each), passable and ridge (1 each), components (4),
# and each landmark's distances (4)
STORE_BYTES_PER_CELL = 4 + 4 + 4 + 4 + 1 + 1 + 4
# the stores compress by at most this much (the demo's stores: 1.7x)
BEST_COMPRESSION = 4.0


def _check_size(path: Path, job: Job, shape) -> None:
    """Refuse, at the dry run, a grid the run could not carry: more than :data:`MAX_CHUNKS`
    chunks, or stores that would not fit on the catalog's disk even compressed as well as
    stores ever are; each with the estimate."""
    rows, cols = (int(v) for v in shape)
    side = int(job.chunks) if isinstance(job.chunks, int) else int(min(job.chunks))
    count = -(-rows // side) * -(-cols // side)
    if count > MAX_CHUNKS:
        need = 64 * math.ceil(math.sqrt(rows * cols / MAX_CHUNKS) / 64)
        _fail(
            path,
            f"[dem] chunks = {job.chunks} cuts the {rows} x {cols} grid into {count:,} chunks "
            f"(a task each, per layer and pass; at most {MAX_CHUNKS:,}); use chunks = {need} "
            "or more",
        )
    per_cell = STORE_BYTES_PER_CELL + 4 * int(job.maps.get("landmarks") or 0)
    need = rows * cols * per_cell
    where = job.catalog
    while not where.exists() and where != where.parent:
        where = where.parent
    try:
        usage = shutil.disk_usage(where)
    except OSError:
        return
    free = usage.free
    if usage.total > 0 and need / BEST_COMPRESSION > free:  # (no size: not a disk, /proc)
        _fail(
            path,
            f"the DEM and maps stores of a {rows} x {cols} grid need about {need / 1e9:,.0f} GB "
            f"(at least {need / BEST_COMPRESSION / 1e9:,.0f} GB compressed); {free / 1e9:,.1f} "
            f"GB are free at {where}: a smaller grid, or a catalog on a larger disk",
        )


def _load_maps(path, doc, job, cell_size: float | None):
    t = doc.get("maps", {})
    if not isinstance(t, dict):
        _fail(path, "[maps] must be a table")
    _check_keys(path, t, MAPS.names(), "maps.")
    t = _checked(path, MAPS, t, "maps.")
    try:  # what the safety map would refuse once the cell side is known
        for key in ("clearance", "horizontal_clearance"):
            if t.get(key) is not None:
                check_clearance(t[key], cell_size, f"maps.{key}", MAPS[key])
    except InvalidParameterError as exc:
        _fail(path, str(exc))
    job.maps = _maps_defaults(t)


def _load_planning(path, doc, job):
    t = doc.get("planning", {})
    if not isinstance(t, dict):
        _fail(path, "[planning] must be a table")
    _check_keys(path, t, PLANNING.names(), "planning.")
    job.planning = _checked(path, PLANNING, t, "planning.")


def _load_vehicle(path, t, where: str, base: dict | None = None) -> dict:
    from .flight import Vehicle

    if not isinstance(t, dict):
        _fail(
            path,
            f"{where.rstrip('.')} must be a table, e.g. {where.rstrip('.')} = "
            "{ speed_m_s = 1.5 }",
        )
    _check_keys(path, t, VEHICLE.names(), where)
    t = _checked(path, VEHICLE, t, where)
    try:
        Vehicle(**{**(base or {}), **t})
    except InvalidParameterError as exc:
        _fail(path, f"[{where.rstrip('.')}]: {exc}")
    return t


def _load_missions(path, doc, job):
    from .outputs.catalog import mission_id

    ms = doc.get("missions", [])
    if not isinstance(ms, list) or not all(isinstance(m, dict) for m in ms):
        _fail(path, "missions must be an array of tables ([[missions]])")
    seen, folders = set(), {}
    for i, m in enumerate(ms):
        where = f"missions[{i}]."
        _check_keys(path, m, _MISSION_KEYS, where)
        name = m.get("name", f"mission-{i + 1:03d}")
        if not isinstance(name, str) or not name.strip():
            _fail(path, f"{where}name must be a non-empty string, got {name!r}")
        if name in seen:
            _fail(path, f"{where}name {name!r} is used twice; mission names must be unique")
        seen.add(name)
        # the folder and Item id (a file system may not tell case apart)
        key = mission_id(name).casefold()
        if key in folders:
            _fail(
                path,
                f"{where}name {name!r} and mission {folders[key]!r} would share the folder and "
                f"Item id {mission_id(name)!r}; rename one",
            )
        folders[key] = name
        mission = {"name": name}
        for end in ("start", "goal"):
            forms = [endpoint_key(end, f) for f in endpoint_forms(m, end)]
            if len(forms) != 1:
                _fail(
                    path,
                    f"{where} needs exactly one of {end} = [row, col], {end}_xy = [x, y] "
                    f"or {end}_lonlat = [lon, lat]; got {forms or 'none'}",
                )
            key = forms[0]
            v = m[key]
            integer = key == end
            if (
                not isinstance(v, list)
                or len(v) != 2
                or not all(
                    isinstance(x, int if integer else int | float) and not isinstance(x, bool)
                    for x in v
                )
            ):
                what = "[row, col] of integers" if integer else "a pair of numbers"
                _fail(path, f"{where}{key} must be {what}, got {v!r}")
            form = endpoint_forms(m, end)[0]
            if form != "cell":
                try:
                    for x, param in zip(
                        v, (LONGITUDE, LATITUDE) if form == "lonlat" else (_COORD,) * 2, strict=True
                    ):
                        param.check(x, f"{where}{key}")
                except InvalidParameterError as exc:
                    _fail(path, str(exc))
            mission[f"{end}_form"] = form
            mission[f"{end}_input"] = list(v)
        plan = {k: m[k] for k in PLANNING.names() if k in m}
        mission.update(_checked(path, PLANNING, plan, where))
        if "vehicle" in m:
            mission["vehicle"] = _load_vehicle(path, m["vehicle"], f"{where}vehicle.", job.vehicle)
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
    workers: int = 0  # the cluster's workers (0: no cluster was needed)
    uncertified: list = field(default_factory=list)  # planned, bound not proven (this run)
    dashboard: str | None = None
    ran: int = 0  # missions this run planned or tried
    replanned: int = 0  # finished missions planned again because they changed
    crs_wkt: str | None = None
    report: Path | None = None  # the catalog's index.html
    run_id: str = field(default_factory=lambda: uuid.uuid4().hex[:12])

    @property
    def ok(self) -> bool:
        return not self.failed


def _report(job: Job, maps_store: Path) -> Path:
    """The catalog's offline report, ``index.html`` (:mod:`pipeline.outputs.report`)."""
    from .outputs.report import write_report
    from .store.maps_store import open_store

    maps = open_store(maps_store) if (maps_store / "zarr.json").exists() else None
    path = write_report(
        job.catalog, maps, title=job.name, mission_names=[m["name"] for m in job.missions]
    )
    log.info("job %s: report %s (open it in a browser; it needs no network)", job.name, path)
    return path


def run_job(
    path: str | os.PathLike,
    scheduler: ClientLike = None,
    overwrite: bool = False,
    dry_run: bool = False,
    scheduler_file: str | os.PathLike | None = None,
    dashboard_address: str | None = None,
    prune: bool = False,
    workers: int | None = None,
) -> JobResult:
    """Run a job file: DEM store, maps store, every mission, the results catalog.

    The stores are ``<catalog>/dem-<hash>.zarr`` and ``<catalog>/maps-<hash>.zarr``, reused
    while the DEM definition and the maps parameters are unchanged. Finished missions (their
    Item exists) are skipped unless ``overwrite``; each mission is written atomically as it
    finishes, so a killed job loses at most the missions in flight. With no ``scheduler``, a
    LocalCluster of 2 single-threaded workers. A performance report (HTML) is saved as
    ``<catalog>/performance-report.html`` unless ``[output] performance_report = false``.
    ``scheduler`` (an address or a
    ``distributed.Client``) or ``scheduler_file`` name the cluster to run on
    (:func:`pipeline.runtime.cluster.session`). What the catalog holds that the job no longer makes
    (stores of other DEM or maps parameters, folders of missions no longer in the job) is
    counted in the log, and removed with ``prune`` (:func:`stale`). ``workers``: the local
    cluster's worker processes (default 2, or dask's configuration ``auv_pipeline.workers``).

    Examples
    --------
    >>> res = pipeline.run_job("tasks/demo.toml")             # doctest: +SKIP
    >>> res.ok, res.catalog                                  # doctest: +SKIP
    (True, PosixPath('catalogs/demo/catalog.json'))
    """
    job = load_job(path)
    if dashboard_address is not None:  # at the dry run too, not when a cluster starts
        from .runtime.cluster import check_dashboard_address

        check_dashboard_address(dashboard_address)
    if workers is not None:
        from .runtime.cluster import local_workers

        local_workers(workers)
    dem_store = job.catalog / f"dem-{job.dem_fingerprint()}.zarr"
    maps_store = job.catalog / f"maps-{job.maps_fingerprint()}.zarr"
    t0 = time.perf_counter()
    check_catalog(job.catalog, job.name)
    if dry_run:
        log.info(
            "dry run: job %s is valid: %d missions; DEM store %s, maps store %s, catalog %s",
            job.name,
            len(job.missions),
            dem_store,
            maps_store,
            job.catalog,
        )
        return JobResult(job, dem_store, dem_store.exists(), 0.0, maps_store=maps_store)
    from .outputs.catalog import write_catalog

    with catalog_lock(job.catalog):
        check_catalog(job.catalog, job.name)  # (as another run may have left it)
        remove_temporaries(job.catalog)
        res = _run_locked(
            job,
            dem_store,
            maps_store,
            overwrite,
            scheduler,
            scheduler_file,
            dashboard_address,
            workers,
        )
        res.catalog = write_catalog(
            job.catalog,
            job.name,
            [m["name"] for m in job.missions],
            description=f"Missions of job {job.name} ({job.path})",
            lonlat=bool(res.crs_wkt),
        )
        res.report = _report(job, maps_store)
        _prune(job, dem_store, maps_store, prune)
    res.seconds = time.perf_counter() - t0
    log.info(
        "job %s: %d planned, %d skipped (finished before), %d failed; catalog %s (%.1f s)",
        job.name,
        res.planned,
        res.skipped,
        len(res.failed),
        res.catalog,
        res.seconds,
    )
    return res


def stale(job: Job, dem_store: Path, maps_store: Path) -> list[Path]:
    """What the catalog of ``job`` holds that this tool made and the job no longer uses: DEM
    and maps stores (this tool's, by their mark) other than ``dem_store`` and ``maps_store``,
    and mission folders (each with its Item) of missions no longer in the job."""
    from .outputs.catalog import COLLECTION, mission_id
    from .store.paths import own_store

    out = []
    for kind, pattern, keep in (
        ("DEM", "dem-*.zarr", dem_store),
        ("maps", "maps-*.zarr", maps_store),
    ):
        for p in sorted(job.catalog.glob(pattern)):
            if p != keep and own_store(p, kind):
                out.append(p)
    ids = {mission_id(m["name"]) for m in job.missions}
    folder = job.catalog / COLLECTION
    if folder.is_dir():
        for p in sorted(folder.iterdir()):
            if p.is_dir() and p.name not in ids and (p / f"{p.name}.json").is_file():
                out.append(p)
    return out


def _size(p: Path) -> int:
    return sum(f.stat().st_size for f in p.rglob("*") if f.is_file() and not f.is_symlink())


def _prune(job: Job, dem_store: Path, maps_store: Path, remove: bool) -> None:
    old = stale(job, dem_store, maps_store)
    if not old:
        return
    size = sum(_size(p) for p in old)
    if remove:
        for p in old:
            shutil.rmtree(p, ignore_errors=True)
        log.info(
            "pruned %d stores and mission folders the job no longer uses (%.2f GB)",
            len(old),
            size / 1e9,
        )
        return
    names = ", ".join(p.name for p in old[:3]) + (
        f" and {len(old) - 3} more" if len(old) > 3 else ""
    )
    log.info(
        "catalog %s holds %d stores and mission folders the job no longer uses (%s; %.2f GB): "
        "`pipeline run %s --prune` removes them",
        job.catalog,
        len(old),
        names,
        size / 1e9,
        job.path,
    )


def _run_locked(job, dem_store, maps_store, overwrite, *cluster) -> JobResult:
    import datetime as dt

    scheduler, scheduler_file, *_ = cluster
    missions = _sorted_missions(job, overwrite)
    if (
        scheduler is None
        and scheduler_file is None
        and not overwrite
        and dem_store.exists()
        and maps_store.exists()
        and all(done is not None for _, done, _ in missions)
    ):
        # no cluster of its own to start (its 2 worker processes took 2-3 s to start and stop)
        # when the run computes nothing; a scheduler given is still reached (its address checked)
        log.info("job %s: nothing to compute: no cluster started", job.name)
        reused = _dem_store(job, dem_store, overwrite)
        res = JobResult(job, dem_store, reused, 0.0, maps_store=maps_store)
        _maps_store(job, dem_store, maps_store, False)
        _missions(job, maps_store, None, missions, res)
        return res
    from distributed import performance_report

    from .runtime.cluster import session
    from .runtime.warmup import ensure_compiled

    with session(*cluster) as client:
        res = JobResult(
            job, dem_store, False, 0.0, maps_store=maps_store, dashboard=client.dashboard_link
        )
        res.workers = len(client.scheduler_info().get("workers", {}))
        log.info("dask dashboard: %s (%d workers)", client.dashboard_link, res.workers)
        # the first run after an install compiles the kernels on both workers at once, so that
        # no stage (and no mission's recorded runtime) holds the compilation
        ensure_compiled(client)
        tmp_report = job.catalog / f".performance-report.tmp-{res.run_id}.html"
        # dask's report takes about a second to draw at the end of a run (the scheduler's
        # task stream, profiles and bandwidths, with bokeh's scripts inlined)
        recording = (
            performance_report(filename=str(tmp_report), mode="inline")
            if job.performance_report
            else nullcontext()
        )
        with recording:
            res.reused = _dem_store(job, dem_store, overwrite)
            built = _maps_store(job, dem_store, maps_store, overwrite or not res.reused)
            _missions(job, maps_store, client, missions, res)
    if not job.performance_report:
        return res  # none asked for: an earlier run's report stays as it is
    if res.reused and not built and not res.ran:
        tmp_report.unlink(missing_ok=True)  # nothing was computed: keep the last report
        return res
    # one self-contained report per run that did work, the newest also as
    # performance-report.html
    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    reports = job.catalog / "reports"
    reports.mkdir(exist_ok=True)
    kept = reports / f"performance-{stamp}-{res.run_id}.html"
    os.replace(tmp_report, kept)
    latest = job.catalog / f".performance-report.html.tmp-{res.run_id}"
    shutil.copyfile(kept, latest)
    os.replace(latest, job.catalog / "performance-report.html")
    return res


@contextmanager
def catalog_lock(catalog: Path):
    """Hold ``<catalog>/.lock`` for a run: a second run on the same catalog refuses with one
    clear line instead of deleting the first one's work in flight. The lock is the operating
    system's (``flock``), so a killed run never leaves it held."""
    import fcntl

    catalog.mkdir(parents=True, exist_ok=True)
    fh = open(catalog / ".lock", "a+")
    try:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            who = fh.read().strip() or "another process"
            raise CatalogBusyError(
                f"catalog {catalog} is in use by another run ({who}); wait for it to finish, "
                "or give this job another [output] catalog"
            ) from None
        fh.seek(0)
        fh.truncate()
        fh.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
        fh.flush()
        yield
    finally:
        fh.close()


# what a run writes into its catalog folder (besides its temporaries, :data:`TEMPORARY`)
CATALOG_ENTRIES = (
    ".lock",
    "catalog.json",
    "dem-*.zarr",
    "maps-*.zarr",
    "missions",
    "report",
    "reports",
    "index.html",
    "performance-report.html",
)


def check_catalog(catalog: Path, job_name: str) -> None:
    """Refuse, with one line, a catalog folder this job may not write into: a folder holding
    another job's catalog (its ``catalog.json`` names that job: the two would drop each other's
    missions); a folder without a catalog that holds anything a run does not write (the job's
    own folder, a user's files). Absent, empty, or this job's catalog: fine."""
    import fnmatch

    if not catalog.exists() and not catalog.is_symlink():
        return
    if not catalog.is_dir():
        return  # a file: creating the lock says so
    index = catalog / "catalog.json"
    if index.exists():
        try:
            owner = json.loads(index.read_text()).get("id")
        except (OSError, ValueError, AttributeError):
            owner = None  # a damaged index of a run's: rewritten at the end of this one
        if owner is not None and owner != job_name:
            raise PipelineError(
                f"catalog {catalog} holds the missions of job {owner!r} (its catalog.json); "
                f"give job {job_name!r} its own [output] catalog, so that neither drops the "
                "other's missions"
            )
        if owner is not None:
            return
    foreign = sorted(
        p.name
        for p in catalog.iterdir()
        if not TEMPORARY.match(p.name)
        and not any(fnmatch.fnmatchcase(p.name, pat) for pat in CATALOG_ENTRIES)
    )
    if foreign:
        shown = ", ".join(foreign[:3]) + (
            f" and {len(foreign) - 3} more" if len(foreign) > 3 else ""
        )
        raise PipelineError(
            f"catalog {catalog} is a folder with other files ({shown}) and no catalog of this "
            "job; a run writes only into a new or empty folder, or its own catalog: give "
            "[output] catalog such a folder"
        )


def remove_temporaries(catalog: Path) -> list[Path]:
    """Remove what killed runs left in ``catalog`` (half-written stores, scratch stores,
    mission folders, reports, coarse maps); call it holding :func:`catalog_lock`, when no
    other run can be writing them. Returns what was removed."""
    patterns = (".*.tmp-*", "missions/.*.tmp-*", "report/.*.tmp-*", "*.zarr/.coarse-rho*.tmp-*")
    # only the names the tool gives its temporaries (a dot, the name, .tmp- and a random hex
    # tag): a user's file that looks alike is left alone
    gone = [p for pattern in patterns for p in catalog.glob(pattern) if TEMPORARY.match(p.name)]
    for p in gone:
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
    if gone:
        log.info("removed %d temporaries left by earlier runs that were killed", len(gone))
    return gone


def _sorted_missions(job: Job, overwrite: bool) -> list[tuple[dict, dict | None, bool]]:
    """Each mission of ``job`` (with its ``fingerprint``, :meth:`Job.mission_fingerprint`), its
    Item when it finished as it is defined now (None: to be planned; always with
    ``overwrite``), and whether it finished under another definition (its fields, the maps, the
    DEM, the library's defaults or results revision). Read once a run, before its cluster."""
    from .outputs.catalog import damaged_assets, finished

    out = []
    for m in job.missions:
        m = {**m, "fingerprint": job.mission_fingerprint(m)}
        done = None if overwrite else finished(job.catalog, m["name"])
        changed = done is not None and done["properties"].get("auv:fingerprint") != m["fingerprint"]
        if done is not None and not changed:
            # a failure is tried again (its cause, a full disk, a damaged store, may be gone;
            # one the mission itself causes fails again, as fast); so is a result whose files
            # went missing or changed
            if done["properties"].get("auv:status") == "failed":
                log.info("%s: failed before: planning it again", m["name"])
                done = None
            elif bad := damaged_assets(job.catalog, done):
                log.warning(
                    "%s: its files %s are missing or changed since it was written: planning it "
                    "again",
                    m["name"],
                    ", ".join(bad),
                )
                done = None
        out.append((m, None if changed else done, changed))
    return out


def _dem_store(job: Job, store: Path, overwrite: bool) -> bool:
    if store.exists() and not overwrite:
        log.info("DEM store %s is up to date: reusing it", store)
        return True
    # here, not above: a run on stores it reuses imports neither xarray nor dask.array
    from .dem import import_dem, write_dem
    from .dem.synthetic import synthetic_dem

    log.info("writing the DEM store %s", store)
    try:
        if job.dem_path is not None:  # read, checked and written in one pass over the file
            import_dem(
                job.dem_path,
                store,
                chunks=job.chunks,
                variable=job.variable,
                cell_size=job.cell_size,
                resolution=job.resolution,
                bbox=job.bbox,
                bbox_xy=job.bbox_xy,
                uncertainty_k=job.uncertainty_k,
                uncertainty=job.uncertainty,
                overwrite=True,
            )
            return False
        dem = synthetic_dem(chunks=job.chunks, **job.synthetic)
    except (InvalidDEMError, InvalidParameterError) as exc:
        raise JobFileError(f"job file {job.path}: {exc}") from exc
    write_dem(dem, store, chunks=job.chunks, overwrite=True)
    return False


def _maps_store(job: Job, dem_store: Path, store: Path, rebuild: bool) -> None:
    if store.exists() and not rebuild:
        log.info("maps store %s is up to date: reusing it", store)
        return False
    from .dem import open_dem
    from .maps.build import build_maps

    log.info("building the maps store %s (%s)", store, job.maps)
    try:
        build_maps(
            open_dem(dem_store, chunks=job.chunks),
            store,
            overwrite=True,
            chunks=job.chunks,
            **job.maps,
        )
    except PipelineError as exc:
        if isinstance(exc, JobFileError):
            raise
        raise JobFileError(f"job file {job.path}: [maps]: {exc}") from exc
    return True


def _missions(job: Job, maps_store: Path, client, missions: list, res: JobResult) -> None:
    """Plan the missions not finished yet (or changed since; ``missions`` as
    :func:`_sorted_missions` gives them), writing each as it ends."""
    from .missions import failed_trajectory, plan_missions
    from .store.maps_store import open_store

    maps = open_store(maps_store)
    res.crs_wkt = maps.crs_wkt
    todo = []
    for m, done, changed in missions:
        if changed:
            log.info(
                "%s: its definition, the maps, the DEM, or the library's defaults or results "
                "revision changed since it was planned: planning it again",
                m["name"],
            )
            res.replanned += 1
        if done is None:
            todo.append(m)
        else:
            res.skipped += 1
            if done["properties"].get("auv:status") == "uncertified":
                res.uncertified.append(m["name"])  # (the exit code of its first run)
    if res.skipped:
        log.info("%d missions finished before: skipped (--overwrite plans them again)", res.skipped)
    ready, bad = [], []
    for m in todo:
        try:
            ready.append(
                {
                    **m,
                    "start": maps.cell_of("start", m["start_form"], m["start_input"]),
                    "goal": maps.cell_of("goal", m["goal_form"], m["goal_input"]),
                }
            )
        except Exception as exc:  # noqa: BLE001 - one mission's failure, not the batch's
            bad.append((m, str(exc) if isinstance(exc, PipelineError) else repr(exc)))
    record = _Recorder(job, maps, res, len(todo))
    for m, msg in bad:
        record(m, failed_trajectory({**job.planning, **m}, msg))
    if ready:
        plan_missions(
            maps,
            ready,
            client=client,
            defaults=job.planning,
            vehicle=job.vehicle,
            quicklooks=job.quicklooks,  # drawn on the workers, side by side
            on_done=lambda i, mission, traj: record(mission, traj),
        )


class _Recorder:
    """Writes each mission's result as it ends and logs it; a mission whose result cannot be
    written is recorded as failed with the reason, and the batch goes on."""

    def __init__(self, job: Job, maps, res: JobResult, total: int):
        self.job, self.maps, self.res, self.total = job, maps, res, total
        self.count = 0
        self.clearance = float(job.maps["clearance"])

    def __call__(self, mission: dict, traj) -> None:
        from .missions import failed_trajectory, min_clearance

        self.count += 1
        self.res.ran += 1
        name = mission["name"]
        png = traj.extra.pop("quicklook_png", None)  # written now, not kept with the results
        try:
            clr = math.nan
            if traj.flight is not None:  # what is flown, from the continuous seabed
                clr = traj.flight.min_clearance_m
            elif traj.planned:  # the grid path, from the grid points
                clr = min_clearance(self.maps, traj, self.clearance)
            self._write(mission, traj, clr, png)
        except (OSError, PipelineError, ValueError) as exc:
            reason = f"its result could not be written: {type(exc).__name__}: {exc}"
            log.error("[%d/%d] %s: FAILED: %s", self.count, self.total, name, reason)
            self.res.failed.append(name)
            from .outputs.catalog import finished

            before = finished(self.job.catalog, name)
            if before is not None and before["properties"].get("auv:status") != "failed":
                # an earlier result is never replaced by a failure to write this one (the
                # next run plans the mission again, its fingerprint or files being other)
                log.error("%s: its earlier result is kept", name)
                return
            try:  # the failure itself, if the disk takes it
                self._write(mission, failed_trajectory({**self.job.planning, **mission}, reason))
            except (OSError, PipelineError, ValueError):
                pass
            return
        if traj.planned:
            self.res.planned += 1
            if traj.status != "ok":
                self.res.uncertified.append(name)
            (log.info if traj.status == "ok" else log.warning)(
                "[%d/%d] %s: %s, %.1f km (<= %.3f x the shortest), %.0f %% ridge, min clearance "
                "%.0f m (%.2f s)%s",
                self.count,
                self.total,
                name,
                traj.status,
                traj.length_m / 1e3,
                traj.certified_ratio,
                100 * traj.ridge_ratio,
                clr,
                traj.runtime_s,
                (
                    f"; flown {traj.flight.flown_length_m / 1e3:.1f} km in "
                    f"{traj.flight.duration_s / 3600:.1f} h, {len(traj.flight.waypoints)} waypoints"
                    if traj.flight is not None
                    else ""
                )
                + (f": {traj.message}" if traj.message else ""),
            )
        else:
            self.res.failed.append(name)
            log.warning("[%d/%d] %s: FAILED: %s", self.count, self.total, name, traj.message)

    def _write(self, mission, traj, clr=math.nan, png=None):
        from .outputs.catalog import write_mission

        write_mission(
            self.job.catalog,
            mission["name"],
            mission,
            traj,
            maps=self.maps,
            crs_wkt=self.maps.crs_wkt,
            min_clearance_m=clr,
            run_id=self.res.run_id,
            quicklook=self.job.quicklooks,
            quicklook_png=png,
        )
