"""The planar vehicle's error-state EKF: the filter model, and the filter started from the fixes.

**The model** (:class:`PlanarFilterModel`). The filter's state is the system's own, on its group
(5-dimensional error): with ``pose_group="se2"`` the right error ``T = That exp(e_T)``, a
body-frame ``(rho_x, rho_y, theta)``; with ``"so2_r2"`` ``(theta, dp_x, dp_y)``, the position
error in the world frame; and ``b = bhat + db``. The filter knows the
motion only through the odometry of ``y_{k+1}``, so for the filter::

    drive    (v, omega) = (v^m - b_v - n2, omega^m - b_omega - n3)     process noise (n2, n3)
    step     the system's exact unicycle step; the biases are constant states
    update   the fix p + n1 from the system's ``measure``, compared by plain difference

The odometry serves the prediction only. Jacobians by autograd.

**The estimator** (:class:`PlanarEKF`). The heading is not measured, and an EKF started with an
unknown heading (a std of ``pi / sqrt 3``) linearises a position update through a heading that
may be off by pi. So it starts at step ``init_steps`` (default 5) from the fixes: the position
of fix ``m``, the heading of the chord from fix 1 to fix ``m`` (the vehicle drives forward),
zero biases; with standard deviations ``s_p sigma`` for the position, for the heading
``sqrt(2) s_p sigma / |chord|`` (the chord's direction noise) plus 0.2 rad (the turn while the
chord was driven), and the biases' ``range / sqrt(3)``. The estimates of steps ``1 .. m-1``
are the raw fix (:meth:`Planar.state_from_measurement`), inside the 10 steps the tables skip.
"""

from __future__ import annotations

import math

import torch

from manifold_nets.data import TrajectoryDataset
from manifold_nets.ekf import BiasedReadingsFilterModel, ErrorStateEKF

from .system import Planar

__all__ = ["PlanarEKF", "PlanarFilterModel"]


class PlanarFilterModel(BiasedReadingsFilterModel):
    """The planar vehicle as an error-state EKF sees it; see the module docstring.

    ``sigma`` is the noise level of the data (the true one: this EKF knows the model).
    """

    system_type = Planar
    process_noise_dim = 2
    measurement_noise_dim = 2

    def bias(self, x):
        return x[..., -2:]

    def process_noise_cov(self, dtype, device=None):
        s = self.system
        std = torch.tensor([s.speed_noise, s.turn_rate_noise], dtype=dtype, device=device)
        return torch.diag((std * self.sigma) ** 2)

    def measurement_noise_cov(self, dtype, device=None):
        return (self.system.gps_noise * self.sigma) ** 2 * torch.eye(2, dtype=dtype, device=device)

    def _bias_std(self) -> list[float]:
        s = self.system
        return [
            max(s.speed_bias_range, 1e-3) / math.sqrt(3),
            max(s.turn_rate_bias_range, 1e-3) / math.sqrt(3),
        ]

    def _std(self, position, heading) -> torch.Tensor:
        """Standard deviations ``(..., 5)`` in the tangent's order from ``(...,)`` tensors."""
        bias = torch.tensor(self._bias_std(), dtype=position.dtype, device=position.device)
        cols = (
            [position, position, heading]
            if self.system.pose_group == "se2"
            else [heading, position, position]
        )
        return torch.cat((torch.stack(cols, dim=-1), bias.expand(*position.shape, 2)), dim=-1)

    def initial_state(self, batch, dtype, device=None):
        """A wide prior at the identity: position std ``position_range / sqrt 3`` (at least
        1 m), heading ``pi / sqrt 3``, the biases' spreads."""
        x0 = self.group.identity((batch,), dtype=dtype, device=device)
        p = max(self.system.position_range / math.sqrt(3), 1.0)
        std = self._std(
            torch.full((batch,), p, dtype=dtype, device=device),
            torch.full((batch,), math.pi / math.sqrt(3), dtype=dtype, device=device),
        )
        return x0, torch.diag_embed(std**2)

    def fixes_prior(self, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(x (N, *element_shape), P (N, 5, 5))`` at the last of the measurements ``y``
        ``(N, m >= 2, 4)``.

        Position: the last fix; heading: the chord from the first fix to the last; zero biases.
        The position error is taken as isotropic, so its body-frame covariance is the same.
        """
        if y.dim() != 3 or y.shape[1] < 2 or y.shape[-1] != 4:
            raise ValueError(
                f"fixes_prior needs (N, m >= 2, 4) measurements, got {tuple(y.shape)}."
            )
        noise = self.system.gps_noise * self.sigma
        chord = y[:, -1, :2] - y[:, 0, :2]
        theta = torch.atan2(chord[:, 1], chord[:, 0])
        length = torch.linalg.vector_norm(chord, dim=-1).clamp_min(1e-3)
        theta_std = (math.sqrt(2) * noise / length).clamp_max(math.pi) + 0.2
        c, s = torch.cos(theta), torch.sin(theta)
        R = torch.stack((c, -s, s, c), dim=-1).unflatten(-1, (2, 2))
        x = self.system.join(R, y[:, -1, :2], torch.zeros_like(y[:, -1, 2:]))
        std = self._std(torch.full_like(theta, noise), theta_std)
        return x, torch.diag_embed(std**2)


class PlanarEKF:
    """The error-state EKF with the vehicle's true model and noise level, as an estimator.

    ``xhat_0 = e``; steps ``1 .. m-1`` the raw fix; at step ``m = init_steps`` the prior of
    :meth:`PlanarFilterModel.fixes_prior`, then the filter.
    ``estimate(data) -> (N, T+1, *element_shape)``.
    """

    name = "ekf"

    def __init__(self, system: Planar, sigma: float, init_steps: int = 5):
        if isinstance(init_steps, bool) or not isinstance(init_steps, int) or init_steps < 2:
            raise ValueError(f"init_steps must be an integer >= 2, got {init_steps!r}.")
        self.system = system
        self.group = system.group
        self.model = PlanarFilterModel(system, sigma)
        self.ekf = ErrorStateEKF(self.model)
        self.init_steps = init_steps
        self.seconds = 0.0  # wall time of the last estimate's filter loop

    def estimate(self, data: TrajectoryDataset) -> torch.Tensor:
        y, m = data.measurements, self.init_steps
        if y.shape[1] < m:
            raise ValueError(f"sequences of {y.shape[1]} steps are shorter than init_steps={m}.")
        x, P = self.model.fixes_prior(y[:, :m])
        res = self.ekf.filter(y[:, m:], x0=x, P0=P)
        self.seconds = res.seconds
        head = self.system.state_from_measurement(y[:, : m - 1])
        x0 = self.group.identity((len(y), 1), dtype=y.dtype, device=y.device)
        return torch.cat((x0, head, res.estimates), dim=1)
