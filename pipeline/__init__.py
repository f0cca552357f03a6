"""Bounded near-bottom cruise trajectory planning (RA* + MCPC) for AUVs over large seabed grids.

The public API (docs/method.md section 8); later stages are added as they land.
"""

from __future__ import annotations

import logging
import os

# GDAL's block cache (5 % of the RAM by default) keeps every tile a DEM import streams through,
# which nearly doubled a large import's peak memory (CHANGELOG.md, "Measurements"): the import
# reads each tile about once, so a small cache loses nothing. Set before GDAL starts; a value
# the user set is kept, and worker processes inherit it.
os.environ.setdefault("GDAL_CACHEMAX", "64")

from ._lazy import submodules
from .exceptions import (
    InvalidDEMError,
    InvalidEndpointError,
    InvalidParameterError,
    JobFileError,
    PipelineError,
    PipelineWarning,
    SchedulerError,
    StoreExistsError,
    UnreachableGoalError,
)

# The rest of the API is imported on first use (PEP 562): ``import pipeline`` itself then costs
# milliseconds, not the seconds of dask.array, xarray, zarr and numba that its stages need, so the
# command line answers ``--help`` and a wrong job file at once. ``pipeline.plan`` and
# ``from pipeline import plan`` work as before; so does a submodule reached as an attribute
# (``pipeline.jobs``).
_LAZY = {
    "cell_size": "dem.canonical",
    "import_dem": "dem.open",
    "open_dem": "dem.open",
    "write_dem": "dem.dem_store",
    "Flight": "flight.vehicle",
    "Vehicle": "flight.vehicle",
    "write_mission": "outputs.files",
    "fly": "flight.fly",
    "run_job": "jobs.run",
    "build_maps": "maps.build",
    "dem_hash": "maps.build",
    "plan": "mcpc.plan",
    "plan_missions": "jobs.missions",
    "PLANNERS": "planners.registry",
    "Status": "trajectory",
    "Trajectory": "trajectory",
    "plan_window": "mcpc.window",
    "fill_depressions": "maps.ridges",
    "flow_accumulation": "maps.ridges",
    "ridge_map": "maps.ridges",
    "passable": "maps.safety",
    "safety_map": "maps.safety",
    "MapsStore": "store.maps_store",
    "open_maps": "store.maps_store",
    "open_store": "store.maps_store",
    "synthetic_dem": "dem.synthetic",
    "verify_missions": "verify.missions",
    "SourceSeabed": "verify.seabed",
}


_submodule = submodules(__name__)


def __getattr__(name: str):
    import importlib

    module = _LAZY.get(name)
    if module is None:  # a submodule, as the eager imports of the API used to bind them
        return _submodule(name)
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("auv-pipeline")  # the installed package's metadata (pyproject.toml)
    except PackageNotFoundError:  # a source tree that was never installed
        return "0+unknown"


__version__ = _version()

# the public names, listed once: the exceptions imported above, then those loaded on first use
__all__ = [
    "InvalidDEMError",
    "InvalidEndpointError",
    "InvalidParameterError",
    "JobFileError",
    "PipelineError",
    "PipelineWarning",
    "SchedulerError",
    "StoreExistsError",
    "UnreachableGoalError",
    "__version__",
    *_LAZY,
]

logging.getLogger(__name__).addHandler(logging.NullHandler())
