"""MCPC (docs/method.md section 6): Algorithm 3 against hand-worked examples, stitched
trajectories on a real Zarr maps store, the fallbacks, and the same result on the synchronous
scheduler, the default LocalCluster and real `dask scheduler` / `dask worker` processes on
loopback."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest
from conftest import metric_dataarray, random_surface
from references import (
    MISSION,
    RING,
    SMALL,
    WALL_END,
    WALL_ROW,
    check_path,
    independent_metrics,
    reference_length,
    wall_dem,
)

import pipeline
from pipeline.exceptions import InvalidParameterError
from pipeline.mcpc.algorithm import remove_loops, restore, segment
from pipeline.mcpc.runners import Section, plan_sections

A = 30.0


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    path = tmp_path_factory.mktemp("mcpc") / "maps.zarr"
    import dask

    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(wall_dem(), path, clearance=60.0, min_accumulation=8)
    return path


@pytest.fixture(scope="module")
def arrays(store):
    ds = pipeline.open_maps(store)
    return {k: ds[k].values for k in ("safety", "ridge", "passable")}


# ------------------------------------------------------------------ Algorithm 3 by hand


def test_segment_straight_row_by_hand():
    pts = np.array([(0, 0), (0, 10), (0, 20), (0, 30), (0, 40), (0, 50)])
    # side 20 reached at (0, 20): a 21 x 21 square centred on (0, 10), clipped at row 0
    assert segment(pts, 20, 0, (100, 100)) == [
        (0, 2, (0, 11, 0, 21)),
        (2, 4, (0, 11, 20, 41)),
        (4, 5, (0, 6, 40, 51)),
    ]


def test_segment_doubling_back_by_hand():
    pts = np.array([(50, 50), (50, 60), (50, 55), (50, 45), (50, 70), (52, 72)])
    # the box grows to cols 45..70 (side 25 >= 20) only at the 5th point; square of side 25
    # centred on (50, 57.5): rows 37..62, cols 45..70, then margin 2
    assert segment(pts, 20, 2, (100, 100)) == [(0, 4, (35, 65, 43, 73)), (4, 5, (48, 55, 68, 75))]


def test_segment_clipped_by_the_map_edge_by_hand():
    pts = np.array([(2, 97), (10, 99), (30, 99)])
    # box rows 2..30, cols 97..99, side 28: cols 84..112 + margin 3 -> clipped to 81..100
    assert segment(pts, 25, 3, (40, 100)) == [(0, 2, (0, 34, 81, 100))]


def test_segment_follows_the_rule_on_random_paths():
    """On 500 random walks: each section ends at the first point whose bounding box with the
    section's earlier points has a side of at least the section size (or at the path's end),
    the next starts there, and its window is the square of the SPEC centred on that box, grown
    by the margin and clipped (written out here point by point)."""
    rng = np.random.default_rng(7)
    for _ in range(500):
        n = int(rng.integers(1, 200))
        pts = np.cumsum(rng.integers(-2, 3, size=(n, 2)), axis=0) + rng.integers(0, 60, size=2)
        size, margin = int(rng.integers(1, 30)), int(rng.integers(0, 8))
        shape = (int(rng.integers(1, 90)), int(rng.integers(1, 90)))
        want, i0 = [], 0
        while i0 < n - 1:
            i1 = i0 + 1
            while i1 < n - 1 and np.ptp(pts[i0 : i1 + 1], axis=0).max() < size:
                i1 += 1
            lo, hi = pts[i0 : i1 + 1].min(axis=0), pts[i0 : i1 + 1].max(axis=0)
            side = int((hi - lo).max())
            start = [math.floor((lo[d] + hi[d] - side) / 2) - margin for d in (0, 1)]
            win = []
            for d in (0, 1):
                a, b = min(start[d], lo[d]), max(start[d] + side + 2 * margin + 1, hi[d] + 1)
                win += [max(int(a), 0), min(int(b), shape[d])]
            want.append((i0, i1, tuple(win)))
            i0 = i1
        assert segment(pts, size, margin, shape) == want


def test_joints_are_snapped_to_the_nearest_passable_cell_of_both_windows(tmp_path):
    """On a seabed with many land blocks (chunks of 16, a last chunk of one cell), random walks
    cut by ``segment``: each inner joint is itself where passable, else the passable cell
    nearest it (squared distance, the first in row order on a tie) in both windows it joins,
    within rho, then 4 rho, then the margin (written out here over the whole passable layer);
    with none, the mission cannot be cut there."""
    import dask

    import pipeline.mcpc.algorithm as mcpc

    rng = np.random.default_rng(11)
    z = random_surface((81, 65), seed=11) * 100.0 - 2000.0
    for _ in range(40):
        r, c = rng.integers(0, 78), rng.integers(0, 62)
        z[r : r + rng.integers(1, 9), c : c + rng.integers(1, 9)] = 20.0
    path = tmp_path / "maps.zarr"
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(
            metric_dataarray(z.astype(np.float32), a=A).chunk(16), path, clearance=45.0
        )
    ok = pipeline.open_maps(path)["passable"].values.astype(bool)
    m = pipeline.open_store(path)
    moved = failed = 0
    for _ in range(300):
        n = int(rng.integers(2, 60))
        pts = np.cumsum(rng.integers(-3, 4, size=(n, 2)), axis=0) + rng.integers(0, 81, size=2)
        pts = np.clip(pts, 0, [80, 64])
        rho, size, margin = (int(v) for v in rng.integers([1, 2, 1], [4, 12, 6]))
        secs = segment(pts, size, margin, ok.shape)
        want = [tuple(int(v) for v in pts[i0]) for i0, _, _ in secs] + [(9, 9)]
        for k in range(1, len(secs)):
            j = want[k]
            if ok[j]:
                continue
            (a0, a1, b0, b1), (c0, c1, d0, d1) = secs[k - 1][2], secs[k][2]
            near = None
            for radius in (rho, 4 * rho, margin):
                r0, r1 = max(a0, c0, j[0] - radius), min(a1, c1, j[0] + radius + 1)
                q0, q1 = max(b0, d0, j[1] - radius), min(b1, d1, j[1] + radius + 1)
                cand = [
                    (r, c) for r in range(r0, r1) for c in range(q0, q1) if ok[r, c]
                ]  # row order
                if cand:
                    near = min(cand, key=lambda v: (v[0] - j[0]) ** 2 + (v[1] - j[1]) ** 2)
                    break
            if near is None:
                want = None
                break
            want[k] = near
            moved += 1
        if want is None:
            failed += 1
            with pytest.raises(pipeline.UnreachableGoalError, match="no passable cell near"):
                mcpc._snapped_joints(m, pts, secs, (9, 9), rho, margin)
        else:
            assert mcpc._snapped_joints(m, pts, secs, (9, 9), rho, margin) == want
    assert moved > 50 and failed > 0


def test_restore_by_hand():
    coarse = np.array([(0, 0), (1, 1), (2, 2), (3, 2)])
    got = restore(coarse, 10, (35, 100), (1, 2), (33, 27))
    # (i, j) -> (10 i + 5, 10 j + 5), row 35 clipped to 34, ends replaced
    assert got.tolist() == [[1, 2], [15, 15], [25, 25], [33, 27]]


def test_remove_loops_by_hand():
    cells = np.array([(0, 0), (0, 1), (1, 1), (1, 0), (0, 1), (0, 2), (1, 3), (0, 2), (0, 3)])
    assert remove_loops(cells).tolist() == [0, 1, 5, 8]


def test_remove_loops_equals_cutting_each_loop_in_turn():
    """Random walks on small tori (many loops, loops inside loops, cells revisited after a
    cut) against the definition, written out with a list: walk the path, and where a cell is
    already kept, cut back to it."""

    def reference(cells):
        kept, idx = [], []
        for i, c in enumerate(map(tuple, cells)):
            if c in kept:
                p = kept.index(c)
                del kept[p + 1 :], idx[p + 1 :]
                continue
            kept.append(c)
            idx.append(i)
        return idx

    rng = np.random.default_rng(1)
    for _ in range(300):
        steps = rng.integers(-1, 2, size=(int(rng.integers(1, 400)), 2))
        cells = np.cumsum(steps, axis=0) % int(rng.integers(2, 12))
        assert remove_loops(cells).tolist() == reference(cells)


# ------------------------------------------------------------------ stitched trajectories


def check_stitched(t, arrays, start, goal):
    check_path(t, arrays["passable"], start, goal)
    length, ridge_len = independent_metrics(t, arrays["safety"], arrays["ridge"], A)
    assert math.isclose(t.length_m, length, rel_tol=1e-9)
    assert math.isclose(t.ridge_length_m, ridge_len, rel_tol=1e-9, abs_tol=1e-6)
    assert t.lower_bound_m <= t.length_m


@pytest.mark.parametrize("planner", ["astar", "ra_star", "lagrangian"])
def test_stitched_trajectory_is_valid_and_keeps_the_bound_per_section(store, arrays, planner):
    t = pipeline.plan(store, **MISSION, planner=planner, omega=1.5, client="synchronous", **SMALL)
    check_stitched(t, arrays, MISSION["start"], MISSION["goal"])
    assert len(t.extra["sections"]) >= 5
    assert t.cells[:, 0].max() > WALL_ROW and t.cells[:, 1].max() >= WALL_END  # round the wall
    for sec in t.extra["sections"][:4]:  # each section within omega of its own optimum
        r0, r1, c0, c1 = sec["window"]
        s, g = np.subtract(sec["start"], (r0, c0)), np.subtract(sec["goal"], (r0, c0))
        opt = reference_length(
            arrays["safety"][r0:r1, c0:c1], arrays["passable"][r0:r1, c0:c1], A, s, g
        )
        assert sec["length_m"] <= 1.5 * opt * (1 + 1e-9)


def test_one_window_equals_scipy_and_bounds_mcpc(store, arrays):
    whole = pipeline.plan(store, **MISSION, planner="astar", mcpc=False, client="synchronous")
    opt = reference_length(
        arrays["safety"], arrays["passable"], A, MISSION["start"], MISSION["goal"]
    )
    assert math.isclose(whole.length_m, opt, rel_tol=1e-9)
    mc = pipeline.plan(store, **MISSION, planner="astar", client="synchronous", **SMALL)
    assert opt * (1 - 1e-9) <= mc.length_m <= 1.5 * opt  # MCPC costs some optimality


@pytest.mark.parametrize(
    ("planner", "coarse_weight", "omega", "weight"),
    [
        ("ra_star", 1.0, 1.5, 1.0),
        ("ra_star", 1.3, 1.5, 1.3),
        ("lagrangian", 1.3, 1.1, 1.1),
        ("astar", 1.3, 1.5, 1.0),  # the optimal planners keep the exact coarse A*
    ],
)
def test_the_coarse_path_is_within_its_weight_of_the_coarse_optimum(
    store, planner, coarse_weight, omega, weight
):
    """The coarse A* is weighted A* of weight min(coarse_weight, omega) for the bounded
    planners, exact A* for the optimal ones: its path is at most that factor longer than the
    coarse map's optimum (scipy on the coarse graph), and equal to it at weight 1."""
    from pipeline.planners.paths import path_metrics

    m = pipeline.open_store(store)
    t = pipeline.plan(
        store,
        **MISSION,
        planner=planner,
        omega=omega,
        client="synchronous",
        coarse_weight=coarse_weight,
        **SMALL,
    )
    co = m.coarse(SMALL["rho"])
    cells = t.extra["coarse_cells"]
    # an array, not a list of pairs: a job's client unpickles every result (as lists, 0.1 ms a
    # mission, a third of the client's CPU in plan_missions)
    assert isinstance(cells, np.ndarray) and cells.ndim == 2 and cells.shape[1] == 2
    z = co["safety"][cells[:, 0], cells[:, 1]]
    length, _, _ = path_metrics(cells, z, np.zeros(len(cells), bool), A * SMALL["rho"])
    opt = reference_length(co["safety"], co["passable"], A * SMALL["rho"], cells[0], cells[-1])
    assert opt * (1 - 1e-9) <= length <= weight * opt * (1 + 1e-9)
    if weight == 1.0:
        assert math.isclose(length, opt, rel_tol=1e-9)
    assert t.extra["coarse_weight"] == coarse_weight


# ------------------------------------------------------------------ fallbacks and errors


def test_blocked_section_is_retried_then_merged(store, arrays):
    m = pipeline.open_store(store)
    sections = [  # the first window is cut by the wall; so is it with the margin doubled
        Section((95, 146, 90, 111), (100, 100), (140, 100)),
        Section((130, 151, 95, 240), (140, 100), (140, 230)),
    ]
    secs, res = plan_sections("synchronous", m, sections, "astar", 1.5, 6)
    # attempts over the span: section 0 twice (margin doubled), section 1 once, merged once
    assert len(secs) == 1 and secs[0].merged and secs[0].attempts == 4
    assert res[0].status == "ok"
    cells = res[0].cells
    assert tuple(cells[0]) == (100, 100) and tuple(cells[-1]) == (140, 230)
    assert arrays["passable"][cells[:, 0], cells[:, 1]].all()
    assert cells[:, 1].max() >= WALL_END


@pytest.mark.timeout(120)
def test_unreachable_goal_is_a_clear_error_not_a_hang(store, arrays):
    inside = ((RING[0] + RING[1]) // 2, (RING[2] + RING[3]) // 2)
    assert arrays["passable"][inside]
    with pytest.raises(pipeline.UnreachableGoalError, match="unreachable|no path"):
        pipeline.plan(
            store, MISSION["start"], inside, planner="ra_star", client="synchronous", **SMALL
        )


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        (dict(start=(WALL_ROW, 10)), pipeline.InvalidEndpointError, "nearest passable cell"),
        (dict(goal=(500, 3)), pipeline.InvalidEndpointError, "off the map"),
        (dict(start=(1.5, 2)), InvalidParameterError, "cell"),
        (dict(omega=0.9), InvalidParameterError, "omega"),
        (dict(rho=0), InvalidParameterError, "rho"),
        (dict(rho=300), InvalidParameterError, "rho"),
        (dict(section_size=3), InvalidParameterError, "section_size"),
        (dict(margin=-1), InvalidParameterError, "margin"),
        (dict(planner="rrt"), InvalidParameterError, "planner"),
        (dict(coarse_weight=0.99), InvalidParameterError, "coarse_weight"),
        (dict(coarse_weight=float("nan")), InvalidParameterError, "coarse_weight"),
        (dict(client=42), InvalidParameterError, "client"),
    ],
)
def test_parameter_errors(store, kwargs, error, match):
    args = {**MISSION, "planner": "astar", "client": "synchronous", **SMALL, **kwargs}
    with pytest.raises(error, match=match):
        pipeline.plan(store, **args)


def test_a_goal_on_land_reads_one_window_only(store, monkeypatch):
    """A goal that is not passable, its start passable: the error names the goal and its
    nearest passable cell, from the one window read around the goal (the start's lookup told
    it passable: no window around it)."""
    m = pipeline.open_store(store)
    read = []
    window = m.window

    def counted(var, r0, r1, c0, c1):
        read.append((var, r0, r1, c0, c1))
        return window(var, r0, r1, c0, c1)

    monkeypatch.setattr(m, "window", counted)  # the real store's reads, counted
    args = {**MISSION, "goal": (WALL_ROW, 10), "planner": "astar", "client": "synchronous"}
    with pytest.raises(pipeline.InvalidEndpointError, match=r"goal .*nearest passable cell"):
        pipeline.plan(m, **args, **SMALL)
    assert len(read) == 1 and read[0][0] == "passable"
    assert read[0][1] <= WALL_ROW < read[0][2] and read[0][3] <= 10 < read[0][4]


def test_missing_store_is_a_clear_error(tmp_path):
    with pytest.raises(pipeline.PipelineError, match="does not exist"):
        pipeline.plan(tmp_path / "nope.zarr", (0, 0), (1, 1))


# ------------------------------------------------------------------ the same on every cluster


def test_same_result_on_every_scheduler(store, real_cluster):
    runs = {}
    runs["synchronous"] = pipeline.plan(store, **MISSION, client="synchronous", **SMALL)
    runs["threads"] = pipeline.plan(store, **MISSION, client="threads", **SMALL)
    runs["default LocalCluster"] = pipeline.plan(store, **MISSION, client=None, **SMALL)
    runs["scheduler address"] = pipeline.plan(store, **MISSION, client=real_cluster, **SMALL)
    ref = runs["synchronous"]
    for name, t in runs.items():
        assert np.array_equal(t.cells, ref.cells), name
        assert t.length_m == ref.length_m, name


def test_plan_missions_runs_each_mission_as_one_task(store, local_client):
    """On a cluster (a client that is not the default one), plan_missions runs every mission
    as one task (its sections in turn inside it, no task per section), and each result equals
    plan() of that mission on its own; a mission that cannot be planned fails alone, with its
    reason."""
    from distributed import get_task_stream

    missions = [
        {**MISSION, **SMALL},
        {"start": MISSION["goal"], "goal": MISSION["start"], **SMALL, "omega": 1.5},
        {"start": (0, 0), "goal": (5000, 5000)},  # outside the map: fails with its reason
    ]
    with get_task_stream(client=local_client) as ts:
        got = pipeline.plan_missions(store, missions, client=local_client, quicklooks=True)
    keys = [str(t["key"]) for t in ts.data]
    assert sum(k.startswith("mission-") for k in keys) == len(missions), keys
    assert not any("section" in k for k in keys), keys
    for m, t in zip(missions[:2], got[:2], strict=True):
        opts = {k: v for k, v in m.items() if k not in ("start", "goal")}
        ref = pipeline.plan(store, m["start"], m["goal"], client="synchronous", **opts)
        assert t.status == ref.status == "ok"
        assert np.array_equal(t.cells, ref.cells) and t.length_m == ref.length_m
    assert got[2].status == "failed" and "goal" in got[2].message
    # quicklooks=True: each planned mission's quick-look drawn by its task, the same picture
    # as drawn here; none for the failed one
    import io

    from matplotlib import image

    from pipeline.outputs.plots import mission_quicklook

    assert "quicklook_png" not in got[2].extra
    for i, t in enumerate(got[:2]):
        on_worker = image.imread(io.BytesIO(t.extra["quicklook_png"]))
        m = pipeline.open_store(store)
        here = mission_quicklook(m, t, io.BytesIO(), title=f"mission {i}", crs_wkt=m.crs_wkt)
        here.seek(0)
        assert on_worker.shape[0] > 500 and np.array_equal(on_worker, image.imread(here))
    # in this process's threads (no cluster), drawn one at a time: the same pictures
    local = pipeline.plan_missions(store, missions[:2], client="synchronous", quicklooks=True)
    for t, u in zip(got[:2], local, strict=True):
        a, b = (image.imread(io.BytesIO(x.extra["quicklook_png"])) for x in (t, u))
        assert np.array_equal(a, b)


@pytest.mark.parametrize("client", ["cluster", "synchronous"])
def test_a_malformed_mission_fails_alone(store, local_client, client):
    """A mission that is no (start, goal) pair, a dict without a goal, or a dict with a near
    miss of an option (``omgea``) is recorded failed with the reason (on_done too); the other
    missions of the batch are planned (a key of the caller's own kept), on a cluster as tasks,
    each the trajectory plan() finds for it alone."""
    good = [dict(MISSION, **SMALL), {"start": MISSION["goal"], "goal": MISSION["start"], **SMALL}]
    typo = {**good[1], "omgea": 1.2}  # planned as omega 2, the default, before
    missions = [good[0], 5, {"start": (1, 1), "name": "no goal"}, {**good[1], "priority": 2}, typo]
    seen = {}
    got = pipeline.plan_missions(
        store,
        missions,
        client=local_client if client == "cluster" else client,
        on_done=lambda i, m, t: seen.setdefault(i, (m, t.status)),
    )
    assert [t.status for t in got] == ["ok", "failed", "failed", "ok", "failed"]
    assert "a mission must be a dict with start and goal" in got[1].message
    assert "a mission needs exactly one of goal (a cell), goal_xy or goal_lonlat" in got[2].message
    assert "mission key 'omgea' is no option of a mission: did you mean 'omega'?" in got[4].message
    assert sorted(seen) == [0, 1, 2, 3, 4] and seen[2][0]["name"] == "no goal"
    assert seen[3][0]["priority"] == 2  # a key of the caller's own, kept
    for m, t in zip(good, (got[0], got[3]), strict=True):
        ref = pipeline.plan(store, m["start"], m["goal"], client="synchronous", **SMALL)
        assert np.array_equal(t.cells, ref.cells) and t.length_m == ref.length_m


def test_plan_missions_in_groups_per_task(store, local_client):
    """``missions_per_task``: the missions go to tasks in groups, the last 2 per cluster
    thread alone; every mission comes back as plan() makes it on its own, once to
    ``on_done``; a mission that fails in a group fails alone."""
    from distributed import get_task_stream

    from pipeline.jobs.missions import mission_groups

    for n, threads, per in ((100, 2, None), (7, 2, 2), (30, 1, 4), (5, 4, 3), (32, 2, None)):
        groups = mission_groups(n, threads, per)
        assert [i for g in groups for i in g] == list(range(n))  # each once, in order
        assert all(len(g) == 1 for g in groups[-min(n, 2 * threads) :])
        assert max(len(g) for g in groups) <= (per or 8)
    assert max(len(g) for g in mission_groups(100, 2, None)) == 6  # 100 // (8 x 2)
    assert max(len(g) for g in mission_groups(15, 2, None)) == 1  # up to 8 a thread: alone
    assert max(len(g) for g in mission_groups(1000, 2, None)) == 8  # at most 8

    missions = [
        {"start": (20 + 6 * i, 20), "goal": (225 - 4 * i, 30 + 10 * i), **SMALL} for i in range(6)
    ]
    missions.insert(1, {"start": (0, 0), "goal": (5000, 5000)})  # outside the map
    seen = []
    with get_task_stream(client=local_client) as ts:
        got = pipeline.plan_missions(
            store,
            missions,
            client=local_client,
            missions_per_task=2,
            on_done=lambda i, m, t: seen.append(i),
        )
    keys = sorted(str(t["key"]).rsplit("-", 1)[0] for t in ts.data)
    # 7 missions on 2 threads: 0-1 grouped, 2 left alone by the grouping, the last 4 alone
    assert keys == [f"mission-{i}" for i in range(2, 7)] + ["missions-0-1"], keys
    assert sorted(seen) == list(range(len(missions)))
    assert got[1].status == "failed" and "goal" in got[1].message
    for k in (0, 2, 3, 6):
        m = missions[k]
        opts = {key: v for key, v in m.items() if key not in ("start", "goal")}
        ref = pipeline.plan(store, m["start"], m["goal"], client="synchronous", **opts)
        assert got[k].status == ref.status == "ok"
        assert np.array_equal(got[k].cells, ref.cells) and got[k].length_m == ref.length_m
    with pytest.raises(InvalidParameterError, match="missions_per_task"):
        pipeline.plan_missions(store, missions[:2], client=local_client, missions_per_task=0)


def test_missions_on_a_fresh_store_run_one_per_worker_thread(store, local_client, tmp_path):
    """On a store whose coarse level is not written yet, plan_missions writes it once before
    the missions start, and each mission task runs alone on its worker's one thread: a dask
    computation inside a task (the coarse level) would otherwise go to the worker's client,
    which secedes the task from the worker's thread limit, so that every queued mission starts
    at once and records the others' time as its own."""
    import shutil
    import time

    from distributed import WorkerPlugin

    class Spans(WorkerPlugin):
        """Each mission task's state changes on its worker, stamped by the worker's own clock
        (the task stream adds the worker's estimate of its offset to the scheduler's clock,
        re-estimated at every heartbeat: under load it jumps by tens of ms between two tasks,
        which made back-to-back missions look concurrent)."""

        name = "mission-spans"

        def setup(self, worker):
            self.log = []

        def transition(self, key, start, finish, **kwargs):
            if str(key).startswith("mission-"):
                self.log.append((str(key), start, finish, time.time()))

    fresh = tmp_path / "maps.zarr"
    shutil.copytree(store, fresh)
    for p in fresh.glob("coarse-rho*"):
        shutil.rmtree(p)
    missions = [
        {"start": (20 + 6 * i, 20), "goal": (225 - 4 * i, 30 + 10 * i), **SMALL} for i in range(6)
    ]
    local_client.register_plugin(Spans())
    try:
        got = pipeline.plan_missions(fresh, missions, client=local_client)
        logs = local_client.run(lambda dask_worker: dask_worker.plugins["mission-spans"].log)
    finally:
        local_client.unregister_worker_plugin("mission-spans")
    assert all(t.status == "ok" for t in got), [t.message for t in got]
    written = (fresh / f"coarse-rho{SMALL['rho']}" / "zarr.json").stat().st_mtime
    # a task that secedes goes from executing to long-running, and its worker starts the next
    assert not [e for log in logs.values() for e in log if "long-running" in (e[1], e[2])], logs
    spans: dict = {}
    for worker, log in logs.items():
        began = {key: t for key, _, finish, t in log if finish == "executing"}
        for key, start, _, t in log:
            if start == "executing":
                spans.setdefault(worker, []).append((began[key], t))
    assert sum(len(v) for v in spans.values()) == len(missions)
    assert written < min(start for runs in spans.values() for start, _ in runs)
    for worker, runs in spans.items():
        runs.sort()
        for (_, stop), (start, _) in zip(runs, runs[1:], strict=False):
            assert start >= stop, f"two missions ran at once on {worker}: {runs}"
    # each mission's recorded runtime is its own: within its task's time
    took = sorted(stop - start for runs in spans.values() for start, stop in runs)
    assert sorted(t.runtime_s for t in got)[-1] <= took[-1] + 1e-3


def test_a_coarse_level_that_does_not_hold_together_is_damage(store, tmp_path):
    """The coarse level is checked once when read (every mission then searches it unchecked):
    a NaN height at a passable coarse cell refuses the store in one line."""
    import shutil

    import zarr

    copy = tmp_path / "maps.zarr"
    shutil.copytree(store, copy)
    rho = SMALL["rho"]
    pipeline.store.maps_store.MapsStore(copy).coarse(rho)  # written into the copy
    group = zarr.open_group(copy / f"coarse-rho{rho}", mode="r+")
    ok = group["passable"][...]
    r, c = np.argwhere(ok)[len(np.argwhere(ok)) // 2]
    safety = group["safety"][...]
    safety[r, c] = np.nan
    group["safety"][...] = safety
    with pytest.raises(pipeline.PipelineError, match=rf"damaged: its coarse level coarse-rho{rho}"):
        # a new MapsStore: the one open_store keeps has the level in memory, checked
        pipeline.plan(
            pipeline.store.maps_store.MapsStore(copy), **MISSION, client="synchronous", **SMALL
        )


@pytest.mark.parametrize("rho", [4, 7])
def test_the_coarse_level_is_the_block_means_of_the_fine_maps(store, arrays, tmp_path, rho):
    """The coarse level against numpy's block means of the fine layers (240 cells a side: at
    rho 7 the last blocks hold 2 rows and columns): the mean of the finite safety heights, the
    share of ridge cells, passable where half the cells are and the mean is finite, coarse
    ridge cells from ``COARSE_RIDGE_FRACTION`` on; written once, then read back by another
    MapsStore (as in another process) equal."""
    import shutil

    from pipeline.store.schema import COARSE_RIDGE_FRACTION

    copy = tmp_path / "maps.zarr"
    shutil.copytree(store, copy)
    co = pipeline.store.maps_store.MapsStore(copy).coarse(rho)
    n = -(-240 // rho)
    want = {k: np.full((n, n), np.nan) for k in ("safety", "ridge", "passable")}
    for i in range(n):
        for j in range(n):
            blk = (slice(i * rho, (i + 1) * rho), slice(j * rho, (j + 1) * rho))
            z = arrays["safety"][blk].astype(np.float64)
            want["safety"][i, j] = z[np.isfinite(z)].mean() if np.isfinite(z).any() else np.nan
            want["ridge"][i, j] = arrays["ridge"][blk].mean()
            want["passable"][i, j] = arrays["passable"][blk].mean()
    np.testing.assert_allclose(co["safety"], want["safety"], rtol=1e-6)
    np.testing.assert_allclose(co["ridge"], want["ridge"], rtol=1e-6)
    passable = (want["passable"] >= 0.5) & np.isfinite(want["safety"])
    np.testing.assert_array_equal(co["passable"], passable)
    np.testing.assert_array_equal(co["ridge_cells"], want["ridge"] >= COARSE_RIDGE_FRACTION)
    assert co["safety"].dtype == np.float32 and co["passable"].dtype == bool
    assert 0 < co["passable"].sum() < n * n and co["ridge_cells"].any()
    again = pipeline.store.maps_store.MapsStore(copy).coarse(rho)  # read from the store this time
    for key, value in co.items():
        np.testing.assert_array_equal(again[key], value)
        assert again[key].dtype == value.dtype


MISSION_PROCESS = """
import sys
import numpy as np
import pipeline

HEAVY = ("xarray", "dask.array", "pandas", "scipy.ndimage", "scipy.sparse")
store, out = sys.argv[1], sys.argv[2]
t = pipeline.plan(store, (20, 20), (225, 30), client="synchronous", rho=4, section_size=24,
                  margin=6)
pipeline.fly(store, t)
np.save(out, np.asarray(t.cells))
print("heavy:", sorted(m for m in HEAVY if m in sys.modules))
"""


def test_a_mission_in_a_new_process_needs_neither_xarray_nor_dask_array(store, tmp_path):
    """What a worker's first mission on a built store imports (each worker of a job pays it
    once): the mission planned and flown in a new process, its coarse level already written,
    loads neither xarray, dask.array, pandas nor scipy's image and sparse modules (0.6-1 s of
    a worker's first mission), and plans the path this process plans."""
    import subprocess

    want = pipeline.plan(store, **MISSION, client="synchronous", **SMALL)  # the level written
    out = tmp_path / "cells.npy"
    proc = subprocess.run(
        [sys.executable, "-c", MISSION_PROCESS, str(store), str(out)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert "heavy: []" in proc.stdout, proc.stdout
    np.testing.assert_array_equal(np.load(out), want.cells)


def _released(start: str, finish: str) -> bool:
    """A task's release by its client: once done, or while the scheduler has not yet heard it
    done (its results reached the client through the queue, pipeline.runtime.inbox)."""
    return start == "memory" or (start == "processing" and finish in ("released", "forgotten"))


def test_a_mission_releases_the_last_ones_tasks_only_after_submitting_its_own(store, local_client):
    """plan() on a cluster keeps its section tasks until the next plan() on that client has
    submitted its own (mcpc._HELD): released at once, they would put a message on the client's
    batched stream just before the next mission's tasks, which then wait for its next batch."""
    from distributed.diagnostics.plugin import SchedulerPlugin

    class Log(SchedulerPlugin):
        name = "section-log"

        def __init__(self):
            self.log = []

        def transition(self, key, start, finish, *args, **kwargs):
            if str(key).startswith("_shared_batch"):
                self.log.append((str(key), start, finish))

    goals = [(225 - 4 * i, 30 + 10 * i) for i in range(3)]
    local_client.register_plugin(Log())
    try:
        for goal in goals:
            t = pipeline.plan(store, (20, 20), goal, client=local_client, **SMALL)
            assert t.status == "ok" and len(t.extra["sections"]) >= 2
        import time

        for _ in range(100):  # the last release is on its way while the last mission returns
            log = local_client.run_on_scheduler(
                lambda dask_scheduler: list(dask_scheduler.plugins["section-log"].log)
            )
            if sum(_released(start, finish) for _, start, finish in log) >= 2 * (len(goals) - 1):
                break
            time.sleep(0.05)
    finally:
        local_client.unregister_scheduler_plugin("section-log")
    # this test's tasks: those submitted while it ran (the first plan() releases the tasks an
    # earlier test's last plan() held, whose transitions the plugin logs too)
    ours = {key for key, start, finish in log if (start, finish) == ("released", "waiting")}
    log = [e for e in log if e[0] in ours]
    keys: list = []  # in the order the scheduler first saw them: 2 tasks a mission (2 threads)
    for key, *_ in log:
        if key not in keys:
            keys.append(key)
    missions = [keys[2 * i : 2 * i + 2] for i in range(len(goals))]
    assert len(keys) == 2 * len(goals), keys
    first_seen = {k: min(i for i, e in enumerate(log) if e[0] == k) for k in keys}
    released = {k: i for i, (k, start, finish) in enumerate(log) if _released(start, finish)}
    for before, after in zip(missions[:-1], missions[1:], strict=True):
        for k in before:
            assert released[k] > min(first_seen[a] for a in after), (k, log)
    assert not set(missions[-1]) & set(released)  # held until the next mission


def test_a_missions_tasks_are_sent_within_a_millisecond(store, local_client):
    """distributed batches a client's messages to its scheduler every 10 ms and a scheduler's
    to a worker every 5 ms: a mission of about 10 ms then met the batch that released the
    mission before it, and its tasks waited for the next. A client that plans is sent every
    pipeline.runtime.cluster.STREAM_INTERVAL_S (1 ms), and so is the scheduler of local_cluster() to
    each of its workers, those added later included."""
    from distributed import Client

    from pipeline.runtime.cluster import STREAM_INTERVAL_S, local_cluster

    assert STREAM_INTERVAL_S <= 0.001

    def intervals(dask_scheduler):
        return sorted(c.interval for c in dask_scheduler.stream_comms.values())

    t = pipeline.plan(store, (20, 20), (225, 30), client=local_client, **SMALL)
    assert t.status == "ok"
    assert local_client.scheduler_comm.interval <= STREAM_INTERVAL_S
    assert local_client.run_on_scheduler(intervals) == [STREAM_INTERVAL_S] * 2

    with local_cluster() as cluster, Client(cluster) as client:
        assert client.scheduler_comm.interval == 0.01  # distributed's own, until plan() runs
        cluster.scale(3)
        client.wait_for_workers(3, timeout=60)
        assert client.run_on_scheduler(intervals) == [STREAM_INTERVAL_S] * 3


def _faults_reallocating(nbytes: int) -> int:
    """Minor page faults of allocating and filling ``nbytes`` again right after an array of
    that size was freed, in this process."""
    import resource

    a = np.ones(nbytes // 8)
    del a
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    b = np.ones(nbytes // 8)
    f1 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    del b
    return f1 - f0


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_local_cluster_workers_reuse_freed_memory(local_client):
    """The workers of the default local cluster take a freed 2 MiB array's memory back for the
    next one (pipeline.runtime.cluster.WORKER_ENV): with dask's own setting every array above
    128 KiB is a fresh mapping, 512 page faults for 2 MiB (below numpy's 4 MiB huge-page size)."""
    faults = local_client.run(_faults_reallocating, 2 * 2**20)
    assert len(faults) == 2
    assert all(f < 64 for f in faults.values()), faults


def _callback_ms(dask_worker=None, dask_scheduler=None) -> dict:
    server = dask_worker if dask_worker is not None else dask_scheduler
    return {k: pc.callback_time for k, pc in server.periodic_callbacks.items()}


def _count_wakeups(dask_worker=None, dask_scheduler=None) -> None:
    """From now on, count the times the process's event loop wakes (its selector's waits)."""
    import asyncio

    selector = asyncio.get_event_loop()._selector
    select = selector.select
    selector.wakeups = 0

    def counted(timeout=None):
        selector.wakeups += 1
        return select(timeout)

    selector.select = counted


def _wakeups(dask_worker=None, dask_scheduler=None) -> int:
    import asyncio

    return asyncio.get_event_loop()._selector.wakeups


def _idle_wakeups(client) -> float:
    """How many times a second a worker's event loop wakes, idle (the mean of the workers
    over a second)."""
    import time

    time.sleep(0.5)  # what an earlier test left the workers to do
    client.run(_count_wakeups)
    t0 = time.perf_counter()
    time.sleep(1.0)
    got = client.run(_wakeups)
    return sum(got.values()) / len(got) / (time.perf_counter() - t0)


def test_local_cluster_housekeeping_is_sparse_and_a_users_setting_wins(local_client):
    """The scheduler, nannies and workers of local_cluster() wake for their housekeeping at
    pipeline.runtime.cluster.HOUSEKEEPING's intervals, not dask's (event loop check every 20 ms,
    profile samples every 10 ms, ...): an idle worker's event loop wakes under a fifth as often
    as at about dask's intervals, set by the user, which win (37 against 410 times a second
    measured). (Its share of a core, measured so before, 0.8 % against 4 % in a quiet hour of
    the VM, was 5-7 % either way in a slow one: not a figure a test can hold.)"""
    import dask
    from distributed import Client

    from pipeline.runtime.cluster import HOUSEKEEPING, local_cluster

    ms = {k: 1000 * dask.utils.parse_timedelta(v) for k, (v, _) in HOUSEKEEPING.items()}
    tick, profile = ms["distributed.admin.tick.interval"], ms["distributed.worker.profile.interval"]
    memory = ms["distributed.worker.memory.monitor-interval"]
    assert local_client.run_on_scheduler(_callback_ms)["tick"] == tick
    for got in local_client.run(_callback_ms).values():
        assert (got["tick"], got["profile"], got["memory_monitor"]) == (tick, profile, memory)
    ours = _idle_wakeups(local_client)

    # dask's intervals, one millisecond longer each: set by the user (a value equal to dask's
    # own default is taken as not set)
    theirs = {
        k: f"{1000 * dask.utils.parse_timedelta(d) + 1:g}ms" for k, (_, d) in HOUSEKEEPING.items()
    }
    with dask.config.set(theirs):
        cluster = local_cluster()
    with cluster, Client(cluster) as client:
        tick_set = 1000 * dask.utils.parse_timedelta(theirs["distributed.admin.tick.interval"])
        assert client.run_on_scheduler(_callback_ms)["tick"] == tick_set
        for got in client.run(_callback_ms).values():
            assert got["tick"] == tick_set and got["profile"] != profile
        reference = _idle_wakeups(client)
    assert ours < 0.2 * reference, (ours, reference)


def _loaded(dask_worker=None) -> dict:
    """A worker's state after it loaded what a mission loads (xarray, dask.array, a compiled
    kernel): its pid, its scratch directory, its plugins."""
    import os

    import numpy as np
    import xarray  # noqa: F401

    from pipeline.planners.bounds import off_ridge_to_goal

    ok = np.ones((3, 3), dtype=bool)
    off_ridge_to_goal(ok, ok, 30.0, 1, 1, -1, -1)
    return {
        "pid": os.getpid(),
        "dir": dask_worker.local_directory,
        "plugins": [*dask_worker.plugins],
    }


def test_local_cluster_workers_end_at_once_when_closed():
    """A closed worker of local_cluster() ends its process without Python's own shutdown
    (pipeline.runtime.exit): the cluster closes in well under the 0.6-1.1 s it took after a job's
    missions (0.05-0.07 s measured), its processes are gone and their scratch directories
    removed (distributed's close ran to its end)."""
    import os
    import time

    import psutil
    from distributed import Client

    from pipeline.runtime.cluster import local_cluster
    from pipeline.runtime.exit import NAME

    cluster = local_cluster()
    client = Client(cluster, set_as_default=False)
    got = client.run(_loaded)
    assert len(got) == 2 and all(NAME in w["plugins"] for w in got.values())
    procs = [psutil.Process(w["pid"]) for w in got.values()]
    client.close()
    t0 = time.perf_counter()
    cluster.close()
    took = time.perf_counter() - t0
    assert took < 0.4, took
    for p in procs:
        assert not p.is_running() or p.status() == psutil.STATUS_ZOMBIE
    assert not any(os.path.exists(w["dir"]) for w in got.values())


# ------------------------------------------------------------------ work sharing between runs


def _claim_all(token, me, bounds, barrier, pause_s):
    """In a process of its own: open the claims of run ``me``, wait for the other runs' tasks,
    then take sections (``pause_s`` each) until none is left; the sections taken, in order."""
    import time

    from pipeline.runtime.share import Claims

    got = []
    with Claims(token, me, bounds) as claims:
        barrier.wait()
        while (i := claims.next()) is not None:
            got.append(i)
            time.sleep(pause_s)
    return got


def test_runs_share_their_sections_between_processes_each_exactly_once():
    """Two processes (real flock on one file): the fast one plans its run in order, then the
    slow one's from its back; every section is taken exactly once, and the file is gone."""
    import multiprocessing as mp
    import os
    import uuid
    from concurrent.futures import ProcessPoolExecutor

    from pipeline.runtime.share import Claims

    token, bounds = uuid.uuid4().hex, [0, 10, 20]
    ctx = mp.get_context("spawn")
    with ctx.Manager() as manager, ProcessPoolExecutor(2, mp_context=ctx) as pool:
        barrier = manager.Barrier(2)
        fast = pool.submit(_claim_all, token, 0, bounds, barrier, 0.0)
        slow = pool.submit(_claim_all, token, 1, bounds, barrier, 0.05)
        fast, slow = fast.result(timeout=60), slow.result(timeout=60)
    assert sorted(fast + slow) == list(range(20))  # each once
    assert fast[:10] == list(range(10)) and len(fast) > 10  # its own run, then the slow one's
    assert fast[10:] == list(range(19, 19 - len(fast[10:]), -1))  # from the back, contiguous
    assert slow == list(range(10, 10 + len(slow)))  # its own run from the front, in order
    assert not os.path.exists(Claims(token, 0, bounds).path)


def test_a_run_whose_task_has_not_opened_the_claims_is_not_taken(tmp_path):
    """A task alone (the other run's task on another host, or not started) plans its own run
    only; a task that opens the claims after the first has gone starts afresh."""
    import uuid

    from pipeline.runtime.share import Claims

    token, bounds = uuid.uuid4().hex, [0, 3, 7]
    with Claims(token, 0, bounds) as c:
        assert [c.next() for _ in range(4)] == [0, 1, 2, None]
    with Claims(token, 1, bounds) as c:
        assert [c.next() for _ in range(5)] == [3, 4, 5, 6, None]


def test_sections_of_a_lost_task_are_planned_again(store, local_client, monkeypatch):
    """A task that died after claiming sections (its worker lost) returns nothing for them:
    the claims file says run 0's first two sections are taken, yet the mission has every
    section, and the same path as in this process."""
    import os
    import uuid

    import pipeline.mcpc.runners as mcpc
    from pipeline.runtime.share import Claims

    ref = pipeline.plan(store, **MISSION, planner="lagrangian", client="synchronous", **SMALL)
    n = len(ref.extra["sections"])
    assert n >= 4
    bounds = np.linspace(0, n, 3).round().astype(int).tolist()
    token = uuid.uuid4().hex
    lost = Claims(token, 0, bounds)
    state = lost._empty()
    state[0] += 2  # run 0's first two sections claimed by the lost task, which opened the file
    state[2] = 1
    with open(lost.path, "wb") as f:
        f.write(state.tobytes())

    class Fixed:
        hex = token

    monkeypatch.setattr(mcpc.uuid, "uuid4", lambda: Fixed)
    try:
        got = pipeline.plan(store, **MISSION, planner="lagrangian", client=local_client, **SMALL)
    finally:
        if os.path.exists(lost.path):
            os.unlink(lost.path)
    assert [s["window"] for s in got.extra["sections"]] == [
        s["window"] for s in ref.extra["sections"]
    ]
    assert all(s["status"] == "ok" for s in got.extra["sections"])
    assert np.array_equal(got.cells, ref.cells) and got.length_m == ref.length_m


def _sections_of(t) -> list:
    """The sections of a planned mission, as plan() cut and snapped them."""
    return [
        Section(tuple(s["window"]), tuple(s["start"]), tuple(s["goal"]))
        for s in t.extra["sections"]
    ]


def test_a_batch_in_this_process_reads_each_next_window_in_a_helper_thread(store, monkeypatch):
    """Out of a dask worker the windows of a run of sections are read by the helper thread,
    each while the one before is searched; the results are those of planning each section
    on its own. A second batch at the same time reads its own (the helper is taken)."""
    import threading

    import pipeline.mcpc.runners as mcpc

    ref = pipeline.plan(store, **MISSION, planner="astar", client="synchronous", **SMALL)
    sections = _sections_of(ref)
    assert len(sections) >= 3
    m = pipeline.open_store(store)
    real, readers = mcpc.read_section, []

    def read_section(st, sec):
        readers.append(threading.current_thread().name)
        return real(st, sec)

    monkeypatch.setattr(mcpc, "read_section", read_section)
    got = mcpc._section_batch(m, sections, "astar", 1.5)
    assert all(name.startswith("pipeline-section-reads") for name in readers), readers
    assert len(readers) == len(sections)
    alone = [mcpc.plan_section(m, sec, "astar", 1.5) for sec in sections]
    for a, b in zip(got, alone, strict=True):
        assert a.ok and np.array_equal(a.cells, b.cells) and a.length_m == b.length_m
    readers.clear()
    with mcpc._READER:  # another batch holds the helper: this one reads in its own thread
        mcpc._section_batch(m, sections, "astar", 1.5)
    assert readers == [threading.current_thread().name] * len(sections)


def test_a_mission_in_this_process_reads_its_windows_ahead_and_frees_the_helper(store, monkeypatch):
    """plan(client="synchronous") has the helper thread read every section's window from the
    moment they are cut (while the joints are snapped), once each; a mission that fails
    between the cut and its sections (no joint can be snapped: it falls back to the whole
    map) frees the helper, so the next mission's windows are read there again. While the
    helper reads, the GIL changes hands every 0.5 ms at most (Python's 5 ms before and after)."""
    import threading

    import pipeline.mcpc.runners as mcpc

    ref = pipeline.plan(store, **MISSION, planner="astar", client="synchronous", **SMALL)
    real, readers, switch = mcpc.read_section, [], []

    def read_section(st, sec):
        readers.append((threading.current_thread().name, tuple(sec.window)))
        switch.append(sys.getswitchinterval())
        return real(st, sec)

    monkeypatch.setattr(mcpc, "read_section", read_section)
    got = pipeline.plan(store, **MISSION, planner="astar", client="synchronous", **SMALL)
    assert np.array_equal(got.cells, ref.cells) and got.length_m == ref.length_m
    windows = [tuple(s["window"]) for s in ref.extra["sections"]]
    assert [w for _, w in readers] == windows  # each window once, in order
    assert all(name.startswith("pipeline-section-reads") for name, _ in readers), readers
    assert set(switch) == {0.0005} and sys.getswitchinterval() == 0.005

    def no_joint(*args, **kwargs):
        raise pipeline.UnreachableGoalError("no passable cell near the joint (1, 2)")

    with monkeypatch.context() as mp:
        mp.setattr("pipeline.mcpc.plan._snapped_joints", no_joint)
        whole = pipeline.plan(store, **MISSION, planner="astar", client="synchronous", **SMALL)
    assert "no passable cell near the joint" in whole.extra["fallback"]
    readers.clear()
    again = pipeline.plan(store, **MISSION, planner="astar", client="synchronous", **SMALL)
    assert np.array_equal(again.cells, ref.cells)
    assert [w for _, w in readers] == windows
    assert all(name.startswith("pipeline-section-reads") for name, _ in readers), readers
    assert sys.getswitchinterval() == 0.005  # set back after a mission that fell back too


@pytest.mark.parametrize("client", ["synchronous", "threads", "cluster"])
def test_a_nan_height_at_a_passable_cell_fails_the_section_with_the_reason(
    store, tmp_path, client, local_client
):
    """The layers of a section's window are checked where they are read (a helper thread in
    one process, the task on a worker): a NaN safety height at a passable cell on the path
    fails the section with the reason, and the mission after its retries, in one line."""
    import shutil

    import zarr

    ref = pipeline.plan(store, **MISSION, client="synchronous", **SMALL)
    copy = tmp_path / "maps.zarr"
    shutil.copytree(store, copy)
    arr = zarr.open_array(copy / "safety", mode="r+")
    r, c = (int(v) for v in ref.cells[len(ref.cells) // 2])
    arr[r, c] = np.nan
    run_on = local_client if client == "cluster" else client
    with pytest.raises(
        pipeline.UnreachableGoalError, match=r"NaN or infinite at passable cell"
    ) as err:
        pipeline.plan(pipeline.store.maps_store.MapsStore(copy), **MISSION, client=run_on, **SMALL)
    assert "\n" not in str(err.value)


# ------------------------------------------------------------------ in this process, on every core


@pytest.mark.parametrize("planner", ["ra_star", "lagrangian"])
def test_threads_share_a_missions_sections_and_plan_each_once(store, monkeypatch, planner):
    """client="threads": the sections are planned by this thread and a helper (2 cores), the
    helper's run taken from the back once this thread's own is done; each section exactly
    once, and the trajectory that of the sections in turn (client="synchronous"). Each search
    is slowed by 20 ms here, so that the helper has surely started before the first ends."""
    import threading
    import time

    import pipeline.mcpc.runners as mcpc

    ref = pipeline.plan(store, **MISSION, planner=planner, client="synchronous", **SMALL)
    n = len(ref.extra["sections"])
    assert n >= 4
    real, who = mcpc._plan_checked, []

    def plan_checked(st, sec, *args):
        who.append((threading.current_thread().name, tuple(sec.window)))
        time.sleep(0.02)
        return real(st, sec, *args)

    monkeypatch.setattr(mcpc, "_plan_checked", plan_checked)
    monkeypatch.setattr(mcpc, "cores", lambda: 2)
    got = pipeline.plan(store, **MISSION, planner=planner, client="threads", **SMALL)
    assert np.array_equal(got.cells, ref.cells) and got.length_m == ref.length_m
    assert [s["window"] for s in got.extra["sections"]] == [
        s["window"] for s in ref.extra["sections"]
    ]
    windows = [tuple(s["window"]) for s in ref.extra["sections"]]
    assert sorted(w for _, w in who) == sorted(windows)  # each once
    me = threading.current_thread().name
    assert {name for name, _ in who} - {me} and all(
        name.startswith("pipeline-sections") for name, _ in who if name != me
    ), who
    index = {w: i for i, w in enumerate(windows)}
    _check_claims(
        {run: [index[w] for name, w in who if (name == me) == (run == 0)] for run in (0, 1)},
        [0, round(n / 2), n],
    )


def _check_claims(got: dict, bounds: list) -> None:
    """Sections taken by run (``got[run]``, in the order taken) under the claims' rule: every
    section once; each run's task its own run from the front, in order, before any other's;
    then the others' from their backs."""
    k = len(bounds) - 1
    assert sorted(i for run in got.values() for i in run) == list(range(bounds[-1]))
    for me in range(k):
        own = [i for i in got[me] if bounds[me] <= i < bounds[me + 1]]
        assert own == list(range(bounds[me], bounds[me] + len(own)))
        assert got[me][: len(own)] == own, got
        for j in range(k):
            if j != me:
                taken = [i for i in got[me] if bounds[j] <= i < bounds[j + 1]]
                assert taken == sorted(taken, reverse=True), got


def test_threads_a_helper_that_cannot_start_is_not_waited_for(store, monkeypatch):
    """The helper pool busy (another mission's sections, plan_missions' threads): this thread
    plans every section, the helper's run from its back, and the mission does not wait for
    the pool; its queued helper is cancelled."""
    import threading
    import time

    import pipeline.mcpc.runners as mcpc
    from pipeline.runtime.threads import shared_pool

    ref = pipeline.plan(store, **MISSION, planner="lagrangian", client="synchronous", **SMALL)
    monkeypatch.setattr(mcpc, "cores", lambda: 2)
    pool = shared_pool("sections", 1)
    hold, started = threading.Event(), threading.Event()

    def busy():
        started.set()
        hold.wait(60)

    blocker = [pool.submit(busy) for _ in range(pool._max_workers)]
    try:
        assert started.wait(10)
        t0 = time.perf_counter()
        got = pipeline.plan(store, **MISSION, planner="lagrangian", client="threads", **SMALL)
        assert time.perf_counter() - t0 < 30  # not the blocker's 60 s
    finally:
        hold.set()
    for fut in blocker:
        fut.result(10)
    assert np.array_equal(got.cells, ref.cells) and got.length_m == ref.length_m
    sections = _sections_of(ref)
    assert len(mcpc._threaded(pipeline.open_store(store), sections, "lagrangian", 2.0)) == len(
        sections
    )


def test_threads_an_error_in_a_helper_is_raised_not_lost(store, monkeypatch):
    """A bug in a helper thread's section (not a section's own failure, which is its result)
    reaches the caller, after this thread has planned the rest."""
    import threading
    import time

    import pipeline.mcpc.runners as mcpc

    ref = pipeline.plan(store, **MISSION, client="synchronous", **SMALL)
    real = mcpc._plan_checked

    def plan_checked(st, sec, *args):
        time.sleep(0.02)
        if threading.current_thread().name.startswith("pipeline-sections"):
            raise RuntimeError("a bug in the helper")
        return real(st, sec, *args)

    monkeypatch.setattr(mcpc, "_plan_checked", plan_checked)
    monkeypatch.setattr(mcpc, "cores", lambda: 2)
    with pytest.raises(RuntimeError, match="a bug in the helper"):
        mcpc._threaded(pipeline.open_store(store), _sections_of(ref), "ra_star", 2.0)


def test_thread_claims_take_each_section_once():
    """ThreadClaims (the rule of the processes' Claims, between threads): 3 threads of
    different speeds on runs of 10, 10 and 11 sections; every section once; each thread's own
    run from its front in order, and what it took of the others from their backs."""
    import threading
    import time

    from pipeline.runtime.share import ThreadClaims

    bounds = [0, 10, 20, 31]
    claims = ThreadClaims(bounds)
    got: dict = {0: [], 1: [], 2: []}
    barrier = threading.Barrier(3)

    def run(me, pause):
        barrier.wait()
        while (i := claims.next(me)) is not None:
            got[me].append(i)
            time.sleep(pause)

    threads = [
        threading.Thread(target=run, args=(me, pause))
        for me, pause in ((0, 0.0), (1, 0.004), (2, 0.012))
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    _check_claims(got, bounds)
    assert len(got[0]) > 10  # the fast thread took from the slow ones
    assert got[0][10] == 30  # first from the back of the run with the most left
    # a thread that never comes: its run is taken by the others, from its back
    claims = ThreadClaims([0, 2, 5])
    assert [claims.next(0) for _ in range(6)] == [0, 1, 4, 3, 2, None]


def test_plan_missions_in_threads(store, monkeypatch):
    """plan_missions(client="threads"): the missions in client threads, the trajectories
    those of the missions planned in turn; a mission's sections shared by threads only while
    fewer missions than cores are in flight (2 cores here)."""
    import pipeline.jobs.missions as pm
    import pipeline.mcpc.runners as mcpc

    real, shared = mcpc._threaded, []

    def threaded(*args):
        shared.append(1)
        return real(*args)

    monkeypatch.setattr(mcpc, "_threaded", threaded)
    monkeypatch.setattr(mcpc, "cores", lambda: 2)
    monkeypatch.setattr(pm, "cores", lambda: 2)
    missions = [
        MISSION,
        dict(start=(20, 20), goal=(100, 230)),
        dict(start=(10, 230), goal=(230, 100)),
    ]
    ref = [pipeline.plan(store, **m, client="synchronous", **SMALL) for m in missions]
    for concurrent, sharing in ((4, False), (2, False), (1, True)):
        shared.clear()
        got = pipeline.plan_missions(
            store,
            [dict(m) for m in missions],
            client="threads",
            defaults=SMALL,
            max_concurrent=concurrent,
        )
        for a, b in zip(got, ref, strict=True):
            assert a.status == b.status == "ok"
            assert np.array_equal(a.cells, b.cells) and a.length_m == b.length_m
        assert (len(shared) == len(missions)) if sharing else not shared, (concurrent, shared)


def test_without_a_shared_file_a_task_plans_its_own_run(monkeypatch, tmp_path):
    """No flock (not POSIX) or no writable directory: each task plans its own run, in order,
    and leaves no file."""
    import uuid

    import pipeline.runtime.share as share

    token, bounds = uuid.uuid4().hex, [0, 3, 7]
    monkeypatch.setattr(share, "fcntl", None)
    with share.Claims(token, 1, bounds) as c:
        assert [c.next() for _ in range(6)] == [3, 4, 5, 6, None, None]
    monkeypatch.undo()
    monkeypatch.setattr(share, "_directory", lambda: str(tmp_path / "missing"))
    with share.Claims(token, 0, bounds) as c:
        assert c.fd is None and [c.next() for _ in range(4)] == [0, 1, 2, None]


def test_a_mission_asks_for_the_worker_threads_at_most_once_a_second(monkeypatch):
    """The number of section tasks follows the cluster's worker threads, asked of the
    scheduler at most once every SLOTS_SECONDS per client (a round trip before every mission
    otherwise): a worker added shows once the count is that old."""
    from distributed import Client, LocalCluster

    from pipeline.mcpc import runners as mcpc

    with (
        LocalCluster(
            n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0"
        ) as cluster,
        Client(cluster) as client,
    ):
        monkeypatch.setattr(mcpc, "SLOTS_SECONDS", 3600.0)
        assert mcpc._slots(client) == 1
        cluster.scale(2)
        client.wait_for_workers(2, timeout=60)
        assert sum(client.nthreads().values()) == 2
        assert mcpc._slots(client) == 1  # asked less than SLOTS_SECONDS ago
        monkeypatch.setattr(mcpc, "SLOTS_SECONDS", 0.0)
        assert mcpc._slots(client) == 2


def test_section_results_reach_the_client_through_the_schedulers_queue(store, local_client):
    """Each section task posts its results to a queue on the scheduler that the client waits
    on (pipeline.runtime.inbox), sooner than through the task's future: every task of a
    mission posts once, the client's next mission posts to the same queue, and the path is
    the one planned in this process."""

    def count_posts(dask_scheduler):
        ext = dask_scheduler.extensions["queues"]
        posts = []

        async def put(name=None, key=None, data=None, client=None, timeout=None):
            posts.append(name)
            return await ext.put(name=name, key=key, data=data, client=client, timeout=timeout)

        dask_scheduler.handlers["queue_put"] = put
        dask_scheduler.inbox_test_posts = posts

    def posts(dask_scheduler):
        return list(dask_scheduler.inbox_test_posts)

    def restore(dask_scheduler):
        ext = dask_scheduler.extensions["queues"]
        dask_scheduler.handlers["queue_put"] = ext.put
        del dask_scheduler.inbox_test_posts

    ref = pipeline.plan(store, **MISSION, client="synchronous", **SMALL)
    assert len(ref.extra["sections"]) >= 2
    local_client.run_on_scheduler(count_posts)
    try:
        for _ in range(2):
            t = pipeline.plan(store, **MISSION, client=local_client, **SMALL)
            assert np.array_equal(t.cells, ref.cells) and t.length_m == ref.length_m
        got = local_client.run_on_scheduler(posts)
    finally:
        local_client.run_on_scheduler(restore)
    assert len(got) == 2 * 2  # 2 worker threads: 2 tasks a mission
    assert len(set(got)) == 1 and got[0].startswith("auv-pipeline-sections-")
    # the client took every post (gathering the futures instead would have left them queued)
    left = local_client.run_on_scheduler(
        lambda dask_scheduler: dask_scheduler.extensions["queues"].queues[got[0]].qsize()
    )
    assert left == 0


def test_failing_section_tasks_are_reported_and_a_scheduler_without_queues_still_serves(
    store, monkeypatch
):
    """A section task that raises posts a note, and the client raises its error at once; one
    that fails without posting is seen by the client's watch on the futures; a scheduler
    without the queue routes serves the missions through the futures. A real LocalCluster, its
    workers threads of this process so that a task can be made to fail."""
    import time

    from distributed import Client, LocalCluster

    from pipeline.mcpc import runners as mcpc
    from pipeline.runtime.inbox import Inbox

    ref = pipeline.plan(store, **MISSION, client="synchronous", **SMALL)

    def same(client):
        t = pipeline.plan(store, **MISSION, client=client, **SMALL)
        assert np.array_equal(t.cells, ref.cells) and t.length_m == ref.length_m

    def fail(*args, **kwargs):
        raise RuntimeError("the disk went away")

    with (
        LocalCluster(
            n_workers=2, threads_per_worker=1, processes=False, dashboard_address=":0"
        ) as cluster,
        Client(cluster) as client,
    ):
        same(client)
        with monkeypatch.context() as mp:
            mp.setattr(
                "pipeline.runtime.inbox.POLL", 30.0
            )  # the watch would take 30 s: the note is seen
            mp.setattr(mcpc, "read_section", fail)
            t0 = time.perf_counter()
            with pytest.raises(RuntimeError, match="the disk went away"):
                pipeline.plan(store, **MISSION, client=client, **SMALL)
            assert time.perf_counter() - t0 < 15.0
            mp.setattr(
                "pipeline.runtime.inbox.POLL", 0.1
            )  # no note: the watch sees the failed futures
            mp.setattr(mcpc, "post", lambda *args: None)
            with pytest.raises(RuntimeError, match="the disk went away"):
                pipeline.plan(store, **MISSION, client=client, **SMALL)
            mp.undo()  # still no post: the watch sees the futures done
            mp.setattr("pipeline.runtime.inbox.POLL", 0.1)
            mp.setattr(mcpc, "post", lambda *args: None)
            same(client)
        same(client)  # the queue serves again (late posts of the failed runs passed over)
        assert Inbox.take(client) is not None
        client.run_on_scheduler(
            lambda dask_scheduler: [
                dask_scheduler.handlers.pop(k) for k in ("queue_create", "queue_put", "queue_get")
            ]
        )
        same(client)  # its queue has no routes now: gathered, and not tried again
        assert Inbox.take(client) is None
        same(client)
        with Client(cluster) as other:  # a new client: it has no queue yet, and gets none
            same(other)
            assert Inbox.take(other) is None
            same(other)
