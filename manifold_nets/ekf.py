"""An error-state extended Kalman filter on any Lie group (a multiplicative EKF on products).

The estimate ``xhat`` lives on the group; the error is a tangent vector ``e`` with the true state
``x = xhat · exp(e)`` (the *right* perturbation, the house convention of ``rplus``) and
``e ~ N(0, P)``, ``P`` ``(*batch, n, n)`` with ``n = group.tangent_dim``. On ``R^n`` this is the
textbook Kalman filter; on SO(3) it is the multiplicative EKF; on a product it is both, factor by
factor, with the cross-covariances.

The model is a :class:`FilterModel`, built on a :class:`manifold_nets.system.System` so that the
simulator's ``step`` and ``measure`` serve the filter unchanged::

    w_k     = drive(xhat_k, y_{k+1}, u_k, q_k)     the drive as the filter reconstructs it;
                                                   q ~ N(0, Q)
    x_{k+1} = step(x_k, w_k)                       the system's dynamics
    z       = measure(x_{k+1}, w_k, r)             the system's measurement model; r ~ N(0, R_n)
    nu      = residual(observation(y_{k+1}), z)    the innovation, in R^d

One filter step (``k -> k+1``), with ``xhat^- = step(xhat, drive(xhat, y, u, 0))``::

    F = d/de rminus(step(xhat·exp(e), drive(xhat·exp(e), y, u, 0)), xhat^-)      (n, n)
    G = d/dq rminus(step(xhat, drive(xhat, y, u, q)), xhat^-)                   (n, q)
    P^- = F P F^T + G Q G^T (+ Q_e, noise entering the error state directly: a bias random walk)
    zhat = measure(xhat^-, w, 0),  nu = residual(observation(y), zhat)
    H = d/de residual(measure(xhat^-·exp(e), w, 0), zhat)                       (d, n)
    M = d/dr residual(measure(xhat^-, w, r), zhat)                              (d, r)
    S = H P^- H^T + M R_n M^T,  K = P^- H^T S^-1,  delta = K nu
    xhat^+ = xhat^- · exp(delta)
    P^+ = (I - K H) P^- (I - K H)^T + K M R_n M^T K^T                   (Joseph form)
    P^+ <- J P^+ J^T,  J = d/de rminus(xhat^-·exp(delta + e), xhat^+)
                                                                        (reset; J_r(delta) on SO(3))
    P^+ <- (P^+ + P^+^T) / 2

With a gate ``g`` (``ErrorStateEKF(model, gate=g)``), an update whose NIS ``nu^T S^-1 nu``
exceeds ``g`` uses ``R_n NIS / g`` instead of ``R_n`` (covariance inflation, per sequence): an
outlier moves the estimate as little as an innovation at the gate would, and a run of large
innovations still pulls a filter that is really off back, where rejecting them would lock it out.

All derivatives are taken at zero by autograd through the group's ``rplus``/``rminus`` and the
model, by default: reverse mode, with the ``d`` output components stacked in a leading
dimension in front of the batch and pulled back in one ``torch.func.vjp`` (so the model must
accept any leading batch dimensions, which the house convention asks of every function).
``jacobians="analytic"`` uses the model's :meth:`FilterModel.process_jacobians` and
:meth:`FilterModel.measurement_jacobians` (and :meth:`FilterModel.reset_jacobian` when it has
one) instead: several times faster, and checked against autograd in the tests.

The measurement is compared through ``residual`` (default: the system's
:meth:`~manifold_nets.system.System.measurement_residual`, itself by default the plain difference
``z - zhat`` in ``R^l``; a system with a measured rotation compares it on the group).

Shapes: measurements ``(N, T, measurement_dim)`` with ``measurements[:, k] = y_{k+1}``; inputs
``(N, T, input_dim)``; estimates ``(N, T+1, *element_shape)`` from ``xhat_0`` (the model's initial
guess), the format of the learned observer's rollout, so ``System.metrics`` applies unchanged.

The models (:class:`FilterModel` and the two ready-made ones, :class:`SystemFilterModel` and
:class:`BiasedReadingsFilterModel`) are in :mod:`manifold_nets.ekf_models`, importable here too;
this module is the filter.
"""

from __future__ import annotations

import math
import time
from typing import NamedTuple

import torch

from .data import TrajectoryDataset
from .ekf_models import (
    BiasedReadingsFilterModel,
    FilterModel,
    SystemFilterModel,
    check_noise_level,
)
from .progress import progress

__all__ = [
    "BiasedReadingsFilterModel",
    "EKFState",
    "ErrorStateEKF",
    "FilterModel",
    "FilterResult",
    "SystemFilterModel",
    "check_noise_level",
]

_JACOBIANS = ("autograd", "analytic")


class EKFState(NamedTuple):
    """The filter's belief: ``x`` ``(B, *element_shape)``, ``P`` ``(B, n, n)``."""

    x: torch.Tensor
    P: torch.Tensor


class FilterResult(NamedTuple):
    """``estimates`` ``(N, T+1, *element_shape)``; ``covariances`` ``(N, T+1, n, n)`` or ``None``;
    ``nis`` ``(N, T)`` the normalised innovation squared ``nu^T S^-1 nu`` (mean ``d`` when the
    filter is consistent); ``seconds`` the wall time of the time loop."""

    estimates: torch.Tensor
    covariances: torch.Tensor | None
    nis: torch.Tensor
    seconds: float


def _lead(t: torch.Tensor, k: int) -> torch.Tensor:
    """``t`` ``(*batch, ...)`` seen as ``(k, *batch, ...)`` (a view, no copy)."""
    return t.expand(k, *t.shape)


def _jacobian_at_zero(fn, dims, d_out: int, batch, like: torch.Tensor) -> list[torch.Tensor]:
    """The Jacobians at 0 of ``fn(*perturbations) -> (d_out, *batch, d_out)`` in each argument.

    Reverse mode with the output rows stacked in front of the batch: argument ``i`` is
    ``(d_out, *batch, dims[i])``, copy ``j`` of the batch is pulled back along output
    component ``j``, so one ``torch.func.vjp`` (one forward and one backward pass over
    ``d_out`` copies of the batch) gives every row of every sequence's Jacobian. ``fn`` must
    let copy ``j`` depend only on its own perturbation (any batched function does). On the CPU
    this is several times faster than forward mode here (``torch.func.jvp``/``jacfwd`` go
    through Python decompositions for some of the groups' operations).
    Returns ``[(*batch, d_out, dims[i])]``.
    """
    primals = tuple(like.new_zeros(d_out, *batch, d) for d in dims)
    _, pullback = torch.func.vjp(fn, *primals)
    eye = torch.eye(d_out, dtype=like.dtype, device=like.device)
    cot = eye.reshape(d_out, *(1,) * len(batch), d_out).expand(d_out, *batch, d_out)
    return [g.movedim(0, -2) for g in pullback(cot)]


def _symmetric(P: torch.Tensor) -> torch.Tensor:
    return 0.5 * (P + P.transpose(-1, -2))


def _cholesky(S: torch.Tensor) -> torch.Tensor:
    """The Cholesky factor of the innovation covariance, or a ValueError that says why not."""
    L, info = torch.linalg.cholesky_ex(_symmetric(S))
    if bool((info != 0).any()):
        raise ValueError(
            "ErrorStateEKF: the innovation covariance S = H P H^T + M R M^T is not positive "
            "definite (zero measurement noise, or a diverged covariance); give the model a "
            "measurement noise > 0."
        )
    return L


class ErrorStateEKF:
    """Error-state EKF on ``model.group``; see the module docstring for the equations.

    ``jacobians``: ``"autograd"`` (default; ``torch.func.vjp``) or ``"analytic"`` (the
    model's methods). ``reset``: re-centre the covariance on the corrected estimate (the
    ``J_r(delta)`` of a multiplicative EKF; the identity on ``R^n``). ``progress``: a bar of
    the steps in :meth:`filter`, shown on a terminal when the run takes over two seconds.
    ``gate``: a threshold on the NIS beyond which the update's measurement noise is inflated
    (module docstring); ``None`` (default): no gate. ``gate_after``: :meth:`filter` leaves its
    first ``gate_after`` steps ungated, for a filter started far off, whose first innovations
    are large because it is (gated, it may converge too slowly and lock onto a wrong state).
    """

    def __init__(
        self,
        model: FilterModel,
        jacobians: str = "autograd",
        reset: bool = True,
        progress: bool = True,
        gate: float | None = None,
        gate_after: int = 0,
    ):
        if not isinstance(model, FilterModel):
            raise TypeError(
                f"ErrorStateEKF needs a FilterModel (e.g. SystemFilterModel(system, sigma)), got "
                f"{type(model).__name__}."
            )
        if jacobians not in _JACOBIANS:
            raise ValueError(f"jacobians must be one of {_JACOBIANS}, got {jacobians!r}.")
        self.model = model
        self.group = model.group
        self.jacobians = jacobians
        self.reset = bool(reset)
        self.progress = bool(progress)
        if gate is not None and (
            isinstance(gate, bool) or not isinstance(gate, (int, float)) or not 0 < gate < math.inf
        ):
            raise ValueError(
                f"gate is a threshold on the NIS nu^T S^-1 nu (e.g. 16.8, the chi-square 99 % "
                f"point for 6 degrees of freedom), > 0, or None; got {gate!r}."
            )
        self.gate = None if gate is None else float(gate)
        if isinstance(gate_after, bool) or not isinstance(gate_after, int) or gate_after < 0:
            raise ValueError(
                f"gate_after is the number of the filter's first steps left ungated, an integer "
                f">= 0; got {gate_after!r}."
            )
        self.gate_after = gate_after
        self.name = "ekf"

    # ------------------------------------------------------------------ Jacobians

    def process_jacobians(self, x, y, u, x_pred=None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(F, G)`` at ``xhat = x`` by autograd, ``(B, n, n)`` and ``(B, n, q)``.

        ``x_pred`` is the predicted ``xhat^-`` when already computed.
        """
        g, m = self.group, self.model
        if x_pred is None:
            x_pred = m.step(x, m.drive(x, y, u))
        dims = (g.tangent_dim, m.process_noise_dim)
        k = g.tangent_dim
        xk, yk, uk, pk = (_lead(t, k) for t in (x, y, u, x_pred))

        def f(e, q):
            xe = g.rplus(xk, e)
            return g.rminus(m.step(xe, m.drive(xe, yk, uk, q)), pk)

        F, G = _jacobian_at_zero(f, dims, g.tangent_dim, g.batch_shape(x), x)
        return F, G

    def measurement_jacobians(self, x, drive, z_hat, d: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``(H, M)`` at ``xhat^- = x`` by autograd, ``(B, d, n)`` and ``(B, d, r)``.

        ``d`` is the size of the residual.
        """
        g, m = self.group, self.model
        dims = (g.tangent_dim, m.measurement_noise_dim)
        k = d
        xk, wk, zk = _lead(x, k), _lead(drive, k), _lead(z_hat, k)

        def h(e, r):
            return m.residual(m.measure(g.rplus(xk, e), wk, r), zk)

        H, M = _jacobian_at_zero(h, dims, d, g.batch_shape(x), x)
        return H, M

    def reset_jacobian(self, x_minus, delta, x_plus) -> torch.Tensor:
        """``d/de rminus(x^-·exp(delta + e), x^+)`` at 0 by autograd, ``(B, n, n)``."""
        g = self.group
        n = g.tangent_dim

        def j(e):
            return g.rminus(g.rplus(_lead(x_minus, n), delta + e), _lead(x_plus, n))

        (J,) = _jacobian_at_zero(j, (n,), n, g.batch_shape(x_minus), x_minus)
        return J

    # ------------------------------------------------------------------ steps

    def init(self, batch: int, dtype=torch.float64, device=None, x0=None, P0=None) -> EKFState:
        """The model's prior, with ``x0`` ``(B, *element_shape)`` / ``P0`` ``(B, n, n)``
        overriding it."""
        mx, mP = self.model.initial_state(batch, dtype, device)
        x = mx if x0 is None else x0.to(dtype=dtype, device=device)
        P = mP if P0 is None else P0.to(dtype=dtype, device=device)
        n = self.group.tangent_dim
        if tuple(x.shape) != (batch, *self.group.element_shape) or tuple(P.shape) != (batch, n, n):
            raise ValueError(
                f"x0 must be {(batch, *self.group.element_shape)} and P0 {(batch, n, n)}; got "
                f"{tuple(x.shape)} and {tuple(P.shape)}."
            )
        return EKFState(x, P)

    def predict(
        self, state: EKFState, y: torch.Tensor, u: torch.Tensor
    ) -> tuple[EKFState, torch.Tensor]:
        """``(xhat^-, P^-)`` and the drive ``w`` used, from ``y_{k+1}`` ``(B, l)`` and ``u_k``."""
        m = self.model
        x, P = state
        w = m.drive(x, y, u)
        x_pred = m.step(x, w)
        if self.jacobians == "analytic":
            F, G = m.process_jacobians(x, y, u)
        else:
            F, G = self.process_jacobians(x, y, u, x_pred)
        Q = m.process_noise_cov(x.dtype, x.device)
        P_pred = F @ P @ F.transpose(-1, -2) + G @ Q @ G.transpose(-1, -2)
        Qe = m.state_noise_cov(x.dtype, x.device)
        if Qe is not None:
            P_pred = P_pred + Qe
        return EKFState(x_pred, _symmetric(P_pred)), w

    def update(
        self, state: EKFState, y: torch.Tensor, drive: torch.Tensor, gated: bool = True
    ) -> tuple[EKFState, torch.Tensor]:
        """``(xhat^+, P^+)`` and the NIS ``(B,)`` from ``y_{k+1}`` and the step's drive;
        ``gated=False`` leaves the gate (if any) out of this update."""
        g, m = self.group, self.model
        x, P = state
        z_hat = m.measure(x, drive)
        nu = m.residual(m.observation(y), z_hat)
        if self.jacobians == "analytic":
            H, M = m.measurement_jacobians(x, drive)
        else:
            H, M = self.measurement_jacobians(x, drive, z_hat, nu.shape[-1])
        Rn = M @ m.measurement_noise_cov(x.dtype, x.device) @ M.transpose(-1, -2)
        PHt = P @ H.transpose(-1, -2)
        HPHt = H @ PHt
        L = _cholesky(HPHt + Rn)
        nis = (nu.unsqueeze(-1) * torch.cholesky_solve(nu.unsqueeze(-1), L)).sum((-1, -2))
        if gated and self.gate is not None and bool((nis > self.gate).any()):
            # an innovation beyond the gate: the measurement noise inflated by nis / gate
            Rn = Rn * (nis / self.gate).clamp(min=1.0)[..., None, None]
            L = _cholesky(HPHt + Rn)
        K = torch.cholesky_solve(PHt.transpose(-1, -2), L).transpose(-1, -2)  # P H^T S^-1
        delta = (K @ nu.unsqueeze(-1)).squeeze(-1)
        x_new = g.rplus(x, delta)
        eye = torch.eye(g.tangent_dim, dtype=x.dtype, device=x.device)
        A = eye - K @ H
        P_new = A @ P @ A.transpose(-1, -2) + K @ Rn @ K.transpose(-1, -2)
        if self.reset:
            J = None
            if self.jacobians == "analytic":
                try:
                    J = m.reset_jacobian(x, delta)
                except NotImplementedError:
                    J = None
            if J is None:
                J = self.reset_jacobian(x, delta, x_new)
            P_new = J @ P_new @ J.transpose(-1, -2)
        return EKFState(x_new, _symmetric(P_new)), nis

    def step(
        self, state: EKFState, y: torch.Tensor, u: torch.Tensor, gated: bool = True
    ) -> tuple[EKFState, torch.Tensor]:
        """One predict and update, ``k -> k+1``; returns the new state and the NIS."""
        state, w = self.predict(state, y, u)
        return self.update(state, y, w, gated)

    # ------------------------------------------------------------------ whole sequences

    def filter(
        self,
        measurements: torch.Tensor,
        inputs: torch.Tensor | None = None,
        x0: torch.Tensor | None = None,
        P0: torch.Tensor | None = None,
        return_covariances: bool = False,
    ) -> FilterResult:
        """Runs over ``measurements`` ``(N, T, l)`` (``inputs`` ``(N, T, m)``); see
        :class:`FilterResult`."""
        m = self.model
        if (
            not isinstance(measurements, torch.Tensor)
            or measurements.dim() != 3
            or (measurements.shape[-1] != m.measurement_dim)
        ):
            shape = getattr(measurements, "shape", type(measurements).__name__)
            raise ValueError(
                f"measurements must be (N, T, {m.measurement_dim}) (measurements[:, k] = y_(k+1)),"
                f" got {tuple(shape)}."
            )
        n_seq, t = measurements.shape[:2]
        if inputs is None:
            inputs = measurements.new_zeros(n_seq, t, m.input_dim)
        if tuple(inputs.shape) != (n_seq, t, m.input_dim):
            raise ValueError(
                f"inputs must be {(n_seq, t, m.input_dim)}, got {tuple(inputs.shape)}."
            )
        dtype, device = measurements.dtype, measurements.device
        state = self.init(n_seq, dtype, device, x0, P0)
        est = measurements.new_empty(n_seq, t + 1, *self.group.element_shape)
        cov = None
        if return_covariances:
            n = self.group.tangent_dim
            cov = measurements.new_empty(n_seq, t + 1, n, n)
            cov[:, 0] = state.P
        nis = measurements.new_empty(n_seq, t)
        est[:, 0] = state.x
        t0 = time.perf_counter()
        with torch.no_grad():
            steps = progress(range(t), desc=f"{self.name} steps", enabled=self.progress, delay=2.0)
            for k in steps:
                gated = k >= self.gate_after
                state, nis[:, k] = self.step(state, measurements[:, k], inputs[:, k], gated)
                est[:, k + 1] = state.x
                if cov is not None:
                    cov[:, k + 1] = state.P
        return FilterResult(est, cov, nis, time.perf_counter() - t0)

    def estimate(self, data: TrajectoryDataset) -> torch.Tensor:
        """Estimates ``(N, T+1, *element_shape)`` on ``data`` (the baselines' common interface)."""
        return self.filter(data.measurements, data.inputs).estimates
