"""How the package compiles its kernels: numba's ``njit``, its on-disk cache made safe for
several processes that compile at once.

numba keeps the machine code of each compiled signature of a kernel in its cache directory: an
index file per kernel (its signatures, and the data file of each) and one data file per
signature. Saving a signature reads the index, takes the first data file name it does not
list, writes the index back, then the data. Two processes that save signatures of one kernel
at the same moment (the warm-up's two processes, a cluster's two workers, the test processes)
both read the index as it was: the index written last drops the other's signature, which is
then compiled again by the next process that needs it; when both took the same data file
name, the index can name a data file that holds the other signature's machine code. Measured
with 4 processes that compile 30 kernels each for a dtype of their own, in step, into one cache
directory: 24 of 240 signatures lost in two rounds without the lock, none with it
(tests/test_warmup.py checks that a save waits for the lock). numba's maintainers suggest a
file lock (numba issue 10128); numba 0.68 has none. Here every save holds an exclusive lock
(``fcntl.flock``) on one file of the cache directory from reading the index to writing the
data. Loading needs no lock: numba writes both files whole and renames them into place.
"""

from __future__ import annotations

import contextlib
import os

from numba import njit

try:
    import fcntl
except ImportError:  # not POSIX: numba's own saving
    fcntl = None

__all__ = ["njit"]

LOCK_NAME = "auv-pipeline-numba.lock"  # in each cache directory the package's kernels use


@contextlib.contextmanager
def _locked(directory: str):
    """An exclusive lock on :data:`LOCK_NAME` in ``directory`` while the block runs (none when
    the file cannot be opened: numba's saving then reports what is wrong)."""
    try:
        fd = os.open(os.path.join(directory, LOCK_NAME), os.O_RDWR | os.O_CREAT, 0o666)
    except OSError:
        yield
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


def _install() -> None:
    """numba's ``IndexDataCacheFile.save`` under :func:`_locked` (once per process; left as it
    is where numba has no such method, or the platform no ``flock``)."""
    from numba.core import caching

    cls = getattr(caching, "IndexDataCacheFile", None)
    save = getattr(cls, "save", None)
    if fcntl is None or save is None or getattr(save, "locked_by_auv_pipeline", False):
        return

    def save_locked(self, key, data):
        directory = getattr(self, "_cache_path", None)
        if directory is None:
            return save(self, key, data)
        with _locked(directory):
            return save(self, key, data)

    save_locked.locked_by_auv_pipeline = True
    cls.save = save_locked


_install()
