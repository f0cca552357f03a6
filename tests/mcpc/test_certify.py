"""The certified bound: landmark distances against scipy's Dijkstra on the planners' graph built
edge by edge, the landmark lower bound never above the optimum L* (scipy), the stored layers
and their placement equal to the in-memory ones for any chunking, and every "ok" mission of
`plan` within omega of L*, with "uncertified" said when it is not proven."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pystac
import pytest
from conftest import assert_lower_layer, metric_dataarray, quantisation_error_bound, random_surface
from hypothesis import given, settings
from hypothesis import strategies as st
from references import A, missions, optimum, reference_graph, wall_with_gap_dem
from scipy.sparse.csgraph import dijkstra as scipy_dijkstra

import pipeline
from pipeline.maps import landmarks as lm
from pipeline.maps.components import label_components
from pipeline.planners import bounds
from pipeline.store.maps_store import MapsStore
from pipeline.store.schema import VARIABLE

EXE = Path(sys.executable).parent / "pipeline"
# the landmarks' Dijkstra on float64 heights: the test kernels of the warm-up (conftest)
pytestmark = pytest.mark.usefixtures("test_kernels_compiled")


def obstacle_map(seed: int, shape, land: float):
    rng = np.random.default_rng(seed)
    surface = random_surface(shape, seed=seed).astype(np.float32) * 40.0
    ok = rng.random(shape) > land
    return surface, ok


def scipy_distances(surface, ok, a, sources):
    g = reference_graph(surface, ok, a)
    return scipy_dijkstra(g, directed=False, indices=sources, min_only=True).reshape(ok.shape)


@settings(max_examples=30, deadline=None)
@given(
    st.integers(0, 10_000),
    st.tuples(st.integers(1, 18), st.integers(1, 18)),
    st.floats(0.0, 0.5),
    st.integers(1, 3),
)
def test_dijkstra_equals_scipy(seed, shape, land, nsrc):
    surface, ok = obstacle_map(seed, shape, land)
    cells = np.flatnonzero(ok.ravel())
    if cells.size == 0:
        return
    src = np.random.default_rng(seed).choice(cells, size=min(nsrc, cells.size), replace=False)
    got = bounds.dijkstra(surface, ok, 7.5, src.astype(np.int64))
    want = scipy_distances(surface, ok, 7.5, src)
    np.testing.assert_array_equal(np.isfinite(got), np.isfinite(want))
    fin = np.isfinite(want)
    np.testing.assert_allclose(got[fin], want[fin], rtol=1e-12, atol=1e-9)


@settings(max_examples=25, deadline=None)
@given(
    st.integers(0, 10_000),
    st.tuples(st.integers(2, 24), st.integers(2, 24)),
    st.floats(0.0, 0.45),
    st.integers(1, 6),
)
def test_lower_bound_never_exceeds_the_optimum(seed, shape, land, k):
    surface, ok = obstacle_map(seed, shape, land)
    if not ok.any():
        return
    rng = np.random.default_rng(seed + 1)
    cells = np.argwhere(ok)
    marks = lm.place_landmarks(surface, ok, A, k)
    assert len(marks) <= k and all(ok[c] for c in marks) and len(set(marks)) == len(marks)
    layers = [lm.landmark_layer(surface, ok, A, c) for c in marks]
    g = reference_graph(surface, ok, A)
    for _ in range(4):
        s, t = (tuple(cells[i]) for i in rng.integers(len(cells), size=2))
        opt = scipy_dijkstra(g, directed=False, indices=s[0] * shape[1] + s[1])[
            t[0] * shape[1] + t[1]
        ]
        lb = bounds.lower_bound([d[s] for d in layers], [d[t] for d in layers])
        if math.isfinite(opt):
            assert 0.0 <= lb <= opt
        else:
            assert lb == 0.0  # no landmark reaches both


@settings(max_examples=30, deadline=None)
@given(
    st.integers(0, 10_000),
    st.tuples(st.integers(2, 22), st.integers(2, 22)),
    st.floats(0.0, 0.4),
    st.sampled_from([("astar", 1.0), ("wastar", 1.5), ("lagrangian", 1.2), ("dijkstra", 1.0)]),
)
def test_searches_with_the_landmark_heuristic_keep_their_bound(seed, shape, land, case):
    planner, omega = case
    surface, ok = obstacle_map(seed, shape, land)
    cells = np.argwhere(ok)
    if len(cells) < 2:
        return
    rng = np.random.default_rng(seed)
    s, g = (tuple(int(v) for v in cells[i]) for i in rng.integers(len(cells), size=2))
    opt = scipy_distances(surface, ok, A, [s[0] * shape[1] + s[1]])[g]
    if not math.isfinite(opt):
        return
    marks = lm.place_landmarks(surface, ok, A, 4)
    layers = np.stack([lm.landmark_layer(surface, ok, A, c) for c in marks])
    ridge = np.random.default_rng(seed + 2).random(shape) < 0.3
    t = pipeline.plan_window(
        surface, ridge, ok, s, g, cell_size=A, planner=planner, omega=omega, landmarks=layers
    )
    assert t.length_m <= omega * opt * (1 + 1e-9)
    assert t.lower_bound_m <= opt * (1 + 1e-12)
    if planner in ("astar", "dijkstra"):
        assert t.length_m == pytest.approx(opt, rel=1e-9)


def test_the_landmark_heuristic_expands_fewer_cells_behind_a_wall(wall):
    path, surface, ok, graph = wall
    m = pipeline.open_store(path)
    start, goal = (20, 150), (180, 150)
    layers = pipeline.open_maps(path)[VARIABLE].values
    ridge = np.zeros(ok.shape, bool)
    plain = pipeline.plan_window(surface, ridge, ok, start, goal, cell_size=A, planner="astar")
    alt = pipeline.plan_window(
        surface, ridge, ok, start, goal, cell_size=A, planner="astar", landmarks=layers
    )
    assert alt.length_m == pytest.approx(plain.length_m, rel=1e-9)
    assert alt.length_m == pytest.approx(optimum(graph, ok.shape, start, goal), rel=1e-9)
    assert alt.expansions < 0.6 * plain.expansions
    whole = pipeline.plan(m, start, goal, planner="astar", mcpc=False, client="synchronous")
    assert whole.length_m == pytest.approx(plain.length_m, rel=1e-9)


def test_the_bound_is_exact_on_a_line_through_a_landmark():
    # a corridor one cell wide: every path runs through the landmark's line, so the bound is
    # the optimum (less the rounding margin)
    surface = np.linspace(0, 300, 40, dtype=np.float32)[None, :].repeat(3, 0)
    ok = np.zeros((3, 40), bool)
    ok[1] = True
    d = lm.landmark_layer(surface, ok, A, (1, 0))
    opt = scipy_distances(surface, ok, A, [1 * 40 + 5])[1, 33]
    lb = bounds.lower_bound([d[1, 5]], [d[1, 33]])
    assert opt * (1 - 1e-6) <= lb <= opt


def test_the_layers_unit_is_the_finest_that_holds_the_map_else_float64():
    """``fixed_point_bits``: the finest unit ``a 2^-b`` whose cap (2^31 units) holds four times
    the way round the map, between 16 and 24 bits; coarser where a move could cost 2^30 units
    (a relief of 2^14 cells' lengths at 16 bits); none where even whole cells would not do,
    and the layer is then float64 distances rounded to float32. Each within its ``2^-b`` and
    the quantised heights' errors a move (none in float64, on the heights themselves) of scipy's
    distances, and never above them."""
    assert lm.fixed_point_bits((100, 100), 400.0, 30.0) == 21  # log2(2^31 / 800) = 21.4
    assert lm.fixed_point_bits((1, 3), 0.0, 30.0) == 24  # capped at 24
    assert lm.fixed_point_bits((10_000, 10_000), 3000.0, 30.0) == 16  # 2^31 / 80 000: 14.7
    assert lm.fixed_point_bits((100, 100), 0.5 * 2**13, 0.5) == 16
    assert lm.fixed_point_bits((100, 100), 0.5 * 2**14, 0.5) == 15
    assert lm.fixed_point_bits((100, 100), 0.5 * 2**30, 0.5) is None
    surface, ok = obstacle_map(3, (30, 40), 0.2)  # 17.7 km of relief (heights x 40)
    cell = tuple(int(v) for v in np.argwhere(ok)[5])
    # 30 m cells: 22 bits; 2 cm cells: 884 000 cells' lengths of relief, 10 bits; 1e-6 m: none
    err = quantisation_error_bound(surface, ok, 1 << lm.QUANT_SHIFT)
    for a, rtol in ((A, 2.0**-22 + 2 * err / A), (0.02, 2.0**-10 + 2 * err / 0.02), (1e-6, 1e-12)):
        want = scipy_distances(surface, ok, a, [cell[0] * 40 + cell[1]])
        assert_lower_layer(lm.landmark_layer(surface, ok, a, cell), want, rtol)


@settings(max_examples=25, deadline=None)
@given(
    st.integers(0, 10_000),
    st.tuples(st.integers(1, 20), st.integers(1, 20)),
    st.floats(0.0, 0.5),
    st.sampled_from([16, 20, 24, 26]),
)
def test_the_fixed_point_dijkstra_equals_the_sweeps(seed, shape, land, bits):
    """Where the row sweeps give up, a layer's distances come from Dijkstra's algorithm in the
    same fixed point: the same integers (the one solution of ``D(v) = min(cap, min_u D(u) +
    c'(u, v))``), also where they pass the cap (26 bits: 32 cells' lengths), on the quantised
    surface a layer's search holds. The heights are scaled down 40 times, and the unit made
    coarser where a move could still cost 2^30 units, as ``fixed_point_bits`` makes sure."""
    from pipeline.planners import sweep

    surface, ok = obstacle_map(seed, shape, land)
    cells = np.argwhere(ok)
    if len(cells) == 0:
        return
    q = lm.quantised(surface / 40.0, ok)
    while math.sqrt(2.0 + (q.relief / A) ** 2) * 2.0**bits >= 2.0**30:
        bits -= 1
    src = tuple(int(v) for v in cells[np.random.default_rng(seed).integers(len(cells))])
    want = sweep.fixed_point_distances(q, q, A, src, bits)
    assert want is not None
    np.testing.assert_array_equal(lm.fixed_point_dijkstra(q, A, src, bits), want)


def test_a_maze_past_the_cap_takes_coarser_units():
    """Serpentine corridors whose paths run past the first unit's cap (2^31 units: 1024 cells'
    lengths at the 21 bits a 100 x 41 map asks for, the maze's paths about 2000): the layer
    is computed again in units 16 times as long, none of its values held at the cap, within
    2^-17 and the quantised heights' errors a move of scipy's distances, and still a proven
    lower bound."""
    from pipeline.planners import sweep

    walls, rows = 20, 100
    ok = np.ones((rows, 2 * walls + 1), bool)
    for k in range(walls):
        ok[:, 2 * k + 1] = False
        ok[(rows - 2 if k % 2 == 0 else 0) : (rows if k % 2 == 0 else 2), 2 * k + 1] = True
    surface = random_surface(ok.shape, seed=4).astype(np.float32)
    assert lm.fixed_point_bits(ok.shape, lm.quantised(surface, ok).relief, A) == 21
    d, unit = lm.layer_distances(surface, ok, A, (0, 0))
    assert unit == A * 2.0**-17
    assert not (d == sweep.FIXED_CAP).any()
    want = scipy_distances(surface, ok, A, [0])
    assert np.nanmax(np.where(np.isfinite(want), want, np.nan)) > 1024 * A  # past the first cap
    err = quantisation_error_bound(surface, ok, 1 << lm.QUANT_SHIFT)
    assert_lower_layer(lm.layer_values(d, unit), want, 2.0**-17 + 2 * err / A)


def test_landmarks_go_to_every_large_component_only():
    ok = np.zeros((60, 80), bool)
    ok[:, :30] = True  # a large region
    ok[:, 40:] = True  # another
    ok[0, 33] = True  # a puddle of one cell (below MIN_COMPONENT_FRACTION)
    comp, _ = label_components(ok)
    marks = lm.place_landmarks(np.zeros(ok.shape, np.float32), ok, A, 4)
    got = {int(comp[c]) for c in marks}
    assert got == {int(comp[0, 0]), int(comp[0, 40])}


# ------------------------------------------------------------------ in the maps store


@pytest.mark.parametrize("chunks", [(48, 56), (64, 64), (100, 37), (96, 112)])
def test_store_layers_equal_the_in_memory_ones_for_any_chunking(tmp_path, chunks):
    # 97 x 113 cells: (96, 112) leaves a last chunk of one cell on both sides
    import dask

    z = random_surface((97, 113), seed=3) * 300.0 - 2000.0
    z[30:34, 10:100] = 50.0  # a land wall with gaps at both ends
    dem = metric_dataarray(z.astype(np.float32), a=A)
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(
            dem,
            tmp_path / "m.zarr",
            clearance=60.0,
            min_accumulation=8,
            chunks=chunks,
            landmarks=5,
        )
    m = pipeline.open_store(tmp_path / "m.zarr")
    ds = pipeline.open_maps(tmp_path / "m.zarr")
    surface, ok = ds["safety"].values, ds["passable"].values.astype(bool)
    assert m.landmarks == lm.place_landmarks(surface, ok, A, 5)
    for i, cell in enumerate(m.landmarks):
        np.testing.assert_array_equal(
            ds[VARIABLE][i].values, lm.landmark_layer(surface, ok, A, cell)
        )


def test_every_landmark_chunk_is_written_also_where_it_does_not_reach(tmp_path):
    import dask
    import zarr

    z = random_surface((300, 40), seed=2) * 50.0 - 1500.0
    z[197:200] = 40.0  # land across: rows 200.. are a region of their own, whose inner chunk
    # (rows 200-299 of the one shard) no distance of the upper region's landmark reaches (a
    # chunk all inf, once not written at all)
    dem = metric_dataarray(z.astype(np.float32), a=A)
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(dem, tmp_path / "m.zarr", clearance=60.0, landmarks=2)
    m = pipeline.open_store(tmp_path / "m.zarr")
    comp = pipeline.open_maps(tmp_path / "m.zarr")["component"].values
    assert len({int(comp[c]) for c in m.landmarks}) == 2  # one in each region
    arr = zarr.open_array(str(tmp_path / "m.zarr" / VARIABLE), mode="r")
    assert arr.chunks == (1, 100, 40) and arr.shards == (1, 300, 40)
    # every inner chunk of every layer is read from the store (a missing one is damage in a
    # complete store), and some are all inf
    dist = np.array([m.landmark_distances((r, 20)) for r in (50, 150, 250)])
    assert m.all_chunks_written and np.isinf(dist).any() and np.isfinite(dist).any()
    import shutil

    shutil.copytree(tmp_path / "m.zarr", tmp_path / "gone.zarr")  # read afresh (no cache)
    (tmp_path / "gone.zarr" / VARIABLE / "c" / "1" / "0" / "0").unlink()
    with pytest.raises(pipeline.PipelineError, match="missing"):
        pipeline.open_store(tmp_path / "gone.zarr").landmark_distances((250, 20))
    assert m.lower_bound((5, 5), (190, 30)) > 0 and m.lower_bound((280, 5), (295, 30)) > 0


@pytest.mark.parametrize(
    "shape, chunks, factor",
    [((65, 33), (16, 16), 3), ((40, 41), (40, 8), 7), ((7, 300), (3, 256), 2), ((9, 9), (9, 9), 9)],
)
def test_placement_regions_tile_the_map_in_whole_blocks(shape, chunks, factor):
    """Every cell in exactly one region (counted cell by cell), every region starting on a
    block's first row and column, about a chunk a side (a last region of one cell included)."""
    regions = lm.placement_regions(shape, chunks, factor)
    hits = np.zeros(shape, dtype=int)
    for r0, r1, c0, c1 in regions:
        assert r0 % factor == 0 and c0 % factor == 0 and r1 > r0 and c1 > c0
        hits[r0:r1, c0:c1] += 1
    assert (hits == 1).all()


@pytest.mark.parametrize("factor", [1, 3, 7, 16])
def test_block_sums_of_regions_assemble_the_whole_maps_against_brute_force(factor):
    """The coarse grid the maps build assembles from its regions' block sums: the kept cells
    per block exactly, and the sums of the surface, against a loop over each block's cells;
    NaN under land counts as 0, padded blocks at the right and bottom edges hold fewer cells."""
    rng = np.random.default_rng(factor)
    shape = (53, 38)
    surface = (rng.normal(size=shape) * 100).astype(np.float32)
    surface[rng.random(shape) < 0.1] = np.nan
    keep = rng.random(shape) < 0.7
    parts = [
        (
            r0 // factor,
            c0 // factor,
            *lm.block_sums(surface[r0:r1, c0:c1], keep[r0:r1, c0:c1], factor),
        )
        for r0, r1, c0, c1 in lm.placement_regions(shape, (16, 20), factor)
    ]
    n, zs = lm.assembled(shape, factor, parts)
    nb = (-(-shape[0] // factor), -(-shape[1] // factor))
    assert n.shape == zs.shape == nb
    for i in range(nb[0]):
        for j in range(nb[1]):
            blk = (slice(i * factor, (i + 1) * factor), slice(j * factor, (j + 1) * factor))
            k = keep[blk]
            assert n[i, j] == k.sum()
            assert zs[i, j] == pytest.approx(float(np.nansum(surface[blk][k], dtype=np.float64)))
    mean, ok = lm.coarse_mean(n, zs, factor)
    ref_mean, ref_ok = lm.coarse_grid(surface, None, keep, factor)
    np.testing.assert_array_equal(ok, ref_ok)
    np.testing.assert_allclose(mean, ref_mean, rtol=1e-6)


def test_component_sizes_from_the_build_equal_the_layers_bincount(tmp_path, monkeypatch):
    """The components' sizes the maps build's component pass hands to the landmark placement
    (summed from its tiles; the map here is 4 x 3 tiles, the last of one row and column) equal
    numpy's bincount of the whole component layer as written; and the layers, computed by
    two tasks of several landmarks each, equal the in-memory ones."""
    import dask

    seen = {}
    staged = lm.landmarks_staged

    def spy(store, k, a, log=None, counts=None):
        seen["counts"] = counts
        return staged(store, k, a, log, counts)

    monkeypatch.setattr(pipeline.maps.build, "landmarks_staged", spy)
    z = random_surface((97, 65), seed=4) * 300.0 - 1000.0
    z[40:43, :] = 80.0  # land across: two components (the sizes of labels 0, 1, 2)
    dem = metric_dataarray(z.astype(np.float32), a=A)
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(
            dem, tmp_path / "m.zarr", clearance=60.0, min_accumulation=8, chunks=32, landmarks=5
        )
    ds = pipeline.open_maps(tmp_path / "m.zarr")
    comp = ds["component"].values
    assert comp.max() >= 2
    np.testing.assert_array_equal(seen["counts"], np.bincount(comp.ravel()))
    surface, ok = ds["safety"].values, ds["passable"].values.astype(bool)
    cells = pipeline.open_store(tmp_path / "m.zarr").landmarks
    assert len(cells) > 2 and cells == lm.place_landmarks(surface, ok, A, 5)
    for i, cell in enumerate(cells):
        np.testing.assert_array_equal(
            ds[VARIABLE][i].values, lm.landmark_layer(surface, ok, A, cell)
        )


@pytest.mark.parametrize("shape, land", [((61, 53), 0.2), ((1, 70), 0.0), ((9, 8), 0.5)])
def test_a_quantised_surface_keeps_each_height_within_its_blocks_error(shape, land):
    """``landmarks.quantised``: every passable cell's height ``base + code * quantum`` (as the
    searches compute it, in float64) within its block's ``error`` of the float32 height, and
    that error within the bound numpy gives from the blocks' relief; ``IMPASSABLE`` exactly on
    the cells that are not passable or have no height (NaN); a flat block exact. Awkward
    shapes: blocks cut by the map's edge, a single row."""
    from pipeline.planners import sweep

    surface, ok = obstacle_map(7, shape, land)
    surface = surface / 40.0
    surface[:8, :8] = -1234.5  # a flat block
    surface[-1, -1] = np.nan  # a height not known: not passable, whatever the mask says
    q = lm.quantised(surface, ok)
    ok[-1, -1] = False
    np.testing.assert_array_equal(q.codes == sweep.IMPASSABLE, ~ok)
    side = 1 << lm.QUANT_SHIFT
    blocks = (np.arange(shape[0])[:, None] // side, np.arange(shape[1])[None, :] // side)
    height = q.base.astype(np.float64)[blocks] + q.codes * q.quantum.astype(np.float64)[blocks]
    error = q.error.astype(np.float64)[blocks]
    z = surface.astype(np.float32).astype(np.float64)
    assert (np.abs(height - z)[ok] <= error[ok]).all()
    assert error.max() <= quantisation_error_bound(surface, ok, side)
    flat = ok[:8, :8]
    np.testing.assert_array_equal(height[:8, :8][flat], -1234.5)
    hi, lo = z[ok].max(), z[ok].min()
    assert hi - lo <= q.relief <= hi - lo + 2 * error.max()


def test_the_stores_quantised_surface_equals_the_in_memory_one(tmp_path):
    """``quantised_surface`` reads a store's safety and passable layers in bands of whole blocks
    (here shards of 20 rows: bands of 16 that cross them, the last of 13): the same codes,
    bases, steps, errors and relief as ``quantised`` of the layers in memory."""
    import dask
    import zarr

    z = random_surface((61, 53), seed=3) * 3 - 1000
    z[22:27, 10:30] = 80.0  # an island: cells that are not passable
    dem = metric_dataarray(z.astype(np.float32), A)
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(dem, tmp_path / "m.zarr", clearance=60.0, chunks=20, landmarks=0)
    ds = pipeline.open_maps(tmp_path / "m.zarr")
    want = lm.quantised(ds["safety"].values, ds["passable"].values.astype(bool))
    group = zarr.open_group(tmp_path / "m.zarr", mode="r")
    got = lm.quantised_surface(str(tmp_path / "m.zarr"), group)
    assert (~ds["passable"].values.astype(bool)).any() and ds["passable"].values.any()
    for name in ("codes", "base", "quantum", "error"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    assert (got.shift, got.relief) == (want.shift, want.relief)


def test_a_landmark_task_holds_one_distance_array_at_a_time(tmp_path, monkeypatch):
    """A task computing several landmarks' layers lets each one's distances go before the
    next search (a view left over from the write once kept them: two whole-map arrays, 2.36
    GiB a worker instead of 1.61 at 10000^2), and writes the layers the in-memory searches
    give (there from the safety and passable layers, in the task from its quantised surface,
    read band by band)."""
    import weakref

    import dask

    dem = metric_dataarray((random_surface((60, 50), seed=6) * 300 - 1000).astype(np.float32), A)
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(dem, tmp_path / "m.zarr", clearance=60.0, landmarks=3)
    cells = pipeline.open_store(tmp_path / "m.zarr").landmarks
    alive = []
    search = lm.layer_distances

    def watched(*args):
        assert not any(ref() is not None for ref in alive)  # the last one's is gone
        out = search(*args)
        d = out[0]
        while isinstance(d.base, np.ndarray):  # the array whose memory every view shares
            d = d.base
        alive.append(weakref.ref(d))
        return out

    monkeypatch.setattr(lm, "layer_distances", watched)
    lm._layers_task(str(tmp_path / "m.zarr"), list(enumerate(cells)), A)
    assert len(alive) == len(cells) == 3
    ds = pipeline.open_maps(tmp_path / "m.zarr")
    surface, ok = ds["safety"].values, ds["passable"].values.astype(bool)
    for i, cell in enumerate(cells):
        np.testing.assert_array_equal(
            ds[VARIABLE][i].values, lm.landmark_layer(surface, ok, A, cell)
        )


def test_a_landmark_task_where_no_fixed_point_serves_takes_the_float32_heights(
    tmp_path, monkeypatch
):
    """Where no fixed point serves (a relief of 2^30 cells' lengths; here ``fixed_point_bits``
    made to say so), a landmark task computes its layers in float64 on the store's float32
    heights, not its quantised ones: scipy's distances on those heights, to float32 rounding."""
    import dask

    dem = metric_dataarray((random_surface((40, 30), seed=8) * 3 - 1000).astype(np.float32), A)
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(dem, tmp_path / "m.zarr", clearance=60.0, landmarks=2)
    cells = pipeline.open_store(tmp_path / "m.zarr").landmarks
    monkeypatch.setattr(lm, "fixed_point_bits", lambda shape, relief, a: None)
    lm._layers_task(str(tmp_path / "m.zarr"), list(enumerate(cells)), A)
    ds = pipeline.open_maps(tmp_path / "m.zarr")
    surface, ok = ds["safety"].values, ds["passable"].values.astype(bool)
    for i, cell in enumerate(cells):
        want = scipy_distances(surface, ok, A, [cell[0] * ok.shape[1] + cell[1]])
        got = ds[VARIABLE][i].values
        np.testing.assert_array_equal(np.isfinite(got), np.isfinite(want))
        fin = np.isfinite(want)
        np.testing.assert_allclose(got[fin], want[fin], rtol=2.0**-24 + 1e-12)


@pytest.mark.parametrize("codec", ["none", "blosc"])
def test_a_landmark_task_reads_the_whole_layer_as_zarr_does(tmp_path, codec):
    """The layers a landmark task holds (copied from the mapped shards of an uncompressed
    sharded layer, else read through zarr) equal zarr's reads, also with a shard missing
    (read as the fill value) and with a last shard of one row and column."""
    import zarr
    from zarr.codecs import BloscCodec

    rng = np.random.default_rng(5)
    data = (rng.normal(size=(65, 33)) * 100).astype(np.float32)
    data[0, 0] = np.nan
    comp = None if codec == "none" else BloscCodec(cname="lz4", clevel=5, shuffle="shuffle")
    g = zarr.open_group(tmp_path / "s.zarr", mode="w", zarr_format=3)
    for name, shards in (("full", (32, 32)), ("holed", (32, 32))):
        arr = g.create_array(
            name, shape=data.shape, chunks=(16, 16), shards=shards, dtype="float32",
            fill_value=-7.0, compressors=comp,
        )  # fmt: skip
        arr[...] = data
    (tmp_path / "s.zarr" / "holed" / "c" / "1" / "0").unlink()
    g = zarr.open_group(tmp_path / "s.zarr", mode="r", zarr_format=3)
    for name in ("full", "holed"):
        got = lm.whole_layer(str(tmp_path / "s.zarr"), g, name)
        np.testing.assert_array_equal(got, g[name][:])
        assert got.dtype == np.float32
    assert (lm.whole_layer(str(tmp_path / "s.zarr"), g, "holed")[32:64, :32] == -7.0).all()


def test_a_store_without_landmarks_has_no_bound(tmp_path):
    import dask

    dem = metric_dataarray((random_surface((40, 40)) * 50 - 1000).astype(np.float32), a=A)
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(dem, tmp_path / "m.zarr", clearance=60.0, landmarks=0)
    m = pipeline.open_store(tmp_path / "m.zarr")
    assert m.landmarks == [] and m.lower_bound((1, 1), (38, 38)) == 0.0


def test_a_store_whose_landmark_layer_is_gone_is_damaged(tmp_path):
    import shutil

    import dask

    dem = metric_dataarray((random_surface((40, 40)) * 50 - 1000).astype(np.float32), a=A)
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(dem, tmp_path / "m.zarr", clearance=60.0, landmarks=2)
    shutil.rmtree(tmp_path / "m.zarr" / VARIABLE / "c" / "1")  # layer 1's chunks
    m = pipeline.open_store(tmp_path / "m.zarr")
    with pytest.raises(pipeline.PipelineError, match=r"chunk \(1, 0, 0\) of its layer"):
        m.lower_bound((1, 1), (38, 38))
    shutil.rmtree(tmp_path / "m.zarr" / VARIABLE)
    with pytest.raises(pipeline.PipelineError, match="landmark layers .* are missing"):
        MapsStore(tmp_path / "m.zarr")  # (open_store would keep the store it opened)


# ------------------------------------------------------------------ certification in plan


@pytest.fixture(scope="module")
def wall(tmp_path_factory):
    """A 200^2 map with a land wall and one narrow gap (test_components), and its graph."""
    import dask

    path = tmp_path_factory.mktemp("certify") / "maps.zarr"
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(wall_with_gap_dem(), path, clearance=60.0, min_accumulation=8)
    ds = pipeline.open_maps(path)
    surface, ok = ds["safety"].values, ds["passable"].values.astype(bool)
    return path, surface, ok, reference_graph(surface, ok, A)


@pytest.mark.parametrize("omega", [1.0, 1.01, 1.2, 2.0])
@pytest.mark.parametrize("planner", ["astar", "ra_star"])
def test_ok_implies_the_bound_against_scipy(wall, omega, planner):
    path, surface, ok, graph = wall
    for s, g in missions(ok, 4, seed=int(omega * 100)):
        t = pipeline.plan(path, s, g, planner=planner, omega=omega, client="synchronous")
        opt = optimum(graph, ok.shape, s, g)
        assert t.lower_bound_m <= opt  # proven: never above the optimum
        assert t.status == "ok", t.message  # repaired when needed, so always certified here
        assert t.length_m <= omega * opt * (1 + pipeline.mcpc.certify.CERTIFY_TOLERANCE)
        assert t.certified_ratio == pytest.approx(t.length_m / t.lower_bound_m)


@settings(max_examples=5, deadline=None)
@given(
    st.integers(0, 10_000),
    st.sampled_from([1.0, 1.01, 1.2, 2.0]),
    st.sampled_from(["ra_star", "astar", "lagrangian"]),
    st.integers(0, 1),
)
def test_ok_implies_the_bound_on_random_obstacle_maps(tmp_path_factory, seed, omega, planner, rep):
    import dask

    rng = np.random.default_rng(seed)
    z = random_surface((60, 70), seed=seed) * 200.0 - 1500.0
    for _ in range(rng.integers(2, 6)):  # land blocks: straight lines cross them
        r, c = rng.integers(0, 50), rng.integers(0, 60)
        z[r : r + rng.integers(3, 12), c : c + rng.integers(3, 25)] = 20.0
    path = tmp_path_factory.mktemp("random") / "m.zarr"
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(
            metric_dataarray(z.astype(np.float32), a=A), path, clearance=45.0, chunks=32
        )
    ds = pipeline.open_maps(path)
    surface, ok = ds["safety"].values, ds["passable"].values.astype(bool)
    graph = reference_graph(surface, ok, A)
    for s, g in missions(ok, 3, seed=seed, min_cells=20):
        t = pipeline.plan(
            path,
            s,
            g,
            planner=planner,
            omega=omega,
            rho=3,
            section_size=12,
            repair_max_cells=rep * 10**6,
            client="synchronous",
        )
        opt = optimum(graph, ok.shape, s, g)
        assert t.lower_bound_m <= opt
        assert t.status == ("ok" if rep else t.status)
        if t.status == "ok":
            assert t.length_m <= omega * opt * (1 + 1e-9)
        else:
            assert t.status == "uncertified" and t.certified_ratio > omega


@pytest.mark.parametrize("rho", [5, 10, 20])
def test_wall_with_gap_is_never_ok_beyond_omega(wall, rho):
    path, surface, ok, graph = wall
    start, goal = (20, 150), (180, 150)  # the gap is far from the straight line
    opt = optimum(graph, ok.shape, start, goal)
    for repair in (25_000_000, 0):
        t = pipeline.plan(
            path,
            start,
            goal,
            planner="ra_star",
            omega=1.5,
            rho=rho,
            section_size=4 * rho,
            repair_max_cells=repair,
            client="synchronous",
        )
        assert t.lower_bound_m <= opt
        if t.status == "ok":
            assert t.length_m <= 1.5 * opt * (1 + 1e-9)
        else:
            assert t.status == "uncertified" and repair == 0


def test_uncertified_says_so_with_the_proven_ratio(wall):
    path, surface, ok, graph = wall
    seen = 0
    for s, g in missions(ok, 8, seed=5):
        t = pipeline.plan(path, s, g, omega=1.0, repair_max_cells=0, client="synchronous")
        if t.status == "uncertified":
            seen += 1
            assert f"{t.certified_ratio:.4f} x the shortest" in t.message
            assert "repair_max_cells" in t.message and "mcpc=False" in t.message
            assert t.length_m > t.lower_bound_m and len(t.cells) > 1
        else:
            assert t.length_m <= optimum(graph, ok.shape, s, g) * (1 + 1e-9)
    assert seen  # at omega 1 a stitched path is rarely proven optimal by the bound alone


def test_the_landmark_bound_beats_the_octile_distance_behind_the_wall(wall):
    path, surface, ok, graph = wall
    start, goal = (20, 150), (180, 150)
    m = pipeline.open_store(path)
    opt = optimum(graph, ok.shape, start, goal)
    octile = A * 160
    assert octile < 0.7 * opt  # the detour through the gap
    assert 0.95 * opt <= m.lower_bound(start, goal) <= opt


UNCERTIFIED_JOB = """
name = "u"
[dem]
chunks = 64
[dem.synthetic]
shape = [120, 120]
cell_size = 30.0
seed = 4
islands = 0
[maps]
clearance = 150.0
[planning]
omega = 1.0
repair_max_cells = 0
rho = 4
{missions}
[output]
catalog = "{catalog}"
performance_report = false
quicklooks = false
"""


def test_a_job_with_uncertified_missions_exits_5_and_writes_them(tmp_path, local_client):
    missions = "".join(
        f'[[missions]]\nname = "m{i}"\nstart = [{3 + 11 * i}, 4]\ngoal = [{115 - 9 * i}, 116]\n'
        for i in range(4)
    )
    job = tmp_path / "job.toml"
    job.write_text(UNCERTIFIED_JOB.format(missions=missions, catalog=tmp_path / "cat"))
    proc = subprocess.run(
        [str(EXE), "run", str(job), "--scheduler", local_client.scheduler.address],
        capture_output=True,
        text=True,
        timeout=600,
    )
    cat = pystac.Catalog.from_file(str(tmp_path / "cat" / "catalog.json"))
    props = {it.id: it.properties for it in cat.get_items(recursive=True)}
    status = [p["auv:status"] for p in props.values()]
    assert len(status) == 4 and set(status) <= {"ok", "uncertified"}
    if "uncertified" in status:
        assert proc.returncode == 5, proc.stderr[-2000:]
        assert "not certified" in proc.stdout and "is not proven" in proc.stderr
    else:
        assert proc.returncode == 0
    for p in props.values():
        assert p["auv:certified_ratio"] == pytest.approx(p["auv:length_m"] / p["auv:lower_bound_m"])
        if p["auv:status"] == "uncertified":
            assert p["auv:certified_ratio"] > 1.0 and "x the shortest" in p["auv:message"]
    assert "uncertified" in status, json.dumps(props, indent=1)[:2000]


@pytest.fixture(scope="module")
def real(tmp_path_factory, topobathy_nc):
    """Real bathymetry with land (matplotlib's topobathy, lon/lat) at 600 m cells: channels,
    straits and the continental slope, 1.6 % of the cells passable."""
    import dask

    tmp = tmp_path_factory.mktemp("real-certify")
    dem = pipeline.open_dem(topobathy_nc, resolution=600.0, chunks=128)
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(
            dem, tmp / "m.zarr", clearance=300.0, surface_clearance=50.0, min_accumulation=8
        )
    ds = pipeline.open_maps(tmp / "m.zarr")
    surface, ok = ds["safety"].values, ds["passable"].values.astype(bool)
    return tmp / "m.zarr", surface, ok, reference_graph(surface, ok, 600.0)


@pytest.mark.parametrize("omega", [1.0, 1.2, 2.0])
def test_real_bathymetry_missions_are_certified_against_scipy(real, omega):
    path, surface, ok, graph = real
    ms = missions(ok, 5, seed=11, min_cells=80)
    detours = 0
    for s, g in ms:
        t = pipeline.plan(path, s, g, omega=omega, rho=4, client="synchronous")
        opt = optimum(graph, ok.shape, s, g)
        assert t.lower_bound_m <= opt
        assert t.status == "ok", t.message
        assert t.length_m <= omega * opt * (1 + 1e-9)
        line = np.linspace(s, g, 400).round().astype(int)
        detours += not ok[line[:, 0], line[:, 1]].all()
    assert detours >= 2  # missions whose straight line crosses land or shallows
