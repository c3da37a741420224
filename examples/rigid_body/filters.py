"""Classical filters for the paper's rigid body: the error-state EKF's model and a complementary filter.

**The EKF model** (:class:`RigidBodyFilterModel`). The filter's state is the system's own state
``(R, p, b_Omega, b_v)`` on ``SO(3) x R^3 x R^3 x R^3`` with the right error
``R = Rhat exp(dtheta)``, ``p = phat + dp``, ``b = bhat + db`` (12-dimensional). The simulator has
measurement noise only, but the filter sees the velocities only through the biased, noisy
readings of ``y_{k+1}``, so for the filter::

    drive   (Omega, v) = (Omega^m - b_Omega - w3, v^m - b_v - w4)   w3, w4 ~ N(0, sigma^2 I): process noise
    step    the system's exact step with that drive; the biases are constant states
    update  (R^m, p^m) = (R exp(w1), p + w2) from the system's ``measure``, compared through the
            system's ``measurement_residual``: (log(Rhat^T R^m), p^m - phat), w1, w2 ~ N(0, sigma^2 I)

The velocity readings serve the prediction only; using them in the update as well would count
their noise twice. The rotation residual ``log(Rhat^T R^m)`` is the noise ``w1`` itself to first
order (the noise is a right perturbation), and it is exact for any size of error, where the
difference of ``vec R`` would be a 9-vector of rank-3 covariance, curved away from the group.

:meth:`RigidBodyFilterModel.process_jacobians` and :meth:`~RigidBodyFilterModel.measurement_jacobians`
are the analytic multiplicative-EKF Jacobians of this discrete model (exact, including the
derivative of ``J_l(phi) v`` in ``phi``), used with ``ErrorStateEKF(model, jacobians="analytic")``;
the tests check them against autograd and finite differences.

**The EKF as an estimator** (:class:`RigidBodyEKF`): the generic
:class:`manifold_nets.ekf.ErrorStateEKF` on that model, started at step 5 from a batch
estimate of the biases over the first 5 measurements (:func:`initialize_from_measurements`;
inside the 10 steps the paper's table skips), or from the prior at step 0.

**The complementary filter** (:class:`ComplementaryFilter`): the passive nonlinear complementary
filter with bias estimation of Mahony, Hamel and Pflimlin (IEEE TAC 2008, eq. 13 with the bias
law of Theorem 5.1), discretised with the exact step,

    Rhat^- = Rhat exp((Omega^m - bhat) dt),    omega = vex(P_a(Rhat^-^T R^m)),
    Rhat   = Rhat^- exp(k_P omega dt),         bhat <- bhat - k_I omega dt,

with ``P_a(M) = (M - M^T)/2``, and the same structure for the position with a body-frame bias
(``p^- = p + Rhat J_l v_hat dt``, ``e = p^m - p^-``, ``p = p^- + k_p e dt``,
``b_v <- b_v - k_b Rhat^T e dt``). Its four gains are chosen by :func:`tune_complementary_gains`,
a grid search on a validation set simulated in code (its own seed, never the inference set).
"""

from __future__ import annotations

import itertools
import logging
import math
from dataclasses import asdict, dataclass

import torch

from groups import SO3
from groups.so3 import left_jacobian, left_jacobian_inverse, skew, unskew
from manifold_nets.data import TrajectoryDataset
from manifold_nets.ekf import BiasedReadingsFilterModel, check_noise_level
from manifold_nets.system import check_number

from .system import RigidBody

__all__ = [
    "ComplementaryFilter",
    "ComplementaryGains",
    "CHI2_99_6DOF",
    "RigidBodyEKF",
    "RigidBodyFilterModel",
    "initialize_from_measurements",
    "jl_times_v_derivative",
    "tune_complementary_gains",
    "tune_ekf_noise",
]

_SO3 = SO3()
log = logging.getLogger(__name__)

#: The chi-square distribution's 99 % point for 6 degrees of freedom (the measured pose's
#: innovation), ``scipy.stats.chi2.ppf(0.99, 6)``: :meth:`RigidBodyEKF.robust`'s gate.
CHI2_99_6DOF = 16.8119


def _check_system(system, who: str) -> None:
    """The filters here work on the paper's layout ``(vec R, p, b_Omega, b_v)`` only."""
    if not isinstance(system, RigidBody):
        raise TypeError(f"{who} needs a RigidBody, got {type(system).__name__}.")
    if system.pose_group != "so3_r3":
        raise ValueError(
            f"{who} works on the paper's group SO(3) x R^3 x R^3 x R^3 (pose_group='so3_r3'); "
            f"this RigidBody has pose_group={system.pose_group!r}. Filter the so3_r3 system (the "
            "same data) and compare through System.metrics."
        )


def _noise_param(name: str, value, zero_ok: bool = False):
    """A noise level of the EKF's model: a float (or a ``(B,)`` tensor, one per sequence)."""
    bound = ">= 0" if zero_ok else "> 0"
    if isinstance(value, torch.Tensor):
        ok = bool(torch.isfinite(value).all()) and bool((value >= 0 if zero_ok else value > 0).all())
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
    ``-B [v]x + 2 B' (phi x v) phi^T + C ((phi.v) I + phi v^T - 2 v phi^T) + 2 C' (phi (phi.v) - t^2 v) phi^T``
    with ``B'``, ``C'`` the derivatives in ``t^2`` (Taylor series near 0).
    """
    from groups import numerics as nx

    t2 = (phi * phi).sum(-1)
    b, c = nx.one_minus_cos_over_t2(t2), nx.t_minus_sin_over_t3(t2)
    db, dc = _dB_dt2(t2), _dC_dt2(t2)
    pv = (phi * v).sum(-1)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device)
    outer = lambda a, w: a.unsqueeze(-1) * w.unsqueeze(-2)
    col = lambda s: s[..., None, None]
    cross = torch.linalg.cross(phi, v)
    dd = phi * pv.unsqueeze(-1) - t2.unsqueeze(-1) * v  # phi x (phi x v)
    return (
        -col(b) * skew(v)
        + col(2 * db) * outer(cross, phi)
        + col(c) * (col(pv) * eye + outer(phi, v) - 2 * outer(v, phi))
        + col(2 * dc) * outer(dd, phi)
    )


# ------------------------------------------------------------------ the EKF's model


class RigidBodyFilterModel(BiasedReadingsFilterModel):
    """The rigid body as an error-state EKF sees it; see the module docstring.

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

        With ``phi = (Omega^m - bhat_Omega) dt``, ``vhat = v^m - bhat_v``, ``t = J_l(phi) vhat dt``::

            dtheta' = exp(phi)^T dtheta - J_r(phi) dt (db_Omega + w3)
            dp'     = dp - Rhat [t]x dtheta - Rhat D dt^2 (db_Omega + w3) - Rhat J_l(phi) dt (db_v + w4)
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


# ------------------------------------------------------------------ the EKF as an estimator


def initialize_from_measurements(
    system: RigidBody, measurements: torch.Tensor, sigma: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """A belief about ``x_m`` from the first ``m`` measurements ``(N, m, 18)`` (``y_1 .. y_m``).

    ``Rhat, phat = R^m_m, p^m_m`` (variance ``sigma^2``), and the biases by averaging over the
    ``m - 1`` consecutive pairs: ``b_Omega = mean_j (Omega^m_j - log(R^m_j^T R^m_{j+1}) / dt)``,
    ``b_v = mean_j (v^m_j - J_l(phi_j)^-1 R^m_j^T (p^m_{j+1} - p^m_j) / dt)`` with
    ``phi_j = (Omega^m_j - b_Omega) dt``. In the mean the rotation noise of consecutive pairs
    telescopes, so ``var(b_Omega) ~ 2 sigma^2 / ((m-1) dt)^2 + sigma^2 / (m-1)`` per axis; the
    covariance returned is that times 2 for ``b_Omega`` and times 4 for ``b_v`` (the rotation
    noise also enters ``b_v``), which covers the spread measured at sigma 0.1 .. 0.5 with
    m = 5 and 10 (2000 sequences each).
    Returns ``(x (N, 18), P (N, 12, 12))``.
    """
    sigma = check_noise_level("initialize_from_measurements", sigma)
    if measurements.dim() != 3 or measurements.shape[-1] != 18 or measurements.shape[1] < 2:
        raise ValueError(
            f"initialize_from_measurements needs (N, m, 18) measurements with m >= 2, got "
            f"{tuple(measurements.shape)}."
        )
    y = measurements
    m, dt = y.shape[1], system.dt
    Rm = y[..., :9].unflatten(-1, (3, 3))
    pm, rates = y[..., 9:12], y[:, 1:, 12:]
    Rt = Rm[:, :-1].transpose(-1, -2)
    b_omega = (rates[..., :3] - _SO3.log(Rt @ Rm[:, 1:]) / dt).mean(1)
    phi = (rates[..., :3] - b_omega.unsqueeze(1)) * dt
    body = (Rt @ (pm[:, 1:] - pm[:, :-1]).unsqueeze(-1)) / dt
    vel = (left_jacobian_inverse(phi) @ body).squeeze(-1)
    b_v = (rates[..., 3:] - vel).mean(1)
    x = torch.cat((y[:, -1, :12], b_omega, b_v), dim=-1)
    a = 2 * sigma**2 / ((m - 1) * dt) ** 2 + sigma**2 / (m - 1)
    var = torch.tensor([sigma**2] * 6 + [2 * a] * 3 + [4 * a] * 3, dtype=y.dtype, device=y.device)
    return x, torch.diag_embed(var).expand(len(y), 12, 12).clone()


class RigidBodyEKF:
    """The error-state EKF with the rigid body's true model, dt and noise level, as an estimator.

    ``init_steps = m > 1`` (default 5, inside the 10 steps the paper's table skips): the
    estimates of steps ``1 .. m-1`` are the raw measurements, the filter starts at step ``m``
    from :func:`initialize_from_measurements` and runs from there (m = 5 gave the lowest errors
    over steps >= 10 of m in {0, 3, 5, 10} at sigma 0.1, 0.3, 0.5, and no divergence). ``init_steps = 0``: it starts at
    step 0 from the model's prior (``(I, 0, 0, 0)``, wide); at sigma >= 0.4 that transient lets
    the rotation residual wrap past pi and a few sequences lock onto a wrong gyro bias
    (``docs/baselines.md``). ``jacobians``: ``"analytic"`` (default, fast) or ``"autograd"``
    (the generic path; same estimates to ~1e-13).
    """

    name = "ekf"

    def __init__(
        self,
        system: RigidBody,
        sigma: float,
        jacobians: str = "analytic",
        init_steps: int = 5,
        reading_std: float | torch.Tensor | None = None,
        pose_std: float | torch.Tensor | None = None,
        bias_walk: float | torch.Tensor = 0.0,
        gate: float | None = None,
        gate_after: int = 0,
    ):
        from manifold_nets.ekf import ErrorStateEKF

        if (
            isinstance(init_steps, bool)
            or not isinstance(init_steps, int)
            or init_steps == 1
            or init_steps < 0
        ):
            raise ValueError(f"init_steps must be 0 or an integer >= 2, got {init_steps!r}.")
        self.system = system
        self.group = system.group
        self.model = RigidBodyFilterModel(
            system, sigma, reading_std=reading_std, pose_std=pose_std, bias_walk=bias_walk
        )
        self.ekf = ErrorStateEKF(
            self.model, jacobians=jacobians, gate=gate, gate_after=gate_after
        )
        self.init_steps = init_steps
        self.seconds = 0.0  # wall time of the last estimate's filter loop

    @classmethod
    def tuned(cls, system: RigidBody, sigma: float, **search) -> RigidBodyEKF:
        """The EKF with its noise levels chosen by :func:`tune_ekf_noise` on data of ``system``
        itself (whatever its true noise and errors are) at ``sigma``; what ``method=ekf_tuned``
        runs. The model stays nominal: only ``reading_std``, ``pose_std`` and ``bias_walk`` move."""
        sigma = check_noise_level("RigidBodyEKF.tuned", sigma)
        noise, _ = tune_ekf_noise(system, sigma, **search)
        log.info("EKF, sigma %g: tuned noise levels %s", sigma, noise)
        return cls(system, sigma, **noise)

    @classmethod
    def robust(
        cls,
        system: RigidBody,
        sigma: float,
        gate: float = CHI2_99_6DOF,
        gate_after: int = 50,
        **kw,
    ) -> RigidBodyEKF:
        """The nominal EKF with an innovation gate (what ``method=ekf_robust`` runs): an update
        whose NIS exceeds ``gate`` (default the chi-square 99 % point for the pose's 6 degrees
        of freedom) has its measurement noise inflated by ``NIS / gate``, so an outlier moves
        the estimate as little as a 99 % innovation would (``ErrorStateEKF(gate=)``). The
        filter's first ``gate_after`` steps are ungated: an outlier among the 5 measurements of
        the start makes the first bias estimate far off, and gated from the start a few
        sequences in 200 converged too slowly and locked onto a wrong gyro bias
        (docs/baselines.md)."""
        return cls(system, sigma, gate=gate, gate_after=gate_after, **kw)

    def __repr__(self) -> str:
        m = self.model
        tuned, params = "", (m.reading_std, m.pose_std, m.bias_walk)
        if not any(isinstance(v, torch.Tensor) for v in params) and params != (
            m.sigma, m.sigma, 0.0
        ):
            tuned = (
                f", reading_std={m.reading_std:g}, pose_std={m.pose_std:g}, "
                f"bias_walk={m.bias_walk:g}"
            )
        if self.ekf.gate is not None:
            tuned += f", gate={self.ekf.gate:g}, gate_after={self.ekf.gate_after}"
        return (
            f"RigidBodyEKF(sigma={m.sigma:g}, jacobians={self.ekf.jacobians!r}, "
            f"init_steps={self.init_steps}{tuned})"
        )

    def start_belief(self, head: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The filter's belief at step ``init_steps`` from the first measurements ``head``
        ``(N, m, 18)``: :func:`initialize_from_measurements`. A filter with a larger state
        (:class:`~.correlated_noise.CorrelatedNoiseEKF`) extends it."""
        return initialize_from_measurements(self.system, head, self.model.sigma)

    def estimate(self, data: TrajectoryDataset) -> torch.Tensor:
        """Estimates ``(N, T+1, 18)``: the system's state (a filter's extra states left out)."""
        y = data.measurements
        m = self.init_steps
        n = self.group.element_shape[0]
        if m == 0:
            res = self.ekf.filter(y)
            self.seconds = res.seconds
            return res.estimates[..., :n]
        if y.shape[1] < m:
            raise ValueError(f"sequences of {y.shape[1]} steps are shorter than init_steps={m}.")
        x, P = self.start_belief(y[:, :m])
        res = self.ekf.filter(y[:, m:], x0=x, P0=P)
        self.seconds = res.seconds
        head = self.system.state_from_measurement(y[:, : m - 1])
        x0 = self.group.identity((len(y), 1), dtype=y.dtype, device=y.device)
        return torch.cat((x0, head, res.estimates[..., :n]), dim=1)


#: The EKF's noise levels searched by :func:`tune_ekf_noise`: the readings' and the pose's noise
#: as multiples of sigma, the biases' random walk in units/s per sqrt(s).
_EKF_GRID = {
    "reading_scale": (0.5, 1.0, 2.0, 4.0, 8.0),
    "pose_scale": (0.5, 1.0, 2.0, 4.0),
    "bias_walk": (0.0, 0.01, 0.03, 0.1, 0.3),
}


def tune_ekf_noise(
    system: RigidBody,
    sigma: float,
    grid: dict | None = None,
    num_sequences: int = 16,
    length: int = 300,
    seed: int = 10_000,
    skip: int = 10,
) -> tuple[dict, dict]:
    """Grid search of the EKF's noise levels on a validation set simulated from ``system``.

    The model (dynamics, measurement equations) stays the nominal rigid body's; only the noise
    it assumes moves: ``reading_std = reading_scale * sigma``, ``pose_std = pose_scale *
    sigma`` and the biases' random walk ``bias_walk``. Simulates ``num_sequences x length`` at
    ``sigma`` from ``seed`` (apart from the inference sets' seeds) and picks the point of the
    grid with the smallest mean ``||Rhat - R||_F + ||phat - p||`` over steps ``>= skip``; the
    whole grid runs as one batch. Returns ``({reading_std, pose_std, bias_walk}, {point: score})``.
    """
    grid = {**_EKF_GRID, **(grid or {})}
    data = system.simulate(num_sequences, length, sigma, torch.Generator().manual_seed(seed))
    combos = list(itertools.product(grid["reading_scale"], grid["pose_scale"], grid["bias_walk"]))
    reps = len(combos)
    column = lambda i: torch.tensor([c[i] for c in combos], dtype=torch.float64).repeat_interleave(
        num_sequences
    )
    ekf = RigidBodyEKF(
        system, sigma, reading_std=column(0) * sigma, pose_std=column(1) * sigma,
        bias_walk=column(2),
    )
    ekf.ekf.progress = False
    many = _repeat(data, reps)
    err = system.metrics(ekf.estimate(many), many)
    score = (err["R"] + err["p"])[:, skip:].mean(1).reshape(reps, num_sequences).mean(1)
    score = torch.nan_to_num(score, nan=math.inf)
    best = combos[int(score.argmin())]
    choice = {"reading_std": best[0] * sigma, "pose_std": best[1] * sigma, "bias_walk": best[2]}
    return choice, {c: float(v) for c, v in zip(combos, score)}


# ------------------------------------------------------------------ complementary filter


@dataclass(frozen=True)
class ComplementaryGains:
    """Continuous-time gains: attitude ``k_P``, gyro bias ``k_I``, position ``k_p``, velocity
    bias ``k_b`` (each step applies ``gain * dt``). Defaults: the grid search's choice at
    sigma = 0.3, dt = 0.1; tune them for other settings (:func:`tune_complementary_gains`)."""

    k_P: float = 4.0
    k_I: float = 16.0
    k_p: float = 2.0
    k_b: float = 4.0


class ComplementaryFilter:
    """Mahony's passive complementary filter with bias estimation, plus its position analogue.

    Starts from the first measurement: ``xhat_0 = e`` (nothing known), ``xhat_1 = (R^m_1,
    p^m_1, 0, 0)``, then filters. Gains may be tensors ``(N,)`` (one set per sequence), which is
    how :func:`tune_complementary_gains` runs a whole grid in one batch.
    """

    name = "complementary"

    def __init__(self, system: RigidBody, gains: ComplementaryGains | None = None):
        _check_system(system, "ComplementaryFilter")
        self.system = system
        self.group = system.group
        self.gains = gains or ComplementaryGains()

    @classmethod
    def tuned(cls, system: RigidBody, sigma: float, **search) -> ComplementaryFilter:
        """The filter with its gains chosen for ``sigma`` by :func:`tune_complementary_gains`
        (keyword arguments go to the search); what ``method=complementary`` runs."""
        gains, _ = tune_complementary_gains(
            system, check_noise_level("ComplementaryFilter.tuned", sigma), **search
        )
        log.info("complementary filter, sigma %g: gains %s", sigma, gains)
        return cls(system, gains)

    def filter(self, measurements: torch.Tensor, gains: dict | None = None) -> torch.Tensor:
        """Estimates ``(N, T+1, 18)`` from ``measurements`` ``(N, T, 18)``.

        ``gains`` maps ``k_P``, ``k_I``, ``k_p``, ``k_b`` to floats or ``(N,)`` tensors
        (default: ``self.gains``).
        """
        if measurements.dim() != 3 or measurements.shape[-1] != 18:
            raise ValueError(f"measurements must be (N, T, 18), got {tuple(measurements.shape)}.")
        n, t = measurements.shape[:2]
        dt = self.system.dt
        g = asdict(self.gains) if gains is None else gains

        def col(name):
            k = torch.as_tensor(g[name], dtype=measurements.dtype, device=measurements.device)
            return (k * dt).reshape(-1, 1) if k.dim() else k * dt

        aP, aI, ap, ab = col("k_P"), col("k_I"), col("k_p"), col("k_b")
        est = measurements.new_empty(n, t + 1, 18)
        est[:, 0] = self.group.identity((n,), dtype=measurements.dtype, device=measurements.device)
        x = self.system.state_from_measurement(measurements[:, 0])
        est[:, 1] = x
        for k in range(1, t):
            y = measurements[:, k]
            b = x[:, 12:]
            xm = self.system.step(x, y[:, 12:] - b)  # predict with bias-corrected readings
            Rm_ = xm[:, :9].unflatten(-1, (3, 3))
            Ry = y[:, :9].unflatten(-1, (3, 3))
            omega = unskew(Rm_.transpose(-1, -2) @ Ry)  # vex(P_a(Rhat^T R^m))
            R = Rm_ @ _SO3.exp(aP * omega)
            e = y[:, 9:12] - xm[:, 9:12]
            p = xm[:, 9:12] + ap * e
            b_omega = b[:, :3] - aI * omega
            b_v = b[:, 3:] - ab * (Rm_.transpose(-1, -2) @ e.unsqueeze(-1)).squeeze(-1)
            x = torch.cat((R.flatten(-2), p, b_omega, b_v), dim=-1)
            est[:, k + 1] = x
        return est

    def __repr__(self) -> str:
        g = self.gains
        return f"ComplementaryFilter(k_P={g.k_P:g}, k_I={g.k_I:g}, k_p={g.k_p:g}, k_b={g.k_b:g})"

    def estimate(self, data: TrajectoryDataset) -> torch.Tensor:
        """Estimates ``(N, T+1, 18)`` on ``data`` with ``self.gains``."""
        return self.filter(data.measurements)


#: Gains in 1/s; with dt = 0.1 a step applies at most ``10 * dt = 1`` of the correction. The
#: biases (up to 10 rad/s, 10 m/s) need large integral gains to be learnt in a few seconds.
_DEFAULT_GRID = {
    "k_P": (1.0, 2.0, 4.0, 6.0, 8.0, 10.0),
    "k_I": (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0),
    "k_p": (1.0, 2.0, 4.0, 6.0, 8.0, 10.0),
    "k_b": (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0),
}


def tune_complementary_gains(
    system: RigidBody,
    sigma: float,
    grid: dict | None = None,
    num_sequences: int = 32,
    length: int = 500,
    seed: int = 10_000,
    skip: int = 10,
) -> tuple[ComplementaryGains, dict]:
    """Grid search of the complementary filter's gains on a simulated validation set.

    Simulates ``num_sequences x length`` at ``sigma`` from ``seed`` (keep it apart from the
    inference sets' seeds), then picks ``(k_P, k_I)`` minimising the mean ``||Rhat - R||_F`` and,
    with those, ``(k_p, k_b)`` minimising the mean ``||phat - p||``, over steps ``>= skip``
    (the attitude does not depend on the position gains). Each grid runs as one batch.
    Returns the gains and ``{"attitude": {(k_P, k_I): err}, "position": {(k_p, k_b): err}}``.
    """
    grid = {**_DEFAULT_GRID, **(grid or {})}
    data = system.simulate(num_sequences, length, sigma, torch.Generator().manual_seed(seed))
    cf = ComplementaryFilter(system)
    base = asdict(ComplementaryGains())
    scores: dict = {}
    best = dict(base)
    for part, (a, b), factor in (
        ("attitude", ("k_P", "k_I"), "R"),
        ("position", ("k_p", "k_b"), "p"),
    ):
        combos = list(itertools.product(grid[a], grid[b]))
        reps = len(combos)
        y = data.measurements.repeat(reps, 1, 1)
        gains = {k: float(v) for k, v in best.items()}
        gains[a] = torch.tensor([c[0] for c in combos]).repeat_interleave(num_sequences)
        gains[b] = torch.tensor([c[1] for c in combos]).repeat_interleave(num_sequences)
        est = cf.filter(y, gains)
        err = system.metrics(est, _repeat(data, reps))[factor]
        mean = err[:, skip:].mean(1).reshape(reps, num_sequences).mean(1)
        scores[part] = {c: float(m) for c, m in zip(combos, mean)}
        i = int(mean.argmin())
        best[a], best[b] = combos[i]
    return ComplementaryGains(**best), scores


def _repeat(data: TrajectoryDataset, reps: int) -> TrajectoryDataset:
    """``data`` with its sequences repeated ``reps`` times (block after block)."""
    return TrajectoryDataset(
        data.states.repeat(reps, 1, 1),
        data.measurements.repeat(reps, 1, 1),
        data.inputs.repeat(reps, 1, 1),
        dict(data.meta),
    )
