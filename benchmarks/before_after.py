"""A mission's planning and flight times at two revisions of the code, on the same maps and
missions.

For a change that must not slow the library down (issue 61 bounds the flight against the
continuous seabed at 1.5x the flight it replaced; issue 63's new layout must keep both within
the machine's noise). This script checks out ``--base`` (a git revision) into a temporary
worktree, builds two maps stores (a synthetic 1500^2 grid at 30 m with R = 300 m, a fine grid;
matplotlib's topobathy lon/lat sample reprojected to 500 m with R = 300 m, a coarse one: R
under a cell), picks missions once, and under each revision, in its own process, times
``pipeline.plan`` (RA*, omega 2, in the process) and ``pipeline.fly`` for each (the best of 3
runs a mission, after a warm-up), printing each revision's median and the ratio. It is not
part of ``./dev bench`` (it needs the repository's history).

    .venv/bin/python benchmarks/before_after.py --base cd04dab [--missions 8]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

BUILD = r"""
import sys, numpy as np, xarray as xr, dask, pipeline
from matplotlib import cbook
out = sys.argv[1]
def main():
    dask.config.set(scheduler="threads")
    dem = pipeline.synthetic_dem((1500, 1500), cell_size=30.0, seed=0, chunks=512)
    pipeline.build_maps(dem, f"{out}/fine.zarr", clearance=300.0, min_accumulation=20, chunks=512)
    d = cbook.get_sample_data("topobathy.npz")
    z = np.asarray(d["topo"], np.float32)
    lon = np.asarray(d["longitude"], float) - 360
    lat = np.asarray(d["latitude"], float)
    xr.DataArray(z, dims=("lat", "lon"), coords={"lat": lat, "lon": lon},
                 name="elevation").to_netcdf(f"{out}/tb.nc")
    dem = pipeline.open_dem(f"{out}/tb.nc", resolution=500.0, chunks=256)
    pipeline.build_maps(dem, f"{out}/coarse.zarr", clearance=300.0, surface_clearance=50.0,
                        chunks=256)
if __name__ == "__main__":
    main()
"""

PICK = r"""
import sys, json, numpy as np, pipeline
store, k = sys.argv[1], int(sys.argv[2])
def main():
    ok = pipeline.open_maps(store)["passable"].values.astype(bool)
    cells = np.argwhere(ok)
    rng = np.random.default_rng(3)
    out = []
    while len(out) < k:
        s, g = cells[rng.integers(len(cells))], cells[rng.integers(len(cells))]
        if np.hypot(*(s - g)) < 60:
            continue
        try:
            t = pipeline.plan(store, tuple(s), tuple(g), planner="ra_star", omega=2.0,
                              client="synchronous")
        except pipeline.PipelineError:  # (separate regions)
            continue
        if t.status == "ok":
            out.append([s.tolist(), g.tolist()])
    print(json.dumps(out))
if __name__ == "__main__":
    main()
"""

TIME = r"""
import sys, json, time, pipeline
store, missions = sys.argv[1], json.loads(sys.argv[2])
def best(f):
    out = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        f()
        out = min(out, time.perf_counter() - t0)
    return out
def main():
    def plan(s, g):
        return pipeline.plan(store, tuple(s), tuple(g), planner="ra_star", omega=2.0,
                             client="synchronous")
    ts = [plan(s, g) for s, g in missions]  # compiled and warm
    veh = {"max_pitch_deg": 15.0}
    pipeline.fly(store, ts[0], veh)
    out = {"plan": [best(lambda s=s, g=g: plan(s, g)) for s, g in missions],
           "fly": [best(lambda t=t: pipeline.fly(store, t, veh)) for t in ts]}
    print(json.dumps(out))
if __name__ == "__main__":
    main()
"""


def run(code: str, *args: str, cwd: Path) -> str:
    proc = subprocess.run(
        [sys.executable, "-c", code, *args],
        cwd=cwd,
        env={"PYTHONPATH": str(cwd), "PATH": "/usr/bin:/bin"},
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode:
        raise SystemExit(f"failed in {cwd}: {proc.stderr.strip().splitlines()[-1]}")
    return proc.stdout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", required=True, help="the git revision to compare with")
    ap.add_argument("--missions", type=int, default=8)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        base = tmp / "base"
        subprocess.run(
            ["git", "worktree", "add", "--detach", str(base), args.base],
            cwd=ROOT,
            check=True,
            capture_output=True,
        )
        try:
            run(BUILD, str(tmp), cwd=ROOT)
            for grid in ("fine", "coarse"):
                store = str(tmp / f"{grid}.zarr")
                missions = run(PICK, store, str(args.missions), cwd=ROOT).strip()
                times = {
                    name: json.loads(run(TIME, store, missions, cwd=tree))
                    for name, tree in (("base", base), ("now", ROOT))
                }
                for what in ("plan", "fly"):
                    b, n = (1e3 * statistics.median(times[k][what]) for k in ("base", "now"))
                    print(
                        f"{grid} grid: {what} per mission, median of {len(times['now'][what])}:"
                        f" {args.base} {b:.2f} ms, now {n:.2f} ms: {n / b:.2f}x"
                    )
        finally:
            subprocess.run(
                ["git", "worktree", "remove", "--force", str(base)], cwd=ROOT, check=False
            )


if __name__ == "__main__":
    main()
