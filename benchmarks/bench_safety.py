"""Issue 3 figures: Table 1 analog, 10000^2 spherical map Zarr -> Zarr on 2 workers, and the
speed ratio against scipy.ndimage.grey_dilation on a 2000 x 2000 block; plus the profile PNG.

    .venv/bin/python benchmarks/bench_safety.py [--quick]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from _common import CLUSTER_PREAMBLE, OUT, machine, run_isolated

TABLE1 = """
import numpy as np, pipeline
dem = pipeline.synthetic_dem((200, 200), cell_size=100.0, seed=0, islands=0, chunks=None)
result = {}
for R in (300.0, 200.0):
    for m in ("spherical", "horizontal", "vertical"):
        S = pipeline.safety_map(dem, m, R)
        result[f"{m} {int(R)}"] = float((S - dem).mean())
"""

SCIPY = """
import time, numpy as np, pipeline
from scipy import ndimage
from pipeline.safety import disc_widths, sphere_heights
dem = pipeline.synthetic_dem(({n}, {n}), cell_size=30.0, seed=0, chunks=None)
z = dem.values
R, a = 300.0, 30.0
pipeline.safety_map(dem[:64, :64], "spherical", R)            # warm the numba cache
ours = []
for _ in range(3):
    t = time.perf_counter(); S = pipeline.safety_map(dem, "spherical", R).values
    ours.append(time.perf_counter() - t)
w = disc_widths(R, a); r = w.size - 1
off = np.arange(-r, r + 1); d2 = a * a * (off[:, None] ** 2 + off[None, :] ** 2)
fp = d2 <= R * R; st = np.where(fp, np.sqrt(np.maximum(R * R - d2, 0.0)), 0.0)
t = time.perf_counter()
ref64 = ndimage.grey_dilation(z.astype(np.float64), footprint=fp, structure=st,
                              mode="constant", cval=-np.inf)
t64 = time.perf_counter() - t
t = time.perf_counter()
ref32 = ndimage.grey_dilation(z, footprint=fp, structure=st, mode="constant", cval=-np.inf)
t32 = time.perf_counter() - t
result = dict(ours_s=min(ours), scipy64_s=t64, scipy32_s=t32,
              identical_to_scipy64_rounded=bool(np.array_equal(S, ref64.astype(np.float32))),
              max_abs_diff_scipy32=float(np.abs(S.astype(np.float64) - ref32).max()),
              footprint_cells=int(fp.sum()))
"""

BIG = CLUSTER_PREAMBLE + """
dem = pipeline.open_dem(src, chunks=1024)
t = time.perf_counter()
S = pipeline.safety_map(dem, "spherical", 300.0)
S.to_dataset().to_zarr("{out}/safety.zarr", mode="w", zarr_format=3, consolidated=False)
result = dict(safety_zarr_s=time.perf_counter() - t, worker_peak_gib=worker_peaks())
client.close(); cluster.close()
shutil.rmtree("{out}/safety.zarr", ignore_errors=True)
"""

PROFILE = """
import numpy as np, pipeline
import matplotlib; matplotlib.use("Agg")
import matplotlib.pyplot as plt
dem = pipeline.synthetic_dem((200, 200), cell_size=100.0, seed=0, islands=0, chunks=None)
row = 60
x = dem.x.values / 1e3
fig, ax = plt.subplots(figsize=(10, 4.2), dpi=110)
ax.fill_between(x, dem.values[row], -7000, color="0.75", label="seabed z")
for m, c in (("vertical", "tab:green"), ("spherical", "tab:blue"), ("horizontal", "tab:red")):
    ax.plot(x, pipeline.safety_map(dem, m, 300.0).values[row], c, lw=1.3, label=f"{{m}} S")
ax.set_ylim(dem.values[row].min() - 200, pipeline.safety_map(dem, "horizontal", 300.0)
            .values[row].max() + 300)
ax.set_xlabel("x (km)"); ax.set_ylabel("height (m)")
ax.set_title("safety surfaces on one profile (row 60 of a 200 x 200 map, 100 m cells, R = 300 m)")
ax.legend(loc="lower right"); fig.tight_layout(); fig.savefig("{png}")
result = {{}}
"""


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    OUT.mkdir(exist_ok=True)
    print(f"machine: {machine()}")
    t1 = run_isolated(TABLE1)
    paper = {"spherical 300": 338, "horizontal 300": 442, "vertical 300": 300,
             "spherical 200": 222, "horizontal 200": 342, "vertical 200": 200}
    print("\nTable 1 analog (200 x 200, 100 m cells, synthetic ridge seed 0): mean raise (m)")
    print("| R | method | ours | paper |\n|---|---|---|---|")
    for k, v in t1.items():
        if k.startswith("peak"):
            continue
        m, R = k.split()
        print(f"| {R} | {m} | +{v:.0f} | +{paper[k]} |")
    n = 1000 if args.quick else 2000
    s = run_isolated(SCIPY.format(n=n))
    print(f"\nspherical R = 300 m, 30 m cells ({s['footprint_cells']}-cell element), "
          f"{n} x {n} in memory:")
    print(f"ours {s['ours_s']:.3f} s; scipy grey_dilation float64 {s['scipy64_s']:.2f} s "
          f"(ratio {s['scipy64_s'] / s['ours_s']:.1f}x), float32 {s['scipy32_s']:.2f} s "
          f"(ratio {s['scipy32_s'] / s['ours_s']:.1f}x); identical to scipy float64 rounded "
          f"to float32: {s['identical_to_scipy64_rounded']}; max |diff| to scipy float32 "
          f"(which rounds twice): {s['max_abs_diff_scipy32']:.2e} m")
    nb = 3000 if args.quick else 10000
    b = run_isolated(BIG.format(n=nb, src=OUT / f"dem{nb}.zarr", out=OUT), timeout=3600)
    print(f"\n{nb} x {nb}, spherical R = 300 m, Zarr -> Zarr, LocalCluster 2 workers x 1 thread:")
    print(f"safety layer {b['safety_zarr_s']:.1f} s; worker peak RSS {b['worker_peak_gib']} "
          f"GiB; client peak {b['peak_rss_gib']} GiB")
    png = Path(__file__).resolve().parents[1] / "docs" / "safety-profile.png"
    run_isolated(PROFILE.format(png=png))
    print(f"\nprofile plot: {png}")
    print(json.dumps({"table1": t1, "scipy": s, "big": b}))


if __name__ == "__main__":
    main()
