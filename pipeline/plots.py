"""Quick-look pictures: hillshaded bathymetry (matplotlib, Agg backend, no display needed)."""

from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import LightSource  # noqa: E402


def _extent_km(dem):
    x = np.asarray(dem["x"].values)
    y = np.asarray(dem["y"].values)
    a = float(dem.attrs.get("cell_size", abs(x[1] - x[0])))
    return [
        (x.min() - a / 2) / 1e3,
        (x.max() + a / 2) / 1e3,
        (y.min() - a / 2) / 1e3,
        (y.max() + a / 2) / 1e3,
    ]


def hillshade_axes(ax, dem, *, vert_exag: float = 3.0, max_side: int = 2000, colorbar=True):
    """Draw ``dem`` hillshaded and coloured by depth on ``ax`` (decimated to ``max_side``)."""
    step = max(1, int(np.ceil(max(dem.shape) / max_side)))
    sub = dem[::step, ::step]
    z = np.asarray(sub.values, dtype=np.float64)
    a = float(dem.attrs.get("cell_size", 1.0)) * step
    y = np.asarray(sub["y"].values)
    if y[0] < y[-1]:  # draw north up
        z = z[::-1]
    ls = LightSource(azdeg=315, altdeg=40)
    zf = np.where(np.isfinite(z), z, np.nanmin(z))
    vmin, vmax = float(np.nanpercentile(z, 0.5)), float(max(np.nanpercentile(z, 99.5), 0.0))
    cmap = plt.get_cmap("gist_earth")
    rgb = ls.shade(
        zf, cmap=cmap, blend_mode="soft", vert_exag=vert_exag, dx=a, dy=a, vmin=vmin, vmax=vmax
    )
    rgb[~np.isfinite(z)] = (0.85, 0.85, 0.85, 1.0)
    ax.imshow(rgb, extent=_extent_km(dem), origin="upper", interpolation="nearest")
    if colorbar:
        sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(vmin, vmax))
        plt.colorbar(sm, ax=ax, shrink=0.8, label="elevation (m)")
    land = np.where(np.isfinite(z), z >= 0, False)
    if land.any():
        ax.contour(
            land.astype(float),
            levels=[0.5],
            colors="k",
            linewidths=0.6,
            extent=_extent_km(dem),
            origin="upper",
        )
    ax.set_xlabel("x (km)")
    ax.set_ylabel("y (km)")
    return ax


def hillshade_png(dem, path: str | os.PathLike, *, title: str | None = None) -> str:
    """Write a hillshade PNG of ``dem`` to ``path`` and return the path."""
    fig, ax = plt.subplots(figsize=(8, 7), dpi=110)
    hillshade_axes(ax, dem)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return str(path)


def mission_quicklook(
    maps, traj, path: str | os.PathLike, *, title: str = "", max_side: int = 800
) -> str:
    """A mission's quick look: hillshade of the region around the track, ridge cells, the track
    coloured by its height above the seabed, start and goal."""
    r0, c0 = traj.cells.min(axis=0)
    r1, c1 = traj.cells.max(axis=0) + 1
    pad = max(20, int(0.15 * max(r1 - r0, c1 - c0)))
    ds = maps.dataset
    rows, cols = maps.shape
    r0, c0 = max(int(r0) - pad, 0), max(int(c0) - pad, 0)
    r1, c1 = min(int(r1) + pad, rows), min(int(c1) + pad, cols)
    step = max(1, int(np.ceil(max(r1 - r0, c1 - c0) / max_side)))
    sub = ds["elevation"][r0:r1:step, c0:c1:step].load()
    sub.attrs["cell_size"] = maps.cell_size
    rdg = ds["ridge"][r0:r1:step, c0:c1:step].values
    fig, ax = plt.subplots(figsize=(7.5, 6.5), dpi=100)
    hillshade_axes(ax, sub, colorbar=False)
    xs, ys = sub["x"].values / 1e3, sub["y"].values / 1e3
    rr, cc = np.nonzero(rdg)
    ax.scatter(xs[cc], ys[rr], s=0.6, c="white", alpha=0.5, linewidths=0)
    import xarray as xr

    elev = (
        ds["elevation"]
        .isel(
            y=xr.DataArray(traj.cells[:, 0], dims="p"), x=xr.DataArray(traj.cells[:, 1], dims="p")
        )
        .values
    )
    above = traj.points[:, 2] - elev
    x, y = traj.points[:, 0] / 1e3, traj.points[:, 1] / 1e3
    sc = ax.scatter(x, y, c=above, s=3, cmap="plasma", zorder=3)
    plt.colorbar(sc, ax=ax, shrink=0.8, label="height above the seabed (m)")
    ax.plot(x[0], y[0], "o", color="lime", ms=8, mec="k", zorder=4, label="start")
    ax.plot(x[-1], y[-1], "*", color="red", ms=12, mec="k", zorder=4, label="goal")
    ax.legend(loc="lower right", fontsize=8)
    ax.set_title(
        f"{title}: {traj.planner}, omega {traj.omega:g}, {traj.length_m / 1e3:.1f} km, "
        f"{100 * traj.ridge_ratio:.0f} % ridge",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return str(path)
