"""Issue 18: maps stores from 5000^2 to 40000^2 cells on this machine, and a mission on the
largest.

For each side, a synthetic DEM store (30 m cells, made once, kept in benchmarks/out) and
`build_maps` from it on a LocalCluster of 2 single-threaded workers, without landmark layers
(a landmark's exact search holds the whole map, 6.2 bytes a cell: 10 GB at 40000^2), each in a
fresh process: wall time, the stages (from the build's log), the peak memory of the client and
of each worker, the store's size. Then two missions (ra_star, omega 2, MCPC) across the
40000^2 map on the same cluster: the first one also builds the coarse levels MCPC plans on.
The scaling curve is docs/build-scaling.png.

    .venv/bin/python benchmarks/bench_scale.py [--quick] [--sides 5000 10000 ...]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess

from _common import CLUSTER_PREAMBLE, OUT, machine, run_isolated
from _report import Report, figure_dir

BUILD = (
    CLUSTER_PREAMBLE
    + """
import logging, os
marks = []
class Marks(logging.Handler):
    def emit(self, record):
        marks.append((time.perf_counter(), record.getMessage()))
lg = logging.getLogger("pipeline.maps.build")
lg.setLevel(logging.INFO)
lg.addHandler(Marks())
out = Path("{out}")
t0 = time.perf_counter()
pipeline.build_maps(pipeline.open_dem(src, chunks=1024), out, landmarks=0, overwrite=True)
total = time.perf_counter() - t0
def at(word):
    return next((t - t0 for t, m in marks if word in m), float("nan"))
size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
result = {{"seconds": total, "fill_s": at("fill:"), "flow_s": at("flow:"),
          "components_s": at("components labelled"), "store_bytes": size,
          "worker_peaks_gib": worker_peaks()}}
"""
)

MISSIONS = (
    CLUSTER_PREAMBLE
    + """
import numpy as np
from pipeline.store import open_store
m = open_store("{out}")
n = m.shape[0]
def passable_near(r0, c0, side=400):
    for k in range(8):  # a window with a passable cell, moving towards the centre
        dr, dc = (k * side if r0 < n // 2 else -k * side), (k * side if c0 < n // 2 else -k * side)
        r1, c1 = r0 + dr, c0 + dc
        cells = np.argwhere(m.window("passable", r1, r1 + side, c1, c1 + side))
        if len(cells):
            r, c = cells[len(cells) // 2]
            return int(r1 + r), int(c1 + c)
    raise RuntimeError("no passable cell near the corner")
runs = []
lo, hi = n // 20, n - n // 20 - 400
for s, g in ((passable_near(lo, lo), passable_near(hi, hi)),
             (passable_near(lo, hi), passable_near(hi, lo))):
    t = time.perf_counter()
    tr = pipeline.plan(m, s, g, planner="ra_star", omega=2.0, client=client)
    runs.append({{"seconds": time.perf_counter() - t, "status": tr.status, "start": s, "goal": g,
                 "length_km": tr.length_m / 1000, "lower_bound_km": tr.lower_bound_m / 1000,
                 "sections": len(tr.extra["sections"]), "message": tr.message}})
result = {{"runs": runs, "worker_peaks_gib": worker_peaks()}}
"""
)


def plot(rows: dict, png) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    sides = sorted(rows)
    cells = np.array([n * n for n in sides], dtype=float) / 1e6
    secs = np.array([rows[n]["seconds"] for n in sides])
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
    ax.loglog(cells, secs, "o-", label="build_maps (measured)")
    ax.loglog(cells, secs[0] * cells / cells[0], "--", color="grey", label="linear in cells")
    for n, c, s in zip(sides, cells, secs, strict=True):
        ax.annotate(f"{n}^2: {s:.0f} s", (c, s), textcoords="offset points", xytext=(-20, 8))
    ax.set_xlabel("map size (million cells)")
    ax.set_ylabel("build time (s)")
    ax.set_title("maps store build, 2 workers x 1 thread")
    ax.legend()
    ax.grid(True, which="both", alpha=0.3)
    workers = np.array([max(rows[n]["worker_peaks_gib"]) for n in sides])
    client = np.array([rows[n]["peak_rss_gib"] for n in sides])
    bx.semilogx(cells, workers, "o-", label="largest worker")
    bx.semilogx(cells, client, "s-", label="client")
    bx.axhline(4.0, color="red", ls=":", label="target: 4 GiB per worker")
    bx.set_xlabel("map size (million cells)")
    bx.set_ylabel("peak resident memory (GiB)")
    bx.set_title("peak memory")
    bx.set_ylim(0, max(4.5, float(client.max()) * 1.15))
    bx.legend()
    bx.grid(True, which="both", alpha=0.3)
    from matplotlib.ticker import FuncFormatter, NullFormatter

    plain = FuncFormatter(lambda v, _: f"{v:g}")
    for axis in (ax.xaxis, ax.yaxis, bx.xaxis):
        axis.set_major_formatter(plain)
        axis.set_minor_formatter(NullFormatter())
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="small maps (a check, not a figure)")
    ap.add_argument("--sides", type=int, nargs="+", default=None)
    args = ap.parse_args()
    sides = args.sides or ([1000, 2000] if args.quick else [5000, 10000, 20000, 40000])
    OUT.mkdir(exist_ok=True)
    print(f"machine: {machine()}", flush=True)
    rep = Report(
        "scale",
        3,
        "Ocean-scale maps: 5000^2 to 40000^2",
        ".venv/bin/python benchmarks/bench_scale.py",
        args.quick,
    )
    rows, failed = {}, {}
    for n in sides:
        out = OUT / f"scale{n}.zarr"
        try:
            rows[n] = run_isolated(
                BUILD.format(n=n, src=OUT / f"dem{n}.zarr", out=out), timeout=4 * 3600
            )
        except (RuntimeError, subprocess.TimeoutExpired) as exc:  # reported, not hidden
            failed[n] = str(exc).strip().splitlines()[-1][:300]
            shutil.rmtree(out, ignore_errors=True)
        print(f"{n}: {rows.get(n) or failed[n]}", flush=True)
        if n != sides[-1]:
            shutil.rmtree(out, ignore_errors=True)
    sides = [n for n in sides if n in rows]
    big = sides[-1]
    out = OUT / f"scale{big}.zarr"
    mis = run_isolated(MISSIONS.format(n=big, src=OUT / f"dem{big}.zarr", out=out), timeout=7200)
    print(json.dumps({"builds": rows, "failed": failed, "missions": mis}), flush=True)
    shutil.rmtree(out, ignore_errors=True)

    rep.p("""`build_maps` from a synthetic DEM store (30 m cells, chunks 1024^2) to a maps store
          on a LocalCluster of 2 workers x 1 thread, every layer but the landmark distances
          (`landmarks = 0`: a landmark's exact search holds the whole map, 6.2 bytes a cell,
          10 GB at 40000^2; missions on such maps are certified by the octile bound, or say
          they are not). Each build in a fresh process; stages from the build's log (time
          since the start when each finished).""")
    table = []
    for n in sides:
        r = rows[n]
        table.append(
            [
                f"{n} x {n}",
                n * n / 1e6,
                r["seconds"],
                r["seconds"] / (n * n) * 1e6,
                r["fill_s"],
                r["flow_s"],
                r["components_s"],
                " / ".join(f"{v:.2f}" for v in r["worker_peaks_gib"]),
                r["peak_rss_gib"],
                r["store_bytes"] / 2**30,
            ]
        )
    rep.table(
        [
            "map",
            "million cells",
            "build s",
            "us per cell",
            "fill done s",
            "flow done s",
            "layers + components done s",
            "worker peaks GiB",
            "client peak GiB",
            "store GiB",
        ],
        table,
    )
    for n, why in failed.items():
        rep.p(f"**{n} x {n} did not complete** on this machine: {why}")
    png = figure_dir(args.quick) / "build-scaling.png"
    plot(rows, png)
    rep.figure(png, "maps store build time and peak memory against map size")
    runs = mis["runs"]
    rep.p(f"""Two missions across the {big} x {big} map (ra_star, omega 2, MCPC defaults, the
          same cluster), corner to corner; the first also builds the coarse levels MCPC plans
          on (kept in the store for later missions).""")
    rep.table(
        ["mission", "start", "goal", "time s", "status", "length km", "lower bound km", "sections"],
        [
            [
                k + 1,
                str(tuple(r["start"])),
                str(tuple(r["goal"])),
                r["seconds"],
                r["status"],
                r["length_km"],
                r["lower_bound_km"],
                r["sections"],
            ]
            for k, r in enumerate(runs)
        ],
    )
    if 10000 in rows:  # issue 17's target for the build
        r = rows[10000]
        rep.headline(
            "scale-10000",
            34,
            "`build_maps` 10000^2, Zarr to Zarr, 2 workers, no landmark layers",
            f"{r['seconds']:.1f} s, workers {max(r['worker_peaks_gib']):.2f} GiB (fill done at "
            f"{r['fill_s']:.1f} s, flow at {r['flow_s']:.1f} s, layers and components at "
            f"{r['components_s']:.1f} s)",
            target="< 25 s, < 1 GiB per worker",
        )
    last = rows[big]
    rep.headline(
        "scale",
        35,
        f"maps store {big}^2 ({big * big / 1e9:.1f}e9 cells), 2 workers, no landmark layers",
        f"{last['seconds']:.0f} s, workers {max(last['worker_peaks_gib']):.2f} GiB, client "
        f"{last['peak_rss_gib']:.2f} GiB; a mission {runs[1]['seconds']:.1f} s "
        f"({runs[0]['seconds']:.0f} s with the coarse levels)",
        target="< 4 GiB per worker, about linear from 5000^2",
    )
    rep.save()


if __name__ == "__main__":
    main()
