"""The Python API at its edges, as a notebook or a plain script meets it: no cluster started
behind one ``plan()``, the local cluster's size, real processes and a real LocalCluster."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from references import missions

import pipeline


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    path = tmp_path_factory.mktemp("api") / "maps.zarr"
    import dask

    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(
            pipeline.synthetic_dem((200, 200), cell_size=50.0, chunks=64, islands=0),
            path,
            clearance=150.0,
            landmarks=2,
        )
    ok = pipeline.open_maps(path)["passable"].values.astype(bool)
    (s, g), *_ = missions(ok, 1, seed=2, min_cells=80)
    return path, [int(v) for v in s], [int(v) for v in g]


def test_a_plain_script_plans_without_a_main_guard_and_without_a_cluster(store):
    """``pipeline.plan`` in a script with no ``if __name__ == "__main__":`` (it started a
    LocalCluster, whose worker processes re-ran the script: tracebacks, "Nanny failed to
    start"): it plans in the script's own process, no worker process started."""
    path, s, g = store
    script = textwrap.dedent(
        f"""
        import multiprocessing, pipeline
        t = pipeline.plan({str(path)!r}, {tuple(s)}, {tuple(g)})
        print(t.status, len(multiprocessing.active_children()))
        import distributed
        try:
            distributed.default_client()
            print("a client")
        except ValueError:
            print("no client")
        """
    )
    proc = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    assert proc.stdout.split() == ["ok", "0", "no", "client"]


def test_an_active_client_is_used_and_none_is_started(store, local_client):
    """Inside ``with client:`` (the user's own cluster) ``plan()`` runs its sections there:
    the scheduler sees its tasks."""
    from distributed import get_task_stream

    path, s, g = store
    with local_client.as_current(), get_task_stream(local_client) as ts:
        t = pipeline.plan(path, tuple(s), tuple(g), mcpc=True, section_size=32)
    assert t.status == "ok" and len(ts.data) > 0
    ref = pipeline.plan(path, tuple(s), tuple(g), mcpc=True, section_size=32)
    assert ref.length_m == pytest.approx(t.length_m)


def test_the_local_clusters_size(tmp_path):
    """``run_job(workers=N)`` and dask's configuration ``auv_pipeline.workers`` size the job's
    LocalCluster (its scheduler counts the workers); a size that is no whole number above 0
    is one line at the dry run."""
    import dask

    job = tmp_path / "job.toml"
    job.write_text(
        "name = 'size'\n[dem.synthetic]\nshape = [60, 60]\n[maps]\nclearance = 100.0\n"
        "[output]\ncatalog = 'cat'\nperformance_report = false\n"
    )
    res = pipeline.run_job(job, workers=3)
    assert res.ok and res.workers == 3
    (tmp_path / "cat" / "catalog.json").unlink()
    for p in (tmp_path / "cat").glob("*.zarr"):
        import shutil

        shutil.rmtree(p)
    with dask.config.set({"auv_pipeline.workers": 1}):
        res = pipeline.run_job(job)
    assert res.workers == 1
    for bad in (0, -2, 1.5):
        with pytest.raises(pipeline.PipelineError, match="number of workers must be a whole"):
            pipeline.run_job(job, workers=bad, dry_run=True)
    assert np.isfinite(res.seconds)


def _nodata_tif(path):
    import rioxarray  # noqa: F401
    from conftest import metric_dataarray

    z = np.random.default_rng(0).uniform(-3100.0, -2900.0, (80, 80)).astype(np.float32)
    z[:, 40:42] = -9999.0  # a band of no-data across the map
    da = metric_dataarray(z, a=100.0).rio.write_crs("EPSG:32610").rio.write_nodata(-9999.0)
    da.rio.to_raster(path)
    return path


@pytest.fixture
def synchronous():
    import dask

    with dask.config.set(scheduler="synchronous"):
        yield


def test_a_dataarray_keeps_its_nodata_and_its_crs_through_every_stage(tmp_path, synchronous):
    """``rioxarray.open_rasterio`` as a notebook calls it (``masked=False``: -9999 in the
    values, the nodata in ``rio.nodata``): the no-data band is never passable (it was, and a
    mission planned through it), and the CRS is the maps store's, read back by rioxarray from
    its CF grid-mapping variable and by the store itself; a DataArray with ``_FillValue`` in its
    attributes alike; several bands are one line naming what to pass."""
    import rioxarray
    import xarray as xr

    tif = _nodata_tif(tmp_path / "nd.tif")
    raw = rioxarray.open_rasterio(tif)
    assert raw.rio.nodata == -9999.0 and float(raw.min()) == -9999.0
    for k, dem in enumerate([raw, raw.squeeze("band", drop=True)]):
        maps = tmp_path / f"m{k}.zarr"
        pipeline.build_maps(dem, maps, clearance=100.0, landmarks=2)
        ds = pipeline.open_maps(maps)
        assert not ds["passable"].values[:, 40:42].any()
        assert np.isnan(ds["elevation"].values[:, 40:42]).all()
        assert ds.rio.crs.to_epsg() == 32610
        assert xr.open_zarr(maps, consolidated=False).rio.crs.to_epsg() == 32610
        assert pipeline.open_store(maps).crs_wkt is not None
    fill = raw.squeeze("band", drop=True).drop_vars("spatial_ref")
    fill.attrs = {"_FillValue": -9999.0}
    pipeline.build_maps(fill, tmp_path / "f.zarr", clearance=100.0, landmarks=2)
    assert not pipeline.open_maps(tmp_path / "f.zarr")["passable"].values[:, 40:42].any()
    three = xr.concat([raw, raw, raw], dim="band")
    with pytest.raises(pipeline.PipelineError, match="select one band"):
        pipeline.build_maps(three, tmp_path / "t.zarr", clearance=100.0)
    # the DEM store keeps the CRS the same way
    pipeline.write_dem(pipeline.open_dem(tif), tmp_path / "dem.zarr")
    assert xr.open_zarr(tmp_path / "dem.zarr", consolidated=False).rio.crs.to_epsg() == 32610
    assert "UTM zone 10N" in pipeline.open_dem(tmp_path / "dem.zarr").attrs["crs_wkt"]


def test_endpoints_in_the_api_as_in_job_files(tmp_path, synchronous):
    """``plan`` and ``plan_missions`` take the ends as a job file does (a cell, ``_xy`` or
    ``_lonlat``) and plan from the cells a job gives for them: the same cells as the job's
    Item records, checked both ways (the cell's own centre and its lon/lat by pyproj)."""
    from pyproj import Transformer

    import pipeline.jobs.job_file as jobs

    tif = _nodata_tif(tmp_path / "nd.tif")
    maps = tmp_path / "m.zarr"
    pipeline.build_maps(pipeline.open_dem(tif), maps, clearance=100.0, landmarks=2)
    m = pipeline.open_store(maps)
    s, g = (5, 5), (70, 30)  # (the no-data band at columns 40-41 parts the map)
    xy = [(float(m.x[c]), float(m.y[r])) for r, c in (s, g)]
    to_ll = Transformer.from_crs(m.crs_wkt, "EPSG:4326", always_xy=True)
    ll = [to_ll.transform(*p) for p in xy]
    ref = pipeline.plan(maps, s, g)
    for kw in (
        dict(start_xy=xy[0], goal_xy=xy[1]),
        dict(start_lonlat=ll[0], goal_lonlat=ll[1]),
        dict(start=s, goal_lonlat=ll[1]),
    ):
        t = pipeline.plan(maps, **kw)
        assert [tuple(t.cells[0]), tuple(t.cells[-1])] == [s, g] and t.length_m == ref.length_m
    got = pipeline.plan_missions(
        maps,
        [{"start_lonlat": ll[0], "goal_xy": xy[1]}, {"start": s, "start_xy": xy[0], "goal": g}],
        client="synchronous",
    )
    assert [tuple(got[0].cells[0]), tuple(got[0].cells[-1])] == [s, g]
    assert got[1].status == "failed" and "exactly one of start" in got[1].message
    with pytest.raises(pipeline.PipelineError, match="exactly one of goal"):
        pipeline.plan(maps, s)
    # the job file's loader and store give the same cells
    job = tmp_path / "job.toml"
    job.write_text(
        f"[dem]\npath = 'nd.tif'\n[maps]\nclearance = 100.0\nlandmarks = 2\n[[missions]]\n"
        f"start_lonlat = [{ll[0][0]!r}, {ll[0][1]!r}]\ngoal_xy = [{xy[1][0]!r}, {xy[1][1]!r}]\n"
    )
    mission = jobs.load_job(job).missions[0]
    cells = [m.cell_of(e, mission[f"{e}_form"], mission[f"{e}_input"]) for e in ("start", "goal")]
    assert cells == [s, g]


def test_results_a_python_user_expects(tmp_path, synchronous):
    """Short reprs, the path and the route as a GeoDataFrame in the maps' CRS, the flight as a
    DataFrame; ``python -m pipeline``; the version from the installed metadata; a LICENSE of
    the declared kind and the ``py.typed`` marker in the package."""
    import importlib.metadata
    from pathlib import Path

    from pipeline.flight.fly import with_flight

    tif = _nodata_tif(tmp_path / "nd.tif")
    maps = tmp_path / "m.zarr"
    pipeline.build_maps(pipeline.open_dem(tif), maps, clearance=100.0, landmarks=2)
    t = pipeline.plan(maps, (5, 5), (70, 30))
    text = repr(t)
    assert len(text) < 300 and text.startswith("Trajectory(ok, ra_star") and "km" in text
    with_flight(maps, t)
    assert len(repr(t)) < 500 and "Flight(ok" in repr(t)
    gdf = t.to_geodataframe()
    assert gdf.crs.to_epsg() == 32610
    grid = gdf[gdf["kind"] == "grid path"]
    np.testing.assert_allclose(np.column_stack([grid.geometry.x, grid.geometry.y]), t.points[:, :2])
    assert (gdf["kind"] == "waypoint").sum() == len(t.flight.waypoints)
    df = t.flight.to_dataframe()
    assert len(df) == len(t.flight.z)
    np.testing.assert_allclose(df["altitude_m"], df["z"] - df["seabed_m"])
    proc = subprocess.run(
        [sys.executable, "-m", "pipeline", "--version"], capture_output=True, text=True
    )
    assert proc.returncode == 0 and importlib.metadata.version("auv-pipeline") in proc.stdout
    assert pipeline.__version__ == importlib.metadata.version("auv-pipeline")
    root = Path(pipeline.__file__).parent
    assert (root / "py.typed").exists()
    licence = (root.parent / "LICENSE").read_text()
    assert licence.startswith("BSD 3-Clause License")
    assert importlib.metadata.metadata("auv-pipeline")["License-Expression"] == "BSD-3-Clause"


def test_data_changing_steps_are_warned_to_a_notebook(tmp_path):
    """Reprojecting a lon/lat grid and reading a DataArray's no-data value raise a
    ``pipeline.PipelineWarning`` (a notebook shows it; the logger had a NullHandler)."""
    import rioxarray
    from test_bad_inputs import _lonlat_nc

    nc = _lonlat_nc(tmp_path / "ll.nc", np.linspace(40, 41, 21), np.linspace(-70, -69, 21))
    with pytest.warns(pipeline.PipelineWarning, match="reprojecting to a local azimuthal"):
        pipeline.open_dem(nc)
    raw = rioxarray.open_rasterio(_nodata_tif(tmp_path / "nd.tif"))
    from pipeline.dem.canonical import as_dem

    with pytest.warns(pipeline.PipelineWarning, match="no-data value -9999 read as NaN"):
        as_dem(raw)


def test_every_public_function_is_typed():
    """Each function ``pipeline`` exports annotates its parameters and its result (the
    package ships ``py.typed``)."""
    import inspect

    untyped = {}
    for name in pipeline.__all__:
        obj = getattr(pipeline, name)
        if not inspect.isfunction(obj):
            continue
        sig = inspect.signature(obj)
        bare = [
            p.name
            for p in sig.parameters.values()
            if p.annotation is inspect.Parameter.empty
            and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
        ]
        if bare or sig.return_annotation is inspect.Signature.empty:
            untyped[name] = bare
    assert untyped == {}


def test_a_nan_nodata_is_no_notice(tmp_path, synchronous):
    """A DEM whose no-data is NaN already (this tool's stores, a float GeoTIFF) is taken as it
    is, with no warning of a changed value."""
    import warnings

    from pipeline.dem.canonical import as_dem

    dem = pipeline.synthetic_dem((40, 40), chunks=None)
    dem.attrs["_FillValue"] = np.float32("nan")
    with warnings.catch_warnings():
        warnings.simplefilter("error", pipeline.PipelineWarning)
        out = as_dem(dem)
    np.testing.assert_array_equal(out.values, dem.values)


@pytest.mark.parametrize("on", ["threads", "cluster"])
def test_a_maps_build_tells_its_progress(tmp_path, monkeypatch, caplog, local_client, on):
    """Each pass of a build over many tiles says, in the log, how many of its tiles are done
    (each tenth, at most every ``TELL_S`` seconds: here every tenth), on dask's threads and on
    a distributed cluster alike (dask's own progress bar sees only the first); the layers are
    those of a build that tells nothing."""
    import logging
    import re

    import dask

    from pipeline.runtime import cluster

    dem = pipeline.synthetic_dem((96, 80), cell_size=50.0, chunks=16, islands=0)
    scheduler = local_client.get if on == "cluster" else "threads"
    with dask.config.set(scheduler=scheduler), caplog.at_level(logging.INFO, "pipeline"):
        quiet = pipeline.build_maps(dem, tmp_path / "quiet.zarr", clearance=150.0, landmarks=1)
        monkeypatch.setattr(cluster, "TELL_S", 0.0)
        caplog.clear()
        told = pipeline.build_maps(dem, tmp_path / "told.zarr", clearance=150.0, landmarks=1)
    lines = [r.getMessage() for r in caplog.records]
    for what in ("fill: ", "flow: ", "layers: ", "components: ", "placing: "):
        counts = [
            (int(m[1]), int(m[2]))
            for line in lines
            if (m := re.search(re.escape(what) + r"(\d+) of (\d+) ", line))
        ]
        assert len(counts) == 10, (what, lines)  # 30 tiles (6 x 5): one line a tenth
        assert [d for d, _ in counts] == [3 * k for k in range(1, 11)] and {
            n for _, n in counts
        } == {30}
    for name in ("elevation", "safety", "passable", "ridge", "component", "landmark_distance"):
        np.testing.assert_array_equal(told[name].values, quiet[name].values)


def test_a_failed_task_is_raised_before_the_others_finish(local_client, tmp_path):
    """A task's error reaches the caller of a told computation as soon as it is known, as
    dask.compute raises it: not after the other tasks (12 s of them on two workers). The first
    task to start fails (whichever the scheduler starts first)."""
    import os
    import time

    import dask

    from pipeline.runtime.cluster import compute_told

    def task(i, first):
        try:
            os.close(os.open(first, os.O_CREAT | os.O_EXCL))
        except FileExistsError:
            time.sleep(1.0)
            return i
        raise ValueError(f"tile {i} is damaged")

    first = str(tmp_path / "first")
    tasks = [dask.delayed(task, pure=False)(i, first) for i in range(24)]
    t0 = time.perf_counter()
    with dask.config.set(scheduler=local_client.get), pytest.raises(ValueError, match="damaged"):
        compute_told(tasks, lambda *a: None)
    assert time.perf_counter() - t0 < 4.0


def test_write_mission_writes_a_folder_of_its_own_and_replaces_only_that(store, tmp_path):
    """``write_mission``: the vehicle files of one flown mission in a new folder; the
    QGroundControl file loads in pymavlink with a waypoint for each of the flight's and the
    home position; the waypoints lie where the flight's do (pyproj); a second write needs
    ``overwrite``, which replaces the folder it wrote and never a folder of the user's (whose
    file stays as it was); a trajectory without its flight, or a URL, is one error."""
    from pymavlink import mavwp
    from pyproj import Transformer

    path, s, g = store
    t = pipeline.plan(path, tuple(s), tuple(g))
    f = pipeline.fly(path, t, {"max_pitch_deg": 15.0})
    files = pipeline.write_mission(path, t, f, tmp_path / "m1")
    kinds = {"track", "grid-path", "waypoints-csv", "waypoints", "qgc", "kml", "imc"}
    assert set(files) == kinds | {"quicklook"}  # the folder as a job writes it
    assert all(p.parent == tmp_path / "m1" and p.is_file() for p in files.values())
    from PIL import Image

    with Image.open(files["quicklook"]) as im:  # a real PNG, as an image reader meets it
        assert im.format == "PNG" and im.size[0] > 400 and im.size[1] > 300
    loader = mavwp.MAVWPLoader()
    assert loader.load(str(files["qgc"])) == len(f.waypoints) + 1
    m = pipeline.open_store(path)
    lon, lat = Transformer.from_crs(m.crs_wkt, 4326, always_xy=True).transform(
        f.waypoints[:, 0], f.waypoints[:, 1]
    )
    got = np.array([(loader.wp(k + 1).y, loader.wp(k + 1).x) for k in range(len(f.waypoints))])
    np.testing.assert_allclose(got, np.c_[lon, lat], rtol=0, atol=1e-7)
    with pytest.raises(pipeline.StoreExistsError, match="exists already"):
        pipeline.write_mission(path, t, f, tmp_path / "m1")
    pipeline.write_mission(path, t, f, tmp_path / "m1", overwrite=True, name="again")
    assert '"name": "again"' in (tmp_path / "m1" / "mission.json").read_text()
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    with pytest.raises(pipeline.StoreExistsError, match="not a mission folder this tool wrote"):
        pipeline.write_mission(path, t, f, mine, overwrite=True)
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]
    assert (mine / "notes.txt").read_text() == "keep me"
    with pytest.raises(pipeline.InvalidParameterError, match="its flight"):
        pipeline.write_mission(path, t, None, tmp_path / "m2")
    with pytest.raises(pipeline.InvalidParameterError, match="local folder"):
        pipeline.write_mission(path, t, f, "s3://bucket/m3")
    assert not (tmp_path / "m2").exists()


def test_a_new_output_format_is_one_writer_and_one_registry_line(store, tmp_path, monkeypatch):
    """The FORMATS registry is the one place a mission folder's files are listed: a format
    registered there (a plain-text list of the waypoints in longitude and latitude) is
    written by ``write_mission`` beside the others, from the same waypoint table (its
    positions are the GeoJSON file's)."""
    from pipeline.outputs.files import FORMATS, Format

    def listing(m, path):
        rows = zip(m.table["lon"], m.table["lat"], m.table["depth_m"], strict=True)
        path.write_text("".join(f"{lon:.8f} {lat:.8f} {d:.2f}\n" for lon, lat, d in rows))

    fmt = Format("waypoints.txt", "waypoints (text)", "text/plain", ("data",), listing, True)
    monkeypatch.setitem(FORMATS, "text", fmt)
    path, s, g = store
    t = pipeline.plan(path, tuple(s), tuple(g))
    f = pipeline.fly(path, t)
    files = pipeline.write_mission(path, t, f, tmp_path / "m1")
    rows = np.loadtxt(files["text"], ndmin=2)
    assert files["text"].name == "waypoints.txt" and len(rows) == len(f.waypoints)
    geo = json.loads(files["waypoints"].read_text())["features"][:-1]
    np.testing.assert_allclose(rows[:, :2], [p["geometry"]["coordinates"][:2] for p in geo])


def test_a_submodule_is_reached_as_an_attribute():
    """``pipeline.maps.build`` and the like after a bare ``import pipeline`` (in a new process,
    where nothing imported them yet), as ``pipeline.jobs`` always was; a name that is no
    submodule is an AttributeError."""
    script = textwrap.dedent(
        """
        import pipeline
        print(pipeline.maps.build.build_maps.__name__, pipeline.store.maps_store.MapsStore.__name__,
              pipeline.runtime.cluster.local_cluster.__name__,
              pipeline.jobs.job_file.load_job.__name__)
        try:
            pipeline.flight.nothing
        except AttributeError as e:
            print("AttributeError")
        """
    )
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == [
        "build_maps",
        "MapsStore",
        "local_cluster",
        "load_job",
        "AttributeError",
    ]
