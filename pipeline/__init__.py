"""Bounded near-bottom cruise trajectory planning (RA* + MCPC) for AUVs over large seabed grids.

The public API (docs/method.md section 8); later stages are added as they land.
"""

from __future__ import annotations

import logging
import os
import warnings

# GDAL's block cache (5 % of the RAM by default) keeps every tile a DEM import streams through
# (1.2 GiB of a 24 GiB machine: a 20000^2 lon/lat import peaked at 2.35 GiB with it, 1.29 GiB
# with 256 MB; at 10000^2 0.92 GiB, 0.64 GiB with 64 MB and no slower): the import reads each
# tile about once, so a small cache loses nothing. Set before GDAL starts; a value the user set
# is kept, and worker processes inherit it.
os.environ.setdefault("GDAL_CACHEMAX", "64")

from .dem import cell_size, import_dem, open_dem, write_dem
from .exceptions import (
    InvalidDEMError,
    InvalidEndpointError,
    InvalidParameterError,
    JobFileError,
    PipelineError,
    SchedulerError,
    StoreExistsError,
    UnreachableGoalError,
)
from .flight import Flight, Vehicle, fly
from .jobs import run_job
from .maps import build_maps, dem_hash
from .mcpc import plan
from .missions import plan_missions
from .planners import PLANNERS, Trajectory, plan_window
from .ridges import fill_depressions, flow_accumulation, ridge_map
from .safety import passable, safety_map
from .store import MapsStore, open_maps, open_store
from .synthetic import synthetic_dem

# odc-geo warps lon/lat grids into numpy arrays and gives GDAL their transform itself, and
# rasterio still warns, at every chunk, that those arrays have none
warnings.filterwarnings(
    "ignore", message="Dataset has no geotransform, gcps, or rpcs", module="rasterio.warp"
)

__version__ = "0.1.0"

__all__ = [
    "InvalidDEMError",
    "InvalidEndpointError",
    "InvalidParameterError",
    "JobFileError",
    "MapsStore",
    "PLANNERS",
    "PipelineError",
    "SchedulerError",
    "StoreExistsError",
    "Trajectory",
    "UnreachableGoalError",
    "__version__",
    "Flight",
    "Vehicle",
    "build_maps",
    "cell_size",
    "dem_hash",
    "fill_depressions",
    "flow_accumulation",
    "fly",
    "import_dem",
    "open_dem",
    "open_maps",
    "open_store",
    "passable",
    "plan",
    "plan_missions",
    "plan_window",
    "ridge_map",
    "run_job",
    "safety_map",
    "synthetic_dem",
    "write_dem",
]

logging.getLogger(__name__).addHandler(logging.NullHandler())
