"""Losses on groups through their embedding: the paper's training loss ``L``.

``L = 1 / (n M N) sum_i sum_{k=1..M} ||pi(xhat^i_k) - pi(x^i_k)||^2``: the squared error of the
embeddings, averaged over sequences, time steps and the ``n = embedding_dim`` coordinates (the
paper's ``1/(18 M)`` for the rigid body). ``xhat_0`` is the fixed starting point (the identity)
and carries no gradient, so it is left out by default (``skip=1``).
"""

from __future__ import annotations

import torch

from groups import LieGroup

__all__ = ["embedding_squared_error", "embedding_mse", "factor_errors"]


def _check(group: LieGroup, estimates: torch.Tensor, states: torch.Tensor) -> None:
    if estimates.shape != states.shape:
        raise ValueError(
            f"estimates {tuple(estimates.shape)} and true states {tuple(states.shape)} must have "
            f"the same shape (N, T+1, *element_shape) with element_shape {group.element_shape}."
        )


def embedding_squared_error(
    group: LieGroup, estimates: torch.Tensor, states: torch.Tensor
) -> torch.Tensor:
    """``||pi(xhat) - pi(x)||^2`` per element: two ``(*batch, *element_shape)`` -> ``(*batch,)``."""
    _check(group, estimates, states)
    diff = group.embed(estimates) - group.embed(states.to(estimates.dtype))
    return (diff * diff).sum(-1)


def embedding_mse(
    group: LieGroup,
    estimates: torch.Tensor,
    states: torch.Tensor,
    skip: int = 1,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """The paper's ``L``: mean over sequences, steps ``k >= skip`` and embedding coordinates.

    ``estimates`` and ``states`` are ``(N, T+1, *element_shape)`` (``x_0 .. x_T``); a scalar in
    the estimates' dtype is returned. ``mask`` (bool ``(N, T+1)``, a dataset's ``mask``) keeps
    only the steps whose true state is known: the mean is over those (0 if there are none), and
    the placeholder states elsewhere never reach the loss or its gradient.
    """
    _check(group, estimates, states)
    if estimates.dim() < 2 + len(group.element_shape) or not 0 <= skip < estimates.shape[1]:
        raise ValueError(
            f"embedding_mse needs (N, T+1, *element_shape) with T+1 > skip={skip}, got "
            f"{tuple(estimates.shape)}."
        )
    sq = embedding_squared_error(group, estimates[:, skip:], states[:, skip:])
    if mask is None:
        return sq.mean() / group.embedding_dim
    if tuple(mask.shape) != tuple(estimates.shape[:2]) or mask.dtype != torch.bool:
        raise ValueError(
            f"mask must be a bool tensor (N, T+1) = {tuple(estimates.shape[:2])}, got "
            f"{mask.dtype} {tuple(mask.shape)}."
        )
    keep = mask[:, skip:].to(sq.device)
    total = torch.where(keep, sq, torch.zeros_like(sq)).sum()
    return total / (keep.sum().clamp(min=1) * group.embedding_dim)


def factor_errors(
    group: LieGroup, estimates: torch.Tensor, states: torch.Tensor
) -> dict[str, torch.Tensor]:
    """``{factor name: ||pi_f(xhat) - pi_f(x)||}``, each ``(*batch,)``, from two
    ``(*batch, *element_shape)``; the names are ``group.factor_names`` (``x`` for a group that
    is not a product)."""
    _check(group, estimates, states)
    diff = group.embed(estimates) - group.embed(states.to(estimates))
    return {
        name: torch.linalg.vector_norm(diff[..., group.embedding_slice(i)], dim=-1)
        for i, name in enumerate(group.factor_names)
    }
