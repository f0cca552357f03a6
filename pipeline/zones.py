"""Keep-out zones: areas a mission's route and flown track never enter (cable corridors,
wrecks, protected areas, another vehicle's box), each kept at a margin.

Zones come from vector files geopandas reads (GeoJSON, GeoPackage, Shapefile; polygons in any
CRS, reprojected to the maps'), from a GeoDataFrame, or as shapely polygons in the maps'
coordinates. :class:`KeepOut` holds them in the maps' CRS; :class:`ZonedStore` is a maps store
whose passable layer has the cells near a zone removed, which every stage reads as it reads a
store: the planners' windows, the coarse level, the endpoints' checks, the flight's corridor.

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
start) closes within :data:`POCKET_SIDES` cells: the regions are labelled as the store's
components are (4-connectivity, docs/method.md section 9). Otherwise an exhaustive search of
the whole map proves it.
"""

from __future__ import annotations

import functools
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .exceptions import InvalidEndpointError, InvalidParameterError, UnreachableGoalError
from .store.maps_store import MapsStore

# the cells removed reach this share of a cell beyond the margin (the module's description)
SLACK = 0.25
# the half-sides of the windows a closed region round an endpoint is looked for in
POCKET_SIDES = (64, 256, 1024)


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
        (prepared), that grown by a twentieth of a cell more (what the cells it may meet
        touch) and shrunk by three quarters of a cell (a cell whose centre it holds lies
        inside)."""
        import shapely

        g = self.kept.buffer(SLACK * a)
        shapely.prepare(g)
        return g, g.buffer(0.05 * a), g.buffer(-0.75 * a)

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
        return shapely.intersects(self._grown(a), shapely.box(x - h, y - h, x + h, y + h))

    def blocked(self, xs: np.ndarray, ys: np.ndarray, a: float) -> np.ndarray:
        """Which cells of the window whose column centres are ``xs`` and row centres ``ys``
        (square cells of side ``a``) are removed: their closed square meets a zone grown by
        the margin and ``SLACK * a``. Exact (shapely) at the zones' edges; the cells deep
        inside a zone and the candidates are found by rasterising (rasterio)."""
        import shapely

        xs = np.asarray(xs, dtype=np.float64)
        ys = np.asarray(ys, dtype=np.float64)
        out = np.zeros((len(ys), len(xs)), dtype=bool)
        g, outer, inner = self._shapes(a)
        x0, y0, x1, y1 = g.bounds
        h = 0.5 * a
        cols = np.flatnonzero((xs + h >= x0) & (xs - h <= x1))
        rows = np.flatnonzero((ys + h >= y0) & (ys - h <= y1))
        if not len(cols) or not len(rows) or g.is_empty:
            return out
        c0, c1, r0, r1 = cols[0], cols[-1] + 1, rows[0], rows[-1] + 1
        sx, sy = xs[c0:c1], ys[r0:r1]
        near = _rasterised(outer, sx, sy, a, all_touched=True)
        inside = _rasterised(inner, sx, sy, a, all_touched=False)
        edge = np.argwhere(near & ~inside)
        sub = inside.copy()
        if len(edge):
            cx, cy = sx[edge[:, 1]], sy[edge[:, 0]]
            boxes = shapely.box(cx - h, cy - h, cx + h, cy + h)
            sub[edge[:, 0], edge[:, 1]] = shapely.intersects(g, boxes)
        out[r0:r1, c0:c1] = sub
        return out


def _rasterised(geom, xs, ys, a: float, all_touched: bool) -> np.ndarray:
    """``geom`` burnt into the grid of cell centres ``xs``, ``ys`` (either direction)."""
    from rasterio.errors import NotGeoreferencedWarning
    from rasterio.features import rasterize
    from rasterio.transform import Affine

    shape = (len(ys), len(xs))
    if geom.is_empty:
        return np.zeros(shape, dtype=bool)
    flip_y, flip_x = len(ys) > 1 and ys[1] > ys[0], len(xs) > 1 and xs[1] < xs[0]
    west, north = xs.min() - 0.5 * a, ys.max() + 0.5 * a
    with warnings.catch_warnings():  # (rasterio takes a window of one row for no transform)
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        burnt = rasterize(
            [(geom, 1)],
            out_shape=shape,
            transform=Affine(a, 0.0, west, 0.0, -a, north),
            all_touched=all_touched,
            dtype="uint8",
        ).astype(bool)
    if flip_y:
        burnt = burnt[::-1]
    if flip_x:
        burnt = burnt[:, ::-1]
    return burnt


# ------------------------------------------------------------------ reading zones


def _name_column(frame) -> str | None:
    for col in frame.columns:
        if str(col).lower() == "name":
            return col
    return None


def read_zone_file(path: str | os.PathLike):
    """A zone file as a GeoDataFrame (its polygons, a ``name`` each, its CRS), checked: one
    :class:`InvalidParameterError` for a file that does not exist or does not parse, that
    holds no polygon, or whose geometry is not polygons, or that has no CRS."""
    import geopandas as gpd

    path = Path(path)
    if not path.exists():
        raise InvalidParameterError(f"keep-out zone file {path} does not exist")
    if not path.is_file() and not path.is_dir():
        raise InvalidParameterError(f"keep-out zone file {path} is not a regular file")
    try:
        frame = gpd.read_file(path)
    except Exception as exc:  # noqa: BLE001 - pyogrio and GDAL raise many types
        what = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
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
    return _named(frame, str(path))


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


def read_zones(keep_out, crs_wkt: str | None, margin_m: float = 0.0) -> KeepOut | None:
    """:class:`KeepOut` of ``keep_out`` in the maps' CRS ``crs_wkt``: a path or a list of
    paths of zone files (:func:`read_zone_file`), a GeoDataFrame (without a CRS: in the maps'
    coordinates), a shapely polygon, a list of them, or a :class:`KeepOut` (its margin kept
    unless ``margin_m`` is given). None or an empty list: None."""
    if keep_out is None:
        return None  # (a mission without zones imports neither geopandas nor pandas)
    import geopandas as gpd
    from shapely.geometry.base import BaseGeometry

    if isinstance(keep_out, KeepOut):
        return keep_out if margin_m is None else KeepOut(keep_out.zones, float(margin_m))
    margin = 0.0 if margin_m is None else float(margin_m)
    if not math.isfinite(margin) or margin < 0:
        raise InvalidParameterError(
            f"`keep_out_margin_m` must be a finite number of metres >= 0, got {margin_m!r}"
        )
    items = (
        [keep_out]
        if isinstance(keep_out, str | os.PathLike | BaseGeometry | gpd.GeoDataFrame)
        else list(keep_out)
    )
    zones = []
    for k, item in enumerate(items):
        if isinstance(item, str | os.PathLike):
            zones += _in_maps_crs(read_zone_file(item), crs_wkt, str(item))
        elif isinstance(item, gpd.GeoDataFrame):
            zones += _in_maps_crs(_named(item, "GeoDataFrame"), crs_wkt, "GeoDataFrame")
        elif isinstance(item, BaseGeometry):
            frame = gpd.GeoDataFrame(geometry=[item])
            zones += _in_maps_crs(_named(frame, f"keep_out[{k}]"), crs_wkt, "shapely")
        else:
            raise InvalidParameterError(
                "`keep_out` takes zone file paths, a GeoDataFrame or shapely polygons, got "
                f"{type(item).__name__}"
            )
    return KeepOut(tuple(zones), margin) if zones else None


def _in_maps_crs(frame, crs_wkt: str | None, source: str) -> list:
    import shapely

    if frame.crs is not None:
        if not crs_wkt:
            raise InvalidParameterError(
                f"keep-out zones {source} have a CRS but the maps have none, so they cannot "
                "be placed on the map; give the zones as shapely polygons in map coordinates"
            )
        frame = frame.to_crs(crs_wkt)
    out = []
    for name, geom in zip(frame["name"], frame.geometry, strict=True):
        if not geom.is_valid:
            geom = shapely.make_valid(geom)
        out.append((str(name), geom))
    return out


# ------------------------------------------------------------------ a maps store with zones


class ZonedStore(MapsStore):
    """The maps store ``base`` with the cells near the zones of ``keep_out`` removed from its
    passable layer (the module's description); everything else is the store's."""

    def __init__(self, base: MapsStore, keep_out: KeepOut):
        import threading

        self.__dict__.update(base.__dict__)
        self.base = base
        self.keep_out = keep_out
        self._coarse = {}
        self._lock = threading.Lock()

    def __reduce__(self):
        return ZonedStore, (self.base, self.keep_out)

    def __repr__(self) -> str:
        return f"ZonedStore({self.base!r}, {self.keep_out!r})"

    def removed(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """Which cells of rows ``r0:r1`` and columns ``c0:c1`` the zones remove."""
        return self.keep_out.blocked(self.x[c0:c1], self.y[r0:r1], self.cell_size)

    def window(self, var: str, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        out = self.base.window(var, r0, r1, c0, c1)
        if var != "passable":
            return out
        return out & ~self.removed(r0, r1, c0, c1)

    def values(self, var: str, cells) -> np.ndarray:
        out = self.base.values(var, cells)
        if var != "passable" or not len(out):
            return out
        cells = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
        x, y = self.x[cells[:, 1]], self.y[cells[:, 0]]
        return out & ~self.keep_out.blocked_at(x, y, self.cell_size)

    def zone_of(self, cell) -> str | None:
        """The zone whose kept area removes ``cell``, or None."""
        r, c = int(cell[0]), int(cell[1])
        if not self.keep_out.blocked_at(self.x[c], self.y[r], self.cell_size):
            return None
        name = self.keep_out.zone_at(self.x[c], self.y[r])
        if name is None:  # within the slack of a quarter cell: the nearest zone
            import shapely

            p = shapely.Point(self.x[c], self.y[r])
            name = min(self.keep_out.zones, key=lambda z: z[1].distance(p))[0]
        return name

    def coarse(self, rho: int) -> dict:
        """The store's coarse level with the coarse cells whose centre lies in a zone grown by
        its margin removed (as a coarse cell is passable when most of its cells are)."""
        with self._lock:
            got = self._coarse.get(rho)
        if got is not None:
            return got
        base = self.base.coarse(rho)
        rows, cols = base["passable"].shape
        a = self.cell_size
        sx = np.sign(self.x[1] - self.x[0]) if len(self.x) > 1 else 1.0
        sy = np.sign(self.y[1] - self.y[0]) if len(self.y) > 1 else -1.0
        xs = self.x[0] - sx * a / 2 + sx * (np.arange(cols) + 0.5) * rho * a
        ys = self.y[0] - sy * a / 2 + sy * (np.arange(rows) + 0.5) * rho * a
        inside = _rasterised(self.keep_out.kept, xs, ys, rho * a, all_touched=False)
        got = {**base, "passable": base["passable"] & ~inside}
        with self._lock:
            self._coarse[rho] = got
        return got

    def components(self, *cells) -> list:
        """The store's components of ``cells``; for a start and a goal in one component, an
        :class:`UnreachableGoalError` when the zones close a region round either that does not
        hold the other (found in windows of :data:`POCKET_SIDES`)."""
        got = self.base.components(*cells)
        if len(cells) == 2 and got[0] is not None and got[0] == got[1]:
            for end, other in (cells, cells[::-1]):
                if self._closed_apart(end, other):
                    raise UnreachableGoalError(
                        f"the goal is unreachable: the keep-out zones "
                        f"({', '.join(self.keep_out.names)}) close off the region of "
                        f"{'start' if end == cells[0] else 'goal'} {tuple(end)} from "
                        f"{'goal' if end == cells[0] else 'start'} {tuple(other)}"
                    )
        return got

    def _closed_apart(self, end, other) -> bool:
        from scipy import ndimage

        rows, cols = self.shape
        r, c = int(end[0]), int(end[1])
        cross = ndimage.generate_binary_structure(2, 1)
        for h in POCKET_SIDES:
            r0, r1 = max(r - h, 0), min(r + h + 1, rows)
            c0, c1 = max(c - h, 0), min(c + h + 1, cols)
            ok = self.window("passable", r0, r1, c0, c1)
            if not ok[r - r0, c - c0]:
                return False  # the endpoints' own checks say what is wrong
            labels, _ = ndimage.label(ok, structure=cross)
            region = labels == labels[r - r0, c - c0]
            open_ = (
                (r0 > 0 and region[0].any())
                or (r1 < rows and region[-1].any())
                or (c0 > 0 and region[:, 0].any())
                or (c1 < cols and region[:, -1].any())
            )
            if not open_:
                orr, oc = int(other[0]) - r0, int(other[1]) - c0
                held = 0 <= orr < r1 - r0 and 0 <= oc < c1 - c0 and region[orr, oc]
                return not held
            if r0 == 0 and c0 == 0 and r1 == rows and c1 == cols:
                return False
        return False


def zoned(m: MapsStore, keep_out, margin_m=None) -> MapsStore:
    """``m`` with the zones of ``keep_out`` (:func:`read_zones`), or ``m`` without any."""
    if isinstance(m, ZonedStore):
        m = m.base
    zones = read_zones(keep_out, m.crs_wkt, margin_m)
    return m if zones is None else ZonedStore(m, zones)


def check_outside(m: MapsStore, name: str, cell) -> None:
    """An :class:`InvalidEndpointError` naming the zone when ``cell`` (``name``: start, goal)
    is removed by a keep-out zone of ``m``."""
    zone_of = getattr(m, "zone_of", None)
    zone = zone_of(cell) if zone_of is not None else None
    if zone is not None:
        margin = m.keep_out.margin_m
        raise InvalidEndpointError(
            f"{name} {tuple(int(v) for v in cell)} lies in keep-out zone {zone!r}"
            + (f" or within its margin of {margin:g} m" if margin else "")
            + "; move it out of the zone"
        )


def entered(keep_out: KeepOut | None, *lines) -> list[str]:
    """The names of the zones whose kept area (the zone and its margin) one of ``lines``
    (each ``(x, y)``: a polyline in map coordinates) enters, checked on the continuous lines
    (shapely)."""
    if keep_out is None:
        return []
    import shapely

    polylines = [
        shapely.LineString(np.column_stack([x, y])) if len(x) > 1 else shapely.Point(x[0], y[0])
        for x, y in lines
    ]
    out = []
    for name, g in keep_out.zones:
        if any(line.distance(g) < keep_out.margin_m or line.intersects(g) for line in polylines):
            out.append(name)
    return out
