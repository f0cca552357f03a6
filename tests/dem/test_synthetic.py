"""The virtual mid-ocean-ridge generator: chunking independence and seabed-like statistics."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import CHUNKINGS
from hypothesis import given, settings
from hypothesis import strategies as st

import pipeline
from pipeline.exceptions import InvalidParameterError


@pytest.fixture(scope="module")
def reference_300():
    return pipeline.synthetic_dem((300, 260), cell_size=30.0, seed=3, chunks=None).values


@pytest.mark.parametrize("chunks", [c for c in CHUNKINGS if c is not None] + [(300, 260), 1])
def test_any_chunking_is_bit_identical(reference_300, chunks):
    if chunks == 1:  # one-cell chunks: a 40 x 30 corner is enough
        d = pipeline.synthetic_dem((300, 260), cell_size=30.0, seed=3, chunks=1)[:40, :30]
        np.testing.assert_array_equal(d.values, reference_300[:40, :30])
        return
    d = pipeline.synthetic_dem((300, 260), cell_size=30.0, seed=3, chunks=chunks)
    assert d.data.chunksize == tuple(min(c, s) for c, s in zip(chunks, (300, 260), strict=True))
    np.testing.assert_array_equal(d.values, reference_300)


@settings(max_examples=12, deadline=None)
@given(
    cr=st.integers(50, 1200),
    cc=st.integers(50, 1200),
    r0=st.integers(0, 5900),
    c0=st.integers(0, 4900),
)
def test_large_map_windows_identical_for_any_chunking(cr, cc, r0, c0):
    """On a 6000 x 5000 map (coarse-lattice path), any chunking gives the same window
    (only the chunks under the window are computed)."""
    ref = pipeline.synthetic_dem((6000, 5000), seed=5, chunks=(1000, 1000))
    other = pipeline.synthetic_dem((6000, 5000), seed=5, chunks=(cr, cc))
    win = (slice(r0, r0 + 100), slice(c0, c0 + 100))
    np.testing.assert_array_equal(other[win].values, ref[win].values)


def test_seed_determines_the_map():
    a = pipeline.synthetic_dem((120, 100), seed=1, chunks=None).values
    b = pipeline.synthetic_dem((120, 100), seed=1, chunks=50).values
    c = pipeline.synthetic_dem((120, 100), seed=2, chunks=None).values
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).mean() > 100.0


def test_canonical_form():
    d = pipeline.synthetic_dem((50, 70), cell_size=25.0, seed=0, chunks=32)
    assert d.name == "elevation" and d.dims == ("y", "x") and d.dtype == np.float32
    assert pipeline.cell_size(d) == 25.0
    np.testing.assert_allclose(np.diff(d.x.values), 25.0)
    np.testing.assert_allclose(np.diff(d.y.values), -25.0)  # north up, row 0 at the top


@pytest.fixture(scope="module")
def seabed():
    return pipeline.synthetic_dem((1000, 1000), cell_size=30.0, seed=0, chunks=None).values


def test_depths_look_like_a_mid_ocean_ridge(seabed):
    z = seabed
    assert np.isfinite(z).all()
    p1, p50, p99 = np.percentile(z, [1, 50, 99])
    assert -6500 <= p1 < -4500 and -5000 < p50 < -2500 and -2500 < p99 < 0
    # open seabed stays below about -450 m; only the islands rise above
    assert ((z > -450) & (z < 0)).mean() < 0.01


def test_islands_make_land_obstacles():
    with_islands = pipeline.synthetic_dem((400, 400), seed=0, islands=3, chunks=None).values
    without = pipeline.synthetic_dem((400, 400), seed=0, islands=0, chunks=None).values
    assert 0 < (with_islands >= 0).mean() < 0.05
    assert not (without >= 0).any()


def test_roughness_spans_many_octaves(seabed):
    """Multi-octave relief: the radially averaged power spectrum falls as a power law over
    more than a decade of wavelengths (a single smooth bump or white noise would not)."""
    z = seabed - seabed.mean()
    z = z * np.outer(np.hanning(z.shape[0]), np.hanning(z.shape[1]))
    p = np.abs(np.fft.fftshift(np.fft.fft2(z))) ** 2
    n = z.shape[0]
    yy, xx = np.indices(p.shape)
    r = np.hypot(yy - n // 2, xx - n // 2).astype(int)
    radial = np.bincount(r.ravel(), p.ravel()) / np.bincount(r.ravel())
    k = np.arange(4, n // 4)  # wavelengths 250 down to 4 cells
    slope, _ = np.polyfit(np.log(k), np.log(radial[k]), 1)
    assert -5.0 < slope < -1.5
    # relief at every scale: each octave band holds a non-negligible share of the power
    bands = [radial[2**i : 2 ** (i + 1)].sum() for i in range(2, 8)]
    assert min(bands) > 1e-6 * max(bands)


def test_ridges_and_valleys_alternate(seabed):
    """Relief has crests with valleys between: along any row, local maxima of the smoothed
    profile are separated by minima at least 100 m lower, many times across the map."""
    from scipy import ndimage, signal

    counts = []
    for row in range(50, 1000, 100):
        prof = ndimage.gaussian_filter1d(seabed[row].astype(float), 3)
        peaks, _ = signal.find_peaks(prof, prominence=100.0)
        counts.append(len(peaks))
    assert np.median(counts) >= 3


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"shape": (0, 10)}, r"shape\[0\] \(rows\)"),
        ({"shape": (10,)}, "pair"),
        ({"shape": (10, 10), "cell_size": 0.0}, "cell_size"),
        ({"shape": (10, 10), "cell_size": float("nan")}, "cell_size"),
        ({"shape": (10, 10), "seed": -1}, "seed"),
        ({"shape": (10, 10), "islands": 11}, "islands"),
        ({"shape": (10, 10), "chunks": 0}, r"chunks\[0\]"),
        ({"shape": (10, 10), "chunks": (4, 4, 4)}, "chunks"),
    ],
)
def test_bad_parameters(kwargs, match):
    with pytest.raises(InvalidParameterError, match=match):
        pipeline.synthetic_dem(**kwargs)
