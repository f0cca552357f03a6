"""MCPC: map compression and parallel computing (SPEC section 6, the paper's Algorithm 3).

``plan`` compresses the maps by ``rho`` (block means, cached in the maps store), plans a coarse
path, restores it to fine cells, cuts it into square sections with a margin, snaps the joints
to passable cells, plans every section as one dask task that reads only its own window from the
Zarr store, and stitches the sections into one continuous, simple trajectory.

Defaults (all in fine cells; ``a`` is the cell size in metres):

- ``rho = max(2, ceil(max(rows, cols) / 1000))``: a coarse grid of at most about 1000 cells a
  side, so the coarse search is a few tens of milliseconds at any map size (10 at 10000^2, the
  paper's value).
- ``section_size = max(4 * rho, ceil(3000 / a))``: sections of about 3 km (100 cells at 30 m).
  The planning work of a mission grows as its length times the section side (a window's area
  per section); larger sections give the ridge search more room, but on the benchmark maps
  5 km sections reached the same ridge ratio as 3 km ones (44-45 %) at 1.4x the work.
- ``margin = max(rho, section_size // 4)``: room on each side of a section's bounding square
  for the fine path to leave the coarse one (to follow a ridge, or round an obstacle the coarse
  map smoothed away). A failing section is retried with the margin doubled.
"""

from __future__ import annotations

import atexit
import math
import os
import shutil
import threading
import time
import uuid
from collections import OrderedDict
from numbers import Integral
from pathlib import Path

import numpy as np
from numba import njit, types
from numba.typed import Dict

from ._validate import positive_int
from .exceptions import InvalidParameterError, PipelineError
from .planners.grid import (
    Trajectory,
    UnreachableGoalError,
    _nearest_passable,
    check_planner,
    heuristic,
    not_passable_error,
    off_map_error,
    plan_window,
)

__all__ = ["coarse_maps", "default_parameters", "plan", "plan_sections", "remove_loops",
           "resolve_client", "restore", "segment", "shutdown"]

COARSE_RIDGE_FRACTION = 0.5  # a coarse cell is a ridge cell when half its fine cells are
_CACHE_BYTES = int(os.environ.get("AUV_PIPELINE_CHUNK_CACHE_MB", "1024")) * 2**20


# --------------------------------------------------------------------------- window reads


class _ChunkCache:
    """Decoded Zarr chunks of the maps stores this process has read (LRU, bounded in bytes).

    Sections of one mission, and missions on one map, read overlapping windows: each worker
    decodes a chunk once and keeps it while it fits in the budget."""

    def __init__(self, budget: int):
        self.budget = budget
        self.used = 0
        self.items: OrderedDict = OrderedDict()
        self.arrays: dict = {}
        self.lock = threading.Lock()

    def array(self, store: str, var: str):
        key = (store, var)
        arr = self.arrays.get(key)
        if arr is None:
            import zarr

            arr = zarr.open_array(os.path.join(store, var), mode="r")
            self.arrays[key] = arr
        return arr

    def chunk(self, store: str, var: str, ci: int, cj: int) -> np.ndarray:
        key = (store, var, ci, cj)
        with self.lock:
            got = self.items.get(key)
            if got is not None:
                self.items.move_to_end(key)
                return got
        arr = self.array(store, var)
        ch, cw = arr.chunks
        block = arr[ci * ch:(ci + 1) * ch, cj * cw:(cj + 1) * cw]
        with self.lock:
            self.items[key] = block
            self.used += block.nbytes
            while self.used > self.budget and len(self.items) > 1:
                _, old = self.items.popitem(last=False)
                self.used -= old.nbytes
        return block

    def window(self, store: str, var: str, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        arr = self.array(store, var)
        ch, cw = arr.chunks
        out = np.empty((r1 - r0, c1 - c0), dtype=arr.dtype)
        for ci in range(r0 // ch, (r1 - 1) // ch + 1):
            for cj in range(c0 // cw, (c1 - 1) // cw + 1):
                blk = self.chunk(store, var, ci, cj)
                br0, bc0 = ci * ch, cj * cw
                a0, a1 = max(r0, br0), min(r1, br0 + blk.shape[0])
                b0, b1 = max(c0, bc0), min(c1, bc0 + blk.shape[1])
                out[a0 - r0:a1 - r0, b0 - c0:b1 - c0] = blk[a0 - br0:a1 - br0, b0 - bc0:b1 - bc0]
        return out

    def clear(self) -> None:
        with self.lock:
            self.items.clear()
            self.arrays.clear()
            self.used = 0


_CACHE = _ChunkCache(_CACHE_BYTES)


# --------------------------------------------------------------------------- the maps


class _Maps:
    """What the client needs of a maps store: its path, shape, cell size and coordinates."""

    def __init__(self, maps):
        import xarray as xr

        from .dem import cell_size
        from .maps import open_maps

        ds = maps if isinstance(maps, xr.Dataset) else open_maps(maps)
        store = ds.attrs.get("store")
        if not store:
            raise InvalidParameterError("`maps` must be a maps store path or a Dataset from "
                                        "pipeline.open_maps (plan reads windows from the store)")
        self.store = str(store)
        self.shape = tuple(int(v) for v in ds["safety"].shape)
        self.a = cell_size(ds["elevation"])
        self.x = np.asarray(ds["x"].values, dtype=np.float64)
        self.y = np.asarray(ds["y"].values, dtype=np.float64)
        self.ds = ds

    def window(self, var, r0, r1, c0, c1):
        return _CACHE.window(self.store, var, r0, r1, c0, c1)


_MAPS: dict = {}


def _maps(maps) -> _Maps:
    """``_Maps`` of a store path, kept per process while the store is unchanged."""
    if isinstance(maps, _Maps):
        return maps
    if isinstance(maps, str | os.PathLike):
        p = Path(maps).resolve()
        try:
            stamp = (p / "zarr.json").stat().st_mtime_ns
        except OSError:
            return _Maps(maps)  # open_maps says what is wrong
        got = _MAPS.get(p)
        if got is None or got[0] != stamp:
            got = (stamp, _Maps(p))
            _MAPS[p] = got
        return got[1]
    return _Maps(maps)


def default_parameters(shape, a: float) -> dict:
    """The default ``rho``, ``section_size`` and ``margin`` for a map (see the module doc)."""
    rho = max(2, math.ceil(max(shape) / 1000))
    section = max(4 * rho, math.ceil(3000.0 / a))
    return {"rho": rho, "section_size": section, "margin": max(rho, section // 4)}


_COARSE: dict = {}


def coarse_maps(maps, rho: int) -> dict:
    """The maps compressed by ``rho`` (SPEC section 6 step 1), as numpy arrays.

    ``safety`` is the block mean of the finite fine values, ``ridge`` the fraction of ridge
    cells, ``passable`` true where at least half the fine cells are passable (and the mean is
    finite). Blocks at the right and bottom edges may be partial. The result is written once
    into the maps store (group ``coarse-rho{rho}``) and read from there afterwards, so that
    many missions and processes share it.
    """
    import xarray as xr

    m = _maps(maps)
    rho = positive_int("rho", rho)
    key = (m.store, rho)
    if key in _COARSE:
        return _COARSE[key]
    group = Path(m.store) / f"coarse-rho{rho}"
    if not (group / "zarr.json").exists():
        ds = m.ds[["safety", "ridge", "passable"]]
        cs = ds.astype("float32").coarsen(y=rho, x=rho, boundary="pad").mean()
        out = xr.Dataset({
            "safety": cs["safety"].astype("float32"),
            "ridge": cs["ridge"].astype("float32"),
            "passable": (cs["passable"] >= 0.5) & np.isfinite(cs["safety"]),
        }).compute()
        out.attrs.update(rho=rho, source="block means of the fine maps (SPEC section 6)")
        tmp = Path(m.store) / f".coarse-rho{rho}.tmp-{uuid.uuid4().hex[:8]}"
        out.to_zarr(tmp, mode="w", zarr_format=3, consolidated=False)
        try:
            os.rename(tmp, group)
        except OSError:  # another process wrote it first: keep theirs
            shutil.rmtree(tmp, ignore_errors=True)
    ds = xr.open_zarr(m.store, group=f"coarse-rho{rho}", consolidated=False).load()
    res = {"safety": ds["safety"].values, "ridge": ds["ridge"].values,
           "passable": ds["passable"].values.astype(bool)}
    _COARSE[key] = res
    return res


# --------------------------------------------------------------------------- Algorithm 3


def restore(coarse_cells: np.ndarray, rho: int, shape, start, goal) -> np.ndarray:
    """Coarse cells to fine points (SPEC section 6 step 3): ``(i, j) -> (i rho + rho // 2,
    j rho + rho // 2)`` clipped to the map; the real start and goal replace the first and last
    point (a path of one coarse cell becomes start, goal)."""
    pts = np.asarray(coarse_cells, dtype=np.int64) * rho + rho // 2
    pts[:, 0] = np.clip(pts[:, 0], 0, shape[0] - 1)
    pts[:, 1] = np.clip(pts[:, 1], 0, shape[1] - 1)
    if len(pts) == 1:
        pts = np.vstack([pts, pts])
    pts[0] = start
    pts[-1] = goal
    return pts


def _window(rmin, rmax, cmin, cmax, margin, shape):
    """The bounding square of the box, centred on it, grown by ``margin``, clipped:
    half-open ``(r0, r1, c0, c1)``."""
    side = max(rmax - rmin, cmax - cmin)
    r0 = math.floor((rmin + rmax - side) / 2) - margin
    c0 = math.floor((cmin + cmax - side) / 2) - margin
    r1 = r0 + side + 2 * margin + 1
    c1 = c0 + side + 2 * margin + 1
    r0, c0 = min(r0, rmin), min(c0, cmin)
    r1, c1 = max(r1, rmax + 1), max(c1, cmax + 1)
    return max(r0, 0), min(r1, shape[0]), max(c0, 0), min(c1, shape[1])


def segment(points: np.ndarray, section_size: int, margin: int, shape) -> list:
    """Cut a restored path into sections (SPEC section 6 step 4).

    Points are added to a section until its bounding box has a side ``>= section_size``; the
    section spans those points and the next section starts at its last point. Returns a list
    of ``(i0, i1, (r0, r1, c0, c1))``: the indices of the section's first and last point in
    ``points`` and its window (half-open, clipped to the map).
    """
    pts = np.asarray(points)
    n = len(pts)
    out = []
    i0 = 0
    while i0 < n - 1:
        rmin = rmax = int(pts[i0, 0])
        cmin = cmax = int(pts[i0, 1])
        j = i0
        while j < n - 1:
            j += 1
            r, c = int(pts[j, 0]), int(pts[j, 1])
            rmin, rmax = min(rmin, r), max(rmax, r)
            cmin, cmax = min(cmin, c), max(cmax, c)
            if max(rmax - rmin, cmax - cmin) >= section_size:
                break
        out.append((i0, j, _window(rmin, rmax, cmin, cmax, margin, shape)))
        i0 = j
    return out


@njit(cache=True)
def _remove_loops(flat):
    where = Dict.empty(key_type=types.int64, value_type=types.int64)
    keep = np.empty(flat.size, dtype=np.int64)
    n = 0
    for i in range(flat.size):
        p = where.get(flat[i], -1)
        if p >= 0:
            for q in range(p + 1, n):
                del where[flat[keep[q]]]
            n = p + 1
            continue
        where[flat[i]] = n
        keep[n] = i
        n += 1
    return keep[:n]


def remove_loops(cells: np.ndarray) -> np.ndarray:
    """Indices that keep ``cells`` simple: where a cell recurs, the loop between its first and
    its last visit is cut out (the path stays 8-connected and only gets shorter)."""
    cells = np.asarray(cells, dtype=np.int64)
    if len(cells) == 0:
        return np.zeros(0, dtype=np.int64)
    flat = cells[:, 0] * (int(cells[:, 1].max()) + 1) + cells[:, 1]
    return _remove_loops(flat)


def _snap(m: _Maps, cell, wins, radius: int):
    """The passable cell nearest ``cell`` inside every window of ``wins`` (within
    ``radius``), or None."""
    r0 = max(max(w[0] for w in wins), cell[0] - radius)
    r1 = min(min(w[1] for w in wins), cell[0] + radius + 1)
    c0 = max(max(w[2] for w in wins), cell[1] - radius)
    c1 = min(min(w[3] for w in wins), cell[1] + radius + 1)
    if r0 >= r1 or c0 >= c1:
        return None
    return _nearest_passable(m.window("passable", r0, r1, c0, c1), cell, (r0, c0))


# --------------------------------------------------------------------------- section tasks


def _section_task(store: str, win, start, goal, planner: str, omega: float, a: float) -> dict:
    """Plan one section on its window, read from the store by this process (a dask task)."""
    r0, r1, c0, c1 = (int(v) for v in win)
    t0 = time.perf_counter()
    surface = _CACHE.window(store, "safety", r0, r1, c0, c1)
    ridge = _CACHE.window(store, "ridge", r0, r1, c0, c1)
    ok = _CACHE.window(store, "passable", r0, r1, c0, c1)
    read_s = time.perf_counter() - t0
    s = (int(start[0]) - r0, int(start[1]) - c0)
    g = (int(goal[0]) - r0, int(goal[1]) - c0)
    try:
        t = plan_window(surface, ridge, ok, s, g, cell_size=a, planner=planner, omega=omega)
    except PipelineError as e:
        return {"status": "failed", "message": str(e), "read_s": read_s, "window": list(win)}
    cells = t.cells + np.array([r0, c0])
    return {"status": "ok", "cells": cells, "z": t.points[:, 2],
            "ridge": ridge[t.cells[:, 0], t.cells[:, 1]], "length_m": t.length_m,
            "lower_bound_m": t.lower_bound_m, "expansions": t.expansions,
            "runtime_s": t.runtime_s, "read_s": read_s, "window": list(win)}


_LOCAL: dict = {}
_LOCAL_LOCK = threading.Lock()


def shutdown() -> None:
    """Close the clients and the local cluster that ``plan`` started in this process (it also
    runs at exit)."""
    with _LOCAL_LOCK:
        items = list(_LOCAL.items())
        _LOCAL.clear()
    for _, x in sorted(items, key=lambda kv: kv[0] == "cluster"):  # clients first
        try:
            x.close()
        except Exception:  # noqa: BLE001 - closing: nothing left to report to
            pass


def resolve_client(client):
    """The cluster to plan on: ``"synchronous"`` (in this process), a ``distributed.Client``,
    a scheduler address, or None: the current default client if there is one, else a
    LocalCluster of 2 single-threaded workers started once per process."""
    if isinstance(client, str) and client == "synchronous":
        return "synchronous"
    from distributed import Client

    if isinstance(client, Client):
        return client
    if isinstance(client, str):
        with _LOCAL_LOCK:
            c = _LOCAL.get(("addr", client))
            if c is None:
                try:
                    c = Client(client, timeout=10, set_as_default=False)
                except OSError as e:
                    raise PipelineError(f"cannot reach the dask scheduler at {client}: {e}; "
                                        "start it (`dask scheduler`) or pass no address to "
                                        "use a local cluster") from None
                _LOCAL[("addr", client)] = c
            return c
    if client is not None:
        raise InvalidParameterError("`client` must be None, 'synchronous', a scheduler address "
                                    f"or a distributed.Client, got {type(client).__name__}")
    try:
        from distributed import get_client

        return get_client()
    except ValueError:
        pass
    with _LOCAL_LOCK:
        if "client" not in _LOCAL:
            from distributed import LocalCluster

            cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                   dashboard_address=":0")
            _LOCAL["cluster"] = cluster
            _LOCAL["client"] = Client(cluster, set_as_default=False)
            atexit.register(shutdown)
        return _LOCAL["client"]


def _section_batch(calls: list) -> list:
    """Several consecutive sections in one task (they share chunks; one task's overhead)."""
    return [_section_task(*c) for c in calls]


def _run(client, calls: list) -> list:
    """Run section calls; on a cluster as about two tasks per worker thread, each a run of
    consecutive sections (a task costs a few milliseconds of scheduling, a small section
    about as much to plan)."""
    if client == "synchronous":
        return _section_batch(calls)
    slots = max(1, sum(client.nthreads().values()))
    k = min(len(calls), 2 * slots)
    bounds = np.linspace(0, len(calls), k + 1).round().astype(int)
    batches = [calls[bounds[i]:bounds[i + 1]] for i in range(k)]
    futures = client.map(_section_batch, batches, pure=False)
    return [r for part in client.gather(futures) for r in part]


# --------------------------------------------------------------------------- plan


def _check_args(planner, omega, m: _Maps, rho, section_size, margin):
    check_planner(planner, omega)
    d = default_parameters(m.shape, m.a)
    rho = d["rho"] if rho is None else positive_int("rho", rho)
    if rho > min(m.shape):
        raise InvalidParameterError(f"`rho` ({rho}) must not exceed the map's shorter side "
                                    f"({min(m.shape)} cells)")
    if section_size is None:
        section_size = max(4 * rho, d["section_size"])
    section_size = positive_int("section_size", section_size, minimum=2)
    if section_size < 2 * rho:
        raise InvalidParameterError(f"`section_size` ({section_size}) must be at least 2 * rho "
                                    f"({2 * rho}): a section spans at least two coarse cells")
    if margin is None:
        margin = max(rho, section_size // 4)
    margin = positive_int("margin", margin, minimum=0)
    return rho, section_size, margin


def _cell(name, value) -> tuple[int, int]:
    try:
        r, c = value
        if not all(isinstance(v, Integral) and not isinstance(v, bool) for v in (r, c)):
            raise TypeError
    except (TypeError, ValueError):
        raise InvalidParameterError(f"`{name}` must be a cell (row, col) of integers, got "
                                    f"{value!r}") from None
    return int(r), int(c)


def _check_endpoints(m: _Maps, start, goal):
    out = []
    for name, cell in (("start", start), ("goal", goal)):
        r, c = _cell(name, cell)
        rows, cols = m.shape
        if not (0 <= r < rows and 0 <= c < cols):
            raise off_map_error(name, r, c, m.shape)
        h = 64
        r0, r1, c0, c1 = max(r - h, 0), min(r + h + 1, rows), max(c - h, 0), min(c + h + 1, cols)
        ok = m.window("passable", r0, r1, c0, c1)
        if not ok[r - r0, c - c0]:
            raise not_passable_error(name, r, c, _nearest_passable(ok, (r, c), (r0, c0)),
                                     f"no passable cell within {h} cells")
        out.append((r, c))
    return out


def _finish(m: _Maps, cells, z, rdg, planner, omega, start, goal, expansions, t0, extra,
            lower=None) -> Trajectory:
    keep = remove_loops(cells)
    extra["loop_cells_removed"] = int(len(cells) - len(keep))
    cells, z, rdg = cells[keep], z[keep], rdg[keep]
    a = m.a
    if len(cells) > 1:
        d = np.diff(cells, axis=0)
        step = np.sqrt(a * a * (d ** 2).sum(axis=1) + np.diff(z.astype(np.float64)) ** 2)
        length = float(step.sum())
        ridge_len = float(step[rdg[1:]].sum())
    else:
        length = ridge_len = 0.0
    h0 = heuristic(a, start[0], start[1], goal[0], goal[1], True)
    points = np.column_stack([m.x[cells[:, 1]], m.y[cells[:, 0]], z])
    return Trajectory(cells=cells, points=points, length_m=length, ridge_length_m=ridge_len,
                      ridge_ratio=ridge_len / length if length > 0 else 0.0,
                      lower_bound_m=float(max(h0, lower or 0.0)), expansions=int(expansions),
                      runtime_s=time.perf_counter() - t0, planner=planner, omega=float(omega),
                      extra=extra)


def plan(maps, start, goal, *, planner: str = "ra_star", omega: float = 2.0, mcpc: bool = True,
         rho: int | None = None, section_size: int | None = None, margin: int | None = None,
         coarse_planner: str = "astar", client=None) -> Trajectory:
    """Plan a mission on a maps store, coarse to fine (MCPC) or in one window.

    Parameters
    ----------
    maps : path or xarray.Dataset
        A maps store (:func:`pipeline.build_maps`) or the Dataset :func:`pipeline.open_maps`
        returned for it.
    start, goal : (row, col)
        Fine cells.
    planner : {"dijkstra", "astar", "wastar", "ra_star", "lagrangian"}
        The planner of every section (and of the whole map with ``mcpc=False``).
    omega : float
        The length bound of the bounded planners, kept per section.
    mcpc : bool
        False plans the whole map in one window (one task).
    rho, section_size, margin : int, optional
        Compression factor, section side and window margin in fine cells; defaults from the
        map (module documentation).
    coarse_planner : str
        Planner of the coarse path (A*, the paper's choice). Coarse ridge cells are those whose
        block is at least half ridge.
    client : None, "synchronous", scheduler address or distributed.Client
        Where the sections run (see :func:`resolve_client`).

    Returns
    -------
    Trajectory
        ``extra`` holds the parameters, the coarse path, every section (window, attempts,
        times) and the timings of the stages.

    Examples
    --------
    >>> t = pipeline.plan("maps.zarr", (120, 80), (9800, 9900), omega=2.0)  # doctest: +SKIP
    """
    t0 = time.perf_counter()
    m = _maps(maps)
    rho, section_size, margin = _check_args(planner, omega, m, rho, section_size, margin)
    check_planner(coarse_planner, omega, "coarse_planner")
    start, goal = _check_endpoints(m, start, goal)
    run_on = resolve_client(client)
    extra: dict = {"mcpc": bool(mcpc), "rho": rho, "section_size": section_size,
                   "margin": margin, "coarse_planner": coarse_planner}
    if not mcpc:
        win = (0, m.shape[0], 0, m.shape[1])
        res = _run(run_on, [(m.store, win, start, goal, planner, float(omega), m.a)])[0]
        if res["status"] != "ok":
            raise UnreachableGoalError(f"no path on the whole map: {res['message']}")
        extra["sections"] = [_section_summary(res, dict(s=start, g=goal, attempts=1))]
        return _finish(m, res["cells"], res["z"], res["ridge"], planner, omega, start, goal,
                       res["expansions"], t0, extra, lower=res["lower_bound_m"])

    # 1-2: compression (cached) and the coarse path
    tc = time.perf_counter()
    co = coarse_maps(m, rho)
    cs = _coarse_endpoint(co["passable"], (start[0] // rho, start[1] // rho))
    cg = _coarse_endpoint(co["passable"], (goal[0] // rho, goal[1] // rho))
    if cs is None or cg is None:
        which = "start" if cs is None else "goal"
        raise UnreachableGoalError(f"no passable coarse cell near the {which} at rho={rho}; "
                                   "try a smaller rho or mcpc=False")
    try:
        ct = plan_window(co["safety"], co["ridge"] >= COARSE_RIDGE_FRACTION, co["passable"], cs,
                         cg, cell_size=m.a * rho, planner=coarse_planner, omega=omega)
    except UnreachableGoalError:
        raise UnreachableGoalError(
            f"no coarse path from {start} to {goal} at rho={rho}: the goal is unreachable, or "
            "reachable only through passages narrower than rho cells; try a smaller rho or "
            "mcpc=False") from None
    extra["coarse_cells"] = ct.cells.tolist()
    extra["coarse_s"] = time.perf_counter() - tc

    # 3-5: restore, segment, snap the joints
    pts = restore(ct.cells, rho, m.shape, start, goal)
    secs = segment(pts, section_size, margin, m.shape)
    joints = [tuple(pts[i0]) for i0, _, _ in secs] + [goal]
    for k in range(1, len(secs)):
        wins = (secs[k - 1][2], secs[k][2])
        snapped = None
        for radius in (rho, 4 * rho, margin):
            snapped = _snap(m, joints[k], wins, radius)
            if snapped is not None:
                break
        if snapped is None:
            raise UnreachableGoalError(f"no passable cell near the joint {joints[k]} between "
                                       f"sections {k - 1} and {k}; try mcpc=False")
        joints[k] = snapped
    sections = [dict(win=w, s=joints[k], g=joints[k + 1], attempts=1)
                for k, (_, _, w) in enumerate(secs)]

    # 6: plan the sections as tasks; retry failures with a doubled margin, then merged
    tp = time.perf_counter()
    sections, results = plan_sections(run_on, m, sections, planner, omega, margin)
    extra["sections_s"] = time.perf_counter() - tp

    # 7: stitch (dropping the duplicated joints), then cut any loops
    cells = np.vstack([r["cells"] if k == 0 else r["cells"][1:]
                       for k, r in enumerate(results)])
    z = np.concatenate([r["z"] if k == 0 else r["z"][1:] for k, r in enumerate(results)])
    rdg = np.concatenate([r["ridge"] if k == 0 else r["ridge"][1:]
                          for k, r in enumerate(results)])
    extra["sections"] = [_section_summary(r, sec) for r, sec in zip(results, sections,
                                                                    strict=True)]
    extra["section_bound_m"] = float(sum(r["lower_bound_m"] for r in results))
    expansions = ct.expansions + sum(r["expansions"] for r in results)
    return _finish(m, cells, z, rdg, planner, omega, start, goal, expansions, t0, extra)


def plan_sections(run_on, m: _Maps, sections: list, planner: str, omega: float, margin: int):
    """Plan ``sections`` (dicts with ``win``, ``s``, ``g``, ``attempts``) as tasks on
    ``run_on`` (SPEC section 6 steps 6-7): a section with no path is retried once with its
    window grown by ``margin`` more cells on each side (the margin doubled), then merged with a
    neighbour into one section over the union of their windows grown by ``margin``; if the
    merged section fails too the mission fails. Returns the final sections and their results.
    """
    sections = [dict(sec) for sec in sections]
    results = _run(run_on, [(m.store, sec["win"], sec["s"], sec["g"], planner, float(omega),
                             m.a) for sec in sections])
    failed = [k for k, r in enumerate(results) if r["status"] != "ok"]
    if failed:
        for k in failed:
            sec = sections[k]
            sec["win"] = _grow(sec["win"], margin, m.shape)
            sec["attempts"] += 1
        again = _run(run_on, [(m.store, sections[k]["win"], sections[k]["s"], sections[k]["g"],
                               planner, float(omega), m.a) for k in failed])
        for k, r in zip(failed, again, strict=True):
            results[k] = r
    while True:
        failed = [k for k, r in enumerate(results) if r["status"] != "ok"]
        if not failed:
            break
        k = failed[0]
        if len(sections) == 1:
            raise UnreachableGoalError(f"section {k} from {sections[k]['s']} to "
                                       f"{sections[k]['g']} has no path: "
                                       f"{results[k]['message']}")
        j = k + 1 if k + 1 < len(sections) else k - 1
        lo, hi = min(k, j), max(k, j)
        if sections[lo].get("merged") or sections[hi].get("merged"):
            raise UnreachableGoalError(
                f"sections {lo}-{hi} from {sections[lo]['s']} to {sections[hi]['g']} have no "
                f"path even merged with a neighbour: {results[k]['message']}; the goal may be "
                "unreachable (try mcpc=False to plan the whole map)")
        w1, w2 = sections[lo]["win"], sections[hi]["win"]
        win = _grow((min(w1[0], w2[0]), max(w1[1], w2[1]), min(w1[2], w2[2]),
                     max(w1[3], w2[3])), margin, m.shape)
        merged = dict(win=win, s=sections[lo]["s"], g=sections[hi]["g"], merged=True,
                      attempts=sections[lo]["attempts"] + sections[hi]["attempts"] + 1)
        res = _run(run_on, [(m.store, win, merged["s"], merged["g"], planner, float(omega),
                             m.a)])[0]
        sections[lo:hi + 1] = [merged]
        results[lo:hi + 1] = [res]
    return sections, results


def _section_summary(r: dict, sec: dict) -> dict:
    return {"window": [int(v) for v in r["window"]], "start": [int(v) for v in sec["s"]],
            "goal": [int(v) for v in sec["g"]], "status": r["status"],
            "attempts": sec["attempts"], "merged": sec.get("merged", False),
            "length_m": r.get("length_m"),
            "runtime_s": r.get("runtime_s"), "read_s": r.get("read_s")}


def _grow(win, by: int, shape):
    r0, r1, c0, c1 = win
    by = max(by, 1)
    return max(r0 - by, 0), min(r1 + by, shape[0]), max(c0 - by, 0), min(c1 + by, shape[1])


def _coarse_endpoint(passable: np.ndarray, cell):
    r = min(cell[0], passable.shape[0] - 1)
    c = min(cell[1], passable.shape[1] - 1)
    if passable[r, c]:
        return r, c
    for radius in (1, 2, 4):
        r0, c0 = max(r - radius, 0), max(c - radius, 0)
        near = _nearest_passable(passable[r0:r + radius + 1, c0:c + radius + 1], (r, c),
                                 (r0, c0))
        if near is not None:
            return near
    return None
