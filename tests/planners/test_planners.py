"""Planners on one window: optimal lengths against scipy's Dijkstra on a graph built here,
skimage's MCP on flat ground, the weighted-A* bound as a property, path validity, errors.


"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import random_surface
from hypothesis import given, settings
from hypothesis import strategies as st
from references import (
    check_path,
    independent_metrics,
    reference_distances,
    reference_graph,
    reference_length,
)
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

import pipeline
from pipeline.exceptions import InvalidEndpointError, InvalidParameterError, UnreachableGoalError

# the planners on float64 heights: the test kernels of the warm-up (conftest)
pytestmark = pytest.mark.usefixtures("test_kernels_compiled")


def obstacle_map(shape, seed, density=0.25):
    rng = np.random.default_rng(seed)
    surface = random_surface(shape, seed=seed).astype(np.float64)
    passable = rng.random(shape) > density
    ridge = rng.random(shape) < 0.3
    return surface, ridge, passable


def endpoints(passable, seed):
    rng = np.random.default_rng(seed)
    cells = np.argwhere(passable)
    a, b = rng.choice(len(cells), 2, replace=False)
    return tuple(cells[a]), tuple(cells[b])


@pytest.mark.parametrize("planner", ["astar", "dijkstra"])
@pytest.mark.parametrize("seed", range(6))
def test_optimal_against_scipy(planner, seed):
    surface, ridge, passable = obstacle_map((40, 35), seed, density=0.2 + 0.04 * seed)
    s, g = endpoints(passable, seed)
    ref = reference_length(surface, passable, 30.0, s, g)
    if not np.isfinite(ref):
        with pytest.raises(UnreachableGoalError, match="no path"):
            pipeline.plan_window(surface, ridge, passable, s, g, cell_size=30.0, planner=planner)
        return
    t = pipeline.plan_window(surface, ridge, passable, s, g, cell_size=30.0, planner=planner)
    assert t.length_m == pytest.approx(ref, rel=1e-9)
    assert t.lower_bound_m == pytest.approx(ref, rel=1e-9)
    check_path(t, passable, s, g)
    length, ridge_len = independent_metrics(t, surface, ridge, 30.0)
    assert t.length_m == pytest.approx(length, rel=1e-12)
    assert t.ridge_length_m == pytest.approx(ridge_len, rel=1e-12)
    assert t.ridge_ratio == pytest.approx(ridge_len / length, rel=1e-12)


@pytest.mark.parametrize("seed", range(4))
def test_bucketed_search_against_scipy(seed):
    """The two-level open list of large windows (``astar_search_bucketed``), run here on small
    ones: Dijkstra (weight 0) and A* find scipy's optimum, weighted A* a path within its
    weight, each traced path measured independently equals its g; with a 100 km cliff in the
    map (moves up it cost more than all the buckets ahead span: the far heap) as well."""
    from pipeline.planners.paths import trace_path
    from pipeline.planners.search import (
        BUCKET_WIDTH,
        BUCKETS,
        NO_GOAL,
        NO_LANDMARKS,
        TIE,
        astar_search_bucketed,
        search_arrays,
    )

    surface, ridge, passable = obstacle_map((45, 38), seed, density=0.15 + 0.05 * seed)
    if seed % 2:
        surface[:, 20:] += 1e5  # each move onto the cliff costs more than the buckets ahead
        assert 1e5 > BUCKETS * BUCKET_WIDTH * 30.0
    z = surface.astype(np.float32)
    s, g = endpoints(passable, seed)
    if seed % 2:  # across the cliff
        cells = np.argwhere(passable)
        s, g = tuple(cells[cells[:, 1] < 10][0]), tuple(cells[cells[:, 1] > 25][-1])
    goal = g[0] * z.shape[1] + g[1]
    ref = reference_length(z.astype(np.float64), passable, 30.0, s, g)
    for weight in (0.0, 1.0, 2.0):
        state, gs, exp, found = astar_search_bucketed(
            z, ridge, passable, 30.0, *s, *g, weight, 0.0, True, NO_LANDMARKS, NO_GOAL,
            *search_arrays(z.size),
        )  # fmt: skip
        assert found == bool(np.isfinite(ref))
        if not found:
            continue
        cells = trace_path(state, z.shape[1], g)
        assert tuple(cells[0]) == s and tuple(cells[-1]) == g
        steps = np.diff(cells, axis=0)
        assert np.all(np.abs(steps).max(axis=1) == 1) and passable[cells[:, 0], cells[:, 1]].all()
        dz = np.diff(z[cells[:, 0], cells[:, 1]].astype(np.float64))
        length = np.sqrt(900.0 * (steps**2).sum(axis=1) + dz * dz).sum()
        assert length == pytest.approx(gs[goal], rel=1e-12)
        if weight <= 1.0:
            assert gs[goal] == pytest.approx(ref, rel=1e-9)
        else:
            assert ref * (1 - 1e-12) <= gs[goal] <= weight * (1 + TIE) * ref * (1 + 1e-12)


def test_whole_large_map_takes_the_bucketed_search():
    """A window from ``BUCKET_CELLS`` cells on is searched with the two-level open list (by
    Dijkstra, weighted A*, and A* where the sweeps give up), and A* there finds the optimum: on
    flat open ground the octile distance, in closed form."""
    from pipeline.planners.paths import trace_path
    from pipeline.planners.search import (
        BUCKET_CELLS,
        NO_GOAL,
        NO_LANDMARKS,
        astar_search_bucketed,
        search_arrays,
        search_kernel,
    )

    rows, cols = 2100, 2000
    assert rows * cols >= BUCKET_CELLS and search_kernel(rows * cols) is astar_search_bucketed
    z = np.full((rows, cols), -3000.0, np.float32)
    ok = np.ones(z.shape, bool)
    s, g = (3, 1990), (2090, 7)
    state, gs, _, found = astar_search_bucketed(
        z, ok, ok, 30.0, *s, *g, 1.0, 0.0, True, NO_LANDMARKS, NO_GOAL, *search_arrays(z.size)
    )
    assert found
    want = 30.0 * (2087 + (math.sqrt(2) - 1) * 1983)
    assert gs[g[0] * cols + g[1]] == pytest.approx(want, rel=1e-12)
    cells = trace_path(state, cols, g)
    assert tuple(cells[0]) == s and np.all(np.abs(np.diff(cells, axis=0)).max(axis=1) == 1)
    # the planner's own search of that window (the sweeps) finds the same length
    t = pipeline.plan_window(z, ok, ok, s, g, cell_size=30.0, planner="astar")
    assert t.length_m == pytest.approx(want, rel=1e-12)
    check_path(t, ok, s, g)


def test_heap_keeps_order_while_it_grows():
    """The searches' heap (``pipeline.planners.heap``), grown by ``heap_reserve`` between
    pushes from 1 slot to thousands, pops every key in sorted order (against numpy's sort)."""
    from pipeline.planners.heap import heap_pop, heap_push, heap_reserve

    rng = np.random.default_rng(7)
    keys = rng.random(5000)
    keys[::7] = keys[1::7]  # ties
    hk, hi, hn = np.empty(1), np.empty(1, dtype=np.int64), 0
    out = []
    for i, k in enumerate(keys):
        hk, hi = heap_reserve(hk, hi, hn, 1 + i % 9)
        assert hk.size >= hn + 1 + i % 9
        hn = heap_push(hk, hi, hn, k, i)
        if i % 5 == 4:  # pops between pushes
            key, item = heap_pop(hk, hi, hn)
            hn -= 1
            out.append((key, keys[item]))
    popped = [k for k, _ in out]
    assert all(k == keys_item for k, keys_item in out)  # items travel with their keys
    while hn:
        key, item = heap_pop(hk, hi, hn)
        hn -= 1
        assert key == keys[item]
        popped.append(key)
    assert len(popped) == keys.size
    tail = np.asarray(popped[len(out) :])
    np.testing.assert_array_equal(tail, np.sort(tail))


@pytest.mark.parametrize("planner", ["dijkstra", "astar", "ra_star"])
def test_large_window_where_the_heaps_outgrow_their_first_size(planner):
    """250 x 250 cells (below the sweeps' SWEEP_CELLS: A*) from the middle to a corner: the
    open lists hold well over the 1024 entries the searches start with (1.4-1.6 thousand for
    A* and Dijkstra), so they grow between passes of the inner loop. Optimal lengths against
    scipy, RA*'s bound."""
    from pipeline.planners.astar import SWEEP_CELLS

    assert 250 * 250 < SWEEP_CELLS
    surface, ridge, passable = obstacle_map((250, 250), 11, density=0.04)
    s = (125, 125)
    g = tuple(np.argwhere(passable[-20:, :20])[-1] + (230, 0))
    passable[s] = True
    ref = reference_length(surface, passable, 30.0, s, g)
    assert np.isfinite(ref)
    t = pipeline.plan_window(
        surface, ridge, passable, s, g, cell_size=30.0, planner=planner, omega=2.0
    )
    check_path(t, passable, s, g)
    if planner == "ra_star":
        assert ref * (1 - 1e-9) <= t.length_m <= 2.0 * ref * (1 + 1e-9)
        assert t.lower_bound_m <= ref * (1 + 1e-9)
    else:
        assert t.length_m == pytest.approx(ref, rel=1e-9)


def test_optimal_on_real_bathymetry(topobathy_tif):
    """Real relief and a real coastline: matplotlib's topobathy (2.4 km cells, too coarse for
    a clearance sphere), planned on the seabed itself over sea cells deeper than 50 m."""
    dem = pipeline.open_dem(topobathy_tif, chunks=None)
    a = pipeline.cell_size(dem)
    z = dem.values.astype(np.float64)
    ok = np.isfinite(z) & (z < -50.0)
    surface = np.nan_to_num(z, nan=0.0)
    from scipy import ndimage

    lab, _ = ndimage.label(ok, structure=np.ones((3, 3)))  # the largest sea, start in it
    big = np.argmax(np.bincount(lab.ravel())[1:]) + 1
    s = tuple(np.argwhere(lab == big)[0])
    d = reference_distances(surface, ok, a, s)
    far = int(np.argmax(np.where(np.isfinite(d), d, -1.0)))  # the farthest reachable cell
    g, ref = divmod(far, surface.shape[1]), float(d[far])
    assert ref > 50 * a
    t = pipeline.plan_window(surface, np.zeros_like(ok), ok, s, g, cell_size=a, planner="astar")
    assert t.length_m == pytest.approx(ref, rel=1e-9)
    check_path(t, ok, s, g)


def test_flat_ground_equals_skimage_mcp():
    from skimage.graph import MCP_Geometric

    shape = (60, 80)
    surface = np.full(shape, -2000.0)
    ok = np.ones(shape, bool)
    m = MCP_Geometric(np.ones(shape), fully_connected=True)
    costs, _ = m.find_costs([(3, 4)])
    for goal in [(50, 70), (3, 79), (59, 4), (30, 30)]:
        t = pipeline.plan_window(surface, ok, ok, (3, 4), goal, cell_size=25.0, planner="astar")
        assert t.length_m == pytest.approx(25.0 * costs[goal], rel=1e-9)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), omega=st.floats(1.0, 4.0), density=st.floats(0.0, 0.35))
def test_wastar_bound_and_validity(seed, omega, density):
    surface, ridge, passable = obstacle_map((25, 30), seed, density)
    s, g = endpoints(passable, seed)
    ref = reference_length(surface, passable, 30.0, s, g)
    if not np.isfinite(ref):
        return
    t = pipeline.plan_window(
        surface, ridge, passable, s, g, cell_size=30.0, planner="wastar", omega=omega
    )
    check_path(t, passable, s, g)
    assert t.length_m <= omega * ref * (1 + 1e-9)
    assert t.lower_bound_m <= ref * (1 + 1e-9)  # a proven lower bound, here checked
    again = pipeline.plan_window(
        surface, ridge, passable, s, g, cell_size=30.0, planner="wastar", omega=omega
    )
    np.testing.assert_array_equal(again.cells, t.cells)  # deterministic


def test_points_use_coordinates():
    surface = np.full((5, 6), -100.0)
    ok = np.ones((5, 6), bool)
    t = pipeline.plan_window(
        surface,
        ok,
        ok,
        (0, 0),
        (4, 5),
        cell_size=10.0,
        planner="astar",
        x=1000.0 + 10.0 * np.arange(6),
        y=500.0 - 10.0 * np.arange(5),
    )
    assert tuple(t.points[0]) == (1000.0, 500.0, -100.0)
    assert tuple(t.points[-1]) == (1050.0, 460.0, -100.0)


# ----------------------------------------------------------------------------- errors


def _small():
    surface = np.full((10, 10), -500.0)
    ok = np.ones((10, 10), bool)
    ok[:, 5] = False  # a wall: the right half is unreachable
    ok[2, 2] = False
    return surface, ok.copy(), ok


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        ({"start": (10, 0)}, InvalidEndpointError, r"start \(10, 0\) is off the map"),
        ({"goal": (-1, 3)}, InvalidEndpointError, r"goal \(-1, 3\) is off the map"),
        (
            {"start": (2, 2)},
            InvalidEndpointError,
            r"start \(2, 2\) is on land or inside the clearance zone; nearest passable cell",
        ),
        ({"goal": (0, 8)}, UnreachableGoalError, "no path from start"),
        ({"omega": 0.5}, InvalidParameterError, "`omega` must be a finite number >= 1, got 0.5"),
        ({"omega": float("nan")}, InvalidParameterError, "`omega` must be a finite number >= 1"),
        ({"cell_size": 0.0}, InvalidParameterError, "`cell_size` must be"),
        ({"planner": "bfs"}, InvalidParameterError, "`planner` must be 'dijkstra', 'astar'"),
        ({"start": "a"}, InvalidParameterError, "must be a cell"),
    ],
)
def test_errors(kwargs, error, match):
    surface, ridge, ok = _small()
    args = dict(start=(0, 0), goal=(9, 4), cell_size=30.0, planner="astar", omega=2.0)
    args.update(kwargs)
    with pytest.raises(error, match=match):
        pipeline.plan_window(surface, ridge, ok, **args)


def test_shape_mismatch_and_nan():
    surface, ridge, ok = _small()
    with pytest.raises(InvalidParameterError, match="one shape"):
        pipeline.plan_window(
            surface, ridge[:5], ok, (0, 0), (9, 4), cell_size=30.0, planner="astar"
        )
    surface[7, 1] = np.nan
    with pytest.raises(InvalidParameterError, match=r"NaN or infinite at passable cell \(7, 1\)"):
        pipeline.plan_window(surface, ridge, ok, (0, 0), (9, 4), cell_size=30.0, planner="astar")


# ----------------------------------------------------------------------------- RA*


def random_mission(seed, density, ridge_share):
    """An obstacle field with random ridge cells, two endpoints, and the scipy optimum; None
    when the endpoints are not connected."""
    surface, _, passable = obstacle_map((25, 30), seed, density)
    ridge = np.random.default_rng(seed + 1).random(surface.shape) < ridge_share
    s, g = endpoints(passable, seed)
    ref = reference_length(surface, passable, 30.0, s, g)
    return (surface, ridge, passable, s, g, ref) if np.isfinite(ref) else None


def test_searches_one_after_another_in_a_thread_are_each_optimal():
    """A* reuses its thread's search arrays: after searches on larger windows (a long path,
    its cells marked in the kept state) and one whose goal is walled off (every reachable
    cell closed), each search on a smaller window still equals scipy."""
    from concurrent.futures import ThreadPoolExecutor

    walled = obstacle_map((50, 50), 7, density=0.0)
    walled[2][:, 25] = False
    cases = [obstacle_map(shape, k, 0.15 + 0.05 * (k % 3)) for k, shape in enumerate(
        [(60, 70), (40, 35), (61, 71), (25, 30), (9, 8), (40, 35)]
    )]  # fmt: skip
    cases.insert(2, walled)
    ends = [endpoints(c[2], k) for k, c in enumerate(cases)]
    ends[2] = ((10, 3), (40, 45))

    def run():
        out = []
        for (surface, ridge, passable), (s, g) in zip(cases, ends, strict=True):
            try:
                t = pipeline.plan_window(
                    surface, ridge, passable, s, g, cell_size=30.0, planner="astar"
                )
                out.append(t)
            except UnreachableGoalError:
                out.append(None)
        return out

    with ThreadPoolExecutor(1) as pool:  # a thread whose arrays start empty
        results = pool.submit(run).result()
    assert results[2] is None
    for (surface, _, passable), (s, g), t in zip(cases, ends, results, strict=True):
        ref = reference_length(surface, passable, 30.0, s, g)
        assert (t is None) == (not np.isfinite(ref))
        if t is not None:
            assert t.length_m == pytest.approx(ref, rel=1e-9)
            check_path(t, passable, s, g)


@pytest.mark.parametrize("seed", range(5))
def test_ra_star_with_omega_one_is_optimal(seed):
    surface, ridge, passable = obstacle_map((35, 40), seed, density=0.2)
    s, g = endpoints(passable, seed)
    ref = reference_length(surface, passable, 30.0, s, g)
    if not np.isfinite(ref):
        return
    t = pipeline.plan_window(
        surface, ridge, passable, s, g, cell_size=30.0, planner="ra_star", omega=1.0
    )
    assert t.length_m == pytest.approx(ref, rel=1e-9)
    check_path(t, passable, s, g)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    omega=st.floats(1.0, 4.0),
    density=st.floats(0.0, 0.35),
    ridge_share=st.floats(0.05, 0.6),
)
def test_ra_star_bound_validity_and_lower_bound(seed, omega, density, ridge_share):
    mission = random_mission(seed, density, ridge_share)
    if mission is None:
        return
    surface, ridge, passable, s, g, ref = mission
    t = pipeline.plan_window(
        surface, ridge, passable, s, g, cell_size=30.0, planner="ra_star", omega=omega
    )
    check_path(t, passable, s, g)  # simple, continuous, passable, no corner cutting
    assert t.length_m <= omega * ref * (1 + 1e-9)
    assert t.lower_bound_m <= ref * (1 + 1e-9)
    length, ridge_len = independent_metrics(t, surface, ridge, 30.0)
    assert t.length_m == pytest.approx(length, rel=1e-12)
    assert t.ridge_length_m == pytest.approx(ridge_len, rel=1e-12)
    again = pipeline.plan_window(
        surface, ridge, passable, s, g, cell_size=30.0, planner="ra_star", omega=omega
    )
    np.testing.assert_array_equal(again.cells, t.cells)


def test_ra_star_heads_for_the_goal_between_ridge_cells():
    """Among admissible states of equal ``Nor`` the ridge search takes the least
    ``g_incons + h`` (docs/method.md section 5): on flat ground with no ridge it walks the
    straight row to the goal, about one expansion a cell. Taking the least ``g_incons``
    instead floods every state closer than the goal, as Dijkstra does (6965 here)."""
    rows, cols = 61, 121
    surface = np.zeros((rows, cols))
    ridge = np.zeros((rows, cols), bool)
    passable = np.ones((rows, cols), bool)
    s, g = (30, 0), (30, cols - 1)
    t = pipeline.plan_window(
        surface, ridge, passable, s, g, cell_size=30.0, planner="ra_star", omega=2.0
    )
    assert t.length_m == pytest.approx(30.0 * (cols - 1), rel=1e-12)
    assert (t.cells[:, 0] == 30).all()
    assert t.expansions <= 2 * cols


def test_ridge_following_ranks_lagrangian_ra_star_astar_on_average():
    ratios = {"astar": [], "ra_star": [], "lagrangian": []}
    for seed in range(12):
        surface, _, passable = obstacle_map((40, 40), seed, density=0.1)
        ridge = np.zeros(surface.shape, bool)
        ridge[::6, :] = True  # ridge lines the planner can follow at some extra length
        ridge[:, ::9] = True
        s, g = endpoints(passable, seed)
        if not np.isfinite(reference_length(surface, passable, 30.0, s, g)):
            continue
        for planner in ratios:
            t = pipeline.plan_window(
                surface, ridge, passable, s, g, cell_size=30.0, planner=planner, omega=2.0
            )
            ratios[planner].append(t.ridge_ratio)
    assert len(ratios["astar"]) >= 8
    assert np.mean(ratios["ra_star"]) >= np.mean(ratios["astar"])
    assert np.mean(ratios["ra_star"]) > 0.4
    assert np.mean(ratios["lagrangian"]) >= np.mean(ratios["ra_star"])


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    omega=st.floats(1.0, 4.0),
    density=st.floats(0.0, 0.35),
    ridge_share=st.floats(0.05, 0.6),
)
def test_lagrangian_bound_validity_and_duality(seed, omega, density, ridge_share):
    mission = random_mission(seed, density, ridge_share)
    if mission is None:
        return
    surface, ridge, passable, s, g, ref = mission
    t = pipeline.plan_window(
        surface, ridge, passable, s, g, cell_size=30.0, planner="lagrangian", omega=omega
    )
    check_path(t, passable, s, g)
    assert t.length_m <= omega * ref * (1 + 1e-9)
    assert t.lower_bound_m == pytest.approx(ref, rel=1e-9)  # it computes the optimum
    length, ridge_len = independent_metrics(t, surface, ridge, 30.0)
    assert t.ridge_length_m == pytest.approx(ridge_len, rel=1e-12)
    # weak duality: the dual bound never exceeds the off-ridge length of a feasible path
    assert t.extra["dual_bound_off_ridge_m"] <= (length - ridge_len) * (1 + 1e-9) + 1e-6
    ra = pipeline.plan_window(
        surface, ridge, passable, s, g, cell_size=30.0, planner="ra_star", omega=omega
    )
    assert (
        t.extra["dual_bound_off_ridge_m"] <= (ra.length_m - ra.ridge_length_m) * (1 + 1e-9) + 1e-6
    )


def _weighted_graph(surface, ridge, passable, a, off_weight, horizontal_off=False, diagonal=None):
    """The planners' graph with each move costing its 3-D length plus ``off_weight`` times
    its off-ridge length (the move ends off the ridge network); ``horizontal_off``: the cost
    is only the horizontal length of the moves that end off the ridge, a diagonal counted as
    ``diagonal`` cells (default sqrt 2)."""
    g = reference_graph(surface, passable, a).tocoo()
    rows, cols = surface.shape
    end_off = ~ridge.ravel()[g.col]
    if horizontal_off:
        d = np.abs(np.divmod(g.row, cols)[0] - np.divmod(g.col, cols)[0]) + np.abs(
            g.row % cols - g.col % cols
        )
        diag = math.sqrt(2.0) if diagonal is None else diagonal
        w = np.where(end_off, a * np.where(d == 2, diag, 1.0), 0.0)
    else:
        w = g.data * (1.0 + off_weight * end_off)
    return coo_matrix((w, (g.row, g.col)), shape=g.shape).tocsr()


def test_lagrangian_at_omega_one_takes_the_most_ridge_among_shortest_paths():
    """On flat ground many paths share the shortest length; at omega 1 the Lagrangian planner
    takes the one with the least off-ridge length among them (its weighted searches find it:
    a shortcut that returned A*'s path at omega 1 would not), which is scipy's Dijkstra on
    length plus 1e-6 x off-ridge length (a longer path is longer by more than the weight
    could ever trade). A* itself finds it on few of these missions."""
    rng = np.random.default_rng(0)
    a_off_more = 0
    for _ in range(12):
        n = 30
        flat = np.full((n, n), -1000.0)
        ok = np.ones((n, n), bool)
        ridge = rng.random((n, n)) < 0.3
        s = (int(rng.integers(0, 5)), int(rng.integers(0, 5)))
        g = (int(rng.integers(20, 30)), int(rng.integers(10, 30)))
        src, dst = s[0] * n + s[1], g[0] * n + g[1]
        shortest = dijkstra(_weighted_graph(flat, ridge, ok, 30.0, 0.0), indices=src)[dst]
        tilted = dijkstra(_weighted_graph(flat, ridge, ok, 30.0, 1e-6), indices=src)[dst]
        least_off = (tilted - shortest) / 1e-6
        kw = dict(cell_size=30.0, omega=1.0)
        lg = pipeline.plan_window(flat, ridge, ok, s, g, planner="lagrangian", **kw)
        a = pipeline.plan_window(flat, ridge, ok, s, g, planner="astar", **kw)
        assert lg.length_m == pytest.approx(shortest, rel=1e-12)
        assert lg.length_m - lg.ridge_length_m == pytest.approx(least_off, abs=1e-4)
        a_off_more += a.length_m - a.ridge_length_m > least_off + 1.0
    assert a_off_more >= 8


@pytest.mark.parametrize("seed", range(6))
def test_lagrangian_takes_the_least_off_ridge_path_without_the_shortest_when_octile_proves_it(
    seed,
):
    """Where the least off-ridge path (length as the tie-break) is within omega times the
    octile distance, a lower bound on L*, it is the answer whatever L* is: the planner then
    searches that path only, not the shortest one, and its answer is scipy's optimum of
    length + 1e7 x off-ridge length; the proven lower bound it reports is still scipy's L*
    (the shortest path searched when asked for, its A* expansions reported apart)."""
    rng = np.random.default_rng(seed)
    surface, _, passable = obstacle_map((30, 36), seed, 0.1)
    ridge = rng.random(surface.shape) < 0.4
    s, g = endpoints(passable, seed)
    ref = reference_length(surface, passable, 30.0, s, g)
    assert np.isfinite(ref)  # connected on these seeds
    cols = surface.shape[1]
    least = dijkstra(
        _weighted_graph(surface, ridge, passable, 30.0, 1e7), indices=s[0] * cols + s[1]
    )
    octile = 30.0 * (
        max(abs(s[0] - g[0]), abs(s[1] - g[1]))
        + (math.sqrt(2) - 1) * min(abs(s[0] - g[0]), abs(s[1] - g[1]))
    )
    t = pipeline.plan_window(
        surface, ridge, passable, s, g, cell_size=30.0, planner="lagrangian", omega=4.0
    )
    check_path(t, passable, s, g)
    length, ridge_len = independent_metrics(t, surface, ridge, 30.0)
    assert length + 1e7 * (length - ridge_len) == pytest.approx(
        least[g[0] * cols + g[1]], rel=1e-12
    )
    assert length <= 4.0 * octile  # these missions are such cases
    assert t.extra["searches"] == 1
    assert t.lower_bound_m == pytest.approx(ref, rel=1e-9)
    shortest = pipeline.plan_window(surface, ridge, passable, s, g, cell_size=30.0, planner="astar")
    assert t.extra["bound_expansions"] == shortest.expansions > 0


@pytest.mark.parametrize("seed", range(4))
def test_off_ridge_bound_and_the_lagrangian_searches_against_scipy(seed):
    """``off_ridge_to_goal`` equals scipy's Dijkstra towards the goal on the graph whose moves
    cost their horizontal length when they end off the ridge (0 on it), a diagonal counted as
    41 / 29 cells, and is at most the distance with diagonals of sqrt 2 (within 0.03 %); given
    the start, it stops there: each cell's bound the smaller of that and the start's. A* with
    either in the heuristic finds scipy's optimum of length + w x off-ridge length, for
    several w, also with the exact lengths to the goal (``goal_layer``, scipy's too)."""
    from pipeline.planners.bounds import OFF_DIAGONAL, OFF_UNITS, off_ridge_to_goal
    from pipeline.planners.lagrangian import goal_layer
    from pipeline.planners.search import astar_search, astar_search_bucketed, search_arrays

    surface, ridge, passable = obstacle_map((30, 34), seed, density=0.15)
    ridge = np.random.default_rng(seed).random(surface.shape) < 0.4
    s, g = endpoints(passable, seed)
    goal = g[0] * surface.shape[1] + g[1]
    # towards the goal: distances from the goal on the transposed graph
    assert (OFF_UNITS, OFF_DIAGONAL) == (29, 41)
    rev = _weighted_graph(
        surface, ridge, passable, 30.0, 0.0, horizontal_off=True, diagonal=41 / 29
    ).T.tocsr()
    want = dijkstra(rev, indices=goal)
    got = off_ridge_to_goal(ridge, passable, 30.0, g[0], g[1], -1, -1)
    np.testing.assert_allclose(got, want, rtol=1e-12)
    # given the start, the search stops there: each bound the smaller of its own and the start's
    start = s[0] * surface.shape[1] + s[1]
    part = off_ridge_to_goal(ridge, passable, 30.0, g[0], g[1], s[0], s[1])
    np.testing.assert_allclose(part, np.minimum(want, want[start]), rtol=1e-12)
    exact = _weighted_graph(surface, ridge, passable, 30.0, 0.0, horizontal_off=True).T.tocsr()
    exact = dijkstra(exact, indices=goal)
    assert np.array_equal(np.isfinite(got), np.isfinite(exact))
    fin = np.isfinite(exact)
    assert (got[fin] <= exact[fin]).all() and (got[fin] >= exact[fin] * (1 - 3e-4)).all()
    assert (got[fin] > 0).sum() > 10  # off-ridge moves were counted
    z = surface.astype(np.float32)  # as a maps store keeps it
    # the exact lengths to the goal, the goal as a landmark (the searches that weigh length
    # more): scipy's Dijkstra towards the goal on the length graph, within float32's rounding
    none = np.zeros((0, 0), np.float32)
    to_goal = goal_layer(none, z, passable, 30.0, g)
    length = _weighted_graph(z.astype(np.float64), ridge, passable, 30.0, 0.0).T.tocsr()
    length = dijkstra(length, indices=goal)
    assert to_goal.shape == (1, z.size)
    assert np.array_equal(np.isfinite(to_goal[0]), np.isfinite(length))
    np.testing.assert_allclose(to_goal[0][np.isfinite(length)], length[np.isfinite(length)], 1e-6)
    assert goal_layer(to_goal, z, passable, 30.0, g).shape == (2, z.size)  # appended
    for w in (0.05, 1.0, 1e7):
        graph = _weighted_graph(z.astype(np.float64), ridge, passable, 30.0, w)
        ref = dijkstra(graph, indices=s[0] * surface.shape[1] + s[1])[goal]
        if not np.isfinite(ref):
            return
        for hoff, lm in ((got, none), (np.zeros(0), none), (got, to_goal), (part, none)):
            for kernel in (astar_search, astar_search_bucketed):
                _, gs, _, found = kernel(
                    z, ridge, passable, 30.0, *s, *g, 1.0, w, True, lm, hoff, *search_arrays(z.size)
                )
                assert found and gs[goal] == pytest.approx(ref, rel=1e-9)


@pytest.mark.parametrize(
    "shape, seed",
    [
        ((30, 34), 0),
        ((30, 34), 1),
        ((41, 23), 2),
        ((1, 17), 3),
        ((13, 1), 4),
        ((2, 2), 5),
        ((3, 40), 6),
        ((25, 19), 7),
    ],
)
def test_lagrangian_bound_against_scipy(shape, seed):
    """``lagrangian_bound``, the weighted searches' heuristic (octile + w x it), against scipy's
    Dijkstra towards the goal: at most the least weighted 3-D cost (length + w x off-ridge
    length) from every cell; consistent on every move of the graph; at least the octile
    distance plus w x the off-ridge bound; where its search settled cells (those at most half
    as far as the start on the horizontal plane), within the rounding of its units of the least
    weighted horizontal cost (scipy on a flat surface); inf where the goal is out of reach. The
    bound of a larger weight, used for this one (the planner does), is one too, and so is the
    bound of a smaller weight raised to this one (``raised_bound``). A* with them finds scipy's
    optimum. Also on windows one cell thin, start and goal anywhere."""
    from pipeline.planners.bounds import lagrangian_bound, off_ridge_to_goal, raised_bound
    from pipeline.planners.search import astar_search, search_arrays

    rng = np.random.default_rng(seed)
    surface = (
        random_surface(shape, seed=seed).astype(np.float64)
        if min(shape) > 2
        else (rng.random(shape) * 200.0)
    )
    passable = rng.random(shape) > 0.15
    ridge = rng.random(shape) < 0.4
    cells = np.argwhere(passable)
    if len(cells) < 2:
        passable[0, 0] = passable[-1, -1] = True
        cells = np.argwhere(passable)
    s, g = endpoints(passable, seed)
    rows, cols = shape
    goal, start = g[0] * cols + g[1], s[0] * cols + s[1]
    rr, cc = np.divmod(np.arange(rows * cols), cols)
    dr, dc = np.abs(rr - g[0]), np.abs(cc - g[1])
    octile = 30.0 * (np.maximum(dr, dc) + (math.sqrt(2.0) - 1.0) * np.minimum(dr, dc))
    hoff = off_ridge_to_goal(ridge, passable, 30.0, *g, -1, -1)
    flat = np.zeros(shape)
    for w in (1.0, 3.0, 50.0, 4e5):
        out = lagrangian_bound(ridge, passable, 30.0, *s, *g, w, hoff)
        bound = octile + w * out
        graph = _weighted_graph(surface, ridge, passable, 30.0, w)
        exact = dijkstra(graph.T.tocsr(), indices=goal)
        assert np.array_equal(np.isfinite(bound), np.isfinite(exact))
        fin = np.isfinite(exact)
        assert (bound[fin] <= exact[fin] * (1 + 1e-12)).all()
        assert (bound[fin] >= octile[fin] + w * hoff[fin] - 1e-9 * exact[fin]).all()
        e = graph.tocoo()  # every move u -> v: h(u) <= cost + h(v)
        both = fin[e.row] & fin[e.col]
        slack = 1e-9 * exact[e.row][both]
        assert (bound[e.row][both] <= e.data[both] + bound[e.col][both] + slack).all()
        horizontal = _weighted_graph(flat, ridge, passable, 30.0, w).T.tocsr()
        horizontal = dijkstra(horizontal, indices=goal)
        if np.isfinite(horizontal[start]):
            near = fin & (horizontal <= 0.5 * horizontal[start])
            # each move's cost in units rounded down: at most one unit a move (a move costs a
            # cell's length, 30 m, at least), the unit a 29th of a cell of length and weight
            # (1 + w) / (400 / 41), 400 units the longest move
            moves = horizontal[near] / 30.0
            unit = 30.0 * 41 * (1 + w) / (29 * 400)
            assert (bound[near] >= horizontal[near] * (1 - 3e-4) - moves * unit).all()
        # the bound of a larger weight serves this one too (the planner's reuse), and that of
        # a smaller one raised to this one (raised_bound), at least the octile distance plus
        # w x the off-ridge bound
        raised = raised_bound(
            lagrangian_bound(ridge, passable, 30.0, *s, *g, w / 3, hoff),
            hoff,
            w / 3,
            w,
            *shape,
            *g,
            30.0,
        )
        assert (octile + w * raised >= octile + w * hoff - 1e-9 * np.nan_to_num(exact)).all()
        for other in (lagrangian_bound(ridge, passable, 30.0, *s, *g, 4 * w, hoff), raised):
            bound = octile + w * other
            assert (bound[fin] <= exact[fin] * (1 + 1e-12)).all()
            assert (bound[e.row][both] <= e.data[both] + bound[e.col][both] + slack).all()
        out = np.maximum(out, lagrangian_bound(ridge, passable, 30.0, *s, *g, 4 * w, hoff))
        ref = dijkstra(graph, indices=start)[goal]
        for h in (out, raised):
            _, gs, _, found = astar_search(
                surface,
                ridge,
                passable,
                30.0,
                *s,
                *g,
                1.0,
                w,
                True,
                np.zeros((0, 0), np.float32),
                h,
                *search_arrays(surface.size),
            )
            assert found == bool(np.isfinite(ref))
            if found:
                assert gs[goal] == pytest.approx(ref, rel=1e-9)


def test_the_lagrangian_planner_takes_its_joint_bound_on_gentle_ground_only(monkeypatch):
    """The weighted searches take ``lagrangian_bound`` (a bound on the horizontal plane) where
    the shortest path's 3-D length exceeds its horizontal length by at most ``BOUND_SLACK``,
    and not on steep ground, where it costs more than it saves; the paths are scipy-optimal
    for their weights either way (the test above), and equal to those without it here."""
    from pipeline.planners import lagrangian

    calls = []
    real = lagrangian.lagrangian_bound

    def counted(*args):
        calls.append(args[7])
        return real(*args)

    rng = np.random.default_rng(1)
    shape = (60, 60)
    passable = rng.random(shape) > 0.2
    ridge = rng.random(shape) < 0.5
    s, g = (2, 2), (57, 55)
    passable[s] = passable[g] = True
    gentle = np.full(shape, -1000.0)  # flat: no slack at all
    steep = gentle + np.random.default_rng(2).random(shape) * 60.0  # 30 m cells, steps to 60 m
    got = {}
    for name, surface in (("gentle", gentle), ("steep", steep)):
        for use in (True, False):
            calls.clear()
            monkeypatch.setattr(lagrangian, "BOUND_SLACK", 0.05 if use else -1.0)
            monkeypatch.setattr(lagrangian, "lagrangian_bound", counted)
            t = pipeline.plan_window(
                surface, ridge, passable, s, g, cell_size=30.0, planner="lagrangian", omega=1.3
            )
            got[name, use] = (t.length_m, t.ridge_length_m, len(calls), t.extra["searches"])
    assert got["gentle", True][2] > 0 and got["gentle", True][3] > 2  # weighted searches ran
    assert got["steep", True][2] == 0 and got["steep", False][2] == 0
    assert got["gentle", False][2] == 0
    for name in ("gentle", "steep"):
        assert got[name, True][:2] == pytest.approx(got[name, False][:2], rel=1e-9)


@pytest.mark.parametrize("shape", [(1, 17), (13, 1), (1, 1), (2, 2), (3, 40), (25, 19)])
def test_off_ridge_bound_on_thin_windows_and_goals_at_the_edge(shape):
    """``off_ridge_to_goal`` against scipy's Dijkstra (as above) on windows one cell thin and
    with the goal in every corner and at the middle of every side: its search runs on the
    window framed by cells it may not enter, which must neither be entered nor block a move
    along the edge."""
    from pipeline.planners.bounds import off_ridge_to_goal

    rows, cols = shape
    rng = np.random.default_rng(rows * 100 + cols)
    surface = np.zeros(shape)
    passable = rng.random(shape) > 0.15
    ridge = rng.random(shape) < 0.4
    goals = {(r, c) for r in (0, rows // 2, rows - 1) for c in (0, cols // 2, cols - 1)}
    goals = sorted((r, c) for r, c in goals if r in (0, rows - 1) or c in (0, cols - 1))
    for g in goals:
        passable[g] = True
    rev = _weighted_graph(
        surface, ridge, passable, 30.0, 0.0, horizontal_off=True, diagonal=41 / 29
    ).T.tocsr()
    for g in goals:
        want = dijkstra(rev, indices=g[0] * cols + g[1])
        got = off_ridge_to_goal(ridge, passable, 30.0, g[0], g[1], -1, -1)
        assert got.shape == (rows * cols,)
        np.testing.assert_allclose(got, want, rtol=1e-12)
        assert np.isinf(got[~passable.ravel()]).all()
        for s in goals:  # stopped at a start: the smaller of each cell's bound and the start's
            part = off_ridge_to_goal(ridge, passable, 30.0, g[0], g[1], s[0], s[1])
            np.testing.assert_allclose(part, np.minimum(want, want[s[0] * cols + s[1]]), 1e-12)


@pytest.mark.parametrize("n", [0, 1, 2, 3, 257])
def test_path_steps_are_the_3d_lengths_bit_for_bit(n):
    """Every step's length against the formula evaluated by Python's own floats, step by step
    (sqrt(a a (dr dr + dc dc) + dz dz) with dz in double precision; ``x ** 2`` is C's pow,
    which may differ from ``x * x`` in the last bit): equal to the last bit, for
    float32 and float64 heights, integer cells of either width, several cell sizes."""
    from pipeline.planners.paths import path_steps

    rng = np.random.default_rng(n)
    cells = np.cumsum(rng.integers(-2, 3, (n, 2)), axis=0)
    for z in (rng.normal(-2000, 300, n).astype(np.float32), rng.normal(-2000, 300, n)):
        for a in (30.0, 1.0 / 3, 92.6):
            for dtype in (np.int64, np.int32):
                got = path_steps(cells.astype(dtype), z, a)
                want = []
                for (r0, c0), (r1, c1), z0, z1 in zip(
                    cells[:-1], cells[1:], z[:-1], z[1:], strict=True
                ):
                    dr, dc, dz = int(r1) - int(r0), int(c1) - int(c0), float(z1) - float(z0)
                    want.append(math.sqrt(a * a * float(dr * dr + dc * dc) + dz * dz))
                assert got.dtype == np.float64 and got.tolist() == want, (n, a, dtype)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_a_traced_path_and_its_metrics_equal_the_step_by_step_ones(dtype):
    """traced_path (a section's path, heights, ridge flags and metrics in one kernel pass)
    against the path read from the parent moves one by one in Python and measured with Python
    floats, each sum taken by numpy over the same steps: the same cells (offset), heights and
    flags, the lengths bit for bit."""
    from pipeline.planners.grid import DC, DR
    from pipeline.planners.paths import traced_path
    from pipeline.planners.registry import PLANNERS
    from pipeline.planners.search import PARENT

    surface = (random_surface((40, 50), seed=11) * 600 - 2000).astype(dtype)
    r, o = random_surface((40, 50), seed=12), random_surface((40, 50), seed=13)
    ridge, passable = r > np.quantile(r, 0.6), o > np.quantile(o, 0.2)
    cells_ok = np.argwhere(passable)
    rng = np.random.default_rng(4)
    done = 0
    for _ in range(20):
        s, t = (tuple(int(v) for v in cells_ok[i]) for i in rng.integers(len(cells_ok), size=2))
        search = PLANNERS["astar"].search(surface, ridge, passable, 30.0, s, t, 1.0, None)
        if not search.found:
            continue
        done += 1
        path, (r, c) = [], t
        while True:  # the parent moves back to the start, in Python
            path.append((r, c))
            code = int(search.state[r * 50 + c])
            if not code & PARENT:
                break
            r, c = r - int(DR[code & 7]), c - int(DC[code & 7])
        path = path[::-1]
        assert path[0] == s
        steps = [
            math.sqrt(900.0 * ((r1 - r0) ** 2 + (c1 - c0) ** 2) + (z1 - z0) ** 2)
            for (r0, c0), (r1, c1) in zip(path[:-1], path[1:], strict=True)
            for z0, z1 in [(float(surface[r0, c0]), float(surface[r1, c1]))]
        ]
        on = [bool(ridge[r, c]) for r, c in path]
        cells, z, flags, length, ridge_len, ratio = traced_path(
            search.state, 50, t, surface, ridge, 30.0, (100, 7)
        )
        assert cells.tolist() == [[r + 100, c + 7] for r, c in path]
        assert z.dtype == np.float64 and z.tolist() == [float(surface[p]) for p in path]
        assert flags.tolist() == on
        assert length == float(np.array(steps).sum())
        want_ridge = float(np.array([x for x, o in zip(steps, on[1:], strict=True) if o]).sum())
        assert ridge_len == want_ridge
        assert ratio == (want_ridge / length if length > 0 else 0.0)
    assert done >= 10
