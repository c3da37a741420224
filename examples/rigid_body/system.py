"""The paper's rigid body (its Section 3) as a :class:`manifold_nets.system.System`.

State ``x = (R, p, b_Omega, b_v)``: attitude, world-frame position and the two turn-on biases.
Two groups for the same state (``pose_group``):

* ``"so3_r3"`` (default, the paper's): ``Product(SO3(), Euclidean(3), Euclidean(3),
  Euclidean(3), names=("R", "p", "b_omega", "b_v"))``, stored flat as the ``(18,)`` vector
  ``(vec R row-major, p, b_Omega, b_v)``, which is also its embedding. The direct product: an
  observer's update moves the position by addition in the world frame.
* ``"se3"``: ``Product(SE3(), Euclidean(3), Euclidean(3), names=("T", "b_omega", "b_v"))``,
  stored as the ``(22,)`` vector ``(vec T row-major (16), b_Omega, b_v)`` with the homogeneous
  ``T = [[R, p], [0, 1]]``. The pose on SE(3): an observer's update ``T exp(xi)`` moves the
  position in the body frame (through SO(3)'s left Jacobian).

Both embed a state as the same ``(vec R, p, b_Omega, b_v)`` in ``R^18`` (SE(3)'s embedding is
``(vec R, p)``), so the first 12 entries of a measurement are the measured pose's embedding in
either; one seed gives the same motion and the same measurements for both, and
:meth:`RigidBody.metrics` has the keys ``R``, ``p``, ``b_omega``, ``b_v`` for both. Everything
that reads a state goes through :meth:`RigidBody.rotation`, :meth:`~RigidBody.position`,
:meth:`~RigidBody.biases` and :meth:`~RigidBody.join`. Kinematics
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
:meth:`RigidBody.observe` is the noise-free measurement and :meth:`RigidBody.apply_noise` applies
``(w1, w2, w3, w4)`` to it (what noise-augmented training uses); ``measure(x, w, n)`` is
``apply_noise(observe(x, w), n)``.

``dt = 0.1`` s by default (the paper states none): the largest measured rate
``|Omega + b_Omega| <= sqrt(3) * 11`` then turns by at most 1.9 rad < pi in a step, so an
observer that integrates the biased reading never wraps the exponential. The constructor
refuses parameters that break this bound, ``sqrt(3) (omega_range + bias_range) dt < pi``.
"""

from __future__ import annotations

import functools
import math

import torch

from groups import SE3, SO3, Euclidean, Product
from manifold_nets.data import TrajectoryDataset
from manifold_nets.system import System, check_last_dim

from .kinematics import (
    exact_rollout_time_major,
    exact_step,
    rk45_rollout,
    sequence_major_into,
    time_major,
)

__all__ = ["POSE_GROUPS", "RigidBody"]

#: The groups a rigid-body state can live on; see the module docstring. The first is the default.
POSE_GROUPS = ("so3_r3", "se3")

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
    noise_dim = 12  # (w1, w2, w3, w4), 3 each

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
        pose_group: str = "so3_r3",
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
        if pose_group not in POSE_GROUPS:
            raise ValueError(
                f"RigidBody: pose_group must be one of {POSE_GROUPS} (so3_r3: the paper's direct "
                f"product SO(3) x R^3, position updated by addition in the world frame; se3: the "
                f"pose in SE(3), body-frame update), got {pose_group!r}."
            )
        self.dt = float(dt)
        self.integrator = integrator
        self.rtol, self.atol = float(rtol), float(atol)
        self.position_range = _check_nonneg("position_range", position_range)
        self.bias_range = _check_nonneg("bias_range", bias_range)
        self.omega_range = _check_nonneg("omega_range", omega_range)
        self.velocity_range = _check_nonneg("velocity_range", velocity_range)
        rate = math.sqrt(3.0) * (self.omega_range + self.bias_range)  # largest rate
        turn = rate * self.dt
        if not turn < math.pi:  # the bound of the module docstring
            raise ValueError(
                "RigidBody: one step can turn by up to sqrt(3) * (omega_range + bias_range) * dt "
                f"= sqrt(3) * ({self.omega_range:g} + {self.bias_range:g}) * {self.dt:g} = "
                f"{turn:.4g} rad, which must be < pi: an observer or filter that integrates the "
                "measured rate over a step would wrap the exponential. Use a smaller dt, "
                f"omega_range or bias_range (dt < {math.pi / rate:.4g} s for these ranges)."
            )
        self.pose_group = pose_group
        self._se3 = pose_group == "se3"
        if self._se3:
            self.group = Product(SE3(), Euclidean(3), Euclidean(3), names=("T", "b_omega", "b_v"))
        else:
            self.group = Product(
                SO3(), Euclidean(3), Euclidean(3), Euclidean(3), names=("R", "p", "b_omega", "b_v")
            )
        self._state_dim = self.group.element_shape[0]  # 18 or 22

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
        if self.pose_group != POSE_GROUPS[0]:  # so the default's cached datasets keep their hash
            cfg["pose_group"] = self.pose_group
        return cfg

    # ------------------------------------------------------------------ the state's layout

    def _check_state(self, x: torch.Tensor, where: str) -> None:
        _check_last(x, self._state_dim, f"state ({self.pose_group} layout) given to {where}")

    def rotation(self, x: torch.Tensor) -> torch.Tensor:
        """The attitude ``R`` ``(*batch, 3, 3)`` of states ``x`` ``(*batch, *element_shape)``
        (a view; no membership check)."""
        self._check_state(x, "rotation")
        if self._se3:
            return x[..., :12].unflatten(-1, (3, 4))[..., :3]
        return x[..., :9].unflatten(-1, (3, 3))

    def position(self, x: torch.Tensor) -> torch.Tensor:
        """The world-frame position ``p`` ``(*batch, 3)`` of states ``x`` (a view)."""
        self._check_state(x, "position")
        return x[..., 3:12:4] if self._se3 else x[..., 9:12]

    def biases(self, x: torch.Tensor) -> torch.Tensor:
        """The biases ``(b_Omega, b_v)`` ``(*batch, 6)`` of states ``x`` (a view)."""
        self._check_state(x, "biases")
        return x[..., -6:]

    def join(self, R: torch.Tensor, p: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """The flat state ``(*batch, *element_shape)`` from ``R`` ``(*batch, 3, 3)``, ``p``
        ``(*batch, 3)`` and ``b = (b_Omega, b_v)`` ``(*batch, 6)`` (batch dimensions broadcast).
        """
        if not isinstance(R, torch.Tensor) or R.dim() < 2 or R.shape[-2:] != (3, 3):
            shape = tuple(R.shape) if isinstance(R, torch.Tensor) else type(R).__name__
            raise ValueError(f"RigidBody.join expects R of shape (*batch, 3, 3), got {shape}.")
        _check_last(p, 3, "position p")
        _check_last(b, 6, "biases (b_Omega, b_v)")
        if not self._se3:
            return _cat(R.flatten(-2), p, b)
        batch = torch.broadcast_shapes(R.shape[:-2], p.shape[:-1], b.shape[:-1])
        top = torch.cat((R.expand(*batch, 3, 3), p.expand(*batch, 3).unsqueeze(-1)), dim=-1)
        bottom = torch.tensor((0.0, 0.0, 0.0, 1.0), dtype=top.dtype, device=top.device)
        return torch.cat(
            (top.flatten(-2), bottom.expand(*batch, 4), b.expand(*batch, 6).to(top)), dim=-1
        )

    def _pose_embedding(self, x: torch.Tensor) -> torch.Tensor:
        """``(vec R, p)`` ``(*batch, 12)``: the measured part of ``y`` (both groups' embedding)."""
        if self._se3:
            T = x[..., :12].unflatten(-1, (3, 4))
            return torch.cat((T[..., :3].flatten(-2), T[..., 3]), dim=-1)
        return x[..., :12]

    # ------------------------------------------------------------------ random laws

    def sample_initial_state(self, num_sequences: int, generator: torch.Generator) -> torch.Tensor:
        """``(N, *element_shape)``: Haar ``R_0``, ``p_0 ~ U[-a, a]^3``, ``(b_Omega, b_v) ~
        U[-b, b]^6`` (the same draws for every ``pose_group``)."""
        R = _SO3.random((num_sequences,), generator=generator, dtype=_DTYPE)
        p = torch.empty(num_sequences, 3, dtype=_DTYPE)
        p.uniform_(-self.position_range, self.position_range, generator=generator)
        b = torch.empty(num_sequences, 6, dtype=_DTYPE)
        b.uniform_(-self.bias_range, self.bias_range, generator=generator)
        return self.join(R, p, b)

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

        ``x`` ``(*batch, *element_shape)``, ``drive`` ``(*batch, 6)``; differentiable (an EKF can
        linearise it). The same motion for both layouts (on SE(3) it is ``T exp((v, Omega) dt)``).
        """
        self.group.check_element(x, "step")
        _check_last(drive, 6, "drive (Omega, v)")
        dt = self.dt if dt is None else dt
        R1, p1 = exact_step(self.rotation(x), self.position(x), drive[..., :3], drive[..., 3:], dt)
        return self.join(R1, p1, self.biases(x))

    def _time_major_pose(self, buf: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Views ``R`` ``(T+1, 3, 3, N)`` and ``p`` ``(T+1, 3, N)`` of a ``(T+1, d, N)`` buffer."""
        if self._se3:
            T = buf[:, :12].unflatten(1, (3, 4))
            return T[:, :, :3], T[:, :, 3]
        return buf[:, :9].unflatten(1, (3, 3)), buf[:, 9:12]

    def rollout(
        self, x0: torch.Tensor, drive: torch.Tensor, show_progress: bool = False
    ) -> torch.Tensor:
        """``(N, T+1, *element_shape)``; exact: the closed form over all sequences at once, in a
        time-major buffer of the state's own layout; rk45: solve_ivp."""
        n, t = drive.shape[:2]
        d = self._state_dim
        if self.integrator == "rk45":
            R, p = rk45_rollout(
                self.rotation(x0), self.position(x0), drive[..., :3], drive[..., 3:], self.dt,
                self.rtol, self.atol, project=True, show_progress=show_progress,
            )
            return self.join(R, p, self.biases(x0)[:, None].expand(n, t + 1, 6))
        # time- and component-major work buffer (T+1, d, N), transposed into place once
        buf = x0.new_empty(t + 1, d, n)
        buf[0] = x0.transpose(0, 1)
        buf[1:, d - 6 :] = x0[:, d - 6 :].transpose(0, 1)  # the biases are constant
        if self._se3:  # the bottom row of T
            buf[1:, 12:15] = 0.0
            buf[1:, 15] = 1.0
        w = drive.permute(1, 2, 0)  # (T, 6, N)
        if not w.is_contiguous():
            w = time_major(drive)
        R, p = self._time_major_pose(buf)
        exact_rollout_time_major(w[:, :3], w[:, 3:], self.dt, R, p, show_progress=show_progress)
        return sequence_major_into(buf, x0.new_empty(n, t + 1, d))

    # ------------------------------------------------------------------ measurements

    def observe(self, x: torch.Tensor, drive: torch.Tensor) -> torch.Tensor:
        """The noise-free ``(vec R, p, Omega + b_Omega, v + b_v)``, ``(*batch, 18)``.

        ``measure(x, w, noise)`` (derived by :class:`~manifold_nets.system.System`) is
        :meth:`apply_noise` of it: ``(vec R exp([w1]x), p + w2, Omega + b_Omega + w3, v + b_v +
        w4)``.
        """
        self.group.check_element(x, "measure")
        _check_last(drive, 6, "drive (Omega, v)")
        return _cat(self._pose_embedding(x), drive + self.biases(x))  # Omega + b_Omega, v + b_v

    def apply_noise(self, measurements: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Noise-free measurements ``(*batch, 18)`` with ``noise = (w1, w2, w3, w4)``
        ``(*batch, 12)`` (already times sigma) applied: ``(vec(R^m exp([w1]x)), p^m + w2,
        Omega^m + w3, v^m + w4)``, ``(*batch, 18)`` (batch dimensions broadcast, dtypes promote).

        ``measure(x, w, n)`` is ``apply_noise(observe(x, w), n)``. Used by noise-augmented
        training (``train.noise.sigma_max > 0``).
        """
        _check_last(measurements, 18, "measurements")
        _check_last(noise, 12, "noise (w1, w2, w3, w4)")
        dtype = torch.promote_types(measurements.dtype, noise.dtype)
        y, w = measurements.to(dtype), noise.to(dtype)
        Rm = (y[..., :9].unflatten(-1, (3, 3)) @ _SO3.exp(w[..., :3])).flatten(-2)
        return _cat(Rm, y[..., 9:] + w[..., 3:])

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

    # ------------------------------------------------------------------ evaluation

    def state_from_measurement(self, y: torch.Tensor) -> torch.Tensor:
        """``(R^m, p^m, 0, 0)``, ``(*batch, *element_shape)``: the measured pose; the biases are
        not measured."""
        _check_last(y, 18, "measurement")
        R = y[..., :9].unflatten(-1, (3, 3))
        return self.join(R, y[..., 9:12], torch.zeros_like(y[..., 12:]))

    def drive_from_measurement(self, y: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The velocity readings ``(Omega^m_k, v^m_k)`` of ``y_{k+1}``, with biases and noise."""
        _check_last(y, 18, "measurement")
        return y[..., 12:]

    def compensated_drive(
        self, x: torch.Tensor, y: torch.Tensor, u: torch.Tensor | None
    ) -> torch.Tensor:
        """The bias-corrected readings ``(Omega^m - bhat_Omega, v^m - bhat_v)``, ``(*batch, 6)``:
        what :meth:`~manifold_nets.system.System.predict` steps with, the biases kept (an EKF's
        predict step)."""
        return self.drive_from_measurement(y, u) - self.biases(x)

    def metrics(self, estimates: torch.Tensor, data: TrajectoryDataset) -> dict[str, torch.Tensor]:
        """``R`` (``||Rhat - R||_F``), ``p`` (``||phat - p||``), ``b_omega``, ``b_v`` (vector
        norms), each ``(N, T')``, for either ``pose_group``. Estimates need not be on the group.

        For ``so3_r3`` these are :meth:`System.metrics`'s per-factor embedding errors; for
        ``se3`` the ``T`` factor's error is split into ``R`` and ``p``.
        """
        out = super().metrics(estimates, data)  # checks the shapes
        if not self._se3:
            return out
        states = data.states.to(dtype=estimates.dtype, device=estimates.device)
        if estimates.shape[1] == states.shape[1] - 1:
            states = states[:, 1:]
        diff = self._pose_embedding(estimates) - self._pose_embedding(states)
        return {
            "R": torch.linalg.vector_norm(diff[..., :9], dim=-1),
            "p": torch.linalg.vector_norm(diff[..., 9:], dim=-1),
            "b_omega": out["b_omega"],
            "b_v": out["b_v"],
        }

    def estimators(self) -> dict:
        """``raw``, ``dead_reckoning`` and, on the paper's group (``pose_group='so3_r3'``), ``ekf``
        (:class:`~.filters.RigidBodyEKF`, the nominal model and noise level ``sigma``),
        ``ekf_tuned`` (the same model with its noise levels searched on data of this system,
        :meth:`~.filters.RigidBodyEKF.tuned`), ``ekf_robust`` (the nominal EKF with an innovation
        gate, :meth:`~.filters.RigidBodyEKF.robust`) and ``complementary``
        (:meth:`~.filters.ComplementaryFilter.tuned`, gains searched per sigma), for
        ``method=<name>``."""
        out = super().estimators()
        if self.pose_group == "so3_r3":
            from .filters import ComplementaryFilter, RigidBodyEKF

            out.update(
                ekf=RigidBodyEKF,
                ekf_tuned=RigidBodyEKF.tuned,
                ekf_robust=RigidBodyEKF.robust,
                complementary=ComplementaryFilter.tuned,
            )
        return out

    def measurement_errors(self, data: TrajectoryDataset) -> dict[str, torch.Tensor]:
        """``||R^m - R||_F`` and ``||p^m - p||`` per step, ``(N, T)`` each: the paper's baseline."""
        pose, y = self._pose_embedding(data.states[:, 1:]), data.measurements
        return {
            "R": torch.linalg.vector_norm(y[..., :9] - pose[..., :9], dim=-1),
            "p": torch.linalg.vector_norm(y[..., 9:12] - pose[..., 9:], dim=-1),
        }
