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

__all__ = ["check_frequencies", "random_sinusoids"]

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
