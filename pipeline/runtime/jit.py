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

numba also keys a kernel's cached machine code by its own source file only: a kernel that
calls or inlines a function of another module (``pipeline.maps.landmarks``' searches take the
heights through ``pipeline.planners.sweep``'s overloads) kept the old code of that function
after its module changed, until its own file changed too. Here the stamp numba keeps with the
cache of each kernel under :data:`ROOTS` (the package) also holds the content of every module
its file imports relatively (``from .x import y``, at any indentation), and of theirs: an
edit to a module makes every kernel whose file reaches it compile again
(tests/test_warmup.py checks it in real processes, against a stale kernel without it).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import re
import sys

from numba import njit

try:
    import fcntl
except ImportError:  # not POSIX: numba's own saving
    fcntl = None

__all__ = ["njit"]

LOCK_NAME = "auv-pipeline-numba.lock"  # in each cache directory the package's kernels use

# the directories whose kernels' cache stamps follow their imports (:func:`dependencies`)
ROOTS = [os.path.dirname(os.path.dirname(os.path.abspath(__file__)))]


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


# ``from .x.y import (a, b)`` / ``from .. import z``, at any indentation: the dots, the module
# and the names (parenthesised over several lines, or to the end of the line)
_RELATIVE = re.compile(
    r"^[ \t]*from[ \t]+(\.+)([\w.]*)[ \t]+import[ \t]+(\([^)]*\)|[^\n]*)", re.MULTILINE
)


def _module_file(path: str) -> str | None:
    """The file of the module at ``path`` (without ``.py``): the module, or the package's
    ``__init__.py``; None when there is neither."""
    if os.path.isfile(path + ".py"):
        return path + ".py"
    init = os.path.join(path, "__init__.py")
    return init if os.path.isfile(init) else None


def imported(path: str) -> set[str]:
    """The files of the modules that the module at ``path`` imports relatively: per name
    imported, the submodule of that name where there is one, else the module named."""
    with open(path, encoding="utf-8") as f:
        text = f.read()
    out = set()
    for dots, module, names in _RELATIVE.findall(text):
        base = os.path.dirname(os.path.abspath(path))
        for _ in range(len(dots) - 1):
            base = os.path.dirname(base)
        where = os.path.join(base, *module.split(".")) if module else base
        for name in re.sub(r"#[^\n]*", "", names).strip("()").replace("\n", " ").split(","):
            name = name.split(" as ")[0].strip()
            if not name:
                continue  # after a trailing comma
            found = _module_file(os.path.join(where, name)) if name != "*" else None
            found = found or _module_file(where)
            if found:
                out.add(os.path.abspath(found))
    return out


@functools.cache
def dependencies(path: str) -> frozenset[str]:
    """``path`` and every module it reaches through relative imports (:func:`imported`), as
    absolute file paths."""
    seen = {os.path.abspath(path)}
    todo = list(seen)
    while todo:
        for dep in imported(todo.pop()) - seen:
            seen.add(dep)
            todo.append(dep)
    return frozenset(seen)


@functools.cache
def _file_digest(path: str, mtime_ns: int, size: int) -> bytes:
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).digest()


@functools.cache
def dependencies_digest(path: str) -> bytes:
    """One hash of the content of :func:`dependencies` of ``path`` (with their names relative
    to its directory), once per process: numba asks for it for each kernel of the file."""
    here = os.path.dirname(os.path.abspath(path))
    h = hashlib.sha256()
    for dep in sorted(dependencies(path)):
        st = os.stat(dep)
        h.update(os.path.relpath(dep, here).encode() + b"\0")
        h.update(_file_digest(dep, st.st_mtime_ns, st.st_size))
    return h.digest()


def _under_roots(path: str) -> bool:
    path = os.path.abspath(path)
    return any(os.path.commonpath([path, root]) == root for root in ROOTS)


def _install_stamps() -> None:
    """numba's source stamp of the kernels under :data:`ROOTS`: its own (the file's hash) and
    :func:`dependencies_digest` (once per process; left as it is where numba has no such
    method)."""
    from numba.core import caching

    mixin = getattr(caching, "_SourceFileBackedLocatorMixin", None)
    own = getattr(mixin, "get_source_stamp", None)
    if own is None or getattr(own, "follows_imports", False):
        return

    def get_source_stamp(self):
        stamp = own(self)
        path = getattr(self, "_py_file", None)
        if not path or getattr(sys, "frozen", False) or not _under_roots(path):
            return stamp
        try:
            return stamp, dependencies_digest(path)
        except (OSError, ValueError):  # a module that cannot be read: numba's stamp alone
            return stamp

    get_source_stamp.follows_imports = True
    mixin.get_source_stamp = get_source_stamp


_install()
_install_stamps()
