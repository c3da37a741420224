"""Causal pre-filters of the readings: the gyroscope's bias from rest, the accelerometer
low-passed in a gyro-strapdown frame.

**Rest bias** (:func:`rest_bias`). At rest the gyroscope measures its bias (0.004 rad/s per axis
on BROAD's IMU, 0.23 deg/s: uncorrected, it tilts an estimate whose correction acts over
seconds by a fraction of a degree, at rest too). Rest is detected as VQF detects it, causally,
over the last ``window`` seconds (1.5 s): every axis of the gyroscope within ``th_gyr`` (2 deg/s)
and of the accelerometer within ``th_acc`` (0.5 m/s^2) standard deviation of its mean over the
window, and the gyroscope's mean below ``th_mean`` (1 deg/s, so a slow steady turn is not taken
for a bias). The bias is the running average, over every rest sample so far, of the gyroscope's
mean over its window (zero before the first rest). Each BROAD trial starts with 26-46 s of rest,
which dominates the average, so the brief near-rests of a hand-held IMU in motion barely move
it: on the 15 training and validation trials it stays within 0.015 deg/s (0.003 RMS) of the
mean over the first rest, where the window mean of the latest rest alone strays by up to
0.8 deg/s.

**Accelerometer low-pass** (:func:`lowpass_acc`).

A tilt correction reads the accelerometer as "up", but during motion it also measures the linear
acceleration, which averages out over time only in a frame that does not turn with the body.
VQF (Laidig and Seel, Information Fusion 2023) therefore low-passes the accelerometer in an
almost inertial frame; :func:`lowpass_acc` does the same, causally, for the learned observer's
input:

* ``Q_t = prod_{i<=t} exp(dt gyr_i)`` the gyroscope integrated from the first sample (body to an
  arbitrary frame that turns only with the gyroscope's bias, 0.004 rad/s on BROAD's IMU);
* ``a^I_t = Q_t acc_t``, low-passed by the first-order filter
  ``f_t = f_{t-1} + alpha (a^I_t - f_{t-1})``, ``alpha = 1 - exp(-dt / tau)``, started at
  ``f_0 = a^I_0``;
* back in the body frame, ``acc'_t = Q_t^T f_t``.

``order=2`` low-passes ``a^I`` by VQF's own filter instead, a second-order Butterworth filter
with the cutoff ``sqrt(2) / (2 pi tau)`` Hz (:func:`butterworth2`), also started at rest on
``a^I_0``. Under a correction that follows it closely it gives VQF's tilt: the complementary
prior alone (``benchmarks/broad_tilt_prior.py --order 2``) reaches VQF's inclination on the
training trials; the zoo's ``broad/attitude`` reads the accelerometer through it
(``docs/real_data.md``).

At rest ``acc' = acc``; under linear acceleration of zero mean over ``tau`` seconds ``acc'`` is
gravity, turned by at most the gyroscope's bias over ``tau`` (about ``0.23 tau`` deg here
uncorrected).

:func:`prefiltered` gives a trial whose ``gyr`` has the rest bias removed (``rest=True``) and
whose ``acc`` is ``acc'`` (``tau > 0``; computed from the corrected gyroscope), so the
observer's layout, its start and everything downstream are unchanged.
Shapes: ``gyr``, ``acc`` ``(T, 3)`` or ``(N, T, 3)`` numpy float64, rad/s and any unit.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch
from scipy.signal import lfilter, lfilter_zi

from groups import SO3

__all__ = [
    "rest_bias", "strapdown", "butterworth2", "butterworth2_at_rest", "check_order", "lowpass_acc",
    "prefiltered", "prefilter_dataset", "OnlinePrefilter",
]

_SO3 = SO3()


def _rolling(x: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Causal mean and standard deviation over the last ``n`` samples along axis -2 (NaN for
    the first ``n - 1``)."""
    c1 = np.cumsum(np.insert(x, 0, 0.0, axis=-2), axis=-2)
    c2 = np.cumsum(np.insert(x * x, 0, 0.0, axis=-2), axis=-2)
    mean = (c1[..., n:, :] - c1[..., :-n, :]) / n
    var = (c2[..., n:, :] - c2[..., :-n, :]) / n - mean**2
    pad = np.full((*x.shape[:-2], n - 1, x.shape[-1]), np.nan)
    return (np.concatenate((pad, mean), -2),
            np.concatenate((pad, np.sqrt(np.clip(var, 0, None))), -2))  # fmt: skip


def rest_bias(
    gyr: np.ndarray, acc: np.ndarray, rate: float, window: float = 1.5,
    th_gyr: float = math.radians(2.0), th_acc: float = 0.5, th_mean: float = math.radians(1.0),
) -> np.ndarray:
    """The gyroscope's bias from rest, ``(*, T, 3)`` rad/s (module docstring); ``gyr`` rad/s,
    ``acc`` m/s^2."""
    gyr, acc = np.asarray(gyr, np.float64), np.asarray(acc, np.float64)
    n = max(2, round(window * rate))
    if gyr.shape[-2] < n:
        return np.zeros_like(gyr)
    g_mean, g_std = _rolling(gyr, n)
    _, a_std = _rolling(acc, n)
    with np.errstate(invalid="ignore"):
        rest = ((g_std.max(-1) < th_gyr) & (a_std.max(-1) < th_acc)
                & (np.linalg.norm(g_mean, axis=-1) < th_mean))  # fmt: skip
    count = np.cumsum(rest, axis=-1)[..., None]
    total = np.cumsum(np.where(rest[..., None], np.nan_to_num(g_mean), 0.0), axis=-2)
    return total / np.maximum(count, 1)  # zero before the first rest


def strapdown(gyr: np.ndarray, dt: float) -> np.ndarray:
    """``(*, T, 3, 3)``: ``Q_t = prod_{i<=t} exp(dt gyr_i)`` of ``gyr`` ``(*, T, 3)`` (a
    parallel prefix product: ``log2 T`` batched matrix products, float64)."""
    Q = _SO3.exp(torch.as_tensor(gyr, dtype=torch.float64) * dt)
    length, d = Q.shape[-3], 1
    while d < length:
        Q = torch.cat((Q[..., :d, :, :], Q[..., :-d, :, :] @ Q[..., d:, :, :]), dim=-3)
        d *= 2
    return Q.numpy()


def butterworth2(rate: float, tau: float) -> tuple[list[float], list[float]]:
    """``(b, a)`` of VQF's accelerometer low-pass: a second-order Butterworth filter with the
    cutoff ``sqrt(2) / (2 pi tau)`` Hz, discretised by the bilinear transform at ``rate`` Hz
    (``a[0] = 1``; unit gain at rest, ``1 / sqrt(2)`` at the cutoff)."""
    k = math.tan(math.pi * (math.sqrt(2.0) / (2.0 * math.pi * tau)) / rate)
    n = 1.0 / (1.0 + math.sqrt(2.0) * k + k * k)
    return ([k * k * n, 2.0 * k * k * n, k * k * n],
            [1.0, 2.0 * (k * k - 1.0) * n, (1.0 - math.sqrt(2.0) * k + k * k) * n])


def check_order(order, owner: str = "the low-pass") -> int:
    """``order`` (1: the first-order low-pass, 2: VQF's second-order Butterworth filter), or a
    ``ValueError`` naming ``owner`` and the choices."""
    if isinstance(order, bool) or order not in (1, 2):
        raise ValueError(f"{owner}: order must be 1 (first order) or 2 (VQF's second-order "
                         f"Butterworth filter), got {order!r}.")
    return int(order)


def butterworth2_at_rest(ba, a):
    """The two state values (direct form II transposed) of :func:`butterworth2`'s filter ``ba``
    at rest on ``a``: the filter started there outputs ``a`` for as long as ``a`` holds (numpy
    arrays or torch tensors alike)."""
    (b0, _, b2), (_, _, a2) = ba
    return (1.0 - b0) * a, (b2 - a2) * a


def lowpass_acc(
    gyr: np.ndarray, acc: np.ndarray, rate: float, tau: float, order: int = 1
) -> np.ndarray:
    """``acc'`` of the module docstring, shaped like ``acc``; ``tau`` seconds (0: ``acc``).
    ``order`` 1: the first-order filter there; 2: VQF's second-order Butterworth filter
    (:func:`butterworth2`), started at rest on ``a^I_0`` like the first."""
    if not (math.isfinite(tau) and tau >= 0):
        raise ValueError(f"the low-pass time constant must be a finite number >= 0 s, got {tau!r}.")
    check_order(order)
    if tau == 0:
        return np.asarray(acc, dtype=np.float64)
    dt = 1.0 / rate
    Q = strapdown(gyr, dt)
    a_i = (Q @ np.asarray(acc, dtype=np.float64)[..., None])[..., 0]
    if order == 1:
        alpha = 1.0 - math.exp(-dt / tau)
        b, a, zi = [alpha], [1.0, alpha - 1.0], (1 - alpha) * a_i[..., :1, :]  # f_0 = a^I_0
    else:
        b, a = butterworth2(rate, tau)
        zi = lfilter_zi(b, a)[:, None] * a_i[..., :1, :]  # at rest on a^I_0: f_0 = a^I_0
    f, _ = lfilter(b, a, a_i, axis=-2, zi=zi)
    return (np.swapaxes(Q, -1, -2) @ f[..., None])[..., 0]


def prefiltered(trial, tau: float = 0.0, rest: bool = False, order: int = 1):
    """``trial`` (a :class:`~.data.Trial`) with its gyroscope's rest bias removed (``rest``)
    and its accelerometer low-passed (``tau`` s, a filter of ``order`` 1 or 2:
    :func:`lowpass_acc`); the trial itself when neither."""
    gyr = trial.gyr - rest_bias(trial.gyr, trial.acc, trial.rate) if rest else trial.gyr
    if tau == 0:
        return dataclasses.replace(trial, gyr=gyr) if rest else trial
    acc = lowpass_acc(gyr, trial.acc, trial.rate, tau, order)
    return dataclasses.replace(trial, gyr=gyr, acc=acc)


def prefilter_dataset(data, dt: float, tau: float = 0.0, rest: bool = False, g0: float = 9.81,
                      order: int = 1):
    """A full-rate :class:`~manifold_nets.data.TrajectoryDataset` of the BROAD layout
    (``y = (acc / g0, mag)``, ``u = gyr`` over each step, step ``dt`` s) pre-filtered like
    :func:`prefiltered`."""
    if tau == 0 and not rest:
        return data
    y, u = data.measurements.clone(), data.inputs.clone()
    gyr, acc = u.double().numpy(), y[..., :3].double().numpy()
    if rest:
        gyr = gyr - rest_bias(gyr, acc * g0, 1.0 / dt)
        u = torch.from_numpy(gyr).to(u)
    if tau:
        y[..., :3] = torch.from_numpy(lowpass_acc(gyr, acc, 1.0 / dt, tau, order)).to(y)
    return type(data)(data.states, y, u, data.meta, data.mask)


class OnlinePrefilter:
    """:func:`prefiltered` one sample at a time, for online use: ``update(gyr, acc) -> (gyr',
    acc')`` (each ``(3,)`` numpy, rad/s and m/s^2; ``order`` that of :func:`lowpass_acc`, the
    second order's state in direct form II transposed) with the same results as the batch functions
    (to rounding: running sums over a ring buffer of the rest window, the strapdown frame
    multiplied out sample by sample)."""

    def __init__(self, rate: float, tau: float = 0.0, rest: bool = False, window: float = 1.5,
                 order: int = 1):
        self.rate, self.tau, self.rest = float(rate), float(tau), bool(rest)
        self.ba = butterworth2(self.rate, self.tau) if check_order(order) == 2 and tau else None
        self.z = None  # the second-order filter's state (direct form II transposed)
        self.n = max(2, round(window * rate))
        self.buf = np.zeros((self.n, 3, 3))  # gyr, gyr^2, acc per sample
        self.sums = np.zeros((3, 3))
        self.acc2 = np.zeros((self.n, 3))
        self.sum_acc2 = np.zeros(3)
        self.count, self.k = 0, 0
        self.total, self.rests = np.zeros(3), 0
        self.alpha = 1.0 - math.exp(-1.0 / (rate * tau)) if tau else 0.0
        self.Q, self.f = np.eye(3), None

    def _bias(self, gyr: np.ndarray, acc: np.ndarray) -> np.ndarray:
        row = np.stack((gyr, gyr * gyr, acc))
        i = self.k % self.n
        self.sums += row - self.buf[i]
        self.sum_acc2 += acc * acc - self.acc2[i]
        self.buf[i], self.acc2[i] = row, acc * acc
        self.k += 1
        if self.k >= self.n:
            mean = self.sums[0] / self.n
            g_std = np.sqrt(np.clip(self.sums[1] / self.n - mean**2, 0, None))
            a_mean = self.sums[2] / self.n
            a_std = np.sqrt(np.clip(self.sum_acc2 / self.n - a_mean**2, 0, None))
            if (g_std.max() < math.radians(2.0) and a_std.max() < 0.5
                    and np.linalg.norm(mean) < math.radians(1.0)):  # fmt: skip
                self.total, self.rests = self.total + mean, self.rests + 1
        return self.total / max(self.rests, 1)

    def update(self, gyr: np.ndarray, acc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        gyr, acc = np.asarray(gyr, np.float64), np.asarray(acc, np.float64)
        if self.rest:
            gyr = gyr - self._bias(gyr, acc)
        if not self.tau:
            return gyr, acc
        w = gyr / self.rate
        t = math.sqrt(float(w @ w))
        K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
        inc = np.eye(3) + K if t < 1e-8 else (
            np.eye(3) + math.sin(t) / t * K + (1 - math.cos(t)) / t**2 * (K @ K))
        self.Q = self.Q @ inc
        a_i = self.Q @ acc
        if self.ba is not None:
            (b0, b1, b2), (_, a1, a2) = self.ba
            if self.z is None:  # at rest on a^I_0
                self.z = list(butterworth2_at_rest(self.ba, a_i))
            self.f = b0 * a_i + self.z[0]
            self.z = [b1 * a_i - a1 * self.f + self.z[1], b2 * a_i - a2 * self.f]
        else:
            self.f = a_i if self.f is None else self.f + self.alpha * (a_i - self.f)
        return gyr, self.Q.T @ self.f
