"""A recalibration of a readout's covariance: each factor's block scaled by a function of the
readout's own level, smoothed over the recent steps, and of the step.

A :class:`~manifold_nets.observer.CovarianceReadout` fitted by the Gaussian likelihood gets its
overall level right (one held-out scale per factor fixes the rest), but its level at one noise
level or another, early or late in a sequence, can be off by a few percent: too little for the
likelihood to see, enough to take a step's ANEES over 1000 sequences out of its 95 % band
(0.950-1.051). :class:`LevelScale` multiplies factor ``f``'s rows of ``L_k`` by
``exp(u_f / 2)`` (so ``P_ff`` by ``exp(u_f)``), with

``u_f = sum_{i, j} w_{f,i,j} h_i(lbar_{f,k}) c_j(k)``,

``lbar_{f,k}`` the readout's level of ``f`` (twice the mean log diagonal of ``L_k`` over ``f``'s
components: ``log det P_ff / d`` for a block-diagonal ``L``) averaged exponentially over ``tau``
steps from the start's, ``h_i`` piecewise-linear hats over the factor's ``knots`` (constant beyond
them) and ``c_j(k)`` the clock ``(1, exp(-k / tau_1), ...)`` (``k`` no earlier than the first step
it was fitted on). A function of what the readout
itself reports, so it needs no truth online; its weights are fitted on held-out sequences
(:func:`manifold_nets.covariance_training.fit_level_scale`: the likelihood of the scaled
covariance, convex in ``w``). The start's covariance (step 0) is left as it is.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from groups import LieGroup

from .covariance import check_clock

__all__ = ["LevelScale", "MAX_KNOTS"]

#: The most knots a level scale may have (the fitted ones: 8); a file asking for more is refused.
MAX_KNOTS = 256


class LevelScale(nn.Module):
    """See the module docstring.

    Args:
        group: the readout's group (its factors).
        knots: ``(F, K)`` increasing levels per factor, ``K >= 2`` (float64).
        weights: ``(F, K, 1 + len(clock))``: ``w``; zeros leave ``P`` as it is.
        clock: the clock's time constants in steps.
        tau: the steps the level is averaged over (``>= 1``).
        first: the first step it was fitted on; the steps before it take its scale (the clock's
            fast terms, fitted from there on, are not extrapolated to the first steps).
    """

    def __init__(self, group: LieGroup, knots: torch.Tensor, weights: torch.Tensor,
                 clock: tuple[float, ...], tau: float, first: int = 1):
        super().__init__()
        clock = check_clock(clock)
        f = len(group.factor_names)
        knots, weights = torch.as_tensor(knots, dtype=torch.float64), torch.as_tensor(
            weights, dtype=torch.float64)
        if knots.dim() != 2 or knots.shape[0] != f or not 2 <= knots.shape[1] <= MAX_KNOTS:
            raise ValueError(f"level scale: knots must be ({f}, K), 2 <= K <= {MAX_KNOTS}, one row per factor of "
                             f"{list(group.factor_names)}; got {tuple(knots.shape)}.")
        if weights.shape != (f, knots.shape[1], 1 + len(clock)):
            raise ValueError(f"level scale: weights must be {(f, knots.shape[1], 1 + len(clock))} "
                             f"for these knots and clock; got {tuple(weights.shape)}.")
        if not (torch.isfinite(knots).all() and torch.isfinite(weights).all()):
            raise ValueError("level scale: knots and weights must be finite.")
        if not bool((knots.diff(dim=1) > 0).all()):
            raise ValueError("level scale: each factor's knots must increase strictly.")
        if isinstance(tau, bool) or not (isinstance(tau, (int, float)) and math.isfinite(tau)
                                         and tau >= 1):
            raise ValueError(f"level scale: tau must be a number of steps >= 1, got {tau!r}.")
        if isinstance(first, bool) or not isinstance(first, int) or first < 0:
            raise ValueError(f"level scale: first must be a step >= 0, got {first!r}.")
        self.group, self.clock, self.tau, self.first = group, clock, float(tau), first
        self.register_buffer("knots", knots)
        self.register_buffer("weights", weights)
        self.register_buffer("taus", torch.tensor(clock, dtype=torch.float64), persistent=False)
        which = torch.zeros(group.tangent_dim, dtype=torch.long)
        for i, name in enumerate(group.factor_names):
            which[group.tangent_slice(name)] = i
        self.register_buffer("which", which, persistent=False)  # each component's factor
        counts = torch.bincount(which, minlength=f).to(torch.float64)
        self.register_buffer("counts", counts, persistent=False)

    def signature(self) -> dict:
        return {"knots": int(self.knots.shape[1]), "clock": list(self.clock), "tau": self.tau,
                "first": self.first}

    def level(self, chol: torch.Tensor) -> torch.Tensor:
        """Each factor's level ``(..., F)`` of Cholesky factors ``(..., n, n)``."""
        log_d = torch.diagonal(chol, dim1=-2, dim2=-1).double().log()
        total = log_d.new_zeros(*log_d.shape[:-1], len(self.counts))
        return 2 * total.index_add(-1, self.which, log_d) / self.counts

    def initial(self, chol0: torch.Tensor) -> torch.Tensor:
        """The averaged level before the first step: the start's ``(B, F)`` (``chol0`` ``(B, n, n)``)."""
        return self.level(chol0)

    def averaged(self, level: torch.Tensor, lbar: torch.Tensor) -> torch.Tensor:
        """The averaged level ``(B, T, F)`` after each of the levels ``(B, T, F)``, from ``lbar``
        ``(B, F)`` before them: ``lbar <- lbar + (level - lbar) / tau``."""
        a, steps = 1.0 / self.tau, []
        for t in range(level.shape[1]):
            lbar = lbar + a * (level[:, t] - lbar)
            steps.append(lbar)
        return torch.stack(steps, 1) if steps else level.new_zeros(level.shape)

    def basis(self, lbar: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
        """``h_i(lbar_f) c_j(k)`` ``(..., F, K, 1 + len(clock))`` at averaged levels ``lbar``
        ``(..., F)`` and steps ``k`` (``lbar``'s leading shape)."""
        return hat_clock_basis(self.knots, self.taus, self.first, lbar, k)

    def log_scale(self, lbar: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
        """``u`` ``(..., F)`` at averaged levels ``lbar`` ``(..., F)`` and steps ``k``."""
        return (self.basis(lbar, k) * self.weights).sum((-1, -2))

    def forward(self, chol: torch.Tensor, lbar: torch.Tensor, start) -> tuple[torch.Tensor, torch.Tensor]:
        """``chol`` ``(B, T, n, n)`` of the steps ``start + 1 .. start + T`` scaled, and the
        averaged level after them, from ``lbar`` ``(B, F)`` before them (``start`` an int or
        ``(B,)``)."""
        if chol.shape[1] == 0:
            return chol.double(), lbar
        lbars = self.averaged(self.level(chol), lbar)
        ks = torch.arange(1, chol.shape[1] + 1, dtype=torch.float64, device=chol.device)
        ks = (start.double().reshape(-1, 1) if isinstance(start, torch.Tensor) else float(start)) + ks
        u = self.log_scale(lbars, ks.expand(lbars.shape[:2]))
        half = torch.exp(0.5 * u)[..., self.which]  # (B, T, n): each row's factor
        return chol.double() * half.unsqueeze(-1), lbars[:, -1]


def hat_clock_basis(knots: torch.Tensor, taus: torch.Tensor, first: int, lbar: torch.Tensor,
                    k: torch.Tensor) -> torch.Tensor:
    """:meth:`LevelScale.basis` of the factors whose ``knots`` ``(F, K)`` are given (a fit takes
    one factor at a time: the basis of millions of steps is large)."""
    lo, hi = knots[:, 0], knots[:, -1]
    x = torch.minimum(torch.maximum(lbar.double(), lo), hi).unsqueeze(-1)  # (..., F, 1)
    left, right = knots[:, :-1], knots[:, 1:]  # (F, K - 1)
    t = ((x - left) / (right - left)).clamp(0, 1)  # how far into each span
    # knot i's hat: rising over the span below it, falling over the span above
    hats = torch.minimum(torch.cat([torch.ones_like(x), t], -1),
                         torch.cat([1 - t, torch.ones_like(x)], -1))  # (..., F, K)
    kk = k.double().clamp_min(first).unsqueeze(-1)
    clock = torch.cat([torch.ones_like(kk), torch.exp(-kk / taus)], -1)  # (..., C + 1)
    return hats.unsqueeze(-1) * clock.unsqueeze(-2).unsqueeze(-2)
