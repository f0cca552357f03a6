"""Writes tasks/data/atoll.nc, the DEM of tasks/bad-missions.toml: 300 x 300 cells of 30 m,
abyssal plain at -2000 m, a seamount whose summit carries an atoll (a ring of land around a
lagoon 800 m deep): the lagoon is passable but cannot be reached from outside.

    .venv/bin/python tasks/data/make_atoll.py
"""

from pathlib import Path

import numpy as np
import xarray as xr

n, a = 300, 30.0
r, c = np.mgrid[0:n, 0:n]
d = np.hypot(r - 150, c - 150)  # cells from the centre
z = -2000.0 + 1900.0 * np.exp(-((d / 110.0) ** 2))  # the seamount
z = np.where(d < 58, -800.0 + 700.0 * (d / 58) ** 4, z)  # the lagoon bowl
z = np.where((d >= 58) & (d < 64), 10.0, z)  # the ring of land
x = (np.arange(n) + 0.5) * a
y = (np.arange(n)[::-1] + 0.5) * a
da = xr.DataArray(
    z.astype("float32"),
    dims=("y", "x"),
    coords={"x": x, "y": y},
    name="elevation",
    attrs={"units": "m"},
)
out = Path(__file__).with_name("atoll.nc")
da.to_netcdf(
    out, encoding={"elevation": {"zlib": True, "complevel": 9, "least_significant_digit": 1}}
)
print(f"wrote {out} ({out.stat().st_size} bytes)")
