"""MCPC: map compression and parallel computing (docs/method.md section 6, the paper's Algorithm 3).

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
- ``margin = max(rho, section_size // 8)``: room on each side of a section's bounding square
  for the fine path to leave the coarse one (to follow a ridge, or round an obstacle the coarse
  map smoothed away). A failing section is retried with the margin doubled. A window's area per
  section is ``(1 + 2 margin / section_size)^2`` section squares, and a section's searches
  cover much of its window (the Lagrangian planner's off-ridge bound all of it): a quarter
  (2.25 squares, the default until results revision 3) against an eighth (1.56) took 0.9-1.2x
  the time with RA* and 1.4-1.5x with the Lagrangian planner, for at most 0.6 points more
  ridge on the benchmark maps, with the same missions certified (benchmarks/RESULTS.md, "One
  mission against pyastar2d").
"""

from __future__ import annotations

import math
import sys
import threading
import time
import uuid
import weakref
from collections import deque
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from numbers import Integral

import numpy as np

from .._types import Cell, ClientLike, Maps, Pair
from ..exceptions import InvalidParameterError, PipelineError, UnreachableGoalError
from ..params import CELL_SIZE, PLANNING, check_planner
from ..planners.core import (
    NO_PASSABLE,
    Trajectory,
    check_arrays,
    heuristic,
    nearest_passable,
    not_passable_error,
    off_map_error,
    path_metrics,
)
from ..planners.registry import PLANNERS
from ..planners.window import search_path, search_window
from ..runtime.cluster import get_client
from ..runtime.inbox import Inbox, post
from ..runtime.jit import njit
from ..runtime.share import Claims, ThreadClaims, split
from ..runtime.threads import cores, shared_pool
from ..store.maps_store import MapsStore, open_store

__all__ = [
    "CERTIFY_TOLERANCE",
    "Section",
    "SectionResult",
    "certified",
    "coarse_rho",
    "default_parameters",
    "plan",
    "plan_section",
    "plan_sections",
    "remove_loops",
    "restore",
    "segment",
]


def default_parameters(shape, a: float) -> dict:
    """The default ``rho``, ``section_size`` and ``margin`` for a map (see the module doc)."""
    rho = max(2, math.ceil(max(shape) / 1000))
    section = max(4 * rho, math.ceil(3000.0 / a))
    return {"rho": rho, "section_size": section, "margin": default_margin(rho, section)}


def default_margin(rho: int, section_size: int) -> int:
    """The default window margin of sections of ``section_size`` at ``rho`` (the module doc)."""
    return max(rho, section_size // 8)


# --------------------------------------------------------------------------- Algorithm 3


def restore(coarse_cells: np.ndarray, rho: int, shape, start, goal) -> np.ndarray:
    """Coarse cells to fine points (docs/method.md section 6 step 3): ``(i, j) -> (i rho + rho // 2,
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
    """Cut a restored path into sections (docs/method.md section 6 step 4).

    Points are added to a section until its bounding box has a side ``>= section_size``; the
    section spans those points and the next section starts at its last point. Returns a list
    of ``(i0, i1, (r0, r1, c0, c1))``: the indices of the section's first and last point in
    ``points`` and its window (half-open, clipped to the map).
    """
    cuts = _cuts(np.ascontiguousarray(points, dtype=np.int64).reshape(-1, 2), int(section_size))
    return [
        (i0, i1, _window(rmin, rmax, cmin, cmax, margin, shape))
        for i0, i1, rmin, rmax, cmin, cmax in cuts.tolist()
    ]


@njit(cache=True)
def _cuts(pts, section_size):
    """:func:`segment`'s sections as rows ``(i0, i1, rmin, rmax, cmin, cmax)``: their first and
    last point and their points' bounding box (compiled: a Python loop over the points took
    0.5-0.8 ms of a 2000^2 mission)."""
    n = pts.shape[0]
    out = np.empty((max(n - 1, 0), 6), dtype=np.int64)
    k = 0
    i0 = 0
    while i0 < n - 1:
        rmin = rmax = pts[i0, 0]
        cmin = cmax = pts[i0, 1]
        j = i0
        while j < n - 1:
            j += 1
            r = pts[j, 0]
            c = pts[j, 1]
            rmin, rmax = min(rmin, r), max(rmax, r)
            cmin, cmax = min(cmin, c), max(cmax, c)
            if max(rmax - rmin, cmax - cmin) >= section_size:
                break
        out[k, 0] = i0
        out[k, 1] = j
        out[k, 2] = rmin
        out[k, 3] = rmax
        out[k, 4] = cmin
        out[k, 5] = cmax
        k += 1
        i0 = j
    return out[:k]


_GOLDEN = np.int64(-7046029254386353131)  # 0x9E3779B97F4A7C15 as a signed 64-bit integer


@njit(cache=True)
def _remove_loops(flat):
    """The kept indices of :func:`remove_loops`. Each cell's last position in ``keep`` sits in
    an open-addressing table (nothing is ever deleted from it): a position is the cell's
    current one when it lies in the kept prefix and ``keep`` still holds that cell there (a
    cut, then later cells, reuse the positions). numba's typed Dict, with a deletion per cell
    of each loop cut, took 0.7 ms for the 13000 cells of a 10000^2 mission."""
    size = 1
    while size < 2 * flat.size:
        size *= 2
    mask = size - 1
    keys = np.full(size, -1, dtype=np.int64)
    vals = np.empty(size, dtype=np.int64)
    keep = np.empty(flat.size, dtype=np.int64)
    n = 0
    for i in range(flat.size):
        key = flat[i]
        h = (key * _GOLDEN) & mask  # Fibonacci hashing of the flat cell index (wraps)
        while keys[h] != -1 and keys[h] != key:
            h = (h + 1) & mask
        if keys[h] == key:
            p = vals[h]
            if p < n and flat[keep[p]] == key:  # a loop back to position p: cut it out
                n = p + 1
                continue
        keys[h] = key
        vals[h] = n
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


def _snapped_joints(m: MapsStore, pts, secs: list, goal, rho: int, margin: int) -> list:
    """The cells where the sections ``secs`` (:func:`segment` of the restored points
    ``pts``) meet, from the start to ``goal``: each inner joint, a restored point, moved to the
    passable cell nearest it in both windows it joins (within ``rho``, else ``4 rho``, else
    ``margin`` cells); UnreachableGoalError where there is none."""
    joints = [(int(pts[i0][0]), int(pts[i0][1])) for i0, _, _ in secs] + [goal]
    # a passable joint is its own snap: it lies in both windows (each holds its section's
    # points); one lookup for all (at 10000^2, 64 joints: 0.04 ms against 1.2 ms)
    passable = m.values("passable", joints[1:-1])
    for k in range(1, len(secs)):
        if passable[k - 1]:
            continue
        wins = (secs[k - 1][2], secs[k][2])
        snapped = None
        for radius in (rho, 4 * rho, margin):
            snapped = _snap(m, joints[k], wins, radius)
            if snapped is not None:
                break
        if snapped is None:
            raise UnreachableGoalError(
                f"no passable cell near the joint {joints[k]} between "
                f"sections {k - 1} and {k}; try mcpc=False"
            )
        joints[k] = snapped
    return joints


def _snap(m: MapsStore, cell, wins, radius: int):
    """The passable cell nearest ``cell`` inside every window of ``wins`` (within
    ``radius``), or None."""
    r0 = max(max(w[0] for w in wins), cell[0] - radius)
    r1 = min(min(w[1] for w in wins), cell[0] + radius + 1)
    c0 = max(max(w[2] for w in wins), cell[1] - radius)
    c1 = min(min(w[3] for w in wins), cell[1] + radius + 1)
    if r0 >= r1 or c0 >= c1:
        return None
    return nearest_passable(m.window("passable", r0, r1, c0, c1), cell, (r0, c0))


# --------------------------------------------------------------------------- sections


@dataclass(frozen=True)
class Section:
    """One section of a mission: its window (half-open ``(r0, r1, c0, c1)`` in fine cells),
    its start and goal cells, how many times it was planned, whether it is a merge."""

    window: tuple[int, int, int, int]
    start: tuple[int, int]
    goal: tuple[int, int]
    attempts: int = 1
    merged: bool = False
    landmarks: int = 0  # landmark layers read for the heuristic (the whole-map search)


@dataclass
class SectionResult:
    """A planned section (``status`` "ok") or the reason it has no path (``"failed"``).
    ``cells`` are map cells; ``z`` and ``ridge`` the surface height and ridge flag on each."""

    status: str
    window: tuple[int, int, int, int]
    message: str = ""
    cells: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    z: np.ndarray = field(default_factory=lambda: np.zeros(0))
    ridge: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    length_m: float | None = None
    lower_bound_m: float | None = None
    expansions: int = 0
    runtime_s: float | None = None
    read_s: float | None = None

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def read_section(store: MapsStore, section: Section) -> tuple:
    """The layers of a section's window read from the store by this process and checked
    (:func:`~pipeline.planners.core.check_arrays`), with the seconds that took: ``((safety,
    ridge, passable, the landmark layers or None), seconds)``, or ``(the error, seconds)``
    when the layers fail the check. Checked here, where they are read: in one process that is
    the helper thread of :func:`_section_batch`, on the core whose cache holds them (the check
    took 30 us a section on the searching core)."""
    r0, r1, c0, c1 = (int(v) for v in section.window)
    t0 = time.perf_counter()
    surface = store.window("safety", r0, r1, c0, c1)
    ridge = store.window("ridge", r0, r1, c0, c1)
    ok = store.window("passable", r0, r1, c0, c1)
    lm = None
    if section.landmarks:
        lm = np.stack(
            [
                store.landmark_window(i, r0, r1, c0, c1)
                for i in store.active_landmarks(section.start, section.goal, section.landmarks)
            ]
        )
    try:
        surface, ridge, ok = check_arrays(surface, ridge, ok)
    except PipelineError as e:
        return e, time.perf_counter() - t0
    return (surface, ridge, ok, lm), time.perf_counter() - t0


def plan_section(
    store: MapsStore, section: Section, planner: str, omega: float, read=None
) -> SectionResult:
    """Plan one section on its window, read from the store by this process (a dask task), or
    given as ``read`` (what :func:`read_section` returned): :func:`pipeline.plan_window`'s
    checks and search, the layers checked by :func:`read_section`."""
    return _plan_checked(store, section, *_checked(store, planner, omega), read)


def _checked(store: MapsStore, planner: str, omega: float) -> tuple:
    """``(planner, omega, cell size, None)`` checked, or ``(..., the error's message)``: once
    for a run of sections (7-13 us a section checked each time)."""
    try:
        planner, omega = check_planner(planner, omega)
        return planner, omega, CELL_SIZE.check(store.cell_size), None
    except PipelineError as e:
        return planner, omega, None, str(e)


def _plan_checked(store, section, planner, omega, a, error, read=None) -> SectionResult:
    """:func:`plan_section` with what :func:`_checked` returned."""
    r0, r1, c0, c1 = (int(v) for v in section.window)
    layers, read_s = read_section(store, section) if read is None else read
    if isinstance(layers, PipelineError):
        return SectionResult("failed", section.window, message=str(layers), read_s=read_s)
    if error is not None:
        return SectionResult("failed", section.window, message=error, read_s=read_s)
    surface, ridge, ok, lm = layers
    s = (int(section.start[0]) - r0, int(section.start[1]) - c0)
    g = (int(section.goal[0]) - r0, int(section.goal[1]) - c0)
    try:
        # a whole map's search proves the mission's bound (_plan_whole); a section's is unused
        whole = (r0, r1, c0, c1) == (0, store.shape[0], 0, store.shape[1])
        p = search_path(surface, ridge, ok, s, g, a, planner, omega, lm, (r0, c0), whole)
    except PipelineError as e:
        return SectionResult("failed", section.window, message=str(e), read_s=read_s)
    return SectionResult(
        "ok",
        section.window,
        cells=p.cells,
        z=p.z,
        ridge=p.on_ridge,
        length_m=p.length_m,
        lower_bound_m=p.lower_bound_m,
        expansions=p.expansions,
        runtime_s=p.runtime_s,
        read_s=read_s,
    )


def _section_batch(
    store: MapsStore, sections: list, planner: str, omega: float, reads=None
) -> list:
    """Several consecutive sections in one task (they share chunks; one task's overhead). Out
    of a dask worker, the next windows (:data:`READ_AHEAD`) are read and checked by a helper
    thread while this one is searched (the searches and the reads release the GIL): on the
    spare core of a process that plans alone, ``client="synchronous"``, a 10000^2 mission's
    fixed cost (its time less its sections' searches) went from 20 ms to 10
    (benchmarks/RESULTS.md, "One mission"). A worker's threads are the cluster's parallelism,
    so a task plans its sections with its own thread only; so does a batch that finds the
    helper busy with another (``plan_missions`` in client threads). ``reads``: the reads of
    the first windows submitted already, by a caller that holds the helper (``_READER``,
    released here; :class:`_ReadAhead`)."""
    checked = _checked(store, planner, omega)
    if reads is None and (len(sections) < 2 or _in_worker() or not _READER.acquire(blocking=False)):
        return [_plan_checked(store, sec, *checked) for sec in sections]
    ahead: deque = deque(reads or ())  # the reads queued, READ_AHEAD at least
    try:
        pool = shared_pool("section-reads", 1)
        out = []
        queued = len(ahead)  # the sections whose read was submitted
        for sec in sections:
            while queued < len(sections) and len(ahead) < READ_AHEAD + 1:
                ahead.append(pool.submit(read_section, store, sections[queued]))
                queued += 1
            out.append(_plan_checked(store, sec, *checked, ahead.popleft().result()))
        return out
    finally:
        for fut in ahead:
            fut.cancel()  # a batch that stopped early (an error) leaves no read queued
        _READER.release()


# windows read ahead of the section being searched: with one, a search shorter than the next
# read waited for it (3.8 ms a 10000^2 mission)
READ_AHEAD = 2


class _Reader:
    """The helper thread's claim: held by the batch (or mission) whose windows it reads.

    While it is held, the interpreter hands the GIL between threads every
    :data:`READ_SWITCH_S` at most (Python's default: 5 ms): the helper's reads and this thread's
    work between searches (snapping the joints, a section's bookkeeping) are both Python, and a
    thread that wants the GIL waited up to the default interval for the other. At 10000^2 the
    helper's first window was not ready 2.4 ms after the sections began, though its reads
    started before the snapping (1.2 ms), and its 65 windows took 17 ms against 6.4 ms alone.
    Measured there (30 missions, in this process, the three intervals in turn, twice): median
    28.9 ms a mission at 5 ms, 26.2-26.6 ms at 0.5 ms, 26.3-28.7 ms at 0.1 ms; the interval is
    set back when the claim ends (a value set meanwhile elsewhere is then overwritten)."""

    def __init__(self):
        self.lock = threading.Lock()
        self.saved = None

    def acquire(self, blocking: bool = True) -> bool:
        if not self.lock.acquire(blocking):
            return False
        self.saved = sys.getswitchinterval()
        if self.saved > READ_SWITCH_S:
            sys.setswitchinterval(READ_SWITCH_S)
        return True

    def release(self) -> None:
        saved, self.saved = self.saved, None
        if saved is not None and saved > READ_SWITCH_S:
            sys.setswitchinterval(saved)
        self.lock.release()

    def __enter__(self):
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()


READ_SWITCH_S = 0.0005
_READER = _Reader()


def _in_worker() -> bool:
    """Whether this thread runs a dask worker's task."""
    distributed = sys.modules.get("distributed")
    if distributed is None:
        return False
    try:
        distributed.get_worker()
    except ValueError:
        return False
    return True


def _shared_batch(
    store: MapsStore,
    sections: list,
    planner: str,
    omega: float,
    token: str,
    me: int,
    bounds,
    inbox: str | None = None,
) -> list:
    """Run ``me`` of ``sections`` (split at ``bounds``) in one task, then sections left in
    the other runs, taken from their backs (:mod:`pipeline.runtime.share`): ``(index,
    result)`` pairs, also posted to ``inbox`` (:mod:`pipeline.runtime.inbox`; on an error, a
    note saying so)."""
    out = []
    checked = _checked(store, planner, omega)
    try:
        with Claims(token, me, bounds) as claims:
            while (i := claims.next()) is not None:
                out.append((i, _plan_checked(store, sections[i], *checked)))
    except BaseException:
        post(inbox, token, me, None)
        raise
    post(inbox, token, me, out)
    return out


class _ReadAhead:
    """In one process (``client="synchronous"``): the windows of a mission's sections read by
    the helper thread of :func:`_section_batch` from the moment segmentation has cut them,
    all of them in turn, while this thread snaps the joints (the windows do not depend on the
    joints). A mission's first run of sections takes the reads (:meth:`run`); the retries read
    their own. :meth:`close` drops what was not taken (a mission that failed first). At
    10000^2 the snapping takes this thread 2.3 ms a mission, and the reads, the longer of the
    two threads' work, started only after it."""

    def __init__(self, store: MapsStore, futures: list):
        self.store = store
        self.futures = futures

    @classmethod
    def start(cls, client, store: MapsStore, windows: list):
        """The reads of ``windows``, or None: on a cluster, with one window, or when the
        helper thread reads for another mission."""
        if client != "synchronous" or len(windows) < 2 or _in_worker():
            return None
        if not _READER.acquire(blocking=False):
            return None
        # one job reads every window in turn, each into a future of its own: 65 submissions
        # at 10000^2 held this thread 0.7-1.0 ms, the futures alone take 0.1 ms
        futures = [Future() for _ in windows]
        try:
            shared_pool("section-reads", 1).submit(_read_windows, store, windows, futures)
        except BaseException:  # the pool refused (the interpreter exiting): the helper freed
            cls._drop(futures)
            raise
        return cls(store, futures)

    def run(self, sections: list, planner: str, omega: float) -> list:
        futures, self.futures = self.futures, None
        if futures is not None and len(futures) != len(sections):  # not this mission's run
            self._drop(futures)
            futures = None
        return _section_batch(self.store, sections, planner, omega, futures)

    def close(self) -> None:
        futures, self.futures = self.futures, None
        if futures is not None:
            self._drop(futures)

    @staticmethod
    def _drop(futures) -> None:
        for fut in futures:
            fut.cancel()  # those not started; the helper is free again for the next batch
        _READER.release()


def _read_windows(store: MapsStore, windows: list, futures: list) -> None:
    """:func:`read_section` of each window into its future, in turn; a future cancelled
    before its turn is skipped."""
    for w, fut in zip(windows, futures, strict=True):
        if not fut.set_running_or_notify_cancel():
            continue
        try:  # a read needs the window only (a mission's sections read no landmark layer)
            fut.set_result(read_section(store, Section(w, (w[0], w[2]), (w[0], w[2]))))
        except BaseException as exc:  # noqa: BLE001 - handed to the section that waits for it
            fut.set_exception(exc)


def _threaded(store: MapsStore, sections: list, planner: str, omega: float) -> list:
    """In this process (``client="threads"``): ``sections`` split into one run of consecutive
    sections per core, this thread planning the first and helper threads the others
    (:func:`pipeline.runtime.threads.shared_pool` ``"sections"``), each taking sections left
    in the others' runs from their backs once its own is done
    (:class:`pipeline.runtime.share.ThreadClaims`);
    the searches release the GIL. A helper that has not started when this thread finds
    nothing left (the pool busy with another mission's sections, ``plan_missions``) is
    cancelled: its run was taken by the others. In a dask worker, one thread plans them all
    (the worker's threads are the cluster's parallelism)."""
    k = min(len(sections), cores())
    if k < 2 or _in_worker():
        return _section_batch(store, sections, planner, omega)
    checked = _checked(store, planner, omega)
    claims = ThreadClaims(split(len(sections), k))
    results: list = [None] * len(sections)

    def plan_run(me: int) -> None:
        while (i := claims.next(me)) is not None:
            results[i] = _plan_checked(store, sections[i], *checked)

    pool = shared_pool("sections", max(1, cores() - 1))
    helpers = [pool.submit(plan_run, me) for me in range(1, k)]
    try:
        plan_run(0)
    finally:
        for fut in helpers:
            fut.cancel()  # not started: its run is planned already (or this thread failed)
    for fut in helpers:
        if not fut.cancelled():
            fut.result()  # a helper's error (a bug: a section's own errors are its result)
    return results


def _run(client, store: MapsStore, sections: list, planner: str, omega: float) -> list:
    """Plan ``sections``; on a cluster as one task per worker thread, each a run of
    consecutive sections (they share chunks, which the worker then decodes once) that, once
    done, takes sections left in the other runs (:mod:`pipeline.runtime.share`). Measured on 2
    workers (benchmarks/RESULTS.md, "One mission"): two tasks per thread cost 30-40 % more
    than one per thread (more round trips, and chunks decoded by both workers). The tasks'
    results come through a queue on the scheduler (:mod:`pipeline.runtime.inbox`), sooner than
    through their futures, which are gathered when the queue cannot serve. In one process a
    :class:`_ReadAhead` of the mission plans its first run with the windows it read."""
    if isinstance(client, _ReadAhead):
        return client.run(sections, planner, omega)
    if client == "synchronous":
        return _section_batch(store, sections, planner, omega)
    if client == "threads":
        return _threaded(store, sections, planner, omega)
    k = min(len(sections), _slots(client))
    bounds = split(len(sections), k)
    token = uuid.uuid4().hex
    inbox = Inbox.take(client)
    futures = client.map(
        _shared_batch,
        [store] * k,
        [sections] * k,
        [planner] * k,
        [omega] * k,
        [token] * k,
        range(k),
        [bounds] * k,
        [inbox.name if inbox else None] * k,
        pure=False,
    )
    # the previous call's tasks are released only now, behind these: see _HELD
    with _HELD_LOCK:
        previous = _HELD.get(client)
        _HELD[client] = futures
    del previous
    parts = None
    if inbox:
        parts = inbox.collect(futures, token, k)
        inbox.give_back()
    if parts is None:
        parts = client.gather(futures)
    results: list = [None] * len(sections)
    for part in parts:
        for i, r in part:
            results[i] = r
    # a section claimed by a task that was lost with its worker (and run again elsewhere)
    missing = [i for i, r in enumerate(results) if r is None]
    if missing:
        again = client.submit(
            _section_batch, store, [sections[i] for i in missing], planner, omega, pure=False
        )
        for i, r in zip(missing, again.result(), strict=True):
            results[i] = r
    return results


# The worker threads of a client's cluster, asked of the scheduler at most once a second per
# client: asking is a round trip before the mission's tasks can go (0.85 ms of a 23 ms mission
# at 2000^2). A count that is a second old is harmless: with fewer threads than tasks the
# tasks run in turn, each its own run (pipeline.runtime.share); with more, some stay idle.
SLOTS_SECONDS = 1.0
_SLOTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _slots(client) -> int:
    """How many section tasks a mission runs on ``client``: its cluster's worker threads."""
    now = time.monotonic()
    got = _SLOTS.get(client)
    if got is None or now - got[0] > SLOTS_SECONDS:
        got = (now, max(1, sum(client.nthreads().values())))
        _SLOTS[client] = got
    return got[1]


# The section tasks of the last call of ``_run`` per client, released by the next call after it
# submits its own tasks. A client sends at most one batch of messages every 10 ms: releasing a
# mission's futures as it returns sends one, and the next mission's tasks, submitted right
# after, waited for the next batch (a task's round trip 10.4 ms back to back on 2 local workers,
# 4.2 ms when the stream is idle). Holding one mission's small results a little longer costs
# nothing.
_HELD: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_HELD_LOCK = threading.Lock()


# --------------------------------------------------------------------------- plan


def coarse_rho(m: MapsStore, rho=None) -> int:
    """The compression factor a mission on ``m`` uses: ``rho``, checked, or the map's default
    (:func:`default_parameters`)."""
    rho = (
        default_parameters(m.shape, m.cell_size)["rho"] if rho is None else PLANNING.rho.check(rho)
    )
    if rho > min(m.shape):
        raise InvalidParameterError(
            f"`rho` ({rho}) must not exceed the map's shorter side ({min(m.shape)} cells)"
        )
    return rho


def _check_args(planner, omega, m: MapsStore, rho, section_size, margin):
    planner, omega = check_planner(planner, omega)
    d = default_parameters(m.shape, m.cell_size)
    rho = coarse_rho(m, rho)
    if section_size is None:
        section_size = max(4 * rho, d["section_size"])
    section_size = PLANNING.section_size.check(section_size)
    if section_size < 2 * rho:
        raise InvalidParameterError(
            f"`section_size` ({section_size}) must be at least 2 * rho "
            f"({2 * rho}): a section spans at least two coarse cells"
        )
    if margin is None:
        margin = default_margin(rho, section_size)
    margin = PLANNING.margin.check(margin)
    return planner, omega, rho, section_size, margin


def _cell(name, value) -> tuple[int, int]:
    try:
        r, c = value
        if not all(isinstance(v, Integral) and not isinstance(v, bool) for v in (r, c)):
            raise TypeError
    except (TypeError, ValueError):
        raise InvalidParameterError(
            f"`{name}` must be a cell (row, col) of integers, got {value!r}"
        ) from None
    return int(r), int(c)


def _check_endpoints(m: MapsStore, start, goal):
    rows, cols = m.shape
    out = []
    for name, cell in (("start", start), ("goal", goal)):
        r, c = _cell(name, cell)
        if not (0 <= r < rows and 0 <= c < cols):
            raise off_map_error(name, r, c, m.shape)
        out.append((r, c))
    passable = m.values("passable", out)
    if passable.all():  # one lookup; a window only to name the nearest cell
        return out
    for name, (r, c), here in zip(("start", "goal"), out, passable, strict=True):
        if here:
            continue  # passable: no window read for it
        h = 64
        r0, r1, c0, c1 = max(r - h, 0), min(r + h + 1, rows), max(c - h, 0), min(c + h + 1, cols)
        ok = m.window("passable", r0, r1, c0, c1)
        if not ok[r - r0, c - c0]:
            raise not_passable_error(
                name,
                r,
                c,
                nearest_passable(ok, (r, c), (r0, c0)),
                NO_PASSABLE if m.passable_cells == 0 else f"no passable cell within {h} cells",
            )
    return out


def _finish(
    m: MapsStore, results: list, planner, omega, start, goal, expansions, t0, extra, lower: float
) -> Trajectory:
    """Stitch section results (dropping the duplicated joints), cut any loops, measure;
    ``lower`` is the proven lower bound on the whole map's optimum known so far."""
    cells = np.vstack([r.cells if k == 0 else r.cells[1:] for k, r in enumerate(results)])
    z = np.concatenate([r.z if k == 0 else r.z[1:] for k, r in enumerate(results)])
    rdg = np.concatenate([r.ridge if k == 0 else r.ridge[1:] for k, r in enumerate(results)])
    keep = remove_loops(cells)
    extra["loop_cells_removed"] = int(len(cells) - len(keep))
    cells, z, rdg = cells[keep], z[keep], rdg[keep]
    length, ridge_len, ratio = path_metrics(cells, z, rdg, m.cell_size)
    a = m.cell_size
    h0 = heuristic(a, start[0], start[1], goal[0], goal[1], True)
    points = np.column_stack([m.x[cells[:, 1]], m.y[cells[:, 0]], z])
    return Trajectory(
        cells=cells,
        points=points,
        length_m=length,
        ridge_length_m=ridge_len,
        ridge_ratio=ratio,
        lower_bound_m=float(max(h0, lower)),
        expansions=int(expansions),
        runtime_s=time.perf_counter() - t0,
        planner=planner,
        omega=float(omega),
        extra=extra,
    )


def plan(
    maps: Maps,
    start: Cell | None = None,
    goal: Cell | None = None,
    *,
    start_xy: Pair | None = None,
    goal_xy: Pair | None = None,
    start_lonlat: Pair | None = None,
    goal_lonlat: Pair | None = None,
    planner: str = PLANNING.planner.default,
    omega: float = PLANNING.omega.default,
    mcpc: bool = PLANNING.mcpc.default,
    rho: int | None = None,
    section_size: int | None = None,
    margin: int | None = None,
    coarse_planner: str = PLANNING.coarse_planner.default,
    coarse_weight: float = PLANNING.coarse_weight.default,
    repair_max_cells: int = PLANNING.repair_max_cells.default,
    client: ClientLike = None,
) -> Trajectory:
    """Plan a mission on a maps store, coarse to fine (MCPC) or in one window, and certify it.

    Certification: ``lower_bound_m`` is a proven lower bound on the shortest safe path ``L*``
    between start and goal on the whole map (the larger of the octile distance, the landmark
    bound of the store and, for a search of the whole map, the planner's own bound). The
    status is ``"ok"`` only when ``length_m <= omega * lower_bound_m`` (up to a relative
    ``CERTIFY_TOLERANCE`` for floating point), which proves ``length_m <= omega * L*``. A
    stitched MCPC path that is not certified is planned again on the whole map (whose search
    proves its own bound) when the map has at most ``repair_max_cells`` cells; otherwise it is
    returned with status ``"uncertified"`` and the proven ratio in ``message``.

    Parameters
    ----------
    maps : path, xarray.Dataset or MapsStore
        A maps store (:func:`pipeline.build_maps`), the Dataset :func:`pipeline.open_maps`
        returned for it, or its :class:`pipeline.store.maps_store.MapsStore`.
    start, goal : (row, col)
        Fine cells; or, instead of either, as a job file gives them:
    start_xy, goal_xy : (x, y)
        Map coordinates (metres, the maps' CRS).
    start_lonlat, goal_lonlat : (lon, lat)
        WGS84 longitude and latitude (the maps need a CRS). Each end in exactly one form.
    planner : str
        The planner of every section (and of the whole map with ``mcpc=False``): a name of
        :data:`pipeline.planners.PLANNERS`.
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
    coarse_weight : float
        For the bounded planners (wastar, ra_star, lagrangian) the coarse A* is weighted A* of
        weight ``min(coarse_weight, omega)`` (1: exact A*, as in the paper): the coarse path
        only guides the sections, and at 1.1 it expands 1/90-1/40 of the cells of the exact
        search (median 0.2-0.4 ms instead of 8-13 ms on the coarse grids of 1000^2 of the
        benchmark maps) for a path at most 10 % longer than the coarse optimum (0.07-1.2 %,
        at most 3.6 %, measured). At 1.05 the search on the 2000^2 map's coarse grid, of 60 m
        cells, whose 3-D lengths exceed the horizontal ones by more than 5 %, took 5x as long
        (median 2.0 ms), with the same ridge and length after the sections. The optimal
        planners (astar, dijkstra) keep the exact coarse A*: their stitched paths follow the
        coarse route, and a 5 % detour there is 5 % on the result. Other coarse planners run
        with the mission's omega.
    repair_max_cells : int
        The largest map (rows x cols) on which an uncertified MCPC path is planned again on
        the whole map; 0 never does.
    client : None, "synchronous", "threads", scheduler address or distributed.Client
        Where the sections run (see :func:`pipeline.runtime.cluster.get_client`). None: the dask
        client this process made current, if there is one, else this process's threads (no
        cluster is started for one mission: a plain script needs no main guard).

    Returns
    -------
    Trajectory
        ``status`` "ok" (certified) or "uncertified"; ``certified_ratio`` is ``length_m /
        lower_bound_m``. ``extra`` holds the parameters, the coarse path, every section
        (window, attempts, times), the timings of the stages and, when the path was repaired,
        ``extra["repair"]``.

    Examples
    --------
    >>> t = pipeline.plan("maps.zarr", (120, 80), (9800, 9900), omega=2.0)  # doctest: +SKIP
    """
    t0 = time.perf_counter()
    m = open_store(maps)
    planner, omega, rho, section_size, margin = _check_args(
        planner, omega, m, rho, section_size, margin
    )
    check_planner(coarse_planner, omega, "coarse_planner")
    coarse_weight = PLANNING.coarse_weight.check(coarse_weight)
    mcpc = PLANNING.mcpc.check(mcpc)
    repair_max_cells = PLANNING.repair_max_cells.check(repair_max_cells)
    given = {
        k: v
        for k, v in dict(
            start=start,
            goal=goal,
            start_xy=start_xy,
            goal_xy=goal_xy,
            start_lonlat=start_lonlat,
            goal_lonlat=goal_lonlat,
        ).items()
        if v is not None
    }
    from ..missions import endpoint_cells

    ends = endpoint_cells(m, given)  # as a job file gives them
    start, goal = _check_endpoints(m, ends["start"], ends["goal"])
    # the components layer proves reachability at once, either way (_Reach)
    reach = _Reach(m, start, goal)
    run_on = get_client(client, own="threads")  # no cluster of its own for one mission
    extra: dict = {
        "mcpc": bool(mcpc),
        "rho": rho,
        "section_size": section_size,
        "margin": margin,
        "coarse_planner": coarse_planner,
        "coarse_weight": coarse_weight,
    }
    bound = _Bound(m, start, goal, extra)
    if not mcpc:
        reach.check()
        return _done(m, _plan_whole(m, run_on, planner, omega, start, goal, t0, extra, bound))
    try:
        t = _plan_mcpc(
            m,
            run_on,
            planner,
            omega,
            start,
            goal,
            t0,
            extra,
            rho,
            section_size,
            margin,
            coarse_planner,
            coarse_weight,
            bound,
            reach,
        )
    except UnreachableGoalError as exc:
        if not reach.check():  # reachability unknown (a store without components): as it says
            raise
        # start and goal share a component, so a path exists that the coarse map or the
        # sections missed (a passage narrower than rho cells): plan the whole map
        extra["fallback"] = f"MCPC found no path ({exc}); planned on the whole map instead"
        return _done(m, _plan_whole(m, run_on, planner, omega, start, goal, t0, extra, bound))
    if certified(t.length_m, t.lower_bound_m, omega):
        return _done(m, t)
    cells = m.shape[0] * m.shape[1]
    if cells > repair_max_cells:
        return _done(m, t, repair=f"the map's {cells} cells exceed repair_max_cells")
    # repair: one search over the whole map, whose planner proves its own bound
    tr = time.perf_counter()
    repair = {
        "reason": f"the stitched path ({t.length_m:.1f} m) is {t.length_m / t.lower_bound_m:.4f}"
        f" x the proven lower bound ({t.lower_bound_m:.1f} m), above omega = {omega:g}",
        "stitched_length_m": t.length_m,
        "stitched_ridge_ratio": t.ridge_ratio,
    }
    extra = {**t.extra, "repair": repair}
    whole = _plan_whole(m, run_on, planner, omega, start, goal, t0, extra, bound)
    repair["seconds"] = time.perf_counter() - tr
    return _done(m, whole)


class _Reach:
    """Whether a mission's start and goal lie in one passable region of the store's components
    layer, looked up in a thread from the start of the mission (on a first read of their chunks,
    0.9 ms at 10000^2) while the coarse path is searched; :meth:`check` waits for it."""

    def __init__(self, m: MapsStore, start, goal):
        self.start, self.goal = start, goal
        self.future = shared_pool("bound", 2).submit(m.components, start, goal)

    def check(self) -> bool:
        """True when start and goal share a component, False for a store without the layer;
        UnreachableGoalError when they lie apart."""
        ca, cb = self.future.result()
        if ca is None:
            return False
        if ca != cb:
            raise UnreachableGoalError(
                f"the goal is unreachable: start {self.start} and goal {self.goal} lie in "
                f"separate passable regions (components {ca} and {cb} of the maps store)"
            )
        return True


class _Bound:
    """The landmark bound of a mission (:meth:`MapsStore.lower_bound`), read in a thread while
    the coarse path and the sections are planned (it decodes one chunk of every landmark layer
    at each end, 16 chunks: about as long as the coarse search); ``value()`` waits for it and
    records it and its time in ``extra``."""

    def __init__(self, m: MapsStore, start, goal, extra: dict):
        self.extra = extra
        self.future = shared_pool("bound", 2).submit(self._read, m, start, goal)

    @staticmethod
    def _read(m, start, goal):
        t0 = time.perf_counter()
        return m.lower_bound(start, goal), time.perf_counter() - t0

    def value(self) -> float:
        bound, seconds = self.future.result()
        self.extra["landmark_bound_m"] = bound
        self.extra["bound_s"] = seconds
        return bound


# ``length <= omega * lower`` is checked up to this relative tolerance: the floating point of
# the lengths, and A*'s tie-breaking (within 1 + TIE of the optimum, TIE = 1e-10)
CERTIFY_TOLERANCE = 1e-9


def certified(length: float, lower: float, omega: float) -> bool:
    """Whether ``length <= omega * lower`` (up to ``CERTIFY_TOLERANCE``): with ``lower`` a
    proven lower bound on the optimum, the proof that ``length <= omega * L*``."""
    return length <= omega * lower * (1.0 + CERTIFY_TOLERANCE)


def _done(m, t: Trajectory, repair: str | None = None) -> Trajectory:
    """:func:`_certify`, and the maps' CRS kept with the trajectory (``extra["crs_wkt"]``:
    :meth:`Trajectory.to_geodataframe` gives its points in it)."""
    if m.crs_wkt:
        t.extra["crs_wkt"] = m.crs_wkt
    return _certify(t, repair)


def _certify(t: Trajectory, repair: str | None = None) -> Trajectory:
    """Set the status from the proven bound: "ok" when certified, else "uncertified" with the
    proven ratio in the message."""
    if certified(t.length_m, t.lower_bound_m, t.omega):
        t.status, t.message = "ok", ""
        return t
    ratio = t.length_m / t.lower_bound_m if t.lower_bound_m > 0 else math.inf
    t.status = "uncertified"
    t.message = (
        f"length {t.length_m:.1f} m is at most {ratio:.4f} x the shortest safe path (proven "
        f"lower bound {t.lower_bound_m:.1f} m), which does not prove the bound omega = "
        f"{t.omega:g}"
        + (f"; not repaired: {repair}" if repair else "")
        + "; plan it with mcpc=False (the whole map) to certify it"
    )
    return t


# landmark layers the whole-map search reads for its heuristic (those that bound the mission
# best). None by default: measured on the benchmark maps (benchmarks/bench_certify.py), reading
# one layer of 10000^2 takes about 3.7 s, more than the landmark heuristic saves A* there
# (6.3 s -> 4.7 s with two layers); on maze-like maps it saves far more. plan_window takes
# layers directly (``landmarks=``).
ACTIVE_LANDMARKS = 0


def _plan_whole(m, run_on, planner, omega, start, goal, t0, extra, bound) -> Trajectory:
    k = min(ACTIVE_LANDMARKS, len(m.landmarks)) if PLANNERS[planner].uses_landmarks else 0
    whole = Section((0, m.shape[0], 0, m.shape[1]), start, goal, landmarks=k)
    res = _run(run_on, m, [whole], planner, omega)[0]
    if not res.ok:
        raise UnreachableGoalError(f"no path on the whole map: {res.message}")
    extra["sections"] = [_section_summary(res, whole)]
    # a search of the whole map proves its own bound on L*
    lower = max(bound.value(), res.lower_bound_m)
    return _finish(m, [res], planner, omega, start, goal, res.expansions, t0, extra, lower)


def _plan_mcpc(
    m,
    run_on,
    planner,
    omega,
    start,
    goal,
    t0,
    extra,
    rho,
    section_size,
    margin,
    coarse_planner,
    coarse_weight,
    bound,
    reach,
) -> Trajectory:
    # 1-2: compression (cached) and the coarse path
    tc = time.perf_counter()
    co = m.coarse(rho)
    cs = _coarse_endpoint(co["passable"], (start[0] // rho, start[1] // rho))
    cg = _coarse_endpoint(co["passable"], (goal[0] // rho, goal[1] // rho))
    if cs is None or cg is None:
        which = "start" if cs is None else "goal"
        raise UnreachableGoalError(
            f"no passable coarse cell near the {which} at rho={rho}; "
            "try a smaller rho or mcpc=False"
        )
    # the coarse A* is weighted A* (see ``coarse_weight``); other planners take omega
    weight = 1.0 if PLANNERS[planner].optimal else min(coarse_weight, omega)
    if coarse_planner == "astar" and weight > 1.0:
        coarse_planner, coarse_omega = "wastar", weight
    else:
        coarse_omega = omega
    try:
        ct = search_window(  # the coarse level's arrays are checked when it is read
            co["safety"],
            co["ridge_cells"],
            co["passable"],
            cs,
            cg,
            m.cell_size * rho,
            coarse_planner,
            coarse_omega,
        )
    except UnreachableGoalError:
        raise UnreachableGoalError(
            f"no coarse path from {start} to {goal} at rho={rho}: the goal is unreachable, or "
            "reachable only through passages narrower than rho cells; try a smaller rho or "
            "mcpc=False"
        ) from None
    extra["coarse_cells"] = ct.cells.astype(np.int32)  # an array: quick to send back
    extra["coarse_s"] = time.perf_counter() - tc
    reach.check()  # before any section: a goal in another region is no mission

    # 3-5: restore, segment, snap the joints
    pts = restore(ct.cells, rho, m.shape, start, goal)
    secs = segment(pts, section_size, margin, m.shape)
    # in one process the windows are read from now on, while the joints are snapped
    ahead = _ReadAhead.start(run_on, m, [w for _, _, w in secs])
    try:
        joints = _snapped_joints(m, pts, secs, goal, rho, margin)
        sections = [Section(w, joints[k], joints[k + 1]) for k, (_, _, w) in enumerate(secs)]

        # 6: plan the sections as tasks; retry failures with a doubled margin, then merged
        tp = time.perf_counter()
        sections, results = plan_sections(ahead or run_on, m, sections, planner, omega, margin)
        extra["sections_s"] = time.perf_counter() - tp
    finally:
        if ahead is not None:
            ahead.close()  # a mission that failed before its sections: its reads dropped

    # 7: stitch, then cut any loops
    extra["sections"] = [_section_summary(r, sec) for r, sec in zip(results, sections, strict=True)]
    expansions = ct.expansions + sum(r.expansions for r in results)
    # the sections' own bounds hold on their windows only: the landmark bound is the proof
    return _finish(m, results, planner, omega, start, goal, expansions, t0, extra, bound.value())


def plan_sections(
    run_on, m: MapsStore, sections: list, planner: str, omega: float, margin: int
) -> tuple[list, list]:
    """Plan ``sections`` (:class:`Section`) as tasks on ``run_on`` (docs/method.md section 6,
    steps 6-7): a section with no path is retried once with its window grown by ``margin``
    more cells on each side (the margin doubled), then merged with a neighbour into one section
    over the union of their windows grown by ``margin``; if the merged section fails too the
    mission fails. Returns the final sections and their :class:`SectionResult`.
    """
    sections = list(sections)
    results = _run(run_on, m, sections, planner, omega)
    failed = [k for k, r in enumerate(results) if not r.ok]
    if failed:
        for k in failed:
            sections[k] = replace(
                sections[k],
                window=_grow(sections[k].window, margin, m.shape),
                attempts=sections[k].attempts + 1,
            )
        again = _run(run_on, m, [sections[k] for k in failed], planner, omega)
        for k, r in zip(failed, again, strict=True):
            results[k] = r
    while True:
        failed = [k for k, r in enumerate(results) if not r.ok]
        if not failed:
            break
        k = failed[0]
        if len(sections) == 1:
            raise UnreachableGoalError(
                f"section {k} from {sections[k].start} to "
                f"{sections[k].goal} has no path: {results[k].message}"
            )
        j = k + 1 if k + 1 < len(sections) else k - 1
        lo, hi = min(k, j), max(k, j)
        if sections[lo].merged or sections[hi].merged:
            raise UnreachableGoalError(
                f"sections {lo}-{hi} from {sections[lo].start} to {sections[hi].goal} have no "
                f"path even merged with a neighbour: {results[k].message}; the goal may be "
                "unreachable (try mcpc=False to plan the whole map)"
            )
        w1, w2 = sections[lo].window, sections[hi].window
        win = _grow(
            (min(w1[0], w2[0]), max(w1[1], w2[1]), min(w1[2], w2[2]), max(w1[3], w2[3])),
            margin,
            m.shape,
        )
        merged = Section(
            win,
            sections[lo].start,
            sections[hi].goal,
            attempts=sections[lo].attempts + sections[hi].attempts + 1,
            merged=True,
        )
        res = _run(run_on, m, [merged], planner, omega)[0]
        sections[lo : hi + 1] = [merged]
        results[lo : hi + 1] = [res]
    return sections, results


def _section_summary(r: SectionResult, sec: Section) -> dict:
    return {
        "window": [int(v) for v in r.window],
        "start": [int(v) for v in sec.start],
        "goal": [int(v) for v in sec.goal],
        "status": r.status,
        "attempts": sec.attempts,
        "merged": sec.merged,
        "length_m": r.length_m,
        "runtime_s": r.runtime_s,
        "read_s": r.read_s,
    }


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
        near = nearest_passable(
            passable[r0 : r + radius + 1, c0 : c + radius + 1], (r, c), (r0, c0)
        )
        if near is not None:
            return near
    return None
