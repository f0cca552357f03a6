"""Compile the numba kernels once, up front, on every core: the first run after an install.

numba compiles a kernel the first time it is called and keeps the machine code in its on-disk
cache (``__pycache__`` beside the source, or ``NUMBA_CACHE_DIR``), so only the first run on a
machine pays: about a minute of compilation on one core. Left to itself, that minute lands
inside the first DEM, maps and missions (whose recorded runtimes then hold it) and the two
workers compile the same kernels side by side. :func:`ensure_compiled` instead compiles them
in two halves at once on two workers, before the job starts, says so in the log, and leaves a
stamp so that later runs skip it.

The halves: one builds a tiny maps store (ridges, components, landmarks, the coarse levels),
then plans one mission on it, flies it (the flight's kernels), widens its corners for a wide
turn radius (the kernels of corners too close for it, which the tiny flight does not meet) and
checks its clearance as a job does, then compiles the bucketed A* of large windows. The
other compiles, meanwhile, what the store's build
reaches later (the safety kernels, the landmarks' search) and what needs no store (every
planner's search on in-memory arrays, the synthetic DEM), then plans on the store with every
planner once it exists. The flight, the longest part after the store, thus follows it at
once, and no process waits idle for the store (the halves were the store and the planners
against the safety kernels, the DEM and the flight, which waited a third of its time for the
store). Each kernel is compiled with the argument types
the pipeline uses, so later calls load it from the cache.

A job compiles only the parts it uses (:func:`job_parts`: no reprojection for a synthetic DEM,
no bucketed A* for a small one, no other clearance method's kernels); the stamp lists the parts
compiled, and a later job that needs another compiles just that.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ..store.paths import write_atomically

log = logging.getLogger(__name__)

# the parts of the warm-up, in the order one process runs them all
PARTS = (
    "maps",
    "landmarks",
    "safety",
    "search",
    "bucketed",
    "planners",
    "synthetic",
    "warp",
    "flight",
)
# how the parts are shared between two processes: the second compiles the landmark layers'
# fixed-point search first, before the first's maps store needs it (the first starts with the
# bucketed A* of large windows, which needs no store); the safety kernels, which the store
# needs at once, the first compiles as it builds it; the second then the searches, before the
# first's planners. Measured in a fresh cache, the halves in seconds: 24.7-25.8 and 27.1-27.9;
# 30.4 and 29.7 with the maps first and the safety kernels before the landmarks (both halves
# then compiled the fixed-point search at once), 22.1 and 21.3 before it existed
HALVES = (
    ("bucketed", "maps", "flight"),
    ("landmarks", "safety", "search", "synthetic", "warp", "planners"),
)
# every part (what a warm-up without a job compiles, and the tests' warm-up)
ALL = frozenset(PARTS)
# what every job needs: compiled together (the planners and the flight use the tiny store the
# maps part builds)
CORE = frozenset({"maps", "landmarks", "search", "planners", "flight"})
# how long a part waits for the tiny maps store another process builds, before building its own
STORE_WAIT_S = 300.0
# the package whose sources the kernels are compiled from
_PACKAGE = Path(__file__).parents[1]


def _stamp_path() -> Path:
    from numba.core import config

    if config.CACHE_DIR:
        return Path(config.CACHE_DIR) / "auv-pipeline-kernels.json"
    return _PACKAGE / "__pycache__" / "kernels.json"


def _fingerprint(root: Path | None = None) -> str:
    """What numba's cache depends on: numba, Python, the CPU and the stamp (modification time
    and size) of every source file under ``root`` (the package)."""
    import numba
    from numba.core import config

    parts = [numba.__version__, sys.version, str(config.CPU_NAME or ""), _cpu_name()]
    root = _PACKAGE if root is None else Path(root)
    for p in sorted(root.rglob("*.py")):
        st = p.stat()
        parts.append(f"{p.relative_to(root)}:{st.st_mtime_ns}:{st.st_size}")
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


def _cpu_name() -> str:
    try:
        import llvmlite.binding as ll

        return ll.get_host_cpu_name()
    except Exception:  # noqa: BLE001 - only a part of the fingerprint
        return ""


def _compiled_parts() -> frozenset:
    """The parts the stamp says were compiled for this installation and these sources (none
    when it is missing or for other sources)."""
    try:
        stamp = json.loads(_stamp_path().read_text())
    except (OSError, ValueError):
        return frozenset()
    if not isinstance(stamp, dict) or stamp.get("fingerprint") != _fingerprint():
        return frozenset()
    return frozenset(stamp.get("parts", ALL)) & ALL


def is_compiled(parts=None) -> bool:
    """Whether the kernels of ``parts`` (names of :data:`ALL`; every part by default) were
    compiled for this installation and these sources."""
    return frozenset(ALL if parts is None else parts) <= _compiled_parts()


def mark_compiled(seconds: float = 0.0, parts=None) -> None:
    """Stamp the kernels of ``parts`` (every part by default) compiled for this installation
    and these sources (what :func:`ensure_compiled` does once it has compiled them), for a
    caller that ran those parts of the warm-up itself (:func:`compile_parts`, say each of
    :data:`HALVES` in a process of its own): later runs then skip them."""
    path = _stamp_path()
    done = sorted(_compiled_parts() | frozenset(ALL if parts is None else parts))
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        stamp = {"fingerprint": _fingerprint(), "parts": done, "seconds": round(seconds, 1)}
        write_atomically(path, json.dumps(stamp))
    except OSError:  # a read-only installation: the warm-up runs again next time, harmlessly
        pass


def job_parts(job) -> frozenset:
    """The parts of the warm-up a job (:class:`~pipeline.jobs.job_file.Job`) needs: every part but
    the synthetic DEM's kernels for a DEM file, the reprojection's and the check against the
    file's own seabed for a synthetic DEM (a file may be reprojected), the A* of windows of
    :data:`~pipeline.planners.search.BUCKET_CELLS` cells for a synthetic DEM smaller than
    that (a file's size is not known before it is read), and the safety kernels of the other
    methods for the spherical one (the maps part's store is spherical)."""
    from ..planners.search import BUCKET_CELLS

    parts = set(ALL)
    if job.dem_path is not None:
        parts.discard("synthetic")
    else:
        parts.discard("warp")
        shape = (job.synthetic or {}).get("shape")
        if shape is not None and int(shape[0]) * int(shape[1]) < BUCKET_CELLS:
            parts.discard("bucketed")
    if (job.maps or {}).get("method", "spherical") == "spherical":
        parts.discard("safety")
    return frozenset(parts)


def _tiny_dem():
    """A 48 x 48 rough seabed with a deep basin and an island, as the DEM store gives it."""
    import xarray as xr

    n = 48
    i, j = np.mgrid[0:n, 0:n].astype(np.float64)
    z = -3000.0 + 400.0 * np.sin(i / 5.0) * np.cos(j / 7.0) + 30.0 * np.sin(i * j / 11.0)
    z[30:36, 30:36] = 5.0  # land: not passable
    a = 30.0
    return xr.DataArray(
        z.astype(np.float32),
        dims=("y", "x"),
        coords={"y": (n - 0.5 - np.arange(n)) * a, "x": (np.arange(n) + 0.5) * a},
        name="elevation",
        attrs={"cell_size": a, "units": "m", "positive": "up", "source": "warm-up"},
    )


def _safety(dem) -> None:
    """The safety kernels of every method, and the passable layer's."""
    from ..maps.build import passable
    from ..maps.safety import safety_map

    for method in ("spherical", "vertical", "horizontal"):
        passable(dem, safety_map(dem, method=method, clearance=60.0)).compute()


def _store(tmp: Path, build: bool) -> Path:
    """The tiny maps store: built here (``build``), or waited for (another process builds it)."""
    store, ready = tmp / "maps.zarr", tmp / "maps.ready"
    if build:
        from ..dem.dem_store import write_dem
        from ..dem.open import open_dem
        from ..maps.build import build_maps

        write_dem(_tiny_dem(), tmp / "dem.zarr", chunks=24, overwrite=True)
        dem = open_dem(tmp / "dem.zarr", chunks=24)
        build_maps(dem, store, clearance=60.0, min_accumulation=4, landmarks=2, overwrite=True)
        ready.touch()
        return store
    t0 = time.monotonic()
    while not ready.exists():
        if time.monotonic() - t0 > STORE_WAIT_S:  # the other half is elsewhere: build one
            return _store(tmp / "own", True)
        time.sleep(0.2)
    return store


def compile_parts(workdir: str | os.PathLike, parts=PARTS) -> dict:
    """Run the warm-up ``parts`` (names from :data:`PARTS`) in this process, with the dask
    scheduler synchronous; ``workdir`` is shared by the processes of one warm-up (the tiny
    store). Returns the seconds each part took."""
    import dask

    import pipeline

    took = {}
    tmp = Path(workdir)
    tmp.mkdir(parents=True, exist_ok=True)
    with dask.config.set(scheduler="synchronous"):
        for part in parts:
            t0 = time.perf_counter()
            if part == "synthetic":
                pipeline.synthetic_dem((64, 64), chunks=32).compute()
            elif part == "warp":
                _warp()
                _source_check()
            elif part == "safety":
                from ..dem.dem_store import write_dem
                from ..dem.open import open_dem

                write_dem(_tiny_dem(), tmp / "dem-safety.zarr", chunks=24, overwrite=True)
                _safety(open_dem(tmp / "dem-safety.zarr", chunks=24))
            elif part == "maps":
                _store(tmp, build=True)
            elif part == "landmarks":
                _landmarks()
            elif part == "search":
                _search_each()
            elif part == "bucketed":
                _search_bucketed()
            elif part == "planners":
                _plan_each(_store(tmp, build=False))
            elif part == "flight":
                store = _store(tmp, build=False)
                t = _plan_each(store, planners=("astar",))
                if t is not None:
                    from ..outputs.files import crc16
                    from ..verify.clearance import min_clearance

                    pipeline.fly(store, t)
                    _widen(store, t)
                    min_clearance(store, t, 60.0)  # a job's independent check of each mission
                    crc16(b"IMC")  # a mission's IMC plan, written by a job's client
            else:
                known = sorted(ALL)
                raise ValueError(f"unknown warm-up part {part!r}; known: {known}")
            took[part] = round(time.perf_counter() - t0, 1)
    return took


def _tiny_arrays():
    """The tiny DEM in memory as a window's safety surface (float32) and its passable cells."""
    z = _tiny_dem().values
    return z, z < -100.0


def _tiny_window():
    """:func:`_tiny_arrays` as a section's window: the surface, a ridge mask, the passable
    cells, and a start and goal (the first and last passable cells)."""
    z, ok = _tiny_arrays()
    rdg = np.random.default_rng(2).random(z.shape) < 0.3
    cells = np.argwhere(ok)
    return z, rdg, ok, tuple(cells[0]), tuple(cells[-1])


def _landmarks() -> None:
    """The kernels of landmark placement and of a landmark's layer (an exact search of the whole
    map), on a map of the types the store's build gives them."""
    from ..maps.landmarks import landmark_layer, place_landmarks

    z, ok = _tiny_arrays()
    place_landmarks(z, ok, 30.0, 2)
    landmark_layer(z, ok, 30.0, tuple(np.argwhere(ok)[0]))


def _search_each() -> None:
    """Every planner's search on in-memory arrays of the types a section's window has (no
    store needed): what :func:`_plan_each` then finds compiled."""
    import pipeline

    from ..planners import sweep
    from ..planners.bounds import lagrangian_bound, off_ridge_to_goal, raised_bound
    from ..planners.paths import measured_path

    z, rdg, ok, s, g = _tiny_window()
    for planner in tuple(pipeline.PLANNERS)[::-1]:
        for omega in (1.0, 1.5):  # at omega 1 the Lagrangian planner's exact goal layer
            try:
                pipeline.plan_window(z, rdg, ok, s, g, cell_size=30.0, planner=planner, omega=omega)
            except pipeline.PipelineError:
                continue
    # on nearly flat ground the Lagrangian planner's weighted searches take a bound of their own
    # (lagrangian.BOUND_SLACK), which the rough tiny map never asks for
    hoff = off_ridge_to_goal(rdg, ok, 30.0, *g, *s)
    raised_bound(
        lagrangian_bound(rdg, ok, 30.0, *s, *g, 2.0, hoff), hoff, 2.0, 4.0, *z.shape, *g, 30.0
    )
    # the exact search of windows from SWEEP_CELLS on (whole large maps), which the tiny map
    # is not
    sweep.flat_between(z, ok, 30.0, s, g)
    got = sweep.search(z, ok, 30.0, s, g)
    if got is not None:
        measured_path(got[0], z, rdg, 30.0)


def _search_bucketed() -> None:
    """The A* of windows from BUCKET_CELLS on (whole large maps), which the tiny map is not: a
    part of its own, so that the process with less of the rest to compile takes it."""
    from ..planners.search import NO_GOAL, NO_LANDMARKS, astar_search_bucketed, search_arrays

    z, rdg, ok, s, g = _tiny_window()
    astar_search_bucketed(
        z, rdg, ok, 30.0, *s, *g, 1.0, 0.0, True, NO_LANDMARKS, NO_GOAL, *search_arrays(z.size)
    )


def _widen(store: Path, t) -> None:
    """The flight's kernels the tiny mission's flight does not meet: those of corners too close
    for the turn radius (``widen_turns``; its grid path's corners with a radius of 10 cells),
    and the required heights over whole grid squares (a clearance of at least
    ``FINE_BELOW`` cells: the tiny store's is 2)."""
    from ..flight.geometry import Corridor, widen_turns
    from ..flight.profile import FINE_BELOW, required_heights
    from ..methods import METHODS
    from ..store.maps_store import open_store

    m = open_store(store)
    cells = np.asarray(t.cells, dtype=np.int64)
    cor = Corridor(m, cells, 3)
    usable = (cor.pas, cor.slot, cor.tr, cor.tc, *m.shape, 3)
    pr, pc = cells[:, 0].astype(np.float64), cells[:, 1].astype(np.float64)
    widen_turns(pr, pc, 10.0, usable)
    # as the flight calls it for whole squares: the squares' diagonal added to every distance
    a, clearance = 30.0, FINE_BELOW * 30.0
    partial = np.zeros(len(pr), dtype=np.uint8)
    code = METHODS["spherical"].code
    extra = a * math.sqrt(2.0)
    required_heights(*cor.grid(), pr, pc, a, clearance, code, clearance, extra, partial)


def _plan_each(store: Path, planners=None):
    """Plan corner to corner on the tiny store with each planner, in sections and whole;
    returns the last trajectory."""
    import pipeline

    cells = np.argwhere(pipeline.open_maps(store)["passable"].values)
    last = None
    for planner in planners or tuple(pipeline.PLANNERS)[::-1]:
        for mcpc in (True, False):
            try:
                last = pipeline.plan(
                    store,
                    tuple(cells[0]),
                    tuple(cells[-1]),
                    planner=planner,
                    omega=1.5,
                    mcpc=mcpc,
                    rho=2,
                    section_size=8,
                    client="synchronous",
                )
            except pipeline.PipelineError:
                continue
    return last


def ensure_compiled(client=None, *, force: bool = False, parts=None) -> float:
    """Compile the kernels of ``parts`` (names of :data:`ALL`; every part by default, a job's
    :func:`job_parts`), unless the stamp says they were compiled for this installation and
    these sources: in two halves on two workers of ``client`` (a ``distributed.Client``), or
    in this process when there is none or a single worker. Logs what it does; returns the
    seconds spent (0 when skipped)."""
    asked = frozenset(ALL if parts is None else parts)
    unknown = asked - ALL
    if unknown:
        raise ValueError(f"unknown warm-up parts {sorted(unknown)}; known: {sorted(ALL)}")
    have = frozenset() if force else _compiled_parts()
    missing = asked - have
    if not missing:
        return 0.0
    if missing & CORE:
        missing |= CORE & asked  # the planners and the flight need the maps part's store
    if have:
        log.info("compiling the kernels of %s, first use only ...", ", ".join(sorted(missing)))
    else:
        log.info("compiling kernels, first run only (about a minute on 2 cores) ...")
    t0 = time.perf_counter()
    try:
        _compile(client, missing)
    except Exception as exc:  # noqa: BLE001 - the kernels then compile as they are first used
        log.warning(
            "compiling the kernels up front failed (%s: %s); they compile as they are "
            "first used instead",
            type(exc).__name__,
            exc,
        )
        return time.perf_counter() - t0
    seconds = time.perf_counter() - t0
    mark_compiled(seconds, missing)
    log.info("kernels compiled in %.1f s (cached for the next runs)", seconds)
    return seconds


def _halves(parts) -> list:
    """:data:`HALVES` with only ``parts``; without the bucketed A*, the first process starts
    with the synthetic DEM instead (the store's build would otherwise reach the landmark
    layers' search while the other process still compiles it, and compile it too)."""
    first, second = HALVES
    if "bucketed" not in parts and "synthetic" in parts:
        first, second = ("synthetic", *first), tuple(p for p in second if p != "synthetic")
    return [h for h in (tuple(p for p in half if p in parts) for half in (first, second)) if h]


def _compile(client, parts=ALL) -> None:
    halves = _halves(parts)
    order = tuple(p for p in PARTS if p in parts)  # one process: the store before its users
    with tempfile.TemporaryDirectory(prefix="auv-warmup-") as tmp:
        workers = sorted(client.scheduler_info()["workers"]) if client is not None else []
        if len(workers) >= 2 and len(halves) == 2:
            futures = [
                client.submit(
                    compile_parts,
                    tmp,
                    half,
                    workers=[w],
                    allow_other_workers=False,
                    pure=False,
                    key=f"compile-kernels-{k}-{os.getpid()}",
                )
                for k, (w, half) in enumerate(zip(workers, halves, strict=False))
            ]
            took = client.gather(futures)
        elif workers:
            took = [client.submit(compile_parts, tmp, order, workers=workers, pure=False).result()]
        else:
            took = [compile_parts(tmp, order)]
    log.debug("warm-up parts (seconds, per process): %s", took)


def _source_check() -> None:
    """The kernel of a mission's check against its DEM file's own seabed (a job's client runs
    it for a DEM read from a file), by every method, on the tiny DEM in memory."""
    from ..verify.seabed import SourceSeabed

    dem = _tiny_dem()
    seabed = SourceSeabed(Path("warm-up"), dem, None)
    x = np.linspace(100.0, 1300.0, 40)
    y, z = np.full(40, 700.0), np.full(40, -2000.0)
    for method in ("spherical", "horizontal", "vertical"):
        seabed.clearances(x, y, z, None, 60.0, method, least_only=True)


def _warp() -> None:
    """The exact reprojection's kernel (lon/lat grids), on a tiny grid."""
    import xarray as xr
    from pyproj import CRS
    from rasterio.transform import from_origin

    from ..dem.reproject import exact_warp

    lon, lat = -20.0 + 0.01 * np.arange(40), 40.0 - 0.01 * np.arange(40)
    src = xr.DataArray(np.zeros((40, 40), np.float32), dims=("y", "x"), coords={"y": lat, "x": lon})
    aeqd = CRS.from_proj4("+proj=aeqd +lat_0=39.8 +lon_0=-19.8 +datum=WGS84 +units=m")
    exact_warp(src, CRS.from_epsg(4326), aeqd, from_origin(-15e3, 15e3, 500.0, 500.0), (40, 40))
