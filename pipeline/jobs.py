"""Job files (TOML) -> DEM store (and, as later stages land, maps, missions and a catalog).

A job file is validated completely before any compute: an unknown key, a wrong type or a
missing file is one :class:`~pipeline.exceptions.JobFileError` naming the key and the file.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from .exceptions import JobFileError, PipelineError

log = logging.getLogger(__name__)

_TOP_KEYS = {"name", "dem", "output"}
_DEM_KEYS = {"path", "synthetic", "chunks", "variable", "cell_size"}
_SYNTH_KEYS = {"shape", "cell_size", "seed", "islands"}
_OUTPUT_KEYS = {"catalog"}


@dataclass
class Job:
    """A validated job file."""

    path: Path
    name: str
    catalog: Path
    chunks: int = 1024
    dem_path: Path | None = None
    variable: str | None = None
    cell_size: float | None = None
    synthetic: dict = field(default_factory=dict)

    def dem_fingerprint(self) -> str:
        """A hash of what defines the DEM: re-running with the same inputs reuses the store."""
        if self.dem_path is not None:
            st = self.dem_path.stat()
            what = {"path": str(self.dem_path.resolve()), "size": st.st_size,
                    "mtime_ns": st.st_mtime_ns, "variable": self.variable,
                    "cell_size": self.cell_size}
        else:
            from .synthetic import GENERATOR_VERSION

            what = {"synthetic": self.synthetic, "version": GENERATOR_VERSION}
        what["chunks"] = self.chunks
        return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:16]


def _fail(path: Path, msg: str):
    raise JobFileError(f"job file {path}: {msg}")


def _check_keys(path: Path, table: dict, allowed: set[str], where: str) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        _fail(path, f"unknown key {where}{unknown[0]!r}; allowed keys here: {sorted(allowed)}")


def _typed(path: Path, table: dict, key: str, types, where: str, what: str):
    value = table[key]
    if isinstance(value, bool) or not isinstance(value, types):
        _fail(path, f"{where}{key} must be {what}, got {value!r}")
    return value


def load_job(path: str | os.PathLike) -> Job:
    """Read and validate a job file without computing anything."""
    path = Path(path)
    if not path.is_file():
        raise JobFileError(f"job file {path} does not exist")
    try:
        with open(path, "rb") as fh:
            doc = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise JobFileError(f"job file {path} is not valid TOML: {exc}") from exc
    _check_keys(path, doc, _TOP_KEYS, "")
    name = doc.get("name", path.stem)
    if not isinstance(name, str) or not name or "/" in name or name.startswith("."):
        _fail(path, f"name must be a non-empty file-name-safe string, got {name!r}")
    dem = doc.get("dem")
    if not isinstance(dem, dict):
        _fail(path, "a [dem] table is required, with path = '...' or a [dem.synthetic] table")
    _check_keys(path, dem, _DEM_KEYS, "dem.")
    if ("path" in dem) == ("synthetic" in dem):
        _fail(path, "[dem] needs exactly one of path = '...' or a [dem.synthetic] table")
    job = Job(path=path, name=name, catalog=Path("catalogs") / name)
    if "chunks" in dem:
        job.chunks = _typed(path, dem, "chunks", int, "dem.", "a positive integer")
        if job.chunks < 1:
            _fail(path, f"dem.chunks must be a positive integer, got {job.chunks}")
    if "path" in dem:
        p = Path(_typed(path, dem, "path", str, "dem.", "a file path"))
        p = p if p.is_absolute() else (path.parent / p)
        if not p.exists():
            _fail(path, f"dem.path {dem['path']!r} does not exist (resolved to {p})")
        job.dem_path = p
        if "variable" in dem:
            job.variable = _typed(path, dem, "variable", str, "dem.", "a string")
        if "cell_size" in dem:
            job.cell_size = float(_typed(path, dem, "cell_size", int | float, "dem.", "a number"))
    else:
        syn = dem["synthetic"]
        if not isinstance(syn, dict):
            _fail(path, "dem.synthetic must be a table")
        _check_keys(path, syn, _SYNTH_KEYS, "dem.synthetic.")
        if "shape" not in syn:
            _fail(path, "dem.synthetic.shape is required, e.g. shape = [2000, 2000]")
        shape = syn["shape"]
        if (not isinstance(shape, list) or len(shape) != 2
                or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 2
                           for v in shape)):
            _fail(path, f"dem.synthetic.shape must be [rows, cols] of integers >= 2, got {shape!r}")
        job.synthetic = {"shape": shape, "cell_size": 30.0, "seed": 0, "islands": 2}
        for key, types, what in (("cell_size", int | float, "a number > 0"),
                                 ("seed", int, "an integer >= 0"),
                                 ("islands", int, "an integer from 0 to 10")):
            if key in syn:
                job.synthetic[key] = _typed(path, syn, key, types, "dem.synthetic.", what)
    out = doc.get("output", {})
    if not isinstance(out, dict):
        _fail(path, "[output] must be a table")
    _check_keys(path, out, _OUTPUT_KEYS, "output.")
    if "catalog" in out:
        job.catalog = Path(_typed(path, out, "catalog", str, "output.", "a directory path"))
    return job


@dataclass
class JobResult:
    job: Job
    dem_store: Path
    reused: bool
    seconds: float


def run_job(path: str | os.PathLike, scheduler: str | None = None, overwrite: bool = False,
            dry_run: bool = False) -> JobResult:
    """Run a job file: for now, build (or reuse) the DEM store of the job.

    The DEM store is ``<catalog>/dem-<fingerprint>.zarr``; a re-run with an unchanged DEM
    definition reuses it unless ``overwrite``.
    """
    from .dem import open_dem, write_dem
    from .synthetic import synthetic_dem

    job = load_job(path)
    store = job.catalog / f"dem-{job.dem_fingerprint()}.zarr"
    t0 = time.perf_counter()
    if dry_run:
        log.info("dry run: job %s is valid; the DEM store would be %s", job.name, store)
        return JobResult(job, store, store.exists(), 0.0)
    if store.exists() and not overwrite:
        log.info("DEM store %s is up to date: reusing it", store)
        return JobResult(job, store, True, time.perf_counter() - t0)
    try:
        if job.dem_path is not None:
            dem = open_dem(job.dem_path, chunks=job.chunks, variable=job.variable,
                           cell_size=job.cell_size)
        else:
            dem = synthetic_dem(chunks=job.chunks, **job.synthetic)
    except PipelineError as exc:
        raise JobFileError(f"job file {job.path}: {exc}") from exc
    with _scheduler(scheduler):
        write_dem(dem, store, chunks=job.chunks, overwrite=True)
    return JobResult(job, store, False, time.perf_counter() - t0)


class _scheduler:
    """Use the dask cluster at ``address`` if given, else the local threaded scheduler."""

    def __init__(self, address: str | None):
        self.address = address
        self.client = None

    def __enter__(self):
        if self.address:
            from distributed import Client

            self.client = Client(self.address)
            log.info("dask dashboard: %s", self.client.dashboard_link)
        return self.client

    def __exit__(self, *exc):
        if self.client is not None:
            self.client.close()
