"""Flyable missions (pipeline.flight, pipeline.outputs.files): the flown track and its waypoints
checked against the terrain by brute force (every DEM grid point, scipy's KD-tree), against
scipy's optimum, and every file read back by an independent reader (pymavlink, fastkml,
geopandas, imcpy, pyproj)."""

from __future__ import annotations

import copy
import csv
import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from references import densify, missions, optimum, reference_graph
from scipy.spatial import cKDTree

import pipeline
from pipeline.flight.fly import with_flight
from pipeline.flight.profile import CLEARANCE_SLACK, band_profile, pitch_envelope
from pipeline.flight.vehicle import Vehicle
from pipeline.outputs import files as exports

# ------------------------------------------------------------------ the profile kernels


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000), st.integers(2, 60), st.floats(0.05, 2.0))
def test_pitch_envelope_is_the_lowest_slope_limited_profile(seed, n, slope):
    rng = np.random.default_rng(seed)
    h = rng.normal(size=n) * 100
    h[rng.random(n) < 0.1] = -np.inf  # no constraint there
    h[rng.integers(n)] = 0.0  # at least one constraint
    s = np.cumsum(rng.random(n) * 30)
    z = pitch_envelope(h, s, slope)
    # brute force: z_i = max_j h_j - slope |s_i - s_j|
    ref = np.max(h[None, :] - slope * np.abs(s[:, None] - s[None, :]), axis=1)
    np.testing.assert_allclose(z, ref, rtol=0, atol=1e-9)
    assert np.all(np.abs(np.diff(z)) <= slope * np.diff(s) + 1e-9)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000), st.integers(2, 80), st.floats(0.05, 1.0), st.floats(1, 100))
def test_band_profile_stays_in_its_band_within_the_pitch_limit(seed, n, slope, band):
    rng = np.random.default_rng(seed)
    s = np.cumsum(0.1 + rng.random(n) * 30)
    env = pitch_envelope(rng.normal(size=n) * 200, s, slope)
    z, brk = band_profile(s, env, band, np.inf, np.full(n - 1, slope))
    assert np.all(z >= env - 1e-6) and np.all(z <= env + band + 1e-6)
    assert np.all(np.abs(np.diff(z)) <= slope * np.diff(s) * (1 + 1e-9) + 1e-9)
    assert brk[0] == 0 and brk[-1] == n - 1
    # straight between breaks
    for a, b in zip(brk[:-1], brk[1:], strict=True):
        t = (s[a : b + 1] - s[a]) / (s[b] - s[a])
        np.testing.assert_allclose(z[a : b + 1], z[a] + t * (z[b] - z[a]), atol=1e-6)


# ------------------------------------------------------------------ a real store, real missions


def grid_points(store) -> np.ndarray:
    """Every DEM grid point of the store as (x, y, z), for the brute-force clearance."""
    ds = pipeline.open_maps(store)
    z = ds["elevation"].values.astype(np.float64)
    xx, yy = np.meshgrid(ds["x"].values, ds["y"].values)
    keep = np.isfinite(z)
    return np.column_stack([xx[keep], yy[keep], z[keep]])


def circumradii(x, y) -> np.ndarray:
    """The radius of the circle through every three consecutive points (inf when straight)."""
    a = np.hypot(x[1:-1] - x[:-2], y[1:-1] - y[:-2])
    b = np.hypot(x[2:] - x[1:-1], y[2:] - y[1:-1])
    c = np.hypot(x[2:] - x[:-2], y[2:] - y[:-2])
    cross = (x[1:-1] - x[:-2]) * (y[2:] - y[:-2]) - (y[1:-1] - y[:-2]) * (x[2:] - x[:-2])
    with np.errstate(divide="ignore", invalid="ignore"):
        r = a * b * c / (2 * np.abs(cross))
    return np.where((np.abs(cross) < 1e-9 * a * b) | (a == 0) | (b == 0), np.inf, r)


@pytest.fixture(scope="module")
def ridge_store(tmp_path_factory):
    """A 300^2 synthetic mid-ocean ridge (georeferenced), its maps, scipy's graph, the grid."""
    import dask

    path = tmp_path_factory.mktemp("flight") / "maps.zarr"
    dem = pipeline.synthetic_dem((300, 300), cell_size=50.0, seed=3, chunks=128)
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(dem, path, clearance=150.0, min_accumulation=10, chunks=128)
    ds = pipeline.open_maps(path)
    surface, ok = ds["safety"].values, ds["passable"].values.astype(bool)
    return path, ok, reference_graph(surface, ok, 50.0), grid_points(path)


@pytest.mark.parametrize(
    "planner, omega, vehicle",
    [
        ("ra_star", 2.0, {}),
        ("lagrangian", 1.5, {"max_pitch_deg": 10.0, "min_turn_radius_m": 80.0}),
        ("astar", 1.0, {"max_pitch_deg": 30.0}),
        ("ra_star", 1.2, {"min_turn_radius_m": 20.0}),
    ],
)
def test_flown_tracks_keep_clearance_pitch_turns_and_the_bound(
    ridge_store, planner, omega, vehicle
):
    path, ok, graph, pts = ridge_store
    tree = cKDTree(pts)
    veh = Vehicle.of(vehicle)
    tan = math.tan(math.radians(veh.max_pitch_deg))
    r_min = veh.turn_radius(50.0)
    for s, g in missions(ok, 2, seed=int(omega * 10), min_cells=120):
        t = pipeline.plan(path, s, g, planner=planner, omega=omega, client="synchronous")
        assert t.status == "ok", t.message
        f = pipeline.fly(path, t, veh)
        assert f.ok, f.problems
        # clearance: every DEM grid point at least R from the flown track and from the
        # waypoints' straight legs, sampled every 2.5 m (ten times denser than the flight's own
        # samples: the clearance holds between them too)
        d, _ = tree.query(densify(np.column_stack([f.x, f.y, f.z]), 2.5))
        assert d.min() >= 150.0 * (1 - 1e-9)
        d, _ = tree.query(densify(f.waypoints[:, :3], 2.5))
        assert d.min() >= 150.0 * (1 - 1e-9)
        # pitch, on the track and on the legs
        assert np.all(np.abs(np.diff(f.z)) <= tan * np.hypot(np.diff(f.x), np.diff(f.y)) + 1e-6)
        w = f.waypoints
        assert np.all(
            np.abs(np.diff(w[:, 2])) <= tan * np.hypot(*np.diff(w[:, :2], axis=0).T) + 1e-6
        )
        # samples no more than one cell apart; turns no tighter than the minimum radius
        assert np.hypot(np.diff(f.x), np.diff(f.y)).max() <= 50.0
        assert circumradii(f.x, f.y).min() >= r_min * (1 - 1e-6)
        # the bound against scipy's optimum on the whole fine graph
        opt = optimum(graph, ok.shape, s, g)
        assert f.flown_length_m <= omega * opt * (1 + 1e-9)
        assert f.route_length_m <= omega * opt * (1 + 1e-9)
        # few waypoints, more where the ridges bend (the route keeps their cover)
        assert len(w) < len(t.cells) / 2
        kept = f.ridge_ratio / t.ridge_ratio
        assert kept >= 0.85, kept
        # the ends are the mission's
        assert np.allclose([f.x[0], f.y[0]], t.points[0, :2])
        assert np.allclose([f.x[-1], f.y[-1]], t.points[-1, :2])
        assert f.duration_s == pytest.approx(f.flown_length_m / veh.speed_m_s)


def test_turns_are_widened_where_the_corners_are_too_close(ridge_store):
    """An out-and-back spur (the path reverses) is cut, not flown with a zero radius."""
    from pipeline.flight.geometry import arcs, widen_turns

    path, ok, *_ = ridge_store
    r = np.array([10.0, 10.0, 10.0, 10.0, 30.0], dtype=np.float64)
    c = np.array([10.0, 40.0, 45.0, 40.0, 40.0], dtype=np.float64)
    usable = (np.ones((1, 64, 64), np.uint8), np.zeros((1, 1), np.int64), 64, 64, 64, 64, 0)
    wr, wc = widen_turns(r, c, 1.0, usable)
    assert len(wr) < len(r)
    rad = arcs(wr, wc, 1.0, 0.25)[3]
    assert np.all(rad[np.isfinite(rad)] >= 1.0 - 1e-9)


def bilinear_seabed_points(z, a, step):
    """The continuous seabed, bilinear between the grid points of ``z`` (row 0 at y = 0, rows
    going up in y, cells of ``a``), sampled every ``step`` metres by scipy: (x, y, z) rows."""
    from scipy.interpolate import RegularGridInterpolator

    rows, cols = z.shape
    f = RegularGridInterpolator((np.arange(rows) * a, np.arange(cols) * a), z.astype(np.float64))
    ys = np.arange(0.0, (rows - 1) * a + 1e-9, step)
    xs = np.arange(0.0, (cols - 1) * a + 1e-9, step)
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    zz = f(np.stack([yy, xx], axis=-1))
    return np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()])


@pytest.mark.parametrize("ratio", [0.3, 0.7, 3.0])
@pytest.mark.parametrize("parts", [1, 2, 8])
def test_required_heights_clear_the_bilinear_seabed_between_grid_points(ratio, parts):
    """Random points over a rough seabed whose clearance R is 0.3, 0.7 and 3 cells: at its
    required height a point is at least R from the bilinear seabed (scipy's interpolation,
    sampled every cell / 40, KD-tree), for the whole squares' bound (``required_heights``)
    and for squares cut in 2 x 2 and 8 x 8 parts (``required_heights_fine``); and above the
    tight height (the lowest that clears the sampled seabed) by no more than the seabed's rise
    over two cells for whole squares, over two parts' sides for parts."""
    from pipeline.flight.profile import required_heights, required_heights_fine

    rng = np.random.default_rng(3)
    a, n = 100.0, 24
    radius = ratio * a
    z = (-2000 + 60 * rng.normal(size=(n, n))).astype(np.float32)
    el, slot = z[None].copy(), np.zeros((1, 1), dtype=np.int64)
    pr, pc = rng.uniform(6, n - 7, 300), rng.uniform(6, n - 7, 300)
    args = (el, slot, n, n, n, n, pr, pc, a, radius, 2, radius)
    flags = np.zeros(0, np.uint8)
    if parts == 1:
        h = required_heights(*args, a * math.sqrt(2.0), flags)
    else:
        h = required_heights_fine(*args, 0.0, parts, flags)
    seabed = bilinear_seabed_points(z, a, a / 40)
    xyz = np.column_stack([pc * a, pr * a, h])
    d, _ = cKDTree(seabed).query(xyz)
    assert d.min() >= radius * (1 - 1e-9), d.min()  # (the samples are no nearer than the seabed)
    flat = cKDTree(seabed[:, :2])
    tight = np.array(
        [
            np.max(seabed[i, 2] + np.sqrt(radius**2 - np.sum((seabed[i, :2] - p) ** 2, axis=1)))
            for p, i in zip(xyz[:, :2], flat.query_ball_point(xyz[:, :2], radius), strict=True)
        ]
    )
    rise = max(np.abs(np.diff(z, axis=0)).max(), np.abs(np.diff(z, axis=1)).max())
    assert np.all(h >= tight - 1e-6)
    assert np.max(h - tight) <= 2 * rise / parts, (np.max(h - tight), rise)


# ------------------------------------------------------------------ files, independent readers


@pytest.fixture(scope="module")
def flown(ridge_store, tmp_path_factory):
    path, ok, _, _ = ridge_store
    m = pipeline.open_store(path)
    (s, g), *_ = missions(ok, 1, seed=7, min_cells=150)
    t = pipeline.plan(path, s, g, planner="ra_star", omega=1.5, client="synchronous")
    with_flight(m, t, {"speed_m_s": 2.0})
    folder = tmp_path_factory.mktemp("files")
    files = exports.write_mission_files(folder, "test mission", "test-1", t, m.crs_wkt, 0.0)
    return m, t, folder, files


def test_every_format_is_written(flown):
    _, _, folder, files = flown
    assert set(files) == {"track", "grid-path", "waypoints-csv", "waypoints", "qgc", "kml", "imc"}
    assert all((folder / f[0]).stat().st_size > 0 for f in files.values())


def test_waypoints_geojson_and_csv_read_back(flown):
    import geopandas as gpd
    from pyproj import Transformer

    m, t, folder, _ = flown
    f = t.flight
    gdf = gpd.read_file(folder / "waypoints.geojson")
    pts = gdf[gdf.geometry.geom_type == "Point"]
    assert len(pts) == len(f.waypoints) and gdf.crs.to_epsg() == 4326
    back = Transformer.from_crs("EPSG:4326", m.crs_wkt, always_xy=True)
    x, y = back.transform(pts.geometry.x.values, pts.geometry.y.values)
    np.testing.assert_allclose(x, f.waypoints[:, 0], atol=0.01)
    np.testing.assert_allclose(y, f.waypoints[:, 1], atol=0.01)
    np.testing.assert_allclose(pts.geometry.z.values, f.waypoints[:, 2], atol=0.01)
    np.testing.assert_allclose(pts["depth_m"].values, -f.waypoints[:, 2], atol=0.01)
    with open(folder / "waypoints.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["lat", "lon", "depth_m", "altitude_m", "speed_m_s", "time_s"]
    np.testing.assert_allclose([float(r["lat"]) for r in rows], pts.geometry.y, atol=1e-8)
    np.testing.assert_allclose([float(r["time_s"]) for r in rows], f.waypoints[:, 3], atol=0.06)
    assert all(float(r["speed_m_s"]) == 2.0 for r in rows)
    alt = np.array([float(r["altitude_m"]) for r in rows])
    # the guarantee is 3-D: at least R from every DEM grid point. Above the bilinear seabed
    # under a waypoint that gives at least sqrt(R^2 - (a / sqrt 2)^2): the highest of the four
    # grid points round it is at most a / sqrt 2 away horizontally (R 150 m, a 30 m: 148.49 m)
    a, r = m.cell_size, 150.0
    assert alt.min() >= math.sqrt(r * r - a * a / 2) - 0.01


def test_waypoints_geojson_is_the_json_of_the_rounded_values():
    """The GeoJSON text, formatted in one go, parses (strict JSON: no NaN) to exactly the
    document of the values rounded as documented (lon and lat 8 decimals, heights 2, time 1,
    ``round``), built here as dicts; halfway and negative-zero values included. A value that
    is not finite is null."""
    from pipeline.outputs.files import waypoints_geojson

    rng = np.random.default_rng(11)
    n = 400
    z = rng.normal(-2000.0, 500.0, n)
    z[:6] = [0.125, -0.125, 2.675, -0.0, 1e-9, -1234.565]  # halfway cases, -0, tiny
    table = {
        "index": np.arange(n),
        "lon": rng.uniform(-180.0, 180.0, n),
        "lat": rng.uniform(-90.0, 90.0, n),
        "z": z,
        "depth_m": -z,
        "altitude_m": rng.uniform(0.0, 400.0, n),
        "speed_m_s": np.full(n, 1.7),
        "time_s": np.concatenate(([0.05, 0.15, 0.25], rng.uniform(0.0, 1e5, n - 3))),
    }

    def strict(text):
        return json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in the GeoJSON"))

    def reference(t):
        def num(v, digits=None):
            v = float(v)
            return None if not math.isfinite(v) else v if digits is None else round(v, digits)

        coords = [[num(t["lon"][k], 8), num(t["lat"][k], 8), num(t["z"][k], 2)] for k in range(n)]
        feats = [
            {
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": coords[k]},
                "properties": {
                    "index": k,
                    "depth_m": num(t["depth_m"][k], 2),
                    "altitude_m": num(t["altitude_m"][k], 2),
                    "speed_m_s": num(t["speed_m_s"][k]),
                    "time_s": num(t["time_s"][k], 1),
                },
            }
            for k in range(n)
        ]
        line = {"type": "LineString", "coordinates": coords}
        feats.append({"type": "Feature", "geometry": line, "properties": {"role": "route"}})
        return {"type": "FeatureCollection", "features": feats}

    assert strict(waypoints_geojson(table)) == reference(table)
    table["altitude_m"][7] = np.nan
    got = strict(waypoints_geojson(table))
    assert got["features"][7]["properties"]["altitude_m"] is None
    assert got == reference(table)


def test_track_parquet_is_geoparquet_in_lonlat(flown):
    import geopandas as gpd
    from pyproj import Transformer

    m, t, folder, _ = flown
    f = t.flight
    gdf = gpd.read_parquet(folder / "track.parquet")
    assert gdf.crs.to_epsg() == 4326 and len(gdf) == len(f.x)
    for col in ("x", "y", "z", "altitude_m", "time_s"):
        np.testing.assert_array_equal(gdf[col].values, getattr(f, col))
    # the points are the samples' longitude and latitude (pyproj from the maps' CRS)
    lon, lat = Transformer.from_crs(m.crs_wkt, 4326, always_xy=True).transform(f.x, f.y)
    np.testing.assert_allclose(gdf.geometry.x.values, lon, rtol=0, atol=1e-9)
    np.testing.assert_allclose(gdf.geometry.y.values, lat, rtol=0, atol=1e-9)
    assert set(gdf.geometry.geom_type) == {"Point"}
    grid = gpd.read_parquet(folder / "grid-path.parquet")
    assert len(grid) == len(t.cells) and (grid["row"].values == t.cells[:, 0]).all()
    assert (grid["col"].values == t.cells[:, 1]).all() and grid.crs.to_epsg() == 4326
    lon, lat = Transformer.from_crs(m.crs_wkt, 4326, always_xy=True).transform(
        t.points[:, 0], t.points[:, 1]
    )
    np.testing.assert_allclose(grid.geometry.x.values, lon, rtol=0, atol=1e-9)
    np.testing.assert_allclose(grid.geometry.y.values, lat, rtol=0, atol=1e-9)


def test_qgc_wpl_loads_in_pymavlink(flown):
    from pymavlink import mavutil, mavwp

    _, t, folder, _ = flown
    f = t.flight
    lines = (folder / "mission.waypoints").read_text().splitlines()
    assert lines[0] == "QGC WPL 110" and all(len(ln.split("\t")) == 12 for ln in lines[1:])
    loader = mavwp.MAVWPLoader()
    n = loader.load(str(folder / "mission.waypoints"))
    assert n == len(f.waypoints) + 1  # the home position, then every waypoint
    gj = json.loads((folder / "waypoints.geojson").read_text())["features"][:-1]
    for k, feat in enumerate(gj):
        w = loader.wp(k + 1)
        assert w.command == mavutil.mavlink.MAV_CMD_NAV_WAYPOINT
        assert w.frame == mavutil.mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT
        lon, lat, z = feat["geometry"]["coordinates"]
        assert w.x == pytest.approx(lat, abs=1e-7) and w.y == pytest.approx(lon, abs=1e-7)
        assert w.z == pytest.approx(z, abs=0.02)  # ArduSub: negative below the surface
    # acceptance radii: the turn radius, or half the shorter leg next to a waypoint (so that
    # the vehicle reaches each waypoint before the next one's radius), legs from pyproj
    from pyproj import Geod

    ll = np.array([feat["geometry"]["coordinates"][:2] for feat in gj])
    legs = Geod(ellps="WGS84").inv(ll[:-1, 0], ll[:-1, 1], ll[1:, 0], ll[1:, 1])[2]
    accept = np.array([loader.wp(k + 1).param2 for k in range(len(gj))])
    assert np.all(accept <= f.turn_radius_m + 0.005)
    assert np.all(accept[:-1] + accept[1:] <= legs + 0.05)  # the radii never overlap
    assert (legs < 2 * f.turn_radius_m).any()  # (which one radius for all would not keep)
    assert np.isclose(accept, f.turn_radius_m, atol=0.005).any()


def test_kml_reads_in_fastkml(flown):
    from fastkml import kml

    _, t, folder, _ = flown
    doc = kml.KML.parse(str(folder / "mission.kml"))
    placemarks = []

    def walk(node):
        for ch in getattr(node, "features", []) or []:
            if type(ch).__name__ == "Placemark":
                placemarks.append(ch)
            walk(ch)

    walk(doc)
    lines = [p for p in placemarks if p.geometry.geom_type == "LineString"]
    points = [p for p in placemarks if p.geometry.geom_type == "Point"]
    assert len(points) == len(t.flight.waypoints) and len(lines) == 2
    assert all(p.geometry.has_z for p in points)
    z = np.array([p.geometry.z for p in points])
    np.testing.assert_allclose(z, t.flight.waypoints[:, 2], atol=0.06)


@pytest.mark.parametrize("name", ["bell\x07 tab\t nul\x00", "</name><x>&amp;", "\ufffe\x1f"])
def test_the_files_of_any_mission_name_read_in_their_own_software(flown, tmp_path, name):
    """A mission name with control characters, markup or XML non-characters: the KML parses
    (the standard library's XML parser and fastkml) with the name as text, each character XML
    cannot hold replaced; the GeoJSON and the IMC plan read back."""
    import xml.etree.ElementTree as ET

    import imcpy
    from fastkml import kml

    m, t, _, _ = flown
    files = exports.write_mission_files(tmp_path, name, "odd-1", t, m.crs_wkt, 0.0)
    assert {"kml", "waypoints", "imc"} <= set(files)
    text = (tmp_path / "mission.kml").read_bytes()
    root = ET.fromstring(text)
    shown = root.find(
        "{http://www.opengis.net/kml/2.2}Document/{http://www.opengis.net/kml/2.2}name"
    )
    allowed = {"\t", "\n", "\r"}
    want = "".join(
        c if c in allowed or (" " <= c and c not in "\ufffe\uffff") else "\ufffd" for c in name
    )
    assert shown.text == want
    kml.KML.parse(str(tmp_path / "mission.kml"))
    json.loads((tmp_path / "waypoints.geojson").read_text())
    assert imcpy.Packet.deserialize((tmp_path / "mission.imc").read_bytes()).plan_id == "odd-1"


def test_imc_plan_reads_in_imcpy(flown):
    import imcpy
    from pyproj import Geod

    _, t, folder, _ = flown
    msg = imcpy.Packet.deserialize((folder / "mission.imc").read_bytes())
    assert msg.msg_name == "PlanSpecification" and msg.plan_id == "test-1"
    man = msg.maneuvers[0]
    assert msg.start_man_id == man.maneuver_id
    fp = man.data
    assert fp.msg_name == "FollowPath" and fp.z_units == imcpy.ZUnits.DEPTH
    assert fp.speed == pytest.approx(2.0) and fp.speed_units == imcpy.SpeedUnits.METERS_PS
    gj = json.loads((folder / "waypoints.geojson").read_text())["features"][:-1]
    lon0, lat0, z0 = gj[0]["geometry"]["coordinates"]
    assert math.degrees(fp.lat) == pytest.approx(lat0, abs=1e-8)  # GeoJSON: 8 decimals
    assert math.degrees(fp.lon) == pytest.approx(lon0, abs=1e-8)
    assert fp.z == pytest.approx(-z0, abs=0.01)
    assert len(fp.points) == len(gj)
    geod = Geod(ellps="WGS84")
    for p, feat in zip(fp.points, gj, strict=True):
        lon, lat, z = feat["geometry"]["coordinates"]
        _, _, dist = geod.inv(lon0, lat0, lon, lat)
        assert math.hypot(p.x, p.y) == pytest.approx(dist, abs=0.5)  # the geodesic, metres
        # where DUNE puts the point: within a centimetre of the waypoint
        la, lo = dune_displace(p.x, p.y, fp.lat, fp.lon)
        _, _, off = geod.inv(lon, lat, math.degrees(lo), math.degrees(la))
        assert off < 0.01, off
        assert fp.z + p.z == pytest.approx(-z, abs=0.02)


# LSTS DUNE's WGS84 (src/DUNE/Coordinates/WGS84.hpp), its formulas written anew from its source:
# how DUNE's FollowPath turns a path point's north and east offsets into a position
_DUNE_A, _DUNE_B = 6378137.0, 6356752.3142
_DUNE_E2, _DUNE_EP2 = 0.00669437999013, 0.00673949674228


def _dune_rn(lat):
    return _DUNE_A / math.sqrt(1 - _DUNE_E2 * math.sin(lat) ** 2)


def dune_displace(n, e, lat, lon):
    """DUNE's ``WGS84::displace(n, e, &lat, &lon)`` (radians): the reference (height 0) in
    ECEF, displaced along the north and east of its geocentric latitude, back to geodetic
    by DUNE's ``fromECEF`` (Bowring's formula)."""
    rn = _dune_rn(lat)
    x = rn * math.cos(lat) * math.cos(lon)
    y = rn * math.cos(lat) * math.sin(lon)
    z = (1 - _DUNE_E2) * rn * math.sin(lat)
    phi = math.atan2(z, math.sqrt(x * x + y * y))
    slon, clon, sphi, cphi = math.sin(lon), math.cos(lon), math.sin(phi), math.cos(phi)
    x += -slon * e - clon * sphi * n
    y += clon * e - slon * sphi * n
    z += cphi * n
    p = math.sqrt(x * x + y * y)
    theta = math.atan2(_DUNE_A * z, p * _DUNE_B)
    num = z + _DUNE_EP2 * _DUNE_B * math.sin(theta) ** 3
    den = p - _DUNE_E2 * _DUNE_A * math.cos(theta) ** 3
    return math.atan2(num, den), math.atan2(y, x)


@pytest.mark.parametrize("lat0", [-62.0, 0.5, 38.0, 71.0])
def test_imc_path_points_land_where_dune_puts_them_on_long_missions(lat0):
    """Waypoints up to 520 km from the reference, in every direction, at four latitudes: the
    offsets read back through imcpy and placed by DUNE's formulas land within 1 m of each
    waypoint (the float32 offsets' resolution; rotating the ECEF difference into the
    geodetic north-east frame put them 1-2 km off)."""
    import imcpy
    from pyproj import Geod

    geod = Geod(ellps="WGS84")
    az = np.arange(0, 360, 15.0)
    dist = np.linspace(20e3, 520e3, len(az))
    lon, lat, _ = geod.fwd(np.full(len(az), -30.0), np.full(len(az), lat0), az, dist)
    lat, lon = np.concatenate([[lat0], lat]), np.concatenate([[-30.0], lon])
    n = len(lat)
    table = {"lat": lat, "lon": lon, "depth_m": np.full(n, 900.0), "speed_m_s": np.full(n, 1.5)}
    fp = imcpy.Packet.deserialize(exports.imc_plan("long", "", table)).maneuvers[0].data
    for p, la, lo in zip(fp.points, lat, lon, strict=True):
        dla, dlo = dune_displace(p.x, p.y, fp.lat, fp.lon)
        _, _, off = geod.inv(lo, la, math.degrees(dlo), math.degrees(dla))
        assert off < 1.0, (la, lo, off)


def test_an_imc_plan_too_large_for_one_message_is_refused_with_the_reason(flown, tmp_path):
    """5000 waypoints need 70 kB, over IMC's 16-bit payload size: the plan is refused with
    the reason (the most that fit), not a struct error; a mission's other files are written and
    its Item says why mission.imc is not."""
    n = 5000
    lat, lon = 40 + np.arange(n) * 1e-4, np.full(n, -20.0)
    table = {"lat": lat, "lon": lon, "depth_m": np.full(n, 900.0), "speed_m_s": np.full(n, 1.5)}
    with pytest.raises(exports.PlanTooLargeError, match=r"5000 waypoints .* at most") as e:
        exports.imc_plan("big", "", table)
    import re

    import imcpy

    most = int(re.search(r"at most (\d+) waypoints", str(e.value)).group(1))
    plan = exports.imc_plan("ok", "", {k: v[:most] for k, v in table.items()})
    assert len(imcpy.Packet.deserialize(plan).maneuvers[0].data.points) == most
    with pytest.raises(exports.PlanTooLargeError):
        exports.imc_plan("ok", "", {k: v[: most + 1] for k, v in table.items()})
    # a mission's files: the flight of `flown` with its waypoints split into 5000 along the route
    m, t, _, _ = flown
    f = t.flight
    k = np.linspace(0, len(f.waypoints) - 1, n)
    w = np.column_stack([np.interp(k, np.arange(len(f.waypoints)), c) for c in f.waypoints.T])
    idx = np.interp(k, np.arange(len(f.waypoints)), f.waypoint_index).astype(int)
    big = copy.copy(t)
    big.flight = dataclasses.replace(f, waypoints=w, waypoint_index=idx)
    files = exports.write_mission_files(tmp_path, "big", "big-1", big, m.crs_wkt, 0.0)
    assert "imc" not in files and not (tmp_path / "mission.imc").exists()
    assert files["skipped"].startswith("mission.imc: 5000 waypoints")
    assert {"waypoints", "qgc", "kml", "track"} <= set(files)


# ------------------------------------------------------------------ the vehicle, jobs


def test_vehicle_bad_values_say_what_is_wrong():
    with pytest.raises(pipeline.InvalidParameterError, match="vehicle.max_pitch_deg"):
        Vehicle(max_pitch_deg=0)
    with pytest.raises(pipeline.InvalidParameterError, match="without a power"):
        Vehicle(battery_wh=100)
    with pytest.raises(pipeline.InvalidParameterError, match="unknown vehicle key"):
        Vehicle.of({"speed": 2})
    assert Vehicle().turn_radius(30.0) == 30.0 and Vehicle().turn_radius(200.0) == 50.0


def test_synthetic_maps_are_georeferenced_on_the_mid_atlantic_ridge():
    from pyproj import Transformer

    dem = pipeline.synthetic_dem((100, 200), cell_size=30.0, chunks=None)
    tr = Transformer.from_crs(dem.attrs["crs_wkt"], "EPSG:4326", always_xy=True)
    lon, lat = tr.transform(200 * 30.0 / 2, 100 * 30.0 / 2)
    assert lon == pytest.approx(-44.83, abs=1e-9) and lat == pytest.approx(26.14, abs=1e-9)
    assert "crs_wkt" not in pipeline.synthetic_dem((10, 10), chunks=None, georeferenced=False).attrs


JOB = """
name = "fly"
[dem]
chunks = 128
[dem.synthetic]
shape = [300, 300]
cell_size = 50.0
seed = 3
[maps]
clearance = 150.0
min_accumulation = 10
[planning]
omega = 1.5
[vehicle]
speed_m_s = 2.0
hotel_power_w = 40.0
propulsion_power_w = 100.0
battery_wh = 100000.0
[[missions]]
name = "fits"
start = [20, 20]
goal = [280, 260]
[[missions]]
name = "flat-battery"
start = [20, 20]
goal = [280, 260]
vehicle = { battery_wh = 50.0 }
[output]
catalog = "cat"
quicklooks = false         # the quick-look is tested with the other job tests
performance_report = false
"""


def test_a_job_flies_its_missions_and_fails_one_over_its_endurance(tmp_path, local_client):
    import pystac
    from pyproj import Transformer

    (tmp_path / "fly.toml").write_text(JOB)
    res = pipeline.run_job(tmp_path / "fly.toml", scheduler=local_client)
    assert res.failed == ["flat-battery"]
    cat = pystac.Catalog.from_file(str(tmp_path / "cat" / "catalog.json"))
    items = {it.id: it for it in cat.get_items(recursive=True)}
    good, flat = items["fits"], items["flat-battery"]
    p = good.properties
    assert p["auv:status"] == "ok" and p["auv:waypoints"] >= 2
    assert p["auv:energy_wh"] == pytest.approx(140.0 * p["auv:duration_s"] / 3600)
    assert p["auv:flown_length_m"] <= 1.5 * p["auv:lower_bound_m"] * (1 + 1e-9)
    for key in ("track", "grid-path", "waypoints", "waypoints-csv", "qgc", "kml", "imc"):
        assert key in good.assets, key
    # WGS84 geometry; the projection extension gives the maps' CRS and the track's box in it
    lon, lat = np.array(good.geometry["coordinates"]).T
    assert -46 < lon.min() < lon.max() < -44 and 25 < lat.min() < lat.max() < 27
    proj = p["proj:wkt2"] if p.get("proj:code") is None else p["proj:code"]
    x0, y0, x1, y1 = p["proj:bbox"]
    tr = Transformer.from_crs(proj, "EPSG:4326", always_xy=True)
    blon, blat = tr.transform([x0, x1], [y0, y1])
    assert good.bbox[0] >= min(blon) - 1e-3 and good.bbox[2] <= max(blon) + 1e-3
    assert flat.properties["auv:status"] == "failed"
    assert "battery" in flat.properties["auv:message"] and "track" in flat.assets
    good.validate()  # the core schema and the projection extension's (tests/data, offline)
    flat.validate()


def test_a_bad_vehicle_table_is_one_clear_line(tmp_path):
    bad = JOB.replace("speed_m_s = 2.0", "speed = 2.0")
    (tmp_path / "bad.toml").write_text(bad)
    proc = subprocess.run(
        [str(Path(sys.executable).with_name("pipeline")), "run", str(tmp_path / "bad.toml")],
        capture_output=True,
        text=True,
    )
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert "unknown key vehicle.'speed'" in proc.stderr or "vehicle.'speed'" in proc.stderr
    bad = JOB.replace("hotel_power_w = 40.0\npropulsion_power_w = 100.0\n", "")
    (tmp_path / "bad2.toml").write_text(bad)
    with pytest.raises(pipeline.JobFileError, match="without a power"):
        pipeline.jobs.job_file.load_job(tmp_path / "bad2.toml")


def test_no_data_holes_and_no_crs(tmp_path):
    """Terrain with no-data holes and no CRS: the flight never passes where the terrain is
    unknown (clearance checked against the known grid points), says where a no-data point's
    grid squares come within the clearance, and only the files in map coordinates are
    written, the Item saying which were skipped."""
    import dask
    from conftest import metric_dataarray, random_surface

    z = random_surface((160, 160), seed=4, holes=True)
    dem = metric_dataarray(z, a=50.0)
    dem.attrs["cell_size"] = 50.0
    path = tmp_path / "maps.zarr"
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(dem.chunk(64), path, clearance=120.0, min_accumulation=6)
    ds = pipeline.open_maps(path)
    ok = ds["passable"].values.astype(bool)
    tree = cKDTree(grid_points(path))
    m = pipeline.open_store(path)
    assert m.crs_wkt is None
    unsure = []
    for s, g in missions(ok, 3, seed=2, min_cells=80):
        t = pipeline.plan(path, s, g, planner="ra_star", omega=1.5, client="synchronous")
        f = pipeline.fly(path, t)
        assert f.ok, f.problems
        assert np.isfinite(f.required_m).all()
        assert tree.query(np.column_stack([f.x, f.y, f.z]))[0].min() >= 120.0 * (1 - 1e-9)
        unsure.append(f.unknown_seabed_samples)
    # the scattered no-data cells lie beyond R of the path's cells, but their grid squares come
    # within R of the route between them: said, with how many samples
    assert all(unsure)
    with_flight(m, t, {})
    assert (
        f"seabed is unknown (a no-data grid point's squares) within the clearance of {unsure[-1]} "
        in t.message
    )
    files = exports.write_mission_files(tmp_path, "m", "m", t, None, 0.0)
    assert set(files) == {"track", "grid-path", "waypoints-csv"}
    import geopandas as gpd

    track = gpd.read_parquet(tmp_path / "track.parquet")  # in map coordinates, no CRS
    assert track.crs is None and len(track) == len(t.flight.x)
    np.testing.assert_array_equal(track.geometry.x.values, t.flight.x)
    np.testing.assert_array_equal(track.geometry.y.values, t.flight.y)
    with open(tmp_path / "waypoints.csv") as fh:
        assert fh.readline().strip() == "x_m,y_m,depth_m,altitude_m,speed_m_s,time_s"


def test_a_fault_in_one_flight_fails_that_mission_only(ridge_store, monkeypatch):
    """A bug in the flight of one mission (a fault injected into it) fails that mission with
    the reason, keeps its planned path, and the batch goes on."""
    import pipeline.jobs.missions as pm

    path, ok, *_ = ridge_store
    real = pm.with_flight
    calls = []

    def faulty(maps, traj, vehicle=None):
        calls.append(1)
        if len(calls) == 1:
            raise IndexError("injected")
        return real(maps, traj, vehicle)

    monkeypatch.setattr(pm, "with_flight", faulty)
    (a, b), (c, d) = missions(ok, 2, seed=11, min_cells=100)
    ts = pipeline.plan_missions(
        path, [(a, b), (c, d)], client="synchronous", vehicle={}, max_concurrent=1
    )
    assert [t.status for t in ts] == ["failed", "ok"]
    assert "IndexError: injected" in ts[0].message and len(ts[0].cells) > 1
    assert ts[1].flight is not None and ts[0].flight is None


def test_a_flight_over_the_bound_alone_is_uncertified_with_the_reason(ridge_store):
    """When the only fault of every smoothing is a flown length above omega x the proven bound
    (here a bound made too small to hold), the mission is uncertified, not failed, and says
    why; the flight is kept."""
    from dataclasses import replace

    path, ok, *_ = ridge_store
    (s, g), *_ = missions(ok, 1, seed=5, min_cells=120)
    t = pipeline.plan(path, s, g, planner="astar", omega=1.0, client="synchronous")
    tight = replace(t, lower_bound_m=0.5 * t.length_m, extra=dict(t.extra))
    with_flight(path, tight, {})
    assert tight.status == "uncertified" and tight.flight is not None
    assert tight.message.startswith("the flown length") and tight.flight.over_bound
    assert tight.flight.problems == [tight.flight.over_bound]


def test_a_mission_whose_start_is_its_goal_says_it_has_nothing_to_fly(ridge_store, tmp_path):
    """start == goal: planned (one cell, length 0), no flight and no waypoint files, and its
    message says why (it said nothing, where every other mission of a job with a vehicle has
    waypoints)."""
    path, ok, *_ = ridge_store
    cell = tuple(int(v) for v in np.argwhere(ok)[len(np.argwhere(ok)) // 2])
    (t,) = pipeline.plan_missions(path, [(cell, cell)], client="synchronous", vehicle={})
    assert t.status == "ok" and len(t.cells) == 1 and t.length_m == 0.0
    assert t.flight is None
    assert t.message == "start and goal are the same cell: nothing to fly, no waypoints"


@pytest.mark.parametrize("method, tile", [(2, 16), (1, 16), (2, 12), (2, 6), (2, 5)])
def test_required_heights_equal_a_brute_force_along_a_track(method, tile):
    """The required heights read the elevation in blocks and pass over those that cannot raise
    the best value so far: along a winding track (each point next to the last, as the flight
    samples it), over rough terrain with no-data holes, unloaded tiles and the map's edges,
    they equal the maximum over every grid point within the radius and a grid square's
    diagonal (numpy), NaN wherever a grid point within that is not loaded or a no-data point
    within the radius; a point flagged where a no-data point's grid squares, not the point
    itself, come within the radius."""
    from pipeline.flight.profile import required_heights

    rng = np.random.default_rng(7)
    rows, cols, a, radius, clearance = 90, 75, 30.0, 260.0, 100.0
    z = rng.normal(0.0, 40.0, (rows, cols)) + 300.0 * np.sin(np.arange(cols) / 9.0)
    z[rng.random((rows, cols)) < 0.002] = np.nan  # no-data cells
    z[40:44, 10:13] = np.nan
    z = z.astype(np.float32)
    nti, ntj = -(-rows // tile), -(-cols // tile)
    slot = np.arange(nti * ntj).reshape(nti, ntj)
    slot[nti - 1, 0] = -1  # a tile not loaded: unknown
    el = np.full((nti * ntj, tile, tile), np.nan, dtype=np.float32)
    for ti in range(nti):
        for tj in range(ntj):
            blk = z[ti * tile : (ti + 1) * tile, tj * tile : (tj + 1) * tile]
            el[slot[ti, tj], : blk.shape[0], : blk.shape[1]] = blk
    known = z.astype(np.float64)
    unloaded = np.zeros((rows, cols), dtype=bool)
    unloaded[(nti - 1) * tile :, :tile] = True
    s = np.linspace(0.0, 1.0, 1500)
    pr = -0.4 + (rows - 0.2) * s + 8.0 * np.sin(19.0 * s)
    pc = (cols - 1) * (0.5 + 0.49 * np.sin(7.0 * s))
    reach = a * math.sqrt(2.0)  # the grid squares' diagonal
    partial = np.zeros(len(pr), dtype=np.uint8)
    h = required_heights(
        el, slot, tile, tile, rows, cols, pr, pc, a, radius, method, clearance, reach, partial
    )  # fmt: skip
    ii, jj = np.mgrid[0:rows, 0:cols]
    for k in range(len(pr)):
        d2 = a * a * ((ii - pr[k]) ** 2 + (jj - pc[k]) ** 2)
        near = d2 <= (radius + reach) ** 2
        # a no-data point's four squares: their least distance from the point
        box2 = (
            a
            * a
            * (
                np.maximum(np.abs(ii - pr[k]) - 1, 0) ** 2
                + np.maximum(np.abs(jj - pc[k]) - 1, 0) ** 2
            )
        )
        good = near & ~unloaded & np.isfinite(known)
        # unknown within the radius: no height; beyond, squares within it: a partial flag
        if (near & unloaded).any() or (np.isnan(known) & (d2 < radius**2)).any():
            ref = np.nan
        elif not good.any():
            ref = -np.inf
        elif method == 2:
            lift = np.maximum(np.sqrt(d2[good]) - reach, 0.0)
            ref = np.max(known[good] + np.sqrt(np.maximum(radius**2 - lift**2, 0.0)))
        else:
            ref = np.max(known[good]) + clearance
        if np.isnan(ref):
            assert np.isnan(h[k]), k
        else:
            assert h[k] == pytest.approx(ref, rel=0, abs=1e-9), k
            assert partial[k] == (np.isnan(known) & (box2 < radius**2)).any(), k
    assert np.isnan(h).any() and np.isfinite(h).sum() > len(h) // 2


@pytest.mark.parametrize("shape, chunks", [((257, 257), 64), ((130, 200), 64), ((70, 9), 8)])
def test_corridor_reads_equal_the_layers_for_awkward_chunkings(tmp_path, shape, chunks):
    """The flight reads the terrain through store chunks stacked as tiles: on chunkings with a
    last chunk of one cell or a side modulo the chunk below the clearance radius, every layer
    read that way equals the layer, and the required heights off the grid equal a brute force
    over the whole elevation array (numpy)."""
    import dask

    from pipeline.flight.geometry import Corridor
    from pipeline.flight.profile import required_heights

    dem = pipeline.synthetic_dem(shape, cell_size=50.0, seed=2, chunks=chunks, islands=0)
    path = tmp_path / "maps.zarr"
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(
            dem, path, clearance=120.0, min_accumulation=6, chunks=chunks, landmarks=0
        )
    m = pipeline.open_store(path)
    ds = pipeline.open_maps(path)
    rows, cols = shape
    cells = np.argwhere(np.ones(shape, dtype=bool))
    cor = Corridor(m, cells, 4)
    i, j = cells[:, 0], cells[:, 1]
    slot = cor.slot[i // cor.tr, j // cor.tc]
    for tiles, var in ((cor.el, "elevation"), (cor.pas, "passable"), (cor.rdg, "ridge")):
        got = tiles[slot, i % cor.tr, j % cor.tc].reshape(shape)
        np.testing.assert_array_equal(got, ds[var].values.astype(tiles.dtype))
    rng = np.random.default_rng(1)
    pr = rng.uniform(-0.5, rows - 0.5, 300)
    pc = rng.uniform(-0.5, cols - 0.5, 300)
    pr[:4], pc[:4] = [rows - 1, rows - 1, 0, rows - 1.3], [cols - 1, 0, cols - 1, cols - 1.2]
    flags = np.zeros(0, np.uint8)
    h = required_heights(
        cor.el, cor.slot, cor.tr, cor.tc, rows, cols, pr, pc, 50.0, 120.0, 2, 0.0, 0.0, flags
    )  # fmt: skip
    z = ds["elevation"].values.astype(np.float64)
    ii, jj = np.mgrid[0:rows, 0:cols]
    for k in range(len(pr)):
        d2 = 2500.0 * ((ii - pr[k]) ** 2 + (jj - pc[k]) ** 2)
        near = d2 <= 120.0**2
        ref = np.max(z[near] + np.sqrt(120.0**2 - d2[near])) if near.any() else -np.inf
        assert h[k] == pytest.approx(ref, rel=0, abs=1e-9)


@pytest.mark.parametrize("crs", ["lonlat", "map CRS", "none"])
def test_point_geoparquet_is_the_file_geoarrow_writes(tmp_path, crs):
    """The track and grid path files' writer against geoarrow-pyarrow's GeoParquet writer on
    the same columns and points: the same `geo` metadata (geometry type, CRS as PROJJSON or
    null, bounding box; the version geopandas writes), the same WKB points, the same
    columns."""
    import json

    import geoarrow.pyarrow as ga
    import pyarrow as pa
    import pyarrow.parquet as pq
    import pyproj
    from geoarrow.pyarrow.io import write_geoparquet_table

    rng = np.random.default_rng(5)
    n = 1001
    x, y = rng.uniform(1e5, 2e5, n), rng.uniform(3e6, 3.1e6, n)
    cols = {"x": x, "y": y, "z": rng.normal(-2000, 300, n), "row": np.arange(n)}
    wkt = pyproj.CRS.from_epsg(32623).to_wkt()
    lonlat = pyproj.Transformer.from_crs(wkt, 4326, always_xy=True).transform(x, y)
    gx, gy, given, ref_crs = {
        "lonlat": (*lonlat, lonlat, "EPSG:4326"),
        "map CRS": (x, y, None, wkt),
        "none": (x, y, None, None),
    }[crs]
    exports._write_points(
        tmp_path / "ours.parquet", cols, x, y, given, None if crs == "none" else wkt
    )
    geom = ga.point().from_geobuffers(None, np.asarray(gx), np.asarray(gy))
    if ref_crs:
        geom = ga.with_crs(geom, ref_crs)
    ref = pa.table({**cols, "geometry": ga.as_wkb(geom)})
    write_geoparquet_table(
        ref, tmp_path / "ref.parquet", write_bbox=True, write_geometry_types=True
    )
    ours, theirs = pq.read_table(tmp_path / "ours.parquet"), pq.read_table(tmp_path / "ref.parquet")
    meta = [json.loads(t.schema.metadata[b"geo"]) for t in (ours, theirs)]
    # the version: the one geopandas writes (the catalog's missions table), geoarrow's older
    import geopandas as gpd

    gpd.GeoDataFrame(geometry=gpd.points_from_xy([0.0], [0.0])).to_parquet(tmp_path / "gp.pq")
    geopandas_version = json.loads(pq.read_schema(tmp_path / "gp.pq").metadata[b"geo"])["version"]
    assert meta[0].pop("version") == geopandas_version
    meta[1].pop("version")
    assert meta[0] == meta[1]
    for name in (*cols, "geometry"):
        assert ours.column(name).to_pylist() == theirs.column(name).to_pylist(), name


def test_a_shortcut_leg_is_allowed_by_its_two_rules():
    """``leg_allowed`` walks a leg once and stops early; it equals the rules written out
    (numpy): every cell its samples (4 a cell) pass is passable with the terrain loaded within
    the pad, a diagonal step cuts no corner, and its off-ridge length (midpoint samples) is at
    most the path's plus half a cell plus the share (at most a tenth of the path's ridge
    length there), at a rate at most the path's plus the share (at most a tenth of the path's
    ridge share). Over random legs on tiles with unloaded ones and the map's edge."""
    from pipeline.flight.geometry import leg_allowed

    rng = np.random.default_rng(3)
    rows, cols, tile, pad, share = 30, 27, 8, 2, 0.02
    nti, ntj = -(-rows // tile), -(-cols // tile)
    slot = np.arange(nti * ntj).reshape(nti, ntj)
    slot[0, ntj - 1] = -1
    slot[nti - 1, 1] = -1
    pas = (rng.random((nti * ntj, tile, tile)) < 0.93).astype(np.uint8)
    rdg = (rng.random((nti * ntj, tile, tile)) < 0.6).astype(np.uint8)
    n = 60
    pr = rng.uniform(-1.0, rows, n)
    pc = rng.uniform(-1.0, cols, n)
    along = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(pr), np.diff(pc)))))
    off = np.concatenate(([0.0], np.cumsum(rng.uniform(0.0, 1.0, n - 1) * np.diff(along))))

    def usable(i, j):
        if not (0 <= i < rows and 0 <= j < cols) or slot[i // tile, j // tile] < 0:
            return False
        if not pas[slot[i // tile, j // tile], i % tile, j % tile]:
            return False
        box = [(min(max(i + di, 0), rows - 1), min(max(j + dj, 0), cols - 1))
               for di in (-pad, pad) for dj in (-pad, pad)]  # fmt: skip
        return all(slot[p // tile, q // tile] >= 0 for p, q in box)

    def reference(i, j):
        dr, dc = pr[j] - pr[i], pc[j] - pc[i]
        m = max(1, math.ceil(max(abs(dr), abs(dc)) * 4.0))
        t = np.arange(m + 1) / m
        cells = np.floor(np.column_stack([pr[i] + t * dr, pc[i] + t * dc]) + 0.5).astype(int)
        keep = np.concatenate(([True], np.any(cells[1:] != cells[:-1], axis=1)))
        cells = cells[keep]
        ok = all(usable(r, c) for r, c in cells)
        for (r0, c0), (r1, c1) in zip(cells[:-1], cells[1:], strict=True):
            if r0 != r1 and c0 != c1:
                ok = ok and usable(r0, c1) and usable(r1, c0)
        tm = (np.arange(m) + 0.5) / m
        mid = np.floor(np.column_stack([pr[i] + tm * dr, pc[i] + tm * dc]) + 0.5).astype(int)
        on = [
            0 <= r < nti * tile and 0 <= c < ntj * tile and slot[r // tile, c // tile] >= 0
            and bool(rdg[slot[r // tile, c // tile], r % tile, c % tile])
            for r, c in mid
        ]  # fmt: skip
        seg = float(np.sum(~np.array(on))) * math.hypot(dr, dc) / m
        ln, path = math.hypot(dr, dc), off[j] - off[i]
        span = along[j] - along[i]
        rate = path / span
        # (the slack at most a tenth of the path's ridge length and of its ridge share there)
        ridge_ok = seg <= path + min(0.5 + share * ln, 0.1 * (span - path)) + 1e-9 * ln
        rate_ok = seg / ln <= rate + min(share, 0.1 * (1 - rate)) + 1e-9
        return ok, ok and ridge_ok and rate_ok

    outcomes = set()
    for _ in range(3000):
        i, j = sorted(rng.choice(n, 2, replace=False))
        ok, want = reference(i, j)
        got = leg_allowed(pr, pc, off, along, i, j, pas, rdg, slot, tile, tile, rows, cols, pad)
        assert got == want, (i, j)
        outcomes.add((ok, want))
    assert outcomes == {(True, True), (True, False), (False, False)}


def test_route_simplification_equals_the_greedy_rule_level_by_level():
    """``_route_vertices`` walks each short leg once for all the levels (``_walk`` without
    limits) and reuses the walk; it equals the greedy rule written out with ``leg_allowed``
    (tested above) and the tolerance, one level after another until one keeps at most
    ``enough`` corners. Over random wandering polylines on tiles with unloaded ones, passable
    and ridge at random."""
    import pipeline.flight.geometry as flight
    from pipeline.flight.geometry import leg_allowed

    rng = np.random.default_rng(5)
    rows, cols, tile, pad = 40, 44, 8, 2
    nti, ntj = -(-rows // tile), -(-cols // tile)
    slot = np.arange(nti * ntj).reshape(nti, ntj)
    slot[0, ntj - 1] = -1
    pas = (rng.random((nti * ntj, tile, tile)) < 0.97).astype(np.uint8)
    rdg = (rng.random((nti * ntj, tile, tile)) < 0.6).astype(np.uint8)
    levels = np.array([(0.5, 0.02), (1.0, 0.05), (2.0, 0.1), (3.0, 0.3)])

    def reference(wr, wc, off, along, enough):
        for level in range(len(levels)):
            tol, share = levels[level]
            keep, i, n = [0], 0, len(wr)
            while i < n - 1:
                j = i + 1
                while j + 1 < n:
                    c = j + 1
                    dr, dc = wr[c] - wr[i], wc[c] - wc[i]
                    ln = math.hypot(dr, dc)
                    ok = ln > 0
                    for q in range(i + 1, c) if ok else ():
                        t = ((wr[q] - wr[i]) * dr + (wc[q] - wc[i]) * dc) / ln**2
                        t = min(1.0, max(0.0, t))
                        gap = math.hypot(wr[i] + t * dr - wr[q], wc[i] + t * dc - wc[q])
                        ok = ok and gap <= tol
                    ok = ok and leg_allowed(  # (the route's rule: no cap on the ridge slack)
                        wr, wc, off, along, i, c, pas, rdg, slot, tile, tile, rows, cols, pad,
                        share, math.inf,
                    )  # fmt: skip
                    if not ok:
                        break
                    j = c
                i = j
                keep.append(i)
            if len(keep) <= enough:
                break
        return keep, level

    stops = set()
    for _ in range(60):
        n = int(rng.integers(3, 60))
        steps = rng.normal(0.0, 1.2, (n - 1, 2)) + rng.normal(0.0, 0.8, 2)
        w = np.cumsum(np.vstack([rng.uniform([4, 4], [rows - 4, cols - 4]), steps]), axis=0)
        wr, wc = np.clip(w[:, 0], 0, rows - 1), np.clip(w[:, 1], 0, cols - 1)
        along = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(wr), np.diff(wc)))))
        off = np.concatenate(([0.0], np.cumsum(rng.uniform(0.0, 1.0, n - 1) * np.diff(along))))
        enough = float(rng.integers(1, n + 1))
        got = flight._route_vertices(
            wr, wc, off, along, levels, enough, rdg, pas, slot, tile, tile, rows, cols, pad
        )
        want, level = reference(wr, wc, off, along, enough)
        assert got.tolist() == want
        stops.add(level)
    assert stops == set(range(len(levels)))  # every level was the last tried for some


@pytest.mark.parametrize("layer", ["elevation", "ridge"])
def test_a_lost_corridor_chunk_is_one_line_naming_it(ridge_store, tmp_path, layer):
    """The corridor reads the ridge and passable tiles first and the elevation behind them, in
    the pool's threads; a chunk lost from the store, in either, stops the flight with the
    damage named in one line (the elevation's when its tiles are first needed), and the pool
    is free for the next flight."""
    import shutil

    from pipeline.exceptions import PipelineError
    from pipeline.store.cache import CACHE

    path, ok, *_ = ridge_store
    copy = tmp_path / "maps.zarr"
    shutil.copytree(path, copy)
    (s, g), (s2, g2) = missions(ok, 2, seed=5, min_cells=150)
    t = pipeline.plan(copy, s, g, client="synchronous")
    lost = copy / layer / "c" / str(s[0] // 128) / str(s[1] // 128)
    assert lost.is_file()
    lost.unlink()
    CACHE.forget(str(copy))
    with pytest.raises(PipelineError, match=rf"damaged: chunk .* of its layer '{layer}'") as e:
        pipeline.fly(copy, t)
    assert "\n" not in str(e.value)
    u = pipeline.plan(path, s2, g2, client="synchronous")
    assert pipeline.fly(path, u).flown_length_m > 0


@pytest.mark.parametrize("tile", [8, 5])
def test_seabed_under_the_track_is_scipys_bilinear_interpolation(tile):
    """The seabed under the track (``_bilinear`` over the corridor's tiles, reading the four
    grid points within one tile by their place in it) equals scipy's linear interpolation of
    the whole grid, at random points, on grid lines and at the map's edges; NaN where a grid
    point with weight is unknown (a no-data cell or a tile not loaded)."""
    from scipy.interpolate import RegularGridInterpolator

    import pipeline.flight.profile as flight

    rng = np.random.default_rng(11)
    rows, cols = 31, 27
    z = rng.normal(-2000.0, 300.0, (rows, cols)).astype(np.float32)
    z[12, 7] = np.nan
    nti, ntj = -(-rows // tile), -(-cols // tile)
    slot = np.arange(nti * ntj).reshape(nti, ntj)
    slot[1, ntj - 1] = -1
    el = np.full((nti * ntj, tile, tile), np.nan, dtype=np.float32)
    known = np.full((rows, cols), np.nan)
    for ti in range(nti):
        for tj in range(ntj):
            blk = z[ti * tile : (ti + 1) * tile, tj * tile : (tj + 1) * tile]
            if slot[ti, tj] >= 0:
                el[slot[ti, tj], : blk.shape[0], : blk.shape[1]] = blk
                known[ti * tile : (ti + 1) * tile, tj * tile : (tj + 1) * tile] = blk
    pr = np.concatenate([rng.uniform(0, rows - 1, 400), rng.integers(0, rows, 100) * 1.0,
                         np.full(20, rows - 1.0), np.zeros(20)])  # fmt: skip
    pc = np.concatenate([rng.uniform(0, cols - 1, 520), rng.integers(0, cols, 20) * 1.0])
    got = flight._bilinear(el, slot, tile, tile, rows, cols, pr, pc)
    ref = RegularGridInterpolator((np.arange(rows), np.arange(cols)), np.nan_to_num(known))
    ref = ref(np.column_stack([pr, pc]))
    for k in range(len(pr)):
        i, j = int(min(np.floor(pr[k]), rows - 2)), int(min(np.floor(pc[k]), cols - 2))
        fi, fj = pr[k] - i, pc[k] - j
        weights = {(i, j): (1 - fi) * (1 - fj), (i + 1, j): fi * (1 - fj),
                   (i, j + 1): (1 - fi) * fj, (i + 1, j + 1): fi * fj}  # fmt: skip
        unknown = any(w > 0 and np.isnan(known[c]) for c, w in weights.items())
        if unknown:
            assert np.isnan(got[k]), k
        else:
            assert got[k] == pytest.approx(ref[k], rel=1e-12, abs=1e-9), k
    assert np.isnan(got).any() and np.isfinite(got).sum() > len(got) // 2


# ---------------------------------------------------------- safe against the continuous seabed


def _seabed_dem(kind: str, n: int, a: float) -> np.ndarray:
    i, j = np.mgrid[0:n, 0:n].astype(np.float64)
    if kind == "flat":
        return np.full((n, n), -3000.0, np.float32)
    if kind == "plane":  # a slope of 0.8 %
        return (-3000.0 + 0.008 * a * (i + 0.5 * j)).astype(np.float32)
    # a sine seabed: relief of 0.6 cells' side, rough at the grid's scale
    return (-3000.0 + 0.3 * a * np.sin(i / 2.3) * np.cos(j / 3.1)).astype(np.float32)


def _flown_over(tmp_path, kind, ratio, method, n=40, a=100.0):
    import dask
    from conftest import metric_dataarray

    dem = metric_dataarray(_seabed_dem(kind, n, a), a=a).rename("elevation")
    dem.attrs.update(cell_size=a, units="m", positive="up")
    clearance = ratio * a
    path = tmp_path / f"{kind}-{ratio}-{method}.zarr"
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(dem, path, method=method, clearance=clearance, chunks=16)
    ok = pipeline.open_maps(path)["passable"].values.astype(bool)
    cells = np.argwhere(ok)
    s, g = tuple(cells[np.argmin(cells.sum(1))]), tuple(cells[np.argmax(cells.sum(1))])
    t = pipeline.plan(path, s, g, planner="ra_star", omega=2.0, client="synchronous")
    veh = {"max_pitch_deg": 15.0, "min_turn_radius_m": 1.5 * a}
    with_flight(path, t, veh)
    return path, t, clearance


def _bilinear_fn(path):
    """The maps store's own elevation as scipy's bilinear interpolant of (x, y)."""
    from scipy.interpolate import RegularGridInterpolator

    ds = pipeline.open_maps(path)
    x, y = ds["x"].values, ds["y"].values
    z = ds["elevation"].values.astype(np.float64)
    f = RegularGridInterpolator((y[::-1], x), z[::-1])
    return f, (x.min(), x.max(), y.min(), y.max())


def independent_clearance(path, xyz, method, clearance, fine):
    """The least clearance of the points ``xyz`` from the continuous (bilinear) seabed of the
    store, by the method: spherical the 3-D distance to the seabed sampled every ``fine``
    metres (KD-tree); vertical the height above the seabed under each point; horizontal the
    height above the highest seabed within the clearance around it."""
    f, (x0, x1, y0, y1) = _bilinear_fn(path)
    if method == "vertical":
        return float(np.min(xyz[:, 2] - f(np.column_stack([xyz[:, 1], xyz[:, 0]]))))
    lo_x, hi_x = max(x0, xyz[:, 0].min() - clearance), min(x1, xyz[:, 0].max() + clearance)
    lo_y, hi_y = max(y0, xyz[:, 1].min() - clearance), min(y1, xyz[:, 1].max() + clearance)
    xs, ys = np.arange(lo_x, hi_x + 1e-9, fine), np.arange(lo_y, hi_y + 1e-9, fine)
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    zz = f(np.stack([yy, xx], axis=-1))
    if method == "spherical":
        d, _ = cKDTree(np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()])).query(xyz)
        return float(d.min())
    tree = cKDTree(np.column_stack([xx.ravel(), yy.ravel()]))
    top = np.array([zz.ravel()[i].max() for i in tree.query_ball_point(xyz[:, :2], clearance)])
    return float(np.min(xyz[:, 2] - top))


@pytest.mark.parametrize(
    "kind, ratio, method",
    [("sine", r, "spherical") for r in (0.5, 0.7, 1.0, 3.0, 10.0)]
    + [("flat", 0.5, "spherical"), ("plane", 0.5, "spherical"), ("plane", 3.0, "spherical")]
    + [("sine", r, m) for r in (0.5, 3.0) for m in ("vertical", "horizontal")],
)
def test_the_route_flown_keeps_r_from_the_continuous_seabed(tmp_path, kind, ratio, method):
    """What the vehicle flies, checked as an operator would: the waypoint route (straight legs
    at the waypoints' heights) and the flown track (the same route with its turns), each
    densified every 2 m, keep the clearance from the bilinear seabed between grid points
    (independently: scipy's interpolation, sampled finely) at R of 0.5 to 10 cells (half a
    cell is the least a maps store takes), for each method; the grid path planned with
    grid-point clearance alone would not. On flat ground the route is level at altitude R;
    on a plane a straight ramp (no reversal)."""
    path, t, clearance = _flown_over(tmp_path, kind, ratio, method)
    assert t.status == "ok", t.message
    f = t.flight
    fine = min(clearance / 20, 10.0)
    for xyz in (densify(f.waypoints[:, :3], 2.0), densify(np.column_stack([f.x, f.y, f.z]), 2.0)):
        least = independent_clearance(path, xyz, method, clearance, fine)
        slack = fine * 0.71 if method != "vertical" else 0.0  # the sampling's own error
        assert least >= clearance * (1 - 1e-6) - 1e-6 - (0 if method == "spherical" else slack)
    # the figure reported is the least clearance over every sample of the track and of the
    # route (it was measured at a hundredth of them and could miss it by tens of metres), to
    # within the reference's sampling and the flight's lattice (parts of at most R / 8, at
    # least 2 a side, at most 32: docs/flyable-missions.md)
    pts = np.concatenate([np.column_stack([f.x, f.y, f.z]), f.route])
    want = independent_clearance(path, pts, method, clearance, fine)
    part = 100.0 / min(32, max(2, math.ceil(8 * 100.0 / clearance)))
    tol = 1e-6 if method == "vertical" else 0.71 * max(fine, part) + 1e-6
    assert abs(f.min_clearance_m - want) <= tol, (f.min_clearance_m, want)
    # the waypoints' legs: pitch within the limit
    w = f.waypoints
    tan = math.tan(math.radians(15.0))
    assert np.all(np.abs(np.diff(w[:, 2])) <= tan * np.hypot(*np.diff(w[:, :2], axis=0).T) + 1e-6)
    assert np.all(np.abs(np.diff(f.z)) <= tan * np.hypot(np.diff(f.x), np.diff(f.y)) + 1e-6)
    # the track is the route: every track sample within a metre of the waypoints' legs in 3-D
    # where the two share their straight parts (the turns cut the corners)
    if kind == "flat":
        assert np.ptp(w[:, 2]) < 1e-6 and f.reversals_per_km == 0.0
        if method == "spherical":
            # at R on flat ground, up to the sampling's allowance (flight.CLEARANCE_SLACK of
            # R for the steps, and the sagitta of the longest chord, half a cell, on an arc)
            sag = (0.5 * 100.0) ** 2 / (8 * f.turn_radius_m)  # (cells of 100 m)
            assert clearance <= f.altitude_median_m <= clearance * (1 + CLEARANCE_SLACK) + sag
    if kind == "plane":
        assert f.reversals_per_km == 0.0


def test_a_break_ending_a_short_leg_is_removed_or_moved_where_the_limits_allow():
    """A height profile over a 100 m route, turn radius 30 m, a break at 50 m ending a 10 m
    leg to the knot at 60 m: removed where the straight line between its neighbours stays
    above every required height and within the pitch limit; else removed and a neighbour's
    height raised as little as the required heights ask (worked out by hand below); else moved
    to 30 m from its neighbours; kept where none of these keeps the limits. Corners stay."""
    from pipeline.flight.profile import resolve_short_legs

    sig = np.arange(0.0, 101.0, 1.0)
    z = np.interp(sig, [0, 50, 60, 100], [0.0, 5.0, 5.5, 8.0])
    wi = np.array([0, 50, 60, 100])
    ends, slopes, low = np.array([0, 100]), np.full(100, 0.5), np.full(101, -np.inf)
    zz = z.copy()
    assert resolve_short_legs(sig, zz, wi, ends, low, slopes, np.inf, 30.0).tolist() == [0, 60, 100]
    np.testing.assert_allclose(zz[:61], 5.5 * sig[:61] / 60)  # the line that replaced it
    # the line 0 -> 60 passes at 5.04 under a required 5.2 at 55: the knot at 60 raised to
    # 5.2 * 60 / 55, the least height whose line from 0 clears it
    high = low.copy()
    high[55] = 5.2
    zz = z.copy()
    assert resolve_short_legs(sig, zz, wi, ends, high, slopes, np.inf, 30.0).tolist() == [
        0,
        60,
        100,
    ]
    assert zz[60] == pytest.approx(5.2 * 60 / 55) and zz[55] == pytest.approx(5.2)
    np.testing.assert_allclose(zz[60:], np.interp(sig[60:], [60, 100], [5.2 * 60 / 55, 8.0]))
    # the same with the route going down after its corner at 60 under a surface limit of 5.6
    # (the knot at 60 cannot rise to 5.67): the break moved to 30 m, its height the least
    # whose line to 60 clears 5.2 at 55 (z30 + (5.5 - z30) 25 / 30 >= 5.2: 3.7)
    down = np.interp(sig, [0, 50, 60, 100], [0.0, 5.0, 5.5, 3.0])
    corners = np.array([0, 60, 100])
    zz = down.copy()
    out = resolve_short_legs(sig, zz, wi, corners, high, slopes, 5.6, 30.0).tolist()
    assert out == [0, 30, 60, 100]
    assert zz[30] == pytest.approx(3.7) and zz[55] >= 5.2 - 1e-12
    # kept: a corner 15 m before the break leaves no room to move it, the line 35 -> 60 passes
    # under 5.2, the corner at 35 cannot rise (a pitch limit of 0.1 before it) nor the one at
    # 60 (the surface limit)
    wi = np.array([0, 35, 50, 60, 100])
    corners = np.array([0, 35, 60, 100])
    z = np.interp(sig, [0, 35, 50, 60, 100], [0.0, 3.5, 5.0, 5.5, 3.0])
    gentle = slopes.copy()
    gentle[:35] = 0.1
    out = resolve_short_legs(sig, z.copy(), wi, corners, high, gentle, 5.6, 30.0).tolist()
    assert out == [0, 35, 50, 60, 100]
    # a corner is never removed
    out = resolve_short_legs(sig, z.copy(), np.array([0, 50, 60, 100]), np.array([0, 50, 100]),
                             low, slopes, np.inf, 30.0)  # fmt: skip
    assert 50 in out.tolist()


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(5.0, 60.0), st.floats(0.0, 40.0))
def test_resolved_short_legs_keep_every_limit(seed, min_leg, band):
    """Random terrain, pitch limits lowered over random turns, the band profile's breaks:
    after ``resolve_short_legs`` the profile, checked here sample by sample, is straight between
    its waypoints, keeps every required height, every interval's pitch limit and the surface
    limit, keeps the corners and both ends' heights, and has no more breaks ending short legs
    than before."""
    from pipeline.flight.profile import pitch_envelope_var, resolve_short_legs

    rng = np.random.default_rng(seed)
    n = int(rng.integers(20, 300))
    sig = np.concatenate(([0.0], np.cumsum(rng.uniform(0.5, 15.0, n - 1))))
    h = np.cumsum(rng.normal(0, 3.0, n))
    h[rng.random(n) < 0.1] = -np.inf
    slopes = np.full(n - 1, 0.36)
    for _ in range(int(rng.integers(0, 6))):
        j = int(rng.integers(0, n - 1))
        slopes[j : j + int(rng.integers(1, 8))] *= rng.uniform(0.6, 1.0)
    corners = np.unique(np.concatenate(([0, n - 1], rng.integers(0, n, int(rng.integers(0, 8))))))
    env = pitch_envelope_var(h, sig, slopes)
    top = float(env.max() + rng.uniform(0, 30))
    z, brk = band_profile(sig, env, band, top, slopes)
    wi = np.union1d(corners, brk)
    z = np.interp(sig, sig[wi], z[wi])
    fixed_ends = z[[0, -1]].copy()

    def short_breaks(knots):
        legs = np.diff(sig[knots]) < min_leg
        brk_end = ~np.isin(knots, corners)
        return int(np.sum(legs & (brk_end[:-1] | brk_end[1:])))

    before = short_breaks(wi)
    out = resolve_short_legs(sig, z, wi.copy(), corners, h, slopes, top, min_leg)
    np.testing.assert_allclose(z, np.interp(sig, sig[out], z[out]), atol=1e-9)
    assert np.all(z >= h - 1e-9) and np.all(z <= top + 1e-9)
    assert np.all(np.abs(np.diff(z)) <= slopes * np.diff(sig) * (1 + 1e-9) + 1e-12)
    assert set(corners.tolist()) <= set(out.tolist())
    np.testing.assert_array_equal(z[[0, -1]], fixed_ends)
    assert short_breaks(out) <= before


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(1.0, 80.0))
def test_turn_slopes_change_no_closer_than_a_leg(seed, min_leg):
    """The pitch limit of the route's profile lowered over turns: never above any turn's own
    limit where it applies, never lowered off every turn's reach once joined runs are counted,
    and it changes only at places at least ``min_leg`` apart and from both ends (checked
    here interval by interval), so a profile held at the limit breaks no closer."""
    from pipeline.flight.profile import turn_slopes

    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 200))
    sig = np.concatenate(([0.0], np.cumsum(rng.uniform(0.5, 20.0, n - 1))))
    starts = np.sort(rng.integers(0, n - 1, int(rng.integers(0, 10))))
    zones = np.array(
        [(j, min(j + int(rng.integers(1, 10)), n - 1), rng.uniform(0.2, 0.36)) for j in starts]
    ).reshape(-1, 3)
    out = turn_slopes(sig, zones, 0.36, min_leg)
    for j0, j1, sl in zones:
        assert np.all(out[int(j0) : int(j1)] <= sl)
    assert np.all(out <= 0.36)
    change = np.flatnonzero(np.diff(out) != 0) + 1  # the samples where the limit changes
    places = np.concatenate(([sig[0]], sig[change], [sig[-1]]))
    if change.size:
        assert np.diff(places).min() >= min_leg
    assert not zones.size or out.min() == pytest.approx(zones[:, 2].min())


@pytest.mark.parametrize("ratio", [0.5, 3.0])
def test_the_flights_own_clearance_check_measures_the_bilinear_seabed(ratio):
    """``seabed_clearance``, the check a flight makes of what it flies, against scipy: the
    least 3-D distance of random points to the bilinear seabed (sampled every cell / 40,
    KD-tree) within the two samplings' precision (each a set of seabed points: never nearer
    than the seabed); a point under the seabed: its negative height above it; the vertical method:
    the height above the seabed under each point."""
    from scipy.interpolate import RegularGridInterpolator

    from pipeline.flight.profile import clearance_blocks, seabed_clearance

    rng = np.random.default_rng(5)
    a, n = 100.0, 24
    radius = ratio * a
    z = (-2000 + 60 * rng.normal(size=(n, n))).astype(np.float32)
    el, slot = z[None].copy(), np.zeros((1, 1), dtype=np.int64)
    under = RegularGridInterpolator((np.arange(n) * a, np.arange(n) * a), z.astype(float))
    tree = cKDTree(bilinear_seabed_points(z, a, a / 40))
    m = 16
    for _ in range(20):
        pr, pc = rng.uniform(6, n - 7, 1), rng.uniform(6, n - 7, 1)
        h = under([[pr[0] * a, pc[0] * a]]) + rng.uniform(0.2, 1.1) * radius
        got = seabed_clearance(
            el, slot, n, n, n, n, pr, pc, h, a, radius, 2, m, np.inf, clearance_blocks(el)
        )
        ref = tree.query([[pc[0] * a, pr[0] * a, h[0]]])[0][0]
        ref = min(ref, 1.25 * radius)
        assert ref - a / 40 <= got <= ref + a / m, (got, ref)  # both samplings of the seabed
    below = under([[pr[0] * a, pc[0] * a]]) - 7.0
    got = seabed_clearance(
        el, slot, n, n, n, n, pr, pc, below, a, radius, 2, m, np.inf, clearance_blocks(el)
    )
    assert got == pytest.approx(-7.0, abs=1e-3)
    got = seabed_clearance(
        el, slot, n, n, n, n, pr, pc, below + 50.0, a, 0.0, 0, m, np.inf, clearance_blocks(el)
    )
    assert got == pytest.approx(43.0, abs=1e-3)


def _tiled(z: np.ndarray, tr: int, tc: int) -> tuple:
    """``z`` as the flight holds a corridor: tiles of ``tr`` x ``tc`` (the last ones padded
    with no-data) and their slot table."""
    rows, cols = z.shape
    nti, ntj = -(-rows // tr), -(-cols // tc)
    el = np.full((nti * ntj, tr, tc), np.nan, dtype=np.float32)
    slot = np.arange(nti * ntj, dtype=np.int64).reshape(nti, ntj)
    for ti in range(nti):
        for tj in range(ntj):
            part = z[ti * tr : (ti + 1) * tr, tj * tc : (tj + 1) * tc]
            el[slot[ti, tj], : part.shape[0], : part.shape[1]] = part
    return el, slot


@pytest.mark.parametrize("method", [2, 1])
def test_the_flights_clearance_check_is_the_same_on_any_tiling(method):
    """The check passes over blocks of grid squares too low to matter; many points in one
    call, each search starting from the least so far: against scipy on the bilinear seabed
    (spherical: KD-tree; horizontal: the highest seabed sample within the radius, brute force),
    and the same figure to the bit on one tile and on tiles of 7 x 5 and 9 x 16 (blocks cut
    by the tiles' edges, a last tile of one row), with no-data cells, and started from a
    known clearance (the lesser of the two)."""
    from pipeline.flight.profile import clearance_blocks, seabed_clearance

    rng = np.random.default_rng(8)
    a, rows, cols, radius, m = 50.0, 37, 29, 180.0, 8
    y, x = np.mgrid[0:rows, 0:cols]
    z = -1500 + 120 * np.sin(x / 4.0) * np.cos(y / 5.0) + 15 * rng.normal(size=(rows, cols))
    z = z.astype(np.float32)
    z[30:33, 2:6] = np.nan  # no seabed known there: its squares are not measured
    pr, pc = rng.uniform(2, rows - 3, 60), rng.uniform(2, cols - 3, 60)
    pr[pr > 29] -= 8.0  # (away from the no-data cells)
    zf = np.where(np.isnan(z), -np.inf, z).astype(np.float64)
    from scipy.interpolate import RegularGridInterpolator

    under = RegularGridInterpolator((np.arange(rows) * a, np.arange(cols) * a), zf)
    h = under(np.column_stack([pr * a, pc * a])) + rng.uniform(0.4, 1.2, 60) * radius
    figures = []
    for tr, tc in ((rows, cols), (7, 5), (9, 16)):
        el, slot = _tiled(z, tr, tc)
        for start in (np.inf, 140.0):
            got = seabed_clearance(
                el, slot, tr, tc, rows, cols, pr, pc, h, a, radius, method, m, start,
                clearance_blocks(el),
            )  # fmt: skip
            figures.append((start, got))
    assert len({g for s, g in figures if s == np.inf}) == 1  # every tiling: the same figure
    assert len({g for s, g in figures if s != np.inf}) == 1
    got = figures[0][1]
    seabed = bilinear_seabed_points(np.where(np.isnan(z), np.nan, z), a, a / m)
    seabed = seabed[np.isfinite(seabed[:, 2])]
    # (the check's lattice of each square is this sampling's: the same seabed points)
    if method == 2:
        d = cKDTree(seabed).query(np.column_stack([pc * a, pr * a, h]))[0]
        ref = float(np.minimum(d, 1.25 * radius).min())
    else:
        ref = math.inf
        for k in range(len(pr)):
            near = np.hypot(seabed[:, 0] - pc[k] * a, seabed[:, 1] - pr[k] * a) < radius
            ref = min(ref, float(h[k] - seabed[near, 2].max()))
    assert got == pytest.approx(ref, abs=1e-3)
    assert figures[1][1] == pytest.approx(min(ref, 140.0), abs=1e-3)


def test_profile_figures_count_reversals_and_altitudes():
    """Up 500 m, level 500 m, down 500 m, up 500 m over a seabed 100 m below the start: two
    reversals (the level piece passed over) in 2 km; the altitude's median and 90th
    percentile by numpy over the samples."""
    from pipeline.flight.profile import profile_figures

    s = np.linspace(0.0, 2000.0, 2001)
    z = np.interp(s, [0, 500, 1000, 1500, 2000], [0.0, 50.0, 50.0, 0.0, 40.0])
    seabed = np.full_like(s, -100.0)
    f = profile_figures(s, z, seabed)
    assert f["reversals_per_km"] == pytest.approx(1.0)
    assert f["altitude_median_m"] == pytest.approx(np.median(z + 100.0))
    assert f["altitude_p90_m"] == pytest.approx(np.percentile(z + 100.0, 90))
    assert f["altitude_min_m"] == pytest.approx(100.0)


@pytest.mark.parametrize("below", [0.0, 2.0])
def test_the_surface_limit_is_kept_exactly(tmp_path, below):
    """A flat seabed ``2R + below`` deep, R 300 m over 30 m cells, turn radius 30 m: the
    lowest safe height lies ``below`` metres under the surface limit (sea level less R). The
    flight's samples need R' > R (the sampling's allowance, about a metre here), which the
    vehicle used to take above the limit: with 2 m to spare it flies, never above the limit
    (the track and the route, numpy); with none it fails, naming the limit."""
    import dask
    from conftest import metric_dataarray

    R, a = 300.0, 30.0
    z = np.full((40, 40), -2 * R - below, np.float32)
    dem = metric_dataarray(z, a=a).rename("elevation")
    path = tmp_path / "flat.zarr"
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(dem, path, clearance=R, chunks=16)
    ok = pipeline.open_maps(path)["passable"].values
    assert ok[5, 5] and ok[34, 30]  # S <= the limit: passable, planned
    t = pipeline.plan(path, (5, 5), (34, 30), omega=1.5, client="synchronous")
    assert t.status == "ok"
    f = pipeline.fly(path, t, {"min_turn_radius_m": 30.0})
    if below:
        assert not f.problems
        assert max(f.z.max(), f.route[:, 2].max(), f.waypoints[:, 2].max()) <= -R + 1e-6
    else:
        assert f.problems and "above the surface limit (300 m)" in f.problems[0]


# ------------------------------------------------------------------ legs any autopilot flies


def _geodesic_points(crs, x0, y0, x1, y1, n=64):
    """pyproj's Geod.npts between the leg's ends, in map coordinates."""
    from pyproj import Geod, Transformer

    to_ll = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    back = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    (lo0, la0), (lo1, la1) = to_ll.transform(x0, y0), to_ll.transform(x1, y1)
    pts = np.array(Geod(ellps="WGS84").npts(lo0, la0, lo1, la1, n))
    return back.transform(pts[:, 0], pts[:, 1])


def _rhumb_points(crs, x0, y0, x1, y1, n=64, steps=4000):
    """The rhumb line as a constant course flown on the ellipsoid: pyproj's Geod.fwd in small
    steps at the course tan(a) = d(lon) / d(psi), psi the isometric latitude of the WGS84
    ellipsoid, for the loxodrome's length (the meridian arc over cos a; along a parallel, the
    parallel's arc)."""
    from pyproj import Geod, Transformer

    geod = Geod(ellps="WGS84")
    e = math.sqrt(geod.es)
    to_ll = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    back = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    (lo0, la0), (lo1, la1) = to_ll.transform(x0, y0), to_ll.transform(x1, y1)

    def psi(lat):
        s = math.sin(math.radians(lat))
        return math.atanh(s) - e * math.atanh(e * s)

    course = math.atan2(math.radians(lo1 - lo0), psi(la1) - psi(la0))
    meridian = abs(geod.inv(lo0, la0, lo0, la1)[2])  # the meridian arc between the latitudes
    length = meridian / abs(math.cos(course))
    lon, lat, out = lo0, la0, [(lo0, la0)]
    for _ in range(steps):
        lon, lat, _ = geod.fwd(lon, lat, math.degrees(course), length / steps)
        out.append((lon, lat))
    track = np.array(out)
    assert geod.inv(lon, lat, lo1, la1)[2] < 1.0  # it reaches the leg's end
    track = track[:: max(steps // n, 1)]
    return back.transform(track[:, 0], track[:, 1])


def _off_chord(px, py, x0, y0, x1, y1):
    dx, dy = x1 - x0, y1 - y0
    t = np.clip(((px - x0) * dx + (py - y0) * dy) / (dx * dx + dy * dy), 0, 1)
    return np.hypot(px - x0 - t * dx, py - y0 - t * dy).max()


def test_a_long_leg_is_split_until_the_geodesic_and_the_rhumb_line_agree():
    """A 150 km leg at 60 N on a local azimuthal equidistant grid: its geodesic (pyproj's
    Geod.npts) and rhumb line (a constant course flown on the ellipsoid) part from the map
    line by kilometres; split_legs adds waypoints until every leg's two lines lie within 5 m
    of its map line, measured by those independent references."""
    from pyproj import CRS

    from pipeline.flight.legs import split_legs

    crs = CRS.from_proj4("+proj=aeqd +lat_0=60 +lon_0=0 +datum=WGS84 +units=m")
    wkt = crs.to_wkt()
    n = 15001
    x = np.linspace(-50_000.0, 100_000.0, n)
    y = np.linspace(40_000.0, 40_000.0 + 20_000.0, n)
    gx, gy = _geodesic_points(crs, x[0], y[0], x[-1], y[-1])
    rx, ry = _rhumb_points(crs, x[0], y[0], x[-1], y[-1])
    assert _off_chord(rx, ry, x[0], y[0], x[-1], y[-1]) > 500.0  # the problem is real
    wi = split_legs(wkt, x, y, np.array([0, n - 1]), 5.0, None)
    assert 4 < len(wi) < 200
    for a, b in zip(wi[:-1], wi[1:], strict=True):
        for px, py in (
            _geodesic_points(crs, x[a], y[a], x[b], y[b], 16),
            _rhumb_points(crs, x[a], y[a], x[b], y[b], 16, 400),
        ):
            assert _off_chord(np.asarray(px), np.asarray(py), x[a], y[a], x[b], y[b]) <= 5.5
    # a longest leg given: none longer
    wi = split_legs(None, x, y, np.array([0, n - 1]), 5.0, 20_000.0)
    assert np.hypot(np.diff(x[wi]), np.diff(y[wi])).max() <= 20_000.0


def test_the_legs_lines_are_measured_at_once_and_the_closest_leg_named(ridge_store):
    """The geodesics and rhumb lines of every leg, sampled and measured in one pass: on a
    flown mission (legs of at most 1.5 km), with a clearance above what is flown (so that
    every leg's lines break it and the flight must say which leg), the least clearance it
    reports lies between the least 3-D distance of the legs' lines (pyproj's Geod.npts and a
    constant course flown on the ellipsoid, every 2 m) from the bilinear seabed (scipy,
    sampled every 4 m) and that at the geodesics' own samples plus the flight's lattice; the
    leg it names comes within that of the least."""
    from pyproj import CRS
    from scipy.interpolate import RegularGridInterpolator

    from pipeline.flight.fly import check_leg_lines

    path, ok, graph, pts = ridge_store
    cells = np.argwhere(ok)  # corner to corner: legs far from the CRS's centre, whose lines part
    t = pipeline.plan(
        path, tuple(cells[10]), tuple(cells[-10]), planner="astar", client="synchronous"
    )
    veh = Vehicle.of({"max_leg_m": 1500.0})
    f = pipeline.fly(path, t, veh)
    wi, least, where, _ = check_leg_lines(path, t, f, veh, clearance=400.0)
    qx, qy, zq = f.route[:, 0], f.route[:, 1], f.route[:, 2]
    assert least < 400.0 and where, (least, where)
    ds = pipeline.open_maps(path)
    crs = CRS.from_wkt(ds["spatial_ref"].attrs["crs_wkt"])
    xs, ys = ds["x"].values, ds["y"].values
    iy = np.argsort(ys)
    seabed = RegularGridInterpolator(
        (ys[iy], xs), ds["elevation"].values.astype(np.float64)[iy]
    )  # fmt: skip
    per_leg = []
    for a, b in zip(wi[:-1], wi[1:], strict=True):
        length = math.hypot(qx[b] - qx[a], qy[b] - qy[a])
        n = int(length / 2.0) + 2
        lines = [  # (the geodesic's interior points, the rhumb line's every step with its ends)
            _geodesic_points(crs, qx[a], qy[a], qx[b], qy[b], n),
            _rhumb_points(crs, qx[a], qy[a], qx[b], qy[b], n, n),
        ]
        frac = np.concatenate([np.arange(1, n + 1) / (n + 1), np.arange(n + 1) / n])
        lx = np.concatenate([np.asarray(v[0]) for v in lines])
        ly = np.concatenate([np.asarray(v[1]) for v in lines])
        lz = zq[a] + (zq[b] - zq[a]) * frac
        # the seabed within 200 m of the leg (beyond the least clearance), every 4 m
        x0, x1 = max(lx.min() - 200, xs.min()), min(lx.max() + 200, xs.max())
        y0, y1 = max(ly.min() - 200, ys.min()), min(ly.max() + 200, ys.max())
        gx, gy = np.meshgrid(np.arange(x0, x1, 4.0), np.arange(y0, y1, 4.0))
        gz = seabed(np.column_stack([gy.ravel(), gx.ravel()]))
        tree = cKDTree(np.column_stack([gx.ravel(), gy.ravel(), gz]))
        per_leg.append(float(tree.query(np.column_stack([lx, ly, lz]))[0].min()))
    ref = min(per_leg)
    lattice = 50.0 / 2  # the flight's lattice at this clearance: 2 parts a square
    assert ref - 3.0 <= least <= ref + lattice, (least, ref)
    j = int(where.rsplit("between waypoints ", 1)[1].split(" and ")[0]) - 1
    assert per_leg[j] <= ref + lattice + 3.0, (where, per_leg[j], ref)


def test_max_leg_splits_the_waypoints_on_the_flown_profile(ridge_store):
    """With max_leg_m, no two waypoints are farther apart, and the waypoints added lie on the
    profile flown (the heights linear between the unsplit waypoints)."""
    path, ok, graph, pts = ridge_store
    ((s, g),) = missions(ok, 1, seed=5, min_cells=150)
    t = pipeline.plan(path, s, g, planner="astar", client="synchronous")
    free = pipeline.fly(path, t, {})
    short = pipeline.fly(path, t, {"max_leg_m": 400.0})
    assert short.ok, short.problems
    w, w0 = short.waypoints, free.waypoints
    assert np.hypot(*np.diff(w[:, :2], axis=0).T).max() <= 400.0 + 1e-6
    assert len(w) > len(w0)
    # every added waypoint on the unsplit legs' straight 3-D lines
    along0 = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(w0[:, :2], axis=0).T))))
    along = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(w[:, :2], axis=0).T))))
    assert along[-1] == pytest.approx(along0[-1], rel=1e-9)
    np.testing.assert_allclose(w[:, 2], np.interp(along, along0, w0[:, 2]), atol=1e-6)


# ------------------------------------------------------------------ planning around the flight


def _shoal_store(tmp_path, z, name):
    """A maps store of the elevations ``z`` (100 m cells), R 300 m, surface clearance 30 m:
    the surface limit 30 m below the sea surface."""
    import dask
    from conftest import metric_dataarray

    path = tmp_path / f"{name}.zarr"
    dem = metric_dataarray(z.astype(np.float32), a=100.0).rename("elevation")
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(dem, path, clearance=300.0, surface_clearance=30.0, chunks=32)
    return path


def _seamount_chain(n=64, seed=3):
    """Seven seamounts across the middle of a 900 m deep plain, their summits 300 to 360 m
    deep: passable over most of their tops at the grid points, some saddles within a metre of
    what the flight can keep."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:n, 0:n].astype(float)
    z = np.full((n, n), -900.0)
    for k in range(7):
        cx, cy = (k + 0.5) * n / 7 + rng.uniform(-2, 2), n / 2 + rng.uniform(-6, 6)
        s, top = rng.uniform(3, 6), rng.uniform(-360, -300)
        bump = (top + 900) * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
        z = np.maximum(z, -900 + bump)
    return z


VEHICLE_NEAR_THE_TOP = {"min_turn_radius_m": 150.0, "max_pitch_deg": 15.0}


def test_a_mission_the_flight_cannot_fly_is_planned_again_and_flies(tmp_path):
    """A seamount chain near the surface limit: the first path's flight needs a height above
    the limit (it fails as flown alone); ``plan_missions`` plans it again around that place
    and flies it. What it flies is checked independently: the clearance of the waypoint route
    and the track from scipy's bilinear seabed (sampled every 15 m), every height under the
    surface limit, the pitch and the turns; its length within omega of scipy's optimum of the
    mission as given (the bound it keeps is that problem's, at most the optimum), and the
    track out of the zone it was planned around."""
    import shapely

    path = _shoal_store(tmp_path, _seamount_chain(), "chain")
    start, goal, omega = (4, 4), (59, 59), 2.0
    first = pipeline.plan(path, start, goal, omega=omega, client="synchronous")
    alone = with_flight(path, first, VEHICLE_NEAR_THE_TOP)
    assert alone.status == "failed" and "above the surface limit (30 m)" in alone.message
    mission = {"name": "across", "start": start, "goal": goal, "omega": omega}
    (t,) = pipeline.plan_missions(path, [mission], vehicle=VEHICLE_NEAR_THE_TOP, client="threads")
    assert t.status == "ok", t.message
    rounds = t.extra["flight_rounds"]
    assert rounds[0]["problem"].startswith("the clearance from the seabed needs")
    assert rounds[-1]["result"].startswith("ok") and t.message.startswith("planned again around")
    f = t.flight
    assert not f.problems
    for xyz in (densify(f.waypoints[:, :3], 2.0), densify(np.column_stack([f.x, f.y, f.z]), 2.0)):
        least = independent_clearance(path, xyz, "spherical", 300.0, 15.0)
        assert least >= 300.0 * (1 - 1e-6) - 1e-6
        assert xyz[:, 2].max() <= -30.0 + 1e-6  # the surface limit
    tan = math.tan(math.radians(15.0))
    w = f.waypoints
    assert np.all(np.abs(np.diff(w[:, 2])) <= tan * np.hypot(*np.diff(w[:, :2], axis=0).T) + 1e-6)
    assert np.all(np.abs(np.diff(f.z)) <= tan * np.hypot(np.diff(f.x), np.diff(f.y)) + 1e-6)
    assert f.min_turn_radius_m >= 150.0 * (1 - 1e-9)
    ds = pipeline.open_maps(path)
    surface, ok = ds["safety"].values, ds["passable"].values.astype(bool)
    best = optimum(reference_graph(surface, ok, 100.0), ok.shape, start, goal)
    assert t.lower_bound_m == first.lower_bound_m <= best * (1 + 1e-9)
    assert t.length_m <= omega * t.lower_bound_m * (1 + 1e-9) <= omega * best * (1 + 1e-9)
    zones = dict(t.keep_out.zones)
    assert "flight round 1" in zones
    track = shapely.LineString(np.column_stack([f.x, f.y]))
    assert not track.intersects(zones["flight round 1"])
    # the Item says how it came to be, and a STAC reader takes it
    import pystac

    from pipeline.outputs.catalog import write_mission as write_item

    d = write_item(
        tmp_path / "cat", "across", mission, t, maps=pipeline.open_store(path),
        crs_wkt=None, min_clearance_m=f.min_clearance_m, run_id="r", quicklook=False,
    )  # fmt: skip
    item = pystac.Item.from_dict(d)
    assert item.properties["auv:flight_rounds"] == rounds
    assert item.properties["auv:lower_bound_m"] == pytest.approx(first.lower_bound_m)


def test_a_mission_with_no_flyable_route_fails_naming_its_rounds(tmp_path):
    """A ridge across the whole map whose crest leaves the planner half a metre under the
    surface limit at the grid points: every route crosses it, and no flight can (its samples
    keep a little more than R). The mission fails after every round, each named; one whose
    start lies on the crest itself stops at once, saying to move the start."""
    n = 48
    y = np.mgrid[0:n, 0:n][0].astype(float)
    crest = -300.0 - 30.0 - 0.5
    z = -900 + (crest + 900) * np.exp(-((y - 24) ** 2) / (2 * 2.0**2))
    path = _shoal_store(tmp_path, z, "wall")
    assert pipeline.open_maps(path)["passable"].values[24].all()  # passable at the grid points
    missions = [
        {"name": "across", "start": (4, 4), "goal": (44, 40)},
        {"name": "from the crest", "start": (24, 4), "goal": (44, 40)},
    ]
    across, crest_start = pipeline.plan_missions(
        path, missions, vehicle=VEHICLE_NEAR_THE_TOP, client="threads"
    )
    assert across.status == "failed"
    assert across.message.startswith("no flyable route within 3 rounds")
    assert [r["round"] for r in across.extra["flight_rounds"]] == [1, 2, 3]
    assert "round 3: " in across.message and "above the surface limit (30 m)" in across.message
    assert crest_start.status == "failed" and "flight_rounds" not in crest_start.extra
    assert crest_start.message.endswith(
        "it breaks in the start's own cell, which no route avoids: move the start"
    )
