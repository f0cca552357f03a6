"""Job files and the command line: real TOML files, the real console script, real stores."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from click.testing import CliRunner

import pipeline
from pipeline.cli import main
from pipeline.exceptions import JobFileError
from pipeline.jobs.job_file import load_job
from pipeline.jobs.run import run_job

GOOD = """
name = "small"
[dem]
chunks = 64
[dem.synthetic]
shape = [150, 120]
cell_size = 50.0
seed = 4
[maps]
landmarks = 1              # the job's steps are tested here, not the bound: one layer is enough
[output]
catalog = "{catalog}"
performance_report = false
"""


def _job(tmp_path, text, name="job.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_run_job_builds_then_reuses_the_dem_store(tmp_path, local_client):
    job = _job(tmp_path, GOOD.format(catalog=tmp_path / "cat"))
    first = run_job(job, scheduler=local_client)
    assert not first.reused and first.dem_store.parent == tmp_path / "cat"
    dem = pipeline.open_dem(first.dem_store, chunks=None)
    ref = pipeline.synthetic_dem((150, 120), cell_size=50.0, seed=4, chunks=None)
    np.testing.assert_array_equal(dem.values, ref.values)
    again = run_job(job, scheduler=local_client)  # --overwrite: the console-script test
    assert again.reused and again.dem_store == first.dem_store


def test_dry_run_computes_nothing(tmp_path):
    job = _job(tmp_path, GOOD.format(catalog=tmp_path / "cat"))
    res = run_job(job, dry_run=True)
    assert not res.dem_store.exists() and not (tmp_path / "cat").exists()


def test_job_with_a_dem_file(tmp_path, topobathy_tif, local_client):
    job = _job(
        tmp_path,
        f'name = "real"\n[dem]\npath = "{topobathy_tif}"\nchunks = 64\n'
        f"resolution = 1200.0\n"  # the file's cells are 2.4 km
        f"[maps]\nclearance = 1000.0\n"
        f'[output]\ncatalog = "{tmp_path / "cat"}"\n',
    )
    res = run_job(job, scheduler=local_client)
    dem = pipeline.open_dem(res.dem_store)
    assert "crs_wkt" in dem.attrs and (dem.values >= 0).any()
    assert pipeline.cell_size(dem) == 1200.0


@pytest.mark.parametrize(
    "text, match",
    [
        ("name = 'x'\n", r"a \[dem\] table is required"),
        ("[dem]\npath = 'a.tif'\n[dem.synthetic]\nshape = [4, 4]\n", "exactly one of"),
        ("[dem]\nsynthetic = { shape = [4, 4] }\ncolour = 'red'\n", "unknown key dem.'colour'"),
        ("[dem.synthetic]\nshape = [4, 4]\nsed = 3\n", r"unknown key dem.synthetic.'sed'"),
        ("[dem.synthetic]\nshape = [4]\n", r"dem.synthetic.shape must be a pair \(rows, cols\)"),
        (
            "[dem.synthetic]\nshape = [4, 4]\nseed = 'one'\n",
            "dem.synthetic.seed must be an integer",
        ),
        ("[dem.synthetic]\ncell_size = 3.0\n", "shape is required"),
        (
            "[dem]\nchunks = 0\nsynthetic = { shape = [4, 4] }\n",
            "dem.chunks must be an integer >= 1",
        ),
        ("[dem]\npath = 'missing.tif'\n", r"dem.path 'missing.tif' does not exist"),
        ("[dem]\npath = 3\n", "dem.path must be a file path"),
        (
            "[dem]\npath = '.'\nresolution = -1.0\n",
            r"dem.resolution must be a finite number of metres > 0",
        ),
        ("[dem]\npath = '.'\nresolution = 'fine'\n", r"dem.resolution must be a finite number"),
        ("planners = 1\n[dem.synthetic]\nshape = [4, 4]\n", "unknown key 'planners'"),
        ("[dem.synthetic\nshape = [4, 4]\n", "not valid TOML"),
        ("name = '../up'\n[dem.synthetic]\nshape = [4, 4]\n", "name must be"),
    ],
)
def test_bad_job_files(tmp_path, text, match):
    job = _job(tmp_path, text)
    with pytest.raises(JobFileError, match=match) as info:
        load_job(job)
    assert str(job) in str(info.value)


def test_missing_job_file(tmp_path):
    with pytest.raises(JobFileError, match="does not exist"):
        load_job(tmp_path / "nope.toml")


def test_demo_job_file_is_valid():
    job = load_job(Path(__file__).parents[1] / "tasks" / "demo.toml")
    assert job.name == "demo" and job.synthetic["shape"] == [2000, 2000]


def test_real_data_job_file_is_valid(tmp_path, topobathy):
    """tasks/topobathy.toml with its DEM made by tasks/data/make_topobathy.py: the file holds
    matplotlib's grid as it is (north first, longitudes west negative)."""
    import runpy
    import shutil

    tasks = Path(__file__).parents[1] / "tasks"
    make = runpy.run_path(str(tasks / "data" / "make_topobathy.py"))["main"]
    (tmp_path / "data").mkdir()
    nc = make(tmp_path / "data" / "topobathy.nc")
    shutil.copy(tasks / "topobathy.toml", tmp_path / "topobathy.toml")
    job = load_job(tmp_path / "topobathy.toml")
    assert job.dem_path == nc and job.resolution == 150.0 and len(job.missions) == 5
    z, lon, lat = topobathy
    ds = xr.open_dataset(nc)
    np.testing.assert_array_equal(ds["elevation"].values[::-1], z)
    np.testing.assert_allclose(ds["lon"].values, lon - 360.0)
    assert all(m["start_form"] == m["goal_form"] == "lonlat" for m in job.missions)


# ----------------------------------------------------------------------------- CLI


def test_cli_synth_import_info(tmp_path, topobathy_tif):
    r = CliRunner()
    out = tmp_path / "s.zarr"
    res = r.invoke(
        main, ["dem", "synth", str(out), "--shape", "100", "80", "--seed", "2", "--chunks", "64"]
    )
    assert res.exit_code == 0, res.output
    ref = pipeline.synthetic_dem((100, 80), seed=2, chunks=None).values
    np.testing.assert_array_equal(pipeline.open_dem(out, chunks=None).values, ref)
    res = r.invoke(main, ["dem", "synth", str(out), "--shape", "100", "80"])
    assert res.exit_code == 2 and "exists already" in res.output
    res = r.invoke(main, ["dem", "import", str(topobathy_tif), str(tmp_path / "r.zarr")])
    assert res.exit_code == 0, res.output
    res = r.invoke(main, ["dem", "info", str(tmp_path / "r.zarr")])
    assert res.exit_code == 0 and "cells of" in res.output and "crs: set" in res.output
    res = r.invoke(main, ["dem", "info", str(out)])  # the store's own chunks, not the reader's
    assert res.exit_code == 0 and "stored in chunks (64, 64)" in res.output
    # georeferenced where asked: the map's centre at the origin given (pyproj), or no CRS
    from pyproj import Transformer

    anchored = tmp_path / "anchored.zarr"
    args = ["--shape", "40", "60", "--origin-lon", "-30.5", "--origin-lat", "40.2"]
    res = r.invoke(main, ["dem", "synth", str(anchored), *args])
    assert res.exit_code == 0, res.output
    crs = pipeline.open_dem(anchored, chunks=None).attrs["crs_wkt"]
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(900.0, 600.0)
    assert lon == pytest.approx(-30.5, abs=1e-9) and lat == pytest.approx(40.2, abs=1e-9)
    plain = tmp_path / "plain.zarr"
    res = r.invoke(main, ["dem", "synth", str(plain), "--shape", "20", "20", "--no-georeferenced"])
    assert res.exit_code == 0 and "crs_wkt" not in pipeline.open_dem(plain, chunks=None).attrs


def test_cli_bad_file_is_one_clear_line(tmp_path):
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"nope")
    res = CliRunner().invoke(main, ["dem", "import", str(bad), str(tmp_path / "o.zarr")])
    assert res.exit_code == 2
    assert f"error: cannot read DEM file {bad}" in res.output
    assert "Traceback" not in res.output


def test_console_script_runs_a_job(tmp_path, local_client):
    """The installed `pipeline` entry point, as a scheduled job would call it, on a running
    cluster given by address (the killed-job test runs it on its own LocalCluster)."""
    job = _job(tmp_path, GOOD.format(catalog=tmp_path / "cat"))
    exe = Path(sys.executable).parent / "pipeline"
    env = dict(os.environ)
    on = ["--scheduler", local_client.scheduler.address]
    proc = subprocess.run(
        [str(exe), "run", str(job), *on], capture_output=True, text=True, timeout=300, env=env
    )
    assert proc.returncode == 0, proc.stderr
    assert (
        "job small: 0 missions planned" in proc.stdout
        and "writing the DEM store" in proc.stderr
        and "dask dashboard: http" in proc.stderr
    )
    # reusing the stores is test_run_job_builds_then_reuses_the_dem_store's; here the flag
    proc = subprocess.run(
        [str(exe), "run", str(job), *on, "--overwrite"],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert proc.returncode == 0 and "writing the DEM store" in proc.stderr
    bad = _job(tmp_path, "[dem]\n", "bad.toml")
    proc = subprocess.run(
        [str(exe), "run", str(bad)], capture_output=True, text=True, timeout=300, env=env
    )
    assert proc.returncode == 2 and "error: job file" in proc.stderr


LIGHT = """
import sys
import pipeline
from pipeline.cli import main

HEAVY = ("dask.array", "distributed", "xarray", "pandas", "zarr", "numba", "scipy", "rasterio")
def loaded():
    return sorted(m for m in HEAVY if m in sys.modules)

assert loaded() == [], loaded()
for args in (["--help"], ["run", "--help"], ["run", sys.argv[1]]):
    try:
        main.main(args, prog_name="pipeline", standalone_mode=True)
    except SystemExit as exc:
        print("exit", exc.code)
assert loaded() == [], loaded()
# every public name still resolves, to the object its module defines
import importlib
for name in pipeline.__all__:
    value = getattr(pipeline, name)
    owner = getattr(value, "__module__", None)
    if owner and owner.startswith("pipeline."):
        assert getattr(importlib.import_module(owner), name) is value, name
assert pipeline.jobs.job_file.load_job is importlib.import_module("pipeline.jobs.job_file").load_job
print("heavy after the API:", loaded())
"""


def test_the_command_line_answers_help_and_a_wrong_job_file_without_the_heavy_imports(tmp_path):
    """``import pipeline`` binds its API on first use (PEP 562), so the command line's help and
    a wrong job file's one-line error come without importing dask.array, distributed, xarray,
    zarr, numba or scipy (3 s on the benchmark machine; the command line imports dask itself
    for its logging settings); every public name still resolves to its module's
    object, and a submodule is still an attribute of the package."""
    bad = _job(tmp_path, "[dem]\n", "bad.toml")
    proc = subprocess.run(
        [sys.executable, "-c", LIGHT, str(bad)], capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.count("exit 0") == 2 and "exit 2" in proc.stdout, proc.stdout
    assert "error: job file" in proc.stderr and "Traceback" not in proc.stderr
    # the names resolved: the stages' libraries were imported then, not before
    assert "heavy after the API: []" not in proc.stdout
