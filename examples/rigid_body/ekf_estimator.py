"""The rigid body's error-state EKF as an estimator: :class:`RigidBodyEKF` (started from a batch
estimate over the first measurements, :func:`initialize_from_measurements`; nominal, tuned or
gated) and the grid search of its noise levels, :func:`tune_ekf_noise`.

The model it filters with is :mod:`.filter_model`'s; the overview is
:mod:`manifold_nets_examples.rigid_body.filters`.
"""

from __future__ import annotations

import itertools
import logging
import math

import torch

from groups import SO3
from groups.so3 import left_jacobian_inverse
from manifold_nets.data import TrajectoryDataset
from manifold_nets.ekf import check_noise_level

from .filter_model import RigidBodyFilterModel
from .filter_support import _repeat
from .system import RigidBody

__all__ = [
    "CHI2_99_6DOF",
    "RigidBodyEKF",
    "initialize_from_measurements",
    "tune_ekf_noise",
]

_SO3 = SO3()
# the logger of the module this was split from (filters), the name log settings select
log = logging.getLogger(__name__.rpartition(".")[0] + ".filters")

#: The chi-square distribution's 99 % point for 6 degrees of freedom (the measured pose's
#: innovation), ``scipy.stats.chi2.ppf(0.99, 6)``: :meth:`RigidBodyEKF.robust`'s gate.
CHI2_99_6DOF = 16.8119


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
    over steps >= 10 of m in {0, 3, 5, 10} at sigma 0.1, 0.3, 0.5, and no divergence).
    ``init_steps = 0``: it starts at step 0 from the model's prior (``(I, 0, 0, 0)``, wide); at
    sigma >= 0.4 that transient lets the rotation residual wrap past pi and a few sequences lock
    onto a wrong gyro bias (``docs/baselines.md``). ``jacobians``: ``"analytic"`` (default, fast)
    or ``"autograd"`` (the generic path; same estimates to ~1e-13).
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

    def estimate_with_covariance(self, data: TrajectoryDataset) -> tuple[torch.Tensor, torch.Tensor]:
        """The estimates ``(N, T+1, 18)`` and the filter's covariances of the system's error
        ``(N, T+1, 12, 12)`` (the right perturbation, ``docs/calibration.md``), NaN before the
        filter's start at step ``init_steps`` (the raw measurements carry no covariance)."""
        return self._run(data, covariances=True)

    def estimate(self, data: TrajectoryDataset) -> torch.Tensor:
        """Estimates ``(N, T+1, 18)``: the system's state (a filter's extra states left out)."""
        return self._run(data, covariances=False)[0]

    def _run(self, data: TrajectoryDataset, covariances: bool):
        y, m = data.measurements, self.init_steps
        n_el, n = self.group.element_shape[0], self.group.tangent_dim
        if m == 0:
            res = self.ekf.filter(y, return_covariances=covariances)
            self.seconds = res.seconds
            cov = res.covariances[..., :n, :n] if covariances else None
            return res.estimates[..., :n_el], cov
        if y.shape[1] < m:
            raise ValueError(f"sequences of {y.shape[1]} steps are shorter than init_steps={m}.")
        x, P = self.start_belief(y[:, :m])
        res = self.ekf.filter(y[:, m:], x0=x, P0=P, return_covariances=covariances)
        self.seconds = res.seconds
        head = self.system.state_from_measurement(y[:, : m - 1])
        x0 = self.group.identity((len(y), 1), dtype=y.dtype, device=y.device)
        est = torch.cat((x0, head, res.estimates[..., :n_el]), dim=1)
        if not covariances:
            return est, None
        nan = y.new_full((len(y), m, n, n), float("nan"))  # steps 0 .. m-1: no filter yet
        return est, torch.cat((nan, res.covariances[..., :n, :n]), dim=1)


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

    def column(i):
        return torch.tensor([c[i] for c in combos], dtype=torch.float64).repeat_interleave(
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
