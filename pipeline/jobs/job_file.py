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
    keep_out = ["zones.geojson"]   # areas never entered (vector files, relative to the
    keep_out_margin_m = 100.0      # job file; any CRS), kept at this distance
    [vehicle]                   # speed_m_s, max_pitch_deg, min_turn_radius_m, waypoint_band_m,
    speed_m_s = 1.5             # hotel_power_w, propulsion_power_w, battery_wh
    [[missions]]
    name = "north-ridge"
    start = [100, 120]          # a cell (row, col); or start_xy = [x, y] in map
    goal = [1800, 1700]         # coordinates, or start_lonlat = [lon, lat]
    via_lonlat = [[-44.8, 26.1]]   # visited in order (or via = cells, via_xy = [...])
    omega = 1.5                 # any [planning] key, for this mission
    vehicle = { max_pitch_deg = 15 }   # any [vehicle] key, for this mission
    [output]
    catalog = "catalogs/demo"
    quicklooks = true           # a plan view and depth profile PNG per mission
    performance_report = true   # dask's performance report of each run (a few MB)
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import shutil
import tomllib
from dataclasses import dataclass, field
from glob import escape as glob_escape
from pathlib import Path

from ..exceptions import (
    InvalidParameterError,
    JobFileError,
)
from ..params import (
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
    VIA_KEYS,
    Param,
    Schema,
    check_clearance,
    check_region,
    endpoint_forms,
    endpoint_key,
    shape2d,
    via_form,
)
from ..store.paths import has_scheme

log = logging.getLogger(__name__)


TOP_KEYS = {"name", "dem", "maps", "planning", "vehicle", "missions", "output"}


_ENDPOINT_KEYS = {f"{w}{form}" for w in ("start", "goal") for form in ("", "_xy", "_lonlat")}


MISSION_KEYS = {"name", "vehicle"} | PLANNING.names() | _ENDPOINT_KEYS | set(VIA_KEYS)


DEM_KEYS = {"path", "synthetic"} | DEM.names()


SYNTH_KEYS = {"shape"} | SYNTHETIC.names()


OUTPUT_KEYS = {"catalog", "quicklooks", "performance_report"}


_COORD = Param("coordinate", "float", None, "")


# Raised whenever a change of the code makes a mission's result differ for the same inputs (the
# planners' paths, the flight), so that a job plans its finished missions again instead of
# keeping results the code would no longer give: 2 is RA*'s ties of Nor by g_incons + h, 3 the
# default window margin of MCPC's sections halved (section_size // 8), 4 the flight's heights
# against the continuous seabed and its profile's breaks a turn radius apart, 5 the surface
# limit kept exactly and the least clearance over every sample of the flight, 6 the clearance
# measured from the DEM file itself (and the clearance, method and sea level in each Item).
RESULTS_REVISION = 6


# How a DEM file becomes the DEM store (a resample of it): 2 is the upper envelope of the file's
# bilinear surface and the region read with a margin (docs/method.md section 1). A job's DEM
# store made otherwise is made again.
DEM_CONSTRUCTION = 2


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
    # the inputs' content hashes (:meth:`content_hash`), made when first asked for
    _hashes: object = field(default=None, init=False, repr=False, compare=False)

    def maps_fingerprint(self) -> str:
        """A hash of the DEM definition and the maps parameters (reuse the maps store)."""
        from ..store.schema import MAPS_VERSION

        what = {"dem": self.dem_fingerprint(), "maps": self.maps, "version": MAPS_VERSION}
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
            "ends": {
                k: mission[k] for k in sorted(mission) if k.startswith(("start", "goal", "via"))
            },
            "planning": plan,
            "vehicle": self.vehicle_of(mission),
            "maps": self.maps_fingerprint(),
            "revision": RESULTS_REVISION,
        }
        if plan.get("keep_out"):
            what["zones"] = [self._zone_files(f) for f in plan["keep_out"]]
        return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:16]

    def content_hash(self, path) -> str:
        """The hash of what the input file or folder ``path`` holds (:mod:`.store.content`),
        kept in the catalog between runs (:meth:`save_hashes`)."""
        from ..store.content import CACHE_NAME, ContentHashes

        if self._hashes is None:
            self._hashes = ContentHashes(self.catalog / CACHE_NAME)
        return self._hashes.of(path)

    def save_hashes(self) -> None:
        """Keep the inputs' hashes in the catalog (a run, holding its lock)."""
        if self._hashes is not None:
            self._hashes.save()

    def _zone_files(self, path: str) -> list:
        """The contents of a zone file and of those beside it that share its stem (a
        Shapefile's .dbf and .prj): a mission planned with zones is planned again when they
        change."""
        p = Path(path)
        files = sorted(p.parent.glob(glob_escape(p.stem) + ".*")) if p.is_file() else [p]
        return [[f.name, self.content_hash(f)] for f in files]

    def vehicle_of(self, mission: dict) -> dict:
        """The vehicle of a mission: the job's [vehicle] with the mission's own keys over it."""
        return {**self.vehicle, **mission.get("vehicle", {})}

    def dem_fingerprint(self) -> str:
        """A hash of what defines the DEM: re-running with the same inputs reuses the store."""
        if self.dem_path is not None:
            what = {
                "path": str(self.dem_path.resolve()),
                "content": self.content_hash(self.dem_path),
                "variable": self.variable,
                "cell_size": self.cell_size,
                "construction": DEM_CONSTRUCTION,
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
        key = unknown[0]
        hint = ""
        if key in VEHICLE.names() and "vehicle" in allowed:  # a mission's vehicle key
            hint = f" ({key!r} is a vehicle's: give it as vehicle = {{{key} = ...}})"
        elif key in VEHICLE.names() and where != "vehicle.":
            hint = f" ({key!r} is a vehicle's: give it under [vehicle])"
        _fail(path, f"unknown key {where}{key!r}{hint}; allowed keys here: {sorted(allowed)}")


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
    """Read and validate a job file without computing anything: its TOML, its name, the DEM,
    the maps, the planning options, the vehicle, the missions and their ratings, the output;
    each step refuses what a run would, in one line naming the key."""
    path = Path(path)
    doc = _read_toml(path)
    _check_keys(path, doc, TOP_KEYS, "")
    job, cell = _load_dem(path, doc, _job_name(path, doc))
    _load_maps(path, doc, job, cell)
    _load_planning(path, doc, job)
    job.vehicle = _load_vehicle(path, doc.get("vehicle", {}), "vehicle.")
    _load_missions(path, doc, job)
    _check_ratings(path, job)
    _load_output(path, doc, job)
    if job.dem_path is None and "shape" in (job.synthetic or {}):
        _check_size(path, job, job.synthetic["shape"])
    return job


def _read_toml(path: Path) -> dict:
    """The job file's TOML document (a byte-order mark allowed), or one line saying why not."""
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
    return doc


def _job_name(path: Path, doc: dict) -> str:
    """The job's name (default: the file's stem), safe as a file name."""
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
    return name


def _load_dem(path: Path, doc: dict, name: str) -> tuple[Job, float | None]:
    """The job with its [dem] table read (a file or a synthetic DEM), and the cell side the
    maps are built on when it can be told before reading the DEM."""
    dem = doc.get("dem")
    if not isinstance(dem, dict):
        _fail(path, "a [dem] table is required, with path = '...' or a [dem.synthetic] table")
    _check_keys(path, dem, DEM_KEYS, "dem.")
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
        # the cell side the maps are built on: the job's, else the file's own when its header
        # says it (so that --dry-run refuses a clearance below half a cell, as a build would)
        cell = job.resolution if job.resolution is not None else _header_cell(p)
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
        _check_keys(path, syn, SYNTH_KEYS, "dem.synthetic.")
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
    return job, cell


def _load_output(path: Path, doc: dict, job: Job) -> None:
    """The [output] table: the catalog (relative to the job file, made absolute), quick-looks
    and the performance report."""
    out = doc.get("output", {})
    if not isinstance(out, dict):
        _fail(path, "[output] must be a table")
    _check_keys(path, out, OUTPUT_KEYS, "output.")
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


def _header_cell(p: Path) -> float | None:
    """The cell side (metres) a raster file's header gives, cheaply (rasterio; no values
    read): its step in a projected CRS in metres, or for longitude and latitude the square
    cell it is reprojected at by default (:func:`~pipeline.dem.reproject.natural_cell`'s
    formula); None when it cannot be told (then the build checks)."""
    try:
        import rasterio

        with rasterio.open(p) as src:
            crs, (dx, dy), bounds = src.crs, src.res, src.bounds
    except Exception:  # noqa: BLE001 - not a raster GDAL opens (a Zarr store, ...): no header
        return None
    if crs is None or dx <= 0 or dy <= 0:
        return None
    try:
        return _cell_of_header(crs, dx, dy, bounds)
    except Exception:  # noqa: BLE001 - a CRS rasterio cannot describe (compound...): the build checks
        return None


def _cell_of_header(crs, dx: float, dy: float, bounds) -> float | None:
    """:func:`_header_cell` from the header's CRS, steps and bounds."""
    if crs.is_geographic:
        from ..dem.reproject import lonlat_cell

        return lonlat_cell(dx, dy, 0.5 * (bounds.bottom + bounds.top))
    if crs.linear_units_factor[1] != 1.0 or abs(dx - dy) > 1e-6 * dx:
        return None  # (feet, or cells not square: the build resamples, then checks)
    return float(dx)


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
        hint = ""
        if cell_size is not None and "half a cell" in str(exc):
            finest = 2 * min(t[k] for k in ("clearance", "horizontal_clearance") if t.get(k))
            where = "[dem] resolution" if job.dem_path is not None else "dem.synthetic.cell_size"
            hint = f" (in this job: a larger [maps] clearance, or {where} = {finest:g} or finer)"
        _fail(path, f"{exc}{hint}")
    job.maps = _maps_defaults(t)


def _load_planning(path, doc, job):
    t = doc.get("planning", {})
    if not isinstance(t, dict):
        _fail(path, "[planning] must be a table")
    _check_keys(path, t, PLANNING.names(), "planning.")
    job.planning = _checked(path, PLANNING, t, "planning.")
    _zone_files(path, job.planning, "planning.")


def _zone_files(path: Path, table: dict, where: str) -> None:
    """``table``'s keep_out files as absolute paths (relative to the job file), each read and
    checked as a run reads it: a missing or unreadable file, a geometry that is not a
    polygon, a file without a CRS is one :class:`JobFileError` (``--dry-run`` included)."""
    from ..constraints.zones import read_zone_file

    if table.get("keep_out") is None:
        return
    files = [str((path.parent / p).resolve()) for p in table["keep_out"]]
    for f in files:
        try:
            read_zone_file(f)
        except InvalidParameterError as exc:
            _fail(path, f"{where}keep_out: {exc}")
    table["keep_out"] = files


def _check_point(path: Path, key: str, p, form: str, given) -> None:
    """A point of a mission (an end, a via point) in its ``form``: a cell of integers, map
    coordinates, or a longitude and latitude in range; ``given`` is shown in the error."""
    integer = form == "cell"
    if not all(
        isinstance(x, int if integer else int | float) and not isinstance(x, bool) for x in p
    ):
        what = "[row, col] of integers" if integer else "pairs of numbers"
        _fail(path, f"{key} must be {'a list of ' if given is not p else ''}{what}, got {given!r}")
    if form != "cell":
        try:
            for x, param in zip(
                p, (LONGITUDE, LATITUDE) if form == "lonlat" else (_COORD,) * 2, strict=True
            ):
                param.check(x, key)
        except InvalidParameterError as exc:
            _fail(path, str(exc))


def _load_via(path: Path, m: dict, mission: dict, where: str) -> None:
    """A mission's via points, checked as its start and goal are: ``via_form`` and
    ``via_input`` in ``mission`` (the cells are found once the maps exist)."""
    try:
        form, points = via_form(m)
    except InvalidParameterError as exc:
        _fail(path, f"{where}{exc}")
    if form is None:
        return
    key = endpoint_key("via", form)
    for p in points:
        _check_point(path, f"{where}{key}", p, form, m[key])
    mission["via_form"] = form
    mission["via_input"] = [list(p) for p in points]


def _check_ratings(path: Path, job: Job) -> None:
    """Each vehicle's rated depth against the maps' surface limit (the sea level less the
    surface clearance, R by default): a rating shallower leaves no height to fly at."""
    vehicles = [("vehicle.", job.vehicle)] + [
        (f"missions[{i}].vehicle.", {**job.vehicle, **m.get("vehicle", {})})
        for i, m in enumerate(job.missions)
    ]
    if all(v.get("max_depth_m") is None for _, v in vehicles):
        return
    from ..constraints.store import check_rating
    from ..store.schema import MapsParameters

    maps = job.maps
    parameters = MapsParameters(
        method=maps["method"],
        clearance_m=float(maps["clearance"]),
        sea_level_m=float(maps.get("sea_level", MAPS.sea_level.default)),
        surface_clearance_m=maps.get("surface_clearance"),
    )
    for where, vehicle in vehicles:
        if vehicle.get("max_depth_m") is not None:
            try:
                check_rating(vehicle["max_depth_m"], parameters)
            except InvalidParameterError as exc:
                _fail(path, f"{where}max_depth_m: {exc}")


def _load_vehicle(path, t, where: str, base: dict | None = None) -> dict:
    from ..flight.vehicle import Vehicle

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
    from ..outputs.catalog import mission_id

    ms = doc.get("missions", [])
    if not isinstance(ms, list) or not all(isinstance(m, dict) for m in ms):
        _fail(path, "missions must be an array of tables ([[missions]])")
    seen, folders = set(), {}
    for i, m in enumerate(ms):
        where = f"missions[{i}]."
        _check_keys(path, m, MISSION_KEYS, where)
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
            form = endpoint_forms(m, end)[0]
            if not isinstance(v, list) or len(v) != 2:
                what = "[row, col] of integers" if form == "cell" else "a pair of numbers"
                _fail(path, f"{where}{key} must be {what}, got {v!r}")
            _check_point(path, f"{where}{key}", v, form, v)
            mission[f"{end}_form"] = form
            mission[f"{end}_input"] = list(v)
        _load_via(path, m, mission, where)
        plan = {k: m[k] for k in PLANNING.names() if k in m}
        mission.update(_checked(path, PLANNING, plan, where))
        _zone_files(path, mission, where)
        if "vehicle" in m:
            mission["vehicle"] = _load_vehicle(path, m["vehicle"], f"{where}vehicle.", job.vehicle)
        job.missions.append(mission)
