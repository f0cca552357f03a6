"""A mission's operational constraints on the maps: keep-out zones
(:mod:`pipeline.constraints.zones`) and the vehicle's rated depth.

:class:`ConstrainedStore` is a maps store as a mission under constraints sees it, read by every
stage as a store is (the planners' windows, the coarse level, the endpoints' checks, the
flight's corridor):

- **keep-out zones** remove from the passable layer every cell whose square comes within the
  margin and a quarter cell of a zone (:class:`pipeline.constraints.zones.KeepOut`);
- **a rated depth** ``D`` raises the safety surface to ``max(S, -D)``: where the lowest safe
  height lies deeper than the rating, the vehicle flies at its rated depth, which keeps the
  clearance from the seabed (it is above the lowest safe height) and stays below the surface
  limit (a rating shallower than that is refused). The path's costs are the 3-D lengths over
  the raised surface.

The certificate (docs/certified-bound.md, "Operational constraints"): removing cells only
removes edges, so the store's landmark bound stays a lower bound under zones. A rated depth
makes edges shorter where it raises the surface (``|max(a, c) - max(b, c)| <= |a - b|``), so
the landmark layers, measured on ``S``, bound nothing there: under a rating the bound is the
octile distance (a lower bound on every path's horizontal length, hence on its 3-D length) and,
for a search of the whole map, the search's own bound on the raised surface.
"""

from __future__ import annotations

import threading

import numpy as np

from ..exceptions import InvalidEndpointError, InvalidParameterError, UnreachableGoalError
from ..store.maps_store import MapsStore

# the half-sides of the windows a closed region round an endpoint is looked for in (a larger
# region is proven apart by the exhaustive search; CHANGELOG.md, "Measurements")
POCKET_SIDES = (64, 256)


class ConstrainedStore(MapsStore):
    """The maps store ``base`` under ``keep_out`` (a :class:`~pipeline.constraints.zones.KeepOut`,
    or None) and ``max_depth_m`` (the vehicle's rated depth in metres, or None): the module's
    description; everything else is the store's."""

    def __init__(self, base: MapsStore, keep_out=None, max_depth_m: float | None = None):
        self.__dict__.update(base.__dict__)
        self.base = base
        self.keep_out = keep_out
        self.max_depth_m = max_depth_m
        if max_depth_m is not None:
            # the landmark layers measure distances over S, which the rating shortens: under a
            # rating they bound nothing, so the store has none (MapsStore.lower_bound is then
            # 0, the octile distance bounding the mission, and active_landmarks none); under
            # zones alone they still bound (the module's description)
            self.landmarks = []
        self._coarse = {}
        self._lock = threading.Lock()

    def __reduce__(self):
        return ConstrainedStore, (self.base, self.keep_out, self.max_depth_m)

    def __repr__(self) -> str:
        parts = [repr(self.base)]
        if self.keep_out is not None:
            parts.append(repr(self.keep_out))
        if self.max_depth_m is not None:
            parts.append(f"rated depth {self.max_depth_m:g} m")
        return f"ConstrainedStore({', '.join(parts)})"

    # ------------------------------------------------------------------ the layers

    def removed(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray | None:
        """Which cells of rows ``r0:r1`` and columns ``c0:c1`` the zones remove (None: none)."""
        if self.keep_out is None:
            return None
        return self.keep_out.blocked(self.x[c0:c1], self.y[r0:r1], self.cell_size)

    @property
    def floor_m(self) -> float | None:
        """The lowest height the rating allows: its depth below the sea surface (the sea
        level less the rated depth, as the vehicle files measure depth), or None."""
        if self.max_depth_m is None:
            return None
        return float(self.base.parameters.sea_level_m) - self.max_depth_m

    def _raised(self, surface: np.ndarray) -> np.ndarray:
        if self.max_depth_m is None:
            return surface
        from ..maps.safety import float32_toward

        # the rating rounded up (never deeper than it) as a float32 surface holds it
        floor = self.floor_m
        if surface.dtype == np.float32:
            floor = float32_toward(floor, np.inf)
        return np.maximum(surface, np.asarray(floor, dtype=surface.dtype))  # NaN kept

    def window(self, var: str, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        out = self.base.window(var, r0, r1, c0, c1)
        if var == "safety":
            return self._raised(out)
        if var == "passable" and self.keep_out is not None:
            return out & ~self.removed(r0, r1, c0, c1)
        return out

    def values(self, var: str, cells) -> np.ndarray:
        out = self.base.values(var, cells)
        if var == "safety":
            return self._raised(out)
        if var != "passable" or self.keep_out is None or not len(out):
            return out
        cells = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
        x, y = self.x[cells[:, 1]], self.y[cells[:, 0]]
        return out & ~self.keep_out.blocked_at(x, y, self.cell_size)

    def coarse(self, rho: int) -> dict:
        """The store's coarse level with the coarse cells whose centre lies in a zone grown by
        its margin removed (as a coarse cell is passable when most of its cells are), and the
        surface raised to the rated depth."""
        from .zones import centres_in

        with self._lock:
            got = self._coarse.get(rho)
        if got is not None:
            return got
        base = self.base.coarse(rho)
        got = {**base, "safety": self._raised(base["safety"])}
        if self.keep_out is not None:
            rows, cols = base["passable"].shape
            a = self.cell_size
            sx = np.sign(self.x[1] - self.x[0]) if len(self.x) > 1 else 1.0
            sy = np.sign(self.y[1] - self.y[0]) if len(self.y) > 1 else -1.0
            xs = self.x[0] - sx * a / 2 + sx * (np.arange(cols) + 0.5) * rho * a
            ys = self.y[0] - sy * a / 2 + sy * (np.arange(rows) + 0.5) * rho * a
            inside = centres_in(self.keep_out.kept, xs, ys)
            got["passable"] = base["passable"] & ~inside
        with self._lock:
            self._coarse[rho] = got
        return got

    # ------------------------------------------------------------------ zones: ends, regions

    def zone_of(self, cell) -> str | None:
        """The zone whose kept area removes ``cell``, or None."""
        if self.keep_out is None:
            return None
        r, c = int(cell[0]), int(cell[1])
        if not self.keep_out.blocked_at(self.x[c], self.y[r], self.cell_size):
            return None
        name = self.keep_out.zone_at(self.x[c], self.y[r])
        if name is None:  # within the slack of a quarter cell: the nearest zone
            import shapely

            p = shapely.Point(self.x[c], self.y[r])
            name = min(self.keep_out.zones, key=lambda z: z[1].distance(p))[0]
        return name

    def components(self, *cells) -> list:
        """The store's components of ``cells``; for a start and a goal in one component, an
        :class:`UnreachableGoalError` when the zones close a region round either that does not
        hold the other (found in windows of :data:`POCKET_SIDES`)."""
        got = self.base.components(*cells)
        if self.keep_out is None or len(cells) != 2 or got[0] is None or got[0] != got[1]:
            return got
        for k, (end, other) in enumerate((cells, cells[::-1])):
            if self._closed_apart(end, other):
                names = ("start", "goal")[k], ("goal", "start")[k]
                raise UnreachableGoalError(
                    f"the goal is unreachable: the keep-out zones "
                    f"({', '.join(self.keep_out.names)}) close off the region of {names[0]} "
                    f"{tuple(int(v) for v in end)} from {names[1]} "
                    f"{tuple(int(v) for v in other)}"
                )
        return got

    def _closed_apart(self, end, other) -> bool:
        from scipy import ndimage

        rows, cols = self.shape
        r, c = int(end[0]), int(end[1])
        cross = ndimage.generate_binary_structure(2, 1)
        for h in POCKET_SIDES:
            r0, r1 = max(r - h, 0), min(r + h + 1, rows)
            c0, c1 = max(c - h, 0), min(c + h + 1, cols)
            if not self.keep_out.near(self.x[c0:c1], self.y[r0:r1], self.cell_size):
                # no zone there: its region closes only round the other end (one component)
                continue
            ok = self.window("passable", r0, r1, c0, c1)
            if not ok[r - r0, c - c0]:
                return False  # the endpoints' own checks say what is wrong
            labels, _ = ndimage.label(ok, structure=cross)
            region = labels == labels[r - r0, c - c0]
            open_ = (
                (r0 > 0 and region[0].any())
                or (r1 < rows and region[-1].any())
                or (c0 > 0 and region[:, 0].any())
                or (c1 < cols and region[:, -1].any())
            )
            if not open_:
                orr, oc = int(other[0]) - r0, int(other[1]) - c0
                held = 0 <= orr < r1 - r0 and 0 <= oc < c1 - c0 and region[orr, oc]
                return not held
            if r0 == 0 and c0 == 0 and r1 == rows and c1 == cols:
                return False
        return False


def constrained(
    m: MapsStore, keep_out=None, margin_m: float | None = None, max_depth_m: float | None = None
) -> MapsStore:
    """``m`` under the zones of ``keep_out`` (:func:`~pipeline.constraints.zones.read_zones`) and
    the rated depth ``max_depth_m``, or ``m`` itself without either. A rating shallower than the
    surface limit (the sea level less the surface clearance: no height would be allowed) is
    one :class:`InvalidParameterError`."""
    from .zones import map_extent, read_zones

    if isinstance(m, ConstrainedStore):
        m = m.base
    zones = read_zones(keep_out, m.crs_wkt, margin_m, map_extent(m))
    if max_depth_m is not None:
        max_depth_m = check_rating(max_depth_m, m.parameters)
    if zones is None and max_depth_m is None:
        return m
    return ConstrainedStore(m, zones, max_depth_m)


def check_rating(max_depth_m, parameters) -> float:
    """The rated depth (metres below the sea surface, as every depth the tool writes) checked
    against the maps' surface limit (the surface clearance below the sea surface): a rating
    shallower leaves no height to fly at, one :class:`InvalidParameterError`."""
    from ..params import VEHICLE

    max_depth_m = VEHICLE.max_depth_m.check(max_depth_m)
    below = float(parameters.sea_level_m) - float(parameters.top_m)  # the surface clearance
    if max_depth_m < below:
        raise InvalidParameterError(
            f"the rated depth {max_depth_m:g} m is shallower than the surface limit, "
            f"{below:g} m below the sea surface (the surface clearance), so no height keeps "
            "both; give the vehicle's real rating, or a smaller surface_clearance"
        )
    return max_depth_m


def check_outside(m: MapsStore, name: str, cell) -> None:
    """An :class:`InvalidEndpointError` naming the zone when ``cell`` (``name``: start, goal)
    is removed by a keep-out zone of ``m``."""
    zone = m.zone_of(cell) if m.keep_out is not None else None
    if zone is not None:
        margin = m.keep_out.margin_m
        raise InvalidEndpointError(
            f"{name} {tuple(int(v) for v in cell)} lies in keep-out zone {zone!r}"
            + (f" or within its margin of {margin:g} m" if margin else "")
            + "; move it out of the zone"
        )
