"""An attitude and heading reference system (AHRS) on SO(3) x R^3: attitude and gyro bias.

State ``x = (R, b_Omega)`` on ``Product(SO3(), Euclidean(3), names=("R", "b_omega"))``, stored
flat as the ``(12,)`` vector ``(vec R row-major, b_Omega)``, which is also its embedding. ``R``
maps body-frame vectors to the world frame (east-north-up: x east, y north, z up).

Dynamics (``dR/dt = R [Omega]x`` with the body rate ``Omega_k`` held over the step, exact)::

    R_{k+1} = R_k exp(Omega_k dt),        b_{k+1} = b_k      (a constant turn-on bias)

The drive is the true body rate ``w_k = Omega_k`` (``drive_dim = 3``), a smooth random profile
(:mod:`manifold_nets_examples.attitude.motion`): per sequence and axis a sum of ``num_terms``
random sinusoids with frequencies in ``[freq_min, freq_max]`` Hz and root mean square
``omega_rms`` rad/s, sampled at ``t_k = k dt``.

Measurement ``y_{k+1}`` in ``R^9``: two known world directions seen in the body frame, and the
gyro reading applied over the step ``k -> k+1`` (the paper's pairing of velocity readings)::

    y_{k+1} = (R_{k+1}^T g + s_g n1,  R_{k+1}^T m + s_m n2,  Omega_k + b + s_w n3),

``n = (n1, n2, n3) ~ N(0, sigma^2 I_9)`` (``noise_dim = 9``), ``s_*`` per-sensor scales (default
1). ``g`` is the direction of gravity and ``m`` that of the Earth's magnetic field, **unit
vectors** by default: ``g = (0, 0, -1)`` (down) and ``m = (0, cos 60 deg, -sin 60 deg)``
(north, dipping 60 deg below the horizon, a mid-latitude inclination), 30 deg apart. With unit
vectors ``sigma`` is the noise per component relative to the vector's length (0.1 ~ 6 deg).
Other vectors (e.g. physical units, 9.81 m/s^2 and 50 uT) are used as given. No attitude is
measured: it must be inferred from the two directions and the integrated gyro. The observer
gets no separate input (``input_dim = 0``): the gyro reading is part of ``y``.

Laws (defaults; each a parameter): ``R_0`` uniform (Haar) on SO(3); the turn-on bias
``b ~ U[-bias_range, bias_range]^3`` with ``bias_range = 0.2`` rad/s (11.5 deg/s, the order of
an uncalibrated consumer MEMS gyroscope's zero-rate offset), one draw per sequence;
``omega_rms = 1`` rad/s per axis with frequencies in ``[0.05, 1]`` Hz (handheld motion);
``dt = 0.1`` s.

Step bound: the measured rate ``Omega + b`` turns by at most
``sqrt(3) (4 omega_rms + bias_range) dt`` in a step (0.73 rad by default), and the constructor
refuses parameters making this ``>= pi``. The sinusoids have no hard bound (Gaussian
amplitudes), so ``4 omega_rms`` per axis is a stated conservative peak
(:data:`~manifold_nets_examples.attitude.motion.PEAK_OVER_RMS`), not a guarantee.

Raw baseline (:meth:`Attitude.measurement_errors`, :meth:`Attitude.state_from_measurement`):
TRIAD (:mod:`manifold_nets_examples.attitude.triad`) from the two measured directions, gravity
first. Dead reckoning reads the drive as the biased gyro (:meth:`Attitude.drive_from_measurement`).
"""

from __future__ import annotations

import functools
import math

import torch

from groups import SO3, Euclidean, Product
from manifold_nets.data import TrajectoryDataset
from manifold_nets.system import System, check_last_dim, check_number

from .motion import check_frequencies, check_turn_per_step, random_sinusoids
from .triad import triad

__all__ = ["GRAVITY", "MAGNETIC", "Attitude"]

_DTYPE = torch.float64
_SO3 = SO3()
_DEG = 180.0 / math.pi

#: Default world directions (east-north-up frame), unit vectors.
GRAVITY = (0.0, 0.0, -1.0)
MAGNETIC = (0.0, 0.5, -math.sqrt(3.0) / 2)  # north, 60 deg below the horizon


_check_last = functools.partial(check_last_dim, "Attitude")


_number = functools.partial(check_number, "Attitude")


def _vector(name: str, value) -> tuple[float, float, float]:
    try:
        v = tuple(float(c) for c in value)
    except (TypeError, ValueError):
        v = ()
    if len(v) != 3 or not all(math.isfinite(c) for c in v) or not any(v):
        raise ValueError(f"Attitude: {name} must be a non-zero 3-vector [x, y, z], got {value!r}.")
    return v


class Attitude(System):
    """The AHRS; see the module docstring for the model, the laws and the layouts."""

    name = "attitude"
    measurement_dim = 9
    input_dim = 0
    drive_dim = 3
    noise_dim = 9

    def __init__(
        self,
        dt: float = 0.1,
        omega_rms: float = 1.0,
        freq_min: float = 0.05,
        freq_max: float = 1.0,
        num_terms: int = 3,
        bias_range: float = 0.2,
        gravity=GRAVITY,
        magnetic=MAGNETIC,
        gravity_noise: float = 1.0,
        magnetic_noise: float = 1.0,
        gyro_noise: float = 1.0,
    ):
        self.dt = _number("dt (the step length in seconds)", dt, positive=True)
        self.omega_rms = _number("omega_rms", omega_rms)
        check_frequencies("Attitude", freq_min, freq_max, self.dt)
        self.freq_min, self.freq_max = float(freq_min), float(freq_max)
        if isinstance(num_terms, bool) or not isinstance(num_terms, int) or num_terms < 1:
            raise ValueError(f"Attitude: num_terms must be a positive integer, got {num_terms!r}.")
        self.num_terms = num_terms
        self.bias_range = _number("bias_range", bias_range)
        check_turn_per_step(
            "Attitude", self.dt, "omega_rms", self.omega_rms, "bias_range", self.bias_range, 3
        )
        self.gravity = _vector("gravity", gravity)
        self.magnetic = _vector("magnetic", magnetic)
        g, m = torch.tensor(self.gravity), torch.tensor(self.magnetic)
        sin = torch.linalg.vector_norm(torch.linalg.cross(g, m)) / (g.norm() * m.norm())
        if sin < math.sin(math.radians(1.0)):
            raise ValueError(
                f"Attitude: gravity {self.gravity} and magnetic {self.magnetic} are (nearly) "
                "collinear; two directions at least 1 deg apart are needed to fix the attitude."
            )
        self.gravity_noise = _number("gravity_noise", gravity_noise)
        self.magnetic_noise = _number("magnetic_noise", magnetic_noise)
        self.gyro_noise = _number("gyro_noise", gyro_noise)
        self.group = Product(SO3(), Euclidean(3), names=("R", "b_omega"))

    def config(self) -> dict:
        return {
            "dt": self.dt,
            "omega_rms": self.omega_rms,
            "freq_min": self.freq_min,
            "freq_max": self.freq_max,
            "num_terms": self.num_terms,
            "bias_range": self.bias_range,
            "gravity": list(self.gravity),
            "magnetic": list(self.magnetic),
            "gravity_noise": self.gravity_noise,
            "magnetic_noise": self.magnetic_noise,
            "gyro_noise": self.gyro_noise,
        }

    def directions(self, dtype=_DTYPE, device=None) -> tuple[torch.Tensor, torch.Tensor]:
        """The world directions ``g`` and ``m``, ``(3,)`` each."""
        return (
            torch.tensor(self.gravity, dtype=dtype, device=device),
            torch.tensor(self.magnetic, dtype=dtype, device=device),
        )

    # ------------------------------------------------------------------ random laws

    def sample_initial_state(self, num_sequences: int, generator: torch.Generator) -> torch.Tensor:
        """``(N, 12)``: Haar ``R_0`` and the turn-on bias ``b ~ U[-bias_range, bias_range]^3``."""
        R = _SO3.random((num_sequences,), generator=generator, dtype=_DTYPE)
        b = torch.empty(num_sequences, 3, dtype=_DTYPE)
        b.uniform_(-self.bias_range, self.bias_range, generator=generator)
        return torch.cat((R.flatten(-2), b), dim=-1)

    def sample_drive(
        self, num_sequences: int, length: int, generator: torch.Generator
    ) -> torch.Tensor:
        """``(N, T, 3)``: the body rates ``Omega_k``, smooth random sinusoids (module docstring)."""
        return random_sinusoids(
            num_sequences, length, 3, self.dt, self.omega_rms, self.freq_min, self.freq_max,
            self.num_terms, generator,
        )

    # ------------------------------------------------------------------ dynamics

    def step(self, x: torch.Tensor, drive: torch.Tensor, dt: float | None = None) -> torch.Tensor:
        """``R' = R exp(Omega dt)``, ``b' = b``; ``x`` ``(*batch, 12)``, ``drive`` ``(*batch, 3)``.

        Exact for a rate held over the step; differentiable (an EKF can linearise it).
        """
        self.group.check_element(x, "step")
        _check_last(drive, 3, "drive (Omega)")
        dt = self.dt if dt is None else dt
        R = x[..., :9].unflatten(-1, (3, 3))
        R1 = R @ _SO3.exp(drive * dt)
        batch = R1.shape[:-2]
        return torch.cat((R1.flatten(-2), x[..., 9:].expand(*batch, 3)), dim=-1)

    # ------------------------------------------------------------------ measurements

    def observe(self, x: torch.Tensor, drive: torch.Tensor) -> torch.Tensor:
        """The noise-free ``(R^T g, R^T m, Omega + b)``, ``(*batch, 9)``; ``measure(x, w, n)``
        adds :meth:`apply_noise`'s ``(s_g n1, s_m n2, s_w n3)``."""
        self.group.check_element(x, "measure")
        _check_last(drive, 3, "drive (Omega)")
        R = x[..., :9].unflatten(-1, (3, 3))
        g, m = self.directions(x.dtype, x.device)
        rates = drive + x[..., 9:]
        batch = torch.broadcast_shapes(R.shape[:-2], rates.shape[:-1])
        # R^T v as a row vector: v^T R
        return torch.cat(
            ((g @ R).expand(*batch, 3), (m @ R).expand(*batch, 3), rates.expand(*batch, 3)), dim=-1
        )

    def apply_noise(self, measurements: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Noise-free measurements ``(*batch, 9)`` plus ``noise`` ``(*batch, 9)`` (already times
        sigma) at the per-sensor scales: the noise is additive, and ``measure(x, w, n)`` is
        ``apply_noise(observe(x, w), n)``. Used by noise-augmented training."""
        _check_last(noise, 9, "noise (n1, n2, n3)")
        scale = torch.tensor(
            [self.gravity_noise] * 3 + [self.magnetic_noise] * 3 + [self.gyro_noise] * 3,
            dtype=noise.dtype, device=noise.device,
        )
        return measurements + noise * scale

    # ------------------------------------------------------------------ evaluation

    def triad(self, measurements: torch.Tensor) -> torch.Tensor:
        """The TRIAD attitude ``(*batch, 3, 3)`` from measurements ``(*batch, 9)``."""
        _check_last(measurements, 9, "measurements")
        g, m = self.directions(measurements.dtype, measurements.device)
        return triad(measurements[..., :3], measurements[..., 3:6], g, m)

    def state_from_measurement(self, y: torch.Tensor) -> torch.Tensor:
        """``(R_triad, 0)``, ``(*batch, 12)``: the TRIAD attitude; the bias is not measured."""
        R = self.triad(y)
        return torch.cat((R.flatten(-2), torch.zeros_like(y[..., 6:])), dim=-1)

    def drive_from_measurement(self, y: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The gyro reading ``Omega^m_k = Omega_k + b + noise`` of ``y_{k+1}``, ``(*batch, 3)``."""
        _check_last(y, 9, "measurements")
        return y[..., 6:]

    def compensated_drive(
        self, x: torch.Tensor, y: torch.Tensor, u: torch.Tensor | None
    ) -> torch.Tensor:
        """The bias-corrected gyro ``Omega^m - bhat``, ``(*batch, 3)``: what the prediction
        (:meth:`~manifold_nets.system.System.predict`) steps with."""
        return self.drive_from_measurement(y, u) - x[..., 9:]

    def metrics(self, estimates: torch.Tensor, data: TrajectoryDataset) -> dict[str, torch.Tensor]:
        """The per-factor errors (``R``: ``||Rhat - R||_F``; ``b_omega``: ``||bhat - b||`` rad/s)
        and ``attitude_deg``, the rotation angle of ``Rhat^T R`` in degrees; each ``(N, T')``."""
        out = super().metrics(estimates, data)
        states = data.states.to(dtype=estimates.dtype, device=estimates.device)
        if estimates.shape[1] == states.shape[1] - 1:
            states = states[:, 1:]
        Rhat = estimates[..., :9].unflatten(-1, (3, 3))
        R = states[..., :9].unflatten(-1, (3, 3))
        out["attitude_deg"] = _SO3.distance(Rhat, R) * _DEG
        return out

    def estimators(self) -> dict:
        """``raw``, ``dead_reckoning`` and ``ekf`` (:class:`~.filters.AttitudeEKF`: the AHRS's
        error-state EKF with the true model and noise level), for ``method=<name>``."""
        from .filters import AttitudeEKF

        return {**super().estimators(), "ekf": AttitudeEKF}

    def measurement_errors(self, data: TrajectoryDataset) -> dict[str, torch.Tensor]:
        """TRIAD from the raw directions against the truth, ``(N, T)`` each: ``R``
        (``||R_triad - R||_F``) and ``attitude_deg`` (its rotation angle in degrees)."""
        R = data.states[:, 1:, :9].unflatten(-1, (3, 3))
        Rt = self.triad(data.measurements)
        return {
            "R": torch.linalg.matrix_norm(Rt - R),
            "attitude_deg": _SO3.distance(Rt, R) * _DEG,
        }
