"""Safety maps and passability against independent references.

References: a brute-force loop over the disc (numpy, float64), and scipy.ndimage.grey_dilation
with the same non-flat structuring element; invariants as hypothesis properties.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import xarray as xr
from conftest import CHUNKINGS, metric_dataarray, random_surface
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from references import assert_correctly_rounded, brute_force, rounded_up, scipy_reference

import pipeline
from pipeline.exceptions import InvalidDEMError, InvalidParameterError


def _dem(z, a=30.0, chunks=None):
    d = metric_dataarray(np.asarray(z, np.float32), a=a)
    d.attrs["cell_size"] = a
    return d if chunks is None else d.chunk(dict(zip(("y", "x"), chunks, strict=True)))


@pytest.fixture(scope="module")
def real_dem(topobathy_tif):
    return pipeline.open_dem(topobathy_tif, chunks=None)


@pytest.mark.parametrize("method", ["vertical", "horizontal", "spherical"])
@pytest.mark.parametrize("R, a", [(300.0, 30.0), (200.0, 100.0), (95.0, 20.0), (40.0, 50.0)])
def test_matches_brute_force_random(method, R, a):
    z = random_surface((37, 29), seed=int(R))
    got = pipeline.safety_map(_dem(z, a), method, R).values
    assert_correctly_rounded(got, brute_force(z, a, method, R))


@pytest.mark.parametrize("method", ["vertical", "horizontal", "spherical"])
def test_never_below_the_exact_lowest_safe_height(method):
    """Stored in float32, the lowest safe height is never below the float64 one (the
    brute-force maximum): rounded to nearest, a fifth of the cells of this map or more would
    lie below it; each is the least float32 at or above it."""
    z = random_surface((60, 60), seed=3)
    ref = brute_force(z, 30.0, method, 95.2)
    got = pipeline.safety_map(_dem(z, 30.0), method, 95.2).values
    assert np.all(got.astype(np.float64) >= ref)
    assert np.all(np.nextafter(got, np.float32(-np.inf)).astype(np.float64) < ref)
    assert (ref.astype(np.float32).astype(np.float64) < ref).mean() > 0.2  # the case exists


def test_horizontal_clearance_differs_from_vertical_part():
    z = random_surface((30, 30), seed=2)
    got = pipeline.safety_map(_dem(z, 30.0), "horizontal", 200.0, horizontal_clearance=95.0)
    assert_correctly_rounded(got.values, brute_force(z, 30.0, "horizontal", 200.0, 95.0))
    assert got.attrs["horizontal_clearance_m"] == 95.0


@pytest.mark.parametrize("method", ["horizontal", "spherical"])
def test_matches_brute_force_on_real_bathymetry(real_dem, method):
    """matplotlib's topobathy (reprojected, 2.4 km cells), R = 5 km: a radius of 2 cells."""
    z = real_dem.values
    a = pipeline.cell_size(real_dem)
    got = pipeline.safety_map(real_dem, method, 5000.0).values
    assert_correctly_rounded(got, brute_force(z, a, method, 5000.0))


def test_nodata_in_the_element_makes_safety_nan():
    z = random_surface((25, 25), seed=5)
    z[12, 12] = np.nan
    S = pipeline.safety_map(_dem(z, 30.0), "spherical", 90.0).values
    ref = brute_force(z, 30.0, "spherical", 90.0)
    assert_correctly_rounded(S, ref)  # NaN exactly where the disc holds no-data
    assert np.isnan(S[12, 9]) and np.isnan(S[9, 12]) and not np.isnan(S[12, 8])


@pytest.mark.parametrize("method", ["horizontal", "spherical"])
def test_signed_zeros_and_nodata_bit_for_bit(method):
    """The kernel's maximum may return either operand for a NaN or for -0.0 against +0.0
    (pipeline/maps/safety.py ``_maximum``): the map still equals the brute force bit for bit, the
    sign of every zero included, on a DEM of +-0.0 and small whole numbers with scattered
    no-data, at a radius whose disc has cells exactly R away (5 cells of 30 m: a cap height of
    +0.0 there)."""
    rng = np.random.default_rng(11)
    z = rng.integers(-2, 3, size=(41, 37)).astype(np.float32)
    z[z == 0] = np.where(rng.random(int((z == 0).sum())) < 0.5, -0.0, 0.0)
    z[rng.random(z.shape) < 0.01] = np.nan
    assert np.signbit(z[z == 0]).any() and np.isnan(z).any()
    got = pipeline.safety_map(_dem(z, 30.0), method, 150.0).values
    ref = rounded_up(brute_force(z, 30.0, method, 150.0))
    assert got.tobytes() == ref.tobytes()  # NaN where the disc holds no-data, the same bits


@pytest.mark.parametrize("R, a", [(300.0, 30.0), (200.0, 100.0), (1000.0, 30.0)])
def test_equals_scipy_grey_dilation(R, a):
    """Identical to scipy's float64 grey dilation, rounded up once to float32."""
    z = pipeline.synthetic_dem((400, 300), cell_size=a, seed=1, chunks=None).values
    got = pipeline.safety_map(_dem(z, a), "spherical", R).values
    np.testing.assert_array_equal(got, rounded_up(scipy_reference(z, a, R)))


@pytest.mark.parametrize("method", ["vertical", "horizontal", "spherical"])
@pytest.mark.parametrize("chunks", [c for c in CHUNKINGS if c is not None] + [(3, 3), (11, 64)])
def test_chunking_independent(method, chunks):
    """Bit-identical for any chunking, including chunks smaller than the radius (10 cells)."""
    z = random_surface((150, 120), seed=7, holes=True)
    ref = pipeline.safety_map(_dem(z, 30.0), method, 300.0).values
    lazy = pipeline.safety_map(_dem(z, 30.0, chunks), method, 300.0)
    assert lazy.chunks is not None  # dask-backed, lazy
    np.testing.assert_array_equal(lazy.values, ref)


def test_keeps_coords_and_records_parameters():
    d = _dem(random_surface((20, 30)), 30.0, (8, 8))
    d.attrs["crs_wkt"] = 'LOCAL_CS["x"]'
    S = pipeline.safety_map(d, "spherical", 120.0)
    assert S.name == "safety" and S.dims == ("y", "x") and S.dtype == np.float32
    xr.testing.assert_equal(S.x, d.x)
    assert S.attrs["method"] == "spherical" and S.attrs["clearance_m"] == 120.0
    assert S.attrs["crs_wkt"] == d.attrs["crs_wkt"] and S.attrs["element_radius_cells"] == 4


# ----------------------------------------------------------------------------- invariants

surfaces = arrays(
    np.float32,
    st.tuples(st.integers(3, 24), st.integers(3, 24)),
    elements=st.floats(-6000, -100, width=32),
)


@settings(max_examples=60, deadline=None)
@given(z=surfaces, R=st.floats(20.0, 400.0), a=st.sampled_from([10.0, 30.0, 100.0]))
def test_spherical_invariants(z, R, a):
    if R < a / 2:
        return
    S = pipeline.safety_map(_dem(z, a), "spherical", R).values.astype(np.float64)
    zz = z.astype(np.float64)
    assert np.all(S >= zz + R - 1e-3)
    rows, cols = z.shape
    r = int(R // a)
    for i in range(rows):
        for j in range(cols):
            dmin = np.inf
            for di in range(-r, r + 1):
                for dj in range(-r, r + 1):
                    ii, jj = i + di, j + dj
                    if 0 <= ii < rows and 0 <= jj < cols:
                        h2 = a * a * (di * di + dj * dj)
                        if h2 <= R * R:
                            d = math.sqrt(h2 + (S[i, j] - zz[ii, jj]) ** 2)
                            assert d >= R - 1e-3
                            dmin = min(dmin, d)
            # the sphere rests on the terrain: some grid point touches it
            assert dmin <= R + 1e-3


@settings(max_examples=60, deadline=None)
@given(z=surfaces, R=st.floats(20.0, 400.0), a=st.sampled_from([10.0, 30.0, 100.0]))
def test_vertical_le_spherical_le_horizontal(z, R, a):
    if R < a / 2:
        return
    d = _dem(z, a)
    V = pipeline.safety_map(d, "vertical", R).values
    S = pipeline.safety_map(d, "spherical", R).values
    H = pipeline.safety_map(d, "horizontal", R).values
    assert np.all(V <= S) and np.all(S <= H)


# ----------------------------------------------------------------------------- passable


def test_passable_rules():
    z = np.full((12, 12), -2000.0, np.float32)
    z[2, 2] = 10.0  # land
    z[8, 8] = np.nan  # no-data
    z[5, 10] = -100.0  # too shallow: S = -40 m, the vehicle would surface
    d = _dem(z, 30.0)
    S = pipeline.safety_map(d, "spherical", 60.0)
    ok = pipeline.passable(d, S).values
    expected = np.isfinite(S.values) & (z < 0) & (S.values <= -60.0)
    np.testing.assert_array_equal(ok, expected)
    assert not ok[2, 2] and not ok[8, 8] and not ok[8, 10] and not ok[5, 10]
    assert ok[0, 11] and ok[11, 0]
    # land cells are impassable whatever the clearance; surface_clearance is settable
    ok0 = pipeline.passable(d, S, surface_clearance=0.0).values
    assert ok0[5, 10] and not ok0[2, 2]
    shallow_sea = pipeline.passable(d, S, sea_level=-1950.0).values  # S = -1940 m
    assert not shallow_sea.any()


def test_passable_lazy_equals_eager():
    z = random_surface((60, 50), seed=3, holes=True) + 2600.0  # some land
    eager = pipeline.passable(_dem(z), pipeline.safety_map(_dem(z), "spherical", 90.0))
    lazy_dem = _dem(z, chunks=(7, 5))
    lazy = pipeline.passable(lazy_dem, pipeline.safety_map(lazy_dem, "spherical", 90.0))
    assert lazy.chunks is not None
    np.testing.assert_array_equal(lazy.values, eager.values)
    assert eager.values.any() and not eager.values.all()


# ----------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"clearance": 0.0}, "`clearance` must be a finite number of metres > 0, got 0.0"),
        ({"clearance": -5.0}, "`clearance` must be a finite number"),
        ({"clearance": float("nan")}, "`clearance` must be a finite number"),
        ({"clearance": "300"}, "`clearance` must be a finite number of metres > 0, got '300'"),
        ({"clearance": 10.0}, "smaller than half a cell .15 m.*cannot resolve"),
        (
            {"method": "round"},
            "`method` must be 'vertical', 'horizontal' or 'spherical', got 'round'",
        ),
        ({"horizontal_clearance": 0.0}, "`horizontal_clearance` must be a finite"),
    ],
)
def test_bad_parameters(kwargs, match):
    with pytest.raises(InvalidParameterError, match=match):
        pipeline.safety_map(_dem(np.zeros((5, 5)) - 100), **kwargs)


@pytest.mark.parametrize(
    "dem, error, match",
    [
        (np.zeros((5, 5)), InvalidParameterError, "must be an xarray.DataArray, got ndarray"),
        (xr.DataArray(np.zeros((2, 5, 5)), dims=("t", "y", "x")), InvalidDEMError, "2-D"),
        (xr.DataArray(np.zeros((5, 5)), dims=("a", "b")), InvalidDEMError, r"dims \('y', 'x'\)"),
        (_dem(np.zeros((5, 5))).astype(np.int32), InvalidDEMError, "floating-point"),
    ],
)
def test_bad_dem(dem, error, match):
    with pytest.raises(error, match=match):
        pipeline.safety_map(dem)


def test_passable_checks_shapes():
    d = _dem(np.zeros((5, 5)) - 500)
    with pytest.raises(InvalidParameterError, match=r"DEM's shape \(5, 5\)"):
        pipeline.passable(d, pipeline.safety_map(_dem(np.zeros((4, 5)) - 500), clearance=20.0))
    with pytest.raises(InvalidParameterError, match="sea_level"):
        pipeline.passable(d, pipeline.safety_map(d, clearance=20.0), sea_level=float("inf"))


def test_each_safety_method_is_known_once():
    """The safety methods' names, kernel numbers and sideways reach come from one registry
    (pipeline.methods): the parameter schema offers exactly its names, each has its own
    kernel number, and the reach is R (3-D), the horizontal radius (disc) or nothing (a line
    straight down), as the stored parameters give it."""
    from pipeline.methods import METHODS
    from pipeline.params import MAPS
    from pipeline.store.schema import MapsParameters

    assert set(MAPS.method.choices) == set(METHODS) == {"vertical", "horizontal", "spherical"}
    assert len({m.code for m in METHODS.values()}) == len(METHODS)
    reach = {
        name: MapsParameters(name, 300.0, horizontal_clearance_m=120.0).reach_m for name in METHODS
    }
    assert reach == {"spherical": 300.0, "horizontal": 120.0, "vertical": 0.0}
