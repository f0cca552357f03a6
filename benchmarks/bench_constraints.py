"""Issue 64 figures: operational constraints on 4000^2 (synthetic, 30 m cells, R = 300 m).

Missions far apart on the map planned and flown four ways, in one process (``client=
"threads"``, the kernels compiled first): without constraints, with 20 keep-out zones (random
polygons of 0.3-1 km across the straight line, a 100 m margin), with 5 via points along the
way, and with both. For each: the planning and flight times and their ratios to the mission
without constraints, the lengths, the status and certified ratio, and the checks that leave
the tool (shapely on the continuous route, the waypoint legs and the flown track: the least
distance from a zone, which must be at least the margin; each via point a waypoint).

    .venv/bin/python benchmarks/bench_constraints.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np
from _common import OUT, far_missions, machine, maps_store
from _report import Report

MARGIN_M = 100.0


def _zones(m, ok, s, g, rng, count: int = 20):
    """``count`` random polygons (7 vertices, 150-500 m from a centre) near the straight line
    from ``s`` to ``g``, none holding an end."""
    import shapely

    a = m.cell_size
    out = []
    while len(out) < count:
        t = rng.uniform(0.1, 0.9)
        r, c = (1 - t) * np.asarray(s) + t * np.asarray(g) + rng.normal(0, 60, 2)
        r, c = int(np.clip(r, 0, m.shape[0] - 1)), int(np.clip(c, 0, m.shape[1] - 1))
        cx, cy = m.x[c], m.y[r]
        ang = np.sort(rng.uniform(0, 2 * np.pi, 7))
        rad = rng.uniform(150.0, 500.0, 7)
        poly = shapely.Polygon(np.c_[cx + rad * np.cos(ang), cy + rad * np.sin(ang)])
        ends = [shapely.Point(m.x[p[1]], m.y[p[0]]) for p in (s, g)]
        if all(poly.distance(e) > MARGIN_M + 2 * a for e in ends):
            out.append(poly)
    return out


def _vias(m, ok, s, g, zones, rng, count: int = 5):
    """``count`` passable points spread along the way, off the straight line, clear of the
    zones and their margins."""
    import shapely

    kept = shapely.union_all([z.buffer(MARGIN_M + 2 * m.cell_size) for z in zones])
    out = []
    for k in range(count):
        while True:
            t = (k + rng.uniform(0.6, 1.4)) / (count + 1)
            r, c = (1 - t) * np.asarray(s) + t * np.asarray(g) + rng.normal(0, 150, 2)
            r, c = int(np.clip(r, 0, m.shape[0] - 1)), int(np.clip(c, 0, m.shape[1] - 1))
            if ok[r, c] and not kept.contains(shapely.Point(m.x[c], m.y[r])):
                out.append((r, c))
                break
    return out


def _least(zones, *lines) -> float:
    import shapely

    geoms = [shapely.LineString(np.c_[x, y]) for x, y in lines]
    return min(line.distance(z) for line in geoms for z in zones) if zones else float("nan")


def run(n: int, count: int) -> list[dict]:
    import pipeline

    store = maps_store(n)
    m = pipeline.open_store(store)
    ok = pipeline.open_maps(store)["passable"]
    missions = far_missions(ok, n, count, seed=64)
    rng = np.random.default_rng(64)
    okv = ok.values
    # the kernels compiled (and the store's coarse level written) before anything is timed
    warm = pipeline.plan(store, *missions[0], client="threads")
    pipeline.fly(store, warm)
    rows = []
    for i, (s, g) in enumerate(missions):
        zones = _zones(m, okv, s, g, rng)
        vias = _vias(m, okv, s, g, zones, rng)
        cases = {
            "none": {},
            "20 zones": dict(keep_out=zones, keep_out_margin_m=MARGIN_M),
            "5 via points": dict(via=vias),
            "both": dict(keep_out=zones, keep_out_margin_m=MARGIN_M, via=vias),
        }
        for name, opts in cases.items():
            t0 = time.perf_counter()
            t = pipeline.plan(store, s, g, client="threads", **opts)
            plan_s = time.perf_counter() - t0
            t1 = time.perf_counter()
            f = pipeline.fly(store, t)
            fly_s = time.perf_counter() - t1
            zs = zones if "keep_out" in opts else []
            via_wp = [
                float(np.hypot(f.waypoints[:, 0] - m.x[c], f.waypoints[:, 1] - m.y[r]).min())
                for r, c in (vias if "via" in opts else [])
            ]
            rows.append(
                dict(
                    mission=i,
                    case=name,
                    plan_s=plan_s,
                    fly_s=fly_s,
                    status=str(t.status),
                    length_km=t.length_m / 1e3,
                    certified_ratio=t.certified_ratio,
                    flown_km=f.flown_length_m / 1e3,
                    flight_problems=len(f.problems),
                    problems=list(f.problems),
                    least_zone_m=_least(
                        zs, t.points[:, :2].T, (f.x, f.y), (f.waypoints[:, 0], f.waypoints[:, 1])
                    ),
                    via_waypoint_m=max(via_wp) if via_wp else float("nan"),
                    via_miss_m=max(f.via_miss_m) if f.via_miss_m else float("nan"),
                )
            )
            print(json.dumps(rows[-1]), flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="2000^2, 2 missions")
    args = ap.parse_args()
    print(machine(), flush=True)
    n, count = (2000, 2) if args.quick else (4000, 5)
    rows = run(n, count)
    (OUT / f"constraints{'-quick' if args.quick else ''}.json").write_text(json.dumps(rows))
    rep = Report(
        "constraints",
        12,
        "Operational constraints: keep-out zones and via points",
        ".venv/bin/python benchmarks/bench_constraints.py",
        args.quick,
    )
    rep.p(f"""{count} missions at least half the map apart on the {n}^2 synthetic map (30 m,
    R = 300 m), each planned (`plan`, ra_star, omega 2, MCPC, `client="threads"`) and flown
    (`fly`, the default vehicle) without constraints, with 20 random keep-out zones of
    0.3-1 km across its straight line (margin {MARGIN_M:g} m), with 5 via points along the
    way, and with both. "least distance" is shapely's, from the zones to the grid path, the
    flown track and the waypoint legs (at least the margin when the constraint holds);
    "via waypoint" the farthest via point from its nearest waypoint (0: each is a waypoint);
    "via miss" the flown track's farthest closest approach to a via point.""")
    base = {r["mission"]: r for r in rows if r["case"] == "none"}
    table = []
    for case in ("none", "20 zones", "5 via points", "both"):
        rs = [r for r in rows if r["case"] == case]
        ratio_p = [r["plan_s"] / base[r["mission"]]["plan_s"] for r in rs]
        ratio_f = [r["fly_s"] / base[r["mission"]]["fly_s"] for r in rs]
        least = [r["least_zone_m"] for r in rs if r["least_zone_m"] == r["least_zone_m"]]
        table.append(
            [
                case,
                statistics.median(r["plan_s"] for r in rs),
                f"{statistics.median(ratio_p):.2f}x",
                statistics.median(r["fly_s"] for r in rs),
                f"{statistics.median(ratio_f):.2f}x",
                statistics.median(r["length_km"] for r in rs),
                max(r["certified_ratio"] for r in rs),
                sum(r["status"] == "ok" for r in rs),
                sum(r["flight_problems"] > 0 for r in rs),
                min(least) if least else "",
                max(
                    (r["via_waypoint_m"] for r in rs if r["via_waypoint_m"] == r["via_waypoint_m"]),
                    default="",
                ),
                max(
                    (r["via_miss_m"] for r in rs if r["via_miss_m"] == r["via_miss_m"]), default=""
                ),
            ]
        )
    rep.table(
        [
            "constraints",
            "plan s (median)",
            "vs none",
            "fly s (median)",
            "vs none",
            "length km",
            "worst certified ratio",
            "ok",
            "flight problems",
            "least distance from a zone m",
            "via waypoint m",
            "via miss m",
        ],
        table,
    )
    seen = sorted({(r["case"], p) for r in rows for p in r["problems"]})
    if seen:
        rep.p(
            "The flight problems (the mission then fails with the reason, as a job records "
            "it): " + "; ".join(f"{case}: {p}" for case, p in seen) + ". A via point drawn "
            "at random may lie where the seabed rises close to the surface limit: the pitch "
            "limit cannot reach it and stay below the limit, which no smoothing can change."
        )
    both = table[3]
    rep.headline(
        "constraints",
        60,
        f"a mission with 20 keep-out zones and 5 via points, {n}^2",
        f"plan {both[2]}, fly {both[4]} the unconstrained time; "
        f"route >= {MARGIN_M:g} m from every zone",
        target="zones kept on the continuous route",
    )
    rep.save()


if __name__ == "__main__":
    main()
