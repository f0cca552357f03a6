"""The benchmark report keeps its sources: a fresh clone (no ``benchmarks/out/``) that reruns one
benchmark with ``./dev bench --only NAME`` gets the other parts back from the committed
RESULTS.md instead of a report with one part."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture
def report_modules(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    import _report
    import run_all

    monkeypatch.setattr(_report, "OUT", tmp_path / "out")
    yield _report, run_all
    for name in ("run_all", "_report", "_common"):
        sys.modules.pop(name, None)


def _parts(_report):
    a = _report.Report("alpha", 1, "Alpha part", "python bench_alpha.py", quick=False)
    a.p("A paragraph\nthat wraps.")
    a.table(["n", "seconds"], [[2000, 0.5], [4000, 1.25]])
    a.headline("one", 12, "alpha at 2000^2", "0.5 s", peer="peer 1.0 s", target="< 1 s")
    a.headline("two", 11, "alpha at 4000^2", "1.25 s")
    b = _report.Report("beta-gamma", 3, "Beta part", "python bench_beta.py", quick=False)
    b.h("A sub-heading")
    b.p("Text with a `<!-- comment -->` in it and a trailing line.\n")
    b.headline("three", 30, "beta", "7 ms", paper="3 s")
    return [a.save(), b.save()]


def test_the_report_restores_its_parts_and_run_exactly(report_modules, tmp_path):
    _report, run_all = report_modules
    saved = _parts(_report)
    run = dict(
        times={"alpha": 60.0, "beta": 30.0},
        failed=[],
        total=90.0,
        commits={"alpha": "abc1234", "beta": "def5678"},
        dates={"alpha": "2026-11-25", "beta": "2026-11-26"},
        machine=dict(cores=2, cpu="x", memory_gib=24, os="linux", python="3.11", libs={}),
    )
    text = run_all.assemble(False, run)
    # the rendered report: both parts, the rows in their order, each part's commit and day
    assert "## Alpha part" in text and "## Beta part" in text
    assert text.index("| alpha at 4000^2") < text.index("| alpha at 2000^2") < text.index("| beta")
    assert "on 2026-11-25 (beta on 2026-11-26)" in text
    assert "commit abc1234 (alpha); commit def5678 (beta)" in text

    results = tmp_path / "RESULTS.md"
    results.write_text(text)
    fresh = tmp_path / "fresh"
    assert run_all.restore_parts(results, fresh) == ["alpha", "beta-gamma"]
    for md in saved:
        assert (fresh / md.name).read_text() == md.read_text()
        js = md.with_suffix(".json")
        assert json.loads((fresh / js.name).read_text()) == json.loads(js.read_text())
    assert json.loads((fresh / "_run.json").read_text()) == run
    # the restored parts assemble into the same report
    _report.OUT = fresh.parent
    (fresh.parent / "report").mkdir()
    for f in fresh.iterdir():
        (fresh.parent / "report" / f.name).write_bytes(f.read_bytes())
    assert run_all.assemble(False, run) == text


def test_restoring_keeps_the_parts_already_there(report_modules, tmp_path):
    _report, run_all = report_modules
    saved = _parts(_report)
    run = run_all._run(dict(times={"alpha": 1.0, "beta": 2.0}, failed=[], total=3.0, commit="c0"))
    results = tmp_path / "RESULTS.md"
    results.write_text(run_all.assemble(False, run))
    saved[0].write_text("## Alpha part\n\nmeasured again\n")  # a part this run rewrote
    saved[1].unlink()
    saved[1].with_suffix(".json").unlink()
    assert run_all.restore_parts(results, saved[0].parent) == ["beta-gamma"]
    assert saved[0].read_text() == "## Alpha part\n\nmeasured again\n"
    assert "## Beta part" in saved[1].read_text()
    # a report written before the markers existed restores nothing
    old = tmp_path / "OLD.md"
    lines = results.read_text().split("\n")
    old.write_text("\n".join(ln for ln in lines if not ln.startswith("<!-- run_all")))
    assert run_all.restore_parts(old, tmp_path / "none") == []
