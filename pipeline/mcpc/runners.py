"""Where a mission's sections are planned: in this process (one thread, or the process's
section threads, each taking sections left in the others' runs), or as dask tasks on a cluster
that post their results to the client's inbox; each section's window read from the maps store
ahead of its search.
"""

from __future__ import annotations

import sys
import threading
import time
import uuid
import weakref
from collections import deque
from concurrent.futures import Future
from dataclasses import dataclass, field, replace

import numpy as np

from ..exceptions import PipelineError, UnreachableGoalError
from ..params import CELL_SIZE, check_planner
from ..planners.endpoints import (
    check_arrays,
)
from ..planners.window import search_path
from ..runtime.inbox import Inbox, post
from ..runtime.share import Claims, ThreadClaims, split
from ..runtime.threads import cores, shared_pool
from ..store.maps_store import MapsStore
from ..trajectory import Status
from .algorithm import _grow


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
        return self.status == Status.OK


def read_section(store: MapsStore, section: Section) -> tuple:
    """The layers of a section's window read from the store by this process and checked
    (:func:`~pipeline.planners.endpoints.check_arrays`), with the seconds that took: ``((safety,
    ridge, passable, the landmark layers or None), seconds)``, or ``(the error, seconds)``
    when the layers fail the check. Checked here, where they are read: in one process that is
    the helper thread of :func:`_section_batch`, on the core whose cache holds them, not on
    the searching core."""
    r0, r1, c0, c1 = (int(v) for v in section.window)
    t0 = time.perf_counter()
    surface = store.window("safety", r0, r1, c0, c1)
    ridge = store.window("ridge", r0, r1, c0, c1)
    ok = store.window("passable", r0, r1, c0, c1)
    lm = None
    active = store.active_landmarks(section.start, section.goal, section.landmarks)
    if active:  # (none under a rated depth, whose surface the layers do not measure)
        lm = np.stack([store.landmark_window(i, r0, r1, c0, c1) for i in active])
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
    for a run of sections, not for each of them."""
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
        return SectionResult(Status.FAILED, section.window, message=str(layers), read_s=read_s)
    if error is not None:
        return SectionResult(Status.FAILED, section.window, message=error, read_s=read_s)
    surface, ridge, ok, lm = layers
    s = (int(section.start[0]) - r0, int(section.start[1]) - c0)
    g = (int(section.goal[0]) - r0, int(section.goal[1]) - c0)
    try:
        # a whole map's search proves the mission's bound (_plan_whole); a section's is unused
        whole = (r0, r1, c0, c1) == (0, store.shape[0], 0, store.shape[1])
        p = search_path(surface, ridge, ok, s, g, a, planner, omega, lm, (r0, c0), whole)
    except PipelineError as e:
        return SectionResult(Status.FAILED, section.window, message=str(e), read_s=read_s)
    return SectionResult(
        Status.OK,
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
    spare core of a process that plans alone, ``client="synchronous"``, that halved a 10000^2
    mission's fixed cost (its time less its sections' searches; CHANGELOG.md,
    "Measurements"). A worker's threads are the cluster's parallelism,
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
# read waited for it
READ_AHEAD = 2


class _Reader:
    """The helper thread's claim: held by the batch (or mission) whose windows it reads.

    While it is held, the interpreter hands the GIL between threads every
    :data:`READ_SWITCH_S` at most (Python's default: 5 ms): the helper's reads and this thread's
    work between searches (snapping the joints, a section's bookkeeping) are both Python, and a
    thread that wants the GIL waited up to the default interval for the other, and the
    helper's reads took several times as long as alone (CHANGELOG.md, "Measurements"). The
    interval is set back when the claim ends (a value set meanwhile elsewhere is then
    overwritten)."""

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
    their own. :meth:`close` drops what was not taken (a mission that failed first). The
    reads, the longer of the two threads' work, would otherwise start only after the
    snapping."""

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
        # one job reads every window in turn, each into a future of its own: a submission a
        # window held this thread several times as long as the futures alone
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
    done, takes sections left in the other runs (:mod:`pipeline.runtime.share`). Two tasks per
    thread cost more than one per thread (more round trips, and chunks decoded by both
    workers; CHANGELOG.md, "Measurements"). The tasks'
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
# client: asking is a round trip before the mission's tasks can go. A count that is a second
# old is harmless: with fewer threads than tasks the tasks run in turn, each its own run
# (pipeline.runtime.share); with more, some stay idle.
_SLOTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

# The section tasks of the last call of ``_run`` per client, released by the next call after it
# submits its own tasks. A client sends at most one batch of messages every 10 ms: releasing a
# mission's futures as it returns sends one, and the next mission's tasks, submitted right
# after, waited for the next batch (a task's round trip then more than doubled). Holding one
# mission's small results a little longer costs nothing.
_HELD: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

SLOTS_SECONDS = 1.0


def _slots(client) -> int:
    """How many section tasks a mission runs on ``client``: its cluster's worker threads."""
    now = time.monotonic()
    got = _SLOTS.get(client)
    if got is None or now - got[0] > SLOTS_SECONDS:
        got = (now, max(1, sum(client.nthreads().values())))
        _SLOTS[client] = got
    return got[1]


_HELD_LOCK = threading.Lock()


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
