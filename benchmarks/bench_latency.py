"""Issue 17: one mission at a time against pyastar2d, on the benchmark maps stores.

Per side (2000^2, 4000^2, 10000^2; benchmarks/out/maps{n}.zarr, built once): 40 missions at
least half the side apart, planned one at a time by

- ``plan()`` with ra_star, omega 2, MCPC defaults, on a LocalCluster of 2 single-threaded
  workers (sections as tasks), in this process (``client="synchronous"``, sections in turn)
  and in this process on its cores (``client="threads"``);
- ``plan()`` with lagrangian, omega 2, the same three ways;
- pyastar2d (C++ A*, uniform cost, no 3-D surface, no ridges) on the whole grid, its weight
  grid (1 passable, inf otherwise) built before the clock.

Each tool runs its missions back to back after one warm-up mission (for pyastar2d too: its
first call on a large grid pays for the memory it allocates; interleaving the tools would
charge that again and again). The fixed cost of a mission: the in-process wall time less the
time of its sections' searches (the coarse search, window reads, snapping, the landmark
bound, stitching). On the cluster, the CPU time of this process (the client and the
LocalCluster's scheduler) and of the workers per mission: what the two cores must run.

    .venv/bin/python benchmarks/bench_latency.py [--quick] [--sides 2000 4000 ...]
"""

from __future__ import annotations

import argparse
import json
import os
import time
import uuid

import numpy as np
import psutil
from _common import OUT, machine, maps_store, passable_neighbour
from _report import Report, faster
from bench_mcpc import missions

from pipeline.runtime.threads import cores

RUNS = (
    ("ra_star, cluster", "ra_star", "cluster"),
    ("ra_star, in-process", "ra_star", "synchronous"),
    ("ra_star, threads", "ra_star", "threads"),
    ("lagrangian, cluster", "lagrangian", "cluster"),
    ("lagrangian, in-process", "lagrangian", "synchronous"),
    ("lagrangian, threads", "lagrangian", "threads"),
)


def _cpu_seconds(procs) -> list[float]:
    """User and system CPU seconds of each process so far."""
    return [sum(p.cpu_times()[:2]) for p in procs]


def run_side(client, n: int, k: int, procs=()) -> dict:
    import pyastar2d

    import pipeline
    from pipeline.store.maps_store import open_store

    m = open_store(maps_store(n))
    # read past the chunk cache of this process, which plans the missions: through it, every
    # passable chunk would be decoded already (the client's snaps and checks, the in-process
    # sections' windows)
    ok = pipeline.open_maps(maps_store(n))["passable"].values
    ms = missions(ok, k + 1, seed=1000 + n)
    out = {}
    for name, planner, where in RUNS:
        run_on = client if where == "cluster" else where
        pipeline.plan(m, *ms[0], planner=planner, omega=2.0, client=run_on)  # warm-up
        times, fixed, search, read = [], [], [], []
        cpu0 = _cpu_seconds(procs)
        for s, g in ms[1:]:
            t0 = time.perf_counter()
            t = pipeline.plan(m, s, g, planner=planner, omega=2.0, client=run_on)
            dt = time.perf_counter() - t0
            times.append(dt)
            secs = t.extra["sections"]
            search.append(sum(sec["runtime_s"] or 0.0 for sec in secs))
            read.append(sum(sec["read_s"] or 0.0 for sec in secs))
            fixed.append(dt - search[-1])
        out[name] = float(np.median(times))
        if where == "cluster" and procs:
            # where a mission's CPU goes on the 2 cores: this process (the client, and the
            # LocalCluster's scheduler on its event loop) and the workers; means per mission
            cpu = np.subtract(_cpu_seconds(procs), cpu0) / len(times)
            out[f"{name} cpu"] = {
                "wall": float(np.mean(times)),
                "client": float(cpu[0]),
                "workers": float(cpu[1:].sum()),
                "search": float(np.mean(search)),
            }
        if where == "synchronous" and planner == "ra_star":
            out.update(
                fixed=float(np.median(fixed)),
                search=float(np.median(search)),
                read=float(np.median(read)),
                fixed_again=_fixed_again(m, ms[1:], planner),
            )
    w = np.where(ok, np.float32(1.0), np.float32(np.inf))
    pyastar2d.astar_path(w, ms[0][0], ms[0][1], allow_diagonal=True)  # warm-up
    times = []
    for s, g in ms[1:]:
        t0 = time.perf_counter()
        pyastar2d.astar_path(w, s, g, allow_diagonal=True)
        times.append(time.perf_counter() - t0)
    out["pyastar2d"] = float(np.median(times))
    # its own fixed cost: a search between two neighbouring cells, which expands one or two
    # cells but allocates and fills its cost and parent arrays for the whole grid
    s = ms[0][0]
    near = passable_neighbour(ok, s)
    times = []
    for _ in range(20):
        t0 = time.perf_counter()
        pyastar2d.astar_path(w, s, near, allow_diagonal=True)
        times.append(time.perf_counter() - t0)
    out["pyastar2d_setup"] = float(np.median(times))
    print(n, {key: round(v * 1e3, 1) for key, v in out.items() if isinstance(v, float)}, "ms")
    for key, v in out.items():
        if isinstance(v, dict):
            print(n, key, {part: round(x * 1e3, 1) for part, x in v.items()}, "ms", flush=True)
    out["margins"] = margin_tradeoff(m, ms[1 : 1 + K_MARGIN])
    return out


K_MARGIN = 20  # missions of the margin comparison, per side


def _fixed_again(m, ms, planner: str) -> float:
    """The median fixed cost of the missions ``ms`` planned again in this process, once their
    windows have been read here before (the shards mapped, their chunks' views made, the pages
    in this process's page tables)."""
    import pipeline

    fixed = []
    for s, g in ms:
        t0 = time.perf_counter()
        t = pipeline.plan(m, s, g, planner=planner, omega=2.0, client="synchronous")
        fixed.append(
            time.perf_counter() - t0 - sum(x["runtime_s"] or 0.0 for x in t.extra["sections"])
        )
    return float(np.median(fixed))


def margin_tradeoff(m, ms) -> dict:
    """The default window margin (``section_size // 8``) against a quarter of the section (the
    default before), in this process: per planner and margin the median time, the mean ridge
    ratio and the missions certified. Each mission runs with both margins, in turn first, so
    that the chunk reads the first one pays fall on both alike."""
    import pipeline
    from pipeline.mcpc.algorithm import default_parameters

    d = default_parameters(m.shape, m.cell_size)
    margins = {"default": d["margin"], "quarter": max(d["rho"], d["section_size"] // 4)}
    out = {}
    for planner in ("ra_star", "lagrangian"):
        got: dict = {k: ([], [], []) for k in margins}
        for i, (s, g) in enumerate(ms):
            for label in list(margins)[:: 1 if i % 2 == 0 else -1]:
                t0 = time.perf_counter()
                t = pipeline.plan(
                    m,
                    s,
                    g,
                    planner=planner,
                    omega=2.0,
                    client="synchronous",
                    margin=margins[label],
                )
                got[label][0].append(time.perf_counter() - t0)
                got[label][1].append(t.ridge_ratio)
                got[label][2].append(t.status == "ok")
        for label, (times, ridge, ok) in got.items():
            out[f"{planner}, {label}"] = dict(
                margin=margins[label],
                seconds=float(np.median(times)),
                ridge=float(np.mean(ridge)),
                ok=int(sum(ok)),
                missions=len(ok),
            )
    print({k: round(v["seconds"] * 1e3, 1) for k, v in out.items()}, "ms", flush=True)
    return out


def _stamp(token: str, me: int, inbox) -> float:
    """A section task that does nothing: its end time, also posted to ``inbox``."""
    from pipeline.runtime.inbox import post

    t = time.time()
    post(inbox, token, me, t)
    return t


def result_delay(client, k: int = 40) -> dict:
    """How long after two tasks that do nothing end their results reach the client, and the
    whole round trip, through the futures (``gather``) and through the scheduler's queue
    (``pipeline.runtime.inbox``, as a mission's sections): medians in seconds, the two ways taken in
    turn, 30 ms apart (a mission's pace)."""
    from pipeline.runtime.inbox import Inbox

    got: dict = {"future": [], "queue": []}
    for _ in range(k):
        for how in got:
            inbox = Inbox.take(client) if how == "queue" else None
            token = uuid.uuid4().hex
            t0 = time.time()
            futures = client.map(
                _stamp, [token] * 2, [0, 1], [inbox.name if inbox else None] * 2, pure=False
            )
            ends = inbox.collect(futures, token, 2) if inbox else None
            if inbox:
                inbox.give_back()
            if ends is None:
                ends = client.gather(futures)
            t1 = time.time()
            got[how].append((t1 - max(ends), t1 - t0))
            del futures
            time.sleep(0.03)
    return {
        how: {
            "after_end": float(np.median([a for a, _ in v])),
            "round_trip": float(np.median([b for _, b in v])),
        }
        for how, v in got.items()
    }


def margin_row(n: int, planner: str, margins: dict) -> list:
    d, q = margins[f"{planner}, default"], margins[f"{planner}, quarter"]
    return [
        f"{n}^2",
        planner,
        f"{d['margin']} / {q['margin']}",
        1e3 * d["seconds"],
        1e3 * q["seconds"],
        f"{q['seconds'] / d['seconds']:.2f}x",
        100 * d["ridge"],
        100 * q["ridge"],
        f"{d['ok']} / {q['ok']} of {d['missions']}",
    ]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="2000^2 only, 5 missions")
    ap.add_argument("--sides", type=int, nargs="*")
    args = ap.parse_args()
    sides = args.sides or ([2000] if args.quick else [2000, 4000, 10000])
    k = 5 if args.quick else 40  # pyastar2d's median of 20 at 2000^2: 13.9, 12.2 ms in two runs
    print(machine(), flush=True)
    for n in sides:
        maps_store(n)
    rep = Report(
        "mission-latency",
        5,
        "One mission against pyastar2d",
        ".venv/bin/python benchmarks/bench_latency.py",
        args.quick,
    )
    from distributed import Client

    from pipeline.runtime.cluster import local_cluster

    with (
        local_cluster(dashboard_address=None) as cl,
        Client(cl) as client,
    ):
        procs = [psutil.Process()] + [psutil.Process(p) for p in client.run(os.getpid).values()]
        rows = {n: run_side(client, n, k, procs) for n in sides}
        delay = result_delay(client)
    (OUT / "latency.json").write_text(
        json.dumps({**{str(n): r for n, r in rows.items()}, "result_delay": delay}, indent=1)
    )
    rep.p(f"""{k} missions per side (start-goal >= side / 2, both passable), omega 2, MCPC with
          its defaults, one `plan()` at a time: on a LocalCluster of 2 workers (sections as
          tasks), in this process (`client="synchronous"`, sections in turn) and in this
          process on its {cores()} cores (`client="threads"`, the sections shared by a thread
          per core, the same trajectories). pyastar2d
          (C++ A*, uniform cost, no 3-D surface, no ridges: an easier problem) on the whole
          grid, its weight grid built before the clock; its own fixed cost is its search
          between two neighbouring cells (it allocates and fills a cost and a parent array of
          the whole grid at every call, so its time follows how fast this machine maps in new
          memory, which varies by the hour: its 2000^2 median was 12.2 to 32.8 ms in runs of
          this script). Each tool runs its missions back to
          back after one warm-up mission. Medians in milliseconds. Fixed cost: the in-process
          mission's wall time less its sections' searches (coarse search, snapping, the
          landmark bound, stitching, and what the window reads add: in one process a helper
          thread reads the sections' windows in order from the moment they are cut, while the
          joints are snapped and then ahead of the searches, so the reads' own time, in
          brackets, mostly overlaps them; on the cluster each worker reads its windows
          itself). The missions planned again in this process show the same cost where their
          windows were read before: the first read of a part of the map in a process maps its
          shards, makes its chunks' views and brings its pages into the process's page tables
          (and its bytes come from memory, not the processor's caches). The stores keep the
          three layers the windows read uncompressed, and a
          window is copied from the memory-mapped shards (docs/method.md section 1; with the
          layers compressed, 10000^2 missions took 26 % longer on the cluster, on the same
          missions in one run: 75.9 against 53.9 ms).""")
    names = [name for name, *_ in RUNS]
    rep.table(
        [
            "side",
            *[f"{nm} ms" for nm in names],
            "pyastar2d ms",
            "pyastar2d, neighbouring cells ms",
            "ra_star (cluster) against pyastar2d",
            "ra_star (threads) against pyastar2d",
            "lagrangian (cluster) against pyastar2d",
            "lagrangian (threads) against pyastar2d",
            "fixed cost ms (reads, in the helper thread)",
            "fixed cost, the missions again ms",
            "sections' search ms",
        ],
        [
            [
                f"{n}^2",
                *[1e3 * r[nm] for nm in names],
                1e3 * r["pyastar2d"],
                1e3 * r["pyastar2d_setup"],
                faster(r["pyastar2d"], r["ra_star, cluster"]),
                faster(r["pyastar2d"], r["ra_star, threads"]),
                faster(r["pyastar2d"], r["lagrangian, cluster"]),
                faster(r["pyastar2d"], r["lagrangian, threads"]),
                f"{1e3 * r['fixed']:.1f} ({1e3 * r['read']:.1f})",
                1e3 * r["fixed_again"],
                1e3 * r["search"],
            ]
            for n, r in rows.items()
        ],
    )
    rep.p(f"""Where a mission's CPU goes, on the cluster (the same missions; means per mission,
          in milliseconds): this process (the client's work: the coarse search, snapping,
          stitching, the landmark bound; and the LocalCluster's scheduler and the client's
          communication, on its event loop) and the two worker processes (the sections'
          searches, their window reads, and each worker's own messaging). Two cores run it all:
          half the CPU is the least wall time a mission can take, however its work is
          shared. The kernel counts a process's CPU time in steps of 10 ms: over {k} missions,
          each process's figure is within {10 / k:.2f} ms of the mean it measures (the
          workers' two within twice that).""")
    rep.table(
        [
            "side",
            "planner",
            "wall ms",
            "CPU, this process ms",
            "CPU, workers ms",
            "of which the sections' searches (wall) ms",
            "CPU in all / 2 cores ms",
        ],
        [
            [
                f"{n}^2",
                planner,
                1e3 * c["wall"],
                1e3 * c["client"],
                1e3 * c["workers"],
                1e3 * c["search"],
                1e3 * (c["client"] + c["workers"]) / 2,
            ]
            for n, r in rows.items()
            for planner in ("ra_star", "lagrangian")
            if (c := r.get(f"{planner}, cluster cpu"))
        ],
    )
    rep.p(f"""The window margin of the sections (docs/method.md section 6): the default,
          `max(rho, section_size // 8)`, against a quarter of the section side (the default
          until results revision 3), in this process, on the first {K_MARGIN} missions of each
          side, each mission planned with both margins (in turn first). A window's area per
          section is `(1 + 2 margin / section_size)^2` section squares: 1.56 against 2.25.""")
    rep.table(
        [
            "side",
            "planner",
            "margin cells (default / quarter)",
            "ms, default",
            "ms, quarter",
            "time, quarter / default",
            "ridge %, default",
            "ridge %, quarter",
            "certified, default / quarter",
        ],
        [
            margin_row(n, planner, r["margins"])
            for n, r in rows.items()
            for planner in ("ra_star", "lagrangian")
        ],
    )
    fut, que = delay["future"], delay["queue"]
    rep.p(f"""How a section task's result reaches the client (the same cluster, two tasks that do
          nothing, 40 times each way, medians): through its future (the worker tells the
          scheduler, the scheduler tells the client, the client fetches the data) it arrived
          {1e3 * fut["after_end"]:.1f} ms after the task ended, a round trip of
          {1e3 * fut["round_trip"]:.1f} ms; through the queue on the scheduler that `plan()`'s
          section tasks post to (`pipeline.runtime.inbox`) {1e3 * que["after_end"]:.1f} ms after, a
          round trip of {1e3 * que["round_trip"]:.1f} ms.""")
    big = max(rows)

    def ways(planner: str, how) -> str:
        return "; ".join(
            f"{label} " + ", ".join(how(r, f"{planner}, {where}") for r in rows.values())
            for label, where in (("threads", "threads"), ("cluster", "cluster"))
        )

    def ms(r, key) -> str:
        return f"{1e3 * r[key]:.0f} ms"

    def against(r, key) -> str:
        return faster(r["pyastar2d"], r[key])

    rep.headline(
        "latency",
        54,
        f"one mission against pyastar2d, {', '.join(f'{n}^2' for n in rows)} (ra_star + MCPC;"
        ' in this process on its cores, `client="threads"`, and on the local cluster)',
        ways("ra_star", ms) + f"; fixed cost {1e3 * rows[big]['fixed']:.0f} ms at {big}^2"
        f" ({1e3 * rows[big]['fixed_again']:.0f} ms planned again)",
        peer="pyastar2d: "
        + ways("ra_star", against)
        + f" (pyastar2d {1e3 * rows[min(rows)]['pyastar2d']:.0f} ms at {min(rows)}^2, of which"
        f" {1e3 * rows[min(rows)]['pyastar2d_setup']:.0f} ms its arrays, which vary by the hour)",
        target="faster at 2000^2 and 4000^2, 3x at 10000^2; fixed cost < 10 ms",
    )
    rep.headline(
        "latency-lagrangian",
        54.5,  # beside the ra_star row
        f"one mission against pyastar2d, {', '.join(f'{n}^2' for n in rows)} (lagrangian + MCPC;"
        " the same two ways)",
        ways("lagrangian", ms),
        peer="pyastar2d: " + ways("lagrangian", against),
        target="faster at 2000^2 and 4000^2, 3x at 10000^2 (issue 17)",
    )
    rep.save()


if __name__ == "__main__":
    main()
