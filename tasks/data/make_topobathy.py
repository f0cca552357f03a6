"""Writes tasks/data/topobathy.nc, the DEM of tasks/topobathy.toml: matplotlib's sample grid
``topobathy.npz`` (real topography and bathymetry off Vancouver Island and the Strait of
Juan de Fuca, 1 arc-minute, 91 x 120 points, -1437 m to +2205 m) as a CF NetCDF file in
lon/lat, the way such grids come from GEBCO or ETOPO. The pipeline reprojects it to metres on
import. The file is generated, not tracked: matplotlib ships the data.

    .venv/bin/python tasks/data/make_topobathy.py
"""

from pathlib import Path

import numpy as np
import xarray as xr
from matplotlib import cbook


def main(out: Path | None = None) -> Path:
    d = cbook.get_sample_data("topobathy.npz")
    z = np.asarray(d["topo"], dtype=np.float32)
    lon = np.asarray(d["longitude"], dtype=np.float64) - 360.0  # 234..238 E -> -126..-122
    lat = np.asarray(d["latitude"], dtype=np.float64)
    if lat[0] < lat[-1]:  # north first, as grids come
        z, lat = z[::-1], lat[::-1]
    da = xr.DataArray(
        z,
        dims=("lat", "lon"),
        name="elevation",
        attrs={"units": "m", "positive": "up"},
        coords={
            "lat": ("lat", lat, {"units": "degrees_north", "standard_name": "latitude"}),
            "lon": ("lon", lon, {"units": "degrees_east", "standard_name": "longitude"}),
        },
    )
    out = Path(out) if out is not None else Path(__file__).with_name("topobathy.nc")
    ds = da.to_dataset()
    ds.attrs["source"] = "matplotlib sample data topobathy.npz"
    ds.to_netcdf(out)
    print(f"wrote {out} ({out.stat().st_size} bytes)")
    return out


if __name__ == "__main__":
    main()
