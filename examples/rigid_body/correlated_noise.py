"""The rigid body's EKF that knows its noise is time-correlated: the noise as part of the state.

:class:`~.mismatch.MismatchedRigidBody` with ``noise_correlation = rho > 0`` draws every noise
component as a stationary AR(1) process, ``n_k = rho n_{k-1} + sqrt(1 - rho^2) e_k`` times
``sigma``. The nominal EKF (:class:`~.filters.RigidBodyEKF`) takes it for white noise. This filter
is the textbook remedy (Bryson and Henrikson, 1968: state augmentation): the twelve noise
components ``n = (n_R, n_p, n_Omega, n_v)`` become states, so the filter knows the noise's law
exactly. It is an oracle for the mismatch benchmark: how far a filter that is told the truth
about the noise gets on the correlated-noise data, and so how far any estimator may hope to.

**The model** (:class:`CorrelatedNoiseFilterModel`). The state is ``(R, p, b_Omega, b_v, n)`` on
``SO(3) x R^3 x R^3 x R^3 x R^12`` (24-dimensional error, ``n`` last). Over ``k -> k+1``, with
``q ~ N(0, (1 - rho^2) sigma^2 I_6)`` the readings' noise innovation::

    n_read'  = rho n_read + q                                       (n_Omega, n_v)
    drive    (Omega, v) = (Omega^m, v^m) - (b_Omega, b_v) - n_read'
    step     the rigid body's exact step with that drive; the biases kept
    n_pose'  = rho n_pose + e,  e ~ N(0, (1 - rho^2) sigma^2 I_6)   (n_R, n_p; the state noise)
    update   (R^m, p^m) = (R' exp(n_R'), p' + n_p') + r

The measured pose is then noise-free given the state; ``r ~ N(0, (floor sigma)^2 I_6)`` with a
small ``floor`` (default 0.01) keeps the innovation covariance invertible and adds 0.005 % to the
pose noise's variance. With ``rho = 0`` the model is the nominal EKF's with the pose noise
``sigma sqrt(1 + floor^2)``, and the estimates agree with it to rounding (tested).

The analytic Jacobians reuse :class:`~.filters.RigidBodyFilterModel`'s: with its ``F``, ``G``
(the base state and the readings' noise), ``F' = [[F, 0, rho G], [0, rho I_6, 0], [0, 0, rho
I_6]]`` and ``G' = [G; 0; I_6]``; the measurement residual ``(log(exp(-n_R) exp(dtheta)
exp(n_R + dn_R)), dp + dn_p)`` gives ``H = [[exp(n_R)^T, 0, 0, 0, J_r(n_R), 0, 0], [0, I, 0, 0,
0, I, 0]]``. The tests check them against autograd.

**The estimator** (:class:`CorrelatedNoiseEKF`, ``method=ekf_ar1``, a
:class:`~.filters.RigidBodyEKF` with its own model and start) starts like the nominal one, at
step ``init_steps`` (5) from :func:`~.filters.initialize_from_measurements`, with the noise
states at 0 (variance ``sigma^2``); the measured pose's error is then minus the pose noise, which
the prior's covariance says (``cov(dtheta, n_R) = -sigma^2 I``), and the bias estimate, a mean of
correlated noise, gets its variance times ``(1 + rho) / (1 - rho)`` (the AR(1) variance of a
mean). ``rho`` is the system's ``noise_correlation`` unless given.
"""

from __future__ import annotations

import torch

from groups import SO3, Euclidean, Product
from groups.so3 import left_jacobian
from manifold_nets.ekf import ErrorStateEKF, FilterModel, check_noise_level

from .filters import RigidBodyEKF, RigidBodyFilterModel
from .system import RigidBody

__all__ = ["CorrelatedNoiseEKF", "CorrelatedNoiseFilterModel"]

_SO3 = SO3()
_BASE = 18  # the rigid body's element (vec R, p, b_Omega, b_v)
_NOISE = 12  # (n_R, n_p, n_Omega, n_v)


def _check_rho(rho) -> float:
    if isinstance(rho, bool) or not isinstance(rho, (int, float)) or not 0 <= rho < 1:
        raise ValueError(
            f"CorrelatedNoiseFilterModel: rho is the noise's AR(1) coefficient and must be in "
            f"[0, 1), got {rho!r}."
        )
    return float(rho)


class CorrelatedNoiseFilterModel(FilterModel):
    """The rigid body with AR(1) measurement noise in the state; see the module docstring.

    ``sigma``: the noise's standard deviation (stationary); ``rho``: its AR(1) coefficient;
    ``floor``: the pose's residual white noise, a fraction of ``sigma`` (> 0).
    """

    process_noise_dim = 6  # the readings' noise innovations
    measurement_noise_dim = 6  # the floor on the measured pose

    def __init__(self, system: RigidBody, sigma: float, rho: float, floor: float = 0.01):
        self.base = RigidBodyFilterModel(system, sigma)  # checks the system and sigma
        self.system = system
        self.sigma = self.base.sigma
        self.rho = _check_rho(rho)
        if isinstance(floor, bool) or not isinstance(floor, (int, float)) or not 0 < floor < 1:
            raise ValueError(
                f"CorrelatedNoiseFilterModel: floor is the pose's white noise as a fraction of "
                f"sigma, in (0, 1), got {floor!r}."
            )
        self.floor = float(floor)
        self.group = Product(
            SO3(), Euclidean(3), Euclidean(3), Euclidean(3), Euclidean(_NOISE),
            names=("R", "p", "b_omega", "b_v", "noise"),
        )
        self.measurement_dim = system.measurement_dim
        self.input_dim = system.input_dim

    # the model

    @staticmethod
    def split(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(base (*, 18), n_pose (*, 6), n_read (*, 6))`` of an augmented element."""
        return x[..., :_BASE], x[..., _BASE : _BASE + 6], x[..., _BASE + 6 :]

    def drive(self, x, y, u, noise=None):
        """``(Omega, v, n_read')`` ``(*, 12)``: the drive and the readings' next noise."""
        base, _, n_read = self.split(x)
        n_next = self.rho * n_read if noise is None else self.rho * n_read + noise
        w = self.system.drive_from_measurement(y, u) - base[..., 12:] - n_next
        return torch.cat((w, n_next), dim=-1)

    def step(self, x, drive):
        base, n_pose, _ = self.split(x)
        moved = self.system.step(base, drive[..., :6])
        return torch.cat((moved, self.rho * n_pose, drive[..., 6:]), dim=-1)

    def measure(self, x, drive, noise=None):
        base, n_pose, _ = self.split(x)
        pose = n_pose if noise is None else n_pose + noise
        pad = pose.new_zeros(*pose.shape[:-1], 6)
        return self.system.measure(base, drive[..., :6], torch.cat((pose, pad), dim=-1))

    def residual(self, z, z_hat):
        return self.system.measurement_residual(z, z_hat)[..., :6]

    def process_noise_cov(self, dtype, device=None):
        return (1 - self.rho**2) * self.sigma**2 * torch.eye(6, dtype=dtype, device=device)

    def measurement_noise_cov(self, dtype, device=None):
        return (self.floor * self.sigma) ** 2 * torch.eye(6, dtype=dtype, device=device)

    def state_noise_cov(self, dtype, device=None):
        """``(1 - rho^2) sigma^2`` on the pose noise's block (the AR(1) innovations)."""
        q = torch.zeros(24, dtype=dtype, device=device)
        q[12:18] = (1 - self.rho**2) * self.sigma**2
        return torch.diag(q)

    def initial_state(self, batch, dtype, device=None):
        """The nominal prior with the noise states at 0, variance ``sigma^2``."""
        x0, P0 = self.base.initial_state(batch, dtype, device)
        return self.augment(x0, P0)

    def augment(self, x: torch.Tensor, P: torch.Tensor, pose_measured: bool = False):
        """The augmented belief from a belief ``(x (B, 18), P (B, 12, 12))`` about the base
        state: noise states 0 with variance ``sigma^2``. ``pose_measured``: ``x``'s pose is the
        last measured one, so its error is minus the pose noise (``cov = -sigma^2 I``)."""
        b = x.shape[0]
        xa = torch.cat((x, x.new_zeros(b, _NOISE)), dim=-1)
        Pa = x.new_zeros(b, 24, 24)
        Pa[:, :12, :12] = P
        s2 = self.sigma**2
        Pa[:, 12:, 12:] = s2 * torch.eye(_NOISE, dtype=x.dtype, device=x.device)
        if pose_measured:
            eye6 = torch.eye(6, dtype=x.dtype, device=x.device)
            Pa[:, :6, 12:18] = -s2 * eye6
            Pa[:, 12:18, :6] = -s2 * eye6
        return xa, Pa

    # analytic Jacobians

    def process_jacobians(self, x, y, u):
        base, _, n_read = self.split(x)
        y_eff = y.clone()
        y_eff[..., 12:] = y[..., 12:] - self.rho * n_read  # the base model's drive, less n_read'
        F0, G0 = self.base.process_jacobians(base, y_eff, u)
        batch = x.shape[:-1]
        F = x.new_zeros(*batch, 24, 24)
        G = x.new_zeros(*batch, 24, 6)
        eye6 = torch.eye(6, dtype=x.dtype, device=x.device)
        F[..., :12, :12] = F0
        F[..., :12, 18:] = self.rho * G0
        F[..., 12:18, 12:18] = self.rho * eye6
        F[..., 18:, 18:] = self.rho * eye6
        G[..., :12, :] = G0
        G[..., 18:, :] = eye6
        return F, G

    def measurement_jacobians(self, x, drive):
        _, n_pose, _ = self.split(x)
        n_R = n_pose[..., :3]
        batch = x.shape[:-1]
        H = x.new_zeros(*batch, 6, 24)
        eye3 = torch.eye(3, dtype=x.dtype, device=x.device)
        H[..., :3, :3] = _SO3.exp(n_R).transpose(-1, -2)
        H[..., :3, 12:15] = left_jacobian(-n_R)  # J_r(n_R)
        H[..., 3:, 3:6] = eye3
        H[..., 3:, 15:18] = eye3
        M = x.new_zeros(*batch, 6, 6)
        M[..., :3, :3] = left_jacobian(-n_R)
        M[..., 3:, 3:] = eye3
        return H, M

    def reset_jacobian(self, x, delta):
        J = torch.eye(24, dtype=delta.dtype, device=delta.device).repeat(*delta.shape[:-1], 1, 1)
        J[..., :3, :3] = left_jacobian(-delta[..., :3])
        return J


class CorrelatedNoiseEKF(RigidBodyEKF):
    """The EKF with the AR(1) noise in its state, as an estimator (``method=ekf_ar1``).

    ``rho``: the noise's AR(1) coefficient, by default the system's ``noise_correlation`` (0 for
    a system without one, where this is the nominal EKF). ``init_steps`` (>= 2: it starts from
    the measurements), ``jacobians``: as :class:`~.filters.RigidBodyEKF`, whose estimate it
    shares; only the start differs (:meth:`start_belief`). Its estimates are the base state's,
    ``(N, T+1, 18)``. The nominal model's constructors (``tuned``, ``robust``) are not for it.
    """

    name = "ekf_ar1"

    def __init__(
        self,
        system: RigidBody,
        sigma: float,
        rho: float | None = None,
        floor: float = 0.01,
        jacobians: str = "analytic",
        init_steps: int = 5,
    ):
        sigma = check_noise_level("CorrelatedNoiseEKF", sigma)
        if rho is None:
            rho = getattr(system, "noise_correlation", 0.0)
        if isinstance(init_steps, bool) or not isinstance(init_steps, int) or init_steps < 2:
            raise ValueError(f"init_steps must be an integer >= 2, got {init_steps!r}.")
        self.system = system
        self.group = system.group
        self.model = CorrelatedNoiseFilterModel(system, sigma, rho, floor)
        self.ekf = ErrorStateEKF(self.model, jacobians=jacobians)
        self.init_steps = init_steps
        self.seconds = 0.0

    def __repr__(self) -> str:
        m = self.model
        return (
            f"CorrelatedNoiseEKF(sigma={m.sigma:g}, rho={m.rho:g}, floor={m.floor:g}, "
            f"jacobians={self.ekf.jacobians!r}, init_steps={self.init_steps})"
        )

    def start_belief(self, head: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The nominal start with the biases' variance times ``(1 + rho) / (1 - rho)`` (the
        variance of a mean of AR(1) noise) and the noise states added; the pose is the last
        measured one (:meth:`CorrelatedNoiseFilterModel.augment`)."""
        x, P = super().start_belief(head)
        P[:, 6:, 6:] *= (1 + self.model.rho) / (1 - self.model.rho)
        return self.model.augment(x, P, pose_measured=True)
