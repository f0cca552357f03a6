"""Bad input and faults, as a user and an operator meet them: each case through the command
line (click's runner, in this process, or the installed console script) or the API, and the
assertion that it ends in one line naming the problem and a documented exit code (2 bad input,
3 the environment), never a traceback.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import zarr
from click.testing import CliRunner
from conftest import metric_dataarray, random_surface

import pipeline
from pipeline.cli import main

EXE = Path(sys.executable).parent / "pipeline"


def one_line_error(res, code: int, match: str) -> None:
    """The command failed with ``code`` and said so in one line containing ``match``."""
    out = res.stderr if hasattr(res, "stderr") and res.stderr is not None else res.output
    assert res.exit_code == code, (res.exit_code, out, getattr(res, "exception", None))
    lines = [ln for ln in out.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("error:")]
    assert len(errors) == 1, out
    assert "Traceback" not in out, out
    assert match in errors[0], (match, errors[0])


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


# ------------------------------------------------------------------ DEM files


def _nc(path, da):
    da.to_dataset(name=da.name or "elevation").to_netcdf(path)
    return path


def _good_tif(path):
    import rioxarray  # noqa: F401

    arr = metric_dataarray(random_surface((64, 64)), a=50.0).rio.write_crs("EPSG:32610")
    arr.rio.to_raster(path)
    return path


def _dem_file(kind, tmp: Path) -> Path:
    z = random_surface((20, 30))
    if kind == "missing":
        return tmp / "nope.tif"
    if kind == "empty tif":
        (tmp / "e.tif").write_bytes(b"")
        return tmp / "e.tif"
    if kind == "garbage tif":
        (tmp / "g.tif").write_bytes(b"not a tiff at all" * 10)
        return tmp / "g.tif"
    if kind == "truncated tif":
        p = _good_tif(tmp / "t.tif")
        data = p.read_bytes()
        p.write_bytes(data[: len(data) // 2])
        return p
    if kind == "garbage nc":
        (tmp / "g.nc").write_bytes(b"CDF\x01 broken" * 20)
        return tmp / "g.nc"
    if kind == "latitude beyond 90":
        da = xr.DataArray(
            z,
            dims=("lat", "lon"),
            coords={"lat": np.linspace(80, 99, 20), "lon": np.linspace(0, 3, 30)},
            name="elevation",
        )
        da["lat"].attrs.update(units="degrees_north", standard_name="latitude")
        da["lon"].attrs.update(units="degrees_east", standard_name="longitude")
        return _nc(tmp / "lat.nc", da)
    if kind == "time steps":
        da = xr.DataArray(np.stack([z, z]), dims=("time", "y", "x"), name="elevation")
        da = da.assign_coords(x=np.arange(30) * 50.0, y=np.arange(20) * 50.0)
        return _nc(tmp / "time.nc", da)
    if kind == "no coordinates":
        return _nc(tmp / "nocoords.nc", xr.DataArray(z, dims=("y", "x"), name="elevation"))
    if kind == "all no-data":
        return _nc(tmp / "nan.nc", metric_dataarray(np.full((20, 30), np.nan, np.float32)))
    if kind == "text values":
        da = metric_dataarray(np.full((20, 30), "x", dtype=object)).astype(str)
        return _nc(tmp / "text.nc", da.rename("elevation"))
    if kind == "unordered coordinates":
        da = metric_dataarray(z)
        x = da["x"].values.copy()
        x[[3, 4]] = x[[4, 3]]
        return _nc(tmp / "unordered.nc", da.assign_coords(x=x).rename("elevation"))
    if kind == "two variables":
        ds = xr.Dataset({"depth_a": metric_dataarray(z), "depth_b": metric_dataarray(z)})
        ds.to_netcdf(tmp / "two.nc")
        return tmp / "two.nc"
    if kind == "one cell":
        return _nc(tmp / "one.nc", metric_dataarray(z[:1, :1]).rename("elevation"))
    if kind == "folder, not a store":
        (tmp / "folder.zarr").mkdir()
        return tmp / "folder.zarr"
    if kind in ("rotated tif", "control points tif"):
        import rasterio
        from rasterio.control import GroundControlPoint
        from rasterio.transform import Affine

        p = tmp / f"{kind.split()[0]}.tif"
        opts = dict(driver="GTiff", height=20, width=30, count=1, dtype="float32", crs="EPSG:32610")
        if kind == "rotated tif":
            opts["transform"] = Affine(30.0, 5.0, 500_000.0, 3.0, -30.0, 5_000_000.0)
        else:
            opts["gcps"] = [
                GroundControlPoint(0, 0, 500_000, 5_000_000),
                GroundControlPoint(0, 29, 500_900, 5_000_100),
                GroundControlPoint(19, 0, 500_100, 4_999_400),
            ]
        with rasterio.open(p, "w", **opts) as dst:
            dst.write(z.astype("float32"), 1)
        return p
    if kind == "asc with fewer rows than its header":
        text = "ncols 30\nnrows 20\nxllcorner 0\nyllcorner 0\ncellsize 50\nNODATA_value -9999\n"
        text += "".join(" ".join(f"{v:.2f}" for v in row) + "\n" for row in z[:12])
        (tmp / "short.asc").write_text(text)
        return tmp / "short.asc"
    if kind == "unknown format":
        (tmp / "dem.txt").write_text("1 2 3\n")
        return tmp / "dem.txt"
    raise AssertionError(kind)


DEM_CASES = [
    ("missing", "does not exist"),
    ("empty tif", "cannot read DEM file"),
    ("garbage tif", "cannot read DEM file"),
    ("truncated tif", "cannot read DEM file"),
    ("garbage nc", "cannot read DEM file"),
    ("latitude beyond 90", "latitudes beyond"),
    ("time steps", "time"),
    ("no coordinates", "cell size"),
    ("all no-data", "no-data"),
    ("text values", "not numbers"),
    ("unordered coordinates", "not strictly increasing or decreasing"),
    ("two variables", "variable"),
    ("one cell", "2 x 2"),
    ("folder, not a store", "cannot read DEM file"),
    ("unknown format", "DEM"),
    ("rotated tif", "is rotated or skewed (its geotransform's rotation terms are 5 and 3)"),
    ("control points tif", "georeferenced by ground control points only"),
    ("asc with fewer rows than its header", "File short, can't read line 12"),
]


@pytest.mark.parametrize("kind, match", DEM_CASES, ids=[k for k, _ in DEM_CASES])
@pytest.mark.parametrize("command", ["import", "info"])
def test_bad_dem_files(tmp_path, kind, match, command):
    src = _dem_file(kind, tmp_path)
    if command == "import":
        res = invoke("dem", "import", src, tmp_path / "out.zarr", "--chunks", "16")
    else:
        res = invoke("dem", "info", src)
    one_line_error(res, 2, match)
    assert not (tmp_path / "out.zarr").exists()
    if kind.endswith("tif") and kind in ("rotated tif", "control points tif"):
        # a cell size given in place of the grid's own coordinates is no way round it
        res = invoke("dem", "import", src, tmp_path / "out.zarr", "--cell-size", "30")
        one_line_error(res, 2, match)


# ------------------------------------------------------------------ job files

SYN = "[dem.synthetic]\nshape = [40, 40]\n"


def _job_text(case: str) -> str:
    """A job file with one defect (top-level keys first, arrays of tables last)."""
    top, tables, missions = "", SYN, ""
    kind, _, value = case.partition(":")
    if kind == "top":
        top = value
    elif kind == "tables":
        tables = value
    elif kind == "extra":
        tables = SYN + value
    elif kind == "mission":
        missions = "[[missions]]\n" + value
    elif kind == "raw":
        return value
    return f"{top}\n{tables}\n{missions}"


M = "start = [1, 2]\ngoal = [3, 4]\n"
JOB_CASES = [
    ("top:planners = 1", "unknown key 'planners'"),
    ("top:name = 3", "name must be"),
    ('top:name = "job\\u0000nul"', "no control characters"),
    ('top:name = "bell\\u0007"', "no control characters"),
    ("tables:name = 'x'", r"a [dem] table is required"),
    ("tables:[dem]\npath = 'a.tif'\n[dem.synthetic]\nshape = [4, 4]", "exactly one of"),
    ("tables:[dem]\ncolour = 1\n[dem.synthetic]\nshape = [4, 4]", "unknown key dem.'colour'"),
    ("tables:[dem.synthetic]\ncell_size = 3.0", "shape is required"),
    ("tables:[dem.synthetic]\nshape = [4]", "dem.synthetic.shape must be a pair"),
    ("tables:[dem.synthetic]\nshape = [1, 1]", "dem.synthetic.shape[0] (rows) must be"),
    ("tables:[dem.synthetic]\nshape = ['a', 'b']", "dem.synthetic.shape[0] (rows) must be"),
    ("tables:[dem.synthetic]\nshape = [40, 40]\ncell_size = -30", "cell_size must be"),
    ("tables:[dem.synthetic]\nshape = [40, 40]\ncell_size = 0", "cell_size must be"),
    ("tables:[dem.synthetic]\nshape = [40, 40]\nislands = 99", "islands must be an integer"),
    ("tables:[dem.synthetic]\nshape = [40, 40]\nseed = -1", "seed must be an integer >= 0"),
    ("tables:[dem.synthetic]\nshape = [40, 40]\nseed = 'x'", "seed must be an integer"),
    ("tables:[dem.synthetic]\nshape = [40, 40]\nsed = 1", "unknown key dem.synthetic.'sed'"),
    ("tables:[dem]\nchunks = 0\n[dem.synthetic]\nshape = [4, 4]", "dem.chunks must be"),
    ("tables:[dem]\nchunks = 1.5\n[dem.synthetic]\nshape = [4, 4]", "dem.chunks must be"),
    ("tables:[dem]\npath = 'missing.tif'", "dem.path 'missing.tif' does not exist"),
    ("tables:[dem]\npath = 3", "dem.path must be a file path"),
    ("tables:[dem]\npath = '.'\nresolution = -1.0", "dem.resolution must be"),
    ("tables:[dem]\npath = '.'\ncell_size = 'big'", "dem.cell_size must be"),
    ("tables:[dem]\npath = '.'\nbbox = [1, 2, 3]", "dem.bbox must be four finite numbers"),
    ("tables:[dem]\npath = '.'\nbbox_xy = [5, 0, 1, 1]", "each minimum below its maximum"),
    (
        "tables:[dem]\npath = '.'\nbbox = [-10, 40, -9, 95]",
        "dem.bbox [-10.0, 40.0, -9.0, 95.0] is not [lon_min, lat_min, lon_max, lat_max]",
    ),
    (
        "tables:[dem]\npath = '.'\nbbox = [0, 0, 1, 1]\nbbox_xy = [0, 0, 1, 1]",
        "one of dem.bbox (longitude, latitude) and dem.bbox_xy, not both",
    ),
    (
        "tables:[dem]\nbbox = [0, 0, 1, 1]\n[dem.synthetic]\nshape = [4, 4]",
        "dem.bbox selects a region of a DEM file",
    ),
    ("tables:[dem]\npath = '.'\nuncertainty_k = -1", "dem.uncertainty_k must be"),
    ("tables:[dem]\npath = '.'\nuncertainty_k = 'two'", "dem.uncertainty_k must be"),
    (
        "tables:[dem]\nuncertainty_k = 2\n[dem.synthetic]\nshape = [4, 4]",
        "dem.uncertainty_k reads a survey's uncertainty band from a DEM file",
    ),
    ("extra:[maps]\nmethod = 'round'", "maps.method must be"),
    ("extra:[maps]\nclearance = 0", "maps.clearance must be a finite number of metres > 0"),
    ("extra:[maps]\nclearance = -5", "maps.clearance must be"),
    ("extra:[maps]\nclearance = '300'", "maps.clearance must be"),
    ("extra:[maps]\nclearance = nan", "maps.clearance must be"),
    ("extra:[maps]\nclearance = inf", "maps.clearance must be"),
    ("extra:[maps]\nclearance = 10.0", "smaller than half a cell"),
    ("extra:[maps]\nhorizontal_clearance = 0", "maps.horizontal_clearance must be"),
    ("extra:[maps]\nsurface_clearance = -1", "maps.surface_clearance must be"),
    ("extra:[maps]\nsea_level = nan", "maps.sea_level must be"),
    ("extra:[maps]\nmin_accumulation = 0", "maps.min_accumulation must be"),
    ("extra:[maps]\nmin_accumulation = 2.5", "maps.min_accumulation must be an integer"),
    ("extra:[maps]\nradius = 3", "unknown key maps.'radius'"),
    ("extra:[maps]\nlandmarks = -1", "maps.landmarks must be an integer from 0 to 64"),
    ("extra:[maps]\nlandmarks = 2.5", "maps.landmarks must be an integer"),
    ("extra:[planning]\nrepair_max_cells = -5", "planning.repair_max_cells must be an integer"),
    ("extra:[planning]\nomega = 0.5", "planning.omega must be a finite number >= 1"),
    ("extra:[planning]\nomega = nan", "planning.omega must be"),
    ("extra:[planning]\nomega = inf", "planning.omega must be"),
    ("extra:[planning]\nplanner = 'rrt'", "planning.planner must be 'dijkstra'"),
    ("extra:[planning]\ncoarse_planner = 'rrt'", "planning.coarse_planner must be"),
    (
        "extra:[planning]\ncoarse_weight = 0.5",
        "planning.coarse_weight must be a finite number >= 1",
    ),
    ("extra:[planning]\nmcpc = 'yes'", "planning.mcpc must be true or false"),
    ("extra:[planning]\nrho = 0", "planning.rho must be an integer >= 1"),
    ("extra:[planning]\nsection_size = 1", "planning.section_size must be"),
    ("extra:[planning]\nmargin = -1", "planning.margin must be"),
    ("extra:[output]\ncatalog = 3", "output.catalog must be"),
    ("extra:[output]\nbucket = 'x'", "unknown key output.'bucket'"),
    ("extra:[output]\nquicklooks = 'yes'", "output.quicklooks must be true or false"),
    (
        "extra:[output]\nperformance_report = 1",
        "output.performance_report must be true or false",
    ),
    (
        "extra:[vehicle]\nmax_pitch_deg = 95",
        "vehicle.max_pitch_deg must be a finite number of degrees above 0 and at most 89, got 95",
    ),
    ("extra:[vehicle]\nbattery_wh = 100", "without a power"),
    ("extra:[vehicle]\nspeed = 2", "unknown key vehicle.'speed'"),
    ("extra:[vehicle]\nspeed_m_s = 0", "vehicle.speed_m_s must be"),
    ("extra:[vehicle]\nmin_turn_radius_m = 'wide'", "vehicle.min_turn_radius_m must be"),
    ("extra:[vehicle]\nwaypoint_band_m = -1", "vehicle.waypoint_band_m must be"),
    ("top:vehicle = 3", "vehicle must be a table"),
    ("mission:" + M + "vehicle = 3", "missions[0].vehicle must be a table"),
    ("mission:" + M + "vehicle = { pitch = 10 }", "unknown key missions[0].vehicle.'pitch'"),
    ("mission:" + M + "vehicle = { battery_wh = 50.0 }", "without a power"),
    ("top:missions = 3", "missions must be an array of tables"),
    ("mission:start = [1, 2]", "needs exactly one of goal"),
    ("mission:start = [1, 2]\nstart_xy = [1.0, 2.0]\ngoal = [3, 4]", "needs exactly one"),
    ("mission:start = [1.5, 2]\ngoal = [3, 4]", r"start must be [row, col]"),
    ("mission:start_xy = [nan, 1.0]\ngoal = [3, 4]", "start_xy must be a finite number"),
    ("mission:start_xy = [inf, 1.0]\ngoal = [3, 4]", "start_xy must be a finite number"),
    ("mission:start_lonlat = [0.0, 95.0]\ngoal = [3, 4]", "start_lonlat must be"),
    ("mission:start_lonlat = [400.0, 0.0]\ngoal = [3, 4]", "start_lonlat must be"),
    ("mission:" + M + "speed = 3", r"unknown key missions[0].'speed'"),
    ("mission:" + M + "omega = 0", "missions[0].omega must be"),
    ("mission:" + M + "planner = 'bfs'", "missions[0].planner must be"),
    ("mission:name = ''\n" + M, "name must be a non-empty string"),
    ("mission:name = 'a'\n" + M + "[[missions]]\nname = 'a'\n" + M, "used twice"),
    ("raw:[dem.synthetic\nshape = [4, 4]", "not valid TOML"),
]


@pytest.mark.parametrize("case, match", JOB_CASES, ids=[str(i) for i in range(len(JOB_CASES))])
def test_bad_job_files_dry_run(tmp_path, case, match):
    job = tmp_path / "job.toml"
    job.write_text(_job_text(case))
    one_line_error(invoke("run", job, "--dry-run"), 2, match)
    assert not (tmp_path / "catalogs").exists()


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda p: p.write_bytes(b"name = '\xff\xfe'\n"), "is not UTF-8"),
        (lambda p: p.mkdir(), "is a directory, not a file"),
        (lambda p: None, "does not exist"),
        (lambda p: os.mkfifo(p), "is not a regular file (a device, a pipe or a socket)"),
    ],
    ids=["not UTF-8", "a directory", "missing", "a FIFO (never opened: it would block)"],
)
def test_unreadable_job_files(tmp_path, make, match):
    job = tmp_path / "job.toml"
    make(job)
    one_line_error(invoke("run", job), 2, match)


def test_a_device_is_not_a_job_file_and_a_byte_order_mark_is_read(tmp_path):
    one_line_error(invoke("run", "/dev/null"), 2, "is not a regular file")
    job = tmp_path / "bom.toml"
    job.write_bytes(b"\xef\xbb\xbf" + f"name = 'bom'\n{SYN}".encode())
    res = invoke("run", job, "--dry-run")
    assert res.exit_code == 0, res.output
    from pipeline.jobs.job_file import load_job

    assert load_job(job).name == "bom"


# ------------------------------------------------------------------ command-line flags


@pytest.fixture
def small_job(tmp_path):
    job = tmp_path / "job.toml"
    job.write_text(f"{SYN}\n[output]\ncatalog = 'cat'\n")
    return job


def test_scheduler_flags(tmp_path, small_job, monkeypatch):
    monkeypatch.setenv("AUV_PIPELINE_CONNECT_TIMEOUT_S", "2")
    cases = [
        (["--scheduler", "tcp://127.0.0.1:1"], 3, "cannot reach the dask scheduler"),
        (["--scheduler", "not an address"], 3, "is not a dask scheduler address"),
        (["--scheduler-file", tmp_path / "none.json"], 3, "cannot read the scheduler address"),
        (["--scheduler-file", small_job], 3, "cannot read the scheduler address"),
    ]
    (tmp_path / "noaddr.json").write_text(json.dumps({"address": 5}))
    cases.append((["--scheduler-file", tmp_path / "noaddr.json"], 3, "holds no scheduler"))
    for flags, code, match in cases:
        one_line_error(invoke("run", small_job, *flags), code, match)
    res = invoke("run", small_job, "--scheduler", "a", "--scheduler-file", "b")
    assert res.exit_code == 2 and "not both" in res.output


@pytest.mark.parametrize(
    "args, match",
    [
        (["dem", "synth", "{t}/s.zarr", "--shape", "0", "5"], "shape[0] (rows)"),
        (["dem", "synth", "{t}/s.zarr", "--cell-size", "-30"], "`cell_size` must be"),
        (["dem", "synth", "{t}/s.zarr", "--islands", "99"], "`islands` must be"),
        (["dem", "synth", "{t}/s.zarr", "--chunks", "0"], "`chunks[0]` must be"),
        (["build-maps", "{t}/none.zarr", "{t}/m.zarr"], "does not exist"),
        (["build-maps", "{t}/dem.zarr", "{t}/m.zarr", "--clearance", "-1"], "clearance"),
        (["build-maps", "{t}/dem.zarr", "{t}/m.zarr", "--clearance", "5"], "half a cell"),
        (["build-maps", "{t}/dem.zarr", "{t}/m.zarr", "--min-accumulation", "0"], "min_acc"),
        (["build-maps", "{t}/dem.zarr", "{t}/m.zarr", "--landmarks", "-1"], "landmarks"),
        (["build-maps", "{t}/dem.zarr", "{t}/m.zarr", "--landmarks", "65"], "landmarks"),
        (["build-maps", "{t}/dem.zarr", "{t}/dem.zarr"], "exists already"),
        (["build-maps", "{t}/dem.zarr", "{t}/m.zarr", "--clearance", "1e7"], "needs about"),
        (["verify", "{t}/none", "--dem", "{t}/dem.zarr"], "does not exist: give a mission"),
        (["verify", "{t}", "--dem", "{t}/dem.zarr"], "holds no mission"),
        (["verify", "{t}/dem.zarr/zarr.json", "--dem", "{t}/dem.zarr"], "neither a mission"),
        (["verify", "{t}", "--dem", "{t}/none.tif"], "DEM file"),
        (["verify", "{t}", "--dem", "{t}/dem.zarr", "--method", "diagonal"], "diagonal"),
    ],
)
def test_bad_cli_arguments(tmp_path, args, match):
    pipeline.write_dem(pipeline.synthetic_dem((40, 40), chunks=None), tmp_path / "dem.zarr")
    res = invoke(*[a.format(t=tmp_path) for a in args])
    one_line_error(res, 2, match)
    assert not (tmp_path / "m.zarr").exists()
    # reported before a cluster is started (its workers took seconds to start first)
    assert "building" not in res.output, res.output


# ------------------------------------------------------------------ the environment


def test_catalog_path_is_a_file_or_unwritable(tmp_path):
    (tmp_path / "file").write_text("x")
    for catalog, match in [
        (tmp_path / "file", "a file stands where a directory is needed"),
        (tmp_path / "file" / "sub", "a path component is a file, not a directory"),
        ("/proc/auv-catalog", "no such file or directory"),
    ]:
        job = tmp_path / "job.toml"
        job.write_text(f"{SYN}\n[output]\ncatalog = '{catalog}'\n")
        one_line_error(invoke("run", job), 3, match)
        if "file" in str(catalog):  # the dry run says so too (it said "valid")
            one_line_error(invoke("run", job, "--dry-run"), 3, match)


def test_output_store_under_a_file_is_an_environment_error(tmp_path):
    (tmp_path / "file").write_text("x")
    res = invoke("dem", "synth", tmp_path / "file" / "s.zarr", "--shape", "20", "20")
    one_line_error(res, 3, "a file stands where a directory is needed")


def test_a_full_disk_is_one_line_and_exit_3(tmp_path):
    """A file-size limit stands in for a full disk (the writes fail with an OSError as they
    do when the disk fills; Python ignores SIGXFSZ)."""
    import resource

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))

    proc = subprocess.run(
        [str(EXE), "dem", "synth", str(tmp_path / "s.zarr"), "--shape", "600", "600"],
        capture_output=True,
        text=True,
        timeout=300,
        preexec_fn=limit,
    )
    assert proc.returncode == 3, proc.stderr
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1].startswith("error: file too large")
    assert not (tmp_path / "s.zarr").exists()


def test_a_full_disk_while_building_maps_is_one_line_and_exit_3(tmp_path):
    """The same during `build-maps`, whose tasks write the scratch tiles and the layers' shards
    themselves: the one line names the full disk (numpy's own file writes said only "N
    requested and M written"), and the worker whose task failed adds no traceback."""
    import resource

    res = invoke("dem", "synth", tmp_path / "dem.zarr", "--shape", "600", "600")
    assert res.exit_code == 0, res.output

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))

    proc = subprocess.run(
        [str(EXE), "build-maps", str(tmp_path / "dem.zarr"), str(tmp_path / "maps.zarr")],
        capture_output=True,
        text=True,
        timeout=300,
        preexec_fn=limit,
    )
    assert proc.returncode == 3, proc.stderr
    assert proc.stderr.strip().splitlines()[-1].startswith("error: file too large")
    # the failed task's traceback, which its worker logs too, is not on stderr
    # (pipeline.runtime.quiet)
    assert "Traceback" not in proc.stderr and "Compute Failed" not in proc.stderr, proc.stderr
    assert not (tmp_path / "maps.zarr").exists()


# ------------------------------------------------------------------ store tampering


@pytest.fixture(scope="module")
def built_store(tmp_path_factory):
    path = tmp_path_factory.mktemp("tamper") / "maps.zarr"
    import dask

    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(
            pipeline.synthetic_dem((60, 60), chunks=32, islands=0), path, clearance=90.0
        )
    return path


def _tamper_attr(store, key, value):
    g = zarr.open_group(store, mode="r+")
    g.attrs[key] = value


def _tamper_params(store):
    g = zarr.open_group(store, mode="r+")
    p = json.loads(g.attrs["parameters"])
    p["clearance_m"] = 10.0
    g.attrs["parameters"] = json.dumps(p)


TAMPER = [
    (lambda s: _tamper_attr(s, "cell_size", 31.0), "damaged: its attributes"),
    (lambda s: _tamper_params(s), "damaged: its attributes"),
    (lambda s: _tamper_attr(s, "maps_version", 99), "not a maps store of this version"),
    (lambda s: shutil.rmtree(s / "ridge"), "damaged: it is incomplete"),
    (lambda s: os.remove(s / "zarr.json"), "is not a Zarr store"),
    (lambda s: os.remove(s / "safety" / "c" / "0" / "1"), "chunk (0, 1) of its layer 'safety'"),
    (
        lambda s: (s / "safety" / "c" / "0" / "1").write_bytes(b"\x00" * 40),
        "chunk c/0/1 of its layer 'safety' cannot be decoded",
    ),
    (lambda s: _tamper_attr(s, "landmarks", "[[1, 2]]"), "damaged: its attributes"),
    (lambda s: shutil.rmtree(s / "landmark_distance"), "damaged: its landmark layers"),
    (
        lambda s: os.remove(s / "landmark_distance" / "c" / "3" / "0" / "0"),
        "chunk (3, 0, 0) of its layer 'landmark_distance'",
    ),
]


@pytest.mark.parametrize("tamper, match", TAMPER, ids=[m for _, m in TAMPER])
def test_tampered_stores_are_refused(tmp_path, built_store, tamper, match):
    store = tmp_path / "maps.zarr"
    shutil.copytree(built_store, store)
    tamper(store)
    with pytest.raises(pipeline.PipelineError, match=match.replace("(", r"\(").replace(")", r"\)")):
        pipeline.plan(store, (5, 5), (50, 50), planner="astar", mcpc=False, client="synchronous")


OPENED = [(t, m) for t, m in TAMPER if "chunk" not in m]  # (a chunk is met when it is read)


@pytest.mark.parametrize("tamper, match", OPENED, ids=[m for _, m in OPENED])
def test_open_maps_refuses_what_planning_refuses(tmp_path, built_store, tamper, match):
    """The Dataset view checks the store as the planners' handle does (one owner of what a
    valid maps store is): a store changed after its build is refused when it is opened."""
    store = tmp_path / "maps.zarr"
    shutil.copytree(built_store, store)
    tamper(store)
    with pytest.raises(pipeline.PipelineError, match=match):
        pipeline.open_maps(store)


def test_a_dem_store_given_as_maps_says_so(tmp_path):
    """A DEM store (write_dem, `pipeline dem import`) given where a maps store goes: it says
    which it is and what to do (it said "not a maps store of this version ... rebuild it")."""
    dem = pipeline.synthetic_dem((40, 40), cell_size=30.0, seed=1, chunks=None)
    path = pipeline.write_dem(dem, tmp_path / "dem.zarr")
    for call in (
        lambda: pipeline.plan(path, (1, 1), (30, 30), client="synchronous"),
        lambda: pipeline.open_maps(path),
    ):
        with pytest.raises(pipeline.PipelineError, match="is a DEM store, not a maps store"):
            call()


def test_an_untampered_copy_plans(tmp_path, built_store):
    store = tmp_path / "maps.zarr"
    shutil.copytree(built_store, store)
    t = pipeline.plan(store, (5, 5), (50, 50), planner="astar", mcpc=False, client="synchronous")
    assert t.status == "ok"


# ------------------------------------------------------------------ API arguments


def _tiny_window(**kwargs):
    args = {"cell_size": 30.0, **kwargs}
    grid = np.zeros((3, 3))
    return pipeline.plan_window(grid, grid, grid == 0, (0, 0), (2, 2), **args)


API = [
    (lambda: pipeline.synthetic_dem((10, 10), islands=11), "`islands` must be"),
    (lambda: pipeline.synthetic_dem((10, 10), seed=-1), "`seed` must be"),
    (lambda: pipeline.synthetic_dem((1, 10)), r"`shape[0] (rows)` must be"),
    (
        lambda: pipeline.safety_map(pipeline.synthetic_dem((10, 10), chunks=None), method="cube"),
        "`method` must be",
    ),
    (
        lambda: pipeline.safety_map(
            pipeline.synthetic_dem((50, 50), chunks=None, cell_size=1.0), clearance=1e6
        ),
        "needs about",
    ),
    (lambda: _tiny_window(omega=float("inf")), "`omega` must be"),
    (lambda: _tiny_window(cell_size=float("nan")), "`cell_size` must be"),
    (lambda: pipeline.plan_missions("/nonexistent.zarr", []), "does not exist"),
    (lambda: pipeline.open_store(42), "`maps` must be"),
    (
        lambda: pipeline.runtime.cluster.get_client(3.5),
        "`client` must be None, 'synchronous', 'threads',",
    ),
]


@pytest.mark.parametrize("call, match", API, ids=[m for _, m in API])
def test_bad_api_arguments(call, match):
    import re

    with pytest.raises(pipeline.PipelineError, match=re.escape(match)):
        call()


def test_a_client_that_is_no_address_is_one_line_at_once(built_store):
    """A misspelt client (``"thread"``) is refused before any dask Client is made: a Client
    refused for its address stayed half made, and the process waited 60 s at exit to print a
    traceback from closing it."""
    import time

    code = (
        "import pipeline\n"
        "try:\n"
        f"    pipeline.plan({str(built_store)!r}, (5, 5), (50, 50), client='thread')\n"
        "except pipeline.PipelineError as e:\n"
        "    print(e)\n"
    )
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert time.perf_counter() - t0 < 30
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stdout.startswith("'thread' is not a dask scheduler address"), proc.stdout
    assert proc.stdout.count("\n") == 1


@pytest.mark.parametrize(
    "form, value, match",
    [
        ("xy", [float("nan"), 1.0], "start_xy must be a pair of finite numbers"),
        ("xy", [float("inf"), 1.0], "start_xy must be a pair of finite numbers"),
        ("xy", ["a", 1.0], "start_xy must be a pair of finite numbers"),
        ("lonlat", [0.0, 95.0], "is not a longitude and latitude"),
        ("xy", [-1e9, 0.0], "off the map"),
    ],
)
def test_mission_coordinates_through_the_api(built_store, form, value, match):
    store = pipeline.open_store(built_store)
    with pytest.raises(pipeline.PipelineError, match=match):
        store.cell_of("start", form, value)


# ------------------------------------------------------------------ only what the tool made


def test_overwrite_replaces_only_a_store_the_tool_wrote(tmp_path, monkeypatch):
    """``--overwrite`` replaces a DEM or maps store this tool wrote (its zarr.json says so) and
    refuses, in one line, a user's folder, a plain file, another program's Zarr store or a store
    of the other kind; what was there is untouched."""
    dem = tmp_path / "dem.zarr"
    assert invoke("dem", "synth", dem, "--shape", "40", "40").exit_code == 0
    tif = _good_tif(tmp_path / "in.tif")
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "a.jpg").write_bytes(b"jpeg")
    notes = tmp_path / "notes.txt"
    notes.write_text("mine")
    other = tmp_path / "other.zarr"
    zarr.open_group(other, mode="w", zarr_format=3).attrs["made_by"] = "another program"
    cases = [
        (("build-maps", dem, photos, "--clearance", "100", "--overwrite"), "not a maps store"),
        (("dem", "import", tif, notes, "--overwrite"), "not a DEM store"),
        (("dem", "synth", photos, "--shape", "20", "20", "--overwrite"), "not a DEM store"),
        (("dem", "synth", other, "--shape", "20", "20", "--overwrite"), "not a DEM store"),
        (("build-maps", dem, dem, "--clearance", "100", "--overwrite"), "not a maps store"),
    ]
    for args, match in cases:
        one_line_error(invoke(*args), 2, match)
    monkeypatch.chdir(photos)
    one_line_error(
        invoke("dem", "synth", ".", "--shape", "20", "20", "--overwrite"), 2, "not a DEM"
    )
    assert (photos / "a.jpg").read_bytes() == b"jpeg" and notes.read_text() == "mine"
    assert sorted(p.name for p in photos.iterdir()) == ["a.jpg"]
    assert dict(zarr.open_group(other, mode="r").attrs) == {"made_by": "another program"}
    assert pipeline.open_dem(dem).shape == (40, 40)
    # its own stores are replaced
    maps = tmp_path / "maps.zarr"
    for _ in range(2):
        res = invoke("build-maps", dem, maps, "--clearance", "100", "--overwrite")
        assert res.exit_code == 0, res.output
    res = invoke("dem", "synth", dem, "--shape", "30", "30", "--overwrite")
    assert res.exit_code == 0 and pipeline.open_dem(dem).shape == (30, 30)


def test_a_catalog_is_never_a_folder_of_other_files(tmp_path):
    """``[output] catalog = ""`` (the job's own folder) or any folder holding files a run does
    not write is refused at the dry run, before anything is written or removed."""
    for catalog in ["", ".", "photos"]:
        folder = tmp_path / catalog
        folder.mkdir(exist_ok=True)
        (folder / "index.html").write_text("my page")
        (folder / ".notes.tmp-1").write_text("mine")
        if catalog == "photos":
            (folder / "a.jpg").write_bytes(b"jpeg")
        job = tmp_path / "job.toml"
        job.write_text(f"{SYN}\n[output]\ncatalog = '{catalog}'\n")
        for args in (("run", job, "--dry-run"), ("run", job)):
            one_line_error(invoke(*args), 2, "is a folder with other files")
        assert (folder / "index.html").read_text() == "my page"
        assert (folder / ".notes.tmp-1").read_text() == "mine"
        assert not (folder / ".lock").exists() and not (folder / "catalog.json").exists()


def test_two_jobs_never_share_a_catalog(tmp_path, local_client):
    """A second job naming a catalog that holds another job's missions is refused: each run
    would otherwise rewrite catalog.json and the missions table with its own missions only."""
    one = tmp_path / "one.toml"
    one.write_text(
        f"name = 'one'\n{SYN}[maps]\nclearance = 100.0\n[output]\ncatalog = 'cat'\n"
        "performance_report = false\n"
    )
    assert pipeline.run_job(one, scheduler=local_client).ok
    before = (tmp_path / "cat" / "catalog.json").read_text()
    two = tmp_path / "two.toml"
    two.write_text(one.read_text().replace("name = 'one'", "name = 'two'"))
    for args in (("run", two, "--dry-run"), ("run", two)):
        one_line_error(invoke(*args), 2, "holds the missions of job 'one'")
    assert (tmp_path / "cat" / "catalog.json").read_text() == before
    assert pipeline.run_job(one, scheduler=local_client).ok  # its own job still runs


def test_two_mission_names_of_one_folder_are_refused(tmp_path):
    from pipeline.outputs.catalog import mission_id

    for a, b in [("a b", mission_id("a b")), ("Deep", "deep")]:
        job = tmp_path / "job.toml"
        job.write_text(
            f'{SYN}\n[[missions]]\nname = "{a}"\nstart = [1, 1]\ngoal = [30, 30]\n'
            f'[[missions]]\nname = "{b}"\nstart = [1, 1]\ngoal = [30, 30]\n'
        )
        one_line_error(invoke("run", job, "--dry-run"), 2, "would share the folder and Item id")


# ------------------------------------------------------------------ never a hang, never raw


def test_a_port_that_answers_but_is_no_scheduler_is_one_line_not_a_hang(tmp_path, small_job):
    """An HTTP server (as the dashboard's port is) at the scheduler address: one line, exit 3,
    in seconds (the client waited on it for ever); a FIFO as the scheduler file or as the DEM
    is named, never opened (its read would block)."""
    import threading
    import time
    from http.server import HTTPServer, SimpleHTTPRequestHandler

    server = HTTPServer(("127.0.0.1", 0), SimpleHTTPRequestHandler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        t0 = time.monotonic()
        res = invoke("run", small_job, "--scheduler", f"tcp://127.0.0.1:{server.server_port}")
        one_line_error(res, 3, "answers but is not a dask scheduler")
        assert time.monotonic() - t0 < 30
    finally:
        server.shutdown()
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    one_line_error(invoke("run", small_job, "--scheduler-file", fifo), 3, "not a regular file")
    one_line_error(invoke("dem", "info", fifo), 2, "not a regular file")
    job = tmp_path / "fifo-dem.toml"
    job.write_text("[dem]\npath = 'fifo'\n")
    one_line_error(invoke("run", job, "--dry-run"), 2, "not a regular file")


@pytest.mark.parametrize(
    "args, match",
    [
        (["run"], "Missing argument 'JOB'. (see `"),
        (["run"], " run --help`)"),
        (["run", "{job}", "--bogus"], "No such option '--bogus'"),
        (["build-maps", "a", "b", "--clearance", "abc"], "'abc' is not a valid float"),
        (["nonsense"], "No such command 'nonsense'"),
        (["dem", "synth"], "Missing argument 'OUT'"),
        (["run", "{job}", "--dashboard-address", "nonsense"], "dashboard address 'nonsense'"),
        (["run", "{job}", "--dashboard-address", ":99999"], "must be PORT, :PORT or HOST:PORT"),
        (["run", "{job}", "--workers", "1000"], "1000 local workers: this machine holds at most"),
        (["run", "{job}", "--dry-run", "--workers", "1000"], "give at most"),
        (["build-maps", "a", "b", "--workers", "1000"], "1000 local workers"),
        (["dem", "info", "http://example.org/dem.tif"], "is a URL: DEMs are read from local"),
        (["dem", "import", "s3://bucket/dem.tif", "{t}/o.zarr"], "is a URL"),
    ],
)
def test_usage_errors_are_one_line(tmp_path, small_job, args, match):
    """click's own errors (a missing argument, an unknown option or command, a bad value) are
    one line naming the command's help, as every other error, with exit code 2."""
    res = invoke(*[a.format(job=small_job, t=tmp_path) for a in args])
    one_line_error(res, 2, match)


@pytest.mark.parametrize(
    "var, value",
    [
        ("AUV_PIPELINE_CONNECT_TIMEOUT_S", "soon"),
        ("AUV_PIPELINE_CONNECT_TIMEOUT_S", "-1"),
        ("AUV_PIPELINE_CHUNK_CACHE_MB", "lots"),
        ("AUV_PIPELINE_CHUNK_CACHE_MB", "1.5"),
    ],
)
def test_a_bad_environment_variable_is_one_line_naming_it(tmp_path, small_job, var, value):
    """Through the installed console script (a variable read at import time would fail before
    the command's error handling), as the command starts: before any work (no catalog made,
    no cluster started)."""
    env = {**os.environ, var: value}
    args = ["run", str(small_job)]
    if var == "AUV_PIPELINE_CONNECT_TIMEOUT_S":
        args += ["--scheduler", "tcp://127.0.0.1:1"]
    else:  # read by the first store read: the maps of a job with a mission
        small_job.write_text(
            small_job.read_text() + "[[missions]]\nstart = [2, 2]\ngoal = [30, 30]\n"
        )
    proc = subprocess.run([str(EXE), *args], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1].startswith(f"error: the environment variable {var}")
    assert not (small_job.parent / "cat").exists()


def test_a_bare_array_is_not_a_dem():
    with pytest.raises(pipeline.PipelineError, match="not a numpy.ndarray; wrap an array"):
        pipeline.build_maps(np.zeros((10, 10)), "unused.zarr")
    with pytest.raises(pipeline.PipelineError, match="not a builtins.list"):
        pipeline.open_dem([[1.0, 2.0]])


def test_a_map_two_cells_thin_plans_and_draws_its_quicklook(tmp_path):
    """A 2 x 1000 grid (a survey line): planned, flown and drawn (the shading's slopes needed
    two cells a side of the thinned picture, and the mission was recorded failed)."""
    from pipeline.flight.fly import with_flight
    from pipeline.outputs.plots import mission_quicklook, shaded_relief

    z = np.full((2, 1000), -3000.0, np.float32)
    z[:, 500:510] = -2900.0
    da = metric_dataarray(z, a=100.0)
    store = tmp_path / "m.zarr"
    pipeline.build_maps(da, store, clearance=100.0, landmarks=2)
    t = pipeline.plan(store, (0, 5), (1, 990), client="synchronous")
    assert t.status == "ok", t.message
    with_flight(store, t)
    png = tmp_path / "ql.png"
    mission_quicklook(pipeline.open_store(store), t, png, title="line", crs_wkt=None)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rgb, _, _ = shaded_relief(np.linspace(-10, 0, 7)[None, :], 100.0)
    assert rgb.shape == (1, 7, 4) and np.isfinite(rgb).all()


def test_a_damaged_dem_store_names_its_chunk(tmp_path):
    """A DEM store written by this tool records the chunks it left unstored (all no-data): one
    of those reads as no-data, any other found missing is damage named at once (it was planned
    on as a no-data hole); a chunk that cannot be decoded is named too (exit 4 before)."""
    z = random_surface((48, 48)).astype(np.float32) - 3000.0
    z[:16, :16] = np.nan  # one whole chunk of no-data: not stored, and not damage
    dem = tmp_path / "dem.zarr"
    src = tmp_path / "in.nc"
    _nc(src, metric_dataarray(z).rename("elevation"))
    assert invoke("dem", "import", src, dem, "--chunks", "16").exit_code == 0
    chunks = dem / "elevation" / "c"
    assert not (chunks / "0" / "0").exists() and (chunks / "1" / "1").exists()
    read = pipeline.open_dem(dem).values
    assert np.isnan(read[:16, :16]).all() and np.isfinite(read[16:, 16:]).all()
    good = tmp_path / "good.zarr"
    shutil.copytree(dem, good)
    (chunks / "1" / "2").unlink()
    one_line_error(
        invoke("dem", "info", dem), 2, "is damaged: chunk c/1/2 of its elevation is missing"
    )
    res = invoke("build-maps", dem, tmp_path / "m.zarr", "--clearance", "100")
    one_line_error(res, 2, "chunk c/1/2 of its elevation is missing (it held data)")
    shutil.rmtree(dem)
    shutil.copytree(good, dem)
    (chunks / "2" / "0").write_bytes(b"\x00not a chunk" * 20)
    res = invoke("build-maps", dem, tmp_path / "m.zarr", "--clearance", "100")
    one_line_error(res, 2, "chunk c/2/0 of its elevation cannot be decoded")
    assert not (tmp_path / "m.zarr").exists()


def test_a_grid_the_run_cannot_carry_is_refused_at_the_dry_run(tmp_path):
    """Too many chunks (a task each, per layer and pass) or stores larger than the disk even
    compressed: one line with the estimate at the dry run, before anything is written."""
    free = shutil.disk_usage(tmp_path).free
    side = int(math.sqrt(free / (22 + 4 * 8) * 4 * 2)) + 1  # twice the disk, compressed 4x
    cases = [
        ("[dem]\nchunks = 2\n[dem.synthetic]\nshape = [300, 300]\n", "into 22,500 chunks"),
        ("[dem.synthetic]\nshape = [200000, 200000]\n", "use chunks = 2048 or more"),
        (
            f"[dem]\nchunks = {max(2048, 64 * (side // 64 // 90 + 1))}\n"
            f"[dem.synthetic]\nshape = [{side}, {side}]\n",
            "GB compressed)",
        ),
    ]
    for text, match in cases:
        job = tmp_path / "job.toml"
        job.write_text(text + "[output]\ncatalog = 'cat'\n")
        for args in (("run", job, "--dry-run"), ("run", job)):
            one_line_error(invoke(*args), 2, match)
        assert not (tmp_path / "cat").exists()


def test_depths_positive_down_are_named_at_map_level(tmp_path):
    """A GeoTIFF of depths (positive down, no attribute saying so) makes maps with no passable
    cell: the build says so, with the likely cause, and so does every mission's failure (each
    said only that its start was on land)."""
    import rioxarray  # noqa: F401

    depths = np.random.default_rng(1).uniform(2900.0, 3100.0, (40, 40)).astype(np.float32)
    tif = tmp_path / "depths.tif"
    metric_dataarray(depths, a=100.0).rio.write_crs("EPSG:32610").rio.to_raster(tif)
    maps = tmp_path / "m.zarr"
    res = invoke("build-maps", tif, maps, "--clearance", "100", "--landmarks", "2")
    assert res.exit_code == 0, res.output
    assert "no cell of the maps is passable" in res.output and "positive down" in res.output
    with pytest.raises(pipeline.PipelineError, match="if its values are depths, positive down"):
        pipeline.plan(maps, (5, 5), (30, 30), client="synchronous")


def _lonlat_nc(path, lat, lon, z=None):
    if z is None:
        z = np.random.default_rng(0).uniform(-4000, -3000, (len(lat), len(lon)))
    da = xr.DataArray(
        z.astype(np.float32), dims=("lat", "lon"), coords={"lat": lat, "lon": lon}, name="elevation"
    )
    da["lat"].attrs.update(units="degrees_north", standard_name="latitude")
    da["lon"].attrs.update(units="degrees_east", standard_name="longitude")
    return _nc(path, da)


def test_lonlat_grids_at_the_antimeridian_and_the_pole(tmp_path):
    """A grid whose longitudes cross 180 degrees as 179.9, -179.9 reads as the same grid with
    longitudes past 180; one ending at 180, and one reaching latitude 90, read with valid
    cells; a whole globe is refused in one line (it ended in an internal error)."""
    lat = np.linspace(-10.0, -5.0, 51)
    east = np.linspace(175.05, 184.95, 100)
    z = np.random.default_rng(3).uniform(-4000, -3000, (51, 100))
    wrapped = np.where(east > 180.0, east - 360.0, east)
    a = pipeline.open_dem(_lonlat_nc(tmp_path / "a.nc", lat, east, z), resolution=5000.0)
    b = pipeline.open_dem(_lonlat_nc(tmp_path / "b.nc", lat, wrapped, z), resolution=5000.0)
    np.testing.assert_array_equal(a.values, b.values)
    assert np.isfinite(a.values).mean() > 0.4
    for k, (la, lo) in enumerate(
        [(lat, np.linspace(170.0, 180.0, 101)), (np.linspace(88, 90, 21), np.linspace(0, 10, 101))]
    ):
        d = pipeline.open_dem(_lonlat_nc(tmp_path / f"c{k}.nc", la, lo), resolution=2000.0)
        assert np.isfinite(d.values).mean() > 0.4
    glob = _lonlat_nc(
        tmp_path / "g.nc", np.linspace(-89.5, 89.5, 180), np.linspace(-179.5, 179.5, 360)
    )
    one_line_error(invoke("dem", "info", glob), 2, "give a bbox around the region to plan on")


def test_a_dem_store_read_through_its_guard_equals_its_source_for_awkward_chunks(tmp_path):
    """The guarded read of a DEM store (a block a chunk, each decoded with its damage named)
    gives the grid as written, with a last chunk row and column of one cell and one chunk of
    no-data left unstored."""
    z = random_surface((49, 33)).astype(np.float32) - 3000.0
    z[:16, 16:32] = np.nan
    src = _nc(tmp_path / "in.nc", metric_dataarray(z).rename("elevation"))
    dem = tmp_path / "dem.zarr"
    assert invoke("dem", "import", src, dem, "--chunks", "16").exit_code == 0
    assert not (dem / "elevation" / "c" / "0" / "1").exists()
    got = pipeline.open_dem(dem, chunks=16)
    assert got.data.chunks == ((16, 16, 16, 1), (16, 16, 1))
    np.testing.assert_array_equal(got.values, pipeline.open_dem(src, chunks=None).values)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda p: pipeline.plan(p, (5, 5), (50, 50), keep_out=5), "got int"),
        (lambda p: pipeline.plan(p, (5, 5), (50, 50), keep_out=b"zones.geojson"), "got bytes"),
        (lambda p: pipeline.plan(p, (5, 5), (50, 50), keep_out={"a": 1}), "got dict"),
        (lambda p: pipeline.plan(p, (5, 5), (50, 50), keep_out=""), "an empty path"),
        (lambda p: pipeline.plan(p, (5, 5), (50, 50), keep_out="https://x.org/z.json"), "URL"),
        (lambda p: pipeline.plan_missions(p, None), "`missions` must be a sequence"),
        (lambda p: pipeline.plan_missions(p, 5), "got int"),
        (lambda p: pipeline.plan_missions(p, {"start": (5, 5)}), "got dict"),
    ],
)
def test_wrong_types_are_one_pipeline_error(built_store, call, match):
    with pytest.raises(pipeline.PipelineError, match=match):
        call(built_store)


def test_a_missions_rating_in_plan_missions_is_kept(built_store):
    """``max_depth_m`` in a mission's dict is plan's own keyword: the path keeps to it (its
    points' heights, numpy), as a vehicle's rating does; given twice and differently, that
    mission fails saying so and the other is planned."""
    import xarray as xr

    safety = xr.open_zarr(built_store)["safety"].values
    free = pipeline.plan(built_store, (5, 5), (50, 50), client="synchronous")
    deepest = -float(free.points[:, 2].min())
    rating = deepest - 0.25 * (deepest + float(np.nanmax(safety)))  # shallower than the path
    a, b = pipeline.plan_missions(
        built_store,
        [
            {"start": (5, 5), "goal": (50, 50), "max_depth_m": rating},
            {
                "start": (5, 5),
                "goal": (50, 50),
                "max_depth_m": rating,
                "vehicle": {"max_depth_m": 1},
            },
        ],
        client="synchronous",
    )
    assert a.status in ("ok", "uncertified"), a.message
    assert -a.points[:, 2].min() <= rating + 1e-6 < deepest
    assert b.status == "failed" and "give the rating once" in b.message


def test_plan_missions_from_a_plain_script_runs_once_in_threads(built_store, tmp_path):
    """A script without ``if __name__ == "__main__":`` calling plan_missions at its top level:
    it plans on its own threads, says so in one warning naming the fix, and its body runs once
    (worker processes would have imported it again and failed to start)."""
    script = tmp_path / "plain.py"
    script.write_text(
        "import pipeline\n"
        "print('body runs')\n"
        f"ts = pipeline.plan_missions({str(built_store)!r},\n"
        "                             [((5, 5), (50, 50)), ((6, 6), (40, 50))])\n"
        "print('statuses', [str(t.status) for t in ts])\n"
    )
    proc = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=300, cwd=tmp_path
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.count("body runs") == 1, proc.stdout
    assert "statuses ['ok', 'ok']" in proc.stdout or "uncertified" in proc.stdout, proc.stdout
    assert "Traceback" not in proc.stderr and "Nanny" not in proc.stderr
    assert 'outside `if __name__ == "__main__":`' in proc.stderr


@pytest.mark.parametrize("via", ["via_xy = [[1e9, 1e9]]", "via_lonlat = [[10.0, 80.0]]"])
def test_one_missions_off_map_via_point_fails_that_mission_alone(tmp_path, local_client, via):
    """A via point in map coordinates or longitude and latitude off the map (the dry run cannot
    see it: the map's extent is known once the DEM is read) fails its mission with the reason,
    naming the point, and the other mission is planned (the whole job stopped with exit 2)."""
    job = tmp_path / "job.toml"
    job.write_text(
        f"name = 'v'\n{SYN}[maps]\nclearance = 100.0\n"
        f"[[missions]]\nname = 'bad'\nstart = [1, 1]\ngoal = [38, 38]\n{via}\n"
        "[[missions]]\nname = 'good'\nstart = [2, 2]\ngoal = [30, 38]\n"
        "[output]\ncatalog = 'cat'\nquicklooks = false\nperformance_report = false\n"
    )
    res = pipeline.run_job(job, scheduler=local_client)
    assert res.failed == ["bad"] and res.planned == 1, res
    item = json.loads((tmp_path / "cat" / "missions" / "bad" / "bad.json").read_text())
    assert "via 1" in item["properties"]["auv:message"]
    assert "is off the map" in item["properties"]["auv:message"]


def test_points_on_the_maps_outer_edges_are_in_its_edge_cells(built_store):
    """The map spans its cells' squares (as the off-map message says): a point on each outer
    edge and corner is in the edge cell there; a hair beyond is off the map; three numbers are
    not a point."""
    from pipeline.store.maps_store import open_store

    m = open_store(built_store)
    x, y, a = m.x, m.y, m.cell_size
    n_r, n_c = len(y), len(x)
    west, east = min(x) - a / 2, max(x) + a / 2
    north, south = max(y) + a / 2, min(y) - a / 2
    row_of = {north: 0 if y[0] > y[-1] else n_r - 1, south: n_r - 1 if y[0] > y[-1] else 0}
    for px, col in ((west, 0), (east, n_c - 1)):
        for py in (north, south):
            assert m.cell_of("start", "xy", (px, py)) == (row_of[py], col)
    with pytest.raises(pipeline.PipelineError, match="is off the map"):
        m.cell_of("start", "xy", (east + 0.01, north))
    with pytest.raises(pipeline.PipelineError, match="must be a pair of finite numbers"):
        m.cell_of("start", "xy", (1.0, 2.0, 3.0))


def test_a_dataarray_of_depths_or_of_no_numbers(tmp_path):
    """A DataArray of depths (``positive = "down"``, as a NetCDF's depth variable) is read as
    elevation, as a file's is (it built a store with nothing passable); bool or complex values
    are refused in one line (they were built)."""
    import xarray as xr

    elev = pipeline.synthetic_dem((48, 48), chunks=None)
    depths = xr.DataArray(
        -elev.values, dims=elev.dims, coords=elev.coords, attrs={**elev.attrs, "positive": "down"}
    )
    got = pipeline.build_maps(depths, tmp_path / "d.zarr", clearance=60.0, landmarks=0)
    want = pipeline.build_maps(elev, tmp_path / "e.zarr", clearance=60.0, landmarks=0)
    np.testing.assert_array_equal(got["elevation"].values, elev.values.astype(np.float32))
    np.testing.assert_array_equal(got["passable"].values, want["passable"].values)
    assert got["passable"].values.mean() > 0.5
    for bad in (elev > -2000, elev.astype(complex)):
        with pytest.raises(pipeline.PipelineError, match="got values of type (bool|complex)"):
            pipeline.build_maps(bad, tmp_path / "bad.zarr", clearance=60.0)


def test_a_geographic_dataarray_names_the_reprojection(tmp_path):
    """A lon/lat DataArray given to build_maps is refused for what it is (it said "cells are
    not square"), naming open_dem, which reprojects it."""
    import rioxarray  # noqa: F401
    import xarray as xr

    a = xr.DataArray(
        np.full((50, 60), -3000.0, np.float32),
        dims=("y", "x"),
        coords={"y": np.linspace(48, 47, 50), "x": np.linspace(-130, -129, 60)},
    ).rio.write_crs("EPSG:4326")
    with pytest.raises(pipeline.PipelineError, match="geographic coordinates .*open_dem"):
        pipeline.build_maps(a, tmp_path / "g.zarr", clearance=60.0)


def test_an_end_on_land_is_answered_in_the_form_it_was_given(tmp_path):
    """A start given in map coordinates or longitude and latitude that lies on land: the error
    names it as given (and its cell) and the nearest passable point in the same form, whose
    cell (pyproj and the grid, independently) is passable."""
    import re

    from pyproj import Transformer

    from pipeline.store.maps_store import open_store

    pipeline.build_maps(
        pipeline.synthetic_dem((64, 64), chunks=None), tmp_path / "m.zarr", clearance=60.0,
        landmarks=0,
    )  # fmt: skip
    m = open_store(tmp_path / "m.zarr")
    passable = np.asarray(
        m.values("passable", [(r, c) for r in range(64) for c in range(64)])
    ).reshape(64, 64)
    r, c = (int(v) for v in np.argwhere(~passable)[0])
    x, y = float(m.x[c]), float(m.y[r])
    to_ll = Transformer.from_crs(m.crs_wkt, "EPSG:4326", always_xy=True)
    lon, lat = to_ll.transform(x, y)
    for kw, form in ((dict(start_xy=(x, y)), "xy"), (dict(start_lonlat=(lon, lat)), "lonlat")):
        with pytest.raises(pipeline.PipelineError) as info:
            pipeline.plan(tmp_path / "m.zarr", goal=(32, 32), client="synchronous", **kw)
        msg = str(info.value)
        assert msg.startswith(f"start_{form} (") and f"(cell ({r}, {c})) is on land" in msg, msg
        px, py = (
            float(v)
            for v in re.search(r"nearest passable point: \(([^,]+), ([^)]+)\)", msg).groups()
        )
        if form == "lonlat":
            px, py = Transformer.from_crs("EPSG:4326", m.crs_wkt, always_xy=True).transform(px, py)
        cc = int(np.argmin(np.abs(m.x - px)))
        rr = int(np.argmin(np.abs(m.y - py)))
        assert passable[rr, cc] and f"(cell ({rr}, {cc}))" in msg, msg


@pytest.mark.parametrize("crs, a, half", [("EPSG:32610", 30.0, 15.0), ("EPSG:4326", 0.0004, 18.2)])
def test_a_clearance_below_half_a_cell_is_refused_at_the_dry_run(tmp_path, crs, a, half):
    """The dry run reads the DEM file's header (rasterio, no values): a clearance below half
    its cell (a lon/lat grid: the cell it is reprojected at, 36.4 m at 47.96 N) is refused
    before anything is read or built, naming [dem] resolution (it was found after the DEM was
    read, without naming it)."""
    import rioxarray  # noqa: F401
    import xarray as xr

    x = (-130.0 if crs == "EPSG:4326" else 500_000.0) + (np.arange(40) + 0.5) * a
    y = (48.0 if crs == "EPSG:4326" else 4_000_000.0) - (np.arange(40) + 0.5) * a
    arr = xr.DataArray(np.full((40, 40), -3000.0, np.float32), dims=("y", "x"),
                       coords={"x": x, "y": y})  # fmt: skip
    arr.rio.write_crs(crs).rio.to_raster(tmp_path / "dem.tif")
    job = tmp_path / "job.toml"
    job.write_text(
        f"name = 'h'\n[dem]\npath = 'dem.tif'\n[maps]\nclearance = {half - 0.1}\n"
        "[[missions]]\nstart = [1, 1]\ngoal = [30, 30]\n[output]\ncatalog = 'cat'\n"
    )
    res = invoke("run", job, "--dry-run")
    one_line_error(res, 2, f"smaller than half a cell ({half:g} m)")
    assert "[dem] resolution" in res.output and not (tmp_path / "cat").exists()
    job.write_text(job.read_text().replace(f"clearance = {half - 0.1}", f"clearance = {half}"))
    assert invoke("run", job, "--dry-run").exit_code == 0
