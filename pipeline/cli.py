"""The ``pipeline`` command line: thin, it parses and calls the library."""

from __future__ import annotations

import logging
import sys
import time

import click

from .exceptions import PipelineError
from .params import DEM, MAPS, SYNTHETIC, Param


def _option(param: Param, *, flag: str | None = None):
    """A click option from the parameter schema: its type, default and help text."""
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
    import dask

    # distributed installs its own INFO handler when imported: keep it to warnings
    dask.config.set({"logging.distributed": "debug" if verbose else "warning"})
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    for noisy in ("distributed", "numba", "rasterio", "fsspec", "asyncio"):
        logging.getLogger(noisy).setLevel(logging.WARNING)


def _progress(what: str):
    from dask.diagnostics import ProgressBar

    click.echo(what, err=True)
    return ProgressBar(dt=1.0, out=sys.stderr)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("-v", "--verbose", is_flag=True, help="Debug logging.")
@click.version_option(package_name="auv-pipeline")
def main(verbose: bool) -> None:
    """Plan near-bottom AUV cruise trajectories over large seabed grids (RA* + MCPC)."""
    _setup_logging(verbose)


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
@_option(DEM.chunks)
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists.")
def dem_synth(out, shape, cell_size, seed, islands, chunks, overwrite):
    """Write a virtual mid-ocean-ridge DEM to the Zarr store OUT."""
    from .dem import write_dem
    from .synthetic import synthetic_dem

    with _errors():
        t0 = time.perf_counter()
        d = synthetic_dem(shape, cell_size=cell_size, seed=seed, chunks=chunks, islands=islands)
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
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists.")
def dem_import(source, out, chunks, variable, cell_size, resolution, overwrite):
    """Import a GeoTIFF, NetCDF / GMT grid or Zarr DEM as the canonical Zarr store OUT."""
    from .dem import open_dem, write_dem

    with _errors():
        t0 = time.perf_counter()
        d = open_dem(
            source, chunks=chunks, variable=variable, cell_size=cell_size, resolution=resolution
        )
        with _progress(f"importing {source} ({d.shape[0]} x {d.shape[1]} cells) into {out}"):
            write_dem(d, out, chunks=chunks, overwrite=overwrite)
        click.echo(f"wrote {out} in {time.perf_counter() - t0:.1f} s")


@dem.command("info")
@click.argument("path", type=click.Path())
def dem_info(path):
    """Describe a DEM file as open_dem sees it."""
    from .dem import open_dem

    with _errors():
        d = open_dem(path, chunks=DEM.chunks.default)
        click.echo(
            f"{path}: {d.shape[0]} x {d.shape[1]} cells of {d.attrs['cell_size']:g} m, "
            f"chunks {d.data.chunksize}"
        )
        click.echo(f"crs: {'set' if 'crs_wkt' in d.attrs else 'none (local metric grid)'}")
        lo, hi = float(d.min().compute()), float(d.max().compute())
        click.echo(f"elevation: {lo:.1f} .. {hi:.1f} m")


@main.command("build-maps")
@click.argument("dem_path", type=click.Path())
@click.argument("out", type=click.Path())
@_option(MAPS.method)
@_option(MAPS.clearance)
@_option(MAPS.horizontal_clearance)
@_option(MAPS.sea_level)
@_option(MAPS.surface_clearance)
@_option(MAPS.min_accumulation)
@click.option("--chunks", type=int, default=None, help="Chunk side; default the DEM's.")
@click.option("--scheduler", default=None, help="Address of a dask scheduler.")
@click.option(
    "--scheduler-file",
    default=None,
    type=click.Path(),
    help="A dask scheduler file (JSON) instead of an address.",
)
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists.")
def build_maps_cmd(dem_path, out, chunks, scheduler, scheduler_file, overwrite, **params):
    """Build the maps store OUT (elevation, safety, passable, accumulation, ridge) from the
    DEM at DEM_PATH."""
    from .cluster import session
    from .dem import open_dem
    from .maps import build_maps

    with _errors():
        t0 = time.perf_counter()
        dem = open_dem(dem_path, chunks=chunks or DEM.chunks.default)
        with (
            session(scheduler, scheduler_file),
            _progress(f"building {params['method']} maps of {dem_path} into {out}"),
        ):
            maps = build_maps(dem, out, chunks=chunks, overwrite=overwrite, **params)
        share = float(maps["passable"].mean().compute())
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
@click.option("--dry-run", is_flag=True, help="Validate the job file and stop.")
@click.option("--overwrite", is_flag=True, help="Recompute what exists already.")
def run(job, scheduler, scheduler_file, dry_run, overwrite):
    """Run the job file JOB (TOML): DEM and maps stores, every mission, the results catalog.

    Exit status: 0 when every mission was planned, 1 when any failed (each failed mission is
    an Item with its reason), 2 for a bad job file or another error before planning."""
    from .jobs import run_job

    if scheduler and scheduler_file:
        raise click.UsageError("give --scheduler or --scheduler-file, not both")
    with _errors():
        res = run_job(
            job,
            scheduler=scheduler,
            scheduler_file=scheduler_file,
            overwrite=overwrite,
            dry_run=dry_run,
        )
        if dry_run:
            click.echo(
                f"job {res.job.name} is valid: {len(res.job.missions)} missions; would "
                f"write {res.job.catalog}"
            )
            return
        click.echo(
            f"job {res.job.name}: {res.planned} missions planned, {res.skipped} "
            f"skipped (finished before), {len(res.failed)} failed; catalog "
            f"{res.catalog} ({res.seconds:.1f} s)"
        )
        if res.failed:
            click.echo(
                f"failed missions: {', '.join(res.failed)} (reasons in their Items, auv:message)",
                err=True,
            )
            sys.exit(1)


class _errors:
    """Turn a PipelineError into one clear line on stderr and exit code 2."""

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc is not None and isinstance(exc, PipelineError):
            click.echo(f"error: {exc}", err=True)
            sys.exit(2)
        return False


if __name__ == "__main__":
    main()
