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
* ``rotated = {"R": [(0, 3), (3, 6)]}``: spans of ``(y, u)`` (the measurement, then the input)
  holding body-frame 3-vectors (an accelerometer's, a magnetometer's reading) of a rotation
  factor ``R`` (SO(3): a ``(3, 3)`` element); the core also reads each rotated into the world
  frame by the estimate, ``Rhat v``. A vector a classical filter compares with a known world
  direction (gravity, north) is then an input the network can compare linearly, where
  ``(vec Rhat, v)`` would need a product.
* ``propagate = {"R": (6, 9)}`` with ``dt``: a kinematic prior. Before the learned update, each
  named factor moves by the velocity it is driven with, read from that span of ``(y, u)`` (a
  gyroscope's rate, a body-frame twist): ``x_f <- x_f · exp(dt · u[start:stop])``, exact for
  group kinematics ``dx/dt = x · (omega)^`` with ``omega`` held over the step. The core then
  reads that prediction (its embedding, the innovation and rotated vectors there) and its
  output corrects it: the network learns what the filter adds to integration, not integration.
* ``clock = (10, 100, 1000)``: time constants in steps; the core also reads
  ``tau / (tau + k)`` for each, ``k`` the steps taken from the start (1 at the first step, 1/2
  at ``k = tau``). A Kalman filter's gain on a constant (a bias) falls like ``1 / k`` as its
  covariance shrinks; a recurrent core without a clock has to count the steps in its state,
  and with a bounded state it tends to a constant gain, whose error stops falling.
* ``innovation_frame = {"p": "R"}``: the core also reads a vector factor's innovation (a
  Euclidean 3-vector with an innovation span) in the frame of a rotation factor's estimate,
  ``Rhat^T (p^m - phat)``. The rigid body's velocity bias enters the position through ``R``
  (``p+ = p + dt R (v^m - b_v)``): a bias error shows as a world-frame innovation
  ``-dt R db_v``, which the core would need a product of ``vec Rhat`` and the innovation to map
  back; in the body frame it is linear. Appended after the clock, so ``train.init_from``
  widens an observer without it (zero weights).
* ``prior_drive = 6``: with a model prior, the core also reads the drive the prior integrated,
  ``System.compensated_drive(xhat_k, y_{k+1}, u_k)`` (the rigid body's bias-corrected readings
  ``(Omega^m - bhat_Omega, v^m - bhat_v)``), that many entries. A reading far outside what the
  motion can do (an outlier) is then a plain input, where from ``y`` and ``embed(xhat)`` the
  network would first have to learn the difference of two large numbers. Appended last;
  ``train.init_from`` widens an observer without it (zero weights).

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
        rotated: ``{factor name: [(start, stop), ...]}``, body-frame 3-vectors in ``(y, u)``
            the core also reads rotated to the world frame by that (SO(3)) factor's estimate.
        propagate: ``{factor name: (start, stop)}``, the span of ``(y, u)`` holding the
            factor's velocity (tangent_dim entries) for the kinematic prior.
        dt: the step length that scales ``propagate``'s velocities (seconds; needed with it).
        clock: time constants ``tau`` (steps, each > 0); the core reads ``tau / (tau + k)``.
        innovation_frame: ``{vector factor: rotation factor}``; the core also reads the vector
            factor's innovation rotated into the rotation factor's estimated frame.
        prior_drive: the width of the model prior's compensated drive the core also reads
            (the system's ``drive_dim``; 0: none). The observer computes it with the callable
            it is given (``ResidualObserver(prior_drive=system.compensated_drive)``).
    """

    innovation: Mapping[str, tuple[int, int]] = field(default_factory=dict)
    relative_only: tuple[str, ...] = ()
    rotated: Mapping[str, tuple[tuple[int, int], ...]] = field(default_factory=dict)
    propagate: Mapping[str, tuple[int, int]] = field(default_factory=dict)
    dt: float | None = None
    clock: tuple[float, ...] = ()
    innovation_frame: Mapping[str, str] = field(default_factory=dict)
    prior_drive: int = 0

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
        rotated = {}
        for name, many in dict(self.rotated or {}).items():
            if isinstance(many, (str, bytes)) or not hasattr(many, "__iter__"):
                raise ValueError(
                    f"rotated[{name!r}] must be a list of (start, stop) spans, got {many!r}."
                )
            rotated[str(name)] = tuple(_span(f"rotated[{name!r}]", span) for span in many)
        object.__setattr__(self, "rotated", rotated)
        propagate = {
            str(name): _span(f"propagate[{name!r}]", span)
            for name, span in dict(self.propagate or {}).items()
        }
        object.__setattr__(self, "propagate", propagate)
        if propagate:
            dt = self.dt
            if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not 0 < dt < 1e6:
                raise ValueError(
                    f"propagate needs dt, the step length in seconds (a positive number), got "
                    f"{dt!r}; the system's dt, e.g. 1/285.714 for a 285.714 Hz IMU."
                )
            object.__setattr__(self, "dt", float(dt))
        object.__setattr__(self, "clock", _clock(self.clock))
        frames = dict(self.innovation_frame or {})
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in frames.items()):
            raise ValueError(
                f"innovation_frame must map factor names to factor names, e.g. {{'p': 'R'}}, "
                f"got {frames!r}."
            )
        object.__setattr__(self, "innovation_frame", frames)
        width = self.prior_drive
        if isinstance(width, bool) or not isinstance(width, int) or width < 0:
            raise ValueError(
                f"prior_drive must be the width of the prior's drive (an integer >= 0, the "
                f"system's drive_dim; 0: none), got {width!r}."
            )

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
        self._check_frames(group)
        return self

    def _check_frames(self, group: LieGroup) -> None:
        names = group.factor_names
        for vec, rot in self.innovation_frame.items():
            for name in (vec, rot):
                if name not in names:
                    raise ValueError(
                        f"innovation_frame names a factor {name!r} that {group!r} does not "
                        f"have; its factors are {list(names)}."
                    )
            if vec not in self.innovation or group.factor(vec).tangent_dim != 3:
                raise ValueError(
                    f"innovation_frame[{vec!r}]: {vec!r} must be a 3-vector factor with an "
                    f"innovation span (innovation: {{{vec}: [start, stop]}}), got "
                    f"{group.factor(vec)!r}."
                )
            if tuple(group.factor(rot).element_shape) != (3, 3):
                raise ValueError(
                    f"innovation_frame[{vec!r}] = {rot!r} must be a rotation of R^3 (SO(3)), got "
                    f"{group.factor(rot)!r}."
                )

    def _check_extras(self, group: LieGroup, context_dim: int) -> None:
        """``rotated`` and ``propagate`` against the group and the ``(y, u)`` width."""
        names = group.factor_names
        for kind, table in (("rotated", self.rotated), ("propagate", self.propagate)):
            for name in table:
                if name not in names:
                    raise ValueError(
                        f"{kind} names a factor {name!r} that {group!r} does not have; its "
                        f"factors are {list(names)}."
                    )
        for name, spans in self.rotated.items():
            if tuple(group.factor(name).element_shape) != (3, 3):
                raise ValueError(
                    f"rotated[{name!r}]: the factor must be a rotation of R^3 (elements (3, 3), "
                    f"SO(3)), got {group.factor(name)!r}."
                )
            for a, b in spans:
                if not (0 <= a and b <= context_dim and b - a == 3):
                    raise ValueError(
                        f"rotated[{name!r}] span ({a}, {b}) must be 3 entries of (y, u) (size "
                        f"{context_dim}): a body-frame 3-vector."
                    )
        for name, (a, b) in self.propagate.items():
            dim = group.factor(name).tangent_dim
            if not (0 <= a and b <= context_dim and b - a == dim):
                raise ValueError(
                    f"propagate[{name!r}] = ({a}, {b}) must be a span of (y, u) (size "
                    f"{context_dim}) of the factor's tangent_dim = {dim} entries: its velocity."
                )

    def extra_columns(self) -> list[int]:
        """The columns of ``(y, u)`` the observer reads raw besides the core's context: the
        ``propagate`` spans (in factor order of the table), then the ``rotated`` spans."""
        cols: list[int] = []
        for a, b in self.propagate.values():
            cols.extend(range(a, b))
        for spans in self.rotated.values():
            for a, b in spans:
                cols.extend(range(a, b))
        return cols

    def rotated_dim(self) -> int:
        """The width of the rotated vectors the core reads: 3 per span."""
        return 3 * sum(len(spans) for spans in self.rotated.values())

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
        self._check_extras(group, measurement_dim + input_dim)
        emb, ctx = self.kept_columns(group, measurement_dim + input_dim)
        return (
            (group.embedding_dim if emb is None else len(emb))
            + (measurement_dim + input_dim if ctx is None else len(ctx))
            + self.innovation_dim(group)
            + self.rotated_dim()
            + len(self.clock)
            + 3 * len(self.innovation_frame)
            + self.prior_drive
        )

    def clock_features(self, k: torch.Tensor) -> torch.Tensor:
        """``tau / (tau + k)`` for each time constant: ``(..., len(clock))`` for the step counts
        ``k`` (a tensor of any shape, in the dtype the features should have)."""
        tau = torch.tensor(self.clock, dtype=k.dtype, device=k.device)
        return tau / (tau + k.unsqueeze(-1))

    def signature(self) -> dict:
        """JSON-able description, part of the observer's checkpoint signature."""
        out = {
            "innovation": {k: list(v) for k, v in self.innovation.items()},
            "relative_only": list(self.relative_only),
        }
        if self.rotated or self.propagate:  # absent keys: the signature of older checkpoints
            out["rotated"] = {k: [list(s) for s in v] for k, v in self.rotated.items()}
            out["propagate"] = {k: list(v) for k, v in self.propagate.items()}
            out["dt"] = self.dt
        if self.clock:  # absent when empty, likewise
            out["clock"] = list(self.clock)
        if self.innovation_frame:
            out["innovation_frame"] = dict(self.innovation_frame)
        if self.prior_drive:
            out["prior_drive"] = self.prior_drive
        return out

    def appended(self) -> list[tuple[str, object, int]]:
        """The inputs the core reads last, in order, with their signature values and widths:
        ``("clock", [tau..], n)``, ``("innovation_frame", {vec: rot}, 3 n)`` and
        ``("prior_drive", n, n)`` when set."""
        out: list[tuple[str, object, int]] = []
        if self.clock:
            out.append(("clock", list(self.clock), len(self.clock)))
        if self.innovation_frame:
            frames = dict(self.innovation_frame)
            out.append(("innovation_frame", frames, 3 * len(frames)))
        if self.prior_drive:
            out.append(("prior_drive", self.prior_drive, self.prior_drive))
        return out


def _span(what: str, span) -> tuple[int, int]:
    try:
        a, b = (int(i) for i in span)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be (start, stop) in (y, u), got {span!r}.") from None
    return a, b


def _clock(taus) -> tuple[float, ...]:
    if isinstance(taus, (str, bytes)) or not hasattr(taus, "__iter__"):
        raise ValueError(
            f"clock must be a list of time constants in steps, e.g. [10, 100, 1000], got {taus!r}."
        )
    out = []
    for tau in taus:
        if isinstance(tau, bool) or not isinstance(tau, (int, float)) or not 0 < tau < 1e12:
            raise ValueError(
                f"clock: each time constant must be a positive number of steps, got {tau!r} "
                f"in {list(taus)!r}."
            )
        out.append(float(tau))
    return tuple(out)
