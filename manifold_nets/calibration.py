"""How far to trust an estimator's covariance: NEES, ANEES with its chi-square band, and the
share of errors inside the 1, 2 and 3 sigma ellipsoids, per factor of the group.

The error of an estimate is the tangent vector at the estimate that reaches the true state,
``xi = Log(xhat^-1 x)`` (``group.rminus(x, xhat)``: the right perturbation, the convention of the
project's EKF and of :mod:`manifold_nets.observer.covariance`). An estimator that reports
``xi ~ N(0, P)`` is *calibrated* when its errors are distributed that way. For a factor with a
``d``-dimensional block ``P_f``:

* ``NEES = xi_f^T P_f^-1 xi_f`` per sequence and step: chi-square with ``d`` degrees of freedom
  when calibrated;
* ``ANEES_k`` = NEES over ``d``, averaged over the ``N`` sequences at step ``k``: its ``N d``
  multiple is chi-square with ``N d`` degrees of freedom, so ``ANEES_k`` lies in the two-sided
  95 % band ``chi2.ppf([0.025, 0.975], N d) / (N d)`` at 95 % of the steps; the ANEES is its mean
  over the steps (near 1: calibrated; above: the filter trusts itself too much; below: too
  little);
* the share of ``(sequence, step)`` errors inside the ``s``-sigma ellipsoid ``NEES <= s^2``,
  against the Gaussian's ``chi2.cdf(s^2, d)`` (68.3 / 95.4 / 99.7 % for ``d = 1``; 19.9 / 73.9 /
  97.1 % for ``d = 3``).

Used by the evaluation for every estimator that gives a covariance (``docs/calibration.md``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.stats import chi2

from groups import LieGroup

__all__ = [
    "SIGMAS", "FactorCalibration", "tangent_errors", "nees", "calibration", "gaussian_share",
    "anees_band", "conformal_scale",
]

#: The ellipsoids whose shares are reported (in standard deviations).
SIGMAS = (1, 2, 3)


def tangent_errors(group: LieGroup, estimates: torch.Tensor, states: torch.Tensor) -> torch.Tensor:
    """``xi = Log(xhat^-1 x)`` ``(*batch, tangent_dim)`` of ``estimates`` against ``states``
    (both ``(*batch, *element_shape)``), in their common dtype (float64 where one is)."""
    dtype = torch.promote_types(estimates.dtype, states.dtype)
    return group.rminus(states.to(dtype), estimates.to(dtype))


def nees(errors: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
    """``xi^T P^-1 xi`` ``(*batch,)`` for errors ``(*batch, d)`` and covariances ``(*batch, d, d)``
    (computed through a Cholesky factor, float64). Raises ``ValueError`` naming the first
    covariance that is not positive definite."""
    e, p = errors.double(), cov.double()
    chol, info = torch.linalg.cholesky_ex(p)
    if bool((info != 0).any()):
        where = tuple(int(i) for i in torch.nonzero(info)[0])
        raise ValueError(
            f"the covariance at index {where} is not positive definite (a Cholesky factor does "
            "not exist); an estimator's covariance must be symmetric positive definite."
        )
    w = torch.linalg.solve_triangular(chol, e.unsqueeze(-1), upper=False).squeeze(-1)
    return (w * w).sum(-1)


def anees_band(sequences: int, dim: int, level: float = 0.95) -> tuple[float, float]:
    """The two-sided ``level`` band of ``ANEES_k`` over ``sequences`` calibrated sequences of a
    ``dim``-dimensional error."""
    dof = sequences * dim
    lo, hi = chi2.ppf([(1 - level) / 2, (1 + level) / 2], dof)
    return float(lo / dof), float(hi / dof)


def gaussian_share(sigma: float, dim: int) -> float:
    """The probability that a ``dim``-dimensional Gaussian error lies inside its ``sigma``-sigma
    ellipsoid, ``chi2.cdf(sigma^2, dim)``."""
    return float(chi2.cdf(sigma**2, dim))


def conformal_scale(nees_values: torch.Tensor, dim: int, sigma: float = 3.0) -> float:
    """The scale ``s`` of a covariance that puts the Gaussian share ``chi2.cdf(sigma^2, dim)``
    of held-out errors inside the ``sigma``-sigma ellipsoid: ``s = q_(k) / sigma^2`` with
    ``q_(k)`` the ``k = ceil((n + 1) share)``-th smallest of the ``n`` NEES values (split
    conformal calibration: a fresh error exchangeable with them has ``NEES <= s sigma^2`` with
    probability at least ``share``, whatever the errors' law). ``nees_values`` 1-D, finite."""
    q = torch.as_tensor(nees_values, dtype=torch.float64).flatten()
    if q.numel() == 0 or not bool(torch.isfinite(q).all()) or bool((q < 0).any()):
        raise ValueError(f"conformal_scale: expected finite non-negative NEES values, got "
                         f"{q.numel()} value(s) with min {float(q.min()) if q.numel() else None}.")
    share = gaussian_share(sigma, dim)
    k = min(q.numel(), int(np.ceil((q.numel() + 1) * share)))
    scale = float(torch.sort(q).values[k - 1]) / sigma**2
    if not scale > 0:
        raise ValueError("conformal_scale: the held-out errors are zero at the quantile; there "
                         "is nothing to scale to (give errors of an estimator that errs).")
    return scale


@dataclass(frozen=True)
class FactorCalibration:
    """One factor's calibration over a set (see the module docstring)."""

    dim: int
    anees: float  #: mean over steps of ANEES_k
    anees_steps: np.ndarray  #: ANEES_k, (T',)
    band: tuple[float, float]  #: the 95 % band of ANEES_k
    in_band: float  #: share of steps with ANEES_k inside the band
    shares: dict[int, float]  #: share of errors inside the s-sigma ellipsoid, s in SIGMAS

    def row(self) -> dict[str, float]:
        """The figures as a flat row (``anees``, ``in_band``, ``in_1sigma`` ...)."""
        return {
            "anees": self.anees, "in_band": self.in_band,
            **{f"in_{s}sigma": v for s, v in self.shares.items()},
        }


def calibration(
    group: LieGroup, errors: torch.Tensor, cov: torch.Tensor, mask: torch.Tensor | None = None
) -> dict[str, FactorCalibration]:
    """Per factor of ``group``: the calibration of ``errors`` ``(N, T, n)`` under ``cov``
    ``(N, T, n, n)`` (the factor's diagonal block of it), over the steps where ``mask``
    ``(N, T)`` holds (default all). ``ANEES_k`` averages the sequences known at step ``k``;
    steps known in no sequence are left out."""
    if errors.dim() != 3 or cov.shape != (*errors.shape, errors.shape[-1]):
        raise ValueError(
            f"errors must be (N, T, n) and cov (N, T, n, n); got {tuple(errors.shape)} and "
            f"{tuple(cov.shape)}."
        )
    if errors.shape[-1] != group.tangent_dim:
        raise ValueError(f"errors have {errors.shape[-1]} components, the group {group.tangent_dim}.")
    known = torch.ones(errors.shape[:2], dtype=torch.bool) if mask is None else mask.bool().cpu()
    out = {}
    for name in group.factor_names:
        s = group.tangent_slice(name)
        d = s.stop - s.start
        q = nees(errors[..., s], cov[..., s, s]).cpu() / d  # (N, T)
        counts = known.sum(0)
        steps = counts > 0
        anees_k = (torch.where(known, q, 0.0).sum(0)[steps] / counts[steps]).numpy()
        bands = [anees_band(int(c), d) for c in counts[steps]]
        inside = np.mean([lo <= a <= hi for a, (lo, hi) in zip(anees_k, bands)])
        n_min = int(counts[steps].min()) if steps.any() else 0
        flat = (q * d)[known]
        out[name] = FactorCalibration(
            dim=d,
            anees=float(anees_k.mean()),
            anees_steps=anees_k,
            band=anees_band(n_min, d) if n_min else (float("nan"), float("nan")),
            in_band=float(inside),
            shares={s_: float((flat <= s_**2).double().mean()) for s_ in SIGMAS},
        )
    return out
