"""Jacobians at zero by reverse-mode autograd, batched: the error-state EKF's generic path
(:class:`manifold_nets.ekf.ErrorStateEKF` with ``jacobians="autograd"``)."""

from __future__ import annotations

import torch

__all__ = ["jacobian_at_zero", "lead"]


def lead(t: torch.Tensor, k: int) -> torch.Tensor:
    """``t`` ``(*batch, ...)`` seen as ``(k, *batch, ...)`` (a view, no copy)."""
    return t.expand(k, *t.shape)


def jacobian_at_zero(fn, dims, d_out: int, batch, like: torch.Tensor) -> list[torch.Tensor]:
    """The Jacobians at 0 of ``fn(*perturbations) -> (d_out, *batch, d_out)`` in each argument.

    Reverse mode with the output rows stacked in front of the batch: argument ``i`` is
    ``(d_out, *batch, dims[i])``, copy ``j`` of the batch is pulled back along output
    component ``j``, so one ``torch.func.vjp`` (one forward and one backward pass over
    ``d_out`` copies of the batch) gives every row of every sequence's Jacobian. ``fn`` must
    let copy ``j`` depend only on its own perturbation (any batched function does). On the CPU
    this is several times faster than forward mode here (``torch.func.jvp``/``jacfwd`` go
    through Python decompositions for some of the groups' operations).
    Returns ``[(*batch, d_out, dims[i])]``.
    """
    primals = tuple(like.new_zeros(d_out, *batch, d) for d in dims)
    _, pullback = torch.func.vjp(fn, *primals)
    eye = torch.eye(d_out, dtype=like.dtype, device=like.device)
    cot = eye.reshape(d_out, *(1,) * len(batch), d_out).expand(d_out, *batch, d_out)
    return [g.movedim(0, -2) for g in pullback(cot)]
