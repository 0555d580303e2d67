"""The project's modules import each other without cycles.

A static walk (``ast``) of every import statement -- at module level, inside functions and under
``if TYPE_CHECKING:`` -- of every module of the project's packages. An edge ``a -> b`` means module
``a`` names module ``b`` in an import (``from pkg import name`` counts as ``pkg.name`` when that is
a module, else as ``pkg``). Any strongly connected component of more than one module is a cycle and
fails the test, named module by module.

The layering itself (which package may import which) is checked too: ``producer`` never imports
``workers`` or ``service``; ``service`` imports ``workers`` only from ``service/up.py`` (which
starts worker processes) and ``service/cli.py`` (``ibr worker``, ``ibr render-local``).
"""

from __future__ import annotations

import ast
from collections.abc import Iterable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("api_schemas", "engine", "producer", "workers", "service", "samples")


def _modules() -> dict[str, Path]:
    out: dict[str, Path] = {}
    for pkg in PACKAGES:
        base = ROOT / pkg
        if not base.is_dir():
            continue
        for path in sorted(base.rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def _imported(module: str, path: Path, modules: dict[str, Path]) -> Iterable[str]:
    is_pkg = path.name == "__init__.py"
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_pkg else module.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                yield sub if sub in modules else target


def import_graph() -> dict[str, set[str]]:
    modules = _modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for module, path in modules.items():
        for name in _imported(module, path, modules):
            # the longest project module the name refers to (``a.b.c`` -> ``a.b`` when c is a name)
            parts = name.split(".")
            while parts and ".".join(parts) not in modules:
                parts.pop()
            if parts:
                target = ".".join(parts)
                if target != module:
                    graph[module].add(target)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each as one cycle path."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    comps: list[list[str]] = []
    counter = 0

    def visit(v: str) -> None:
        nonlocal counter
        index[v] = low[v] = counter
        counter += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp: list[str] = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                comps.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return [_cycle_path(graph, set(c)) for c in comps]


def _cycle_path(graph: dict[str, set[str]], comp: set[str]) -> list[str]:
    """One concrete cycle inside a component: a -> b -> ... -> a."""
    start = min(comp)
    prev: dict[str, str] = {}
    frontier = [start]
    while frontier:
        nxt: list[str] = []
        for v in frontier:
            for w in sorted(graph[v] & comp):
                if w == start:
                    path = [v]
                    while path[-1] != start:
                        path.append(prev[path[-1]])
                    return [start, *reversed(path[:-1]), start] if len(path) > 1 else [start, v, start]
                if w not in prev:
                    prev[w] = v
                    nxt.append(w)
        frontier = nxt
    return sorted(comp)


def test_no_import_cycles() -> None:
    found = cycles(import_graph())
    assert not found, "import cycles:\n" + "\n".join(" -> ".join(c) for c in found)


def test_layers() -> None:
    graph = import_graph()
    bad: list[str] = []
    for module, targets in sorted(graph.items()):
        top = module.split(".")[0]
        for t in sorted(targets):
            ttop = t.split(".")[0]
            if top == "producer" and ttop in ("workers", "service"):
                bad.append(f"{module} -> {t}")
            if top == "service" and ttop == "workers" and module not in ("service.up", "service.cli"):
                bad.append(f"{module} -> {t}")
            if top in ("engine", "api_schemas") and ttop in ("producer", "workers", "service"):
                bad.append(f"{module} -> {t}")
    assert not bad, "imports against the layering:\n" + "\n".join(bad)


def test_graph_sees_a_cycle() -> None:
    """The walk itself: a made-up two-module cycle is found and named."""
    graph = {"a.x": {"a.y"}, "a.y": {"a.x", "a.z"}, "a.z": set()}
    assert cycles(graph) == [["a.x", "a.y", "a.x"]]


def test_no_private_names_imported_across_modules() -> None:
    """``from x import _name`` between the modules of producer, workers and service: a private name
    is its module's own business (a shared helper gets a public name in the module that owns it)."""
    modules = _modules()
    bad: list[str] = []
    for module, path in sorted(modules.items()):
        if module.split(".")[0] not in ("producer", "workers", "service"):
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] in PACKAGES:
                bad += [f"{module}: from {node.module} import {a.name}" for a in node.names
                        if a.name.startswith("_") and not a.name.startswith("__")]
    assert not bad, "private names imported across modules:\n" + "\n".join(bad)
