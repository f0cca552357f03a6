"""The types the public functions' annotations name (for readers and type checkers; nothing
here runs at import but the aliases)."""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Union

if TYPE_CHECKING:
    import geopandas as gpd
    import xarray as xr
    from distributed import Client
    from shapely.geometry.base import BaseGeometry

    from .constraints.zones import KeepOut
    from .flight.vehicle import Vehicle
    from .store.maps_store import MapsStore

# a file or store: a path, or for stores a URL (s3://...)
PathLike = str | os.PathLike
# a grid cell (row, col)
Cell = tuple[int, int]
# a point (x, y) in map metres, or (lon, lat) in degrees
Pair = tuple[float, float]
# a region (west, south, east, north)
Box = tuple[float, float, float, float]
# dask chunks: a side, (rows, cols), or what xarray takes
Chunks = int | tuple[int, int] | dict | str | None
# a maps store: its path, the Dataset open_maps gives, or its MapsStore
Maps = Union[str, os.PathLike, "xr.Dataset", "MapsStore"]
# where work runs: None, "synchronous", "threads", a scheduler address or a Client
ClientLike = Union[None, str, "Client"]
# a DEM: a file, or an xarray DataArray / Dataset
DEMLike = Union[str, os.PathLike, "xr.DataArray", "xr.Dataset"]
# a vehicle: a Vehicle, a dict of its keys, or None (the defaults)
VehicleLike = Union["Vehicle", dict, None]
# keep-out zones: vector files, a GeoDataFrame, shapely polygons (map coordinates) or KeepOut
ZonesLike = Union[str, os.PathLike, list, "gpd.GeoDataFrame", "BaseGeometry", "KeepOut", None]
