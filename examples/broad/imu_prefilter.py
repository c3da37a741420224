""":mod:`.prefilter`'s two causal pre-filters in torch, as the library's readings-filter piece.

:class:`ImuPrefilter` is a :class:`manifold_nets.observer.ReadingsFilter` of BROAD's layout
(``y = (acc / G0, mag / M0)`` ``(*, 6)``, ``u = gyr`` ``(*, 3)`` rad/s, paired as the observer
reads them): the gyroscope less its bias estimated at rest (``rest``), the accelerometer
low-passed over ``tau`` seconds in a gyro-strapdown frame (``tau > 0``), and for a 6-D observer
the magnetometer zeroed (``magnetometer=False``), at ``rate`` samples a second. Its step is
:class:`.prefilter.OnlinePrefilter`'s, batched and without a data-dependent branch (so
``torch.export`` traces it); its whole-sequence method the batch functions' (:func:`.prefilter.
rest_bias`, :func:`.prefilter.lowpass_acc`) continued from a state. Step, sequence, the online
and the batch numpy filters agree to rounding (``tests/test_broad_prefilter_piece.py``).

State, each ``(B, ...)`` in the filter's dtype: ``count`` ``(B,)`` the samples seen; with
``rest``: ``window`` ``(B, n, 12)`` the last ``n`` samples' ``(gyr, gyr^2, acc, acc^2)`` (acc in
m/s^2), oldest first (zeros before the start), ``bias_sum`` ``(B, 3)`` the sum of the window
means at rest so far and ``rests`` ``(B,)`` their number; with ``tau > 0``: ``frame`` ``(B, 3,
3)`` the strapdown ``Q_t`` and ``lowpassed`` ``(B, 3)`` the filtered ``f_t`` (in ``y``'s units;
with ``order=2``, VQF's second-order filter, ``lowpass_state`` ``(B, 3, 2)`` instead).

:meth:`~.simulator.BroadSimulator.readings_filter` builds one from the system's config (its
``rest_bias``, ``acc_lowpass``, ``magnetometer`` and ``dt``): the filter runs at the observer's
step. For an observer that steps every ``k``-th sample (``zoo:broad/attitude``: ``k = 8``) that
is the decimated stream's rate; the BROAD commands filter the full-rate recording before they
decimate it (``docs/real_data.md`` gives the difference).
"""

from __future__ import annotations

import math

import torch

from groups import SO3
from manifold_nets.observer import ReadingsFilter
from manifold_nets.system import check_number

from .data import G0
from .prefilter import butterworth2, butterworth2_at_rest, check_order

__all__ = ["ImuPrefilter", "MAX_WINDOW"]

_SO3 = SO3()
#: The longest rest window, in samples, a filter may hold (1.5 s at 66 kHz): a config with a
#: tiny ``dt`` is refused instead of allocating gigabytes.
MAX_WINDOW = 100_000


def _positive(name: str, v, zero: bool = False) -> float:
    return check_number("ImuPrefilter", name, v, positive=not zero)


class ImuPrefilter(ReadingsFilter):
    """The rest bias, the strapdown low-pass and the zeroed magnetometer; see the module.

    Args:
        rate: samples a second of the readings it is fed.
        tau: the low-pass time constant in seconds (0: the accelerometer as it is).
        rest: remove the gyroscope's bias estimated at rest.
        magnetometer: keep the magnetometer (``False``: its columns zeroed, a 6-D observer).
        window: the rest window in seconds; ``th_gyr`` (rad/s), ``th_acc`` (m/s^2) and
            ``th_mean`` (rad/s) VQF's rest thresholds; ``g0`` the accelerometer's unit in
            ``y`` (m/s^2).
        order: the low-pass, 1 (first order) or 2 (VQF's second-order Butterworth filter,
            :func:`.prefilter.butterworth2`; its state ``lowpass_state`` ``(B, 3, 2)``, direct
            form II transposed, in place of ``lowpassed``).
    """

    name = "broad_imu_prefilter"

    def __init__(self, rate: float, tau: float = 0.0, rest: bool = False,
                 magnetometer: bool = True, window: float = 1.5,
                 th_gyr: float = math.radians(2.0), th_acc: float = 0.5,
                 th_mean: float = math.radians(1.0), g0: float = G0, order: int = 1):
        super().__init__(measurement_dim=6, input_dim=3)
        self.order = check_order(order, "ImuPrefilter")
        self.rate, self.tau = _positive("rate", rate), _positive("tau", tau, zero=True)
        for what, flag in (("rest", rest), ("magnetometer", magnetometer)):
            if not isinstance(flag, bool):
                raise ValueError(f"ImuPrefilter: {what} must be true or false, got {flag!r}.")
        self.rest, self.magnetometer = rest, magnetometer
        self.window = _positive("window", window)
        self.th_gyr, self.th_acc = _positive("th_gyr", th_gyr), _positive("th_acc", th_acc)
        self.th_mean, self.g0 = _positive("th_mean", th_mean), _positive("g0", g0)
        self.n = max(2, round(self.window * self.rate))
        if rest and self.n > MAX_WINDOW:
            raise ValueError(
                f"ImuPrefilter: a rest window of {self.window:g} s at {self.rate:g} Hz holds "
                f"{self.n} samples, more than {MAX_WINDOW}; is the rate (1 / the system's dt) "
                "right?"
            )
        self.alpha = 1.0 - math.exp(-1.0 / (self.rate * self.tau)) if self.tau else 0.0
        self.ba = butterworth2(self.rate, self.tau) if self.tau and order == 2 else None

    def extra_signature(self) -> dict:
        return {"rate": self.rate, "tau": self.tau, "rest": self.rest,
                "magnetometer": self.magnetometer, "window": self.window, "th_gyr": self.th_gyr,
                "th_acc": self.th_acc, "th_mean": self.th_mean, "g0": self.g0,
                **({"order": 2} if self.order == 2 else {})}  # fmt: skip

    def state_names(self) -> list[str]:
        lowpass = ["frame", "lowpass_state" if self.ba is not None else "lowpassed"]
        return (["count"] + (["window", "bias_sum", "rests"] if self.rest else [])
                + (lowpass if self.tau else []))  # fmt: skip

    def init_state(self, batch: int, dtype: torch.dtype = torch.float64, device=None):
        if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
            raise ValueError(f"batch must be a positive integer, got {batch!r}.")
        kw = {"dtype": dtype, "device": device}
        out = [torch.zeros(batch, **kw)]
        if self.rest:
            out += [torch.zeros(batch, self.n, 12, **kw), torch.zeros(batch, 3, **kw),
                    torch.zeros(batch, **kw)]
        if self.tau:
            shape = (batch, 3, 2) if self.ba is not None else (batch, 3)
            out += [torch.eye(3, **kw).expand(batch, 3, 3).clone(), torch.zeros(shape, **kw)]
        return tuple(out)

    def _rest_test(self, sums: torch.Tensor, seen: torch.Tensor):
        """``(window mean of gyr (*, 3), at rest (*,))`` from window sums ``(*, 12)``."""
        s = sums / self.n
        mean, a_mean = s[..., 0:3], s[..., 6:9]
        g_std = (s[..., 3:6] - mean * mean).clamp_min(0).sqrt()
        a_std = (s[..., 9:12] - a_mean * a_mean).clamp_min(0).sqrt()
        rest = ((seen >= self.n) & (g_std.amax(-1) < self.th_gyr) & (a_std.amax(-1) < self.th_acc)
                & (torch.linalg.vector_norm(mean, dim=-1) < self.th_mean))  # fmt: skip
        return mean, rest

    def _rows(self, gyr: torch.Tensor, acc: torch.Tensor) -> torch.Tensor:
        a = acc * self.g0
        return torch.cat((gyr, gyr * gyr, a, a * a), -1)

    def _out(self, y: torch.Tensor, acc: torch.Tensor) -> torch.Tensor:
        mag = y[..., 3:6] if self.magnetometer else torch.zeros_like(y[..., 3:6])
        return torch.cat((acc, mag), -1)

    def step_unchecked(self, state, y, u):
        count, rest = state[0], state[1:]
        gyr, acc = u, y[:, 0:3]
        out = [count + 1]
        if self.rest:
            window, total, rests = rest[:3]
            rest = rest[3:]
            window = torch.cat((window[:, 1:], self._rows(gyr, acc)[:, None]), 1)
            mean, at_rest = self._rest_test(window.sum(1), count + 1)
            total = total + torch.where(at_rest[:, None], mean, torch.zeros_like(mean))
            rests = rests + at_rest.to(rests.dtype)
            gyr = gyr - total / rests.clamp_min(1)[:, None]
            out += [window, total, rests]
        if self.tau:
            frame, f = rest
            frame = frame @ _SO3.exp(gyr / self.rate)
            a_i = (frame @ acc[:, :, None])[..., 0]
            if self.ba is not None:
                (b0, b1, b2), (_, a1, a2) = self.ba
                z = torch.where((count == 0)[:, None, None], self._at_rest(a_i), f)
                f = b0 * a_i + z[..., 0]
                state = torch.stack((b1 * a_i - a1 * f + z[..., 1], b2 * a_i - a2 * f), -1)
            else:
                f = torch.where((count == 0)[:, None], a_i, f)  # f_0 = a^I_0
                f = state = f + self.alpha * (a_i - f)
            acc = (frame.transpose(-1, -2) @ f[:, :, None])[..., 0]
            out += [frame, state]
        return tuple(out), self._out(y, acc), gyr

    def _at_rest(self, a: torch.Tensor) -> torch.Tensor:
        """``(*, 3, 2)``: the second-order filter's state at rest on ``a`` ``(*, 3)``."""
        return torch.stack(butterworth2_at_rest(self.ba, a), -1)

    def sequence_unchecked(self, state, y, u):
        if y.shape[1] == 0:
            return state, y, u
        count, rest = state[0], state[1:]
        steps = y.shape[1]
        seen = count[:, None] + torch.arange(1, steps + 1, dtype=count.dtype, device=count.device)
        gyr, acc = u, y[..., 0:3]
        out = [count + steps]
        if self.rest:
            window, total, rests = rest[:3]
            rest = rest[3:]
            history = torch.cat((window, self._rows(gyr, acc)), 1)  # (N, n + T, 12)
            mean, at_rest = self._rest_test(_window_sums(history, self.n), seen)
            total = total[:, None] + torch.where(at_rest[..., None], mean, 0.0).cumsum(1)
            rests = rests[:, None] + at_rest.to(rests.dtype).cumsum(1)
            gyr = gyr - total / rests.clamp_min(1)[..., None]
            out += [history[:, -self.n :], total[:, -1], rests[:, -1]]
        if self.tau:
            frame, f = rest
            frames = frame[:, None] @ _prefix_product(_SO3.exp(gyr / self.rate))
            a_i = (frames @ acc[..., None])[..., 0]
            if self.ba is not None:
                z = torch.where((count == 0)[:, None, None], self._at_rest(a_i[:, 0]), f)
                f, last = _lowpass2(a_i, z, self.ba)
            else:
                f = torch.where((count == 0)[:, None], a_i[:, 0], f)  # f_0 = a^I_0
                f = _lowpass(a_i, f, self.alpha)
                last = f[:, -1]
            acc = (frames.transpose(-1, -2) @ f[..., None])[..., 0]
            out += [frames[:, -1], last]
        return tuple(out), self._out(y, acc), gyr


def _window_sums(history: torch.Tensor, n: int) -> torch.Tensor:
    """``(N, T, W)``: the sum of the ``n`` rows of ``history`` ``(N, n + T, W)`` ending at each
    of its last ``T`` rows, each a sum of at most ``n`` numbers (a running prefix and suffix sum
    within blocks of ``n`` rows: no cumulative sum over the whole sequence to lose digits in)."""
    nb, length, w = history.shape
    blocks = -(-length // n)
    h = torch.cat((history, history.new_zeros(nb, blocks * n - length, w)), 1).unflatten(1, (blocks, n))
    prefix = h.cumsum(2)
    suffix = h.flip(2).cumsum(2).flip(2)  # suffix[b, i]: rows i.. of block b
    after = torch.cat((suffix[:, :, 1:], suffix.new_zeros(nb, blocks, 1, w)), 2)
    sums = prefix[:, 1:] + after[:, :-1]  # window ending at row r of block b >= 1
    return sums.flatten(1, 2)[:, : length - n]


def _prefix_product(m: torch.Tensor) -> torch.Tensor:
    """``(N, T, 3, 3)``: ``m_0 m_1 .. m_t`` for each ``t`` (``log2 T`` batched products)."""
    d, length = 1, m.shape[1]
    while d < length:
        m = torch.cat((m[:, :d], m[:, :-d] @ m[:, d:]), 1)
        d *= 2
    return m


def _lowpass(a: torch.Tensor, f_prev: torch.Tensor, alpha: float) -> torch.Tensor:
    """``(N, T, 3)``: ``f_t = f_{t-1} + alpha (a_t - f_{t-1})`` from ``f_prev`` ``(N, 3)`` (a
    parallel scan: ``log2 T`` passes, each term a sum of decaying powers)."""
    beta = 1.0 - alpha
    c = alpha * a
    c = torch.cat((c[:, :1] + beta * f_prev[:, None], c[:, 1:]), 1)
    d, length, power = 1, c.shape[1], beta
    while d < length:
        c = torch.cat((c[:, :d], c[:, d:] + power * c[:, :-d]), 1)
        power *= power
        d *= 2
    return c


def _lowpass2(a: torch.Tensor, z: torch.Tensor, ba) -> tuple[torch.Tensor, torch.Tensor]:
    """``(N, T, 3)`` outputs and the last state ``(N, 3, 2)`` of the second-order filter ``ba``
    (``(b, a)``, :func:`.prefilter.butterworth2`) on ``a`` ``(N, T, 3)`` from the state ``z``
    ``(N, 3, 2)`` (direct form II transposed: ``s_t = A s_{t-1} + B a_t``, ``f_t = b0 a_t +
    s_{t-1}[0]``; a parallel scan of ``log2 T`` passes, as :func:`_lowpass`)."""
    (b0, b1, b2), (_, a1, a2) = ba
    A = a.new_tensor([[-a1, 1.0], [-a2, 0.0]])
    s = a[..., None] * a.new_tensor([b1 - a1 * b0, b2 - a2 * b0])  # (N, T, 3, 2)
    s = torch.cat((s[:, :1] + z[:, None] @ A.T, s[:, 1:]), 1)
    d, length, power = 1, s.shape[1], A
    while d < length:
        s = torch.cat((s[:, :d], s[:, d:] + s[:, :-d] @ power.T), 1)
        power = power @ power
        d *= 2
    before = torch.cat((z[:, None], s[:, :-1]), 1)
    return b0 * a + before[..., 0], s[:, -1]
