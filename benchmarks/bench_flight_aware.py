"""Issue 74 figures: planning that hears the flight, and a flight that keeps the ridges.

Random missions on three maps, each planned and flown with ``plan_missions`` (in-process
threads, after a warm-up of two missions) by the library before (``--before``, by default the
revision before issue 74, checked out in a git worktree) and after, each in a process of its
own. Per map and version: missions failed for their flight, the share of the grid path's
ridge share the flown track keeps (both measured here alike: the share of the length over
ridge cells, the track walked every eighth of a cell against the maps' ridge layer, the grid
path cell to cell), waypoints, the flown length against the grid path's, and the time per
mission. The lower bound's strength, bound / L* with L* from scipy's Dijkstra
on the graph built here from the definition (``bench_certify.csgraph``), is measured on the
missions as given (the bound a mission keeps is the one proven for them).

Maps: a seamount field (240^2 cells of 1000 m, 40 Gaussian seamounts with summits 2600-3400 m
deep on a 5000 m plain; R 3000 m, surface clearance 100 m; vehicle: turn radius 400 m, pitch
15 degrees: the settings of the issue's Hawaii runs); matplotlib's real bathymetry off
Vancouver Island as ``tasks/topobathy.toml`` builds it (150 m cells, R 100 m, surface
clearance 50 m; the default vehicle); the benchmark's 2000^2 synthetic ridge (30 m, R 300 m;
the default vehicle).

    .venv/bin/python benchmarks/bench_flight_aware.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np
from _common import OUT, checkout, machine, maps_store
from _report import Report
from bench_certify import csgraph, optimum

ROOT = Path(__file__).resolve().parents[1]
SEAMOUNT_VEHICLE = {"min_turn_radius_m": 400.0, "max_pitch_deg": 15.0}
# the library before the flight was heard by the planner (the parent of issue 74's first commit)
BEFORE = "44d0ad8"


def seamount_store() -> Path:
    """``benchmarks/out/seamounts.zarr``, built once."""
    import rioxarray  # noqa: F401 - the .rio accessor
    import xarray as xr

    import pipeline

    store = OUT / "seamounts.zarr"
    if store.exists():
        return store
    rng = np.random.default_rng(0)
    n, a = 240, 1000.0
    y, x = np.mgrid[0:n, 0:n].astype(float)
    z = np.full((n, n), -5000.0) + 300 * np.sin(x / 17) * np.cos(y / 23)
    for _ in range(40):
        cy, cx = rng.uniform(0, n, 2)
        s, top = rng.uniform(4, 12), rng.uniform(-3400, -2600)
        z = np.maximum(
            z, -5000 + (top + 5000) * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / s**2 / 2)
        )
    dem = xr.DataArray(
        z.astype("float32"),
        dims=("y", "x"),
        coords={"y": (n - 1 - np.arange(n)) * a + a / 2, "x": np.arange(n) * a + a / 2},
        name="elevation",
    ).rio.write_crs("EPSG:32610")
    pipeline.build_maps(dem, store, clearance=3000.0, surface_clearance=100.0)
    return store


def topobathy_store() -> Path:
    """The maps of ``tasks/topobathy.toml``'s DEM (its resolution and maps parameters)."""
    import pipeline

    store = OUT / "topobathy-maps.zarr"
    if store.exists():
        return store
    nc = ROOT / "tasks" / "data" / "topobathy.nc"
    if not nc.exists():
        subprocess.run(
            [sys.executable, str(ROOT / "tasks" / "data" / "make_topobathy.py")], check=True
        )
    dem = pipeline.open_dem(nc, resolution=150.0)
    pipeline.build_maps(dem, store, method="spherical", clearance=100.0, surface_clearance=50.0)
    return store


def random_missions(ok: np.ndarray, count: int, seed: int, min_cells: int) -> list[dict]:
    """``count`` missions between passable cells of one component at least ``min_cells``
    apart (Chebyshev)."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    labels, _ = ndimage.label(ok, structure=np.ones((3, 3)))
    cells = np.argwhere(ok)
    out = []
    while len(out) < count:
        s, g = cells[rng.integers(len(cells))], cells[rng.integers(len(cells))]
        if labels[tuple(s)] == labels[tuple(g)] and np.abs(s - g).max() >= min_cells:
            out.append(
                {"name": f"m{len(out)}", "start": tuple(map(int, s)), "goal": tuple(map(int, g))}
            )
    return out


MEASURE = r"""
import json, sys, time
sys.path.insert(0, sys.argv[1])
import numpy as np
import pipeline
store, missions = sys.argv[2], json.loads(sys.argv[3])
vehicle, omega = json.loads(sys.argv[4]), float(sys.argv[5])
def share(ridge, x0, y0, a, x, y):
    # the share of the polyline (map x, y) over ridge cells, walked every eighth of a cell
    on = total = 0.0
    for k in range(1, len(x)):
        ln = ((x[k] - x[k - 1]) ** 2 + (y[k] - y[k - 1]) ** 2) ** 0.5
        n = max(1, int(8 * ln / a) + 1)
        t = (np.arange(n) + 0.5) / n
        c = np.floor((x[k - 1] + t * (x[k] - x[k - 1]) - x0) / a + 0.5).astype(int)
        r = np.floor((y0 - (y[k - 1] + t * (y[k] - y[k - 1]))) / a + 0.5).astype(int)
        inside = (r >= 0) & (r < ridge.shape[0]) & (c >= 0) & (c < ridge.shape[1])
        hit = np.zeros(n, bool)
        hit[inside] = ridge[r[inside], c[inside]]
        on += ln * hit.mean()
        total += ln
    return on / total if total > 0 else 0.0
def main():
    ds = pipeline.open_maps(store)
    ridge = ds["ridge"].values.astype(bool)
    xs, ys = ds["x"].values, ds["y"].values
    x0, y0, a = float(xs[0]), float(ys[0]), float(xs[1] - xs[0])
    ms = [{**m, "start": tuple(m["start"]), "goal": tuple(m["goal"]), "omega": omega}
          for m in missions]
    pipeline.plan_missions(store, ms[:2], vehicle=vehicle, client="threads")  # compiled, warm
    t0 = time.perf_counter()
    ts = pipeline.plan_missions(store, ms, vehicle=vehicle, client="threads")
    per = (time.perf_counter() - t0) / len(ms)
    rows = []
    for m, t in zip(ms, ts):
        f = t.flight
        rows.append(dict(
            mission=m["name"], status=str(t.status),
            for_flight=bool(str(t.status) == "failed" and f is not None),
            rounds=len(t.extra.get("flight_rounds", [])),
            planned=share(ridge, x0, y0, a, x0 + a * t.cells[:, 1], y0 - a * t.cells[:, 0]),
            flown=share(ridge, x0, y0, a, f.x, f.y) if f is not None else None,
            waypoints=len(f.waypoints) if f is not None else None,
            flown_over_grid=f.flown_length_m / t.length_m if f is not None else None,
            lower_bound_m=t.lower_bound_m,
        ))
    print(json.dumps(dict(rows=rows, per=per)))
if __name__ == "__main__":
    main()
"""


def flown(store: Path, missions: list, vehicle: dict | None, omega: float, code: Path) -> tuple:
    """The missions planned and flown by the library at ``code`` (a checkout's root), in a
    process of its own: each mission's figures, and the time per mission."""
    out = subprocess.run(
        [sys.executable, "-c", MEASURE, str(code), str(store), json.dumps(missions),
         json.dumps(vehicle or {}), str(omega)],
        capture_output=True, text=True, check=True, cwd=code,
    )  # fmt: skip
    got = json.loads(out.stdout.strip().splitlines()[-1])
    return got["rows"], got["per"]


def summary(rows: list, per_mission_s: float) -> dict:
    ok = [r for r in rows if r["status"] != "failed" and r["flown"] is not None]
    kept = [r["flown"] / r["planned"] if r["planned"] > 0 else 1.0 for r in ok]
    return dict(
        failed_for_flight=sum(r["for_flight"] for r in rows),
        failed=sum(r["status"] == "failed" for r in rows),
        flown=len(ok),
        kept_90=sum(k >= 0.9 for k in kept) / len(kept) if kept else float("nan"),
        kept_min=min(kept) if kept else float("nan"),
        kept_median=statistics.median(kept) if kept else float("nan"),
        waypoints_median=statistics.median(r["waypoints"] for r in ok) if ok else float("nan"),
        flown_over_grid_max=max(r["flown_over_grid"] for r in ok) if ok else float("nan"),
        replanned=sum(r["rounds"] > 0 for r in rows),
        per_mission_s=per_mission_s,
    )


def hard_missions(ok: np.ndarray, count: int, seed: int, min_cells: int) -> list[dict]:
    """Of 20 x ``count`` random missions (:func:`random_missions`), the ``count`` whose
    straight line is most blocked (the share of its samples, every half cell, on cells that
    are not passable): where the lower bound is weakest."""
    cands = random_missions(ok, 20 * count, seed + 1, min_cells)

    def blocked(m):
        (r0, c0), (r1, c1) = m["start"], m["goal"]
        n = 2 * max(abs(r1 - r0), abs(c1 - c0)) + 1
        t = np.linspace(0.0, 1.0, n)
        r = np.rint(r0 + t * (r1 - r0)).astype(int)
        c = np.rint(c0 + t * (c1 - c0)).astype(int)
        return float(np.mean(~ok[r, c]))

    return sorted(cands, key=blocked, reverse=True)[:count]


def bound_strength(store: Path, missions: list, bounds: list) -> list[float]:
    """bound / L* of each mission (L* from scipy's Dijkstra on the maps' graph)."""
    import pipeline

    ds = pipeline.open_maps(store)
    ok = ds["passable"].values.astype(bool)
    graph = csgraph(ds["safety"].values, ok, float(abs(ds["x"].values[1] - ds["x"].values[0])))
    out = []
    for m, bound in zip(missions, bounds, strict=True):
        best = optimum(graph, ok.shape, m["start"], m["goal"])
        if np.isfinite(best) and best > 0 and bound == bound:
            out.append(bound / best)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer missions, no 2000^2 map")
    ap.add_argument("--before", default=BEFORE, help="the revision measured as before")
    args = ap.parse_args()
    print(machine(), flush=True)
    import pipeline

    maps = [
        ("seamount field (1000 m cells)", seamount_store(), SEAMOUNT_VEHICLE, 1.5, 40, 60),
        ("real bathymetry off Vancouver Island (150 m)", topobathy_store(), None, 2.0, 40, 150),
    ]
    if not args.quick:
        maps.append(("synthetic ridge 2000^2 (30 m)", maps_store(2000), None, 2.0, 20, 800))
    results = []
    with checkout(args.before) as old:
        for label, store, vehicle, omega, count, min_cells in maps:
            ok = pipeline.open_maps(store)["passable"].values.astype(bool)
            missions = random_missions(ok, count // (4 if args.quick else 1), 74, min_cells)
            results.append(_versions(label, store, vehicle, omega, missions, old))
    _report(results, args)


def _versions(label, store, vehicle, omega, missions, old: Path) -> dict:
    """The missions flown by the library before and after; the bound's strength after."""
    out = {}
    for version, code in (("before", old), ("after", ROOT)):
        rows, per = flown(store, missions, vehicle, omega, code)
        out[version] = dict(rows=rows, summary=summary(rows, per))
        print(label, version, json.dumps(out[version]["summary"]), flush=True)
    strength = bound_strength(store, missions, [r["lower_bound_m"] for r in out["after"]["rows"]])
    import pipeline

    ok = pipeline.open_maps(store)["passable"].values.astype(bool)
    hard = hard_missions(ok, len(missions) // 2, 74, max(8, len(ok) // 8))
    bounds = []
    for m in hard:
        try:
            t = pipeline.plan(store, m["start"], m["goal"], omega=omega, client="synchronous")
            bounds.append(t.lower_bound_m)
        except pipeline.PipelineError:  # (apart for the planner's graph: no corner cutting)
            bounds.append(float("nan"))
    return dict(
        label=label,
        omega=omega,
        count=len(missions),
        out=out,
        strength=strength,
        hard=bound_strength(store, hard, bounds),
    )


def _report(results: list, args) -> None:
    (OUT / f"flight-aware{'-quick' if args.quick else ''}.json").write_text(json.dumps(results))
    rep = Report(
        "flight_aware",
        17,
        "Flight-aware planning: planned again around the flight, the ridges kept",
        ".venv/bin/python benchmarks/bench_flight_aware.py",
        args.quick,
    )
    rep.p(__doc__.split("\n\n")[1] + "\n\n" + __doc__.split("\n\n")[2])
    rows = []
    for r in results:
        for version in ("before", "after"):
            s = r["out"][version]["summary"]
            rows.append(
                [
                    r["label"],
                    version,
                    f"{r['count']} (omega {r['omega']:g})",
                    s["failed_for_flight"],
                    s["failed"],
                    s["replanned"],
                    f"{100 * s['kept_90']:.0f} %",
                    f"{100 * s['kept_min']:.0f} %",
                    f"{100 * s['kept_median']:.0f} %",
                    s["waypoints_median"],
                    f"{s['flown_over_grid_max']:.3f}",
                    f"{1000 * s['per_mission_s']:.0f} ms",
                ]
            )
    rep.table(
        [
            "map",
            "version",
            "missions",
            "failed for the flight",
            "failed (all reasons)",
            "planned again",
            "flown keeping >= 90 % of the ridge share",
            "least kept",
            "median kept",
            "waypoints (median)",
            "flown / grid length (max)",
            "time per mission",
        ],
        rows,
    )
    srows = []
    for r in results:
        for kind, key in (("random (those above)", "strength"), ("hard", "hard")):
            st = np.array(r[key])
            srows.append(
                [
                    r["label"],
                    f"{len(st)} {kind}",
                    f"{100 * np.mean(st >= 0.95):.0f} %",
                    f"{np.median(st):.3f}",
                    f"{st.min():.3f}",
                ]
            )
    rep.p("""The lower bound each mission keeps against scipy's L* of the mission as given, for
    the missions above and for hard ones: of 20 times as many random missions at least an
    eighth of the map apart, those whose straight line crosses the most impassable cells
    (planned with `plan`, the same omega):""")
    rep.table(["map", "missions", "bound >= 0.95 L*", "median bound / L*", "least"], srows)
    for r in results:
        b, a = r["out"]["before"]["summary"], r["out"]["after"]["summary"]
        rep.headline(
            f"flight_aware_{r['label'].split()[0]}",
            74,
            f"flight-aware planning, {r['label']}: failed for the flight; kept >= 90 % ridge",
            f"{a['failed_for_flight']} (was {b['failed_for_flight']}); {100 * a['kept_90']:.0f} % "
            f"(was {100 * b['kept_90']:.0f} %)",
            target="0 where a flyable route exists; >= 90 % of missions",
        )
    rep.p(f"Machine: {machine()}")
    rep.save()


if __name__ == "__main__":
    main()
