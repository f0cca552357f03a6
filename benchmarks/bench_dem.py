"""Issue 2 figures: synthetic 10000 x 10000 DEM to Zarr, and a 4000 x 4000 GeoTIFF import.

Each case runs in a fresh process (so numba compilation is cached, not timed, and peak memory
is that process's own); the threaded dask scheduler uses the machine's 2 cores.

    .venv/bin/python benchmarks/bench_dem.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import shutil

from _common import OUT, machine, run_isolated

SYNTH = """
import time, dask, pipeline
pipeline.synthetic_dem((64, 64), chunks=None)              # warm the numba cache
dask.config.set(scheduler="threads", num_workers=2)
t = time.perf_counter()
pipeline.write_dem(pipeline.synthetic_dem(({n}, {n}), cell_size=30.0, seed=0, chunks=1024),
                   "{store}", chunks=1024, overwrite=True)
result = {{"seconds": time.perf_counter() - t}}
"""

MAKE_TIFF = """
import pipeline, rioxarray
d = pipeline.synthetic_dem(({n}, {n}), cell_size=30.0, seed=1, chunks=None)
d = d.rio.write_crs("EPSG:32630").rio.write_nodata(float("nan"))
d.rio.to_raster("{tif}", tiled=True, blockxsize=512, blockysize=512, compress="DEFLATE")
result = {{}}
"""

IMPORT = """
import time, dask, pipeline
dask.config.set(scheduler="threads", num_workers=2)
t = time.perf_counter()
pipeline.import_dem("{tif}", "{store}", chunks=1024, overwrite=True)
result = {{"seconds": time.perf_counter() - t}}
"""


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="smaller maps (a check, not a figure)")
    args = ap.parse_args()
    n_synth, n_tif = (2000, 1000) if args.quick else (10000, 4000)
    OUT.mkdir(exist_ok=True)
    print(f"machine: {machine()}")
    rows = []
    store = OUT / "synth.zarr"
    r = run_isolated(SYNTH.format(n=n_synth, store=store))
    rows.append((f"synthetic_dem {n_synth} x {n_synth} -> Zarr", r))
    tif, store2 = OUT / "import.tif", OUT / "import.zarr"
    run_isolated(MAKE_TIFF.format(n=n_tif, tif=tif))
    r = run_isolated(IMPORT.format(tif=tif, store=store2))
    rows.append((f"open_dem + import {n_tif} x {n_tif} GeoTIFF -> Zarr", r))
    print("| case | wall time (s) | peak memory (GiB) |")
    print("|---|---|---|")
    for name, r in rows:
        print(f"| {name} | {r['seconds']:.1f} | {r['peak_rss_gib']} |")
    print(json.dumps({name: r for name, r in rows}))
    for p in (store, store2, tif):
        shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)


if __name__ == "__main__":
    main()
