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


def _runtime_imports(path: Path) -> set[str]:
    """:func:`_imports` less those under ``if TYPE_CHECKING:`` (not imports at run time)."""
    tree = ast.parse(path.read_text())
    typing_only = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            typing_only.update(id(n) for n in ast.walk(node))
    keep = [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))
            and id(n) not in typing_only]
    module = ast.Module(body=keep, type_ignores=[])
    tmp = path.with_name(path.name)  # the same package for relative imports
    out = set()
    for node in module.body:
        single = ast.Module(body=[node], type_ignores=[])
        out |= _imports_of(tmp, single)
    return out


def _imports_of(path: Path, tree: ast.Module) -> set[str]:
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
    if path.name == "__init__.py":
        package = ".".join(path.relative_to(ROOT).parts[:-1])
    out = set()
    for node in tree.body:
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")[: len(package.split(".")) - node.level + 1] if node.level else []
            name = ".".join(base + ([node.module] if node.module else []))
            out.add(name)
            out.update(f"{name}.{alias.name}" for alias in node.names)
    return out


def test_the_library_has_no_import_cycle():
    """Module by module (a package is its ``__init__``), every import at run time, lazy ones
    too: ``cli.train`` and ``cli.evaluate`` share ``cli.tasks``, the observer knows neither the
    checkpoint format nor deployment."""
    modules = {}
    for path in _modules("manifold_nets"):
        parts = path.relative_to(ROOT).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        modules[name] = path
    graph = {
        name: {m for m in _runtime_imports(path) if m in modules and m != name
               and not name.startswith(m + ".")}  # a module's own package __init__ runs first
        for name, path in modules.items()
    }
    cycles = []

    def visit(node, stack, seen):
        for nxt in graph[node]:
            if nxt in stack:
                cycles.append(" -> ".join(stack[stack.index(nxt):] + [nxt]))
            elif nxt not in seen:
                seen.add(nxt)
                visit(nxt, [*stack, nxt], seen)

    for start in graph:
        visit(start, [start], {start})
    assert not cycles, sorted(set(cycles))[:10]


@pytest.mark.parametrize("folder", ["groups", "manifold_nets", "examples"])
def test_no_module_is_longer_than_500_lines(folder):
    long = [f"{p.relative_to(ROOT)} ({n})" for p in _modules(folder)
            if (n := len(p.read_text().splitlines())) > 500]
    assert long == []


def test_the_observer_is_one_short_class():
    import inspect

    from manifold_nets.observer import ResidualObserver, observer

    params = [p for p in inspect.signature(ResidualObserver.__init__).parameters if p != "self"]
    assert len(params) <= 8, params
    assert len(inspect.getsource(observer).splitlines()) <= 300
