"""Operational constraints (pipeline.constraints.zones, pipeline.constraints.store).

Keep-out zones: the cells they remove against shapely's brute force, the route, the waypoint
legs and the flown track against the zones themselves (shapely, not the cells), the
certificate against scipy's Dijkstra on the graph without the removed cells, zones in
longitude and latitude on a UTM map, ends in a zone, goals cut off, bad zone files, job files.
The rated depth: the surface, the lengths and the certificate against numpy and scipy on the
raised surface, the flight and the vehicle files as their readers see them (pymavlink). Via
points: the order, the legs and the bound against scipy's Dijkstra per leg, the waypoints."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest
import shapely
from conftest import metric_dataarray, random_surface
from pyproj import Transformer
from references import cell_metrics, optimum, reference_graph

import pipeline
from pipeline.constraints.zones import KeepOut
from pipeline.exceptions import InvalidEndpointError, InvalidParameterError, UnreachableGoalError

A = 30.0
CRS = "EPSG:32629"  # the test maps' x0 = 500 km, y0 = 5000 km: UTM zone 29 north, 9 W
N = 120


@pytest.fixture(scope="module")
def zone_store(tmp_path_factory):
    """A gently rolling deep seabed, N x N cells of 30 m, with a CRS; (path, maps)."""
    import rioxarray  # noqa: F401

    z = random_surface((N, N), seed=5) * 0.3 - 2000.0
    dem = metric_dataarray(z.astype(np.float32), a=A).rio.write_crs(CRS).chunk(40)
    path = tmp_path_factory.mktemp("zones") / "maps.zarr"
    maps = pipeline.build_maps(dem, path, clearance=60.0, landmarks=4)
    return path, maps


def _xy(maps, cell):
    return float(maps.x[cell[1]]), float(maps.y[cell[0]])


def _boxes(maps):
    """Two zones across the straight line from cell (10, 10) to (110, 110)."""
    x0, y0 = _xy(maps, (40, 25))
    x1, y1 = _xy(maps, (55, 70))
    x2, y2 = _xy(maps, (70, 60))
    x3, y3 = _xy(maps, (85, 100))
    return {
        "cable": shapely.box(min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1)),
        "wreck": shapely.box(min(x2, x3), min(y2, y3), max(x2, x3), max(y2, y3)),
    }


def _removed_reference(maps, zones: dict, margin: float):
    """The cells whose closed square comes within margin + a / 4 of a zone, by shapely."""
    X, Y = np.meshgrid(maps.x.values, maps.y.values)
    h = A / 2
    boxes = shapely.box(X - h, Y - h, X + h, Y + h)
    grown = shapely.union_all([g.buffer(margin + A / 4) for g in zones.values()])
    return shapely.intersects(grown, boxes)


# ------------------------------------------------------------------ the cells removed


@pytest.mark.parametrize("margin, ascending", [(0.0, False), (10.0, True), (95.0, False)])
def test_removed_cells_are_those_whose_square_comes_within_the_margin(margin, ascending):
    """KeepOut.blocked against every cell's square tested by shapely: random concave
    polygons, margins below a cell and of several, windows of odd origins and sizes, rows
    ascending or descending."""
    rng = np.random.default_rng(4)
    xs = 300_000.0 + (np.arange(97) + 0.5) * A
    ys = 6_000_000.0 - (np.arange(83) + 0.5) * A
    if ascending:
        ys = ys[::-1]
    zones = []
    for k in range(6):
        cx, cy = rng.uniform(xs[0], xs[-1]), rng.uniform(ys.min(), ys.max())
        t = np.sort(rng.uniform(0, 2 * np.pi, 9))
        r = rng.uniform(10.0, 500.0, 9)  # spikes thinner than a cell too
        zones.append((f"z{k}", shapely.Polygon(np.c_[cx + r * np.cos(t), cy + r * np.sin(t)])))
    ko = KeepOut(tuple(zones), margin)
    grown = shapely.union_all([g.buffer(margin + A / 4) for _, g in zones])
    for r0, r1, c0, c1 in [(0, 83, 0, 97), (7, 8, 3, 97), (11, 60, 29, 30), (40, 83, 51, 96)]:
        X, Y = np.meshgrid(xs[c0:c1], ys[r0:r1])
        want = shapely.intersects(grown, shapely.box(X - A / 2, Y - A / 2, X + A / 2, Y + A / 2))
        got = ko.blocked(xs[c0:c1], ys[r0:r1], A)
        assert np.array_equal(got, want), (r0, r1, c0, c1)
        assert want.any() or (r1 - r0) * (c1 - c0) < 100


_RACE = """
import numpy as np, shapely
from concurrent.futures import ThreadPoolExecutor
from pipeline.constraints.zones import KeepOut
rng = np.random.default_rng(0)
a = 30.0
xs = 500000 + (np.arange(400) + 0.5) * a
ys = 5000000 - (np.arange(400) + 0.5) * a
zones = []
for k in range(20):
    cx, cy = rng.uniform(xs[0], xs[-1]), rng.uniform(ys[-1], ys[0])
    t = np.sort(rng.uniform(0, 2 * np.pi, 7)); r = rng.uniform(100, 900, 7)
    zones.append((f"z{k}", shapely.Polygon(np.c_[cx + r * np.cos(t), cy + r * np.sin(t)])))
ko = KeepOut(tuple(zones), 100.0)
ref = ko.blocked(xs, ys, a)
def job(i):
    r0, c0 = (i * 37) % 300, (i * 53) % 300
    got = ko.blocked(xs[c0:c0 + 100], ys[r0:r0 + 100], a)
    return np.array_equal(got, ref[r0:r0 + 100, c0:c0 + 100])
with ThreadPoolExecutor(8) as ex:
    print("same", all(ex.map(job, range(200))))
"""


def test_cells_are_removed_from_many_threads_at_once():
    """The sections of a mission on threads ask for their windows' removed cells at once:
    GEOS's prepared geometries are not thread-safe (without the lock this process crashed in
    each of three runs), and every window equals the whole map's answer."""
    got = subprocess.run([sys.executable, "-c", _RACE], capture_output=True, text=True)
    assert got.returncode == 0 and "same True" in got.stdout, got.stderr[-2000:]
    assert "Warning" not in got.stderr


# ------------------------------------------------------------------ routes and certificates


@pytest.mark.parametrize("planner, mcpc", [("ra_star", True), ("astar", False)])
def test_a_route_round_the_zones_keeps_the_margin_and_its_certificate(zone_store, planner, mcpc):
    """The grid path, the waypoint legs and the flown track keep the margin from both zones
    (shapely on the continuous lines), the path detours (without zones it crosses them), and
    the certificate holds against scipy's Dijkstra on the graph without the removed cells."""
    path, maps = zone_store
    zones, margin = _boxes(maps), 40.0
    s, g = (10, 10), (110, 110)
    opts = dict(planner=planner, mcpc=mcpc, omega=1.5, rho=4, section_size=24, margin=6)
    free = pipeline.plan(path, s, g, **opts)
    kept = shapely.union_all([z.buffer(margin) for z in zones.values()])
    assert shapely.LineString(free.points[:, :2]).intersects(kept)  # the zones are in the way
    t = pipeline.plan(path, s, g, keep_out=list(zones.values()), keep_out_margin_m=margin, **opts)
    assert t.status == "ok" and t.keep_out is not None
    for name, z in zones.items():
        assert shapely.LineString(t.points[:, :2]).distance(z) >= margin, name
    passable = maps["passable"].values & ~_removed_reference(maps, zones, margin)
    best = optimum(reference_graph(maps["safety"].values, passable, A), passable.shape, s, g)
    assert t.lower_bound_m <= best * (1 + 1e-9)
    assert t.length_m <= 1.5 * best * (1 + 1e-9)
    assert t.length_m > free.length_m
    f = pipeline.fly(path, t, {"min_turn_radius_m": 45.0})
    # the shortcuts were taken round the zones (the flight's corridor lacks their cells), not
    # given up for the path's own corners once they entered one
    assert not f.problems and f.smoothing == "shortcuts"
    track = shapely.LineString(np.c_[f.x, f.y])
    legs = shapely.LineString(f.waypoints[:, :2])
    for name, z in zones.items():
        assert track.distance(z) >= margin and legs.distance(z) >= margin, name


def test_zones_in_lonlat_on_a_utm_map(zone_store, tmp_path):
    """A GeoJSON file in WGS84 (its own CRS) on a UTM map: the route keeps out of the zone
    taken back to UTM by pyproj, and the Item records the zone's name."""
    path, maps = zone_store
    box = _boxes(maps)["cable"]
    to_ll = Transformer.from_crs(CRS, "EPSG:4326", always_xy=True)
    ring = np.array(box.exterior.coords)
    dense = np.vstack([np.linspace(p, q, 20) for p, q in zip(ring[:-1], ring[1:], strict=True)])
    lon, lat = to_ll.transform(dense[:, 0], dense[:, 1])
    doc = {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "properties": {"name": "cable corridor"},
                "geometry": {"type": "Polygon", "coordinates": [np.c_[lon, lat].tolist()]},
            }
        ],
    }
    (tmp_path / "zones.geojson").write_text(json.dumps(doc))
    t = pipeline.plan(path, (10, 10), (110, 110), keep_out=tmp_path / "zones.geojson")
    back = Transformer.from_crs("EPSG:4326", CRS, always_xy=True).transform(lon, lat)
    zone = shapely.Polygon(np.c_[back])
    assert t.status == "ok" and t.keep_out.names == ["cable corridor"]
    assert not shapely.LineString(t.points[:, :2]).intersects(zone)


def _feature_collection(path, zones: dict, crs: str | None = None):
    """A GeoJSON file of the polygons ``zones`` (by name), with a ``crs`` member when given."""
    doc = {
        "type": "FeatureCollection",
        "features": [
            {"type": "Feature", "properties": {"name": k}, "geometry": shapely.geometry.mapping(z)}
            for k, z in zones.items()
        ],
    }
    if crs:
        doc["crs"] = {"type": "name", "properties": {"name": crs}}
    path.write_text(json.dumps(doc))
    return path


def test_zones_never_vanish(zone_store, tmp_path, caplog):
    """Zone files as they come from elsewhere: a GeoJSON in map metres without its ``crs``
    member (read as longitude and latitude by definition) is placed where its coordinates lie
    on the map, with a warning, and the route keeps out of it (shapely); the same coordinates
    off the map are refused in one line; a box of 1e300 metres and a world box in longitude
    and latitude cover the whole map (no route, said so); a zone with its latitude and
    longitude swapped lies off the map and is named in a warning; a ``crs`` member PROJ does not
    know is refused; every layer of a GeoPackage is read."""
    import geopandas as gpd

    path, maps = zone_store
    zones = _boxes(maps)
    bare = _feature_collection(tmp_path / "bare.geojson", zones)
    with caplog.at_level("WARNING", logger="pipeline.constraints.zones"):
        t = pipeline.plan(path, (10, 10), (110, 110), keep_out=bare, keep_out_margin_m=30.0)
    assert (
        "are not longitude and latitude" in caplog.text and "read in the map's CRS" in caplog.text
    )
    assert t.status == "ok" and sorted(t.keep_out.names) == ["cable", "wreck"]
    for z in zones.values():
        assert shapely.LineString(t.points[:, :2]).distance(z) >= 30.0
    far = {k: shapely.affinity.translate(z, 1e6, 0) for k, z in zones.items()}
    f = _feature_collection(tmp_path / "far.geojson", far)
    match = "are not longitude and latitude, as the file's CRS says, and do not lie on the map"
    with pytest.raises(InvalidParameterError, match=match):
        pipeline.plan(path, (10, 10), (110, 110), keep_out=f)
    # a box of 1e300 metres from the origin covers the map: the ends lie in it, said so
    huge = _feature_collection(tmp_path / "huge.geojson", {"huge": shapely.box(0, 0, 1e300, 1e300)})
    with pytest.raises(pipeline.PipelineError, match="lies in keep-out zone 'huge'"):
        pipeline.plan(path, (10, 10), (110, 110), keep_out=huge)
    world = _feature_collection(
        tmp_path / "world.geojson", {"world": shapely.box(-180, -90, 180, 90)}
    )
    with pytest.raises(pipeline.PipelineError, match="world"):
        pipeline.plan(path, (10, 10), (110, 110), keep_out=world)
    # a crs member PROJ does not know (GDAL reads the file as longitude and latitude)
    unknown = json.loads(bare.read_text())
    unknown["crs"] = {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::999999"}}
    (tmp_path / "unknown.geojson").write_text(json.dumps(unknown))
    with pytest.raises(InvalidParameterError, match="names the CRS 'urn:ogc:def:crs:EPSG::999999'"):
        pipeline.plan(path, (10, 10), (110, 110), keep_out=tmp_path / "unknown.geojson")
    to_ll = Transformer.from_crs(CRS, "EPSG:4326", always_xy=True)
    lon, lat = to_ll.transform(*np.array(zones["cable"].exterior.coords).T)
    swapped = _feature_collection(
        tmp_path / "swapped.geojson", {"swapped": shapely.Polygon(np.c_[lat, lon])}
    )
    caplog.clear()
    with caplog.at_level("WARNING", logger="pipeline.constraints.zones"):
        pipeline.plan(path, (10, 10), (110, 110), keep_out=swapped)
    assert "keep-out zone 'swapped'" in caplog.text and "lies off the map" in caplog.text
    gpkg = tmp_path / "two.gpkg"
    for k, (name, z) in enumerate(zones.items()):
        gpd.GeoDataFrame({"name": [name]}, geometry=[z], crs=CRS).to_file(
            gpkg, layer=f"layer{k}", driver="GPKG"
        )
    t = pipeline.plan(path, (10, 10), (110, 110), keep_out=gpkg, keep_out_margin_m=30.0)
    assert sorted(t.keep_out.names) == ["cable", "wreck"]
    for z in zones.values():
        assert shapely.LineString(t.points[:, :2]).distance(z) >= 30.0


# ------------------------------------------------------------------ ends and cut-off goals


def test_an_end_in_a_zone_or_its_margin_names_the_zone(zone_store):
    path, maps = zone_store
    import geopandas as gpd

    zones = _boxes(maps)
    frame = gpd.GeoDataFrame({"name": list(zones)}, geometry=list(zones.values()))
    inside = (47, 50)
    with pytest.raises(
        InvalidEndpointError, match=r"start \(47, 50\) lies in keep-out zone 'cable'"
    ):
        pipeline.plan(path, inside, (110, 110), keep_out=frame)
    x, y = _xy(maps, (110, 110))
    near = {"buoy": shapely.Point(x + 100.0, y).buffer(20.0)}  # the goal 80 m from it
    with pytest.raises(
        InvalidEndpointError, match=r"goal .* 'keep_out\[0\]' or within its margin of 90 m"
    ):
        pipeline.plan(
            path, (10, 10), (110, 110), keep_out=list(near.values()), keep_out_margin_m=90
        )


def test_a_goal_cut_off_by_zones_is_unreachable_at_once_and_the_batch_goes_on(zone_store):
    """A ring of zones round the goal: proven unreachable within a second (the closed region
    round it), named; in plan_missions that mission fails with the reason and the other is
    planned."""
    path, maps = zone_store
    x, y = _xy(maps, (100, 100))
    ring = shapely.Point(x, y).buffer(300.0).difference(shapely.Point(x, y).buffer(200.0))
    t0 = time.perf_counter()
    with pytest.raises(UnreachableGoalError, match="keep-out zones .* close off"):
        pipeline.plan(path, (10, 10), (100, 100), keep_out=[ring])
    assert time.perf_counter() - t0 < 5.0
    ts = pipeline.plan_missions(
        path,
        [
            {"start": (10, 10), "goal": (100, 100), "keep_out": [ring]},
            {"start": (10, 10), "goal": (30, 100), "keep_out": [ring]},
        ],
        client="threads",
    )
    assert ts[0].status == "failed" and "close off" in ts[0].message
    assert ts[1].status == "ok"


# ------------------------------------------------------------------ bad zone files


def _dry_run(job):
    """``pipeline run JOB --dry-run`` in a process of its own, from the job's folder."""
    return subprocess.run(
        [sys.executable, "-m", "pipeline", "run", str(job), "--dry-run"],
        capture_output=True,
        text=True,
        cwd=job.parent,
    )


def _gpkg_without_crs(path):
    import warnings

    import geopandas as gpd

    with warnings.catch_warnings():  # pyogrio: "'crs' was not provided"
        warnings.simplefilter("ignore", UserWarning)
        gpd.GeoDataFrame({"name": ["a"]}, geometry=[shapely.box(0, 0, 1, 1)]).to_file(path)
    return path


def _points(path):
    import geopandas as gpd

    gpd.GeoDataFrame(
        {"name": ["mooring"]}, geometry=[shapely.Point(-9.0, 45.0)], crs="EPSG:4326"
    ).to_file(path)
    return path


BAD = [
    ("missing.geojson", lambda p: p, "does not exist"),
    ("garbage.geojson", lambda p: (p.write_text("{not json"), p)[1], "is not valid GeoJSON"),
    ("garbage.txt", lambda p: (p.write_text("{not json"), p)[1], "cannot be read as a vector"),
    (
        "unclosed.geojson",
        lambda p: (
            p.write_text(
                '{"type": "Polygon", "coordinates": [[[-9, 45], [-8.9, 45], [-8.9, 45.1]]]}'
            ),
            p,
        )[1],
        "is not valid GeoJSON .*; fix the file",
    ),
    ("points.geojson", _points, "'mooring' .* is a Point, not a polygon"),
    ("nocrs.gpkg", _gpkg_without_crs, "has no coordinate reference system"),
]


@pytest.mark.parametrize("name, make, match", BAD, ids=[b[0] for b in BAD])
def test_bad_zone_files_are_one_line_in_the_api_and_the_job(
    zone_store, tmp_path, name, make, match
):
    path, _ = zone_store
    zf = make(tmp_path / name)
    with pytest.raises(InvalidParameterError, match=match):
        pipeline.plan(path, (10, 10), (110, 110), keep_out=zf)
    job = tmp_path / "job.toml"
    job.write_text(
        f'name = "z"\n[dem.synthetic]\nshape = [64, 64]\n[planning]\nkeep_out = ["{name}"]\n'
        '[[missions]]\nstart = [1, 1]\ngoal = [60, 60]\n[output]\ncatalog = "out"\n'
    )
    got = _dry_run(job)
    assert got.returncode == 2, got.stderr
    lines = got.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and "planning.keep_out" in lines[0]
    assert not (tmp_path / "out").exists()


def test_zones_with_a_crs_on_a_map_without_one_say_so(tmp_path):
    dem = pipeline.synthetic_dem((64, 64), cell_size=30.0, seed=1, chunks=None, georeferenced=False)
    pipeline.build_maps(dem, tmp_path / "m.zarr", clearance=60.0, landmarks=0)
    import geopandas as gpd

    zone = gpd.GeoDataFrame(geometry=[shapely.box(-9, 45, -8.9, 45.1)], crs="EPSG:4326")
    with pytest.raises(InvalidParameterError, match="the maps have none"):
        pipeline.plan(tmp_path / "m.zarr", (1, 1), (60, 60), keep_out=zone)


def test_a_job_with_zone_files_plans_round_them_and_records_them(tmp_path, local_client):
    """[planning] keep_out (a file relative to the job, in WGS84) and a mission's own
    keep_out: the job's missions keep out of the zones on a real cluster (the zones read
    once in the client and sent as geometry), each Item names its zones and margin (and a
    via point given in longitude and latitude, its cell and legs; the report draws it), a
    mission whose goal lies in its own zone fails with the zone's name, the other completes;
    a re-run skips the finished one, and plans it again once its zone file changed."""
    import geopandas as gpd

    from pipeline.jobs.run import run_job
    from pipeline.outputs.catalog import finished

    dem = pipeline.synthetic_dem((160, 160), cell_size=30.0, seed=2, chunks=None)
    ll = Transformer.from_crs(dem.attrs["crs_wkt"], "EPSG:4326", always_xy=True)
    x, y = float(dem.x[80]), float(dem.y[80])
    square = shapely.box(x - 450, y - 450, x + 450, y + 450)
    zone = shapely.Polygon(np.c_[ll.transform(*np.array(square.exterior.coords).T)])
    (tmp_path / "z").mkdir()
    gpd.GeoDataFrame({"name": ["exercise area"]}, geometry=[zone], crs="EPSG:4326").to_file(
        tmp_path / "z" / "zones.geojson"
    )
    near = shapely.Polygon(
        np.c_[
            ll.transform(
                *np.array(shapely.box(x - 100, y - 2000, x + 100, y + 2000).exterior.coords).T
            )
        ]
    )
    gpd.GeoDataFrame({"name": ["cable"]}, geometry=[near], crs="EPSG:4326").to_file(
        tmp_path / "z" / "cable.geojson"
    )
    via_ll = ll.transform(float(dem.x[130]), float(dem.y[30]))  # a via point, cell (30, 130)
    job = tmp_path / "job.toml"
    job.write_text(
        'name = "zones"\n[dem]\nchunks = 80\n[dem.synthetic]\nshape = [160, 160]\nseed = 2\n'
        "[maps]\nclearance = 60.0\nlandmarks = 2\n"
        '[planning]\nkeep_out = ["z/zones.geojson"]\nkeep_out_margin_m = 60.0\n'
        "rho = 4\nsection_size = 24\n"
        '[[missions]]\nname = "across"\nstart = [20, 20]\ngoal = [140, 140]\n'
        f"via_lonlat = [[{via_ll[0]!r}, {via_ll[1]!r}]]\n"
        '[[missions]]\nname = "on the cable"\nstart = [20, 20]\ngoal = [80, 80]\n'
        'keep_out = ["z/cable.geojson"]\n'
        '[output]\ncatalog = "out"\nquicklooks = false\nperformance_report = false\n'
    )
    res = run_job(job, scheduler=local_client)
    across = finished(tmp_path / "out", "across")
    cable = finished(tmp_path / "out", "on the cable")
    p = across["properties"]
    assert p["auv:status"] == "ok", p["auv:message"]
    assert p["auv:keep_out"] == ["exercise area"] and p["auv:keep_out_margin_m"] == 60.0
    assert p["auv:via_cells"] == [[30, 130]] and [x["to"] for x in p["auv:legs"]] == [
        "via 1",
        "goal",
    ]
    assert p["auv:via_xy"] == [[round(float(dem.x[130]), 2), round(float(dem.y[30]), 2)]]
    track = gpd.read_parquet(tmp_path / "out" / "missions" / "across" / "track.parquet")
    utm = track.to_crs(dem.attrs["crs_wkt"]) if track.crs is not None else track
    assert shapely.LineString(utm.geometry.get_coordinates().values).distance(square) >= 60.0
    # the zones' file, as GeoJSON readers take it: the zone where it was, in longitude and
    # latitude; the report draws it in Chromium
    got = gpd.read_file(tmp_path / "out" / "missions" / "across" / "keep-out.geojson")
    assert list(got["name"]) == ["exercise area"] and list(got["margin_m"]) == [60.0]
    back = got.to_crs(dem.attrs["crs_wkt"]).geometry[0]
    assert back.hausdorff_distance(square) < 0.01 and "keep-out" in across["assets"]
    from _browser import offline_page

    with offline_page(tmp_path / "out" / "index.html") as (page, problems):
        assert page.locator("path.zone").count() == 1
        assert page.locator("path.track").count() == page.locator("path.via").count() == 1
    assert not any(problems.values()), problems
    q = cable["properties"]
    assert q["auv:status"] == "failed" and "keep-out zone 'cable'" in q["auv:message"]
    assert res.failed == ["on the cable"]
    again = run_job(job, scheduler=local_client)
    assert again.skipped == 1  # the finished one (a failed mission is tried again)
    (tmp_path / "z" / "zones.geojson").write_text(
        (tmp_path / "z" / "zones.geojson").read_text().replace("exercise area", "range")
    )
    third = run_job(job, scheduler=local_client)
    assert third.skipped == 0  # the mission of the changed file planned again
    assert finished(tmp_path / "out", "across")["properties"]["auv:keep_out"] == ["range"]


# ------------------------------------------------------------------ the rated depth


def test_a_rated_depth_raises_the_surface_and_every_file_keeps_it(zone_store, tmp_path):
    """A rating at the median depth of the lowest safe heights (half of them deeper): the
    path's heights are max(S, -D) at its cells (numpy), its length the 3-D length over them,
    its certificate holds against scipy's Dijkstra on the raised surface; the flight never
    goes deeper than D, which binds for a stretch, keeps the clearance; the QGroundControl
    file read by pymavlink and the CSV hold no depth beyond D."""
    import csv

    from pymavlink import mavwp

    path, maps = zone_store
    safety = maps["safety"].values
    depth = float(np.round(-np.nanmedian(safety)))
    assert np.nanmin(safety) < -depth < np.nanmax(safety)  # the rating binds somewhere
    raised = np.maximum(safety, -depth)
    s, g = (10, 10), (110, 110)
    t = pipeline.plan(path, s, g, max_depth_m=depth, omega=1.5, rho=4, section_size=24, margin=6)
    assert t.status == "ok" and t.max_depth_m == depth
    np.testing.assert_array_equal(t.points[:, 2], raised[t.cells[:, 0], t.cells[:, 1]])
    length, _ = cell_metrics(t.cells, raised, maps["ridge"].values, A)
    assert t.length_m == pytest.approx(length, rel=1e-9)
    ok = maps["passable"].values
    best = optimum(reference_graph(raised, ok, A), ok.shape, s, g)
    assert t.lower_bound_m <= best * (1 + 1e-9) and t.length_m <= 1.5 * best * (1 + 1e-9)
    f = pipeline.fly(path, t, {"max_depth_m": depth})
    assert not f.problems and f.max_depth_m == depth
    assert f.z.min() >= -depth - 1e-6 and f.route[:, 2].min() >= -depth - 1e-6
    assert f.at_rated_depth_m > 100.0 and f.min_clearance_m >= 60.0 * (1 - 1e-6)
    files = pipeline.write_mission(path, t, f, tmp_path / "m")
    loader = mavwp.MAVWPLoader()
    loader.load(str(files["qgc"]))
    alts = [loader.wp(k).z for k in range(1, loader.count())]  # -depth (ArduSub)
    assert min(alts) >= -depth - 0.005 and min(alts) < -depth + 1.0
    with open(files["waypoints-csv"], newline="") as fh:
        assert max(float(r["depth_m"]) for r in csv.DictReader(fh)) <= depth + 0.005
    # a batch's vehicle rating plans its missions for it too (as a job's [vehicle] does)
    (b,) = pipeline.plan_missions(
        path, [{"start": s, "goal": g, "omega": 1.5}], vehicle={"max_depth_m": depth}
    )
    assert b.max_depth_m == depth and b.flight.z.min() >= -depth - 1e-6
    assert b.length_m == pytest.approx(cell_metrics(b.cells, raised, maps["ridge"].values, A)[0])


def test_a_rating_no_height_can_keep_is_refused(zone_store, tmp_path):
    """A rated depth shallower than the surface limit (sea level less the surface clearance,
    60 m here): one error in the API, and in a job file before anything is computed."""
    path, _ = zone_store
    with pytest.raises(InvalidParameterError, match=r"rated depth 40 m is shallower than"):
        pipeline.plan(path, (10, 10), (110, 110), max_depth_m=40.0)
    job = tmp_path / "job.toml"
    job.write_text(
        'name = "d"\n[dem.synthetic]\nshape = [64, 64]\n[maps]\nclearance = 60.0\n'
        "[vehicle]\nmax_depth_m = 40.0\n"
        '[[missions]]\nstart = [1, 1]\ngoal = [60, 60]\n[output]\ncatalog = "out"\n'
    )
    got = _dry_run(job)
    assert got.returncode == 2, got.stderr
    assert got.stderr.count("\n") == 1 and "rated depth 40 m" in got.stderr


@pytest.mark.parametrize("sea_level", [200.0, -300.0])
def test_a_rating_is_a_depth_below_the_sea_surface(tmp_path, sea_level):
    """One depth convention: with the sea surface at ``sea_level`` (the DEM's datum elsewhere),
    a rating of D metres keeps every point of the route, the flight and the waypoint CSV at
    most D metres below the sea surface (the CSV's depth column is sea level less z), and the
    rating binds (the free route goes deeper). A rating between the surface clearance and the
    sea level's offset is accepted (it was refused, measured from z = 0)."""
    import csv

    import rioxarray  # noqa: F401

    z = random_surface((80, 80), seed=5) * 0.3 - 2000.0 + sea_level
    dem = metric_dataarray(z.astype(np.float32), a=A).rio.write_crs(CRS)
    path = tmp_path / "maps.zarr"
    maps = pipeline.build_maps(
        dem, path, clearance=60.0, landmarks=0, sea_level=sea_level, surface_clearance=100.0
    )
    s, g = (5, 5), (75, 75)
    free = pipeline.plan(path, s, g, client="synchronous")
    deepest = sea_level - float(free.points[:, 2].min())
    rating = deepest - 200.0
    assert rating > 100.0  # deeper than the surface clearance, so it leaves heights to fly at
    vehicle = {"max_depth_m": rating, "min_turn_radius_m": 30.0}
    (t,) = pipeline.plan_missions(path, [{"start": s, "goal": g}], vehicle=vehicle)
    assert t.status in ("ok", "uncertified"), t.message
    assert sea_level - t.points[:, 2].min() <= rating + 1e-3
    assert sea_level - t.flight.z.min() <= rating + 1e-3 and not t.flight.problems
    folder = tmp_path / "files"
    pipeline.write_mission(maps, t, t.flight, folder)
    with open(folder / "waypoints.csv") as fh:
        depths = [float(row["depth_m"]) for row in csv.DictReader(fh)]
    assert max(depths) <= rating + 0.01 and max(depths) > rating - 50.0
    pipeline.plan(path, s, g, max_depth_m=150.0, client="synchronous")  # 150 >= 100: accepted
    with pytest.raises(InvalidParameterError, match="100 m below the sea surface"):
        pipeline.plan(path, s, g, max_depth_m=90.0)


# ------------------------------------------------------------------ via points


def test_via_points_are_visited_in_order_and_bounded_by_the_legs_optima(zone_store):
    """Through two via points round a zone: the path passes each via cell in order, its
    length is the legs' 3-D lengths (numpy), its bound at most the sum of the legs' optima and
    its length within omega of it (scipy's Dijkstra per leg, the zone's cells removed); the
    flight's waypoints hold each via cell's centre, in order, and its closest approach is the
    track's own."""
    path, maps = zone_store
    zones, margin = _boxes(maps), 40.0
    s, g, via = (10, 10), (110, 110), [(100, 20), (20, 100)]
    t = pipeline.plan(
        path, s, g, via=via, keep_out=list(zones.values()), keep_out_margin_m=margin,
        omega=1.5, rho=4, section_size=24, margin=6,
    )  # fmt: skip
    assert t.status == "ok"
    idx = np.asarray(t.extra["via_index"])
    assert [tuple(c) for c in t.cells[idx]] == via and np.all(np.diff(idx) > 0)
    assert [leg["to"] for leg in t.extra["legs"]] == ["via 1", "via 2", "goal"]
    surface, ridge = maps["safety"].values, maps["ridge"].values
    assert t.length_m == pytest.approx(cell_metrics(t.cells, surface, ridge, A)[0], rel=1e-9)
    ok = maps["passable"].values & ~_removed_reference(maps, zones, margin)
    graph = reference_graph(surface, ok, A)
    ends = [s, *via, g]
    best = sum(optimum(graph, ok.shape, a, b) for a, b in zip(ends[:-1], ends[1:], strict=True))
    assert t.lower_bound_m <= best * (1 + 1e-9) and t.length_m <= 1.5 * best * (1 + 1e-9)
    f = pipeline.fly(path, t, {"min_turn_radius_m": 30.0})
    assert not f.problems
    centres = [_xy(maps, v) for v in via]
    hit = [int(np.flatnonzero(np.hypot(*(f.waypoints[:, :2] - c).T) < 1e-6)[0]) for c in centres]
    assert hit == sorted(hit)
    near = [float(np.hypot(f.x - cx, f.y - cy).min()) for cx, cy in centres]
    np.testing.assert_allclose(f.via_miss_m, near)
    for name, z in zones.items():
        assert shapely.LineString(np.c_[f.x, f.y]).distance(z) >= margin, name


def test_via_points_in_map_coordinates_and_lonlat_are_their_cells(zone_store):
    """via_xy a third of a cell off a cell's centre, via_lonlat of that point (pyproj): the
    same cells as via given as cells, and the same path."""
    path, maps = zone_store
    cells = [(100, 20), (20, 100)]
    xy = [(_xy(maps, c)[0] + A / 3, _xy(maps, c)[1] - A / 3) for c in cells]
    ll = [Transformer.from_crs(CRS, "EPSG:4326", always_xy=True).transform(*p) for p in xy]
    opts = dict(omega=1.5, rho=4, section_size=24, margin=6)
    by_cell = pipeline.plan(path, (10, 10), (110, 110), via=cells, **opts)
    for kw in (dict(via_xy=xy), dict(via_lonlat=ll)):
        t = pipeline.plan(path, (10, 10), (110, 110), **kw, **opts)
        assert np.array_equal(t.cells, by_cell.cells), kw


def test_via_miss_is_measured_to_the_point_as_given(zone_store):
    """A via point given 0.45 cell off its cell's centre on both axes (0.64 cell from it),
    each way: via_miss_m is the track's closest approach to the point as given (numpy), and
    the mission's message says so exactly when that is more than half a cell (at least one
    of the four is)."""
    from pipeline.flight.fly import with_flight

    path, maps = zone_store
    cx, cy = _xy(maps, (100, 20))
    opts = dict(omega=1.5, rho=4, section_size=24, margin=6)
    far = 0
    for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        given = (cx + sx * 0.45 * A, cy + sy * 0.45 * A)
        t = pipeline.plan(path, (10, 10), (110, 110), via_xy=[given], **opts)
        t = with_flight(path, t, {"min_turn_radius_m": 30.0})
        f = t.flight
        near = float(np.hypot(f.x - given[0], f.y - given[1]).min())
        assert f.via_miss_m == pytest.approx([near])
        said = "from via 1 as given, more than half a cell" in (t.message or "")
        assert said == (near > 0.5 * A), (near, t.message)
        far += said
    assert far >= 1


def test_bad_via_points_name_the_point(zone_store):
    path, maps = zone_store
    zones = _boxes(maps)
    with pytest.raises(InvalidEndpointError, match=r"via 2 \(47, 50\) lies in keep-out zone"):
        pipeline.plan(path, (10, 10), (110, 110), via=[(5, 5), (47, 50)], keep_out=[zones["cable"]])
    with pytest.raises(InvalidEndpointError, match="via 1"):
        pipeline.plan(path, (10, 10), (110, 110), via=[(500, 5)])
    with pytest.raises(InvalidParameterError, match="one form"):
        pipeline.plan(path, (10, 10), (110, 110), via=[(5, 5)], via_xy=[(1.0, 2.0)])
    with pytest.raises(InvalidParameterError, match="list of pairs"):
        pipeline.plan(path, (10, 10), (110, 110), via=[5, 5])


def test_a_via_point_on_land_is_named(tmp_path):
    """A via point on a cell that is not passable (an island of the generated scene): one
    error naming it and the nearest passable cell."""
    dem = pipeline.synthetic_dem((96, 96), cell_size=30.0, seed=1, islands=2, chunks=None)
    maps = pipeline.build_maps(dem, tmp_path / "m.zarr", clearance=60.0, landmarks=0)
    ok = maps["passable"].values
    land = tuple(int(v) for v in np.argwhere(~ok)[0])
    s, g = (tuple(int(v) for v in c) for c in np.argwhere(ok)[[0, -1]])
    with pytest.raises(InvalidEndpointError, match=rf"via 1 \({land[0]}, {land[1]}\).*nearest"):
        pipeline.plan(tmp_path / "m.zarr", s, g, via=[land])


def test_the_quicklook_shows_zones_via_points_and_the_rating(zone_store, monkeypatch, tmp_path):
    """The quick-look of a mission under all three constraints, drawn as a job draws it: its
    plan view's legend names the zones, their margin and the via points, its profile draws the
    rated depth at -D and says so in its legend (the figure as matplotlib saves it)."""
    from matplotlib.figure import Figure

    from pipeline.outputs.plots import mission_quicklook

    path, maps = zone_store
    ql = tmp_path / "q.png"
    depth = float(np.round(-np.nanmedian(maps["safety"].values)))
    zones = list(_boxes(maps).values())
    t = pipeline.plan(
        path, (10, 10), (110, 110), via=[(100, 20), (20, 100)], keep_out=zones,
        keep_out_margin_m=40.0, max_depth_m=depth, omega=1.5, rho=4, section_size=24, margin=6,
    )  # fmt: skip
    t = pipeline.jobs.missions.with_flight(
        path, t, {"min_turn_radius_m": 30.0, "max_depth_m": depth}
    )
    saved = []
    save = Figure.savefig
    monkeypatch.setattr(
        Figure, "savefig", lambda self, *a, **k: (saved.append(self), save(self, *a, **k))[1]
    )
    m = pipeline.open_store(path)
    mission_quicklook(m, t, ql, title="constraints", crs_wkt=m.crs_wkt)
    (fig,) = saved
    labels = [
        t.get_text() for ax in fig.axes for leg in [ax.get_legend()] if leg for t in leg.get_texts()
    ]
    assert "keep-out zone" in labels and "its margin (40 m)" in labels
    assert "via points (2, in order)" in labels
    assert any(lab.startswith(f"rated depth ({depth:g} m") for lab in labels)
    profile = fig.axes[-1]
    assert any(np.allclose(line.get_ydata(), -depth) for line in profile.get_lines())
    assert ql.stat().st_size > 10_000


@pytest.fixture(scope="module")
def basin_store(tmp_path_factory):
    """A rough basin deeper everywhere than the rating of :data:`BASIN_DEPTH` less the
    clearance: under the rating its surface is flat, while the landmark layers measure the
    rough one; (path, maps)."""
    from scipy import ndimage

    rng = np.random.default_rng(1)
    z = ndimage.gaussian_filter(rng.normal(size=(90, 90)), 1.5) * 600.0 - 2500.0
    dem = metric_dataarray(z.astype(np.float32), a=A).chunk(32)
    path = tmp_path_factory.mktemp("basin") / "maps.zarr"
    return path, pipeline.build_maps(dem, path, clearance=100.0, landmarks=6)


BASIN_DEPTH = 1000.0


@pytest.mark.parametrize("landmarks", [0, 4])
def test_a_rated_depth_never_certifies_with_the_landmark_layers(
    basin_store, monkeypatch, landmarks
):
    """The landmark layers measure S; the rating shortens every edge it flattens. With the
    landmark heuristics on (the whole-map search reads them) or off, every planner, with MCPC
    and without, returns a length within omega of, and a bound under, scipy's Dijkstra on
    max(S, -D). (With the layers as A*'s heuristic, A* at omega 1 returned "ok" 5 % above the
    optimum on this map, with that length as its proven bound.)"""
    import pipeline.mcpc.plan as mcpc_plan

    monkeypatch.setattr(mcpc_plan, "ACTIVE_LANDMARKS", landmarks)
    path, maps = basin_store
    safety, ok = maps["safety"].values, maps["passable"].values
    assert np.nanmax(safety) < -BASIN_DEPTH  # the rating raises every cell
    raised = np.maximum(safety, np.float32(-BASIN_DEPTH))
    graph = reference_graph(raised, ok, A)
    for s, g in (((3, 3), (86, 86)), ((45, 2), (45, 87)), ((5, 80), (80, 8))):
        best = optimum(graph, ok.shape, s, g)
        assert 0 < best < np.inf
        for planner in ("dijkstra", "astar", "wastar", "ra_star", "lagrangian"):
            omega = 1.0 if planner in ("dijkstra", "astar") else 1.2
            for mcpc in (False, True):
                t = pipeline.plan(
                    path, s, g, planner=planner, omega=omega, max_depth_m=BASIN_DEPTH,
                    mcpc=mcpc, rho=4, section_size=24, margin=6,
                )  # fmt: skip
                where = (planner, mcpc, s, g, t.length_m, t.lower_bound_m, best)
                assert t.status == "ok", where
                assert t.lower_bound_m <= best * (1 + 1e-9), where
                assert t.length_m <= omega * best * (1 + 1e-9), where


@pytest.mark.parametrize("radius, step", [(3.0, 0.5), (1.5, 0.5), (8.0, 0.05)])
def test_the_flown_arcs_keep_the_margin_between_their_samples(radius, step):
    """The flight checks its track against the zones on the polyline through its samples; a
    turn's arc lies outside those chords by up to a sagitta. The true arc (its centre on the
    corner's bisector, tangent to both legs, in numpy), densified: it lies within
    ``arc_sagitta`` of the polyline (shapely), and not far within; a zone placed outside the arc
    within the margin of it, but beyond the margin from every chord, is found with that slack
    and missed without it."""
    from pipeline.flight.geometry import arc_sagitta, arcs

    wr, wc = np.array([0.0, 0.0, 20.0]), np.array([0.0, 20.0, 26.0])  # a turn of 73 degrees
    pr, pc, _, radii, tan_d = arcs(wr, wc, radius, step)
    samples = shapely.LineString(np.c_[pc, pr])
    # the true arc: tangent to both legs at tan_d from the corner, its centre r off each leg
    u = np.array([wr[1] - wr[0], wc[1] - wc[0]]) / np.hypot(wr[1] - wr[0], wc[1] - wc[0])
    v = np.array([wr[2] - wr[1], wc[2] - wc[1]]) / np.hypot(wr[2] - wr[1], wc[2] - wc[1])
    corner = np.array([wr[1], wc[1]])
    t0, t1 = corner - u * tan_d[1], corner + v * tan_d[1]
    side = np.sign(u[0] * v[1] - u[1] * v[0])
    n0 = side * np.array([-u[1], u[0]])
    centre = t0 + n0 * radii[1]
    assert np.hypot(*(t1 - centre)) == pytest.approx(radii[1], rel=1e-9)
    a0, a1 = (np.arctan2(*(p - centre)) for p in (t0, t1))
    a1 = a0 + (a1 - a0 + np.pi) % (2 * np.pi) - np.pi
    ang = np.linspace(a0, a1, 20001)
    arc = centre + radii[1] * np.c_[np.sin(ang), np.cos(ang)]  # (row, col)
    off = shapely.distance(shapely.points(arc[:, 1], arc[:, 0]), samples)
    sag = arc_sagitta(radii, step)
    assert 0.75 * sag <= off.max() <= sag * (1 + 1e-6)
    # a zone outside the arc where it lies farthest from its chords
    k = int(np.argmax(off))
    out = (arc[k] - centre) / radii[1]
    margin = 2.0
    near = arc[k] + out * (margin - 0.5 * off[k])
    zone = shapely.Point(near[1], near[0]).buffer(1e-4 * sag)
    keep = KeepOut((("rock", zone),), margin)
    assert shapely.Point(arc[k, 1], arc[k, 0]).distance(zone) < margin  # the arc enters
    track = (pc, pr)
    assert pipeline.constraints.zones.entered(keep, track) == []  # on the chords alone: missed
    assert pipeline.constraints.zones.entered(keep, track, slack=(sag,)) == ["rock"]


HOSTILE = [
    "</script><script>window.pwned = 1</script>",
    "<!--<script>window.pwned = 2</script>",
    '<img src=x onerror="window.pwned = 3">',
    "a & b \u2028 c \u2029 d ' \"",
]


def test_hostile_names_are_text_in_the_report(tmp_path, local_client):
    """Mission, zone and job names holding markup (as a zone file from elsewhere may): the
    report renders in Chromium with every mission's row in its table and each name shown as the
    text it is (in the table and in the zones' and points' tooltips), and nothing of it runs."""
    import geopandas as gpd

    from pipeline.jobs.run import run_job

    dem = pipeline.synthetic_dem((120, 120), cell_size=30.0, seed=2, chunks=None)
    x, y = float(dem.x[60]), float(dem.y[60])
    (tmp_path / "z").mkdir()
    gpd.GeoDataFrame(
        {"name": HOSTILE[1:3]},
        geometry=[
            shapely.box(x - 200, y + 900, x + 200, y + 1300),
            shapely.box(x, y, x + 90, y + 90),
        ],
        crs=dem.attrs["crs_wkt"],
    ).to_file(tmp_path / "z" / "zones.geojson")
    missions = "".join(
        f"[[missions]]\nname = {json.dumps(name)}\nstart = [10, {10 + 30 * k}]\n"
        f"goal = [110, {20 + 30 * k}]\n"
        for k, name in enumerate(HOSTILE)
    )
    job = tmp_path / "job.toml"
    job.write_text(
        f'name = "evil"\n[dem]\nchunks = 60\n[dem.synthetic]\nshape = [120, 120]\nseed = 2\n'
        "[maps]\nclearance = 60.0\nlandmarks = 2\n"
        '[planning]\nkeep_out = ["z/zones.geojson"]\nkeep_out_margin_m = 30.0\n'
        f"{missions}"
        '[output]\ncatalog = "out"\nquicklooks = false\nperformance_report = false\n'
    )
    res = run_job(job, scheduler=local_client)
    assert res.planned == len(HOSTILE), res
    from _browser import offline_page

    with offline_page(tmp_path / "out" / "index.html") as (page, problems):
        assert page.evaluate("window.pwned") is None
        rows = page.locator("#missions tbody tr")
        assert rows.count() == len(HOSTILE)
        shown = page.locator("#missions tbody").inner_text()
        for name in HOSTILE:
            assert name.split("\u2028")[0] in shown, (name, shown)
        assert page.locator("path.zone").count() == 2 * len(HOSTILE)  # each mission its own
        page.locator("path.zone").first.hover(force=True)
        tips = page.locator(".leaflet-tooltip").all_inner_texts()
        assert any(t.startswith("keep-out zone: <") for t in tips), tips
    assert not any(problems.values()), problems


def test_zones_that_split_a_large_map_are_named(tmp_path):
    """A zone wall across a map larger than the pocket check's windows (1100 cells): the
    mission fails naming the zone as the cause (it said only 'no path on the whole map'), on
    the whole-map search and under MCPC."""
    import geopandas as gpd

    pipeline.build_maps(
        pipeline.synthetic_dem((1100, 1100), chunks=550, islands=0), tmp_path / "m.zarr",
        clearance=60.0, landmarks=2,
    )  # fmt: skip
    maps = pipeline.open_maps(tmp_path / "m.zarr")
    y = float(maps.y[550])
    wall = gpd.GeoDataFrame(
        {"name": ["cable wall"]},
        geometry=[shapely.box(float(maps.x.min()) - 50, y - 40, float(maps.x.max()) + 50, y + 40)],
    )
    for mcpc in (False, True):
        with pytest.raises(pipeline.PipelineError, match="keep-out zones \\(cable wall, kept 30 m"):
            pipeline.plan(
                tmp_path / "m.zarr", (100, 550), (1000, 550), keep_out=wall,
                keep_out_margin_m=30.0, mcpc=mcpc, client="synchronous",
            )  # fmt: skip
