"""Issue 4 figures: ridge layers (fill + D8 + accumulation + ridge) Zarr -> Zarr on 2 workers
(the staged path build_maps uses)
for 10000^2 and 20000^2, pysheds against our in-memory path on 4000^2 (separate processes,
each with its own peak memory), and the ridge-over-hillshade PNG.

    .venv/bin/python benchmarks/bench_ridges.py [--quick] [--skip-20000] [--sides N ...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from _common import CLUSTER_PREAMBLE, OUT, machine, run_isolated

RIDGE_ZARR = CLUSTER_PREAMBLE + """
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
    ap.add_argument("--sides", type=int, nargs="*", help="only these map sides, Zarr only")
    args = ap.parse_args()
    OUT.mkdir(exist_ok=True)
    print(f"machine: {machine()}")
    sides = [2000] if args.quick else [10000] + ([] if args.skip_20000 else [20000])
    sides = args.sides or sides
    rows = {}
    for n in sides:
        r = run_isolated(RIDGE_ZARR.format(n=n, src=OUT / f"dem{n}.zarr", out=OUT), timeout=7200)
        rows[n] = r
        print(f"\n{n} x {n}, ridge layers Zarr -> Zarr, LocalCluster 2 workers x 1 thread: "
              f"total {r['total_s']:.1f} s (tiles flooded + fill solve "
              f"{r['flood_and_fill_solve_s']:.1f}, flow summaries + solve "
              f"{r['flow_summaries_and_solve_s']:.1f}, accumulation + ridge written "
              f"{r['acc_ridge_write_s']:.1f}); worker peak RSS {r['worker_peak_gib']} GiB, "
              f"client peak {r['peak_rss_gib']} GiB; ridge cells {100 * r['ridge_share']:.2f} %;"
              f" a whole build_maps (every layer) {r['build_maps_s']:.1f} s")
    if args.sides:
        print(json.dumps({"zarr": rows}))
        return
    n = 1000 if args.quick else 4000
    ours = run_isolated(OURS_MEM.format(n=n, out=OUT))
    theirs = run_isolated(PYSHEDS.format(n=n, out=OUT))
    print(f"\n{n} x {n} in memory, fill + D8 + accumulation + threshold:")
    print(f"ours {ours['seconds']:.2f} s, peak {ours['peak_rss_gib']} GiB; pysheds "
          f"{theirs['seconds']:.2f} s, peak {theirs['peak_rss_gib']} GiB; time ratio "
          f"{theirs['seconds'] / ours['seconds']:.1f}x; ridge IoU {theirs['iou']:.4f}")
    png = Path(__file__).resolve().parents[1] / "docs" / "ridge-map.png"
    run_isolated(PNG.format(png=png))
    print(f"\nridge map plot: {png}")
    print(json.dumps({"zarr": rows, "ours": ours, "pysheds": theirs}))


if __name__ == "__main__":
    main()
