"""A guard against lock-out: re-acquire a measured factor that the learned robust weights shut out.

A :class:`~manifold_nets.observer.measurement.RobustMeasurement` learns to give an implausible
innovation a small weight, and a learned weight function may *redescend*: the larger the
innovation, the smaller its weight. That is what rejects an outlier, and it is also how an
observer gets lost for good. Once the estimate of a measured factor drifts far enough from the
truth (a burst of outliers in the readings that drive its prediction), every measurement looks
like an outlier, gets a weight near zero, and the observer runs on its prediction alone while
the error grows. Sporadic outliers give a small weight at a few steps; a lock-out gives one at
every step.

:class:`LockOutGuard` tells the two apart by time. After each step of its observer it forms each
measured factor's innovation at the new estimate, ``nu_f = log(xhat_f^-1 m_f)``, the learned
weight that innovation gets, ``w_f(||nu_f||)``, and the average of those weights over the last
``tau`` steps (an exponential average, starting at 1)::

    a_f <- a_f + (w_f - a_f) / tau

When ``a_f`` falls below ``floor`` the factor is re-acquired: its estimate is set to the
measured element, ``xhat_f <- xhat_f exp(nu_f)`` (``m_f`` itself for a reading on the group; on
the group for a noisy embedding too), and ``a_f`` starts again at 1. The core's state and the
other factors are kept. A guard that never fires leaves the observer's estimates unchanged to
the last bit (the reset is a ``torch.where``; the eager rollout and step skip it when no factor
is lost, the exported step does not branch).

The guard runs in the rollout (:meth:`LockOutGuard.rollout`, which also returns where it reset),
in the online step (:meth:`LockOutGuard.step`; :class:`GuardedState` holds the averages) and in
the exported step (:class:`GuardedStep`, one more state tensor, ``lock_out_average``
``(B, F)``). A :class:`~manifold_nets.observer.CalibratedObserver` takes a guarded observer
like a plain one, so a covariance readout reads the guarded estimates::

    guarded = LockOutGuard(observer, tau=20.0, floor=0.1)
    run = guarded.rollout(measurements)          # run.estimates, run.resets (N, T, F)
    calibrated = CalibratedObserver(guarded, readout)
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

from .checks import check_sequences, check_start
from .measurement import RobustMeasurement
from .observer import ObserverState, ResidualObserver
from .piece import check_number
from .robust import safe_norm
from .wrapper import WrapsObserver

__all__ = ["GuardedRollout", "GuardedState", "GuardedStep", "LockOutGuard", "reacquire"]


class GuardedState(NamedTuple):
    """The online state of a :class:`LockOutGuard`: the observer's and the averaged weights
    ``(B, F)`` (one per measured factor, in the state dtype). ``estimate``, ``hidden`` and
    ``steps`` are the observer's."""

    observer: ObserverState
    average: torch.Tensor

    @property
    def estimate(self) -> torch.Tensor:
        return self.observer.estimate

    @property
    def hidden(self):
        return self.observer.hidden

    @property
    def steps(self) -> int:
        return self.observer.steps


class GuardedRollout(NamedTuple):
    """A guarded rollout: the estimates ``(N, T+1, *element_shape)``, the final
    :class:`GuardedState`, the core's states kept (or ``None``) and ``resets`` ``(N, T, F)``
    (bool): where a factor was re-acquired, after step ``k`` (the estimate ``k + 1``)."""

    estimates: torch.Tensor
    final: GuardedState
    hidden: tuple | None
    resets: torch.Tensor


def reacquire(observer: ResidualObserver, tau: float, floor: float, x: torch.Tensor, measured,
              average: torch.Tensor, branch: bool = True):
    """The guard's check after one step of ``observer``: ``x`` ``(B, numel)`` the new estimates
    (state dtype), ``measured`` the measured elements of the step's ``y``, ``average`` ``(B, F)``.
    Returns ``(x, average, lost)``: the estimates with each lost factor set to its measurement
    (``xhat_f exp(nu_f)``, on the group), the new averages, and ``lost`` ``(B, F)`` (bool). One
    computation for the rollout, the online and the exported step; ``branch`` (eager only, not
    the traced step) returns ``x`` itself at once when no factor is lost, the same values without
    forming the re-acquired elements."""
    m = observer.measurement
    nu = m.innovations(x, measured)
    norms = torch.stack([safe_norm(n) for n in nu], dim=-1)
    w = m.robust(norms.to(observer.net_dtype)).to(average.dtype)
    average = average + (w - average) / tau
    lost = average < floor
    if branch and not bool(lost.any()):
        return x, average, lost
    new = x.clone()
    for j, ((f, xs, _), n) in enumerate(zip(m.spans, nu)):
        # xhat_f exp(nu_f): the measured element, on the group even when the reading is not
        # quite (a noisy embedding), as the robust measurement forms it
        at = f.rplus(x[:, xs].unflatten(-1, f.element_shape), n).reshape(x.shape[0], -1)
        new[:, xs] = torch.where(lost[:, j : j + 1], at.to(x.dtype), x[:, xs])
    return new, torch.where(lost, torch.ones_like(average), average), lost


class LockOutGuard(WrapsObserver):
    """An observer with a robust measurement, guarded against lock-out; see the module docstring.

    Args:
        observer: a :class:`ResidualObserver` whose measurement is a
            :class:`~manifold_nets.observer.measurement.RobustMeasurement`.
        tau: the time constant of the averaged weights, in steps (>= 1).
        floor: the average below which a factor is re-acquired (> 0).
    """

    def __init__(self, observer: ResidualObserver, tau: float = 20.0, floor: float = 0.1):
        super().__init__()
        if not isinstance(observer, ResidualObserver):
            raise TypeError(f"LockOutGuard guards a ResidualObserver, got {type(observer).__name__}.")
        if not isinstance(observer.measurement, RobustMeasurement):
            raise ValueError(
                "LockOutGuard reads the learned robust weights of the observer's measured factors, "
                f"but its measurement is a plain {type(observer.measurement).__name__}: a plain "
                "measurement weighs every innovation by 1 and cannot lock out. Guard an observer "
                "trained with model.measurement={type: robust, ...}."
            )
        self.observer = observer
        self.tau, self.floor = self.check_settings(tau, floor)

    @staticmethod
    def check_settings(tau: object = 20.0, floor: object = 0.1) -> tuple[float, float]:
        """``(tau, floor)`` as floats; a ``ValueError`` naming the one that is not a number in
        its range (``tau`` in ``[1, 1e12]`` steps, ``floor`` in ``[1e-12, 1e12]``: above 0)."""
        return (check_number("LockOutGuard: tau", tau, 1.0, 1e12),
                check_number("LockOutGuard: floor", floor, 1e-12, 1e12))

    # ------------------------------------------------------------------ the observer's description
    # (group, widths, dtypes, device: the observer's, WrapsObserver)

    @property
    def factors(self) -> list[str]:
        """The measured factors, in the order of the averages' last dimension."""
        return list(self.observer.measurement.factors)

    def settings(self) -> dict:
        return {"tau": self.tau, "floor": self.floor}

    def signature(self) -> dict:
        """The observer's signature with the guard's settings under ``lock_out``."""
        return {**self.observer.signature(), "lock_out": self.settings()}

    def extra_repr(self) -> str:
        return f"tau={self.tau:g}, floor={self.floor:g}"

    # ------------------------------------------------------------------ the guard

    def guard(self, x: torch.Tensor, measured, average: torch.Tensor):
        """:func:`reacquire` with this guard's observer and settings."""
        return reacquire(self.observer, self.tau, self.floor, x, measured, average)

    # ------------------------------------------------------------------ rollout and online step

    def init_state(self, batch: int, device=None, estimate: torch.Tensor | None = None
                   ) -> GuardedState:
        """The observer's start (``estimate``: a measured one) and averages of 1."""
        start = self.observer.init_state(batch, device, estimate)
        ones = torch.ones(batch, len(self.factors), dtype=self.state_dtype,
                          device=start.estimate.device)
        return GuardedState(start, ones)

    def _start(self, state, n: int, device) -> GuardedState:
        if state is None:
            return self.init_state(n, device)
        if not isinstance(state, GuardedState):
            raise TypeError(f"state must be a GuardedState (LockOutGuard.init_state), got "
                            f"{type(state).__name__}.")
        want = (n, len(self.factors))
        if tuple(state.average.shape) != want:
            raise ValueError(f"state.average has shape {tuple(state.average.shape)}, expected "
                             f"{want} (a sequence by the measured factors {self.factors}).")
        check_start(self.observer, state.observer, n)
        return state

    def rollout(self, measurements, inputs=None, state: GuardedState | None = None,
                keep_hidden: bool = False) -> GuardedRollout:
        """The guarded rollout over ``(N, T, l)`` (and ``(N, T, m)``) from ``state`` (default the
        observer's start); ``keep_hidden`` also keeps the core's state after every step."""
        obs = self.observer
        yu, ys = check_sequences(obs, measurements, inputs)  # (T, N, l + m)
        n, steps = yu.shape[1], yu.shape[0]
        state = self._start(state, n, yu.device)
        x = state.estimate.reshape(n, obs.update.numel).to(obs.state_dtype)
        hidden, average = state.hidden, state.average.to(obs.state_dtype)
        measured = list(zip(*(m.unbind(0) for m in obs.measurement.elements(ys))))
        xs, hs, lost = [x], [hidden], []
        per_step = zip(yu.unbind(0), ys.unbind(0), measured, obs.schedule(state.steps, steps))
        for yu_k, ys_k, m_k, t_k in per_step:
            x, hidden = obs.step_unchecked(x, hidden, yu_k, ys_k, m_k, t_k)
            x, average, lost_k = self.guard(x, m_k, average)
            xs.append(x)
            lost.append(lost_k)
            if keep_hidden:
                hs.append(hidden)
        est = torch.stack(xs, dim=1).unflatten(-1, obs.group.element_shape)
        final = GuardedState(ObserverState(est[:, -1], hidden, state.steps + steps), average)
        kept = tuple(torch.stack(h, dim=1) for h in zip(*hs)) if keep_hidden else None
        return GuardedRollout(est, final, kept, torch.stack(lost, dim=1))

    def forward(self, measurements, inputs=None, state: GuardedState | None = None,
                return_state: bool = False):
        """The guarded estimates ``(N, T+1, *element_shape)`` (and the final state)."""
        run = self.rollout(measurements, inputs, state)
        return (run.estimates, run.final) if return_state else run.estimates

    def step(self, state: GuardedState, y: torch.Tensor, u: torch.Tensor | None = None
             ) -> GuardedState:
        """One online step: the observer's, then the guard's check of ``y`` ``(B, l)``."""
        obs = self.observer
        new = obs.step(state.observer, y, u)
        b = new.estimate.shape[0]
        measured = obs.measurement.elements(y.reshape(b, -1).to(obs.state_dtype))
        x, average, _ = self.guard(new.estimate.reshape(b, -1), measured,
                                   state.average.to(obs.state_dtype))
        estimate = x.view(b, *obs.group.element_shape)
        return GuardedState(ObserverState(estimate, new.hidden, new.steps), average)

    def online_step_module(self) -> GuardedStep:
        """The exported step with the averages as one more state tensor (:class:`GuardedStep`)."""
        return GuardedStep(self)


class GuardedStep(nn.Module):
    """:class:`manifold_nets.deploy.OnlineStep`, then the guard:
    ``(x, *state, lock_out_average, y[, u]) -> (x_next, *state_next, lock_out_average_next)``.
    Each module sits at one place in it (``step.observer``; see
    :class:`~manifold_nets.observer.calibrated.CalibratedStep`)."""

    def __init__(self, guarded: LockOutGuard):
        super().__init__()
        self.step = guarded.observer.online_step_module()
        self.tau, self.floor = guarded.tau, guarded.floor
        self.clock = self.step.clock
        self.num_hidden = self.step.num_hidden + 1

    @property
    def observer(self) -> ResidualObserver:
        """The observer (reached through :attr:`step`, not a second submodule)."""
        return self.step.observer

    def lock_out(self) -> dict:
        """The guard's settings (what the exported step's description records)."""
        return {"tau": self.tau, "floor": self.floor}

    def state_names(self) -> list[str]:
        return [*self.step.state_names(), "lock_out_average"]

    def initial_state(self, batch: int = 1) -> tuple[torch.Tensor, ...]:
        obs = self.observer
        ones = torch.ones(batch, len(obs.measurement.factors), dtype=obs.state_dtype,
                          device=obs.device)
        return (*self.step.initial_state(batch), ones)

    def example_inputs(self, batch: int = 1) -> tuple[torch.Tensor, ...]:
        readings = self.step.example_inputs(batch)[1 + self.step.num_hidden :]
        return (*self.initial_state(batch), *readings)

    def forward(self, x: torch.Tensor, *args: torch.Tensor) -> tuple[torch.Tensor, ...]:
        k = self.step.num_hidden
        state, average, rest = args[:k], args[k], args[k + 1 :]
        out = self.step(x, *state, *rest)
        obs = self.observer
        measured = obs.measurement.elements(rest[0].to(obs.state_dtype))
        x, average, _ = reacquire(obs, self.tau, self.floor, out[0], measured,
                                  average.to(obs.state_dtype), branch=False)
        return (x, *out[1:], average)
