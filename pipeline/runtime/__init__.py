"""Where and how the work runs: dask clusters and clients (:mod:`.cluster`), the compiled
kernels' cache (:mod:`.jit`), the process's thread pools (:mod:`.threads`) and shared claims
(:mod:`.share`), a worker's inbox for notes from the client (:mod:`.inbox`), distributed's quiet
task errors (:mod:`.quiet`) and exit handling (:mod:`.exit`)."""

from .._lazy import submodules

__getattr__ = submodules(__name__)
