"""A dask array written to a Zarr array in bands of chunk rows: the graph of one band at a time
(never the whole map's), each band's tasks computed where the scheduler runs them and their
blocks written by the tasks themselves.
"""

from __future__ import annotations

import uuid

# the output a banded write (:func:`store_in_bands`) computes at a time: a band of chunk rows of
# at most this many bytes (one chunk row at least)
BAND_BYTES = 256 * 2**20


def store_in_bands(data, target, *, band_bytes: int = BAND_BYTES, progress=None, also=()) -> list:
    """Write the dask array ``data`` (2-D, or more with the rows on its first axis) into
    ``target`` (a Zarr array of its shape whose chunks are ``data``'s blocks), a band of block
    rows at a time, each band at most ``band_bytes`` of output, so that memory follows the
    band, not the map. ``progress(done, total)`` after each band.

    dask's local schedulers keep a task's result until every task that needs it is done, and
    run any task that is ready: in one graph of a reprojection (each output chunk warps the
    source chunks it overlaps) they read far ahead of the warps, and a large GeoTIFF import
    held gigabytes (benchmarks/bench_dem.py measures the peak). A band's graph holds only what
    that band needs. What the next band needs too (the source chunks astride the boundary) is
    computed once, kept, and handed to the next band's graph as a value: the file is read once
    and the chunks written are those of one graph. On a distributed client what is kept stays
    on the workers (futures) and two bands are in flight, so that the next band's reads
    overlap this one's warps.

    ``also``: delayed values computed by tasks of ``data``'s graph (a warp's figures, made
    with its blocks), each computed in the band that computes its task and returned, in
    order."""
    import functools

    import dask
    import dask.array as da
    from dask.core import flatten, get_dependencies

    from ..runtime.cluster import computing_client

    stored = da.store(data, target, lock=False, compute=False)
    client = computing_client()
    get = dask.base.get_scheduler(collections=[stored])
    rows = [list(flatten(r)) for r in stored.__dask_keys__()]
    row_bytes = max(1, data.nbytes // max(len(rows), 1))
    per = max(1, int(band_bytes // row_bytes))
    bands = [[k for r in rows[i : i + per] for k in r] for i in range(0, len(rows), per)]
    graph = dict(stored.__dask_graph__())
    extra = {d.key: d for d in also}
    for d in also:
        graph.update(d.__dask_graph__())
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

    got_also: dict = {}
    known: dict = {}
    writing: list = []  # on a cluster, the writes of the bands sent and not waited for yet
    for i, keys in enumerate(bands):
        band = cull(keys, known)
        mine = [k for k in extra if k not in got_also and needs(k) <= band.keys()]
        if mine:
            band.update(cull(mine, known))
        keep: list = []
        if i + 1 < len(bands):
            later = cull(bands[i + 1], {})
            shared = band.keys() & later.keys()
            # the shared results the next band uses directly (not only through other shared ones)
            used = set().union(*(needs(j) for j in later if j not in shared))
            keep = [k for k in shared if k in used]
        if client is None:
            got = get(band, keys + keep + mine)
            got_also.update(zip(mine, got[len(keys) + len(keep) :], strict=True))
            if progress is not None:
                progress(i + 1, len(bands))
        else:
            got = _send(client, band, keys + keep + mine)
            got_also.update(zip(mine, got[len(keys) + len(keep) :], strict=True))
            writing.append(got[: len(keys)])
            if len(writing) > 1:  # a task's error is raised here
                client.gather(writing.pop(0))
                if progress is not None:
                    progress(i, len(bands))
        known = dict(zip(keep, got[len(keys) : len(keys) + len(keep)], strict=True))
    for futures in writing:
        client.gather(futures)
        if progress is not None:
            progress(len(bands), len(bands))
    rest = [k for k in extra if k not in got_also]  # (none: each is made with a block)
    if rest:
        got_also.update(zip(rest, dask.compute(*(extra[k] for k in rest)), strict=True))
    values = [got_also[d.key] for d in also]
    if client is not None:
        values = [v.result() if hasattr(v, "result") else v for v in values]
    return values


def _send(client, graph: dict, keys: list) -> list:
    """Futures of ``keys`` of ``graph`` computed on ``client``'s cluster. Sent as delayed
    objects of one named layer: ``client.get`` tokenizes a plain graph first, which grew with
    the map to milliseconds a task; named, a band costs little."""

    from dask.delayed import Delayed
    from dask.highlevelgraph import HighLevelGraph

    name = f"band-{uuid.uuid4().hex}"
    layer = HighLevelGraph.from_collections(name, graph, dependencies=())
    return client.compute([Delayed(k, layer, layer=name) for k in keys], optimize_graph=False)


def _value(v):
    """A task's result kept from an earlier band (:func:`store_in_bands`)."""
    return v
