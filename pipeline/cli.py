"""The ``pipeline`` command line: thin, it parses and calls the library."""

from __future__ import annotations

import errno
import logging
import sys
import time
import traceback
import warnings

import click

from .exceptions import CatalogBusyError, PipelineError, SchedulerError
from .params import DEM, MAPS, SYNTHETIC, Param


def _option(param: Param, *, flag: str | None = None):
    """A click option from the parameter schema: its type, default and help text."""
    if param.kind == "bool":
        name = flag or "--" + param.name.replace("_", "-")
        return click.option(
            f"{name}/--no-{name[2:]}",
            param.name,
            default=param.default,
            show_default=True,
            help=param.help,
        )
    if param.kind == "box":
        return click.option(
            flag or "--" + param.name.replace("_", "-"),
            param.name,
            type=float,
            nargs=4,
            default=None,
            help=f"{param.help}: {param.unit}",
        )
    if param.kind == "choice":
        kind = click.Choice(list(param.options()))
    else:
        kind = {"float": float, "int": int, "str": str}[param.kind]
    flag = flag or "--" + param.name.replace("_", "-")
    return click.option(
        flag,
        param.name,
        type=kind,
        default=param.default,
        show_default=param.default is not None,
        help=param.option_help(),
    )


def _setup_logging(verbose: bool) -> None:
    import warnings

    import dask

    from .exceptions import PipelineWarning
    from .runtime import cluster

    # the log says what a PipelineWarning says: one line each, not two
    warnings.simplefilter("ignore", PipelineWarning)

    cluster.QUIET_TASK_ERRORS = not verbose
    # distributed installs its own INFO handler when imported: keep it to warnings
    dask.config.set({"logging.distributed": "debug" if verbose else "warning"})
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    for noisy in (
        "distributed",
        "numba",
        "rasterio",
        "fsspec",
        "asyncio",
        "s3fs",
        "botocore",
        "aiobotocore",
    ):
        logging.getLogger(noisy).setLevel(logging.WARNING)


def _progress(what: str):
    from dask.diagnostics import ProgressBar

    click.echo(what, err=True)
    return ProgressBar(dt=1.0, out=sys.stderr)


# click's error for a group given no command (it then prints the group's help)
_NO_ARGS = getattr(click.exceptions, "NoArgsIsHelpError", ())


class _OneLineGroup(click.Group):
    """click's group whose usage errors (a missing argument, an unknown option, a bad value) are
    one ``error:`` line naming the command's help, as every other error is, not click's
    several lines of usage."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode, **extra)
        try:
            rv = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except click.exceptions.Abort:
            click.echo("error: aborted", err=True)
            sys.exit(EXIT_BAD_INPUT)
        except _NO_ARGS as exc:  # `pipeline` or `pipeline dem` alone: the help, as asked
            click.echo(exc.ctx.get_help())
            sys.exit(EXIT_OK)
        except click.ClickException as exc:
            msg = exc.format_message()
            ctx = getattr(exc, "ctx", None)
            if isinstance(exc, click.UsageError) and ctx is not None:
                msg = f"{msg} (see `{ctx.command_path} --help`)"
            click.echo(f"error: {' '.join(msg.split())}", err=True)
            sys.exit(exc.exit_code)
        sys.exit(rv if isinstance(rv, int) else EXIT_OK)


@click.group(cls=_OneLineGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.option("-v", "--verbose", is_flag=True, help="Debug logging.")
@click.version_option(package_name="auv-pipeline")
def main(verbose: bool) -> None:
    """Plan near-bottom AUV cruise trajectories over large seabed grids (RA* + MCPC)."""
    _VERBOSE["on"] = verbose
    _setup_logging(verbose)
    _stop_on_sigterm()
    from .runtime.env import check_environment

    with _errors():  # a bad setting: one line before any work
        check_environment()


class Terminated(KeyboardInterrupt):
    """SIGTERM (a scheduler's, a container's stop): unwinds as an interrupt does, so that the
    cluster and the files in flight are closed as on Ctrl-C, and ends in one line."""


def _stop_on_sigterm() -> None:
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return  # (signals are the main thread's)

    def stop(signum, frame):
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # a second one ends at once
        # the cluster's client cancels its waits as it closes: asyncio would log each
        logging.getLogger("asyncio").setLevel(logging.CRITICAL)
        raise Terminated()

    signal.signal(signal.SIGTERM, stop)


@main.group()
def dem() -> None:
    """Create or import DEMs as canonical chunked Zarr stores."""


@dem.command("synth")
@click.argument("out", type=click.Path())
@click.option(
    "--shape", nargs=2, type=int, default=(2000, 2000), show_default=True, help="Rows and columns."
)
@_option(SYNTHETIC.cell_size)
@_option(SYNTHETIC.seed)
@_option(SYNTHETIC.islands)
@_option(SYNTHETIC.origin_lon)
@_option(SYNTHETIC.origin_lat)
@_option(SYNTHETIC.georeferenced)
@_option(DEM.chunks)
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists.")
def dem_synth(out, shape, cell_size, seed, islands, chunks, overwrite, **where):
    """Write a virtual mid-ocean-ridge DEM to the Zarr store OUT."""
    from .dem.dem_store import write_dem
    from .dem.synthetic import synthetic_dem

    with _errors():
        t0 = time.perf_counter()
        d = synthetic_dem(
            shape, cell_size=cell_size, seed=seed, chunks=chunks, islands=islands, **where
        )
        with _progress(f"generating {shape[0]} x {shape[1]} cells into {out}"):
            write_dem(d, out, chunks=chunks, overwrite=overwrite)
        click.echo(f"wrote {out} in {time.perf_counter() - t0:.1f} s")


@dem.command("import")
@click.argument("source", type=click.Path())
@click.argument("out", type=click.Path())
@_option(DEM.chunks)
@_option(DEM.variable)
@_option(DEM.cell_size)
@_option(DEM.resolution)
@_option(DEM.bbox)
@_option(DEM.bbox_xy)
@_option(DEM.uncertainty_k)
@_option(DEM.uncertainty)
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists.")
def dem_import(source, out, overwrite, **options):
    """Import a GeoTIFF, BAG, ESRI ASCII, NetCDF / GMT grid or Zarr DEM as the Zarr store OUT
    (options: those of open_dem, by the parameter schema), in one pass over the file."""
    from .dem.open import import_dem, open_dem

    with _errors():
        t0 = time.perf_counter()
        with _progress(f"importing {source} into {out}"):
            import_dem(source, out, overwrite=overwrite, **options)
        rows, cols = open_dem(out).shape  # the store's metadata: the file is read once
        click.echo(f"wrote {out} ({rows} x {cols} cells) in {time.perf_counter() - t0:.1f} s")


@dem.command("info")
@click.argument("path", type=click.Path())
def dem_info(path):
    """Describe a DEM file as open_dem sees it."""
    from .dem.open import open_dem
    from .dem.readers import file_chunks, reading

    with _errors():
        d = open_dem(path, chunks=DEM.chunks.default)
        stored = file_chunks(path)
        click.echo(
            f"{path}: {d.shape[0]} x {d.shape[1]} cells of {d.attrs['cell_size']:g} m, "
            + (f"stored in chunks {stored}" if stored else "stored unchunked")
        )
        click.echo(f"crs: {'set' if 'crs_wkt' in d.attrs else 'none (local metric grid)'}")
        with reading(path):
            lo, hi = float(d.min().compute()), float(d.max().compute())
        click.echo(f"elevation: {lo:.1f} .. {hi:.1f} m")


@main.command("verify")
@click.argument("missions", type=click.Path())
@click.option(
    "--dem", "dem_path", required=True, type=click.Path(), help="The DEM file to check against."
)
@click.option("--variable", default=None, help="Its elevation variable, when it has several.")
@click.option(
    "--uncertainty-k", type=float, default=None, help="Check against elevation + k * sigma."
)
@click.option("--clearance", type=float, default=None, help="R (metres); default the mission's.")
@click.option(
    "--method",
    type=click.Choice(["spherical", "horizontal", "vertical"]),
    default=None,
    help="How the clearance is measured; default the mission's.",
)
@click.option(
    "--max-depth", type=float, default=None, help="The rated depth; default the mission's."
)
@click.option(
    "--keep-out",
    multiple=True,
    type=click.Path(),
    help="Zone files to check besides the mission's.",
)
@click.option("--keep-out-margin", type=float, default=None, help="Their margin (metres).")
def verify_cmd(missions, dem_path, keep_out, **options):
    """Re-check finished MISSIONS (a mission folder, its Item, or a catalog) against a DEM
    file: clearance from its own seabed along the waypoint route and the track, depth against
    the rating, keep-out margins, pitch and turn radius, each with where it is worst. Exit 0
    only when every check of every mission holds (1 otherwise)."""
    from .verify.missions import report, verify_missions

    with _errors():
        verdicts = verify_missions(missions, dem_path, keep_out=list(keep_out) or None, **options)
        click.echo(report(verdicts))
        if not all(v.holds for v in verdicts):
            sys.exit(EXIT_MISSIONS_FAILED)


@main.command("build-maps")
@click.argument("dem_path", type=click.Path())
@click.argument("out", type=click.Path())
@_option(MAPS.method)
@_option(MAPS.clearance)
@_option(MAPS.horizontal_clearance)
@_option(MAPS.sea_level)
@_option(MAPS.surface_clearance)
@_option(MAPS.min_accumulation)
@_option(MAPS.landmarks)
@click.option("--chunks", type=int, default=None, help="Chunk side; default the DEM's.")
@click.option("--scheduler", default=None, help="Address of a dask scheduler.")
@click.option(
    "--scheduler-file",
    default=None,
    type=click.Path(),
    help="A dask scheduler file (JSON) instead of an address.",
)
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists.")
@click.option(
    "--workers", type=int, default=None, help="Worker processes of the local cluster (default 2)."
)
def build_maps_cmd(dem_path, out, chunks, scheduler, scheduler_file, overwrite, workers, **params):
    """Build the maps store OUT (elevation, safety, passable, accumulation, ridge, component,
    landmark distances) from the DEM at DEM_PATH."""
    from .dem.open import open_dem
    from .maps.build import build_maps, check_build_arguments
    from .runtime.cluster import local_workers, session
    from .store.paths import is_url, require_writable

    with _errors():
        t0 = time.perf_counter()
        if workers is not None and not (scheduler or scheduler_file):
            local_workers(workers)  # (at once: reading the DEM may take a while)
        dem = open_dem(dem_path, chunks=chunks or DEM.chunks.default)
        # a wrong argument, a wrong bucket or credential before a cluster is started
        check_build_arguments(dem, out, chunks=chunks, overwrite=overwrite, **params)
        if is_url(out):
            require_writable(out)
        with session(scheduler, scheduler_file, workers=workers) as client:
            # the passes tell their progress in the log (dask's own bar sees only its local
            # schedulers); the dashboard shows each task
            click.echo(f"building {params['method']} maps of {dem_path} into {out}", err=True)
            click.echo(f"dask dashboard: {client.dashboard_link}", err=True)
            maps = build_maps(dem, out, chunks=chunks, overwrite=overwrite, **params)
        share = float(maps["passable"].mean().compute())
        if share == 0.0:
            from .planners.endpoints import NO_PASSABLE

            click.echo(f"warning: {NO_PASSABLE}", err=True)
        click.echo(
            f"wrote {out} in {time.perf_counter() - t0:.1f} s; "
            f"{100 * share:.1f} % of cells passable"
        )


@main.command("run")
@click.argument("job", type=click.Path())
@click.option("--scheduler", default=None, help="Address of a dask scheduler (tcp://host:port).")
@click.option(
    "--scheduler-file",
    default=None,
    type=click.Path(),
    help="A dask scheduler file (JSON) instead of an address.",
)
@click.option(
    "--dashboard-address",
    default=None,
    help="Where the local cluster's dashboard listens (default 127.0.0.1:8787, or a free "
    "port); e.g. 0.0.0.0:8787 to serve it to other machines.",
)
@click.option("--dry-run", is_flag=True, help="Validate the job file and stop.")
@click.option("--overwrite", is_flag=True, help="Recompute what exists already.")
@click.option(
    "--prune",
    is_flag=True,
    help="Remove what the catalog holds that the job no longer uses (stores of other DEM or "
    "maps parameters, folders of missions no longer in the job).",
)
@click.option(
    "--workers",
    type=int,
    default=None,
    help="Worker processes of the local cluster (default 2, or dask's configuration "
    "auv_pipeline.workers); with --scheduler, the cluster's own.",
)
def run(job, scheduler, scheduler_file, dashboard_address, dry_run, overwrite, prune, workers):
    """Run the job file JOB (TOML): DEM and maps stores, every mission, the results catalog.

    Exit status: 0 every mission planned and certified; 1 some missions failed (each is an
    Item with its reason, the others are written); 2 bad input (job file, DEM, arguments); 3
    the environment (disk, permissions, memory, an unreachable scheduler, a catalog in use by
    another run); 4 an internal error (a bug: -v shows the traceback); 5 every mission
    planned, some not certified (status "uncertified", the proven ratio in the Item)."""
    from .jobs.run import run_job

    if scheduler and scheduler_file:
        raise click.UsageError("give --scheduler or --scheduler-file, not both")
    with _errors():
        res = run_job(
            job,
            scheduler=scheduler,
            scheduler_file=scheduler_file,
            dashboard_address=dashboard_address,
            overwrite=overwrite,
            dry_run=dry_run,
            prune=prune,
            workers=workers,
        )
        if dry_run:
            click.echo(
                f"job {res.job.name} is valid: {len(res.job.missions)} missions; would "
                f"write {res.job.catalog}"
            )
            return
        click.echo(
            f"job {res.job.name}: {res.planned} missions planned, {res.skipped} "
            f"skipped (finished before), {len(res.failed)} failed"
            + (f", {res.replanned} planned again (changed)" if res.replanned else "")
            + (f", {len(res.uncertified)} not certified" if res.uncertified else "")
            + f"; catalog {res.catalog} ({res.seconds:.1f} s)"
        )
        if res.uncertified:
            click.echo(
                f"missions whose bound length <= omega * shortest is not proven: "
                f"{', '.join(res.uncertified)} (the proven ratio in their Items, auv:message)",
                err=True,
            )
        if res.failed:
            click.echo(
                f"failed missions: {', '.join(res.failed)} (reasons in their Items, auv:message)",
                err=True,
            )
            sys.exit(EXIT_MISSIONS_FAILED)
        if res.uncertified:
            sys.exit(EXIT_UNCERTIFIED)


# exit codes, part of the interface (README "Exit codes")
EXIT_OK, EXIT_MISSIONS_FAILED, EXIT_BAD_INPUT, EXIT_ENVIRONMENT, EXIT_BUG = 0, 1, 2, 3, 4
EXIT_UNCERTIFIED = 5
_VERBOSE = {"on": False}


def _os_message(exc: OSError) -> str:
    """One line for an error of the operating system (disk, permissions, paths)."""
    where = f" ({exc.filename})" if getattr(exc, "filename", None) else ""
    hints = {
        errno.ENOSPC: "no space left on the device; free some space or write elsewhere",
        errno.EDQUOT: "disk quota exceeded; free some space or write elsewhere",
        errno.EACCES: "permission denied; check the permissions or write elsewhere",
        errno.EPERM: "operation not permitted; check the permissions or write elsewhere",
        errno.EROFS: "the file system is read-only; write elsewhere",
        errno.ENOTDIR: "a path component is a file, not a directory; choose another path",
        errno.EISDIR: "a directory stands where a file is expected; choose another path",
        errno.ENOENT: "no such file or directory",
        errno.EEXIST: "a file stands where a directory is needed; choose another path",
        errno.EFBIG: "file too large (a full disk or a file-size limit); free some space or "
        "write elsewhere",
    }
    what = hints.get(exc.errno, exc.strerror or str(exc) or type(exc).__name__)
    return f"{what}{where}"


class _errors:
    """Every error ends in one line on stderr and a documented exit code (never a traceback,
    unless -v): 2 bad input (PipelineError), 3 the environment (disk, permissions, memory, an
    unreachable scheduler, a busy catalog), 4 a bug (anything else; -v shows the traceback)."""

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc is None or isinstance(
            exc, SystemExit | click.exceptions.Exit | click.ClickException | click.exceptions.Abort
        ):
            return False
        if isinstance(exc, Terminated):
            click.echo(
                "error: terminated (SIGTERM); what finished is kept, and a re-run goes on "
                "from there",
                err=True,
            )
            sys.exit(143)
        if isinstance(exc, KeyboardInterrupt):
            click.echo("error: interrupted", err=True)
            # what the interrupt cut short (a store's read in zarr's event loop) is freed as
            # Python ends, each unawaited coroutine with a warning of its own
            warnings.filterwarnings("ignore", "coroutine .* was never awaited", RuntimeWarning)
            sys.exit(130)
        if isinstance(exc, SchedulerError | CatalogBusyError):
            code, msg = EXIT_ENVIRONMENT, str(exc)
        elif isinstance(exc, PipelineError):
            code, msg = EXIT_BAD_INPUT, str(exc)
        elif isinstance(exc, MemoryError):
            code, msg = EXIT_ENVIRONMENT, "out of memory; use smaller chunks or a larger machine"
        elif isinstance(exc, OSError):
            code, msg = EXIT_ENVIRONMENT, _os_message(exc)
        else:
            code = EXIT_BUG
            msg = (
                f"internal error ({type(exc).__name__}: {exc}); run with -v for the "
                "traceback and report it"
            )
        if _VERBOSE["on"]:
            traceback.print_exception(exc)
        click.echo(f"error: {' '.join(msg.split())}", err=True)
        sys.exit(code)


if __name__ == "__main__":
    main()
