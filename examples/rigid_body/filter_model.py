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
from manifold_nets.ekf import BiasedReadingsFilterModel
from manifold_nets.ekf_so3 import (
    exp_and_left_jacobian,
    matmul,
    skew_matrix,
    so3_coefficients,
    so3_log,
)
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


def jl_times_v_derivative(
    phi: torch.Tensor,
    v: torch.Tensor,
    coefficients: torch.Tensor | None = None,
    K: torch.Tensor | None = None,
) -> torch.Tensor:
    """``d(J_l(phi) v)/dphi``, ``(*batch, 3, 3)``, for ``phi``, ``v`` ``(*batch, 3)``.

    From ``J_l(phi) v = v + B phi x v + C phi x (phi x v)`` with ``B = (1 - cos t)/t^2``,
    ``C = (t - sin t)/t^3``, ``t = |phi|``:
    ``-B [v]x + C (phi.v) I + phi (C v)^T + (u - 2 C v) phi^T``,
    ``u = 2 B' phi x v + 2 C' phi x (phi x v)`` (the outer products as one ``(3, 4) (4, 3)``
    product) with ``B'``, ``C'`` the derivatives in ``t^2`` (:func:`manifold_nets.ekf_so3.so3_coefficients`,
    passed as ``coefficients`` with ``K = [phi]x`` when already computed).
    """
    if coefficients is None:
        coefficients = so3_coefficients((phi * phi).sum(-1))
    if K is None:
        K = skew_matrix(phi)
    c = _constants(phi)
    Kv = matmul(K, v.unsqueeze(-1))
    U = torch.cat((phi.unsqueeze(-1), Kv, matmul(K, Kv), v.unsqueeze(-1)), -1)  # (*, 3, 4)
    W = (coefficients @ c["d_weights"]).unsqueeze(-1) * torch.stack((v, phi, phi, phi), -2)
    # C (phi.v) I - B [v]x, flattened: (C (phi.v), B v) @ (vec I; -vec [e_k]x)
    pv = (phi * v).sum(-1, keepdim=True)
    scalars = torch.cat((coefficients[..., 2:3] * pv, coefficients[..., 1:2] * v), -1)
    base = (scalars @ c["d_base"]).view(*phi.shape[:-1], 3, 3)
    return torch.baddbmm(base, U, W) if U.dim() == 3 else base + U @ W


def _constants(like: torch.Tensor) -> dict[str, torch.Tensor]:
    """The model's constant matrices in ``like``'s dtype and device, made once: the tables of
    :func:`jl_times_v_derivative` (``d_weights``, ``d_base``), ``eye3``, ``eye12``,
    ``bias_rows`` ``[0 | I_6]`` (F's last rows), ``reset_zeros`` and ``reset_rows`` (the
    reset Jacobian's constant part) and ``top_half`` ``(12, 1)`` (1 on rows 0..5: G is F's bias columns there)."""
    key = (like.dtype, like.device)
    c = _CONSTANTS.get(key)
    if c is None:
        eye12 = torch.eye(12, dtype=like.dtype, device=like.device)
        skew = skew_matrix(eye12[:3, :3]).flatten(-2)  # (3, 9): vec [e_k]x
        d_weights = torch.zeros(5, 4, dtype=like.dtype, device=like.device)
        d_weights[2, 0], d_weights[3, 1], d_weights[4, 2], d_weights[2, 3] = 1.0, 2.0, 2.0, -2.0
        c = _CONSTANTS[key] = {
            "d_weights": d_weights,  # (A, B, C, B', C') -> (C, 2 B', 2 C', -2 C)
            "d_base": torch.cat((eye12[:3, :3].reshape(1, 9), -skew)),
            "eye3": eye12[:3, :3].clone(),
            "eye12": eye12,
            "bias_rows": eye12[6:].clone(),
            "reset_zeros": eye12[:3, 3:].clone(),  # (3, 9) beside J_r
            "reset_rows": eye12[3:].clone(),  # [0 | I_9]

            "top_half": (torch.arange(12, device=like.device) < 6).to(like.dtype).unsqueeze(-1),
        }
    return c


_CONSTANTS: dict = {}


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
    measured_states = slice(0, 6)  # H = [I_6 | 0]: the update measures the pose's error

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

    def linearize_step(self, x, y, u):
        """The prediction ``(xhat^-, w)`` and :meth:`process_jacobians` ``(F, G)`` in one pass
        (the system's exact step, written here with the exponential it shares with ``F``)."""
        dt = self.dt
        w = self.drive(x, y, u)
        phi, vhat = w[..., :3] * dt, w[..., 3:]
        E, Jl, K, coefficients = exp_and_left_jacobian(phi)
        t = matmul(Jl, (vhat * -dt).unsqueeze(-1))  # (*batch, 3, 1): minus the displacement
        D = jl_times_v_derivative(phi, vhat, coefficients, K)
        R = x[..., :9].unflatten(-1, (3, 3))
        mJl = Jl * -dt
        # R [-t, -[t]x, -D dt^2, -J_l dt, exp(phi)]: the step and F's position row (its I apart)
        blocks = torch.cat((t, skew_matrix(t.squeeze(-1)), D * -(dt * dt), mJl, E), -1)
        RB = matmul(R, blocks)
        x_pred = torch.cat((RB[..., 10:].flatten(-2), x[..., 9:12] - RB[..., 0], x[..., 12:]), -1)
        zero, c = torch.zeros_like(E), _constants(x)
        top = torch.cat((E.transpose(-1, -2), zero, mJl.transpose(-1, -2), zero), -1)
        middle = torch.cat((RB[..., 1:4], c["eye3"].expand_as(E), RB[..., 4:10]), -1)
        F = torch.cat((top, middle, c["bias_rows"].expand(*x.shape[:-1], 6, 12)), -2)
        G = F[..., 6:12] * c["top_half"]  # F's bias columns, rows 6..11 zero
        return x_pred, w, F, G

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
        return self.linearize_step(x, y, u)[2:]

    def linearize_measurement(self, x, drive, y):
        """``nu = (log(Rhat^T R^m), p^m - phat)``, ``H = [I_6 | 0]`` ``(6, 12)``, ``M = I_6``
        (``None``): the residual of the system's ``measurement_residual``, without the readings."""
        R = x[..., :9].unflatten(-1, (3, 3))
        Rm = y[..., :9].unflatten(-1, (3, 3))
        nu = torch.cat((so3_log(matmul(R.transpose(-1, -2), Rm)), y[..., 9:12] - x[..., 9:12]), -1)
        return nu, _constants(x)["eye12"][:6], None

    def measurement_jacobians(self, x, drive):
        """``H = [I_6 | 0]``, ``M = I_6``: the residual ``(log(exp(dtheta) exp(w1)), dp + w2)``."""
        batch = x.shape[:-1]
        eye = torch.eye(12, dtype=x.dtype, device=x.device)
        H = eye[:6].expand(*batch, 6, 12)
        M = eye[:6, :6].expand(*batch, 6, 6)
        return H, M

    def linearize_reset(self, x, delta):
        """``x·exp(delta)`` and :meth:`reset_jacobian`, sharing ``exp(dtheta)`` and ``J_l``."""
        E, Jl, _, _ = exp_and_left_jacobian(delta[..., :3])
        R = x[..., :9].unflatten(-1, (3, 3))
        x_new = torch.cat((matmul(R, E).flatten(-2), x[..., 9:] + delta[..., 3:]), -1)
        return x_new, self._reset_matrix(Jl.transpose(-1, -2))

    def _reset_matrix(self, Jr: torch.Tensor) -> torch.Tensor:
        """``blockdiag(J_r, I_9)`` ``(*batch, 12, 12)``, written once (a large batch's cost is
        its memory traffic)."""
        c, batch = _constants(Jr), Jr.shape[:-2]
        top = torch.cat((Jr, c["reset_zeros"].expand(*batch, 3, 9)), -1)
        return torch.cat((top, c["reset_rows"].expand(*batch, 9, 12)), -2)

    def reset_jacobian(self, x, delta):
        """``blockdiag(J_r(dtheta), I_9)``: ``log(exp(-d) exp(d + e)) = J_r(d) e + O(e^2)``."""
        return self.linearize_reset(x, delta)[1]
