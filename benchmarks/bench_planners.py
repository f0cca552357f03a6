"""Issue 5 figures: the planners on one window.

1. Tables 2 and 3 analog: a 200 x 200 virtual ridge DEM (30 m), one long mission, omega 2.5 /
   2.0 / 1.8 / 1.0, without and with the spherical safety map (300 m), ``ra_star`` and
   ``lagrangian`` beside the paper; the top-view PNG of the paths (docs/planners-200.png).
2. Pareto figure: length / L* against ridge ratio over omega for ra_star, lagrangian, wastar,
   astar on 50 random missions (docs/pareto.png), with the time of lagrangian against ra_star.
3. The core's speed on a 4000 x 4000 obstacle map: ``astar`` against pyastar2d (C++ A*) and
   scikit-image ``MCP_Geometric`` (Dijkstra), same missions, same run.
4. Table 4's "RA* without MCPC" analog: ra_star omega 3 on a 5000 x 5000 map in one window
   (maps built once into benchmarks/out/maps5000.zarr), peak memory of that process.

    .venv/bin/python benchmarks/bench_planners.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from _common import OUT, machine, maps_store, run_isolated

DOCS = Path(__file__).resolve().parents[1] / "docs"
OMEGAS = (2.5, 2.0, 1.8, 1.0)
PAPER = {  # SPEC section 7: (length km, ridge ratio %) per omega
    "no safety map (Table 2)": {2.5: (8.194, 78.4), 2.0: (8.001, 71.9), 1.8: (7.867, 67.7),
                                1.0: (5.250, 37.2)},
    "spherical safety map (Table 3)": {2.5: (8.389, 78.2), 2.0: (8.129, 69.5),
                                       1.8: (7.963, 66.2), 1.0: (5.463, 37.5)},
}
# the 200 x 200 case: a 6 km window of the demo's 2000 x 2000 synthetic DEM (seed 0, no islands)
# with 30 m relief (a whole ridge scene generated on 200^2 is far steeper than the paper's map);
# the ridge threshold is SPEC's floor of 8 cells; one long diagonal mission
CASE200 = dict(seed=0, window=(800, 1000), min_acc=8, start=(10, 10), goal=(190, 170),
               clearance=300.0)


def case200_maps():
    import pipeline

    r0, c0 = CASE200["window"]
    big = pipeline.synthetic_dem((2000, 2000), cell_size=30.0, seed=CASE200["seed"], islands=0,
                                 chunks=None)
    dem = big[r0:r0 + 200, c0:c0 + 200].copy()
    ridge = pipeline.flow_accumulation(dem).values >= CASE200["min_acc"]
    safety = pipeline.safety_map(dem, "spherical", CASE200["clearance"])
    ok_safe = pipeline.passable(dem, safety).values
    variants = {"no safety map (Table 2)": (dem.values, np.ones(ridge.shape, bool)),
                "spherical safety map (Table 3)": (safety.values, ok_safe)}
    return dem, ridge, variants


def tables23() -> dict:
    from pipeline.planners import plan_window

    dem, ridge, variants = case200_maps()
    x, y = dem["x"].values, dem["y"].values
    out = {"ridge_cells_pct": round(100 * float(ridge.mean()), 1), "tables": {}, "paths": {}}
    for name, (surface, ok) in variants.items():
        rows = {}
        for planner in ("ra_star", "lagrangian"):
            for om in OMEGAS:
                t = plan_window(surface, ridge, ok, CASE200["start"], CASE200["goal"],
                                cell_size=30.0, planner=planner, omega=om, x=x, y=y)
                rows[f"{planner} {om}"] = dict(length_km=t.length_m / 1e3,
                                               ridge_km=t.ridge_length_m / 1e3,
                                               ratio_pct=100 * t.ridge_ratio,
                                               bound=t.length_m / t.lower_bound_m,
                                               ms=1e3 * t.runtime_s)
                out["paths"][f"{name}|{planner}|{om}"] = t.points[:, :2].tolist()
        out["tables"][name] = rows
    return out


def plot200(res: dict, png: Path) -> None:
    import matplotlib.pyplot as plt

    from pipeline.plots import hillshade_axes

    dem, ridge, _ = case200_maps()
    fig, axes = plt.subplots(2, 2, figsize=(11, 10.5), dpi=100)
    colours = dict(zip(OMEGAS, ("#d62728", "#ff7f0e", "#9467bd", "#1f77b4"), strict=True))
    x, y = dem["x"].values / 1e3, dem["y"].values / 1e3
    rr, cc = np.nonzero(ridge)
    for i, planner in enumerate(("ra_star", "lagrangian")):
        for j, name in enumerate(PAPER):
            ax = axes[i, j]
            hillshade_axes(ax, dem, colorbar=False)
            ax.scatter(x[cc], y[rr], s=1.2, c="white", alpha=0.7, linewidths=0,
                       label="ridge cells")
            for om in OMEGAS:
                p = np.asarray(res["paths"][f"{name}|{planner}|{om}"]) / 1e3
                row = res["tables"][name][f"{planner} {om}"]
                ax.plot(p[:, 0], p[:, 1], color=colours[om], lw=1.6,
                        label=f"omega {om}: {row['length_km']:.1f} km, "
                              f"{row['ratio_pct']:.0f} % ridge")
            ax.set_title(f"{planner}, {name.split(' (')[0]}", fontsize=10)
            ax.legend(loc="lower right", fontsize=7, framealpha=0.85, markerscale=6)
    fig.suptitle("200 x 200 virtual ridge DEM (30 m cells): paths for four omega values "
                 "(the paper's Figures 10 and 11)", fontsize=11)
    fig.tight_layout()
    fig.savefig(png)
    plt.close(fig)


PARETO_OMEGAS = (1.0, 1.1, 1.25, 1.5, 2.0, 2.5, 3.0)


def pareto(n_missions: int) -> dict:
    """Mean length / L* and ridge ratio per planner and omega on random missions (400^2 map)."""
    import pipeline
    from pipeline.planners import plan_window

    dem = pipeline.synthetic_dem((400, 400), cell_size=30.0, seed=1, chunks=None)
    safety = pipeline.safety_map(dem, "spherical", 300.0)
    ok = pipeline.passable(dem, safety).values
    ridge = pipeline.flow_accumulation(dem).values >= 20
    surf = safety.values
    rng = np.random.default_rng(5)
    cells = np.argwhere(ok)
    missions = []
    while len(missions) < n_missions:
        s, t = cells[rng.integers(len(cells), size=2)]
        if np.hypot(*(s - t)) < 150:
            continue
        try:
            plan_window(surf, ridge, ok, s, t, cell_size=30.0, planner="astar")
        except pipeline.PipelineError:
            continue  # separated by land: draw again
        missions.append((tuple(s), tuple(t)))
    res = {}
    for planner in ("astar", "wastar", "ra_star", "lagrangian"):
        for om in (1.0,) if planner == "astar" else PARETO_OMEGAS:
            lens, ratios, secs, bound_ok = [], [], [], True
            for s, t in missions:
                opt = plan_window(surf, ridge, ok, s, t, cell_size=30.0, planner="astar")
                tr = plan_window(surf, ridge, ok, s, t, cell_size=30.0, planner=planner,
                                 omega=om)
                lens.append(tr.length_m / opt.length_m)
                ratios.append(tr.ridge_ratio)
                secs.append(tr.runtime_s)
                bound_ok &= tr.length_m <= om * opt.length_m * (1 + 1e-9)
            res[f"{planner} {om}"] = dict(planner=planner, omega=om,
                                          length_over_opt=float(np.mean(lens)),
                                          ridge_ratio=float(np.mean(ratios)),
                                          ridge_ratio_p10=float(np.percentile(ratios, 10)),
                                          ms_mean=1e3 * float(np.mean(secs)),
                                          bound_held=bool(bound_ok))
    return dict(missions=len(missions), ridge_cells_pct=round(100 * float(ridge.mean()), 1),
                rows=res)


def plot_pareto(res: dict, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 5.5), dpi=110)
    styles = {"astar": ("k", "*"), "wastar": ("#7f7f7f", "s"), "ra_star": ("#d62728", "o"),
              "lagrangian": ("#1f77b4", "D")}
    for planner, (col, mk) in styles.items():
        rows = [r for r in res["rows"].values() if r["planner"] == planner]
        xs = [r["length_over_opt"] for r in rows]
        ys = [100 * r["ridge_ratio"] for r in rows]
        ax.plot(xs, ys, marker=mk, color=col, label=planner, ms=7 if mk == "*" else 5)
        if planner in ("ra_star", "lagrangian"):
            for r, xv, yv in zip(rows, xs, ys, strict=True):
                ax.annotate(f"{r['omega']:g}", (xv, yv), textcoords="offset points",
                            xytext=(4, -10 if planner == "ra_star" else 4), fontsize=7,
                            color=col)
    ax.set_xlabel("path length / shortest length (mean)")
    ax.set_ylabel("ridge ratio (%, mean)")
    ax.set_title(f"Length against ridge ratio over omega, {res['missions']} random missions\n"
                 f"(400 x 400 synthetic map, 30 m, spherical 300 m; labels: omega)", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(png)
    plt.close(fig)


CORE = """
import time, numpy as np, pyastar2d
from scipy import ndimage
from skimage.graph import MCP_Geometric
from pipeline.planners import plan_window
n = {n}
rng = np.random.default_rng(0)
# obstacle map: 0.05 % of the cells seed discs of radius ~12 cells (15 % of the map blocked)
ok = ~ndimage.binary_dilation(rng.random((n, n)) < 0.0005, iterations=12)
free = np.argwhere(ok)
missions = []
while len(missions) < {m}:
    s, t = free[rng.integers(len(free), size=2)]
    if np.hypot(*(s - t)) > 0.6 * n:
        missions.append((tuple(int(v) for v in s), tuple(int(v) for v in t)))
flat = np.zeros((n, n), np.float32)
nor = np.zeros((n, n), bool)
w = np.where(ok, 1.0, np.inf).astype(np.float32)
plan_window(flat[:64, :64], nor[:64, :64], ok[:64, :64], (0, 0), (3, 3), cell_size=1.0,
            planner="astar")
def octile_len(p):
    d = np.abs(np.diff(np.asarray(p), axis=0))
    return float(np.sqrt((d ** 2).sum(axis=1)).sum())
result = dict(passable_pct=100 * float(ok.mean()), missions=[])
for s, t in missions:
    row = {{}}
    t0 = time.perf_counter()
    tr = plan_window(flat, nor, ok, s, t, cell_size=1.0, planner="astar")
    row["ours_s"] = time.perf_counter() - t0
    row["ours_exp"] = tr.expansions
    row["ours_len"] = tr.length_m
    t0 = time.perf_counter()
    p = pyastar2d.astar_path(w, s, t, allow_diagonal=True)
    row["pyastar2d_s"] = time.perf_counter() - t0
    row["pyastar2d_len"] = octile_len(p)
    row["pyastar2d_corner_cuts"] = int(sum(1 for a, b in zip(p[:-1], p[1:])
                                           if a[0] != b[0] and a[1] != b[1]
                                           and not (ok[a[0], b[1]] and ok[b[0], a[1]])))
    if {mcp}:
        t0 = time.perf_counter()
        mcp = MCP_Geometric(w, fully_connected=True)
        costs, _ = mcp.find_costs([s], [t])
        q = mcp.traceback(t)
        row["mcp_s"] = time.perf_counter() - t0
        row["mcp_len"] = octile_len(q)
    result["missions"].append(row)
"""

RA5000 = """
import time, numpy as np, pipeline
from pipeline.planners import plan_window
from pipeline.planners.grid import _nearest_passable
ds = pipeline.open_maps("{store}")
S = ds.safety.values; rdg = ds.ridge.values; ok = ds.passable.values
n = S.shape[0]
s = _nearest_passable(ok[:300, :300], (100, 100))
g = _nearest_passable(ok[-300:, -300:], (200, 200)); g = (g[0] + n - 300, g[1] + n - 300)
plan_window(S[:64, :64], rdg[:64, :64], ok[:64, :64], (1, 1), (60, 60), cell_size=30.0,
            planner="{planner}", omega=3.0)   # compile outside the timing
import resource
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
t0 = time.perf_counter()
tr = plan_window(S, rdg, ok, s, g, cell_size=30.0, planner="{planner}", omega=3.0)
result = dict(planner="{planner}", s=time.perf_counter() - t0, search_s=tr.runtime_s,
              expansions=tr.expansions, length_km=tr.length_m / 1e3,
              ridge_pct=100 * tr.ridge_ratio, lower_bound_km=tr.lower_bound_m / 1e3,
              rss_before_search_gib=round(base, 3), ridge_cells_pct=100 * float(rdg.mean()),
              start=list(map(int, s)), goal=list(map(int, g)))
"""


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer missions, 2000^2 core map, "
                    "no 5000^2 window")
    ap.add_argument("--only", choices=("tables", "pareto", "core", "ra5000"))
    args = ap.parse_args()
    print(machine(), flush=True)
    OUT.mkdir(exist_ok=True)
    DOCS.mkdir(exist_ok=True)

    def want(k):
        return args.only in (None, k)

    if want("tables"):
        res = tables23()
        print(f"\nTables 2/3 analog: 200 x 200 window {CASE200['window']} of the 2000^2 "
              f"seed-0 DEM, 30 m, mission {CASE200['start']} -> "
              f"{CASE200['goal']}, ridge cells {res['ridge_cells_pct']} % "
              f"(min_accumulation {CASE200['min_acc']})")
        for name, rows in res["tables"].items():
            print(f"\n{name}")
            print("| omega | paper length km | paper ridge % | ra_star length km | ridge km | "
                  "ridge % | lagrangian length km | ridge km | ridge % |")
            print("|---|---|---|---|---|---|---|---|---|")
            for om in OMEGAS:
                r, lg = rows[f"ra_star {om}"], rows[f"lagrangian {om}"]
                pl, pr = PAPER[name][om]
                print(f"| {om} | {pl:.2f} | {pr:.1f} | {r['length_km']:.2f} | "
                      f"{r['ridge_km']:.2f} | {r['ratio_pct']:.1f} | {lg['length_km']:.2f} | "
                      f"{lg['ridge_km']:.2f} | {lg['ratio_pct']:.1f} |")
        plot200(res, DOCS / "planners-200.png")
        print(f"wrote {DOCS / 'planners-200.png'}")

    if want("pareto"):
        t0 = time.perf_counter()
        res = pareto(12 if args.quick else 50)
        print(f"\nPareto: {res['missions']} random missions, 400 x 400 (seed 1), ridge cells "
              f"{res['ridge_cells_pct']} % ({time.perf_counter() - t0:.0f} s)")
        print("| planner | omega | length / L* | ridge ratio % | p10 ridge % | ms / mission | "
              "bound held |")
        print("|---|---|---|---|---|---|---|")
        for r in res["rows"].values():
            print(f"| {r['planner']} | {r['omega']} | {r['length_over_opt']:.3f} | "
                  f"{100 * r['ridge_ratio']:.1f} | {100 * r['ridge_ratio_p10']:.1f} | "
                  f"{r['ms_mean']:.1f} | {r['bound_held']} |")
        rows = res["rows"]
        ratios = [rows[f"lagrangian {om}"]["ms_mean"] / rows[f"ra_star {om}"]["ms_mean"]
                  for om in PARETO_OMEGAS]
        print("lagrangian time / ra_star time per omega: "
              + ", ".join(f"{om}: {r:.1f}x" for om, r in zip(PARETO_OMEGAS, ratios,
                                                             strict=True)))
        plot_pareto(res, DOCS / "pareto.png")
        (OUT / "pareto.json").write_text(json.dumps(res, indent=1))
        print(f"wrote {DOCS / 'pareto.png'}")

    if want("core"):
        n = 2000 if args.quick else 4000
        r = run_isolated(CORE.format(n=n, m=5, mcp=True))
        ms = r["missions"]
        tot = {k: sum(m[k] for m in ms) for k in ("ours_s", "pyastar2d_s", "mcp_s", "ours_exp")}
        print(f"\nCore speed: {n} x {n} obstacle map ({r['passable_pct']:.0f} % passable), "
              f"{len(ms)} missions, same process")
        print("| mission | astar s | expansions | pyastar2d s | MCP_Geometric s | "
              "astar length | pyastar2d length | MCP length | pyastar2d corner cuts |")
        print("|---|---|---|---|---|---|---|---|---|")
        for i, m in enumerate(ms):
            print(f"| {i} | {m['ours_s']:.3f} | {m['ours_exp']} | {m['pyastar2d_s']:.3f} | "
                  f"{m['mcp_s']:.2f} | {m['ours_len']:.1f} | {m['pyastar2d_len']:.1f} | "
                  f"{m['mcp_len']:.1f} | {m['pyastar2d_corner_cuts']} |")
        print(f"total: astar {tot['ours_s']:.2f} s, pyastar2d {tot['pyastar2d_s']:.2f} s "
              f"(astar / pyastar2d = {tot['ours_s'] / tot['pyastar2d_s']:.2f}), MCP_Geometric "
              f"{tot['mcp_s']:.1f} s (MCP / astar = {tot['mcp_s'] / tot['ours_s']:.1f}); astar "
              f"{tot['ours_exp'] / tot['ours_s'] / 1e6:.2f} M expansions/s; peak RSS "
              f"{r['peak_rss_gib']} GiB")

    if want("ra5000") and not args.quick:
        store = maps_store(5000)
        print("\nTable 4 'without MCPC' analog: 5000 x 5000, omega 3, one window "
              "(each planner in its own process)")
        print("| planner | time s | search s | expansions | length km | ridge % | "
              "lower bound km | peak RSS GiB | of which maps |")
        print("|---|---|---|---|---|---|---|---|---|")
        for planner in ("astar", "ra_star", "lagrangian"):
            r = run_isolated(RA5000.format(store=store, planner=planner))
            print(f"| {planner} | {r['s']:.2f} | {r['search_s']:.2f} | {r['expansions']} | "
                  f"{r['length_km']:.1f} | {r['ridge_pct']:.1f} | {r['lower_bound_km']:.1f} | "
                  f"{r['peak_rss_gib']} | {r['rss_before_search_gib']} |")
        print(f"(mission {r['start']} -> {r['goal']}, ridge cells {r['ridge_cells_pct']:.1f} %)")


if __name__ == "__main__":
    main()
