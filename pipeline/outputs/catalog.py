"""The results catalog: a self-contained STAC catalog of missions (pystac), GeoParquet tables
(geopandas) and quick-look PNGs.

Layout under the catalog directory::

    catalog.json                      root catalog
    index.html, report/hillshade.png  the offline report for a browser (pipeline.outputs.report)
    missions/collection.json          the job's Collection; asset missions.parquet
    missions/missions.parquet         one row per mission (LineString, auv: properties)
    missions/<id>/<id>.json           one Item per mission (failed ones too)
    missions/<id>/track.parquet       the flown track (x, y, z, altitude, time; lon/lat points)
    missions/<id>/grid-path.parquet   the planned grid path (cells, safety surface)
    missions/<id>/waypoints.geojson   waypoints, WGS84 (also waypoints.csv)
    missions/<id>/mission.waypoints   QGroundControl / ArduSub (QGC WPL 110)
    missions/<id>/mission.kml         Google Earth
    missions/<id>/mission.imc         LSTS IMC plan (Neptus, DUNE)
    missions/<id>/quicklook.png       plan view and depth profile

Item geometries are WGS84 longitude/latitude (RFC 7946) when the DEM has a CRS, with the STAC
projection extension giving the maps' CRS; the file formats are described in
:mod:`pipeline.outputs.files` and ``docs/flyable-missions.md``.

A mission's folder is written beside its place and renamed into it when complete, so the
Item's presence means the mission is finished (a re-run skips it).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import functools
import hashlib
import json
import math
import os
import re
import shutil
import uuid
from pathlib import Path

import numpy as np

from ..exceptions import PipelineError
from ..store.paths import write_atomically

COLLECTION = "missions"


_SAFE = re.compile(r"[^A-Za-z0-9_-]")
_MAX_ID = 80


def mission_id(name: str) -> str:
    """The Item id and folder name of the mission ``name``: letters, digits, ``_`` and ``-``
    only, at most about 90 characters. A name that is not such an id already gets the
    replaced characters and a short hash of the name (so that two names never share an id);
    the name as given stays in the Item's ``auv:name``."""
    safe = _SAFE.sub("-", name)[:_MAX_ID]
    if safe == name:
        return name
    digest = hashlib.sha256(name.encode("utf-8", "surrogatepass")).hexdigest()[:10]
    return f"{safe.strip('-') or 'mission'}-{digest}"


def mission_dir(root: Path, name: str) -> Path:
    return Path(root) / COLLECTION / mission_id(name)


def finished(root: Path, name: str) -> dict | None:
    """The Item of the finished mission ``name``, or None (absent or unreadable: to be planned
    again)."""
    mid = mission_id(name)
    p = mission_dir(root, name) / f"{mid}.json"
    try:
        item = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(item, dict) or not isinstance(item.get("properties"), dict):
        return None  # (a JSON of the user's own)
    return item if tool_files(p.parent) is not None else None


# the mark the tool leaves in each mission folder it writes: the files it wrote there (what a
# re-run replaces and --prune removes; anything else in the folder is the user's and stays)
MARK = ".pipeline-mission"  # (JSON; not named *.json: it is no Item)
TOOL = "auv-pipeline"


def tool_files(folder: Path) -> list[str] | None:
    """The names of the files the tool wrote in the mission folder ``folder``, from its mark;
    for a folder written before the mark, its Item (``<folder name>.json`` holding the tool's
    ``auv:run_id``) and the Item's assets. None when the folder is not the tool's."""
    try:
        mark = json.loads((folder / MARK).read_text())
        if isinstance(mark, dict) and mark.get("made_by") == TOOL:
            return [str(f) for f in mark.get("files", []) if "/" not in str(f)] + [MARK]
    except (OSError, ValueError):
        pass
    try:
        item = json.loads((folder / f"{folder.name}.json").read_text())
        if not isinstance(item, dict) or "auv:run_id" not in item.get("properties", {}):
            return None
        hrefs = [str(a.get("href", "")) for a in (item.get("assets") or {}).values()]
    except (OSError, ValueError, AttributeError):
        return None
    names = [h[2:] if h.startswith("./") else h for h in hrefs]
    return [f"{folder.name}.json"] + [n for n in names if n and "/" not in n]


def remove_tool_files(folder: Path) -> list[str]:
    """Remove what the tool wrote in the mission folder ``folder`` (:func:`tool_files`) and the
    folder itself when nothing else is left; returns the names of the user's files kept."""
    for name in tool_files(folder) or []:
        with contextlib.suppress(FileNotFoundError):
            (folder / name).unlink()
    kept = sorted(p.name for p in folder.iterdir())
    if not kept:
        folder.rmdir()
    return kept


def _replace(final: Path, tmp: Path, name: str) -> None:
    """Put the new mission folder ``tmp`` in place of ``final``: the files the tool wrote
    there before are replaced, the user's own files are moved into the new folder; a folder
    of that name the tool did not write is never touched."""
    if final.exists():
        mine = tool_files(final)
        if mine is None:
            raise PipelineError(
                f"{final} exists and was not written by this tool: move it away or rename "
                f"mission {name!r}"
            )
        for p in final.iterdir():
            if p.name not in mine and not (tmp / p.name).exists():
                os.rename(p, tmp / p.name)  # the user's own file, kept
        shutil.rmtree(final)
    os.rename(tmp, final)


def damaged_assets(root: Path, item: dict) -> list[str]:
    """The files of a finished mission's Item that are missing, whose size is not the one
    written (``auv:asset_bytes``; Items written before it are checked for presence only), or
    whose content is plainly damaged (:func:`_intact`)."""
    folder = Path(root) / COLLECTION / item.get("id", "")
    sizes = item.get("properties", {}).get("auv:asset_bytes") or {}
    bad = []
    for key, asset in sorted((item.get("assets") or {}).items()):
        href = str(asset.get("href", ""))
        path = folder / (href[2:] if href.startswith("./") else href)
        try:
            size = path.stat().st_size
        except OSError:
            bad.append(path.name)
            continue
        if (key in sizes and sizes[key] != size) or not _intact(path, size):
            bad.append(path.name)
    return bad


def _intact(path: Path, size: int) -> bool:
    """What can be told of a file's content without reading it: a Parquet file begins and
    ends with its magic bytes (a damaged one that kept its size is then seen too)."""
    if path.suffix != ".parquet":
        return True
    try:
        with open(path, "rb") as fh:
            head = fh.read(4)
            fh.seek(max(size - 4, 0))
            return head == b"PAR1" and fh.read(4) == b"PAR1"
    except OSError:
        return False


def write_mission(
    root: Path,
    name: str,
    mission: dict,
    traj,
    *,
    maps,
    crs_wkt,
    min_clearance_m: float,
    run_id: str,
    quicklook: bool = True,
    quicklook_png: bytes | None = None,
) -> dict:
    """Write the Item and assets of the mission ``name`` atomically; returns the Item as a
    dict. ``mission["fingerprint"]``, when given, is kept as ``auv:fingerprint`` (what a re-run
    compares to decide whether the mission changed). ``quicklook_png``: the quick-look already
    drawn (``plan_missions(quicklooks=True)``), else it is drawn here."""
    import pystac

    mid = mission_id(name)
    final = mission_dir(root, name)
    tmp = final.parent / f".{mid}.tmp-{uuid.uuid4().hex[:8]}"
    tmp.mkdir(parents=True)
    try:
        ok = len(traj.cells) > 1  # a path (failed by a vehicle limit, it is kept to inspect)
        geom = bbox = None
        assets = {}
        props = {}
        if ok:
            files, geom, bbox, props = _mission_files(tmp, name, mid, traj, maps, crs_wkt)
            for key, (href, title, media, roles) in files.items():
                assets[key] = pystac.Asset(f"./{href}", title=title, media_type=media, roles=roles)
            if quicklook:
                if quicklook_png:  # drawn where the mission was planned
                    (tmp / "quicklook.png").write_bytes(quicklook_png)
                else:
                    from .plots import mission_quicklook

                    mission_quicklook(
                        maps, traj, tmp / "quicklook.png", title=name, crs_wkt=crs_wkt
                    )
                assets["quicklook"] = pystac.Asset(
                    "./quicklook.png",
                    title="plan view and depth profile",
                    media_type=pystac.MediaType.PNG,
                    roles=["overview"],
                )
        # each file's size as written: a re-run plans a mission again whose files went
        # missing or changed (:func:`damaged_assets`)
        props["auv:asset_bytes"] = {
            key: (tmp / a.href[2:]).stat().st_size for key, a in sorted(assets.items())
        }
        props.update(
            {
                f"auv:{k}": json_value(v)
                for k, v in (
                    ("length_m", traj.length_m),
                    ("ridge_length_m", traj.ridge_length_m),
                    ("ridge_ratio", traj.ridge_ratio),
                    ("omega", traj.omega),
                    ("lower_bound_m", traj.lower_bound_m),
                    ("certified_ratio", traj.certified_ratio),
                    ("min_clearance_m", min_clearance_m),
                    ("runtime_s", traj.runtime_s),
                )
            }
        )
        props.update(
            {
                "auv:name": name,
                "auv:fingerprint": mission.get("fingerprint"),
                "auv:planner": traj.planner,
                "auv:status": traj.status,
                "auv:message": traj.message,
                "auv:run_id": run_id,
                "auv:start": [
                    json_value(v) for v in mission.get("start_input", mission.get("start", []))
                ],
                "auv:goal": [
                    json_value(v) for v in mission.get("goal_input", mission.get("goal", []))
                ],
                "auv:sections": len(traj.extra.get("sections", [])) if ok else 0,
                "auv:expansions": int(traj.expansions),
            }
        )
        if traj.extra.get("legs"):  # via points: as given, and each leg's figures
            props["auv:via"] = [
                [json_value(v) for v in p] for p in mission.get("via_input", mission.get("via"))
            ]
            props["auv:legs"] = [
                {k: json_value(v) for k, v in leg.items()} for leg in traj.extra["legs"]
            ]
            via = np.asarray(traj.extra["via_index"], dtype=np.int64)
            props["auv:via_xy"] = traj.points[via, :2].round(2).tolist()
            props["auv:via_cells"] = traj.cells[via].tolist()
        if traj.extra.get("flight_rounds"):  # planned again around its flight's problems
            props["auv:flight_rounds"] = [
                {k: json_value(v) for k, v in r.items()} for r in traj.extra["flight_rounds"]
            ]
        par = getattr(maps, "parameters", None)
        if par is not None:  # what a check of the mission (pipeline verify) measures against
            props["auv:clearance_m"] = par.clearance_m
            props["auv:clearance_method"] = par.method
            if par.method == "horizontal":
                props["auv:horizontal_clearance_m"] = par.horizontal_clearance_m or par.clearance_m
            props["auv:sea_level_m"] = par.sea_level_m
        if traj.keep_out is not None:  # the keep-out zones it avoids, and their margin
            props["auv:keep_out"] = list(traj.keep_out.names)
            props["auv:keep_out_margin_m"] = traj.keep_out.margin_m
        item = pystac.Item(mid, geom, bbox, _dt.datetime.now(_dt.UTC), props, assets=assets)
        if ok and crs_wkt:
            _projection(item, crs_wkt, traj)
        d = item.to_dict(include_self_link=False, transform_hrefs=False)
        d["links"] = [
            {"rel": "root", "href": "../../catalog.json", "type": "application/json"},
            {"rel": "parent", "href": "../collection.json", "type": "application/json"},
            {"rel": "collection", "href": "../collection.json", "type": "application/json"},
        ]
        d["collection"] = COLLECTION
        (tmp / f"{mid}.json").write_text(_item_text(d))
        written = sorted(p.name for p in tmp.iterdir())
        (tmp / MARK).write_text(json.dumps({"made_by": TOOL, "files": written}))
        _replace(final, tmp, name)
        return d
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


PREFIX = "auv:"  # the catalog's own Item properties
_BOOKKEEPING = ("asset_bytes",)  # the files' sizes, for the re-run's check; not a result


def properties(item: dict) -> dict:
    """A mission Item's own results (its ``auv:`` properties) by their names without the
    prefix, as the missions GeoParquet's columns and the report's page hold them."""
    n = len(PREFIX)
    return {
        k[n:]: v
        for k, v in item.get("properties", {}).items()
        if k.startswith(PREFIX) and k[n:] not in _BOOKKEEPING
    }


def json_value(v):
    """``v`` as JSON holds it: a numpy scalar as its Python value, a float that is not finite
    as None (JSON has no NaN)."""
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def _mission_files(folder: Path, name: str, mid: str, traj, maps, crs_wkt):
    """Write a mission's files; returns its assets, its geometry and bbox (WGS84 when the DEM
    has a CRS: the waypoint route, or the grid path without a flight) and its flight's
    properties."""
    from .files import LONLAT_FILES, PARQUET, to_lonlat, write_grid_path, write_mission_files

    f = traj.flight
    props = {}
    if f is None:
        write_grid_path(folder / "grid-path.parquet", traj, crs_wkt)
        files = {"grid-path": ("grid-path.parquet", "planned grid path (cells)", PARQUET, ["data"])}
        xy = traj.points[:, :2]
    else:
        sea = maps.parameters.sea_level_m
        files = write_mission_files(folder, name, mid, traj, crs_wkt, sea)
        skipped = files.pop("skipped", None)
        xy = f.waypoints[:, :2]
        props = {
            f"auv:{k}": json_value(v)
            for k, v in (
                ("flown_length_m", f.flown_length_m),
                ("route_length_m", f.route_length_m),
                ("flown_ridge_ratio", f.ridge_ratio),
                ("duration_s", f.duration_s),
                ("max_pitch_deg", f.max_pitch_deg),
                ("min_turn_radius_m", f.min_turn_radius_m),
                ("waypoints", len(f.waypoints)),
                ("energy_wh", f.energy_wh),
                ("altitude_median_m", f.altitude_median_m),
                ("altitude_p90_m", f.altitude_p90_m),
                ("min_altitude_m", f.altitude_min_m),
                ("vertical_reversals_per_km", f.reversals_per_km),
                ("unknown_seabed_samples", f.unknown_seabed_samples),
                ("legs_shorter_than_turn_radius", f.short_legs),
            )
        }
        if f.via_miss_m:  # how close the flown track comes to each via point
            props["auv:via_miss_m"] = [round(v, 2) for v in f.via_miss_m]
        if f.max_depth_m is not None:  # the rating kept, and how far it was flown at
            props["auv:max_depth_m"] = f.max_depth_m
            props["auv:at_rated_depth_m"] = json_value(f.at_rated_depth_m)
        props["auv:smoothing"] = f.smoothing
        props["auv:vehicle"] = {**f.vehicle.to_dict(), "min_turn_radius_m": f.turn_radius_m}
        if f.problems:
            props["auv:flight_problems"] = list(f.problems)
        if skipped:
            props["auv:skipped_files"] = skipped
        if crs_wkt is None:
            props["auv:skipped_files"] = (
                f"{', '.join(LONLAT_FILES)}: the DEM has no coordinate reference system, so "
                "there are no latitudes and longitudes"
            )
    ll = to_lonlat(crs_wkt, xy[:, 0], xy[:, 1])
    pts = np.column_stack(ll) if ll is not None else xy
    geom = {"type": "LineString", "coordinates": pts.tolist()}
    bbox = [float(pts[:, 0].min()), float(pts[:, 1].min())]
    bbox += [float(pts[:, 0].max()), float(pts[:, 1].max())]
    return files, geom, bbox, props


@functools.lru_cache(maxsize=8)
def _epsg_or_wkt2(crs_wkt: str) -> tuple:
    """(EPSG code or None, WKT2) of a CRS: pyproj's EPSG lookup is slow, so once per job's
    maps rather than once per mission."""
    from pyproj import CRS

    crs = CRS.from_wkt(crs_wkt)
    return crs.to_epsg(), crs.to_wkt()


def _projection(item, crs_wkt: str, traj) -> None:
    """The STAC projection extension: the maps' CRS (an EPSG code when it has one, else
    WKT2) and the track's bounding box in it."""
    from pystac.extensions.projection import ProjectionExtension

    proj = ProjectionExtension.ext(item, add_if_missing=True)
    epsg, wkt2 = _epsg_or_wkt2(crs_wkt)
    proj.code = f"EPSG:{epsg}" if epsg else None
    if not epsg:
        proj.wkt2 = wkt2
    f = traj.flight
    xy = np.column_stack([f.x, f.y]) if f is not None else traj.points[:, :2]
    proj.bbox = [float(v) for v in (*xy.min(axis=0), *xy.max(axis=0))]


def write_catalog(
    root: Path, name: str, mission_names: list[str], *, description: str, lonlat: bool
) -> Path:
    """The root catalog, the Collection and the missions GeoParquet, from the Items on disk."""
    import geopandas as gpd
    import pystac
    from shapely.geometry import shape

    root = Path(root)
    items = [finished(root, m) for m in mission_names]
    items = [it for it in items if it is not None]
    rows, geoms = [], []
    for it in items:
        row = {"id": it["id"], "datetime": it["properties"]["datetime"]}
        row.update(
            {k: (json.dumps(v) if isinstance(v, list) else v) for k, v in properties(it).items()}
        )
        rows.append(row)
        geoms.append(shape(it["geometry"]) if it.get("geometry") else None)
    gdf = gpd.GeoDataFrame(rows, geometry=geoms, crs="EPSG:4326" if lonlat else None)
    coll_dir = root / COLLECTION
    coll_dir.mkdir(parents=True, exist_ok=True)
    write_atomically(coll_dir / "missions.parquet", write=gdf.to_parquet)

    boxes = [it["bbox"] for it in items if it.get("bbox")]
    bbox = (
        [
            min(b[0] for b in boxes),
            min(b[1] for b in boxes),
            max(b[2] for b in boxes),
            max(b[3] for b in boxes),
        ]
        if boxes
        else [0.0, 0.0, 0.0, 0.0]
    )
    times = sorted(it["properties"]["datetime"] for it in items)
    t0 = _dt.datetime.fromisoformat(times[0]) if times else _dt.datetime.now(_dt.UTC)
    t1 = _dt.datetime.fromisoformat(times[-1]) if times else t0
    coll = pystac.Collection(
        COLLECTION,
        description,
        pystac.Extent(pystac.SpatialExtent([bbox]), pystac.TemporalExtent([[t0, t1]])),
        title=f"{name}: planned missions",
    )
    coll.add_asset(
        "missions",
        pystac.Asset(
            "./missions.parquet",
            title="all missions",
            media_type="application/vnd.apache.parquet",
            roles=["data"],
        ),
    )
    cd = coll.to_dict(include_self_link=False, transform_hrefs=False)
    cd["links"] = [
        {"rel": "root", "href": "../catalog.json", "type": "application/json"},
        {"rel": "parent", "href": "../catalog.json", "type": "application/json"},
    ] + [
        {"rel": "item", "href": f"./{it['id']}/{it['id']}.json", "type": "application/geo+json"}
        for it in items
    ]
    cat = pystac.Catalog(name, description, title=name)
    kd = cat.to_dict(include_self_link=False, transform_hrefs=False)
    kd["links"] = [
        {"rel": "root", "href": "./catalog.json", "type": "application/json"},
        {"rel": "child", "href": f"./{COLLECTION}/collection.json", "type": "application/json"},
    ]
    _atomic_json(coll_dir / "collection.json", cd)
    _atomic_json(root / "catalog.json", kd)
    return root / "catalog.json"


# stands in for an Item's geometry while the rest is indented (NUL: no other string has it)
_GEOMETRY_TOKEN = "\x00geometry\x00"


def _item_text(item: dict) -> str:
    """An Item's JSON indented as ``json.dumps(item, indent=1)`` but its geometry on one line:
    indenting runs json's Python encoder, slow on the geometry's thousands of numbers; on one
    line the C encoder writes them."""
    if not item.get("geometry"):
        return json.dumps(item, indent=1)
    text = json.dumps({**item, "geometry": _GEOMETRY_TOKEN}, indent=1)
    return text.replace(json.dumps(_GEOMETRY_TOKEN), json.dumps(item["geometry"]), 1)


def _atomic_json(path: Path, doc: dict) -> None:
    write_atomically(path, json.dumps(doc, indent=1))
