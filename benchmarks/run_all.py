"""The whole evaluation in one command: ``./dev bench`` (or ``make bench``).

Runs every ``bench_*.py`` script in turn, each of which measures its cases in fresh processes
and writes its part of the report, then assembles ``benchmarks/RESULTS.md``: the machine, the
date, a headline table (ours against the paper and the peers measured in the same run), an
index of the paper's Tables 1-6 and Figures 9-14 with where each analog is, and every part.
The figures (PNG) are regenerated into ``docs/``, and the README's "Results" block is rewritten
from the same headline table.

``--quick`` runs smaller cases (a check that everything runs, under 10 minutes on 2 cores) and
writes ``benchmarks/out/RESULTS-quick.md`` and ``benchmarks/out/quick-figures/`` instead, so
the published results are left alone. ``--only dem safety ...`` runs some scripts only (their
parts replace the old ones; the rest are reused). The report carries its parts' sources in HTML
comments (each part's headline rows, the run's times and commits), so that in a fresh clone,
which has no ``benchmarks/out/``, ``--only`` first restores the other parts from the committed
RESULTS.md instead of dropping them.

    ./dev bench [--quick] [--only NAME ...] [--script-args ARG ...]
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

from _common import machine_info as machine
from _report import parts_dir

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
OUT = HERE / "out"
LOGS = OUT / "logs"
# the order the scripts run in and their parts appear in
SCRIPTS = [
    "dem",
    "safety",
    "ridges",
    "scale",
    "planners",
    "mcpc",
    "latency",
    "jobs",
    "realdata",
    "certify",
    "flight",
    "constraints",
    "user_seabed",
    "flight_aware",
    "flight_cost",
]

PAPER_INDEX = [
    (
        "Table 1",
        "mean raise of the three safety maps, R = 200 / 300 m",
        "safety",
        "our 200 x 200 map is a synthetic ridge scene, theirs a survey; same 100 m cells",
    ),
    ("Figure 9", "a DEM and its spherical safety map", "safety", "same scale and R"),
    (
        "Table 2",
        "RA* without a safety map, omega 2.5 / 2.0 / 1.8 / 1.0",
        "planners",
        "a 200 x 200 window of our synthetic DEM at 30 m; the Lagrangian planner beside RA*",
    ),
    ("Table 3", "the same with the spherical safety map", "planners", "as Table 2"),
    (
        "Figures 10, 11",
        "RA*'s paths for the four omega values",
        "planners",
        "top views; both planners",
    ),
    (
        "Table 4",
        "RA*/A* with and without MCPC, 5000^2, omega 3",
        "mcpc",
        "our synthetic 5000^2 map; 2 cores, not 16",
    ),
    ("Figure 12", "the four Table 4 paths", "mcpc", "top view over the hillshade"),
    (
        "Table 5",
        "time per mission against map size, 500^2 to 10000^2, omega 2",
        "mcpc",
        "6 sizes, not 20; the maps are prebuilt (the paper's times exclude them too)",
    ),
    ("Figure 13", "time against map size", "mcpc", "with the p10-p90 spread"),
    (
        "Table 6",
        "RA* against MRA*, RRT*, WA* on 10000^2",
        "mcpc",
        "MRA* and RRT* are not available to run; WA* (ours) and pyastar2d are",
    ),
    (
        "Figure 14",
        "case study: 2000^2, RA*+MCPC omega 3, corner to corner",
        "mcpc",
        'their "average safety distance" is not defined: we give the height above the seabed '
        "and the 3-D distance to the ground",
    ),
]


def git_commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            cwd=ROOT,
            check=True,
        ).stdout.strip()
        changed = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            cwd=ROOT,
        ).stdout.splitlines()
        # what the benchmarks write themselves (a run after another --only run) is not code
        dirty = [line for line in changed if not _is_output(line[3:].strip())]
        return out + (" (with uncommitted changes)" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _is_output(path: str) -> bool:
    """Whether a path of the repository is what ``./dev bench`` writes: the report, the
    README's results block, the figures."""
    return path in ("benchmarks/RESULTS.md", "README.md") or (
        path.startswith("docs/") and path.endswith(".png")
    )


def run_script(name: str, quick: bool, extra: list[str] = ()) -> tuple[int, float]:
    """Run bench_<name>.py (with ``extra`` arguments), teeing its output into
    out/logs/<name>.log; (exit code, seconds)."""
    LOGS.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-u", str(HERE / f"bench_{name}.py")] + (["--quick"] if quick else [])
    cmd += list(extra)
    t0 = time.perf_counter()
    with open(LOGS / f"{name}.log", "w") as log:
        proc = subprocess.Popen(
            cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
        for line in proc.stdout:
            sys.stdout.write(line)
            log.write(line)
        rc = proc.wait()
    return rc, time.perf_counter() - t0


def headline_rows(quick: bool, keys: tuple | None = None) -> list[dict]:
    """The parts' headline rows in their order; with ``keys``, those rows only."""
    rows = []
    for f in sorted(parts_dir(quick).glob("[0-9]*.json")):
        rows += [r for k, r in json.loads(f.read_text()).items() if keys is None or k in keys]
    return sorted(rows, key=lambda r: r["order"])


# the headline rows the README shows (RESULTS.md shows them all): one mission on a large map,
# against a peer, the largest maps build, the certificate, flyable missions, a batch, the
# constraints
FRONT = ("t5", "latency", "scale", "certify", "flight", "throughput", "constraints")


def headline_table(rows: list[dict]) -> str:
    out = [
        "| what | ours (2 cores, Python) | the paper (16 cores, MATLAB) | peer, same run | "
        "target |",
        "|---|---|---|---|---|",
    ]
    out += [
        f"| {r['what']} | {r['ours']} | {r['paper'] or '-'} | {r['peer'] or '-'} | "
        f"{r['target'] or '-'} |"
        for r in rows
    ]
    return "\n".join(out)


def _measured_at(commits: dict) -> str:
    """``commit X`` when every part was measured at one commit, else which parts at which."""
    by: dict = {}
    for name, commit in commits.items():
        by.setdefault(commit, []).append(name)
    if len(by) == 1:
        return f"commit {next(iter(by))}"
    return "; ".join(f"commit {c} ({', '.join(names)})" for c, names in by.items())


def _measured_on(dates: dict) -> str:
    """``2026-11-25`` when every part was measured that day, else the most common day and the
    other parts' days: ``2026-11-25 (latency, planners on 2026-11-26)``."""
    by: dict = {}
    for name, day in dates.items():
        by.setdefault(day, []).append(name)
    if not by:
        return time.strftime("%Y-%m-%d")
    main_day = max(by, key=lambda d: len(by[d]))
    others = [f"{', '.join(names)} on {d}" for d, names in sorted(by.items()) if d != main_day]
    return main_day + (f" ({'; '.join(others)})" if others else "")


def assemble(quick: bool, run: dict) -> str:
    """The report from the parts in ``parts_dir(quick)`` and the run record ``run`` (each part's
    time, commit and day, the failed scripts, the machine the last measurements ran on)."""
    times, failed, total_s = run["times"], run["failed"], run["total"]
    commits, dates, m = run["commits"], run["dates"], run["machine"]
    libs = ", ".join(f"{k} {v}" for k, v in m["libs"].items())
    mode = (
        "quick mode: smaller cases, a check that everything runs (the sizes are in every table)"
        if quick
        else "full mode"
    )
    parts = sorted(parts_dir(quick).glob("*.md"))
    by_name = {p.stem.split("-", 1)[1]: p for p in parts}
    lines = [
        "# Benchmark results" + (" (quick check)" if quick else ""),
        "",
        "Regenerated by `./dev bench" + (" --quick" if quick else "") + "` "
        f"(`benchmarks/run_all.py`) on {_measured_on(dates)}, {mode}; measured at "
        + _measured_at(commits)
        + f"; the parts took {total_s / 60:.1f} min ("
        + ", ".join(f"{k} {v / 60:.1f}" for k, v in times.items())
        + " min). Do not edit by "
        "hand: the scripts write every number and sentence below.",
        "",
        f"**Machine**: {m['cores']} cores ({m['cpu']}), {m['memory_gib']} GiB, {m['os']}, "
        f"Python {m['python']}; {libs}.",
        "",
        "**How it is measured**: every case runs in a fresh Python process (numba's compiled "
        "code cached on disk beforehand, never timed); times are wall-clock unless a table says "
        "otherwise; peak memory is the process's own peak resident set (`VmHWM`: not "
        "`ru_maxrss`, which a process inherits from the one that starts it; before 2026-11-27 "
        "the figures were `ru_maxrss`, which could show a parent's peak) and that of "
        "each dask worker where a LocalCluster of 2 single-threaded workers is used (the one "
        "the package starts, `pipeline.runtime.cluster.local_cluster`, its workers' allocator "
        "set by `pipeline.runtime.cluster.WORKER_ENV`). Peers run "
        "in the same script, on the same data, right before or after ours. This VM's timings "
        "vary by 10-40 % from run to run within an hour and by up to 3x between hours "
        "(pyastar2d's missions in the latency benchmark took 2.4-2.5x as long in its run "
        "before 11:12 UTC on 2026-11-27 as in its run at 13:40, the same code), so compare "
        "ratios within one part, not figures of parts run at different times. The paper's "
        "figures come "
        "from a 16-core desktop "
        "running MATLAB, on its own survey data, with the maps built beforehand; ours include "
        "building the maps, reported separately.",
        "",
    ]
    if failed:
        lines += [
            f"**FAILED**: {', '.join(failed)} (exit code non-zero; their logs are in "
            "benchmarks/out/logs/). Their parts below may be from an earlier run.",
            "",
        ]
    lines += [
        RUN_MARK.format(json.dumps(run)),
        "",
        "## Headline",
        "",
        headline_table(headline_rows(quick)),
        "",
        "## The paper's tables and figures, and where their analogs are",
        "",
        "| paper | what | analog in | what differs |",
        "|---|---|---|---|",
    ]
    for item, what, where, differs in PAPER_INDEX:
        lines.append(f"| {item} | {what} | [{where}](#{anchor(by_name, where)}) | {differs} |")
    lines.append("")
    for p in parts:
        heads = p.with_suffix(".json")
        heads = json.loads(heads.read_text()) if heads.exists() else {}
        lines.append(PART_MARK.format(p.stem, json.dumps(heads)))
        lines.append(p.read_text())
    return "\n".join(lines)


# the report's sources, kept in it as HTML comments (hidden when rendered; one line each)
RUN_MARK = "<!-- run_all run: {} -->"
PART_MARK = "<!-- run_all part {}: {} -->"
_MARK = re.compile(r"^<!-- run_all (run|part (\d\d-[a-z_-]+)): (.*) -->$")


def restore_parts(results: Path, parts: Path) -> list[str]:
    """Write into ``parts`` the parts of the report ``results`` that ``parts`` lacks (their text,
    their headline rows) and the run file if it is missing; the names restored. A report
    written before the markers existed restores nothing."""
    if not results.exists():
        return []
    parts.mkdir(parents=True, exist_ok=True)
    restored, run, cur, body = [], None, None, []

    def flush():
        if cur is not None and not (parts / f"{cur[0]}.md").exists():
            (parts / f"{cur[0]}.md").write_text("\n".join(body))
            (parts / f"{cur[0]}.json").write_text(json.dumps(cur[1], indent=1))
            restored.append(cur[0].split("-", 1)[1])

    for line in results.read_text().split("\n"):
        m = _MARK.match(line)
        if m and m.group(1) == "run":
            run = json.loads(m.group(3))
        elif m:
            flush()
            cur, body = (m.group(2), json.loads(m.group(3))), []
        elif cur is not None:
            body.append(line)
    flush()
    run_file = parts / "_run.json"
    if run is not None and not run_file.exists():
        run_file.write_text(json.dumps(run))
    return restored


def anchor(by_name: dict, name: str) -> str:
    p = by_name.get(name)
    if p is None:
        return name
    title = p.read_text().splitlines()[0].lstrip("# ").strip().lower()
    return re.sub(r"[^a-z0-9 -]", "", title).replace(" ", "-")


README_START = "<!-- results:start (written by benchmarks/run_all.py) -->"
README_END = "<!-- results:end -->"


def update_readme(run: dict) -> None:
    readme = ROOT / "README.md"
    text = readme.read_text()
    if README_START not in text or README_END not in text:
        print("README.md has no results markers; not updated")
        return
    block = "\n".join(
        [
            README_START,
            "",
            f"Measured on a {run['machine']['cores']}-core machine by `./dev bench` on "
            f"{_measured_on(run['dates'])}; every figure, how it was measured, the machine and the "
            "analog of each of the paper's tables and figures are in "
            "[benchmarks/RESULTS.md](benchmarks/RESULTS.md), with the other headline rows.",
            "",
            headline_table(headline_rows(False, FRONT)),
            "",
            "![planning time against map size](docs/mcpc-scaling.png)",
            "",
            "![a planned trajectory on real bathymetry](docs/topobathy-missions.png)",
            "",
            README_END,
        ]
    )
    head, rest = text.split(README_START, 1)
    tail = rest.split(README_END, 1)[1]
    readme.write_text(head + block + tail)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller cases, under 10 minutes")
    ap.add_argument("--only", nargs="+", choices=SCRIPTS, help="run these scripts only")
    ap.add_argument(
        "--script-args",
        nargs="+",
        default=[],
        metavar="ARG",
        help="arguments passed on to the scripts run (with --only), e.g. --reuse-zarr",
    )
    ap.add_argument(
        "--assemble",
        action="store_true",
        help="run nothing: rebuild the report from the parts of the last run",
    )
    args = ap.parse_args()
    run_file = parts_dir(args.quick) / "_run.json"
    if args.assemble:
        return write(args.quick, _run(json.loads(run_file.read_text())))
    names = args.only or SCRIPTS
    if not args.only:
        shutil.rmtree(parts_dir(args.quick), ignore_errors=True)
    elif not args.quick:  # a fresh clone has no parts: take the others from the committed report
        kept = restore_parts(HERE / "RESULTS.md", parts_dir(False))
        if kept:
            print(f"restored from RESULTS.md the parts {', '.join(kept)}")
    times, failed = {}, []
    commit = git_commit()  # the code that measures (the scripts' figures make the tree dirty)
    today = time.strftime("%Y-%m-%d")
    t0 = time.perf_counter()
    for name in names:
        print(f"\n=== bench_{name}.py ===", flush=True)
        rc, dt = run_script(name, args.quick, args.script_args)
        times[name] = dt
        if rc != 0:
            failed.append(f"bench_{name}.py")
    total = time.perf_counter() - t0
    parts_dir(args.quick).mkdir(parents=True, exist_ok=True)
    # --assemble later keeps each part's commit and day
    run = dict(
        times=times,
        failed=failed,
        total=total,
        commits={name: commit for name in names},
        dates={name: today for name in names},
        machine=machine(),
    )
    if args.only and run_file.exists():  # the other parts are from the last run: keep its times
        last = _run(json.loads(run_file.read_text()))
        run["times"] = {**last["times"], **times}
        run["commits"] = {**last["commits"], **run["commits"]}
        run["dates"] = {**last["dates"], **run["dates"]}
        run["failed"] = [f for f in last["failed"] if f[len("bench_") : -3] not in names] + failed
        run["total"] = sum(run["times"].values())
    run_file.write_text(json.dumps(run))
    return write(args.quick, run)


def _run(run: dict) -> dict:
    """A run file with each part's commit and day and the machine (older run files name one
    commit for all, and no days or machine: today and this machine)."""
    commits = run.get("commits") or {name: run["commit"] for name in run["times"]}
    dates = run.get("dates") or {name: time.strftime("%Y-%m-%d") for name in run["times"]}
    return dict(run, commits=commits, dates=dates, machine=run.get("machine") or machine())


def write(quick: bool, run: dict) -> int:
    target = OUT / "RESULTS-quick.md" if quick else HERE / "RESULTS.md"
    target.write_text(assemble(quick, run))
    if not quick:
        update_readme(run)
    total, failed = run["total"], run["failed"]
    print(f"\nwrote {target} ({total / 60:.1f} min)" + (f"; FAILED: {failed}" if failed else ""))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
