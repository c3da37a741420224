"""The package's shape: dependencies point one way, the index is complete, functions stay short.

``examples -> manifold_nets -> groups``, and inside ``manifold_nets`` the commands (``cli``) sit
above the library: no library module and no example imports a command, ``groups`` imports
neither ``manifold_nets`` nor the examples (the folder ``examples/``, imported as
``manifold_nets_examples``). Read from the source (``ast``), nothing is run.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import groups
import manifold_nets

ROOT = Path(__file__).resolve().parents[1]


def _modules(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


def _imports(path: Path) -> set[str]:
    """Absolute names of the modules ``path`` imports (relative imports resolved)."""
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
    if path.name == "__init__.py":
        package = ".".join(path.relative_to(ROOT).parts[:-1])
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            out.add(name)
            out.update(f"{name}.{alias.name}" for alias in node.names)
    return out


def _offending(folder: str, forbidden: tuple[str, ...], skip: str | None = None) -> list[str]:
    bad = []
    for path in _modules(folder):
        rel = path.relative_to(ROOT).as_posix()
        if skip and rel.startswith(skip):
            continue
        hits = sorted(
            name for name in _imports(path)
            if any(name == f or name.startswith(f + ".") for f in forbidden)
        )
        bad += [f"{rel} imports {name}" for name in hits]
    return bad


def test_groups_import_neither_the_learning_library_nor_the_examples():
    assert _offending("groups", ("manifold_nets", "manifold_nets_examples")) == []


def test_the_library_imports_no_command_and_no_example():
    forbidden = ("manifold_nets.cli", "manifold_nets_examples")
    assert _offending("manifold_nets", forbidden, skip="manifold_nets/cli") == []


def test_examples_import_no_command():
    assert _offending("examples", ("manifold_nets.cli",)) == []


@pytest.mark.parametrize("package", [groups, manifold_nets], ids=["groups", "manifold_nets"])
def test_the_index_exports_what_it_lists(package):
    assert package.__all__, "an index with nothing in it"
    for name in package.__all__:
        assert getattr(package, name, None) is not None, f"{package.__name__}.{name} is missing"
        assert not name.startswith("_")


@pytest.mark.parametrize("folder", ["groups", "manifold_nets"])
def test_no_function_is_longer_than_80_lines(folder):
    long = []
    for path in _modules(folder):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > 80:
                    long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({length})")
    assert long == []
