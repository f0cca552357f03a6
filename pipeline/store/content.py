"""What an input file or folder holds, as a hash: a job's DEM (a file, or a Zarr store's folder)
and its zone files are fingerprinted by their content, so that one rewritten in place, or
replaced by another of the same size and modification time (as ``cp -p``, ``rsync -t`` or tar
leave it), is always seen as changed.

Hashing reads every byte (SHA-256, about 1.4 GB/s on one core), so each file's hash is kept
with its stamp (size, modification and status-change times, inode and device) in the job's
catalog (:data:`CACHE_NAME`): a file whose stamp is unchanged is not read again. The stamp
cannot hide a change: the status-change time is set by the system on every write, rename or
attribute change, and no tool can set it back."""

from __future__ import annotations

import hashlib
import json
import os
import uuid
from pathlib import Path

# the hashes of a job's inputs, kept in its catalog between runs
CACHE_NAME = ".input-hashes.json"


def _stamp(st: os.stat_result) -> list:
    return [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino, st.st_dev]


class ContentHashes:
    """Content hashes of files and folders, each file read once while its stamp holds; kept in
    ``cache`` (a JSON file) when given and :meth:`save` is called."""

    def __init__(self, cache: Path | None = None):
        self.cache = cache
        self.entries: dict = {}
        self.used: set = set()
        if cache is not None:
            try:
                entries = json.loads(Path(cache).read_text())
                if isinstance(entries, dict):
                    self.entries = entries
            except (OSError, ValueError):
                pass  # absent or damaged: everything is hashed again

    def of(self, path) -> str:
        """The hash of the file ``path``, or of a folder's files: each one's path within it
        and the hash of its content, a line each, in the order of the paths."""
        p = Path(os.path.abspath(path))
        if not p.is_dir():
            return self._file(p)
        files = sorted(
            (Path(root, name).relative_to(p).as_posix(), Path(root, name))
            for root, _, names in os.walk(p)
            for name in names
        )
        h = hashlib.sha256()
        for rel, f in files:
            h.update(f"{rel}\0{self._file(f)}\n".encode())
        return h.hexdigest()

    def _file(self, p: Path) -> str:
        key = str(p)
        st = p.stat()
        self.used.add(key)
        entry = self.entries.get(key)
        if isinstance(entry, dict) and entry.get("stamp") == _stamp(st):
            return entry["hash"]
        with open(p, "rb") as fh:
            digest = hashlib.file_digest(fh, "sha256").hexdigest()
        # the stamp taken after the read too: a file written meanwhile is hashed next time
        stamp = _stamp(st)
        self.entries[key] = {"stamp": stamp if _stamp(p.stat()) == stamp else None, "hash": digest}
        return digest

    def save(self) -> None:
        """Keep the hashes of the files used since this was made (the others are dropped) in
        the cache file, when its folder exists; a failure to write only costs a re-read."""
        if self.cache is None or not Path(self.cache).parent.is_dir():
            return
        keep = {k: v for k, v in self.entries.items() if k in self.used}
        # (named as the tool's temporaries are: one a killed run left is removed by the next)
        tmp = Path(self.cache).with_name(f"{CACHE_NAME}.tmp-{uuid.uuid4().hex[:8]}")
        try:
            tmp.write_text(json.dumps(keep))
            os.replace(tmp, self.cache)
        except OSError:
            tmp.unlink(missing_ok=True)
