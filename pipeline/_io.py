"""Atomic writes: a store or file is written beside its destination, then moved into place."""

from __future__ import annotations

import os
import shutil
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from .exceptions import StoreExistsError


@contextmanager
def atomic_path(path: str | os.PathLike, *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary sibling of ``path``; on success move it to ``path``.

    A reader never sees a half-written store: until the final ``rename`` the destination is
    either absent or the previous complete version. On any error the temporary is removed.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise StoreExistsError(
            f"{path} exists already; pass overwrite=True (--overwrite) to replace it"
        )
    path.parent.mkdir(parents=True, exist_ok=True)
    tag = uuid.uuid4().hex[:8]
    tmp = path.with_name(f".{path.name}.tmp-{tag}")
    try:
        yield tmp
        if path.exists():
            old = path.with_name(f".{path.name}.old-{tag}")
            os.rename(path, old)
            os.rename(tmp, path)
            _remove(old)
        else:
            os.rename(tmp, path)
    except BaseException:
        remove_settled(tmp)
        raise


def remove_settled(p: Path, *, settle_s: float = 1.0, give_up_s: float = 30.0) -> None:
    """Remove ``p`` and keep removing it until it has stayed absent for ``settle_s``.

    When one task of a dask computation fails, tasks already running on other threads or
    workers still finish and write their chunks, which can recreate the temporary store after a
    single removal.
    """
    deadline = time.monotonic() + give_up_s
    quiet_since = None
    while time.monotonic() < deadline:
        if p.exists() or p.is_symlink():
            _remove(p)
            quiet_since = None
        elif quiet_since is None:
            quiet_since = time.monotonic()
        elif time.monotonic() - quiet_since >= settle_s:
            return
        time.sleep(0.05)


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    elif p.exists():
        p.unlink()
