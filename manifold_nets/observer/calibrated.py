"""An observer with its covariance: :class:`CalibratedObserver` puts an observer, a
:class:`~manifold_nets.observer.CovarianceReadout` and optionally a
:class:`~manifold_nets.observer.LevelScale` together (:mod:`manifold_nets.observer.covariance`
says what the readout reads and how). Its rollout returns the estimates and the covariances
``(N, T+1, n, n)``, its online step the new state and ``P``, and its exported step
(:meth:`CalibratedObserver.online_step_module`) more state tensors (the readout's memory, the
level scale's averaged level) and one more output, ``P``. Neither changes the estimate: fitted on
a frozen observer, the point estimates are the observer's to the last bit.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

from groups import LieGroup

from .covariance import (
    CovarianceReadout, input_width, readout_inputs, steps_taken, with_context,
)
from .level_scale import LevelScale
from .lock_out import LockOutGuard
from .observer import ObserverState, ResidualObserver

__all__ = ["CalibratedObserver", "CalibratedState", "CalibratedStep"]


def _reads(observer) -> ResidualObserver | None:
    """The :class:`ResidualObserver` a readout of its core or residuals reads in ``observer``:
    itself, the one a :class:`LockOutGuard` guards, or ``None`` (any other observer)."""
    if isinstance(observer, LockOutGuard):
        return observer.observer
    return observer if isinstance(observer, ResidualObserver) else None


class CalibratedState(NamedTuple):
    """The online state of a :class:`CalibratedObserver`: the observer's, the readout's memory
    ``(B, memory)`` and, with a level scale, its averaged level ``(B, F)``."""

    observer: ObserverState
    memory: torch.Tensor
    level: torch.Tensor | None = None


class CalibratedObserver(nn.Module):
    """An observer, its covariance readout and optionally a level scale of the readout's
    covariance (:class:`LevelScale`); see the module docstring."""

    def __init__(self, observer: ResidualObserver, readout: CovarianceReadout,
                 level_scale: LevelScale | None = None):
        super().__init__()
        if level_scale is not None and (
                not isinstance(level_scale, LevelScale)
                or level_scale.group.factor_names != readout.group.factor_names
                or level_scale.group.tangent_dim != readout.n):
            raise ValueError(
                "level_scale must be a LevelScale of the readout's group (factors "
                f"{list(readout.group.factor_names)}), got {type(level_scale).__name__}."
            )
        reads = _reads(observer)
        if reads is None and not (
                readout.source == "readings" and isinstance(observer, nn.Module)
                and hasattr(observer, "online_step_module")):
            raise TypeError(
                f"a {readout.source} readout reads one ResidualObserver's (or a LockOutGuard's) "
                f"{'core' if readout.source == 'hidden' else 'measured factors'}; got a "
                f"{type(observer).__name__}. A readout of source 'readings' serves any observer "
                "(an EnsembleObserver, a FilteredObserver)."
            )
        if readout.source in ("residual", "residual_size") and not reads.measurement.factors:
            raise ValueError(
                "a residual readout reads the measured factors' residuals, but the observer's "
                "measurement names no measured factor; use source='hidden'."
            )
        width = input_width(observer if reads is None else reads, readout.source)
        if readout.width != width or readout.n != observer.group.tangent_dim:
            raise ValueError(
                f"the readout reads {readout.width} numbers ({readout.source}) into a "
                f"{readout.n}-dimensional covariance; this observer gives {width} and its tangent "
                f"space has {observer.group.tangent_dim} dimensions."
            )
        self.observer, self.readout, self.level_scale = observer, readout, level_scale

    @property
    def group(self) -> LieGroup:
        return self.observer.group

    @property
    def reads(self):
        """The :class:`ResidualObserver` whose core or measured factors the readout reads (the
        observer, or the one a :class:`LockOutGuard` guards), or the observer itself when the
        readout reads its readings alone."""
        reads = _reads(self.observer)
        return self.observer if reads is None else reads

    def inputs(self, x, y, u, hidden, context: torch.Tensor | None = None) -> torch.Tensor:
        """:func:`readout_inputs` of this observer and readout, and the step's ``context``
        (:func:`with_context`)."""
        z = readout_inputs(self.reads, self.readout.source, x, y, u, hidden)
        return with_context(self.readout, z, context)

    def forward(self, measurements, inputs=None, state: ObserverState | None = None,
                context: torch.Tensor | None = None):
        """``(estimates (N, T+1, *element_shape), covariances (N, T+1, n, n))`` from the
        observer's start (or ``state``: an observer state, the readout's memory and a level
        scale's average starting fresh);
        the first covariance is the start's. ``context`` ``(N, T, context)``: the side
        information of each step, for a readout that reads some."""
        if _reads(self.observer) is not None:
            run = self.observer.rollout(measurements, inputs, state=state, keep_hidden=True)
            estimates = run.estimates
            z = self.inputs(
                estimates[:, 1:].flatten(2), measurements, inputs,
                tuple(h[:, 1:] for h in run.hidden), context,
            )
        else:  # any other observer, read by its readings alone
            estimates = self.observer(measurements, inputs, state=state)
            z = self.inputs(None, measurements, inputs, None, context)
        n = estimates.shape[0]
        start = 0 if state is None else steps_taken(state)
        chol, _ = self.readout.cholesky(z, self.readout.initial_memory(n, z.device), start)
        first = self.readout.initial_cholesky((n,))
        if self.level_scale is not None:
            chol, _ = self.level_scale(chol, self.level_scale.initial(first), start)
        chol = torch.cat([first.unsqueeze(1), chol], dim=1)
        return estimates, CovarianceReadout.covariance(chol)

    def init_state(self, batch: int, device=None, estimate: torch.Tensor | None = None
                   ) -> CalibratedState:
        """The observer's start (``estimate``: a measured one), the readout's fresh memory (and
        the start's level)."""
        level = None if self.level_scale is None else self.level_scale.initial(
            self.readout.initial_cholesky((batch,)).to(device))
        return CalibratedState(self.observer.init_state(batch, device, estimate),
                               self.readout.initial_memory(batch, device), level)

    def step(self, state: CalibratedState, y: torch.Tensor, u: torch.Tensor | None = None,
             context: torch.Tensor | None = None):
        """One online step: ``(new state, P (B, n, n))``; ``context`` ``(B, context)``."""
        obs = self.observer.step(state.observer, y, u)
        if _reads(self.observer) is not None:
            z = self.inputs(obs.estimate.flatten(1), y, u, obs.hidden, context)
        else:  # any other observer, read by its readings alone
            z = self.inputs(None, y, u, None, context)
        k = steps_taken(state.observer)
        chol, memory = self.readout.cholesky(z.unsqueeze(1), state.memory, k)
        level = state.level
        if self.level_scale is not None:
            chol, level = self.level_scale(chol, level, k)
        return CalibratedState(obs, memory, level), CovarianceReadout.covariance(chol[:, 0])

    def online_step_module(self) -> nn.Module:
        """The exported step with the readout's memory (and the averaged level) as more state
        tensors and ``P`` as the last output (:class:`CalibratedStep`)."""
        return CalibratedStep(self)


class CalibratedStep(nn.Module):
    """:class:`manifold_nets.deploy.OnlineStep` of the observer, then ``P``:
    ``(x, *state, memory[, level][, clock_steps], y[, u][, context]) -> (x_next, *state_next,
    memory_next[, level_next][, clock_steps_next], P)`` (``P`` ``(B, n, n)``, float64; ``level``
    ``(B, F)`` with a level scale; ``context`` for a readout that reads some). A readout with a
    clock, and a level scale, read the steps taken from the observer's own ``steps`` state tensor
    where it has one (a centred head, a step decay), else from ``clock_steps`` ``(B,)``
    (float64), one more state tensor. Each
    module sits at one place in it (``step.observer``, ``readout``): ``torch.export``'s
    non-strict tracer patches a module class reached by two paths, and the patch outlived the
    export."""

    def __init__(self, calibrated: CalibratedObserver):
        super().__init__()
        self.step = calibrated.observer.online_step_module()
        self.readout, self.level_scale = calibrated.readout, calibrated.level_scale
        obs = _reads(calibrated.observer)
        self.layers = 0 if obs is None else len(obs.core.initial_hidden(1))
        self.clocked = bool(getattr(self.step, "clock", False))  # the observer counts its steps
        self.steps_at = self.step.state_names().index("steps") if self.clocked else None
        counts = bool(self.readout.clock) or self.level_scale is not None
        self.own_count = counts and not self.clocked

    @property
    def observer(self):
        """The observer whose step this extends (what ``export_observer`` describes)."""
        return self.step.observer

    @property
    def prefilter(self):
        """The observer's readings filter, when its step runs one (else ``None``)."""
        return getattr(self.step, "prefilter", None)

    def state_names(self) -> list[str]:
        """The observer's state names after ``x``, then ``memory`` (``level``, ``clock_steps``)."""
        return [*self.step.state_names(), "memory", *(["level"] if self.level_scale else []),
                *(["clock_steps"] if self.own_count else [])]

    def extra_inputs(self) -> list[str]:
        """The inputs after ``y`` and ``u``: ``context`` for a readout that reads some."""
        return ["context"] if self.readout.context else []

    def example_inputs(self, batch: int = 1) -> tuple[torch.Tensor, ...]:
        """The initial state, zero readings (and zero context) of the right shapes and dtypes."""
        readings = self.step.example_inputs(batch)[1 + self.step.num_hidden:]
        context = next(self.readout.parameters()).new_zeros(batch, self.readout.context)
        return (*self.initial_state(batch), *readings,
                *((context,) if self.readout.context else ()))

    def initial_state(self, batch: int = 1):
        steps = (torch.zeros(batch, dtype=torch.float64),) if self.own_count else ()
        level = () if self.level_scale is None else (
            self.level_scale.initial(self.readout.initial_cholesky((batch,))),)
        return (*self.step.initial_state(batch), self.readout.initial_memory(batch), *level,
                *steps)

    def forward(self, x: torch.Tensor, *args: torch.Tensor):
        k = self.step.num_hidden  # the observer's state tensors after x, then the memory
        state, memory, args = args[:k], args[k], args[k + 1 :]
        level, args = (args[0], args[1:]) if self.level_scale is not None else (None, args)
        steps, rest = (args[0], args[1:]) if self.own_count else (None, args)
        context, rest = (rest[-1], rest[:-1]) if self.readout.context else (None, rest)
        out = self.step(x, *state, *rest)
        u = rest[1] if len(rest) > 1 else None
        z = readout_inputs(self.step.observer, self.readout.source, out[0], rest[0], u,
                           out[1 : 1 + self.layers])
        z = with_context(self.readout, z, context)
        start = steps if steps is not None else state[self.steps_at] if self.clocked else 0
        chol, memory = self.readout.cholesky(z.unsqueeze(1), memory, start)
        levels = ()
        if self.level_scale is not None:
            chol, level = self.level_scale(chol, level, start)
            levels = (level,)
        count = () if steps is None else (steps + 1,)
        return (*out, memory, *levels, *count, CovarianceReadout.covariance(chol[:, 0]))
