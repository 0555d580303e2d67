"""The ``ibr-client`` distribution ships what its modules import, and nothing of the engine's kernels.

A static walk (``ast``) of every import statement of every module clients/python/pyproject.toml
packs (its ``packages`` and ``py-modules``, from the repository's directories): each import of a
project package must name a module the distribution packs, and no third-party import may go
beyond the dependencies it declares. Fast; the slow test_client_distribution.py installs it."""

from __future__ import annotations

import ast
import sys
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PYPROJECT = REPO / "clients" / "python" / "pyproject.toml"
PROJECT_PACKAGES = {"api_schemas", "engine", "ibr_client", "producer", "samples", "service", "workers", "bench"}
# what the declared dependencies provide to import (httpx, pydantic, typer, rich, numpy, and theirs)
DECLARED_IMPORTS = {"httpx", "pydantic", "pydantic_core", "typer", "rich", "numpy", "click"}


def _shipped() -> dict[str, Path]:
    conf = tomllib.loads(PYPROJECT.read_text())["tool"]["setuptools"]
    root = (PYPROJECT.parent / conf["package-dir"][""]).resolve()
    assert root == REPO
    out: dict[str, Path] = {}
    for pkg in conf["packages"]:
        base = root.joinpath(*pkg.split("."))
        out[pkg] = base / "__init__.py"
        for path in base.glob("*.py"):
            if path.name != "__init__.py":
                out[f"{pkg}.{path.stem}"] = path
    for mod in conf["py-modules"]:
        parts = mod.split(".")
        out[mod] = root.joinpath(*parts).with_suffix(".py")
        if (root / parts[0] / "__init__.py").exists():
            out[parts[0]] = root / parts[0] / "__init__.py"
    return out


def _imports(node: ast.AST) -> set[str]:
    """Every name an import under ``node`` reads: ``import a.b`` -> a.b; ``from a import b`` -> a, a.b."""
    names: set[str] = set()
    for sub in ast.walk(node):
        if isinstance(sub, ast.Import):
            names |= {a.name for a in sub.names}
        elif isinstance(sub, ast.ImportFrom) and sub.level == 0 and sub.module:
            names.add(sub.module)
            names |= {f"{sub.module}.{a.name}" for a in sub.names}
    return names


def _is_module(name: str) -> bool:
    path = REPO.joinpath(*name.split("."))
    return path.with_suffix(".py").exists() or (path / "__init__.py").exists()


def test_the_client_distribution_packs_every_module_it_imports() -> None:
    shipped = _shipped()
    assert {"ibr_client.cli", "ibr_client.client", "api_schemas.service", "engine.methods"} <= set(shipped)
    missing: list[str] = []
    foreign: list[str] = []
    for module, path in sorted(shipped.items()):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        never_run = {n for node in ast.walk(tree)  # ``if TYPE_CHECKING:`` imports
                     if isinstance(node, ast.If) and getattr(node.test, "id", "") == "TYPE_CHECKING"
                     for n in _imports(node)}
        for name in sorted(_imports(tree) - never_run):
            top = name.split(".")[0]
            if top in PROJECT_PACKAGES:
                # a module must be packed; a name from a module (``from a.b import C``), its module
                if (name not in shipped and _is_module(name)) or (
                        not _is_module(name) and name.rsplit(".", 1)[0] not in shipped):
                    missing.append(f"{module}: {name}")
            elif top not in sys.stdlib_module_names and top not in DECLARED_IMPORTS and top != "__future__":
                foreign.append(f"{module}: {name}")
    assert not missing, "imports the client distribution does not pack:\n" + "\n".join(missing)
    assert not foreign, "imports of undeclared dependencies:\n" + "\n".join(foreign)
