"""Inputs known by their content (pipeline.store.content), against hashlib on the bytes."""

from __future__ import annotations

import hashlib
import json
import os

from pipeline.store.content import ContentHashes


def test_a_file_and_a_folder_hash_what_they_hold_and_the_cache_never_hides_a_change(tmp_path):
    f = tmp_path / "dem.tif"
    f.write_bytes(b"abc" * 1000)
    cache = tmp_path / "cat" / ".input-hashes.json"
    cache.parent.mkdir()
    h = ContentHashes(cache)
    assert h.of(f) == hashlib.sha256(b"abc" * 1000).hexdigest()
    store = tmp_path / "s.zarr"
    (store / "c" / "0").mkdir(parents=True)
    (store / "zarr.json").write_text("{}")
    (store / "c" / "0" / "0").write_bytes(b"\x00" * 64)
    want = hashlib.sha256()
    for rel, data in (("c/0/0", b"\x00" * 64), ("zarr.json", b"{}")):
        want.update(f"{rel}\0{hashlib.sha256(data).hexdigest()}\n".encode())
    assert h.of(store) == want.hexdigest()
    h.save()
    kept = json.loads(cache.read_text())
    assert set(kept) == {str(f), str(store / "zarr.json"), str(store / "c" / "0" / "0")}
    # the same size and modification time, other bytes: a new hash, cache or not
    st = os.stat(f)
    f.write_bytes(b"abd" * 1000)
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert ContentHashes(cache).of(f) == hashlib.sha256(b"abd" * 1000).hexdigest()
    # a damaged cache costs a read, nothing else
    cache.write_text("{not json")
    assert ContentHashes(cache).of(f) == hashlib.sha256(b"abd" * 1000).hexdigest()
    # the files used are kept, the others dropped
    again = ContentHashes(cache)
    again.of(f)
    again.save()
    assert set(json.loads(cache.read_text())) == {str(f)}
