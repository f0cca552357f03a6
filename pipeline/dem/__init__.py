"""Stage 1, the DEM: files read as they are (:mod:`.readers`), made canonical (:mod:`.canonical`:
metres, positive up, square cells, no-data as NaN), reprojected exactly (:mod:`.reproject`),
written to and read from DEM stores (:mod:`.dem_store`), opened and imported (:mod:`.open`),
and synthetic seabeds for tests and demos (:mod:`.synthetic`).
"""

from .._lazy import submodules

__getattr__ = submodules(__name__)
