"""Issue 7 figures: the demo job's wall time and peak memory from a cold catalog, and the
throughput of ``plan_missions`` (missions per second) for 100 missions on a 4000 x 4000 maps
store on a LocalCluster of 2 single-threaded workers, then for 40 of them flown and recorded
as a job records them. Issue 17's cold start: ``./dev demo`` in
a fresh clone of the last commit (a new virtual environment, nothing compiled), install and
compilation timed apart.

    .venv/bin/python benchmarks/bench_jobs.py [--quick] [--no-cold-start]
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import OUT, machine, maps_store, run_isolated, run_job_timed
from _report import Report

ROOT = Path(__file__).resolve().parents[1]

THROUGHPUT = """
import time, numpy as np, pipeline
from distributed import Client
from pipeline.runtime.cluster import local_cluster
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
# the store's files in the operating system's file cache, as after any earlier use of the map
# (this part runs after the scale part's 40000^2 builds, which push them out of it)
import os
t0 = time.perf_counter()
cached = 0
for top, _, files in os.walk(store):
    for f in files:
        with open(os.path.join(top, f), "rb") as fh:
            while chunk := fh.read(1 << 20):
                cached += len(chunk)
cache_s = time.perf_counter() - t0
with local_cluster(dashboard_address=None) as cl, \\
        Client(cl) as c:
    pipeline.plan_missions(store, missions[:4], client=c)   # warm: coarse maps, chunks
    from distributed import WorkerPlugin
    class Spans(WorkerPlugin):  # each mission task's start and end by the worker's own clock
        name = "spans"
        def setup(self, worker):
            self.log = []
        def transition(self, key, start, finish, **kwargs):
            if str(key).startswith("mission") and "executing" in (start, finish):
                self.log.append((str(key), finish == "executing", time.time()))
    c.register_plugin(Spans())
    def cpu():
        r = __import__("resource").getrusage(__import__("resource").RUSAGE_SELF)
        return r.ru_utime + r.ru_stime
    before = c.run(cpu)
    cpu0 = cpu()
    t0 = time.perf_counter()
    ts = pipeline.plan_missions(store, missions, client=c)
    dt = time.perf_counter() - t0
    client_cpu = 100 * (cpu() - cpu0) / dt
    after = c.run(cpu)
    busy = [round(100 * (after[w] - before[w]) / dt) for w in sorted(after)]
    logs = c.run(lambda dask_worker: dask_worker.plugins["spans"].log)
    c.unregister_worker_plugin("spans")
    occupied = []
    for w in sorted(logs):
        began, total = {{}}, 0.0
        for key, starts, t in logs[w]:
            if starts:
                began[key] = t
            elif key in began:
                total += t - began.pop(key)
        occupied.append(round(100 * total / dt))
    tasks = sum(len(v) for v in logs.values()) // 2
    t0 = time.perf_counter()
    for m in missions[:20]:
        pipeline.plan(store, m["start"], m["goal"], omega=m["omega"], client=c)
    seq = (time.perf_counter() - t0) / 20
    # as a job runs them: each flown by the default vehicle, then recorded by the client as it
    # ends (the independent clearance check, the mission's files and STAC Item; no quick-look)
    import tempfile
    from pathlib import Path
    from pipeline.outputs.catalog import write_mission
    from pipeline.verify.clearance import min_clearance
    named = [dict(m, name=f"m{{i}}") for i, m in enumerate(missions[:{k_rec}])]
    maps = pipeline.open_store(store)
    R = maps.parameters.clearance_m
    t0 = time.perf_counter()
    pipeline.plan_missions(store, named, client=c, vehicle={{}})
    flown_s = time.perf_counter() - t0
    busy_rec = [0.0]
    with tempfile.TemporaryDirectory() as tmp:
        def record(i, m, t):
            a = time.perf_counter()
            clr = min_clearance(maps, t, R)
            write_mission(Path(tmp), m["name"], m, t, maps=maps, crs_wkt=maps.crs_wkt,
                          min_clearance_m=clr, run_id="bench", quicklook=False)
            busy_rec[0] += time.perf_counter() - a
        t0 = time.perf_counter()
        pipeline.plan_missions(store, named, client=c, vehicle={{}}, on_done=record)
        recorded_s = time.perf_counter() - t0
    peaks = [round(v, 3) for v in c.run(own_peak_gib).values()]
result = dict(missions=len(ts), ok=sum(t.status == "ok" for t in ts), seconds=dt,
              per_s=len(ts) / dt, sequential_s=seq, busy=busy, occupied=occupied,
              client_cpu=client_cpu, tasks=tasks, cached_mib=cached / 2**20, cache_s=cache_s,
              ridge=float(np.mean([t.ridge_ratio for t in ts if t.status == "ok"])),
              worker_peak_gib=peaks, recorded=len(named), flown_per_s=len(named) / flown_s,
              recorded_per_s=len(named) / recorded_s,
              record_ms=1e3 * busy_rec[0] / len(named))
"""


def demo() -> dict:
    d = run_job_timed(ROOT / "tasks" / "demo.toml")
    d["stages"] = re.findall(
        r"INFO pipeline\.\w+: (built maps store .*|wrote DEM store .*)", d["log"]
    )
    return d


def _demo_again() -> tuple[float, subprocess.CompletedProcess]:
    """``pipeline run tasks/demo.toml`` on the catalog :func:`demo` filled, as run_job_timed
    runs it: its wall time and the finished process."""
    exe = Path(sys.executable).parent / "pipeline"
    t0 = time.perf_counter()
    proc = subprocess.run(
        [str(exe), "run", "tasks/demo.toml"], capture_output=True, text=True, cwd=ROOT
    )
    return time.perf_counter() - t0, proc


def rerun(times: int = 3) -> dict:
    """:func:`_demo_again` ``times`` times: every mission finished, nothing to plan. Wall
    times, and whether each run said it started no cluster."""
    runs = [_demo_again() for _ in range(times)]
    return dict(
        walls=[w for w, _ in runs],
        no_cluster=all(p.returncode == 0 and "no cluster started" in p.stderr for _, p in runs),
    )


def replan(times: int = 3) -> dict:
    """:func:`_demo_again` ``times`` times, the missions' results removed before each: both
    stores reused, every mission planned again (as when a job's missions change on built
    maps). Wall times, and whether each run reused both stores and planned the 8 missions."""
    import shutil

    runs = []
    for _ in range(times):
        shutil.rmtree(ROOT / "catalogs" / "demo" / "missions", ignore_errors=True)
        runs.append(_demo_again())
    return dict(
        walls=[w for w, _ in runs],
        right=all(
            p.returncode == 0
            and p.stderr.count("is up to date: reusing it") == 2
            and "8 missions planned" in p.stdout
            for _, p in runs
        ),
    )


def compiled_after_warm_up(package: Path) -> list:
    """The kernels whose numba cache index (``__pycache__/*.nbi`` beside their sources) was
    written after the warm-up's stamp: signatures the job compiled itself, in its stages (the
    warm-up missed them). Empty when there is no stamp."""
    stamp = package / "__pycache__" / "kernels.json"
    if not stamp.exists():
        return []
    after = stamp.stat().st_mtime
    return sorted(p.name.split("-")[0] for p in package.rglob("*.nbi") if p.stat().st_mtime > after)


def cold_start(rev: str | None = None) -> dict:
    """``./dev demo`` in a fresh clone of HEAD (or of the commit ``rev``): total wall time,
    install, kernel compilation, the job, and the missions' recorded runtimes (from the log's
    timestamps)."""
    with tempfile.TemporaryDirectory(prefix="cold-start-") as tmp:
        clone = Path(tmp) / "clone"
        subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
        if rev is not None:
            subprocess.run(["git", "checkout", "-q", rev], cwd=clone, check=True)
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=clone, capture_output=True, text=True
        ).stdout.strip()
        env = {k: v for k, v in os.environ.items() if not k.startswith(("VIRTUAL_ENV", "NUMBA"))}
        t0 = time.time()
        out = subprocess.run(["./dev", "demo"], cwd=clone, capture_output=True, text=True, env=env)
        wall = time.time() - t0
        late = compiled_after_warm_up(clone / "pipeline")
    log = out.stdout + out.stderr
    compiled = re.search(r"kernels compiled in ([\d.]+) s", log)
    runtimes = [float(v) for v in re.findall(r"\[\d+/\d+\] .*\(([\d.]+) s\); flown", log)]
    job = re.search(r"catalog .*\(([\d.]+) s\)$", log, re.M)
    job_s = float(job.group(1)) if job else None
    said = out.stdout.strip().splitlines()
    return dict(
        exit=out.returncode,
        commit=commit,
        wall_s=wall,
        # everything before the job: the virtual environment, the install, Python's start
        install_s=wall - job_s if job_s is not None else None,
        compile_s=float(compiled.group(1)) if compiled else None,
        announced="compiling kernels, first run only" in log,
        job_s=job_s,
        mission_max_s=max(runtimes) if runtimes else None,
        missions=len(runtimes),
        late=late,
        tail=said[-1] if said else "",
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="20 missions on 2000^2")
    ap.add_argument("--no-cold-start", action="store_true", help="skip the fresh-clone demo")
    args = ap.parse_args()
    quick = args.quick
    print(machine(), flush=True)
    OUT.mkdir(exist_ok=True)
    rep = Report("jobs", 6, "Batch jobs", ".venv/bin/python benchmarks/bench_jobs.py", quick)
    d = demo()
    rep.h("The demo job")
    rep.p(f"""`pipeline run tasks/demo.toml` (the README's `./dev demo`) from an empty catalog,
          under `/usr/bin/time -v`: exit {d["exit"]}, **{d["wall_s"]:.1f} s** wall, client
          process peak RSS **{d["client_peak_gib"]:.2f} GiB** (the 2 workers are separate
          processes). It generates the 2000 x 2000 DEM store, builds the maps store, plans eight
          missions (each a task, one per worker at a time), writes the catalog and starts and
          stops its cluster.
          Its last line: `{d["summary"]}`.""")
    for line in d["stages"]:
        rep.p(f"- {line}")
    again = rerun()
    rep.p(f"""Run again on the catalog it filled (every mission finished, nothing to plan), three
          times: {", ".join(f"{w:.1f}" for w in again["walls"])} s wall; each said it started no
          cluster: {"yes" if again["no_cluster"] else "no"} (it writes the catalog and the
          report, whose hillshade it keeps from the first run).""")
    re_ = replan()
    rep.p(f"""With its missions' results removed first (both stores reused, the 8 missions planned
          again, as when a job's missions change on built maps), three times:
          {", ".join(f"{w:.1f}" for w in re_["walls"])} s wall; each reused both stores and
          planned the 8 missions: {"yes" if re_["right"] else "no"}.""")
    rep.headline(
        "demo",
        60,
        "the demo job (`./dev demo`) from an empty catalog",
        f"{d['wall_s']:.0f} s, client {d['client_peak_gib']:.2f} GiB, exit {d['exit']}",
        target="a few minutes",
    )
    if not args.no_cold_start:
        c = cold_start()
        rep.h("Cold start: the first `./dev demo` in a fresh clone")
        rep.p(f"""`git clone` of commit {c["commit"]} into an empty directory, then `./dev demo`
              there: a new virtual environment (the library and its dependencies only, installed
              by uv), numba's cache empty. Exit {c["exit"]}; **{c["wall_s"]:.0f} s** in all:
              {c["install_s"]:.0f} s before the job (virtual environment, install, start), then
              the job {c["job_s"]} s, of which the kernels' compilation, up front on both
              workers,
              {c["compile_s"]} s (announced in the log: {"yes" if c["announced"] else "no"}).
              The {c["missions"]} missions' recorded runtimes are at most
              {c["mission_max_s"]} s (compilation excluded). Kernels the job compiled after the
              warm-up (the warm-up missed them; each then compiled in its stage, possibly on
              both workers): {", ".join(c["late"]) or "none"}. Its last line:
              `{c["tail"]}`.""")
        rep.headline(
            "cold-start",
            59,
            "first `./dev demo` in a fresh clone (install + compile + job)",
            f"{c['wall_s']:.0f} s (install {c['install_s']:.0f} s, compile "
            f"{c['compile_s']} s), exit {c['exit']}",
            target="< 2 min",
        )
    n, k = (2000, 20) if quick else (4000, 100)
    r = run_isolated(THROUGHPUT.format(store=maps_store(n), k=k, k_rec=min(k, 40)))
    rep.h("Many missions at once: `plan_missions`")
    rep.p(f"""{r["missions"]} random missions (start-goal > 0.3 x side, omega 1.5 / 2 / 3,
          ra_star + MCPC) on the {n} x {n} maps store, LocalCluster of 2 single-threaded
          workers, coarse maps and chunk caches warm, and the store's files
          ({r["cached_mib"]:.0f} MiB) read once first ({r["cache_s"]:.1f} s), so that they are
          in the operating system's file cache as after any earlier use of the map (this part
          runs after the scale part's 40000^2 builds, which push them out; read from disk, the
          workers wait for it): {r["seconds"]:.1f} s =
          **{r["per_s"]:.1f} missions/s** ({r["ok"]} of {r["missions"]} ok; mean ridge ratio
          {100 * r["ridge"]:.0f} %), against {1 / r["sequential_s"]:.1f} missions/s one `plan()`
          at a time. The missions ran in {r["tasks"]} tasks (`missions_per_task` by default:
          groups of up to 8 missions, an eighth of a thread's share, in turn on one worker,
          the last 2 per thread alone). The
          workers ran a mission task {r["occupied"]} % of the time (by their own clocks) and
          used CPU {r["busy"]} % of the time (their CPU time over the wall time); the client
          process, which also runs the scheduler, used {r["client_cpu"]:.0f} % of a core, on
          the same 2 cores. Peak RSS: client {r["peak_rss_gib"]} GiB, workers
          {r["worker_peak_gib"]} GiB. Target (issue 17): 40 missions/s with both workers busy
          more than 90 % of the time.""")
    rep.p(f"""As a job runs them ({r["recorded"]} of these missions): each also flown by the
          default vehicle on its worker, {r["flown_per_s"]:.1f} missions/s; and recorded by the
          client as it ends, as `pipeline run` does (the independent clearance check against
          the DEM's grid points, the track, grid path, waypoint and vehicle files and the STAC
          Item; quick-looks off): **{r["recorded_per_s"]:.1f} missions/s**, the client spending
          {r["record_ms"]:.0f} ms recording each mission.""")
    rep.headline(
        "throughput",
        61,
        f"`plan_missions`, {k} missions on {n}^2, 2 workers",
        f"{r['per_s']:.1f} missions/s, workers in tasks {r['occupied']} %, CPU {r['busy']} %",
        peer=f"one `plan()` at a time: {1 / r['sequential_s']:.1f} /s",
        target=">= 40 /s, workers > 90 % busy",
    )
    rep.save()


if __name__ == "__main__":
    main()
