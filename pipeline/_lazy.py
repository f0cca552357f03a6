"""A package's submodules reached as attributes (``pipeline.store.maps_store``) are imported on
first use, as ``pipeline.jobs`` is after a bare ``import pipeline``: each package binds
``__getattr__ = submodules(__name__)`` (PEP 562)."""

from __future__ import annotations

import importlib


def submodules(package: str):
    """A module ``__getattr__`` for ``package`` that imports its submodule of the name asked
    for, and raises AttributeError where there is none."""

    def __getattr__(name: str):
        if name.startswith("__"):
            raise AttributeError(name)
        try:
            return importlib.import_module(f"{package}.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"{package}.{name}":
                raise
            raise AttributeError(f"module {package!r} has no attribute {name!r}") from None

    return __getattr__
