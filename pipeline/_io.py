"""Where stores live, and atomic writes.

A store is a local path (a shared directory on a cluster) or an fsspec URL (``s3://bucket/key``
and the like): object storage every worker can reach. Local stores are written beside their
destination and moved into place; object storage has no rename, so a store there is written in
place and is complete only once its final attributes are written (a reader refuses it until
then), and a failed build removes what it wrote."""

from __future__ import annotations

import os
import re
import shutil
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from .exceptions import PipelineError, StoreExistsError


def layer_codec():
    """The codec of every Zarr layer the pipeline keeps (DEM stores, maps layers, landmark
    distances): blosc LZ4 with byte shuffle. Builds read the DEM several times and missions
    read windows of the maps layers and the landmark chunks at both ends. Measured on 1024^2
    float32 blocks of the benchmark maps: synthetic elevation decodes 3.3x faster than with
    zarr's default (zstd level 0: 0.87 ms against 2.88), encodes 4.5x faster and compresses
    more (1.74:1 against 1.24:1); landmark distances decode 5.2x faster than with blosc zstd
    and bit shuffle (0.68 ms against 3.53) at the same ratio (2.88:1)."""
    from zarr.codecs import BloscCodec

    return (BloscCodec(cname="lz4", clevel=5, shuffle="shuffle"),)


INNER_CHUNK = 256  # the largest side of a maps layer's inner chunk (the unit a window reads)


def inner_chunks(chunks, largest: int = INNER_CHUNK) -> tuple[int, ...]:
    """The inner chunk of a maps layer whose shards are ``chunks``: on each side the largest
    divisor of the shard's side that is at most ``largest`` (:data:`INNER_CHUNK`: 1024 -> 256,
    300 -> 150, 89 -> 89)."""
    return tuple(
        next(d for d in range(min(int(c), largest), 0, -1) if int(c) % d == 0) for c in chunks
    )


# The layers a mission's sections read window by window. In a local store they are kept
# uncompressed: a window is then copied straight out of the shard files, memory-mapped
# (pipeline.store.ChunkCache.window), with no decoding and no decoded chunk held. At 10000^2
# the decoding (blosc LZ4: 66-99 us a 256^2 float32 inner chunk, 53 us a bool one) and the
# fresh memory of the decoded chunks made a mission's reads 34 ms, longer than its searches
# (21 ms); mapped, 13-16 ms (benchmarks/RESULTS.md, "One mission against pyastar2d"). The cost
# is disk: 4 + 1 + 1 bytes a cell (a 10000^2 store's three layers 600 MB, against 245 MB
# compressed). On object storage, where bytes travel, they stay compressed.
WINDOW_LAYERS = ("safety", "ridge", "passable")


def layer_encoding(chunks, compress: bool = True) -> dict:
    """The Zarr encoding of a maps layer written in blocks of ``chunks``: shards of ``chunks``
    (what a dask task writes, what dask reads the layer by) holding inner chunks of
    :func:`inner_chunks` (what a mission reads), each compressed with :func:`layer_codec`
    unless ``compress`` is false (:data:`WINDOW_LAYERS` of a local store).
    A section's window (about 150^2 cells) covers a few 256^2 inner chunks; with 1024^2
    chunks it decoded whole chunks: 11.5 M cells a layer for a mission across the 10000^2 map
    against 3.4 M (benchmarks/bench_latency.py)."""
    shards = tuple(int(c) for c in chunks)
    return {
        "chunks": inner_chunks(shards),
        "shards": shards,
        "compressors": layer_codec() if compress else None,
    }


def storage_chunks(arr) -> tuple[int, ...]:
    """The blocks a Zarr array was written in: its shards, or its chunks without sharding (the
    dask chunks to read it with)."""
    shards = getattr(arr, "shards", None)
    return tuple(int(v) for v in (shards if shards is not None else arr.chunks))


# the output a banded write (:func:`store_in_bands`) computes at a time: a band of chunk rows of
# at most this many bytes (one chunk row at least)
BAND_BYTES = 256 * 2**20


def store_in_bands(data, target, *, band_bytes: int = BAND_BYTES, progress=None) -> None:
    """Write the dask array ``data`` (2-D, or more with the rows on its first axis) into
    ``target`` (a Zarr array of its shape whose chunks are ``data``'s blocks), a band of block
    rows at a time, each band at most ``band_bytes`` of output, so that memory follows the
    band, not the map. ``progress(done, total)`` after each band.

    dask's local schedulers keep a task's result until every task that needs it is done, and
    run any task that is ready: in one graph of a reprojection (each output chunk warps the
    source chunks it overlaps) they read far ahead of the warps, and a 40000^2 GeoTIFF import
    held 3.0 GiB (benchmarks/bench_dem.py). A band's graph holds only what that band needs. What
    the next band needs too (the source chunks astride the boundary) is computed once, kept,
    and handed to the next band's graph as a value: the file is read once and the chunks
    written are those of one graph. On a distributed client what is kept stays on the workers
    (futures) and two bands are in flight, so that the next band's reads overlap this one's
    warps."""
    import functools

    import dask
    import dask.array as da
    from dask.core import flatten, get_dependencies

    from .runtime.cluster import computing_client

    stored = da.store(data, target, lock=False, compute=False)
    client = computing_client()
    get = dask.base.get_scheduler(collections=[stored])
    rows = [list(flatten(r)) for r in stored.__dask_keys__()]
    row_bytes = max(1, data.nbytes // max(len(rows), 1))
    per = max(1, int(band_bytes // row_bytes))
    bands = [[k for r in rows[i : i + per] for k in r] for i in range(0, len(rows), per)]
    graph = dict(stored.__dask_graph__())
    deps: dict = {}

    def needs(key) -> set:
        if key not in deps:
            deps[key] = get_dependencies(graph, key)
        return deps[key]

    def cull(keys, known: dict) -> dict:
        """The tasks ``keys`` need, those of ``known`` as their values (nothing below them)."""
        out: dict = {}
        todo = list(keys)
        while todo:
            key = todo.pop()
            if key in out:
                continue
            if key in known:  # a future stands for its own key, as in a persisted collection
                v = known[key]
                out[key] = v if client is not None else (functools.partial(_value, v),)
                continue
            out[key] = graph[key]
            todo.extend(needs(key))
        return out

    known: dict = {}
    writing: list = []  # on a cluster, the writes of the bands sent and not waited for yet
    for i, keys in enumerate(bands):
        band = cull(keys, known)
        keep: list = []
        if i + 1 < len(bands):
            later = cull(bands[i + 1], {})
            shared = band.keys() & later.keys()
            # the shared results the next band uses directly (not only through other shared ones)
            used = set().union(*(needs(j) for j in later if j not in shared))
            keep = [k for k in shared if k in used]
        if client is None:
            got = get(band, keys + keep)
            if progress is not None:
                progress(i + 1, len(bands))
        else:
            got = _send(client, band, keys + keep)
            writing.append(got[: len(keys)])
            if len(writing) > 1:  # a task's error is raised here
                client.gather(writing.pop(0))
                if progress is not None:
                    progress(i, len(bands))
        known = dict(zip(keep, got[len(keys) :], strict=True))
    for futures in writing:
        client.gather(futures)
        if progress is not None:
            progress(len(bands), len(bands))


def _send(client, graph: dict, keys: list) -> list:
    """Futures of ``keys`` of ``graph`` computed on ``client``'s cluster. Sent as delayed
    objects of one named layer: ``client.get`` tokenizes a plain graph first, which took 1.7 ms a
    task of a 20000^2 reprojection and 30 ms at 40000^2; named, 7 ms a band of 200 tasks."""
    import uuid

    from dask.delayed import Delayed
    from dask.highlevelgraph import HighLevelGraph

    name = f"band-{uuid.uuid4().hex}"
    layer = HighLevelGraph.from_collections(name, graph, dependencies=())
    return client.compute([Delayed(k, layer, layer=name) for k in keys], optimize_graph=False)


def _value(v):
    """A task's result kept from an earlier band (:func:`store_in_bands`)."""
    return v


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


def save_tile(scratch, name: str, tile: tuple, array) -> None:
    """Tile ``tile`` (its place in the tile grid) of the build scratch layer ``name``, kept as
    one ``.npy`` file under ``scratch`` (a path or a URL): each tile has one writer and is read
    whole, so no chunk grid constrains the tiles. Through zarr, an uncompressed 1024^2 float32
    chunk took 6.6 ms to write and 3.9 ms to read; as a file it reads in 1.8 ms and writes in
    what the page cache costs (1.2-15 ms on the benchmark VM, by how much waits to be
    written)."""
    import io

    import numpy as np

    key = f"{tile[0]}.{tile[1]}.npy"
    buf = io.BytesIO()
    np.save(buf, np.asarray(array), allow_pickle=False)
    if is_url(scratch):
        fs, path = filesystem(join(str(scratch), name, key))
        fs.pipe_file(path, buf.getvalue())
        return
    folder = os.path.join(scratch, name)
    os.makedirs(folder, exist_ok=True)
    # written by Python's file, not numpy's tofile: a full disk then raises the OSError with
    # its errno (ENOSPC, EFBIG), which the command line turns into its one line
    with open(os.path.join(folder, key), "wb") as f:
        f.write(buf.getbuffer())


def load_tile(scratch, name: str, tile: tuple, mapped: bool = False):
    """The tile :func:`save_tile` kept; with ``mapped``, a local tile is memory-mapped (read
    only: a caller that copies part of it reads only that part's pages)."""
    import io

    import numpy as np

    key = f"{tile[0]}.{tile[1]}.npy"
    if is_url(scratch):
        fs, path = filesystem(join(str(scratch), name, key))
        return np.load(io.BytesIO(fs.cat_file(path)), allow_pickle=False)
    return np.load(
        os.path.join(scratch, name, key), mmap_mode="r" if mapped else None, allow_pickle=False
    )


def load_window(scratch, name: str, r_off, c_off, r0: int, r1: int, c0: int, c1: int, dtype):
    """Rows ``r0:r1`` and columns ``c0:c1`` of the scratch layer ``name`` whose tiles
    :func:`save_tile` kept on the grid of row and column offsets ``r_off`` and ``c_off``
    (tile ``(i, j)`` covers rows ``r_off[i]:r_off[i + 1]``): a window across as many tiles as
    it spans, so a halo of any width is read from the tiles that hold it, with no dask task
    that slices one tile for another."""
    import numpy as np

    out = np.empty((r1 - r0, c1 - c0), dtype=dtype)
    remote = is_url(scratch)
    i0 = int(np.searchsorted(r_off, r0, side="right")) - 1
    i1 = int(np.searchsorted(r_off, r1, side="left"))
    j0 = int(np.searchsorted(c_off, c0, side="right")) - 1
    j1 = int(np.searchsorted(c_off, c1, side="left"))
    for i in range(i0, i1):
        a0, a1 = max(r0, int(r_off[i])), min(r1, int(r_off[i + 1]))
        for j in range(j0, j1):
            b0, b1 = max(c0, int(c_off[j])), min(c1, int(c_off[j + 1]))
            top = a0 - int(r_off[i])
            if remote:  # only the rows wanted, in one range request
                tile = _tile_rows(scratch, name, (i, j), top, a1 - int(r_off[i]))
                top = 0
            else:
                tile = load_tile(scratch, name, (i, j), mapped=True)
            out[a0 - r0 : a1 - r0, b0 - c0 : b1 - c0] = tile[
                top : top + a1 - a0, b0 - int(c_off[j]) : b1 - int(c_off[j])
            ]
            del tile
    return out


def _tile_rows(scratch: str, name: str, tile: tuple, a: int, b: int):
    """Rows ``a:b`` of a 2-D tile :func:`save_tile` kept on object storage: its ``.npy``
    header, then those rows' bytes (C order), each in one range request."""
    import io

    import numpy as np

    fs, path = filesystem(join(str(scratch), name, f"{tile[0]}.{tile[1]}.npy"))
    head = io.BytesIO(fs.cat_file(path, start=0, end=4096))
    fmt = np.lib.format
    version = fmt.read_magic(head)
    read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
    shape, fortran, dtype = read(head)
    if fortran:  # rows not contiguous: the whole tile
        return load_tile(scratch, name, tile)[a:b]
    row = shape[1] * dtype.itemsize
    start = head.tell() + a * row
    data = fs.cat_file(path, start=start, end=start + (b - a) * row)
    return np.frombuffer(data, dtype=dtype).reshape(b - a, shape[1])


def tile_array(scratch, name: str, chunks, dtype):
    """The scratch layer ``name`` that :func:`save_tile` kept, as a dask array of ``chunks`` (a
    tile a block, the block's place in the grid its tile's)."""
    import dask.array as da
    import numpy as np

    return da.map_blocks(
        _load_block, scratch, name, chunks=chunks, dtype=dtype, meta=np.empty((0, 0), dtype)
    )


def _load_block(scratch, name: str, block_info=None):
    return load_tile(scratch, name, tuple(block_info[None]["chunk-location"]))


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


# the variable of a store that holds its CRS, as CF conventions and rioxarray have it
GRID_MAPPING = "spatial_ref"


def grid_mapping(crs_wkt: str | None) -> tuple | None:
    """How a store holds the CRS ``crs_wkt`` (None without one): ``(variable, attrs)``, the CF
    grid-mapping variable as rioxarray writes it (a 0-d variable whose attributes are the CRS's
    CF parameters, ``crs_wkt`` and GDAL's ``spatial_ref``; named :data:`GRID_MAPPING`) and the
    attributes each layer takes: ``grid_mapping`` naming it, and GDAL's Zarr ``_CRS``."""
    if not crs_wkt:
        return None
    import numpy as np
    import xarray as xr
    from pyproj import CRS

    crs = CRS.from_wkt(crs_wkt)
    try:
        attrs = crs.to_cf()
    except Exception:  # noqa: BLE001 - a CRS without a CF form: its WKT only
        attrs = {}
    attrs.update(crs_wkt=crs_wkt, spatial_ref=crs_wkt)
    layer = {"grid_mapping": GRID_MAPPING, "_CRS": {"wkt": crs_wkt}}
    return xr.DataArray(np.int32(0), attrs=attrs), layer


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
