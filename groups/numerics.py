"""The safe sinc-like helpers and their thresholds: one place for all the numerics of the groups.

Public for authors of a group or a system who need the same coefficients (``from groups import
numerics as nx``; ``nx.sin_over_t(t2)``), so that nobody writes a second, subtly different
``sin(t)/t``.

Every function here takes ``t2 = theta**2`` (a smooth function of the tangent vector, so no
``sqrt`` is differentiated at 0) and returns a coefficient of the closed-form exponential,
logarithm or Jacobian of a rotation by the angle ``theta``.

Each function uses the "double where" pattern: below a per-dtype threshold the input of the
closed form is replaced *before* the singular operation by a harmless constant, the closed form
and a Taylor series are both evaluated, and ``torch.where`` selects. The unused branch then
cannot produce NaN or Inf in the backward pass, so values *and* gradients are finite at exactly
``theta = 0``.

Thresholds are chosen for differentiation, not only for values (a threshold at machine epsilon
gives wrong float32 derivatives of ``(1 - cos t) / t**2`` near ``t = 1e-3``): the series are kept
to ``O(t**6)`` or ``O(t**8)`` so that they are exact to rounding well past the threshold.
Closed forms are written without cancellation where one exists (``1 - cos t = 2 sin(t/2)**2``).

When nothing differentiates through the input (:func:`records`: no recorded backward, no
``torch.func`` transform) the safe input is not needed, and the coefficients whose closed form
has no cancellation (``sin_over_t``, ``one_minus_cos_over_t2``, ``atan2_over_s``) are their
closed form alone, with ``t2`` raised to ``eps**2`` (where they equal their value at 0 to
rounding): within an ulp or two of the series below the threshold, in a third of the
operations. The others keep their series (it is their value's accuracy too).
"""

from __future__ import annotations

import torch

__all__ = [
    "small_angle_threshold",
    "sin_over_t",
    "one_minus_cos_over_t2",
    "t_minus_sin_over_t3",
    "half_t_cot_half_t",
    "inv_left_jacobian_coeff",
    "atan2_over_s",
    "records",
    "cached_constant",
]

# theta below which the Taylor branch is used. float32 needs larger values: autograd's derivative
# of the closed forms loses about eps / theta**k of relative accuracy.
_THRESHOLDS = {
    # name: (float32, float64)
    "default": (1e-2, 5e-3),
    "cubic": (0.25, 2e-2),  # (t - sin t) / t**3 and friends cancel in three orders
}


def small_angle_threshold(dtype: torch.dtype, kind: str = "default") -> float:
    """The angle below which the Taylor branch is used for ``dtype`` (float16/bfloat16 as float32)."""
    f32, f64 = _THRESHOLDS[kind]
    return f64 if dtype == torch.float64 else f32


_CACHE: dict[tuple, torch.Tensor] = {}


def cached_constant(name: str, build, like: torch.Tensor, dtype=None) -> torch.Tensor:
    """``build()`` (a float64 or int64 tensor) in ``like``'s device and ``dtype`` (default
    ``like``'s), made once per ``name``, dtype and device and cached: a table a kernel reads
    every call. Made afresh while ``torch.compile`` / ``torch.export`` trace and for a tensor
    subclass (a fake tensor must not enter the cache); made outside inference mode, so a table
    first made there still serves recorded graphs."""
    dtype = like.dtype if dtype is None else dtype
    if torch.compiler.is_compiling() or type(like) is not torch.Tensor:
        return build().to(dtype=dtype, device=like.device)
    key = (name, dtype, like.device)
    table = _CACHE.get(key)
    if table is None:
        with torch.inference_mode(False), torch.no_grad():
            table = build().to(dtype=dtype, device=like.device)
        _CACHE[key] = table
    return table


def records(t: torch.Tensor) -> bool:
    """Whether something differentiates through ``t``: autograd records a backward (grad mode,
    ``t`` requires grad) or a ``torch.func`` transform is active. Only then do the helpers
    need their safe inputs and series: otherwise they compute the same values in fewer
    operations."""
    return (torch.is_grad_enabled() and t.requires_grad) or (
        torch._C._are_functorch_transforms_active()
    )


def _split(t2: torch.Tensor, kind: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Returns ``(small, t2_safe)``: the mask of the series branch and ``t2`` with it set to 1.

    Without a recorded backward ``t2`` itself: the closed form's NaN at 0 is then discarded by
    the ``where`` and cannot reach a gradient (the same values, two operations fewer)."""
    thr = small_angle_threshold(t2.dtype, kind)
    small = t2 < thr * thr
    if not records(t2):
        return small, t2
    t2_safe = torch.where(small, torch.ones_like(t2), t2)
    return small, t2_safe


def _away_from_zero(t2: torch.Tensor) -> torch.Tensor:
    """``t2`` raised to ``eps**2`` where smaller (there the coefficients below are their values
    at 0 to rounding), so that a closed form is finite at 0 and meets no subnormal number."""
    return t2.clamp(min=torch.finfo(t2.dtype).eps ** 2)


def sin_over_t(t2: torch.Tensor) -> torch.Tensor:
    """``sin(t) / t`` with ``t = sqrt(t2)``."""
    if not records(t2):  # values only: the closed form is exact to rounding down to 0
        t = _away_from_zero(t2).sqrt()
        return torch.sin(t) / t
    small, t2s = _split(t2, "default")
    t = t2s.sqrt()
    exact = torch.sin(t) / t
    series = 1.0 - t2 / 6.0 * (1.0 - t2 / 20.0 * (1.0 - t2 / 42.0))
    return torch.where(small, series, exact)


def one_minus_cos_over_t2(t2: torch.Tensor) -> torch.Tensor:
    """``(1 - cos t) / t**2``, computed as ``2 sin(t/2)**2 / t**2`` (no cancellation)."""
    if not records(t2):  # values only: the closed form is exact to rounding down to 0
        t2 = _away_from_zero(t2)
        s = torch.sin(0.5 * t2.sqrt())
        return 2.0 * s * s / t2
    small, t2s = _split(t2, "default")
    t = t2s.sqrt()
    s = torch.sin(0.5 * t)
    exact = 2.0 * s * s / t2s
    series = 0.5 - t2 / 24.0 * (1.0 - t2 / 30.0 * (1.0 - t2 / 56.0))
    return torch.where(small, series, exact)


def t_minus_sin_over_t3(t2: torch.Tensor) -> torch.Tensor:
    """``(t - sin t) / t**3``, the coefficient of ``K**2`` in the SO(3) left Jacobian."""
    small, t2s = _split(t2, "cubic")
    t = t2s.sqrt()
    exact = (t - torch.sin(t)) / (t2s * t)
    series = (1.0 / 6.0) - t2 / 120.0 * (
        1.0 - t2 / 42.0 * (1.0 - t2 / 72.0 * (1.0 - t2 / 110.0))
    )
    return torch.where(small, series, exact)


def half_t_cot_half_t(t2: torch.Tensor) -> torch.Tensor:
    """``(t/2) cot(t/2)``: the diagonal of the inverse SE(2) V matrix. Finite for ``|t| < 2 pi``."""
    small, t2s = _split(t2, "default")
    h = 0.5 * t2s.sqrt()
    exact = h * torch.cos(h) / torch.sin(h)
    series = 1.0 - t2 / 12.0 - t2 * t2 / 720.0 - t2 * t2 * t2 / 30240.0
    return torch.where(small, series, exact)


def inv_left_jacobian_coeff(t2: torch.Tensor) -> torch.Tensor:
    """``D(t) = 1/t**2 - (t/2) cot(t/2) / t**2``, so that ``J_l(w)^-1 = I - K/2 + D K**2``.

    ``(t/2) cot(t/2)`` has no singularity at ``t = pi`` (it is 0 there), unlike the textbook
    ``(1 + cos t) / (2 t sin t)`` form, so the coefficient is finite on the whole log domain.
    """
    small, t2s = _split(t2, "cubic")
    h = 0.5 * t2s.sqrt()
    exact = (1.0 - h * torch.cos(h) / torch.sin(h)) / t2s
    series = 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0 + t2 * t2 * t2 / 1209600.0
    return torch.where(small, series, exact)


def atan2_over_s(s2: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """``atan2(s, c) / s`` with ``s = sqrt(s2) >= 0``; ``c > 0`` is assumed where ``s`` is small.

    Used by logarithms written through a unit quaternion or a unit complex number: the angle
    over the sine of the (half) angle.
    """
    if not (records(s2) or records(c)):  # values only: the closed form is exact to rounding
        s = _away_from_zero(s2).sqrt()
        return torch.atan2(s, c) / s
    small, s2s = _split(s2, "default")
    s = s2s.sqrt()
    exact = torch.atan2(s, c) / s
    # atan(x)/x with x = s/c, times 1/c, for c near 1 (the only place s can be small and c > 0).
    c_safe = torch.where(small, c, torch.ones_like(c))
    x2 = s2 / (c_safe * c_safe)
    series = (1.0 - x2 / 3.0 + x2 * x2 / 5.0 - x2 * x2 * x2 / 7.0) / c_safe
    return torch.where(small, series, exact)
