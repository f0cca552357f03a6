"""Safe against the user's own seabed (docs/method.md section 1): every resample the tool makes
lies on or above the bilinear surface of the file's own grid, a crop reads what it covers, a
mission's clearance is measured from the file, and ``pipeline verify`` re-checks finished
missions against any DEM. References: scipy's bilinear interpolation of the file's grid, pyproj,
brute-force sampling; never the code's own resample.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import xarray as xr
from click.testing import CliRunner
from pyproj import CRS, Transformer
from references import assert_upper_envelope
from scipy.interpolate import RegularGridInterpolator

import pipeline
from pipeline.cli import main
from pipeline.jobs.run import run_job
from pipeline.verify.missions import verify_missions
from pipeline.verify.seabed import SourceSeabed

UTM = "EPSG:32610"


def _tif(path, z, a, x0=500_000.0, y0=4_000_000.0, crs=UTM):
    import rioxarray  # noqa: F401

    rows, cols = z.shape
    x = x0 + (np.arange(cols) + 0.5) * a
    y = y0 - (np.arange(rows) + 0.5) * a
    arr = xr.DataArray(z.astype(np.float32), dims=("y", "x"), coords={"x": x, "y": y})
    arr.rio.write_crs(crs).rio.to_raster(path)
    return path, x, y


def _walls(n=300, a=30.0):
    """Flat at -3000 m with six north-south walls one cell wide rising to -1500 m."""
    z = np.full((n, n), -3000.0)
    for k in range(6):
        z[:, 30 + 45 * k] = -1500.0
    return z


def _pinnacles(n=300, seed=2):
    """A field of single-cell pinnacles 200 to 1500 m high on a gentle slope."""
    rng = np.random.default_rng(seed)
    z = -3000.0 + np.linspace(0, 200, n)[None, :] + np.zeros((n, 1))
    r, c = rng.integers(0, n, 300), rng.integers(0, n, 300)
    z[r, c] += rng.uniform(200, 1500, 300)
    return z


@pytest.mark.parametrize("field", [_walls, _pinnacles])
@pytest.mark.parametrize(("factor", "chunks"), [(2, None), (3.3, (37, 5)), (7, 16), (10, None)])
def test_a_coarser_resolution_never_erases_terrain(tmp_path, field, factor, chunks):
    """Walls and pinnacles narrower than a target cell, at 2x to 10x coarser cells (an odd
    ratio, awkward chunks: a last chunk of one column): the planning seabed's own bilinear
    surface is on or above the file's everywhere (scipy), no higher than it must be, and the
    narrowest wall still stands in it."""
    z = field()
    path, x, y = _tif(tmp_path / "f.tif", z, 30.0)
    dem = pipeline.open_dem(path, resolution=30.0 * factor, chunks=chunks)
    if chunks is not None:
        dem = dem.load()
    raised = assert_upper_envelope(dem, z, x, y)
    assert raised.max() > 0
    v = dem.values
    assert np.nanmax(v) == pytest.approx(z.max(), abs=1e-3)  # the highest point kept


def test_a_written_store_records_its_construction(tmp_path):
    """import_dem writes the raise it made (mean, greatest) and the construction, equal to
    the raise measured against scipy's bilinear surface of the file."""
    z = _pinnacles(200)
    path, x, y = _tif(tmp_path / "p.tif", z, 30.0)
    store = pipeline.import_dem(path, tmp_path / "dem.zarr", resolution=100.0, chunks=64)
    dem = pipeline.open_dem(store, chunks=None)
    assert "upper envelope" in dem.attrs["seabed_surface"]
    raised = assert_upper_envelope(dem, z, x, y)
    assert dem.attrs["seabed_raise_max_m"] == pytest.approx(raised.max(), abs=1e-2)
    assert dem.attrs["source"] == str(path)


def test_a_bbox_crop_reads_what_it_covers(tmp_path, topobathy, caplog):
    """A lon/lat grid cropped by a bbox: the store's edge nodes are on or above the file's
    surface (read with a margin of source cells, never its edge values copied outward); a
    bbox reaching beyond the file leaves the nodes beyond it no-data, said in the log; a bbox
    whose edges fall on cell centres keeps its last row and column."""
    z, lon, lat = topobathy
    lon = lon - 360.0
    import rioxarray  # noqa: F401
    from conftest import lonlat_dataarray

    arr = lonlat_dataarray(z, lon, lat).rename(lat="y", lon="x").rio.write_crs("EPSG:4326")
    path = tmp_path / "ll.tif"
    arr.rio.to_raster(path)
    # the file's own grid (its axes even: the sample's latitudes are not), as rasterio reads it
    read = rioxarray.open_rasterio(path).squeeze(drop=True)
    z, lon, lat = read.values.astype(np.float64), read.x.values, read.y.values
    ls = np.sort(lat)
    box = (float(lon[20]), float(ls[10]), float(lon[60]), float(ls[30]))
    dem = pipeline.open_dem(path, bbox=box, chunks=None, resolution=2000.0)
    assert_upper_envelope(dem, z, lon, lat, CRS.from_epsg(4326))
    assert np.isfinite(dem.values).all()  # the box lies inside the file
    # a bbox reaching beyond the file: the grid covers the file's part of it, and its nodes
    # beyond the file's outer half cells (the projected grid's corners) are no-data, said
    beyond = (float(lon[-5]), float(ls[5]), float(lon[-1]) + 0.5, float(ls[20]))
    with caplog.at_level("WARNING", logger="pipeline"):
        out = pipeline.open_dem(path, bbox=beyond, chunks=None, resolution=2000.0)
    to_ll = Transformer.from_crs(CRS.from_wkt(out.attrs["crs_wkt"]), "EPSG:4326", always_xy=True)
    olon, olat = to_ll.transform(*np.meshgrid(out.x.values, out.y.values))
    half = abs(lon[1] - lon[0]) / 2
    assert olon.max() <= lon.max() + half + 0.05  # not the half degree beyond the file
    off = olon > lon.max() + half
    assert np.isnan(out.values[off]).all()
    assert_upper_envelope(out, z, lon, lat, CRS.from_epsg(4326))
    caplog.clear()
    with caplog.at_level("WARNING", logger="pipeline"):
        whole = pipeline.open_dem(path, chunks=None, resolution=2000.0)
    assert np.isnan(whole.values).any() and "beyond the source's coverage" in caplog.text
    # bbox_xy on a projected grid at centres made by arithmetic: 83 x 143 read, not 82 x 142
    zz = np.random.default_rng(1).normal(-2000, 50, (100, 160))
    p2, x, y = _tif(tmp_path / "m.tif", zz, 0.1 * 3)
    cut = pipeline.open_dem(p2, bbox_xy=(x[10], y[92], x[150], y[10]), chunks=None)
    assert cut.shape == (83 + 2, 141 + 2)  # the cells within, and one more each side


def _run(tmp, name, path, dem, missions, client, planned):
    """A job on the file ``path`` (``dem``: more [dem] keys), R 300 m, A*, run on ``client``;
    ``missions``: TOML of its [[missions]]."""
    job = tmp / "job.toml"
    job.write_text(
        f'''name = "{name}"
[dem]
path = "{path}"
chunks = 64
{dem}
[maps]
clearance = 300.0
landmarks = 0
[planning]
planner = "astar"
{missions}
[output]
catalog = "{tmp / "cat"}"
quicklooks = false
performance_report = false
'''
    )
    res = run_job(job, scheduler=client)
    assert res.planned == planned, res


@pytest.fixture(scope="module")
def walls_job(tmp_path_factory, local_client):
    """The issue's case: a 30 m GeoTIFF with walls one cell wide, planned at 200 m cells with
    R = 300 m, one mission straight across the walls."""
    tmp = tmp_path_factory.mktemp("walls")
    z = _walls(300)
    path, x, y = _tif(tmp / "walls.tif", z, 30.0)
    missions = f"""[[missions]]
name = "across"
start_xy = [{x[5]}, {y[150]}]
goal_xy = [{x[290]}, {y[140]}]"""
    _run(tmp, "walls", path, "resolution = 200.0", missions, local_client, 1)
    return tmp, path, z, x, y


def _track(tmp):
    import pandas as pd

    (item,) = (tmp / "cat").glob("**/missions/*/*.json")
    t = pd.read_parquet(item.parent / "track.parquet")
    return item, t


def test_the_walls_mission_and_pipeline_verify(walls_job, tmp_path):
    """The walls job (built once: its three checks in one test, so that the job runs once
    whichever worker takes it)."""
    _a_mission_over_narrow_walls_keeps_its_clearance_from_the_file(walls_job)
    _verify_names_where_a_newer_survey_breaks_the_clearance(walls_job, tmp_path)
    _verify_checks_the_rating_and_the_zones_it_is_given(walls_job, tmp_path)


def _a_mission_over_narrow_walls_keeps_its_clearance_from_the_file(walls_job):
    """Over the walls, not through them: every track sample at least R above the file's own
    bilinear seabed below it (scipy); the clearance the mission reports is from the file,
    at least R; pipeline verify holds."""
    tmp, path, z, x, y = walls_job
    item, t = _track(tmp)
    f = RegularGridInterpolator((y[::-1], x), z[::-1])
    inside = (t.x >= x[0]) & (t.x <= x[-1]) & (t.y >= y[-1]) & (t.y <= y[0])
    below = f(np.column_stack([t.y[inside], t.x[inside]]))
    assert (t.z[inside] - below).min() >= 300.0 - 1e-3
    assert t.z.max() > -1500.0 + 300.0 - 1e-3  # it climbs over the walls
    props = json.loads(item.read_text())["properties"]
    assert props["auv:min_clearance_m"] >= 300.0 - 1e-3
    (v,) = verify_missions(item.parent, path)
    assert v.holds, v.checks
    assert v.checks[0].worst == pytest.approx(props["auv:min_clearance_m"], abs=0.05)


def _verify_names_where_a_newer_survey_breaks_the_clearance(walls_job, tmp_path):
    """A newer survey with a pinnacle under the track: pipeline verify fails (exit 1) and
    names the point; the clearance it gives is the brute-force one (the least over the track
    samples' 3-D distances to a dense sampling of the new surface bounds it above)."""
    tmp, path, z, x, y = walls_job
    item, t = _track(tmp)
    k = len(t) // 2
    r = int(np.argmin(np.abs(y - t.y.iloc[k])))
    c = int(np.argmin(np.abs(x - t.x.iloc[k])))
    newer = z.copy()
    newer[r, c] = t.z.iloc[k] - 120.0  # 120 m under the vehicle
    p2, _, _ = _tif(tmp_path / "newer.tif", newer, 30.0)
    result = CliRunner().invoke(main, ["verify", str(item.parent), "--dem", str(p2)])
    assert result.exit_code == 1, result.output
    assert "FAIL clearance" in result.output and "km along the" in result.output
    assert "0 of 1 missions hold" in result.output
    (v,) = verify_missions(tmp / "cat", p2)
    worst = v.checks[0].worst
    # the pinnacle's top is a point of the new seabed: no clearance exceeds the least
    # distance of a track sample from it
    top = np.array([x[c], y[r], newer[r, c]])
    reach = np.sqrt((t.x - top[0]) ** 2 + (t.y - top[1]) ** 2 + (t.z - top[2]) ** 2).min()
    assert 100.0 < worst <= reach + 1e-3
    ok = CliRunner().invoke(main, ["verify", str(item), "--dem", str(path)])
    assert ok.exit_code == 0 and "1 of 1 missions hold" in ok.output, ok.output


@pytest.mark.parametrize("geographic", [False, True])
@pytest.mark.parametrize("method", ["spherical", "horizontal", "vertical"])
@pytest.mark.parametrize("ratio", [0.3, 1.0, 10.0])
def test_the_clearance_from_a_file_against_brute_force(tmp_path, geographic, method, ratio):
    """SourceSeabed's clearance of points from a rough surface (R from 0.3 to 10 cells),
    projected and lon/lat: between the brute force over the surface sampled at a sixteenth of
    a cell (grid points included; it bounds a least distance above and a highest seabed
    below) and that less the sampling's reach."""
    rng = np.random.default_rng(3)
    n = 40
    z = rng.normal(-1000.0, 30.0, (n, n)).astype(np.float32).astype(np.float64)  # as stored
    if geographic:
        a_deg = 0.0005
        path, x, y = _tif(tmp_path / "g.tif", z, a_deg, -120.0, 45.0, "EPSG:4326")
        map_crs = CRS.from_proj4("+proj=aeqd +lat_0=44.99 +lon_0=-119.99 +datum=WGS84 +units=m")
    else:
        path, x, y = _tif(tmp_path / "p.tif", z, 30.0)
        map_crs = CRS.from_user_input(UTM)
    sb = SourceSeabed.open(path)
    a = sb.cell_m()
    R = ratio * a
    from pyproj import Geod

    to_src = Transformer.from_crs(map_crs, sb.crs, always_xy=True)
    to_map = Transformer.from_crs(sb.crs, map_crs, always_xy=True)
    cx, cy = to_map.transform(x[n // 2], y[n // 2])
    px = cx + rng.uniform(-5 * a, 5 * a, 6)
    py = cy + rng.uniform(-5 * a, 5 * a, 6)
    sx, sy = to_src.transform(px, py)
    f = RegularGridInterpolator((y[::-1], x), z[::-1])
    pz = f(np.column_stack([sy, sx])) + rng.uniform(0.2, 1.5, 6) * max(R, 30.0)
    got = sb.clearances(px, py, pz, map_crs.to_wkt(), R, method)
    # brute force: the surface at a sixteenth of a cell in the file's own coordinates, its
    # points placed in ground metres around each point (pyproj's Geod)
    fine_x = np.linspace(x[0], x[-1], 16 * (n - 1) + 1)
    fine_y = np.linspace(y[0], y[-1], 16 * (n - 1) + 1)
    gx, gy = np.meshgrid(fine_x, fine_y)
    gz = f(np.column_stack([gy.ravel(), gx.ravel()]))
    geod = Geod(ellps="WGS84")
    to_ll = Transformer.from_crs(sb.crs, "EPSG:4326", always_xy=True)
    lon_g, lat_g = to_ll.transform(gx.ravel(), gy.ravel())
    step = a / 16
    slope = max(np.abs(np.diff(z, axis=0)).max(), np.abs(np.diff(z, axis=1)).max()) / a
    for k in range(6):
        plon, plat = to_ll.transform(sx[k], sy[k])
        az, _, dist = geod.inv(np.full(gz.size, plon), np.full(gz.size, plat), lon_g, lat_g)
        if method == "vertical":
            assert got[k] == pytest.approx(pz[k] - f([[sy[k], sx[k]]])[0], abs=1e-6)
            continue
        if method == "spherical":
            d = np.sqrt(dist**2 + (pz[k] - gz) ** 2)
            brute = min(d[dist <= 1.25 * R].min(), 1.25 * R)
            assert brute - step * (1 + slope) <= got[k] <= brute + 1e-3
        else:
            brute = pz[k] - gz[dist < R].max()
            assert brute - step * 1.5 * slope <= got[k] <= brute + 1e-3


@pytest.mark.parametrize("method", ["spherical", "horizontal"])
def test_the_least_clearance_from_a_file_is_that_of_every_point_measured(tmp_path, method):
    """``least_only`` (what a mission's check against the DEM file asks): the least clearance
    of 3000 points along a wavy line over a rough lon/lat grid with no-data holes, and which
    point has it, are those of every point measured in full (itself checked against brute force
    above); the points over no-data are NaN either way; the others read their own clearance or
    ``inf`` (not below the least before them), never less; in groups whose windows the
    points' whole window holds, and read group by group when it is too large."""
    from pipeline.verify import seabed as sbm
    from pipeline.verify.seabed import SourceSeabed

    rng = np.random.default_rng(5)
    n = 120
    z = rng.normal(-1000.0, 40.0, (n, n))
    z[98:103, 57:63] = np.nan  # no-data the line crosses (half way along it)
    path, x, y = _tif(tmp_path / "g.tif", z, 0.0005, -120.0, 45.0, "EPSG:4326")
    sb = SourceSeabed.open(path)
    map_crs = CRS.from_proj4("+proj=aeqd +lat_0=44.97 +lon_0=-119.97 +datum=WGS84 +units=m")
    to_map = Transformer.from_crs("EPSG:4326", map_crs, always_xy=True)
    t = np.linspace(0.05, 0.95, 3000)
    lon = x[0] + (x[-1] - x[0]) * t
    lat = y[-1] + (y[0] - y[-1]) * (0.5 + 0.35 * np.sin(9 * t))
    px, py = to_map.transform(lon, lat)
    f = RegularGridInterpolator((y[::-1], x), np.nan_to_num(z, nan=-1000.0)[::-1])
    pz = f(np.column_stack([lat, lon])) + rng.uniform(30.0, 200.0, t.size)
    R = 60.0
    full = sb.clearances(px, py, pz, map_crs.to_wkt(), R, method)
    for cells in (sbm.WINDOW_CELLS, 100):  # one window for all, and a window a group
        sbm.WINDOW_CELLS, kept = cells, sbm.WINDOW_CELLS
        try:
            least = sb.clearances(px, py, pz, map_crs.to_wkt(), R, method, least_only=True)
        finally:
            sbm.WINDOW_CELLS = kept
        assert np.isnan(full).any() and np.array_equal(np.isnan(least), np.isnan(full))
        k = int(np.nanargmin(full))
        assert int(np.nanargmin(least)) == k and abs(least[k] - full[k]) <= 1e-3
        measured = np.isfinite(least)
        assert np.all(np.abs(least[measured] - full[measured]) <= 1e-3)
        assert 0 < measured.sum() < 0.5 * np.isfinite(full).sum()  # most points unmeasured
    # the points lowest over the seabed under them are those next to the no-data (their own
    # clearance unknown): the bound they give is under every other point's, which are then
    # measured in full
    vertical = sb.clearances(px, py, pz, map_crs.to_wkt(), R, "vertical")
    near = np.isnan(full) & np.isfinite(vertical)
    assert near.any()
    low = pz + 400.0  # every other point well clear
    low[near] = pz[near] - vertical[near] + 0.5
    full2 = sb.clearances(px, py, low, map_crs.to_wkt(), R, method)
    least2 = sb.clearances(px, py, low, map_crs.to_wkt(), R, method, least_only=True)
    assert np.array_equal(np.isnan(least2), np.isnan(full2)) and np.nanmin(full2) > 1.5
    k = int(np.nanargmin(full2))
    assert int(np.nanargmin(least2)) == k and abs(least2[k] - full2[k]) <= 1e-3
    if method == "spherical":  # and the least against scipy's KD-tree over the surface
        from scipy.spatial import cKDTree

        k4 = 4 * (n - 1) + 1  # the surface every quarter cell, in the map's metres
        fy, fx = np.linspace(y[-1], y[0], k4), np.linspace(x[0], x[-1], k4)
        gx, gy = np.meshgrid(fx, fy)
        gz = RegularGridInterpolator((y[::-1], x), z[::-1])(
            np.column_stack([gy.ravel(), gx.ravel()])
        )
        mx, my = to_map.transform(gx.ravel(), gy.ravel())
        keep = np.isfinite(gz)
        tree = cKDTree(np.column_stack([mx[keep], my[keep], gz[keep]]))
        ok = np.isfinite(least)
        brute = tree.query(np.column_stack([px[ok], py[ok], pz[ok]]))[0].min()
        step = 55.6 / 4 * math.sqrt(2)  # a quarter cell's diagonal, in metres (at most)
        slope = np.nanmax(np.abs(np.diff(z, axis=1))) / 39.0
        assert brute - step * (1 + slope) <= np.nanmin(least) <= brute + 1e-3


def _verify_checks_the_rating_and_the_zones_it_is_given(walls_job, tmp_path):
    """pipeline verify with a rated depth shallower than the track's deepest point (numpy, from
    the track file) and a zone across the track (shapely's distance): both checks fail and
    name what fails; a rating below the deepest point and a zone far away hold."""
    import geopandas as gpd
    from shapely.geometry import box

    tmp, path, z, x, y = walls_job
    item, t = _track(tmp)
    deepest = float(-t.z.min())  # (sea level 0)
    k = len(t) // 3
    across = box(t.x.iloc[k] - 50, t.y.iloc[k] - 50, t.x.iloc[k] + 50, t.y.iloc[k] + 50)
    far = box(x[0] - 5000, y[0] + 5000, x[0] - 4000, y[0] + 6000)
    zones = tmp_path / "zones.geojson"
    gpd.GeoDataFrame({"name": ["cable"]}, geometry=[across], crs=UTM).to_file(zones)
    (v,) = verify_missions(item, path, max_depth=deepest - 10.0, keep_out=[zones])
    checks = {c.name: c for c in v.checks}
    assert not v.holds
    assert not checks["depth against the rating"].holds
    assert checks["depth against the rating"].worst == pytest.approx(deepest, abs=0.01)
    assert not checks["keep-out margin"].holds and "cable" in checks["keep-out margin"].where
    gpd.GeoDataFrame({"name": ["far"]}, geometry=[far], crs=UTM).to_file(zones)
    (v,) = verify_missions(item, path, max_depth=deepest + 10.0, keep_out=[zones],
                           keep_out_margin=100.0)  # fmt: skip
    assert v.holds, [c.line() for c in v.checks]


def test_missions_along_a_bbox_edge_keep_their_clearance_from_the_file(tmp_path, local_client):
    """A lon/lat GeoTIFF cropped by a bbox, planned at 300 m cells with R 300 m, a mission
    0.01 degree inside the bbox's south edge and one inside its east edge: every track sample
    at least R above the file's own bilinear seabed (scipy, in the file's lon/lat), and
    pipeline verify holds."""
    from scipy import ndimage

    rng = np.random.default_rng(7)
    n, step, lon0, lat0 = 300, 0.002, -128.0, 45.0
    z = ndimage.gaussian_filter(rng.normal(0, 1, (n, n)), 12) * 2e4 - 3000.0
    z[rng.integers(0, n, 80), rng.integers(0, n, 80)] += 600.0  # narrow pinnacles
    path, lon, lat = _tif(tmp_path / "ll.tif", z, step, lon0, lat0, "EPSG:4326")
    box = [lon0 + 0.1, lat0 - 0.5, lon0 + 0.5, lat0 - 0.1]
    missions = f"""[[missions]]
name = "south"
start_lonlat = [{box[0] + 0.03}, {box[1] + 0.01}]
goal_lonlat = [{box[2] - 0.03}, {box[1] + 0.01}]
[[missions]]
name = "east"
start_lonlat = [{box[2] - 0.01}, {box[1] + 0.03}]
goal_lonlat = [{box[2] - 0.01}, {box[3] - 0.03}]"""
    _run(tmp_path, "edges", path, f"bbox = {box}\nresolution = 300.0", missions, local_client, 2)
    import geopandas as gpd

    f = RegularGridInterpolator((lat[::-1], lon), z.astype(np.float32)[::-1].astype(np.float64))
    for item in (tmp_path / "cat").glob("**/missions/*/*.json"):
        t = gpd.read_parquet(item.parent / "track.parquet")  # GeoParquet: lon/lat points
        below = f(np.column_stack([t.geometry.y, t.geometry.x]))
        assert (t.z.to_numpy() - below).min() >= 300.0 - 1e-3, item
    verdicts = verify_missions(tmp_path / "cat", path)
    assert len(verdicts) == 2 and all(v.holds for v in verdicts), [v.checks for v in verdicts]


def test_verify_walks_the_geodesic_and_the_rhumb_line_of_each_leg(tmp_path):
    """One 150 km leg at 60 N (a mission folder written here: its Item, track and waypoints),
    level 350 m above a flat seabed, and a pinnacle under the middle of the leg's rhumb line
    (a constant course, 800 m from the straight map line): verify fails the clearance and names
    the rhumb-line route; a pinnacle under the map line's middle is found on the map line."""
    import pandas as pd
    from pyproj import Transformer

    crs = CRS.from_proj4("+proj=aeqd +lat_0=60 +lon_0=0 +datum=WGS84 +units=m")
    to_ll = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    x0, y0, x1, y1 = -50_000.0, 40_000.0, 100_000.0, 60_000.0
    from pipeline.flight.legs import leg_lines

    (rx, ry) = leg_lines(crs.to_wkt(), x0, y0, x1, y1, [0.5])["rhumb line"]
    assert math.hypot(rx[0, 0] - (x0 + x1) / 2, ry[0, 0] - (y0 + y1) / 2) > 500
    lon = np.arange(-3.0, 3.0, 0.005)
    lat = np.arange(61.5, 59.5, -0.005)
    z = np.full((lat.size, lon.size), -3350.0)

    def pinnacle(px, py, height):
        plon, plat = to_ll.transform(px, py)
        z[np.argmin(np.abs(lat - plat)), np.argmin(np.abs(lon - plon))] = height

    for name, (px, py) in {
        "rhumb": (rx[0, 0], ry[0, 0]),
        "map": ((x0 + x1) / 2, (y0 + y1) / 2),
    }.items():
        folder = tmp_path / name
        folder.mkdir()
        z[:] = -3350.0
        pinnacle(px, py, -3100.0)  # 100 m under the vehicle at -3000 m
        import rioxarray  # noqa: F401

        arr = xr.DataArray(z.astype(np.float32), dims=("y", "x"), coords={"x": lon, "y": lat})
        arr.rio.write_crs("EPSG:4326").rio.to_raster(folder / "dem.tif")
        s = np.linspace(0, 1, 3001)
        x, y = x0 + (x1 - x0) * s, y0 + (y1 - y0) * s
        pd.DataFrame(
            {"x": x, "y": y, "z": -3000.0, "s_m": s * math.hypot(x1 - x0, y1 - y0)}
        ).to_parquet(folder / "track.parquet")
        wl, wa = to_ll.transform([x0, x1], [y0, y1])
        pd.DataFrame({"lat": wa, "lon": wl, "depth_m": [3000.0, 3000.0]}).to_csv(
            folder / "waypoints.csv", index=False
        )
        item = {"type": "Feature", "properties": {
            "auv:name": name, "auv:clearance_m": 300.0, "auv:clearance_method": "spherical",
            "auv:sea_level_m": 0.0, "proj:wkt2": crs.to_wkt()}}  # fmt: skip
        (folder / f"{name}.json").write_text(json.dumps(item))
        (v,) = verify_missions(folder, folder / "dem.tif")
        check = v.checks[0]
        assert not check.holds and check.worst < 250.0, check  # (the pinnacle on its node)
        if name == "rhumb":  # found on the rhumb line only: the map line passes 800 m away
            assert "rhumb-line route" in check.where, check.where
        else:
            assert "rhumb-line" not in check.where, check.where


def _same_stamp(path, write):
    """Rewrite ``path`` by ``write()`` and set its size and modification time back to what they
    were (as ``cp -p``, ``rsync -t`` or tar leave a replaced file)."""
    import os

    st = os.stat(path)
    write()
    assert os.stat(path).st_size == st.st_size
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))


def test_an_input_changed_in_place_with_its_size_and_time_is_planned_again(tmp_path, local_client):
    """Inputs are known by their content: a GeoTIFF DEM replaced by one with a ridge across the
    route, a zone file moved onto the route, and a chunk of a Zarr DEM raised, each with the
    same size and modification time as before, plan the mission again (and the new track keeps
    its clearance from the new file, by pipeline verify); an untouched re-run skips it."""
    import shapely
    import zarr

    z = np.full((60, 60), -3000.0)
    path, x, y = _tif(tmp_path / "dem.tif", z, 100.0)
    zone = tmp_path / "zone.geojson"

    def zone_at(x0):  # a 400 m square, its coordinates always written with the same width
        box = shapely.box(x0, y[40], x0 + 400.0, y[36])
        zone.write_text(
            json.dumps(
                {
                    "type": "FeatureCollection",
                    "crs": {"type": "name", "properties": {"name": UTM}},
                    "features": [
                        {
                            "type": "Feature",
                            "properties": {"name": "box"},
                            "geometry": shapely.geometry.mapping(box),
                        }
                    ],
                }
            )
        )

    zone_at(x[5])  # off the route
    missions = f"""[[missions]]
name = "m"
start_xy = [{x[5]}, {y[30]}]
goal_xy = [{x[55]}, {y[30]}]
keep_out = ["{zone}"]"""
    _run(tmp_path, "inplace", path, "", missions, local_client, 1)
    _run(tmp_path, "inplace", path, "", missions, local_client, 0)  # nothing changed

    ridge = z.copy()
    ridge[:, 28:32] = -2000.0
    _same_stamp(path, lambda: _tif(path, ridge, 100.0))
    _run(tmp_path, "inplace", path, "", missions, local_client, 1)
    (verdict,) = verify_missions(tmp_path / "cat", dem=path)
    assert verdict.holds, verdict
    _same_stamp(zone, lambda: zone_at(x[27]))  # across the route now
    _run(tmp_path, "inplace", path, "", missions, local_client, 1)
    (verdict,) = verify_missions(tmp_path / "cat", dem=path, keep_out=zone)
    assert verdict.holds, verdict  # the new track keeps its margin from the zone where it is now

    # a Zarr DEM (uncompressed: a chunk's size is its shape's), one chunk rewritten in place
    store = tmp_path / "dem.zarr"
    (tmp_path / "zarr").mkdir()
    arr = xr.DataArray(
        z.astype(np.float32), dims=("y", "x"), coords={"x": x, "y": y}, name="elevation"
    )
    arr.attrs["crs_wkt"] = CRS.from_user_input(UTM).to_wkt()
    arr.to_dataset().to_zarr(
        store, encoding={"elevation": {"compressors": None}}, consolidated=False
    )
    _run(tmp_path / "zarr", "inplace-zarr", store, "", missions, local_client, 1)
    (chunk,) = [p for p in (store / "elevation" / "c").rglob("*") if p.is_file()]
    _same_stamp(chunk, lambda: zarr.open_array(store / "elevation", mode="r+").__setitem__(
        (slice(None), slice(28, 32)), -2000.0))  # fmt: skip
    _run(tmp_path / "zarr", "inplace-zarr", store, "", missions, local_client, 1)
