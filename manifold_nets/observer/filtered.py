"""An observer behind the pre-filter of its readings: raw readings in, the observer's estimates out.

A :class:`FilteredObserver` puts a :class:`~manifold_nets.observer.readings_filter.ReadingsFilter`
in front of a :class:`~manifold_nets.observer.observer.ResidualObserver` (as
:class:`~manifold_nets.observer.CalibratedObserver` puts a readout behind one): its
rollout filters the readings, then rolls the observer over them; its online step filters one
sample, then steps; its exported step (:meth:`FilteredObserver.online_step_module`, what
:func:`manifold_nets.export_observer` traces) carries the filter's state as more state tensors.
Nothing in the observer changes: on readings that went through the filter already, the observer
alone gives the same estimates::

    observer, system, _ = load_observer("zoo:broad/attitude")
    filtered = with_readings_filter(observer, system)   # the observer itself when none
    estimates = filtered(raw_measurements, raw_inputs)

The filter computes in its own dtype (default the observer's state dtype) and hands the observer
its readings in it; the observer casts them as it casts any readings.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

from .ensemble import EnsembleObserver
from .observer import ObserverState, ResidualObserver
from .readings_filter import FilterState, ReadingsFilter
from .wrapper import WrapsObserver

__all__ = ["FilteredObserver", "FilteredState", "FilteredStep", "with_readings_filter"]


class FilteredState(NamedTuple):
    """The online state of a :class:`FilteredObserver`: the observer's and the filter's."""

    observer: ObserverState
    filter: FilterState


def with_readings_filter(observer: ResidualObserver, system, dtype: torch.dtype | None = None):
    """``observer`` behind ``system.readings_filter()`` (a :class:`FilteredObserver`), or
    ``observer`` itself when the system has none (or is an older one without the hook)."""
    hook = getattr(system, "readings_filter", None)
    prefilter = hook() if callable(hook) else None
    return observer if prefilter is None else FilteredObserver(prefilter, observer, dtype)


class FilteredObserver(WrapsObserver):
    """A readings filter, then an observer; see the module docstring.

    Args:
        prefilter: the :class:`ReadingsFilter` (its widths those of the observer's readings).
        observer: the :class:`ResidualObserver` trained on filtered readings (or an
            :class:`~manifold_nets.observer.EnsembleObserver` of such: the filter runs once).
        dtype: the filter's dtype (default: the observer's state dtype).
    """

    def __init__(self, prefilter: ReadingsFilter, observer: ResidualObserver,
                 dtype: torch.dtype | None = None):
        super().__init__()
        if not isinstance(observer, (ResidualObserver, EnsembleObserver)):
            raise TypeError(f"observer must be a ResidualObserver or an EnsembleObserver, got "
                            f"{type(observer).__name__}.")
        if not isinstance(prefilter, ReadingsFilter):
            raise TypeError(
                f"prefilter must be a ReadingsFilter (manifold_nets.observer.readings_filter), got "
                f"{type(prefilter).__name__}."
            )
        if (prefilter.measurement_dim, prefilter.input_dim) != (observer.measurement_dim,
                                                                  observer.input_dim):
            raise ValueError(
                f"the filter reads y of width {prefilter.measurement_dim} and u of width "
                f"{prefilter.input_dim}; the observer reads {observer.measurement_dim} and "
                f"{observer.input_dim}: build the filter for the observer's system."
            )
        dtype = observer.state_dtype if dtype is None else dtype
        if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
            raise TypeError(f"dtype must be a floating torch.dtype, got {dtype!r}.")
        self.prefilter, self.observer, self.filter_dtype = prefilter, observer, dtype

    # ------------------------------------------------------------------ the observer's description
    # (group, widths, dtypes, device: the observer's, WrapsObserver)

    def signature(self) -> dict:
        """The observer's signature with the filter's under ``readings_filter``."""
        return {**self.observer.signature(), "readings_filter": self.prefilter.signature()}

    # ------------------------------------------------------------------ rollout and online step

    def init_state(self, batch: int, device=None, estimate: torch.Tensor | None = None
                   ) -> FilteredState:
        """The observer's start (the identity, or ``estimate``) and the filter's."""
        device = self.device if device is None else device
        return FilteredState(self.observer.init_state(batch, device, estimate),
                             self.prefilter.init_state(batch, self.filter_dtype, device))

    def forward(self, measurements, inputs=None, state: FilteredState | None = None,
                return_state: bool = False):
        """The observer's estimates ``(N, T+1, *element_shape)`` over the raw readings
        ``(N, T, l)`` (and ``(N, T, m)``), filtered first; from ``state`` (default: the
        observer's start and a fresh filter; a :class:`FilteredState` whose ``observer`` may be
        ``None`` for the observer's start). ``return_state`` also returns the final state."""
        n = measurements.shape[0] if isinstance(measurements, torch.Tensor) else 1
        device = measurements.device if isinstance(measurements, torch.Tensor) else None
        start = None if state is None else state.observer
        fstate = (self.prefilter.init_state(n, self.filter_dtype, device) if state is None
                  else state.filter)  # fmt: skip
        y, u, fstate = self.prefilter(measurements, inputs, fstate)
        est, final = self.observer(y, u, state=start, return_state=True)
        return (est, FilteredState(final, fstate)) if return_state else est

    def step(self, state: FilteredState, y: torch.Tensor, u: torch.Tensor | None = None):
        """One online step on a raw sample ``y`` ``(B, l)``, ``u`` ``(B, m)``: the new
        :class:`FilteredState` (its ``observer.estimate`` is ``xhat_{k+1}``)."""
        fstate, y, u = self.prefilter.step(state.filter, y, u)
        return FilteredState(self.observer.step(state.observer, y, u), fstate)

    def online_step_module(self) -> FilteredStep:
        """The exported step with the filter's state as more state tensors (:class:`FilteredStep`)."""
        return FilteredStep(self)


class FilteredStep(nn.Module):
    """The filter's step, then :class:`manifold_nets.deploy.OnlineStep`, on plain tensors:
    ``(x, *state, *filter_state, y, [u]) -> (x_next, *state_next, *filter_state_next)``.

    ``y`` and ``u`` are the raw readings in the filter's dtype (``(B, l)``, ``(B, m)``, any
    views); the observer's state tensors are :class:`~manifold_nets.deploy.OnlineStep`'s. Each
    module sits at one place in it (``step.observer``, ``prefilter``; see
    :class:`~manifold_nets.observer.calibrated.CalibratedStep`)."""

    def __init__(self, filtered: FilteredObserver):
        super().__init__()
        self.step = filtered.observer.online_step_module()
        self.prefilter = filtered.prefilter
        self.filter_dtype = filtered.filter_dtype
        self.num_filter = len(self.prefilter.state_names())
        self.num_hidden = self.step.num_hidden + self.num_filter

    @property
    def observer(self) -> ResidualObserver:
        """The observer (reached through :attr:`step`, not a second submodule)."""
        return self.step.observer

    def state_names(self) -> list[str]:
        return self.step.state_names() + [f"filter_{n}" for n in self.prefilter.state_names()]

    def initial_state(self, batch: int = 1) -> tuple[torch.Tensor, ...]:
        """``(x, *state, *filter_state)`` before the first step."""
        device = self.observer.device
        return (*self.step.initial_state(batch),
                *self.prefilter.init_state(batch, self.filter_dtype, device))

    def example_inputs(self, batch: int = 1) -> tuple[torch.Tensor, ...]:
        """Arguments of the right shapes and dtypes for tracing (the initial state, zero readings:
        ``y`` and ``u`` in the filter's dtype)."""
        obs, kw = self.observer, {"dtype": self.filter_dtype, "device": self.observer.device}
        u = (torch.zeros(batch, obs.input_dim, **kw),) if obs.input_dim else ()
        return (*self.initial_state(batch), torch.zeros(batch, obs.measurement_dim, **kw), *u)

    def forward(self, x: torch.Tensor, *args: torch.Tensor) -> tuple[torch.Tensor, ...]:
        obs = self.observer
        want = self.num_hidden + 1 + (1 if obs.input_dim else 0)
        if len(args) != want:
            raise TypeError(
                f"FilteredStep takes (x, {self.step.num_hidden} observer state tensors, "
                f"{self.num_filter} filter state tensors, y" + (", u)" if obs.input_dim else ")")
                + f", got {1 + len(args)} tensors."
            )
        k = self.step.num_hidden
        state, fstate = args[:k], tuple(args[k : self.num_hidden])
        y = args[self.num_hidden].to(self.filter_dtype).contiguous()
        u = args[-1].to(self.filter_dtype).contiguous() if obs.input_dim else None
        fstate, y, u = self.prefilter.step_unchecked(fstate, y, u)
        out = self.step(x, *state, y, *((u,) if obs.input_dim else ()))
        return (*out, *fstate)
