"""The job-file reference and JSON Schema (pipeline.jobs.schema): the committed files are what
the generator writes from the parameter schema, and the JSON Schema (jsonschema's validator)
agrees with the job loader, the reference, on the project's job files and on bad ones."""

from __future__ import annotations

import copy
import json
import tomllib
from pathlib import Path

import pytest
from jsonschema import Draft202012Validator

import pipeline
from pipeline.jobs.schema import json_schema, markdown

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def test_the_committed_reference_and_schema_are_the_generated_ones():
    """docs/job-file.md and docs/job-file.schema.json cannot drift from pipeline/params.py:
    regenerate them with `python -m pipeline.jobs.schema docs/`."""
    assert (DOCS / "job-file.md").read_text() == markdown()
    assert json.loads((DOCS / "job-file.schema.json").read_text()) == json_schema()
    Draft202012Validator.check_schema(json_schema())
    for name in (
        "clearance",
        "omega",
        "keep_out",
        "max_depth_m",
        "via_lonlat",
        "performance_report",
    ):
        assert f"`{name}`" in markdown(), name


@pytest.mark.parametrize("job", sorted((ROOT / "tasks").glob("*.toml")), ids=lambda p: p.name)
def test_the_projects_job_files_are_valid(job):
    doc = tomllib.loads(job.read_text())
    errors = list(Draft202012Validator(json_schema()).iter_errors(doc))
    assert not errors, [e.message for e in errors]


GOOD = {
    "name": "s",
    "dem": {"synthetic": {"shape": [64, 64]}},
    "maps": {"clearance": 60.0},
    "planning": {"omega": 1.5, "keep_out_margin_m": 10.0},
    "vehicle": {"max_depth_m": 3000.0},
    "missions": [
        {"start": [1, 1], "goal": [60, 60], "via": [[30, 30]]},
        {"start_xy": [1.0, 2.0], "goal_lonlat": [-44.8, 26.1], "omega": 2.0},
    ],
    "output": {"catalog": "out", "quicklooks": False},
}


def _set(doc, path, value):
    d = doc
    for k in path[:-1]:
        d = d[k]
    if value is _DROP:
        del d[path[-1]]
    else:
        d[path[-1]] = value


_DROP = object()
BAD = [
    (("maps", "clearence"), 300.0),  # an unknown key in each table
    (("planning", "omgea"), 2.0),
    (("vehicle", "speed"), 1.5),
    (("output", "format"), "x"),
    (("colour",), "red"),
    (("maps", "clearance"), "300"),  # a wrong type
    (("planning", "mcpc"), "yes"),
    (("maps", "clearance"), -1.0),  # out of range
    (("planning", "omega"), 0.5),
    (("maps", "landmarks"), 99),
    (("maps", "method"), "cubic"),
    (("missions", 0, "start_xy"), [1.0, 2.0]),  # a start in two forms
    (("missions", 0, "via_xy"), [[1.0, 2.0]]),  # via points in two forms
    (("missions", 1, "start_xy"), _DROP),  # no start
    (("dem", "path"), "x.tif"),  # a path and a generator
    (("dem",), _DROP),
]


@pytest.mark.parametrize("path, value", BAD, ids=[".".join(map(str, p)) for p, _ in BAD])
def test_the_schema_refuses_what_the_loader_refuses(tmp_path, path, value):
    """Each bad variant of a good job file: the loader refuses it with one JobFileError, and
    the JSON Schema refuses it too; the good file passes both."""
    validator = Draft202012Validator(json_schema())
    import tomli_w

    good = tmp_path / "good.toml"
    good.write_text(tomli_w.dumps(GOOD))
    pipeline.jobs.job_file.load_job(good)
    assert not list(validator.iter_errors(GOOD))
    doc = copy.deepcopy(GOOD)
    _set(doc, path, value)
    bad = tmp_path / "bad.toml"
    bad.write_text(tomli_w.dumps(doc))
    with pytest.raises(pipeline.JobFileError):
        pipeline.jobs.job_file.load_job(bad)
    assert list(validator.iter_errors(doc))


def test_the_citation_file_is_valid_cff():
    """CITATION.cff against the Citation File Format 1.2.0 schema (its published JSON Schema,
    kept in tests/data as the STAC schemas are): the software and the article it implements."""
    import yaml
    from jsonschema import Draft7Validator

    schema = json.loads(
        (ROOT / "tests" / "data" / "citation-file-format-1.2.0.schema.json").read_text()
    )
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    errors = [e.message for e in Draft7Validator(schema).iter_errors(cff)]
    assert not errors, errors
    assert cff["version"] == pipeline.__version__ and cff["license"] == "BSD-3-Clause"
    assert cff["references"][0]["doi"] == "10.3390/jmse11010007"
