"""``pipeline verify``: finished missions re-checked against any DEM file (the one planned on,
or a newer or finer survey of the same area), independently of the maps they were planned on
(docs/guide.md, "Verifying a mission").

A mission's waypoint route (its waypoints joined by straight map lines, by geodesics and by rhumb
lines, as autopilots steer) and its flown track are walked in steps of at most a quarter of the
DEM's cell and of the clearance, and at each point
the clearance from the file's own bilinear seabed is measured (:mod:`pipeline.verify.seabed`); the
depth against the vehicle's rating, the distance from each keep-out zone against its margin,
the pitch and the turn radius of the track are checked too. Each check says where it is worst.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._types import PathLike
from ..exceptions import InvalidParameterError
from ..methods import METHODS
from .seabed import TOLERANCE_M, SourceSeabed


@dataclass
class Check:
    """One check of a mission: whether it holds, its worst figure against its limit, and
    where (a sentence)."""

    name: str
    holds: bool
    worst: float
    limit: float
    where: str = ""
    unit: str = "m"

    def line(self) -> str:
        mark = "ok  " if self.holds else "FAIL"
        u = self.unit
        if math.isinf(self.worst):  # (a straight track has no turn; no zone is near)
            return f"  {mark} {self.name}: none (limit {self.limit:g} {u})"
        return f"  {mark} {self.name}: {self.worst:.2f} {u} (limit {self.limit:g} {u}){self.where}"


@dataclass
class Verdict:
    """A mission's checks; ``problem`` when it cannot be verified at all (no track, no CRS)."""

    mission: str
    item: Path
    checks: list[Check] = field(default_factory=list)
    problem: str | None = None

    @property
    def holds(self) -> bool:
        return self.problem is None and all(c.holds for c in self.checks)


def mission_items(target) -> list[Path]:
    """The mission Items of ``target``: an Item's JSON file, a mission folder, a catalog
    folder or its ``catalog.json``."""
    target = Path(target)
    if not target.exists():
        raise InvalidParameterError(
            f"{target} does not exist: give a mission folder, an Item or a catalog"
        )
    if target.is_file():
        doc = _json(target)
        if doc.get("type") == "Feature":
            return [target]
        if doc.get("type") == "Catalog":
            target = target.parent
        else:
            raise InvalidParameterError(
                f"{target} is neither a mission Item nor a catalog.json of this tool's"
            )
    own = target / f"{target.name}.json"
    if own.is_file():
        return [own]
    items = sorted(
        p / f"{p.name}.json"
        for p in (target / "missions").glob("*")
        if (p / f"{p.name}.json").is_file()
    )
    if not items:
        raise InvalidParameterError(
            f"{target} holds no mission: give a mission folder (catalogs/<job>/missions/<id>), "
            "its Item (<id>.json) or a catalog folder"
        )
    return items


def _json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InvalidParameterError(f"cannot read {path} as JSON: {exc}") from None


def verify_missions(
    target: PathLike,
    dem: PathLike | SourceSeabed,
    *,
    variable: str | None = None,
    uncertainty_k: float | None = None,
    clearance: float | None = None,
    method: str | None = None,
    horizontal_clearance: float | None = None,
    max_depth: float | None = None,
    keep_out: PathLike | list[PathLike] | None = None,
    keep_out_margin: float | None = None,
) -> list[Verdict]:
    """Every mission of ``target`` (:func:`mission_items`) checked against the DEM file
    ``dem``; the clearance, method, rating and zones are the mission's own (its Item and its
    ``keep-out.geojson``) unless given."""
    seabed = (
        dem
        if isinstance(dem, SourceSeabed)
        else SourceSeabed.open(dem, variable=variable, uncertainty_k=uncertainty_k)
    )
    extra = None
    if keep_out:
        from ..constraints.zones import read_zone_file

        extra = [
            read_zone_file(p)
            for p in ([keep_out] if isinstance(keep_out, str | Path) else keep_out)
        ]
    out = []
    for item in mission_items(target):
        out.append(
            _verify_one(
                item, seabed, clearance, method, horizontal_clearance, max_depth, extra,
                keep_out_margin,
            )
        )  # fmt: skip
    return out


def _verify_one(item, seabed, clearance, method, horizontal, max_depth, zones, margin) -> Verdict:
    doc = _json(item)
    props = doc.get("properties", {})
    name = props.get("auv:name", item.stem)
    verdict = Verdict(name, item)
    folder = item.parent
    crs_wkt = _crs_of_item(doc)
    track = folder / "track.parquet"
    if not track.is_file():
        verdict.problem = (
            f"no flown track to verify (status {props.get('auv:status', 'unknown')}"
            + (f": {props['auv:message']}" if props.get("auv:message") else "")
            + ")"
        )
        return verdict
    if crs_wkt is None and seabed.crs is not None:
        verdict.problem = "the mission has no CRS (its DEM had none): verify it on that DEM's grid"
        return verdict
    import pandas as pd

    t = pd.read_parquet(track, columns=["x", "y", "z", "s_m"])
    wp = folder / "waypoints.csv"
    route = None
    sea = float(props.get("auv:sea_level_m", 0.0))
    if wp.is_file():  # the waypoints as the vehicle is given them
        route = _waypoints(pd.read_csv(wp), crs_wkt, sea)
    R = float(clearance if clearance is not None else props.get("auv:clearance_m", math.nan))
    how = method or props.get("auv:clearance_method", "spherical")
    if not math.isfinite(R):
        verdict.problem = "the mission does not record its clearance: give --clearance"
        return verdict
    radius = float(horizontal or props.get("auv:horizontal_clearance_m") or R)
    reach = METHODS[how].reach_m(R, radius)
    step = max(min(R / 4.0, seabed.cell_m() / 4.0), 0.05)
    lines = {"track": t[["x", "y", "z"]].to_numpy(dtype=np.float64)}
    if route is not None:
        lines["waypoint route"] = route
        if crs_wkt and len(route) > 1:  # as an autopilot may steer between the waypoints
            lines.update(_autopilot_routes(route, crs_wkt, step))
    worst = (math.inf, "")
    unknown = 0
    for label, pts in lines.items():
        x, y, z, s = _walk(pts, step)
        c = seabed.clearances(x, y, z, crs_wkt, reach, how, least_only=True)
        unknown += int(np.isnan(c).sum())
        if np.isfinite(c).any():
            k = int(np.nanargmin(c))
            if c[k] < worst[0]:
                worst = (
                    float(c[k]),
                    f" at {s[k] / 1e3:.3f} km along the {label}{_lonlat(crs_wkt, x[k], y[k])}",
                )
    holds = worst[0] >= R - TOLERANCE_M and unknown == 0
    where = worst[1]
    if unknown:
        where += f"; {unknown} points lie off the DEM or over its no-data (not verified there)"
    verdict.checks.append(
        Check(f"clearance from {seabed.path.name} ({how})", holds, worst[0], R, where)
    )
    rating = max_depth if max_depth is not None else props.get("auv:max_depth_m")
    if rating is not None:
        deepest = (-math.inf, "")
        for label, pts in lines.items():
            k = int(np.argmin(pts[:, 2]))
            d = sea - float(pts[k, 2])
            if d > deepest[0]:
                deepest = (d, f" on the {label}{_lonlat(crs_wkt, pts[k, 0], pts[k, 1])}")
        verdict.checks.append(
            Check(
                "depth against the rating",
                deepest[0] <= float(rating) + 1e-6,
                deepest[0],
                float(rating),
                deepest[1],
            )
        )
    _zones_check(verdict, folder, crs_wkt, lines, zones, margin)
    vehicle = props.get("auv:vehicle") or {}
    xyz = lines["track"]
    if len(xyz) > 1 and "max_pitch_deg" in vehicle:
        ds = np.hypot(np.diff(xyz[:, 0]), np.diff(xyz[:, 1]))
        pitch = np.degrees(np.arctan2(np.abs(np.diff(xyz[:, 2])), ds))
        k = int(np.argmax(pitch))
        lim = float(vehicle["max_pitch_deg"])
        verdict.checks.append(
            Check("pitch", pitch[k] <= lim + 0.01, float(pitch[k]), lim,
                  f" at {t['s_m'].iloc[k] / 1e3:.3f} km along the track", "deg")
        )  # fmt: skip
    if len(xyz) > 2 and vehicle.get("min_turn_radius_m"):
        r = _circumradii(xyz[:, 0], xyz[:, 1])
        k = int(np.argmin(r))
        lim = float(vehicle["min_turn_radius_m"])
        verdict.checks.append(
            Check("turn radius", r[k] >= lim * (1 - 1e-3), float(r[k]), lim,
                  f" at {t['s_m'].iloc[k + 1] / 1e3:.3f} km along the track")
        )  # fmt: skip
    return verdict


def _autopilot_routes(route: np.ndarray, crs_wkt: str, step: float) -> dict:
    """The waypoint route along the geodesic and along the rhumb line of each leg (pyproj;
    heights linear along the leg), in steps of at most ``step``: ``{"geodesic route": xyz,
    "rhumb-line route": xyz}``."""
    from ..flight.legs import leg_lines

    out: dict = {"geodesic route": [], "rhumb-line route": []}
    for k in range(len(route) - 1):
        (x0, y0, z0), (x1, y1, z1) = route[k], route[k + 1]
        f = np.linspace(0.0, 1.0, int(math.ceil(math.hypot(x1 - x0, y1 - y0) / step)) + 2)
        z = z0 + (z1 - z0) * f
        steered = leg_lines(crs_wkt, x0, y0, x1, y1, f)
        for name, key in (("geodesic route", "geodesic"), ("rhumb-line route", "rhumb line")):
            lx, ly = steered[key]
            out[name].append(np.column_stack([lx.ravel(), ly.ravel(), z]))
    return {name: np.vstack(parts) for name, parts in out.items()}


def _waypoints(w, crs_wkt, sea: float) -> np.ndarray:
    """The waypoints of a ``waypoints.csv`` (lat, lon or x_m, y_m; depth) as map x, y, z."""
    if "lat" in w.columns:
        from pyproj import CRS, Transformer

        tr = Transformer.from_crs("EPSG:4326", CRS.from_wkt(crs_wkt), always_xy=True)
        x, y = tr.transform(w["lon"].to_numpy(), w["lat"].to_numpy())
    else:
        x, y = w["x_m"].to_numpy(), w["y_m"].to_numpy()
    z = sea - w["depth_m"].to_numpy(dtype=np.float64)
    return np.column_stack([x, y, z]).astype(np.float64)


def _zones_check(verdict, folder, crs_wkt, lines, zones, margin) -> None:
    """The distance of the route and the track from each keep-out zone against its margin:
    the mission's own zones (``keep-out.geojson``) and any given."""
    from shapely.geometry import LineString

    frames = list(zones or [])
    own = folder / "keep-out.geojson"
    own_margin = None
    if own.is_file():
        from ..constraints.zones import read_zone_file

        frame = read_zone_file(own)
        frames.append(frame)
        if "margin_m" in frame.columns and len(frame):
            own_margin = float(frame["margin_m"].iloc[0])
    if not frames:
        return
    m = float(margin if margin is not None else own_margin if own_margin is not None else 0.0)
    shapes = []
    for frame in frames:
        f = frame.to_crs(crs_wkt) if frame.crs is not None and crs_wkt else frame
        for k, g in enumerate(f.geometry):
            label = str(f["name"].iloc[k]) if "name" in f.columns else f"zone {k + 1}"
            shapes.append((label, g))
    near, inside = (math.inf, ""), False
    for label, pts in lines.items():
        line = LineString(pts[:, :2])
        for zname, g in shapes:
            d = float(line.distance(g))
            if d < near[0]:
                near = (d, f": {zname}, from the {label}")
            if line.intersects(g):  # (in a zone is never kept, whatever the margin)
                inside = True
                near = (0.0, f": the {label} enters {zname}")
    holds = not inside and near[0] >= m - 1e-6
    verdict.checks.append(Check("keep-out margin", holds, near[0], m, near[1]))


def source_clearance(seabed: SourceSeabed, flight, maps) -> float:
    """The least clearance of a flight (its waypoint route and its track) from the DEM file's
    own seabed, by the maps' method and clearance: the figure a mission reports
    (``auv:min_clearance_m``). NaN where a point lies off the file or over its no-data."""
    par = maps.parameters
    step = max(min(par.clearance_m / 4.0, seabed.cell_m() / 4.0), 0.05)
    least = math.inf
    for pts in (np.column_stack([flight.x, flight.y, flight.z]), flight.route):
        x, y, z, _ = _walk(np.asarray(pts, dtype=np.float64), step)
        c = seabed.clearances(x, y, z, maps.crs_wkt, par.reach_m, par.method, least_only=True)
        if np.isnan(c).any():
            return math.nan
        least = min(least, float(c.min()))
    return least


def _walk(pts: np.ndarray, step: float) -> tuple:
    """The polyline ``pts`` (x, y, z) walked in steps of at most ``step`` horizontally (its
    height linear between its points), and each point's distance along it."""
    d = np.hypot(np.diff(pts[:, 0]), np.diff(pts[:, 1]))
    n = np.maximum(np.ceil(d / step).astype(np.int64), 1)
    idx = np.repeat(np.arange(len(d)), n)
    frac = np.concatenate([np.arange(k) / k for k in n]) if len(n) else np.zeros(0)
    x = np.append(pts[idx, 0] + frac * (pts[idx + 1, 0] - pts[idx, 0]), pts[-1, 0])
    y = np.append(pts[idx, 1] + frac * (pts[idx + 1, 1] - pts[idx, 1]), pts[-1, 1])
    z = np.append(pts[idx, 2] + frac * (pts[idx + 1, 2] - pts[idx, 2]), pts[-1, 2])
    s = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))))
    return x, y, z, s


def _circumradii(x, y) -> np.ndarray:
    """The radius of the circle through each three consecutive points (inf where straight)."""
    ax, ay, bx, by, cx, cy = x[:-2], y[:-2], x[1:-1], y[1:-1], x[2:], y[2:]
    ab, bc, ca = np.hypot(bx - ax, by - ay), np.hypot(cx - bx, cy - by), np.hypot(ax - cx, ay - cy)
    cross = np.abs((bx - ax) * (cy - ay) - (by - ay) * (cx - ax))
    with np.errstate(divide="ignore", invalid="ignore"):
        r = ab * bc * ca / (2.0 * cross)
    # a straight run (its turn below a millionth of a radian) is no turn
    straight = cross <= 1e-6 * ab * bc
    return np.where(straight | ~np.isfinite(r), np.inf, r)


def _crs_of_item(doc: dict) -> str | None:
    props = doc.get("properties", {})
    code, wkt2 = props.get("proj:code") or props.get("proj:epsg"), props.get("proj:wkt2")
    if wkt2:
        return wkt2
    if code:
        from pyproj import CRS

        return CRS.from_user_input(code if isinstance(code, str) else f"EPSG:{code}").to_wkt()
    return None


def _lonlat(crs_wkt, x, y) -> str:
    if not crs_wkt:
        return f" (x {x:.1f}, y {y:.1f})"
    from ..outputs.files import to_lonlat

    lon, lat = to_lonlat(crs_wkt, np.array([x]), np.array([y]))
    la, lo = float(lat[0]), float(lon[0])
    return f" ({abs(la):.5f} {'N' if la >= 0 else 'S'}, {abs(lo):.5f} {'E' if lo >= 0 else 'W'})"


def report(verdicts: list[Verdict]) -> str:
    """The verdicts as lines: each mission's result and its checks."""
    lines = []
    for v in verdicts:
        if v.problem:
            lines.append(f"{v.mission}: NOT VERIFIED: {v.problem}")
            continue
        lines.append(f"{v.mission}: {'holds' if v.holds else 'FAILS'}")
        lines.extend(c.line() for c in v.checks)
    held = sum(v.holds for v in verdicts)
    lines.append(f"{held} of {len(verdicts)} missions hold")
    return "\n".join(lines)
