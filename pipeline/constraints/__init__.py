"""A mission's operational constraints: keep-out zones read from vector files or polygons
(:mod:`.zones`) and the maps store as a mission under its zones and the vehicle's rated depth
sees it (:mod:`.store`)."""

from .._lazy import submodules

__getattr__ = submodules(__name__)
