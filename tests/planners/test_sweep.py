"""The exact search of large windows by row sweeps (``pipeline.planners.sweep``): its region
against a brute-force evaluation, its lengths against scipy's Dijkstra on the graph built in
``test_planners`` (awkward shapes, obstacles, mazes that turn back many times, detours that
grow the region, no path), its paths checked move by move, its budget handing over to A*, and
the ``astar`` planner taking it on a window from ``SWEEP_CELLS`` cells."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import assert_lower_layer, quantisation_error_bound, random_surface
from references import (
    cell_metrics,
    check_cells,
    check_path,
    independent_metrics,
    reference_distances,
)
from scipy import ndimage
from test_planners import obstacle_map

import pipeline
from pipeline.planners import astar, sweep

A = 30.0


def octile(s, g):
    dr, dc = abs(s[0] - g[0]), abs(s[1] - g[1])
    return A * (max(dr, dc) + (math.sqrt(2) - 1) * min(dr, dc))


def solve_and_check(surface, passable, s, g):
    """sweep.search against scipy's Dijkstra; returns its extra. The surface is searched as a
    maps store's windows hold it, float32 (the type the kernels are compiled for before the
    tests; float64 would compile the sweeps again, about 20 s of a core); scipy's graph takes
    the same heights as float64."""
    surface = np.asarray(surface, dtype=np.float32)
    ref = float(
        reference_distances(surface.astype(np.float64), passable, A, s)[
            g[0] * surface.shape[1] + g[1]
        ]
    )
    got = sweep.search(surface, passable, A, s, g)
    assert got is not None
    cells, relaxed, extra = got
    if not np.isfinite(ref):
        assert len(cells) == 0
        assert extra["region_cells"] == surface.size  # grown to the whole map to prove it
        return extra
    check_cells(cells, passable, s, g)
    assert cell_metrics(cells, surface, passable, A)[0] == pytest.approx(ref, rel=1e-12)
    assert relaxed >= 1
    return extra


def oct_to(ii, jj, p):
    dr, dc = np.abs(ii - p[0]), np.abs(jj - p[1])
    return A * (np.maximum(dr, dc) + (math.sqrt(2) - 1) * np.minimum(dr, dc))


@pytest.mark.parametrize("seed", range(3))
def test_region_rows_against_brute_force(seed):
    """Per row, the interval equals the cells where oct(s, v) + oct(v, g) <= bound, evaluated
    for every cell with numpy, on shapes with one row or one column too."""
    rng = np.random.default_rng(seed)
    for shape in [(1, 40), (40, 1), (37, 53), (64, 17)]:
        rows, cols = shape
        ii, jj = np.mgrid[0:rows, 0:cols]
        for _ in range(8):
            s = (int(rng.integers(rows)), int(rng.integers(cols)))
            g = (int(rng.integers(rows)), int(rng.integers(cols)))
            bound = octile(s, g) * (1 + rng.choice([0.0, 0.01, 0.2, 3.0])) + rng.random() * A

            inside = oct_to(ii, jj, s) + oct_to(ii, jj, g) <= bound
            lo, hi = sweep.region_rows(rows, cols, A, *s, *g, bound)
            got = (jj >= lo[:, None]) & (jj <= hi[:, None])
            np.testing.assert_array_equal(got, inside)


def brute_relax_row(surface, ok, d_p, d_i, lo, hi, i, p):
    """Row i after a pull from row p (none: ``p`` None) and the closure along row i, cell by
    cell in Python: ``d_p``, ``d_i`` the rows' distances over all columns (inf outside their
    spans)."""
    cols = surface.shape[1]

    def move(r0, c0, r1, c1):
        dz = float(surface[r1, c1]) - float(surface[r0, c0])
        return math.sqrt(A * A * ((r1 - r0) ** 2 + (c1 - c0) ** 2) + dz * dz)

    new = d_i.copy()
    for j in range(lo[i], hi[i] + 1):
        if not ok[i, j] or p is None:
            continue
        for dc in (-1, 0, 1):
            u = j + dc
            if not (lo[p] <= u <= hi[p] and 0 <= u < cols and ok[p, u]):
                continue
            if dc and not (ok[p, j] and ok[i, u]):
                continue
            new[j] = min(new[j], d_p[u] + move(p, u, i, j))
    while True:  # along the row until nothing falls
        before = new.copy()
        for j in range(lo[i], hi[i] + 1):
            for u in (j - 1, j + 1):
                if lo[i] <= u <= hi[i] and ok[i, j] and ok[i, u]:
                    new[j] = min(new[j], new[u] + move(i, u, i, j))
        if np.array_equal(before, new):
            return new


@pytest.mark.parametrize("seed", range(4))
def test_a_row_relaxation_lowers_every_cell_a_move_can_lower(seed):
    """One row pulled from the row above or below it (``_relax_row``) against the same pull
    and the closure along the row in Python: distances spread within a few cell lengths of
    each other (so many moves fall just below or just above a cell's value, where the pull's
    filter decides), spans that overlap partly, impassable cells. Row i starts closed along
    itself, as the sweeps keep every row."""
    rng = np.random.default_rng(seed)
    cols = 30
    for _ in range(150):
        surface = (rng.random((2, cols)) * rng.choice([0.0, 5.0, 60.0])).astype(np.float32)
        ok = rng.random((2, cols)) > rng.choice([0.0, 0.2])
        lo = rng.integers(0, 8, 2)
        hi = cols - 1 - rng.integers(0, 8, 2)
        i, p = (1, 0) if rng.random() < 0.5 else (0, 1)
        full = np.full((2, cols), np.inf)
        for r in (0, 1):
            span = slice(lo[r], hi[r] + 1)
            full[r, span] = 1000.0 + rng.random(hi[r] - lo[r] + 1) * 4 * A
            full[r, span][rng.random(hi[r] - lo[r] + 1) < 0.2] = np.inf
        full[~ok] = np.inf
        full[i] = brute_relax_row(surface, ok, None, full[i], lo, hi, i, None)
        off = np.array([0, hi[0] - lo[0] + 1, hi[0] - lo[0] + hi[1] - lo[1] + 2])
        d = np.concatenate([full[0, lo[0] : hi[0] + 1], full[1, lo[1] : hi[1] + 1]])
        want = brute_relax_row(surface, ok, full[p], full[i], lo, hi, i, p)
        scratch = np.empty((9, cols + 2))
        _, fell = sweep._relax_row(surface, ok, A, sweep.METRES, i, p, lo, hi, off, d, scratch)
        got = d[off[i] : off[i + 1]]
        np.testing.assert_allclose(got, want[lo[i] : hi[i] + 1], rtol=1e-15)
        assert fell == bool((want < full[i]).any())


@pytest.mark.parametrize("seed", range(8))
def test_lengths_against_scipy_on_awkward_shapes(seed):
    """Random relief and obstacles (0-40 % of the cells) on maps of one row, one column, two
    rows and odd sizes; a few endpoints each, some with no path between them."""
    shapes = [(1, 60), (60, 1), (2, 45), (41, 37), (23, 70), (70, 23), (50, 50), (3, 3)]
    shape = shapes[seed]
    surface, _, passable = obstacle_map(shape, seed, density=0.05 * seed)
    rng = np.random.default_rng(seed)
    cells = np.argwhere(passable)
    for _ in range(4):
        s, g = (tuple(cells[k]) for k in rng.choice(len(cells), 2))
        solve_and_check(surface, passable, s, g)


def test_start_is_goal_and_neighbours():
    surface, _, passable = obstacle_map((20, 20), 1, density=0.0)
    surface = surface.astype(np.float32)  # as solve_and_check searches it (the compiled type)
    cells, _, extra = sweep.search(surface, passable, A, (5, 5), (5, 5))
    assert cells.tolist() == [[5, 5]] and extra["rounds"] == 1
    for g in [(5, 6), (6, 6), (4, 5), (4, 4)]:
        solve_and_check(surface, passable, (5, 5), g)


def maze(rows: int, walls: int, gap: int = 2):
    """Vertical walls every second column from column 1, open alternately at the bottom and at
    the top: the only path from the left to the right turns back ``walls`` times."""
    cols = 2 * walls + 1
    passable = np.ones((rows, cols), bool)
    for k in range(walls):
        c = 2 * k + 1
        passable[:, c] = False
        if k % 2 == 0:
            passable[rows - gap :, c] = True
        else:
            passable[:gap, c] = True
    surface = random_surface((rows, cols), seed=walls).astype(np.float32)
    return surface, passable


def test_a_maze_that_turns_back_needs_a_sweep_a_turn_and_stays_exact():
    """Each corridor of the maze runs against the last, so each needs a sweep of its own; the
    octile distance is far below the path, so the region grows to hold it."""
    surface, passable = maze(30, 12)
    extra = solve_and_check(surface, passable, (0, 0), (0, 24))
    assert extra["sweeps"] >= 12
    assert extra["rounds"] >= 2


def test_no_cell_leaves_a_nan_behind():
    """No-data heights (NaN) under impassable cells never enter a distance."""
    surface, _, passable = obstacle_map((40, 40), 3, density=0.3)
    surface[~passable] = np.nan
    cells = np.argwhere(passable)
    solve_and_check(surface, passable, tuple(cells[0]), tuple(cells[-1]))


def test_a_wall_across_the_straight_line_grows_the_region_to_the_detour():
    """A wall with one gap near its end: the optimum is far above the first bound, so a
    second round (the region of the path found) proves it."""
    rows, cols = 60, 80
    surface = random_surface((rows, cols), seed=4).astype(np.float32)
    passable = np.ones((rows, cols), bool)
    passable[:, 40] = False
    passable[-3:, 40] = True
    extra = solve_and_check(surface, passable, (30, 2), (30, 77))
    assert extra["rounds"] >= 2


def test_a_maze_past_the_budget_goes_to_astar(monkeypatch):
    """More turns than MAX_SWEEPS: the sweeps give up (None), and the planner's A* finds the
    optimum instead, on a window the planner would sweep."""
    surface, passable = maze(20, sweep.MAX_SWEEPS + 6)
    s, g = (0, 0), (0, passable.shape[1] - 1)
    assert sweep.search(surface, passable, A, s, g) is None
    monkeypatch.setattr(astar, "SWEEP_CELLS", 1)
    t = pipeline.plan_window(surface, passable, passable, s, g, cell_size=A, planner="astar")
    ref = float(reference_distances(surface.astype(np.float64), passable, A, s)[g[1]])
    assert t.length_m == pytest.approx(ref, rel=1e-9)
    assert "engine" not in t.extra
    check_path(t, passable, s, g)


def test_the_astar_planner_sweeps_a_large_window_exactly():
    """A 300 x 300 window (over SWEEP_CELLS cells) with relief and 10 % obstacles, corner to
    corner and across: the planner's path (its engine the sweeps) is scipy's optimum, its bound
    the same, its metrics those measured step by step."""
    assert 300 * 300 >= astar.SWEEP_CELLS
    surface, ridge, passable = obstacle_map((300, 300), 21, density=0.1)
    surface = surface.astype(np.float32)  # a maps store's type (see solve_and_check)
    cells = np.argwhere(passable)
    s = tuple(cells[0])
    d = reference_distances(surface.astype(np.float64), passable, A, s)
    for g in [tuple(cells[-1]), tuple(cells[len(cells) // 2]), tuple(cells[297])]:
        ref = float(d[g[0] * 300 + g[1]])
        t = pipeline.plan_window(surface, ridge, passable, s, g, cell_size=A, planner="astar")
        assert t.extra["engine"] == "sweep"
        assert t.length_m == pytest.approx(ref, rel=1e-12)
        assert ref * (1 - 1e-9) <= t.lower_bound_m <= ref * (1 + 1e-12)
        check_path(t, passable, s, g)
        length, ridge_len = independent_metrics(t, surface, ridge, A)
        assert t.length_m == pytest.approx(length, rel=1e-12)
        assert t.ridge_length_m == pytest.approx(ridge_len, rel=1e-12)


def test_the_astar_planner_takes_astar_on_flat_ground_exactly():
    """On a flat window (over SWEEP_CELLS cells, with obstacles) the planner runs A*, which
    follows the straight line there, not the sweeps: scipy's optimum all the same.
    ``flat_between`` against numpy: one height over the passable cells of the region, whatever
    lies under the obstacles (a region along the first row, which the last column ends)."""
    rng = np.random.default_rng(5)
    passable = ~ndimage.binary_dilation(rng.random((300, 300)) < 0.002, iterations=4)
    surface = np.full(passable.shape, -2500.0, np.float32)
    surface[~passable] = rng.random(int((~passable).sum())) * 100  # under land: not looked at
    cells = np.argwhere(passable)
    s = tuple(cells[0])
    d = reference_distances(surface.astype(np.float64), passable, A, s)
    for g in [tuple(cells[-1]), tuple(cells[len(cells) // 3])]:
        t = pipeline.plan_window(surface, passable, passable, s, g, cell_size=A, planner="astar")
        assert "engine" not in t.extra  # A*
        assert t.length_m == pytest.approx(float(d[g[0] * 300 + g[1]]), rel=1e-12)
        check_path(t, passable, s, g)
    ii, jj = np.mgrid[0:300, 0:300]
    a, b = (0, 0), (0, 299)
    region = oct_to(ii, jj, a) + oct_to(ii, jj, b) <= octile(a, b) * (1 + sweep.SLACK)
    assert region[:, 299].any()
    for z, ok in [
        (surface, passable),
        (surface, np.ones_like(passable)),
        (np.where(np.arange(300) == 299, np.float32(1.0), surface), passable),  # last column
        (surface, np.zeros_like(passable)),
    ]:
        want = np.unique(z[region & ok]).size <= 1
        assert sweep.flat_between(z, ok, A, a, b) == want


def test_the_planner_decides_on_the_ground_between_the_two_ends():
    """``flat_between``: one height over the passable cells of the sweeps' first region between
    two cells (those with ``oct(s, v) + oct(v, g) <= (1 + SLACK) oct(s, g)``, here by numpy),
    whatever lies outside it; the ``astar`` planner takes A* where that ground is flat and the
    sweeps where it is not, scipy's optimum either way."""
    rng = np.random.default_rng(9)
    n = 300
    passable = ~ndimage.binary_dilation(rng.random((n, n)) < 0.002, iterations=3)
    ii, jj = np.mgrid[0:n, 0:n]
    s, g = (40, 30), (260, 250)
    passable[s], passable[g] = True, True
    region = oct_to(ii, jj, s) + oct_to(ii, jj, g) <= octile(s, g) * (1 + sweep.SLACK)
    surface = np.full((n, n), -2500.0, np.float32)
    surface[~region] = -2500.0 + rng.random(int((~region).sum())) * 50  # relief outside only
    hilly = surface + np.float32(0.0)
    inside = np.argwhere(region & passable)
    hilly[tuple(inside[len(inside) // 2])] = -2400.0  # one cell inside the region
    for z, want in ((surface, True), (hilly, False)):
        assert sweep.flat_between(z, passable, A, s, g) == want
        assert want == (np.unique(z[region & passable]).size <= 1)
        assert np.unique(z[passable]).size > 1  # relief outside the region
        t = pipeline.plan_window(z, passable, passable, s, g, cell_size=A, planner="astar")
        assert ("engine" in t.extra) == (not want)  # the sweeps name themselves
        ref = reference_distances(z.astype(np.float64), passable, A, s)[g[0] * n + g[1]]
        assert t.length_m == pytest.approx(float(ref), rel=1e-12)
        check_path(t, passable, s, g)


@pytest.mark.parametrize("seed", range(6))
def test_distances_to_every_cell_equal_dijkstra_bit_for_bit(seed):
    """The whole map as the region (a landmark's layer): the same float64 values as the bucket
    Dijkstra of ``pipeline.maps.landmarks``, bit for bit, and scipy's to rounding, on awkward shapes
    with islands (one row, one column, odd sizes) and in a maze that turns back 8 times."""
    from pipeline.maps import landmarks as lm

    if seed == 5:
        surface, passable = maze(60, 8)
    else:
        shape = [(1, 70), (70, 1), (41, 37), (64, 97), (120, 80)][seed]
        surface, _, passable = obstacle_map(shape, seed, density=0.08 * seed)
    z = surface.astype(np.float32)
    rng = np.random.default_rng(seed)
    cells = np.argwhere(passable)
    for k in rng.choice(len(cells), 3):
        src = tuple(int(v) for v in cells[k])
        got = sweep.distances(z, passable, A, src)
        assert got is not None
        want = lm.dijkstra(z, passable, A, np.array([src[0] * z.shape[1] + src[1]]))
        np.testing.assert_array_equal(got, want)
        ref = reference_distances(z.astype(np.float64), passable, A, src).reshape(z.shape)
        np.testing.assert_allclose(got, ref, rtol=1e-12)


def test_a_layer_past_the_budget_comes_from_dijkstra(monkeypatch):
    """With the sweeps' budget cut below one relaxation a cell, a landmark's layer is
    Dijkstra's, and still scipy's distances, less at most a unit and the quantised heights'
    errors a move (``quantisation_error_bound``)."""
    from pipeline.maps import landmarks as lm

    surface, _, passable = obstacle_map((50, 60), 7, density=0.2)
    z = surface.astype(np.float32)
    src = tuple(int(v) for v in np.argwhere(passable)[10])
    monkeypatch.setattr(sweep, "BUDGET", 0.01)
    assert sweep.distances(z, passable, A, src) is None
    ref = reference_distances(z.astype(np.float64), passable, A, src).reshape(z.shape)
    d, unit = lm.layer_distances(z, passable, A, src)
    err = quantisation_error_bound(z, passable, 1 << lm.QUANT_SHIFT)
    assert_lower_layer(lm.layer_values(d, unit), ref, (unit + 2 * err) / A)


@pytest.mark.parametrize(
    "seed, bits", [(0, 16), (1, 18), (2, 24), (3, 20), (4, 26), (5, 16), (6, 29)]
)
def test_fixed_point_distances_lie_less_than_a_unit_a_move_below_scipys(seed, bits):
    """The landmark layers' distances (``fixed_point_distances``: whole units of ``A 2^-bits``,
    each move's cost rounded down, values held at ``FIXED_CAP``) on the quantised surface the
    layers' task holds (``landmarks.quantised``): never above scipy's shortest distances, less
    than one unit and the two cells' height errors (``quantisation_error_bound``) a move below
    them (every move is at least ``A`` long: a relative ``2^-bits + 2 err / A``), the capped
    ones at the cap, not reached exactly where scipy's are inf (also past the cap, which the
    two finest units reach on these maps). Awkward shapes, obstacles, a maze."""
    from pipeline.maps import landmarks as lm

    if seed == 5:
        surface, passable = maze(60, 8)
    else:
        shape = [(1, 70), (70, 1), (41, 37), (64, 97), (120, 80), None, (90, 60)][seed]
        surface, _, passable = obstacle_map(shape, seed, density=0.05 * seed)
    z = surface.astype(np.float32)
    q = lm.quantised(z, passable)
    err = quantisation_error_bound(z, passable, 1 << lm.QUANT_SHIFT)
    unit, cap = A * 2.0**-bits, sweep.FIXED_CAP
    rng = np.random.default_rng(seed)
    cells = np.argwhere(passable)
    for k in rng.choice(len(cells), 3):
        src = tuple(int(v) for v in cells[k])
        got = sweep.fixed_point_distances(q, q, A, src, bits)
        assert got is not None and got.dtype == np.uint32
        ref = reference_distances(z.astype(np.float64), passable, A, src).reshape(z.shape)
        fin = np.isfinite(ref)
        np.testing.assert_array_equal(got != sweep.FIXED_UNREACHED, fin)
        units = got[fin].astype(np.float64)
        exact = ref[fin] / unit  # scipy's distances in units
        assert (units <= np.minimum(exact * (1 + 1e-12), cap)).all()
        low = exact * (1 - 2.0**-bits - 2 * err / A) - 1e-6
        assert (units >= np.minimum(low, cap)).all()
        assert (units == cap).any() == (exact >= cap).any()
