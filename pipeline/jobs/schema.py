"""The job file's reference and JSON Schema, generated from the parameter schema
(:mod:`pipeline.params`) and the job loader's tables (:mod:`pipeline.jobs.job_file`), so that
neither can drift from what a run accepts.

    python -m pipeline.jobs.schema docs/     # writes docs/job-file.md, docs/job-file.schema.json

``tests/test_job_schema.py`` checks that the committed files are what this module writes, and
that the JSON Schema accepts the project's job files and refuses what the loader refuses.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from ..params import (
    DEM,
    MAPS,
    PERFORMANCE_REPORT,
    PLANNING,
    QUICKLOOKS,
    SYNTHETIC,
    VEHICLE,
    VIA_KEYS,
    Param,
    Schema,
)
from .job_file import DEM_KEYS, MISSION_KEYS, OUTPUT_KEYS, SYNTH_KEYS, TOP_KEYS

# the keys that are not parameters of a schema, each with its JSON Schema and its line
# the [output] table's parameters (the catalog's path is the loader's own key)
_OUTPUT_SCHEMA = Schema("output", QUICKLOOKS, PERFORMANCE_REPORT)
_PAIR = {"type": "array", "items": {"type": "number"}, "minItems": 2, "maxItems": 2}
_CELL = {"type": "array", "items": {"type": "integer"}, "minItems": 2, "maxItems": 2}
_OWN = {
    "name": ({"type": "string", "minLength": 1}, "the job's name (also the report's title)"),
    "dem.path": ({"type": "string", "minLength": 1}, "a DEM file (GeoTIFF, BAG, .asc, NetCDF, "
                 ".grd) or Zarr store, relative to the job file; or [dem.synthetic]"),
    "dem.synthetic.shape": ({**_CELL, "items": {"type": "integer", "minimum": 2}},
                            "[rows, cols] of the generated seabed"),
    "output.catalog": ({"type": "string", "minLength": 1},
                       "the results catalog's directory, relative to the job file"),
    "missions.name": ({"type": "string", "minLength": 1}, "the mission's name, unique in the job"),
    "missions.start": (_CELL, "the start cell [row, col]"),
    "missions.start_xy": (_PAIR, "the start in the maps' coordinates [x, y] (metres)"),
    "missions.start_lonlat": (_PAIR, "the start's [longitude, latitude] (WGS84 degrees)"),
    "missions.goal": (_CELL, "the goal cell [row, col]"),
    "missions.goal_xy": (_PAIR, "the goal in the maps' coordinates [x, y] (metres)"),
    "missions.goal_lonlat": (_PAIR, "the goal's [longitude, latitude] (WGS84 degrees)"),
    "missions.via": ({"type": "array", "items": _CELL, "minItems": 1},
                     "via points visited in order, as cells [[row, col], ...]"),
    "missions.via_xy": ({"type": "array", "items": _PAIR, "minItems": 1},
                        "via points in the maps' coordinates [[x, y], ...]"),
    "missions.via_lonlat": ({"type": "array", "items": _PAIR, "minItems": 1},
                            "via points as [[longitude, latitude], ...]"),
}  # fmt: skip


def _param_schema(p: Param) -> dict:
    """One parameter as JSON Schema, with its bounds, default and help."""
    if p.kind == "bool":
        out: dict = {"type": "boolean"}
    elif p.kind == "int":
        out = {"type": "integer"}
    elif p.kind == "float":
        out = {"type": "number"}
    elif p.kind == "str":
        out = {"type": "string", "minLength": 1}
    elif p.kind == "choice":
        out = {"type": "string", "enum": list(p.options())}
    elif p.kind == "box":
        out = {"type": "array", "items": {"type": "number"}, "minItems": 4, "maxItems": 4}
    elif p.kind == "paths":  # one path, or a list of them
        one = {"type": "string", "minLength": 1}
        out = {"anyOf": [one, {"type": "array", "items": one}]}
    else:  # pragma: no cover - a new kind needs its line here
        raise ValueError(f"no JSON Schema for parameter kind {p.kind!r}")
    if p.kind in ("int", "float"):
        if p.minimum is not None:
            out["minimum"] = p.minimum
        if p.above is not None:
            out["exclusiveMinimum"] = p.above
        if p.maximum is not None:
            out["maximum"] = p.maximum
    if p.default is not None:
        out["default"] = p.default
    out["description"] = p.option_help()
    return out


def _table(schema: Schema | None, keys: set, prefix: str, extra: dict | None = None) -> dict:
    props = {}
    for key in sorted(keys):
        if schema is not None and key in schema:
            props[key] = _param_schema(schema[key])
        elif f"{prefix}{key}" in _OWN:
            js, text = _OWN[f"{prefix}{key}"]
            props[key] = {**js, "description": text}
    props.update(extra or {})
    return {"type": "object", "properties": props, "additionalProperties": False}


def json_schema() -> dict:
    """The JSON Schema (draft 2020-12) of a job file, as TOML parses it."""
    vehicle = _table(VEHICLE, VEHICLE.names(), "vehicle.")
    planning = _table(PLANNING, PLANNING.names(), "planning.")
    synthetic = _table(SYNTHETIC, SYNTH_KEYS, "dem.synthetic.")
    synthetic["required"] = ["shape"]
    dem = _table(DEM, DEM_KEYS - {"synthetic"}, "dem.", {"synthetic": synthetic})
    dem["oneOf"] = [{"required": ["path"]}, {"required": ["synthetic"]}]
    mission = _table(PLANNING, MISSION_KEYS - {"vehicle"}, "missions.", {"vehicle": vehicle})
    one = [
        {"oneOf": [{"required": [k]} for k in (end, f"{end}_xy", f"{end}_lonlat")]}
        for end in ("start", "goal")
    ]
    via = {"not": {"anyOf": [{"required": [a, b]} for a in VIA_KEYS for b in VIA_KEYS if a < b]}}
    mission["allOf"] = [*one, via]
    output = _table(_OUTPUT_SCHEMA, OUTPUT_KEYS, "output.")
    top = {
        "name": {**_OWN["name"][0], "description": _OWN["name"][1]},
        "dem": dem,
        "maps": _table(MAPS, MAPS.names(), "maps."),
        "planning": planning,
        "vehicle": vehicle,
        "missions": {"type": "array", "items": mission},
        "output": output,
    }
    assert set(top) == TOP_KEYS, "a top-level table of the loader is missing here"
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "auv-pipeline job file",
        "description": "A job file (TOML): a DEM, its maps, missions, the results catalog. "
        "Generated from pipeline/params.py by pipeline/jobs/schema.py.",
        "type": "object",
        "properties": top,
        "required": ["name", "dem"],
        "additionalProperties": False,
    }


def _rows(schema: Schema | None, keys: set, prefix: str) -> list[str]:
    rows = []
    for key in sorted(keys):
        if schema is not None and key in schema:
            p = schema[key]
            default = "" if p.default is None else f"`{json.dumps(p.default)}`"
            rows.append(
                f"| `{key}` | {_kind(p)} | {default} | {p.unit or ''} | {p.describe()} | {p.help} |"
            )
        elif f"{prefix}{key}" in _OWN:
            js, text = _OWN[f"{prefix}{key}"]
            rows.append(f"| `{key}` | {js['type']} | | | | {text} |")
    return rows


def _kind(p: Param) -> str:
    """The parameter's type as TOML names it."""
    return {
        "paths": "string or array of strings",
        "box": "array of 4 numbers",
        "choice": "string",
        "str": "string",
        "bool": "boolean",
        "int": "integer",
    }.get(p.kind, p.kind)


_HEAD = ["| key | type | default | unit | valid values | meaning |", "|---|---|---|---|---|---|"]


def markdown() -> str:
    """The job file's reference: every table and key with its type, default, unit, range and
    meaning."""
    out = [
        "# Job file reference",
        "",
        "<!-- generated by `python -m pipeline.jobs.schema docs/` from pipeline/params.py; "
        "do not edit by hand (tests/test_job_schema.py checks it) -->",
        "",
        "A job file is TOML. Every key below is checked before any compute: an unknown key, a "
        "wrong type or a value out of range is one line naming the key and the file (`pipeline "
        "run JOB --dry-run` checks a file without running it). Paths are relative to the job "
        "file. A JSON Schema of the same, for editors: "
        "[job-file.schema.json](job-file.schema.json).",
        "",
        "## Top level",
        "",
        *_HEAD,
        f"| `name` | string | | | | {_OWN['name'][1]} |",
        "",
        "## `[dem]`: the DEM (a file, or `[dem.synthetic]`)",
        "",
        *_HEAD,
        *_rows(DEM, DEM_KEYS - {"synthetic"}, "dem."),
        "",
        "## `[dem.synthetic]`: a generated seabed",
        "",
        *_HEAD,
        *_rows(SYNTHETIC, SYNTH_KEYS, "dem.synthetic."),
        "",
        "## `[maps]`: the safety and ridge maps",
        "",
        *_HEAD,
        *_rows(MAPS, MAPS.names(), "maps."),
        "",
        "## `[planning]`: every mission's planning defaults",
        "",
        *_HEAD,
        *_rows(PLANNING, PLANNING.names(), "planning."),
        "",
        "## `[vehicle]`: the vehicle every mission flies",
        "",
        *_HEAD,
        *_rows(VEHICLE, VEHICLE.names(), "vehicle."),
        "",
        "## `[[missions]]`: one table per mission",
        "",
        "Each mission gives its start and its goal in exactly one form each, via points in at "
        "most one form, and may override any `[planning]` key and, as `vehicle = { ... }`, any "
        "`[vehicle]` key.",
        "",
        *_HEAD,
        *_rows(None, MISSION_KEYS - PLANNING.names() - {"vehicle"}, "missions."),
        "",
        "## `[output]`: the results catalog",
        "",
        *_HEAD,
        *_rows(_OUTPUT_SCHEMA, OUTPUT_KEYS, "output."),
        "",
    ]
    return "\n".join(out)


def write(folder: str | Path) -> list[Path]:
    """Write ``job-file.md`` and ``job-file.schema.json`` into ``folder``."""
    folder = Path(folder)
    md = folder / "job-file.md"
    js = folder / "job-file.schema.json"
    md.write_text(markdown())
    js.write_text(json.dumps(json_schema(), indent=1) + "\n")
    return [md, js]


if __name__ == "__main__":  # pragma: no cover - the command in the module's description
    for p in write(sys.argv[1] if len(sys.argv) > 1 else "docs"):
        print(p)
