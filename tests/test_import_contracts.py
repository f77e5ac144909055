"""The import graph of ``eva_engine``, ``jobs``, ``service`` and ``bench``, read from the source (every import
statement, those inside functions too), keeps the architecture's boundaries:

- the engine is a library: it never imports ``jobs`` or ``service``, its consumers;
- the worker runs without the web service: ``jobs`` never imports ``service``;
- the product never imports its benchmarks: no package but ``bench`` imports ``bench``;
- the rasterizer is the bottom layer: ``eva_engine.render`` imports nothing of ``eva_engine.body``,
  ``eva_engine.avatar`` or ``eva_engine.train``;
- no cycles: between modules, nor between the parts of any package (``eva_engine.train`` and
  ``eva_engine.avatar``, or ``jobs`` and ``service``, ...).

An edge is what one statement names: ``import a.b`` depends on ``a.b``; ``from a import b`` on ``a``
and, when ``b`` is a module, on ``a.b`` too (a package's ``__init__`` runs before its names are
read). Parent packages that Python imports on the way are not edges: every submodule would depend
on its package's ``__init__``. Imports under ``if TYPE_CHECKING:`` never run: they count for the
boundaries and for the module cycles (a circle of annotations is a circle of concepts), not for
the cycles between a package's parts.
"""

from __future__ import annotations

import ast
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("eva_engine", "jobs", "service", "bench")
FORBIDDEN = [
    ("eva_engine", ("jobs", "service", "bench"), "the engine is a library; jobs and service use it"),
    ("jobs", ("service", "bench"), "the worker runs without the web service"),
    ("service", ("bench",), "the product never imports its benchmarks"),
    (
        "eva_engine.render",
        ("eva_engine.body", "eva_engine.avatar", "eva_engine.train"),
        "the rasterizer is the bottom layer",
    ),
]


@dataclass(frozen=True)
class Edge:
    source: str
    target: str
    line: int
    typing_only: bool  # under ``if TYPE_CHECKING:``

    def __str__(self) -> str:
        kind = ", typing only" if self.typing_only else ""
        return f"{self.source} -> {self.target} (line {self.line}{kind})"


def find_modules(root: Path, packages: Iterable[str]) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` file of ``packages`` under ``root``."""
    modules = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _named(node: ast.Import | ast.ImportFrom, module: str, is_package: bool) -> list[str]:
    """The dotted names one import statement depends on (see the module docstring)."""
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    base = node.module or ""
    if node.level:  # relative: from the importing module's package
        package = module if is_package else module.rpartition(".")[0]
        for _ in range(node.level - 1):
            package = package.rpartition(".")[0]
        base = f"{package}.{base}" if base else package
    return [base] + [f"{base}.{alias.name}" for alias in node.names]


def import_edges(modules: dict[str, Path]) -> list[Edge]:
    """Every import of one of ``modules`` by another, wherever the statement is in the file."""

    def resolve(name: str) -> str | None:  # the deepest of our modules that ``name`` names
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    edges = []
    for module, path in modules.items():
        is_package = path.name == "__init__.py"
        pending = [(node, False) for node in ast.parse(path.read_text(), str(path)).body]
        while pending:
            node, typing_only = pending.pop()
            if isinstance(node, ast.Import | ast.ImportFrom):
                targets = {resolve(name) for name in _named(node, module, is_package)}
                edges += [Edge(module, t, node.lineno, typing_only) for t in sorted(targets - {None, module})]
                continue
            if isinstance(node, ast.If) and _is_type_checking(node.test):
                pending += [(child, True) for child in node.body]
                pending += [(child, typing_only) for child in node.orelse]
                continue
            pending += [(child, typing_only) for child in ast.iter_child_nodes(node)]
    return edges


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` (node -> successors) as [a, b, ..., a], or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt) :] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def module_graph(edges: Iterable[Edge], typing: bool = False) -> dict[str, set[str]]:
    """Module -> the modules it imports (with ``typing``, typing-only imports too)."""
    graph: dict[str, set[str]] = {}
    for edge in edges:
        if typing or not edge.typing_only:
            graph.setdefault(edge.source, set()).add(edge.target)
    return graph


def part_graph(package: str, modules: Iterable[str], edges: Iterable[Edge]) -> dict[str, set[str]]:
    """The modules and subpackages directly in ``package`` ("" for the top level), each standing for
    everything below it, and the imports between them (``package``'s own ``__init__`` left out: a
    package's ``__init__`` gathers its parts)."""
    prefix = f"{package}." if package else ""

    def part(name: str) -> str | None:
        if name == package or not name.startswith(prefix):
            return None
        return prefix + name[len(prefix) :].split(".")[0]

    graph: dict[str, set[str]] = {}
    for edge in edges:
        source, target = part(edge.source), part(edge.target)
        if source and target and source != target and not edge.typing_only:
            graph.setdefault(source, set()).add(target)
    return graph


def _within(name: str, package: str) -> bool:
    return name == package or name.startswith(package + ".")


@pytest.fixture(scope="module")
def project() -> tuple[dict[str, Path], list[Edge]]:
    modules = find_modules(ROOT, PACKAGES)
    return modules, import_edges(modules)


@pytest.mark.parametrize(("importer", "forbidden", "why"), FORBIDDEN, ids=[f[0] for f in FORBIDDEN])
def test_boundaries(project, importer, forbidden, why):
    _, edges = project
    crossing = [
        e for e in edges if _within(e.source, importer) and any(_within(e.target, f) for f in forbidden)
    ]
    assert not crossing, f"{why}:\n" + "\n".join(map(str, crossing))


def test_no_module_imports_itself_round_a_cycle(project):
    cycle = find_cycle(module_graph(project[1]))
    assert cycle is None, " -> ".join(cycle)


def test_no_cycle_even_through_typing_only_imports(project):
    """Stricter than running code needs: a cycle of annotations is a circle of concepts too (a job
    kind's module and ``jobs.pipeline`` were one until ``JobKind`` moved beside ``JobRun``)."""
    cycle = find_cycle(module_graph(project[1], typing=True))
    assert cycle is None, " -> ".join(cycle)


def test_no_cycles_between_the_parts_of_a_package(project):
    modules, edges = project
    packages = [""] + [name for name, path in modules.items() if path.name == "__init__.py"]
    cycles = [(p or "top level", c) for p in packages if (c := find_cycle(part_graph(p, modules, edges)))]
    assert not cycles, "\n".join(f"{p}: {' -> '.join(c)}" for p, c in cycles)


def test_the_graph_holds_every_module(project):
    modules, edges = project
    assert {"eva_engine.render.rasterize", "jobs.pipeline", "service.routers.avatars"} <= set(modules)
    pairs = {(e.source, e.target) for e in edges}
    assert ("service.app", "service.routers.avatars") in pairs
    assert ("jobs.avatar", "eva_engine.train") in pairs  # imported inside a function


def test_the_graph_sees_lazy_relative_and_package_imports(tmp_path):
    """The reader on a small tree: imports inside functions, relative ones, ``from package import
    module``, and typing-only ones."""
    files = {
        "pkg/__init__.py": "from pkg.a import f\n",
        "pkg/a.py": "def f():\n    from . import b\n    return b\n",
        "pkg/b.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.sub.c import C\n",
        "pkg/sub/__init__.py": "",
        "pkg/sub/c.py": "import os\n\nclass C:\n    def g(self):\n        import pkg.a\n",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    modules = find_modules(tmp_path, ["pkg"])
    edges = import_edges(modules)
    assert {(e.source, e.target, e.typing_only) for e in edges} == {
        ("pkg", "pkg.a", False),
        ("pkg.a", "pkg", False),  # `from . import b` runs pkg/__init__ first
        ("pkg.a", "pkg.b", False),
        ("pkg.b", "pkg.sub.c", True),
        ("pkg.sub.c", "pkg.a", False),
    }
    assert find_cycle(module_graph(edges)) == ["pkg", "pkg.a", "pkg"]
    assert find_cycle(part_graph("pkg", modules, edges)) is None  # pkg.b -> pkg.sub is typing only
    edges.append(Edge("pkg.b", "pkg.sub.c", 3, typing_only=False))
    assert find_cycle(part_graph("pkg", modules, edges)) == ["pkg.a", "pkg.b", "pkg.sub", "pkg.a"]
