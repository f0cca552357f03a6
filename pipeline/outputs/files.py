"""A mission's files for people and vehicles: the flown track and the grid path (GeoParquet),
the waypoints (GeoJSON, CSV), a QGroundControl / ArduSub mission (QGC WPL 110), a Google Earth
file (KML) and an LSTS IMC plan for Neptus and DUNE (a ``PlanSpecification`` holding one
``FollowPath``).

Heights: ``z`` is the vehicle's height (metres, positive up, the DEM's vertical datum);
``depth_m = sea_level - z``; ``altitude_m`` is the height above the seabed (the DEM interpolated
bilinearly under the vehicle). Horizontal positions are the maps' projection (``x``, ``y``)
and WGS84 longitude and latitude (degrees) when the DEM has a CRS; without one, only the
files in map coordinates are written (the Item says which were skipped).
"""

from __future__ import annotations

import functools
import math
import re
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING
from xml.sax.saxutils import escape

import numpy as np

from .._types import Maps, PathLike
from ..runtime.jit import njit

if TYPE_CHECKING:
    from ..flight.vehicle import Flight
    from ..trajectory import Trajectory

PARQUET = "application/vnd.apache.parquet"
KML_TRACK_POINTS = 4000
# the tracks' columns are floats that hardly repeat: pyarrow's default dictionary encoding is
# tried on each, abandoned, and made a track's write several times slower and its file larger
PARQUET_OPTIONS = {"use_dictionary": False}


@functools.lru_cache(maxsize=8)
def _to_wgs84(crs_wkt: str):
    from pyproj import CRS, Transformer

    crs = CRS.from_wkt(crs_wkt)
    if crs.is_geographic:
        return None
    return Transformer.from_crs(crs, "EPSG:4326", always_xy=True)


def to_lonlat(crs_wkt: str | None, x, y):
    """Longitudes and latitudes (WGS84, degrees) of map coordinates, or None without a CRS."""
    if not crs_wkt:
        return None
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    tr = _to_wgs84(crs_wkt)
    if tr is None:
        return x, y
    lon, lat = tr.transform(x, y)
    return np.asarray(lon), np.asarray(lat)


@functools.lru_cache(maxsize=8)
def _projjson(crs: str) -> dict:
    """A CRS (WKT, or an authority code) as the PROJJSON dict GeoParquet metadata holds."""
    from pyproj import CRS

    return CRS.from_user_input(crs).to_json_dict()


# a WKB point, little-endian: byte order 1, geometry type 1 (Point), x, y (21 bytes, packed)
_WKB_POINT = np.dtype([("order", "u1"), ("type", "<u4"), ("x", "<f8"), ("y", "<f8")])


def _write_points(path: Path, columns: dict, x, y, lonlat, crs_wkt) -> None:
    """A GeoParquet 1.1 file (the version geopandas writes the catalog's missions table in)
    of point rows: ``columns`` and a WKB point geometry in WGS84 longitude and latitude
    (``lonlat``), else in the maps' CRS (``x``, ``y``; ``crs`` null without one), with its CRS
    (PROJJSON), geometry type and bounding box in the file's ``geo`` metadata. The points are
    laid out as WKB by numpy and the table written by pyarrow (geoarrow-pyarrow's writer makes
    the same file, tests/flight/test_flight.py, at several times the cost of a track's
    write)."""
    import json

    import pyarrow as pa
    import pyarrow.parquet as pq

    gx, gy = lonlat if lonlat is not None else (x, y)
    gx = np.asarray(gx, dtype=np.float64)
    gy = np.asarray(gy, dtype=np.float64)
    n = len(gx)
    wkb = np.empty(n, dtype=_WKB_POINT)
    wkb["order"], wkb["type"], wkb["x"], wkb["y"] = 1, 1, gx, gy
    offsets = np.arange(0, _WKB_POINT.itemsize * (n + 1), _WKB_POINT.itemsize, dtype=np.int32)
    geometry = pa.Array.from_buffers(
        pa.binary(), n, [None, pa.py_buffer(offsets), pa.py_buffer(wkb.view(np.uint8))]
    )
    crs = "EPSG:4326" if lonlat is not None else crs_wkt
    bbox = [float(gx.min()), float(gy.min()), float(gx.max()), float(gy.max())] if n else []
    geo = {
        "version": "1.1.0",
        "primary_column": "geometry",
        "columns": {
            "geometry": {
                "encoding": "WKB",
                "geometry_types": ["Point"],
                "crs": _projjson(crs) if crs else None,
                "bbox": bbox,
            }
        },
    }
    table = pa.table({**{k: np.asarray(v) for k, v in columns.items()}, "geometry": geometry})
    table = table.replace_schema_metadata({"geo": json.dumps(geo)})
    pq.write_table(table, path, **PARQUET_OPTIONS)


def write_track(path: Path, flight, crs_wkt: str | None, lonlat=None) -> None:
    """The flown track, one row per sample (no two more than half a cell apart)."""
    f = flight
    if lonlat is None:
        lonlat = to_lonlat(crs_wkt, f.x, f.y)
    cols = {
        "x": f.x,
        "y": f.y,
        "z": f.z,
        "altitude_m": f.altitude_m,
        "seabed_m": f.seabed_m,
        "required_m": f.required_m,
        "s_m": f.s,
        "time_s": f.time_s,
    }
    _write_points(path, cols, f.x, f.y, lonlat, crs_wkt)


def write_grid_path(path: Path, traj, crs_wkt: str | None) -> None:
    """The planned grid path: its cells, their centres and the safety surface there."""
    x, y, z = traj.points[:, 0], traj.points[:, 1], traj.points[:, 2]
    cols = {"row": traj.cells[:, 0], "col": traj.cells[:, 1], "x": x, "y": y, "z": z}
    _write_points(path, cols, x, y, to_lonlat(crs_wkt, x, y), crs_wkt)


def waypoint_table(flight, sea_level: float, lonlat) -> dict:
    """The waypoints as columns: index, lat, lon, x, y, z, depth_m, altitude_m, speed_m_s,
    time_s (lat and lon None without a CRS)."""
    w = flight.waypoints
    seabed = flight.route_seabed_m[flight.waypoint_index]
    return {
        "index": np.arange(len(w)),
        "lat": None if lonlat is None else lonlat[1],
        "lon": None if lonlat is None else lonlat[0],
        "x": w[:, 0],
        "y": w[:, 1],
        "z": w[:, 2],
        "depth_m": sea_level - w[:, 2],
        "altitude_m": w[:, 2] - seabed,
        "speed_m_s": np.full(len(w), flight.vehicle.speed_m_s),
        "time_s": w[:, 3],
    }


def _lists(table: dict, *keys) -> list:
    """Columns of a table as lists of Python floats, which format one by one faster than numpy
    scalars (the files' text is written value by value)."""
    return [np.asarray(table[k], dtype=np.float64).tolist() for k in keys]


def write_waypoints_csv(path: Path, table: dict) -> None:
    """lat, lon, depth_m, altitude_m, speed_m_s, time_s (x_m, y_m without a CRS); rows end
    with CRLF (RFC 4180)."""
    geo = table["lat"] is not None
    head = ["lat", "lon"] if geo else ["x_m", "y_m"]
    row = ("{:.8f},{:.8f}" if geo else "{:.2f},{:.2f}") + ",{:.2f},{:.2f},{:g},{:.1f}"
    a, b, depth, alt, speed, tt = _lists(
        table,
        *(("lat", "lon") if geo else ("x", "y")),
        "depth_m",
        "altitude_m",
        "speed_m_s",
        "time_s",
    )
    lines = [",".join(head + ["depth_m", "altitude_m", "speed_m_s", "time_s"])]
    lines += [row.format(a[k], b[k], depth[k], alt[k], speed[k], tt[k]) for k in range(len(a))]
    with open(path, "w", newline="") as fh:
        fh.write("\r\n".join(lines) + "\r\n")


# one waypoint of the GeoJSON file, and one position of its route, from its values formatted
# as JSON numbers (:func:`_json_numbers`): the JSON ``json.dumps`` writes for the same values
# rounded (``round(x, 8)`` and ``"{:.8f}"`` round alike), formatted in one go (faster than
# json's encoder of the same document; CHANGELOG.md, "Measurements")
_GEOJSON_POSITION = "[{}, {}, {}]"
_GEOJSON_POINT = (
    '{{"type": "Feature", "geometry": {{"type": "Point", "coordinates": '
    + _GEOJSON_POSITION
    + "}}, "
    '"properties": {{"index": {}, "depth_m": {}, "altitude_m": {}, "speed_m_s": {}, '
    '"time_s": {}}}}}'
)
# the columns of a waypoint, each with its format (speed as Python writes it)
_GEOJSON_COLUMNS = (
    ("lon", "{:.8f}"),
    ("lat", "{:.8f}"),
    ("z", "{:.2f}"),
    ("depth_m", "{:.2f}"),
    ("altitude_m", "{:.2f}"),
    ("speed_m_s", "{!r}"),
    ("time_s", "{:.1f}"),
)


def _json_numbers(values, spec: str) -> list:
    """``values`` formatted by ``spec`` as JSON number texts, ``null`` where a value is not
    finite (JSON has no NaN)."""
    values = np.asarray(values, dtype=np.float64)
    text = list(map(spec.format, values.tolist()))
    for k in np.flatnonzero(~np.isfinite(values)).tolist():
        text[k] = "null"
    return text


def waypoints_geojson(table: dict) -> str:
    """RFC 7946 (WGS84 lon, lat, height in metres, positive up): one Point per waypoint with
    its depth, altitude, speed and time, and the route as a LineString; the file's text. A
    value that is not finite (an altitude over no-data) is written ``null``."""
    lon, lat, z, depth, alt, speed, tt = (
        _json_numbers(table[key], spec) for key, spec in _GEOJSON_COLUMNS
    )
    index = np.asarray(table["index"]).tolist()
    n = range(len(lon))
    feats = [
        _GEOJSON_POINT.format(lon[k], lat[k], z[k], index[k], depth[k], alt[k], speed[k], tt[k])
        for k in n
    ]
    route = ", ".join([_GEOJSON_POSITION.format(lon[k], lat[k], z[k]) for k in n])
    feats.append(
        '{"type": "Feature", "geometry": {"type": "LineString", "coordinates": ['
        + route
        + ']}, "properties": {"role": "route"}}'
    )
    return '{"type": "FeatureCollection", "features": [' + ", ".join(feats) + "]}"


def keep_out_geojson(keep_out, crs_wkt: str) -> str:
    """RFC 7946: one Feature per keep-out zone (its ``name`` and the ``margin_m`` kept from
    it), the polygon in WGS84 longitude and latitude, its edges divided every 50 m first so
    that the reprojected shape follows the zone."""
    import json

    import shapely

    tr = _to_wgs84(crs_wkt)
    feats = []
    for name, g in keep_out.zones:
        g = shapely.segmentize(g, 50.0)
        if tr is not None:
            g = shapely.transform(g, lambda xy: np.column_stack(tr.transform(xy[:, 0], xy[:, 1])))
        feats.append(
            {
                "type": "Feature",
                "geometry": shapely.geometry.mapping(g),
                "properties": {"name": name, "margin_m": keep_out.margin_m},
            }
        )
    return json.dumps({"type": "FeatureCollection", "features": feats})


# MAVLink: MAV_CMD_NAV_WAYPOINT, MAV_FRAME_GLOBAL, MAV_FRAME_GLOBAL_RELATIVE_ALT
_NAV_WAYPOINT, _FRAME_GLOBAL, _FRAME_RELATIVE_ALT = 16, 0, 3


def acceptance_radii(table: dict, turn_radius_m: float) -> np.ndarray:
    """Each waypoint's acceptance radius (metres): the vehicle's turn radius, or less where a
    leg next to the waypoint is shorter than twice that, half the shorter leg (an autopilot
    that takes a waypoint as reached within its radius would otherwise pass over one closer
    to the last than the radius, and the heights between them with it)."""
    x, y = np.asarray(table["x"], dtype=np.float64), np.asarray(table["y"], dtype=np.float64)
    legs = np.hypot(np.diff(x), np.diff(y))
    near = np.minimum(np.append(legs, np.inf), np.insert(legs, 0, np.inf))
    return np.minimum(turn_radius_m, 0.5 * near)


def qgc_wpl(table: dict, acceptance_m) -> str:
    """A QGC WPL 110 mission (QGroundControl, ArduSub, Mission Planner): row 0 the home
    position at the surface above the first waypoint, then one NAV_WAYPOINT per waypoint in
    the frame relative to home, altitude ``-depth_m`` (ArduSub: negative is below the
    surface), acceptance radius ``acceptance_m`` (one for every waypoint, or one each:
    :func:`acceptance_radii`). 12 tab-separated fields per row: index, current, frame,
    command, param1-4, latitude, longitude, altitude, autocontinue."""
    lat, lon, depth = _lists(table, "lat", "lon", "depth_m")
    accept = np.broadcast_to(np.asarray(acceptance_m, dtype=np.float64), (len(lat),)).tolist()
    # index, current, frame, command, param1, param2 (acceptance), param3, param4, lat, lon, alt
    fixed = f"{_NAV_WAYPOINT}\t0\t"  # command, param1
    place = "\t0\t0\t{:.8f}\t{:.8f}\t"  # param3, param4, latitude, longitude
    home = f"0\t1\t{_FRAME_GLOBAL}\t{fixed}0" + place + "0.00\t1"
    row = "{}" + f"\t0\t{_FRAME_RELATIVE_ALT}\t{fixed}" + "{:.2f}" + place + "{:.2f}\t1"
    rows = ["QGC WPL 110", home.format(lat[0], lon[0])]
    rows += [row.format(k + 1, accept[k], lat[k], lon[k], -depth[k]) for k in range(len(lat))]
    return "\n".join(rows) + "\n"


# characters XML 1.0 does not allow in a document (control characters other than tab and the
# line ends, the surrogates and two non-characters)
_NOT_XML = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\ud800-\udfff\ufffe\uffff]")


def _xml_text(text: str) -> str:
    """``text`` as XML character data: escaped, and each character XML cannot hold (a
    mission name may have any) replaced by U+FFFD."""
    return escape(_NOT_XML.sub("\ufffd", text))


def kml(name: str, flight, table: dict, lonlat_track) -> bytes:
    """KML 2.2 for Google Earth: the flown track and the waypoint route as 3-D lines (absolute
    heights, negative below sea level) and one placemark per waypoint."""
    # the flown track at most KML_TRACK_POINTS vertices (a line for the eye; the exact track
    # is track.parquet)
    n = len(flight.z)
    keep = np.arange(0, n, max(1, -(-n // KML_TRACK_POINTS)))
    if keep[-1] != n - 1:
        keep = np.append(keep, n - 1)
    route = _coords(table["lon"], table["lat"], table["z"])
    lines = (
        (
            "flown track",
            "#track",
            _coords(lonlat_track[0][keep], lonlat_track[1][keep], flight.z[keep]),
        ),
        ("waypoint route", "#route", route),
    )
    out = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        '<kml xmlns="http://www.opengis.net/kml/2.2"><Document>',
        f"<name>{_xml_text(name)}</name>",
    ]
    for sid, colour, width in (("track", "ff0000ff", "3"), ("route", "ff00ffff", "1.5")):
        out.append(
            f'<Style id="{sid}"><LineStyle><color>{colour}</color><width>{width}</width>'
            "</LineStyle></Style>"
        )
    for title, style, coords in lines:
        out.append(
            f"<Placemark><name>{title}</name><styleUrl>{style}</styleUrl><LineString>"
            f"<altitudeMode>absolute</altitudeMode><coordinates>{' '.join(coords)}"
            "</coordinates></LineString></Placemark>"
        )
    out.append("<Folder><name>waypoints</name>")
    depth, alt, tt = _lists(table, "depth_m", "altitude_m", "time_s")
    mark = (
        "<Placemark><name>WP{}</name><description>depth {:.0f} m, altitude {:.0f} m, t = {:.0f} s"
        "</description><Point><altitudeMode>absolute</altitudeMode><coordinates>{}"
        "</coordinates></Point></Placemark>"
    )
    out += [mark.format(k, depth[k], alt[k], tt[k], c) for k, c in enumerate(route)]
    out.append("</Folder></Document></kml>")
    return "\n".join(out).encode("utf-8")


def _coords(lon, lat, z) -> list:
    """KML coordinates: a ``lon,lat,height`` tuple per point (joined by spaces in a line)."""
    lon, lat, z = (np.asarray(v, dtype=np.float64).tolist() for v in (lon, lat, z))
    return list(map("{:.8f},{:.8f},{:.1f}".format, lon, lat, z))


# ---------------------------------------------------------------- IMC (LSTS), binary

_IMC_SYNC = 0xFE54
_PLAN_SPECIFICATION, _PLAN_MANEUVER, _FOLLOW_PATH, _PATH_POINT = 551, 552, 457, 458
_Z_DEPTH, _SPEED_M_S = 1, 0
_IMC_PATH_POINT = np.dtype([("id", "<u2"), ("n", "<f4"), ("e", "<f4"), ("d", "<f4")])


def _crc16_table() -> np.ndarray:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return np.array(table, dtype=np.int64)


_CRC16 = _crc16_table()


@njit(cache=True)
def _crc16_bytes(data, table):
    crc = 0
    for b in data:
        crc = (crc >> 8) ^ table[(crc ^ b) & 0xFF]
    return crc


def crc16(data: bytes) -> int:
    """CRC-16/IBM (polynomial 0x8005 reflected, initial value 0): IMC's packet checksum, a
    byte at a time from a table, compiled (orders of magnitude faster than in Python)."""
    return int(_crc16_bytes(np.frombuffer(data, dtype=np.uint8), _CRC16))


def _text(s: str) -> bytes:
    b = s.encode("ascii", "replace")
    return struct.pack("<H", len(b)) + b


# WGS84 as DUNE's ``WGS84`` class defines it (src/DUNE/Coordinates/WGS84.hpp)
_WGS84_A = 6378137.0
_WGS84_E2 = 0.00669437999013


def _ecef(lat, lon, hae=0.0):
    """ECEF coordinates (metres) of geodetic latitudes and longitudes (radians)."""
    rn = _WGS84_A / np.sqrt(1.0 - _WGS84_E2 * np.sin(lat) ** 2)
    return np.stack(
        [
            (rn + hae) * np.cos(lat) * np.cos(lon),
            (rn + hae) * np.cos(lat) * np.sin(lon),
            ((1.0 - _WGS84_E2) * rn + hae) * np.sin(lat),
        ],
        axis=-1,
    )


def ned_offsets(lat0, lon0, lat, lon):
    """North and east offsets (metres) from a reference (degrees) that LSTS DUNE's
    ``WGS84::displace(n, e, &lat, &lon)`` turns into the points ``lat``, ``lon`` (degrees),
    as DUNE's FollowPath places its path points. DUNE displaces in ECEF: the reference on the
    ellipsoid plus ``n`` along the north and ``e`` along the east direction of its geocentric
    latitude, with no down term, so a point lies on the plane through the reference normal to
    the geocentric vertical, above the ellipsoid, and reads as the latitude and longitude of
    that ECEF point. The offsets are where the ellipsoid normal of each point meets that
    plane (its geodetic latitude and longitude are the point's), in the plane's north and east
    directions: DUNE reads them back within millimetres (tests/flight/test_flight.py re-implements
    its formulas). Rotating the ECEF difference into the reference's geodetic north-east frame
    instead put points 1-2 km off on 500 km missions."""
    p0 = _ecef(math.radians(lat0), math.radians(lon0))
    phi = math.atan2(p0[2], math.hypot(p0[0], p0[1]))  # geocentric latitude
    lam = math.radians(lon0)
    north = np.array(
        [-math.cos(lam) * math.sin(phi), -math.sin(lam) * math.sin(phi), math.cos(phi)]
    )
    east = np.array([-math.sin(lam), math.cos(lam), 0.0])
    up = np.array([math.cos(lam) * math.cos(phi), math.sin(lam) * math.cos(phi), math.sin(phi)])
    la, lo = (
        np.radians(np.asarray(lat, dtype=np.float64)),
        np.radians(np.asarray(lon, dtype=np.float64)),
    )
    base = _ecef(la, lo)
    normal = np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], axis=-1)
    h = ((p0 - base) @ up) / (normal @ up)  # along each point's normal to DUNE's plane
    d = base + h[:, None] * normal - p0
    return d @ north, d @ east


# the largest IMC message, header (20 bytes) and checksum (2) included: its payload size is a
# 16-bit field, and DUNE's and imcpy's readers take packets of at most this size
IMC_MAX_PACKET = 0xFFFF
IMC_MAX_PAYLOAD = IMC_MAX_PACKET - 22


class PlanTooLargeError(ValueError):
    """An IMC plan whose message cannot hold all its waypoints."""


def imc_plan(plan_id: str, description: str, table: dict, *, timestamp=None) -> bytes:
    """An IMC ``PlanSpecification`` packet (little-endian, CRC-16) holding one maneuver, a
    ``FollowPath``: its reference is the first waypoint (latitude and longitude in radians,
    ``z`` its depth in metres, ``z_units`` DEPTH, the speed in m/s) and its ``PathPoint``s are
    the waypoints as north, east and depth offsets from it (metres)."""
    lat, lon, depth = table["lat"], table["lon"], np.asarray(table["depth_m"], dtype=np.float64)
    north, east = ned_offsets(float(lat[0]), float(lon[0]), lat, lon)
    # PathPoint messages: their id, then north, east and depth offsets as float32 (packed)
    points = np.empty(len(depth), dtype=_IMC_PATH_POINT)
    points["id"], points["n"], points["e"], points["d"] = _PATH_POINT, north, east, depth - depth[0]
    points = points.tobytes()
    follow = (
        struct.pack("<H", _FOLLOW_PATH)
        + struct.pack(
            "<HddfBfB",
            0,  # timeout: none
            math.radians(float(lat[0])),
            math.radians(float(lon[0])),
            float(depth[0]),
            _Z_DEPTH,
            float(table["speed_m_s"][0]),
            _SPEED_M_S,
        )
        + struct.pack("<H", len(north))
        + points
        + _text("")  # custom
    )
    man_id = "follow-path"
    maneuver = struct.pack("<H", _PLAN_MANEUVER) + _text(man_id) + follow + b"\0\0" + b"\0\0"
    payload = (
        _text(plan_id)
        + _text(description)
        + _text("")  # vnamespace
        + struct.pack("<H", 0)  # variables
        + _text(man_id)
        + struct.pack("<H", 1)
        + maneuver
        + struct.pack("<HHH", 0, 0, 0)  # transitions, start actions, end actions
    )
    if len(payload) > IMC_MAX_PAYLOAD:
        most = (IMC_MAX_PAYLOAD - (len(payload) - len(points))) // _IMC_PATH_POINT.itemsize
        raise PlanTooLargeError(
            f"{len(north)} waypoints make an IMC plan of {len(payload)} bytes, more than one "
            f"IMC message holds ({IMC_MAX_PAYLOAD} besides its header): at most {most} "
            "waypoints fit; the waypoints are in waypoints.csv and waypoints.geojson"
        )
    stamp = time.time() if timestamp is None else timestamp
    header = struct.pack(
        "<HHHdHBHB", _IMC_SYNC, _PLAN_SPECIFICATION, len(payload), stamp, 0, 0xFF, 0xFFFF, 0xFF
    )
    body = header + payload
    return body + struct.pack("<H", crc16(body))


@dataclass(frozen=True)
class Mission:
    """What a mission's files are written from: its name and plan id, the trajectory and its
    flight, the maps' CRS (WKT or None), the flown track in longitude and latitude (or None
    without a CRS) and the waypoint table (:func:`waypoint_table`)."""

    name: str
    plan_id: str
    traj: object
    flight: object
    crs_wkt: str | None
    lonlat: tuple | None
    table: dict


@dataclass(frozen=True)
class Format:
    """One file of a mission folder: its name, the catalog asset's title, media type and
    roles, and ``write(mission, path)``. A format with ``lonlat`` needs the track in
    longitude and latitude (a DEM with a CRS); ``write`` may raise :class:`PlanTooLargeError`
    to skip its file with the reason."""

    file: str
    title: str
    media_type: str
    roles: tuple[str, ...]
    write: Callable[[Mission, Path], None]
    lonlat: bool = False
    wanted: Callable[[Mission], bool] | None = None  # None: every mission has this file


def _bytes(make: Callable[[Mission], bytes | str]) -> Callable[[Mission, Path], None]:
    """A writer of the file's content ``make(mission)`` (text as UTF-8)."""

    def write(m: Mission, path: Path) -> None:
        data = make(m)
        path.write_bytes(data.encode() if isinstance(data, str) else data)

    return write


# a mission folder's files, in the order they are written; a new output format is a writer
# and one line here
FORMATS = {
    "track": Format(
        "track.parquet",
        "flown track (x, y, z, altitude, time)",
        PARQUET,
        ("data",),
        lambda m, path: write_track(path, m.flight, m.crs_wkt, m.lonlat),
    ),
    "grid-path": Format(
        "grid-path.parquet",
        "planned grid path (cells)",
        PARQUET,
        ("data",),
        lambda m, path: write_grid_path(path, m.traj, m.crs_wkt),
    ),
    "waypoints-csv": Format(
        "waypoints.csv",
        "waypoints (CSV)",
        "text/csv",
        ("data",),
        lambda m, path: write_waypoints_csv(path, m.table),
    ),
    "waypoints": Format(
        "waypoints.geojson",
        "waypoints (GeoJSON, WGS84)",
        "application/geo+json",
        ("data",),
        _bytes(lambda m: waypoints_geojson(m.table)),
        lonlat=True,
    ),
    "qgc": Format(
        "mission.waypoints",
        "QGroundControl / ArduSub mission (QGC WPL 110)",
        "text/plain",
        ("data",),
        _bytes(lambda m: qgc_wpl(m.table, acceptance_radii(m.table, m.flight.turn_radius_m))),
        lonlat=True,
    ),
    "kml": Format(
        "mission.kml",
        "Google Earth (KML)",
        "application/vnd.google-earth.kml+xml",
        ("visual",),
        _bytes(lambda m: kml(m.name, m.flight, m.table, m.lonlat)),
        lonlat=True,
    ),
    "imc": Format(
        "mission.imc",
        "LSTS IMC PlanSpecification with a FollowPath (Neptus, DUNE)",
        "application/octet-stream",
        ("data",),
        _bytes(lambda m: imc_plan(m.plan_id, m.name[:200], m.table)),
        lonlat=True,
    ),
    "keep-out": Format(
        "keep-out.geojson",
        "keep-out zones avoided (GeoJSON, WGS84)",
        "application/geo+json",
        ("data",),
        _bytes(lambda m: keep_out_geojson(m.traj.keep_out, m.crs_wkt)),
        lonlat=True,
        wanted=lambda m: m.traj.keep_out is not None,
    ),
}
# the files in longitude and latitude, not written without a CRS
LONLAT_FILES = tuple(f.file for f in FORMATS.values() if f.lonlat)


def write_mission_files(folder: Path, name: str, plan_id: str, traj, crs_wkt, sea_level) -> dict:
    """Every file of :data:`FORMATS` of a mission with a flight into ``folder``; returns
    ``{asset key: (file, title, media type, roles)}``, and under ``"skipped"`` why a file was
    not written (an IMC plan too large for one message). Without a CRS the ``LONLAT_FILES``
    are not written."""
    f = traj.flight
    folder = Path(folder)
    wll = to_lonlat(crs_wkt, f.waypoints[:, 0], f.waypoints[:, 1])
    table = waypoint_table(f, sea_level, wll)
    m = Mission(name, plan_id, traj, f, crs_wkt, to_lonlat(crs_wkt, f.x, f.y), table)
    out, skipped = {}, []
    for key, fmt in FORMATS.items():
        if (fmt.lonlat and wll is None) or (fmt.wanted is not None and not fmt.wanted(m)):
            continue
        try:
            fmt.write(m, folder / fmt.file)
        except PlanTooLargeError as e:
            skipped.append(f"{fmt.file}: {e}")
            continue
        out[key] = (fmt.file, fmt.title, fmt.media_type, list(fmt.roles))
    if skipped:
        out["skipped"] = "; ".join(skipped)
    return out


# the version of a mission folder's layout (write_mission's mission.json)
MISSION_FOLDER_VERSION = 1


def write_mission(
    maps: Maps,
    traj: Trajectory,
    flight: Flight,
    folder: PathLike,
    *,
    name: str | None = None,
    overwrite: bool = False,
    quicklook: bool = True,
) -> dict[str, Path]:
    """Write a mission's files for people and vehicles into the new folder ``folder``, as a
    job writes them into its catalog: the flown track and the grid path (GeoParquet), the
    waypoints (CSV, GeoJSON), a QGroundControl / ArduSub mission, a KML file and an IMC plan
    (docs/flyable-missions.md, "Files"), the quick-look (``quicklook.png``: plan view and
    depth profile) and ``mission.json`` (the trajectory's and the flight's figures).

    Parameters
    ----------
    maps : path, xarray.Dataset or MapsStore
        The maps store ``traj`` was planned on (its CRS and sea level).
    traj : Trajectory
        A planned trajectory (:func:`pipeline.plan`).
    flight : Flight
        Its flight (:func:`pipeline.fly`).
    folder : path
        Written atomically (complete, or not at all); an existing folder is replaced only with
        ``overwrite`` and only when this function wrote it.
    name : str, optional
        The mission's name in the files (default: the folder's name).
    quicklook : bool
        Draw ``quicklook.png`` (about a second), as a job does by default.

    Returns
    -------
    dict
        ``{file kind: path}`` of the files written (without a CRS, the files in longitude
        and latitude are not written).

    Examples
    --------
    >>> f = pipeline.fly("maps.zarr", t, {"speed_m_s": 1.5})          # doctest: +SKIP
    >>> pipeline.write_mission("maps.zarr", t, f, "out/m1")["qgc"]   # doctest: +SKIP
    PosixPath('out/m1/mission.waypoints')
    """
    import dataclasses
    import json

    from ..exceptions import InvalidParameterError
    from ..store.maps_store import open_store
    from ..store.paths import STORE_MARKS, atomic_path, has_scheme
    from .catalog import json_value

    if has_scheme(str(folder)):
        raise InvalidParameterError(f"{folder}: mission files are written to a local folder")
    if not traj.planned or flight is None:
        raise InvalidParameterError(
            "write_mission needs a planned trajectory and its flight: "
            "f = pipeline.fly(maps, t) after t = pipeline.plan(...)"
        )
    m = open_store(maps)
    folder = Path(folder)
    name = folder.name if name is None else str(name)
    sea = m.parameters.sea_level_m
    flown = dataclasses.replace(traj, flight=flight)
    with atomic_path(folder, kind="mission", overwrite=overwrite) as tmp:
        tmp.mkdir()
        files = write_mission_files(tmp, name, name, flown, m.crs_wkt, sea)
        skipped = files.pop("skipped", None)
        if quicklook:
            from .plots import mission_quicklook

            mission_quicklook(m, flown, tmp / "quicklook.png", title=name, crs_wkt=m.crs_wkt)
            files["quicklook"] = ("quicklook.png",)
        figures = {
            "name": name,
            "status": traj.status,
            "length_m": traj.length_m,
            "lower_bound_m": traj.lower_bound_m,
            "omega": traj.omega,
            "certified_ratio": traj.certified_ratio,
            "ridge_ratio": traj.ridge_ratio,
            "flown_length_m": flight.flown_length_m,
            "duration_s": flight.duration_s,
            "waypoints": len(flight.waypoints),
            "vehicle": flight.vehicle.to_dict(),
            "files": sorted(f for f, *_ in files.values()),
            "skipped": skipped,
        }
        figures = {k: json_value(v) for k, v in figures.items()}
        meta = {"attributes": {STORE_MARKS["mission"]: MISSION_FOLDER_VERSION}, **figures}
        (tmp / "mission.json").write_text(json.dumps(meta, indent=1, allow_nan=False))
    return {key: folder / f for key, (f, *_) in files.items()}
