"""Registries of the classes a file may name: every imported ``System`` and ``RecurrentCore``.

A run folder or a checkpoint names its system by a ``_target_`` string
(``examples.rigid_body.system.RigidBody``) and its core by ``model.core``. Rebuilding an
observer from a file someone else wrote must not import, let alone call, whatever such a string
names (``_target_: os.system``). So the classes that *may* be named register themselves when
they are defined: :class:`~manifold_nets.system.System` and
:class:`~manifold_nets.cores.RecurrentCore` call :meth:`Registry.add` from their
``__init_subclass__``, and a file's string is only ever looked up here. A class is in a registry
exactly when its module has been imported by the program (the library's own, the shipped
examples a command imports, the user's own modules); the library never imports a module because
a file names it.

Keys are ``f"{cls.__module__}.{cls.__qualname__}"``, the dotted path hydra's ``_target_`` uses.
"""

from __future__ import annotations

__all__ = ["Registry", "UnknownTargetError", "class_path"]


class UnknownTargetError(ValueError):
    """A file names a class that is not registered (not imported, or not of the right kind)."""


def class_path(cls: type) -> str:
    """``module.qualname`` of ``cls``: its key in a registry."""
    return f"{cls.__module__}.{cls.__qualname__}"


class Registry:
    """The subclasses of one base class that have been imported, by :func:`class_path`.

    Args:
        kind: what the classes are (``"System"``), for messages.
        base: the base class's dotted path, for messages (``"manifold_nets.System"``).
        plugins: the entry-point group whose modules are imported on a miss
            (:func:`manifold_nets.plugins.load_plugins`), e.g. ``"manifold_nets.systems"``.
    """

    def __init__(self, kind: str, base: str, plugins: str | None = None):
        self.kind, self.base, self.plugins = kind, base, plugins
        self._classes: dict[str, type] = {}

    def add(self, cls: type) -> type:
        """Registers ``cls`` under its :func:`class_path` (a later definition of the same path,
        e.g. a reloaded module, replaces the earlier one). Returns ``cls``."""
        self._classes[class_path(cls)] = cls
        return cls

    def __contains__(self, path: object) -> bool:
        return path in self._classes

    def names(self) -> list[str]:
        """The registered paths, sorted."""
        return sorted(self._classes)

    def lookup(self, path: object, where: str = "the file") -> type:
        """The registered class of dotted path ``path``; :class:`UnknownTargetError` otherwise.

        ``where`` names the source of ``path`` in the message
        (``"run/config.yaml: system._target_"``).
        Nothing is imported.
        """
        if not isinstance(path, str) or not path:
            raise UnknownTargetError(
                f"{where} must name a {self.kind} class by its dotted path, got {path!r}."
            )
        cls = self._classes.get(path)
        if cls is None and self.plugins:  # what installed packages declare (manifold_nets.plugins)
            from .plugins import load_plugins

            load_plugins(self.plugins)
            cls = self._classes.get(path)
        if cls is None:
            known = ", ".join(self.names()) or "none"
            raise UnknownTargetError(
                f"{where} names {path!r}, which is not a registered {self.kind} (a subclass of "
                f"{self.base} whose module has been imported). If it is yours, import the module "
                f"that defines it first, or declare it as an entry point of your package "
                f"({self.plugins or 'none'}; docs/your_own_project.md); manifold_nets never "
                f"imports a module a file names. "
                f"Registered: {known}."
            )
        return cls
