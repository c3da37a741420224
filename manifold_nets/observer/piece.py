"""What every piece of the observer shares: its kind, its config name, its checks and signature.

A piece is a small ``nn.Module`` of one *kind* (``prior``, ``measurement``, ``feature``, ``head``,
``scale``) with one interface per kind (see those modules). A concrete piece class with a
``name`` registers itself in :data:`PIECES` under ``(kind, name)``: that is what a model config
may name (``{type: centred, c: 0.85}``), and nothing else; a file never makes the library import
or call anything it names. Each piece

* checks its own arguments in ``__init__`` and, in :meth:`Piece.bind`, against the group and the
  measurement it is bound to (one place, one message);
* describes itself in :meth:`Piece.signature` (what a checkpoint must match);
* may depend on the step count through :meth:`Piece.schedule`, computed once per rollout from a
  float64 tensor of step counts (the one schedule computation of the rollout, the online step
  and the exported step);
* may say how it widens an older checkpoint that lacked it (``train.init_from``):
  :meth:`Piece.widen` (default: it adds no weight, nothing to do).
"""

from __future__ import annotations

from typing import Any, ClassVar

import torch
from torch import nn

__all__ = [
    "PIECES", "Piece", "piece_class", "check_number", "check_int", "check_spans",
    "check_factor",
]

#: Every registered piece class by ``(kind, name)``.
PIECES: dict[tuple[str, str], type[Piece]] = {}


class Piece(nn.Module):
    """The base of every piece; see the module docstring."""

    kind: ClassVar[str] = ""
    #: The name a config gives (``type:``); empty for an abstract class.
    name: ClassVar[str] = ""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        # only a class that names itself: not a subclass that inherits the name (torch.export's
        # tracer subclasses a module it reaches by two paths; it must not replace the piece)
        if cls.__dict__.get("name"):
            PIECES[(cls.kind, cls.name)] = cls

    def bind(self, group, measurement) -> Piece:  # noqa: ARG002
        """Checks the piece against the state's group and the bound measurement; sets what it
        needs to know of them. Returns ``self``."""
        return self

    def settings(self) -> dict[str, Any]:
        """The piece's arguments, JSON-able (its config block without ``type``)."""
        return {}

    def signature(self) -> dict[str, Any]:
        """What a checkpoint must match: the type and the settings."""
        return {"type": self.name, **self.settings()}

    def schedule(self, k: torch.Tensor) -> torch.Tensor | None:  # noqa: ARG002
        """The piece's per-step values for the float64 step counts ``k`` ``(T,)`` (``(T, ...)``,
        float64), or ``None`` when it does not depend on the step count."""
        return None

    def widen(self, state: dict, prefix: str, old: dict | None) -> dict:  # noqa: ARG002
        """A ``state_dict`` for an observer with this piece from one whose signature had
        ``old`` in its place (``None``: no such piece). Default: the piece adds no weight."""
        return state

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={v!r}" for k, v in self.settings().items())


def piece_class(kind: str, name: object, where: str) -> type[Piece]:
    """The registered piece class of ``kind`` called ``name``; a ``ValueError`` naming ``where``
    and the registered names otherwise (nothing is imported)."""
    cls = PIECES.get((kind, name)) if isinstance(name, str) else None
    if cls is None:
        known = sorted(n for k, n in PIECES if k == kind)
        raise ValueError(f"{where}: {name!r} is not a {kind} piece; the {kind}s are {known}.")
    return cls


def check_number(owner: str, value: object, low: float, high: float, what: str = "") -> float:
    """``value`` as a float, or a ``ValueError`` naming ``owner`` unless ``low <= value <= high``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not low <= value <= high:
        raise ValueError(f"{owner} must be a number in [{low:g}, {high:g}]{what}, got {value!r}.")
    return float(value)


def check_int(owner: str, value: object, low: int, what: str = "", high: int | None = None) -> int:
    """``value``, or a ``ValueError`` naming ``owner`` unless it is an integer ``>= low`` (and
    ``<= high``, when given)."""
    if isinstance(value, bool) or not isinstance(value, int) or value < low or (
        high is not None and value > high
    ):
        bound = f">= {low}" if high is None else f"in {low} .. {high}"
        raise ValueError(f"{owner} must be an integer {bound}{what}, got {value!r}.")
    return value


def check_spans(label: str, table, within: str) -> dict[str, tuple[int, int]]:
    """``{name: (start, stop)}`` from a mapping of spans, or a ``ValueError`` naming
    ``label[name]`` and what the span is of (``within``: ``"y"``, ``"(y, u)"``)."""
    out = {}
    for name, span in dict(table or {}).items():
        try:
            a, b = (int(i) for i in span)
        except (TypeError, ValueError):
            raise ValueError(
                f"{label}[{name!r}] must be (start, stop) in {within}, got {span!r}."
            ) from None
        out[str(name)] = (a, b)
    return out


def check_factor(owner: str, group, name: str) -> None:
    """A ``ValueError`` naming ``owner`` unless ``group`` has a factor ``name``."""
    if name not in group.factor_names:
        raise ValueError(
            f"{owner} names a factor {name!r} that {group!r} does not have; its factors are "
            f"{list(group.factor_names)}."
        )
