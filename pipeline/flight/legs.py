"""Legs any autopilot flies the same way (docs/flyable-missions.md, "Legs"): between two waypoints
an autopilot steers along the straight map line, the geodesic or the rhumb line, and on a long
leg these part by kilometres. The waypoints are made close enough that the three lie within
:func:`leg_tolerance` of each other (and no leg is longer than the vehicle's ``max_leg_m``), and
the geodesic and the rhumb line of each leg are given to the flight's checks.
"""

from __future__ import annotations

import functools

import numpy as np

# the most the map line, the geodesic and the rhumb line of a leg may part (metres), and the
# share of the clearance
LEG_DEVIATION_M = 5.0


LEG_DEVIATION_SHARE = 1.0 / 20.0


# where each leg's lines are measured: at these fractions of it
_FRACTIONS = np.linspace(0.0, 1.0, 17)[1:-1]


def leg_tolerance(clearance_m: float) -> float:
    """How far the three lines of a leg may part: min(5 m, R/20)."""
    return min(LEG_DEVIATION_M, LEG_DEVIATION_SHARE * clearance_m)


@functools.lru_cache(maxsize=8)
def _transformers(crs_wkt: str):
    from pyproj import CRS, Geod, Transformer

    crs = CRS.from_wkt(crs_wkt)
    to_ll = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    from_ll = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    merc = "+proj=merc +datum=WGS84 +units=m +no_defs"
    to_merc = Transformer.from_crs("EPSG:4326", merc, always_xy=True)
    from_merc = Transformer.from_crs(merc, "EPSG:4326", always_xy=True)
    return to_ll, from_ll, to_merc, from_merc, Geod(ellps="WGS84")


def leg_lines(crs_wkt: str, x0, y0, x1, y1, fractions) -> dict:
    """The points at ``fractions`` (k,) of each leg ``(x0, y0) -> (x1, y1)`` (n,) along the
    geodesic and along the rhumb line between its ends, in map coordinates: ``{"geodesic":
    (x, y), "rhumb line": (x, y)}``, each (n, k)."""
    x0 = np.atleast_1d(np.asarray(x0, dtype=np.float64))
    f = np.asarray(fractions, dtype=np.float64).ravel()
    n, k = x0.size, f.size
    points = leg_points(crs_wkt, x0, y0, x1, y1, np.repeat(np.arange(n), k), np.tile(f, n))
    return {name: (x.reshape(n, k), y.reshape(n, k)) for name, (x, y) in points.items()}


def leg_points(crs_wkt: str, x0, y0, x1, y1, leg, fractions) -> dict:
    """The point at ``fractions[p]`` of leg ``leg[p]`` (each (p,)) of the legs ``(x0, y0) ->
    (x1, y1)`` (n,) along the geodesic and along the rhumb line between its ends, in map
    coordinates: ``{"geodesic": (x, y), "rhumb line": (x, y)}``, each (p,): the points of many
    legs, each at fractions of its own, in one pass of pyproj."""
    to_ll, from_ll, to_merc, from_merc, geod = _transformers(crs_wkt)
    x0, y0, x1, y1 = (np.atleast_1d(np.asarray(v, dtype=np.float64)) for v in (x0, y0, x1, y1))
    lon0, lat0 = to_ll.transform(x0, y0)
    lon1, lat1 = to_ll.transform(x1, y1)
    lon0, lat0, lon1, lat1 = (
        np.atleast_1d(np.asarray(v, dtype=np.float64)) for v in (lon0, lat0, lon1, lat1)
    )
    az, _, dist = geod.inv(lon0, lat0, lon1, lat1)
    leg = np.asarray(leg, dtype=np.int64)
    f = np.asarray(fractions, dtype=np.float64)
    glon, glat, _ = geod.fwd(lon0[leg], lat0[leg], np.asarray(az)[leg], np.asarray(dist)[leg] * f)
    mx0, my0 = (np.asarray(v) for v in to_merc.transform(lon0, lat0))
    mx1, my1 = (np.asarray(v) for v in to_merc.transform(lon1, lat1))
    rlon, rlat = from_merc.transform(
        mx0[leg] + (mx1 - mx0)[leg] * f, my0[leg] + (my1 - my0)[leg] * f
    )
    gx, gy = from_ll.transform(glon, glat)
    rx, ry = from_ll.transform(rlon, rlat)
    return {
        "geodesic": (np.asarray(gx, dtype=np.float64), np.asarray(gy, dtype=np.float64)),
        "rhumb line": (np.asarray(rx, dtype=np.float64), np.asarray(ry, dtype=np.float64)),
    }


def deviation(crs_wkt: str, x0, y0, x1, y1) -> np.ndarray:
    """How far (metres, map coordinates) each leg's geodesic or rhumb line strays from its
    straight map line, at :data:`_FRACTIONS` of it."""
    x0, y0, x1, y1 = (np.atleast_1d(np.asarray(v, dtype=np.float64)) for v in (x0, y0, x1, y1))
    lines = leg_lines(crs_wkt, x0, y0, x1, y1, _FRACTIONS)
    out = np.zeros(x0.size)
    dx, dy = (x1 - x0)[:, None], (y1 - y0)[:, None]
    ll = np.maximum(dx * dx + dy * dy, 1e-300)
    for px, py in lines.values():
        t = np.clip(((px - x0[:, None]) * dx + (py - y0[:, None]) * dy) / ll, 0.0, 1.0)
        d = np.hypot(px - (x0[:, None] + t * dx), py - (y0[:, None] + t * dy))
        out = np.maximum(out, np.where(np.isfinite(d), d, np.inf).max(axis=1))
    return out


def split_legs(
    crs_wkt: str | None, x, y, wi, tol: float, max_leg: float | None, deviations: bool = False
):
    """The waypoint indices ``wi`` into the route's samples ``x, y`` (map coordinates) with
    more of them, each leg halved at its middle sample until its map line, geodesic and rhumb
    line lie within ``tol`` of each other (with a CRS) and it is no longer than ``max_leg``;
    a leg of two samples is not split further. With ``deviations``, also each leg's
    :func:`deviation` (zeros without a CRS), each leg's computed once."""
    wi = np.asarray(wi, dtype=np.int64)
    unknown = np.nan if crs_wkt else 0.0  # a leg's deviation to compute (none without a CRS)
    dev = np.full(max(wi.size - 1, 0), unknown)
    for _ in range(64):
        a, b = wi[:-1], wi[1:]
        new = np.isnan(dev)
        if new.any():
            dev[new] = deviation(crs_wkt, x[a[new]], y[a[new]], x[b[new]], y[b[new]])
        bad = dev > tol
        if max_leg is not None:
            bad |= np.hypot(x[b] - x[a], y[b] - y[a]) > max_leg
        bad &= b - a >= 2
        if not bad.any():
            break
        # each leg split in two: its halves' deviations to be computed
        keep = np.repeat(dev, np.where(bad, 2, 1))
        keep[np.repeat(bad, np.where(bad, 2, 1))] = unknown
        wi = np.unique(np.concatenate([wi, (a[bad] + b[bad]) // 2]))
        dev = keep
    return (wi, dev) if deviations else wi
