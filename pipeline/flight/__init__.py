"""Stage 5, missions a vehicle can fly (docs/flyable-missions.md): the vehicle and its flight
(:mod:`.vehicle`), the horizontal route with its turns (:mod:`.geometry`), the vertical
profile clear of the continuous seabed (:mod:`.profile`), and :func:`~.fly.fly`, which makes a
flight of a planned trajectory (:mod:`.fly`).
"""

from .._lazy import submodules

__getattr__ = submodules(__name__)
