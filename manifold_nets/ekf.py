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
``jacobians="analytic"`` asks the model instead, one call per stage of a step:
:meth:`FilterModel.linearize_step` (``xhat^-``, ``w``, ``F``, ``G``),
:meth:`FilterModel.linearize_measurement` (``nu``, ``H``, ``M``) and
:meth:`FilterModel.linearize_reset` (``xhat^+``, ``J``; autograd where the model has no ``J``).
By default these call the model's separate methods (:meth:`FilterModel.process_jacobians` and
so on); a model overrides them to share the work of a stage (one ``exp`` for the step and its
Jacobians). Several times faster, and checked against autograd in the tests.

What a step costs (the time loop of small batches is the number of torch operations): the
covariances ``Q``, ``R_n``, ``Q_e`` are read once per run (:meth:`ErrorStateEKF.constants`),
one Cholesky solve gives the NIS and the gain together, and the Joseph form and the reset are
one sandwich, ``(J A) P (J A)^T + (J K) R (J K)^T`` with ``J A = J - (J K) H`` (by selection
where ``H`` is rows of the identity: ``FilterModel.measured_states``). ``P^-`` is symmetrised by
:meth:`~ErrorStateEKF.predict`, not in :meth:`~ErrorStateEKF.step` (the update reads one
triangle of ``S`` and symmetrises ``P^+``). ``compile=True``: the step as one ``torch.compile``
graph, its kernels called from C++. ``benchmarks/results/ekf.md`` has the measurements.

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

import logging
import math
import time
from typing import NamedTuple

import torch

from .data import TrajectoryDataset
from .ekf_jacobians import jacobian_at_zero, lead
from .ekf_so3 import matmul
from .ekf_models import (
    BiasedReadingsFilterModel,
    FilterModel,
    SystemFilterModel,
    check_noise_level,
)
from .progress import progress

__all__ = [
    "BiasedReadingsFilterModel",
    "EKFConstants",
    "EKFState",
    "ErrorStateEKF",
    "FilterModel",
    "FilterResult",
    "SystemFilterModel",
    "check_noise_level",
]

_JACOBIANS = ("autograd", "analytic")
# the compiled step's kernels called from generated C++, not Python (batch 1: about 2x faster)
_COMPILE_OPTIONS = {"cpp_wrapper": True}


def _no_shim_note(record: logging.LogRecord) -> bool:  # inductor's note that it then calls
    return "linalg_cholesky_ex" not in record.getMessage()  # cholesky_ex by a proxy: as meant


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


def _symmetric(P: torch.Tensor) -> torch.Tensor:
    return (P + P.transpose(-1, -2)).mul_(0.5)


def _sandwich(A: torch.Tensor, B: torch.Tensor, plus: torch.Tensor | None = None) -> torch.Tensor:
    """``A B A^T`` (``+ plus``: a temporary of the step, added to in place where the shapes
    let, so that a large batch allocates one ``(B, n, n)`` fewer)."""
    AB = matmul(A, B)
    if plus is None:
        return matmul(AB, A.transpose(-1, -2))
    if AB.dim() == 3 and A.dim() == 3 and plus.shape == AB.shape[:-1] + A.shape[-2:-1]:
        return plus.baddbmm_(AB, A.transpose(-1, -2))
    return plus + matmul(AB, A.transpose(-1, -2))


def _minus_product(C: torch.Tensor, A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """``C - A B``, fused where both factors are batched (a shared ``B`` makes ``A B`` one
    matrix product over the whole batch, faster than a batched one)."""
    if A.dim() == 3 and B.dim() == 3:
        return torch.baddbmm(C, A, B, alpha=-1.0)
    return C - A @ B


_NOT_PD = (
    "ErrorStateEKF: the innovation covariance S = H P H^T + M R M^T is not positive definite "
    "(zero measurement noise, or a diverged covariance); give the model a measurement noise > 0."
)


def _solve(S: torch.Tensor, rhs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``S^-1 rhs`` by Cholesky (from ``S``'s lower triangle) and whether the factorisation
    failed: a ValueError at once in eager code; compiled, a tensor ``failed`` to check after the
    step (a graph cannot raise)."""
    if torch.compiler.is_compiling():
        L, info = torch.linalg.cholesky_ex(S)
        return torch.cholesky_solve(rhs, L), (info != 0).any()
    try:
        return torch.cholesky_solve(rhs, torch.linalg.cholesky(S)), None
    except torch.linalg.LinAlgError:
        raise ValueError(_NOT_PD) from None


def _check_factored(failed: torch.Tensor | None) -> None:
    if failed is not None and bool(failed):
        raise ValueError(_NOT_PD)


class EKFConstants(NamedTuple):
    """What a run takes from the model once, not at every step: the covariances ``Q``
    ``(q, q)`` or ``(B, q, q)``, ``Rn`` ``(r, r)`` or ``(B, r, r)``, ``Qe`` (or ``None``) and the
    identity ``eye`` ``(n, n)``. From :meth:`ErrorStateEKF.constants`."""

    Q: torch.Tensor
    Rn: torch.Tensor
    Qe: torch.Tensor | None
    eye: torch.Tensor


class ErrorStateEKF:
    """Error-state EKF on ``model.group``; see the module docstring for the equations.

    ``jacobians``: ``"autograd"`` (default; ``torch.func.vjp``) or ``"analytic"`` (the
    model's :meth:`~FilterModel.linearize_step`, :meth:`~FilterModel.linearize_measurement` and
    :meth:`~FilterModel.linearize_reset`). ``reset``: re-centre the covariance on the corrected
    estimate (the ``J_r(delta)`` of a multiplicative EKF; the identity on ``R^n``).
    ``progress``: a bar of the steps in :meth:`filter`, shown on a terminal when the run takes
    over two seconds. ``gate``: a threshold on the NIS beyond which the update's measurement
    noise is inflated (module docstring); ``None`` (default): no gate. ``gate_after``:
    :meth:`filter` leaves its first ``gate_after`` steps ungated, for a filter started far off,
    whose first innovations are large because it is (gated, it may converge too slowly and lock
    onto a wrong state). ``compile``: run each step as one ``torch.compile`` graph (analytic
    Jacobians only; a one-off compilation of tens of seconds, then fewer, fused operations per
    step: faster than eager at every batch measured, ``benchmarks/results/ekf.md``).
    """

    def __init__(
        self,
        model: FilterModel,
        jacobians: str = "autograd",
        reset: bool = True,
        progress: bool = True,
        gate: float | None = None,
        gate_after: int = 0,
        compile: bool = False,
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
        if compile and jacobians != "analytic":
            raise ValueError(
                "compile=True compiles the analytic step; use jacobians='analytic' with it."
            )
        self.compile = bool(compile)
        self._compiled = None
        self._selection = model.measured_slice() if jacobians == "analytic" else None
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
        xk, yk, uk, pk = (lead(t, k) for t in (x, y, u, x_pred))

        def f(e, q):
            xe = g.rplus(xk, e)
            return g.rminus(m.step(xe, m.drive(xe, yk, uk, q)), pk)

        F, G = jacobian_at_zero(f, dims, g.tangent_dim, g.batch_shape(x), x)
        return F, G

    def measurement_jacobians(self, x, drive, z_hat, d: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``(H, M)`` at ``xhat^- = x`` by autograd, ``(B, d, n)`` and ``(B, d, r)``.

        ``d`` is the size of the residual.
        """
        g, m = self.group, self.model
        dims = (g.tangent_dim, m.measurement_noise_dim)
        k = d
        xk, wk, zk = lead(x, k), lead(drive, k), lead(z_hat, k)

        def h(e, r):
            return m.residual(m.measure(g.rplus(xk, e), wk, r), zk)

        H, M = jacobian_at_zero(h, dims, d, g.batch_shape(x), x)
        return H, M

    def reset_jacobian(self, x_minus, delta, x_plus) -> torch.Tensor:
        """``d/de rminus(x^-·exp(delta + e), x^+)`` at 0 by autograd, ``(B, n, n)``."""
        g = self.group
        n = g.tangent_dim

        def j(e):
            return g.rminus(g.rplus(lead(x_minus, n), delta + e), lead(x_plus, n))

        (J,) = jacobian_at_zero(j, (n,), n, g.batch_shape(x_minus), x_minus)
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

    def constants(self, dtype=torch.float64, device=None) -> EKFConstants:
        """The model's covariances and the identity, for :meth:`step` in a loop (computed
        once: pass them to every step of a run)."""
        m = self.model
        eye = torch.eye(self.group.tangent_dim, dtype=dtype, device=device)
        return EKFConstants(
            m.process_noise_cov(dtype, device),
            m.measurement_noise_cov(dtype, device),
            m.state_noise_cov(dtype, device),
            eye,
        )

    def predict(
        self, state: EKFState, y: torch.Tensor, u: torch.Tensor, constants=None
    ) -> tuple[EKFState, torch.Tensor]:
        """``(xhat^-, P^-)`` and the drive ``w`` used, from ``y_{k+1}`` ``(B, l)`` and ``u_k``."""
        (x_pred, P_pred), w = self._predict(state, y, u, constants)
        return EKFState(x_pred, _symmetric(P_pred)), w

    def _predict(self, state, y, u, constants) -> tuple[EKFState, torch.Tensor]:
        """:meth:`predict` with ``P^-`` as computed, symmetric to rounding (:meth:`step`'s: the
        update reads one triangle of ``H P^- H^T`` and symmetrises its result)."""
        m = self.model
        x, P = state
        c = constants or self.constants(x.dtype, x.device)
        if self.jacobians == "analytic":
            x_pred, w, F, G = m.linearize_step(x, y, u)
        else:
            w = m.drive(x, y, u)
            x_pred = m.step(x, w)
            F, G = self.process_jacobians(x, y, u, x_pred)
        P_pred = _sandwich(F, P, _sandwich(G, c.Q))
        if c.Qe is not None:
            P_pred = P_pred.add_(c.Qe) if P_pred.shape == P.shape else P_pred + c.Qe
        return EKFState(x_pred, P_pred), w

    def update(
        self,
        state: EKFState,
        y: torch.Tensor,
        drive: torch.Tensor,
        gated: bool = True,
        constants=None,
    ) -> tuple[EKFState, torch.Tensor]:
        """``(xhat^+, P^+)`` and the NIS ``(B,)`` from ``y_{k+1}`` and the step's drive;
        ``gated=False`` leaves the gate (if any) out of this update."""
        c = constants or self.constants(state.x.dtype, state.x.device)
        x, P, nis, failed = self._update(state, y, drive, gated, c)
        _check_factored(failed)
        return EKFState(x, P), nis

    def _update(self, state, y, drive, gated, c):
        """:meth:`update`'s arithmetic: ``(x^+, P^+, nis, failed)``, ``failed`` a tensor (True
        where a Cholesky factorisation failed) in a compiled step, ``None`` in an eager one
        (which raises at once)."""
        g, m = self.group, self.model
        x, P = state
        if self.jacobians == "analytic":
            nu, H, M = m.linearize_measurement(x, drive, y)
        else:
            z_hat = m.measure(x, drive)
            nu = m.residual(m.observation(y), z_hat)
            H, M = self.measurement_jacobians(x, drive, z_hat, nu.shape[-1])
        Rn = c.Rn if M is None else _sandwich(M, c.Rn)
        sel = self._selection
        if sel is None:
            PHt = matmul(P, H.transpose(-1, -2))
            HPHt = matmul(H, PHt)
        else:  # H = I[sel]: P H^T is P's columns sel, H P H^T their rows sel
            PHt = P[..., sel]
            HPHt = PHt[..., sel, :]
        nu_col = nu.unsqueeze(-1)
        rhs = torch.cat((nu_col, PHt.transpose(-1, -2)), -1)  # [nu | H P]
        X, failed = _solve(HPHt + Rn, rhs)  # S^-1 [nu | H P]
        nis = (nu_col * X[..., :1]).sum((-1, -2))
        if gated and self.gate is not None:
            # an innovation beyond the gate: the measurement noise inflated by nis / gate
            # (compiled: always, by a factor of exactly 1 below the gate; no branch in a graph)
            compiling = torch.compiler.is_compiling()
            if compiling or bool((nis > self.gate).any()):
                Rn = Rn * (nis / self.gate).clamp(min=1.0)[..., None, None]
                X, failed_again = _solve(HPHt + Rn, rhs)
                failed = failed_again if failed is None else failed | failed_again
        delta = matmul(PHt, X[..., :1]).squeeze(-1)  # K nu
        K = X[..., 1:].transpose(-1, -2)  # P H^T S^-1
        if not self.reset:
            x_new, J = g.rplus(x, delta), None
        elif self.jacobians == "analytic":
            x_new, J = m.linearize_reset(x, delta)
        else:
            x_new, J = g.rplus(x, delta), None
        if J is None and self.reset:
            J = self.reset_jacobian(x, delta, x_new)
        # Joseph form and reset in one: J (A P A^T + K Rn K^T) J^T with A = I - K H is
        # (J A) P (J A)^T + (J K) Rn (J K)^T, and J A = J - (J K) H
        if J is None:
            J = c.eye
        else:
            K = matmul(J, K)
        if sel is None:
            JA = _minus_product(J, K, H)
        else:  # (J K) H: J K in the columns sel, zeros elsewhere
            JA = J - torch.nn.functional.pad(K, (sel.start, J.shape[-1] - sel.stop))
        return x_new, _symmetric(_sandwich(JA, P, _sandwich(K, Rn))), nis, failed

    def _step(self, x, P, y, u, gated, c):
        """One step on plain tensors, ``(x, P, nis, failed)``: what :meth:`step` runs, eager or
        compiled."""
        state, w = self._predict(EKFState(x, P), y, u, c)
        return self._update(state, y, w, gated, c)

    def step(
        self,
        state: EKFState,
        y: torch.Tensor,
        u: torch.Tensor,
        gated: bool = True,
        constants: EKFConstants | None = None,
    ) -> tuple[EKFState, torch.Tensor]:
        """One predict and update, ``k -> k+1``; returns the new state and the NIS.

        ``constants``: :meth:`constants` for the state's dtype and device, computed once for a
        loop of steps (default: computed here). With ``compile=True`` the step runs as one
        compiled graph (compiled at the first call, again for a new shape or dtype)."""
        c = constants or self.constants(state.x.dtype, state.x.device)
        step = self._step
        if self.compile:
            if self._compiled is None:
                logging.getLogger("torch._inductor.ir").addFilter(_no_shim_note)
                options = _COMPILE_OPTIONS
                self._compiled = torch.compile(self._step, dynamic=False, options=options)
            step = self._compiled
        x, P, nis, failed = step(state.x, state.P, y, u, gated, c)
        _check_factored(failed)
        return EKFState(x, P), nis

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
        consts = self.constants(dtype, device)
        xs, Ps, nis = [state.x], [state.P], []  # stacked after the loop: no copy per step
        t0 = time.perf_counter()
        with torch.inference_mode():  # the step's tensors are local, the stacks made outside
            ys, us = measurements.unbind(1), inputs.unbind(1)
            steps = progress(range(t), desc=f"{self.name} steps", enabled=self.progress, delay=2.0)
            for k in steps:
                state, nis_k = self.step(state, ys[k], us[k], k >= self.gate_after, consts)
                xs.append(state.x)
                nis.append(nis_k)
                if return_covariances:
                    Ps.append(state.P)
        nis = torch.stack(nis, 1) if nis else measurements.new_empty(n_seq, 0)
        cov = torch.stack(Ps, 1) if return_covariances else None
        return FilterResult(torch.stack(xs, 1), cov, nis, time.perf_counter() - t0)

    def estimate(self, data: TrajectoryDataset) -> torch.Tensor:
        """Estimates ``(N, T+1, *element_shape)`` on ``data`` (the baselines' common interface)."""
        return self.filter(data.measurements, data.inputs).estimates
