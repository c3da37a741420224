"""Priors: where the estimate goes before the learned correction, ``x^- = prior(x_k, y, u)``.

The paper has none (:class:`NoPrior`): the core's output moves the estimate alone. With a prior
the core learns what a filter's update adds to the prediction, not the prediction:

* :class:`SystemPrior`: the system's nominal model, ``System.predict(x, y, u)`` (for the rigid
  body the step with the bias-corrected readings);
* :class:`RobustSystemPrior`: the same step taken with each component of the drive weighted by a
  learned M-estimator weight function, ``d_i <- w_i(|d_i|) d_i``, ``d = System.compensated_drive``
  (a reading the motion cannot produce, an outlier, is pulled in before it moves anything);
* :class:`KinematicPrior`: named factors move by a measured velocity, ``x_f <- x_f exp(dt u_f)``
  (a gyroscope's rate), the rest stays.

Interface: ``forward(x (B, numel) state dtype, yu (B, l + m) network dtype, ys (B, l + m) state
dtype) -> x^- (B, numel)``.
"""

from __future__ import annotations


from groups import Euclidean

from .piece import Piece, check_factor, check_int, check_number, check_spans
from .robust import MAX_SIZE, RobustWeights

__all__ = ["Prior", "NoPrior", "SystemPrior", "RobustSystemPrior", "KinematicPrior"]


class Prior(Piece):
    """``forward(x, yu, ys) -> x^-``: see the module docstring."""

    kind = "prior"
    #: Whether ``x^-`` is a prediction of the measurement (a centred head needs one).
    predicts = True


class NoPrior(Prior):
    """The paper's: ``x^- = x_k``."""

    name, predicts = "none", False

    def forward(self, x, yu, ys):
        return x


class SystemPrior(Prior):
    """``x^- = system.predict(x, y, u)``, the system's nominal model (differentiable in ``x``).

    The signature records that there is one (``{type: system}``), not which system.
    """

    name = "system"

    def __init__(self, system):
        super().__init__()
        if not callable(getattr(system, "predict", None)):
            raise TypeError(f"SystemPrior needs a System, got {type(system).__name__}.")
        self.system = system

    def bind(self, group, measurement):
        if repr(self.system.group) != repr(group):
            raise ValueError(
                f"the system prior predicts on {self.system.group!r}, but the observer's group is "
                f"{group!r} (a prior cannot be combined with factors taken off the group)."
            )
        self.l, self.m, self.shape = measurement.dim, measurement.input_dim, group.element_shape
        return self

    def _yu(self, x, ys):
        return x.unflatten(-1, self.shape), ys[:, : self.l], ys[:, self.l :] if self.m else None

    def forward(self, x, yu, ys):
        return self.system.predict(*self._yu(x, ys)).flatten(1)


class RobustSystemPrior(SystemPrior):
    """The system's step with a robustly weighted drive (module docstring).

    Args:
        system: a System whose ``predict`` is the base class's (``step(x, compensated_drive)``).
        width: steps of each learned weight function (>= 1); span: where they start (> 0).
    """

    name = "robust_system"

    def __init__(self, system, width: int = 16, span: float = 4.0):
        super().__init__(system)
        from manifold_nets.system import System

        if type(system).predict is not System.predict:
            raise ValueError(
                f"the robust system prior steps the weighted drive with {type(system).__name__}"
                f".step, but {type(system).__name__} overrides predict, so its prior may not be "
                "step(x, compensated_drive(x, y, u)). Write the prediction's drive in "
                "compensated_drive and leave predict to the base class, or use the plain "
                "system prior."
            )
        width = check_int("robust system prior: width", width, 1, high=MAX_SIZE)
        span = check_number("robust system prior: span", span, 1e-12, 1e12)
        self.robust = RobustWeights(system.drive_dim, width, span)

    def settings(self):
        return {"width": self.robust.width, "span": self.robust.span}

    def forward(self, x, yu, ys):
        x, y, u = self._yu(x, ys)
        d = self.system.compensated_drive(x, y, u)
        w = self.robust(d.abs().to(yu.dtype)).to(d.dtype)  # d_i <- w_i(|d_i|) d_i
        return self.system.step(x, w * d).flatten(1)

    def widen(self, state, prefix, old):
        """From the plain system prior: the weights start as the identity."""
        if old is not None and old.get("type") == self.name:
            return state
        new = RobustWeights(self.robust.channels, self.robust.width, self.robust.span)
        new = new.to(self.robust.amplitude)
        return {**state, **{f"{prefix}robust.{k}": v for k, v in new.state_dict().items()}}


class KinematicPrior(Prior):
    """``x_f <- x_f exp(dt u_f)`` for each named factor, ``u_f = (y, u)[start:stop]``.

    Args:
        velocities: ``{factor name: (start, stop)}``, the span of ``(y, u)`` holding the
            factor's velocity (``tangent_dim`` entries).
        dt: the step length in seconds (> 0).
    """

    name = "kinematic"

    def __init__(self, velocities: dict, dt: float):
        super().__init__()
        self.velocities = check_spans("kinematic prior: velocities", velocities, "(y, u)")
        if not self.velocities:
            raise ValueError("kinematic prior: name at least one factor's velocity span.")
        self.dt = check_number(
            "kinematic prior: dt", dt, 1e-12, 1e6, " (the step length in seconds, e.g. "
            "1/285.714 for a 285.714 Hz IMU)",
        )

    def bind(self, group, measurement):
        width = measurement.dim + measurement.input_dim
        self._moves = []
        for fname, (a, b) in self.velocities.items():
            check_factor("kinematic prior: velocities", group, fname)
            f = group.factor(fname)
            if not (0 <= a and b <= width and b - a == f.tangent_dim):
                raise ValueError(
                    f"kinematic prior: velocities[{fname!r}] = ({a}, {b}) must be a span of "
                    f"(y, u) (size {width}) of the factor's tangent_dim = {f.tangent_dim} entries."
                )
            self._moves.append((f, group.element_slice(fname), slice(a, b)))
        return self

    def settings(self):
        return {"velocities": {k: list(v) for k, v in self.velocities.items()}, "dt": self.dt}

    def forward(self, x, yu, ys):
        x = x.clone()
        for f, xs, cols in self._moves:
            w = yu[:, cols].to(x.dtype) * self.dt
            shape = f.element_shape
            if isinstance(f, Euclidean):
                x[:, xs] = x[:, xs] + w
            else:
                new = f.rplus(x[:, xs].unflatten(-1, shape), w)
                x[:, xs] = new.flatten(-len(shape)) if len(shape) > 1 else new
        return x


