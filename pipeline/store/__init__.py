"""Stage 3, the maps store as the planners read it: its format (:mod:`.schema`), the
:class:`~.maps_store.MapsStore` handle and :func:`~.maps_store.open_maps` (:mod:`.maps_store`),
the process's chunk cache (:mod:`.cache`), direct shard reads and writes (:mod:`.zarr_direct`),
where stores live and how they are written atomically (:mod:`.paths`), and dask arrays written
to a store in bands (:mod:`.bands`).
"""

from .._lazy import submodules

__getattr__ = submodules(__name__)
