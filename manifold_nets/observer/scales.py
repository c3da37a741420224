"""Step scales: ``v <- scale(v, k)``, applied in the listed order after the head.

* :class:`OutputScale`: ``v <- s v``. For corrections much smaller than 1 (1e-3 rad a step of a
  35 Hz filter) a small scale keeps the optimiser's steps on the weights in proportion.
* :class:`StepDecay`: ``{factor: K_f}``; those factors' components are scaled by
  ``d_k = min(1, K_f / k)`` at the step from ``x_k``: after ``K_f`` steps their step size falls like
  ``1 / k``, as a Kalman filter's gain on a constant does (for factors the system keeps
  constant or nearly so, such as the rigid body's biases). It adds no weight.
* :class:`Projection`: ``{factor: directions}``; those factors' components are projected onto
  the span of the given tangent directions, so the core can move them only that way (for an
  attitude updated in the world frame, ``{x: [[0, 0, 1]]}``: a heading-only correction, which a
  magnetometer's disturbance cannot turn into a tilt). It adds no weight.

Interface: ``forward(v (B, tangent_dim), d) -> v``, ``d`` the scale's schedule value for the step.
"""

from __future__ import annotations

import torch

from .piece import Piece, check_factor, check_int, check_number

__all__ = ["StepScale", "OutputScale", "StepDecay", "Projection"]


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


class Projection(StepScale):
    """``v_f <- P_f v_f``, ``P_f`` the orthogonal projection onto the span of the directions
    named for factor ``f``; see the module docstring.

    Args:
        factors: ``{factor name: [direction, ...]}``, each direction ``tangent_dim`` numbers in
            the factor's tangent coordinates (the frame its update rule moves it in), linearly
            independent, fewer than ``tangent_dim`` of them.
    """

    name = "projection"

    def __init__(self, factors: dict):
        super().__init__()
        self.factors = {}
        for n, dirs in dict(factors or {}).items():
            try:
                rows = [[float(c) for c in d] for d in dirs]
                a = torch.tensor(rows, dtype=torch.float64)
            except (TypeError, ValueError):
                a = None
            if a is None or a.dim() != 2 or not 0 < a.shape[0] < a.shape[1] \
                    or not torch.isfinite(a).all() or torch.linalg.matrix_rank(a) < a.shape[0]:
                raise ValueError(
                    f"projection: factors[{n!r}] must be a list of linearly independent "
                    f"directions, fewer than the tangent's size (e.g. [[0, 0, 1]]), got {dirs!r}."
                )
            self.factors[str(n)] = rows
        if not self.factors:
            raise ValueError("projection: name at least one factor, e.g. {x: [[0, 0, 1]]}.")

    def settings(self):
        return {"factors": {n: [list(d) for d in dirs] for n, dirs in self.factors.items()}}

    def bind(self, group, measurement):
        n = group.tangent_dim
        P = torch.eye(n, dtype=torch.float64)
        for name, rows in self.factors.items():
            check_factor("projection: factors", group, name)
            cols = group.tangent_slice(name)
            a = torch.tensor(rows, dtype=torch.float64)
            if a.shape[1] != cols.stop - cols.start:
                raise ValueError(f"projection: factors[{name!r}]: each direction must have the "
                                 f"factor's tangent_dim = {cols.stop - cols.start} numbers.")
            P[cols, cols] = a.T @ torch.linalg.solve(a @ a.T, a)
        self.register_buffer("_P", P, persistent=False)
        return self

    def forward(self, v, d=None):
        return v @ self._P.to(v)  # P is symmetric
