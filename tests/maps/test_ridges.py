"""Ridge maps: depression fill, D8 on the inverted DEM, accumulation, threshold.

References: the single-array implementation for chunked parity (bit for bit), pysheds (its own
priority-flood, D8 and accumulation code) for the filled DEM and the ridge cells, brute-force
D8 and path-following accumulation written here, and hypothesis invariants.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import xarray as xr
from conftest import CHUNKINGS, metric_dataarray, pysheds_ridges, random_surface
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import pipeline
from pipeline.exceptions import InvalidDEMError, InvalidParameterError
from pipeline.maps.ridges import (
    DC,
    DR,
    accumulation_single,
    default_min_accumulation,
    fill_single,
    flow_directions,
)


def _dem(z, a=30.0, chunks=None):
    d = metric_dataarray(np.asarray(z, np.float32), a=a)
    d.attrs["cell_size"] = a
    return d if chunks is None else d.chunk(dict(zip(("y", "x"), chunks, strict=True)))


def _cases(topobathy_dem):
    return {
        "random": random_surface((90, 70), seed=11),
        "flats+holes": random_surface((90, 70), seed=12, flats=True, holes=True),
        "synthetic": pipeline.synthetic_dem((120, 100), seed=4, chunks=None).values,
        "real": topobathy_dem.values,
    }


@pytest.fixture(scope="module")
def real(topobathy_tif):
    return pipeline.open_dem(topobathy_tif, chunks=None)


@pytest.mark.parametrize("case", ["random", "flats+holes", "synthetic", "real"])
@pytest.mark.parametrize("chunks", CHUNKINGS)
def test_chunked_equals_single_array(real, case, chunks):
    z = _cases(real)[case]
    F = fill_single(z)
    A = accumulation_single(F)
    d = _dem(z, chunks=chunks)
    filled = pipeline.fill_depressions(d)
    acc = pipeline.flow_accumulation(d)  # fills again, lazily, inside its own graph
    if chunks is not None:
        assert filled.chunks is not None and acc.chunks is not None  # lazy
    np.testing.assert_array_equal(filled.values, F)
    acc = acc.compute()
    np.testing.assert_array_equal(acc.values, A)
    rdg = pipeline.ridge_map(d, min_accumulation=8, accumulation=acc)
    np.testing.assert_array_equal(rdg.values, A >= 8)


def test_large_flat_and_big_hole_chunked():
    z = np.full((80, 90), -3000.0, np.float32)
    z[10:70, 10:80] = -3500.0  # one big depression, flat after filling
    z[30:50, 30:60] = np.nan  # a hole in it: its rim drains into the hole
    z[5, 5] = -2000.0
    F, A = fill_single(z), accumulation_single(fill_single(z))
    for ch in [(7, 5), (13, 64), (80, 90)]:
        d = _dem(z, chunks=ch)
        np.testing.assert_array_equal(pipeline.fill_depressions(d).values, F)
        np.testing.assert_array_equal(pipeline.flow_accumulation(d).values, A)


# ----------------------------------------------------------------------------- pysheds


def test_pysheds_generator_is_compiled_in_each_process_not_cached():
    """The reference's numba generator (pysheds' ``count``) is compiled afresh in each process:
    numba cannot compile a function using a generator it loaded from its disk cache, so a cached
    ``count`` beside an uncached priority flood (a warm-up ended between their saves) failed
    every later process's comparison with pysheds, ``KeyError: int64 generator(func=count``."""
    from numba.core.caching import NullCache

    pysheds_ridges(np.zeros((3, 3), np.float32))  # imports pysheds as the comparisons do
    from pysheds import _sgrid

    assert isinstance(_sgrid.count._cache, NullCache)
    assert not isinstance(_sgrid._priority_flood._cache, NullCache)  # the rest is cached


@pytest.mark.parametrize("seed", [0, 1])
def test_against_pysheds(seed, pysheds_ready):
    """Filled DEM: exactly pysheds' fill_depressions. Ridge cells at the default threshold:
    intersection over union >= 0.98. The two D8 codes differ only where the rules differ:
    pysheds gives flats no direction and breaks slope ties in its own neighbour order, so a
    few cells on ties route the other way; anything larger would be a real disagreement."""
    z = pipeline.synthetic_dem((600, 600), cell_size=30.0, seed=seed, chunks=None).values
    pf, pa = pysheds_ridges(z)
    F = fill_single(z)
    np.testing.assert_array_equal(F.astype(np.float64), pf)
    A = accumulation_single(F)
    thr = default_min_accumulation(30.0)
    ours, theirs = A >= thr, pa >= thr
    assert ours.sum() > 50
    iou = (ours & theirs).sum() / (ours | theirs).sum()
    assert iou >= 0.98, iou
    assert (A == pa).mean() > 0.999


def test_real_bathymetry_against_pysheds(topobathy, pysheds_ready):
    z = topobathy[0]  # the source grid itself: real bathymetry and land, no no-data
    pf, pa = pysheds_ridges(z)
    F = fill_single(z)
    np.testing.assert_array_equal(F.astype(np.float64), pf)
    A = accumulation_single(F)
    ours, theirs = A >= 8, pa >= 8
    assert (ours & theirs).sum() / (ours | theirs).sum() >= 0.95


# ----------------------------------------------------------------------------- brute force


def brute_d8(F):
    """docs/method.md section 3, step 3, transcribed: steepest strictly positive drop of -F per
    distance, first in the order E, SE, S, SW, W, NW, N, NE on ties; -1 otherwise."""
    w = -F.astype(np.float64)
    rows, cols = w.shape
    out = np.full((rows, cols), -1)
    for i in range(rows):
        for j in range(cols):
            if np.isnan(w[i, j]):
                continue
            best, code = 0.0, -1
            for k, (di, dj) in enumerate(
                [(0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1), (-1, 0), (-1, 1)]
            ):
                ii, jj = i + di, j + dj
                if 0 <= ii < rows and 0 <= jj < cols and not np.isnan(w[ii, jj]):
                    drop = (w[i, j] - w[ii, jj]) / math.hypot(di, dj)
                    if drop > best:
                        best, code = drop, k
            out[i, j] = code
    return out


def brute_accumulation(dirs, valid):
    """Walk downstream from every cell, counting each cell on the way."""
    acc = np.zeros(dirs.shape, dtype=np.int64)
    for i, j in zip(*np.nonzero(valid), strict=True):
        steps = 0
        while True:
            acc[i, j] += 1
            k = dirs[i, j]
            if k < 0:
                break
            i, j = i + DR[k], j + DC[k]
            steps += 1
            assert steps <= dirs.size, "cycle in D8"
    return acc


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_d8_and_accumulation_brute_force(seed):
    z = random_surface((40, 35), seed=seed, flats=seed == 2, holes=seed == 3)
    F = fill_single(z)
    dirs = flow_directions(F)
    np.testing.assert_array_equal(dirs, brute_d8(F))
    np.testing.assert_array_equal(accumulation_single(F), brute_accumulation(dirs, np.isfinite(z)))


# ----------------------------------------------------------------------------- invariants


surfaces = arrays(
    np.float32,
    st.tuples(st.integers(2, 20), st.integers(2, 20)),
    elements=st.one_of(
        st.floats(-100, 100, width=32), st.sampled_from([np.float32(np.nan), np.float32(0.0)])
    ),
)


def _outlet_mask(z):
    valid = np.isfinite(z)
    pad = np.pad(~valid, 1, constant_values=True)
    near = np.zeros_like(valid)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            near |= pad[1 + di : 1 + di + z.shape[0], 1 + dj : 1 + dj + z.shape[1]]
    return valid & near  # the map edge counts as no-data outside


@settings(max_examples=80, deadline=None)
@given(z=surfaces)
def test_fill_and_flow_invariants(z):
    valid = np.isfinite(z)
    F = fill_single(z)
    assert np.array_equal(np.isnan(F), ~valid)
    assert np.all(F[valid] >= z[valid])
    # no interior depression: every valid cell reaches an outlet by a non-ascending path
    reach = _outlet_mask(z).copy()
    changed = True
    while changed:
        changed = False
        for i, j in zip(*np.nonzero(valid & ~reach), strict=True):
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    ii, jj = i + di, j + dj
                    if (
                        0 <= ii < z.shape[0]
                        and 0 <= jj < z.shape[1]
                        and reach[ii, jj]
                        and F[ii, jj] <= F[i, j]
                    ):
                        reach[i, j] = changed = True
    assert reach[valid].all()
    # filling is minimal: lowering any raised cell would leave it in a pit: it equals the
    # minimax height of its paths to an outlet, which never exceeds its own if it is an outlet
    assert np.all(F[_outlet_mask(z)] == z[_outlet_mask(z)])
    A = accumulation_single(F)
    dirs = flow_directions(F)
    assert np.all(A[valid] >= 1) and np.all(A[~valid] == 0)
    assert A[valid & (dirs == -1)].sum() == valid.sum()  # every cell ends in one sink
    np.testing.assert_array_equal(A, brute_accumulation(dirs, valid))  # asserts no cycle


@settings(max_examples=25, deadline=None)
@given(z=surfaces, cr=st.integers(2, 9), cc=st.integers(2, 9))
def test_any_chunking_property(z, cr, cc):
    F = fill_single(z)
    if not np.isfinite(z).any():
        return
    d = _dem(z, chunks=(cr, cc))
    np.testing.assert_array_equal(pipeline.fill_depressions(d).values, F)
    np.testing.assert_array_equal(pipeline.flow_accumulation(d).values, accumulation_single(F))


# ----------------------------------------------------------------------------- API and errors


def test_default_threshold():
    assert default_min_accumulation(30.0) == 1112  # 1 km^2 of 30 m cells
    assert default_min_accumulation(100.0) == 100
    assert default_min_accumulation(1000.0) == 8  # never fewer than 8 cells
    d = _dem(random_surface((30, 30)), a=100.0)
    assert pipeline.ridge_map(d).attrs["min_accumulation"] == 100


@pytest.mark.parametrize(
    "value, match", [(0, ">= 1, got 0"), (-3, ">= 1"), (2.5, "integer"), ("8", "integer")]
)
def test_bad_min_accumulation(value, match):
    with pytest.raises(InvalidParameterError, match=match):
        pipeline.ridge_map(_dem(random_surface((10, 10))), min_accumulation=value)


def test_all_nodata_dem():
    d = _dem(np.full((10, 10), np.nan, np.float32))
    with pytest.raises(InvalidDEMError, match="entirely no-data"):
        pipeline.flow_accumulation(d)
    with pytest.raises(InvalidDEMError, match="entirely no-data"):
        pipeline.ridge_map(d.chunk({"y": 5, "x": 5}))


def test_valid_cells_beyond_the_first_chunk_count():
    """The no-data check reads the first chunk, then the rest only when that one is all NaN."""
    from pipeline.dem.canonical import require_valid_cells

    z = np.full((10, 10), np.nan, np.float32)
    z[9, 9] = -100.0  # in the last chunk only
    require_valid_cells(_dem(z).chunk({"y": 5, "x": 5}), "entirely no-data")
    z[9, 9] = np.nan
    with pytest.raises(InvalidDEMError, match="entirely no-data"):
        require_valid_cells(_dem(z).chunk({"y": 5, "x": 5}), "entirely no-data")


def test_not_a_dataarray():
    with pytest.raises(InvalidParameterError, match="xarray.DataArray"):
        pipeline.flow_accumulation(np.zeros((4, 4)))
    with pytest.raises(InvalidDEMError, match="dims"):
        pipeline.fill_depressions(xr.DataArray(np.zeros((4, 4)), dims=("a", "b")))


@pytest.mark.parametrize("chunks", [(7, 5), (64, 64), (100, 37), (90, 70), (89, 23)])
def test_staged_ridge_layers_equal_single_array(tmp_path, chunks):
    """The staged passes (each tile flooded once, scratch tiles, elementwise finish with
    halos), composed as ridge_layers_staged does, equal the single array too."""
    import dask
    import dask.array as da

    from pipeline.maps.ridges import ridge_layers_staged

    z = random_surface((90, 70), seed=21, flats=True, holes=True)
    F = fill_single(z)
    A = accumulation_single(F)
    f, a, r = ridge_layers_staged(da.from_array(z, chunks=chunks), tmp_path / "s.zarr", 20)
    fv, av, rv = dask.compute(f, a, r)
    np.testing.assert_array_equal(fv, F)
    np.testing.assert_array_equal(av, A)
    np.testing.assert_array_equal(rv, A >= 20)


@pytest.mark.parametrize("chunks", [(7, 5), (89, 23), (90, 69), (64, 64)])
def test_build_maps_ridge_layers_equal_single_array(tmp_path, chunks):
    """The ridge layers build_maps writes (its own pass 3: a tile's accumulation beside its
    other layers) equal the single-array fill and accumulation (checked against pysheds
    above) for awkward tilings: tiles of 7 x 5, a last row of tiles one cell high, a last
    column one cell wide, no-data holes and flats."""
    z = random_surface((90, 70), seed=21, flats=True, holes=True) - 3000.0
    dem = metric_dataarray(z, a=30.0).chunk(dict(zip(("y", "x"), chunks, strict=True)))
    maps = pipeline.build_maps(
        dem, tmp_path / "m.zarr", clearance=30.0, min_accumulation=20, landmarks=0
    )
    A = accumulation_single(fill_single(z))
    np.testing.assert_array_equal(maps["accumulation"].values, A)
    np.testing.assert_array_equal(maps["ridge"].values, A >= 20)
