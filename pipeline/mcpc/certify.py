"""The certificate of a planned mission (docs/certified-bound.md): a proven lower bound on the
shortest safe path (the octile distance, the store's landmark bound, a whole-map search's own
bound), the status it proves (``ok`` when ``length <= omega * bound``, else ``uncertified``
with the proven ratio), and the goal's reachability.
"""

from __future__ import annotations

import math
import time

from ..exceptions import UnreachableGoalError
from ..runtime.threads import shared_pool
from ..store.maps_store import MapsStore
from ..trajectory import Status, Trajectory


class _Reach:
    """Whether a mission's start and goal lie in one passable region of the store's components
    layer, looked up in a thread from the start of the mission (a first read of their chunks
    takes about a millisecond) while the coarse path is searched; :meth:`check` waits for
    it."""

    def __init__(self, m: MapsStore, start, goal):
        self.start, self.goal = start, goal
        self.future = shared_pool("bound", 2).submit(m.components, start, goal)

    def check(self) -> bool:
        """True when start and goal share a component, False for a store without the layer;
        UnreachableGoalError when they lie apart."""
        ca, cb = self.future.result()
        if ca is None:
            return False
        if ca != cb:
            raise UnreachableGoalError(
                f"the goal is unreachable: start {self.start} and goal {self.goal} lie in "
                f"separate passable regions (components {ca} and {cb} of the maps store)"
            )
        return True


class _Bound:
    """The landmark bound of a mission (:meth:`MapsStore.lower_bound`), read in a thread while
    the coarse path and the sections are planned (it decodes one chunk of every landmark layer
    at each end, 16 chunks: about as long as the coarse search); ``value()`` waits for it and
    records it and its time in ``extra``."""

    def __init__(self, m: MapsStore, start, goal, extra: dict):
        self.extra = extra
        self.future = shared_pool("bound", 2).submit(self._read, m, start, goal)

    @staticmethod
    def _read(m, start, goal):
        t0 = time.perf_counter()
        return m.lower_bound(start, goal), time.perf_counter() - t0

    def value(self) -> float:
        bound, seconds = self.future.result()
        self.extra["landmark_bound_m"] = bound
        self.extra["bound_s"] = seconds
        return bound


# ``length <= omega * lower`` is checked up to this relative tolerance: the floating point of
# the lengths, and A*'s tie-breaking (within 1 + TIE of the optimum, TIE = 1e-10)
CERTIFY_TOLERANCE = 1e-9


def certified(length: float, lower: float, omega: float) -> bool:
    """Whether ``length <= omega * lower`` (up to ``CERTIFY_TOLERANCE``): with ``lower`` a
    proven lower bound on the optimum, the proof that ``length <= omega * L*``."""
    return length <= omega * lower * (1.0 + CERTIFY_TOLERANCE)


def _done(m, t: Trajectory, repair: str | None = None) -> Trajectory:
    """:func:`_certify`, and the maps' CRS kept with the trajectory (``extra["crs_wkt"]``:
    :meth:`Trajectory.to_geodataframe` gives its points in it)."""
    if m.crs_wkt:
        t.extra["crs_wkt"] = m.crs_wkt
    t.keep_out = m.keep_out  # the zones it avoids, for its flight
    t.max_depth_m = m.max_depth_m  # the rated depth it was planned for
    return _certify(t, repair)


def _certify(t: Trajectory, repair: str | None = None) -> Trajectory:
    """Set the status from the proven bound: "ok" when certified, else "uncertified" with the
    proven ratio in the message."""
    if certified(t.length_m, t.lower_bound_m, t.omega):
        t.status, t.message = Status.OK, ""
        return t
    ratio = t.length_m / t.lower_bound_m if t.lower_bound_m > 0 else math.inf
    t.status = Status.UNCERTIFIED
    t.message = (
        f"length {t.length_m:.1f} m is at most {ratio:.4f} x the shortest safe path (proven "
        f"lower bound {t.lower_bound_m:.1f} m), which does not prove the bound omega = "
        f"{t.omega:g}"
        + (f"; not repaired: {repair}" if repair else "")
        + "; plan it with mcpc=False (the whole map) to certify it"
    )
    return t
