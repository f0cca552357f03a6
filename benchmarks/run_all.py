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
parts replace the old ones; the rest are reused).

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
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            cwd=ROOT,
        ).stdout.strip()
        return out + (" (with uncommitted changes)" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


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


def headline_rows(quick: bool) -> list[dict]:
    rows = []
    for f in sorted(parts_dir(quick).glob("[0-9]*.json")):
        rows += json.loads(f.read_text()).values()
    return sorted(rows, key=lambda r: r["order"])


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


def assemble(quick: bool, times: dict, failed: list[str], total_s: float, commits: dict) -> str:
    m = machine()
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
        f"(`benchmarks/run_all.py`) on {time.strftime('%Y-%m-%d')}, {mode}; measured at "
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
        "otherwise; peak memory is the process's peak resident set (`ru_maxrss`) and that of "
        "each dask worker where a LocalCluster of 2 single-threaded workers is used (the one "
        "the package starts, `pipeline.cluster.local_cluster`, its workers' allocator set by "
        "`pipeline.cluster.WORKER_ENV`). Peers run "
        "in the same script, on the same data, right before or after ours. This VM's timings "
        "vary by 10-40 % from run to run. The paper's figures come from a 16-core desktop "
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
        lines.append(p.read_text())
    return "\n".join(lines)


def anchor(by_name: dict, name: str) -> str:
    p = by_name.get(name)
    if p is None:
        return name
    title = p.read_text().splitlines()[0].lstrip("# ").strip().lower()
    return re.sub(r"[^a-z0-9 -]", "", title).replace(" ", "-")


README_START = "<!-- results:start (written by benchmarks/run_all.py) -->"
README_END = "<!-- results:end -->"


def update_readme() -> None:
    readme = ROOT / "README.md"
    text = readme.read_text()
    if README_START not in text or README_END not in text:
        print("README.md has no results markers; not updated")
        return
    block = "\n".join(
        [
            README_START,
            "",
            f"Measured on a {machine()['cores']}-core machine by `./dev bench` on "
            f"{time.strftime('%Y-%m-%d')}; every figure, how it was measured, the machine and the "
            "analog of each of the paper's tables and figures are in "
            "[benchmarks/RESULTS.md](benchmarks/RESULTS.md).",
            "",
            headline_table(headline_rows(False)),
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
        last = json.loads(run_file.read_text())
        return write(args.quick, last["times"], last["failed"], last["total"], _commits(last))
    names = args.only or SCRIPTS
    if not args.only:
        shutil.rmtree(parts_dir(args.quick), ignore_errors=True)
    times, failed = {}, []
    commit = git_commit()  # the code that measures (the scripts' figures make the tree dirty)
    t0 = time.perf_counter()
    for name in names:
        print(f"\n=== bench_{name}.py ===", flush=True)
        rc, dt = run_script(name, args.quick, args.script_args)
        times[name] = dt
        if rc != 0:
            failed.append(f"bench_{name}.py")
    total = time.perf_counter() - t0
    parts_dir(args.quick).mkdir(parents=True, exist_ok=True)
    commits = {name: commit for name in names}  # --assemble later keeps them
    if args.only and run_file.exists():  # the other parts are from the last run: keep its times
        last = json.loads(run_file.read_text())
        times = {**last["times"], **times}
        commits = {**_commits(last), **commits}
        failed = [f for f in last["failed"] if f[len("bench_") : -3] not in names] + failed
        total = sum(times.values())
    run_file.write_text(json.dumps(dict(times=times, failed=failed, total=total, commits=commits)))
    return write(args.quick, times, failed, total, commits)


def _commits(run: dict) -> dict:
    """Each part's commit in a run file (older run files name one commit for all)."""
    return run.get("commits") or {name: run["commit"] for name in run["times"]}


def write(quick: bool, times: dict, failed: list, total: float, commits: dict) -> int:
    target = OUT / "RESULTS-quick.md" if quick else HERE / "RESULTS.md"
    target.write_text(assemble(quick, times, failed, total, commits))
    if not quick:
        update_readme()
    print(f"\nwrote {target} ({total / 60:.1f} min)" + (f"; FAILED: {failed}" if failed else ""))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
