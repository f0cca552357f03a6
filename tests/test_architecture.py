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
    assert _outside(("pipeline",), "from pipeline.params import _x")
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


def _unit(module: str) -> str:
    """The part of the package a module belongs to: its subpackage (``pipeline.store.cache``:
    ``store``), or itself for a top-level module (``pipeline.params``: ``params``)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "pipeline"


def _module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(source: str, module: str, package: bool) -> set[str]:
    """The pipeline modules that ``source`` (module ``module``) imports, at any indentation
    (a function's imports too), except those only a type checker reads (``if
    TYPE_CHECKING:``)."""
    tree = ast.parse(source)
    typing_only = {
        id(n)
        for block in ast.walk(tree)
        if isinstance(block, ast.If) and "TYPE_CHECKING" in ast.unparse(block.test)
        for n in ast.walk(block)
    }
    here = module.split(".") if package else module.split(".")[:-1]
    out = set()
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = here[: len(here) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] == "pipeline":
                out.add(target)
                out.update(f"{target}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.split(".")[0] == "pipeline")
    return out


def _unit_graph(files, root: Path = ROOT):
    """The imports between the parts of the package (:func:`_unit`), a networkx graph whose
    edges name one import each."""
    import networkx

    modules = {_module_name(p, root): p for p in files}
    graph = networkx.DiGraph()
    for module, path in modules.items():
        for target in _imports(path.read_text(), module, path.name == "__init__.py"):
            if target in modules and target != "pipeline" and _unit(target) != _unit(module):
                graph.add_edge(_unit(module), _unit(target), line=f"{module} -> {target}")
    return graph


def test_no_import_cycle_between_the_parts_of_the_package():
    """The subpackages and top-level modules import one another without a cycle, counting
    the imports inside functions (a cycle there only waits for its first call): each stage
    can be read, tested and replaced on top of the ones below it."""
    import networkx

    graph = _unit_graph(sorted((ROOT / "pipeline").rglob("*.py")))
    cycles = list(networkx.simple_cycles(graph))
    assert not cycles, [
        [graph.edges[a, b]["line"] for a, b in zip(c, c[1:] + c[:1], strict=True)] for c in cycles
    ]
    # the stages stand in the order of the pipeline
    order = [
        "runtime",
        "planners",
        "params",
        "store",
        "dem",
        "maps",
        "constraints",
        "mcpc",
        "verify",
        "jobs",
    ]
    for low, high in zip(order, order[1:], strict=False):
        assert not networkx.has_path(graph, low, high), f"{low} reaches {high}"


def test_the_cycle_check_sees_a_cycle_through_a_function(tmp_path):
    pkg = tmp_path / "pipeline"
    (pkg / "a").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a" / "__init__.py").write_text("")
    (pkg / "a" / "x.py").write_text("def f():\n    from ..b import y\n")
    (pkg / "b.py").write_text(
        "from typing import TYPE_CHECKING\nfrom .a.x import f\nif TYPE_CHECKING:\n"
        "    from .c import z\ny = 1\n"
    )
    (pkg / "c.py").write_text("from .b import y\n")
    graph = _unit_graph(sorted(pkg.rglob("*.py")), root=tmp_path)
    assert set(graph.edges) == {("a", "b"), ("b", "a"), ("c", "b")}  # b -> c: a type only
