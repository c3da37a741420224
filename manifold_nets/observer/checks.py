"""The observer's input checks, done once before the loop (nothing inside it is checked).

:func:`check_sequences` validates a rollout's measurements and inputs and returns them
time-major, ``(T, N, l + m)``, in the network dtype (what the features read) and in the state
dtype (what the prior and the measured factors read, as given); :func:`check_step_args` the same
for one online step; :func:`check_start` a given start state.
"""

from __future__ import annotations

import torch

__all__ = ["check_sequences", "check_step_args", "check_start"]


def _describe(t) -> str:
    if isinstance(t, torch.Tensor):
        return f"{type(t).__name__} of dtype {t.dtype}"
    return type(t).__name__


def check_sequences(obs, measurements, inputs) -> tuple[torch.Tensor, torch.Tensor]:
    """``(yu, ys)``, each ``(T, N, l + m)``: network dtype and state dtype."""
    dim, m = obs.measurement_dim, obs.input_dim
    if not isinstance(measurements, torch.Tensor) or not measurements.is_floating_point():
        raise TypeError(
            f"measurements must be a floating-point torch.Tensor (N, T, {dim}), got "
            f"{_describe(measurements)}."
        )
    if measurements.dim() != 3 or measurements.shape[-1] != dim:
        raise ValueError(
            f"measurements must have shape (N, T, measurement_dim={dim}), got "
            f"{tuple(measurements.shape)}; is this data from the system the observer was built for?"
        )
    n, t = measurements.shape[:2]
    if t < 1 or n < 1:
        raise ValueError(
            "measurements must hold at least one sequence of one step, got "
            f"{tuple(measurements.shape)}."
        )
    parts = [measurements]
    if inputs is None:
        if m:
            raise ValueError(f"this observer reads inputs u of size {m}; pass inputs (N, T, {m}).")
    else:
        if not isinstance(inputs, torch.Tensor) or not inputs.is_floating_point():
            raise TypeError(f"inputs must be a floating-point torch.Tensor (N, T, {m}).")
        if tuple(inputs.shape) != (n, t, m):
            raise ValueError(
                f"inputs must have shape (N, T, input_dim) = ({n}, {t}, {m}) to match the "
                f"measurements, got {tuple(inputs.shape)}."
            )
        if m:
            parts.append(inputs)
    dev = obs.device
    ys = torch.cat([p.to(device=dev, dtype=obs.state_dtype) for p in parts], dim=-1)
    yu = torch.cat([p.to(device=dev, dtype=obs.net_dtype) for p in parts], dim=-1)
    # a data-dependent branch: checked in eager use, left out of a traced or captured graph
    # (the captured training step, manifold_nets.graphed_step, checks its batches eagerly first)
    capturing = yu.is_cuda and torch.cuda.is_current_stream_capturing()
    if not torch.compiler.is_compiling() and not capturing and not bool(torch.isfinite(yu).all()):
        raise ValueError(
            "measurements/inputs hold NaN or Inf (or values beyond the network dtype's range); "
            "the observer needs finite data."
        )
    return yu.transpose(0, 1).contiguous(), ys.transpose(0, 1).contiguous()


def check_step_args(obs, state, y, u) -> tuple[torch.Tensor, torch.Tensor]:
    """``(yu, ys)`` of one online step, each ``(B, l + m)``."""
    if not isinstance(y, torch.Tensor) or y.dim() != 2:
        raise ValueError(
            f"y must be a tensor (B, measurement_dim={obs.measurement_dim}), got "
            f"{tuple(y.shape) if isinstance(y, torch.Tensor) else type(y).__name__}."
        )
    yu, ys = check_sequences(obs, y[:, None], None if u is None else u[:, None])
    if state.estimate.shape[0] != yu.shape[1]:
        raise ValueError(
            f"the state holds a batch of {state.estimate.shape[0]}, y a batch of {yu.shape[1]}."
        )
    return yu[0], ys[0]


def check_start(obs, state, n: int):
    """``state`` unless its estimate is not ``(n, *element_shape)`` or not finite."""
    want = (n, *obs.group.element_shape)
    if tuple(state.estimate.shape) != want:
        raise ValueError(
            f"state.estimate has shape {tuple(state.estimate.shape)}, expected {want} for {n} "
            "sequences."
        )
    if not torch.compiler.is_compiling():
        if not bool(torch.isfinite(state.estimate).all()):
            raise ValueError("state.estimate holds NaN or Inf; start from a finite element.")
        tol = 1e-6 if state.estimate.dtype == torch.float64 else 1e-3
        err = float(obs.group.membership_error(state.estimate.to(obs.state_dtype)).max())
        if err > tol:
            raise ValueError(
                f"state.estimate is off the group {obs.group!r} (membership error {err:.3g} > "
                f"{tol:g}); start from an element of the group, e.g. group.identity."
            )
    return state
