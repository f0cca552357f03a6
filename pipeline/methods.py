"""The safety methods, each known once (docs/method.md section 2): how the clearance ``R`` is
kept from the terrain. ``spherical``: every point of the seabed at least ``R`` away in 3-D;
``horizontal``: every point within a horizontal radius (``horizontal_clearance``, default
``R``) at least ``R`` below; ``vertical``: the seabed straight below at least ``R`` below.

Every stage takes a method's facts from :data:`METHODS`: the parameter schema its names, the
maps build its safety surface's kernel (:func:`pipeline.maps.safety.block_kernel`), the flight
the number its compiled kernels know it by and how far its clearance reaches sideways. A new
method is one entry here, its safety surface's kernel and its branch of the flight's
required-height kernels.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SafetyMethod:
    """One way of keeping the clearance from the terrain."""

    name: str
    code: int  # the number the compiled kernels (the flight's required heights) know it by
    summary: str
    # whether the clearance reaches sideways to R (spherical), to the horizontal radius
    # (horizontal), or not at all (vertical)
    reach: str

    def reach_m(self, clearance_m: float, radius_m: float) -> float:
        """How far the clearance reaches sideways from a point, for the clearance ``R`` and
        the horizontal radius."""
        return {"clearance": clearance_m, "radius": radius_m, "none": 0.0}[self.reach]


METHODS: dict[str, SafetyMethod] = {
    m.name: m
    for m in (
        SafetyMethod("vertical", 0, "the seabed straight below at least R below", "none"),
        SafetyMethod(
            "horizontal", 1, "the seabed within a horizontal radius at least R below", "radius"
        ),
        SafetyMethod("spherical", 2, "the seabed at least R away in 3-D", "clearance"),
    )
}
