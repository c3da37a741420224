"""The paper's rigid body (its Section 3) as a :class:`manifold_nets.system.System`.

State ``x = (R, p, b_Omega, b_v)`` on ``SO(3) x R^3 x R^3 x R^3``, stored flat as the ``(18,)``
vector ``(vec R row-major, p, b_Omega, b_v)``, which is also its embedding. Kinematics
``dR/dt = R [Omega]x``, ``dp/dt = R v`` with the body velocities ``Omega, v ~ U[-1, 1]^3`` drawn
at every step and held over it (the drive ``w_k = (Omega_k, v_k)``, ``drive_dim = 6``); the
turn-on biases are constant over a sequence.

Laws (defaults; every range is a parameter):

* ``R_0`` uniform (Haar) on SO(3); ``p_0 ~ U[-1, 1]^3``; ``b_Omega, b_v ~ U[-10, 10]^3``,
  one draw per sequence;
* ``Omega_k, v_k ~ U[-1, 1]^3`` independently at every step.

Measurement ``y_{k+1} = (vec R^m_{k+1}, p^m_{k+1}, Omega^m_k, v^m_k)`` in ``R^18`` with
``R^m = R exp([w1]x)``, ``p^m = p + w2``, ``Omega^m = Omega + b_Omega + w3``,
``v^m = v + b_v + w4``, ``w_i ~ N(0, sigma^2 I_3)`` (``noise_dim = 12``): the velocity reading in
``y_{k+1}`` is the one applied over the step ``k -> k+1``. No control input (``input_dim = 0``).

``dt = 0.1`` s by default (the paper states none): the largest measured rate
``|Omega + b_Omega| <= sqrt(3) * 11`` then turns by at most 1.9 rad < pi in a step, so an
observer that integrates the biased reading never wraps the exponential.
"""

from __future__ import annotations

import functools
import math

import torch

from groups import SO3, Euclidean, Product

from manifold_nets.data import TrajectoryDataset
from manifold_nets.system import System, check_last_dim

from .kinematics import (
    exact_rollout_time_major,
    exact_step,
    rk45_rollout,
    sequence_major_into,
    time_major,
)

__all__ = ["RigidBody"]

_DTYPE = torch.float64
_SO3 = SO3()
_INTEGRATORS = ("exact", "rk45")


def _cat(*parts: torch.Tensor) -> torch.Tensor:
    """Concatenates on the last dimension after broadcasting the batch dimensions."""
    batch = torch.broadcast_shapes(*(q.shape[:-1] for q in parts))
    return torch.cat([q.expand(*batch, q.shape[-1]) for q in parts], dim=-1)


_check_last = functools.partial(check_last_dim, "RigidBody")


def _check_nonneg(name: str, value: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value < math.inf:
        raise ValueError(f"RigidBody: {name} must be a number >= 0, got {value!r}.")
    return float(value)


class RigidBody(System):
    """The rigid body of the paper; see the module docstring for the laws and the layouts."""

    name = "rigid_body"
    measurement_dim = 18
    input_dim = 0
    drive_dim = 6
    noise_dim = 12

    def __init__(
        self,
        dt: float = 0.1,
        integrator: str = "exact",
        rtol: float = 1e-10,
        atol: float = 1e-10,
        position_range: float = 1.0,
        bias_range: float = 10.0,
        omega_range: float = 1.0,
        velocity_range: float = 1.0,
    ):
        if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not 0 < dt < math.inf:
            raise ValueError(
                f"RigidBody: dt is the step length in seconds and must be finite and > 0, "
                f"got {dt!r}."
            )
        if integrator not in _INTEGRATORS:
            raise ValueError(
                f"RigidBody: integrator must be one of {_INTEGRATORS} (exact: closed form; rk45: "
                f"scipy's solve_ivp reference), got {integrator!r}."
            )
        for name, tol in (("rtol", rtol), ("atol", atol)):
            if isinstance(tol, bool) or not isinstance(tol, (int, float)) or not tol > 0:
                raise ValueError(f"RigidBody: {name} must be > 0, got {tol!r}.")
        self.dt = float(dt)
        self.integrator = integrator
        self.rtol, self.atol = float(rtol), float(atol)
        self.position_range = _check_nonneg("position_range", position_range)
        self.bias_range = _check_nonneg("bias_range", bias_range)
        self.omega_range = _check_nonneg("omega_range", omega_range)
        self.velocity_range = _check_nonneg("velocity_range", velocity_range)
        self.group = Product(
            SO3(), Euclidean(3), Euclidean(3), Euclidean(3), names=("R", "p", "b_omega", "b_v")
        )

    def config(self) -> dict:
        cfg = {
            "dt": self.dt,
            "integrator": self.integrator,
            "position_range": self.position_range,
            "bias_range": self.bias_range,
            "omega_range": self.omega_range,
            "velocity_range": self.velocity_range,
        }
        if self.integrator == "rk45":  # the tolerances only matter to RK45
            cfg.update(rtol=self.rtol, atol=self.atol)
        return cfg

    # ------------------------------------------------------------------ random laws

    def sample_initial_state(self, num_sequences: int, generator: torch.Generator) -> torch.Tensor:
        """``(N, 18)``: Haar ``R_0``, ``p_0 ~ U[-a, a]^3``, ``(b_Omega, b_v) ~ U[-b, b]^6``."""
        R = _SO3.random((num_sequences,), generator=generator, dtype=_DTYPE)
        p = torch.empty(num_sequences, 3, dtype=_DTYPE)
        p.uniform_(-self.position_range, self.position_range, generator=generator)
        b = torch.empty(num_sequences, 6, dtype=_DTYPE)
        b.uniform_(-self.bias_range, self.bias_range, generator=generator)
        return torch.cat((R.flatten(-2), p, b), dim=-1)

    def sample_drive(
        self, num_sequences: int, length: int, generator: torch.Generator
    ) -> torch.Tensor:
        """``(N, T, 6)``: ``(Omega_k, v_k)``, ``Omega ~ U[-r_w, r_w]^3``, ``v ~ U[-r_v, r_v]^3``.

        Drawn in time-major order, ``(T, 6, N)`` in memory (the layout :meth:`rollout` works in),
        and returned as an ``(N, T, 6)`` view of it.
        """
        w = torch.empty(length, 6, num_sequences, dtype=_DTYPE)
        w.uniform_(-1.0, 1.0, generator=generator)
        if self.omega_range != 1.0:
            w[:, :3] *= self.omega_range
        if self.velocity_range != 1.0:
            w[:, 3:] *= self.velocity_range
        return w.permute(2, 0, 1)

    # ------------------------------------------------------------------ dynamics

    def step(self, x: torch.Tensor, drive: torch.Tensor, dt: float | None = None) -> torch.Tensor:
        """The exact step: ``R' = R exp(Omega dt)``, ``p' = p + R J_l(Omega dt) v dt``, biases kept.

        ``x`` ``(*batch, 18)``, ``drive`` ``(*batch, 6)``; differentiable (an EKF can linearise it).
        """
        self.group._check_element(x, "step")
        _check_last(drive, 6, "drive (Omega, v)")
        dt = self.dt if dt is None else dt
        R, p = x[..., :9].unflatten(-1, (3, 3)), x[..., 9:12]
        R1, p1 = exact_step(R, p, drive[..., :3], drive[..., 3:], dt)
        return _cat(R1.flatten(-2), p1, x[..., 12:])

    def rollout(
        self, x0: torch.Tensor, drive: torch.Tensor, show_progress: bool = False
    ) -> torch.Tensor:
        """``(N, T+1, 18)``; exact: the closed form over all sequences at once; rk45: solve_ivp."""
        n, t = drive.shape[:2]
        R0, p0 = x0[:, :9].unflatten(-1, (3, 3)), x0[:, 9:12]
        if self.integrator == "rk45":
            R, p = rk45_rollout(
                R0, p0, drive[..., :3], drive[..., 3:], self.dt, self.rtol, self.atol,
                project=True, show_progress=show_progress,
            )
            return torch.cat((R.flatten(-2), p, x0[:, None, 12:].expand(n, t + 1, 6)), dim=-1)
        # time- and component-major work buffer (T+1, 18, N), transposed into place once
        buf = x0.new_empty(t + 1, 18, n)
        buf[0] = x0.transpose(0, 1)
        buf[1:, 12:] = x0[:, 12:].transpose(0, 1)  # the biases are constant
        w = drive.permute(1, 2, 0)  # (T, 6, N)
        if not w.is_contiguous():
            w = time_major(drive)
        exact_rollout_time_major(
            w[:, :3], w[:, 3:], self.dt, buf[:, :9].unflatten(1, (3, 3)), buf[:, 9:12],
            show_progress=show_progress,
        )
        return sequence_major_into(buf, x0.new_empty(n, t + 1, 18))

    # ------------------------------------------------------------------ measurements

    def measure(
        self, x: torch.Tensor, drive: torch.Tensor, noise: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``(vec R exp([w1]x), p + w2, Omega + b_Omega + w3, v + b_v + w4)``, ``(*batch, 18)``."""
        self.group._check_element(x, "measure")
        _check_last(drive, 6, "drive (Omega, v)")
        rates = drive + x[..., 12:]  # Omega + b_Omega, v + b_v
        if noise is None:
            return _cat(x[..., :12], rates)
        _check_last(noise, 12, "noise (w1, w2, w3, w4)")
        R = x[..., :9].unflatten(-1, (3, 3))
        Rm = (R @ _SO3.exp(noise[..., :3])).flatten(-2)
        return _cat(Rm, x[..., 9:12] + noise[..., 3:6], rates + noise[..., 6:])

    def measurement_residual(self, y: torch.Tensor, y_hat: torch.Tensor) -> torch.Tensor:
        """``(log(Rhat^T R^m), p^m - phat, Omega^m - Omegahat^m, v^m - vhat^m)``, ``(*batch, 12)``.

        The rotation is compared on SO(3), in the tangent at the predicted ``Rhat`` (a right
        difference, like the noise ``R^m = R exp([w1]x)``), so the residual is ``w1`` itself to
        first order; the rest are plain differences. ``y_hat``'s rotation part must be a rotation.
        """
        _check_last(y, 18, "measurement")
        _check_last(y_hat, 18, "predicted measurement")
        Rm = y[..., :9].unflatten(-1, (3, 3))
        Rhat = y_hat[..., :9].unflatten(-1, (3, 3))
        return _cat(_SO3.log(Rhat.transpose(-1, -2) @ Rm), y[..., 9:] - y_hat[..., 9:])

    def state_from_measurement(self, y: torch.Tensor) -> torch.Tensor:
        """``(R^m, p^m, 0, 0)``, ``(*batch, 18)``: the measured pose; the biases are not measured."""
        _check_last(y, 18, "measurement")
        return torch.cat((y[..., :12], torch.zeros_like(y[..., 12:])), dim=-1)

    def drive_from_measurement(self, y: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The velocity readings ``(Omega^m_k, v^m_k)`` of ``y_{k+1}``, biases and noise included."""
        _check_last(y, 18, "measurement")
        return y[..., 12:]

    def measurement_errors(self, data: TrajectoryDataset) -> dict[str, torch.Tensor]:
        """``||R^m - R||_F`` and ``||p^m - p||`` per step, ``(N, T)`` each: the paper's baseline."""
        x, y = data.states[:, 1:], data.measurements
        return {
            "R": torch.linalg.vector_norm(y[..., :9] - x[..., :9], dim=-1),
            "p": torch.linalg.vector_norm(y[..., 9:12] - x[..., 9:12], dim=-1),
        }
