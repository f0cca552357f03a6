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
    return [(x.min() - a / 2) / 1e3, (x.max() + a / 2) / 1e3,
            (y.min() - a / 2) / 1e3, (y.max() + a / 2) / 1e3]


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
    rgb = ls.shade(zf, cmap=cmap, blend_mode="soft", vert_exag=vert_exag, dx=a, dy=a,
                   vmin=vmin, vmax=vmax)
    rgb[~np.isfinite(z)] = (0.85, 0.85, 0.85, 1.0)
    ax.imshow(rgb, extent=_extent_km(dem), origin="upper", interpolation="nearest")
    if colorbar:
        sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(vmin, vmax))
        plt.colorbar(sm, ax=ax, shrink=0.8, label="elevation (m)")
    land = np.where(np.isfinite(z), z >= 0, False)
    if land.any():
        ax.contour(land.astype(float), levels=[0.5], colors="k", linewidths=0.6,
                   extent=_extent_km(dem), origin="upper")
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
