"""Issue 6 figures: MCPC on maps stores (benchmarks/out/maps{n}.zarr, built once).

1. Table 5 analog: per map side, 20 random missions, ra_star omega 2 + MCPC on a LocalCluster of
   2 single-threaded workers, maps built; median and spread; docs/mcpc-scaling.png. Also A*+MCPC
   against the full-map optimum (A* in one window) on 5 missions per side up to 5000^2.
2. Table 4 analog, 5000^2, omega 3: RA*+MCPC, A*+MCPC, RA* and A* without MCPC.
3. Table 6 analog, 10000^2, omega 2: ra_star+MCPC against wastar on the full map and pyastar2d
   on the full map, same run.
4. The quality cost of MCPC: 20 missions on 2000^2, ra_star stitched against one window.
5. docs/mcpc-sections.png: a stitched trajectory with its section windows.

    .venv/bin/python benchmarks/bench_mcpc.py [--quick] [--sides 500 1000 ...]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
from _common import OUT, machine, maps_store

DOCS = Path(__file__).resolve().parents[1] / "docs"
PAPER_T5 = {500: 0.26, 10000: 3.12}


def missions(ok: np.ndarray, k: int, seed: int, min_frac: float = 0.5):
    rng = np.random.default_rng(seed)
    n = ok.shape[0]
    out = []
    while len(out) < k:
        s = rng.integers(n, size=2)
        g = rng.integers(n, size=2)
        if ok[tuple(s)] and ok[tuple(g)] and np.hypot(*(s - g)) >= min_frac * n:
            out.append((tuple(int(v) for v in s), tuple(int(v) for v in g)))
    return out


def worker_peaks(client):
    import resource

    def peak():
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20

    return [round(v, 3) for v in client.run(peak).values()]


def timed(fn, *a, **k):
    import pipeline

    t0 = time.perf_counter()
    try:
        t = fn(*a, **k)
    except pipeline.PipelineError as e:
        return None, time.perf_counter() - t0, str(e)
    return t, time.perf_counter() - t0, ""


def table5(client, sides, n_missions):
    import pipeline

    rows = {}
    for n in sides:
        store = maps_store(n)
        ok = pipeline.open_maps(store)["passable"].values
        ms = missions(ok, n_missions + 1, seed=n)
        t0 = time.perf_counter()
        pipeline.plan(store, *ms[0], planner="ra_star", omega=2.0, client=client)  # warm-up
        warm = time.perf_counter() - t0
        times, ratios, fails, secs = [], [], 0, []
        for s, g in ms[1:]:
            t, dt, err = timed(pipeline.plan, store, s, g, planner="ra_star", omega=2.0,
                               client=client)
            if t is None:
                fails += 1
                print(f"  {n}: mission {s}->{g} failed: {err}")
                continue
            times.append(dt)
            ratios.append(t.ridge_ratio)
            secs.append(len(t.extra["sections"]))
        opt = []
        if n <= 5000:
            for s, g in ms[1:6]:
                full, _, _ = timed(pipeline.plan, store, s, g, planner="astar", mcpc=False,
                                   client=client)
                mc, _, _ = timed(pipeline.plan, store, s, g, planner="astar", client=client)
                if full is not None and mc is not None:
                    opt.append(mc.length_m / full.length_m)
        rows[n] = dict(median=statistics.median(times), p10=float(np.percentile(times, 10)),
                       p90=float(np.percentile(times, 90)), max=max(times),
                       ridge=statistics.mean(ratios), sections=statistics.mean(secs),
                       fails=fails, first_mission_s=warm,
                       astar_mcpc_over_opt=(statistics.mean(opt), max(opt)) if opt else None)
        r = rows[n]
        print(f"| {n} | {r['median']:.3f} | {r['p10']:.3f} - {r['p90']:.3f} | {r['max']:.3f} | "
              f"{r['sections']:.1f} | {100 * r['ridge']:.1f} | {r['fails']} | "
              f"{r['first_mission_s']:.2f} | "
              + (f"{r['astar_mcpc_over_opt'][0]:.4f} / {r['astar_mcpc_over_opt'][1]:.4f}"
                 if r["astar_mcpc_over_opt"] else "-") + f" | {PAPER_T5.get(n, '')} |",
              flush=True)
    return rows


def plot_scaling(rows, png):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sides = sorted(rows)
    med = [rows[n]["median"] for n in sides]
    lo = [rows[n]["median"] - rows[n]["p10"] for n in sides]
    hi = [rows[n]["p90"] - rows[n]["median"] for n in sides]
    fig, ax = plt.subplots(figsize=(7, 4.8), dpi=110)
    ax.errorbar(sides, med, yerr=[lo, hi], marker="o", capsize=4,
                label="ours: ra_star + MCPC, 2 workers (median, p10-p90)")
    ax.plot(sorted(PAPER_T5), [PAPER_T5[n] for n in sorted(PAPER_T5)], "s--", color="grey",
            label="paper (Table 5), 16 cores, MATLAB")
    ax.set_xlabel("map side (cells, 30 m)")
    ax.set_ylabel("planning time per mission (s)")
    ax.set_title("Planning time against map size, omega 2, maps prebuilt (paper's Figure 13)",
                 fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png)
    plt.close(fig)


def table4(client):
    import pipeline

    store = maps_store(5000)
    ok = pipeline.open_maps(store)["passable"].values
    s, g = missions(ok, 1, seed=44, min_frac=0.9)[0]
    print(f"\nTable 4 analog: 5000 x 5000, omega 3, mission {s} -> {g}")
    print("| method | time s | length km | ridge km | ridge % | worker peak RSS GiB | paper |")
    print("|---|---|---|---|---|---|---|")
    paper = {"RA*+MCPC": "2.58 s, 66.5 %", "A*+MCPC": "2.03 s", "RA* without MCPC": "20.5 s",
             "A* without MCPC": "15.4 s"}
    out = {}
    for name, planner, mcpc in (("RA*+MCPC", "ra_star", True), ("A*+MCPC", "astar", True),
                                ("RA* without MCPC", "ra_star", False),
                                ("A* without MCPC", "astar", False)):
        pipeline.plan(store, s, g, planner=planner, omega=3.0, mcpc=mcpc, client=client)
        t, dt, _ = timed(pipeline.plan, store, s, g, planner=planner, omega=3.0, mcpc=mcpc,
                         client=client)
        out[name] = t
        print(f"| {name} | {dt:.2f} | {t.length_m / 1e3:.1f} | {t.ridge_length_m / 1e3:.1f} | "
              f"{100 * t.ridge_ratio:.1f} | {max(worker_peaks(client))} | {paper[name]} |",
              flush=True)
    print("(each planned once untimed first, so the workers hold the chunks; RA* without MCPC "
          "reads the whole map on one worker)")
    return store, out["RA*+MCPC"]


def table6(client, n):
    import pyastar2d

    import pipeline

    store = maps_store(n)
    ds = pipeline.open_maps(store)
    ok = ds["passable"].values
    ms = missions(ok, 3, seed=66, min_frac=0.8)
    w = np.where(ok, np.float32(1.0), np.float32(np.inf))
    print(f"\nTable 6 analog: {n} x {n}, omega 2, 3 long missions")
    print("| mission | method | time s | length km | ridge % | paper (10000^2) |")
    print("|---|---|---|---|---|---|")
    ratios = []
    for i, (s, g) in enumerate(ms):
        pipeline.plan(store, s, g, planner="ra_star", omega=2.0, client=client)  # warm
        ra, t_ra, _ = timed(pipeline.plan, store, s, g, planner="ra_star", omega=2.0,
                            client=client)
        wa, t_wa, _ = timed(pipeline.plan, store, s, g, planner="wastar", omega=2.0,
                            mcpc=False, client=client)
        t0 = time.perf_counter()
        p = pyastar2d.astar_path(w, s, g, allow_diagonal=True)
        t_py = time.perf_counter() - t0
        S = ds["safety"]
        z = np.asarray(S.isel(y=xr_index(p[:, 0]), x=xr_index(p[:, 1])).values, np.float64)
        d = np.diff(p, axis=0)
        py_len = float(np.sqrt(900.0 * (d ** 2).sum(axis=1) + np.diff(z) ** 2).sum())
        rdg = ds["ridge"].isel(y=xr_index(p[:, 0]), x=xr_index(p[:, 1])).values
        step = np.sqrt(900.0 * (d ** 2).sum(axis=1) + np.diff(z) ** 2)
        py_ratio = float(step[rdg[1:]].sum() / step.sum())
        for name, t, dt, paper in (("ra_star + MCPC", ra, t_ra, "RA* 3.12 s"),
                                   ("wastar, whole map", wa, t_wa, "WA* 25.4 s"),
                                   ("pyastar2d, whole map", None, t_py, "")):
            length = t.length_m / 1e3 if t else py_len / 1e3
            ratio = 100 * (t.ridge_ratio if t else py_ratio)
            print(f"| {i} | {name} | {dt:.2f} | {length:.1f} | {ratio:.1f} | {paper} |",
                  flush=True)
        ratios.append((t_py / t_ra, t_wa / t_ra))
    print("time ratios per mission (pyastar2d / ours, wastar / ours): "
          + ", ".join(f"{a:.1f}x, {b:.1f}x" for a, b in ratios))
    print("(pyastar2d's lengths: its path measured on the safety surface; it optimises a "
          "unit-cost grid where a diagonal costs as much as a straight step)")


def xr_index(v):
    import xarray as xr

    return xr.DataArray(np.asarray(v), dims="p")


def quality(client, n_missions):
    import pipeline

    store = maps_store(2000)
    ok = pipeline.open_maps(store)["passable"].values
    ms = missions(ok, n_missions, seed=7)
    rl, rr, ml, mr = [], [], [], []
    for s, g in ms:
        one, _, _ = timed(pipeline.plan, store, s, g, planner="ra_star", omega=2.0, mcpc=False,
                          client=client)
        mc, _, _ = timed(pipeline.plan, store, s, g, planner="ra_star", omega=2.0,
                         client=client)
        if one is None or mc is None:
            continue
        rl.append(mc.length_m / one.length_m)
        rr.append(mc.ridge_ratio - one.ridge_ratio)
        ml.append(one.length_m)
        mr.append(one.ridge_ratio)
    print(f"\nQuality cost of MCPC, 2000^2, omega 2, {len(rl)} missions: stitched length / "
          f"one-window length: mean {np.mean(rl):.3f} (min {min(rl):.3f}, max {max(rl):.3f}); "
          f"ridge ratio stitched - one window: mean {100 * np.mean(rr):+.1f} points "
          f"(one window mean {100 * np.mean(mr):.1f} %)")


def plot_sections(store, t, png):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.patches as mpatches
    import matplotlib.pyplot as plt

    import pipeline
    from pipeline.plots import hillshade_axes

    ds = pipeline.open_maps(store)
    fig, ax = plt.subplots(figsize=(9, 8.2), dpi=110)
    hillshade_axes(ax, ds["elevation"], max_side=1500, colorbar=False)
    x, y = ds["x"].values / 1e3, ds["y"].values / 1e3
    a = float(abs(x[1] - x[0]))
    for k, sec in enumerate(t.extra["sections"]):
        r0, r1, c0, c1 = sec["window"]
        ax.add_patch(mpatches.Rectangle((x[c0] - a / 2, y[r1 - 1] - a / 2), (c1 - c0) * a,
                                        (r1 - r0) * a, fill=False, lw=0.7,
                                        ec="yellow" if k % 2 else "orange"))
    rho = t.extra["rho"]
    cc = np.asarray(t.extra["coarse_cells"]) * rho + rho // 2
    cc = np.clip(cc, 0, len(y) - 1)
    ax.plot(x[cc[:, 1]], y[cc[:, 0]], color="white", lw=0.8, ls="--", label="coarse path (A*)")
    ax.plot(t.points[:, 0] / 1e3, t.points[:, 1] / 1e3, color="red", lw=1.1,
            label=f"stitched ra_star: {t.length_m / 1e3:.0f} km, "
                  f"{100 * t.ridge_ratio:.0f} % ridge")
    ax.plot([], [], color="orange", lw=0.8, label=f"{len(t.extra['sections'])} section windows")
    ax.legend(loc="lower right", fontsize=8)
    ax.set_title(f"MCPC on a {len(y)} x {len(x)} map: rho {rho}, sections "
                 f"{t.extra['section_size']} cells + margin {t.extra['margin']} "
                 f"(the paper's Figures 7 and 14)", fontsize=10)
    fig.tight_layout()
    fig.savefig(png)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="sides 500-2000, 5 missions each")
    ap.add_argument("--sides", type=int, nargs="*")
    ap.add_argument("--only", choices=("t5", "t4", "t6", "quality"))
    args = ap.parse_args()
    sides = args.sides or ([500, 1000, 2000] if args.quick else
                           [500, 1000, 2000, 3000, 5000, 10000])
    k = 5 if args.quick else 20
    print(machine(), flush=True)
    OUT.mkdir(exist_ok=True)
    for n in sides:
        maps_store(n)
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None) as cl, \
            Client(cl) as client:
        if args.only in (None, "t5"):
            print("\nTable 5 analog: ra_star omega 2 + MCPC, default rho / sections, "
                  f"{k} random missions per side (start-goal >= side / 2), maps prebuilt")
            print("| side | median s | p10 - p90 s | max s | sections | ridge % | failed | "
                  "first mission s | A*+MCPC / optimum (mean / max) | paper s |")
            print("|---|---|---|---|---|---|---|---|---|---|")
            rows = table5(client, sides, k)
            plot_scaling(rows, DOCS / "mcpc-scaling.png")
            (OUT / "table5.json").write_text(json.dumps({str(n): r for n, r in rows.items()},
                                                        indent=1))
            print(f"wrote {DOCS / 'mcpc-scaling.png'}; worker peaks {worker_peaks(client)} GiB")
        if args.only in (None, "t4") and not args.quick:
            store, t = table4(client)
            plot_sections(store, t, DOCS / "mcpc-sections.png")
            print(f"wrote {DOCS / 'mcpc-sections.png'}")
        if args.only in (None, "t6"):
            table6(client, 2000 if args.quick else 10000)
        if args.only in (None, "quality"):
            quality(client, 5 if args.quick else 20)


if __name__ == "__main__":
    main()
