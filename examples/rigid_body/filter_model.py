"""The rigid body as an error-state EKF sees it: :class:`RigidBodyFilterModel`, with the
analytic Jacobians of its discrete model and the derivative of ``J_l(phi) v`` they need
(:func:`jl_times_v_derivative`).

The model's equations: :mod:`manifold_nets_examples.rigid_body.filters`; the filter that runs
it: :mod:`.ekf_estimator`.
"""

from __future__ import annotations

import math

import torch

from groups import SO3
from groups.so3 import left_jacobian, skew
from manifold_nets.ekf import BiasedReadingsFilterModel
from manifold_nets.system import check_number

from .filter_support import _check_system
from .system import RigidBody

__all__ = ["RigidBodyFilterModel", "jl_times_v_derivative"]

_SO3 = SO3()


def _noise_param(name: str, value, zero_ok: bool = False):
    """A noise level of the EKF's model: a float (or a ``(B,)`` tensor, one per sequence)."""
    bound = ">= 0" if zero_ok else "> 0"
    if isinstance(value, torch.Tensor):
        ok = bool(torch.isfinite(value).all()) and bool(
            (value >= 0 if zero_ok else value > 0).all()
        )
        if not ok or value.dim() != 1:
            raise ValueError(f"{name} must be finite and {bound} (a (B,) tensor), got {value!r}.")
        return value
    return check_number("RigidBodyEKF", name, value, positive=not zero_ok)


def _scaled_eye(std, n: int, dtype, device) -> torch.Tensor:
    """``std^2 I_n`` ``(n, n)``, or ``(B, n, n)`` for a ``(B,)`` tensor of ``std``."""
    eye = torch.eye(n, dtype=dtype, device=device)
    if isinstance(std, torch.Tensor):
        return std.to(dtype=dtype, device=device).square()[:, None, None] * eye
    return std**2 * eye


# ------------------------------------------------------------------ d(J_l(phi) v)/dphi


def _dB_dt2(t2: torch.Tensor) -> torch.Tensor:
    """``d/d(t^2) (1 - cos t)/t^2 = (t sin t - 2 (1 - cos t)) / (2 t^4)``."""
    small = t2 < (0.1 if t2.dtype == torch.float64 else 0.5) ** 2
    s = torch.where(small, torch.ones_like(t2), t2)
    t = s.sqrt()
    exact = (t * torch.sin(t) - 4.0 * torch.sin(0.5 * t) ** 2) / (2.0 * s * s)
    series = -1 / 24 + t2 * (1 / 360 + t2 * (-1 / 13440 + t2 / 907200))
    return torch.where(small, series, exact)


def _dC_dt2(t2: torch.Tensor) -> torch.Tensor:
    """``d/d(t^2) (t - sin t)/t^3 = (3 sin t - 2 t - t cos t) / (2 t^5)``."""
    small = t2 < (0.1 if t2.dtype == torch.float64 else 0.5) ** 2
    s = torch.where(small, torch.ones_like(t2), t2)
    t = s.sqrt()
    exact = (3.0 * torch.sin(t) - 2.0 * t - t * torch.cos(t)) / (2.0 * s * s * t)
    series = -1 / 120 + t2 * (1 / 2520 + t2 * (-1 / 120960 + t2 / 9979200))
    return torch.where(small, series, exact)


def jl_times_v_derivative(phi: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``d(J_l(phi) v)/dphi``, ``(*batch, 3, 3)``, for ``phi``, ``v`` ``(*batch, 3)``.

    From ``J_l(phi) v = v + B phi x v + C phi x (phi x v)`` with ``B = (1 - cos t)/t^2``,
    ``C = (t - sin t)/t^3``, ``t = |phi|``:
    ``-B [v]x + 2 B' (phi x v) phi^T + C ((phi.v) I + phi v^T - 2 v phi^T)``
    ``+ 2 C' (phi (phi.v) - t^2 v) phi^T``
    with ``B'``, ``C'`` the derivatives in ``t^2`` (Taylor series near 0).
    """
    from groups import numerics as nx

    t2 = (phi * phi).sum(-1)
    b, c = nx.one_minus_cos_over_t2(t2), nx.t_minus_sin_over_t3(t2)
    db, dc = _dB_dt2(t2), _dC_dt2(t2)
    pv = (phi * v).sum(-1)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device)

    def outer(a, w):
        return a.unsqueeze(-1) * w.unsqueeze(-2)

    def col(s):
        return s[..., None, None]

    cross = torch.linalg.cross(phi, v)
    dd = phi * pv.unsqueeze(-1) - t2.unsqueeze(-1) * v  # phi x (phi x v)
    return (
        -col(b) * skew(v)
        + col(2 * db) * outer(cross, phi)
        + col(c) * (col(pv) * eye + outer(phi, v) - 2 * outer(v, phi))
        + col(2 * dc) * outer(dd, phi)
    )


class RigidBodyFilterModel(BiasedReadingsFilterModel):
    """The rigid body as an error-state EKF sees it; see
    :mod:`manifold_nets_examples.rigid_body.filters`.

    ``sigma`` is the noise level of the data (the true one: this EKF knows the model).
    The prior is ``xhat_0 = (I, 0, 0, 0)`` (the mean of the system's laws for ``p`` and the
    biases) with independent errors: ``rotation_std`` per axis (default ``pi / sqrt(3)``, the
    spread of a uniform rotation: the first update then jumps close to ``R^m``), and the standard
    deviations of the uniform laws, ``range / sqrt(3)``, for ``p`` and the biases.
    """

    system_type = RigidBody
    measurement_noise_dim = 6  # (w1, w2): the measured pose
    process_noise_dim = 6  # (w3, w4): the gyro and velocity readings

    def __init__(
        self,
        system: RigidBody,
        sigma: float,
        rotation_std: float = math.pi / math.sqrt(3),
        reading_std: float | torch.Tensor | None = None,
        pose_std: float | torch.Tensor | None = None,
        bias_walk: float | torch.Tensor = 0.0,
    ):
        _check_system(system, "RigidBodyFilterModel")
        super().__init__(system, sigma)
        if not rotation_std > 0:
            raise ValueError(f"rotation_std must be > 0, got {rotation_std!r}.")
        self.rotation_std = float(rotation_std)
        self.dt = system.dt
        default = lambda v: self.sigma if v is None else v  # noqa: E731
        self.reading_std = _noise_param("reading_std", default(reading_std))
        self.pose_std = _noise_param("pose_std", default(pose_std))
        self.bias_walk = _noise_param("bias_walk", bias_walk, zero_ok=True)

    # model

    def bias(self, x):
        return x[..., 12:18]

    def process_noise_cov(self, dtype, device=None):
        """``reading_std^2 I_6`` (default ``sigma``): the velocity readings' noise."""
        return _scaled_eye(self.reading_std, 6, dtype, device)

    def measurement_noise_cov(self, dtype, device=None):
        """``pose_std^2 I_6`` (default ``sigma``): the measured pose's noise."""
        return _scaled_eye(self.pose_std, 6, dtype, device)

    def state_noise_cov(self, dtype, device=None):
        """``bias_walk^2 dt`` on the bias block per step (a random walk); ``None`` when zero."""
        if not isinstance(self.bias_walk, torch.Tensor) and self.bias_walk == 0.0:
            return None
        mask = torch.zeros(12, dtype=dtype, device=device)
        mask[6:] = 1.0
        return _scaled_eye(self.bias_walk, 12, dtype, device) * mask * self.dt

    def initial_state(self, batch, dtype, device=None):
        x0 = self.group.identity((batch,), dtype=dtype, device=device)
        s = self.system
        std = torch.tensor(
            [self.rotation_std] * 3
            + [max(s.position_range, 1e-3) / math.sqrt(3)] * 3
            + [max(s.bias_range, 1e-3) / math.sqrt(3)] * 6,
            dtype=dtype,
            device=device,
        )
        return x0, torch.diag_embed(std**2).expand(batch, 12, 12).clone()

    # analytic Jacobians

    def process_jacobians(self, x, y, u):
        """The discrete multiplicative-EKF ``F`` ``(*batch, 12, 12)`` and ``G`` ``(*batch, 12, 6)``.

        With ``phi = (Omega^m - bhat_Omega) dt``, ``vhat = v^m - bhat_v``,
        ``t = J_l(phi) vhat dt``::

            dtheta' = exp(phi)^T dtheta - J_r(phi) dt (db_Omega + w3)
            dp'     = dp - Rhat [t]x dtheta - Rhat D dt^2 (db_Omega + w3)
                      - Rhat J_l(phi) dt (db_v + w4)
            db'     = db

        with ``J_r(phi) = J_l(phi)^T`` and ``D = d(J_l(phi) vhat)/dphi``.
        """
        dt = self.dt
        w = self.drive(x, y, u)
        phi, vhat = w[..., :3] * dt, w[..., 3:]
        R = x[..., :9].unflatten(-1, (3, 3))
        Jl = left_jacobian(phi)
        t = (Jl @ vhat.unsqueeze(-1)).squeeze(-1) * dt
        D = jl_times_v_derivative(phi, vhat)
        batch = x.shape[:-1]
        F = torch.zeros(*batch, 12, 12, dtype=x.dtype, device=x.device)
        eye3 = torch.eye(3, dtype=x.dtype, device=x.device)
        F[..., 0:3, 0:3] = _SO3.exp(phi).transpose(-1, -2)
        F[..., 0:3, 6:9] = -Jl.transpose(-1, -2) * dt
        F[..., 3:6, 0:3] = -R @ skew(t)
        F[..., 3:6, 3:6] = eye3
        F[..., 3:6, 6:9] = -(R @ D) * dt * dt
        F[..., 3:6, 9:12] = -(R @ Jl) * dt
        F[..., 6:12, 6:12] = torch.eye(6, dtype=x.dtype, device=x.device)
        G = F[..., :, 6:12].clone()
        G[..., 6:12, :] = 0.0
        return F, G

    def measurement_jacobians(self, x, drive):
        """``H = [I_6 | 0]``, ``M = I_6``: the residual ``(log(exp(dtheta) exp(w1)), dp + w2)``."""
        batch = x.shape[:-1]
        eye = torch.eye(12, dtype=x.dtype, device=x.device)
        H = eye[:6].expand(*batch, 6, 12)
        M = eye[:6, :6].expand(*batch, 6, 6)
        return H, M

    def reset_jacobian(self, x, delta):
        """``blockdiag(J_r(dtheta), I_9)``: ``log(exp(-d) exp(d + e)) = J_r(d) e + O(e^2)``."""
        batch = delta.shape[:-1]
        J = torch.eye(12, dtype=delta.dtype, device=delta.device).repeat(*batch, 1, 1)
        J[..., :3, :3] = left_jacobian(-delta[..., :3])
        return J
