"""What the core reads besides the paper's inputs: innovation terms and relative-only factors.

The paper's core reads ``(embed(xhat_k), y_{k+1}, u_k)``. :class:`ObserverInputs` describes two
optional extensions (both off by default):

* ``innovation = {"R": (0, 9), "p": (9, 12)}``: the measurement holds the embedding of some
  factors directly (the rigid body's ``y`` starts with ``vec R^m`` and ``p^m``); for each named
  factor ``f`` the core also reads the tangent vector ``rminus(m_f, xhat_f) = log(xhat_f^-1 m_f)``
  from the estimate to the measured factor ``m_f = unembed(y[start:stop])``: the innovation of a
  classical observer, which turns the nonlinear comparison of two embedded elements into an
  input the network can use linearly.
* ``relative_only = ("p",)``: those factors' absolute estimate and measurement are left out of
  the core's input, so the core sees them only through their innovation ``p^m - phat`` (each
  needs an innovation span). For the rigid body, whose motion does not depend on where it is,
  the observer is then invariant to translations of the whole trajectory.

The object is plain data; :meth:`ObserverInputs.check` validates it against a group and a
measurement size, :meth:`ObserverInputs.core_input_size` says how wide the core's input is, and
:meth:`ObserverInputs.kept_columns` which columns of ``embed(xhat)`` and ``(y, u)`` it reads.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import torch

from groups import LieGroup

__all__ = ["ObserverInputs"]


@dataclass(frozen=True)
class ObserverInputs:
    """The optional inputs of the core (see the module docstring); the default is the paper's.

    Args:
        innovation: ``{factor name: (start, stop)}``, ``y[..., start:stop]`` the measured
            embedding of that factor.
        relative_only: factor names (each with an innovation span) the core reads only through
            their innovation.
    """

    innovation: Mapping[str, tuple[int, int]] = field(default_factory=dict)
    relative_only: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        spans = {}
        for name, span in dict(self.innovation or {}).items():
            try:
                a, b = (int(i) for i in span)
            except (TypeError, ValueError):
                raise ValueError(
                    f"innovation[{name!r}] must be (start, stop) in y, got {span!r}."
                ) from None
            spans[str(name)] = (a, b)
        object.__setattr__(self, "innovation", spans)
        object.__setattr__(self, "relative_only", tuple(self.relative_only or ()))

    def check(self, group: LieGroup, measurement_dim: int) -> ObserverInputs:
        """Raises ``ValueError`` naming the problem unless every factor exists in ``group``, every
        span is a slice of ``y`` as long as its factor's embedding, and every relative-only
        factor has a span. Returns ``self``."""
        names = group.factor_names
        for name, (a, b) in self.innovation.items():
            if name not in names:
                raise ValueError(
                    f"innovation names a factor {name!r} that {group!r} does not have; its "
                    f"factors are {list(names)}."
                )
            dim = group.factor(name).embedding_dim
            if not (0 <= a < b <= measurement_dim and b - a == dim):
                raise ValueError(
                    f"innovation[{name!r}] = ({a}, {b}) must be a span of y (size "
                    f"{measurement_dim}) of the factor's embedding_dim = {dim} entries."
                )
        for name in self.relative_only:
            if name not in names:
                raise ValueError(
                    f"relative_only names a factor {name!r} that {group!r} does not have; its "
                    f"factors are {list(names)}."
                )
            if name not in self.innovation:
                raise ValueError(
                    f"relative_only factor {name!r} has no innovation span: the core would not "
                    "see it at all. Add it to innovation ({name: [start, stop]} in y) or drop it."
                )
        return self

    def innovation_dim(self, group: LieGroup) -> int:
        """The width of the innovation terms: the named factors' tangent dimensions."""
        return sum(group.factor(name).tangent_dim for name in self.innovation)

    def kept_columns(
        self, group: LieGroup, context_dim: int
    ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """Index tensors of the columns of ``embed(xhat)`` and of ``(y, u)`` (``context_dim``
        wide) that the core reads; ``None`` for all of them (no relative-only factor)."""
        if not self.relative_only:
            return None, None
        emb = torch.ones(group.embedding_dim, dtype=torch.bool)
        ctx = torch.ones(context_dim, dtype=torch.bool)
        for name in self.relative_only:
            emb[group.embedding_slice(name)] = False
            a, b = self.innovation[name]
            ctx[a:b] = False
        return emb.nonzero().flatten(), ctx.nonzero().flatten()

    def core_input_size(self, group: LieGroup, measurement_dim: int, input_dim: int = 0) -> int:
        """What the core reads per step: ``embed(xhat)``, ``y`` and ``u`` less the relative-only
        columns, plus the innovation terms. Checks the inputs against the group first."""
        self.check(group, measurement_dim)
        emb, ctx = self.kept_columns(group, measurement_dim + input_dim)
        return (
            (group.embedding_dim if emb is None else len(emb))
            + (measurement_dim + input_dim if ctx is None else len(ctx))
            + self.innovation_dim(group)
        )

    def signature(self) -> dict:
        """JSON-able description, part of the observer's checkpoint signature."""
        return {
            "innovation": {k: list(v) for k, v in self.innovation.items()},
            "relative_only": list(self.relative_only),
        }
