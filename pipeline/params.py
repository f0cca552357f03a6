"""The parameter schema: every user-facing parameter once, with its default, bounds, unit and
help text.

The library's argument checks, the job-file loader (so ``--dry-run`` refuses whatever a run
would refuse, with the same message) and the command line's options and ``--help`` texts all
read these tables. A check names the parameter as its caller knows it: ``` `clearance` ``` in
the library, ``maps.clearance`` in a job file.

Planner names are not listed here: the planner registry (:mod:`pipeline.planners.registry`)
owns them, and :func:`check_planner` asks it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from numbers import Integral, Real
from typing import Any

from .exceptions import InvalidParameterError
from .methods import METHODS as SAFETY_METHODS

DEFAULT_CHUNK = 1024


@dataclass(frozen=True)
class Param:
    """One parameter: its kind (``"float"``, ``"int"``, ``"bool"``, ``"choice"``, ``"str"``),
    default (None: derived from other values, see the help), bounds and unit."""

    name: str
    kind: str
    default: Any
    help: str
    unit: str = ""
    minimum: float | None = None  # inclusive
    above: float | None = None  # exclusive
    maximum: float | None = None  # inclusive
    choices: tuple | Callable[[], tuple] = ()  # a callable: asked when needed (registries)

    def options(self) -> tuple:
        """The valid values of a choice."""
        return self.choices() if callable(self.choices) else self.choices

    def describe(self) -> str:
        """What a valid value is, in words (the middle of every error message)."""
        if self.kind == "bool":
            return "true or false"
        if self.kind == "box":
            return f"four finite numbers {self.unit}, each minimum below its maximum"
        if self.kind == "str":
            return "a string"
        if self.kind == "paths":
            return "a file path or a list of file paths"
        if self.kind == "choice":
            names = [repr(c) for c in self.options()]
            return (", ".join(names[:-1]) + " or " + names[-1]) if len(names) > 1 else names[0]
        what = "an integer" if self.kind == "int" else "a finite number"
        if self.unit and self.kind == "float":
            what += f" of {self.unit}"
        if self.minimum is not None and self.maximum is not None:
            return f"{what} from {_fmt(self.minimum)} to {_fmt(self.maximum)}"
        if self.above is not None and self.maximum is not None:
            return f"{what} above {_fmt(self.above)} and at most {_fmt(self.maximum)}"
        if self.minimum is not None:
            what += f" >= {_fmt(self.minimum)}"
        if self.above is not None:
            what += f" > {_fmt(self.above)}"
        if self.maximum is not None:
            what += f" <= {_fmt(self.maximum)}"
        return what

    def check(self, value, label: str | None = None):
        """``value`` normalised (an int, a float, a bool, a str), or one
        :class:`InvalidParameterError` that names ``label`` (default ``` `name` ```)."""
        label = label or f"`{self.name}`"

        def bad():
            return InvalidParameterError(f"{label} must be {self.describe()}, got {value!r}")

        if self.kind == "bool":
            if not isinstance(value, bool):
                raise bad()
            return value
        if self.kind == "str":
            if not isinstance(value, str) or not value:
                raise bad()
            return value
        if self.kind == "paths":
            paths = [value] if isinstance(value, str) else value
            if not isinstance(paths, list) or not all(isinstance(p, str) and p for p in paths):
                raise bad()
            return paths
        if self.kind == "choice":
            if not isinstance(value, str) or value not in self.options():
                raise bad()
            return value
        if self.kind == "box":
            try:
                box = [float(v) for v in value]
                ok = all(not isinstance(v, bool | str) for v in value)
            except (TypeError, ValueError):
                raise bad() from None
            if not ok or len(box) != 4 or not all(math.isfinite(v) for v in box):
                raise bad()
            if not (box[0] < box[2] and box[1] < box[3]):
                raise bad()
            return tuple(box)
        if isinstance(value, bool) or not isinstance(
            value, Integral if self.kind == "int" else Real
        ):
            raise bad()
        v = int(value) if self.kind == "int" else float(value)
        if self.kind == "float" and not math.isfinite(v):
            raise bad()
        if (
            (self.minimum is not None and v < self.minimum)
            or (self.above is not None and v <= self.above)
            or (self.maximum is not None and v > self.maximum)
        ):
            raise bad()
        return v

    def check_optional(self, value, label: str | None = None):
        """As :meth:`check`, with None passed through (a default derived later)."""
        return None if value is None else self.check(value, label)

    def option_help(self) -> str:
        """The help text of the command-line option (the unit, then the help)."""
        return f"{self.help} ({self.unit})" if self.unit else self.help


def _fmt(v) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


class Schema:
    """The parameters of one stage, by name (``MAPS.clearance``, ``MAPS["clearance"]``)."""

    def __init__(self, title: str, *params: Param):
        self.title = title
        self._params = {p.name: p for p in params}

    def __getattr__(self, name: str) -> Param:
        try:
            return self.__dict__["_params"][name]
        except KeyError:
            raise AttributeError(name) from None

    def __getitem__(self, name: str) -> Param:
        return self._params[name]

    def __iter__(self):
        return iter(self._params.values())

    def __contains__(self, name) -> bool:
        return name in self._params

    def names(self) -> set[str]:
        return set(self._params)

    def defaults(self) -> dict:
        return {p.name: p.default for p in self if p.default is not None}

    def check(self, values: dict, where: str = "") -> dict:
        """Every value of ``values`` checked (None kept: derived later); ``where`` prefixes the
        names in messages (``"maps."``)."""
        out = {}
        for k, v in values.items():
            out[k] = self[k].check_optional(v, f"{where}{k}" if where else None)
        return out


METHODS = tuple(SAFETY_METHODS)  # the safety methods' names (pipeline.methods)

CELL_SIZE = Param("cell_size", "float", None, "cell side", "metres", above=0)
LONGITUDE = Param("longitude", "float", None, "", "degrees", minimum=-180.0, maximum=360.0)
LATITUDE = Param("latitude", "float", None, "", "degrees", minimum=-90.0, maximum=90.0)
QUICKLOOKS = Param("quicklooks", "bool", True, "a plan view and depth profile PNG per mission")
PERFORMANCE_REPORT = Param(
    "performance_report", "bool", True, "a dask performance report (HTML) of each run"
)
MISSIONS_PER_TASK = Param(
    "missions_per_task", "int", None, "missions one cluster task plans, in turn", minimum=1
)

# the synthetic generator's version: a DEM store made by another version is made again (a job
# fingerprints its DEM with it); its seed stream takes it too
GENERATOR_VERSION = 1

SYNTHETIC = Schema(
    "the generated seabed (synthetic_dem, [dem.synthetic])",
    Param("cell_size", "float", 30.0, "cell side", "metres", above=0),
    Param("seed", "int", 0, "random seed of the scene", minimum=0),
    Param("islands", "int", 2, "islands breaking the surface", minimum=0, maximum=10),
    Param(
        "origin_lon",
        "float",
        -44.83,
        "longitude of the map's centre (default: the Mid-Atlantic Ridge at the TAG field)",
        "degrees",
        minimum=-180.0,
        maximum=180.0,
    ),
    Param(
        "origin_lat",
        "float",
        26.14,
        "latitude of the map's centre",
        "degrees",
        minimum=-85.0,
        maximum=85.0,
    ),
    Param(
        "georeferenced",
        "bool",
        True,
        "give the map a CRS (a transverse Mercator centred on the origin); false: map "
        "coordinates only",
    ),
)

DEM = Schema(
    "DEM input (open_dem, [dem])",
    Param("chunks", "int", DEFAULT_CHUNK, "chunk side of the Zarr stores", "cells", minimum=1),
    Param("variable", "str", None, "variable to read from a NetCDF or Zarr file"),
    Param("cell_size", "float", None, "cell side of a grid without coordinates", "metres", above=0),
    Param("resolution", "float", None, "resample to square cells of this side", "metres", above=0),
    Param(
        "bbox",
        "box",
        None,
        "read only this region of the file: longitude and latitude (WGS84) of its corners",
        "[lon_min, lat_min, lon_max, lat_max] in degrees",
    ),
    Param(
        "bbox_xy",
        "box",
        None,
        "read only this region of the file, in the file's own coordinates",
        "[x_min, y_min, x_max, y_max] in the file's units",
    ),
    Param(
        "uncertainty_k",
        "float",
        None,
        "plan on the shoal side of the survey's uncertainty band: the seabed is taken as "
        "elevation + k * sigma, so every clearance grows by k * sigma (a BAG's uncertainty "
        "band, or the variable named by `uncertainty`)",
        "multiples of the vertical uncertainty sigma",
        minimum=0,
    ),
    Param(
        "uncertainty",
        "str",
        None,
        "the band or variable holding sigma when its name is not one of uncertainty, sigma, "
        "stdev, std, tvu",
    ),
)

MAPS = Schema(
    "safety and ridge maps (build_maps, [maps])",
    Param(
        "method",
        "choice",
        "spherical",
        "how the clearance is measured: 3-D (a sphere), horizontally (a disc) or vertically",
        choices=METHODS,
    ),
    Param("clearance", "float", 300.0, "R, the clearance kept from the terrain", "metres", above=0),
    Param(
        "horizontal_clearance",
        "float",
        None,
        "R_h of the horizontal method; default R",
        "metres",
        above=0,
    ),
    Param("sea_level", "float", 0.0, "the sea surface", "metres"),
    Param(
        "surface_clearance",
        "float",
        None,
        "depth the safety surface stays below sea level; default R",
        "metres",
        minimum=0,
    ),
    Param(
        "min_accumulation",
        "int",
        None,
        "ridge threshold: accumulation of at least this many cells; default a 1 km^2 area",
        "cells",
        minimum=1,
    ),
    Param(
        "landmarks",
        "int",
        8,
        "landmark distance layers stored for the proven lower bound (0: none)",
        minimum=0,
        maximum=64,
    ),
)


def _planner_names() -> tuple:
    from .planners.registry import PLANNERS

    return tuple(PLANNERS)


PLANNING = Schema(
    "planning (plan, [planning], per mission)",
    Param("planner", "choice", "ra_star", "planner of every section", choices=_planner_names),
    Param("omega", "float", 2.0, "length bound: length <= omega * shortest", minimum=1),
    Param("mcpc", "bool", True, "coarse to fine (MCPC); false plans the whole map in one window"),
    Param(
        "rho",
        "int",
        None,
        "compression factor; default max(2, ceil(side / 1000))",
        "cells",
        minimum=1,
    ),
    Param("section_size", "int", None, "section side; default about 3 km", "cells", minimum=2),
    Param(
        "margin",
        "int",
        None,
        "window margin round a section; default section_size / 8",
        "cells",
        minimum=0,
    ),
    Param(
        "coarse_planner", "choice", "astar", "planner of the coarse path", choices=_planner_names
    ),
    Param(
        "coarse_weight",
        "float",
        1.1,
        "weight of the coarse A* for the bounded planners (weighted A*, at most omega; 1: "
        "exact A*, which astar and dijkstra always use): the coarse path, a guide for the "
        "sections, is within this factor of the coarse optimum",
        minimum=1,
    ),
    Param(
        "repair_max_cells",
        "int",
        25_000_000,
        "a path MCPC cannot certify is planned again on the whole map when the map has at "
        "most this many cells (0: never)",
        "cells",
        minimum=0,
    ),
    Param(
        "keep_out",
        "paths",
        None,
        "keep-out zones the route and the flown track never enter: vector files (GeoJSON, "
        "GeoPackage, Shapefile; polygons in any CRS), relative to the job file",
    ),
    Param(
        "keep_out_margin_m",
        "float",
        None,
        "distance kept from every keep-out zone; default 0",
        "metres",
        minimum=0,
    ),
)


VEHICLE = Schema(
    "the vehicle (fly, [vehicle], per mission vehicle = {...})",
    Param("speed_m_s", "float", 1.5, "cruise speed through the water", "m/s", above=0),
    Param(
        "max_pitch_deg",
        "float",
        20.0,
        "steepest climb or dive the vehicle holds",
        "degrees",
        above=0,
        maximum=89,
    ),
    Param(
        "min_turn_radius_m",
        "float",
        None,
        "tightest horizontal turn; default one cell side, at most 50 m",
        "metres",
        above=0,
    ),
    Param(
        "waypoint_band_m",
        "float",
        None,
        "how far above the lowest safe profile the waypoint legs may fly; default the "
        "narrowest of R/4, R/2, R that needs fewer waypoints than a tenth of the path's cells",
        "metres",
        minimum=0,
    ),
    Param(
        "max_depth_m",
        "float",
        None,
        "the vehicle's rated depth below the sea surface: no point of the route deeper; where "
        "the lowest safe height lies deeper the vehicle flies at it",
        "metres",
        above=0,
    ),
    Param(
        "max_leg_m",
        "float",
        None,
        "longest leg between two waypoints; however long, a leg is split until the map line, "
        "the geodesic and the rhumb line between its waypoints lie within min(5 m, R/20) of "
        "each other",
        "metres",
        above=0,
    ),
    Param("hotel_power_w", "float", None, "power of everything but propulsion", "W", minimum=0),
    Param("propulsion_power_w", "float", None, "propulsion power at cruise speed", "W", minimum=0),
    Param(
        "battery_wh",
        "float",
        None,
        "usable energy; a mission needing more fails with the reason",
        "Wh",
        above=0,
    ),
)


def check_planner(planner, omega, name: str = "planner") -> tuple[str, float]:
    """A registered planner name and a finite ``omega >= 1``, or one clear error. A valid
    name and a float omega (what ``plan()`` passes every section) return at once: the generic
    checks cost a noticeable share of a short section's search."""
    from .planners.registry import PLANNERS

    if (
        isinstance(planner, str)
        and planner in PLANNERS
        and type(omega) is float
        and PLANNING.omega.minimum <= omega < math.inf
    ):
        return planner, omega
    PLANNING.planner.check(planner, f"`{name}`")
    return planner, PLANNING.omega.check(omega)


# the forms a mission's end takes, in job files and in the API: a cell (``start``), map
# coordinates (``start_xy``) or longitude and latitude (``start_lonlat``)
ENDPOINT_FORMS = ("cell", "xy", "lonlat")


def endpoint_key(end: str, form: str) -> str:
    """The key of ``end`` (``"start"``, ``"goal"``) in ``form`` (:data:`ENDPOINT_FORMS`)."""
    return end if form == "cell" else f"{end}_{form}"


def endpoint_forms(mission: dict, end: str) -> list[str]:
    """The forms in which ``mission`` gives its ``end`` (one, when it is well made)."""
    return [f for f in ENDPOINT_FORMS if endpoint_key(end, f) in mission]


def check_region(bbox, bbox_xy, where: str = "") -> tuple | None:
    """``("lonlat" | "xy", box)`` from a DEM's ``bbox`` (WGS84 degrees) or ``bbox_xy`` (the
    file's own coordinates), checked, or None (no region). ``where`` prefixes the names in the
    errors (``"dem."`` in a job file, which names its keys that way)."""

    def name(key: str) -> str:
        return f"{where}{key}" if where else f"`{key}`"

    if bbox is not None and bbox_xy is not None:
        raise InvalidParameterError(
            f"give one of {name('bbox')} (longitude, latitude) and {name('bbox_xy')}, not both"
        )
    if bbox_xy is not None:
        return "xy", DEM.bbox_xy.check(bbox_xy, name("bbox_xy"))
    if bbox is None:
        return None
    box = DEM.bbox.check(bbox, name("bbox"))
    if not (-90 <= box[1] and box[3] <= 90 and -180 <= box[0] and box[2] <= 360):
        raise InvalidParameterError(
            f"{name('bbox')} {list(box)} is not [lon_min, lat_min, lon_max, lat_max]: "
            "latitudes from -90 to 90, longitudes from -180 to 360"
        )
    return "lonlat", box


def shape2d(name: str, value, *, minimum: int = 2, label: str | None = None) -> tuple[int, int]:
    """A (rows, cols) pair of integers >= ``minimum`` (a map has at least 2 x 2 cells)."""
    try:
        rows, cols = value
    except (TypeError, ValueError):
        raise InvalidParameterError(
            f"{label or f'`{name}`'} must be a pair (rows, cols), got {value!r}"
        ) from None
    side = Param(name, "int", None, "", minimum=minimum)
    lab = (
        (lambda i, what: f"{label}[{i}] ({what})")
        if label
        else (lambda i, what: f"`{name}[{i}] ({what})`")
    )
    return side.check(rows, lab(0, "rows")), side.check(cols, lab(1, "cols"))


def chunks2d(value, shape: tuple[int, int]) -> tuple[int, int] | None:
    """Normalise ``chunks`` (None, an int, or a (rows, cols) pair) to a pair of chunk sides."""
    if value is None:
        return None
    if isinstance(value, Integral) and not isinstance(value, bool):
        pair = (value, value)
    else:
        try:
            pair = tuple(value)
        except TypeError:
            pair = ()
        if len(pair) != 2:
            raise InvalidParameterError(
                f"`chunks` must be None, an integer or a (rows, cols) pair, got {value!r}"
            )
    side = DEM.chunks
    r = side.check(pair[0], "`chunks[0]`")
    c = side.check(pair[1], "`chunks[1]`")
    return min(r, shape[0]), min(c, shape[1])


def check_clearance(
    value, a: float | None, label: str = "`clearance`", param=MAPS.clearance
) -> float:
    """A clearance in metres (``param``'s bounds), refused when a DEM of cell side ``a`` cannot
    resolve it (below half a cell); ``a`` None skips that part (cell side not known yet)."""
    value = param.check(value, label)
    if a is not None and value < a / 2:
        raise InvalidParameterError(
            f"{label} = {value:g} m is smaller than half a cell ({a / 2:g} m): the clearance "
            "zone would hold no grid point but the cell itself, so the DEM cannot resolve it; "
            "use a larger clearance or a finer DEM"
        )
    return value


def endpoint_form(mission: dict, end: str) -> tuple[str, object]:
    """``(form, value)`` of a mission's ``end`` (``"start"`` or ``"goal"``) as a job file
    gives it: ``end`` a cell ``(row, col)``, ``end_xy`` map coordinates or ``end_lonlat``
    (longitude, latitude); exactly one of them, else one :class:`InvalidParameterError`."""
    forms = endpoint_forms(mission, end)
    if len(forms) != 1:
        raise InvalidParameterError(
            f"a mission needs exactly one of {end} (a cell), {end}_xy or {end}_lonlat, got "
            f"{mission!r}"
        )
    return forms[0], mission[endpoint_key(end, forms[0])]


def endpoint_cells(m, mission: dict) -> dict:
    """``mission`` with its start and goal as cells of the maps store ``m`` (from any of the
    forms :func:`endpoint_form` reads; the cells the job file's loader gives), and its via
    points, if any, as the list ``via`` of cells (:func:`via_form`)."""
    out = dict(mission)
    for end in ("start", "goal"):
        form, value = endpoint_form(mission, end)
        # a cell as given: the planner checks it is one (a row of 1.5 is no cell)
        out[end] = value if form == "cell" else m.cell_of(end, form, value)
    form, points = via_form(mission)
    if form is not None:
        for key in VIA_KEYS:
            out.pop(key, None)
        out["via"] = [
            p if form == "cell" else m.cell_of(f"via {k + 1}", form, p)
            for k, p in enumerate(points)
        ]
    return out


# a mission's via points, visited in order: cells (``via``), map coordinates (``via_xy``) or
# longitude and latitude (``via_lonlat``), one form for all of them
VIA_KEYS = tuple(endpoint_key("via", f) for f in ENDPOINT_FORMS)


def via_form(mission: dict) -> tuple[str | None, list]:
    """``(form, points)`` of a mission's via points, ``(None, [])`` without any; more than
    one form, or points that are not a list of pairs, is one :class:`InvalidParameterError`."""
    forms = endpoint_forms(mission, "via")
    if not forms:
        return None, []
    if len(forms) > 1:
        raise InvalidParameterError(
            f"a mission's via points take one form: via (cells), via_xy or via_lonlat, got "
            f"{', '.join(endpoint_key('via', f) for f in forms)}"
        )
    key = endpoint_key("via", forms[0])
    points = mission[key]
    try:
        points = [tuple(p) for p in points]
        if not points or not all(len(p) == 2 for p in points):
            raise TypeError
    except TypeError:
        raise InvalidParameterError(
            f"{key} must be a list of pairs ([[a, b], ...]) visited in order, got {points!r}"
        ) from None
    return forms[0], points
