"""The observer's rate: BROAD's 285.7 Hz recordings seen every ``k``-th sample, and back.

A recurrent network stepped 285.7 times a second costs a CPU minutes per trial and has to learn
corrections of 1e-4 rad. The attitude moves between corrections by what the gyroscope says, so
the observer can run at ``285.7 / k`` Hz with nothing of the gyroscope lost:

* :func:`decimate` turns a full-rate dataset (states ``x_0 .. x_L``, measurements
  ``y_1 .. y_L``, gyro inputs ``u_0 .. u_{L-1}`` with ``u_i`` the rate over sample ``i -> i+1``)
  into one with a step of ``k`` samples: the states and the mask every ``k``-th sample, the
  measurement at the end of each step, and as input the constant rate that turns exactly as the
  ``k`` readings do, ``log(prod_i exp(dt u_i)) / (k dt)``. An observer whose kinematic prior
  integrates that rate over ``k dt`` reproduces the full-rate integration to rounding.
* :func:`upsample` fills the samples between two estimates by integrating the gyroscope from
  the earlier estimate (``R_{jk+i} = R_{jk} prod_{l<i} exp(dt u_{jk+l})``), so every sample of a
  trial has an estimate, and the metric sees all of them.

Shapes: full rate ``(N, L+1, 3, 3)`` states, ``(N, L, 6)`` measurements, ``(N, L, 3)`` inputs;
decimated ``(N, J+1, 3, 3)``, ``(N, J, 6)``, ``(N, J, 3)`` with ``J = L // k`` (a tail of fewer
than ``k`` samples is cropped; :func:`upsample` still covers it from the last estimate).
"""

from __future__ import annotations

import torch

from groups import SO3
from manifold_nets.data import TrajectoryDataset

__all__ = ["decimate", "upsample", "increments"]

_SO3 = SO3()


def _check_k(k: int) -> int:
    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise ValueError(f"the decimation factor k must be a positive integer, got {k!r}.")
    return k


def increments(rates: torch.Tensor, dt: float, k: int) -> torch.Tensor:
    """``(N, J, 3, 3)``: the rotation of each block of ``k`` gyro readings ``(N, J*k, 3)``."""
    n, length = rates.shape[:2]
    steps = _SO3.exp(rates * dt).unflatten(1, (length // k, k))  # (N, J, k, 3, 3)
    out = steps[:, :, 0]
    for i in range(1, k):
        out = out @ steps[:, :, i]
    return out


def decimate(ds: TrajectoryDataset, k: int, dt: float) -> TrajectoryDataset:
    """``ds`` (full rate, step ``dt`` seconds) with a step of ``k`` samples; see the module."""
    k = _check_k(k)
    if k == 1:
        return ds
    j = ds.length // k
    if j < 1:
        raise ValueError(f"sequences of {ds.length} steps are shorter than k = {k} samples.")
    u = ds.inputs[:, : j * k].to(torch.float64)
    rate = _SO3.log(increments(u, dt, k)) / (k * dt)
    mask = None if ds.mask is None else ds.mask[:, : j * k + 1 : k]
    meta = {**ds.meta, "decimation": k}
    return TrajectoryDataset(
        ds.states[:, : j * k + 1 : k], ds.measurements[:, k - 1 : j * k : k],
        rate.to(ds.inputs.dtype), meta, mask,
    )


def upsample(estimates: torch.Tensor, rates: torch.Tensor, dt: float, k: int) -> torch.Tensor:
    """Full-rate estimates ``(N, L+1, 3, 3)`` from decimated ones ``(N, J+1, 3, 3)`` and the
    full-rate gyro ``(N, L, 3)``: each sample from the last estimate at or before it."""
    k = _check_k(k)
    n, length = rates.shape[:2]
    j = estimates.shape[1] - 1
    if k == 1:
        return estimates
    if j != length // k:
        raise ValueError(
            f"{j + 1} estimates do not fit {length} gyro readings at k = {k} ({length // k + 1} "
            "expected)."
        )
    pad = (j + 1) * k - length  # the tail after the last estimate, padded to a whole block
    u = torch.cat((rates, rates.new_zeros(n, pad, 3)), 1).to(estimates.dtype)
    steps = _SO3.exp(u * dt).unflatten(1, (j + 1, k))  # (N, J+1, k, 3, 3)
    out = [estimates]
    R = estimates
    for i in range(k - 1):
        R = R @ steps[:, :, i]
        out.append(R)
    full = torch.stack(out, 2).flatten(1, 2)  # (N, (J+1) k, 3, 3): sample jk + i
    return full[:, : length + 1]
