"""The maps store: written once, atomically, read lazily; values against scipy."""

from __future__ import annotations

import numpy as np
import pytest
import zarr
from click.testing import CliRunner
from references import rounded_up, scipy_reference

import pipeline
from pipeline.cli import main
from pipeline.exceptions import StoreExistsError
from pipeline.params import MAPS


def test_build_maps_store(tmp_path):
    dem = pipeline.synthetic_dem((300, 250), cell_size=30.0, seed=2, chunks=64)
    maps = pipeline.build_maps(dem, tmp_path / "maps.zarr", clearance=300.0)
    assert set(maps.data_vars) == {
        "elevation",
        "safety",
        "passable",
        "accumulation",
        "ridge",
        "component",
        "landmark_distance",
    }
    assert maps["landmark_distance"].shape == (MAPS.landmarks.default, 300, 250)
    for k, v in maps.data_vars.items():  # chunked identically; landmark layers in small chunks
        assert v.data.chunksize == ((64, 64) if k != "landmark_distance" else (1, 64, 64))
    g = zarr.open_group(tmp_path / "maps.zarr", mode="r")
    assert g.metadata.zarr_format == 3 and g["safety"].chunks == (64, 64)
    z = dem.values
    ref = rounded_up(scipy_reference(z, 30.0, 300.0))
    np.testing.assert_array_equal(maps["safety"].values, ref)
    np.testing.assert_array_equal(maps["elevation"].values, z)
    np.testing.assert_array_equal(maps["passable"].values, (z < 0) & (ref <= -300.0))
    # ridge layers equal the single-array computation (checked against pysheds in
    # test_ridges.py), threshold 1112 cells = 1 km^2 of 30 m cells
    from pipeline.maps.ridges import accumulation_single, fill_single

    acc = accumulation_single(fill_single(z))
    np.testing.assert_array_equal(maps["accumulation"].values, acc)
    np.testing.assert_array_equal(maps["ridge"].values, acc >= 1112)
    assert maps["ridge"].values.any()
    p = maps.attrs["parameters"]
    assert p["method"] == "spherical" and p["clearance_m"] == 300.0 and p["chunks"] == [64, 64]
    assert p["min_accumulation"] == 1112
    assert maps.attrs["dem_hash"] == pipeline.dem_hash(dem.compute())
    assert maps.attrs["cell_size"] == 30.0


@pytest.mark.parametrize(
    "shape, chunks",
    [
        ((257, 257), 64),  # k * chunk + 1 on both sides: a last chunk of one cell
        ((129, 67), 64),  # one-cell last rows; 67 mod 64 = 3 columns, below the radius (10)
        ((130, 200), 64),  # 2 and 8 cells: both below the radius
        ((12, 9), 4),  # smaller than the structuring element (radius 10 > 9 columns)
        ((2, 2), 2),  # the smallest DEM
    ],
)
def test_every_layer_equals_the_in_memory_result_on_awkward_chunkings(tmp_path, shape, chunks):
    """Each layer of build_maps against the single-array references (scipy's grey dilation
    for the safety surface, the in-memory fill and accumulation checked against pysheds in
    test_ridges.py), built by dask's threads so that tiles are written in parallel, each
    tile's safety halo read across as many scratch tiles as it spans (a last chunk of one
    cell is merged into the tile before it, and its store block written from there)."""
    from pipeline.maps.components import label_components
    from pipeline.maps.ridges import accumulation_single, fill_single

    dem = pipeline.synthetic_dem(shape, cell_size=30.0, seed=3, chunks=chunks)
    maps = pipeline.build_maps(dem, tmp_path / "m.zarr", clearance=300.0, min_accumulation=8)
    z = dem.values
    assert maps.attrs["dem_hash"] == pipeline.dem_hash(dem.compute())
    ref = rounded_up(scipy_reference(z, 30.0, 300.0))
    acc = accumulation_single(fill_single(z))
    np.testing.assert_array_equal(maps["elevation"].values, z)
    np.testing.assert_array_equal(maps["safety"].values, ref)
    np.testing.assert_array_equal(maps["passable"].values, (z < 0) & (ref <= -300.0))
    np.testing.assert_array_equal(maps["accumulation"].values, acc)
    np.testing.assert_array_equal(maps["ridge"].values, acc >= 8)
    labels, _ = label_components(maps["passable"].values)  # checked against scipy's csgraph
    np.testing.assert_array_equal(maps["component"].values, labels)
    # landmark layers (in chunks of their own): the in-memory layers from the same cells
    from pipeline.maps import landmarks

    cells = pipeline.open_store(tmp_path / "m.zarr").landmarks
    ok = maps["passable"].values.astype(bool)
    assert cells == landmarks.place_landmarks(maps["safety"].values, ok, 30.0)
    for i, cell in enumerate(cells):
        np.testing.assert_array_equal(
            maps[landmarks.VARIABLE][i].values,
            landmarks.landmark_layer(maps["safety"].values, ok, 30.0, cell),
        )
    for k, v in maps.data_vars.items():
        if k != landmarks.VARIABLE:
            assert v.encoding["chunks"] == (min(chunks, shape[0]), min(chunks, shape[1]))


@pytest.mark.parametrize("method", ["horizontal", "vertical"])
def test_other_safety_methods_build_the_brute_force_layers_across_tiles(tmp_path, method):
    """The horizontal and vertical safety surfaces written by build_maps (each tile's halo read
    from its neighbours' scratch tiles, a last chunk of one row and of 3 columns, no-data
    cells next to tile borders) against the brute-force transcription of the method, and the
    passable layer against its definition."""
    from references import assert_correctly_rounded, brute_force

    dem = pipeline.synthetic_dem((49, 35), cell_size=30.0, seed=5, chunks=16)
    z = dem.values.copy()
    z[15:18, 30] = np.nan  # at a tile corner: its neighbours' halos see it
    z[0, 0] = np.nan
    dem = dem.copy(data=z).chunk(16)
    maps = pipeline.build_maps(
        dem,
        tmp_path / "m.zarr",
        method=method,
        clearance=200.0,
        horizontal_clearance=95.0 if method == "horizontal" else None,
        min_accumulation=8,
        landmarks=0,
    )
    ref = brute_force(z, 30.0, method, 200.0, 95.0)
    assert_correctly_rounded(maps["safety"].values, ref)
    np.testing.assert_array_equal(maps["elevation"].values, z)
    with np.errstate(invalid="ignore"):
        want = (z < 0) & np.isfinite(ref) & (rounded_up(ref) <= np.float32(-200.0))
    np.testing.assert_array_equal(maps["passable"].values, want)
    assert 0 < want.sum() < want.size


def test_dem_hash_is_chunking_independent_and_content_sensitive():
    dem = pipeline.synthetic_dem((200, 170), seed=0, chunks=None)
    h = pipeline.dem_hash(dem)
    for ch in [(7, 5), (64, 64), (200, 170)]:
        parts = pipeline.dem_hash(dem.chunk(dict(zip(("y", "x"), ch, strict=True))))
        total = int(parts.compute().sum(dtype=np.uint64))
        assert f"{total:016x}" == h
    other = dem.copy(data=dem.values.copy())
    other.values[100, 100] += np.float32(0.5)
    assert pipeline.dem_hash(other) != h
    swapped = dem.copy(data=dem.values[::-1].copy())  # same values, other places
    assert pipeline.dem_hash(swapped) != h


def test_refuses_to_clobber_and_rebuilds_on_request(tmp_path):
    dem = pipeline.synthetic_dem((64, 64), chunks=32)
    pipeline.build_maps(dem, tmp_path / "m.zarr", clearance=90.0)
    with pytest.raises(StoreExistsError, match="overwrite"):
        pipeline.build_maps(dem, tmp_path / "m.zarr", clearance=90.0)
    m = pipeline.build_maps(
        dem, tmp_path / "m.zarr", method="vertical", clearance=90.0, overwrite=True
    )
    assert m.attrs["parameters"]["method"] == "vertical"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.zarr"]


def test_bad_parameters_fail_before_any_write(tmp_path):
    dem = pipeline.synthetic_dem((64, 64), chunks=32)
    with pytest.raises(pipeline.InvalidParameterError, match="`method` must be"):
        pipeline.build_maps(dem, tmp_path / "m.zarr", method="cube")
    assert not any(tmp_path.iterdir())


def test_open_maps_missing(tmp_path):
    with pytest.raises(pipeline.PipelineError, match="does not exist"):
        pipeline.open_maps(tmp_path / "none.zarr")


def test_cli_build_maps(tmp_path, local_client):
    r = CliRunner()
    dem_store = tmp_path / "dem.zarr"
    pipeline.write_dem(pipeline.synthetic_dem((120, 100), chunks=64), dem_store, chunks=64)
    res = r.invoke(
        main,
        [
            "build-maps",
            str(dem_store),
            str(tmp_path / "maps.zarr"),
            "--method",
            "horizontal",
            "--clearance",
            "200",
            "--landmarks",
            "3",
            "--scheduler",
            local_client.scheduler.address,
        ],
    )
    assert res.exit_code == 0, res.output
    assert "passable" in res.output and "dask dashboard: http" in res.output
    maps = pipeline.open_maps(tmp_path / "maps.zarr")
    assert maps.attrs["parameters"]["method"] == "horizontal"
    assert maps.attrs["parameters"]["landmarks"] == 3 == maps["landmark_distance"].shape[0]
    res = r.invoke(
        main, ["build-maps", str(dem_store), str(tmp_path / "m2.zarr"), "--clearance", "5"]
    )
    assert res.exit_code == 2 and "smaller than half a cell" in res.output


def test_landmarks_too_large_for_the_machine_are_refused_before_any_compute(tmp_path):
    """A map whose landmark searches (7.2 bytes a cell, each holding the whole map) cannot fit
    in half of this machine's memory is refused in one line naming the fix, at once (the map
    here is a lazy array, never computed), and nothing is written."""
    import time

    import dask.array as da
    import psutil
    import xarray as xr

    cells = psutil.virtual_memory().total / 7  # one search would need all the memory
    side = int(np.ceil(np.sqrt(cells)))
    z = da.full((side, side), -3000.0, dtype=np.float32, chunks=4096)
    a = 30.0
    dem = xr.DataArray(
        z,
        dims=("y", "x"),
        coords={"y": (side - 0.5 - np.arange(side)) * a, "x": (np.arange(side) + 0.5) * a},
        name="elevation",
        attrs={"cell_size": a},
    )
    t0 = time.perf_counter()
    with pytest.raises(pipeline.InvalidParameterError, match="set landmarks = 0") as info:
        pipeline.build_maps(dem, tmp_path / "m.zarr", landmarks=2)
    assert time.perf_counter() - t0 < 30 and "\n" not in str(info.value)
    assert f"{side} x {side} map" in str(info.value)
    assert not (tmp_path / "m.zarr").exists()


def _build_in_a_task(path):
    """On a worker: build a small store under the synchronous scheduler (as the first run's
    kernel warm-up does), and say which scheduler dask would use afterwards in that block."""
    import dask
    from dask.base import get_scheduler
    from dask.local import get_sync

    with dask.config.set(scheduler="synchronous"):
        dem = pipeline.synthetic_dem((48, 40), cell_size=30.0, seed=1, chunks=16)
        pipeline.build_maps(dem, path, clearance=60.0, min_accumulation=4, landmarks=1)
        return get_scheduler() is get_sync


def test_a_build_inside_a_task_stays_on_the_scheduler_it_was_given(tmp_path, local_client):
    """build_maps in a dask task under ``scheduler="synchronous"`` computes in that task: it
    does not make the worker's client the process's default scheduler (which sent the warm-up's
    computations to a cluster whose two threads its own tasks held: a first `./dev demo` that
    waited minutes)."""
    assert local_client.submit(_build_in_a_task, str(tmp_path / "m.zarr"), pure=False).result(
        timeout=120
    )
    assert pipeline.open_maps(tmp_path / "m.zarr")["passable"].shape == (48, 40)


@pytest.mark.parametrize("where", ["local", "memory"])
def test_scratch_windows_across_tiles_equal_the_map_sliced(tmp_path, where):
    """A window of any size read from the build's scratch tiles (local files memory-mapped,
    or on an fsspec filesystem by row ranges, C- or Fortran-ordered tiles) equals the whole
    map sliced: windows inside one tile, across tiles one cell wide, and the whole map."""
    from pipeline.maps.scratch import load_window, save_tile

    rng = np.random.default_rng(7)
    z = rng.normal(size=(23, 17)).astype(np.float32)
    r_off, c_off = np.array([0, 8, 16, 22, 23]), np.array([0, 1, 9, 17])
    scratch = str(tmp_path / "s") if where == "local" else f"memory://scratch-{tmp_path.name}"
    for i in range(len(r_off) - 1):
        for j in range(len(c_off) - 1):
            tile = z[r_off[i] : r_off[i + 1], c_off[j] : c_off[j + 1]]
            save_tile(scratch, "dem", (i, j), np.asfortranarray(tile) if (i + j) % 2 else tile)
    windows = [(0, 23, 0, 17), (2, 5, 3, 7), (7, 17, 0, 2), (15, 23, 8, 10), (22, 23, 16, 17)]
    windows += [
        tuple(sorted(rng.integers(0, 24, 2))) + tuple(sorted(rng.integers(0, 18, 2)))
        for _ in range(40)
    ]
    for r0, r1, c0, c1 in windows:
        if r0 < r1 and c0 < c1:
            got = load_window(scratch, "dem", r_off, c_off, r0, r1, c0, c1, np.float32)
            np.testing.assert_array_equal(got, z[r0:r1, c0:c1])
