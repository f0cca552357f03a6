"""Maps stores on object storage (S3) that every worker reads: a real S3-compatible server
(moto's, on loopback), a LocalCluster's worker processes building and planning on a store
through s3:// URLs, against a store built on the local disk from the same DEM."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zarr
from references import MISSION, SMALL, check_path, wall_dem

import pipeline
import pipeline.runtime.cluster
from pipeline.exceptions import PipelineError, StoreExistsError
from pipeline.store.schema import VARIABLE

BUILD = dict(clearance=60.0, min_accumulation=8, landmarks=2)


def dem():
    """The MCPC tests' DEM (a land wall, a closed ring) in four chunks: every object store
    request goes through moto's Python server, a few ms each."""
    return wall_dem().chunk(120)


@pytest.fixture(scope="module")
def s3():
    """A moto S3 server on loopback with a bucket ``survey``; the endpoint and credentials in
    the environment (as an operator sets them on every machine), so that processes started
    from here find them."""
    import s3fs
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("AWS_ENDPOINT_URL", f"http://{host}:{port}")
        mp.setenv("AWS_ACCESS_KEY_ID", "operator")
        mp.setenv("AWS_SECRET_ACCESS_KEY", "secret")
        mp.setenv("AWS_DEFAULT_REGION", "us-east-1")
        s3fs.S3FileSystem.clear_instance_cache()
        fs = s3fs.S3FileSystem()
        fs.mkdir("survey")
        yield fs
        s3fs.S3FileSystem.clear_instance_cache()
    server.stop()


def test_a_store_on_s3_is_built_and_planned_on_by_the_workers(s3, tmp_path, local_client):
    import dask

    local = tmp_path / "maps.zarr"
    url = "s3://survey/maps.zarr"
    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(dem(), local, **BUILD)
    # the S3 settings on every worker, as an operator sets them on every machine (these
    # worker processes started before the server did)
    settings = {k: os.environ[k] for k in os.environ if k.startswith("AWS_")}
    local_client.run(_settle, settings)
    try:
        with pipeline.runtime.cluster.session(local_client):
            pipeline.build_maps(dem(), url, **BUILD)
        # nothing but the store is left in the bucket (no scratch store, no write probe)
        s3.invalidate_cache()
        assert s3.ls("survey") == ["survey/maps.zarr"]
        got, ref = pipeline.open_maps(url), pipeline.open_maps(local)
        assert got.attrs["store"] == url
        # elevation is the DEM given; every other layer equals the local build's
        assert np.array_equal(got["elevation"].values, dem().values.astype(np.float32))
        layers = ["safety", "passable", "accumulation", "ridge", "component", VARIABLE]
        for var in layers:
            a, b = got[var].values, ref[var].values
            assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), var
        for key in ("dem_hash", "landmarks", "parameters", "signature"):
            assert got.attrs[key] == ref.attrs[key], key
        # a mission planned by the workers, reading the store from S3 only
        t = pipeline.plan(url, **MISSION, client=local_client, **SMALL)
        u = pipeline.plan(local, **MISSION, client="synchronous", **SMALL)
        check_path(t, ref["passable"].values, MISSION["start"], MISSION["goal"])
        assert np.array_equal(t.cells, u.cells)
        assert t.length_m == u.length_m and t.status == u.status
        # many missions at once, each a task on the workers, from S3
        back = ((225, 30), (20, 20))
        many = pipeline.plan_missions(
            url, [(MISSION["start"], MISSION["goal"]), back], client=local_client, defaults=SMALL
        )
        assert np.array_equal(many[0].cells, u.cells)
        check_path(many[1], ref["passable"].values, *back)
        # the coarse maps the mission planned on were kept in the store, marked complete
        coarse = zarr.open_group(f"{url}/coarse-rho{SMALL['rho']}", mode="r")
        assert coarse.attrs["complete"] is True
        # a chunk lost from the bucket is damage, said in one line, never NaN planned on
        s3.rm("survey/maps.zarr/safety/c/0/0")
        with pytest.raises(PipelineError, match=r"damaged: chunk \(0, 0\) of its layer 'safety'"):
            pipeline.plan(url, **MISSION, client="synchronous", **SMALL)
    finally:
        local_client.run(_forget, list(settings))


def _settle(settings):
    """Set the S3 settings on a worker."""
    os.environ.update(settings)


def _forget(names):
    """Remove the S3 settings from a worker again (and the filesystems made with them)."""
    import s3fs

    for k in names:
        os.environ.pop(k, None)
    s3fs.S3FileSystem.clear_instance_cache()


def test_object_storage_problems_are_one_line_each(s3, tmp_path):
    t0 = time.perf_counter()
    with pytest.raises(PipelineError, match="cannot be reached.*bucket exists"):
        pipeline.build_maps(dem(), "s3://no-such-bucket/maps.zarr", **BUILD)
    assert time.perf_counter() - t0 < 30  # refused before any compute
    with pytest.raises(PipelineError, match="does not exist"):
        pipeline.open_maps("s3://survey/absent.zarr")
    with pytest.raises(PipelineError, match="does not exist"):
        pipeline.plan("s3://survey/absent.zarr", **MISSION)
    # a build that did not finish leaves a store without its final attributes
    zarr.open_group("s3://survey/partial.zarr", mode="w", zarr_format=3)
    with pytest.raises(PipelineError, match="incomplete"):
        pipeline.open_maps("s3://survey/partial.zarr")
    with pytest.raises(StoreExistsError, match="exists already"):
        pipeline.build_maps(dem(), "s3://survey/partial.zarr", **BUILD)


def test_a_server_that_refuses_is_one_line(tmp_path):
    """A store URL whose filesystem connects as it is made (ftp://) and cannot: one line
    naming the URL and the cause, from the API and the command line; it was a raw socket
    error."""
    import socket

    with socket.socket() as sk:  # a port nothing listens on
        sk.bind(("127.0.0.1", 0))
        port = sk.getsockname()[1]
    url = f"ftp://127.0.0.1:{port}/maps.zarr"
    with pytest.raises(PipelineError, match=r"cannot be reached \(ConnectionRefusedError") as err:
        pipeline.plan(url, **MISSION)
    assert "server answers" in str(err.value) and "AWS" not in str(err.value)
    path = tmp_path / "dem.zarr"
    dem().to_dataset(name="elevation").to_zarr(path, zarr_format=3, consolidated=False)
    res = subprocess.run(
        [Path(sys.executable).parent / "pipeline", "build-maps", path, url, "--landmarks", "0"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    lines = [x for x in res.stderr.splitlines() if x.strip()]
    assert res.returncode == 2 and len(lines) == 1, res.stderr  # bad input: the store
    assert lines[0].startswith(f"error: {url}") and "cannot be reached" in lines[0]


def test_the_cli_says_in_one_line_when_the_bucket_is_wrong(s3, tmp_path):
    path = tmp_path / "dem.zarr"
    dem().to_dataset(name="elevation").to_zarr(path, zarr_format=3, consolidated=False)
    res = subprocess.run(
        [
            Path(sys.executable).parent / "pipeline",
            "build-maps",
            path,
            "s3://no-such-bucket/maps.zarr",
            "--landmarks",
            "0",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode != 0
    lines = [x for x in res.stderr.splitlines() if x.strip()]
    # one line, before a cluster is started; no log of the S3 client, no traceback
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("error: s3://no-such-bucket/maps.zarr cannot be reached")
