"""A job run (:func:`run_job`): its DEM and maps stores built or reused, every mission planned
and flown on a cluster and written as it finishes, the results catalog and the report; one
run at a time per catalog (a lock), missions finished before skipped, failed ones retried, and
only what the tool made ever removed (``--prune``).
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import socket
import time
import uuid
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path

from .._types import ClientLike
from ..exceptions import (
    CatalogBusyError,
    InvalidDEMError,
    InvalidParameterError,
    JobFileError,
    PipelineError,
)
from ..params import endpoint_key
from ..store.paths import TEMPORARY
from ..trajectory import Status
from .job_file import Job, load_job

log = logging.getLogger(__name__)


@dataclass
class JobResult:
    """What a job run did."""

    job: Job
    dem_store: Path
    reused: bool
    seconds: float
    maps_store: Path | None = None
    catalog: Path | None = None
    planned: int = 0
    skipped: int = 0
    failed: list = field(default_factory=list)  # names of failed missions (this run or before)
    workers: int = 0  # the cluster's workers (0: no cluster was needed)
    uncertified: list = field(default_factory=list)  # planned, bound not proven (this run)
    dashboard: str | None = None
    ran: int = 0  # missions this run planned or tried
    replanned: int = 0  # finished missions planned again because they changed
    crs_wkt: str | None = None
    report: Path | None = None  # the catalog's index.html
    run_id: str = field(default_factory=lambda: uuid.uuid4().hex[:12])

    @property
    def ok(self) -> bool:
        return not self.failed


def _report(job: Job, maps_store: Path) -> Path:
    """The catalog's offline report, ``index.html`` (:mod:`pipeline.outputs.report`)."""
    from ..outputs.report import write_report
    from ..store.maps_store import open_store

    maps = open_store(maps_store) if (maps_store / "zarr.json").exists() else None
    path = write_report(
        job.catalog, maps, title=job.name, mission_names=[m["name"] for m in job.missions]
    )
    log.info("job %s: report %s (open it in a browser; it needs no network)", job.name, path)
    return path


def run_job(
    path: str | os.PathLike,
    scheduler: ClientLike = None,
    overwrite: bool = False,
    dry_run: bool = False,
    scheduler_file: str | os.PathLike | None = None,
    dashboard_address: str | None = None,
    prune: bool = False,
    workers: int | None = None,
) -> JobResult:
    """Run a job file: DEM store, maps store, every mission, the results catalog.

    The stores are ``<catalog>/dem-<hash>.zarr`` and ``<catalog>/maps-<hash>.zarr``, reused
    while the DEM definition and the maps parameters are unchanged. Finished missions (their
    Item exists) are skipped unless ``overwrite``; each mission is written atomically as it
    finishes, so a killed job loses at most the missions in flight. With no ``scheduler``, a
    LocalCluster of 2 single-threaded workers. A performance report (HTML) is saved as
    ``<catalog>/performance-report.html`` unless ``[output] performance_report = false``.
    ``scheduler`` (an address or a
    ``distributed.Client``) or ``scheduler_file`` name the cluster to run on
    (:func:`pipeline.runtime.cluster.session`). What the catalog holds that the job no longer makes
    (stores of other DEM or maps parameters, folders of missions no longer in the job) is
    counted in the log, and removed with ``prune`` (:func:`stale`). ``workers``: the local
    cluster's worker processes (default 2, or dask's configuration ``auv_pipeline.workers``).

    Examples
    --------
    >>> res = pipeline.run_job("tasks/demo.toml")             # doctest: +SKIP
    >>> res.ok, res.catalog                                  # doctest: +SKIP
    (True, PosixPath('catalogs/demo/catalog.json'))
    """
    job = load_job(path)
    if dashboard_address is not None:  # at the dry run too, not when a cluster starts
        from ..runtime.cluster import check_dashboard_address

        check_dashboard_address(dashboard_address)
    if workers is not None:
        from ..runtime.cluster import local_workers

        local_workers(workers)
    dem_store = job.catalog / f"dem-{job.dem_fingerprint()}.zarr"
    maps_store = job.catalog / f"maps-{job.maps_fingerprint()}.zarr"
    t0 = time.perf_counter()
    check_catalog(job.catalog, job.name)
    if dry_run:
        log.info(
            "dry run: job %s is valid: %d missions; DEM store %s, maps store %s, catalog %s",
            job.name,
            len(job.missions),
            dem_store,
            maps_store,
            job.catalog,
        )
        return JobResult(job, dem_store, dem_store.exists(), 0.0, maps_store=maps_store)
    from ..outputs.catalog import write_catalog

    with catalog_lock(job.catalog):
        check_catalog(job.catalog, job.name)  # (as another run may have left it)
        remove_temporaries(job.catalog)
        res = _run_locked(
            job,
            dem_store,
            maps_store,
            overwrite,
            scheduler,
            scheduler_file,
            dashboard_address,
            workers,
        )
        job.save_hashes()
        res.catalog = write_catalog(
            job.catalog,
            job.name,
            [m["name"] for m in job.missions],
            description=f"Missions of job {job.name} ({job.path})",
            lonlat=bool(res.crs_wkt),
        )
        res.report = _report(job, maps_store)
        _prune(job, dem_store, maps_store, prune)
    res.seconds = time.perf_counter() - t0
    log.info(
        "job %s: %d planned, %d skipped (finished before), %d failed; catalog %s (%.1f s)",
        job.name,
        res.planned,
        res.skipped,
        len(res.failed),
        res.catalog,
        res.seconds,
    )
    return res


def stale(job: Job, dem_store: Path, maps_store: Path) -> list[Path]:
    """What the catalog of ``job`` holds that this tool made and the job no longer uses: DEM
    and maps stores (this tool's, by their mark) other than ``dem_store`` and ``maps_store``,
    and mission folders the tool wrote (by their mark, :func:`~pipeline.outputs.catalog.tool_files`)
    of missions no longer in the job; a folder of the user's own is never among them."""
    from ..outputs.catalog import COLLECTION, mission_id, tool_files
    from ..store.paths import own_store

    out = []
    for kind, pattern, keep in (
        ("DEM", "dem-*.zarr", dem_store),
        ("maps", "maps-*.zarr", maps_store),
    ):
        for p in sorted(job.catalog.glob(pattern)):
            if p != keep and own_store(p, kind):
                out.append(p)
    ids = {mission_id(m["name"]) for m in job.missions}
    folder = job.catalog / COLLECTION
    if folder.is_dir():
        for p in sorted(folder.iterdir()):
            if p.is_dir() and p.name not in ids and tool_files(p) is not None:
                out.append(p)
    return out


def _size(p: Path) -> int:
    """What removing ``p`` frees: a store's files, or those the tool wrote in a mission folder."""
    if p.suffix != ".zarr":
        from ..outputs.catalog import tool_files

        files = [p / f for f in tool_files(p) or []]
        return sum(f.stat().st_size for f in files if f.is_file() and not f.is_symlink())
    return sum(f.stat().st_size for f in p.rglob("*") if f.is_file() and not f.is_symlink())


def _prune(job: Job, dem_store: Path, maps_store: Path, remove: bool) -> None:
    old = stale(job, dem_store, maps_store)
    if not old:
        return
    size = sum(_size(p) for p in old)
    if remove:
        from ..outputs.catalog import remove_tool_files

        kept = []
        for p in old:
            if p.suffix == ".zarr":
                shutil.rmtree(p, ignore_errors=True)
            else:  # only the files the tool wrote in a mission folder
                kept += [f"{p.name}/{f}" for f in remove_tool_files(p)]
        log.info(
            "pruned %d stores and mission folders the job no longer uses (%.2f GB)%s",
            len(old),
            size / 1e9,
            f"; kept {len(kept)} files of yours in them ({', '.join(kept[:3])})" if kept else "",
        )
        return
    names = ", ".join(p.name for p in old[:3]) + (
        f" and {len(old) - 3} more" if len(old) > 3 else ""
    )
    log.info(
        "catalog %s holds %d stores and mission folders the job no longer uses (%s; %.2f GB): "
        "`pipeline run %s --prune` removes them",
        job.catalog,
        len(old),
        names,
        size / 1e9,
        job.path,
    )


def _run_locked(job, dem_store, maps_store, overwrite, *cluster) -> JobResult:
    import datetime as dt

    scheduler, scheduler_file, *_ = cluster
    missions = _sorted_missions(job, overwrite)
    if (
        scheduler is None
        and scheduler_file is None
        and not overwrite
        and dem_store.exists()
        and maps_store.exists()
        and all(done is not None for _, done, _ in missions)
    ):
        # no cluster of its own to start (its worker processes take seconds to start and stop)
        # when the run computes nothing; a scheduler given is still reached (its address checked)
        log.info("job %s: nothing to compute: no cluster started", job.name)
        reused = _dem_store(job, dem_store, overwrite)
        res = JobResult(job, dem_store, reused, 0.0, maps_store=maps_store)
        _maps_store(job, dem_store, maps_store, False)
        _missions(job, maps_store, None, missions, res)
        return res
    from distributed import performance_report

    from ..runtime.cluster import session
    from .warmup import ensure_compiled, job_parts

    with session(*cluster) as client:
        res = JobResult(
            job, dem_store, False, 0.0, maps_store=maps_store, dashboard=client.dashboard_link
        )
        res.workers = len(client.scheduler_info().get("workers", {}))
        log.info("dask dashboard: %s (%d workers)", client.dashboard_link, res.workers)
        # the first run after an install compiles the kernels the job uses on both workers at
        # once, so that no stage (and no mission's recorded runtime) holds the compilation
        ensure_compiled(client, parts=job_parts(job))
        tmp_report = job.catalog / f".performance-report.tmp-{res.run_id}.html"
        # dask's report takes about a second to draw at the end of a run (the scheduler's
        # task stream, profiles and bandwidths, with bokeh's scripts inlined)
        recording = (
            performance_report(filename=str(tmp_report), mode="inline")
            if job.performance_report
            else nullcontext()
        )
        try:
            with recording:
                res.reused = _dem_store(job, dem_store, overwrite)
                built = _maps_store(job, dem_store, maps_store, overwrite or not res.reused)
                _missions(job, maps_store, client, missions, res)
        except BaseException:
            # dask writes the report as the run ends, failed too: a run that did not finish
            # keeps none (else the next run would find it as a killed run's temporary)
            tmp_report.unlink(missing_ok=True)
            raise
    if not job.performance_report:
        return res  # none asked for: an earlier run's report stays as it is
    if res.reused and not built and not res.ran:
        tmp_report.unlink(missing_ok=True)  # nothing was computed: keep the last report
        return res
    # one self-contained report per run that did work, the newest also as
    # performance-report.html
    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    reports = job.catalog / "reports"
    reports.mkdir(exist_ok=True)
    kept = reports / f"performance-{stamp}-{res.run_id}.html"
    os.replace(tmp_report, kept)
    latest = job.catalog / f".performance-report.html.tmp-{res.run_id}"
    shutil.copyfile(kept, latest)
    os.replace(latest, job.catalog / "performance-report.html")
    return res


@contextmanager
def catalog_lock(catalog: Path):
    """Hold ``<catalog>/.lock`` for a run: a second run on the same catalog refuses with one
    clear line instead of deleting the first one's work in flight. The lock is the operating
    system's (``flock``), so a killed run never leaves it held."""
    import fcntl

    catalog.mkdir(parents=True, exist_ok=True)
    fh = open(catalog / ".lock", "a+")
    try:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            who = fh.read().strip() or "another process"
            raise CatalogBusyError(
                f"catalog {catalog} is in use by another run ({who}); wait for it to finish, "
                "or give this job another [output] catalog"
            ) from None
        fh.seek(0)
        fh.truncate()
        fh.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
        fh.flush()
        yield
    finally:
        fh.close()


# what a run writes into its catalog folder (besides its temporaries, :data:`TEMPORARY`)
CATALOG_ENTRIES = (
    ".lock",
    "catalog.json",
    "dem-*.zarr",
    "maps-*.zarr",
    "missions",
    "report",
    "reports",
    "index.html",
    "performance-report.html",
    ".input-hashes.json",
)


def check_catalog(catalog: Path, job_name: str) -> None:
    """Refuse, with one line, a catalog folder this job may not write into: a folder holding
    another job's catalog (its ``catalog.json`` names that job: the two would drop each other's
    missions); a folder without a catalog that holds anything a run does not write (the job's
    own folder, a user's files). Absent, empty, or this job's catalog: fine."""
    import errno
    import fnmatch

    if catalog.exists() and not catalog.is_dir():  # (at the dry run too, as the run says)
        raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), str(catalog))
    for parent in catalog.parents:
        if parent.exists():
            if not parent.is_dir():
                raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(parent))
            break
    if not catalog.exists() and not catalog.is_symlink():
        return
    index = catalog / "catalog.json"
    if index.exists():
        try:
            owner = json.loads(index.read_text()).get("id")
        except (OSError, ValueError, AttributeError):
            owner = None  # a damaged index of a run's: rewritten at the end of this one
        if owner is not None and owner != job_name:
            raise PipelineError(
                f"catalog {catalog} holds the missions of job {owner!r} (its catalog.json); "
                f"give job {job_name!r} its own [output] catalog, so that neither drops the "
                "other's missions"
            )
        if owner is not None:
            return
    foreign = sorted(
        p.name
        for p in catalog.iterdir()
        if not TEMPORARY.match(p.name)
        and not any(fnmatch.fnmatchcase(p.name, pat) for pat in CATALOG_ENTRIES)
    )
    if foreign:
        shown = ", ".join(foreign[:3]) + (
            f" and {len(foreign) - 3} more" if len(foreign) > 3 else ""
        )
        raise PipelineError(
            f"catalog {catalog} is a folder with other files ({shown}) and no catalog of this "
            "job; a run writes only into a new or empty folder, or its own catalog: give "
            "[output] catalog such a folder"
        )


def remove_temporaries(catalog: Path) -> list[Path]:
    """Remove what killed runs left in ``catalog`` (half-written stores, scratch stores,
    mission folders, reports, coarse maps); call it holding :func:`catalog_lock`, when no
    other run can be writing them. Returns what was removed."""
    patterns = (".*.tmp-*", "missions/.*.tmp-*", "report/.*.tmp-*", "*.zarr/.coarse-rho*.tmp-*")
    # only the names the tool gives its temporaries (a dot, the name, .tmp- and a random hex
    # tag): a user's file that looks alike is left alone
    gone = [p for pattern in patterns for p in catalog.glob(pattern) if TEMPORARY.match(p.name)]
    for p in gone:
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
    if gone:
        log.info(
            "removed %d temporaries an earlier run left behind (one killed or failed)", len(gone)
        )
    return gone


def _sorted_missions(job: Job, overwrite: bool) -> list[tuple[dict, dict | None, bool]]:
    """Each mission of ``job`` (with its ``fingerprint``, :meth:`Job.mission_fingerprint`), its
    Item when it finished as it is defined now (None: to be planned; always with
    ``overwrite``), and whether it finished under another definition (its fields, the maps, the
    DEM, the library's defaults or results revision). Read once a run, before its cluster."""
    from ..outputs.catalog import damaged_assets, finished

    out = []
    for m in job.missions:
        m = {**m, "fingerprint": job.mission_fingerprint(m)}
        done = None if overwrite else finished(job.catalog, m["name"])
        changed = done is not None and done["properties"].get("auv:fingerprint") != m["fingerprint"]
        if done is not None and not changed:
            # a failure is tried again (its cause, a full disk, a damaged store, may be gone;
            # one the mission itself causes fails again, as fast); so is a result whose files
            # went missing or changed
            if done["properties"].get("auv:status") == Status.FAILED:
                log.info("%s: failed before: planning it again", m["name"])
                done = None
            elif bad := damaged_assets(job.catalog, done):
                log.warning(
                    "%s: its files %s are missing or changed since it was written: planning it "
                    "again",
                    m["name"],
                    ", ".join(bad),
                )
                done = None
        out.append((m, None if changed else done, changed))
    return out


def _dem_store(job: Job, store: Path, overwrite: bool) -> bool:
    if store.exists() and not overwrite:
        log.info("DEM store %s is up to date: reusing it", store)
        return True
    # here, not above: a run on stores it reuses imports neither xarray nor dask.array
    from ..dem.dem_store import write_dem
    from ..dem.open import import_dem
    from ..dem.synthetic import synthetic_dem

    log.info("writing the DEM store %s", store)
    try:
        if job.dem_path is not None:  # read, checked and written in one pass over the file
            import_dem(
                job.dem_path,
                store,
                chunks=job.chunks,
                variable=job.variable,
                cell_size=job.cell_size,
                resolution=job.resolution,
                bbox=job.bbox,
                bbox_xy=job.bbox_xy,
                uncertainty_k=job.uncertainty_k,
                uncertainty=job.uncertainty,
                overwrite=True,
            )
            return False
        dem = synthetic_dem(chunks=job.chunks, **job.synthetic)
    except (InvalidDEMError, InvalidParameterError) as exc:
        raise JobFileError(f"job file {job.path}: {exc}") from exc
    write_dem(dem, store, chunks=job.chunks, overwrite=True)
    return False


def _maps_store(job: Job, dem_store: Path, store: Path, rebuild: bool) -> None:
    if store.exists() and not rebuild:
        log.info("maps store %s is up to date: reusing it", store)
        return False
    from ..dem.open import open_dem
    from ..maps.build import build_maps

    log.info("building the maps store %s (%s)", store, job.maps)
    try:
        build_maps(
            open_dem(dem_store, chunks=job.chunks),
            store,
            overwrite=True,
            chunks=job.chunks,
            **job.maps,
        )
    except PipelineError as exc:
        if isinstance(exc, JobFileError):
            raise
        raise JobFileError(f"job file {job.path}: [maps]: {exc}") from exc
    return True


def _missions(job: Job, maps_store: Path, client, missions: list, res: JobResult) -> None:
    """Plan the missions not finished yet (or changed since; ``missions`` as
    :func:`_sorted_missions` gives them), writing each as it ends."""
    from ..store.maps_store import open_store
    from .missions import failed_trajectory, plan_missions

    maps = open_store(maps_store)
    res.crs_wkt = maps.crs_wkt
    todo = []
    for m, done, changed in missions:
        if changed:
            log.info(
                "%s: its definition, the maps, the DEM, or the library's defaults or results "
                "revision changed since it was planned: planning it again",
                m["name"],
            )
            res.replanned += 1
        if done is None:
            todo.append(m)
        else:
            res.skipped += 1
            if done["properties"].get("auv:status") == Status.UNCERTIFIED:
                res.uncertified.append(m["name"])  # (the exit code of its first run)
    if res.skipped:
        log.info("%d missions finished before: skipped (--overwrite plans them again)", res.skipped)
    ready, bad = [], []
    zones = _Zones(job, maps)
    for m in todo:
        try:
            ready.append(
                {
                    **m,
                    "start": maps.cell_of("start", m["start_form"], m["start_input"]),
                    "goal": maps.cell_of("goal", m["goal_form"], m["goal_input"]),
                    **_via_points(m),
                    **zones.of(m),
                }
            )
        except Exception as exc:  # noqa: BLE001 - one mission's failure, not the batch's
            bad.append((m, str(exc) if isinstance(exc, PipelineError) else repr(exc)))
    record = _Recorder(job, maps, res, len(todo))
    for m, msg in bad:
        record(m, failed_trajectory({**job.planning, **m}, msg))
    if ready:
        defaults = {k: v for k, v in job.planning.items() if k != "keep_out"}
        plan_missions(
            maps,
            ready,
            client=client,
            defaults=defaults,
            vehicle=job.vehicle,
            quicklooks=job.quicklooks,  # drawn on the workers, side by side
            # recorded as the job gives it (the zones' files, not their geometry)
            on_done=lambda i, mission, traj: record(
                {k: v for k, v in mission.items() if k != "keep_out"}, traj
            ),
        )


def _via_points(mission: dict) -> dict:
    """A job mission's via points under their key (``via``, ``via_xy``, ``via_lonlat``), for
    ``plan`` to find their cells, or ``{}`` without any."""
    if "via_form" not in mission:
        return {}
    return {endpoint_key("via", mission["via_form"]): mission["via_input"]}


class _Zones:
    """The keep-out zones of a job's missions, read once in this process (each distinct set
    of files and margin) and sent to the workers as geometry: a cluster's workers need not
    see the job's files."""

    def __init__(self, job: Job, maps):
        from ..constraints.zones import map_extent

        self.job, self.crs, self.read = job, maps.crs_wkt, {}
        self.extent = map_extent(maps)

    def of(self, mission: dict) -> dict:
        """The mission's ``keep_out`` as :class:`~pipeline.constraints.zones.KeepOut` (none:
        ``{}``)."""
        from ..constraints.zones import read_zones

        files = mission.get("keep_out", self.job.planning.get("keep_out"))
        if not files:
            return {}
        margin = mission.get("keep_out_margin_m", self.job.planning.get("keep_out_margin_m"))
        key = (tuple(files), margin)
        if key not in self.read:
            self.read[key] = read_zones(files, self.crs, margin, self.extent)
        return {"keep_out": self.read[key]}


class _Recorder:
    """Writes each mission's result as it ends and logs it; a mission whose result cannot be
    written is recorded as failed with the reason, and the batch goes on."""

    def __init__(self, job: Job, maps, res: JobResult, total: int):
        self.job, self.maps, self.res, self.total = job, maps, res, total
        self.count = 0
        self.clearance = float(job.maps["clearance"])
        self.source = None  # the user's own DEM file: the clearance is measured from it
        if job.dem_path is not None and job.cell_size is None:
            from ..verify.seabed import SourceSeabed

            try:
                self.source = SourceSeabed.open(
                    job.dem_path,
                    variable=job.variable,
                    uncertainty_k=job.uncertainty_k,
                    uncertainty=job.uncertainty,
                )
            except PipelineError as exc:
                log.warning("the clearance is measured from the DEM store: %s", exc)

    def __call__(self, mission: dict, traj) -> None:
        from ..verify.clearance import min_clearance
        from ..verify.missions import source_clearance
        from .missions import failed_trajectory

        self.count += 1
        self.res.ran += 1
        name = mission["name"]
        png = traj.extra.pop("quicklook_png", None)  # written now, not kept with the results
        try:
            clr = math.nan
            if traj.flight is not None and self.source is not None:  # from the user's DEM
                clr = source_clearance(self.source, traj.flight, self.maps)
                if math.isnan(clr):  # (no-data within reach: the flight's own figure)
                    clr = traj.flight.min_clearance_m
            elif traj.flight is not None:  # what is flown, from the continuous seabed
                clr = traj.flight.min_clearance_m
            elif traj.planned:  # the grid path, from the grid points
                clr = min_clearance(self.maps, traj, self.clearance)
            self._write(mission, traj, clr, png)
        except (OSError, PipelineError, ValueError) as exc:
            reason = f"its result could not be written: {type(exc).__name__}: {exc}"
            log.error("[%d/%d] %s: FAILED: %s", self.count, self.total, name, reason)
            self.res.failed.append(name)
            from ..outputs.catalog import finished

            before = finished(self.job.catalog, name)
            if before is not None and before["properties"].get("auv:status") != Status.FAILED:
                # an earlier result is never replaced by a failure to write this one (the
                # next run plans the mission again, its fingerprint or files being other)
                log.error("%s: its earlier result is kept", name)
                return
            try:  # the failure itself, if the disk takes it
                self._write(mission, failed_trajectory({**self.job.planning, **mission}, reason))
            except (OSError, PipelineError, ValueError):
                pass
            return
        if traj.planned:
            self.res.planned += 1
            if traj.status != Status.OK:
                self.res.uncertified.append(name)
            (log.info if traj.status == Status.OK else log.warning)(
                "[%d/%d] %s: %s, %.1f km (<= %.3f x the shortest), %.0f %% ridge, min clearance "
                "%.0f m (%.2f s)%s",
                self.count,
                self.total,
                name,
                traj.status,
                traj.length_m / 1e3,
                traj.certified_ratio,
                100 * traj.ridge_ratio,
                clr,
                traj.runtime_s,
                (
                    f"; flown {traj.flight.flown_length_m / 1e3:.1f} km in "
                    f"{traj.flight.duration_s / 3600:.1f} h, {100 * traj.flight.ridge_ratio:.0f} % "
                    f"ridge, {len(traj.flight.waypoints)} waypoints"
                    if traj.flight is not None
                    else ""
                )
                + (f": {traj.message}" if traj.message else ""),
            )
        else:
            self.res.failed.append(name)
            log.warning("[%d/%d] %s: FAILED: %s", self.count, self.total, name, traj.message)

    def _write(self, mission, traj, clr=math.nan, png=None):
        from ..outputs.catalog import write_mission

        write_mission(
            self.job.catalog,
            mission["name"],
            mission,
            traj,
            maps=self.maps,
            crs_wkt=self.maps.crs_wkt,
            min_clearance_m=clr,
            run_id=self.res.run_id,
            quicklook=self.job.quicklooks,
            quicklook_png=png,
        )
