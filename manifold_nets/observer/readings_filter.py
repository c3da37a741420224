"""A causal, stateful pre-filter of an observer's readings: what they go through before it reads them.

An observer may be trained on readings that went through a filter first (a sensor's bias
estimated and removed, a signal low-passed): run on the readings as recorded it is another,
worse, filter. A :class:`ReadingsFilter` is that filter as a module, so that the rollout, the
online step and the exported step apply it (:class:`~manifold_nets.observer.filtered.
FilteredObserver`). A system names its own with :meth:`~manifold_nets.system.System.
readings_filter`, built by the system's code from the plain numbers of its config.

A subclass writes :meth:`init_state` (its state: a tuple of tensors, each ``(B, ...)``),
:meth:`state_names` and :meth:`step_unchecked` (one sample of every sequence, nothing checked:
what the exported step traces); it may write :meth:`sequence_unchecked` (whole sequences from a
state, faster than the loop over :meth:`step_unchecked` that it is by default, and equal to it to
rounding). The public :meth:`step` and :meth:`forward` check their arguments once and call them.

Shapes: one step ``y`` ``(B, l)``, ``u`` ``(B, m)`` (``y = y_{k+1}``, ``u = u_k``, paired as the
observer reads them); sequences ``(N, T, l)`` and ``(N, T, m)``; ``u`` is ``None`` when ``m = 0``.
The filter computes in the dtype of its state (:meth:`init_state`'s ``dtype``) and returns the
readings in it; any float input dtype and any strides are accepted.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["ReadingsFilter", "FilterState"]

#: A filter's state: a tuple of tensors, each ``(B, ...)``.
FilterState = tuple[torch.Tensor, ...]


class ReadingsFilter(nn.Module):
    """The interface of a causal pre-filter of ``(y, u)``; see the module docstring.

    Args:
        measurement_dim: the width ``l`` of ``y`` it reads and returns.
        input_dim: the width ``m`` of ``u`` (0: no input).
    """

    #: A short name, for messages and the signature.
    name = "readings_filter"

    def __init__(self, measurement_dim: int, input_dim: int = 0):
        super().__init__()
        for what, v in (("measurement_dim", measurement_dim), ("input_dim", input_dim)):
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ValueError(f"{self.name}: {what} must be an integer >= 0, got {v!r}.")
        self.measurement_dim, self.input_dim = measurement_dim, input_dim

    # ------------------------------------------------------------------ what a subclass writes

    def init_state(self, batch: int, dtype: torch.dtype = torch.float64, device=None) -> FilterState:
        """The state before the first sample, each tensor ``(batch, ...)`` in ``dtype``."""
        raise NotImplementedError(f"{type(self).__name__} must write init_state.")

    def state_names(self) -> list[str]:
        """One name per state tensor (the exported step's input names)."""
        raise NotImplementedError(f"{type(self).__name__} must write state_names.")

    def step_unchecked(self, state: FilterState, y: torch.Tensor, u: torch.Tensor | None):
        """One sample: ``(state, y', u')`` from ``y`` ``(B, l)`` and ``u`` ``(B, m)`` (or None),
        both already in the state's dtype, contiguous."""
        raise NotImplementedError(f"{type(self).__name__} must write step_unchecked.")

    def sequence_unchecked(self, state: FilterState, y: torch.Tensor, u: torch.Tensor | None):
        """Whole sequences, ``y`` ``(N, T, l)``, ``u`` ``(N, T, m)`` or None, in the state's
        dtype: ``(state after them, y', u')``. Default: :meth:`step_unchecked` sample by sample."""
        ys, us = [], []
        for k in range(y.shape[1]):
            state, y_k, u_k = self.step_unchecked(state, y[:, k], None if u is None else u[:, k])
            ys.append(y_k)
            us.append(u_k)
        return state, torch.stack(ys, 1), None if u is None else torch.stack(us, 1)

    def signature(self) -> dict:
        """What the filter is (JSON-able): its name, its sizes and :meth:`extra_signature`."""
        return {"type": self.name, "measurement_dim": self.measurement_dim,
                "input_dim": self.input_dim, **self.extra_signature()}

    def extra_signature(self) -> dict:
        """The subclass's own parameters, JSON-able."""
        return {}

    # ------------------------------------------------------------------ checked entry points

    def step(self, state: FilterState, y: torch.Tensor, u: torch.Tensor | None = None):
        """One checked sample (:meth:`step_unchecked`): ``(state, y' (B, l), u' (B, m))``."""
        yy, uu = self._checked(y, u, state, sequence=False)
        return self.step_unchecked(state, yy, uu)

    def forward(self, y: torch.Tensor, u: torch.Tensor | None = None,
                state: FilterState | None = None):
        """Whole sequences (:meth:`sequence_unchecked`) from ``state`` (default
        :meth:`init_state` in float64 on ``y``'s device): ``(y', u', state after them)``."""
        if state is None:
            n = y.shape[0] if isinstance(y, torch.Tensor) and y.dim() == 3 else 1
            state = self.init_state(n, torch.float64, y.device if isinstance(y, torch.Tensor) else None)
        yy, uu = self._checked(y, u, state, sequence=True)
        state, yy, uu = self.sequence_unchecked(state, yy, uu)
        return yy, uu, state

    def _checked(self, y, u, state: FilterState, sequence: bool):
        """``(y, u)`` checked against the widths, the state's batch, cast to its dtype."""
        lead = "(N, T, " if sequence else "(B, "
        rank = 3 if sequence else 2
        who = f"{self.name} ({type(self).__name__})"
        if not isinstance(y, torch.Tensor) or not y.is_floating_point() or y.dim() != rank \
                or y.shape[-1] != self.measurement_dim:  # fmt: skip
            got = tuple(y.shape) if isinstance(y, torch.Tensor) else type(y).__name__
            raise ValueError(
                f"{who} reads measurements y {lead}{self.measurement_dim}) as floats, got {got}; "
                "pass the readings the observer's system records (all of their columns, in its "
                "order), not already filtered or cut ones."
            )
        if self.input_dim and (not isinstance(u, torch.Tensor) or not u.is_floating_point()
                               or tuple(u.shape) != (*y.shape[:-1], self.input_dim)):  # fmt: skip
            got = tuple(u.shape) if isinstance(u, torch.Tensor) else type(u).__name__
            raise ValueError(
                f"{who} reads inputs u {tuple(y.shape[:-1])} + ({self.input_dim},) beside y, got "
                f"{got}; pass the system's inputs with every column."
            )
        if not state or state[0].shape[0] != y.shape[0]:
            raise ValueError(
                f"{who}: the state holds a batch of {state[0].shape[0] if state else 0}, y a batch "
                f"of {y.shape[0]}; start from init_state({y.shape[0]}, ...)."
            )
        dtype, device = state[0].dtype, state[0].device
        y = y.to(device=device, dtype=dtype).contiguous()
        u = u.to(device=device, dtype=dtype).contiguous() if self.input_dim else None
        return y, u
