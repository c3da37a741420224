"""A planar vehicle on SE(2) x R x R: pose and odometry biases from GPS-like position fixes.

State: the pose ``T = [[R(theta), p], [0, 1]]`` (``p`` the position in metres in the world
frame, ``theta`` the heading from the world x axis) and the odometry biases ``b_v`` (m/s) and
``b_omega`` (rad/s). Two groups for the same state (``pose_group``):

* ``"se2"`` (default): ``Product(SE2(), Euclidean(1), Euclidean(1), names=("pose", "b_v",
  "b_omega"))``, stored flat as the ``(11,)`` vector ``(vec T row-major (9), b_v, b_omega)``.
  The group of the motion: the observer's update ``T exp(v)`` is a body-frame correction.
* ``"so2_r2"``: ``Product(SO2(), Euclidean(2), Euclidean(1), Euclidean(1), names=("R", "p",
  "b_v", "b_omega"))``, stored as ``(vec R (4), p (2), b_v, b_omega)``, ``(8,)``: the direct
  product, like the paper's SO(3) x R^3 for the rigid body; the position is updated by addition
  in the world frame.

Both embed a state as the same ``(R00, R01, R10, R11, p_x, p_y, b_v, b_omega)`` in ``R^8``, so
losses and metrics compare them directly; the simulated motion and measurements are identical.

Dynamics: a unicycle, ``dp/dt = v (cos theta, sin theta)``, ``dtheta/dt = omega``, with the
forward speed ``v_k`` and the turn rate ``omega_k`` held over the step. That is the constant
body twist ``(v, 0, omega)`` of SE(2), so the step is exact::

    T_{k+1} = T_k exp((v_k dt, 0, omega_k dt)),        b_{k+1} = b_k    (constant turn-on biases)

The drive is ``w_k = (v_k, omega_k)`` (``drive_dim = 2``), smooth random profiles
(:mod:`manifold_nets_examples.attitude.motion`, sums of random sinusoids ``s(t)``): the vehicle
always drives forward, ``v = v_mean exp(s_v(t))`` with a per-sequence cruising speed
``v_mean ~ U[speed_min, speed_max]`` and a relative variation ``s_v`` of root mean square
``speed_variation`` (0.2: about +-20 %); ``omega = s_omega(t)`` of root mean square
``turn_rate_rms``; both with ``num_terms`` sinusoids of frequencies in ``[freq_min, freq_max]``
Hz.

Measurement ``y_{k+1}`` in ``R^4``: a GPS-like position fix and the odometry readings applied
over the step ``k -> k+1`` (the paper's pairing)::

    y_{k+1} = (p_{k+1} + s_p n1,  v_k + b_v + s_v n2,  omega_k + b_omega + s_w n3),

``n ~ N(0, sigma^2 I_4)`` (``noise_dim = 4``; ``n1`` is 2-D), ``s_*`` per-sensor scales
(default 1: at ``sigma = 0.1`` a 10 cm fix, 0.1 m/s and 0.1 rad/s odometry noise). The heading
is never measured: it must be inferred from the way the fixes move. No separate input
(``input_dim = 0``): the odometry is part of ``y``.

Laws (defaults; each a parameter): ``p_0 ~ U[-position_range, position_range]^2`` with 2 m,
``theta_0 ~ U(-pi, pi]``; ``b_v ~ U[-0.2, 0.2]`` m/s and ``b_omega ~ U[-0.1, 0.1]`` rad/s, one
draw per sequence; ``v_mean ~ U[0.5, 1.5]`` m/s, ``speed_variation = 0.2``, ``turn_rate_rms =
0.5`` rad/s, frequencies in ``[0.02, 0.5]`` Hz; ``dt = 0.1`` s (10 Hz fixes).

Step bound: the measured turn rate ``omega + b_omega`` turns the heading by at most
``(4 turn_rate_rms + turn_rate_bias_range) dt`` in a step (0.21 rad by default), and the
constructor refuses parameters making this ``>= pi``. The sinusoids have no hard bound
(Gaussian amplitudes), so ``4 turn_rate_rms`` is a stated conservative peak
(:data:`~manifold_nets_examples.attitude.motion.PEAK_OVER_RMS`), not a guarantee.

Raw baselines (:meth:`Planar.measurement_errors`): the fix itself for the position, and the
course over ground (the direction from the previous fix to the current one) for the heading.
:meth:`Planar.state_from_measurement` reads the pose at the fix (heading 0, zero biases) and
:meth:`Planar.drive_from_measurement` the biased odometry, for dead reckoning.
"""

from __future__ import annotations

import functools
import math

import torch

from manifold_nets_examples.attitude.motion import (
    check_frequencies,
    check_turn_per_step,
    random_sinusoids,
)
from groups import SE2, SO2, Euclidean, Product
from manifold_nets.data import TrajectoryDataset
from manifold_nets.system import System, check_last_dim, check_number

__all__ = ["POSE_GROUPS", "Planar", "course_over_ground"]

#: The groups a planar state can live on; see the module docstring.
POSE_GROUPS = ("se2", "so2_r2")

_DTYPE = torch.float64
_SE2 = SE2()
_DEG = 180.0 / math.pi


_check_last = functools.partial(check_last_dim, "Planar")


_number = functools.partial(check_number, "Planar")


def _wrap(angle: torch.Tensor) -> torch.Tensor:
    """An angle difference wrapped to ``[-pi, pi]``."""
    return torch.atan2(torch.sin(angle), torch.cos(angle))


def course_over_ground(fixes: torch.Tensor) -> torch.Tensor:
    """The direction of travel between consecutive fixes, ``(N, T, 2) -> (N, T)`` radians.

    Entry ``k`` is the direction from fix ``k-1`` to fix ``k``; entry 0 (no previous fix)
    repeats entry 1. Needs ``T >= 2``.
    """
    if fixes.dim() != 3 or fixes.shape[-1] != 2 or fixes.shape[1] < 2:
        raise ValueError(
            f"course_over_ground expects fixes (N, T >= 2, 2), got {tuple(fixes.shape)}."
        )
    d = fixes[:, 1:] - fixes[:, :-1]
    cog = torch.atan2(d[..., 1], d[..., 0])
    return torch.cat((cog[:, :1], cog), dim=1)


class Planar(System):
    """The planar vehicle; see the module docstring for the model, the laws and the layouts."""

    name = "planar"
    measurement_dim = 4
    input_dim = 0
    drive_dim = 2
    noise_dim = 4

    def __init__(
        self,
        dt: float = 0.1,
        position_range: float = 2.0,
        speed_min: float = 0.5,
        speed_max: float = 1.5,
        speed_variation: float = 0.2,
        turn_rate_rms: float = 0.5,
        freq_min: float = 0.02,
        freq_max: float = 0.5,
        num_terms: int = 3,
        speed_bias_range: float = 0.2,
        turn_rate_bias_range: float = 0.1,
        gps_noise: float = 1.0,
        speed_noise: float = 1.0,
        turn_rate_noise: float = 1.0,
        pose_group: str = "se2",
    ):
        self.dt = _number("dt (the step length in seconds)", dt, positive=True)
        self.position_range = _number("position_range", position_range)
        self.speed_min = _number("speed_min", speed_min, positive=True)
        self.speed_max = _number("speed_max", speed_max, positive=True)
        if self.speed_min > self.speed_max:
            raise ValueError(
                f"Planar: the cruising speed is drawn from U[speed_min, speed_max]; need "
                f"speed_min <= speed_max, got {speed_min!r}, {speed_max!r}."
            )
        self.speed_variation = _number("speed_variation", speed_variation)
        self.turn_rate_rms = _number("turn_rate_rms", turn_rate_rms)
        check_frequencies("Planar", freq_min, freq_max, self.dt)
        self.freq_min, self.freq_max = float(freq_min), float(freq_max)
        if isinstance(num_terms, bool) or not isinstance(num_terms, int) or num_terms < 1:
            raise ValueError(f"Planar: num_terms must be a positive integer, got {num_terms!r}.")
        self.num_terms = num_terms
        self.speed_bias_range = _number("speed_bias_range", speed_bias_range)
        self.turn_rate_bias_range = _number("turn_rate_bias_range", turn_rate_bias_range)
        check_turn_per_step(
            "Planar", self.dt, "turn_rate_rms", self.turn_rate_rms,
            "turn_rate_bias_range", self.turn_rate_bias_range, 1,
        )  # fmt: skip
        self.gps_noise = _number("gps_noise", gps_noise)
        self.speed_noise = _number("speed_noise", speed_noise)
        self.turn_rate_noise = _number("turn_rate_noise", turn_rate_noise)
        if pose_group not in POSE_GROUPS:
            raise ValueError(
                f"Planar: pose_group must be one of {POSE_GROUPS} (se2: the pose in SE(2); "
                f"so2_r2: heading and position as the direct product SO(2) x R^2), got "
                f"{pose_group!r}."
            )
        self.pose_group = pose_group
        if pose_group == "se2":
            self.group = Product(
                SE2(), Euclidean(1), Euclidean(1), names=("pose", "b_v", "b_omega")
            )
            self._cos_sin, self._position = (0, 3), [2, 5]
        else:
            self.group = Product(
                SO2(), Euclidean(2), Euclidean(1), Euclidean(1), names=("R", "p", "b_v", "b_omega")
            )
            self._cos_sin, self._position = (0, 2), [4, 5]

    def config(self) -> dict:
        keys = (
            "dt", "position_range", "speed_min", "speed_max", "speed_variation", "turn_rate_rms",
            "freq_min", "freq_max", "num_terms", "speed_bias_range", "turn_rate_bias_range",
            "gps_noise", "speed_noise", "turn_rate_noise", "pose_group",
        )
        return {k: getattr(self, k) for k in keys}

    # ------------------------------------------------------------------ the state's layout

    def rotation(self, x: torch.Tensor) -> torch.Tensor:
        """The heading as a rotation ``R(theta)`` ``(*batch, 2, 2)`` of states ``x``."""
        if self.pose_group == "se2":
            return x[..., :9].unflatten(-1, (3, 3))[..., :2, :2]
        return x[..., :4].unflatten(-1, (2, 2))

    def position(self, x: torch.Tensor) -> torch.Tensor:
        """The position ``p`` ``(*batch, 2)`` (metres, world frame) of states ``x``."""
        return x[..., self._position]

    def heading(self, x: torch.Tensor) -> torch.Tensor:
        """The heading ``theta = atan2(R10, R00)`` in ``(-pi, pi]`` of states ``x``."""
        c, s = self._cos_sin
        return torch.atan2(x[..., s], x[..., c])

    def join(self, R: torch.Tensor, p: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """The flat state from ``R`` ``(*batch, 2, 2)``, ``p`` and ``b = (b_v, b_omega)``
        ``(*batch, 2)`` each (batch dimensions broadcast)."""
        batch = torch.broadcast_shapes(R.shape[:-2], p.shape[:-1], b.shape[:-1])
        R, p, b = R.expand(*batch, 2, 2), p.expand(*batch, 2), b.expand(*batch, 2)
        if self.pose_group == "so2_r2":
            return torch.cat((R.flatten(-2), p, b), dim=-1)
        o, i = torch.zeros_like(p[..., 0]), torch.ones_like(p[..., 0])
        T = torch.stack(
            (R[..., 0, 0], R[..., 0, 1], p[..., 0], R[..., 1, 0], R[..., 1, 1], p[..., 1], o, o, i),
            dim=-1,
        )
        return torch.cat((T, b), dim=-1)

    # ------------------------------------------------------------------ random laws

    def sample_initial_state(self, num_sequences: int, generator: torch.Generator) -> torch.Tensor:
        """``(N, *element_shape)``: ``p_0`` uniform in the square, ``theta_0`` uniform, the
        turn-on biases."""
        n = num_sequences
        u = torch.rand(n, 5, generator=generator, dtype=_DTYPE) * 2 - 1  # U[-1, 1)
        p = u[:, :2] * self.position_range
        theta = -u[:, 2] * math.pi  # U(-pi, pi]
        b = u[:, 3:5] * torch.tensor([self.speed_bias_range, self.turn_rate_bias_range],
                                     dtype=_DTYPE)
        c, s = torch.cos(theta), torch.sin(theta)
        R = torch.stack((c, -s, s, c), dim=-1).unflatten(-1, (2, 2))
        return self.join(R, p, b)

    def sample_drive(
        self, num_sequences: int, length: int, generator: torch.Generator
    ) -> torch.Tensor:
        """``(N, T, 2)``: ``(v_k, omega_k)``, ``v = v_mean exp(s_v)``, ``omega = s_omega``."""
        v_mean = torch.empty(num_sequences, 1, 1, dtype=_DTYPE)
        v_mean.uniform_(self.speed_min, self.speed_max, generator=generator)
        rms = torch.tensor([self.speed_variation, self.turn_rate_rms], dtype=_DTYPE)
        w = random_sinusoids(
            num_sequences, length, 2, self.dt, rms, self.freq_min, self.freq_max,
            self.num_terms, generator,
        )
        w[..., :1] = v_mean * torch.exp(w[..., :1])
        return w

    # ------------------------------------------------------------------ dynamics

    def step(self, x: torch.Tensor, drive: torch.Tensor, dt: float | None = None) -> torch.Tensor:
        """``T' = T exp((v dt, 0, omega dt))``, biases kept; ``x`` ``(*batch, *element_shape)``,
        ``drive`` ``(*batch, 2)``. Exact for a held ``(v, omega)``; differentiable.

        With ``exp((v dt, 0, omega dt)) = [[R_inc, t_inc], [0, 1]]``: ``R' = R R_inc``,
        ``p' = p + R t_inc`` (the same product for both layouts)."""
        self.group.check_element(x, "step")
        _check_last(drive, 2, "drive (v, omega)")
        dt = self.dt if dt is None else dt
        v, w = drive.unbind(-1)
        inc = _SE2.exp(torch.stack((v * dt, torch.zeros_like(v), w * dt), dim=-1))
        R = self.rotation(x)
        R1 = R @ inc[..., :2, :2]
        p1 = self.position(x) + (R @ inc[..., :2, 2:]).squeeze(-1)
        return self.join(R1, p1, x[..., -2:])

    # ------------------------------------------------------------------ measurements

    def observe(self, x: torch.Tensor, drive: torch.Tensor) -> torch.Tensor:
        """The noise-free ``(p, v + b_v, omega + b_omega)``, ``(*batch, 4)``; ``measure(x, w,
        n)`` adds :meth:`apply_noise`'s ``(s_p n1, s_v n2, s_w n3)``."""
        self.group.check_element(x, "measure")
        _check_last(drive, 2, "drive (v, omega)")
        return torch.cat(torch.broadcast_tensors(self.position(x), drive + x[..., -2:]), dim=-1)

    def apply_noise(self, measurements: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Noise-free measurements ``(*batch, 4)`` plus ``noise`` ``(*batch, 4)`` (already times
        sigma) at the per-sensor scales: the noise is additive, and ``measure(x, w, n)`` is
        ``apply_noise(observe(x, w), n)``. Used by noise-augmented training."""
        _check_last(noise, 4, "noise (n1 (2), n2, n3)")
        scale = torch.tensor(
            [self.gps_noise] * 2 + [self.speed_noise, self.turn_rate_noise],
            dtype=noise.dtype, device=noise.device,
        )
        return measurements + noise * scale

    # ------------------------------------------------------------------ evaluation

    def state_from_measurement(self, y: torch.Tensor) -> torch.Tensor:
        """The pose at the fix with heading 0 and zero biases, ``(*batch, *element_shape)``:
        the position is measured, the heading and the biases are not (left at the identity)."""
        _check_last(y, 4, "measurements")
        eye = torch.eye(2, dtype=y.dtype, device=y.device)
        return self.join(eye, y[..., :2], torch.zeros_like(y[..., 2:]))

    def drive_from_measurement(self, y: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The odometry ``(v + b_v, omega + b_omega) + noise`` of ``y_{k+1}``, ``(*batch, 2)``."""
        _check_last(y, 4, "measurements")
        return y[..., 2:]

    def compensated_drive(
        self, x: torch.Tensor, y: torch.Tensor, u: torch.Tensor | None
    ) -> torch.Tensor:
        """The bias-corrected odometry ``(v^m - bhat_v, omega^m - bhat_omega)``, ``(*batch, 2)``:
        what the prediction (:meth:`~manifold_nets.system.System.predict`) steps with."""
        return self.drive_from_measurement(y, u) - x[..., -2:]

    def metrics(self, estimates: torch.Tensor, data: TrajectoryDataset) -> dict[str, torch.Tensor]:
        """The per-factor errors (``pose``, or ``R`` and ``p``: embedding norms; ``b_v`` m/s;
        ``b_omega`` rad/s),
        ``position_m`` (``||phat - p||``) and ``heading_deg`` (``|thetahat - theta|`` wrapped,
        degrees); each ``(N, T')``."""
        out = super().metrics(estimates, data)
        states = data.states.to(dtype=estimates.dtype, device=estimates.device)
        if estimates.shape[1] == states.shape[1] - 1:
            states = states[:, 1:]
        out["position_m"] = torch.linalg.vector_norm(
            self.position(estimates) - self.position(states), dim=-1
        )
        out["heading_deg"] = _wrap(self.heading(estimates) - self.heading(states)).abs() * _DEG
        return out

    def estimators(self) -> dict:
        """``raw``, ``dead_reckoning`` and ``ekf`` (:class:`~.filters.PlanarEKF`: the vehicle's
        error-state EKF with the true model and noise level), for ``method=<name>``."""
        from .filters import PlanarEKF

        return {**super().estimators(), "ekf": PlanarEKF}

    def measurement_errors(self, data: TrajectoryDataset) -> dict[str, torch.Tensor]:
        """The raw baselines, ``(N, T)`` each: ``position_m``, the fix's error, and
        ``heading_deg``, the course over ground's (:func:`course_over_ground`; needs ``T >= 2``)."""
        x, y = data.states[:, 1:], data.measurements
        out = {"position_m": torch.linalg.vector_norm(y[..., :2] - self.position(x), dim=-1)}
        if data.length >= 2:
            cog = course_over_ground(y[..., :2])
            out["heading_deg"] = _wrap(cog - self.heading(x)).abs() * _DEG
        return out
