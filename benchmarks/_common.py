"""Helpers for the benchmark scripts: machine description and isolated, memory-measured runs."""

from __future__ import annotations

import contextlib
import inspect
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from importlib import metadata
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT = HERE / "out"


def own_peak_gib() -> float:
    """This process's own peak resident memory, GiB: the high-water mark of its memory map
    (``VmHWM`` of /proc/self/status). Not ``ru_maxrss``, which a process started by another
    inherits from it (exec keeps the peak of the memory map it replaces, the parent's own when
    Python starts the child with vfork): measured, a fresh Python child of a process that had
    peaked at 1.24 GiB reported ru_maxrss 1.24 GiB and VmHWM 0.01 GiB, so the isolated runs'
    and the workers' peaks could be their parents'. ru_maxrss where there is no /proc."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 2**20
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


# own_peak_gib's source, for the code the isolated processes run (they do not import this module)
PEAK_FN = inspect.getsource(own_peak_gib)


LIBRARIES = (
    "numpy",
    "numba",
    "scipy",
    "dask",
    "distributed",
    "xarray",
    "zarr",
    "rasterio",
    "rioxarray",
    "pystac",
    "geopandas",
    "matplotlib",
    "pyastar2d",
    "scikit-image",
    "pysheds",
)


def machine_info() -> dict:
    """Cores, CPU model, memory, OS, Python and the versions of the libraries measured."""
    cpu = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    libs = {}
    for p in LIBRARIES:
        try:
            libs[p] = metadata.version(p)
        except metadata.PackageNotFoundError:
            libs[p] = "missing"
    return dict(
        cores=os.cpu_count(),
        cpu=cpu,
        memory_gib=round(mem),
        os=platform.platform(),
        python=platform.python_version(),
        libs=libs,
    )


def machine() -> str:
    m = machine_info()
    libs = ", ".join(f"{k} {v}" for k, v in m["libs"].items())
    return (
        f"{m['cores']} cores ({m['cpu']}), {m['memory_gib']} GiB, Python {m['python']}, "
        f"{libs}; {time.strftime('%Y-%m-%d')}"
    )


def run_job_timed(job: Path) -> dict:
    """``pipeline run JOB`` under ``/usr/bin/time -v`` from an empty catalog: exit code, wall
    time, the client process's peak RSS, its stderr (the log) and its last stdout line."""
    import re
    import shutil

    from pipeline.jobs.job_file import load_job

    shutil.rmtree(HERE.parent / load_job(job).catalog, ignore_errors=True)
    cmd = ["/usr/bin/time", "-v", str(Path(sys.executable).parent / "pipeline"), "run", str(job)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=HERE.parent)
    wall = time.perf_counter() - t0
    peak = re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr)
    return dict(
        exit=proc.returncode,
        wall_s=wall,
        client_peak_gib=int(peak.group(1)) / 2**20 if peak else float("nan"),
        log=proc.stderr,
        summary=(proc.stdout.strip().splitlines() or ["-"])[-1],
    )


_WRAP = (
    "import json, resource\n"
    + PEAK_FN
    + """
{code}
result["peak_rss_gib"] = round(own_peak_gib(), 3)
if "peak_rss_children_gib" not in result:  # (the largest worker's, where the code records it)
    _kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    result["peak_rss_children_gib"] = round(_kids / 2**20, 3)
print(json.dumps(result))
"""
)


def run_isolated(code: str, *, timeout: float = 1800) -> dict:
    """Run ``code`` (which sets a dict ``result``) in a fresh Python process.

    Returns ``result`` plus ``peak_rss_gib``, the process's own peak resident memory
    (:func:`own_peak_gib`, which the code may call), and ``peak_rss_children_gib``, the largest
    of its workers' (the code records it with ``own_peak_gib`` on each worker before its
    cluster closes; else the largest ru_maxrss of its child processes, which counts at least
    this process's peak when each started).
    """
    proc = subprocess.run(
        [sys.executable, "-c", _WRAP.format(code=code)],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=HERE.parent,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"benchmark child failed:\n{proc.stderr[-4000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


# a preamble for run_isolated snippets: make the n x n synthetic DEM store if it is missing,
# then start a LocalCluster of 2 single-threaded workers (`client`), warmed with `warm()`
CLUSTER_PREAMBLE = """
import time, dask, pipeline, shutil, resource, xarray as xr
from pathlib import Path
from distributed import Client
from pipeline.runtime.cluster import local_cluster
src = "{src}"
if not Path(src).exists():
    with dask.config.set(scheduler="threads"):
        pipeline.write_dem(pipeline.synthetic_dem(({n}, {n}), cell_size=30.0, seed=0,
                                                  chunks=1024), src, chunks=1024)
cluster = local_cluster(dashboard_address=None)
client = Client(cluster)
small = pipeline.synthetic_dem((300, 300), chunks=100)
pipeline.safety_map(small, "spherical", 300.0).compute()   # warm the workers' numba caches
pipeline.flow_accumulation(small).compute()
def worker_peaks():
    return [round(v, 3) for v in client.run(own_peak_gib).values()]
"""

# ridge threshold of the planning benchmarks' maps: 20 cells (1.8 ha at 30 m) marks about 8 % of
# the cells, a network dense enough to follow (the 1 km^2 default marks under 1 %)
BENCH_MIN_ACC = 20


def quantised_layers(group) -> bool:
    """Whether the maps store ``group`` (zarr) holds landmark layers searched on quantised
    heights, as builds now search them (their ``quantised_blocks`` attribute)."""
    return "landmark_distance" in group and "quantised_blocks" in group["landmark_distance"].attrs


def maps_store(n: int, *, min_accumulation: int = BENCH_MIN_ACC) -> Path:
    """``benchmarks/out/maps{n}.zarr``: the maps of the n x n synthetic ridge DEM (seed 0, 30 m,
    spherical clearance 300 m), built once and reused afterwards."""
    store = OUT / f"maps{n}.zarr"
    if store.exists():
        import zarr

        group = zarr.open_group(store, mode="r")
        current = "landmarks" in group.attrs and group["safety"].shards is not None
        if current and "landmark_distance" in group:  # the landmark layers sharded too,
            layers = group["landmark_distance"]  # searched on quantised heights
            current = layers.shards is not None and quantised_layers(group)
        # the layers missions read window by window stored uncompressed, as builds now do
        current = current and not group["safety"].compressors
        if current:
            return store
        import shutil

        print(
            f"{store.name} predates the landmark layers, their sharding or quantised heights, "
            "or the uncompressed window layers: building it again"
        )
        shutil.rmtree(store)
    build = f"""
    dem = pipeline.synthetic_dem(({n}, {n}), cell_size=30.0, seed=0, chunks=1024)
    pipeline.build_maps(dem, "{store}", method="spherical", clearance=300.0,
                        min_accumulation={min_accumulation}, chunks=1024)"""
    # up to 5000^2 dask's threads in one process are quickest (no cluster to start); larger maps
    # are built the way a job builds them, by a LocalCluster of 2 single-threaded workers
    code = (
        "import dask, pipeline\nfrom distributed import Client\n"
        + "from pipeline.runtime.cluster import local_cluster\n"
        + (
            "with dask.config.set(scheduler='threads', num_workers=2):"
            if n <= 5000
            else "with local_cluster(dashboard_address=None) as cl, Client(cl):"
        )
        + build
        + (
            "\nresult = {}\n"
            if n <= 5000
            else "\n    result = {'peak_rss_children_gib': round(max(Client.current()"
            ".run(own_peak_gib).values()), 3)}\n"
        )
    )
    OUT.mkdir(exist_ok=True)
    print(f"building {store.name} (once) ...", flush=True)
    t0 = time.perf_counter()
    res = run_isolated(code, timeout=7200)
    res["seconds"] = time.perf_counter() - t0
    (OUT / f"maps{n}.build.json").write_text(json.dumps(res))  # peak memory of the build
    return store


def far_missions(ok, n: int, count: int, seed: int) -> list:
    """``count`` missions on the n x n map whose passable layer is ``ok`` (lazy xarray): both
    ends passable and at least half the map apart."""
    import numpy as np

    rng = np.random.default_rng(seed)
    out = []
    while len(out) < count:
        s, g = rng.integers(n, size=2), rng.integers(n, size=2)
        if (
            np.hypot(*(s - g)) >= 0.5 * n
            and ok[int(s[0]), int(s[1])].values
            and ok[int(g[0]), int(g[1])].values
        ):
            out.append((tuple(int(v) for v in s), tuple(int(v) for v in g)))
    return out


def passable_neighbour(ok, cell) -> tuple[int, int]:
    """A passable cell next to ``cell`` (east, south, west or north, the first that is): the
    goal of a peer's search of one step, whose time is then its own fixed cost."""
    r, c = cell
    return next(
        (r + dr, c + dc)
        for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0))
        if 0 <= r + dr < ok.shape[0] and 0 <= c + dc < ok.shape[1] and ok[r + dr, c + dc]
    )


@contextlib.contextmanager
def checkout(rev: str):
    """The library as it was at the git revision ``rev``: a checkout's root, in a temporary git
    worktree removed afterwards (a before/after measure, each version in a process of its own
    run from its root)."""
    root = Path(__file__).resolve().parents[1]
    tree = Path(tempfile.mkdtemp(prefix="before-")) / "code"
    git = ["git", "worktree"]
    subprocess.run([*git, "add", "--detach", str(tree), rev], cwd=root, check=True)
    try:
        yield tree
    finally:
        subprocess.run([*git, "remove", "--force", str(tree)], cwd=root, check=False)
