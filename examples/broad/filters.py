"""Classical filters on BROAD, tuned on training trials only: Mahony's complementary filter and
the project's error-state EKF on SO(3) x R^3.

Both use the accelerometer as a measured "up" (``(0, 0, 1)`` in ENU: at rest it reads the
reaction to gravity) and the magnetometer as a measured ``m_ref``, the unit field direction in ENU
estimated from training trials (:func:`magnetic_reference`), both normalised to unit length; the
gyro drives the prediction (the sample's own reading over the step into it, as in
:mod:`.data`). Both start at sample 0 from TRIAD (acc up first, mag second) and return one
quaternion ``(T, 4)`` (w, x, y, z) per sample, sample 0 included.

**Complementary** (Mahony, Hamel, Pflimlin, IEEE TAC 2008, the explicit complementary filter
with bias estimation), with ``v_hat = R_hat^T v_ref``::

    w_mes = (a x a_hat) + k_m (m x m_hat)
    R_hat <- R_hat exp((gyr - b_hat + k_p w_mes) dt),    b_hat <- b_hat - k_i w_mes dt

batched over trials and a grid of gains ``(k_p, k_i, k_m)`` at once (numpy float64).

**EKF** (:class:`BroadFilterModel` in :class:`manifold_nets.ekf.ErrorStateEKF`, analytic
Jacobians): state ``(R, b_omega)`` on ``Product(SO3(), Euclidean(3))``, drive ``(gyr - b - n_g,
n_b)`` (gyro noise, bias random walk per step), update ``(a, m) = (R^T e_z, R^T m_ref) + r``.
Batched over trials and a grid of noise levels (the covariances carry a batch dimension). The
model's ``linearize_*`` methods compute each stage of a step in one pass (one ``exp`` for the
prediction and its Jacobians, one for the correction and the reset), so a step is about a
hundred torch operations.

Tuning (:func:`tune`): the gains with the least mean (over training trials) total RMSE of the
benchmark's metric, the error accumulated online so a grid over whole trials fits in memory.
"""

from __future__ import annotations

import itertools
import math
import time

import numpy as np
import torch

from groups import SO3, Euclidean, Product
from manifold_nets.ekf import ErrorStateEKF, FilterModel
from manifold_nets.ekf_so3 import exp_and_left_jacobian, matmul, skew_matrix

from ..attitude.triad import triad
from .data import Trial, quat_to_matrix
from .metric import matrix_to_quat

__all__ = [
    "MAHONY_GRID",
    "EKF_GRID",
    "magnetic_reference",
    "initial_attitude",
    "complementary",
    "BroadFilterModel",
    "ekf",
    "tune",
    "dead_reckoning",
]

UP = np.array([0.0, 0.0, 1.0])
#: ``(k_p, k_i, k_m)``: rad/s per unit of cross product, 1/s^2, the magnetometer's weight
MAHONY_GRID = {"k_p": [0.1, 0.3, 1.0, 3.0], "k_i": [0.0, 0.003, 0.03], "k_m": [0.1, 0.3, 1.0]}
#: standard deviations: gyro rad/s, bias walk rad/s per step, unit acc and unit mag per step
#: (9 combinations: a step of the EKF takes about 0.4 ms of one CPU core at a batch of 8, 0.85 ms
#: at 99 (this grid over the 11 training trials), 1.6 ms at 200 (benchmarks/results/ekf.md), and
#: :func:`tune` runs it on the first ``max_samples`` of each trial)
EKF_GRID = {
    "gyro": [0.01],
    "bias_walk": [1e-5],
    "acc": [0.1, 0.3, 1.0],
    "mag": [0.3, 1.0, 3.0],
}
#: samples per training trial :func:`tune` uses for the EKF by default (52 s of each)
EKF_TUNE_SAMPLES = 15000


def _head(trial: Trial, n: int) -> Trial:
    """The first ``n`` samples of ``trial``."""
    cut = {f: getattr(trial, f)[:n] for f in ("gyr", "acc", "mag", "quat", "movement")}
    return Trial(name=trial.name, rate=trial.rate, **cut)


class _OneThread:
    """Torch on one thread inside the block: the EKF's small batched ops only lose from more
    (on a shared machine the idle threads spin and slow every step several-fold)."""

    def __enter__(self):
        self.n = torch.get_num_threads()
        torch.set_num_threads(1)

    def __exit__(self, *exc):
        torch.set_num_threads(self.n)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def magnetic_reference(trials: list[Trial]) -> np.ndarray:
    """``m_ref`` ``(3,)``: the mean of ``R_ref unit(mag)`` over known-reference samples, unit."""
    total = np.zeros(3)
    for t in trials:
        k = t.known
        total += np.einsum("tij,tj->i", quat_to_matrix(t.quat[k]), _unit(t.mag[k]))
    return _unit(total)


def initial_attitude(acc: np.ndarray, mag: np.ndarray, m_ref: np.ndarray) -> np.ndarray:
    """TRIAD ``(..., 3, 3)`` from body ``acc``, ``mag`` ``(..., 3)``: acc up, mag to ``m_ref``."""
    t = [torch.as_tensor(np.asarray(v, dtype=np.float64)) for v in (acc, mag, UP, m_ref)]
    return triad(*t).numpy()


def _padded(trials: list[Trial]) -> dict[str, np.ndarray]:
    """``(Nt, Tmax, ...)`` unit acc/mag, gyro, reference (flat matrices ``ref``, quaternions
    ``refq``) and ``use`` (the scored samples: movement and a known reference).

    Trials shorter than the longest are padded with their last sample (never scored).
    """
    t_max = max(len(t) for t in trials)

    def pad(a):
        return np.concatenate((a, np.repeat(a[-1:], t_max - len(a), axis=0)))

    out = {"gyr": [], "acc": [], "mag": [], "ref": [], "refq": [], "use": []}
    for t in trials:
        known = t.known
        refq = np.where(known[:, None], t.quat, [1.0, 0, 0, 0])
        out["refq"].append(pad(refq))
        ref = quat_to_matrix(refq).reshape(-1, 9)
        use = np.zeros(t_max, dtype=bool)
        use[: len(t)] = t.movement & known
        out["gyr"].append(pad(t.gyr))
        out["acc"].append(pad(_unit(t.acc)))
        out["mag"].append(pad(_unit(t.mag)))
        out["ref"].append(pad(ref))
        out["use"].append(use)
    return {k: np.stack(v) for k, v in out.items()}


def _angle_sq(R_flat: np.ndarray, ref_flat: np.ndarray) -> np.ndarray:
    """Squared total angle between rotations given flat ``(..., 9)``: ``arccos((tr - 1) / 2)^2``."""
    tr = (R_flat * ref_flat).sum(-1)
    return np.arccos(np.clip((tr - 1) / 2, -1.0, 1.0)) ** 2


def _quat_exp(theta: np.ndarray) -> np.ndarray:
    """``exp`` of rotation vectors ``(..., 3)`` as quaternions ``(..., 4)``."""
    a = np.linalg.norm(theta, axis=-1, keepdims=True)
    s = np.where(a > 1e-12, np.sin(a / 2) / np.maximum(a, 1e-300), 0.5 - a * a / 48)
    return np.concatenate((np.cos(a / 2), s * theta), axis=-1)


def _qmul(p, q):
    pw, pv = p[..., :1], p[..., 1:]
    qw, qv = q[..., :1], q[..., 1:]
    w = pw * qw - (pv * qv).sum(-1, keepdims=True)
    return np.concatenate((w, pw * qv + qw * pv + np.cross(pv, qv)), axis=-1)


def _mahony_loop(data, m_ref, gains, rate, store):
    """The filter over padded ``data`` for gains ``(G, 3)``: states ``(G, Nt, ...)``.

    Returns ``(quats (G, Nt, T, 4) or None, sum of squared total errors (G, Nt), counts (Nt,))``.
    """
    kp, ki, km = (gains[:, i, None, None] for i in range(3))
    n_g, (n_t, t_max) = len(gains), data["gyr"].shape[:2]
    R0 = initial_attitude(data["acc"][:, 0], data["mag"][:, 0], m_ref)
    q = np.broadcast_to(matrix_to_quat(R0), (n_g, n_t, 4)).copy()
    b = np.zeros((n_g, n_t, 3))
    out = np.empty((n_g, n_t, t_max, 4)) if store else None
    sq = np.zeros((n_g, n_t))
    dt = 1.0 / rate
    for k in range(t_max):
        if k > 0:
            R = quat_to_matrix(q)
            a_hat, m_hat = R[..., 2, :], np.einsum("gnji,j->gni", R, m_ref)
            w_mes = np.cross(data["acc"][:, k], a_hat) + km * np.cross(data["mag"][:, k], m_hat)
            q = _qmul(q, _quat_exp((data["gyr"][:, k] - b + kp * w_mes) * dt))
            q /= np.linalg.norm(q, axis=-1, keepdims=True)
            b = b - ki * w_mes * dt
        if store:
            out[:, :, k] = q
        use = data["use"][:, k]
        if use.any():
            dot = np.abs((q[:, use] * data["refq"][use, k]).sum(-1))
            sq[:, use] += (2 * np.arccos(np.clip(dot, 0.0, 1.0))) ** 2
    return out, sq, data["use"].sum(1)


def complementary(
    trials: list[Trial], m_ref: np.ndarray, k_p: float, k_i: float, k_m: float
) -> list[np.ndarray]:
    """Mahony's filter with the given gains on each trial: quaternions ``(T, 4)`` per trial."""
    data = _padded(trials)
    quats, _, _ = _mahony_loop(data, m_ref, np.array([[k_p, k_i, k_m]]), trials[0].rate, True)
    return [quats[0, i, : len(t)] for i, t in enumerate(trials)]


def dead_reckoning(trials: list[Trial], m_ref: np.ndarray) -> list[np.ndarray]:
    """The gyro integrated from the TRIAD start, no correction (quaternions ``(T, 4)`` each)."""
    return complementary(trials, m_ref, 0.0, 0.0, 0.0)


class BroadFilterModel(FilterModel):
    """The AHRS of BROAD for :class:`~manifold_nets.ekf.ErrorStateEKF`; see the module docstring.

    ``x`` ``(*batch, 12)`` (``R`` row-major, ``b``), ``y`` ``(*batch, 6)`` unit (acc, mag),
    ``u`` ``(*batch, 3)`` gyro rad/s. The noise levels are floats or tensors ``(B,)`` (one per
    sequence of a batched grid); then the covariances are ``(B, 6, 6)``.
    """

    group = Product(SO3(), Euclidean(3), names=("R", "b_omega"))
    measurement_dim = 6
    input_dim = 3
    process_noise_dim = 6
    measurement_noise_dim = 6

    def __init__(self, rate, m_ref, gyro=0.01, bias_walk=1e-5, acc=0.3, mag=1.0):
        self.dt = 1.0 / float(rate)
        self.m_ref = torch.as_tensor(np.asarray(m_ref, dtype=np.float64))
        self.std = {"gyro": gyro, "bias_walk": bias_walk, "acc": acc, "mag": mag}
        self._made: dict = {}

    def _cov(self, names, dtype, device):
        parts = [torch.as_tensor(self.std[n], dtype=dtype, device=device) for n in names]
        std = torch.stack(torch.broadcast_tensors(*parts), -1)
        return torch.diag_embed(std.repeat_interleave(3, -1) ** 2)

    def _constants(self, like: torch.Tensor) -> dict[str, torch.Tensor]:
        """``world`` ``(3, 2)`` (``e_z``, ``m_ref``), ``bias_rows`` ``[0 | I_3]`` ``(3, 6)`` (and
        twice, ``bias_rows_FG``), ``zeros`` ``(6, 3)``, in ``like``'s dtype and device, made
        once."""
        key = (like.dtype, like.device)
        c = self._made.get(key)
        if c is None:
            up = torch.tensor([0.0, 0.0, 1.0], dtype=like.dtype, device=like.device)
            eye6 = torch.eye(6, dtype=like.dtype, device=like.device)
            c = self._made[key] = {
                "world": torch.stack((up, self.m_ref.to(like)), -1),
                "bias_rows": eye6[3:],
                "bias_rows_FG": torch.cat((eye6[3:], eye6[3:]), -1),
                "zeros": torch.zeros(6, 3, dtype=like.dtype, device=like.device),
            }
        return c

    def drive(self, x, y, u, noise=None):
        w = u - x[..., 9:12]
        if noise is None:
            return torch.cat((w, torch.zeros_like(w)), -1)
        return torch.cat((w - noise[..., :3], noise[..., 3:]), -1)

    def step(self, x, drive):
        return self.group.rplus(x, torch.cat((drive[..., :3] * self.dt, drive[..., 3:]), -1))

    def _directions(self, x):
        """``R^T (e_z, m_ref)`` ``(*batch, 2, 3)``."""
        R = x[..., :9].unflatten(-1, (3, 3))
        return (R.transpose(-1, -2) @ self._constants(x)["world"]).transpose(-1, -2)

    def measure(self, x, drive, noise=None):
        z = self._directions(x).reshape(*x.shape[:-1], 6)
        return z if noise is None else z + noise

    def process_noise_cov(self, dtype, device=None):
        return self._cov(("gyro", "bias_walk"), dtype, device)

    def measurement_noise_cov(self, dtype, device=None):
        return self._cov(("acc", "mag"), dtype, device)

    def initial_state(self, batch, dtype, device=None):
        x0 = self.group.identity((batch,), dtype=dtype, device=device)
        std = torch.tensor([1.0] * 3 + [0.01] * 3, dtype=dtype, device=device)
        return x0, torch.diag_embed(std**2).expand(batch, 6, 6).clone()

    def _blocks(self, top: torch.Tensor) -> torch.Tensor:
        """``[[top], [0 | I_3]]`` ``(*batch, 6, 6)`` from ``top`` ``(*batch, 3, 6)``."""
        rows = self._constants(top)["bias_rows"].expand(*top.shape[:-2], 3, 6)
        return torch.cat((top, rows), -2)

    def linearize_step(self, x, y, u):
        """``R^- = R exp(w dt)``, ``w = u - b``; ``F = [[exp(w dt)^T, -J_r dt], [0, I]]``,
        ``G = [[-J_r dt, 0], [0, I]]`` with ``J_r = J_r(w dt)``."""
        w = u - x[..., 9:12]
        E, Jl, _, _ = exp_and_left_jacobian(w * self.dt)
        R = x[..., :9].unflatten(-1, (3, 3))
        x_pred = torch.cat((matmul(R, E).flatten(-2), x[..., 9:12]), -1)
        mJr = Jl.transpose(-1, -2) * -self.dt
        c = self._constants(x)
        top = torch.cat((E.transpose(-1, -2), mJr, mJr, c["zeros"][:3].expand_as(E)), -1)
        FG = torch.cat((top, c["bias_rows_FG"].expand_as(top)), -2)  # [F | G]
        return x_pred, torch.cat((w, torch.zeros_like(w)), -1), FG[..., :6], FG[..., 6:]

    def process_jacobians(self, x, y, u):
        return self.linearize_step(x, y, u)[2:]

    def linearize_measurement(self, x, drive, y):
        """``nu = y - (R^T e_z, R^T m_ref)``, ``H = [[[d_1]x, 0], [[d_2]x, 0]]``, ``M = I``."""
        d = self._directions(x)  # (*batch, 2, 3)
        nu = y - d.reshape(*x.shape[:-1], 6)
        Hd = skew_matrix(d).reshape(*x.shape[:-1], 6, 3)
        zeros = self._constants(x)["zeros"].expand(*x.shape[:-1], 6, 3)
        return nu, torch.cat((Hd, zeros), -1), None

    def measurement_jacobians(self, x, drive):
        _, H, _ = self.linearize_measurement(x, drive, x.new_zeros(*x.shape[:-1], 6))
        return H, torch.eye(6, dtype=x.dtype, device=x.device).expand(*x.shape[:-1], 6, 6)

    def linearize_reset(self, x, delta):
        """``(R exp(dtheta), b + db)`` and ``blockdiag(J_r(dtheta), I_3)``."""
        E, Jl, _, _ = exp_and_left_jacobian(delta[..., :3])
        R = x[..., :9].unflatten(-1, (3, 3))
        x_new = torch.cat((matmul(R, E).flatten(-2), x[..., 9:12] + delta[..., 3:]), -1)
        zeros = self._constants(x)["zeros"][:3].expand_as(E)
        return x_new, self._blocks(torch.cat((Jl.transpose(-1, -2), zeros), -1))

    def reset_jacobian(self, x, delta):
        return self.linearize_reset(x, delta)[1]


def _ekf_loop(data, m_ref, noise, rate, store):
    """The EKF over padded ``data`` for noise levels ``noise`` ``{name: (G,)}``, batch ``G * Nt``.

    Returns ``(flat R (G, Nt, T, 9) or None, squared total errors (G, Nt), counts (Nt,), s)``.
    """
    n_g, (n_t, t_max) = len(next(iter(noise.values()))), data["gyr"].shape[:2]
    per_seq = {k: torch.as_tensor(np.repeat(np.asarray(v, float), n_t)) for k, v in noise.items()}
    model = BroadFilterModel(rate, m_ref, **per_seq)
    filt = ErrorStateEKF(model, jacobians="analytic", progress=False)
    # the measurements and the gyro of every step, time-major: (T, Nt, 6), (T, Nt, 3)
    y_all = torch.from_numpy(np.concatenate((data["acc"], data["mag"]), -1).swapaxes(0, 1).copy())
    u_all = torch.from_numpy(data["gyr"].swapaxes(0, 1).copy())
    R0 = torch.from_numpy(initial_attitude(data["acc"][:, 0], data["mag"][:, 0], m_ref))
    x0 = torch.cat((R0.reshape(n_t, 9), torch.zeros(n_t, 3)), -1).repeat(n_g, 1)
    std = torch.tensor([0.05] * 3 + [0.01] * 3, dtype=torch.float64)
    state = filt.init(n_g * n_t, x0=x0, P0=torch.diag_embed(std**2).expand(n_g * n_t, 6, 6))
    consts = filt.constants(torch.float64)
    out = np.empty((n_g, n_t, t_max, 9)) if store else None
    sq = np.zeros((n_g, n_t))
    t0 = time.perf_counter()
    with torch.inference_mode(), _OneThread():
        for k in range(t_max):
            if k > 0:
                y, u = y_all[k], u_all[k]
                if n_g > 1:  # one copy per grid point
                    y, u = y.repeat(n_g, 1), u.repeat(n_g, 1)
                state, _ = filt.step(state, y, u, True, consts)
            R = state.x[:, :9].numpy().reshape(n_g, n_t, 9)
            if store:
                out[:, :, k] = R
            use = data["use"][:, k]
            if use.any():
                sq[:, use] += _angle_sq(R[:, use], data["ref"][use, k])
    return out, sq, data["use"].sum(1), time.perf_counter() - t0


def ekf(trials: list[Trial], m_ref: np.ndarray, **noise: float) -> list[np.ndarray]:
    """The EKF with noise levels ``noise`` (:data:`EKF_GRID`'s names) on each trial: ``(T, 4)``.

    The wall time of the filter loop is left in ``ekf.seconds``.
    """
    levels = {k: [noise.get(k, v[0])] for k, v in EKF_GRID.items()}
    flat, _, _, seconds = _ekf_loop(_padded(trials), m_ref, levels, trials[0].rate, True)
    ekf.seconds = seconds
    return [matrix_to_quat(flat[0, i, : len(t)].reshape(-1, 3, 3)) for i, t in enumerate(trials)]


def tune(
    method: str, trials: list[Trial], m_ref: np.ndarray, grid: dict | None = None,
    max_samples: int | None = -1,
):
    """Grid search on ``trials`` (training only): ``(best gains dict, [(gains, mean RMSE deg)])``.

    ``method`` is ``"complementary"`` (grid :data:`MAHONY_GRID`) or ``"ekf"`` (:data:`EKF_GRID`);
    the score is the mean over trials of the total RMSE (degrees) of the benchmark's metric.
    ``max_samples``: score on the first samples of each trial only (``None``: whole trials;
    default: whole trials for the complementary filter, :data:`EKF_TUNE_SAMPLES` for the EKF).
    """
    if max_samples == -1:
        max_samples = None if method == "complementary" else EKF_TUNE_SAMPLES
    if max_samples is not None:
        trials = [_head(t, max_samples) for t in trials]
    if method not in ("complementary", "ekf"):
        raise ValueError(f"method must be 'complementary' or 'ekf', got {method!r}.")
    grid = grid or (MAHONY_GRID if method == "complementary" else EKF_GRID)
    names = list(grid)
    combos = np.array(list(itertools.product(*(grid[n] for n in names))), dtype=float)
    data = _padded(trials)
    if method == "complementary":
        _, sq, count, *_ = _mahony_loop(data, m_ref, combos, trials[0].rate, False)
    else:
        cols = {n: combos[:, i] for i, n in enumerate(names)}
        _, sq, count, _ = _ekf_loop(data, m_ref, cols, trials[0].rate, False)
    score = np.degrees(np.sqrt(sq / np.maximum(count, 1))).mean(1)
    score = np.where(np.isfinite(score), score, math.inf)
    table = [(dict(zip(names, map(float, c))), float(s)) for c, s in zip(combos, score)]
    return table[int(np.argmin(score))][0], table
