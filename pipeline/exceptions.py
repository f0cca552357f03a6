"""The one base error of the pipeline and its specific subclasses.

Every message names the argument or file, the value, and how to fix it, so that a batch job
can record it as a mission's failure reason and a person can act on it.
"""

from __future__ import annotations


class PipelineError(Exception):
    """Base class of every error the pipeline raises on purpose."""


class InvalidParameterError(PipelineError, ValueError):
    """An argument has a wrong type or value (e.g. ``omega < 1``, a chunk size of 0)."""


class InvalidDEMError(PipelineError, ValueError):
    """A DEM file or array cannot be understood as a seabed grid."""


class JobFileError(PipelineError, ValueError):
    """A job file (TOML) is malformed, has an unknown key, or names a missing file."""


class StoreExistsError(PipelineError, FileExistsError):
    """An output store exists already and ``overwrite`` was not given."""


class InvalidEndpointError(PipelineError, ValueError):
    """A start or goal is off the map or not passable."""


class UnreachableGoalError(PipelineError):
    """No path joins the start and the goal through passable cells."""


class SchedulerError(PipelineError):
    """The dask cluster to run on cannot be reached or started."""


class CatalogBusyError(PipelineError):
    """Another run holds the catalog's lock."""


class PipelineWarning(UserWarning):
    """A step that changed the data as it was read (reprojected, resampled, negated depths, a
    no-data value read as NaN): logged, and warned so that a notebook shows it too."""


def notice(logger, msg: str, *args) -> None:
    """Log ``msg % args`` as a warning of ``logger`` and warn it as a :class:`PipelineWarning`
    (the command line shows the log line only)."""
    import warnings

    logger.warning(msg, *args)
    warnings.warn(msg % args if args else msg, PipelineWarning, stacklevel=3)
