"""Step scales: ``v <- scale(v, k)``, applied in the listed order after the head.

* :class:`OutputScale`: ``v <- s v``. For corrections much smaller than 1 (1e-3 rad a step of a
  35 Hz filter) a small scale keeps the optimiser's steps on the weights in proportion.
* :class:`StepDecay`: ``{factor: K_f}``; those factors' components are scaled by
  ``d_k = min(1, K_f / k)`` at the step from ``x_k``: after ``K_f`` steps their step size falls like
  ``1 / k``, as a Kalman filter's gain on a constant does (for factors the system keeps
  constant or nearly so, such as the rigid body's biases). It adds no weight.

Interface: ``forward(v (B, tangent_dim), d) -> v``, ``d`` the scale's schedule value for the step.
"""

from __future__ import annotations

from .piece import Piece, check_factor, check_int, check_number

__all__ = ["StepScale", "OutputScale", "StepDecay"]


class StepScale(Piece):
    """See the module docstring."""

    kind = "scale"


class OutputScale(StepScale):
    """``v <- s v``, ``s > 0``. (``train.init_from`` from another scale rescales the head's output
    rows, :mod:`~manifold_nets.observer.widen`.)"""

    name = "output"

    def __init__(self, scale: float):
        super().__init__()
        self.scale = check_number("output scale", scale, 1e-30, 1e30, " (> 0)")

    def settings(self):
        return {"scale": self.scale}

    def forward(self, v, d=None):
        return v * self.scale


class StepDecay(StepScale):
    """``v_f <- min(1, K_f / k) v_f`` for the named factors; see the module docstring.

    Args:
        factors: ``{factor name: K_f}``, each an integer >= 1 (steps).
    """

    name = "step_decay"

    def __init__(self, factors: dict):
        super().__init__()
        self.factors = {
            str(n): check_int(f"step decay: factors[{n!r}]", k, 1, " (steps before the factor's "
                              "step size starts to fall like K / k)")
            for n, k in dict(factors or {}).items()
        }
        if not self.factors:
            raise ValueError("step decay: name at least one factor, e.g. {b_omega: 50}.")

    def settings(self):
        return {"factors": dict(self.factors)}

    def bind(self, group, measurement):
        for n in self.factors:
            check_factor("step decay: factors", group, n)
        self._columns = [(group.tangent_slice(n), k) for n, k in self.factors.items()]
        self.n = group.tangent_dim
        return self

    def schedule(self, k):
        d = k.new_ones((*k.shape, self.n))
        for cols, big_k in self._columns:
            d[..., cols] = (big_k / k.clamp(min=1)).clamp(max=1.0)[..., None]
        return d

    def forward(self, v, d=None):
        return v * d
