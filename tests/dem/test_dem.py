"""DEM ingestion: GeoTIFF, NetCDF, GMT grids and Zarr to the canonical elevation DataArray.

References are independent of the code under test: the arrays the tests themselves wrote, and
for reprojection, pyproj plus scipy's RegularGridInterpolator on the source lon/lat grid.
"""

from __future__ import annotations

from pathlib import Path

import dask.array as da
import numpy as np
import pytest
import xarray as xr
from conftest import lonlat_dataarray, metric_dataarray, random_surface, write_bag
from pyproj import CRS, Transformer
from references import assert_upper_envelope
from scipy.interpolate import RegularGridInterpolator

import pipeline
from pipeline.exceptions import InvalidDEMError, StoreExistsError


def _write_tif(arr: xr.DataArray, path, crs="EPSG:32610", nodata=None):
    import rioxarray  # noqa: F401

    arr = arr.rio.write_crs(crs)
    if nodata is not None:
        arr = arr.rio.write_nodata(nodata)
    arr.rio.to_raster(path)
    return path


def test_geotiff_projected_int16_with_nodata(tmp_path):
    rng = np.random.default_rng(1)
    z = rng.integers(-5000, -100, size=(40, 30)).astype(np.int16)
    z[3, 4] = -32768
    path = _write_tif(metric_dataarray(z, a=50.0), tmp_path / "dem.tif", nodata=-32768)
    dem = pipeline.open_dem(path, chunks=16)
    assert dem.name == "elevation" and dem.dims == ("y", "x") and dem.dtype == np.float32
    assert isinstance(dem.data, da.Array) and dem.data.chunksize == (16, 16)
    assert dem.attrs["cell_size"] == 50.0 and pipeline.cell_size(dem) == 50.0
    assert CRS.from_wkt(dem.attrs["crs_wkt"]).to_epsg() == 32610
    v = dem.values
    assert np.isnan(v[3, 4])
    expected = z.astype(np.float32)
    expected[3, 4] = np.nan
    np.testing.assert_array_equal(v, expected)
    np.testing.assert_allclose(dem.x.values, 500_000 + (np.arange(30) + 0.5) * 50.0)


def test_geotiff_in_memory(tmp_path):
    z = random_surface((20, 25))
    path = _write_tif(metric_dataarray(z, a=10.0), tmp_path / "dem.tif")
    dem = pipeline.open_dem(path, chunks=None)
    assert isinstance(dem.data, np.ndarray)
    np.testing.assert_array_equal(dem.values, z)


def _reference_reprojection(dem, z, lon, lat):
    """Sample the source lon/lat grid bilinearly at the lon/lat of the output cell centres."""
    crs = CRS.from_wkt(dem.attrs["crs_wkt"])
    to_ll = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    xx, yy = np.meshgrid(dem.x.values, dem.y.values)
    lo, la = to_ll.transform(xx, yy)
    lo = np.where(lo < 0, lo + 360.0, lo) if lon.min() > 180 else lo
    order = np.argsort(lat)
    interp = RegularGridInterpolator(
        (lat[order], lon), z[order].astype(np.float64), bounds_error=False, fill_value=np.nan
    )
    # the source's cells are areas: its outer half cells hold the edge points' values
    hy, hx = abs(lat[1] - lat[0]) / 2, abs(lon[1] - lon[0]) / 2
    out = (
        (la < lat.min() - hy)
        | (la > lat.max() + hy)
        | (lo < lon.min() - hx)
        | (lo > lon.max() + hx)
    )
    la, lo = np.clip(la, lat.min(), lat.max()), np.clip(lo, lon.min(), lon.max())
    ref = interp(np.stack([la, lo], axis=-1))
    ref[out] = np.nan
    return ref


@pytest.mark.parametrize("chunks", [None, 64, (37, 295)])
def test_a_real_tenth_degree_grid_is_reprojected_above_the_source(tmp_path, topobathy, chunks):
    """matplotlib's real bathymetry on an even 0.1-degree lon/lat grid (scipy's bilinear
    resampling of the sample grid, written as a GeoTIFF), reprojected to 1000 m cells, in
    memory and in chunks (one of 37 rows and 295 of 296 columns: a last chunk of one column):
    the upper envelope of the source's bilinear surface (pyproj and scipy, independently),
    no-data exactly beyond the source's cells; and exact_warp, the bilinear resample, under
    1 m from pyproj's exact transform of every cell centre then bilinear in the source (GDAL's
    approximate transformer was 8 m rms off, up to 51 m)."""
    z, lon, lat = topobathy
    lon = lon - 360.0
    glat = np.arange(lat.min() + 0.01, lat.max(), 0.1)[::-1]  # north first, as GeoTIFFs are
    glon = np.arange(lon.min() + 0.01, lon.max(), 0.1)
    interp = RegularGridInterpolator((lat, lon), z.astype(np.float64))
    la, lo = np.meshgrid(glat, glon, indexing="ij")
    grid = interp(np.stack([la, lo], axis=-1)).astype(np.float32)
    arr = lonlat_dataarray(grid, glon, glat).rename(lat="y", lon="x")
    path = _write_tif(arr, tmp_path / "tenth.tif", crs="EPSG:4326")
    dem = pipeline.open_dem(path, resolution=1000.0, chunks=chunks)
    assert dem.shape == (222, 296)
    v = dem.values.astype(np.float64)
    ref = _reference_reprojection(dem, grid, glon, glat)
    assert np.array_equal(np.isnan(v), np.isnan(ref))  # the same cells have no source
    assert np.isfinite(ref).mean() > 0.85
    raised = assert_upper_envelope(dem, grid, glon, glat, CRS.from_epsg(4326))
    assert 0 < np.median(raised) < 300  # metres, on a relief of 3600 m, cells of 1 km
    from rasterio.transform import from_origin

    from pipeline.dem.reproject import exact_warp

    a = pipeline.cell_size(dem)
    transform = from_origin(dem.x.values[0] - a / 2, dem.y.values[0] + a / 2, a, a)
    crs = CRS.from_wkt(dem.attrs["crs_wkt"])
    exact = exact_warp(arr, CRS.from_epsg(4326), crs, transform, dem.shape).values
    ok = np.isfinite(ref)
    err = exact[ok] - ref[ok]
    assert np.sqrt(np.mean(err**2)) < 1.0 and np.abs(err).max() < 1.0, np.abs(err).max()


@pytest.mark.parametrize("fixture", ["topobathy_tif", "topobathy_nc"])
def test_real_lonlat_dem_is_reprojected(request, fixture, topobathy, caplog):
    """matplotlib's real bathymetry off Vancouver Island, through a real GeoTIFF and NetCDF."""
    z, lon, lat = topobathy
    path = request.getfixturevalue(fixture)
    with caplog.at_level("WARNING", logger="pipeline"):
        dem = pipeline.open_dem(path, chunks=32)
    assert "geographic" in caplog.text and "azimuthal equidistant" in caplog.text
    crs = CRS.from_wkt(dem.attrs["crs_wkt"])
    assert crs.is_projected and "Azimuthal Equidistant" in crs.to_wkt()
    # resolution close to the source's: 1/30 deg of longitude at 49 N, 1/45 deg of latitude
    dx_m = (lon[1] - lon[0]) * 111_320 * np.cos(np.radians(lat.mean()))
    dy_m = abs(lat[1] - lat[0]) * 111_320
    a = pipeline.cell_size(dem)
    assert 0.9 * min(dx_m, dy_m) <= a <= 1.1 * max(dx_m, dy_m)
    # square cells, metric coordinates, extent about the source's
    assert np.allclose(np.diff(dem.x.values), a) and np.allclose(np.diff(dem.y.values), -a)
    width_km = (dem.x.values[-1] - dem.x.values[0]) / 1e3
    assert 250 < width_km < 330  # 4 degrees of longitude at 49 N is about 292 km
    # the upper envelope of the source's bilinear surface, against pyproj and scipy, on the
    # grid the file holds (a GeoTIFF's is even: its latitudes are not the sample's uneven ones)
    if fixture == "topobathy_tif":
        import rioxarray

        held = rioxarray.open_rasterio(path).squeeze("band", drop=True)
        z, lon, lat = held.values, held.x.values + 360.0, held.y.values
    assert_upper_envelope(dem.load(), z, lon - 360.0, lat, CRS.from_epsg(4326))
    ref = _reference_reprojection(dem, z, lon, lat)
    v = dem.values.astype(np.float64)
    inner = np.isfinite(ref) & np.isfinite(v)
    assert inner.sum() > 0.7 * v.size
    # land detection: real land and sea both present; the source's land is land
    land_ref = ref[inner] >= 0
    assert 0.2 < land_ref.mean() < 0.8
    assert np.all(v[inner][land_ref] >= 0)


def test_netcdf_projected_grd_and_depth_positive_down(tmp_path, caplog):
    z = random_surface((30, 40))
    arr = metric_dataarray(-z, a=25.0)  # stored as depths, positive down
    arr.attrs["positive"] = "down"
    path = tmp_path / "depth.grd"
    arr.to_dataset(name="z").to_netcdf(path)
    with caplog.at_level("WARNING", logger="pipeline"):
        dem = pipeline.open_dem(path, chunks=None)
    assert "positive='down'" in caplog.text
    np.testing.assert_array_equal(dem.values, z)
    assert dem.attrs["cell_size"] == 25.0


def test_old_gmt_grid_format(tmp_path):
    """The 1-D GMT grid layout: z flattened row-major from the top row, x_range/y_range."""
    z = random_surface((12, 9))
    ny, nx = z.shape
    ds = xr.Dataset(
        {
            "x_range": ("side", [1000.0, 1000.0 + 8 * 20.0], {"units": "m"}),
            "y_range": ("side", [0.0, 11 * 20.0], {"units": "m"}),
            "z_range": ("side", [float(z.min()), float(z.max())]),
            "spacing": ("side", [20.0, 20.0]),
            "dimension": ("side", np.array([nx, ny], dtype=np.int32)),
            "z": ("xysize", z.ravel(), {"node_offset": 0}),
        }
    )
    path = tmp_path / "old.grd"
    ds.to_netcdf(path, format="NETCDF3_CLASSIC")
    dem = pipeline.open_dem(path, chunks=None)
    np.testing.assert_array_equal(dem.values, z)
    np.testing.assert_allclose(dem.x.values, 1000.0 + np.arange(9) * 20.0)
    np.testing.assert_allclose(dem.y.values, 220.0 - np.arange(12) * 20.0)


def test_non_square_cells_are_resampled(tmp_path, caplog):
    rows, cols = 40, 30
    x = (np.arange(cols) + 0.5) * 40.0
    y = 4000.0 - (np.arange(rows) + 0.5) * 10.0
    xx, yy = np.meshgrid(x, y)
    z = (-3000 + 0.5 * xx - 0.8 * yy).astype(np.float32)  # a plane: bilinear is exact
    arr = xr.DataArray(z, dims=("y", "x"), coords={"x": x, "y": y})
    path = tmp_path / "rect.nc"
    arr.to_dataset(name="elevation").to_netcdf(path)
    with caplog.at_level("WARNING", logger="pipeline"):
        dem = pipeline.open_dem(path, chunks=None)
    assert "resampling to square" in caplog.text
    a = pipeline.cell_size(dem)
    assert a == pytest.approx(20.0)
    # a plane's highest over the square of half-side a around a node: its corner uphill
    # (+x, -y), where that corner lies within the source's points
    xx2, yy2 = np.meshgrid(dem.x.values, dem.y.values)
    ref = -3000 + 0.5 * (xx2 + a) - 0.8 * (yy2 - a)
    inside = (xx2 + a <= x[-1]) & (yy2 - a >= y[-1]) & (xx2 - a >= x[0]) & (yy2 + a <= y[0])
    assert inside.sum() > 100
    np.testing.assert_allclose(dem.values[inside], ref[inside], atol=0.05)
    assert_upper_envelope(dem, z, x, y)


def test_resolution_resamples_a_projected_grid(tmp_path):
    """A 50 m survey grid asked at 20 m: the upper envelope of its bilinear surface."""

    z = random_surface((30, 40), seed=3)
    arr = metric_dataarray(z, a=50.0)
    path = tmp_path / "survey.nc"
    arr.to_dataset(name="elevation").to_netcdf(path)
    dem = pipeline.open_dem(path, chunks=None, resolution=20.0)
    assert pipeline.cell_size(dem) == 20.0
    assert dem.shape == (75, 100)  # the same extent: 1500 x 2000 m
    assert np.allclose(np.diff(dem.x.values), 20.0) and np.allclose(np.diff(dem.y.values), -20.0)
    assert_upper_envelope(dem, z, arr.x.values, arr.y.values)


def test_resolution_sets_the_reprojected_cell(topobathy_nc, topobathy):
    z, lon, lat = topobathy
    dem = pipeline.open_dem(topobathy_nc, chunks=None, resolution=1000.0)
    assert pipeline.cell_size(dem) == 1000.0
    assert np.allclose(np.diff(dem.x.values), 1000.0)
    width_km = (dem.x.values[-1] - dem.x.values[0]) / 1e3
    assert 250 < width_km < 330  # the same extent as at the default (2.4 km) cells
    assert_upper_envelope(dem, z, lon - 360.0, lat, CRS.from_epsg(4326))


@pytest.mark.parametrize("bad", [0.0, -5.0, float("nan")])
def test_resolution_must_be_positive(tmp_path, bad):
    path = tmp_path / "g.nc"
    metric_dataarray(random_surface((10, 10))).to_dataset(name="elevation").to_netcdf(path)
    with pytest.raises(pipeline.PipelineError, match="resolution"):
        pipeline.open_dem(path, chunks=None, resolution=bad)


def test_uneven_axis_is_resampled(tmp_path, caplog):
    x = np.array([0.0, 10.0, 21.0, 30.0, 40.0, 49.0, 60.0])
    y = 100.0 - np.arange(5) * 10.0
    z = np.broadcast_to(-2000.0 + 2.0 * x, (5, 7)).astype(np.float32)  # linear in x
    path = tmp_path / "uneven.nc"
    xr.DataArray(z, dims=("y", "x"), coords={"x": x, "y": y}).to_dataset(
        name="elevation"
    ).to_netcdf(path)
    with caplog.at_level("WARNING", logger="pipeline"):
        dem = pipeline.open_dem(path, chunks=None)
    assert "unevenly spaced" in caplog.text
    np.testing.assert_allclose(dem.x.values, np.arange(7) * 10.0)
    # rising with x: the highest within a cell is a cell east, no farther than the last point
    up = np.minimum(dem.x.values + 10.0, 60.0)
    np.testing.assert_allclose(dem.values, np.broadcast_to(-2000.0 + 2.0 * up, (5, 7)), atol=1e-3)


def test_no_coordinates_needs_cell_size(tmp_path):
    z = random_surface((10, 12))
    path = tmp_path / "bare.nc"
    xr.DataArray(z, dims=("row", "col")).to_dataset(name="elevation").to_netcdf(path)
    with pytest.raises(InvalidDEMError, match="no coordinates and no cell size"):
        pipeline.open_dem(path)
    dem = pipeline.open_dem(path, chunks=None, cell_size=5.0)
    assert pipeline.cell_size(dem) == 5.0
    np.testing.assert_array_equal(dem.values, z)


def test_zarr_roundtrip_any_chunks(tmp_path):
    z = random_surface((130, 70), holes=True)
    src = metric_dataarray(z, a=30.0)
    tif = _write_tif(src, tmp_path / "in.tif")
    dem = pipeline.open_dem(tif, chunks=(33, 17))
    store = pipeline.write_dem(dem, tmp_path / "dem.zarr", chunks=64)
    back = pipeline.open_dem(store, chunks=64)
    assert back.data.chunksize == (64, 64)
    np.testing.assert_array_equal(back.values, z)
    assert back.attrs["cell_size"] == 30.0
    assert CRS.from_wkt(back.attrs["crs_wkt"]).to_epsg() == 32610
    import zarr

    g = zarr.open_group(store, mode="r")
    assert g.metadata.zarr_format == 3
    assert g["elevation"].chunks == (64, 64)


def test_write_is_atomic_and_refuses_to_clobber(tmp_path):
    dem = pipeline.synthetic_dem((64, 64), chunks=32)
    store = pipeline.write_dem(dem, tmp_path / "d.zarr", chunks=32)
    with pytest.raises(StoreExistsError, match="overwrite"):
        pipeline.write_dem(dem, store)

    def boom(block, block_info=None):
        if block_info[0]["chunk-location"] == (1, 1):
            raise RuntimeError("disk full")
        return block

    bad = dem.copy(data=dem.data.map_blocks(boom, dtype=np.float32))
    with pytest.raises(RuntimeError, match="disk full"):
        pipeline.write_dem(bad, store, chunks=32, overwrite=True)
    # the old complete store is still there, no temporary left behind
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.zarr"]
    np.testing.assert_array_equal(pipeline.open_dem(store, chunks=None).values, dem.values)


def test_import_dem_cli_function(tmp_path, topobathy_tif):
    store = pipeline.import_dem(topobathy_tif, tmp_path / "real.zarr", chunks=64)
    dem = pipeline.open_dem(store)
    assert dem.attrs["pipeline_dem_version"] == 1 and "crs_wkt" in dem.attrs
    assert (dem.values >= 0).any() and (dem.values < -500).any()


# ----------------------------------------------------------------------------- bad input


def _bad_multiband(p):
    arr = xr.DataArray(
        np.zeros((3, 8, 8), np.float32),
        dims=("band", "y", "x"),
        coords={"band": [1, 2, 3], "x": np.arange(8.0) * 10, "y": 80 - np.arange(8.0) * 10},
    )
    return _write_tif(arr, p.with_suffix(".tif"))


def _bad_all_nan(p):
    return _write_tif(metric_dataarray(np.full((8, 8), np.nan, np.float32)), p.with_suffix(".tif"))


def _bad_nodata_everywhere(p):
    z = np.full((8, 8), -9999, np.int16)
    return _write_tif(metric_dataarray(z), p.with_suffix(".tif"), nodata=-9999)


def _bad_no_coords(p):
    xr.DataArray(np.zeros((8, 8), np.float32), dims=("a", "b")).to_dataset(
        name="elevation"
    ).to_netcdf(p.with_suffix(".nc"))
    return p.with_suffix(".nc")


def _bad_text_type(p):
    arr = xr.DataArray(
        np.array([["a", "b"], ["c", "d"]]),
        dims=("y", "x"),
        coords={"x": [0.0, 1.0], "y": [1.0, 0.0]},
    )
    arr.to_dataset(name="elevation").to_netcdf(p.with_suffix(".nc"))
    return p.with_suffix(".nc")


def _bad_garbage(p):
    q = p.with_suffix(".tif")
    q.write_bytes(b"this is not a tiff at all" * 10)
    return q


def _bad_empty_nc(p):
    q = p.with_suffix(".nc")
    q.write_bytes(b"")
    return q


def _bad_unordered(p):
    arr = xr.DataArray(
        np.zeros((4, 4), np.float32),
        dims=("y", "x"),
        coords={"x": [0.0, 2.0, 1.0, 3.0], "y": [3.0, 2.0, 1.0, 0.0]},
    )
    arr.to_dataset(name="elevation").to_netcdf(p.with_suffix(".nc"))
    return p.with_suffix(".nc")


def _bad_3d_netcdf(p):
    arr = xr.DataArray(
        np.zeros((2, 4, 4), np.float32),
        dims=("time", "y", "x"),
        coords={"x": np.arange(4.0), "y": np.arange(4.0)[::-1]},
    )
    arr.to_dataset(name="elevation").to_netcdf(p.with_suffix(".nc"))
    return p.with_suffix(".nc")


def _bad_two_vars(p):
    c = {"x": np.arange(4.0), "y": np.arange(4.0)[::-1]}
    xr.Dataset(
        {"a": (("y", "x"), np.zeros((4, 4))), "b": (("y", "x"), np.ones((4, 4)))}, coords=c
    ).to_netcdf(p.with_suffix(".nc"))
    return p.with_suffix(".nc")


def _bad_plain_dir(p):
    p.mkdir()
    return p


def _bad_missing(p):
    return p.with_suffix(".tif")


def _bad_one_row(p):
    arr = xr.DataArray(
        np.zeros((1, 5), np.float32), dims=("y", "x"), coords={"x": np.arange(5.0), "y": [0.0]}
    )
    arr.to_dataset(name="elevation").to_netcdf(p.with_suffix(".nc"))
    return p.with_suffix(".nc")


@pytest.mark.parametrize(
    "make, match",
    [
        (_bad_multiband, r"3 bands .*none is named elevation.*variable=\.\.\."),
        (_bad_3d_netcdf, r"3-D \(time=2"),
        (_bad_all_nan, "holds no valid elevation"),
        (_bad_nodata_everywhere, "holds no valid elevation"),
        (_bad_no_coords, "no coordinates and no cell size"),
        (_bad_text_type, "not numbers"),
        (_bad_garbage, "cannot read DEM file"),
        (_bad_empty_nc, "cannot read DEM file"),
        (_bad_unordered, "not strictly increasing or decreasing"),
        (_bad_two_vars, r"several 2-D variables \['a', 'b'\]"),
        (_bad_plain_dir, "not a Zarr store"),
        (_bad_missing, "does not exist"),
        (_bad_one_row, "at least 2 x 2"),
    ],
)
def test_bad_files_are_refused_clearly(tmp_path, make, match):
    path = make(tmp_path / "bad")
    with pytest.raises(InvalidDEMError, match=match) as info:
        pipeline.open_dem(path)
    assert str(path) in str(info.value)  # the message names the file


def test_variable_picks_one_of_several(tmp_path):
    c = {"x": np.arange(4.0) * 10, "y": (np.arange(4.0) * 10)[::-1]}
    path = tmp_path / "two.nc"
    xr.Dataset(
        {"a": (("y", "x"), np.zeros((4, 4))), "b": (("y", "x"), -np.ones((4, 4)))}, coords=c
    ).to_netcdf(path)
    assert float(pipeline.open_dem(path, variable="b", chunks=None).mean()) == -1.0
    with pytest.raises(InvalidDEMError, match="no variable 'c'"):
        pipeline.open_dem(path, variable="c")


def test_cell_size_rejects_non_dataarray():
    with pytest.raises(pipeline.InvalidParameterError, match="xarray.DataArray"):
        pipeline.cell_size(np.zeros((3, 3)))


def test_lonlat_dataarray_helper_roundtrip(topobathy):
    z, lon, lat = topobathy
    arr = lonlat_dataarray(z, lon, lat)
    assert arr.lat.values[0] > arr.lat.values[-1]


def test_a_geotiff_is_read_in_chunks_not_whole(tmp_path):
    """A large file must never be one dask chunk (dem info or an import would hold it all)."""
    import rioxarray  # noqa: F401

    arr = metric_dataarray(random_surface((300, 260)), a=50.0).rio.write_crs("EPSG:32610")
    arr.rio.to_raster(tmp_path / "big.tif", tiled=True, blockxsize=64, blockysize=64)
    dem = pipeline.open_dem(tmp_path / "big.tif", chunks=64)
    assert dem.data.chunksize == (64, 64)
    assert pipeline.dem.readers.file_chunks(tmp_path / "big.tif") == (64, 64)


def test_a_new_dem_format_is_one_reader_and_one_registry_line(tmp_path, monkeypatch):
    """The READERS registry is the one place formats are known: a reader of .npz grids (its
    own x, y and z arrays) registered there is recognised by suffix, opened by open_dem as
    any DEM (the canonical grid, chunked, cell size from the coordinates) and listed in the
    message for a file of no known format."""
    from pipeline.dem.readers import READERS, Reader

    z = random_surface((40, 30))
    x, y = 100.0 + 25.0 * np.arange(30), 5000.0 - 25.0 * np.arange(40)
    np.savez(tmp_path / "grid.npz", x=x, y=y, z=z)

    def read_npz(path, chunks, variable, uncertainty):
        with np.load(path) as f:
            arr = xr.DataArray(f["z"], dims=("y", "x"), coords={"y": f["y"], "x": f["x"]})
        return (arr if chunks is None else arr.chunk(chunks)), None

    fmt = Reader("npz", "a NumPy grid (.npz)", read_npz, lambda p: None, suffixes=(".npz",))
    monkeypatch.setitem(READERS, "npz", fmt)
    dem = pipeline.open_dem(tmp_path / "grid.npz", chunks=16)
    assert dem.dims == ("y", "x") and dem.data.chunksize == (16, 16)
    assert dem.attrs["cell_size"] == 25.0
    np.testing.assert_array_equal(dem.values, z.astype(dem.dtype))
    (tmp_path / "grid.xyz").write_text("1 2 3\n")
    with pytest.raises(InvalidDEMError, match=r"a Zarr store or a NumPy grid \(\.npz\)"):
        pipeline.open_dem(tmp_path / "grid.xyz")


# ------------------------------------------------------------------ a region of a file (bbox)


def _rchar() -> int:
    """Bytes this process has read through read() calls so far (Linux /proc/self/io)."""
    with open("/proc/self/io") as fh:
        return int(next(v for k, v in (line.split(": ") for line in fh) if k == "rchar"))


def test_bbox_xy_reads_only_its_window_of_a_tiled_geotiff(tmp_path):
    """The region equals the cells of the array whose centres lie in the box, one cell more on
    each side (indices computed here from the coordinates), and reading it reads the tiles it
    touches, not the file (bytes read by this process, /proc/self/io)."""
    import rioxarray  # noqa: F401

    z = random_surface((2048, 2048), seed=4).astype(np.float32) * 100 - 3000
    arr = metric_dataarray(z, a=50.0).rio.write_crs("EPSG:32610")
    path = tmp_path / "big.tif"
    arr.rio.to_raster(path, tiled=True, blockxsize=256, blockysize=256)
    x, y = arr.x.values, arr.y.values
    box = (x[700] + 10.0, y[1400] - 10.0, x[1000] - 10.0, y[1100] + 10.0)  # x0, y0, x1, y1
    # the first read in a process imports modules (read() calls too): do it on another file
    small = arr[:300, :300]
    small.rio.to_raster(tmp_path / "small.tif", tiled=True, blockxsize=256, blockysize=256)
    warm = (x[10], y[200], x[100], y[50])
    pipeline.open_dem(tmp_path / "small.tif", chunks=256, bbox_xy=warm).values.sum()
    before = _rchar()
    dem = pipeline.open_dem(path, chunks=1024, bbox_xy=box)  # read in the file's tiles
    got = dem.values
    read = _rchar() - before
    cols = np.nonzero((x >= box[0] - 50) & (x <= box[2] + 50))[0]
    rows = np.nonzero((y >= box[1] - 50) & (y <= box[3] + 50))[0]
    np.testing.assert_array_equal(got, z[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1])
    np.testing.assert_array_equal(dem.x.values, x[cols[0] : cols[-1] + 1])
    assert got.shape == (
        303,
        301,
    )  # rows 1099..1401 (the box edges lie 10 m outside), cols 700..1000
    size = path.stat().st_size
    assert read < 0.15 * size, (read, size)  # 3 x 3 of 8 x 8 tiles touched, and the header
    before = _rchar()
    whole = pipeline.open_dem(path, chunks=256).values  # the whole file, for scale
    assert _rchar() - before > 0.9 * size and whole.shape == (2048, 2048)


def test_import_reads_the_file_once_and_skips_no_data_chunks(tmp_path):
    """import_dem reads a tiled GeoTIFF once (its check for a valid cell is made on what it
    writes, not in a pass of its own), stores no chunk that is all no-data, and the store reads
    back as the file (NaN where the file has no data)."""
    import rioxarray  # noqa: F401

    z = random_surface((1024, 1024), seed=6).astype(np.float32) * 100 - 3000
    z[:256, :512] = np.nan  # two whole chunks of 256^2 without data
    arr = metric_dataarray(z, a=50.0).rio.write_crs("EPSG:32610").rio.write_nodata(np.nan)
    path = tmp_path / "tiled.tif"
    arr.rio.to_raster(path, tiled=True, blockxsize=256, blockysize=256)
    small = tmp_path / "small.tif"  # the first read in a process imports modules
    arr[:300, :300].rio.to_raster(small, tiled=True, blockxsize=256, blockysize=256)
    pipeline.import_dem(small, tmp_path / "small.zarr", chunks=256)
    import rasterio

    before = _rchar()
    with rasterio.Env(GDAL_CACHEMAX=1):  # 1 MB of GDAL's block cache: a second pass re-reads
        store = pipeline.import_dem(path, tmp_path / "dem.zarr", chunks=256)
    read = _rchar() - before
    size = path.stat().st_size
    assert 0.9 * size < read < 1.4 * size, (read, size)
    stored = sorted(
        p.relative_to(store) for p in (store / "elevation" / "c").rglob("*") if p.is_file()
    )
    assert len(stored) == 16 - 2 and Path("elevation/c/0/0") not in stored
    np.testing.assert_array_equal(pipeline.open_dem(store, chunks=None).values, z)


def test_bbox_in_lon_lat_on_a_projected_file_covers_the_box(tmp_path):
    z = random_surface((400, 300), seed=5).astype(np.float32) * 50 - 2000
    arr = metric_dataarray(z, a=50.0)
    path = _write_tif(arr, tmp_path / "utm.tif")
    to_ll = Transformer.from_crs("EPSG:32610", "EPSG:4326", always_xy=True)
    lon0, lat0 = to_ll.transform(float(arr.x[60]), float(arr.y[300]))
    lon1, lat1 = to_ll.transform(float(arr.x[200]), float(arr.y[100]))
    dem = pipeline.open_dem(path, chunks=128, bbox=(lon0, lat0, lon1, lat1))
    assert dem.shape[0] < 400 and dem.shape[1] < 300
    # every point of the box's outline, in map coordinates, lies inside the region read
    to_xy = Transformer.from_crs("EPSG:4326", "EPSG:32610", always_xy=True)
    t = np.linspace(0, 1, 50)
    ring = [
        *zip(lon0 + t * (lon1 - lon0), np.full(50, lat0), strict=True),
        *zip(lon0 + t * (lon1 - lon0), np.full(50, lat1), strict=True),
        *zip(np.full(50, lon0), lat0 + t * (lat1 - lat0), strict=True),
        *zip(np.full(50, lon1), lat0 + t * (lat1 - lat0), strict=True),
    ]
    bx, by = to_xy.transform(*np.array(ring).T)
    assert dem.x.min() <= bx.min() and bx.max() <= dem.x.max()
    assert dem.y.min() <= by.min() and by.max() <= dem.y.max()
    # and it is the box, not much more: at most two cells beyond the outline on each side
    assert dem.x.min() >= bx.min() - 100.5 and dem.x.max() <= bx.max() + 100.5
    np.testing.assert_array_equal(dem.values, arr.sel(x=dem.x, y=dem.y).values)


@pytest.mark.parametrize("fixture", ["topobathy_tif", "topobathy_nc"])
def test_bbox_on_a_lon_lat_grid_either_longitude_convention(request, fixture):
    """The real lon/lat grid, as a GeoTIFF (longitudes -180..180) and as a NetCDF file
    (0..360): the same western-longitude box selects the same region, reprojected."""
    path = request.getfixturevalue(fixture)
    whole = pipeline.open_dem(path, chunks=None)
    box = (-124.0, 48.3, -123.2, 48.9)
    dem = pipeline.open_dem(path, chunks=None, bbox=box)
    assert dem.size < 0.5 * whole.size
    to_ll = Transformer.from_crs(CRS.from_wkt(dem.attrs["crs_wkt"]), "EPSG:4326", always_xy=True)
    xx, yy = np.meshgrid(dem.x.values[[0, -1]], dem.y.values[[0, -1]])
    lon, lat = to_ll.transform(xx.ravel(), yy.ravel())
    assert lon.min() <= box[0] + 0.02 and lon.max() >= box[2] - 0.02  # it covers the box
    assert lat.min() <= box[1] + 0.02 and lat.max() >= box[3] - 0.02
    assert lon.min() >= box[0] - 0.1 and lat.max() <= box[3] + 0.1  # and not much more


def test_bbox_errors_are_one_clear_line(tmp_path, topobathy_nc):
    arr = metric_dataarray(random_surface((40, 40)), a=50.0)
    plain = tmp_path / "plain.nc"
    arr.to_dataset(name="elevation").to_netcdf(plain)  # no CRS
    tif = _write_tif(arr, tmp_path / "a.tif")
    cases = [
        (dict(bbox=(-124, 48, -123, 49), bbox_xy=(0, 0, 1, 1)), tif, "not both"),
        (dict(bbox=(-124, 48, -123)), tif, "bbox` must be four finite numbers"),
        (dict(bbox=(-123, 48, -124, 49)), tif, "each minimum below its maximum"),
        (dict(bbox_xy=("a", 0, 1, 1)), tif, "bbox_xy` must be four finite numbers"),
        (dict(bbox=(-124, 48, -123, 95)), tif, "latitudes from -90 to 90"),
        (dict(bbox=(10, 10, 11, 11)), tif, "does not overlap DEM file"),
        (dict(bbox=(-124, 48, -123, 49)), plain, "has no coordinate reference system"),
        (dict(bbox=(-1, 48, 1, 49)), topobathy_nc, "crosses longitude 0"),
    ]
    for kwargs, path, match in cases:
        with pytest.raises(pipeline.PipelineError, match=match):
            pipeline.open_dem(path, chunks=None, **kwargs)


def test_a_lon_lat_grid_is_reprojected_chunk_by_chunk(tmp_path):
    """The reprojection streams: the result is a dask array in the requested chunks, and one
    output chunk reads the source window it needs, not the file (bytes read, /proc/self/io)."""
    import rioxarray  # noqa: F401

    n = 1024
    lon = -130.0 + (np.arange(n) + 0.5) * 0.004
    lat = 50.0 - (np.arange(n) + 0.5) * 0.004
    glon, glat = np.meshgrid(lon, lat)
    z = (-3000 + 800 * np.sin(glon * 9.0) * np.cos(glat * 7.0)).astype(np.float32)  # smooth
    arr = lonlat_dataarray(z, lon, lat).rename(lat="y", lon="x").rio.write_crs("EPSG:4326")
    path = tmp_path / "lonlat.tif"
    arr.rio.to_raster(path, tiled=True, blockxsize=128, blockysize=128)
    small = tmp_path / "small.tif"  # the first read in a process imports modules: not here
    arr[:300, :300].rio.to_raster(small, tiled=True, blockxsize=128, blockysize=128)
    pipeline.open_dem(small, chunks=128, validate=False).values.sum()
    dem = pipeline.open_dem(path, chunks=128, validate=False)
    assert isinstance(dem.data, da.Array) and dem.data.chunksize == (128, 128)
    before = _rchar()
    corner = dem.data.blocks[0, 0].compute()
    read = _rchar() - before
    assert np.isfinite(corner).any()
    assert read < 0.2 * path.stat().st_size, (read, path.stat().st_size)
    # the chunks together: the same reprojection as in memory (GDAL's approximate transformer
    # places samples within 1/8 cell either way), and an independent bilinear sampling
    v = dem.values
    whole = pipeline.open_dem(path, chunks=None, validate=False).values
    ref = _reference_reprojection(dem, z, lon, lat)
    ok = np.isfinite(v) & np.isfinite(whole) & np.isfinite(ref)
    assert ok.mean() > 0.9
    assert np.abs(v[ok] - whole[ok]).max() < 1e-2  # each node alone, its lattice aside
    assert np.all(v[ok] >= ref[ok] - 1e-3)  # the upper envelope
    assert np.median(v[ok] - ref[ok]) < 50.0  # metres, on a 1600 m relief, 364 m cells


# ------------------------------------------------------------------ written band by band


def _counted_max_filter(x, chunks, calls):
    """A 3 x 3 maximum filter of ``x`` as a dask graph whose source blocks count their runs in
    ``calls``: every output block needs the source blocks around it."""

    def source(block, block_info=None):
        calls[block_info[0]["chunk-location"]] += 1
        return block

    from scipy import ndimage

    a = da.from_array(x, chunks=chunks).map_blocks(source, dtype=x.dtype)
    return a.map_overlap(
        lambda v: ndimage.maximum_filter(v, size=3, mode="nearest"), depth=1, boundary="nearest"
    )


@pytest.mark.parametrize("scheduler", ["threads", "synchronous"])
def test_a_banded_write_equals_the_whole_and_reads_each_block_once(scheduler):
    """store_in_bands (the DEM writer's) on a graph where each output block needs its
    neighbours' source blocks, in awkward chunks (a last chunk row and column of one cell):
    for bands of one block row, two, and the whole, the array written equals scipy's filter
    of the whole array, and every source block ran exactly once (the blocks astride a band's
    boundary are kept for the next band, not read again)."""
    from collections import Counter

    import dask
    import zarr
    from scipy import ndimage

    from pipeline.store.bands import store_in_bands

    x = np.random.default_rng(4).normal(size=(301, 201)).astype(np.float32)
    ref = ndimage.maximum_filter(x, size=3, mode="nearest")
    row = 201 * 100 * 4  # the bytes of one block row
    for band_bytes in (1, 2 * row, 10**9):
        calls: Counter = Counter()
        out = _counted_max_filter(x, 100, calls)
        target = zarr.create_array(store={}, shape=x.shape, chunks=(100, 100), dtype="float32")
        seen: list = []
        with dask.config.set(scheduler=scheduler):
            store_in_bands(
                out, target, band_bytes=band_bytes, progress=lambda d, k, s=seen: s.append((d, k))
            )
        assert np.array_equal(target[:], ref), band_bytes
        assert len(calls) == 4 * 3 and set(calls.values()) == {1}, (band_bytes, calls)
        bands = {1: 4, 2 * row: 2, 10**9: 1}[band_bytes]
        assert seen == [(d, bands) for d in range(1, bands + 1)]


def test_a_banded_write_holds_about_a_band():
    """What dask holds while a band is computed stays within a few block rows of a 20-row map,
    with bands of one block row (measured by a scheduler callback on its results)."""
    from collections import Counter

    import dask
    import zarr
    from dask.callbacks import Callback

    from pipeline.store.bands import store_in_bands

    x = np.random.default_rng(5).normal(size=(1000, 400))
    row = 400 * 50 * 8
    held = [0]

    class Held(Callback):
        def _posttask(self, key, result, dsk, state, id):
            held[0] = max(held[0], sum(getattr(v, "nbytes", 0) for v in state["cache"].values()))

    out = _counted_max_filter(x, 50, Counter())
    target = zarr.create_array(store={}, shape=x.shape, chunks=(50, 50), dtype="float64")
    with dask.config.set(scheduler="threads"), Held():
        store_in_bands(out, target, band_bytes=row)
    assert np.isfinite(target[:]).all()
    assert held[0] <= 6 * row, held[0] / row


def test_a_reprojection_written_in_bands_reads_each_source_chunk_once(tmp_path, local_client):
    """A lon/lat grid reprojected chunk by chunk (``exact_warp``, as lon/lat DEMs are: each
    output chunk samples the source window it needs) from a source whose chunks
    count their reads, written a band of one chunk row at a time: the same values as computed
    whole, every source chunk read once (those astride a band's boundary kept for the next
    band); under a distributed client (what is kept stays on the workers) the same values."""
    from collections import Counter

    import dask
    import xarray as xr
    import zarr
    from pyproj import CRS
    from rasterio.warp import calculate_default_transform

    from pipeline.dem.reproject import exact_warp
    from pipeline.store.bands import store_in_bands

    n = 1024
    lon = -60.0 + (np.arange(n) + 0.5) * 0.004
    lat = 45.0 - (np.arange(n) + 0.5) * 0.004
    glon, glat = np.meshgrid(lon, lat)
    z = (-3000 + 800 * np.sin(glon * 9.0) * np.cos(glat * 7.0)).astype(np.float32)
    reads: Counter = Counter()

    def read(block, block_info=None):
        reads[block_info[0]["chunk-location"]] += 1
        return block

    source = da.from_array(z, chunks=128).map_blocks(read, dtype=z.dtype)
    src = xr.DataArray(source, coords={"y": lat, "x": lon}, dims=("y", "x"))
    aeqd = CRS.from_proj4("+proj=aeqd +lat_0=43 +lon_0=-58 +datum=WGS84 +units=m")
    wgs84 = CRS.from_epsg(4326)
    transform, w, h = calculate_default_transform(
        wgs84, aeqd, n, n, left=-60.0, bottom=lat[-1] - 0.002, right=lon[-1] + 0.002, top=45.0,
        resolution=400.0,
    )  # fmt: skip
    out = exact_warp(src, wgs84, aeqd, transform, (h, w), (128, 128))
    rows = out.data.numblocks[0]
    assert rows >= 4
    with dask.config.set(scheduler="threads"):
        whole = out.values
        reads.clear()
        target = zarr.create_array(store={}, shape=out.shape, chunks=(128, 128), dtype="f4")
        done = []
        store_in_bands(out.data, target, band_bytes=1, progress=lambda d, k: done.append(k))
    assert done[-1] == rows
    assert np.isfinite(whole).mean() > 0.5
    assert np.array_equal(target[:], whole, equal_nan=True)
    assert len(reads) == (n // 128) ** 2 and set(reads.values()) == {1}, reads
    target = zarr.create_array(
        store=str(tmp_path / "cluster.zarr"), shape=out.shape, chunks=(128, 128), dtype="f4"
    )
    with dask.config.set(scheduler=local_client):
        store_in_bands(out.data, target, band_bytes=1)
    assert np.array_equal(target[:], whole, equal_nan=True)


# ------------------------------------------------------------------ survey uncertainty (BAG)


def _survey(shape=(50, 61), seed=3):
    z = random_surface(shape, seed=seed)
    sigma = np.random.default_rng(seed).uniform(0.0, 20.0, shape).astype(np.float32)
    z[7, 9] = np.nan  # no elevation
    sigma[11, 13] = np.nan  # an elevation without an uncertainty
    return z, sigma


def test_a_bag_plans_on_elevation_plus_k_sigma(tmp_path, caplog):
    """The grid of a BAG read with uncertainty_k is elevation + k sigma of the two bands as
    rasterio reads them; chunked (a last chunk of one row) equals in memory; a cell without
    sigma is no-data; without uncertainty_k the elevation band alone, and the log says why."""
    import rasterio

    z, sigma = _survey()
    path = write_bag(tmp_path, z, sigma)
    with rasterio.open(path) as src:
        assert src.descriptions == ("elevation", "uncertainty")
        rz, rs = (src.read(i, masked=True).filled(np.nan) for i in (1, 2))
    np.testing.assert_array_equal(rz, z)  # the BAG holds what the test wrote
    expected = (rz + np.float32(2.5) * rs).astype(np.float32)
    assert np.isnan(expected[11, 13]) and np.isnan(expected[7, 9])
    for chunks in (None, 49, (17, 60)):
        dem = pipeline.open_dem(path, chunks=chunks, uncertainty_k=2.5)
        np.testing.assert_array_equal(dem.values, expected)
    assert dem.attrs["uncertainty_k"] == 2.5 and "uncertainty" in dem.attrs["surface"]
    assert dem.attrs["cell_size"] == 30.0
    assert CRS.from_wkt(dem.attrs["crs_wkt"]).to_epsg() == 32610  # the horizontal part
    with caplog.at_level("INFO", logger="pipeline"):
        plain = pipeline.open_dem(path, chunks=None)
    np.testing.assert_array_equal(plain.values, rz)
    assert "uncertainty band 'uncertainty', not used" in caplog.text


def test_netcdf_depths_with_a_named_uncertainty_variable(tmp_path):
    """A positive-down NetCDF with its sigma in a variable of its own name: the surface is
    -depth + k sigma; the variable is found by the usual names or by `uncertainty`."""
    z, sigma = _survey((30, 40), seed=4)
    c = metric_dataarray(z, a=25.0).coords
    ds = xr.Dataset({"depth": (("y", "x"), -z), "tvu_95": (("y", "x"), sigma)}, coords=c)
    ds["depth"].attrs["positive"] = "down"
    path = tmp_path / "survey.nc"
    ds.to_netcdf(path)
    with pytest.raises(InvalidDEMError, match="no uncertainty band or variable"):
        pipeline.open_dem(path, variable="depth", uncertainty_k=1.0)
    dem = pipeline.open_dem(
        path, chunks=7, variable="depth", uncertainty_k=1.5, uncertainty="tvu_95"
    )
    np.testing.assert_array_equal(dem.values, (z + np.float32(1.5) * sigma).astype(np.float32))
    ds.rename({"tvu_95": "TVU"}).to_netcdf(tmp_path / "named.nc")
    dem = pipeline.open_dem(tmp_path / "named.nc", chunks=None, uncertainty_k=1.0)  # found
    np.testing.assert_array_equal(dem.values, (z + sigma).astype(np.float32))


def test_uncertainty_errors_are_one_clear_line(tmp_path):
    z, sigma = _survey((20, 20))
    bag = write_bag(tmp_path, z, np.where(np.arange(20) == 5, -1.0, sigma).astype(np.float32))
    tif = _write_tif(metric_dataarray(z), tmp_path / "plain.tif")
    store = pipeline.write_dem(pipeline.open_dem(tif), tmp_path / "dem.zarr")
    cases = [
        (lambda: pipeline.open_dem(bag, uncertainty_k=1.0), "holds negative values"),
        (lambda: pipeline.open_dem(tif, uncertainty_k=1.0), "no uncertainty band or variable"),
        (lambda: pipeline.open_dem(tif, uncertainty="tvu"), "has one band"),
        (lambda: pipeline.open_dem(bag, uncertainty="tvu"), "has no band 'tvu'"),
        (lambda: pipeline.open_dem(bag, uncertainty_k=-1.0), "uncertainty_k` must be"),
        (lambda: pipeline.open_dem(store, uncertainty_k=1.0), "already a pipeline DEM store"),
    ]
    for call, match in cases:
        with pytest.raises(pipeline.PipelineError, match=match) as info:
            call()
        assert "\n" not in str(info.value)


def test_a_mission_on_a_bag_keeps_clearance_plus_k_sigma_from_the_survey(tmp_path):
    """Maps built on the shoal surface: every cell of a planned path lies at least
    clearance + k sigma above the surveyed seabed below it, and at least the clearance away
    (in 3-D) from the shoal surface at every cell within reach: checked by brute force on the
    bands as rasterio reads them."""
    import rasterio

    k, R = 2.0, 60.0
    z = random_surface((60, 60), seed=5)
    sigma = np.random.default_rng(5).uniform(0.0, 25.0, z.shape).astype(np.float32)
    path = write_bag(tmp_path, z, sigma)
    with rasterio.open(path) as src:
        rz, rs = (src.read(i).astype(np.float64) for i in (1, 2))
    dem = pipeline.open_dem(path, uncertainty_k=k)
    store = tmp_path / "maps.zarr"
    pipeline.build_maps(dem, store, clearance=R, landmarks=0)
    t = pipeline.plan(store, (3, 3), (56, 55), planner="astar", mcpc=False, client="synchronous")
    assert t.status == "ok" and len(t.cells) > 50
    a, h = 30.0, t.points[:, 2]
    shoal = rz + k * rs
    reach = int(R // a)
    for (r, c), hp in zip(t.cells, h, strict=True):
        assert hp >= rz[r, c] + R + k * rs[r, c] - 1e-3
        for dr in range(-reach, reach + 1):
            for dc in range(-reach, reach + 1):
                d = a * np.hypot(dr, dc)
                if d <= R and 0 <= r + dr < 60 and 0 <= c + dc < 60:
                    assert hp >= shoal[r + dr, c + dc] + np.sqrt(R * R - d * d) - 1e-3


# ------------------------------------------------------------------ ESRI ASCII grids

UTM31 = (
    'PROJCS["WGS_1984_UTM_Zone_31N",GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984",SPHEROID['
    '"WGS_1984",6378137.0,298.257223563]],PRIMEM["Greenwich",0.0],UNIT["Degree",'
    '0.0174532925199433]],PROJECTION["Transverse_Mercator"],PARAMETER["False_Easting",500000.0],'
    'PARAMETER["False_Northing",0.0],PARAMETER["Central_Meridian",3.0],PARAMETER["Scale_Factor",'
    '0.9996],PARAMETER["Latitude_Of_Origin",0.0],UNIT["Meter",1.0]]'
)
WGS84 = (
    'GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984",SPHEROID["WGS_1984",6378137.0,298.257223563]],'
    'PRIMEM["Greenwich",0.0],UNIT["Degree",0.0174532925199433]]'
)


def _write_asc(path, z, x0, y0, cell, prj=None):
    """An ESRI ASCII grid written by hand (first row the northernmost), NODATA -9999."""
    rows, cols = z.shape
    lines = [
        f"ncols {cols}",
        f"nrows {rows}",
        f"xllcorner {x0!r}",
        f"yllcorner {y0!r}",
        f"cellsize {cell!r}",
        "NODATA_value -9999",
    ]
    lines += [" ".join(f"{v:.2f}" for v in row) for row in np.where(np.isnan(z), -9999.0, z)]
    path.write_text("\n".join(lines) + "\n")
    if prj is not None:
        path.with_suffix(".prj").write_text(prj)
    return path


def test_an_esri_ascii_grid_is_read_with_the_crs_of_its_prj(tmp_path):
    """Values, no-data, cell centres (the header's lower-left corner, the first row the
    northernmost) and CRS against the text written, in memory and in awkward chunks (7 x 9
    cells in chunks of 4: last chunks of 3 and 1)."""
    rng = np.random.default_rng(5)
    z = np.round(-2000.0 + 50.0 * rng.normal(size=(7, 9)), 2)
    z[2, 3] = np.nan
    path = _write_asc(tmp_path / "survey.asc", z, 500000.0, 4000000.0, 30.0, prj=UTM31)
    want = z.astype(np.float32)
    for chunks in (None, 4):
        dem = pipeline.open_dem(path, chunks=chunks)
        np.testing.assert_array_equal(dem.values, want)
        np.testing.assert_allclose(dem.x.values, 500000.0 + (np.arange(9) + 0.5) * 30.0)
        np.testing.assert_allclose(dem.y.values, 4000000.0 + (7 - np.arange(7) - 0.5) * 30.0)
        assert dem.attrs["cell_size"] == 30.0
        assert CRS.from_wkt(dem.attrs["crs_wkt"]).to_epsg() == 32631
    store = pipeline.import_dem(path, tmp_path / "dem.zarr", chunks=4)
    np.testing.assert_array_equal(pipeline.open_dem(store, chunks=None).values, want)


def test_a_lon_lat_grid_without_a_crs_is_read_as_lon_lat(tmp_path, caplog):
    """An ESRI ASCII grid in degrees without its .prj (as EMODnet's come): its cells of
    0.001 "units" were taken for metres. It is read as lon/lat, with a warning, exactly as the
    same grid with a WGS84 .prj is."""
    import logging

    rng = np.random.default_rng(6)
    z = np.round(-1500.0 + 20.0 * rng.normal(size=(12, 10)), 2)
    cell = 1.0 / 960.0  # EMODnet's 1/16 arc minute
    bare = _write_asc(tmp_path / "bare.asc", z, -10.5, 45.2, cell)
    told = _write_asc(tmp_path / "told.asc", z, -10.5, 45.2, cell, prj=WGS84)
    with caplog.at_level(logging.WARNING, logger="pipeline.dem"):
        got = pipeline.open_dem(bare, chunks=None)
    assert "no coordinate reference system" in caplog.text and "read as lon/lat" in caplog.text
    ref = pipeline.open_dem(told, chunks=None)
    assert 60.0 < got.attrs["cell_size"] < 120.0  # metres, not 0.001
    assert got.attrs["cell_size"] == ref.attrs["cell_size"]
    np.testing.assert_array_equal(got.values, ref.values)
    np.testing.assert_array_equal(got.x.values, ref.x.values)
    assert CRS.from_wkt(got.attrs["crs_wkt"]) == CRS.from_wkt(ref.attrs["crs_wkt"])


def test_import_dem_takes_open_dems_keywords_and_names_an_unknown_one(tmp_path):
    """import_dem forwards open_dem's keywords (a bbox_xy region, chunks) and refuses one it
    does not know with the list it takes, before reading anything."""
    import rioxarray  # noqa: F401

    arr = metric_dataarray(random_surface((60, 50)), a=40.0).rio.write_crs("EPSG:32610")
    arr.rio.to_raster(tmp_path / "in.tif")
    x, y = arr.x.values, arr.y.values
    box = (x[10], y[40], x[29], y[20])  # x_min, y_min, x_max, y_max: centres of cells
    store = pipeline.import_dem(tmp_path / "in.tif", tmp_path / "dem.zarr", chunks=8, bbox_xy=box)
    dem = pipeline.open_dem(store, chunks=8)
    want = arr.sel(x=slice(x[9], x[30]), y=slice(y[19], y[41]))  # and one cell more each side
    np.testing.assert_array_equal(dem.x.values, want.x.values)
    np.testing.assert_array_equal(dem.values, want.values.astype(dem.dtype))
    assert dem.data.chunksize == (8, 8)
    with pytest.raises(pipeline.PipelineError, match=r"no option 'chunk'; .* chunks, variable"):
        pipeline.import_dem(tmp_path / "in.tif", tmp_path / "other.zarr", chunk=8)
    assert not (tmp_path / "other.zarr").exists()


def test_the_highest_of_a_bilinear_surface_over_a_box():
    """The upper envelope's kernels (reproject.box_max, and small_box_max for boxes over at
    most 2 x 3 source cells) on random boxes of a random grid (thin, on grid lines, within
    one cell, whole; small ones with sides on grid lines too): the highest of scipy's
    bilinear surface over the box's candidate points (its corners, its sides' crossings with
    the grid lines, the grid points inside), and never below a dense sampling of the box."""
    from pipeline.dem.reproject import box_max, small_box_max

    rng = np.random.default_rng(4)
    z = rng.normal(0.0, 10.0, (9, 11)).astype(np.float32)
    f = RegularGridInterpolator((np.arange(9.0), np.arange(11.0)), z.astype(np.float64))
    boxes = [rng.uniform(0, 8, 2).tolist() + rng.uniform(0, 10, 2).tolist() for _ in range(400)]
    boxes += [
        [3.0, 3.0, 2.5, 7.0],
        [2.2, 2.7, 4.0, 4.0],
        [0.0, 8.0, 0.0, 10.0],
        [5.5, 5.5, 6.5, 6.5],
    ]
    boxes += [[1.0, 4.0, 2.0, 6.0], [6.3, 6.6, 7.2, 7.9]]
    small = []
    for _ in range(400):  # about a source cell each way, sides on grid lines at times
        i, j = rng.uniform(0, 5.8), rng.uniform(0, 6.8)
        di, dj = rng.uniform(0, 2.2), rng.uniform(0, 3.2)
        b = [i, i + di, j, j + dj]
        small.append([float(round(v)) if rng.random() < 0.25 else v for v in b])
    for b in boxes + small:
        lo_i, hi_i = sorted(b[:2])
        lo_j, hi_j = sorted(b[2:])
        got = box_max(z, 0, 0, lo_i, hi_i, lo_j, hi_j)
        assert small_box_max(z, 0, 0, lo_i, hi_i, lo_j, hi_j) == pytest.approx(got, abs=1e-9)
        us = np.unique([lo_i, hi_i, *range(int(np.ceil(lo_i)), int(np.floor(hi_i)) + 1)])
        vs = np.unique([lo_j, hi_j, *range(int(np.ceil(lo_j)), int(np.floor(hi_j)) + 1)])
        uu, vv = np.meshgrid(us, vs, indexing="ij")
        want = f(np.column_stack([uu.ravel(), vv.ravel()])).max()
        assert got == pytest.approx(want, abs=1e-9), (b, got, want)
        du, dv = np.meshgrid(np.linspace(lo_i, hi_i, 41), np.linspace(lo_j, hi_j, 41))
        assert got >= f(np.column_stack([du.ravel(), dv.ravel()])).max() - 1e-9


def test_a_zarr_or_netcdf_with_its_crs_in_a_variable_of_its_own(tmp_path):
    """A store written as rioxarray and xarray leave it (``write_crs``, then ``to_zarr`` or
    ``to_netcdf`` of the Dataset) keeps the CRS in a ``spatial_ref`` variable that the elevation
    may no longer name: the DEM takes that CRS (pyproj's equality), as a GeoTIFF's is taken."""
    import rioxarray  # noqa: F401

    z = np.full((20, 30), -3000.0, np.float32)
    x = 500_000.0 + (np.arange(30) + 0.5) * 50.0
    y = 4_000_000.0 - (np.arange(20) + 0.5) * 50.0
    arr = xr.DataArray(z, dims=("y", "x"), coords={"x": x, "y": y}, name="elevation")
    ds = arr.rio.write_crs("EPSG:32610").to_dataset()
    ds["elevation"].attrs.pop("grid_mapping", None)
    ds["elevation"].encoding.pop("grid_mapping", None)
    ds = ds.reset_coords("spatial_ref")  # a variable of its own, no longer linked
    ds.to_zarr(tmp_path / "d.zarr", consolidated=False)
    ds.to_netcdf(tmp_path / "d.nc")
    for path in (tmp_path / "d.zarr", tmp_path / "d.nc"):
        dem = pipeline.open_dem(path, chunks=None)
        assert CRS.from_wkt(dem.attrs["crs_wkt"]) == CRS.from_epsg(32610), path
