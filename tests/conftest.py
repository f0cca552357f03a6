"""Shared fixtures: real bathymetry (matplotlib's topobathy sample), small synthetic grids, one
LocalCluster for the session, real scheduler and worker processes."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

# chunkings every chunked function is checked with: tiny uneven, power of two, ragged, single
CHUNKINGS = [(7, 5), (64, 64), (100, 37), None]

_WARM: list = []  # the warm-up processes (tests/_warm_numba.py)
_WARM_DIR = "PIPELINE_TEST_WARM_DIR"  # where they write a file per step done


def pytest_sessionstart(session):
    """In a fresh environment numba compiles every kernel on first use (about two minutes of
    one core for the library's, about 20 s for the pysheds kernels the comparisons call), then
    caches it on disk. Two processes (tests/_warm_numba.py) compile the library's kernels in
    the two halves of ``pipeline.jobs.warmup`` at once; then one compiles the argument types only
    the tests use, then pysheds', while the tests run. Under pytest-xdist (``./dev test`` runs
    one test process per core, up to 4) only the controller starts them; every test process
    waits for the library's kernels (the cores are busy compiling them meanwhile), the pysheds
    comparisons for pysheds'."""
    if hasattr(session.config, "workerinput"):  # an xdist worker: the controller started them
        return
    from pipeline.jobs.warmup import is_compiled

    marks = Path(tempfile.mkdtemp(prefix="pipeline-warm-"))
    os.environ[_WARM_DIR] = str(marks)  # inherited by the xdist workers started after this
    if is_compiled():  # a warm environment: nothing to wait for
        (marks / "library").touch()
    script = str(Path(__file__).with_name("_warm_numba.py"))
    for half in ("first", "second"):
        _WARM.append(
            subprocess.Popen(
                [sys.executable, script, half, str(marks)],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        )


def pytest_unconfigure(config):
    for proc in _WARM:  # a warm-up still running when the tests are done (a short selection)
        if proc.poll() is None:
            proc.terminate()


def _wait_for_warm_up(step: str, timeout: float = 900.0) -> None:
    marks = os.environ.get(_WARM_DIR)
    deadline = time.monotonic() + timeout
    while marks and not (Path(marks) / step).exists() and time.monotonic() < deadline:
        if _WARM and all(p.poll() is not None for p in _WARM):
            return  # the warm-up died: the tests compile what they need themselves
        time.sleep(0.2)


@pytest.fixture(scope="session", autouse=True)
def library_kernels_compiled():
    """The library's kernels are in numba's cache before the first test (a cold start)."""
    _wait_for_warm_up("library")


@pytest.fixture(scope="session", autouse=True)
def offline_stac_schemas():
    """Items carry the STAC projection extension, whose schema pystac would fetch from the
    network: validate against the copy of its fields in tests/data instead (no network)."""
    import json

    import pystac.validation

    url = "https://stac-extensions.github.io/projection/v2.0.0/schema.json"
    schema = json.loads(
        Path(__file__).with_name("data").joinpath("stac-projection-v2.0.0.json").read_text()
    )
    pystac.validation.RegisteredValidator.get_validator().schema_cache[url] = schema


@pytest.fixture(scope="session")
def test_kernels_compiled():
    """The warm-up has compiled the argument types only the tests use (compile_test_kernels):
    the modules that call the kernels with them wait for it rather than compile them a second
    time beside it (in a fresh clone the two test processes compiled the landmarks' Dijkstra and
    RA* on float64 heights while the warm-up was compiling them: about 18 s of CPU twice over,
    the session cluster's set-up among them)."""
    _wait_for_warm_up("tests")


@pytest.fixture(scope="session")
def pysheds_ready():
    """The warm-up has compiled the pysheds kernels the comparisons call."""
    _wait_for_warm_up("pysheds")


def _import_pysheds():
    """Import pysheds with its numba kernels compiled as they are first called.

    pysheds 0.5 gives each of its 90 kernels an explicit signature, so importing it compiles
    them all: about a minute of one core in a fresh environment (then 4-5 s per process to load
    them from the cache), though the comparisons call a handful. The import here drops those
    signatures: the same functions, compiled on first call for the argument types they are
    given (the filled DEM, D8 codes and accumulation are equal bit for bit either way).

    Its generator ``count`` (``itertools.count`` in numba, used by the priority flood) is not
    cached on disk: numba cannot compile a function that uses a generator it loaded from the
    cache (``KeyError: int64 generator(func=count ...)`` in ``get_generator_impl``). With
    ``count`` cached and the priority flood not (a warm-up ended between the two saves: a short
    test selection ends it), every later process failed the pysheds comparisons until the cache
    was cleared. Compiled afresh in each process instead, in a fraction of a second."""
    import inspect

    if "pysheds.grid" not in sys.modules:
        import numba

        eager = numba.njit

        def jit(f, options):
            if inspect.isgeneratorfunction(f):
                options = {**options, "cache": False}
            return eager(f, **options)

        def lazy(*args, **options):
            if args and inspect.isfunction(args[0]):
                return jit(args[0], options)
            return lambda f: jit(f, options)  # @njit(signature, ...): drop the signature

        numba.njit = lazy
        try:
            import pysheds.grid  # noqa: F401
        finally:
            numba.njit = eager
    if not hasattr(np, "in1d"):  # pysheds 0.5 calls numpy.in1d, removed in numpy 2.4
        np.in1d = np.isin


def pysheds_ridges(z):
    """pysheds' filled DEM and D8 accumulation on the inverted filled DEM (the ridge layers'
    reference), for a grid of 30 m cells."""
    _import_pysheds()
    from affine import Affine
    from pysheds.grid import Grid
    from pysheds.sview import Raster, ViewFinder

    vf = ViewFinder(affine=Affine(30.0, 0, 0, 0, -30.0, 0), shape=z.shape, nodata=np.nan)
    grid = Grid(viewfinder=vf)
    filled = grid.fill_depressions(Raster(z.astype(np.float64), viewfinder=vf))
    inv = Raster(-np.asarray(filled), viewfinder=vf)
    dirmap = (64, 128, 1, 2, 4, 8, 16, 32)
    fdir = grid.flowdir(inv, dirmap=dirmap, flats=-1, pits=-2, nodata_out=0)
    return np.asarray(filled), np.asarray(grid.accumulation(fdir, dirmap=dirmap))


def compile_kernels() -> None:
    """Compile every numba kernel the tests use into numba's on-disk cache: the pipeline's own
    warm-up (pipeline.jobs.warmup, as a job's first run does), then the argument types only the
    tests use (the session cluster runs this before its workers start)."""
    from pipeline.jobs.warmup import ensure_compiled

    ensure_compiled()
    compile_test_kernels()


def compile_test_kernels() -> None:
    """The kernels with the argument types only the tests use."""
    import dask

    import pipeline
    from pipeline.maps.ridges import accumulation_single, fill_single

    with dask.config.set(scheduler="synchronous"):
        small = pipeline.synthetic_dem((40, 40), chunks=None)
        for method in ("vertical", "horizontal", "spherical"):
            pipeline.safety_map(small, method=method, clearance=60.0)
            pipeline.safety_map(small.chunk(16), method=method, clearance=60.0).compute()
        accumulation_single(fill_single(small.values))
    surface = random_surface((12, 12)).astype(np.float64)
    ridge, ok = np.zeros(surface.shape, bool), np.ones(surface.shape, bool)
    for planner in pipeline.PLANNERS:
        pipeline.plan_window(
            surface, ridge, ok, (0, 0), (11, 11), cell_size=30.0, planner=planner, omega=1.5
        )
    # what the tests call directly: the landmarks' Dijkstra on float64 heights (the library
    # runs it on a store's float32 ones), the searches' heap on its own
    from pipeline.planners.bounds import dijkstra
    from pipeline.planners.heap import heap_pop, heap_push, heap_reserve

    dijkstra(surface, ok, 30.0, np.array([0], dtype=np.int64))
    keys, items = heap_reserve(np.empty(1), np.empty(1, dtype=np.int64), 0, 2)
    heap_pop(keys, items, heap_push(keys, items, 0, 1.0, 0))


@pytest.fixture(scope="session")
def local_client(tmp_path_factory, test_kernels_compiled):
    """One LocalCluster of 2 single-threaded worker processes for every test that needs a
    cluster but does not test starting one (jobs take it as their scheduler): its workers
    import the library and load the compiled kernels once. Every kernel is in numba's cache
    before they start (compile_kernels; in a fresh clone it waits for the warm-up's test
    kernels rather than compile them a second time beside it)."""
    from distributed import Client

    from pipeline.runtime.cluster import local_cluster

    compile_kernels()
    cluster = local_cluster()
    client = Client(cluster, set_as_default=False)
    yield client
    client.close()
    cluster.close()


@pytest.fixture(scope="session")
def topobathy():
    """(elevation, lon, lat): real bathymetry and topography off Vancouver Island, lon/lat grid."""
    from matplotlib import cbook

    d = cbook.get_sample_data("topobathy.npz")
    z = np.asarray(d["topo"], dtype=np.float32)
    lon = np.asarray(d["longitude"], dtype=np.float64)
    lat = np.asarray(d["latitude"], dtype=np.float64)
    return z, lon, lat


def lonlat_dataarray(z, lon, lat) -> xr.DataArray:
    """A CF-style lon/lat DataArray (latitudes north first, as a GeoTIFF stores them)."""
    if lat[0] < lat[-1]:
        z, lat = z[::-1], lat[::-1]
    return xr.DataArray(
        z,
        dims=("lat", "lon"),
        coords={
            "lat": ("lat", lat, {"units": "degrees_north", "standard_name": "latitude"}),
            "lon": ("lon", lon, {"units": "degrees_east", "standard_name": "longitude"}),
        },
        name="topo",
        attrs={"units": "m"},
    )


@pytest.fixture(scope="session")
def topobathy_tif(tmp_path_factory, topobathy):
    """The topobathy grid written as a real EPSG:4326 GeoTIFF."""
    import rioxarray  # noqa: F401

    z, lon, lat = topobathy
    arr = lonlat_dataarray(z, lon - 360.0, lat).rename(lat="y", lon="x")
    arr = arr.rio.write_crs("EPSG:4326")
    path = tmp_path_factory.mktemp("real") / "topobathy.tif"
    arr.rio.to_raster(path)
    return path


@pytest.fixture(scope="session")
def topobathy_nc(tmp_path_factory, topobathy):
    """The topobathy grid written as a real CF NetCDF file (lat/lon dims, 0..360 longitudes)."""
    z, lon, lat = topobathy
    path = tmp_path_factory.mktemp("real") / "topobathy.nc"
    lonlat_dataarray(z, lon, lat).to_dataset().to_netcdf(path)
    return path


def metric_dataarray(
    z: np.ndarray, a: float = 50.0, x0: float = 500_000.0, y0: float = 5_000_000.0
) -> xr.DataArray:
    """A north-up projected grid of cell side ``a`` with ``z`` as values."""
    rows, cols = z.shape
    return xr.DataArray(
        z,
        dims=("y", "x"),
        coords={"x": x0 + (np.arange(cols) + 0.5) * a, "y": y0 - (np.arange(rows) + 0.5) * a},
    )


def random_surface(shape, seed=0, flats=False, holes=False) -> np.ndarray:
    """A rough random seabed (smoothed noise), optionally with flats and no-data holes."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    z = ndimage.gaussian_filter(rng.normal(size=shape), 2.0) * 400.0 - 3000.0
    z += rng.normal(size=shape) * 5.0
    if flats:
        z[shape[0] // 4 : shape[0] // 2, shape[1] // 4 : shape[1] // 2] = -2900.0
    if holes:
        z[rng.random(shape) < 0.01] = np.nan
        z[: shape[0] // 6, -shape[1] // 6 :] = np.nan
    return z.astype(np.float32)


def quantisation_error_bound(surface, ok, side: int) -> float:
    """An independent bound (numpy, from the definition) on how far a passable cell's height in
    a landmark search's quantised surface (pipeline.maps.landmarks.quantised: 65 534 steps of its
    ``side`` x ``side`` block's relief) may lie from its float32 height: half a step, and a
    little more for the step's float32 rounding and float64 sums of heights."""
    z = np.where(ok, np.asarray(surface, dtype=np.float64), np.nan)
    worst = 0.0
    for r in range(0, z.shape[0], side):
        for c in range(0, z.shape[1], side):
            b = z[r : r + side, c : c + side]
            if np.isfinite(b).any():
                worst = max(worst, float(np.nanmax(b) - np.nanmin(b)))
    top = float(np.nanmax(np.abs(z))) if np.isfinite(z).any() else 0.0
    return 0.51 * worst / 65534 + 1e-9 * (top + 1.0)


def assert_lower_layer(got, want, rtol: float) -> None:
    """A landmark layer ``got`` (float32 metres) against scipy's distances ``want``: inf at the
    same cells, never above them (but for float32 rounding), and at most ``rtol`` below."""
    fin = np.isfinite(want)
    np.testing.assert_array_equal(np.isfinite(got), fin)
    g, w = got[fin].astype(np.float64), want[fin]
    assert (g <= w * (1 + 2.0**-24)).all()
    assert (g >= w * (1 - rtol - 2.0**-24)).all()


def write_bag(tmp_path, z, sigma, a=30.0):
    """A BAG (GDAL's driver: an elevation and an uncertainty band) from a two-band GeoTIFF;
    NaN cells are written as the BAG's no-data."""
    import rasterio
    from rasterio.shutil import copy
    from rasterio.transform import from_origin

    nodata = 1.0e6
    tif = tmp_path / "two-band.tif"
    profile = dict(
        driver="GTiff",
        width=z.shape[1],
        height=z.shape[0],
        count=2,
        dtype="float32",
        crs="EPSG:32610",
        transform=from_origin(500_000.0, 5_000_000.0, a, a),
        nodata=nodata,
    )
    with rasterio.open(tif, "w", **profile) as dst:
        dst.write(np.where(np.isnan(z), nodata, z).astype(np.float32), 1)
        dst.write(np.where(np.isnan(sigma), nodata, sigma).astype(np.float32), 2)
    copy(tif, tmp_path / "survey.bag", driver="BAG")
    return tmp_path / "survey.bag"


def start_dask_cluster(directory: Path, workers: int = 2):
    """A real `dask scheduler` and single-threaded `dask worker` processes on loopback, the
    workers started in a working directory of their own (``directory/workers``: not the
    test's nor the job's, as on a cluster whose workers start elsewhere).

    Returns (address, scheduler process, worker processes)."""
    import json
    import subprocess
    import sys
    import time

    from distributed import Client

    sched_file = directory / "scheduler.json"
    bindir = Path(sys.executable).parent
    sched = subprocess.Popen(
        [
            bindir / "dask",
            "scheduler",
            "--host",
            "127.0.0.1",
            "--port",
            "0",
            "--no-dashboard",
            "--scheduler-file",
            sched_file,
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.time() + 60
    while not sched_file.exists() and time.time() < deadline:
        time.sleep(0.2)
    elsewhere = directory / "workers"
    elsewhere.mkdir(exist_ok=True)
    procs = [
        subprocess.Popen(
            [
                bindir / "dask",
                "worker",
                "--nthreads",
                "1",
                "--no-nanny",
                "--no-dashboard",
                "--scheduler-file",
                sched_file.resolve(),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            cwd=elsewhere,
        )
        for _ in range(workers)
    ]
    addr = json.loads(sched_file.read_text())["address"]
    with Client(addr, timeout=60) as c:
        c.wait_for_workers(workers, timeout=60)
    return addr, sched, procs


def stop_dask_cluster(sched, procs) -> None:
    """Workers first, then the scheduler (a worker whose scheduler went first keeps trying to
    reconnect); whatever has not stopped within seconds is killed."""
    for group in (procs, [sched]):
        for p in group:
            if p.poll() is None:
                p.terminate()
        for p in group:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


@pytest.fixture(scope="module")
def real_cluster(tmp_path_factory):
    """A real `dask scheduler` and two single-threaded `dask worker` processes on loopback."""
    import pipeline.runtime.cluster

    addr, sched, procs = start_dask_cluster(tmp_path_factory.mktemp("cluster"))
    yield addr
    pipeline.runtime.cluster.shutdown()  # the clients plan() opened, before their scheduler goes
    stop_dask_cluster(sched, procs)


@pytest.fixture(autouse=True)
def no_leaked_default_scheduler():
    """A test leaves dask's default scheduler as it found it: a client left as the default
    (a closed one, or one whose cluster is gone) would make every later in-process compute in
    this test process wait forever."""
    import dask

    before = dask.config.get("scheduler", None)
    yield
    from distributed.client import _global_clients

    after = dask.config.get("scheduler", None)
    live = [c for c in list(_global_clients.values()) if c.status != "closed"]
    assert after == before and not _global_clients, (
        f"the test left dask's default scheduler {after!r} (was {before!r}) and clients "
        f"{list(_global_clients.values())} ({len(live)} open)"
    )


SHM = Path("/dev/shm")


def orphaned_semaphores(names) -> set:
    """Those of the POSIX semaphores ``names`` (files ``/dev/shm/sem.*``) that no live process
    has open. An open named semaphore is a mapping of its file in ``/proc/PID/maps``, under the
    name glibc first gave the file (it links the final name after mapping it): matched by
    inode."""
    inodes = {}
    for n in names:
        try:
            inodes[os.stat(SHM / n).st_ino] = n
        except OSError:
            continue
    for maps in Path("/proc").glob("[0-9]*/maps"):
        try:
            lines = maps.read_text().splitlines()
        except OSError:  # the process ended, or is not ours to read
            continue
        for line in lines:
            fields = line.split(maxsplit=5)
            if len(fields) == 6 and fields[5].startswith(str(SHM) + "/"):
                inodes.pop(int(fields[4]), None)
        if not inodes:
            break
    return set(inodes.values())


@pytest.fixture
def killed_processes_semaphores_removed():
    """Removes the semaphores that processes this test kills with SIGKILL leave behind: the
    multiprocessing locks of a job's local cluster (their resource tracker dies with the job's
    process group) stayed in /dev/shm, 14 a run of the suite. Only those made during the test
    that no live process has open (a concurrent test's are)."""
    before = {p.name for p in SHM.glob("sem.*")} if SHM.is_dir() else set()
    yield
    if not SHM.is_dir():
        return
    for name in orphaned_semaphores({p.name for p in SHM.glob("sem.*")} - before):
        (SHM / name).unlink(missing_ok=True)
