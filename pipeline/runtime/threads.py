"""Thread pools kept by each process for the work it splits between threads (the landmark bound
beside a mission's planning, the flight's corridor reads and required heights): a pool started
for each call costs a thread start per thread, about half a millisecond each on the benchmark
machine, several times per mission."""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

_POOLS: dict = {}
_LOCK = threading.Lock()


def shared_pool(name: str, workers: int) -> ThreadPoolExecutor:
    """This process's pool ``name`` of ``workers`` threads, started on first use and kept (a
    forked child starts its own). Its tasks must not wait on tasks of the same pool."""
    with _LOCK:
        got = _POOLS.get(name)
        if got is None or got[0] != os.getpid():
            pool = ThreadPoolExecutor(workers, thread_name_prefix=f"pipeline-{name}")
            got = _POOLS[name] = (os.getpid(), pool)
        return got[1]


def cores() -> int:
    """The cores this process may run on (its CPU affinity where the system tells it)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)
