"""Real data through the whole pipeline: matplotlib's sample bathymetry off Vancouver Island
(``topobathy.npz``: lon/lat, 2 arc-minutes, 56 % land) written as a CF NetCDF file, then
``pipeline run tasks/topobathy.toml``: import and reprojection, safety and ridge maps, five
missions given in lon/lat, the STAC catalog with GeoParquet tracks and quick-looks. The
catalog is read back with pystac and geopandas and the missions drawn on one map.

    .venv/bin/python benchmarks/bench_realdata.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

from _common import machine, run_job_timed
from _report import Report, figure_dir

ROOT = Path(__file__).resolve().parents[1]
JOB = ROOT / "tasks" / "topobathy.toml"
CATALOG = ROOT / "catalogs" / "topobathy"


def run_job() -> dict:
    subprocess.run(
        [sys.executable, str(ROOT / "tasks" / "data" / "make_topobathy.py")], check=True, cwd=ROOT
    )
    r = run_job_timed(JOB)
    sys.stderr.write(r["log"][-3000:])
    maps = re.search(r"built maps store \S+ \((.*)\) in ([\d.]+) s", r["log"])
    r.update(
        maps_s=float(maps.group(2)) if maps else float("nan"),
        maps_what=maps.group(1) if maps else "?",
    )
    return r


def crs_name(crs) -> str:
    if crs is None:
        return "none"
    op = getattr(crs, "coordinate_operation", None)
    return op.method_name if op is not None else crs.name


def read_catalog() -> tuple[list[dict], dict]:
    import geopandas as gpd
    import pystac

    import pipeline

    cat = pystac.Catalog.from_file(str(CATALOG / "catalog.json"))
    items = list(cat.get_items(recursive=True))
    rows = []
    for it in sorted(items, key=lambda i: i.id):
        p = it.properties
        track = gpd.read_parquet(CATALOG / "missions" / it.id / "grid-path.parquet")
        rows.append(
            dict(
                id=it.id,
                status=p["auv:status"],
                planner=p.get("auv:planner"),
                omega=p.get("auv:omega"),
                length_km=p.get("auv:length_m", 0) / 1e3,
                ridge_pct=100 * (p.get("auv:ridge_ratio") or 0.0),
                min_clearance_m=p.get("auv:min_clearance_m"),
                runtime_s=p.get("auv:runtime_s"),
                points=len(track),
                crs=crs_name(track.crs),
            )
        )
    maps = next(CATALOG.glob("maps-*.zarr"))
    ds = pipeline.open_maps(maps)
    info = dict(
        shape=tuple(ds.sizes[d] for d in ("y", "x")),
        cell=float(pipeline.cell_size(ds["elevation"])),
        land_pct=100 * float((ds["elevation"] > 0).mean()),
        passable_pct=100 * float(ds["passable"].mean()),
        ridge_pct=100 * float(ds["ridge"].mean()),
        maps=maps,
    )
    return rows, info


def plot(rows, info, png: Path) -> None:
    import geopandas as gpd
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from matplotlib.colors import ListedColormap

    import pipeline
    from pipeline.outputs.plots import hillshade_axes

    ds = pipeline.open_maps(info["maps"])
    fig, ax = plt.subplots(figsize=(11, 8.4), dpi=100)
    hillshade_axes(ax, ds["elevation"], max_side=1000)
    ok = ds["passable"].values[::2, ::2]
    x, y = ds["x"].values / 1e3, ds["y"].values / 1e3
    ax.imshow(
        np.ma.masked_where(ok, ok),
        extent=[x[0], x[-1], y[-1], y[0]],
        cmap=ListedColormap(["black"]),
        alpha=0.25,
        interpolation="nearest",
    )
    colours = ["#e41a1c", "#ff7f00", "#ffff33", "#f781bf", "white", "#984ea3"]
    for k, r in enumerate(rows):
        track = gpd.read_parquet(CATALOG / "missions" / r["id"] / "track.parquet")
        ax.plot(
            track["x"] / 1e3,
            track["y"] / 1e3,
            color=colours[k % 6],
            lw=1.8,
            label=f"{r['id']} ({r['planner']}, omega {r['omega']}): {r['length_km']:.0f} "
            f"km, {r['ridge_pct']:.0f} % ridge",
        )
    ax.legend(loc="upper right", fontsize=7.5, framealpha=0.9)
    ax.set_title(
        "Real bathymetry off Vancouver Island (matplotlib's topobathy, 150 m cells): "
        "five missions\n(shaded dark: not passable, i.e. land or under 150 m of "
        "water once the 100 m clearance is added)",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(png)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="the same (the case is small)")
    args = ap.parse_args()
    quick = args.quick
    print(machine(), flush=True)
    rep = Report(
        "realdata",
        7,
        "Real data: bathymetry off Vancouver Island",
        ".venv/bin/python benchmarks/bench_realdata.py",
        quick,
    )
    r = run_job()
    rows, info = read_catalog()
    unproven = [f"{x['id']} (omega {x['omega']:g})" for x in rows if x["status"] == "uncertified"]
    exit_note = (
        f" (EXIT_UNCERTIFIED: every mission planned; {', '.join(unproven)} reported uncertified)"
        if r["exit"] == 5
        else ""
    )
    rep.p(f"""matplotlib's sample grid `topobathy.npz` (real topography and bathymetry, 91 x 120
          points at 2 arc-minutes in lon/lat, -1437 to +2205 m) written as a CF NetCDF file by
          `tasks/data/make_topobathy.py`, then `pipeline run tasks/topobathy.toml`: the DEM is
          reprojected to a local azimuthal equidistant grid and resampled to 150 m cells
          ({info["shape"][0]} x {info["shape"][1]}; {info["land_pct"]:.0f} % land), the maps
          built ({r["maps_what"]}; {info["passable_pct"]:.1f} % passable, {info["ridge_pct"]:.1f}
          % ridge cells) in {r["maps_s"]:.1f} s, five missions planned from lon/lat endpoints on
          a LocalCluster of 2 workers, and the catalog written. The whole job: exit
          {r["exit"]}{exit_note}, **{r["wall_s"]:.1f} s** wall, client peak
          {r["client_peak_gib"]:.2f} GiB. The catalog read back with pystac and geopandas:""")
    rep.table(
        [
            "mission",
            "status",
            "planner",
            "omega",
            "length km",
            "ridge %",
            "min clearance m (3-D, from the DEM)",
            "planning s",
            "track points",
            "track CRS",
        ],
        [
            [
                x["id"],
                x["status"],
                x["planner"],
                x["omega"],
                x["length_km"],
                x["ridge_pct"],
                x["min_clearance_m"],
                x["runtime_s"],
                x["points"],
                x["crs"],
            ]
            for x in rows
        ],
    )
    rep.p("""The straits are channels, valleys of the seabed: the ridge network there is
          sparse, on the channel flanks, and much of it is too shallow to pass, so the ridge
          ratios are low; the continental slope, cut by canyons and spurs, has more. The
          2.4 km survey step is coarser than the 100 m clearance allows (cells of at most
          twice the clearance), so the job resamples it to 150 m (`[dem] resolution`): the
          terrain between survey points is then planar, which is all the data says.""")
    png = figure_dir(quick) / "topobathy-missions.png"
    plot(rows, info, png)
    rep.figure(png, "the five missions on the real bathymetry")
    ok = sum(x["status"] == "ok" for x in rows)
    rep.headline(
        "real",
        70,
        "real bathymetry (matplotlib's topobathy, lon/lat, with land): the whole job",
        f"{r['wall_s']:.0f} s, {ok} of {len(rows)} missions ok, min clearance "
        f"{min(x['min_clearance_m'] for x in rows if x['status'] == 'ok'):.1f} m",
        target="import, maps, missions, catalog, plots",
    )
    rep.save()
    print(json.dumps(dict(job=r, missions=rows), default=str))
    # exit 5 (the CLI's EXIT_UNCERTIFIED) is a complete job in which some missions could not be
    # proven within omega x L* and say so: the omega 1 mission over this rough terrain (README,
    # "Flyable missions"); any other code, or a failed mission, fails the benchmark
    uncertified_only = r["exit"] == 5 and all(x["status"] in ("ok", "uncertified") for x in rows)
    if r["exit"] != 0 and not uncertified_only:
        sys.exit(f"pipeline run {JOB} exited {r['exit']}")


if __name__ == "__main__":
    main()
