"""Keep-out zones: areas a mission's route and flown track never enter (cable corridors,
wrecks, protected areas, another vehicle's box), each kept at a margin.

Zones come from vector files geopandas reads (GeoJSON, GeoPackage, Shapefile; polygons in any
CRS, reprojected to the maps'), from a GeoDataFrame, or as shapely polygons in the maps'
coordinates. :class:`KeepOut` holds them in the maps' CRS; a
:class:`pipeline.constraints.store.ConstrainedStore` is a maps store whose passable layer has the
cells near a zone removed, which every stage reads as it reads a store: the planners'
windows, the coarse level, the endpoints' checks, the flight's corridor.

The cells removed are those whose closed square comes within ``margin + a / 4`` of a zone
(``a`` the cell side): the grid path, a polyline through the centres of cells each a step from
the last, lies in the squares of its cells, so it keeps the margin; the flight's straight legs
are walked in samples at most ``a / 2.8`` apart over cells that are not removed, so every
point of a leg is within ``a / 5.6`` of such a cell and keeps the margin too. The flown track
(the legs with their turns rounded) is checked against the zones themselves (shapely), and a
smoothing that enters one is not used (docs/flyable-missions.md). Removing cells only
shortens no path: the store's landmark bound stays a lower bound on the shortest path that
avoids the zones, so the certificate holds as it is (docs/certified-bound.md).

A goal that zones cut off is proven unreachable at once when the region round it (or round the
start) closes within :data:`pipeline.constraints.store.POCKET_SIDES` cells: the regions are labelled
as the store's components are (4-connectivity, docs/method.md section 9). Otherwise an
exhaustive search of the whole map proves it.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..exceptions import InvalidParameterError, notice

log = logging.getLogger(__name__)

# the cells removed reach this share of a cell beyond the margin (the module's description)
SLACK = 0.25
# GEOS's prepared geometries are not thread-safe (libgeos/geos#825): the sections' threads
# test cells against one at a time (a segfault otherwise, seen with the sections of a mission
# on threads)
_PREPARED = threading.Lock()


@dataclass(frozen=True, eq=False)
class KeepOut:
    """Keep-out zones in the maps' coordinates: ``zones`` a tuple of ``(name, polygon)`` (a
    shapely Polygon or MultiPolygon each), kept at ``margin_m`` metres."""

    zones: tuple
    margin_m: float = 0.0

    def __repr__(self) -> str:
        return f"KeepOut({len(self.zones)} zones, margin {self.margin_m:g} m)"

    @property
    def names(self) -> list[str]:
        return [name for name, _ in self.zones]

    @functools.cached_property
    def kept(self):
        """Every zone grown by the margin, as one geometry: what the route never enters."""
        import shapely

        return shapely.union_all([g.buffer(self.margin_m) for _, g in self.zones])

    def _grown(self, a: float):
        """The zones grown by the margin and ``SLACK`` cells of side ``a``, prepared."""
        return self._shapes(a)[0]

    @functools.lru_cache(maxsize=4)  # noqa: B019 - one object per mission, a few cell sides
    def _shapes(self, a: float) -> tuple:
        """For cells of side ``a``: the zones grown by the margin and ``SLACK`` cells
        (prepared), and its separate parts, each as ``(part, its bounds, the part grown by
        three quarters of a cell: it holds the centre of every cell the part meets, the part
        shrunk by as much: a cell whose centre it holds lies inside the part)``, all prepared:
        a window is tested against the parts that come near it only."""
        import shapely

        g = self.kept.buffer(SLACK * a)
        shapely.prepare(g)
        parts = []
        for part in getattr(g, "geoms", [g]):
            if part.is_empty:
                continue
            part = shapely.Polygon(part.exterior, part.interiors)  # a geometry of its own
            shapely.prepare(part)
            # a cell whose square meets the part has its centre within half a diagonal of it
            near, inner = part.buffer(0.75 * a), part.buffer(-0.75 * a)
            shapely.prepare(near)
            shapely.prepare(inner)
            parts.append((part, part.bounds, near, inner))
        return g, parts

    def near(self, xs: np.ndarray, ys: np.ndarray, a: float) -> bool:
        """Whether any zone's removed cells may lie in the window of column centres ``xs``
        and row centres ``ys`` (their bounds meet)."""
        h = 0.5 * a
        wx0, wx1 = float(np.min(xs)) - h, float(np.max(xs)) + h
        wy0, wy1 = float(np.min(ys)) - h, float(np.max(ys)) + h
        return any(
            x0 <= wx1 and wx0 <= x1 and y0 <= wy1 and wy0 <= y1
            for _, (x0, y0, x1, y1), _, _ in self._shapes(a)[1]
        )

    def zone_at(self, x: float, y: float) -> str | None:
        """The name of a zone whose kept area (the zone and its margin) holds the point."""
        import shapely

        p = shapely.Point(x, y)
        for name, g in self.zones:
            if g.distance(p) <= self.margin_m:
                return name
        return None

    def blocked_at(self, x: np.ndarray, y: np.ndarray, a: float) -> np.ndarray:
        """Which cells centred at ``(x, y)`` (side ``a``) are removed (:meth:`blocked`'s rule,
        exactly, for a few cells)."""
        import shapely

        x, y, h = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64), 0.5 * a
        boxes = shapely.box(x - h, y - h, x + h, y + h)
        with _PREPARED:
            return shapely.intersects(self._grown(a), boxes)

    def blocked(self, xs: np.ndarray, ys: np.ndarray, a: float) -> np.ndarray:
        """Which cells of the window whose column centres are ``xs`` and row centres ``ys``
        (square cells of side ``a``) are removed: their closed square meets a zone grown by
        the margin and ``SLACK * a``. Exact (shapely): the cells near a zone's edge by their
        squares, those deep inside or far outside by their centres."""
        import shapely

        xs = np.asarray(xs, dtype=np.float64)
        ys = np.asarray(ys, dtype=np.float64)
        out = np.zeros((len(ys), len(xs)), dtype=bool)
        h = 0.5 * a
        for part, (x0, y0, x1, y1), outer, inner in self._shapes(a)[1]:
            cols = np.flatnonzero((xs + h >= x0) & (xs - h <= x1))
            rows = np.flatnonzero((ys + h >= y0) & (ys - h <= y1))
            if not len(cols) or not len(rows):
                continue
            c0, c1, r0, r1 = cols[0], cols[-1] + 1, rows[0], rows[-1] + 1
            sx, sy = np.meshgrid(xs[c0:c1], ys[r0:r1])
            with _PREPARED:
                near = shapely.contains_xy(outer, sx, sy)
                sub = shapely.contains_xy(inner, sx, sy)
                edge = np.nonzero(near & ~sub)
                if len(edge[0]):
                    cx, cy = sx[edge], sy[edge]
                    boxes = shapely.box(cx - h, cy - h, cx + h, cy + h)
                    sub[edge] = shapely.intersects(part, boxes)
            out[r0:r1, c0:c1] |= sub
        return out


def centres_in(geom, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Which cells of the grid of column centres ``xs`` and row centres ``ys`` have their
    centre in ``geom`` (shapely; only the cells within its bounds tested)."""
    import shapely

    out = np.zeros((len(ys), len(xs)), dtype=bool)
    if geom.is_empty:
        return out
    x0, y0, x1, y1 = geom.bounds
    cols = np.flatnonzero((xs >= x0) & (xs <= x1))
    rows = np.flatnonzero((ys >= y0) & (ys <= y1))
    if len(cols) and len(rows):
        c0, c1, r0, r1 = cols[0], cols[-1] + 1, rows[0], rows[-1] + 1
        gx, gy = np.meshgrid(xs[c0:c1], ys[r0:r1])
        with _PREPARED:
            out[r0:r1, c0:c1] = shapely.contains_xy(geom, gx, gy)
    return out


# ------------------------------------------------------------------ reading zones


def _name_column(frame) -> str | None:
    for col in frame.columns:
        if str(col).lower() == "name":
            return col
    return None


# the vector files zones come in, by suffix: one that does not parse is a damaged one of them
_VECTOR_KINDS = {
    ".geojson": "GeoJSON",
    ".json": "GeoJSON",
    ".gpkg": "GeoPackage",
    ".shp": "a Shapefile",
}


def read_zone_file(path: str | os.PathLike):
    """A zone file as a GeoDataFrame (its polygons, a ``name`` each, its CRS), checked: one
    :class:`InvalidParameterError` for a file that does not exist or does not parse, that
    holds no polygon, or whose geometry is not polygons, or that has no CRS."""
    if not str(path).strip():
        raise InvalidParameterError(
            "`keep_out` holds an empty path; give a zone file's path, or leave it out"
        )
    if "://" in str(path):
        raise InvalidParameterError(
            f"keep-out zone file {path} is a URL: zone files are read from local paths; "
            "download it first"
        )
    path = Path(path)
    if not path.exists():
        raise InvalidParameterError(f"keep-out zone file {path} does not exist")
    if not path.is_file() and not path.is_dir():
        raise InvalidParameterError(f"keep-out zone file {path} is not a regular file")
    try:
        frame = _every_layer(path)
    except Exception as exc:  # noqa: BLE001 - pyogrio and GDAL raise many types
        what = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        kind = _VECTOR_KINDS.get(path.suffix.lower())
        if kind is not None:  # the right kind of file, damaged or malformed
            raise InvalidParameterError(
                f"keep-out zone file {path} is not valid {kind} ({what}); fix the file"
            ) from None
        raise InvalidParameterError(
            f"keep-out zone file {path} cannot be read as a vector file ({what}); give "
            "GeoJSON, GeoPackage or a Shapefile"
        ) from None
    if frame.crs is None:
        raise InvalidParameterError(
            f"keep-out zone file {path} has no coordinate reference system; write one into it "
            "(GeoJSON is WGS84 longitude and latitude by definition: a .geojson file with "
            "projected coordinates needs its 'crs' member)"
        )
    unknown = _unknown_crs_member(path) if frame.crs.to_epsg() == 4326 else None
    if unknown is not None:  # GDAL read it as longitude and latitude
        raise InvalidParameterError(
            f"keep-out zone file {path} names the CRS {unknown!r}, which PROJ does not know; "
            "write a known one in its 'crs' member (such as urn:ogc:def:crs:EPSG::32610) or "
            "the coordinates in longitude and latitude"
        )
    return _named(frame, str(path))


def _unknown_crs_member(path: Path) -> str | None:
    """The name in a GeoJSON file's ``crs`` member when PROJ cannot read it (GDAL then takes
    the file as WGS84 longitude and latitude without a word), else None."""
    if path.suffix.lower() not in (".geojson", ".json") or not path.is_file():
        return None
    import json

    from pyproj import CRS
    from pyproj.exceptions import CRSError

    try:
        name = json.loads(path.read_text(encoding="utf-8"))["crs"]["properties"]["name"]
    except (ValueError, KeyError, TypeError, UnicodeDecodeError):
        return None  # no named crs member (GDAL read the file: its JSON is sound)
    try:
        CRS.from_user_input(str(name))
    except CRSError:
        return str(name)
    return None


def _every_layer(path: Path):
    """Every layer of a vector file as one GeoDataFrame (a GeoPackage may hold several), each
    layer in the first one's CRS."""
    import warnings

    import geopandas as gpd
    import pandas as pd
    import pyogrio

    with warnings.catch_warnings():  # (GDAL's own warnings: what matters is raised, in a line)
        warnings.simplefilter("ignore", RuntimeWarning)
        layers = [str(row[0]) for row in pyogrio.list_layers(path)]
        if len(layers) <= 1:
            return gpd.read_file(path)
        frames = [gpd.read_file(path, layer=name) for name in layers]
    crs = next((f.crs for f in frames if f.crs is not None), None)
    if crs is not None and any(f.crs is None for f in frames):
        bare = [n for n, f in zip(layers, frames, strict=True) if f.crs is None]
        raise InvalidParameterError(
            f"keep-out zone file {path}: layer {bare[0]!r} has no coordinate reference "
            "system (the others have one); write one into it"
        )
    frames = [f.to_crs(crs) if crs is not None else f for f in frames]
    return gpd.GeoDataFrame(pd.concat(frames, ignore_index=True), crs=crs)


def _named(frame, source: str):
    """``frame`` with a ``name`` per row (its own, else ``source #k``) and polygons only."""
    import shapely

    col = _name_column(frame)
    names = []
    for k, (geom, name) in enumerate(
        zip(frame.geometry, frame[col] if col is not None else [None] * len(frame), strict=True)
    ):
        label = str(name) if name is not None and str(name).strip() else f"{source} #{k + 1}"
        if geom is None or geom.is_empty:
            raise InvalidParameterError(f"keep-out zone {label!r} ({source}) has no geometry")
        if geom.geom_type not in ("Polygon", "MultiPolygon"):
            raise InvalidParameterError(
                f"keep-out zone {label!r} ({source}) is a {geom.geom_type}, not a polygon: a "
                "zone is an area (Polygon or MultiPolygon); buffer a line or a point by the "
                "distance to keep"
            )
        if not geom.is_valid:
            fixed = shapely.make_valid(geom)
            if fixed.geom_type not in ("Polygon", "MultiPolygon"):
                raise InvalidParameterError(
                    f"keep-out zone {label!r} ({source}) is not a valid polygon "
                    f"({shapely.is_valid_reason(geom)})"
                )
        names.append(label)
    if not len(frame):
        raise InvalidParameterError(f"keep-out zone file {source} holds no zone")
    out = frame[[frame.geometry.name]].copy()
    out["name"] = names
    return out.set_geometry(frame.geometry.name)


def read_zones(
    keep_out, crs_wkt: str | None, margin_m: float = 0.0, extent: tuple | None = None
) -> KeepOut | None:
    """:class:`KeepOut` of ``keep_out`` in the maps' CRS ``crs_wkt``: a path or a list of
    paths of zone files (:func:`read_zone_file`), a GeoDataFrame (without a CRS: in the maps'
    coordinates), a shapely polygon, a list of them, or a :class:`KeepOut` (its margin kept
    unless ``margin_m`` is given). None or an empty list: None. With the map's ``extent``
    (x min, y min, x max, y max), zones are placed against it (:func:`_in_maps_crs`)."""
    if keep_out is None:
        return None  # (a mission without zones imports neither geopandas nor pandas)
    import geopandas as gpd
    from shapely.geometry.base import BaseGeometry

    if isinstance(keep_out, KeepOut):  # the same object while its margin is (its shapes kept)
        if margin_m is None or float(margin_m) == keep_out.margin_m:
            return keep_out
        return KeepOut(keep_out.zones, float(margin_m))
    margin = 0.0 if margin_m is None else float(margin_m)
    if not math.isfinite(margin) or margin < 0:
        raise InvalidParameterError(
            f"`keep_out_margin_m` must be a finite number of metres >= 0, got {margin_m!r}"
        )
    one = (str, os.PathLike, BaseGeometry, gpd.GeoDataFrame)
    if isinstance(keep_out, one):
        items = [keep_out]
    elif isinstance(keep_out, list | tuple):
        items = list(keep_out)
    else:  # (bytes, a dict or a number would be read item by item as something else)
        raise InvalidParameterError(
            "`keep_out` takes a zone file's path, a GeoDataFrame, a shapely polygon or a list "
            f"of them, got {type(keep_out).__name__}"
        )
    zones, shapes = [], {}
    for k, item in enumerate(items):
        if isinstance(item, str | os.PathLike):
            zones += _in_maps_crs(read_zone_file(item), crs_wkt, str(item), extent)
        elif isinstance(item, gpd.GeoDataFrame):
            zones += _in_maps_crs(_named(item, "GeoDataFrame"), crs_wkt, "GeoDataFrame", extent)
        elif isinstance(item, BaseGeometry):
            shapes[f"keep_out[{k}]"] = item  # in the maps' coordinates, checked together
        else:
            raise InvalidParameterError(
                "`keep_out` takes zone file paths, a GeoDataFrame or shapely polygons, got "
                f"{type(item).__name__}"
            )
    if shapes:
        frame = gpd.GeoDataFrame({"name": list(shapes)}, geometry=list(shapes.values()))
        zones += _in_maps_crs(_named(frame, "keep_out"), crs_wkt, "shapely", extent)
    return KeepOut(tuple(zones), margin) if zones else None


def _in_maps_crs(frame, crs_wkt: str | None, source: str, extent: tuple | None = None) -> list:
    """The zones of ``frame`` as (name, polygon) in the maps' CRS. A zone never vanishes
    silently: coordinates that a geographic CRS cannot hold (a GeoJSON in map metres without
    its ``crs`` member) are read in the map's CRS when they lie on the map, else refused; a
    geographic zone is cut to a window around the map before it is projected (a world box
    would become infinite); a zone that is not finite in the map's CRS is refused, and one
    off the map is named in a warning."""
    import shapely

    if frame.crs is not None:
        if not crs_wkt:
            raise InvalidParameterError(
                f"keep-out zones {source} have a CRS but the maps have none, so they cannot "
                "be placed on the map; write the DEM's CRS into its file (then the maps have "
                "it), or in Python give the zones as shapely polygons in map coordinates"
            )
        if frame.crs.is_geographic:
            frame = _geographic(frame, crs_wkt, source, extent)
        frame = frame.to_crs(crs_wkt)
    out = []
    on_map = shapely.box(*extent) if extent is not None else None
    for name, geom in zip(frame["name"], frame.geometry, strict=True):
        if geom is not None and not geom.is_valid:
            geom = shapely.make_valid(geom)
        if geom is None or geom.is_empty:
            notice(
                log, "keep-out zone %r (%s) lies off the map: it constrains nothing", name, source
            )
            continue
        if not np.all(np.isfinite(geom.bounds)):
            raise InvalidParameterError(
                f"keep-out zone {name!r} ({source}) cannot be placed on the map: its "
                "coordinates are not finite in the map's CRS; check the zone file's CRS"
            )
        if on_map is not None and not geom.intersects(on_map):
            notice(
                log,
                "keep-out zone %r (%s) lies off the map (its bounds %s, the map's %s): it "
                "constrains nothing; check its coordinates and CRS",
                name,
                source,
                _rounded(geom.bounds),
                _rounded(extent),
            )
        out.append((str(name), geom))
    return out


def map_extent(m) -> tuple:
    """The extent (x min, y min, x max, y max) of the maps ``m``: its cells' outer edges."""
    a = m.cell_size / 2
    return (
        float(np.min(m.x)) - a,
        float(np.min(m.y)) - a,
        float(np.max(m.x)) + a,
        float(np.max(m.y)) + a,
    )


def _rounded(b) -> str:
    return "(" + ", ".join(f"{v:.6g}" for v in b) + ")"


def _geographic(frame, crs_wkt: str, source: str, extent: tuple | None):
    """A geographic ``frame`` made ready to project onto the map: read in the map's CRS when
    its coordinates cannot be longitude and latitude but lie on the map (with a warning),
    refused when they lie nowhere; else cut to the map's window in its CRS (a degree around
    it), so that what lies far beyond the map is not projected."""
    import shapely
    from pyproj import Transformer

    b = frame.total_bounds
    if not (-180.0 <= b[0] and b[2] <= 360.0 and -90.0 <= b[1] and b[3] <= 90.0):
        if extent is not None and shapely.box(*b).intersects(shapely.box(*extent)):
            notice(
                log,
                "keep-out zones %s: coordinates %s are not longitude and latitude, as the file's "
                "CRS says, but lie on the map: read in the map's CRS (write its CRS into the "
                "file to say so)",
                source,
                _rounded(b),
            )
            return frame.set_crs(crs_wkt, allow_override=True)
        raise InvalidParameterError(
            f"keep-out zones {source}: coordinates {_rounded(b)} are not longitude and "
            "latitude, as the file's CRS says, and do not lie on the map"
            + (f" {_rounded(extent)}" if extent is not None else "")
            + "; write the file's CRS into it (a GeoJSON in projected coordinates needs its "
            "'crs' member)"
        )
    if extent is None:
        return frame
    to_geo = Transformer.from_crs(crs_wkt, frame.crs, always_xy=True)
    w = to_geo.transform_bounds(*extent, densify_pts=21)
    if w[0] > w[2]:  # (the map spans the antimeridian: its zones are projected whole)
        return frame
    window = shapely.box(
        max(w[0] - 1.0, -180.0),
        max(w[1] - 1.0, -90.0),
        min(w[2] + 1.0, 360.0),
        min(w[3] + 1.0, 90.0),
    )
    out = frame.copy()
    out[out.geometry.name] = [
        g.intersection(window) if g is not None else g for g in frame.geometry
    ]
    return out


def entered(keep_out: KeepOut | None, *lines, slack=None) -> list[str]:
    """The names of the zones whose kept area (the zone and its margin) one of ``lines``
    (each ``(x, y)``: a polyline in map coordinates) enters, checked on the continuous lines
    (shapely). ``slack`` (metres, one a line; default none) is how far the line flown may lie
    off the polyline (the arcs of a track between their samples): a line is taken to enter
    where it comes within the margin and its slack."""
    if keep_out is None:
        return []
    import shapely

    slack = [0.0] * len(lines) if slack is None else [float(v) for v in slack]
    polylines = [
        shapely.LineString(np.column_stack([x, y])) if len(x) > 1 else shapely.Point(x[0], y[0])
        for x, y in lines
    ]
    out = []
    for name, g in keep_out.zones:
        if any(
            line.distance(g) < keep_out.margin_m + extra or line.intersects(g)
            for line, extra in zip(polylines, slack, strict=True)
        ):
            out.append(name)
    return out
