"""Issue 7 figures: the demo job's wall time and peak memory from a cold catalog, and the
throughput of ``plan_missions`` (missions per second) for 100 missions on a 4000 x 4000 maps
store on a LocalCluster of 2 single-threaded workers.

    .venv/bin/python benchmarks/bench_jobs.py [--quick]
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

from _common import OUT, machine, maps_store, run_isolated

ROOT = Path(__file__).resolve().parents[1]

THROUGHPUT = """
import time, numpy as np, pipeline
from distributed import Client, LocalCluster
store = "{store}"
ok = pipeline.open_maps(store)["passable"].values
rng = np.random.default_rng(11)
n = ok.shape[0]
missions = []
while len(missions) < {k}:
    s, g = rng.integers(n, size=2), rng.integers(n, size=2)
    if ok[tuple(s)] and ok[tuple(g)] and np.hypot(*(s - g)) > 0.3 * n:
        missions.append({{"start": tuple(map(int, s)), "goal": tuple(map(int, g)),
                         "omega": float(rng.choice([1.5, 2.0, 3.0]))}})
with LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None) as cl, \\
        Client(cl) as c:
    pipeline.plan_missions(store, missions[:4], client=c)   # warm: coarse maps, chunks
    t0 = time.perf_counter()
    ts = pipeline.plan_missions(store, missions, client=c)
    dt = time.perf_counter() - t0
    t0 = time.perf_counter()
    for m in missions[:20]:
        pipeline.plan(store, m["start"], m["goal"], omega=m["omega"], client=c)
    seq = (time.perf_counter() - t0) / 20
    peaks = [round(v / 2**20, 3) for v in c.run(lambda: __import__("resource").getrusage(
        __import__("resource").RUSAGE_SELF).ru_maxrss).values()]
result = dict(missions=len(ts), ok=sum(t.status == "ok" for t in ts), seconds=dt,
              per_s=len(ts) / dt, sequential_s=seq,
              ridge=float(np.mean([t.ridge_ratio for t in ts if t.status == "ok"])),
              worker_peak_gib=peaks)
"""


def demo() -> dict:
    cat = ROOT / "catalogs" / "demo"
    shutil.rmtree(cat, ignore_errors=True)
    cmd = ["/usr/bin/time", "-v", str(Path(sys.executable).parent / "pipeline"), "run",
           str(ROOT / "tasks" / "demo.toml")]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    wall = time.perf_counter() - t0
    peak = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr).group(1))
    stages = re.findall(r"INFO pipeline\.\w+: (built maps store .*|wrote DEM store .*)",
                        proc.stderr)
    return dict(exit=proc.returncode, wall_s=wall, client_peak_gib=peak / 2**20,
                summary=proc.stdout.strip().splitlines()[-1], stages=stages)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="20 missions on 2000^2")
    args = ap.parse_args()
    print(machine(), flush=True)
    OUT.mkdir(exist_ok=True)
    d = demo()
    print(f"\nDemo job from an empty catalog (`pipeline run tasks/demo.toml`): exit {d['exit']}, "
          f"wall {d['wall_s']:.1f} s, client process peak RSS {d['client_peak_gib']:.2f} GiB "
          f"(/usr/bin/time -v; the 2 workers are separate processes)")
    print(f"  {d['summary']}")
    for s in d["stages"]:
        print(f"  {s}")
    n, k = (2000, 20) if args.quick else (4000, 100)
    r = run_isolated(THROUGHPUT.format(store=maps_store(n), k=k))
    print(f"\nplan_missions: {r['missions']} missions ({r['ok']} ok) on {n} x {n}, ra_star "
          f"omega 1.5-3, 2 workers: {r['seconds']:.1f} s = **{r['per_s']:.1f} missions/s** "
          f"(one at a time with plan(): {r['sequential_s']:.3f} s each = "
          f"{1 / r['sequential_s']:.1f} /s); mean ridge {100 * r['ridge']:.0f} %; client peak "
          f"{r['peak_rss_gib']} GiB, workers {r['worker_peak_gib']} GiB")


if __name__ == "__main__":
    main()
