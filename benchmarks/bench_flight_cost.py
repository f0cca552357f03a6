"""Issue 75 figures: what the flight costs beside the planning it follows.

Long random missions (ends at least half the map apart, omega 1.5 / 2 / 3 in turn) on the
synthetic ridge maps (30 m cells, R 300 m), planned and then flown with the default vehicle,
by the library before (``--before``, by default the revision before the flight's check was
made cheaper, checked out in a git worktree) and after, each in a process of its own after a
warm-up of two missions: the planning (``plan_missions``, in-process, one thread) and the
flight (``fly``) of each mission timed apart, and the flight's own least clearance of each
mission compared between the versions (the cheaper check must give the same figures). Then
``plan_missions`` with the default vehicle (planned and flown on the worker) on a LocalCluster
of 2 single-threaded workers, 80 long missions on the 4000^2 maps: missions per second.

    .venv/bin/python benchmarks/bench_flight_cost.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

from _common import OUT, checkout, far_missions, machine, maps_store
from _report import Report

ROOT = Path(__file__).resolve().parents[1]
# the library before the flight's own check was made cheaper
BEFORE = "927faea"

MEASURE = r"""
import json, sys, time
sys.path.insert(0, sys.argv[1])
import pipeline
store, missions = sys.argv[2], json.loads(sys.argv[3])
ms = [{**m, "start": tuple(m["start"]), "goal": tuple(m["goal"])} for m in missions]
pipeline.plan_missions(store, ms[:2], vehicle={}, client="synchronous")  # compiled, warm
plan, fly, least = [], [], []
for m in ms:
    t0 = time.perf_counter()
    t = pipeline.plan_missions(store, [m], client="synchronous")[0]
    t1 = time.perf_counter()
    f = pipeline.fly(store, t, {})
    t2 = time.perf_counter()
    plan.append(t1 - t0)
    fly.append(t2 - t1)
    least.append(f.min_clearance_m)
print(json.dumps(dict(plan=plan, fly=fly, least=least)))
"""

THROUGHPUT = r"""
import json, sys, time
sys.path.insert(0, sys.argv[1])
import pipeline
from distributed import Client, LocalCluster
store, missions = sys.argv[2], json.loads(sys.argv[3])
ms = [{**m, "start": tuple(m["start"]), "goal": tuple(m["goal"])} for m in missions]
with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                  dashboard_address=None) as cluster, Client(cluster) as c:
    pipeline.plan_missions(store, ms[:4], vehicle={}, client=c)  # compiled and warm on both
    out = []
    for _ in range(3):
        t0 = time.perf_counter()
        ts = pipeline.plan_missions(store, ms, vehicle={}, client=c)
        out.append(time.perf_counter() - t0)
    ok = sum(t.flight is not None and str(t.status) != "failed" for t in ts)
print(json.dumps(dict(seconds=out, ok=ok)))
"""


def _run(code: str, checkout: Path, *args) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", code, str(checkout), *args],
        capture_output=True, text=True, check=True, cwd=checkout,
    )  # fmt: skip
    return json.loads(out.stdout.strip().splitlines()[-1])


def _missions(n: int, count: int) -> list[dict]:
    import pipeline

    ok = pipeline.open_maps(maps_store(n))["passable"]
    return [
        {"name": f"m{k}", "start": s, "goal": g, "omega": (1.5, 2.0, 3.0)[k % 3]}
        for k, (s, g) in enumerate(far_missions(ok, n, count, 75))
    ]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer missions, no 10000^2 map")
    ap.add_argument("--before", default=BEFORE, help="the revision measured as before")
    args = ap.parse_args()
    print(machine(), flush=True)
    sizes = [(2000, 20), (4000, 20)] + ([] if args.quick else [(10000, 10)])
    rows, same = [], []
    with checkout(args.before) as old:
        for n, count in sizes:
            ms = _missions(n, count // (2 if args.quick else 1))
            got = {}
            for version, code in (("before", old), ("after", ROOT)):
                got[version] = _run(MEASURE, code, str(maps_store(n)), json.dumps(ms))
                g = got[version]
                plan, fly = statistics.median(g["plan"]), statistics.median(g["fly"])
                ratio = statistics.median(f / p for f, p in zip(g["fly"], g["plan"], strict=True))
                rows.append([f"{n}^2", len(ms), version, plan, fly, ratio])
                print(rows[-1], flush=True)
            diff = max(
                abs(a - b)
                for a, b in zip(got["before"]["least"], got["after"]["least"], strict=True)
            )
            same.append((n, diff))
        ms = _missions(4000, 40 if args.quick else 80)
        batch = {}
        for version, code in (("before", old), ("after", ROOT)):
            batch[version] = _run(THROUGHPUT, code, str(maps_store(4000)), json.dumps(ms))
            print(version, batch[version], flush=True)
    _report(rows, same, batch, len(ms), args)


def _report(rows, same, batch, count, args) -> None:
    (OUT / f"flight-cost{'-quick' if args.quick else ''}.json").write_text(
        json.dumps(dict(rows=rows, same=same, batch=batch))
    )
    rep = Report(
        "flight_cost",
        18,
        "What the flight costs beside its planning",
        ".venv/bin/python benchmarks/bench_flight_cost.py",
        args.quick,
    )
    rep.p(__doc__.split("\n\n")[1])
    rep.table(
        ["map", "missions", "version", "planning (median)", "flight (median)", "flight / planning"],
        [
            [m, k, v, f"{1000 * p:.1f} ms", f"{1000 * f:.1f} ms", f"{r:.2f}x"]
            for m, k, v, p, f, r in rows
        ],
    )
    rep.p(
        "The flight's own least clearance of each mission, after against before: largest "
        "difference " + ", ".join(f"{d:.2g} m at {n}^2" for n, d in same) + " (target: none)."
    )
    per = {v: count / min(b["seconds"]) for v, b in batch.items()}
    rep.p(
        f"`plan_missions` with the default vehicle, {count} long missions on the 4000^2 maps, "
        f"LocalCluster of 2 single-threaded workers (best of 3): before {per['before']:.1f} "
        f"missions/s, after {per['after']:.1f} missions/s ({batch['after']['ok']} of {count} "
        "flown ok); target (issue 75): >= 200 missions/s."
    )
    after = [r for r in rows if r[2] == "after"]
    rep.headline(
        "flight_cost",
        75,
        "the flight of a long mission against its planning (median, 2000^2 to 10000^2)",
        ", ".join(f"{r[5]:.2f}x at {r[0]}" for r in after)
        + f"; plan + fly {per['after']:.0f} missions/s at 4000^2",
        target="<= 0.25x at every size; >= 200 missions/s",
    )
    rep.p(f"Machine: {machine()}")
    rep.save()


if __name__ == "__main__":
    main()
