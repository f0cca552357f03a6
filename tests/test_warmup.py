"""The first run's up-front compilation (pipeline.warmup): announced, run in two halves on two
workers, stamped so that later runs skip it, and never fatal."""

from __future__ import annotations

import logging
import os

import pytest

from pipeline import warmup


def test_fingerprint_follows_every_source_file(tmp_path):
    (tmp_path / "a.py").write_text("x = 1\n")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "b.py").write_text("y = 2\n")
    first = warmup._fingerprint(tmp_path)
    assert warmup._fingerprint(tmp_path) == first
    st = (tmp_path / "sub" / "b.py").stat()
    os.utime(tmp_path / "sub" / "b.py", ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    touched = warmup._fingerprint(tmp_path)
    assert touched != first  # numba recompiles a touched file's kernels: so do we
    (tmp_path / "a.py").write_text("x = 10\n")
    assert warmup._fingerprint(tmp_path) not in (first, touched)


@pytest.fixture
def stamp(tmp_path, monkeypatch):
    path = tmp_path / "kernels.json"
    monkeypatch.setattr(warmup, "_stamp_path", lambda: path)
    return path


def test_compiles_once_in_two_halves_on_two_workers(local_client, stamp, caplog):
    caplog.set_level(logging.DEBUG, logger="pipeline.warmup")
    assert not warmup.is_compiled()
    seconds = warmup.ensure_compiled(local_client)
    assert seconds > 0 and warmup.is_compiled() and stamp.exists()
    text = caplog.text
    assert "compiling kernels, first run only" in text
    # each half ran on its own worker (the parts' timings come back per process)
    parts = [r for r in caplog.records if r.getMessage().startswith("warm-up parts")]
    assert len(parts) == 1
    per_process = parts[0].args[0]
    assert [sorted(p) for p in per_process] == [sorted(h) for h in warmup.HALVES]
    caplog.clear()
    assert warmup.ensure_compiled(local_client) == 0.0  # stamped: skipped, silently
    assert "compiling" not in caplog.text


def test_a_failed_warm_up_is_not_fatal(stamp, monkeypatch, caplog):
    def broken(client):
        raise OSError("no space left on device")

    monkeypatch.setattr(warmup, "_compile", broken)
    caplog.set_level(logging.INFO, logger="pipeline.warmup")
    warmup.ensure_compiled(None)
    assert "compile as they are first used instead" in caplog.text
    assert "no space left on device" in caplog.text
    assert not warmup.is_compiled()  # tried again next time


_PLAN_EVERY_PLANNER = """
import json, numpy as np, pipeline
from pipeline import landmarks
from pipeline.planners import core, ra_star
z = np.random.default_rng(1).normal(size=(40, 40)).astype(np.float32) * 50 - 3000
ok = np.ones(z.shape, bool)
rdg = np.random.default_rng(2).random(z.shape) < 0.3
for planner in ("dijkstra", "astar", "wastar", "ra_star", "lagrangian"):
    pipeline.plan_window(z, rdg, ok, (0, 0), (39, 30), cell_size=30.0, planner=planner, omega=1.5)
# at omega 1 the Lagrangian planner's searches weigh length more: the exact lengths to the goal
pipeline.plan_window(z, rdg, ok, (0, 0), (39, 30), cell_size=30.0, planner="lagrangian", omega=1.0)
kernels = (core.astar_search, core.off_ridge_to_goal, ra_star._ra_star, landmarks.dijkstra)
print(json.dumps({k.__name__: [sum(k.stats.cache_hits.values()), sum(k.stats.cache_misses.values())]
                  for k in kernels}))
"""


def test_the_planners_kernels_load_from_the_cache_in_the_next_process():
    """What one process compiles, the next loads from numba's on-disk cache: a kernel whose
    cache key numba cannot make (an omitted array argument types as its default object)
    compiled again in every process, 1-3 s a search, inside missions' recorded runtimes. The
    session's warm-up processes (tests/_warm_numba.py) compiled them: a new process that plans
    with every planner loads each kernel from the cache and compiles none."""
    import json
    import subprocess
    import sys

    run = subprocess.run(
        [sys.executable, "-c", _PLAN_EVERY_PLANNER], capture_output=True, text=True, check=True
    )
    counts = json.loads(run.stdout.strip().splitlines()[-1])
    assert {k: v[1] for k, v in counts.items()} == {k: 0 for k in counts}, counts  # none compiled
    assert all(hits > 0 for hits, _ in counts.values()), counts  # each loaded from the cache


# a process that compiles one cached kernel in the directory given (its cache: __pycache__ there)
_CACHE_CHILD = """
import sys, time
sys.path.insert(0, sys.argv[1])
import pipeline._jit  # the package's kernels compile through it
import numpy as np
import kernel
print("compiling", flush=True)
kernel.f(np.ones(3))
print("saved", flush=True)
"""


def test_a_kernel_is_saved_to_numbas_cache_under_the_lock(tmp_path):
    """numba's cache index is read, extended and written back by each save, so processes that
    save signatures of one kernel at once lose some (24 of 240 in 4 processes compiling 30
    kernels each for a dtype of their own, in step, without the lock of pipeline._jit; none
    with it). Here this process holds the cache directory's lock while a real process
    compiles a kernel: its signature reaches the cache only once the lock is released."""
    import fcntl
    import subprocess
    import sys
    import time

    from pipeline._jit import LOCK_NAME

    (tmp_path / "kernel.py").write_text(
        "from numba import njit\n\n\n@njit(cache=True)\ndef f(x):\n    return x.sum()\n"
    )
    cache = tmp_path / "__pycache__"  # numba's cache beside a writable source file
    cache.mkdir()
    root = os.path.dirname(os.path.dirname(os.path.abspath(warmup.__file__)))
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["PYTHONPATH"] = os.pathsep.join([root, os.environ.get("PYTHONPATH", "")])
    with open(cache / LOCK_NAME, "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        child = subprocess.Popen(
            [sys.executable, "-c", _CACHE_CHILD, str(tmp_path)],
            env=env,
            stdout=subprocess.PIPE,
            text=True,
        )
        assert child.stdout.readline() == "compiling\n"
        time.sleep(3.0)  # a kernel of one line compiles in a fraction of that
        assert child.poll() is None and not list(cache.glob("*.nbi")), "saved without the lock"
        fcntl.flock(lock, fcntl.LOCK_UN)
        assert child.stdout.readline() == "saved\n"
    assert child.wait(timeout=60) == 0
    assert len(list(cache.glob("kernel.f-*.nbi"))) == 1 and len(list(cache.glob("*.nbc"))) == 1
