"""Compile the numba kernels the tests use into numba's on-disk cache: the library's (with
the argument types the tests use), then pysheds' (which compiles about 80 functions when it is
imported). tests/conftest.py starts this in a process of its own at the start of a session, on
the core the tests leave idle; in a warm environment it finishes in seconds."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from conftest import compile_kernels  # noqa: E402

compile_kernels()

import pysheds.grid  # noqa: E402, F401
