"""The code's shape: no module reaches into another subpackage's private names."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]


def _private_uses(source: str, package: tuple):
    """(line, what) for every private name of another pipeline module that ``source`` (a
    module of ``package``, e.g. ``("pipeline", "planners")``) uses: ``from pipeline.x import
    _y`` (or relative), and ``pipeline.x._y``."""
    tree = ast.parse(source)
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = list(package[: len(package) - node.level + 1])
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            if module.split(".")[0] != "pipeline":
                continue
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__"):
                    yield node.lineno, f"from {module} import {alias.name}"
        elif (
            isinstance(node, ast.Attribute)
            and node.attr.startswith("_")
            and not node.attr.startswith("__")
        ):
            chain = node.value
            while isinstance(chain, ast.Attribute):
                chain = chain.value
            if isinstance(chain, ast.Name) and chain.id == "pipeline":
                yield node.lineno, ast.unparse(node)


FILES = sorted(p for d in ("pipeline", "tests", "benchmarks") for p in (ROOT / d).rglob("*.py"))


def _outside(package: tuple, what: str) -> bool:
    """Whether the private name in ``what`` (``from pipeline.x.y import _z`` or
    ``pipeline.x.y._z``) belongs to another subpackage than ``package``: the modules of one
    subpackage (``pipeline.store``) share their private names; a top-level module of
    ``pipeline``, the tests and the benchmarks share none."""
    module = what.split()[1] if what.startswith("from ") else what.rsplit(".", 1)[0]
    owner = tuple(module.split(".")[:-1])
    return not (len(package) > 1 and package[0] == "pipeline" and owner == package)


@pytest.mark.parametrize("path", FILES, ids=[str(p.relative_to(ROOT)) for p in FILES])
def test_no_private_name_of_another_subpackage(path):
    package = path.parent.relative_to(ROOT).parts
    uses = [u for u in _private_uses(path.read_text(), package) if _outside(package, u[1])]
    assert not uses, f"{path.relative_to(ROOT)} uses private names: {uses}"


def test_a_subpackage_shares_its_private_names_only_within():
    assert not _outside(("pipeline", "store"), "from pipeline.store.cache import _x")
    assert _outside(("pipeline", "mcpc"), "from pipeline.store.cache import _x")
    assert _outside(("pipeline",), "from pipeline.jobs import _x")
    assert _outside(("tests",), "pipeline.store.cache._x")
    assert _outside(("pipeline", "store"), "from pipeline.store import _x")  # its __init__


def test_the_check_sees_private_names():
    src = (
        "from ..mcpc import _grow\nfrom .core import _trace, Search\nimport pipeline\n"
        "pipeline.store.maps_store._STORES\nfrom numpy import _core\n"
    )
    assert [w for _, w in _private_uses(src, ("pipeline", "planners"))] == [
        "from pipeline.mcpc import _grow",
        "from pipeline.planners.core import _trace",
        "pipeline.store.maps_store._STORES",
    ]


def _numba_jit_imports(source: str) -> list:
    """The lines of ``source`` that take numba's compilers (``njit``, ``jit``) from numba."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "numba":
            if any(a.name in ("njit", "jit") for a in node.names):
                out.append(node.lineno)
        elif isinstance(node, ast.Attribute) and node.attr in ("njit", "jit"):
            if isinstance(node.value, ast.Name) and node.value.id == "numba":
                out.append(node.lineno)
    return out


def test_the_packages_kernels_compile_through_one_module():
    """Every kernel of the package is compiled by ``pipeline.runtime.jit.njit``, whose module
    makes numba's on-disk cache safe for processes that compile at once: no other module takes
    numba's compilers itself."""
    assert _numba_jit_imports("from numba import njit, prange\nimport numba\nnumba.njit(f)\n") == [
        1,
        3,
    ]
    found = {
        str(p.relative_to(ROOT)): lines
        for p in sorted((ROOT / "pipeline").rglob("*.py"))
        if p != ROOT / "pipeline" / "runtime" / "jit.py"
        and (lines := _numba_jit_imports(p.read_text()))
    }
    assert not found, f"kernels compiled past pipeline.runtime.jit: {found}"
