"""Several observers of one group run side by side; the estimate is their barycentre on the group.

Observers of one configuration trained from different seeds err differently; their average errs
less than most of them (on BROAD an ensemble of three seeds buys 0.06-0.14 deg over their mean
in cross-validation, docs/real_data.md). An :class:`EnsembleObserver` runs each member's own recursion on the same
readings (a member's estimate feeds only itself) and returns, at every step, the members'
barycentre (:meth:`groups.LieGroup.mean`): on the group, as each member's estimate is::

    members = [load_observer(run).filtered() for run in runs]   # or ResidualObservers
    ensemble = EnsembleObserver(members)
    estimates = ensemble(measurements, inputs)                 # (N, T+1, *element_shape)
    state = ensemble.init_state(batch)
    state = ensemble.step(state, y, u)                         # state.estimate: the barycentre

Members are :class:`~manifold_nets.observer.ResidualObserver` s or observers behind their
readings filter (:class:`~manifold_nets.observer.FilteredObserver`), of one group, one
measurement and input width and one state dtype; each reads the raw readings as it would alone.
Its cost is the members' together. Its exported step (:meth:`EnsembleObserver.
online_step_module`, what :func:`manifold_nets.export_observer` traces) takes every member's
state tensors in turn and returns the barycentre first.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import torch
from torch import nn

from .observer import ResidualObserver

__all__ = ["EnsembleObserver", "EnsembleState", "EnsembleStep"]


class EnsembleState(NamedTuple):
    """The online state: each member's own state, and their barycentre ``(B, *element_shape)``."""

    members: tuple
    estimate: torch.Tensor


def _estimate(state) -> torch.Tensor:
    """A member state's estimate (an ``ObserverState``'s, or a ``FilteredState``'s observer's)."""
    return state.estimate if hasattr(state, "estimate") else state.observer.estimate


class EnsembleObserver(nn.Module):
    """Members run side by side, their barycentre out; see the module docstring.

    Args:
        members: one or more :class:`ResidualObserver` or :class:`FilteredObserver` of one group,
            measurement width, input width and state dtype.
        iterations: of the barycentre (:meth:`groups.LieGroup.mean`; the default reaches
            float64's precision for members within 0.1 rad of each other).
    """

    def __init__(self, members: Sequence[nn.Module], iterations: int = 4):
        super().__init__()
        members = list(members) if isinstance(members, (list, tuple)) else members
        if not isinstance(members, list) or not members:
            raise ValueError("members must be a non-empty list of observers (ResidualObserver or "
                             "FilteredObserver), e.g. [load_observer(run).filtered() for run in runs].")
        for i, m in enumerate(members):
            # a FilteredObserver is known by its observer (filtered.py imports this module)
            if not isinstance(m, ResidualObserver) and not (
                    isinstance(m, nn.Module) and isinstance(getattr(m, "observer", None), ResidualObserver)
            ):
                raise TypeError(f"member {i} is a {type(m).__name__}; members must be "
                                f"ResidualObserver or FilteredObserver.")
        first = members[0]
        for i, m in enumerate(members[1:], 1):
            for what in ("group", "measurement_dim", "input_dim", "state_dtype"):
                if getattr(m, what) != getattr(first, what):
                    raise ValueError(
                        f"member {i}'s {what} is {getattr(m, what)!r}, member 0's "
                        f"{getattr(first, what)!r}: an ensemble's members estimate one state "
                        f"from the same readings."
                    )
        if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
            raise ValueError(f"iterations must be an int >= 1, got {iterations!r}.")
        self.members = nn.ModuleList(members)
        self.iterations = iterations

    # ------------------------------------------------------------------ the observer's description

    @property
    def group(self):
        return self.members[0].group

    @property
    def measurement_dim(self) -> int:
        return self.members[0].measurement_dim

    @property
    def input_dim(self) -> int:
        return self.members[0].input_dim

    @property
    def state_dtype(self) -> torch.dtype:
        return self.members[0].state_dtype

    @property
    def net_dtype(self) -> torch.dtype:
        return self.members[0].net_dtype

    @property
    def device(self) -> torch.device:
        return self.members[0].device

    def signature(self) -> dict[str, Any]:
        """The members' signatures, in order, and the barycentre's iterations."""
        return {"ensemble": [m.signature() for m in self.members], "iterations": self.iterations}

    def barycentre(self, estimates: Sequence[torch.Tensor]) -> torch.Tensor:
        """The members' estimates ``[(*batch, *element_shape)]`` -> their barycentre."""
        return self.group.mean(torch.stack(list(estimates)), 0, self.iterations)

    # ------------------------------------------------------------------ rollout and online step

    def init_state(self, batch: int, device=None, estimate: torch.Tensor | None = None
                   ) -> EnsembleState:
        """Every member's start (the identity, a fresh core and filter), and their barycentre;
        with ``estimate`` ``(batch, *element_shape)`` every member starts there instead (a
        measured start, e.g. TRIAD of the first reading)."""
        states = tuple(m.init_state(batch, device, estimate) for m in self.members)
        return EnsembleState(states, self.barycentre([_estimate(s) for s in states]))

    def forward(self, measurements, inputs=None, state: EnsembleState | None = None,
                return_state: bool = False):
        """The barycentre of the members' rollouts ``(N, T+1, *element_shape)`` over the readings
        ``(N, T, l)`` (and ``(N, T, m)``), each member from its state in ``state`` (default its
        start). ``return_state`` also returns the final :class:`EnsembleState`."""
        starts = [None] * len(self.members) if state is None else list(state.members)
        if len(starts) != len(self.members):
            raise ValueError(f"state holds {len(starts)} member states; the ensemble has "
                             f"{len(self.members)} members.")
        runs = [m(measurements, inputs, state=s, return_state=True)
                for m, s in zip(self.members, starts)]  # fmt: skip
        est = self.barycentre([e for e, _ in runs])
        if not return_state:
            return est
        return est, EnsembleState(tuple(f for _, f in runs), est[:, -1])

    def step(self, state: EnsembleState, y: torch.Tensor, u: torch.Tensor | None = None):
        """One online step of every member on ``y`` ``(B, l)``, ``u`` ``(B, m)``: the new
        :class:`EnsembleState` (its ``estimate`` is the members' barycentre)."""
        if len(state.members) != len(self.members):
            raise ValueError(f"state holds {len(state.members)} member states; the ensemble has "
                             f"{len(self.members)} members.")
        states = tuple(m.step(s, y, u) for m, s in zip(self.members, state.members))
        return EnsembleState(states, self.barycentre([_estimate(s) for s in states]))

    def online_step_module(self) -> EnsembleStep:
        """The exported step: every member's, then the barycentre (:class:`EnsembleStep`)."""
        return EnsembleStep(self)


class EnsembleStep(nn.Module):
    """Every member's check-free step, then the barycentre, on plain tensors:
    ``(x, *member_0_state, *member_1_state, ..., y, [u]) -> (x_next, *member_states_next)``.

    A member's state tensors are those of its own step (``(x_i, *hidden_i, *filter_state_i)``,
    :class:`~manifold_nets.deploy.OnlineStep`, :class:`~manifold_nets.observer.FilteredStep`);
    ``x`` is the barycentre ``(B, numel)``, an output only (the members never read it)."""

    def __init__(self, ensemble: EnsembleObserver):
        super().__init__()
        self._ensemble = (ensemble,)  # not a submodule: the members are reached through steps
        self.steps = nn.ModuleList(m.online_step_module() for m in ensemble.members)
        self.sizes = [1 + s.num_hidden for s in self.steps]
        self.num_hidden = sum(self.sizes)

    @property
    def observer(self) -> EnsembleObserver:
        """The ensemble (its description; its members run through :attr:`steps`)."""
        return self._ensemble[0]

    def state_names(self) -> list[str]:
        return [f"member{i}_{n}" for i, s in enumerate(self.steps) for n in ["x", *s.state_names()]]

    def initial_state(self, batch: int = 1) -> tuple[torch.Tensor, ...]:
        """``(x, *member states)`` before the first step; ``x`` the members' barycentre."""
        states = [s.initial_state(batch) for s in self.steps]
        return (self._mean([st[0] for st in states]), *[t for st in states for t in st])

    def example_inputs(self, batch: int = 1) -> tuple[torch.Tensor, ...]:
        """Arguments of the right shapes and dtypes for tracing (the initial state, zero readings
        as the first member's step takes them)."""
        readings = self.steps[0].example_inputs(batch)[self.sizes[0]:]
        return (*self.initial_state(batch), *readings)

    def _mean(self, xs: list[torch.Tensor]) -> torch.Tensor:
        obs = self.observer
        shaped = [x.view(x.shape[0], *obs.group.element_shape) for x in xs]
        return obs.barycentre(shaped).reshape(xs[0].shape[0], -1)

    def forward(self, x: torch.Tensor, *args: torch.Tensor) -> tuple[torch.Tensor, ...]:
        del x  # the barycentre is an output only
        readings = 1 + (1 if self.observer.input_dim else 0)
        if len(args) != self.num_hidden + readings:
            raise TypeError(
                f"EnsembleStep takes (x, {self.num_hidden} member state tensors "
                f"({' + '.join(map(str, self.sizes))}), y" + (", u)" if readings == 2 else ")")
                + f", got {1 + len(args)} tensors."
            )
        state, ys, out, at = args[: self.num_hidden], args[self.num_hidden :], [], 0
        for step, size in zip(self.steps, self.sizes):
            out.append(step(*state[at : at + size], *ys))
            at += size
        return (self._mean([o[0] for o in out]), *[t for o in out for t in o])
