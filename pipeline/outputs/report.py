"""The catalog's report: ``index.html`` at the catalog's root, a page that opens with no
network (from a USB stick, on a ship), in any current browser.

What it shows, read from the catalog's own files (so it can be written again at any time):

- a map (Leaflet, pan and zoom) of every mission's flown track over a hillshade of the DEM, in
  the maps' own coordinates (kilometres), coloured by mission, with start, goal and waypoints;
  clicking a track opens its properties;
- per mission: its properties, the depth profile along the flown track (seabed, the lowest safe
  height, the flown height) and links to every file the catalog holds for it;
- a sortable table of all missions, failed ones with their reasons.

Layout: ``index.html`` (Leaflet's script and style inlined, the missions' data as JSON inside
it) and ``report/hillshade.png`` beside it; the mission files are linked where they are. The
page's template, style and script are ``pipeline/outputs/static/report.{html,css,js}``;
Leaflet 1.9.4 ships with the package (``pipeline/outputs/static/leaflet``, BSD 2-Clause).
"""

from __future__ import annotations

import csv
import datetime as _dt
import functools
import html
import json
import logging
import math
from pathlib import Path

import numpy as np

from ..store.paths import write_atomically
from .catalog import COLLECTION, finished, properties

log = logging.getLogger(__name__)

STATIC = Path(__file__).parent / "static"  # the page, its style and script
LEAFLET = STATIC / "leaflet"
HILLSHADE_SIDE = 1600  # the hillshade picture's longer side at most, in pixels
TRACK_POINTS = 1500  # points per track on the map and in the profile at most
PALETTE = (
    "#e41a1c",
    "#377eb8",
    "#4daf4a",
    "#984ea3",
    "#ff7f00",
    "#a65628",
    "#f781bf",
    "#17becf",
    "#bcbd22",
    "#6a3d9a",
)


def write_report(root, maps=None, *, title: str, mission_names: list[str]) -> Path:
    """Write ``index.html`` (and ``report/hillshade.png``, :func:`hillshade`) at the catalog
    ``root`` from the Items and files of the missions ``mission_names``; ``maps`` (a
    :class:`MapsStore`, or None) gives the hillshade and the coordinate system. Returns the
    page's path."""
    root = Path(root)
    crs_wkt = getattr(maps, "crs_wkt", None)
    data = {
        "title": title,
        "written": _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "hillshade": hillshade(root, maps),
        "missions": [],
        "performance_report": (root / "performance-report.html").exists(),
    }
    for k, name in enumerate(mission_names):
        item = finished(root, name)
        if item is None:
            continue
        data["missions"].append(_mission(root, item, k, crs_wkt))
    page = _page(data)
    return write_atomically(root / "index.html", page)


# --------------------------------------------------------------------------- data

# the picture's drawing: a hillshade kept from an earlier run is drawn again when this changes
HILLSHADE_VERSION = 1


def hillshade(root, maps) -> dict | None:
    """``report/hillshade.png`` under the catalog ``root``, the hillshade of the maps store
    ``maps`` (a :class:`MapsStore`; None: no picture), and what the page needs of it (extent,
    colour scale). Drawn once per maps store: ``report/hillshade.json`` notes the store it was
    drawn from (its path, shape, coordinates and signature, which covers the DEM's hash), and a
    later run on the same store reuses both files (drawing it imports matplotlib and shades up
    to ``HILLSHADE_SIDE``^2 pixels: over a second in a new process). A store without a signature
    (built before it had one) is drawn every time."""
    if maps is None:
        return None
    side = Path(root) / "report"
    side.mkdir(parents=True, exist_ok=True)
    png, note = side / "hillshade.png", side / "hillshade.json"
    signature = getattr(maps, "signature", None)
    key = {
        "version": HILLSHADE_VERSION,
        "side": HILLSHADE_SIDE,
        "maps": str(maps.path),
        "shape": list(maps.shape),
        "x": [float(maps.x[0]), float(maps.x[-1])],
        "y": [float(maps.y[0]), float(maps.y[-1])],
        "signature": signature,
    }
    if signature is not None and png.exists():
        try:
            kept = json.loads(note.read_text())
            if kept.get("key") == key:
                return kept["hillshade"]
        except (OSError, ValueError, KeyError):
            pass  # missing or unreadable: drawn again
    note.unlink(missing_ok=True)  # never beside a picture it does not describe
    data = _hillshade(maps, png)
    if signature is not None:
        write_atomically(note, json.dumps({"key": key, "hillshade": data}))
    return data


def _hillshade(maps, png: Path) -> dict:
    """The DEM hillshaded (:func:`pipeline.outputs.plots.shaded_relief`), north up, at most
    ``HILLSHADE_SIDE`` pixels a side; its extent in map metres and its colour scale."""
    import matplotlib.pyplot as plt

    from .plots import RELIEF_CMAP, plan_layers, shaded_relief

    rows, cols = maps.shape
    # the store's overview (made once, kept in the store) on large maps, not a read of the
    # whole elevation layer at every run
    sub, _ = plan_layers(maps, 0, rows, 0, cols, max(rows, cols) / HILLSHADE_SIDE)
    z = np.asarray(sub.values, dtype=np.float64)
    if maps.y[0] < maps.y[-1]:  # rows run south to north: draw north up
        z = z[::-1]
    rgb, vmin, vmax = shaded_relief(z, float(sub.attrs["cell_size"]))
    from PIL import Image

    pixels = (np.clip(rgb[..., :3], 0, 1) * 255 + 0.5).astype(np.uint8)
    image = Image.fromarray(pixels, "RGB")
    # compression level 6 took several times as long as level 3
    write_atomically(png, write=lambda tmp: image.save(tmp, compress_level=3), suffix=".png")
    a = maps.cell_size
    cmap = plt.get_cmap(RELIEF_CMAP)
    stops = [
        "#{:02x}{:02x}{:02x}".format(*(int(round(255 * c)) for c in cmap(t)[:3]))
        for t in np.linspace(0, 1, 11)
    ]
    return {
        "href": f"report/{png.name}",
        "extent": [
            float(min(maps.x[0], maps.x[-1]) - a / 2),
            float(min(maps.y[0], maps.y[-1]) - a / 2),
            float(max(maps.x[0], maps.x[-1]) + a / 2),
            float(max(maps.y[0], maps.y[-1]) + a / 2),
        ],
        "vmin": vmin,
        "vmax": vmax,
        "stops": stops,
    }


# the results the page shows (:func:`catalog.properties`' names); a mission that failed or was
# not flown lacks some, shown blank
_SHOWN = (
    "status",
    "planner",
    "omega",
    "length_m",
    "lower_bound_m",
    "certified_ratio",
    "flown_length_m",
    "ridge_ratio",
    "flown_ridge_ratio",
    "duration_s",
    "waypoints",
    "min_clearance_m",
    "altitude_median_m",
    "altitude_p90_m",
    "vertical_reversals_per_km",
    "max_pitch_deg",
    "energy_wh",
    "runtime_s",
)


def _mission(root: Path, item: dict, k: int, crs_wkt: str | None) -> dict:
    mid = item["id"]
    folder = root / COLLECTION / mid
    m = {
        **dict.fromkeys(_SHOWN),  # what a failed mission's Item lacks, as null
        **properties(item),
        "id": mid,
        "colour": PALETTE[k % len(PALETTE)],
        "files": [{"href": f"{COLLECTION}/{mid}/{mid}.json", "title": "STAC Item (JSON)"}],
        "track": None,
        "profile": None,
        "waypoint_xy": [],
        "zones": [],
    }
    m["name"] = m.get("name") or mid
    m["message"] = m.get("message") or ""
    for key, asset in sorted(item.get("assets", {}).items()):
        href = asset["href"][2:] if asset["href"].startswith("./") else asset["href"]
        m["files"].append(
            {"href": f"{COLLECTION}/{mid}/{href}", "title": asset.get("title") or key}
        )
    try:
        _drawn(m, folder, item, crs_wkt)
    except Exception as exc:  # noqa: BLE001 - pyarrow, csv, pyproj: a damaged file each
        # the report is drawn without what cannot be read, and says so (a re-run plans a
        # mission whose files changed again)
        what = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        log.warning("report: mission %s: a file cannot be read (%s)", m["name"], what)
        m["track"], m["profile"], m["waypoint_xy"] = None, None, []
        m["message"] = (m["message"] + "; " if m["message"] else "") + (
            f"its files cannot be read ({type(exc).__name__}: {what}); plan it again (remove "
            "its folder, or run the job with --overwrite)"
        )
    return m


def _drawn(m: dict, folder: Path, item: dict, crs_wkt: str | None) -> None:
    """``m``'s track, profile and waypoints from the mission's files: the flown track, else
    the grid path on the safety surface (planned, not flown); only files its Item lists."""
    listed = {str(a.get("href", "")).removeprefix("./") for a in item.get("assets", {}).values()}
    track = folder / "track.parquet"
    grid = folder / "grid-path.parquet"
    if track.name in listed:
        t = _columns(track, ("x", "y", "z", "seabed_m", "required_m", "s_m"))
        m["track"] = _thin_xy(t["x"], t["y"])
        m["profile"] = _profile(t["s_m"], t["seabed_m"], t["required_m"], t["z"])
    elif grid.name in listed:
        t = _columns(grid, ("x", "y", "z"))
        s = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(t["x"]), np.diff(t["y"])))))
        m["track"] = _thin_xy(t["x"], t["y"])
        m["profile"] = _profile(s, None, t["z"], None)
    wpt = folder / "waypoints.csv"
    if wpt.name in listed:
        m["waypoint_xy"] = _waypoints(wpt, crs_wkt)
    zones = folder / "keep-out.geojson"
    if zones.name in listed and crs_wkt:
        m["zones"] = _zones(zones, crs_wkt)


def _zones(path: Path, crs_wkt: str) -> list:
    """The keep-out zones' outer rings in map coordinates, from the mission's GeoJSON file
    (longitude and latitude projected back to the maps' coordinate system)."""
    tr = _to_map(crs_wkt)
    rings = []
    for feat in json.loads(path.read_text())["features"]:
        geom = feat["geometry"]
        polys = [geom["coordinates"]] if geom["type"] == "Polygon" else geom["coordinates"]
        for poly in polys:
            lon, lat = np.asarray(poly[0], dtype=np.float64).T[:2]
            x, y = tr.transform(lon, lat)
            rings.append(
                {"name": feat["properties"].get("name"), "ring": np.c_[x, y].round(1).tolist()}
            )
    return rings


def _columns(path: Path, names) -> dict:
    import pyarrow.parquet as pq

    table = pq.read_table(path, columns=list(names))
    return {n: np.asarray(table.column(n).to_numpy(), dtype=np.float64) for n in names}


def _buckets(n: int) -> np.ndarray:
    """Bucket starts that cut ``n`` samples into at most ``TRACK_POINTS`` runs."""
    return np.unique(np.linspace(0, n, min(n, TRACK_POINTS) + 1).astype(int))[:-1]


def _thin_xy(x, y) -> list:
    """A track thinned to at most ``TRACK_POINTS`` points (every k-th, the last kept)."""
    idx = np.unique(np.append(_buckets(len(x)), len(x) - 1))
    return [[round(float(x[i]), 2), round(float(y[i]), 2)] for i in idx]


def _profile(s, seabed, required, z) -> dict:
    """The profile thinned to at most ``TRACK_POINTS`` runs, without hiding a close pass: per
    run the highest seabed and safe height and the lowest flown height."""
    starts = _buckets(len(s))

    def red(v, how):
        if v is None:
            return None
        v = np.asarray(v, dtype=np.float64)
        out = how.reduceat(v, starts)
        return [round(float(u), 2) if math.isfinite(u) else None for u in out]

    return {
        "s_km": [round(float(v) / 1e3, 4) for v in np.asarray(s)[starts]] + [float(s[-1]) / 1e3],
        "seabed": _end(red(seabed, np.fmax), seabed),
        "required": _end(red(required, np.fmax), required),
        "flown": _end(red(z, np.fmin), z),
    }


def _end(values, full):
    """``values`` with the last sample appended (the profile reaches the goal)."""
    if values is None:
        return None
    last = float(np.asarray(full)[-1])
    return values + [round(last, 2) if math.isfinite(last) else None]


@functools.lru_cache(maxsize=8)
def _to_map(crs_wkt: str):
    """The transformer from WGS84 longitude and latitude to the maps' coordinates (one for
    every mission of a report)."""
    from pyproj import CRS, Transformer

    return Transformer.from_crs("EPSG:4326", CRS.from_wkt(crs_wkt), always_xy=True)


def _waypoints(path: Path, crs_wkt: str | None) -> list:
    """The waypoints in map coordinates: the CSV's x_m, y_m, or its lat, lon projected back
    to the maps' coordinate system."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        return []
    if "x_m" in rows[0]:
        return [[float(r["x_m"]), float(r["y_m"])] for r in rows]
    if not crs_wkt:
        return []
    x, y = _to_map(crs_wkt).transform(
        [float(r["lon"]) for r in rows], [float(r["lat"]) for r in rows]
    )
    return [[round(float(a), 2), round(float(b), 2)] for a, b in zip(x, y, strict=True)]


# --------------------------------------------------------------------------- the page


def _clean(v):
    """JSON without NaN or infinity (None instead)."""
    if isinstance(v, dict):
        return {k: _clean(u) for k, u in v.items()}
    if isinstance(v, list | tuple):
        return [_clean(u) for u in v]
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, np.generic):
        return _clean(v.item())
    return v


# what the data inlined in the page may not hold as itself: "<" and ">" (no "</script" closes
# the element and no "<!--" turns the parser to the escaped state where it would not close),
# "&", and the two line separators older scripts read as line ends; JSON's own escapes stand
# for them, as each string still means
_SCRIPT_ESCAPES = {
    "<": "\\u003c",
    ">": "\\u003e",
    "&": "\\u0026",
    "\u2028": "\\u2028",
    "\u2029": "\\u2029",
}


def _script_json(data) -> str:
    """``data`` as JSON safe to inline in an HTML script element (:data:`_SCRIPT_ESCAPES`)."""
    text = json.dumps(data, allow_nan=False, separators=(",", ":"))
    for raw, escaped in _SCRIPT_ESCAPES.items():
        text = text.replace(raw, escaped)
    return text


def _page(data: dict) -> str:
    """The page: ``static/report.html`` with Leaflet, the report's style and script
    (``static/report.css``, ``static/report.js``) and the data inlined."""
    payload = _script_json(_clean(data))

    def read(path: Path) -> str:
        return path.read_text(encoding="utf-8")

    leaflet = read(LEAFLET / "leaflet.js").replace("//# sourceMappingURL=leaflet.js.map", "")
    return (
        read(STATIC / "report.html")
        .replace("__TITLE__", html.escape(data["title"]))
        .replace("/*__LEAFLET_CSS__*/", read(LEAFLET / "leaflet.css"))
        .replace("/*__STYLE__*/", read(STATIC / "report.css"))
        .replace("__DATA__", payload)
        .replace("/*__LEAFLET_JS__*/", leaflet)  # no request for its source map
        .replace("/*__APP__*/", read(STATIC / "report.js"))
    )
