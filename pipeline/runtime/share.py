"""Work sharing between the section tasks of one mission whose workers run on one host.

A mission's sections are planned as one task per worker thread, each a run of consecutive
sections (neighbours share chunks, which a worker then decodes once). Split by count, the runs
rarely cost the same: a Lagrangian section takes one search or five, so the mission waited
for the slower run, about a quarter longer than an even split on the latency benchmark's
missions (CHANGELOG.md, "Measurements"). dask balances tasks, not the items inside one, and a
task per section costs a scheduler round trip each, more than most sections.

So the runs share their work through a small file that every task of the mission opens (in
``/dev/shm`` where there is one, else the temporary directory): per run the next section from
its front and the end of what is left, under an exclusive ``flock``. A task takes its own run
from the front; when it is done it takes from the back of the run with the most left, one
section at a time, so that what each task plans stays contiguous. A claim costs microseconds.

Tasks take from each other only once both have opened the file: workers on other hosts (or
in other containers) see no file of ours and each plans just its own run, as without sharing;
the results are the same either way. A task that dies after a claim (a lost worker) leaves
its claimed sections unplanned: :mod:`pipeline.mcpc` plans any missing section again. The
last task to finish removes the file.

In one process (``client="threads"``) the runs are planned by threads, one run each, with the
same rule under a lock (:class:`ThreadClaims`).
"""

from __future__ import annotations

import os
import tempfile
import threading
from pathlib import Path

import numpy as np

try:
    import fcntl
except ImportError:  # not POSIX: each task plans its own run
    fcntl = None


def _directory() -> str:
    shm = Path("/dev/shm")
    if shm.is_dir() and os.access(shm, os.W_OK):
        return str(shm)
    return tempfile.gettempdir()


class Claims:
    """The shared claims of ``k`` runs of sections (``bounds``: run ``j`` is sections
    ``bounds[j]`` to ``bounds[j + 1] - 1``) for task ``me``; ``token`` names the mission's file.
    Use as a context manager: iterate :meth:`next` until it returns None.

    The file holds int64s: per run its front (next to take from the front), its end (one past
    the last section left) and whether its task has opened the file; then how many tasks have
    finished."""

    def __init__(self, token: str, me: int, bounds):
        self.bounds = [int(b) for b in bounds]
        self.k = len(self.bounds) - 1
        self.me = me
        self.path = os.path.join(_directory(), f"auv-pipeline-sections-{token}")
        self.fd = None
        self.mine = None  # the state without a shared file: no other run opened, this one alone

    def __enter__(self):
        if fcntl is not None:
            try:
                self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
            except OSError:
                self.fd = None  # no shared file: this run alone
        if self.fd is not None:
            try:
                with self._locked() as st:
                    st[3 * self.me + 2] = 1
            except OSError:  # a full or odd file system: this run alone
                os.close(self.fd)
                self.fd = None
        return self

    def _locked(self):
        return _Locked(self)

    def _empty(self) -> np.ndarray:
        return state(self.bounds)

    def next(self) -> int | None:
        """The next section for this task to plan, or None when none is left for it."""
        try:
            return self._claim()
        except OSError:  # the file failed us: stop here; what is left is planned again
            return None

    def _claim(self) -> int | None:
        with self._locked() as st:
            return take(st, self.k, self.me)

    def __exit__(self, *exc):
        if self.fd is None:
            return False
        try:
            with self._locked() as st:
                st[3 * self.k] += 1
                # every task that opened the file is done: nobody reads it again (a task that
                # opens it later starts a new one, with its own run left whole)
                if st[3 * self.k] >= st[2 : 3 * self.k : 3].sum():
                    try:
                        os.unlink(self.path)
                    except FileNotFoundError:  # removed already (a task that opened it late)
                        pass
        except OSError:
            pass  # the file stays behind: a few bytes named by the mission
        finally:
            os.close(self.fd)
            self.fd = None
        return False


def split(n: int, k: int) -> list[int]:
    """The bounds of ``n`` sections split into ``k`` runs of consecutive sections, as even as
    counts allow: run ``j`` is ``bounds[j]`` to ``bounds[j + 1] - 1``."""
    return np.linspace(0, n, k + 1).round().astype(int).tolist()


def state(bounds, opened: bool = False) -> np.ndarray:
    """The claims' state of the runs split at ``bounds``, none taken: per run its front, its
    end and whether its task has opened the claims (``opened``: all of them), then how many
    tasks have finished."""
    k = len(bounds) - 1
    st = np.zeros(3 * k + 1, dtype=np.int64)
    for j in range(k):
        st[3 * j] = bounds[j]
        st[3 * j + 1] = bounds[j + 1]
        st[3 * j + 2] = int(opened)
    return st


def take(st: np.ndarray, k: int, me: int) -> int | None:
    """The next section for run ``me``'s task, claimed in ``st`` (the caller holds its lock):
    the front of its own run, else the back of the opened run with the most left; None when
    none is left for it."""
    if st[3 * me] < st[3 * me + 1]:
        st[3 * me] += 1
        return int(st[3 * me] - 1)
    left = [
        (int(st[3 * j + 1] - st[3 * j]), j)
        for j in range(k)
        if j != me and st[3 * j + 2] and st[3 * j] < st[3 * j + 1]
    ]
    if not left:
        return None
    _, j = max(left)
    st[3 * j + 1] -= 1
    return int(st[3 * j + 1])


class ThreadClaims:
    """The claims of ``bounds``'s runs between threads of this process, one run per thread
    (:meth:`next` with its run): the same rule as :class:`Claims`, under a lock, every run
    open from the start: a thread that starts late, or never, has its run taken from the
    back by the others."""

    def __init__(self, bounds):
        self.k = len(bounds) - 1
        self.st = state([int(b) for b in bounds], opened=True)
        self.lock = threading.Lock()

    def next(self, me: int) -> int | None:
        with self.lock:
            return take(self.st, self.k, me)


class _Locked:
    """The claims' state, read under an exclusive lock and written back on exit (without a
    shared file, the task's own copy)."""

    def __init__(self, claims: Claims):
        self.c = claims

    def __enter__(self) -> np.ndarray:
        if self.c.fd is None:
            if self.c.mine is None:
                self.c.mine = self.c._empty()
            return self.c.mine
        fcntl.flock(self.c.fd, fcntl.LOCK_EX)
        size = 8 * (3 * self.c.k + 1)
        raw = os.pread(self.c.fd, size, 0)
        self.st = np.frombuffer(raw, dtype=np.int64).copy() if len(raw) == size else None
        if self.st is None:  # the first task here: the runs as split
            self.st = self.c._empty()
        return self.st

    def __exit__(self, *exc):
        if self.c.fd is None:
            return False
        try:
            if exc[0] is None:
                os.pwrite(self.c.fd, self.st.tobytes(), 0)
        finally:
            fcntl.flock(self.c.fd, fcntl.LOCK_UN)
        return False
