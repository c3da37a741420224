"""Plugins: the systems, cores and trained observers that installed packages declare.

A package registers what it provides once, in its ``pyproject.toml``, as entry points::

    [project.entry-points."manifold_nets.systems"]
    my_robot = "my_package.system"          # a module that defines System subclasses
    [project.entry-points."manifold_nets.cores"]
    my_core = "my_package.cores"            # RecurrentCore subclasses
    [project.entry-points."manifold_nets.zoo"]
    my_robot = "my_package"                 # a package with a zoo/<name>/ folder per observer

When a file names a class that is not registered (:mod:`manifold_nets.registry`), the registry
imports the modules that the installed packages declare in its group, and looks again; a
``zoo:<package>/<name>`` path is ``<package's folder>/zoo/<name>``. What is imported is what an
installed distribution declares, never a module a file names. This project's own examples
declare theirs (``manifold_nets_examples``), so its systems and its zoo need no import by hand.
"""

from __future__ import annotations

import importlib
import warnings
from importlib.metadata import entry_points
from pathlib import Path

__all__ = ["ZOO_PREFIX", "load_plugins", "zoo_entries", "zoo_path", "locate"]

#: A path that starts with this names a zoo entry: ``zoo:rigid_body/nominal``.
ZOO_PREFIX = "zoo:"
_loaded: set[str] = set()


def load_plugins(group: str) -> None:
    """Imports every module the installed packages declare in the entry-point ``group`` (once).
    A module that fails to import is skipped with a warning naming it."""
    if group in _loaded:
        return
    _loaded.add(group)
    for ep in entry_points(group=group):
        try:
            ep.load()
        except Exception as err:  # a broken plugin must not break the others
            warnings.warn(f"the {group} plugin {ep.name!r} ({ep.value}) failed to import: {err}",
                          RuntimeWarning, stacklevel=2)


def _zoo_packages() -> dict[str, str]:
    return {ep.name: ep.value for ep in entry_points(group="manifold_nets.zoo")}


def zoo_entries() -> list[str]:
    """Every installed zoo entry, ``<package>/<name>``, sorted."""
    out = []
    for key, module in _zoo_packages().items():
        folder = _folder(module)
        if folder is not None and (folder / "zoo").is_dir():
            out += [f"{key}/{p.name}" for p in (folder / "zoo").iterdir() if _is_entry(p)]
    return sorted(out)


def _is_entry(path: Path) -> bool:
    """A zoo entry's folder: a run folder (``config.yaml``) or an ensemble folder (``members/``)."""
    return (path / "config.yaml").is_file() or (path / "members").is_dir()


def _folder(module: str) -> Path | None:
    spec = importlib.util.find_spec(module)
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations)))


def zoo_path(name: str) -> Path:
    """The folder of the zoo entry ``name`` (``rigid_body/nominal``); a ``ValueError`` listing
    the installed entries otherwise. Also imports the package, which registers its systems."""
    key, _, entry = str(name).partition("/")
    module = _zoo_packages().get(key)
    folder = _folder(module) if module else None
    path = None if folder is None or not entry else folder / "zoo" / entry
    if path is None or "/" in entry or entry.startswith(".") or not _is_entry(path):
        raise ValueError(
            f"{ZOO_PREFIX}{name} is not an installed zoo entry; the entries are "
            f"{zoo_entries() or 'none (is manifold_nets installed with its examples?)'}."
        )
    importlib.import_module(module)
    load_plugins("manifold_nets.systems")
    return path


def locate(path) -> Path:
    """``path`` as a ``Path``; ``zoo:<package>/<name>`` is the zoo entry's folder."""
    text = str(path)
    if text.startswith(ZOO_PREFIX):
        return zoo_path(text[len(ZOO_PREFIX):])
    return Path(path)
