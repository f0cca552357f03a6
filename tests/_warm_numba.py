"""Compile the numba kernels the tests use into numba's on-disk cache, one half in each of two
processes (tests/conftest.py starts both at the start of a session; in a warm environment they
finish in seconds):

    python tests/_warm_numba.py first|second MARKS

- first: the first half of the library's warm-up (``pipeline.jobs.warmup.HALVES``; writes
  MARKS/first), then the argument types only the tests use (MARKS/tests), then the pysheds
  kernels the comparisons call (conftest.pysheds_ridges on a small grid; MARKS/pysheds).
- second: the other half, then (once the first is done) stamps the library compiled
  (``pipeline.jobs.warmup.mark_compiled``) where both halves ran to their end, else runs the
  library's whole warm-up (from the cache, what the halves compiled); writes MARKS/library,
  which every test process waits for. (Running the whole warm-up from the cache to stamp it
  took 2-5 s: MARKS/library after 25.6-27.0 s in a fresh numba cache, 23.3-25.4 s now, three
  runs each way in turn, in a fast hour of the VM.)

In a fresh environment on this project's 2-core VM: MARKS/first after 56 s, MARKS/library
after 66 s (the tests start), MARKS/tests after 81 s, MARKS/pysheds after 103 s. With the
tests' own types compiled before MARKS/first, as they were, the tests started after 79-84 s.
The modules that call kernels with the tests' own types, and the session's cluster, wait for
MARKS/tests (conftest.test_kernels_compiled): compiling them beside this process cost the two
test processes 75 s of compilation in a fresh clone. Any other test that needs a kernel still
being compiled here compiles it itself: numba's cache takes both (pipeline.runtime.jit).
"""

import atexit
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
half, marks = sys.argv[1], Path(sys.argv[2])
work = marks / "work"
# every mark this half writes is written however it ends (an error in a step, or a failed
# import): a test process waits for its mark, and compiles what it needs itself once it is there
atexit.register(
    lambda: [
        (marks / m).touch() for m in (("first", "tests", "pysheds"), ("library",))[half != "first"]
    ]
)

from conftest import compile_test_kernels  # noqa: E402

from pipeline.jobs.warmup import HALVES, compile_parts, ensure_compiled, mark_compiled  # noqa: E402

if half == "first":
    try:
        compile_parts(work, HALVES[0])
        (marks / "first-done").touch()
    finally:
        (marks / "first").touch()
    try:  # after the mark: the tests start once the library is compiled, not these too
        compile_test_kernels()
    finally:
        (marks / "tests").touch()
    try:
        import numpy as np
        from conftest import pysheds_ridges

        pysheds_ridges(np.random.default_rng(0).normal(size=(20, 20)).astype(np.float32))
    finally:
        (marks / "pysheds").touch()
else:
    try:
        t0 = time.monotonic()
        compile_parts(work, HALVES[1])
        deadline = time.monotonic() + 600
        while not (marks / "first").exists() and time.monotonic() < deadline:
            time.sleep(0.2)
        if (marks / "first-done").exists():
            mark_compiled(time.monotonic() - t0)
        else:  # the first half failed or is late: the whole warm-up, which stamps it
            ensure_compiled()
    finally:
        (marks / "library").touch()
