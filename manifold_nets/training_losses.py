"""The loss of one training batch: where its rollout starts, the loss it is scored by, and the
validation loss over a whole dataset; also the time pieces truncated BPTT rolls out one by one.

Used by the loop of :mod:`manifold_nets.training_loop`; :mod:`manifold_nets.training` describes
the protocol.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from .data import TrajectoryDataset
from .losses import embedding_factor_log_mse, embedding_log_mse, embedding_mse
from .observer import ObserverState, ResidualObserver

__all__ = ["LOSSES", "StartFn", "batch_loss", "initial_state", "validation_loss"]

#: Where rollouts start: ``batch -> (B, *element_shape)`` initial estimates.
StartFn = Callable[[TrajectoryDataset], torch.Tensor]

#: The training losses (``train.loss``), each ``(group, estimates, states, mask=) -> scalar``:
#: ``mse`` the paper's ``L``, ``log_mse`` the mean of each sequence's ``log L_i`` (every
#: sequence's relative error weighs alike, whatever its noise level), ``factor_log_mse`` the mean
#: of each sequence's ``log L_if`` over the factors too (every factor's relative error weighs
#: alike; :mod:`~manifold_nets.losses`).
LOSSES = {
    "mse": embedding_mse, "log_mse": embedding_log_mse, "factor_log_mse": embedding_factor_log_mse
}


def batch_loss(
    model: ResidualObserver,
    batch: TrajectoryDataset,
    start: StartFn | None = None,
    loss: str = "mse",
    skip: int = 1,
    weights=None,
) -> torch.Tensor:
    """The loss (:data:`LOSSES`; default the embedding MSE ``L``) of ``model`` rolled out over
    ``batch`` (its steps ``k < skip`` and those whose true state is unknown, ``batch.mask``
    False, left out), started at ``start(batch)`` or the identity; ``weights`` per embedding
    coordinate (``train.loss_weights``, :mod:`manifold_nets.losses`)."""
    inputs = batch.inputs if batch.inputs.shape[-1] else None
    est = model(batch.measurements, inputs, state=initial_state(model, batch, start))
    return LOSSES[loss](
        model.group, est, batch.states.to(est), skip=skip, mask=batch.mask, weights=weights
    )


def initial_state(
    model: ResidualObserver, batch: TrajectoryDataset, start: StartFn | None = None
) -> ObserverState | None:
    """Where ``batch``'s rollout starts: ``start(batch)`` and the core's initial hidden state, or
    ``None`` (the observer's own start, the identity) without ``start``."""
    if start is None:
        return None
    x0 = start(batch).to(device=model.device, dtype=model.state_dtype)
    return ObserverState(x0, model.core.initial_hidden(len(batch), device=model.device))


def _chunks(batch: TrajectoryDataset, length: int):
    """``batch`` cut along time into pieces of ``length`` steps; piece ``i`` holds states
    ``x_{iL} .. x_{(i+1)L}`` (the first is where the previous piece ended)."""
    for a in range(0, batch.length, length):
        b = min(a + length, batch.length)
        mask = None if batch.mask is None else batch.mask[:, a : b + 1]
        yield TrajectoryDataset(
            batch.states[:, a : b + 1], batch.measurements[:, a:b], batch.inputs[:, a:b],
            batch.meta, mask,
        )


@torch.no_grad()
def validation_loss(
    model: ResidualObserver,
    data: TrajectoryDataset,
    batch_size: int = 500,
    start: StartFn | None = None,
    loss: str = "mse",
    skip: int = 1,
    weights=None,
) -> float:
    """The loss (:data:`LOSSES`; default the embedding MSE ``L``) of ``model`` on ``data``,
    averaged over all its sequences (steps ``k < skip`` left out)."""
    was = model.training
    model.eval()
    total = 0.0
    n = len(data)
    for s in range(0, n, batch_size):
        idx = torch.arange(s, min(n, s + batch_size))
        total += float(batch_loss(model, data[idx], start, loss, skip, weights)) * len(idx)
    model.train(was)
    return total / n
