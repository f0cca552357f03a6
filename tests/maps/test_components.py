"""Connected components of the passable graph: against scipy's connected_components on the
planners' own graph (8 moves, no corner cutting) built edge by edge, chunk-wise equal to the
in-memory labels for any chunking, stored by build_maps, and used by plan: "unreachable" only
when proven, and a reachable goal that MCPC misses planned on the whole map."""

from __future__ import annotations

import math

import dask.array as da
import numpy as np
import pytest
from conftest import CHUNKINGS
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from references import check_path, reference_graph, reference_length, wall_with_gap_dem
from scipy.sparse.csgraph import connected_components

import pipeline
from pipeline.maps.components import components_staged, label_components


def reference_partition(ok: np.ndarray) -> np.ndarray:
    """Components of the planners' graph, edge by edge, by scipy.sparse.csgraph."""
    graph = reference_graph(np.zeros(ok.shape), ok, 1.0)
    return connected_components(graph, directed=False)[1].reshape(ok.shape)


def same_partition(labels, ref, ok) -> bool:
    """The same grouping of passable cells (one label per reference component and back)."""
    pairs = set(zip(labels[ok].tolist(), ref[ok].tolist(), strict=True))
    return len(pairs) == len({a for a, _ in pairs}) == len({b for _, b in pairs})


@settings(max_examples=40, deadline=None)
@given(arrays(bool, st.tuples(st.integers(1, 14), st.integers(1, 14))))
def test_components_are_those_of_the_planners_graph(ok):
    labels, n = label_components(ok)
    assert (labels[~ok] == 0).all() and (labels[ok] > 0).all()
    assert same_partition(labels, reference_partition(ok), ok)
    assert n == len(np.unique(labels[ok]))


def test_diagonal_contact_alone_does_not_join():
    ok = np.array([[1, 0], [0, 1]], dtype=bool)  # the diagonal would cut two corners
    labels, n = label_components(ok)
    assert n == 2 and labels[0, 0] != labels[1, 1]


@pytest.mark.parametrize(
    "shape, chunks",
    [((123, 97), ch) for ch in CHUNKINGS if ch]
    + [((129, 65), (64, 64)), ((130, 67), (64, 64)), ((5, 300), (1, 7)), ((2, 2), (1, 1))],
)
def test_chunked_equals_in_memory_for_any_chunking(tmp_path, shape, chunks):
    rng = np.random.default_rng(sum(shape))
    ok = rng.random(shape) > 0.42  # near the percolation threshold: long, winding regions
    want, n = label_components(ok)
    got, count = components_staged(da.from_array(ok, chunks=chunks), tmp_path / "scratch")
    np.testing.assert_array_equal(got.compute(), want)
    assert count == n


# ------------------------------------------------------------------ what plan makes of it

A = 30.0


@pytest.fixture(scope="module")
def wall_store(tmp_path_factory):
    import dask

    path = tmp_path_factory.mktemp("wall") / "maps.zarr"
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(wall_with_gap_dem(), path, clearance=60.0, min_accumulation=8)
    return path


@pytest.mark.timeout(60)
@pytest.mark.parametrize("mcpc, rho", [(True, None), (True, 20), (False, None)])
def test_unreachable_is_proven_and_instant(wall_store, mcpc, rho, monkeypatch):
    """The goal inside the closed ring: the components say so before any window is read,
    whether the coarse search finds no path (rho 2) or one through the ring (rho 20, blocks
    wider than its wall), and for the whole map."""
    import pipeline.mcpc.runners as mcpc_module

    read = []
    monkeypatch.setattr(mcpc_module, "read_section", lambda *args: read.append(args))
    with pytest.raises(pipeline.UnreachableGoalError, match="separate passable regions"):
        pipeline.plan(wall_store, (180, 20), (40, 60), mcpc=mcpc, rho=rho, client="synchronous")
    assert read == []


@pytest.mark.parametrize("rho", [5, 10, 20])
def test_a_reachable_goal_behind_a_narrow_gap_is_found(wall_store, rho):
    ds = pipeline.open_maps(wall_store)
    surface, ok = ds["safety"].values, ds["passable"].values
    start, goal = (20, 150), (180, 150)
    t = pipeline.plan(
        wall_store,
        start,
        goal,
        planner="astar",
        rho=rho,
        section_size=4 * rho,
        client="synchronous",
    )
    check_path(t, ok, start, goal)
    opt = reference_length(surface, ok, A, start, goal)
    assert math.isfinite(opt) and t.length_m >= opt * (1 - 1e-9)
    assert t.cells[:, 1].min() < 20  # through the gap
    if rho >= 10:  # the coarse map does not see the wall: MCPC fails, the whole map is planned
        assert "MCPC found no path" in t.extra["fallback"]


def test_build_maps_stores_the_components(wall_store):
    maps = pipeline.open_maps(wall_store)
    want, _ = label_components(maps["passable"].values)
    np.testing.assert_array_equal(maps["component"].values, want)
    assert want.max() >= 2  # the lagoon is a region of its own
    store = pipeline.open_store(wall_store)
    assert store.component((180, 20)) == want[180, 20] != store.component((40, 60))
