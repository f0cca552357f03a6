"""The Python API at its edges, as a notebook or a plain script meets it: no cluster started
behind one ``plan()``, the local cluster's size, real processes and a real LocalCluster."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest
from test_certify import missions

import pipeline


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    path = tmp_path_factory.mktemp("api") / "maps.zarr"
    import dask

    with dask.config.set(scheduler="synchronous"):
        pipeline.build_maps(
            pipeline.synthetic_dem((200, 200), cell_size=50.0, chunks=64, islands=0),
            path,
            clearance=150.0,
            landmarks=2,
        )
    ok = pipeline.open_maps(path)["passable"].values.astype(bool)
    (s, g), *_ = missions(ok, 1, seed=2, min_cells=80)
    return path, [int(v) for v in s], [int(v) for v in g]


def test_a_plain_script_plans_without_a_main_guard_and_without_a_cluster(store):
    """``pipeline.plan`` in a script with no ``if __name__ == "__main__":`` (it started a
    LocalCluster, whose worker processes re-ran the script: tracebacks, "Nanny failed to
    start"): it plans in the script's own process, no worker process started."""
    path, s, g = store
    script = textwrap.dedent(
        f"""
        import multiprocessing, pipeline
        t = pipeline.plan({str(path)!r}, {tuple(s)}, {tuple(g)})
        print(t.status, len(multiprocessing.active_children()))
        import distributed
        try:
            distributed.default_client()
            print("a client")
        except ValueError:
            print("no client")
        """
    )
    proc = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    assert proc.stdout.split() == ["ok", "0", "no", "client"]


def test_an_active_client_is_used_and_none_is_started(store, local_client):
    """Inside ``with client:`` (the user's own cluster) ``plan()`` runs its sections there:
    the scheduler sees its tasks."""
    from distributed import get_task_stream

    path, s, g = store
    with local_client.as_current(), get_task_stream(local_client) as ts:
        t = pipeline.plan(path, tuple(s), tuple(g), mcpc=True, section_size=32)
    assert t.status == "ok" and len(ts.data) > 0
    ref = pipeline.plan(path, tuple(s), tuple(g), mcpc=True, section_size=32)
    assert ref.length_m == pytest.approx(t.length_m)


def test_the_local_clusters_size(tmp_path):
    """``run_job(workers=N)`` and dask's configuration ``auv_pipeline.workers`` size the job's
    LocalCluster (its scheduler counts the workers); a size that is no whole number above 0
    is one line at the dry run."""
    import dask

    job = tmp_path / "job.toml"
    job.write_text(
        "name = 'size'\n[dem.synthetic]\nshape = [60, 60]\n[maps]\nclearance = 100.0\n"
        "[output]\ncatalog = 'cat'\nperformance_report = false\n"
    )
    res = pipeline.run_job(job, workers=3)
    assert res.ok and res.workers == 3
    (tmp_path / "cat" / "catalog.json").unlink()
    for p in (tmp_path / "cat").glob("*.zarr"):
        import shutil

        shutil.rmtree(p)
    with dask.config.set({"auv_pipeline.workers": 1}):
        res = pipeline.run_job(job)
    assert res.workers == 1
    for bad in (0, -2, 1.5):
        with pytest.raises(pipeline.PipelineError, match="number of workers must be a whole"):
            pipeline.run_job(job, workers=bad, dry_run=True)
    assert np.isfinite(res.seconds)
