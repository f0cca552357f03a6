"""Quick-look pictures: hillshaded bathymetry (matplotlib, Agg backend, no display needed)."""

from __future__ import annotations

import math
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import LightSource  # noqa: E402

# PNG encoding at zlib level 1: a quick-look (shaded relief, which compresses little at any
# level) in a third of the time of the default level 6, a tenth larger
FAST_PNG = {"compress_level": 1}


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


def _land(z: np.ndarray) -> np.ndarray:
    """Where the grid is land (at or above 0 m), no-data excluded."""
    return np.where(np.isfinite(z), z >= 0, False)


RELIEF_CMAP = "gist_earth"


def shaded_relief(z: np.ndarray, a: float, *, vert_exag: float = 3.0):
    """The hillshaded, depth-coloured picture of the grid ``z`` (cells of ``a`` metres, rows as
    drawn): RGBA floats, no-data light grey, and the colour scale's ``vmin``, ``vmax`` (the
    0.5 and 99.5 percentiles, the top at least sea level) of :data:`RELIEF_CMAP`."""
    z = np.asarray(z, dtype=np.float64)
    ls = LightSource(azdeg=315, altdeg=40)
    zf = np.where(np.isfinite(z), z, np.nanmin(z))
    vmin, vmax = float(np.nanpercentile(z, 0.5)), float(max(np.nanpercentile(z, 99.5), 0.0))
    rows, cols = zf.shape
    # the shading's slopes need two cells a side: a grid one cell thin (a map, or its
    # thinned picture, of one row) is shaded flat along that side
    zf = np.pad(zf, ((0, max(0, 2 - rows)), (0, max(0, 2 - cols))), mode="edge")
    rgb = ls.shade(
        zf,
        cmap=plt.get_cmap(RELIEF_CMAP),
        blend_mode="soft",
        vert_exag=vert_exag,
        dx=a,
        dy=a,
        vmin=vmin,
        vmax=vmax,
    )[:rows, :cols]
    rgb[~np.isfinite(z)] = (0.85, 0.85, 0.85, 1.0)
    return rgb, vmin, vmax


def hillshade_axes(ax, dem, *, vert_exag: float = 3.0, max_side: int = 2000, colorbar=True):
    """Draw ``dem`` hillshaded and coloured by depth on ``ax`` (decimated to ``max_side``);
    ``colorbar``: True (beside the axes), False, or axes to draw it in, horizontally."""
    step = max(1, int(np.ceil(max(dem.shape) / max_side)))
    sub = dem[::step, ::step]
    z = np.asarray(sub.values, dtype=np.float64)
    a = float(dem.attrs.get("cell_size", 1.0)) * step
    y = np.asarray(sub["y"].values)
    if y[0] < y[-1]:  # draw north up
        z = z[::-1]
    rgb, vmin, vmax = shaded_relief(z, a, vert_exag=vert_exag)
    cmap = plt.get_cmap(RELIEF_CMAP)
    ax.imshow(rgb, extent=_extent_km(dem), origin="upper", interpolation="nearest")
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(vmin, vmax))
    if isinstance(colorbar, plt.Axes):
        ax.figure.colorbar(sm, cax=colorbar, orientation="horizontal", label="seabed elevation (m)")
    elif colorbar:
        ax.figure.colorbar(sm, ax=ax, shrink=0.8, label="elevation (m)")
    land = _land(z)
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
    fig.savefig(path, pil_kwargs=FAST_PNG)
    plt.close(fig)
    return str(path)


def _nice_step(span: float) -> float:
    """A graticule step (degrees) giving about 3 to 6 lines over ``span`` degrees."""
    for st in (0.01, 0.02, 0.05, 0.1, 0.2, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0):
        if span / st <= 6:
            return st
    return 30.0


# facecolor, not fc: given by its own name, the patch takes it at once instead of first
# resolving the default patch colour, a colour-cycle entry (milliseconds a label)
_LABEL_BOX = dict(boxstyle="round,pad=0.15", facecolor="white", edgecolor="none", alpha=0.75)


def graticule(ax, crs_wkt: str, extent_km) -> None:
    """Lines of constant longitude and latitude over a map in km of a projected CRS, labelled
    at the bottom and left edges."""
    from pyproj import CRS, Transformer

    crs = CRS.from_wkt(crs_wkt)
    if crs.is_geographic:
        return
    fwd = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    inv = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    x0, x1, y0, y1 = (v * 1e3 for v in extent_km)
    ex = np.linspace(x0, x1, 25)
    ey = np.linspace(y0, y1, 25)
    bx = np.concatenate([ex, np.full(25, x1), ex[::-1], np.full(25, x0)])
    by = np.concatenate([np.full(25, y0), ey, np.full(25, y1), ey[::-1]])
    lon, lat = fwd.transform(bx, by)
    style = dict(color="0.15", lw=0.5, ls=(0, (4, 3)), alpha=0.7, zorder=2)
    for which, lo, hi in (("lon", min(lon), max(lon)), ("lat", min(lat), max(lat))):
        st = _nice_step(hi - lo)
        for v in np.arange(np.ceil(lo / st) * st, hi + 1e-12, st):
            t = np.linspace(
                min(lat) if which == "lon" else min(lon),
                max(lat) if which == "lon" else max(lon),
                100,
            )
            x, y = (
                inv.transform(np.full(100, v), t)
                if which == "lon"
                else inv.transform(t, np.full(100, v))
            )
            ax.plot(np.asarray(x) / 1e3, np.asarray(y) / 1e3, **style)
            hemi = ("E" if v >= 0 else "W") if which == "lon" else ("N" if v >= 0 else "S")
            label = f"{abs(v):.{max(0, -int(np.floor(np.log10(st))))}f}\N{DEGREE SIGN}{hemi}"
            if which == "lon":
                at, _ = inv.transform(v, fwd.transform((x0 + x1) / 2, y0)[1])
                at = (at / 1e3, y0 / 1e3) if x0 <= at <= x1 else None
            else:
                _, at = inv.transform(fwd.transform(x0, (y0 + y1) / 2)[0], v)
                at = (x0 / 1e3, at / 1e3) if y0 <= at <= y1 else None
            if at is not None:  # inside the map, at its lower or left edge
                ax.annotate(
                    label,
                    at,
                    xytext=(2, 3),
                    textcoords="offset points",
                    ha="left",
                    va="bottom",
                    fontsize=7,
                    color="0.1",
                    bbox=_LABEL_BOX,
                    zorder=7,
                )
    ax.set_xlim(x0 / 1e3, x1 / 1e3)
    ax.set_ylim(y0 / 1e3, y1 / 1e3)


RIDGE_RGBA = (0.55, 0.95, 1.0, 0.4)


def plan_layers(maps, r0, r1, c0, c1, step: float):
    """The elevation (a DataArray with its coordinates) and the ridge mask of rows ``r0:r1``
    and columns ``c0:c1`` of the maps, reduced by ``k = ceil(step)`` for a picture: from the
    store's overview at the first of the factors 2, 3, 4, 6, 8, 12, 16, ... not below ``k``
    (block means, ridge where a block holds any) when the region covers a sixteenth of the
    map or more (an overview is made from the whole map, once, so only a few factors are
    made); else from the full layers, every ``k``-th cell of the elevation and the ridge of
    each ``k x k`` block. The choice depends on the region alone, so that a mission's picture
    is the same wherever and whenever it is drawn."""
    import xarray as xr

    k = max(1, int(math.ceil(step - 1e-9)))
    f = 1
    if k > 1:  # 2^j or 3 x 2^(j-1), the first not below k: at most 1.5 k
        f = 2 ** math.ceil(math.log2(k))
        if 3 * f // 4 >= k:
            f = 3 * f // 4
    rows, cols = maps.shape
    if f == 1 or 16 * (r1 - r0) * (c1 - c0) < rows * cols:
        sub = xr.DataArray(
            maps.window("elevation", r0, r1, c0, c1)[::k, ::k],
            dims=("y", "x"),
            coords={"y": maps.y[r0:r1:k], "x": maps.x[c0:c1:k]},
        )
        sub.attrs["cell_size"] = maps.cell_size * k
        ridge = maps.window("ridge", r0, r1, c0, c1)
        if k > 1:
            h, w = -(-ridge.shape[0] // k) * k, -(-ridge.shape[1] // k) * k
            pad = np.zeros((h, w), dtype=bool)
            pad[: ridge.shape[0], : ridge.shape[1]] = ridge
            ridge = pad.reshape(h // k, k, w // k, k).any(axis=(1, 3))
        return sub, ridge.astype(np.uint8)
    ov = maps.overview(f)
    i0, j0 = r0 // f, c0 // f
    i1, j1 = min(-(-r1 // f), ov["elevation"].shape[0]), min(-(-c1 // f), ov["elevation"].shape[1])
    dy = maps.y[1] - maps.y[0] if len(maps.y) > 1 else -maps.cell_size
    dx = maps.x[1] - maps.x[0] if len(maps.x) > 1 else maps.cell_size
    centre = (f - 1) / 2  # a block's centre, in cells from its first
    sub = xr.DataArray(
        ov["elevation"][i0:i1, j0:j1],
        dims=("y", "x"),
        coords={
            "y": maps.y[0] + (np.arange(i0, i1) * f + centre) * dy,
            "x": maps.x[0] + (np.arange(j0, j1) * f + centre) * dx,
        },
    )
    sub.attrs["cell_size"] = maps.cell_size * f
    return sub, ov["ridge"][i0:i1, j0:j1].astype(np.uint8)


def mission_quicklook(
    maps,
    traj,
    path,
    *,
    title: str = "",
    crs_wkt: str | None = None,
    max_side: int = 700,
):
    """A mission's quick look: a plan view (hillshade, ridge network, the grid path faint, the
    flown track bold, waypoints, start and goal; a lon/lat graticule when the maps have a
    CRS) above the depth profile along the flown track (seabed, the lowest safe height, the
    flown height, waypoints), with the clearance and the vehicle's limits stated.

    ``path``: a file path (returned as a string) or a binary file object (returned as is),
    written as PNG. The figure is made outside pyplot (no figure manager, nothing to close)."""
    box = _mission_box(maps, traj)
    sub, rdg = plan_layers(maps, *box, max(box[1] - box[0], box[3] - box[2]) / max_side)
    fig, gs = _quicklook_figure(box, maps.cell_size)
    ax = fig.add_subplot(gs[0, :])
    host = fig.add_subplot(gs[1, 2])
    host.axis("off")
    hillshade_axes(ax, sub, colorbar=host.inset_axes([0.05, 0.7, 0.9, 0.12]))
    handles = _plan_view(ax, sub, rdg, traj, crs_wkt)
    leg = fig.add_subplot(gs[1, 0])
    leg.axis("off")
    leg.legend(handles=handles, loc="upper left", fontsize=8, frameon=False, ncols=2)
    side = fig.add_subplot(gs[1, 1])
    side.axis("off")
    text = "\n".join(_summary_lines(traj))
    side.text(0.05, 1.0, text, transform=side.transAxes, fontsize=8, va="top")
    # a mission's name as its title; a character that cannot be printed shows as "?"
    # y given: the title sits where matplotlib would put it over axes with no ticks on top,
    # without its search of every tick label's extent (a noticeable share of each quick-look)
    ax.set_title("".join(c if c.isprintable() else "?" for c in str(title)), fontsize=11, y=1.0)
    _depth_profile(fig.add_subplot(gs[2, :]), maps.parameters, traj)
    fig.savefig(path, format="png", pil_kwargs=FAST_PNG)
    return str(path) if isinstance(path, str | os.PathLike) else path


def _mission_box(maps, traj) -> tuple:
    """``(r0, r1, c0, c1)``: the cells the plan view shows, the mission's track and grid path
    with a margin around them, within the map."""
    f = traj.flight
    xs_all, ys_all = (f.x, f.y) if f is not None else (traj.points[:, 0], traj.points[:, 1])
    cols_f = (xs_all - maps.x[0]) / (maps.x[1] - maps.x[0])
    rows_f = (ys_all - maps.y[0]) / (maps.y[1] - maps.y[0])
    rows, cols = maps.shape
    span = max(rows_f.max() - rows_f.min(), cols_f.max() - cols_f.min())
    pad = max(20, int(0.08 * span))
    r0 = max(int(np.floor(min(rows_f.min(), traj.cells[:, 0].min()))) - pad, 0)
    c0 = max(int(np.floor(min(cols_f.min(), traj.cells[:, 1].min()))) - pad, 0)
    r1 = min(int(np.ceil(max(rows_f.max(), traj.cells[:, 0].max()))) + pad + 1, rows)
    c1 = min(int(np.ceil(max(cols_f.max(), traj.cells[:, 1].max()))) + pad + 1, cols)
    return r0, r1, c0, c1


def _quicklook_figure(box: tuple, a: float) -> tuple:
    """``(figure, gridspec)``: the plan view following the box's extent (rows of ``a``
    metres), the legend, the summary and the colour bar below it, the profile at the bottom."""
    from matplotlib.figure import Figure

    r0, r1, c0, c1 = box
    w_km, h_km = (c1 - c0) * a, (r1 - r0) * a
    plan_w = 9.0
    plan_h = float(np.clip(plan_w * h_km / w_km, 2.5, 9.0))
    fig_w, fig_h = plan_w + 1.2, plan_h + 6.0
    fig = Figure(figsize=(fig_w, fig_h), dpi=100)
    # fixed margins in inches (a tight bounding box would draw the figure twice)
    gs = fig.add_gridspec(
        3,
        3,
        height_ratios=[plan_h, 1.5, 2.7],
        width_ratios=[1.2, 1.2, 1.0],
        hspace=0.12,
        left=0.9 / fig_w,
        right=1 - 0.25 / fig_w,
        top=1 - 0.35 / fig_h,
        bottom=0.95 / fig_h,
    )
    return fig, gs


def _plan_view(ax, sub, rdg, traj, crs_wkt) -> list:
    """The ridge cells, the graticule, the grid path, the flown track, the waypoints, start
    and goal over the hillshade on ``ax``; returns the legend's handles."""
    from matplotlib.colors import ListedColormap
    from matplotlib.lines import Line2D

    f = traj.flight
    ext = _extent_km(sub)
    ridge_cmap = ListedColormap([(0, 0, 0, 0), RIDGE_RGBA])
    rdg = rdg[: sub.shape[0], : sub.shape[1]]
    if sub["y"].values[0] < sub["y"].values[-1]:
        rdg = rdg[::-1]
    ax.imshow(
        rdg,
        extent=ext,
        origin="upper",
        cmap=ridge_cmap,
        vmin=0,
        vmax=1,
        interpolation="nearest",
        zorder=1,
    )
    if crs_wkt:
        graticule(ax, crs_wkt, ext)
    zones = _keep_out(ax, traj.keep_out, ext)
    gx, gy = traj.points[:, 0] / 1e3, traj.points[:, 1] / 1e3
    ax.plot(gx, gy, color="0.25", lw=0.8, alpha=0.6, zorder=3)
    handles = [
        Line2D([], [], color=RIDGE_RGBA[:3], lw=6, alpha=RIDGE_RGBA[3], label="ridge cells"),
        Line2D(
            [],
            [],
            color="0.25",
            lw=0.8,
            alpha=0.6,
            label=f"grid path ({traj.length_m / 1e3:.1f} km)",
        ),
    ]
    if f is not None:
        ax.plot(f.x / 1e3, f.y / 1e3, color="#d62728", lw=2.0, zorder=4)
        handles.append(
            Line2D(
                [],
                [],
                color="#d62728",
                lw=2.0,
                label=f"flown track ({f.flown_length_m / 1e3:.1f} km)",
            )
        )
        wx, wy = f.waypoints[:, 0] / 1e3, f.waypoints[:, 1] / 1e3
        ax.plot(wx, wy, "o", ms=3, mfc="white", mec="k", mew=0.6, zorder=5)
        handles.append(
            Line2D(
                [],
                [],
                ls="",
                marker="o",
                ms=4,
                mfc="white",
                mec="k",
                label=f"waypoints ({len(wx)})",
            )
        )
        sx, sy, ex_, ey_ = f.x[0], f.y[0], f.x[-1], f.y[-1]
    else:
        sx, sy, ex_, ey_ = gx[0] * 1e3, gy[0] * 1e3, gx[-1] * 1e3, gy[-1] * 1e3
    via = np.asarray(traj.extra.get("via_index", []), dtype=np.int64)
    if via.size:
        vx, vy = traj.points[via, 0] / 1e3, traj.points[via, 1] / 1e3
        ax.plot(vx, vy, "D", color="#00bcd4", ms=8, mec="k", zorder=6)
        for k, (px, py) in enumerate(zip(vx, vy, strict=True)):
            ax.annotate(str(k + 1), (px, py), xytext=(6, 6), textcoords="offset points",
                        fontsize=8, zorder=7, bbox=dict(boxstyle="round,pad=0.15", fc="white",
                        ec="none", alpha=0.85))  # fmt: skip
        handles.append(
            Line2D([], [], ls="", marker="D", color="#00bcd4", mec="k", ms=7,
                   label=f"via points ({via.size}, in order)")
        )  # fmt: skip
    ax.plot(sx / 1e3, sy / 1e3, "o", color="lime", ms=9, mec="k", zorder=6)
    ax.plot(ex_ / 1e3, ey_ / 1e3, "*", color="gold", ms=14, mec="k", zorder=6)
    handles += [
        Line2D([], [], ls="", marker="o", color="lime", mec="k", ms=8, label="start"),
        Line2D([], [], ls="", marker="*", color="gold", mec="k", ms=12, label="goal"),
    ]
    if _land(sub.values).any():  # the coastline hillshade_axes draws
        handles.append(Line2D([], [], color="k", lw=0.6, label="coastline"))
    ax.set_aspect("equal")
    return handles + zones


ZONE_COLOUR = "#7b3294"  # keep-out zones: purple, apart from the track's red and the ridges
ZONE_FILL = (0.48, 0.2, 0.58, 0.25)  # the same, translucent


def _keep_out(ax, keep_out, ext) -> list:
    """The keep-out zones within the view (hatched) and their margins (dashed) on ``ax``, the
    view's limits kept; their legend handles."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    if keep_out is None:
        return []
    import shapely

    view = shapely.box(ext[0] * 1e3, ext[2] * 1e3, ext[1] * 1e3, ext[3] * 1e3)
    shown = False
    for _, g in keep_out.zones:
        for part, style in ((g, "zone"), (g.buffer(keep_out.margin_m), "margin")):
            if style == "margin" and not keep_out.margin_m:
                continue
            part = part.intersection(view.buffer(0.05 * view.length))
            for poly in getattr(part, "geoms", [part]):
                if poly.is_empty or poly.geom_type != "Polygon":
                    continue
                shown = True
                x, y = np.asarray(poly.exterior.coords).T / 1e3
                if style == "zone":
                    ax.fill(x, y, fc=ZONE_FILL, ec=ZONE_COLOUR, lw=1.0,
                            hatch="//", zorder=2)  # fmt: skip
                else:
                    ax.plot(x, y, color=ZONE_COLOUR, lw=0.8, ls="--", zorder=2)
    ax.set_xlim(ext[0], ext[1])
    ax.set_ylim(ext[2], ext[3])
    if not shown:
        return []
    handles = [Patch(fc=ZONE_FILL, ec=ZONE_COLOUR, hatch="//", label="keep-out zone")]
    if keep_out.margin_m:
        handles.append(
            Line2D([], [], color=ZONE_COLOUR, lw=0.8, ls="--",
                   label=f"its margin ({keep_out.margin_m:g} m)")
        )  # fmt: skip
    return handles


def _summary_lines(traj) -> list[str]:
    """The mission's figures beside the legend: planner and bound, status, lengths and ridge
    shares, and the flight's duration, pitch, tightest turn and energy."""
    f = traj.flight
    lines = [
        f"planner {traj.planner}, omega {traj.omega:g}",
        f"status: {traj.status}",
        f"grid path {traj.length_m / 1e3:.1f} km, {100 * traj.ridge_ratio:.0f} % ridge",
    ]
    if f is not None:
        v = f.vehicle
        lines += [
            f"flown {f.flown_length_m / 1e3:.1f} km, {100 * f.ridge_ratio:.0f} % ridge",
            f"duration {f.duration_s / 3600:.1f} h at {v.speed_m_s:g} m/s",
            f"max pitch {f.max_pitch_deg:.1f} deg (limit {v.max_pitch_deg:g})",
            f"tightest turn {f.min_turn_radius_m:.0f} m (min {f.turn_radius_m:g})"
            if np.isfinite(f.min_turn_radius_m)
            else "no turn",
        ]
        if f.energy_wh is not None:
            lines.append(f"energy {f.energy_wh:.0f} Wh")
    return lines


def _depth_profile(pr, params, traj) -> None:
    """The depth profile along the flown track on ``pr``: the seabed under it, the lowest safe
    height, the flown height, the waypoint legs and the waypoints (the grid path's heights
    when the mission was not flown)."""
    f = traj.flight
    method, clearance = params.method, params.clearance_m
    if f is not None:
        s = f.s / 1e3
        floor = float(np.nanmin(f.seabed_m)) - 100
        pr.fill_between(
            s, floor, f.seabed_m, color="#8c6d46", alpha=0.8, lw=0, label="seabed under the track"
        )
        pr.plot(
            s,
            f.required_m,
            color="#1f77b4",
            lw=0.8,
            ls="--",
            label=f"lowest safe height ({clearance:g} m clearance, {method})",
        )
        pr.plot(s, f.z, color="#d62728", lw=1.6, label="flown height (lowest within pitch)")
        from scipy.spatial import cKDTree

        # the waypoint legs and each waypoint at the distance of the nearest flown sample
        tree = cKDTree(np.column_stack([f.x, f.y]))
        along = s[tree.query(f.route[:, :2])[1]]
        pr.plot(along, f.route[:, 2], color="k", lw=0.7, alpha=0.8, label="waypoint legs")
        near = tree.query(f.waypoints[:, :2])[1]
        pr.plot(
            s[near],
            f.waypoints[:, 2],
            "o",
            ms=2.5,
            mfc="white",
            mec="k",
            mew=0.5,
            label="waypoints",
        )
        top = max(float(np.nanmax(f.z)), float(np.nanmax(f.route[:, 2])))
        if f.max_depth_m is not None:
            pr.axhline(
                -f.max_depth_m,
                color=ZONE_COLOUR,
                lw=1.0,
                ls="-.",
                label=f"rated depth ({f.max_depth_m:g} m; the limit for "
                f"{f.at_rated_depth_m / 1e3:.1f} km)",
            )
            floor = min(floor, -f.max_depth_m - 100)
        pr.set_ylim(floor, max(top, float(np.nanmax(f.seabed_m))) + 150)
        pr.set_title(
            f"depth profile: clearance {clearance:g} m from the seabed, at and between grid "
            f"points; pitch <= {f.vehicle.max_pitch_deg:g} deg; turns >= {f.turn_radius_m:g} m",
            fontsize=9,
            y=1.0,
        )
    else:
        gs_ = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(traj.points[:, :2], axis=0).T))))
        pr.plot(gs_ / 1e3, traj.points[:, 2], color="0.3", lw=1, label="grid path height")
    pr.set_xlabel("distance along the track (km)")
    pr.set_ylabel("height (m)")
    pr.grid(alpha=0.3)
    pr.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), fontsize=7, frameon=False, ncols=4)
