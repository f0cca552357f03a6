"""The maps store's chunk reads: the direct decode (chunk file + numcodecs, or a shard's index
then its inner chunk's bytes) against zarr's own reads, for every layout the stores use and
awkward shapes; zarr for every other layout."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import zarr
from conftest import metric_dataarray, random_surface
from zarr.codecs import BloscCodec, GzipCodec, ZstdCodec

import pipeline
from pipeline.store.cache import CACHE, ChunkCache
from pipeline.store.zarr_direct import (
    MappedLayer,
    ShardWriter,
    ZarrBlockWriter,
    block_writer,
    direct_reader,
)

CODECS = {
    "blosc-lz4-shuffle": BloscCodec(cname="lz4", clevel=5, shuffle="shuffle"),
    "blosc-zstd-bitshuffle": BloscCodec(cname="zstd", clevel=3, shuffle="bitshuffle"),
    "zstd": ZstdCodec(level=0),
    "none": None,  # the layers a mission reads window by window, in a local store
}
# shapes with a last chunk of one cell, and a side modulo the chunk below any window
SHAPES = [((65, 33), (16, 16)), ((40, 41), (40, 8)), ((7, 300), (3, 256))]


def _array(path, data, chunks, codec, **kw):
    a = zarr.create_array(
        path, shape=data.shape, chunks=chunks, dtype=data.dtype, compressors=codec, **kw
    )
    a[...] = data
    return zarr.open_array(path, mode="r")


# sharded: shards of several inner chunks, a last shard of one inner chunk and of a partial one,
# shards of one inner chunk, inner chunks of one cell
SHARDED = [
    ((65, 33), (16, 16), (32, 32)),
    ((40, 41), (8, 8), (40, 16)),
    ((7, 300), (1, 100), (3, 200)),
    ((50, 50), (25, 25), (25, 25)),
]


@pytest.mark.parametrize("codec", list(CODECS))
@pytest.mark.parametrize("shape, chunks, shards", [(*s, None) for s in SHAPES] + SHARDED, ids=str)
@pytest.mark.parametrize("dtype", ["float32", "bool", "int32"])
def test_direct_reads_equal_zarr(tmp_path, codec, shape, chunks, shards, dtype):
    rng = np.random.default_rng(3)
    data = rng.normal(size=shape).astype(np.float32) * 100
    if dtype == "float32":
        data[0, 0] = np.nan
    data = data.astype(dtype) if dtype != "bool" else data > 0
    arr = _array(tmp_path / "a", data, chunks, CODECS[codec], shards=shards)
    assert direct_reader(arr, str(tmp_path), "a") is not None  # the direct path is taken
    # windows of a sharded uncompressed layer are copied from its mapped shards
    mapped = MappedLayer.of(arr, str(tmp_path), "a")
    assert (mapped is not None) == (codec == "none" and shards is not None)
    cache = ChunkCache(2**30)
    for _ in range(25):
        r0, c0 = rng.integers(shape[0]), rng.integers(shape[1])
        r1, c1 = rng.integers(r0, shape[0]) + 1, rng.integers(c0, shape[1]) + 1
        got = cache.window(str(tmp_path), "a", r0, r1, c0, c1, complete=True)
        np.testing.assert_array_equal(got, arr[r0:r1, c0:c1])
        assert got.dtype == arr.dtype
    np.testing.assert_array_equal(
        cache.window(str(tmp_path), "a", 0, *shape[:1], 0, shape[1]), data
    )


def _files(root) -> dict:
    """Every chunk or shard file under a Zarr array's directory, by its key: its bytes."""
    return {
        str(p.relative_to(root)): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != "zarr.json"
    }


@pytest.mark.parametrize("codec", list(CODECS))
@pytest.mark.parametrize(
    "shape, chunks, shards",
    SHARDED + [((600, 700), (256, 256), (512, 512)), ((9, 70), (3, 8), (9, 32))],
    ids=str,
)
@pytest.mark.parametrize("dtype", ["float32", "bool", "int32"])
def test_the_shard_writer_writes_the_bytes_zarr_writes(
    tmp_path, codec, shape, chunks, shards, dtype
):
    """Shards written by ShardWriter (the maps build's layers) against zarr's own write of the
    same data: the same files, byte for byte (inner chunks in zarr's order, those wholly past
    the edge left out, the parts of one filled with the fill value, the index and its CRC32C);
    and zarr reads back the data. Shards of unequal inner chunk counts a side (4 x 1, 3 x 4)
    exercise zarr's compressed Z-order."""
    rng = np.random.default_rng(5)
    data = rng.normal(size=shape).astype(np.float32) * 100
    if dtype == "float32":
        data[rng.random(shape) < 0.05] = np.nan
    data = data.astype(dtype) if dtype != "bool" else data > 0
    kw = dict(
        shape=shape, chunks=chunks, shards=shards, dtype=data.dtype, compressors=CODECS[codec]
    )
    fill = dict(fill_value=np.nan) if dtype == "float32" else {}
    ref = zarr.create_array(tmp_path / "zarr", config={"write_empty_chunks": True}, **kw, **fill)
    ref[...] = data
    zarr.create_array(tmp_path / "ours", config={"write_empty_chunks": True}, **kw, **fill)
    write = block_writer(str(tmp_path), "ours")
    assert isinstance(write, ShardWriter)
    for i in range(-(-shape[0] // shards[0])):
        for j in range(-(-shape[1] // shards[1])):
            block = data[i * shards[0] : (i + 1) * shards[0], j * shards[1] : (j + 1) * shards[1]]
            assert write((i, j), block) == len(_files(tmp_path / "ours")[f"c/{i}/{j}"])
    assert _files(tmp_path / "ours") == _files(tmp_path / "zarr")
    np.testing.assert_array_equal(zarr.open_array(tmp_path / "ours", mode="r")[...], data)
    with pytest.raises(ValueError, match="given a block"):
        write((0, 0), data[:1, :1] if shape != (1, 1) else data[:0])


def test_other_layouts_are_written_by_zarr(tmp_path):
    data = np.arange(40 * 40, dtype=np.float32).reshape(40, 40)
    zarr.create_array(
        tmp_path / "p", shape=data.shape, chunks=(16, 16), dtype=data.dtype, compressors=None
    )
    write = block_writer(str(tmp_path), "p")
    assert isinstance(write, ZarrBlockWriter)
    for i in range(3):
        for j in range(3):
            write((i, j), data[i * 16 : (i + 1) * 16, j * 16 : (j + 1) * 16])
    np.testing.assert_array_equal(zarr.open_array(tmp_path / "p", mode="r")[...], data)


def test_reads_in_several_threads_at_once_equal_zarr(tmp_path):
    """Each thread reads a chunk's bytes into a buffer of its own (the decode releases the GIL
    while another thread reads): windows read by 4 threads at once, every chunk decoded anew,
    equal zarr's read."""
    from concurrent.futures import ThreadPoolExecutor

    rng = np.random.default_rng(8)
    data = rng.normal(size=(512, 512)).astype(np.float32)
    arr = _array(tmp_path / "a", data, (64, 64), CODECS["blosc-lz4-shuffle"], shards=(256, 256))
    assert direct_reader(arr, str(tmp_path), "a") is not None  # the direct path is taken
    windows = [tuple(int(v) for v in rng.integers(0, 448, 2)) for _ in range(400)]

    def read(w):
        cache = ChunkCache(0)  # nothing kept: every window decodes its chunks
        r, c = w
        return cache.window(str(tmp_path), "a", r, r + 64, c, c + 64, complete=True)

    with ThreadPoolExecutor(4) as pool:
        for (r, c), got in zip(windows, pool.map(read, windows), strict=True):
            np.testing.assert_array_equal(got, data[r : r + 64, c : c + 64])


@pytest.mark.parametrize("shape, chunks, shards", [(*s, None) for s in SHAPES] + SHARDED, ids=str)
@pytest.mark.parametrize("dtype, tile", [("float32", "float32"), ("bool", "uint8")])
def test_a_chunk_read_into_a_tile_equals_zarr(tmp_path, shape, chunks, shards, dtype, tile):
    """``chunk_into`` (the flight's corridor) decodes a chunk straight into a tile of its full
    shape, or copies it from the cache when the cache holds it, or reads it through zarr for a
    layout read otherwise (gzip): each time the part within the layer equals the
    data and the returned shape is that part's (clipped at the last row and column of
    chunks)."""
    rng = np.random.default_rng(5)
    data = rng.normal(size=shape).astype(np.float32) * 100
    data = data.astype(dtype) if dtype != "bool" else data > 0
    arr = _array(tmp_path / "a", data, chunks, CODECS["blosc-lz4-shuffle"], shards=shards)
    other = _array(tmp_path / "b", data, chunks, GzipCodec(level=1), shards=shards)
    assert direct_reader(arr, str(tmp_path), "a") is not None
    assert direct_reader(other, str(tmp_path), "b") is None
    ch, cw = chunks
    cache = ChunkCache(2**30)
    for var in ("a", "b"):
        for kept in (False, True):  # decoded into the tile, then copied from the cache
            for ci in range(-(-shape[0] // ch)):
                for cj in range(-(-shape[1] // cw)):
                    if kept:
                        cache.chunk(str(tmp_path), var, ci, cj)
                    out = np.zeros(chunks, dtype=tile)
                    # not complete: a chunk of the fill value only is not written (bool)
                    h, w = cache.chunk_into(str(tmp_path), var, ci, cj, out)
                    want = data[ci * ch : (ci + 1) * ch, cj * cw : (cj + 1) * cw]
                    assert (h, w) == want.shape
                    np.testing.assert_array_equal(out[:h, :w], want.astype(tile))


def test_shard_files_stay_open_within_a_bound_while_threads_read_them(tmp_path, monkeypatch):
    """A reader keeps the last ``OPEN_FILES`` shard files of a layer open. With a bound of one,
    four threads sharing one cache drop each other's files all the time: every read still
    equals the data (a file dropped while another thread reads it stays open until that read
    ends), and no more files stay open than the bound."""
    import gc
    import os
    from concurrent.futures import ThreadPoolExecutor

    monkeypatch.setattr("pipeline.store.zarr_direct.OPEN_FILES", 1)
    rng = np.random.default_rng(9)
    data = rng.normal(size=(512, 512)).astype(np.float32)
    _array(tmp_path / "a", data, (32, 32), CODECS["blosc-lz4-shuffle"], shards=(128, 128))
    windows = [tuple(int(v) for v in rng.integers(0, 448, 2)) for _ in range(400)]
    cache = ChunkCache(0)  # one reader for the four threads; every window decodes its chunks

    def read(w):
        r, c = w
        return cache.window(str(tmp_path), "a", r, r + 64, c, c + 64, complete=True)

    def open_here():
        fds = []
        for fd in os.listdir("/proc/self/fd"):
            try:
                fds.append(os.readlink(f"/proc/self/fd/{fd}"))
            except OSError:
                continue  # the listing's own descriptor
        return [p for p in fds if p.startswith(str(tmp_path / "a"))]

    with ThreadPoolExecutor(4) as pool:
        for (r, c), got in zip(windows, pool.map(read, windows), strict=True):
            np.testing.assert_array_equal(got, data[r : r + 64, c : c + 64])
    gc.collect()
    assert len(open_here()) == 1  # 16 shard files read, the last one kept
    cache.clear()
    gc.collect()
    assert open_here() == []


def test_the_stack_of_landmark_layers_equals_zarr(tmp_path):
    rng = np.random.default_rng(4)
    data = rng.uniform(0, 1e5, size=(3, 70, 45)).astype(np.float32)
    data[1, 60:, :] = np.inf
    for chunks in ((1, 32, 32), (3, 16, 40), (2, 64, 64)):
        arr = _array(tmp_path / f"l{chunks[0]}", data, chunks, CODECS["blosc-zstd-bitshuffle"])
        cache = ChunkCache(2**30)
        cells = ((0, 0), (69, 44), (33, 17), (64, 40))
        # all kept before any is checked: each is its own array, not a view of the buffer
        got = [cache.stack_values(str(tmp_path), f"l{chunks[0]}", r, c, True) for r, c in cells]
        for (r, c), values in zip(cells, got, strict=True):
            np.testing.assert_array_equal(values, arr[:, r, c])
        assert cache.used == 0  # read past the cache


def test_other_layouts_are_read_by_zarr(tmp_path):
    from zarr.codecs import BytesCodec, ShardingCodec

    data = np.arange(40 * 40, dtype=np.float32).reshape(40, 40)
    plain = _array(tmp_path / "p", data, (8, 8), GzipCodec(level=1))  # not blosc nor zstd
    index_first = zarr.create_array(  # a shard index at the start of each shard
        tmp_path / "s",
        shape=data.shape,
        chunks=(16, 16),
        dtype=data.dtype,
        serializer=ShardingCodec(
            chunk_shape=(8, 8), codecs=[BytesCodec(), CODECS["zstd"]], index_location="start"
        ),
        compressors=None,
    )
    index_first[...] = data
    for name, arr in (("s", zarr.open_array(tmp_path / "s")), ("p", plain)):
        assert direct_reader(arr, str(tmp_path), name) is None
        got = ChunkCache(2**30).window(str(tmp_path), name, 3, 29, 5, 40)
        np.testing.assert_array_equal(got, data[3:29, 5:40])


def test_a_missing_chunk_reads_as_the_fill_value_unless_the_store_is_complete(tmp_path):
    a = zarr.create_array(
        tmp_path / "m",
        shape=(20, 20),
        chunks=(10, 10),
        dtype="float32",
        fill_value=-7.0,
        compressors=CODECS["blosc-lz4-shuffle"],
    )
    a[:10, :10] = 1.0  # the other three chunks are never written
    cache = ChunkCache(2**30)
    got = cache.window(str(tmp_path), "m", 5, 15, 5, 15)
    assert (got[:5, :5] == 1.0).all() and (got[5:, :] == -7.0).all()
    with pytest.raises(pipeline.PipelineError, match=r"chunk \(0, 1\) of its layer 'm' is missing"):
        ChunkCache(2**30).window(str(tmp_path), "m", 5, 15, 5, 15, complete=True)


def test_a_corrupt_chunk_is_damage_not_a_traceback(tmp_path):
    data = np.ones((20, 20), dtype=np.float32)
    _array(tmp_path / "c", data, (10, 10), CODECS["blosc-lz4-shuffle"])
    (tmp_path / "c" / "c" / "1" / "0").write_bytes(b"not a blosc frame at all")
    with pytest.raises(
        pipeline.PipelineError, match=r"damaged: chunk c/1/0 of its layer 'c' cannot be decoded"
    ):
        ChunkCache(2**30).window(str(tmp_path), "c", 0, 20, 0, 20, complete=True)


def _sharded_layer(tmp_path, name="h", codec="blosc-lz4-shuffle"):
    data = np.arange(40 * 40, dtype=np.float32).reshape(40, 40)
    _array(
        tmp_path / name,
        data,
        (8, 8),
        CODECS[codec],
        shards=(16, 16),
        config={"write_empty_chunks": True},
    )
    return data


@pytest.mark.parametrize("codec", ["blosc-lz4-shuffle", "none"])
def test_a_shard_or_an_inner_chunk_missing_is_damage_in_a_complete_store(tmp_path, codec):
    import os

    data = _sharded_layer(tmp_path, codec=codec)
    os.remove(tmp_path / "h" / "c" / "1" / "0")  # rows 16-31, columns 0-15
    got = ChunkCache(2**30).window(str(tmp_path), "h", 0, 40, 0, 40)  # not complete: fill
    assert (got[16:32, :16] == 0).all() and (got[:16] == data[:16]).all()
    with pytest.raises(pipeline.PipelineError, match=r"chunk \(2, 0\) of its layer 'h' is missing"):
        ChunkCache(2**30).window(str(tmp_path), "h", 10, 20, 0, 5, complete=True)
    # a shard whose index says an inner chunk was never written
    arr = zarr.open_array(tmp_path / "h", mode="r+", config={"write_empty_chunks": False})
    arr[32:40, 8:16] = 0  # all fill value: zarr drops the inner chunk from its shard
    with pytest.raises(pipeline.PipelineError, match=r"chunk \(4, 1\) of its layer 'h' is missing"):
        ChunkCache(2**30).window(str(tmp_path), "h", 32, 40, 0, 40, complete=True)


@pytest.mark.parametrize("codec", ["blosc-lz4-shuffle", "none"])
def test_a_bad_shard_index_is_damage_not_a_traceback(tmp_path, codec):
    _sharded_layer(tmp_path, codec=codec)
    shard = tmp_path / "h" / "c" / "0" / "1"
    raw = bytearray(shard.read_bytes())
    raw[-10] ^= 0xFF  # inside the index: its checksum no longer matches
    shard.write_bytes(bytes(raw))
    with pytest.raises(pipeline.PipelineError, match=r"damaged: chunk c/0/1 of its layer 'h'"):
        ChunkCache(2**30).window(str(tmp_path), "h", 0, 40, 0, 40, complete=True)
    shard.write_bytes(b"short")  # shorter than the index itself
    with pytest.raises(pipeline.PipelineError, match=r"damaged: chunk c/0/1 of its layer 'h'"):
        ChunkCache(2**30).window(str(tmp_path), "h", 0, 40, 0, 40, complete=True)


def test_mapped_shards_stay_within_a_bound_and_their_chunks_go_with_them(tmp_path, monkeypatch):
    """A mapped layer keeps at most MAPPED_SHARDS shards mapped; the chunk views of a shard it
    unmaps go with it, and windows across every shard still equal zarr's reads."""
    import pipeline.store.zarr_direct as store_mod

    monkeypatch.setattr(store_mod, "MAPPED_SHARDS", 2)
    data = _sharded_layer(tmp_path, codec="none")  # 40 x 40, shards 16^2 of inner chunks 8^2
    cache = ChunkCache(2**30)
    rng = np.random.default_rng(8)
    for _ in range(40):
        r0, c0 = rng.integers(40), rng.integers(40)
        r1, c1 = rng.integers(r0, 40) + 1, rng.integers(c0, 40) + 1
        got = cache.window(str(tmp_path), "h", r0, r1, c0, c1, complete=True)
        np.testing.assert_array_equal(got, data[r0:r1, c0:c1])
        layer = cache.mapped[(str(tmp_path), "h")]
        assert len(layer.shards) <= 2
        assert {(i // 2, j // 2) for i, j in layer.blocks} <= set(layer.shards)


def test_an_uncompressed_inner_chunk_of_the_wrong_size_is_damage(tmp_path):
    """A shard whose index (checksum and all) gives an uncompressed inner chunk fewer bytes
    than its cells need, or bytes past the end of the file."""
    from numcodecs.checksum32 import CRC32C

    data = _sharded_layer(tmp_path, codec="none")
    shard = tmp_path / "h" / "c" / "0" / "0"
    raw = shard.read_bytes()
    n = 4  # inner chunks a shard (16 / 8 on each side)
    table = np.frombuffer(raw[-(16 * n + 4) : -4], dtype="<u8").reshape(n, 2).copy()
    np.testing.assert_array_equal(  # the layer is what it was, read through its mapped shards
        ChunkCache(2**30).window(str(tmp_path), "h", 0, 40, 0, 40, complete=True), data
    )
    for offset, size in ((table[1, 0], table[1, 1] - 4), (len(raw), table[1, 1])):
        bad = table.copy()
        bad[1] = (offset, size)
        index = CRC32C(location="end").encode(bad.tobytes())
        shard.write_bytes(raw[: -(16 * n + 4)] + bytes(index))
        with pytest.raises(
            pipeline.PipelineError, match=r"damaged: chunk c/0/0 \(inner chunk \(0, 1\)\) of its"
        ):
            ChunkCache(2**30).window(str(tmp_path), "h", 0, 16, 0, 16, complete=True)


def test_a_store_rebuilt_in_place_is_not_read_through_old_chunks(tmp_path):
    """A maps store rebuilt at the same path, in a process that read the old one (a worker of
    a long-lived cluster between two jobs, a notebook): its windows are the new store's, as
    zarr reads them, not chunks decoded from the old store and kept in the process's cache."""
    import dask

    path = tmp_path / "maps.zarr"
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(pipeline.synthetic_dem((120, 120), seed=1, chunks=60), path)
        old = pipeline.open_store(path).window("safety", 0, 120, 0, 120)
        pipeline.build_maps(
            pipeline.synthetic_dem((120, 120), seed=2, chunks=60), path, overwrite=True
        )
    new = zarr.open_group(path, mode="r")["safety"][...]
    assert not np.array_equal(old, new, equal_nan=True)  # the rebuild changed the layer
    got = pipeline.open_store(path).window("safety", 0, 120, 0, 120)
    np.testing.assert_array_equal(got, new)


def test_a_local_store_keeps_the_window_layers_uncompressed_and_reads_them_mapped(tmp_path):
    """build_maps writes safety, ridge and passable without a compressor in a local store (the
    other layers compressed); their windows, copied from the mapped shards, equal zarr's."""
    from pipeline.store.schema import WINDOW_LAYERS

    path = _maps_of(random_surface((70, 45), seed=4) * 400.0, tmp_path)
    group = zarr.open_group(path, mode="r")
    for var in ("elevation", "accumulation", *WINDOW_LAYERS):
        arr = group[var]
        compressed = var not in WINDOW_LAYERS
        assert (len(arr.compressors) > 0) == compressed, var
        assert (MappedLayer.of(arr, str(path), var) is None) == compressed
    m = pipeline.open_store(path)
    rng = np.random.default_rng(2)
    for var in WINDOW_LAYERS:
        for _ in range(10):
            r0, c0 = rng.integers(70), rng.integers(45)
            r1, c1 = rng.integers(r0, 70) + 1, rng.integers(c0, 45) + 1
            got = m.window(var, r0, r1, c0, c1)
            np.testing.assert_array_equal(got, group[var][r0:r1, c0:c1])
    assert all(CACHE.mapped[(m.path, v)] is not None for v in WINDOW_LAYERS)


def test_values_at_cells_equal_zarr_in_mapped_and_compressed_layers(tmp_path):
    """``MapsStore.values`` (one value per cell, as the snapping of a mission's joints reads
    the passable layer) against zarr's whole layer, at random cells and at the corners of the
    last chunks (one cell wide: 70 x 49 in chunks of 16), for the mapped, uncompressed layers
    and the compressed ones read through the chunk cache."""
    from pipeline.store.schema import WINDOW_LAYERS

    path = _maps_of(random_surface((70, 49), seed=6) * 400.0, tmp_path)
    group = zarr.open_group(path, mode="r")
    m = pipeline.open_store(path)
    rng = np.random.default_rng(3)
    cells = [(int(r), int(c)) for r, c in rng.integers(0, [70, 49], size=(200, 2))]
    cells += [(0, 0), (69, 48), (64, 48), (69, 0), (63, 47)]
    for var in (*WINDOW_LAYERS, "component", "elevation"):
        whole = group[var][:]
        got = m.values(var, cells)
        assert got.dtype == whole.dtype and got.shape == (len(cells),)
        np.testing.assert_array_equal(got, whole[tuple(np.array(cells).T)])
        assert (CACHE.mapped[(m.path, var)] is None) == (var not in WINDOW_LAYERS)
    assert m.values("passable", []).shape == (0,)


def _maps_of(z, tmp_path):
    """The maps store of the seabed ``z`` (50 m cells, chunks of 16), built in this process."""
    import dask

    dem = metric_dataarray(z, a=50.0)
    dem.attrs["cell_size"] = 50.0
    path = tmp_path / "maps.zarr"
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(dem.chunk(16), path, clearance=120.0, min_accumulation=6, landmarks=0)
    return path


@pytest.mark.parametrize("factor", [2, 4, 8])
@pytest.mark.parametrize("shape", [(61, 43), (49, 33)], ids=str)
def test_overview_is_the_block_mean_of_the_elevation_and_any_ridge(tmp_path, factor, shape):
    """The pictures' overview of a maps store (sides not multiples of the factor, chunks of 16
    with a last chunk of one cell, no-data holes, one block wholly no-data) against numpy's
    block means and block any."""
    z = random_surface(shape, seed=5, holes=True)
    z[:8, :8] = np.nan  # a block with no elevation at all
    path = _maps_of(z, tmp_path)
    ds = pipeline.open_maps(path)
    elev = ds["elevation"].values.astype(np.float64)
    ridge = ds["ridge"].values.astype(bool)
    ov = pipeline.open_store(path).overview(factor)
    rows, cols = elev.shape
    nr, nc = -(-rows // factor), -(-cols // factor)
    assert ov["elevation"].shape == ov["ridge"].shape == (nr, nc)
    for i in range(nr):
        for j in range(nc):
            blk = elev[i * factor : (i + 1) * factor, j * factor : (j + 1) * factor]
            known = blk[np.isfinite(blk)]
            if known.size:
                assert ov["elevation"][i, j] == pytest.approx(known.mean(), abs=1e-3)
            else:
                assert np.isnan(ov["elevation"][i, j])
            rb = ridge[i * factor : (i + 1) * factor, j * factor : (j + 1) * factor]
            assert ov["ridge"][i, j] == rb.any()
    assert np.isnan(ov["elevation"]).any() and ov["ridge"].any()
    # written into the store once: a new process (a fresh MapsStore) reads the same arrays
    again = pipeline.store.maps_store.MapsStore(str(path)).overview(factor)
    np.testing.assert_array_equal(again["elevation"], ov["elevation"])
    assert (path / f"overview-f{factor}" / "zarr.json").is_file()


def test_a_quicklooks_plan_view_layers_follow_its_region(tmp_path):
    """A quick-look's plan view: a region of a sixteenth of the map or more from the overview
    (block means at the block centres, ridge where a block has any), a smaller one from every
    k-th cell of the elevation and the ridge of each k x k block (numpy on the layers)."""
    from pipeline.outputs.plots import plan_layers

    path = _maps_of(random_surface((64, 48), seed=6, holes=True), tmp_path)
    m = pipeline.open_store(path)
    ds = pipeline.open_maps(path)
    elev, ridge = ds["elevation"].values.astype(np.float64), ds["ridge"].values.astype(bool)
    x, y = ds["x"].values, ds["y"].values
    sub, rdg = plan_layers(m, 0, 64, 8, 48, 3.7)  # the whole height: from the overview at 4
    blocks = elev[:, 8:48].reshape(16, 4, 10, 4)
    with warnings.catch_warnings():  # blocks of no-data only: NaN, as the overview's
        warnings.simplefilter("ignore", RuntimeWarning)
        want = np.nanmean(blocks, axis=(1, 3))
    np.testing.assert_allclose(sub.values, want, atol=1e-3)
    np.testing.assert_allclose(sub["x"].values, x[8:48].reshape(10, 4).mean(axis=1))
    np.testing.assert_allclose(sub["y"].values, y.reshape(16, 4).mean(axis=1))
    assert sub.attrs["cell_size"] == 200.0
    np.testing.assert_array_equal(rdg, ridge[:, 8:48].reshape(16, 4, 10, 4).any(axis=(1, 3)))
    sub, rdg = plan_layers(m, 0, 64, 0, 48, 2.5)  # k = 3: the overview at 3, a partial row
    assert sub.shape == (22, 16) and sub.attrs["cell_size"] == 150.0
    pad = np.full((66, 48), np.nan)
    pad[:64] = elev
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        want = np.nanmean(pad.reshape(22, 3, 16, 3), axis=(1, 3))
    np.testing.assert_allclose(sub.values, want, atol=1e-3)
    sub, rdg = plan_layers(m, 10, 22, 5, 17, 2.6)  # 12 x 12 cells: every third cell
    np.testing.assert_array_equal(sub.values, elev[10:22:3, 5:17:3])
    np.testing.assert_array_equal(sub["x"].values, x[5:17:3])
    np.testing.assert_array_equal(rdg, ridge[10:22, 5:17].reshape(4, 3, 4, 3).any(axis=(1, 3)))


def test_a_stores_parameters_are_read_once_with_the_defaults_of_older_stores():
    """``MapsStore.parameters``: the build's parameters as one frozen object; a store built
    before a key was kept reads its default (spherical, sea level 0, surface clearance R); the
    horizontal radius is the horizontal method's own clearance where it was given."""
    import dataclasses

    from pipeline.store.schema import MapsParameters

    old = MapsParameters.from_attrs('{"clearance_m": 300}')
    assert (old.method, old.sea_level_m, old.radius_m, old.top_m) == (
        "spherical",
        0.0,
        300.0,
        -300.0,
    )
    h = MapsParameters.from_attrs(
        {
            "method": "horizontal",
            "clearance_m": 100.0,
            "horizontal_clearance_m": 250.0,
            "sea_level_m": 5.0,
            "surface_clearance_m": 20.0,
        }
    )
    assert (h.radius_m, h.top_m) == (250.0, -15.0)
    assert (
        MapsParameters.from_attrs(
            {"method": "spherical", "clearance_m": 100.0, "horizontal_clearance_m": 250.0}
        ).radius_m
        == 100.0
    )
    with pytest.raises(dataclasses.FrozenInstanceError):
        h.clearance_m = 1.0


def test_a_file_is_written_whole_or_not_at_all(tmp_path):
    """``write_atomically``: the new content replaces the old at once; a write that fails
    half-way leaves the old file as it was and no temporary beside it."""
    from pipeline.store.paths import TEMPORARY, write_atomically

    path = tmp_path / "index.html"
    write_atomically(path, "old")
    assert path.read_text() == "old"

    def half(tmp):
        tmp.write_text("half of the new")
        assert TEMPORARY.match(tmp.name) and tmp.suffix == ".png"
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space"):
        write_atomically(path, write=half, suffix=".png")
    assert path.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["index.html"]
    write_atomically(path, b"\x89new")
    assert path.read_bytes() == b"\x89new"
