"""Clearance measured independently of the maps a mission was planned on: the DEM file's own
seabed (:mod:`.seabed`), finished missions re-checked against any DEM (:mod:`.missions`,
:func:`pipeline.verify_missions`, ``pipeline verify``) and a planned track against the DEM
store's grid points (:mod:`.clearance`)."""

from .._lazy import submodules

__getattr__ = submodules(__name__)
