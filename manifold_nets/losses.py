"""Losses on groups through their embedding: the paper's training loss ``L``.

``L = 1 / (n M N) sum_i sum_{k=1..M} ||pi(xhat^i_k) - pi(x^i_k)||^2``: the squared error of the
embeddings, averaged over sequences, time steps and the ``n = embedding_dim`` coordinates (the
paper's ``1/(18 M)`` for the rigid body). ``xhat_0`` is the fixed starting point (the identity)
and carries no gradient, so it is left out by default (``skip=1``).

``embedding_log_mse`` is the framework's alternative (``train.loss: log_mse``): the mean over
sequences of ``log(L_i + eps)``, with ``L_i`` sequence ``i``'s own embedding MSE. ``L`` weighs a
sequence by its squared error, so with one noise level per sequence the noisiest ones decide the
gradient (an error of 0.36 at sigma 0.5 weighs 9x one of 0.12 at sigma 0.1); the log weighs
every sequence's relative error alike (its gradient is ``grad L_i / (L_i + eps)``).

``embedding_factor_log_mse`` (``train.loss: factor_log_mse``) takes that one step further, to the
factors of a product group: the mean over sequences of ``(1/F) sum_f log(L_if + eps)``, with
``L_if`` sequence ``i``'s MSE over factor ``f``'s embedding coordinates. In ``log L_i`` a factor
weighs by its share of the squared error, so a factor tracked to a small error in its own units
(the rigid body's biases: 0.03 against the attitude's 0.08 at sigma 0.1) hardly moves the
gradient; here every factor's relative error weighs alike, as the per-factor error ratios of the
comparison table do. For a group that is not a product it is ``log_mse``.

Every loss takes ``weights`` (``train.loss_weights``): one non-negative number per embedding
coordinate that multiplies its squared error (the mean stays over the ``n`` coordinates, so
weights of 1 are the unweighted loss). They choose what the loss asks of the estimate: SO(3)'s
embedding is the rotation matrix row by row, and its third row is ``R^T e_z``, "up" seen from
the body, so the weights ``[0, 0, 0, 0, 0, 0, 1, 1, 1]`` score an attitude's inclination alone
and leave its heading free (an observer without a magnetometer, whose heading nothing
measures); ``None`` is every weight 1.
"""

from __future__ import annotations

import math

import torch

from groups import LieGroup

__all__ = [
    "embedding_squared_error",
    "embedding_mse",
    "embedding_log_mse",
    "embedding_factor_log_mse",
    "sequence_mse",
    "factor_sequence_mse",
    "factor_errors",
    "check_loss_weights",
    "LOG_MSE_EPS",
]

#: ``eps`` of :func:`embedding_log_mse`: keeps the log finite for a sequence tracked exactly.
LOG_MSE_EPS = 1e-8


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


def check_loss_weights(weights, n: int | None = None) -> list[float] | None:
    """``weights`` as a list of floats, or ``None``; a ``ValueError`` naming the fix unless they
    are finite numbers >= 0, not all 0, and (with ``n``) one per embedding coordinate."""
    if weights is None:
        return None
    if isinstance(weights, (str, bytes)) or not hasattr(weights, "__len__"):
        raise ValueError(
            f"loss_weights must be a list of numbers, one per embedding coordinate, or null; got "
            f"{weights!r}."[:500]
        )
    out = list(weights)
    bad = [w for w in out if isinstance(w, bool) or not isinstance(w, (int, float))
           or not math.isfinite(w) or w < 0]
    if bad or not out or not any(w > 0 for w in out):
        raise ValueError(
            "loss_weights must be finite numbers >= 0, not all 0 (one per embedding coordinate; "
            f"null for the unweighted loss); got {weights!r}."[:500]
        )
    if n is not None and len(out) != n:
        raise ValueError(
            f"loss_weights has {len(out)} numbers; the group's embedding has {n} coordinates "
            "(one weight per coordinate)."
        )
    return [float(w) for w in out]


def _check_rollout(
    group: LieGroup, estimates: torch.Tensor, skip: int, mask: torch.Tensor | None
) -> None:
    if estimates.dim() < 2 + len(group.element_shape) or not 0 <= skip < estimates.shape[1]:
        raise ValueError(
            f"the loss needs (N, T+1, *element_shape) with T+1 > skip={skip}, got "
            f"{tuple(estimates.shape)}."
        )
    if mask is not None and (
        tuple(mask.shape) != tuple(estimates.shape[:2]) or mask.dtype != torch.bool
    ):
        raise ValueError(
            f"mask must be a bool tensor (N, T+1) = {tuple(estimates.shape[:2])}, got "
            f"{mask.dtype} {tuple(mask.shape)}."
        )


def _kept_squares(
    group: LieGroup,
    estimates: torch.Tensor,
    states: torch.Tensor,
    skip: int,
    mask: torch.Tensor | None,
    weights=None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The squared embedding errors ``(N, steps, n)`` of the steps ``k >= skip`` that ``mask``
    keeps (0 elsewhere), each times its coordinate's weight, and their number per sequence
    ``(N,)``."""
    _check(group, estimates, states)
    _check_rollout(group, estimates, skip, mask)
    n = group.embedding_dim
    diff = group.embed(estimates[:, skip:]) - group.embed(states[:, skip:].to(estimates.dtype))
    sq = (diff * diff).reshape(diff.shape[0], -1, n)
    if weights is not None:
        w = check_loss_weights(weights, n)
        sq = sq * torch.tensor(w, dtype=sq.dtype, device=sq.device)
    if mask is None:
        return sq, torch.full(sq.shape[:1], sq.shape[1], dtype=torch.long, device=sq.device)
    keep = mask[:, skip:].to(sq.device).reshape(sq.shape[0], -1)
    sq = torch.where(keep[..., None], sq, torch.zeros_like(sq))
    return sq, keep.sum(-1)


def sequence_mse(
    group: LieGroup,
    estimates: torch.Tensor,
    states: torch.Tensor,
    skip: int = 1,
    mask: torch.Tensor | None = None,
    weights=None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Each sequence's embedding MSE over its steps ``k >= skip`` (those ``mask`` keeps) and the
    number of those steps: two ``(N,)`` tensors; a sequence without a kept step has MSE 0."""
    sq, count = _kept_squares(group, estimates, states, skip, mask, weights)
    return sq.sum(-1).sum(-1) / (count.clamp(min=1) * group.embedding_dim), count


def factor_sequence_mse(
    group: LieGroup,
    estimates: torch.Tensor,
    states: torch.Tensor,
    skip: int = 1,
    mask: torch.Tensor | None = None,
    weights=None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Each sequence's MSE over each factor's embedding coordinates (``group.factor_names``
    order), ``(N, F)``, and the number of kept steps ``(N,)``; as :func:`sequence_mse`, whose
    value is their mean weighted by the factors' embedding dimensions."""
    sq, count = _kept_squares(group, estimates, states, skip, mask, weights)
    per = sq.sum(-2)
    slices = [group.embedding_slice(i) for i in range(len(group.factor_names))]
    mse = torch.stack([per[:, s].mean(-1) for s in slices], -1)
    return mse / count.clamp(min=1)[:, None], count


def embedding_mse(
    group: LieGroup,
    estimates: torch.Tensor,
    states: torch.Tensor,
    skip: int = 1,
    mask: torch.Tensor | None = None,
    weights=None,
) -> torch.Tensor:
    """The paper's ``L``: mean over sequences, steps ``k >= skip`` and embedding coordinates.

    ``estimates`` and ``states`` are ``(N, T+1, *element_shape)`` (``x_0 .. x_T``); a scalar in
    the estimates' dtype is returned. ``mask`` (bool ``(N, T+1)``, a dataset's ``mask``) keeps
    only the steps whose true state is known: the mean is over those (0 if there are none), and
    the placeholder states elsewhere never reach the loss or its gradient. ``weights``: module
    docstring.
    """
    per_seq, count = sequence_mse(group, estimates, states, skip, mask, weights)
    if mask is None:
        return per_seq.mean()
    return (per_seq * count).sum() / count.sum().clamp(min=1)


def embedding_log_mse(
    group: LieGroup,
    estimates: torch.Tensor,
    states: torch.Tensor,
    skip: int = 1,
    mask: torch.Tensor | None = None,
    eps: float = LOG_MSE_EPS,
    weights=None,
) -> torch.Tensor:
    """``mean_i log(L_i + eps)`` over the sequences with a kept step, ``L_i`` the embedding MSE
    of sequence ``i`` (:func:`sequence_mse`, same arguments); 0 if no sequence has one."""
    return _mean_log(*sequence_mse(group, estimates, states, skip, mask, weights), eps)


def embedding_factor_log_mse(
    group: LieGroup,
    estimates: torch.Tensor,
    states: torch.Tensor,
    skip: int = 1,
    mask: torch.Tensor | None = None,
    eps: float = LOG_MSE_EPS,
    weights=None,
) -> torch.Tensor:
    """``mean_i (1/F) sum_f log(L_if + eps)`` over the sequences with a kept step, ``L_if`` the
    MSE of sequence ``i`` over factor ``f``'s embedding coordinates (:func:`factor_sequence_mse`,
    same arguments); 0 if no sequence has one. :func:`embedding_log_mse` for one factor."""
    return _mean_log(*factor_sequence_mse(group, estimates, states, skip, mask, weights), eps)


def _mean_log(mse: torch.Tensor, count: torch.Tensor, eps: float) -> torch.Tensor:
    """The mean over the sequences with a kept step (``count > 0``) of ``log(mse + eps)``, first
    averaged over the factors when ``mse`` is ``(N, F)``; 0 if no sequence has one."""
    logs = torch.log(mse + eps)
    if logs.dim() == 2:
        logs = logs.mean(-1)
    has = count > 0
    return torch.where(has, logs, torch.zeros_like(logs)).sum() / has.sum().clamp(min=1)


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
