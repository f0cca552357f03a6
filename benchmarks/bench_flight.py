"""Issues 16 and 61 figures: missions a vehicle can fly.

1. Every mission of the demo job (tasks/demo.toml, synthetic 2000^2 at 30 m, 8 missions) and of
   the real-bathymetry job (tasks/topobathy.toml, 5 missions), run as jobs with the default
   vehicle, checked from the catalog's own files against independent references: the flown
   track (track.parquet) and the waypoints' straight legs (waypoints.csv, sampled every 5 m)
   against every DEM grid point and against the continuous seabed (scipy's bilinear
   interpolation sampled finely around the route; KD-trees, 3-D distances: clearance >= R),
   the altitude and vertical reversals per km, legs shorter than the turn radius, and a figure
   of the depth profiles (docs/flight-profiles.png); pitch between
   consecutive samples; the turn radius as the circumradius of every three consecutive track
   samples; the flown length against omega x L* (scipy.sparse.csgraph.dijkstra on the whole
   fine graph built here); waypoints against the grid path's cells (target < 10 %).
2. 10000^2: what producing the flown track and every file (and the quick-look, apart) adds to a
   mission's planning time (target < 20 %).

    .venv/bin/python benchmarks/bench_flight.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import OUT, far_missions, machine, maps_store
from _report import Report, figure_dir
from bench_certify import csgraph, optimum

ROOT = Path(__file__).resolve().parents[1]


def circumradii(x, y) -> np.ndarray:
    a = np.hypot(x[1:-1] - x[:-2], y[1:-1] - y[:-2])
    b = np.hypot(x[2:] - x[1:-1], y[2:] - y[1:-1])
    c = np.hypot(x[2:] - x[:-2], y[2:] - y[:-2])
    cross = (x[1:-1] - x[:-2]) * (y[2:] - y[:-2]) - (y[1:-1] - y[:-2]) * (x[2:] - x[:-2])
    with np.errstate(divide="ignore", invalid="ignore"):
        r = a * b * c / (2 * np.abs(cross))
    return np.where((np.abs(cross) < 1e-9 * a * b) | (a == 0) | (b == 0), np.inf, r)


def legs(xyz: np.ndarray, step: float) -> np.ndarray:
    out = [xyz[:1]]
    for p, q in zip(xyz[:-1], xyz[1:], strict=True):
        n = max(1, int(math.ceil(math.hypot(*(q - p)[:2]) / step)))
        out.append(p + (np.arange(1, n + 1) / n)[:, None] * (q - p))
    return np.concatenate(out)


def seabed_near(
    z: np.ndarray, x: np.ndarray, y: np.ndarray, pts: np.ndarray, reach: float, fine: float
):
    """The continuous seabed (bilinear between the grid points ``z`` at coordinates ``x``,
    ``y``: scipy's interpolation) sampled about every ``fine`` metres over every grid square
    within ``reach`` of a point of ``pts`` (x, y), as a KD-tree of (x, y, z), and the sampling's
    covering radius in plan (a distance to the samples exceeds the true one by at most that)."""
    from scipy.interpolate import RegularGridInterpolator
    from scipy.spatial import cKDTree

    a = abs(float(x[1] - x[0]))
    iy = np.argsort(y)
    f = RegularGridInterpolator((y[iy], x), z[iy])
    ci = np.clip(np.rint((pts[:, 0] - x[0]) / (x[1] - x[0])), 0, len(x) - 2).astype(int)
    ri = np.clip(np.rint((pts[:, 1] - y[0]) / (y[1] - y[0])), 0, len(y) - 2).astype(int)
    k = int(math.ceil(reach / a)) + 1
    squares = set()
    for dr in range(-k, k + 1):
        for dc in range(-k, k + 1):
            rr = np.clip(ri + dr, 0, len(y) - 2)
            cc = np.clip(ci + dc, 0, len(x) - 2)
            squares.update(zip(rr.tolist(), cc.tolist(), strict=True))
    sq = np.array(sorted(squares))
    n = int(math.ceil(a / fine))
    u = np.linspace(0.0, 1.0, n + 1)
    uu, vv = (g.ravel() for g in np.meshgrid(u, u))
    sx = (x[sq[:, 1]][:, None] + uu[None, :] * (x[1] - x[0])).ravel()
    sy = (y[sq[:, 0]][:, None] + vv[None, :] * (y[1] - y[0])).ravel()
    sz = f(np.column_stack([sy, sx]))
    keep = np.isfinite(sz)
    cover = a / n / math.sqrt(2.0)
    return cKDTree(np.column_stack([sx[keep], sy[keep], sz[keep]])), cover


def run(job: Path, catalog: Path) -> Path:
    """Run a job file into ``catalog`` (a copy of the job with that [output] catalog)."""
    import tomllib

    import pipeline

    text = job.read_text()
    doc = tomllib.loads(text)
    lines = [ln for ln in text.splitlines() if not ln.strip().startswith("catalog")]
    if "path" in doc["dem"]:
        p = (job.parent / doc["dem"]["path"]).resolve()
        lines = [f'path = "{p}"' if ln.strip().startswith("path") else ln for ln in lines]
    tmp = catalog.parent / f"{catalog.name}.toml"
    tmp.write_text(
        "\n".join(lines).replace("[output]", "") + f'\n[output]\ncatalog = "{catalog}"\n'
    )
    res = pipeline.run_job(tmp, overwrite=True)
    return Path(res.maps_store)


# waypoints.csv writes latitude and longitude to 8 decimals (about a millimetre): a leg read
# back from it is a leg shorter than the turn radius only when shorter by more than this
LEG_ROUNDING = 0.01


def check_catalog(name: str, catalog: Path, store: Path) -> list[dict]:
    import csv

    import geopandas as gpd
    from pyproj import Transformer
    from scipy.spatial import cKDTree

    import pipeline

    ds = pipeline.open_maps(store)
    m = pipeline.open_store(store)
    a = m.cell_size
    z = ds["elevation"].values.astype(np.float64)
    xx, yy = np.meshgrid(ds["x"].values, ds["y"].values)
    keep = np.isfinite(z)
    tree = cKDTree(np.column_stack([xx[keep], yy[keep], z[keep]]))
    surface, ok = ds["safety"].values, ds["passable"].values.astype(bool)
    graph = csgraph(surface, ok, a)
    R = m.parameters.clearance_m
    sea = m.parameters.sea_level_m
    to_map = Transformer.from_crs("EPSG:4326", m.crs_wkt, always_xy=True) if m.crs_wkt else None
    rows = []
    for item_path in sorted((catalog / "missions").glob("*/*.json")):
        it = json.loads(item_path.read_text())
        p = it["properties"]
        folder = item_path.parent
        if "track" not in it["assets"]:
            rows.append(dict(map=name, mission=p["auv:name"], status=p["auv:status"]))
            continue
        tr = gpd.read_parquet(folder / "track.parquet")
        grid = gpd.read_parquet(folder / "grid-path.parquet")
        x, y, zz = tr["x"].values, tr["y"].values, tr["z"].values
        d_track = tree.query(np.column_stack([x, y, zz]))[0].min()
        with open(folder / "waypoints.csv") as fh:
            w = list(csv.DictReader(fh))
        if to_map is not None:
            wx, wy = to_map.transform([float(r["lon"]) for r in w], [float(r["lat"]) for r in w])
        else:
            wx, wy = [float(r["x_m"]) for r in w], [float(r["y_m"]) for r in w]
        wz = sea - np.array([float(r["depth_m"]) for r in w])
        route = legs(np.column_stack([wx, wy, wz]), 5.0)
        d_legs = tree.query(route)[0].min()
        # against the continuous (bilinear) seabed, sampled finely around the route
        dense_track = legs(np.column_stack([x, y, zz]), 5.0)
        fine = min(a / 4, R / 20)
        bil, cover = seabed_near(
            z, ds["x"].values, ds["y"].values, np.vstack([route, dense_track])[:, :2], R, fine
        )
        b_track = float(bil.query(dense_track)[0].min())
        b_legs = float(bil.query(route)[0].min())
        wleg = np.hypot(np.diff(wx), np.diff(wy))
        turn_m = p["auv:vehicle"]["min_turn_radius_m"]
        thin = slice(None, None, max(1, len(x) // 1500))
        profile = dict(
            s_km=(tr["s_m"].values[thin] / 1e3).tolist(),
            z=zz[thin].tolist(),
            seabed=tr["seabed_m"].values[thin].tolist(),
        )
        tan = math.tan(math.radians(p["auv:vehicle"]["max_pitch_deg"]))
        pitch = np.degrees(np.arctan2(np.abs(np.diff(zz)), np.hypot(np.diff(x), np.diff(y))))
        wl = np.hypot(np.diff(wx), np.diff(wy))
        # the CSV's depths have 2 decimals: a leg may seem steeper by 1 cm over its length
        wexcess = float(np.max(np.abs(np.diff(wz)) - tan * wl - 0.011, initial=-np.inf))
        s = tuple(int(v) for v in grid[["row", "col"]].values[0])
        g = tuple(int(v) for v in grid[["row", "col"]].values[-1])
        opt = optimum(graph, ok.shape, s, g)
        flown = float(np.hypot(np.hypot(np.diff(x), np.diff(y)), np.diff(zz)).sum())
        rlen = float(np.hypot(np.hypot(np.diff(wx), np.diff(wy)), np.diff(wz)).sum())
        spacing = float(np.hypot(np.diff(x), np.diff(y)).max())
        rows.append(
            dict(
                map=name,
                mission=p["auv:name"],
                status=p["auv:status"],
                planner=p["auv:planner"],
                omega=p["auv:omega"],
                cells=len(grid),
                waypoints=len(w),
                clearance_track=float(d_track),
                clearance_legs=float(d_legs),
                bilinear_track=b_track,
                bilinear_legs=b_legs,
                bilinear_cover=cover,
                short_legs=int(np.sum(wleg < turn_m - LEG_ROUNDING)),
                shortest_leg=float(wleg.min()),
                altitude_median=p.get("auv:altitude_median_m"),
                altitude_p90=p.get("auv:altitude_p90_m"),
                reversals_km=p.get("auv:vertical_reversals_per_km"),
                unknown_seabed=p.get("auv:unknown_seabed_samples", 0),
                profile=profile,
                R=R,
                max_pitch=float(pitch.max()),
                leg_pitch_excess_m=wexcess,
                pitch_limit=p["auv:vehicle"]["max_pitch_deg"],
                min_radius=float(circumradii(x, y).min()),
                radius_limit=p["auv:vehicle"]["min_turn_radius_m"],
                grid_len=p["auv:length_m"],
                flown_len=flown,
                route_len=rlen,
                opt=opt,
                flown_over_opt=flown / opt,
                route_over_opt=rlen / opt,
                spacing_cells=spacing / a,
                ridge_grid=p["auv:ridge_ratio"],
                ridge_flown=p["auv:flown_ridge_ratio"],
                duration_h=p["auv:duration_s"] / 3600,
            )
        )
        r = rows[-1]
        print(
            f"  {name} {r['mission']}: clearance {r['clearance_track']:.2f} / legs "
            f"{r['clearance_legs']:.2f} m (R {R:g}), bilinear {b_track:.2f} / {b_legs:.2f} m, "
            f"altitude {r['altitude_median']:.0f} / {r['altitude_p90']:.0f} m, "
            f"{r['reversals_km']:.2f} reversals/km, {r['short_legs']} legs < {turn_m:g} m, "
            f"pitch {r['max_pitch']:.2f}, radius "
            f"{r['min_radius']:.1f}, flown {r['flown_over_opt']:.4f} L* (omega "
            f"{r['omega']}), {r['waypoints']} waypoints / {r['cells']} cells",
            flush=True,
        )
    return rows


def overhead(n: int, k: int) -> dict:
    """Planning time of k missions on the n^2 store, and what the flight and files add."""
    from distributed import Client

    import pipeline
    from pipeline.dem.synthetic import local_crs
    from pipeline.flight.fly import with_flight
    from pipeline.outputs.files import write_mission_files
    from pipeline.outputs.plots import mission_quicklook
    from pipeline.runtime.cluster import local_cluster

    store = maps_store(n)
    m = pipeline.open_store(store)
    # the benchmark's maps predate the synthetic maps' CRS: the one a job gives this map now
    crs = m.crs_wkt or local_crs(-44.83, 26.14, n * 30.0 / 2, n * 30.0 / 2).to_wkt()
    ok = pipeline.open_maps(store)["passable"]
    ms = far_missions(ok, n, k + 1, seed=n + 1)
    rows = []
    with (
        local_cluster(dashboard_address=None) as cluster,
        Client(cluster) as client,
        tempfile.TemporaryDirectory() as tmp,
    ):
        t = pipeline.plan(m, *ms[0], planner="ra_star", omega=2.0, client=client)  # warm-up
        with_flight(m, t, {})
        for i, (s, g) in enumerate(ms[1:]):
            t0 = time.perf_counter()
            t = pipeline.plan(m, s, g, planner="ra_star", omega=2.0, client=client)
            t1 = time.perf_counter()
            with_flight(m, t, {})
            t2 = time.perf_counter()
            folder = Path(tmp) / f"m{i}"
            folder.mkdir()
            write_mission_files(folder, f"m{i}", f"m{i}", t, crs, 0.0)
            t3 = time.perf_counter()
            mission_quicklook(m, t, folder / "quicklook.png", title=f"m{i}", crs_wkt=crs)
            t4 = time.perf_counter()
            f = t.flight
            rows.append(
                dict(
                    plan_s=t1 - t0,
                    fly_s=t2 - t1,
                    files_s=t3 - t2,
                    quicklook_s=t4 - t3,
                    cells=len(t.cells),
                    samples=len(f.x),
                    waypoints=len(f.waypoints),
                    problems=f.problems,
                    status=t.status,
                )
            )
            r = rows[-1]
            print(
                f"  {n}^2 mission {i}: plan {r['plan_s']:.3f} s, flight {r['fly_s']:.3f} s, "
                f"files {r['files_s']:.3f} s, quick-look {r['quicklook_s']:.2f} s; "
                f"{r['cells']} cells, {r['waypoints']} waypoints",
                flush=True,
            )
    med = {key: statistics.median(r[key] for r in rows) for key in rows[0] if key.endswith("_s")}
    share = [(r["fly_s"] + r["files_s"]) / r["plan_s"] for r in rows]
    return dict(
        n=n, rows=rows, median=med, share_median=statistics.median(share), share_max=max(share)
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="the demo job only, 4000^2")
    ap.add_argument("--report-only", action="store_true")
    args = ap.parse_args()
    print(machine(), flush=True)
    saved = OUT / ("flight-quick.json" if args.quick else "flight.json")
    rep = Report(
        "flight",
        9,
        "Flyable missions: the flown track, waypoints and files",
        ".venv/bin/python benchmarks/bench_flight.py",
        args.quick,
    )
    if args.report_only:
        d = json.loads(saved.read_text())
        rows, big = d["rows"], d["big"]
    else:
        OUT.mkdir(exist_ok=True)
        rows = []
        jobs = [("demo (synthetic 2000^2, 30 m)", "demo")]
        if not args.quick:
            sys.path.insert(0, str(ROOT / "tasks" / "data"))
            import subprocess

            subprocess.run(
                [sys.executable, str(ROOT / "tasks" / "data" / "make_topobathy.py")],
                check=True,
                cwd=ROOT,
            )
            jobs.append(("real bathymetry (topobathy, 150 m)", "topobathy"))
        for name, job in jobs:
            cat = OUT / f"flight-{job}"
            store = run(ROOT / "tasks" / f"{job}.toml", cat)
            rows += check_catalog(name, cat, store)
            if job == "demo":  # the README's picture of one mission
                import shutil

                shutil.copyfile(
                    cat / "missions" / "axis-crossing-lagrangian" / "quicklook.png",
                    figure_dir(args.quick) / "flight-quicklook.png",
                )
        big = overhead(4000 if args.quick else 10000, 3 if args.quick else 10)
        saved.write_text(json.dumps(dict(rows=rows, big=big)))
    flown = [r for r in rows if "clearance_track" in r]
    rep.p(f"""Each job run with the default vehicle (1.5 m/s, pitch <= 20 deg, turn radius one
          cell, at most 50 m); every mission checked from the catalog's own files: the flown
          track (track.parquet) and the waypoints' straight legs (waypoints.csv sampled every
          5 m) against every DEM grid point with scipy's KD-tree (3-D distance); the pitch
          between consecutive samples of the track and along every leg (the legs' depths are
          read from the CSV, rounded to 1 cm: a leg counts as steeper than the limit when its
          rise exceeds tan(limit) x its length by more than that rounding); the turn radius
          as the circumradius of every three consecutive track samples; the flown 3-D length
          against omega x L* (scipy.sparse.csgraph.dijkstra on the whole fine graph built in
          the script). {len(flown)} missions flown of {len(rows)}.""")
    rep.table(
        [
            "map",
            "mission",
            "planner, omega",
            "clearance track / legs (m), R",
            "max pitch deg, track (limit)",
            "tightest turn m (min)",
            "flown / L*",
            "route / L*",
            "grid / flown ridge",
            "waypoints / cells",
            "duration h",
        ],
        [
            [
                r["map"].split(" (")[0],
                r["mission"],
                f"{r['planner']}, {r['omega']:g}",
                f"{r['clearance_track']:.1f} / {r['clearance_legs']:.1f}, {r['R']:g}",
                f"{r['max_pitch']:.2f} ({r['pitch_limit']:g})",
                f"{r['min_radius']:.1f} ({r['radius_limit']:g})",
                f"{r['flown_over_opt']:.3f} (<= {r['omega']:g})",
                f"{r['route_over_opt']:.3f}",
                f"{100 * r['ridge_grid']:.0f} / {100 * r['ridge_flown']:.0f} %",
                f"{r['waypoints']} / {r['cells']} ({100 * r['waypoints'] / r['cells']:.1f} %)",
                f"{r['duration_h']:.1f}",
            ]
            for r in flown
        ],
    )
    bad = {
        "clearance": sum(
            min(r["clearance_track"], r["clearance_legs"], r["bilinear_track"], r["bilinear_legs"])
            < r["R"] * (1 - 1e-6)
            for r in flown
        ),
        "pitch": sum(
            r["max_pitch"] > r["pitch_limit"] + 1e-6 or r["leg_pitch_excess_m"] > 0 for r in flown
        ),
        "turn": sum(r["min_radius"] < r["radius_limit"] * (1 - 1e-6) for r in flown),
        "bound": sum(
            max(r["flown_over_opt"], r["route_over_opt"]) > r["omega"] * (1 + 1e-9) for r in flown
        ),
        "waypoints": sum(r["waypoints"] >= 0.1 * r["cells"] for r in flown),
    }
    share = max(r["waypoints"] / r["cells"] for r in flown)
    over = [
        f"{r['mission']} (omega {r['omega']:g}: flown {r['flown_over_opt']:.4f} L*, status "
        f"{r['status']})"
        for r in flown
        if max(r["flown_over_opt"], r["route_over_opt"]) > r["omega"] * (1 + 1e-9)
    ]
    many = [
        f"{r['mission']} ({100 * r['waypoints'] / r['cells']:.0f} %)"
        for r in flown
        if r["waypoints"] >= 0.1 * r["cells"]
    ]
    statuses = sorted({r["status"] for r in flown})
    counts = ", ".join(f"{sum(r['status'] == st for r in flown)} {st}" for st in statuses)
    rep.p(f"""Violations over {len(flown)} missions: clearance {bad["clearance"]}, pitch
          {bad["pitch"]}, turn radius {bad["turn"]}; flown length above omega x L*:
          {bad["bound"]}{": " + "; ".join(over) if over else ""}. Waypoints at or above 10 %
          of the grid path's cells: {bad["waypoints"]}{": " + ", ".join(many) if many else ""}
          (largest share {100 * share:.1f} %). Samples at most
          {max(r["spacing_cells"] for r in flown):.2f} cells apart. Statuses: {counts}.""")
    rep.h("Against the continuous seabed; near the bottom")
    rep.p("""The same files against the seabed between grid points: scipy's bilinear
          interpolation of the store's elevation, sampled every min(cell / 4, R / 20) metres
          over every grid square within R of the route (a KD-tree; a distance to the samples
          exceeds the true one by at most the sampling's covering radius, given), the track
          and the legs densified every 5 m. Altitude and reversals are the Item's
          (`auv:altitude_median_m`, `auv:altitude_p90_m`, `auv:vertical_reversals_per_km`);
          short legs: waypoint legs shorter than the vehicle's minimum turn radius (by more than
          the 1 cm the CSV's rounded latitudes and longitudes can take off a leg).""")
    rep.table(
        [
            "mission",
            "bilinear clearance track / legs m (R; sampling)",
            "altitude median / p90 m",
            "reversals / km",
            "legs < turn radius (shortest m)",
            "samples by unknown squares",
        ],
        [
            [
                r["mission"],
                f"{r['bilinear_track']:.1f} / {r['bilinear_legs']:.1f} ({r['R']:g}; "
                f"{r['bilinear_cover']:.1f})",
                f"{r['altitude_median']:.0f} / {r['altitude_p90']:.0f}",
                f"{r['reversals_km']:.2f}",
                f"{r['short_legs']} ({r['shortest_leg']:.0f})",
                r["unknown_seabed"],
            ]
            for r in flown
        ],
    )
    below = sum(min(r["bilinear_track"], r["bilinear_legs"]) < r["R"] * (1 - 1e-6) for r in flown)
    rep.p(f"""Below R from the bilinear seabed: {below} of {len(flown)} missions.""")
    png = figure_dir(args.quick) / "flight-profiles.png"
    profiles_figure(flown, png)
    rep.figure(png, "flown heights, the bilinear seabed under them and the seabed + R")
    med = big["median"]
    rep.h(f"Cost at {big['n']}^2")
    rep.p(f"""{len(big["rows"])} missions at least half the map apart (ra_star, omega 2, MCPC,
          a LocalCluster of 2 workers), each then flown and written. Medians: planning
          {med["plan_s"]:.3f} s, the flown track and waypoints {med["fly_s"]:.3f} s, every
          file (track and grid path GeoParquet, waypoints GeoJSON and CSV, QGC WPL, KML, IMC)
          {med["files_s"]:.3f} s: the flight and the files add {100 * big["share_median"]:.0f}
          % to the planning time (worst mission {100 * big["share_max"]:.0f} %; target < 20
          %). The quick-look PNG (plan view and profile, matplotlib) takes
          {med["quicklook_s"]:.2f} s more and is drawn as before.""")
    rep.table(
        ["mission", "cells", "waypoints", "plan s", "flight s", "files s", "quick-look s"],
        [
            [i, r["cells"], r["waypoints"], r["plan_s"], r["fly_s"], r["files_s"], r["quicklook_s"]]
            for i, r in enumerate(big["rows"])
        ],
    )
    limits = sum(bad[k] for k in ("clearance", "pitch", "turn"))
    few = sum(r["waypoints"] < 0.1 * r["cells"] for r in flown)
    rep.headline(
        "flight",
        58,
        "flyable missions (demo + real bathymetry): flown track against the DEM and the "
        "bilinear seabed, bound, waypoints, cost",
        f"{limits} violations of clearance, pitch, turn radius in {len(flown)} missions; "
        f"flown <= omega L* on {len(flown) - bad['bound']} (the others uncertified); "
        f"waypoints < 10 % of cells on {few} (max {100 * share:.1f} %); +"
        f"{100 * big['share_median']:.0f} % time at {big['n']}^2",
        target="0 violations; < 10 % of cells; < 20 %",
    )
    rep.save()


def profiles_figure(flown: list[dict], png: Path) -> None:
    """The depth profile of up to six missions: the vehicle's height, the seabed under it and
    the seabed raised by R, against the distance flown."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pick = flown[:: max(1, len(flown) // 6)][:6]
    fig, axes = plt.subplots(len(pick), 1, figsize=(10, 2.2 * len(pick)), squeeze=False)
    for ax, r in zip(axes[:, 0], pick, strict=True):
        pr = r["profile"]
        sea = np.array(pr["seabed"])
        ax.fill_between(pr["s_km"], sea, sea.min() - 100, color="0.75", label="seabed (bilinear)")
        ax.plot(pr["s_km"], sea + r["R"], color="tab:orange", lw=0.8, label="seabed + R")
        ax.plot(pr["s_km"], pr["z"], color="tab:blue", lw=1.2, label="vehicle")
        ax.set_title(
            f"{r['map'].split(' (')[0]}: {r['mission']} (R {r['R']:g} m; "
            f"{r['reversals_km']:.2f} reversals/km)",
            fontsize=9,
        )
        ax.set_ylabel("height (m)")
    axes[-1, 0].set_xlabel("distance flown (km)")
    axes[0, 0].legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
