"""An attitude simulator on SO(3) whose sensors match the IMU of the BROAD dataset.

For pre-training an observer on simulated data before fine-tuning it on BROAD's recordings
(Laidig et al., Data 6(7):72, 2021, CC-BY-4.0). The layout is the real-data reader's, so the
same observer reads both.

State ``x = R`` on ``SO3()``, ``(*batch, 3, 3)``: body -> East-North-Up world,
``v_world = R v_body``. Step ``dt = 1/285.714`` s (BROAD's rate). Dynamics (exact for a rate
held over the step)::

    R_{k+1} = R_k exp(Omega_k dt)

Drive ``w_k`` ``(*batch, 18)``, everything that is not the state, in physical units::

    w = (Omega (rad/s), b (rad/s), n_gyr (rad/s), a_lin (m/s^2, world), d_body (uT), d_world (uT))
         0:3            3:6         6:9            9:12                  12:15         15:18

the true body rate, the gyro bias, the gyro's white noise, the linear acceleration, a hard-iron
offset (a magnet attached to the board) and a world-fixed field perturbation (a magnet standing
nearby). Input and measurement (``G0 = 9.81`` m/s^2, ``M0 = 44`` uT, ``g_up = (0, 0, G0)``)::

    u_k     = gyr_{k+1} = Omega_k + b_k + n_gyr_k                                    (3,) rad/s
    y_{k+1} = (acc / G0, mag / M0) + noise                                           (6,)
    acc     = R_{k+1}^T (g_up + a_lin_k)          (the specific force: at rest R^T (0, 0, +G0))
    mag     = R_{k+1}^T (m_ref + d_world_k) + d_body_k,   m_ref = B (0, cos dip, -sin dip)

The accelerometer/magnetometer noise ``nu`` ``(6,)`` enters in :meth:`apply_noise` as
``y + nu * (acc_noise / G0, mag_noise / M0)`` per axis: ``sigma = 1`` is the real IMU's white
noise. The gyro noise is part of the drive at its measured level (``gyro_noise``), whatever
``sigma`` is.

Laws (each a constructor parameter; the defaults are measured on BROAD's training trials,
``examples/broad/sensor_model.md``):

- ``R_0``: with probability ``level_fraction`` near level (tilt ~ U[0, tilt_max_deg] about a
  uniform horizontal axis; the real trials start within 3 deg of level) with a uniform heading,
  otherwise Haar-uniform (windows from inside a trial start anywhere: the trials reach tilts of
  170 deg).
- ``Omega``: per axis a sum of ``num_terms`` random sinusoids (:mod:`..attitude.motion`) with
  frequencies in ``omega_freq`` Hz and an rms per sequence log-uniform in ``omega_rms`` rad/s,
  times a rest envelope: with probability ``rest_probability`` one rest interval of
  ``rest_duration`` s (raised-cosine edges of ``rest_ramp`` s) where rate and linear
  acceleration vanish; its norm clipped at ``max_rate`` (``max_rate dt < pi``: a step turns by
  less than pi).
- ``b_k = b_0 + bias_walk * sqrt(dt) * sum of N(0, I)``, ``b_0 ~ N(0, bias_std^2 I)``.
- ``a_lin``: random sinusoids per world axis, frequencies ``acc_freq`` Hz, rms per sequence
  log-uniform in ``acc_rms`` m/s^2, times the rest envelope.
- ``d_body``: with probability ``hard_iron_probability`` a constant offset of size
  ``U[hard_iron_range] * M0`` in a uniform direction, else 0.
- ``d_world``: with probability ``world_disturbance_probability`` random sinusoids per world
  axis, frequencies ``world_disturbance_freq`` Hz, rms ``world_disturbance_rms * M0``, else 0.

Shapes: states ``(N, T+1, 3, 3)``, drives ``(N, T, 18)``, inputs ``(N, T, 3)``,
measurements ``(N, T, 6)``. :meth:`BroadSimulator.state_from_measurement` is TRIAD
(:mod:`..attitude.triad`): up from the accelerometer first, then the model's field direction.
"""

from __future__ import annotations

import functools
import math

import torch

from groups import SO3
from manifold_nets.data import TrajectoryDataset
from manifold_nets.system import System, check_last_dim, check_number

from ..attitude.motion import check_frequencies, random_sinusoids
from ..attitude.triad import triad

__all__ = ["G0", "M0", "BROAD_DT", "BroadSimulator"]

_DTYPE = torch.float64
_SO3 = SO3()
_DEG = 180.0 / math.pi
_OWNER = "BroadSimulator"

#: Scales of the measurement layout (the real-data reader's): acc / G0, mag / M0.
G0 = 9.81
M0 = 44.0
#: BROAD's sampling period in seconds (285.714 Hz).
BROAD_DT = 1.0 / 285.714

_check_last = functools.partial(check_last_dim, _OWNER)
_number = functools.partial(check_number, _OWNER)


def _range(name: str, value, positive: bool = False) -> tuple[float, float]:
    """``[lo, hi]`` with ``0 <= lo <= hi`` finite (``lo > 0`` if ``positive``), as a tuple."""
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        lo = hi = math.nan
    bad = not (math.isfinite(lo) and math.isfinite(hi)) or lo < 0 or lo > hi
    if bad or (positive and lo <= 0):
        rel = "0 < lo" if positive else "0 <= lo"
        raise ValueError(f"{_OWNER}: {name} must be a range [lo, hi] with {rel} <= hi, "
                         f"got {value!r}.")
    return lo, hi


def _vector3(name: str, value) -> tuple[float, float, float]:
    """A 3-vector of finite numbers >= 0 (per-axis noise levels)."""
    try:
        v = tuple(float(c) for c in value)
    except (TypeError, ValueError):
        v = ()
    if len(v) != 3 or not all(math.isfinite(c) and c >= 0 for c in v):
        raise ValueError(f"{_OWNER}: {name} must be 3 finite numbers >= 0 (x, y, z), "
                         f"got {value!r}.")
    return v


def _probability(name: str, value) -> float:
    p = _number(name, value)
    if p > 1:
        raise ValueError(f"{_OWNER}: {name} is a probability in [0, 1], got {value!r}.")
    return p


def _log_uniform(n: int, lo: float, hi: float, generator: torch.Generator) -> torch.Tensor:
    """``(n,)`` draws log-uniform in ``[lo, hi]`` (uniform if ``lo == 0``)."""
    u = torch.rand(n, generator=generator, dtype=_DTYPE)
    if lo == 0 or lo == hi:
        return lo + (hi - lo) * u
    return torch.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * u)


def _unit_vectors(n: int, generator: torch.Generator) -> torch.Tensor:
    """``(n, 3)`` directions uniform on the sphere."""
    v = torch.randn(n, 3, generator=generator, dtype=_DTYPE)
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(1e-300)


def _rotation_about(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """``exp(angle * axis)``, ``(n, 3), (n,) -> (n, 3, 3)``."""
    return _SO3.exp(axis * angle[:, None])


class BroadSimulator(System):
    """Attitude on SO(3) with BROAD's IMU: see the module docstring for the model and laws."""

    name = "broad_sim"
    measurement_dim = 6
    input_dim = 3
    drive_dim = 18
    noise_dim = 6

    def __init__(
        self,
        dt: float = BROAD_DT,
        level_fraction: float = 0.5,
        tilt_max_deg: float = 3.0,
        omega_rms=(0.5, 3.5),
        omega_freq=(0.1, 3.0),
        num_terms: int = 4,
        max_rate: float = 20.0,
        rest_probability: float = 0.3,
        rest_duration=(0.2, 1.0),
        rest_ramp: float = 0.1,
        bias_std: float = 0.0041,
        bias_walk: float = 6e-6,
        gyro_noise=(0.0018, 0.0016, 0.0019),
        acc_rms=(0.7, 16.8),
        acc_freq=(0.2, 4.0),
        acc_noise=(0.043, 0.047, 0.073),
        magnetic_strength: float = 43.7,
        magnetic_dip_deg: float = 69.5,
        mag_noise=(0.33, 0.33, 0.31),
        hard_iron_probability: float = 0.25,
        hard_iron_range=(0.2, 1.3),
        world_disturbance_probability: float = 0.25,
        world_disturbance_rms: float = 0.25,
        world_disturbance_freq=(0.1, 1.0),
        magnetometer: bool = True,
        acc_lowpass: float = 0.0,
        rest_bias: bool = False,
        acc_lowpass_order: int = 1,
    ):
        self.dt = _number("dt (the step length in seconds)", dt, positive=True)
        self._init_motion(level_fraction, tilt_max_deg, omega_rms, omega_freq, num_terms,
                          max_rate, rest_probability, rest_duration, rest_ramp)
        self.bias_std = _number("bias_std (rad/s)", bias_std)
        self.bias_walk = _number("bias_walk (rad/s/sqrt(s))", bias_walk)
        self.gyro_noise = _vector3("gyro_noise (rad/s)", gyro_noise)
        self.acc_rms = _range("acc_rms (m/s^2)", acc_rms)
        self.acc_freq = _range("acc_freq (Hz)", acc_freq)
        check_frequencies(_OWNER, *self.acc_freq, self.dt)
        self.acc_noise = _vector3("acc_noise (m/s^2)", acc_noise)
        self.magnetic_strength = _number("magnetic_strength (uT)", magnetic_strength,
                                         positive=True)
        self.magnetic_dip_deg = _number("magnetic_dip_deg", magnetic_dip_deg)
        if self.magnetic_dip_deg > 89.0:
            raise ValueError(f"{_OWNER}: magnetic_dip_deg must be in [0, 89] so that the field "
                             f"fixes the heading; got {magnetic_dip_deg!r}.")
        self.mag_noise = _vector3("mag_noise (uT)", mag_noise)
        self.hard_iron_probability = _probability("hard_iron_probability", hard_iron_probability)
        self.hard_iron_range = _range("hard_iron_range (multiples of M0)", hard_iron_range)
        self.world_disturbance_probability = _probability(
            "world_disturbance_probability", world_disturbance_probability)
        self.world_disturbance_rms = _number("world_disturbance_rms (multiples of M0)",
                                             world_disturbance_rms)
        self.world_disturbance_freq = _range("world_disturbance_freq (Hz)",
                                             world_disturbance_freq)
        check_frequencies(_OWNER, *self.world_disturbance_freq, self.dt)
        self._init_readings(magnetometer, acc_lowpass, rest_bias, acc_lowpass_order)
        self.group = SO3()

    def _init_readings(self, magnetometer, acc_lowpass, rest_bias, acc_lowpass_order=1) -> None:
        """How a learned observer of this system reads the recordings (:mod:`.prefilter`,
        :func:`.evaluate.input_settings`), kept in the system's config so that a trained
        observer's files say it: with or without the ``magnetometer`` (a 6-D observer), the
        accelerometer low-passed over ``acc_lowpass`` seconds (0: raw) by a filter of
        ``acc_lowpass_order`` 1 (first order) or 2 (VQF's Butterworth filter), the gyroscope less
        its ``rest_bias``. The simulation itself is unchanged by them."""
        for name, flag in (("magnetometer", magnetometer), ("rest_bias", rest_bias)):
            if not isinstance(flag, bool):
                raise ValueError(f"{_OWNER}: {name} must be true or false, got {flag!r}.")
        self.magnetometer, self.rest_bias = magnetometer, rest_bias
        self.acc_lowpass = _number("acc_lowpass (s)", acc_lowpass)
        if isinstance(acc_lowpass_order, bool) or acc_lowpass_order not in (1, 2):
            raise ValueError(f"{_OWNER}: acc_lowpass_order must be 1 (first order) or 2 (VQF's "
                             f"second-order Butterworth filter), got {acc_lowpass_order!r}.")
        if acc_lowpass_order == 2 and not self.acc_lowpass > 0:
            raise ValueError(f"{_OWNER}: acc_lowpass_order 2 is the order of the accelerometer's "
                             "low-pass, and acc_lowpass is 0 (no low-pass): give acc_lowpass "
                             "(seconds, e.g. 3) or drop acc_lowpass_order.")
        self.acc_lowpass_order = int(acc_lowpass_order)
        kind = "" if self.acc_lowpass_order == 1 else " (second-order Butterworth)"
        steps = [what for what, on in (
            ("the magnetometer zeroed", not magnetometer),
            ("the gyroscope less its bias estimated at rest", rest_bias),
            (f"the accelerometer low-passed over {self.acc_lowpass:g} s{kind} in a "
             "gyro-strapdown frame", self.acc_lowpass > 0),
        ) if on]
        self.preprocessing = None if not steps else (
            "; ".join(steps) + " (readings_filter(): examples/broad/imu_prefilter.py, which "
            "mn-apply and the exported step of a FilteredObserver run; OnlinePrefilter in numpy)"
        )

    def readings_filter(self):
        """The pre-filter of :meth:`_init_readings` as a torch module (:class:`.imu_prefilter.
        ImuPrefilter`) at the observer's rate ``1 / dt``, built from the config's numbers; ``None``
        when the observer reads the readings as they are."""
        if self.preprocessing is None:
            return None
        from .imu_prefilter import ImuPrefilter

        return ImuPrefilter(1.0 / self.dt, tau=self.acc_lowpass, rest=self.rest_bias,
                            magnetometer=self.magnetometer, order=self.acc_lowpass_order)

    def _init_motion(self, level_fraction, tilt_max_deg, omega_rms, omega_freq, num_terms,
                     max_rate, rest_probability, rest_duration, rest_ramp) -> None:
        """Validates and stores the parameters of the initial attitude and the motion."""
        self.level_fraction = _probability("level_fraction", level_fraction)
        self.tilt_max_deg = _number("tilt_max_deg", tilt_max_deg)
        if self.tilt_max_deg > 180:
            raise ValueError(f"{_OWNER}: tilt_max_deg must be in [0, 180], got {tilt_max_deg!r}.")
        self.omega_rms = _range("omega_rms (rad/s per axis)", omega_rms)
        self.omega_freq = _range("omega_freq (Hz)", omega_freq)
        check_frequencies(_OWNER, *self.omega_freq, self.dt)
        if isinstance(num_terms, bool) or not isinstance(num_terms, int) or num_terms < 1:
            raise ValueError(f"{_OWNER}: num_terms must be a positive integer, got {num_terms!r}.")
        self.num_terms = num_terms
        self.max_rate = _number("max_rate (rad/s)", max_rate, positive=True)
        if self.max_rate * self.dt >= math.pi:
            raise ValueError(
                f"{_OWNER}: max_rate * dt = {self.max_rate * self.dt:.3g} rad; one step must "
                f"turn by less than pi. Lower max_rate (rad/s) or dt.")
        if self.omega_rms[1] > self.max_rate:
            raise ValueError(f"{_OWNER}: omega_rms upper end {self.omega_rms[1]} exceeds "
                             f"max_rate={self.max_rate}; raise max_rate or lower omega_rms.")
        self.rest_probability = _probability("rest_probability", rest_probability)
        self.rest_duration = _range("rest_duration (s)", rest_duration)
        self.rest_ramp = _number("rest_ramp (s)", rest_ramp)

    def config(self) -> dict:
        out = {}
        for key in _CONFIG_KEYS:
            v = getattr(self, key)
            out[key] = list(v) if isinstance(v, tuple) else v
        out.update({k: getattr(self, k) for k, v in _READING_DEFAULTS.items()
                    if getattr(self, k) != v})  # fmt: skip
        return out

    def magnetic_field(self, dtype=_DTYPE, device=None) -> torch.Tensor:
        """The undisturbed world field ``m_ref`` in uT, ``(3,)``: north (+y), dipping down."""
        dip = math.radians(self.magnetic_dip_deg)
        b = self.magnetic_strength
        return torch.tensor([0.0, b * math.cos(dip), -b * math.sin(dip)], dtype=dtype,
                            device=device)

    # ------------------------------------------------------------------ random laws

    def sample_initial_state(self, num_sequences: int, generator: torch.Generator) -> torch.Tensor:
        """``(N, 3, 3)``: near level with a uniform heading (``level_fraction``), else Haar."""
        n = num_sequences
        haar = _SO3.random((n,), generator=generator, dtype=_DTYPE)
        level = torch.rand(n, generator=generator, dtype=_DTYPE) < self.level_fraction
        heading = torch.rand(n, generator=generator, dtype=_DTYPE) * (2 * math.pi)
        axis_angle = torch.rand(n, generator=generator, dtype=_DTYPE) * (2 * math.pi)
        tilt = torch.rand(n, generator=generator, dtype=_DTYPE) * math.radians(self.tilt_max_deg)
        z = torch.zeros(n, dtype=_DTYPE)
        up = torch.stack((z, z, z + 1), dim=-1)
        horizontal = torch.stack((torch.cos(axis_angle), torch.sin(axis_angle), z), dim=-1)
        tilted = _rotation_about(up, heading) @ _rotation_about(horizontal, tilt)
        return torch.where(level[:, None, None], tilted, haar)

    def _rest_envelope(self, n: int, t: int, generator: torch.Generator) -> torch.Tensor:
        """``(N, T, 1)`` in [0, 1]: 0 inside one rest interval (some sequences), 1 elsewhere."""
        has = torch.rand(n, 1, generator=generator, dtype=_DTYPE) < self.rest_probability
        lo, hi = self.rest_duration
        length = lo + (hi - lo) * torch.rand(n, 1, generator=generator, dtype=_DTYPE)
        horizon = t * self.dt
        start = (torch.rand(n, 1, generator=generator, dtype=_DTYPE) * horizon) - 0.5 * length
        time = torch.arange(t, dtype=_DTYPE)[None] * self.dt
        ramp = max(self.rest_ramp, 1e-12)
        inside = torch.minimum(time - start, start + length - time) / ramp
        w = 0.5 - 0.5 * torch.cos(math.pi * inside.clamp(0.0, 1.0))
        return torch.where(has, 1.0 - w, torch.ones_like(w))[..., None]

    def sample_drive(
        self, num_sequences: int, length: int, generator: torch.Generator
    ) -> torch.Tensor:
        """``(N, T, 18)``: the drive of the module docstring, drawn by its laws."""
        n, t, k = num_sequences, length, self.num_terms
        env = self._rest_envelope(n, t, generator)
        omega = random_sinusoids(n, t, 3, self.dt, 1.0, *self.omega_freq, k, generator)
        omega = omega * _log_uniform(n, *self.omega_rms, generator)[:, None, None] * env
        norm = torch.linalg.vector_norm(omega, dim=-1, keepdim=True)
        omega = omega * (self.max_rate / norm.clamp_min(self.max_rate))
        b0 = torch.randn(n, 1, 3, generator=generator, dtype=_DTYPE) * self.bias_std
        walk = torch.randn(n, t, 3, generator=generator, dtype=_DTYPE)
        bias = b0 + (self.bias_walk * math.sqrt(self.dt)) * (walk.cumsum(1) - walk[:, :1])
        gyro = torch.tensor(self.gyro_noise, dtype=_DTYPE)
        n_gyr = torch.randn(n, t, 3, generator=generator, dtype=_DTYPE) * gyro
        acc = random_sinusoids(n, t, 3, self.dt, 1.0, *self.acc_freq, k, generator)
        acc = acc * _log_uniform(n, *self.acc_rms, generator)[:, None, None] * env
        return torch.cat((omega, bias, n_gyr, acc, *self._magnetic_drive(n, t, generator)), -1)

    def _magnetic_drive(self, n: int, t: int, generator: torch.Generator):
        """``d_body`` and ``d_world`` in uT, ``(N, T, 3)`` each (module docstring)."""
        on = torch.rand(n, 1, 1, generator=generator, dtype=_DTYPE) < self.hard_iron_probability
        lo, hi = self.hard_iron_range
        size = (lo + (hi - lo) * torch.rand(n, generator=generator, dtype=_DTYPE)) * M0
        d_body = (_unit_vectors(n, generator) * size[:, None])[:, None].expand(n, t, 3)
        d_body = torch.where(on, d_body, torch.zeros_like(d_body))
        on = torch.rand(n, 1, 1, generator=generator, dtype=_DTYPE)
        on = on < self.world_disturbance_probability
        rms = self.world_disturbance_rms * M0
        d_world = random_sinusoids(n, t, 3, self.dt, rms, *self.world_disturbance_freq,
                                   self.num_terms, generator)
        return d_body, torch.where(on, d_world, torch.zeros_like(d_world))

    # ------------------------------------------------------------------ dynamics and sensors

    def step(self, x: torch.Tensor, drive: torch.Tensor, dt: float | None = None) -> torch.Tensor:
        """``R exp(Omega dt)``; ``x`` ``(*batch, 3, 3)``, ``drive`` ``(*batch, 18)``."""
        self.group.check_element(x, "step")
        _check_last(drive, self.drive_dim, "drive")
        dt = self.dt if dt is None else dt
        return x @ _SO3.exp(drive[..., :3] * dt)

    def rollout(
        self, x0: torch.Tensor, drive: torch.Tensor, show_progress: bool = False
    ) -> torch.Tensor:
        """``(N, T+1, 3, 3)``: :meth:`step`'s product, with every ``exp(Omega_k dt)`` computed
        in one batched call first (the per-step loop is then one small matmul)."""
        n, t = drive.shape[:2]
        turns = _SO3.exp(drive[..., :3] * self.dt)  # (N, T, 3, 3)
        states = x0.new_empty(n, t + 1, 3, 3)
        states[:, 0] = x0
        for k in range(t):
            states[:, k + 1] = states[:, k] @ turns[:, k]
        return states

    def inputs(self, drive: torch.Tensor) -> torch.Tensor:
        """The gyro reading ``Omega + b + n_gyr`` in rad/s, ``(*batch, 3)``."""
        _check_last(drive, self.drive_dim, "drive")
        return drive[..., 0:3] + drive[..., 3:6] + drive[..., 6:9]

    def observe(self, x: torch.Tensor, drive: torch.Tensor) -> torch.Tensor:
        """The noise-free ``(acc / G0, mag / M0)``, ``(*batch, 6)`` (module docstring)."""
        self.group.check_element(x, "measure")
        _check_last(drive, self.drive_dim, "drive")
        drive = drive.to(x.dtype)
        up = torch.tensor([0.0, 0.0, G0], dtype=x.dtype, device=x.device)
        m_ref = self.magnetic_field(x.dtype, x.device)
        # R^T v for a batch of v: (v^T R) as a row vector
        acc = ((up + drive[..., 9:12])[..., None, :] @ x)[..., 0, :] / G0
        world = (m_ref + drive[..., 15:18])[..., None, :] @ x
        mag = (world[..., 0, :] + drive[..., 12:15]) / M0
        return torch.cat(torch.broadcast_tensors(acc, mag), dim=-1)

    def noise_scale(self, dtype=_DTYPE, device=None) -> torch.Tensor:
        """Per-axis noise at ``sigma = 1`` in measurement units, ``(6,)``: BROAD's IMU."""
        return torch.tensor([a / G0 for a in self.acc_noise] + [m / M0 for m in self.mag_noise],
                            dtype=dtype, device=device)

    def apply_noise(self, measurements: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """``y + noise * noise_scale()``, ``(*batch, 6)``; ``noise`` already times sigma."""
        _check_last(noise, self.noise_dim, "noise (acc, mag)")
        return measurements + noise * self.noise_scale(noise.dtype, noise.device)

    # ------------------------------------------------------------------ baselines

    def state_from_measurement(self, y: torch.Tensor) -> torch.Tensor:
        """TRIAD: up from ``y[..., :3]`` first, then the field from ``y[..., 3:6]``,
        ``(*batch, 6) -> (*batch, 3, 3)``. Exact for noise-free, undisturbed ``y``."""
        _check_last(y, self.measurement_dim, "measurements")
        up = torch.tensor([0.0, 0.0, 1.0], dtype=y.dtype, device=y.device)
        return triad(y[..., :3], y[..., 3:6], up, self.magnetic_field(y.dtype, y.device))

    def drive_from_measurement(self, y: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The drive as read: the gyro reading as the rate, the rest zero, ``(*batch, 18)``."""
        _check_last(u, self.input_dim, "inputs (gyro)")
        return torch.cat((u, u.new_zeros(*u.shape[:-1], self.drive_dim - 3)), dim=-1)

    def measurement_errors(self, data: TrajectoryDataset) -> dict[str, torch.Tensor]:
        """TRIAD against the truth, ``(N, T)`` each: ``R`` (``||R_triad - R||_F``) and
        ``attitude_deg`` (its rotation angle in degrees)."""
        R = data.states[:, 1:]
        Rt = self.state_from_measurement(data.measurements)
        return {"R": torch.linalg.matrix_norm(Rt - R),
                "attitude_deg": _SO3.distance(Rt, R) * _DEG}

    def metrics(self, estimates: torch.Tensor, data: TrajectoryDataset) -> dict[str, torch.Tensor]:
        """The base errors (``x``: ``||Rhat - R||_F``) and ``attitude_deg``, each ``(N, T')``."""
        out = super().metrics(estimates, data)
        states = data.states.to(dtype=estimates.dtype, device=estimates.device)
        if estimates.shape[1] == states.shape[1] - 1:
            states = states[:, 1:]
        out["attitude_deg"] = _SO3.distance(estimates, states) * _DEG
        return out


_CONFIG_KEYS = (
    "dt", "level_fraction", "tilt_max_deg", "omega_rms", "omega_freq", "num_terms", "max_rate",
    "rest_probability", "rest_duration", "rest_ramp", "bias_std", "bias_walk", "gyro_noise",
    "acc_rms", "acc_freq", "acc_noise", "magnetic_strength", "magnetic_dip_deg", "mag_noise",
    "hard_iron_probability", "hard_iron_range", "world_disturbance_probability",
    "world_disturbance_rms", "world_disturbance_freq",
)
#: How an observer reads the recordings (:meth:`BroadSimulator._init_readings`): in the config
#: only where they differ from these defaults (the raw 9-D readings), so configs written before
#: them (``configs/system/broad_sim.yaml``, the first zoo entry) are still the whole config.
_READING_DEFAULTS = {"magnetometer": True, "acc_lowpass": 0.0, "rest_bias": False,
                     "acc_lowpass_order": 1}
