"""Batch jobs end to end: real job files, a real LocalCluster or real scheduler and worker
processes, the results catalog read back with pystac (STAC schema validation), geopandas and
matplotlib; bad missions, kill-and-resume with SIGKILL, a worker killed mid-job."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import geopandas as gpd
import numpy as np
import pystac
import pytest
from conftest import (
    SHM,
    orphaned_semaphores,
    random_surface,
    start_dask_cluster,
    stop_dask_cluster,
    write_bag,
)
from matplotlib import image
from references import densify
from scipy import ndimage
from scipy.interpolate import RegularGridInterpolator
from scipy.spatial import cKDTree

import pipeline
from pipeline.exceptions import JobFileError
from pipeline.jobs.job_file import load_job
from pipeline.jobs.run import run_job
from pipeline.verify.clearance import clearances

ROOT = Path(__file__).parents[1]
EXE = Path(sys.executable).parent / "pipeline"

JOB = """
name = "{name}"
[dem]
chunks = 128
[dem.synthetic]
shape = [{n}, {n}]
cell_size = 30.0
seed = 1
islands = 0
[maps]
clearance = 150.0
min_accumulation = 20
[planning]
planner = "ra_star"
omega = 2.0
{missions}
[output]
catalog = "{catalog}"
quicklooks = {quicklooks}
performance_report = {performance_report}
"""

MISSIONS4 = """
[[missions]]
name = "cells"
start = [10, 12]
goal = [280, 270]
[[missions]]
name = "xy"
start_xy = [600.0, 8500.0]
goal_xy = [8000.0, 700.0]
planner = "lagrangian"
omega = 1.5
[[missions]]
name = "one-window"
start = [150, 5]
goal = [150, 290]
mcpc = false
[[missions]]
name = "astar"
start = [280, 20]
goal = [20, 280]
planner = "astar"
"""


def write_job(
    tmp_path,
    n=300,
    missions=MISSIONS4,
    name="t",
    file="job.toml",
    quicklooks=False,
    performance_report=False,
):
    """A job file; without quick-looks (each takes a second) and dask's performance report
    (a second a run) unless the test looks at them."""
    p = tmp_path / file
    p.write_text(
        JOB.format(
            name=name,
            n=n,
            missions=missions,
            catalog=tmp_path / "cat",
            quicklooks=str(quicklooks).lower(),
            performance_report=str(performance_report).lower(),
        )
    )
    return p


def console(job, client, *flags, **kw):
    """``pipeline run JOB FLAGS`` through the installed console script, on ``client``'s
    scheduler (a real process, as an operator runs it)."""
    return subprocess.run(
        [str(EXE), "run", str(job), *flags, "--scheduler", client.scheduler.address],
        capture_output=True,
        text=True,
        timeout=300,
        **kw,
    )


@pytest.fixture(scope="session")
def stores(tmp_path_factory, local_client):
    """The DEM and maps stores of the 300^2 test jobs, built once by a job without missions;
    each test copies them into its own catalog, where its job finds and reuses them."""
    tmp = tmp_path_factory.mktemp("stores")
    res = run_job(write_job(tmp, missions=""), scheduler=local_client)
    assert not res.reused and res.planned == 0
    return tmp / "cat"


def with_stores(stores, tmp_path):
    import shutil

    for p in stores.glob("*.zarr"):
        shutil.copytree(p, tmp_path / "cat" / p.name)


@pytest.fixture(scope="module")
def done(tmp_path_factory, stores, local_client):
    tmp = tmp_path_factory.mktemp("job")
    with_stores(stores, tmp)
    job = write_job(tmp, quicklooks=True, performance_report=True)
    return job, run_job(job, scheduler=local_client)


def test_an_item_file_is_its_document_indented_with_the_geometry_on_one_line(done):
    """Each mission's Item file is its document as ``json.dumps(indent=1)`` writes it, but
    for the geometry, which is on one line."""
    _, res = done
    items = sorted((res.catalog.parent / "missions").glob("*/*.json"))
    assert len(items) >= 4
    for path in items:
        text = path.read_text()
        doc = json.loads(text)
        if not doc.get("geometry"):
            assert text == json.dumps(doc, indent=1)
            continue
        assert len(doc["geometry"]["coordinates"]) > 2
        want = json.dumps({**doc, "geometry": None}, indent=1).replace(
            '"geometry": null', '"geometry": ' + json.dumps(doc["geometry"]), 1
        )
        assert text == want


def test_catalog_loads_and_items_validate_against_the_stac_schema(done):
    job, res = done
    assert res.ok and res.planned == 4 and res.catalog.name == "catalog.json"
    cat = pystac.Catalog.from_file(str(res.catalog))
    items = {it.id: it for it in cat.get_items(recursive=True)}
    assert set(items) == {"cells", "xy", "one-window", "astar"}
    coll = cat.get_child("missions")
    assert coll is not None and isinstance(coll, pystac.Collection)
    coll.validate()
    for it in items.values():
        it.validate()  # the STAC JSON schemas (bundled with pystac), jsonschema
        p = it.properties
        assert p["auv:status"] == "ok" and p["auv:message"] == ""
        assert p["auv:ridge_length_m"] <= p["auv:length_m"]
        assert p["auv:lower_bound_m"] <= p["auv:length_m"]
        assert it.geometry["type"] == "LineString"
        assert set(it.assets) == {
            "track",
            "grid-path",
            "waypoints",
            "waypoints-csv",
            "qgc",
            "kml",
            "imc",
            "quicklook",
        }
    assert items["xy"].properties["auv:planner"] == "lagrangian"
    assert items["xy"].properties["auv:omega"] == 1.5


def test_geoparquet_and_pngs(done):
    job, res = done
    root = res.catalog.parent
    table = gpd.read_parquet(root / "missions" / "missions.parquet")
    assert sorted(table["id"]) == ["astar", "cells", "one-window", "xy"]
    assert (table.geometry.geom_type == "LineString").all()
    for mid in table["id"]:
        item = json.loads((root / "missions" / mid / f"{mid}.json").read_text())
        # the Item's geometry is the waypoint route in WGS84, as in waypoints.geojson
        wps = gpd.read_file(root / "missions" / mid / "waypoints.geojson")
        wps = wps[wps.geometry.geom_type == "Point"]
        coords = np.array(item["geometry"]["coordinates"])
        np.testing.assert_allclose(np.column_stack([wps.geometry.x, wps.geometry.y]), coords)
        track = gpd.read_parquet(root / "missions" / mid / "track.parquet")
        assert track.crs.to_epsg() == 4326 and {"x", "y", "z", "time_s"} <= set(track)
        grid = gpd.read_parquet(root / "missions" / mid / "grid-path.parquet")
        assert {"row", "col", "x", "y", "z"} <= set(grid)
        png = image.imread(root / "missions" / mid / "quicklook.png")
        assert png.ndim == 3 and png.shape[0] > 100 and png.shape[1] > 100
    assert (root / "performance-report.html").stat().st_size > 1000


def _report_data(page) -> dict:
    return json.loads(page.evaluate("document.getElementById('report-data').textContent"))


def test_the_report_opens_offline_in_chromium(done, tmp_path):
    """index.html in headless Chromium with the network off: the hillshade, every track with
    its waypoints, start and goal, the table; a click on a track opens its properties, the
    profile hides no close pass (against track.parquet), every file link resolves, the table
    sorts; no failed request, no request off the disk, no console error."""
    from _browser import offline_page

    job, res = done
    root = res.catalog.parent
    assert res.report == root / "index.html"
    items = {
        it.id: it for it in pystac.Catalog.from_file(str(res.catalog)).get_items(recursive=True)
    }
    with offline_page(res.report) as (page, problems):
        widths = page.evaluate(
            "Array.from(document.querySelectorAll('img.leaflet-image-layer'))"
            ".map(i => [i.naturalWidth, i.naturalHeight])"
        )
        assert len(widths) == 1 and min(widths[0]) > 100  # the hillshade, loaded from disk
        ds = pipeline.open_maps(res.maps_store)
        data = _report_data(page)
        a = float(ds.attrs["cell_size"])
        np.testing.assert_allclose(
            data["hillshade"]["extent"],
            [
                ds.x.min() - a / 2,
                ds.y.min() - a / 2,
                ds.x.max() + a / 2,
                ds.y.max() + a / 2,
            ],
        )
        assert page.locator("path.track").count() == len(items)
        wp = sum(it.properties["auv:waypoints"] for it in items.values())
        assert page.locator("path.waypoint").count() == wp
        assert page.locator("path.start").count() == page.locator("path.goal").count() == 4
        rows = page.locator("#missions tbody tr")
        assert rows.count() == len(items)
        names = sorted(rows.nth(i).locator("td").first.inner_text() for i in range(4))
        assert names == sorted(items)
        # a click on a track: its properties in a popup and in the side panel
        page.locator("path.track-xy").dispatch_event("click")
        popup = page.locator(".leaflet-popup-content").inner_text()
        p = items["xy"].properties
        assert "lagrangian, 1.50" in popup and f"{p['auv:certified_ratio']:.4f}" in popup
        assert f"{p['auv:length_m'] / 1e3:.2f} km" in popup
        alt = f"{p['auv:altitude_median_m']:.0f} m median, {p['auv:altitude_p90_m']:.0f} m 90th"
        assert alt in popup and f"{p['auv:vertical_reversals_per_km']:.2f} per km" in popup
        assert page.locator("#details-title").inner_text() == "xy"
        for series in ("seabed", "required", "flown"):
            assert page.locator(f"#profile svg .series-{series}").count() == 1
        legend = page.locator("#profile-legend").inner_text()
        assert "seabed" in legend and "lowest safe height" in legend and "flown" in legend
        # every file of the mission is linked, and every link resolves on disk
        hrefs = page.locator("#files a").evaluate_all("as => as.map(a => a.getAttribute('href'))")
        assert {h.split("/")[-1] for h in hrefs} >= {
            Path(v.href).name for v in items["xy"].assets.values()
        }
        assert all((root / h).is_file() for h in hrefs)
        # sorting by length: ascending, then descending
        head = page.locator("#missions th", has_text="length km")
        for order in ("ascending", "descending"):
            head.click()
            got = rows.evaluate_all("rs => rs.map(r => Number(r.cells[4].dataset.value))")
            assert got == sorted(got, reverse=order == "descending")
            assert head.get_attribute("aria-sort") == order
        page.screenshot(path=str(tmp_path / "report.png"), full_page=True)
    assert problems == {"failed": [], "external": [], "errors": []}
    # the profile keeps each track's highest seabed and lowest flown height (thinned by runs)
    for m in data["missions"]:
        t = gpd.read_parquet(root / "missions" / m["id"] / "track.parquet")
        assert len(m["profile"]["flown"]) <= 1501
        assert max(m["profile"]["seabed"]) == pytest.approx(t["seabed_m"].max(), abs=0.01)
        assert min(m["profile"]["flown"]) == pytest.approx(t["z"].min(), abs=0.01)
        assert min(m["profile"]["s_km"]) == 0 and m["profile"]["s_km"][-1] == pytest.approx(
            t["s_m"].iloc[-1] / 1e3
        )
    shot = image.imread(tmp_path / "report.png")
    assert shot.shape[0] > 1000 and shot[..., :3].std() > 0.05  # a page, not a blank


def test_min_clearance_against_brute_force(done):
    """The reported clearance of what is flown, against the DEM's bilinear seabed (scipy), and
    the grid path's clearance function against every grid point of the DEM (3-D distances)."""
    job, res = done
    root = res.catalog.parent
    dem = pipeline.open_dem(next(root.glob("dem-*.zarr")), chunks=None)
    gx, gy = np.meshgrid(dem["x"].values, dem["y"].values)
    grid = np.column_stack([gx.ravel(), gy.ravel(), dem.values.ravel().astype(np.float64)])
    for mid in ("cells", "astar"):
        item = json.loads((root / "missions" / mid / f"{mid}.json").read_text())
        track = gpd.read_parquet(root / "missions" / mid / "grid-path.parquet")
        pts = np.column_stack([track["x"], track["y"], track["z"]])
        each = np.concatenate(
            [
                np.sqrt(((grid[None, :, :] - pts[k : k + 50, None, :]) ** 2).sum(axis=2)).min(
                    axis=1
                )
                for k in range(0, len(pts), 50)
            ]
        )
        # the reported clearance is of what is flown: the track file and the waypoint file's
        # straight legs (every 2 m) against the bilinear seabed of the DEM (scipy, sampled
        # every cell / 10), never under the clearance
        reported = item["properties"]["auv:min_clearance_m"]
        flown = gpd.read_parquet(root / "missions" / mid / "track.parquet")
        wps = gpd.read_file(root / "missions" / mid / "waypoints.geojson")
        props = item["properties"]
        wps = wps[wps.geometry.geom_type == "Point"].to_crs(
            props.get("proj:code") or props["proj:wkt2"]
        )
        legs = np.column_stack([wps.geometry.x, wps.geometry.y, wps.geometry.z])
        fxyz = np.concatenate(
            [np.column_stack([flown["x"], flown["y"], flown["z"]]), densify(legs, 2.0)]
        )
        a = float(dem["x"].values[1] - dem["x"].values[0])
        x, y = dem["x"].values, dem["y"].values[::-1]
        f = RegularGridInterpolator((y, x), dem.values[::-1].astype(np.float64))
        fx = np.arange(x[0], x[-1] + 1e-9, a / 10)
        fy = np.arange(y[0], y[-1] + 1e-9, a / 10)
        yy, xx = np.meshgrid(fy, fx, indexing="ij")
        # the figure is searched up to 1.25 R (a mission whose least clearance is larger
        # reports 1.25 R): the seabed samples farther than that horizontally from every point
        # cannot be nearer, and are left out (the DEM cells within 1.25 R of a point's cell)
        near = np.zeros(dem.shape, bool)
        near[
            np.clip(((y[-1] - fxyz[:, 1]) / a + 0.5).astype(int), 0, dem.shape[0] - 1),
            np.clip(((fxyz[:, 0] - x[0]) / a + 0.5).astype(int), 0, dem.shape[1] - 1),
        ] = True
        near = ndimage.binary_dilation(near, np.ones((15, 15), bool))  # 7 cells > 1.25 R + a
        rows = np.clip(((y[-1] - yy) / a + 0.5).astype(int), 0, dem.shape[0] - 1)
        cols = np.clip(((xx - x[0]) / a + 0.5).astype(int), 0, dem.shape[1] - 1)
        keep = near[rows, cols]
        xk, yk = xx[keep], yy[keep]
        seabed = np.column_stack([xk, yk, f(np.column_stack([yk, xk]))])
        ref = min(cKDTree(seabed).query(fxyz)[0].min(), 1.25 * 150.0)
        assert reported >= 150.0 * (1 - 1e-6)
        assert ref - a / 10 <= reported <= ref + a / 10, (reported, ref)
        # the grid path's clearance from the grid points, the check of a mission not flown:
        # per point, within a radius that holds every point's nearest grid point
        traj = SimpleNamespace(cells=track[["row", "col"]].to_numpy(), points=pts)
        per_point = clearances(next(root.glob("maps-*.zarr")), traj, 2 * float(each.max()))
        np.testing.assert_allclose(per_point, each, atol=1e-6)


def test_rerun_skips_finished_missions(done, local_client):
    job, res = done
    root = res.catalog.parent
    before = {
        m: json.loads((root / "missions" / m / f"{m}.json").read_text())["properties"]["auv:run_id"]
        for m in ("cells", "xy")
    }
    again = run_job(job, scheduler=local_client)
    assert again.skipped == 4 and again.planned == 0 and again.ok
    after = {
        m: json.loads((root / "missions" / m / f"{m}.json").read_text())["properties"]["auv:run_id"]
        for m in ("cells", "xy")
    }
    assert after == before


# ------------------------------------------------------------------ bad jobs and missions


@pytest.mark.parametrize(
    "extra, match",
    [
        ("[maps]\nmethod = 'round'\n", "maps.method must be"),
        ("[maps]\nclearance = -5\n", "maps.clearance must be a finite number of metres > 0"),
        ("[maps]\nmin_accumulation = 2.5\n", "maps.min_accumulation must be an integer"),
        ("[maps]\nradius = 3\n", "unknown key maps.'radius'"),
        ("[planning]\nomega = 0.5\n", "planning.omega must be a finite number >= 1"),
        ("[planning]\nplanner = 'rrt'\n", "planning.planner must be 'dijkstra'"),
        ("[planning]\nmcpc = 'yes'\n", "planning.mcpc must be true or false"),
        ("[planning]\nrho = 0\n", "planning.rho must be an integer >= 1"),
        ("[[missions]]\nstart = [1, 2]\n", r"missions\[0\]. needs exactly one of goal"),
        (
            "[[missions]]\nstart = [1, 2]\nstart_xy = [1.0, 2.0]\ngoal = [3, 4]\n",
            "needs exactly one of start",
        ),
        ("[[missions]]\nstart = [1.5, 2]\ngoal = [3, 4]\n", r"start must be \[row, col\]"),
        (
            "[[missions]]\nstart = [1, 2]\ngoal = [3, 4]\nspeed = 3\n",
            r"unknown key missions\[0\].'speed'",
        ),
        (
            "[[missions]]\nname = 'a'\nstart = [1, 2]\ngoal = [3, 4]\n"
            "[[missions]]\nname = 'a'\nstart = [1, 2]\ngoal = [3, 4]\n",
            "used twice",
        ),
        (
            "[[missions]]\nstart = [1, 2]\ngoal = [3, 4]\nomega = 0\n",
            r"missions\[0\].omega must be a finite number >= 1",
        ),
        ("missions = 3\n", "missions must be an array of tables"),
    ],
)
def test_bad_job_files_name_the_key(tmp_path, extra, match):
    p = tmp_path / "bad.toml"
    # top-level keys and tables go before [dem.synthetic], arrays of tables after it
    p.write_text(
        f"{extra}\n[dem.synthetic]\nshape = [40, 40]\n"
        if not extra.startswith("[[")
        else f"[dem.synthetic]\nshape = [40, 40]\n{extra}"
    )
    with pytest.raises(JobFileError, match=match) as info:
        load_job(p)
    assert str(p) in str(info.value)


def test_bad_missions_job_reports_failed_items_and_exits_1(tmp_path, local_client):
    import shutil

    # the job file as shipped, in a copy of tasks/ (its catalog is relative to the job file)
    shutil.copytree(ROOT / "tasks", tmp_path / "tasks")
    proc = subprocess.run(
        [
            str(EXE),
            "run",
            str(tmp_path / "tasks" / "bad-missions.toml"),
            "--scheduler",
            local_client.scheduler.address,
        ],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=tmp_path,
    )
    assert proc.returncode == 1, proc.stderr[-3000:]
    assert "4 failed" in proc.stdout
    root = tmp_path / "catalogs" / "bad-missions"
    cat = pystac.Catalog.from_file(str(root / "catalog.json"))
    items = {it.id: it for it in cat.get_items(recursive=True)}
    for it in items.values():
        it.validate()
    status = {
        k: (it.properties["auv:status"], it.properties["auv:message"]) for k, it in items.items()
    }
    # (its first route's flight cut away from the ridges past the atoll's shallows, where a
    # route along them breaks the surface limit: it was planned again around them)
    assert status["good-one"][0] == "ok"
    assert status["good-one"][1] == "" or status["good-one"][1].startswith("planned again")
    assert status["start-on-land"][0] == "failed"
    assert (
        "on land" in status["start-on-land"][1] and "nearest passable" in status["start-on-land"][1]
    )
    assert "unreachable" in status["goal-in-the-lagoon"][1]
    assert "off the map" in status["off-the-map"][1]
    assert "no coordinate reference system" in status["lonlat-without-crs"][1]
    assert items["start-on-land"].geometry is None
    # the report: every mission in the table, the failed ones with their reasons
    from _browser import offline_page

    with offline_page(root / "index.html") as (page, problems):
        rows = page.locator("#missions tbody tr")
        assert rows.count() == len(items)
        failed = page.locator("#missions tbody tr.failed")
        assert failed.count() == 4
        text = {
            failed.nth(i).locator("td").first.inner_text(): failed.nth(i).inner_text()
            for i in range(4)
        }
        assert set(text) == {k for k, (st, _) in status.items() if st == "failed"}
        assert "on land" in text["start-on-land"] and "off the map" in text["off-the-map"]
        assert page.locator("path.track").count() == 1  # only the good mission has a track
    assert problems == {"failed": [], "external": [], "errors": []}


# ------------------------------------------------------------------ kill, resume, lose a worker

MANY = "".join(
    f"""
[[missions]]
name = "m{i:02d}"
start = [{5 + 3 * i}, 5]
goal = [{290 - 2 * i}, 290]
planner = "lagrangian"
mcpc = false
"""
    for i in range(8)
)


def _items(root):
    """run_id of every finished mission (a folder being written is hidden and skipped)."""
    out = {}
    missions = root / "missions"
    if not missions.is_dir():
        return out
    # Hidden folders are skipped before they are listed: the job renames them while this polls.
    for name in sorted(os.listdir(missions)):
        if name.startswith("."):
            continue
        try:  # a finished folder is replaced whole when its mission is planned again
            for p in (missions / name).glob("*.json"):
                out[name] = json.loads(p.read_text())["properties"]["auv:run_id"]
        except FileNotFoundError:
            continue
    return out


def test_killed_job_resumes_with_every_mission_once(
    tmp_path, stores, killed_processes_semaphores_removed
):
    with_stores(stores, tmp_path)
    job = write_job(tmp_path, n=300, missions=MANY, name="kill")
    root = tmp_path / "cat"
    proc = subprocess.Popen(
        [str(EXE), "run", str(job)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    deadline = time.time() + 400
    while time.time() < deadline and not _items(root) and proc.poll() is None:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)  # the job and its local workers, at once
    proc.wait()
    first = _items(root)
    assert 1 <= len(first) < 8, "the job should be killed halfway"
    again = subprocess.run([str(EXE), "run", str(job)], capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr[-3000:]
    assert f"{len(first)} skipped" in again.stdout
    final = _items(root)
    assert sorted(final) == [f"m{i:02d}" for i in range(8)]  # every mission, once
    assert all(final[k] == v for k, v in first.items())  # finished ones not recomputed
    assert not list((root / "missions").glob(".*tmp*"))  # nothing half-written left
    cat = pystac.Catalog.from_file(str(root / "catalog.json"))
    assert len(list(cat.get_items(recursive=True))) == 8
    # a third run computes nothing, and starts no cluster for it (its workers would log)
    (root / "index.html").unlink()
    idle = subprocess.run([str(EXE), "run", str(job)], capture_output=True, text=True, timeout=600)
    assert idle.returncode == 0, idle.stderr[-3000:]
    assert "0 missions planned, 8 skipped" in idle.stdout
    assert "no cluster started" in idle.stderr
    assert "dask dashboard" not in idle.stderr and "distributed." not in idle.stderr
    assert _items(root) == final and (root / "index.html").exists()


_HOLD_A_LOCK = """
import multiprocessing, sys, time
lock = multiprocessing.get_context("spawn").Lock()
print(lock._semlock.name, flush=True)
time.sleep(60)
"""


@pytest.mark.skipif(not SHM.is_dir(), reason="no /dev/shm")
def test_the_semaphores_of_a_killed_process_are_told_from_live_ones():
    """What the kill tests remove afterwards (conftest.killed_processes_semaphores_removed):
    a real process's named semaphore is orphaned once the process is killed with SIGKILL
    with its process group (its resource tracker too, which would otherwise unlink the
    semaphore: a job's group dies so), never while it lives; this process's own lock is
    never."""
    import multiprocessing

    mine = multiprocessing.get_context("spawn").Lock()
    child = subprocess.Popen(
        [sys.executable, "-c", _HOLD_A_LOCK],
        stdout=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        theirs = "sem." + child.stdout.readline().strip().lstrip("/")
        names = {"sem." + mine._semlock.name.lstrip("/"), theirs}
        assert (SHM / theirs).exists()
        assert orphaned_semaphores(names) == set()
    finally:
        os.killpg(child.pid, signal.SIGKILL)
        child.wait()
    assert orphaned_semaphores(names) == {theirs}
    (SHM / theirs).unlink()


def test_job_on_a_real_scheduler_survives_a_killed_worker(
    tmp_path, stores, killed_processes_semaphores_removed
):
    addr, sched, workers = start_dask_cluster(tmp_path)
    try:
        with_stores(stores, tmp_path)
        job = write_job(tmp_path, n=300, missions=MANY, name="workers")
        root = tmp_path / "cat"
        proc = subprocess.Popen(
            [str(EXE), "run", str(job), "--scheduler", addr],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        deadline = time.time() + 400
        while time.time() < deadline and not _items(root) and proc.poll() is None:
            time.sleep(0.05)
        workers[0].kill()  # SIGKILL one of the two workers mid-job
        out, err = proc.communicate(timeout=600)
        assert proc.returncode == 0, err[-3000:]
        assert "8 missions planned" in out
        final = _items(root)
        assert sorted(final) == [f"m{i:02d}" for i in range(8)]
        assert workers[0].poll() is not None  # it really died
    finally:
        stop_dask_cluster(sched, workers)


def test_demo_job_file_is_valid_and_has_six_or_more_missions():
    job = load_job(ROOT / "tasks" / "demo.toml")
    assert len(job.missions) >= 6
    assert len({m.get("planner", job.planning["planner"]) for m in job.missions}) >= 3
    assert len({m.get("omega", job.planning["omega"]) for m in job.missions}) >= 3


# ------------------------------------------------------------------ nothing stale, nothing lost

TWO = """
[[missions]]
name = "east"
start = [150, 5]
goal = [150, 290]
mcpc = false
[[missions]]
name = "south"
start = [5, 150]
goal = [290, 150]
mcpc = false
"""


def _run_ids(root):
    return {k: v for k, v in _items(root).items()}


def test_a_changed_mission_or_maps_is_planned_again(tmp_path, stores, local_client, caplog):
    with_stores(stores, tmp_path)
    job = write_job(tmp_path, missions=TWO, name="edit")
    root = tmp_path / "cat"
    run_job(job, scheduler=local_client)
    first = _run_ids(root)
    # the goal of one mission edited: that one is planned again, the other is skipped
    job.write_text(job.read_text().replace("goal = [150, 290]", "goal = [140, 280]"))
    with caplog.at_level("INFO", logger="pipeline.jobs.run"):
        res = run_job(job, scheduler=local_client)
    second = _run_ids(root)
    assert res.skipped == 1 and res.replanned == 1 and res.ok
    assert second["south"] == first["south"] and second["east"] != first["east"]
    assert "east: its definition, the maps, the DEM, or the library's defaults" in caplog.text
    item = json.loads((root / "missions" / "east" / "east.json").read_text())
    assert item["properties"]["auv:goal"] == [140, 280]
    # the job's clearance changed: new maps, every mission planned again on them
    job.write_text(job.read_text().replace("clearance = 150.0", "clearance = 200.0"))
    res = run_job(job, scheduler=local_client)
    third = _run_ids(root)
    assert res.replanned == 2 and res.skipped == 0
    assert all(third[k] != second[k] for k in third)
    for mid in ("east", "south"):
        item = json.loads((root / "missions" / mid / f"{mid}.json").read_text())
        assert item["properties"]["auv:min_clearance_m"] >= 200.0 - 1e-2


def test_a_new_default_or_results_revision_plans_finished_missions_again(
    tmp_path, stores, local_client, monkeypatch
):
    """A finished mission is kept only while the code would give the same result: a planning
    default that changed (the job does not set it), or a new RESULTS_REVISION (a planner that
    now returns other paths), plans it again."""
    import pipeline.jobs.job_file
    import pipeline.params

    with_stores(stores, tmp_path)
    job = write_job(tmp_path, missions=TWO, name="rev")
    run_job(job, scheduler=local_client)
    assert run_job(job, scheduler=local_client).skipped == 2
    monkeypatch.setattr(
        "pipeline.jobs.job_file.RESULTS_REVISION", pipeline.jobs.job_file.RESULTS_REVISION + 1
    )
    res = run_job(job, scheduler=local_client)
    assert res.replanned == 2 and res.skipped == 0 and res.ok
    assert run_job(job, scheduler=local_client).skipped == 2
    defaults = pipeline.params.PLANNING.defaults()
    assert "coarse_weight" not in job.read_text() and "coarse_weight" in defaults
    changed = {**defaults, "coarse_weight": defaults["coarse_weight"] + 0.1}
    monkeypatch.setattr(pipeline.params.PLANNING, "defaults", lambda: changed)
    res = run_job(job, scheduler=local_client)
    assert res.replanned == 2 and res.skipped == 0 and res.ok


NAMES = [
    "collection.json",
    "missions.parquet",
    "a#b?c\\\\d",
    "x" * 300,
    "nul\\u0000in",
    "ok",
    "</script><b>bold</b>",
]


def test_any_mission_name_gives_a_catalog_pystac_loads(tmp_path, stores, local_client):
    with_stores(stores, tmp_path)
    missions = "".join(
        f'\n[[missions]]\nname = "{n}"\nstart = [150, {5 + i}]\ngoal = [150, 60]\nmcpc = false\n'
        for i, n in enumerate(NAMES)
    )
    job = write_job(tmp_path, missions=missions, name="names")
    res = run_job(job, scheduler=local_client)
    assert res.ok and res.planned == len(NAMES)
    cat = pystac.Catalog.from_file(str(res.catalog))
    items = list(cat.get_items(recursive=True))
    got = {it.properties["auv:name"] for it in items}
    assert got == {n.encode().decode("unicode_escape") for n in NAMES}
    for it in items:
        it.validate()
        assert all(c.isalnum() or c in "-_" for c in it.id) and len(it.id) <= 91
    assert len({it.id for it in items}) == len(NAMES)
    table = gpd.read_parquet(res.catalog.parent / "missions" / "missions.parquet")
    assert len(table) == len(NAMES)
    # the report shows every name as text: nothing in a name is taken as markup
    from _browser import offline_page

    with offline_page(res.report) as (page, problems):
        shown = page.locator("#missions tbody tr td:first-child").all_inner_texts()
        assert "</script><b>bold</b>" in shown and "ok" in shown and "x" * 300 in shown
        assert page.locator("#missions b").count() == 0
    assert problems == {"failed": [], "external": [], "errors": []}


def test_a_second_run_on_a_busy_catalog_refuses(tmp_path, local_client):
    from pipeline.jobs.run import catalog_lock

    job = write_job(tmp_path, missions="", name="busy")
    with catalog_lock(tmp_path / "cat"):
        with pytest.raises(pipeline.PipelineError, match="is in use by another run"):
            run_job(job, scheduler=local_client)
        proc = console(job, local_client)
    assert proc.returncode == 3, proc.stderr
    assert proc.stderr.count("\n") == 1 and "is in use by another run (pid" in proc.stderr


def test_temporaries_of_killed_runs_go_and_a_no_op_run_keeps_the_report(
    tmp_path, stores, local_client
):
    with_stores(stores, tmp_path)
    root = tmp_path / "cat"
    job = write_job(tmp_path, missions=TWO, name="tmp", performance_report=True)
    run_job(job, scheduler=local_client)
    report = root / "performance-report.html"
    html = report.read_text()
    assert "<script" in html and "cdn.bokeh.org" not in html  # opens offline
    left = [
        root / ".maps-0123.zarr.tmp-ab12cd34",
        root / ".maps-0123.zarr.tmp-ab12cd34-scratch",
        root / "missions" / ".east.tmp-0badf00d",
        next(root.glob("maps-*.zarr")) / ".coarse-rho2.tmp-12345678",
    ]
    for p in left:
        (p / "c").mkdir(parents=True)
    (root / ".performance-report.tmp-0123456789ab.html").write_text("half")
    half = [
        root / "report" / ".hillshade.png.tmp-1234abcd.png",
        root / "report" / ".x.tmp-1a2b3c4d",
    ]
    for p in half:
        p.write_text("half")
    # a user's files that look alike (no random hex tag the tool gives its own) stay
    users = [
        root / ".notes.tmp-1",
        root / "report" / ".draft.tmp-v2",
        root / "missions" / ".x.tmp-",
    ]
    for p in users:
        p.write_text("mine")
    before = report.stat().st_mtime_ns
    shade = (root / "report" / "hillshade.png").stat().st_mtime_ns
    res = run_job(job, scheduler=local_client)  # nothing to do
    assert res.skipped == 2 and res.ran == 0
    assert not any(p.exists() for p in left + half)
    assert all(p.read_text() == "mine" for p in users)
    assert sorted(root.glob(".*.tmp-*")) == [root / ".notes.tmp-1"]
    assert report.stat().st_mtime_ns == before  # the no-op run kept the last report
    # and the hillshade of the same maps store (pipeline.outputs.report.hillshade)
    assert (root / "report" / "hillshade.png").stat().st_mtime_ns == shade
    assert len(list((root / "reports").glob("performance-*.html"))) == 1


def test_a_failed_run_leaves_no_temporary_and_the_next_run_finds_none(
    tmp_path, local_client, caplog
):
    """A run that fails in its maps build (a clearance the Zarr DEM's cells cannot resolve,
    found once the DEM is read) leaves nothing half-written: the next run, fixed, removes no
    temporary and says nothing of killed runs."""
    dem = pipeline.synthetic_dem((60, 60), cell_size=100.0, seed=1, chunks=None)
    dem.to_dataset(name="elevation").to_zarr(tmp_path / "dem.zarr", zarr_format=3)
    text = (
        'name = "failed"\n[dem]\npath = "dem.zarr"\n[maps]\nclearance = {c}\n'
        '[[missions]]\nname = "a"\nstart = [5, 5]\ngoal = [50, 50]\n'
        '[output]\ncatalog = "cat"\nperformance_report = true\n'
    )
    job = tmp_path / "job.toml"
    job.write_text(text.format(c=20))
    with pytest.raises(
        pipeline.JobFileError, match=r"\[maps\]: `clearance` = 20 m is smaller than half"
    ):
        run_job(job, scheduler=local_client)
    assert [p.name for p in (tmp_path / "cat").rglob(".*tmp*")] == []
    job.write_text(text.format(c=150))
    with caplog.at_level("INFO", logger="pipeline.jobs.run"):
        assert run_job(job, scheduler=local_client).ok
    assert "temporaries" not in caplog.text and "killed" not in caplog.text
    assert (tmp_path / "cat" / "performance-report.html").is_file()


NO_OP_RUN = """
import sys
from pipeline.cli import main

HEAVY = ("xarray", "dask.array", "scipy.ndimage")
try:
    main.main(["run", sys.argv[1]], prog_name="pipeline", standalone_mode=True)
except SystemExit as exc:
    print("exit", exc.code)
print("heavy:", sorted(m for m in HEAVY if m in sys.modules))
"""


def test_a_run_on_stores_it_reuses_imports_neither_xarray_nor_dask_array(tmp_path, stores):
    """A job run again on the DEM and maps stores it made (or with a new mission on built
    maps) checks and reuses them without importing xarray or dask.array (about a second of its
    client's start; the first run on a catalog draws the report's hillshade, which takes them).
    This one has nothing to plan, so it starts no cluster either."""
    with_stores(stores, tmp_path)
    job = write_job(tmp_path, missions="", name="reuse")
    for _ in range(2):
        proc = subprocess.run(
            [sys.executable, "-c", NO_OP_RUN, str(job)],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert proc.returncode == 0 and "exit 0" in proc.stdout, proc.stderr
    assert "heavy: []" in proc.stdout, proc.stdout + proc.stderr
    assert proc.stderr.count("is up to date: reusing it") == 2


def test_the_reports_hillshade_is_drawn_once_per_maps_store(tmp_path, stores):
    """A second report on the same maps store reuses the picture the first drew (the same
    pixels as one drawn anew); another store, or a note that does not read, draws it again."""
    from pipeline.outputs.report import hillshade
    from pipeline.store.maps_store import open_store

    src = next(stores.glob("maps-*.zarr"))
    maps = open_store(src)
    png, note = tmp_path / "report" / "hillshade.png", tmp_path / "report" / "hillshade.json"
    first = hillshade(tmp_path, maps)
    drawn = png.stat().st_mtime_ns
    assert hillshade(tmp_path, maps) == first and png.stat().st_mtime_ns == drawn
    assert hillshade(tmp_path / "anew", maps) == first  # drawn in a catalog of its own
    assert np.array_equal(image.imread(png), image.imread(tmp_path / "anew" / "report" / png.name))
    note.write_text("{not json")
    hillshade(tmp_path, maps)
    assert png.stat().st_mtime_ns != drawn
    drawn = png.stat().st_mtime_ns
    import shutil

    other = open_store(shutil.copytree(src, tmp_path / "elsewhere.zarr"))
    assert hillshade(tmp_path, other) == first and png.stat().st_mtime_ns != drawn


def test_a_job_without_the_performance_report_writes_none_and_keeps_the_last(
    tmp_path, stores, local_client
):
    """[output] performance_report = false: the run computes, writes its missions and no dask
    performance report; the report an earlier run left stays as it is."""
    with_stores(stores, tmp_path)
    root = tmp_path / "cat"
    (root / "performance-report.html").write_text("an earlier run's report")
    res = run_job(write_job(tmp_path, missions=TWO, name="quiet"), scheduler=local_client)
    assert res.ok and res.planned == 2
    assert (root / "performance-report.html").read_text() == "an earlier run's report"
    assert not (root / "reports").exists() and not list(root.glob(".performance-report*"))


def test_a_mission_that_cannot_be_written_fails_alone(tmp_path, stores, local_client):
    with_stores(stores, tmp_path)
    job = write_job(tmp_path, missions=TWO, name="unwritable")
    blocker = tmp_path / "cat" / "missions" / "east"
    blocker.parent.mkdir(parents=True)
    blocker.write_text("a file where the mission's folder goes")
    res = run_job(job, scheduler=local_client)
    assert res.failed == ["east"] and res.planned == 1
    assert _items(tmp_path / "cat").keys() == {"south"}  # the other one is written


def test_a_job_reads_only_its_bbox_of_a_dem_file(tmp_path, topobathy_tif, local_client):
    """[dem] bbox: the DEM store holds the region (its lon/lat corners cover the box), the
    region is part of the DEM's definition (another box is another store)."""
    from pyproj import CRS, Transformer

    box = [-124.0, 48.3, -123.2, 48.9]
    job = tmp_path / "job.toml"
    text = f"""
name = "crop"
[dem]
path = "{topobathy_tif}"
bbox = {box}
[maps]
clearance = 2500.0
landmarks = 0
[output]
catalog = "{tmp_path / "cat"}"
"""
    job.write_text(text)
    res = run_job(job, scheduler=local_client)
    assert res.ok and res.planned == 0
    dem = pipeline.open_dem(res.dem_store, chunks=None)
    whole = pipeline.open_dem(topobathy_tif, chunks=None)
    assert dem.size < 0.5 * whole.size
    to_ll = Transformer.from_crs(CRS.from_wkt(dem.attrs["crs_wkt"]), "EPSG:4326", always_xy=True)
    xx, yy = np.meshgrid(dem.x.values[[0, -1]], dem.y.values[[0, -1]])
    lon, lat = to_ll.transform(xx.ravel(), yy.ravel())
    assert lon.min() <= box[0] + 0.02 and lon.max() >= box[2] - 0.02
    assert lat.min() <= box[1] + 0.02 and lat.max() >= box[3] - 0.02
    other = load_job(job)
    job.write_text(text.replace(str(box), str([-124.0, 48.3, -123.3, 48.9])))
    assert load_job(job).dem_fingerprint() != other.dem_fingerprint()


def test_a_job_plans_on_the_shoal_side_of_a_bag(tmp_path, local_client):
    """[dem] uncertainty_k: the job's DEM store holds elevation + k sigma of the BAG's bands
    (read here by rasterio), and k is part of the DEM's definition (another k, another store)."""
    import rasterio

    z = random_surface((40, 50), seed=2)
    sigma = np.random.default_rng(2).uniform(0.0, 10.0, z.shape).astype(np.float32)
    bag = write_bag(tmp_path, z, sigma)
    job = tmp_path / "job.toml"
    text = f"""
name = "survey"
[dem]
path = "{bag}"
uncertainty_k = 3.0
[maps]
clearance = 60.0
landmarks = 0
[output]
catalog = "{tmp_path / "cat"}"
"""
    job.write_text(text)
    res = run_job(job, scheduler=local_client)
    assert res.ok
    with rasterio.open(bag) as src:
        rz, rs = src.read(1), src.read(2)
    dem = pipeline.open_dem(res.dem_store, chunks=None)
    np.testing.assert_array_equal(dem.values, rz + np.float32(3.0) * rs)
    assert dem.attrs["uncertainty_k"] == 3.0
    first = load_job(job).dem_fingerprint()
    job.write_text(text.replace("uncertainty_k = 3.0", "uncertainty_k = 2.0"))
    assert load_job(job).dem_fingerprint() != first


# ------------------------------------------------------------------ failures tried again


def _props(root):
    """The properties of every mission's Item, by id."""
    return {
        p.parent.name: json.loads(p.read_text())["properties"]
        for p in (root / "missions").glob("*/*.json")
        if p.stem == p.parent.name
    }


def test_a_failure_is_tried_again_once_its_cause_is_gone(tmp_path, stores, local_client):
    """A maps store damaged under a run (a chunk of the passable layer overwritten) fails the
    missions that read it; the store repaired, the next run plans them again rather than
    skipping them as finished, and exits 0."""
    with_stores(stores, tmp_path)
    job = write_job(tmp_path, missions=TWO, name="retry")
    chunk = next((tmp_path / "cat").glob("maps-*.zarr")) / "passable" / "c" / "1" / "1"
    good = chunk.read_bytes()
    chunk.write_bytes(b"\x00damaged" * 16)
    res = run_job(job, scheduler=local_client)
    assert sorted(res.failed) == ["east", "south"] and not res.ok
    items = _props(tmp_path / "cat")
    assert {p["auv:status"] for p in items.values()} == {"failed"}
    assert all("damaged" in p["auv:message"] for p in items.values())
    chunk.write_bytes(good)
    res = run_job(job, scheduler=local_client)
    assert res.ok and res.planned == 2 and res.skipped == 0
    assert {p["auv:status"] for p in _props(tmp_path / "cat").values()} == {"ok"}
    assert run_job(job, scheduler=local_client).skipped == 2  # and then finished


def test_a_finished_mission_keeps_its_exit_code_and_its_files(tmp_path, stores, local_client):
    """A re-run counts an uncertified mission as uncertified (exit 5 again, not 1); a mission
    whose file was deleted, truncated or overwritten is planned again; a file damaged under the
    report does not stop the run: the report says so for that mission."""
    with_stores(stores, tmp_path)
    job = write_job(tmp_path, missions=TWO, name="kept")
    root = tmp_path / "cat"
    assert run_job(job, scheduler=local_client).ok
    east = root / "missions" / "east" / "east.json"
    item = json.loads(east.read_text())
    item["properties"]["auv:status"] = "uncertified"  # as a run that could not certify it
    east.write_text(json.dumps(item))
    proc = console(job, local_client)
    assert proc.returncode == 5, proc.stderr
    res = run_job(job, scheduler=local_client)
    assert res.uncertified == ["east"] and not res.failed and res.skipped == 2
    # files gone or changed: planned again
    (root / "missions" / "east" / "track.parquet").unlink()
    csv_file = root / "missions" / "south" / "waypoints.csv"
    csv_file.write_text(csv_file.read_text()[:-20])
    res = run_job(job, scheduler=local_client)
    assert res.planned == 2 and res.skipped == 0 and res.ok
    assert (root / "missions" / "east" / "track.parquet").exists()
    # a Parquet file overwritten in place, its size kept: planned again too
    track = root / "missions" / "south" / "track.parquet"
    size = track.stat().st_size
    track.write_bytes(bytes(size))
    res = run_job(job, scheduler=local_client)
    assert res.planned == 1 and res.skipped == 1 and res.ok
    assert track.read_bytes()[:4] == b"PAR1"
    # a damaged file the checks cannot see (the CSV's content, its size kept) under the
    # report: the run ends, the report names the mission's problem
    wpt = root / "missions" / "east" / "waypoints.csv"
    track = root / "missions" / "east" / "track.parquet"
    raw = bytearray(track.read_bytes())
    raw[-8:-4] = (len(raw) * 2).to_bytes(4, "little")  # a footer longer than the file
    track.write_bytes(bytes(raw))
    assert wpt.exists()
    res = run_job(job, scheduler=local_client)
    assert res.ok and res.skipped == 2
    page = (root / "index.html").read_text()
    assert "its files cannot be read" in page


def test_a_result_that_cannot_be_written_keeps_the_earlier_one(tmp_path, stores, local_client):
    """A mission planned again (its goal edited) on a full disk (a file-size limit stands in
    for it: the writes fail as they do when the disk fills) keeps its earlier Item and files,
    never a failed Item in their place; with the disk back, the next run writes the new one."""
    import resource

    with_stores(stores, tmp_path)
    job = write_job(tmp_path, missions=TWO, name="full")
    root = tmp_path / "cat"
    assert run_job(job, scheduler=local_client).ok
    before = (root / "missions" / "east" / "east.json").read_text()
    job.write_text(job.read_text().replace("goal = [150, 290]", "goal = [140, 280]"))

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (4_000, 4_000))

    proc = console(job, local_client, preexec_fn=limit)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr, proc.stderr
    assert "east: its earlier result is kept" in proc.stderr
    assert (root / "missions" / "east" / "east.json").read_text() == before
    res = run_job(job, scheduler=local_client)
    assert res.ok and res.replanned == 1
    item = json.loads((root / "missions" / "east" / "east.json").read_text())
    assert item["properties"]["auv:goal"] == [140, 280]


def test_sigterm_ends_a_run_in_one_line_and_the_rerun_goes_on(tmp_path):
    """SIGTERM (a scheduler's or a container's stop) while the maps are built: exit 143, one
    line saying so, no traceback and no leaked semaphore; the re-run completes the job."""
    import signal

    job = write_job(tmp_path, missions=TWO, name="term")
    proc = subprocess.Popen(
        [str(EXE), "run", str(job)], stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True
    )
    lines = []
    for line in proc.stderr:
        lines.append(line)
        if "building the maps store" in line:
            proc.send_signal(signal.SIGTERM)
            break
    rest = proc.stderr.read()
    assert proc.wait(timeout=120) == 143, "".join(lines) + rest
    assert "Traceback" not in rest and "semaphore" not in rest, rest
    assert rest.strip().splitlines()[-1].startswith("error: terminated (SIGTERM)")
    proc = subprocess.run([str(EXE), "run", str(job)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert set(_props(tmp_path / "cat")) == {"east", "south"}


def test_ctrl_c_ends_a_run_in_one_line(tmp_path):
    """Ctrl-C as a terminal sends it (SIGINT to every process of the group: the run and its
    workers) while the maps are built: exit 130, one line, no traceback from any worker
    (there were 3-9); the re-run completes the job."""
    import os
    import signal

    job = write_job(tmp_path, missions=TWO, name="intr")
    proc = subprocess.Popen(
        [str(EXE), "run", str(job)],
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
        start_new_session=True,  # its own group, as a terminal's job
        # as a terminal starts it: Ctrl-C not ignored (a pytest-xdist worker ignores it, and an
        # ignored SIGINT is inherited)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    lines = []
    for line in proc.stderr:
        lines.append(line)
        if "building the maps store" in line:
            os.killpg(proc.pid, signal.SIGINT)
            break
    rest = proc.stderr.read()
    assert proc.wait(timeout=120) == 130, "".join(lines) + rest
    assert "Traceback" not in rest and "KeyboardInterrupt" not in rest, rest
    assert rest.strip().splitlines()[-1] == "error: interrupted", rest
    proc = subprocess.run([str(EXE), "run", str(job)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert set(_props(tmp_path / "cat")) == {"east", "south"}


def test_old_stores_and_missions_are_counted_and_pruned_on_request(
    tmp_path, stores, local_client, caplog
):
    """A job whose maps parameters changed and one of whose missions was removed: the run says
    what the catalog holds that the job no longer uses, and removes it only with prune; what
    the job uses and the user's files stay: a folder of their own among the missions (with a
    JSON of its name), their file in a mission folder that is planned again, and their file
    in a pruned mission's folder (the tool's files go, the folder stays with it)."""
    with_stores(stores, tmp_path)
    job = write_job(tmp_path, missions=TWO, name="prune")
    root = tmp_path / "cat"
    run_job(job, scheduler=local_client)
    old_maps = next(root.glob("maps-*.zarr"))
    job.write_text(
        job.read_text()
        .replace("clearance = 150.0", "clearance = 200.0")
        .replace('name = "south"', 'name = "north"')
    )
    (root / "notes.txt").write_text("mine")
    survey = root / "missions" / "my-survey"
    survey.mkdir()
    (survey / "my-survey.json").write_text('{"id": "my-survey", "properties": {}}')
    (survey / "raw.dat").write_bytes(b"\x00" * 100)
    (root / "missions" / "east" / "dive-log.md").write_text("east, mine")
    (root / "missions" / "south" / "dive-log.md").write_text("south, mine")
    with caplog.at_level("INFO", logger="pipeline.jobs.run"):
        res = run_job(job, scheduler=local_client)
    assert res.ok and old_maps.exists() and (root / "missions" / "south").exists()
    # east planned again (a new clearance): its folder replaced, the user's file moved over
    assert (root / "missions" / "east" / "dive-log.md").read_text() == "east, mine"
    assert "holds 2 stores and mission folders the job no longer uses" in caplog.text
    assert "--prune` removes them" in caplog.text
    proc = console(job, local_client, "--prune")
    assert proc.returncode == 0, proc.stderr
    assert "pruned 2 stores and mission folders" in proc.stderr
    assert "kept 1 files of yours in them (south/dive-log.md)" in proc.stderr
    assert not old_maps.exists()
    assert [p.name for p in (root / "missions" / "south").iterdir()] == ["dive-log.md"]
    assert sorted(p.name for p in survey.iterdir()) == ["my-survey.json", "raw.dat"]
    assert (root / "missions" / "east" / "dive-log.md").read_text() == "east, mine"
    assert len(list(root.glob("maps-*.zarr"))) == 1 and len(list(root.glob("dem-*.zarr"))) == 1
    collection = json.loads((root / "missions" / "collection.json").read_text())
    items = {link["href"] for link in collection["links"] if link["rel"] == "item"}
    assert items == {"./east/east.json", "./north/north.json"}
    assert (root / "notes.txt").read_text() == "mine"


def test_a_folder_of_the_users_own_named_as_a_mission_is_never_touched(
    tmp_path, stores, local_client
):
    """A folder the tool did not write where a mission's folder goes (no mark, no Item of the
    tool's): that mission fails, saying so in one line, the folder is left as it was, and the
    other mission completes."""
    with_stores(stores, tmp_path)
    job = write_job(tmp_path, missions=TWO, name="theirs")
    mine = tmp_path / "cat" / "missions" / "east"
    mine.mkdir(parents=True)
    (mine / "raw.dat").write_bytes(b"\x01" * 10)
    (mine / "east.json").write_text('{"note": "my own east survey"}')
    proc = console(job, local_client)
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    assert "missions/east exists and was not written by this tool" in proc.stderr
    assert sorted(p.name for p in mine.iterdir()) == ["east.json", "raw.dat"]
    assert (mine / "east.json").read_text() == '{"note": "my own east survey"}'
    south = json.loads((tmp_path / "cat" / "missions" / "south" / "south.json").read_text())
    assert south["properties"]["auv:status"] in ("ok", "uncertified")
