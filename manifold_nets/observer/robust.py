"""Learned robust weights: the observer's M-estimator weight functions, one per channel.

An M-estimator downweights a residual by its size: it uses ``w(r) r`` in place of ``r``, with a
weight function ``w`` that is 1 for ordinary residuals and falls for implausible ones (Huber's
``min(1, c / r)``, Tukey's biweight). :class:`RobustWeights` learns such a ``w`` per channel
instead of fixing its shape and threshold::

    w_i(r) = 1 + sum_j a_ij tanh((r - k_ij) / h_ij),       r >= 0,  j = 1 .. width

a sum of ``width`` smooth steps with learned heights ``a``, knots ``k`` and widths ``h > 0``.
The heights start at zero, so a new map is the identity (``w = 1``): an observer given one
computes exactly what it did without, and training moves it only as far as the data asks. The
knots start evenly spread over ``[0, span]`` (``span`` in the units of ``r``), each width at
twice their spacing.

Two pieces use it (:mod:`manifold_nets.observer`):

* :class:`~manifold_nets.observer.priors.RobustSystemPrior`: each component of the drive the model prior integrates (the rigid body's
  bias-corrected gyro and velocity readings), ``d_i <- w_i(|d_i|) d_i``: a reading the motion
  cannot produce (an outlier) is pulled in before it moves the prediction;
* :class:`~manifold_nets.observer.measurement.RobustMeasurement`: each measured factor's innovation, ``nu_f <- w_f(||nu_f||) nu_f``, and
  the measurement the core reads with it, ``m_f <- xhat_f^- exp(nu_f)``: a gate on implausible
  measurements, learned.

Shapes: ``forward(r)``: ``r`` ``(..., channels)`` -> ``w`` ``(..., channels)``, in the
parameters' dtype. :func:`safe_norm` is the Euclidean norm with a gradient that stays finite at
zero (the "double where": the square root never sees a zero it is differentiated at).
"""

from __future__ import annotations

import math

import torch
from torch import nn

__all__ = ["RobustWeights", "check_span", "safe_norm"]


def check_span(span: object, label: str = "RobustWeights: span") -> float:
    """``span`` as a float, or a ``ValueError`` naming ``label`` unless it is a finite number > 0."""
    if isinstance(span, bool) or not isinstance(span, (int, float)) or not 0 < span < math.inf:
        raise ValueError(f"{label} must be a number > 0, got {span!r}.")
    return float(span)


def safe_norm(v: torch.Tensor) -> torch.Tensor:
    """``||v||`` over the last dimension, ``(...)``; its gradient is 0 (not NaN) at ``v = 0``."""
    sq = (v * v).sum(-1)
    positive = sq > 0
    return torch.where(positive, torch.where(positive, sq, torch.ones_like(sq)).sqrt(), 0.0 * sq)


#: The most channels and steps a weight function may have: the shipped observers use 16 steps;
#: the bound keeps a file that asks for 10**9 from allocating before it is refused.
MAX_SIZE = 4096


class RobustWeights(nn.Module):
    """``channels`` learned weight functions of ``width`` steps each; see the module docstring.

    Args:
        channels: how many weight functions (one per drive component or innovation factor).
        width: steps per function, an integer >= 1.
        span: where the knots start, evenly over ``[0, span]``, in the units of ``r`` (> 0).
    """

    def __init__(self, channels: int, width: int = 16, span: float = 4.0):
        super().__init__()
        for name, val in (("channels", channels), ("width", width)):
            if isinstance(val, bool) or not isinstance(val, int) or not 1 <= val <= MAX_SIZE:
                raise ValueError(
                    f"RobustWeights: {name} must be an integer in 1 .. {MAX_SIZE}, got {val!r}."
                )
        self.channels, self.width, self.span = channels, width, check_span(span)
        knots = torch.linspace(0.0, self.span, width).expand(channels, width).clone()
        spacing = self.span / max(width - 1, 1)
        self.amplitude = nn.Parameter(torch.zeros(channels, width))
        self.knots = nn.Parameter(knots)
        self.log_width = nn.Parameter(torch.full((channels, width), math.log(2.0 * spacing)))

    def forward(self, r: torch.Tensor) -> torch.Tensor:
        if r.shape[-1] != self.channels:
            raise ValueError(
                f"RobustWeights: r must have shape (..., {self.channels}), got {tuple(r.shape)}."
            )
        z = (r.unsqueeze(-1) - self.knots) * torch.exp(-self.log_width)
        return 1.0 + (self.amplitude * torch.tanh(z)).sum(-1)

    def signature(self) -> dict:
        """What a checkpoint must match (JSON-able)."""
        return {"channels": self.channels, "width": self.width, "span": self.span}

    def extra_repr(self) -> str:
        return f"channels={self.channels}, width={self.width}, span={self.span:g}"
