"""The first run's up-front compilation (pipeline.jobs.warmup): announced, run in two halves
on two workers, stamped so that later runs skip it, and never fatal."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import pytest

from pipeline.jobs import warmup


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
    caplog.set_level(logging.DEBUG, logger="pipeline.jobs.warmup")
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
    def broken(client, parts):
        raise OSError("no space left on device")

    monkeypatch.setattr(warmup, "_compile", broken)
    caplog.set_level(logging.INFO, logger="pipeline.jobs.warmup")
    warmup.ensure_compiled(None)
    assert "compile as they are first used instead" in caplog.text
    assert "no space left on device" in caplog.text
    assert not warmup.is_compiled()  # tried again next time


_PLAN_EVERY_PLANNER = """
import json, numpy as np, pipeline
from pipeline.planners import bounds, ra_star, search
z = np.random.default_rng(1).normal(size=(40, 40)).astype(np.float32) * 50 - 3000
ok = np.ones(z.shape, bool)
rdg = np.random.default_rng(2).random(z.shape) < 0.3
for planner in ("dijkstra", "astar", "wastar", "ra_star", "lagrangian"):
    pipeline.plan_window(z, rdg, ok, (0, 0), (39, 30), cell_size=30.0, planner=planner, omega=1.5)
# at omega 1 the Lagrangian planner's searches weigh length more: the exact lengths to the goal
pipeline.plan_window(z, rdg, ok, (0, 0), (39, 30), cell_size=30.0, planner="lagrangian", omega=1.0)
kernels = (search.astar_search, bounds.off_ridge_to_goal, ra_star._ra_star, bounds.dijkstra)
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


def _child_env() -> dict:
    """The environment of a child process that imports this checkout's pipeline and keeps
    numba's cache beside the sources it compiles (no NUMBA_CACHE_DIR)."""
    root = str(Path(warmup.__file__).resolve().parents[2])
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["PYTHONPATH"] = os.pathsep.join([root, os.environ.get("PYTHONPATH", "")])
    return env


# a process that compiles one cached kernel in the directory given (its cache: __pycache__ there)
_CACHE_CHILD = """
import sys, time
sys.path.insert(0, sys.argv[1])
import pipeline.runtime.jit  # the package's kernels compile through it
import numpy as np
import kernel
print("compiling", flush=True)
kernel.f(np.ones(3))
print("saved", flush=True)
"""


def test_a_kernel_is_saved_to_numbas_cache_under_the_lock(tmp_path):
    """numba's cache index is read, extended and written back by each save, so processes that
    save signatures of one kernel at once lose some (24 of 240 in 4 processes compiling 30
    kernels each for a dtype of their own, in step, without the lock of pipeline.runtime.jit; none
    with it). Here this process holds the cache directory's lock while a real process
    compiles a kernel: its signature reaches the cache only once the lock is released."""
    import fcntl
    import subprocess
    import sys
    import time

    from pipeline.runtime.jit import LOCK_NAME

    (tmp_path / "kernel.py").write_text(
        "from numba import njit\n\n\n@njit(cache=True)\ndef f(x):\n    return x.sum()\n"
    )
    cache = tmp_path / "__pycache__"  # numba's cache beside a writable source file
    cache.mkdir()
    env = _child_env()
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


# a process that runs pkg.caller.twice_plus (its cache: pkg/__pycache__) with the stamps of
# pipeline.runtime.jit following the imports of pkg's modules ("follow") or numba's own ("numba")
_STALE_CHILD = """
import json, sys
sys.path.insert(0, sys.argv[1])
import pipeline.runtime.jit as jit
if sys.argv[2] == "follow":
    jit.ROOTS.append(sys.argv[1])
from pkg.caller import twice_plus
value = twice_plus(1.0)
print(json.dumps([value, sum(twice_plus.stats.cache_hits.values())]))
"""

_CALLEE = "from numba import njit\n\n\n@njit(cache=True)\ndef plus(x):\n    return x + {}\n"
_CALLER = (
    "from numba import njit\n\nfrom .callee import plus\n\n\n"
    "@njit(cache=True)\ndef twice_plus(x):\n    return 2.0 * plus(x)\n"
)


def test_a_kernel_compiles_again_when_a_module_it_calls_changes(tmp_path):
    """numba keys a kernel's cache by its own file: after an edit to a module whose function
    the kernel calls, the next process ran the kernel's old machine code (the landmark
    searches kept sweep.py's old overloads so). With pipeline.runtime.jit's stamps the kernel
    compiles again, and loads from the cache while nothing changes. Real processes, numba's
    real cache beside a package of two modules."""
    import json
    import subprocess
    import sys

    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "caller.py").write_text(_CALLER)
    env = _child_env()

    def run(stamps: str, add: int) -> tuple[float, int]:
        (pkg / "callee.py").write_text(_CALLEE.format(add))
        out = subprocess.run(
            [sys.executable, "-c", _STALE_CHILD, str(tmp_path), stamps],
            env=env,
            capture_output=True,
            text=True,
            check=True,
        )
        value, hits = json.loads(out.stdout.strip().splitlines()[-1])
        return value, hits

    assert run("numba", 1) == (4.0, 0)
    assert run("numba", 10) == (4.0, 1)  # the old code of plus, from the cache: the defect
    assert run("follow", 10) == (22.0, 0)  # compiled again
    assert run("follow", 10) == (22.0, 1)  # loaded: the cache still serves
    assert run("follow", 100) == (202.0, 0)


def test_the_stamps_follow_the_package_imports():
    """What a kernel's cache stamp covers (pipeline.runtime.jit.dependencies), on the package
    itself: the landmark searches reach the sweeps' overloads and the planners' search, not
    the MCPC package; the sweeps do not reach the landmark layers; the search reaches the
    modules it imports and nothing else."""
    from pipeline.runtime.jit import ROOTS, dependencies

    def deps(name):
        return {os.path.relpath(p, ROOTS[0]) for p in dependencies(os.path.join(ROOTS[0], name))}

    landmarks = deps("maps/landmarks.py")
    assert {
        "maps/landmarks.py",
        "planners/sweep.py",
        "planners/search.py",
        "planners/heap.py",
    } <= landmarks
    assert "maps/landmarks.py" not in deps("planners/sweep.py")
    assert deps("planners/search.py") == {
        "planners/search.py",
        "planners/grid.py",
        "planners/heap.py",
        "runtime/jit.py",
        "exceptions.py",
    }
    assert not any(p.startswith("mcpc/") for p in landmarks)


def test_the_stamps_read_every_form_of_relative_import(tmp_path):
    """pipeline.runtime.jit.imported on a package written for it: names over several lines with
    comments between them, ``as``, a submodule imported by name from its package, an import
    inside a function, two dots; an absolute import and a name that is not a module add
    nothing of their own."""
    from pipeline.runtime.jit import dependencies, imported

    (tmp_path / "pkg" / "sub").mkdir(parents=True)
    files = {
        "pkg/__init__.py": "",
        "pkg/a.py": (
            "import numpy as np\nfrom .b import f as h\nfrom . import (\n    b,  # a module\n"
            "    # and a package\n    sub,\n)\n\n\ndef k():\n    from .sub.c import x\n"
            "    return x\n"
        ),
        "pkg/b.py": "from .sub import d\n",
        "pkg/sub/__init__.py": "",
        "pkg/sub/c.py": "from .. import b\n",
        "pkg/sub/d.py": "from ..b import nothing_here  # b's own name\n",
    }
    for name, text in files.items():
        (tmp_path / name).write_text(text)

    def rel(paths):
        return {os.path.relpath(p, tmp_path) for p in paths}

    assert rel(imported(str(tmp_path / "pkg/a.py"))) == {
        "pkg/b.py",
        "pkg/sub/__init__.py",
        "pkg/sub/c.py",
    }
    assert rel(imported(str(tmp_path / "pkg/sub/d.py"))) == {"pkg/b.py"}
    assert rel(dependencies(str(tmp_path / "pkg/a.py"))) == {
        "pkg/a.py",
        "pkg/b.py",
        "pkg/sub/__init__.py",
        "pkg/sub/c.py",
        "pkg/sub/d.py",
    }


def _job(tmp_path, dem: str, maps: str = "") -> object:
    from pipeline.jobs.job_file import load_job

    (tmp_path / "j.toml").write_text(
        f'name = "j"\n{dem}\n{maps}\n[[missions]]\nname = "m"\nstart = [1, 1]\ngoal = [5, 5]\n'
    )
    return load_job(tmp_path / "j.toml")


def test_a_job_compiles_only_the_parts_it_uses(tmp_path):
    syn = "[dem.synthetic]\nshape = [{0}, {0}]\ncell_size = 30.0"
    small = warmup.job_parts(_job(tmp_path, syn.format(2000)))
    # a synthetic DEM is not reprojected; 2000^2 cells are fewer than the bucketed A*'s
    assert small == warmup.CORE | {"synthetic"}
    big = warmup.job_parts(_job(tmp_path, syn.format(2048)))
    assert big == warmup.CORE | {"synthetic", "bucketed"}
    (tmp_path / "d.tif").write_bytes(b"")  # never read: only the job file's keys matter
    other = warmup.job_parts(
        _job(tmp_path, '[dem]\npath = "d.tif"', '[maps]\nmethod = "vertical"\nclearance = 50.0')
    )
    # a file may be reprojected and of any size; the store's method is not the vertical one
    assert other == warmup.ALL - {"synthetic"}


def test_a_later_job_compiles_only_what_the_stamp_lacks(stamp, caplog):
    caplog.set_level(logging.DEBUG, logger="pipeline.jobs.warmup")
    assert warmup.ensure_compiled(None, parts={"synthetic"}) > 0
    assert warmup.is_compiled({"synthetic"}) and not warmup.is_compiled({"warp"})
    assert "compiling kernels, first run only" in caplog.text
    caplog.clear()
    assert warmup.ensure_compiled(None, parts={"synthetic", "warp"}) > 0
    assert "compiling the kernels of warp, first use only" in caplog.text
    ran = [r.args[0] for r in caplog.records if r.getMessage().startswith("warm-up parts")]
    assert [list(p) for p in ran[0]] == [["warp"]]  # the synthetic DEM's were not run again
    assert warmup.is_compiled({"synthetic", "warp"}) and not warmup.is_compiled()
    caplog.clear()
    assert warmup.ensure_compiled(None, parts={"warp"}) == 0.0
    assert "compiling" not in caplog.text
    with pytest.raises(ValueError, match="unknown warm-up parts"):
        warmup.ensure_compiled(None, parts={"dem"})
