"""The results catalog: a self-contained STAC catalog of missions (pystac), GeoParquet tables
(geopandas) and quick-look PNGs.

Layout under the catalog directory::

    catalog.json                      root catalog
    missions/collection.json          the job's Collection; asset missions.parquet
    missions/missions.parquet         one row per mission (LineString, auv: properties)
    missions/<id>/<id>.json           one Item per mission (failed ones too)
    missions/<id>/track.parquet       the trajectory points (x, y, z) as GeoParquet
    missions/<id>/quicklook.png       hillshade, ridge cells, track coloured by clearance

A mission's folder is written beside its place and renamed into it when complete, so the
Item's presence means the mission is finished (a re-run skips it).
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import os
import re
import shutil
import uuid
from pathlib import Path

import numpy as np

COLLECTION = "missions"


def _transformer(crs_wkt: str | None):
    if not crs_wkt:
        return None
    from pyproj import CRS, Transformer

    crs = CRS.from_wkt(crs_wkt)
    if crs.is_geographic:
        return None
    return Transformer.from_crs(crs, "EPSG:4326", always_xy=True)


def _lonlat(points_xy: np.ndarray, crs_wkt: str | None) -> np.ndarray:
    tr = _transformer(crs_wkt)
    if tr is None:
        return points_xy
    lon, lat = tr.transform(points_xy[:, 0], points_xy[:, 1])
    return np.column_stack([lon, lat])


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
        return json.loads(p.read_text())
    except (OSError, ValueError):
        return None


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
) -> dict:
    """Write the Item and assets of the mission ``name`` atomically; returns the Item as a
    dict. ``mission["fingerprint"]``, when given, is kept as ``auv:fingerprint`` (what a re-run
    compares to decide whether the mission changed)."""
    import pystac

    mid = mission_id(name)
    final = mission_dir(root, name)
    tmp = final.parent / f".{mid}.tmp-{uuid.uuid4().hex[:8]}"
    tmp.mkdir(parents=True)
    try:
        ok = traj.planned and len(traj.cells) > 1
        geom = bbox = None
        assets = {}
        if ok:
            ll = _lonlat(traj.points[:, :2], crs_wkt)
            geom = {"type": "LineString", "coordinates": ll.tolist()}
            bbox = [
                float(ll[:, 0].min()),
                float(ll[:, 1].min()),
                float(ll[:, 0].max()),
                float(ll[:, 1].max()),
            ]
            _track_parquet(tmp / "track.parquet", traj, crs_wkt)
            assets["track"] = pystac.Asset(
                "./track.parquet",
                title="trajectory points x, y, z",
                media_type="application/vnd.apache.parquet",
                roles=["data"],
            )
            if quicklook:
                from .plots import mission_quicklook

                title = "".join(c if c.isprintable() else "?" for c in name)
                mission_quicklook(maps, traj, tmp / "quicklook.png", title=title)
                assets["quicklook"] = pystac.Asset(
                    "./quicklook.png",
                    title="quick look",
                    media_type=pystac.MediaType.PNG,
                    roles=["overview"],
                )
        props = {
            f"auv:{k}": _num(v)
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
        props.update(
            {
                "auv:name": name,
                "auv:fingerprint": mission.get("fingerprint"),
                "auv:planner": traj.planner,
                "auv:status": traj.status,
                "auv:message": traj.message,
                "auv:run_id": run_id,
                "auv:start": [
                    _num(v) for v in mission.get("start_input", mission.get("start", []))
                ],
                "auv:goal": [_num(v) for v in mission.get("goal_input", mission.get("goal", []))],
                "auv:sections": len(traj.extra.get("sections", [])) if ok else 0,
                "auv:expansions": int(traj.expansions),
            }
        )
        item = pystac.Item(mid, geom, bbox, _dt.datetime.now(_dt.UTC), props, assets=assets)
        d = item.to_dict(include_self_link=False, transform_hrefs=False)
        d["links"] = [
            {"rel": "root", "href": "../../catalog.json", "type": "application/json"},
            {"rel": "parent", "href": "../collection.json", "type": "application/json"},
            {"rel": "collection", "href": "../collection.json", "type": "application/json"},
        ]
        d["collection"] = COLLECTION
        (tmp / f"{mid}.json").write_text(json.dumps(d, indent=1))
        if final.exists():
            shutil.rmtree(final)
        os.rename(tmp, final)
        return d
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _num(v):
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def _track_parquet(path: Path, traj, crs_wkt: str | None) -> None:
    import geopandas as gpd
    from shapely import points

    gdf = gpd.GeoDataFrame(
        {"row": traj.cells[:, 0], "col": traj.cells[:, 1], "z": traj.points[:, 2]},
        geometry=points(traj.points[:, 0], traj.points[:, 1], traj.points[:, 2]),
        crs=crs_wkt or None,
    )
    gdf.to_parquet(path)


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
            {
                k.split(":", 1)[1]: (json.dumps(v) if isinstance(v, list) else v)
                for k, v in it["properties"].items()
                if k.startswith("auv:")
            }
        )
        rows.append(row)
        geoms.append(shape(it["geometry"]) if it.get("geometry") else None)
    gdf = gpd.GeoDataFrame(rows, geometry=geoms, crs="EPSG:4326" if lonlat else None)
    coll_dir = root / COLLECTION
    coll_dir.mkdir(parents=True, exist_ok=True)
    tmp = coll_dir / f".missions.parquet.tmp-{uuid.uuid4().hex[:8]}"
    gdf.to_parquet(tmp)
    os.replace(tmp, coll_dir / "missions.parquet")

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


def _atomic_json(path: Path, doc: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}")
    tmp.write_text(json.dumps(doc, indent=1))
    os.replace(tmp, path)
