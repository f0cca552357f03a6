"""Issue 4 figures: ridge layers (fill + D8 + accumulation + ridge) Zarr -> Zarr on 2 workers
(the staged path build_maps uses)
for 10000^2 and 20000^2, pysheds against our in-memory path on 4000^2 (separate processes,
each with its own peak memory), and the ridge-over-hillshade PNG.

    .venv/bin/python benchmarks/bench_ridges.py [--quick] [--skip-20000] [--sides N ...]
"""

from __future__ import annotations

import argparse
import json

from _common import CLUSTER_PREAMBLE, OUT, machine, run_isolated
from _report import Report, faster, figure_dir

RIDGE_ZARR = (
    CLUSTER_PREAMBLE
    + """
out = "{out}"
dem = pipeline.open_dem(src, chunks=1024)
from pipeline.ridges import ridge_layers_staged, default_min_accumulation
marks = []
t0 = time.perf_counter()
filled, acc, rdg = ridge_layers_staged(dem.data, out + "/scratch.zarr",
                                       default_min_accumulation(30.0),
                                       log=lambda *a: marks.append(time.perf_counter()))
t1 = time.perf_counter()
xr.Dataset({{"accumulation": (("y", "x"), acc), "ridge": (("y", "x"), rdg)}}).to_zarr(
    out + "/ridge.zarr", mode="w", zarr_format=3, consolidated=False)
t4 = time.perf_counter()
share = float(xr.open_zarr(out + "/ridge.zarr", consolidated=False)["ridge"].mean())
peaks = worker_peaks()
t5 = time.perf_counter()
pipeline.build_maps(dem, out + "/maps.zarr", method="spherical", clearance=300.0,
                    overwrite=True)
t6 = time.perf_counter()
client.close(); cluster.close()
for p in ("scratch.zarr", "ridge.zarr", "maps.zarr"):
    shutil.rmtree(out + "/" + p, ignore_errors=True)
result = dict(total_s=t4 - t0, flood_and_fill_solve_s=marks[0] - t0,
              flow_summaries_and_solve_s=marks[1] - marks[0], acc_ridge_write_s=t4 - t1,
              ridge_share=share, worker_peak_gib=peaks, build_maps_s=t6 - t5)
"""
)

OURS_MEM = """
import time, numpy as np, pipeline
from pipeline.ridges import fill_single, accumulation_single, default_min_accumulation
z = pipeline.synthetic_dem(({n}, {n}), cell_size=30.0, seed=1, chunks=None).values
fill_single(z[:50, :50]); accumulation_single(fill_single(z[:50, :50]))   # warm cache
t = time.perf_counter()
F = fill_single(z); A = accumulation_single(F); r = A >= default_min_accumulation(30.0)
result = dict(seconds=time.perf_counter() - t, ridge=int(r.sum()))
np.save("{out}/ours_ridge.npy", r)
"""

PYSHEDS = """
import sys, time, numpy as np, pipeline
sys.path.insert(0, "tests")
from test_ridges import _pysheds                      # the tests' pysheds runner (in1d alias)
from pipeline.ridges import default_min_accumulation
z = pipeline.synthetic_dem(({n}, {n}), cell_size=30.0, seed=1, chunks=None).values
_pysheds(z[:50, :50])                                 # warm its numba
t = time.perf_counter()
A = _pysheds(z)[1]
r = A >= default_min_accumulation(30.0)
result = dict(seconds=time.perf_counter() - t, ridge=int(r.sum()))
ours = np.load("{out}/ours_ridge.npy")
result["iou"] = float((ours & r).sum() / (ours | r).sum())
"""

PNG = """
import numpy as np, pipeline, matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.colors import ListedColormap
from pipeline import plots
dem = pipeline.synthetic_dem((2000, 2000), seed=0, chunks=500)
rdg = pipeline.ridge_map(dem).values
from scipy import ndimage
shown = ndimage.binary_dilation(rdg, np.ones((5, 5), bool))  # one-cell lines, drawn 5 wide
fig, ax = plt.subplots(figsize=(8.5, 7.2), dpi=110)
plots.hillshade_axes(ax, dem.compute())
ax.imshow(np.ma.masked_where(~shown, shown), cmap=ListedColormap(["red"]), interpolation="nearest",
          extent=plots._extent_km(dem), origin="upper", alpha=0.9)
ax.set_title(f"ridge cells (accumulation of the inverted filled DEM >= 1 km^2): "
             f"{{100 * rdg.mean():.2f}} % of cells (drawn 5 cells wide)", fontsize=9)
fig.tight_layout(); fig.savefig("{png}")
result = {{}}
"""


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--skip-20000", action="store_true")
    ap.add_argument(
        "--sides",
        type=int,
        nargs="*",
        help="only these map sides, Zarr only (printed, not reported)",
    )
    args = ap.parse_args()
    quick = args.quick
    OUT.mkdir(exist_ok=True)
    print(f"machine: {machine()}")
    sides = [2000] if quick else [10000] + ([] if args.skip_20000 else [20000])
    sides = args.sides or sides
    rows = {}
    for n in sides:
        r = run_isolated(RIDGE_ZARR.format(n=n, src=OUT / f"dem{n}.zarr", out=OUT), timeout=7200)
        rows[n] = r
        print(f"{n}: {r}", flush=True)
    if args.sides:
        print(json.dumps({"zarr": rows}))
        return
    rep = Report("ridges", 3, "Ridge maps", ".venv/bin/python benchmarks/bench_ridges.py", quick)
    rep.h("Large maps, Zarr to Zarr")
    rep.p("""Fill + D8 + accumulation + ridge threshold (default 1 km^2: 1112 cells of 30 m)
          from the DEM's Zarr store (chunks 1024) to a Zarr store on a LocalCluster of 2 workers
          x 1 thread: the path `build_maps` takes (each tile flooded once into a scratch store,
          two small global solves on the client, the fill finished elementwise with one-cell
          halos). The paper builds its ridge map in ArcGIS and reports no time.""")
    rep.table(
        [
            "map",
            "total s",
            "tiles flooded + fill solve s",
            "flow summaries + solve s",
            "accumulation + ridge written s",
            "ridge cells %",
            "worker peak RSS GiB",
            "client peak RSS GiB",
            "whole `build_maps` (every layer) s",
        ],
        [
            [
                f"{n} x {n}",
                r["total_s"],
                r["flood_and_fill_solve_s"],
                r["flow_summaries_and_solve_s"],
                r["acc_ridge_write_s"],
                100 * r["ridge_share"],
                " / ".join(map(str, r["worker_peak_gib"])),
                r["peak_rss_gib"],
                r["build_maps_s"],
            ]
            for n, r in rows.items()
        ],
    )
    rep.p("""No worker ever holds the map, only a tile (1024^2) with its halo. The limit is the
          client: the two global solves hold every tile's perimeter, which grows with the
          number of tiles times the tile side; for much larger maps, larger tiles cut it.
          Target at 10000^2: < 90 s, < 4 GiB per worker.""")
    for n, r in rows.items():
        rep.headline(
            f"zarr{n}",
            30 + n // 10000,
            f"ridge layers {n}^2, Zarr -> Zarr, 2 workers",
            f"{r['total_s']:.0f} s, {max(r['worker_peak_gib']):.2f} GiB per worker",
            target="< 90 s, < 4 GiB (10000^2)" if n <= 10000 else "completes",
        )

    n = 1000 if quick else 4000
    ours = run_isolated(OURS_MEM.format(n=n, out=OUT))
    theirs = run_isolated(PYSHEDS.format(n=n, out=OUT))
    ratio = theirs["seconds"] / ours["seconds"]
    rep.h("Against pysheds")
    rep.p(f"""{n} x {n} synthetic DEM (seed 1) in memory, each tool in its own process (so each
          peak is its own): fill, D8 on the inverted filled DEM, accumulation, threshold.""")
    rep.table(
        ["", "time s", "peak RSS GiB"],
        [
            [
                "ours (single-array path: priority-flood fill, D8, accumulation)",
                ours["seconds"],
                ours["peak_rss_gib"],
            ],
            [
                "pysheds (fill_depressions, flowdir, accumulation)",
                theirs["seconds"],
                theirs["peak_rss_gib"],
            ],
            [
                "ratio pysheds / ours",
                f"**{ratio:.1f}x**",
                f"{theirs['peak_rss_gib'] / ours['peak_rss_gib']:.2f}x",
            ],
        ],
    )
    rep.p(f"""Ridge cells at the default threshold: intersection over union with pysheds'
          **{theirs["iou"]:.4f}** (the tests also compare the filled DEMs exactly, on other seeds
          and on real bathymetry).""")
    rep.headline(
        "pysheds",
        32,
        f"ridge layers {n}^2 in memory",
        f"{ours['seconds']:.1f} s, {ours['peak_rss_gib']:.2f} GiB",
        peer=f"pysheds {theirs['seconds']:.1f} s, {theirs['peak_rss_gib']:.2f} GiB "
        f"(**{faster(theirs['seconds'], ours['seconds'])}**); ridge IoU "
        f"{theirs['iou']:.3f}",
    )
    png = figure_dir(quick) / "ridge-map.png"
    run_isolated(PNG.format(png=png))
    rep.figure(
        png, "ridge cells over the hillshade of the 2000 x 2000 demo DEM (the paper's Figure 8)"
    )
    rep.save()
    print(json.dumps({"zarr": rows, "ours": ours, "pysheds": theirs}))


if __name__ == "__main__":
    main()
