"""The AHRS's error-state EKF: the filter model, and the filter started from TRIAD.

**The model** (:class:`AttitudeFilterModel`). The filter's state is the system's own
``(R, b_Omega)`` on SO(3) x R^3, with the right error ``R = Rhat exp(dtheta)``, ``b = bhat + db``
(6-dimensional). The simulator has measurement noise only, but the filter knows the rate only
through the gyro reading of ``y_{k+1}``, so for the filter::

    drive    Omega = Omega^m - b - n3               n3 ~ N(0, (s_w sigma)^2 I_3): process noise
    step     the system's exact step; the bias is a constant state
    update   (R^T g, R^T m) from the system's ``measure`` with noise (n1, n2),
             compared with the measured directions y[0:6] by plain difference

The gyro reading serves the prediction only: using it in the update as well would count its
noise twice. Jacobians by autograd (:class:`manifold_nets.ekf.ErrorStateEKF`'s generic path).

**The estimator** (:class:`AttitudeEKF`). An EKF is a local method: started at the identity with
a wide prior, the first update of a rotation that is off by up to pi linearises badly. So it
starts at the first measurement, from TRIAD: ``xhat_1 = (R_triad(y_1), 0)`` with an attitude
standard deviation per axis of ``4 sigma / sin(angle(g, m))`` (generous: the heading about
gravity is known to about ``sigma / |m_horizontal|``) and the bias's ``bias_range / sqrt(3)``
(the spread of its uniform law); ``xhat_0 = e`` as for every estimator.
"""

from __future__ import annotations

import math

import torch

from manifold_nets.data import TrajectoryDataset
from manifold_nets.ekf import BiasedReadingsFilterModel, ErrorStateEKF

from .system import Attitude

__all__ = ["AttitudeEKF", "AttitudeFilterModel"]


class AttitudeFilterModel(BiasedReadingsFilterModel):
    """The AHRS as an error-state EKF sees it; see the module docstring.

    ``sigma`` is the noise level of the data (the true one: this EKF knows the model).
    """

    system_type = Attitude
    process_noise_dim = 3
    measurement_noise_dim = 6

    def bias(self, x):
        return x[..., 9:12]

    def process_noise_cov(self, dtype, device=None):
        s = self.system.gyro_noise * self.sigma
        return s**2 * torch.eye(3, dtype=dtype, device=device)

    def measurement_noise_cov(self, dtype, device=None):
        s = self.system
        std = (
            torch.tensor([s.gravity_noise] * 3 + [s.magnetic_noise] * 3, dtype=dtype, device=device)
            * self.sigma
        )
        return torch.diag(std**2)

    def initial_state(self, batch, dtype, device=None):
        """A wide prior at the identity (the attitude std ``pi / sqrt 3``, a uniform rotation's)."""
        x0 = self.group.identity((batch,), dtype=dtype, device=device)
        b = max(self.system.bias_range, 1e-3) / math.sqrt(3)
        std = torch.tensor([math.pi / math.sqrt(3)] * 3 + [b] * 3, dtype=dtype, device=device)
        return x0, torch.diag_embed(std**2).expand(batch, 6, 6).clone()

    def triad_prior(self, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(x (N, 12), P (N, 6, 6))``: TRIAD of ``y`` ``(N, 9)``, zero bias; see the module."""
        s = self.system
        g, m = s.directions(y.dtype, y.device)
        sin = torch.linalg.vector_norm(torch.linalg.cross(g, m)) / (g.norm() * m.norm())
        noise = max(s.gravity_noise, s.magnetic_noise) * self.sigma
        rot = 4 * noise / float(sin)
        b = max(s.bias_range, 1e-3) / math.sqrt(3)
        std = torch.tensor([rot] * 3 + [b] * 3, dtype=y.dtype, device=y.device)
        return s.state_from_measurement(y), torch.diag_embed(std**2).expand(len(y), 6, 6).clone()


class AttitudeEKF:
    """The error-state EKF with the AHRS's true model and noise level, as an estimator.

    ``xhat_0 = e``, ``xhat_1`` from TRIAD (:meth:`AttitudeFilterModel.triad_prior`), then the
    filter over ``y_2 .. y_T``. ``estimate(data) -> (N, T+1, 12)`` (the baselines' interface).
    """

    name = "ekf"

    def __init__(self, system: Attitude, sigma: float):
        self.system = system
        self.group = system.group
        self.model = AttitudeFilterModel(system, sigma)
        self.ekf = ErrorStateEKF(self.model)
        self.seconds = 0.0  # wall time of the last estimate's filter loop

    def estimate(self, data: TrajectoryDataset) -> torch.Tensor:
        y = data.measurements
        x1, P1 = self.model.triad_prior(y[:, 0])
        res = self.ekf.filter(y[:, 1:], x0=x1, P0=P1)
        self.seconds = res.seconds
        x0 = self.group.identity((len(y), 1), dtype=y.dtype, device=y.device)
        return torch.cat((x0, res.estimates), dim=1)
