"""Smooth random motion profiles: a sum of random sinusoids per channel and per sequence.

A real device does not turn at a fresh random rate every step (the paper's rigid body draws
``Omega ~ U[-1, 1]^3`` at every step); its rates are smooth in time. :func:`random_sinusoids`
draws, per sequence and per channel ``c``, ``K`` sinusoids and samples their sum at the step
times ``t_k = k dt``::

    s_c(t) = sum_{j=1..K} a_cj sin(2 pi f_cj t + phi_cj),
    a_cj ~ N(0, 2 rms^2 / K),   f_cj ~ U[f_min, f_max] (Hz),   phi_cj ~ U[0, 2 pi),

independently. Each term has mean square ``E[a^2] / 2 = rms^2 / K``, so ``E[s_c(t)^2] = rms^2``
at every ``t``: ``rms`` is the root mean square over sequences and time, while a single
sequence may be calmer or livelier than that (its amplitudes are random). ``s`` is infinitely
differentiable, with ``|ds/dt| <= 2 pi f_max sum_j |a_cj|``.

The draws come from the given ``torch.Generator`` in a fixed order (amplitudes, frequencies,
phases), so a seed fixes the profiles. Everything is float64.
"""

from __future__ import annotations

import math

import torch

__all__ = ["PEAK_OVER_RMS", "check_frequencies", "check_turn_per_step", "random_sinusoids"]

_DTYPE = torch.float64


def check_frequencies(owner: str, freq_min: float, freq_max: float, dt: float) -> None:
    """Raises ``ValueError`` unless ``0 <= freq_min <= freq_max < 1 / (2 dt)`` (Nyquist)."""
    for name, f in (("freq_min", freq_min), ("freq_max", freq_max)):
        if isinstance(f, bool) or not isinstance(f, (int, float)) or not 0 <= f < math.inf:
            raise ValueError(f"{owner}: {name} is a frequency in Hz, >= 0; got {f!r}.")
    if freq_min > freq_max:
        raise ValueError(f"{owner}: freq_min={freq_min} must not exceed freq_max={freq_max}.")
    nyquist = 0.5 / dt
    if freq_max >= nyquist:
        raise ValueError(
            f"{owner}: freq_max={freq_max} Hz is at or above the Nyquist frequency 1/(2 dt) = "
            f"{nyquist:g} Hz of the step dt={dt}; the sampled motion would alias. Lower freq_max "
            "or dt."
        )


#: The stated bound on a profile's size, in units of its rms: ``|s_c(t)| <= 4 rms``. The law has
#: no hard bound (the amplitudes are Gaussian), so this is a conservative multiple rather than a
#: guarantee: ``s_c(t)`` has variance ``rms^2``, and a value beyond 4 rms is as rare as a 4-sigma
#: Gaussian one (~6e-5 of the samples).
PEAK_OVER_RMS = 4.0


def check_turn_per_step(
    owner: str, dt: float, rms_name: str, rms: float, bias_name: str, bias: float, axes: int
) -> None:
    """Raises ``ValueError`` unless a measured rate (a profile of rms ``rms`` per axis plus a bias
    of at most ``bias``, on ``axes`` axes) turns by less than pi in one step::

        sqrt(axes) * (PEAK_OVER_RMS * rms + bias) * dt < pi,

    so an observer or filter that integrates the measured rate over a step never wraps the
    exponential (and ``log`` of one step stays unique). The message names the parameters and
    the largest ``dt`` they allow.
    """
    rate = math.sqrt(axes) * (PEAK_OVER_RMS * rms + bias)
    turn = rate * dt
    if not turn < math.pi:
        root = f"sqrt({axes}) * " if axes > 1 else ""
        raise ValueError(
            f"{owner}: one step can turn by up to {root}({PEAK_OVER_RMS:g} * {rms_name} + "
            f"{bias_name}) * dt = {root}({PEAK_OVER_RMS:g} * {rms:g} + {bias:g}) * {dt:g} = "
            f"{turn:.4g} rad, which must be < pi ({PEAK_OVER_RMS:g} * {rms_name}: the stated "
            "peak of the random sinusoids); an observer or filter that integrates the measured "
            f"rate over a step would wrap the exponential. Use a smaller dt, {rms_name} or "
            f"{bias_name} (dt < {math.pi / rate:.4g} s for these values)."
        )


def random_sinusoids(
    num_sequences: int,
    length: int,
    channels: int,
    dt: float,
    rms: float | torch.Tensor,
    freq_min: float,
    freq_max: float,
    num_terms: int,
    generator: torch.Generator,
) -> torch.Tensor:
    """Sums of ``num_terms`` random sinusoids sampled at ``t_k = k dt``, ``k = 0 .. length-1``.

    Returns ``(num_sequences, length, channels)`` float64. ``rms`` is a number or a
    ``(channels,)`` tensor (one root mean square per channel). See the module docstring for the
    law. Works one term at a time, so the temporaries are ``(N, T, channels)``.
    """
    if isinstance(num_terms, bool) or not isinstance(num_terms, int) or num_terms < 1:
        raise ValueError(f"num_terms must be a positive integer, got {num_terms!r}.")
    n, t, c, k = num_sequences, length, channels, num_terms
    rms = torch.as_tensor(rms, dtype=_DTYPE).expand(c)
    amp = torch.randn(n, 1, c, k, generator=generator, dtype=_DTYPE)
    amp.mul_((rms * math.sqrt(2.0 / k))[:, None])
    freq = torch.empty(n, 1, c, k, dtype=_DTYPE).uniform_(freq_min, freq_max, generator=generator)
    phase = torch.empty(n, 1, c, k, dtype=_DTYPE).uniform_(0.0, 2 * math.pi, generator=generator)
    time = (torch.arange(t, dtype=_DTYPE) * dt)[None, :, None]  # (1, T, 1)
    out = torch.zeros(n, t, c, dtype=_DTYPE)
    for j in range(k):
        arg = (2 * math.pi) * freq[..., j] * time + phase[..., j]  # (N, T, C)
        out.addcmul_(amp[..., j], torch.sin_(arg))
    return out
