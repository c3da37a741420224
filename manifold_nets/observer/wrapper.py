"""What a module that wraps one observer says about it: the group, the widths of the readings,
the dtypes and the device are the wrapped observer's (``self.observer``).

:class:`~manifold_nets.observer.FilteredObserver` (a readings filter in front) and
:class:`~manifold_nets.observer.LockOutGuard` (a check behind every step) derive from
:class:`WrapsObserver`, so that code written for a :class:`ResidualObserver` (the evaluation's
rollout, the checks of a start) reads them the same way.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["WrapsObserver"]


class WrapsObserver(nn.Module):
    """A module around ``self.observer``; its description is the observer's."""

    observer: nn.Module

    @property
    def group(self):
        return self.observer.group

    @property
    def measurement_dim(self) -> int:
        return self.observer.measurement_dim

    @property
    def input_dim(self) -> int:
        return self.observer.input_dim

    @property
    def state_dtype(self) -> torch.dtype:
        return self.observer.state_dtype

    @property
    def net_dtype(self) -> torch.dtype:
        return self.observer.net_dtype

    @property
    def device(self) -> torch.device:
        return self.observer.device
