"""Where stores live, and atomic writes.

A store is a local path (a shared directory on a cluster) or an fsspec URL (``s3://bucket/key``
and the like): object storage every worker can reach. Local stores are written beside their
destination and moved into place; object storage has no rename, so a store there is written in
place and is complete only once its final attributes are written (a reader refuses it until
then), and a failed build removes what it wrote. Only what this tool wrote is ever replaced
(:func:`own_store`).
"""

from __future__ import annotations

import os
import re
import shutil
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ..exceptions import PipelineError, StoreExistsError


def is_url(p) -> bool:
    """Whether ``p`` names object storage (an fsspec URL such as ``s3://bucket/key``) rather
    than a local or shared path; ``file://`` URLs are local paths."""
    return isinstance(p, str) and "://" in p and not p.startswith("file://")


# a URL of any scheme (file:// and http:// too): DEM files are read from local paths only
_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*://")


def has_scheme(p) -> bool:
    """Whether ``p`` is written as a URL of any scheme (``s3://``, ``http://``, ``file://``)."""
    return isinstance(p, str) and _SCHEME.match(p) is not None


def location(p) -> str:
    """The canonical name of a store: a URL as given (no trailing ``/``), else the absolute
    path. Workers open stores by this name."""
    if is_url(p):
        return p.rstrip("/")
    if isinstance(p, str) and p.startswith("file://"):
        p = p[len("file://") :]
    return str(Path(p).resolve())


def join(base: str, *parts: str) -> str:
    """``base`` / ``parts`` for a path or a URL."""
    return "/".join([str(base).rstrip("/"), *parts]) if is_url(base) else os.path.join(base, *parts)


def filesystem(url: str):
    """The fsspec filesystem of ``url`` and the path in it; one line if its package is not
    installed, or if the filesystem connects as it is made and cannot (ftp://, sftp://)."""
    import fsspec

    try:
        return fsspec.core.url_to_fs(url)
    except (ImportError, ValueError) as exc:
        raise PipelineError(
            f"{url}: this kind of storage needs a package that is not installed ({exc}); for "
            "s3:// install s3fs (pip install 'auv-pipeline[s3]')"
        ) from None
    except Exception as exc:  # noqa: BLE001 - socket, paramiko, ... each raise their own
        raise unreachable(url, exc) from None


def unreachable(url: str, exc: BaseException) -> PipelineError:
    """The one line for object storage that cannot be reached or read."""
    what = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    hint = (
        "that the bucket exists, and the endpoint and credentials (AWS_ENDPOINT_URL, "
        "AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, or ~/.aws) on"
        if str(url).startswith(("s3://", "s3a://"))
        else "and that its server answers from"
    )
    return PipelineError(
        f"{url} cannot be reached ({type(exc).__name__}: {what}); check the URL, {hint} "
        "this machine and every worker"
    )


def exists(p) -> bool:
    """Whether the file or store ``p`` (a path or a URL) exists."""
    if not is_url(p):
        return os.path.exists(p)
    fs, path = filesystem(p)
    try:
        return fs.exists(path)
    except Exception as exc:  # noqa: BLE001 - botocore, aiohttp, ... each raise their own
        raise unreachable(p, exc) from None


def stamp(p):
    """A value that changes when the file ``p`` is rewritten (its mtime, an object's ETag), or
    None when it is absent."""
    if not is_url(p):
        try:
            return os.stat(p).st_mtime_ns
        except OSError:
            return None
    fs, path = filesystem(p)
    try:
        fs.invalidate_cache(path)
        info = fs.info(path)
    except FileNotFoundError:
        return None
    except Exception as exc:  # noqa: BLE001
        raise unreachable(p, exc) from None
    return info.get("ETag") or info.get("LastModified") or info.get("mtime") or info.get("size")


def store_exists(p) -> bool:
    """Whether a store is at ``p``: for a URL its ``zarr.json`` (object storage has no
    directories), for a path anything there."""
    return exists(join(p, "zarr.json")) if is_url(p) else os.path.exists(p)


def remove_tree(p) -> None:
    """Remove the store ``p`` (a path or a URL) if it exists."""
    if not is_url(p):
        _remove(Path(p))
        return
    fs, path = filesystem(p)
    try:
        if fs.exists(path):
            fs.rm(path, recursive=True)
    except FileNotFoundError:
        pass


def require_writable(url: str) -> None:
    """Write and remove one small object under ``url``, before a long computation that ends by
    writing there: a wrong bucket, endpoint or credential is then one line at once."""
    fs, path = filesystem(url)
    probe = f"{path.rstrip('/')}.write-probe"
    try:
        fs.pipe(probe, b"")
        fs.rm(probe)
    except Exception as exc:  # noqa: BLE001
        raise unreachable(url, exc) from None


# the names of the tool's temporaries: a dot, the name, .tmp- and a random hex tag (and the
# suffix a writer needs, or a maps build's scratch stores beside its store)
TEMPORARY = re.compile(r"^\..+\.tmp-[0-9a-f]{8,12}(\.png|\.html|-scratch|-components)?$")


# the attribute by which a store of each kind says, in its root zarr.json (a mission folder:
# in its mission.json), that this tool wrote it: only such a store or folder is ever replaced
STORE_MARKS = {
    "DEM": "pipeline_dem_version",
    "maps": "maps_version",
    "mission": "pipeline_mission_version",
}


MARK_FILES = {"DEM": "zarr.json", "maps": "zarr.json", "mission": "mission.json"}


def own_store(p, kind: str) -> bool:
    """Whether ``p`` (a path or a URL) holds a ``kind`` store (``"DEM"`` or ``"maps"``), or a
    mission folder (``"mission"``), that this tool wrote: the ``attributes`` of its root
    ``zarr.json`` (``mission.json``) name the kind's mark (:data:`STORE_MARKS`)."""
    import json

    meta = join(p, MARK_FILES[kind])
    try:
        if is_url(p):
            fs, path = filesystem(meta)
            text = fs.cat_file(path)
        elif os.path.isdir(p) and not os.path.islink(p):
            text = Path(meta).read_bytes()
        else:
            return False
        attrs = json.loads(text).get("attributes") or {}
    except Exception:  # noqa: BLE001 - absent, unreadable, not JSON: not one of ours
        return False
    return isinstance(attrs, dict) and STORE_MARKS[kind] in attrs


def check_replaceable(path, kind: str, overwrite: bool) -> None:
    """Raise :class:`StoreExistsError` where something is at ``path`` and it may not be
    replaced: without ``overwrite``, or (with it) where it is not a ``kind`` store this tool
    wrote. A folder, a file or another program's store is never deleted."""
    if not (store_exists(path) or (not is_url(path) and os.path.islink(path))):
        return
    if not overwrite:
        raise StoreExistsError(
            f"{path} exists already; pass overwrite=True (--overwrite) to replace it"
        )
    if not own_store(path, kind):
        raise StoreExistsError(
            f"{path} exists and is not a {kind} {'folder' if kind == 'mission' else 'store'} "
            "this tool wrote, so --overwrite does not "
            "replace it; give another output path, or move it away yourself"
        )


@contextmanager
def target(path, *, kind: str, overwrite: bool = False) -> Iterator[str]:
    """:func:`atomic_path` for a local path; for a URL, the URL itself (removed first when
    ``overwrite`` and it holds a ``kind`` store of this tool's, and removed again if the block
    fails)."""
    if not is_url(path):
        with atomic_path(path, kind=kind, overwrite=overwrite) as tmp:
            yield str(tmp)
        return
    url = location(path)
    check_replaceable(url, kind, overwrite)
    require_writable(url)
    if overwrite:
        remove_tree(url)
    try:
        yield url
    except BaseException:
        remove_settled(url)
        raise


@contextmanager
def atomic_path(path: str | os.PathLike, *, kind: str, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary sibling of ``path``; on success move it to ``path``, replacing what
    was there only with ``overwrite`` and only if it is a ``kind`` store this tool wrote
    (:func:`check_replaceable`).

    A reader never sees a half-written store: until the final ``rename`` the destination is
    either absent or the previous complete version. On any error the temporary is removed.
    """
    path = Path(path)
    check_replaceable(path, kind, overwrite)
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


def remove_settled(p, *, settle_s: float = 1.0, give_up_s: float = 30.0) -> None:
    """Remove ``p`` (a path or a URL) and keep removing it until it has stayed absent for
    ``settle_s``.

    When one task of a dask computation fails, tasks already running on other threads or
    workers still finish and write their chunks, which can recreate the temporary store after a
    single removal.
    """
    deadline = time.monotonic() + give_up_s
    quiet_since = None
    while time.monotonic() < deadline:
        if exists(p) if is_url(p) else (Path(p).exists() or Path(p).is_symlink()):
            remove_tree(p)
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


def write_atomically(path, content: str | bytes | None = None, *, write=None, suffix: str = ""):
    """Write the file ``path`` whole or not at all: ``content`` (text as UTF-8, or bytes), or
    what ``write(tmp)`` writes at the path it is given, goes to a temporary beside ``path``
    (named as :data:`TEMPORARY` says, ending in ``suffix`` where a writer needs one, such as
    ``.png``), which then replaces ``path``; a failed write removes the temporary. Returns
    ``path``."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}{suffix}")
    try:
        if write is not None:
            write(tmp)
        elif isinstance(content, bytes):
            tmp.write_bytes(content)
        else:
            tmp.write_text(content, encoding="utf-8")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path
