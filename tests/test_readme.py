"""The README's own-DEM job file and its Python example, run as written (copied out of the
README, not retyped here) on a small GeoTIFF the test makes where the README's longitudes and
latitudes lie, so the front door cannot rot: each exits 0, plans certified missions and writes
the vehicle files the README names; the job and the script agree on the shared mission."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import geopandas
import numpy as np
import pyarrow.parquet as pq
import pytest
import rioxarray  # noqa: F401 - registers .rio

import pipeline

README = Path(__file__).resolve().parents[1] / "README.md"
EXE = Path(sys.executable).parent / "pipeline"


def readme_block(name: str, page: Path = README) -> str:
    """The fenced block after the README's ``<!-- tested: ... as NAME -->`` comment (or that
    of another ``page``)."""
    text = page.read_text()
    m = re.search(
        r"<!-- tested: [^>]*as " + re.escape(name) + r" -->\n```\w+\n(.*?)\n```", text, re.S
    )
    assert m, f"{page.name} has no block tested as {name}"
    return m.group(1) + "\n"


def make_survey(folder: Path) -> None:
    """``survey.tif`` in ``folder``: a 20 x 20 km GeoTIFF (50 m cells, a local projection
    centred on 44.83 W 26.14 N, as the README's coordinates assume), with a no-data value."""
    dem = pipeline.synthetic_dem((400, 400), cell_size=50.0, seed=3, islands=0).compute()
    dem = dem.rio.write_crs(dem.attrs.pop("crs_wkt")).rio.write_nodata(-9999.0)
    dem.attrs.pop("cell_size")
    dem.rio.to_raster(folder / "survey.tif")


def test_the_readme_job_file_and_python_example_run_as_written(tmp_path):
    """The job file with the console script; the Python example in a plain script (no main
    guard, no cluster), which prints the trajectory, the flight and the QGroundControl file's
    path, and plans the job's first mission to the same length."""
    make_survey(tmp_path)
    (tmp_path / "survey.toml").write_text(readme_block("survey.toml"))
    proc = subprocess.run(
        [str(EXE), "run", "survey.toml"], cwd=tmp_path, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stderr
    missions = tmp_path / "survey-catalog" / "missions"
    table = geopandas.read_parquet(missions / "missions.parquet").set_index("name")
    assert sorted(table.index) == ["north-east", "south-west"]
    assert set(table["status"]) == {"ok"}
    for name in table.index:
        files = {p.name for p in (missions / name).iterdir()}
        assert {"mission.waypoints", "mission.kml", "mission.imc", "waypoints.csv"} <= files
    # every GeoParquet file of the catalog declares one version (pyarrow reads the metadata)
    versions = {
        json.loads(pq.read_schema(f).metadata[b"geo"])["version"]
        for f in [missions / "missions.parquet", *missions.glob("*/*.parquet")]
    }
    assert versions == {"1.1.0"}

    (tmp_path / "example.py").write_text(readme_block("example.py"))
    proc = subprocess.run(
        [sys.executable, "example.py"], cwd=tmp_path, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    out = proc.stdout.splitlines()
    assert out[0].startswith("Trajectory(ok") and out[1].startswith("Flight(ok")
    assert out[2] == "survey-mission/mission.waypoints"
    assert (tmp_path / out[2]).read_text().startswith("QGC WPL 110")
    figures = json.loads((tmp_path / "survey-mission" / "mission.json").read_text())
    assert figures["status"] == "ok" and np.isfinite(figures["lower_bound_m"])
    assert figures["length_m"] == pytest.approx(table.loc["north-east", "length_m"], rel=1e-9)


def test_the_documentation_shows_the_same_examples():
    """The site's getting-started page shows the job file and the script the test above runs,
    character for character."""
    page = README.parent / "docs" / "getting-started.md"
    for name in ("survey.toml", "example.py"):
        assert readme_block(name, page) == readme_block(name), name
