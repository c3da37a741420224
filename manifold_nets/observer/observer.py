"""The residual-on-algebra observer (the paper's Section 2 and Algorithm 1), made of pieces.

Per step ``k`` (``y = y_{k+1}``, ``u = u_k``)::

    x^-     = prior(x_k, y, u)                   none (the paper), the system's model, kinematic
    z       = cat(f(view) for f in features)     embedding, readings, innovation, ...
    v, h    = head(core, z, h, k)                plain T(z), centred, gain
    v       = scale(v, k) for scale in scales    output scale, step decay
    x_{k+1} = update(x^-, v)                     per factor: x·exp(v), absolute, left

starting from the identity, so the estimate never leaves the group. Each piece is a small module
(:mod:`~manifold_nets.observer.priors`, :mod:`.features`, :mod:`.heads`, :mod:`.scales`,
:mod:`.measurement`, :mod:`.update`); the loop never asks which are there. The rollout
(:meth:`ResidualObserver.forward`), the online step (:meth:`ResidualObserver.step`) and the
exported step (:class:`manifold_nets.deploy.OnlineStep`) run the same :meth:`ResidualObserver.
step_unchecked` with the same schedule (:meth:`ResidualObserver.schedule`); a training rollout
of the paper's step runs its operations fused across steps (:func:`.fused.lean_steps`).

Shapes: measurements ``(N, T, l)`` with ``measurements[:, k] = y_{k+1}``, inputs ``(N, T, m)``
(``None`` when ``m == 0``); the rollout returns ``(N, T+1, *group.element_shape)``,
``xhat_0 .. xhat_T``. The state has its own dtype (``GroupUpdate.state_dtype``, float64 by
default), the network its parameters' (float32 by default): the network reads its features in
its dtype and ``v`` is cast to the state dtype before the update. Inputs are checked once,
before the loop (:mod:`~manifold_nets.observer.checks`); nothing inside it is.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import nn

from groups import LieGroup

from ..cores import GRUCore, Hidden, RecurrentCore
from .checks import check_sequences, check_start, check_step_args
from .compiling import compiled
from .features import Embedding, Feature, Readings, reads_as_one
from .fused import lean_steps, runs_lean
from .heads import Head, PlainHead
from .measurement import Measurement
from .priors import NoPrior, Prior
from .scales import StepScale
from .update import GroupUpdate

__all__ = ["ObserverState", "ResidualObserver", "Rollout"]


class ObserverState(NamedTuple):
    """The online state: the estimate ``(B, *element_shape)``, the core's hidden state and the
    steps taken from the start (the clock of the schedules; one count for the batch)."""

    estimate: torch.Tensor
    hidden: Hidden
    steps: int = 0


class Rollout(NamedTuple):
    """A rollout: the estimates ``(N, T+1, *element_shape)``, the final state, and (when kept)
    the core's state after every step, each hidden tensor ``(N, T+1, ...)`` from the start's."""

    estimates: torch.Tensor
    final: ObserverState
    hidden: Hidden | None = None


class ResidualObserver(nn.Module):
    """The paper's observer on ``group``, with pieces; see the module docstring.

    Args:
        group: the state's group (any :class:`groups.LieGroup`).
        measurement: a :class:`~manifold_nets.observer.measurement.Measurement` (sizes of ``y``
            and ``u``, the factors ``y`` measures), or the size of ``y`` (no input, none measured).
        core: a :class:`~manifold_nets.cores.RecurrentCore` from the features' width to the
            head's output size, or a factory ``(input_size, output_size) -> core`` (e.g.
            ``functools.partial(GRUCore, hidden_size=128)``); default a 512 x 2
            :class:`~manifold_nets.cores.GRUCore` (the paper's). A core made here starts where
            the head says (:meth:`~manifold_nets.observer.heads.Head.reset`).
        update: a :class:`~manifold_nets.observer.update.GroupUpdate` (per-factor rules, the
            state dtype); default residual everywhere, float64.
        prior: a :class:`~manifold_nets.observer.priors.Prior`; default none (the paper's).
        features: :class:`~manifold_nets.observer.features.Feature` s, read in this order;
            default the paper's ``[Embedding(), Readings()]``.
        head: a :class:`~manifold_nets.observer.heads.Head`; default the plain head.
        scales: :class:`~manifold_nets.observer.scales.StepScale` s, applied in this order.
    """

    def __init__(
        self,
        group: LieGroup,
        measurement: Measurement | int,
        core: RecurrentCore | None = None,
        *,
        update: GroupUpdate | None = None,
        prior: Prior | None = None,
        features: Sequence[Feature] | None = None,
        head: Head | None = None,
        scales: Sequence[StepScale] = (),
    ):
        super().__init__()
        if not isinstance(group, LieGroup):
            raise TypeError(f"group must be a groups.LieGroup, got {type(group).__name__}.")
        if not isinstance(measurement, Measurement):
            measurement = Measurement(measurement)
        prior = NoPrior() if prior is None else prior
        head = PlainHead() if head is None else head
        features = [Embedding(), Readings()] if features is None else list(features)
        for kind, piece, cls in [
            ("measurement", measurement, Measurement), ("prior", prior, Prior), ("head", head, Head),
            *[("feature", f, Feature) for f in features], *[("scale", s, StepScale) for s in scales],
        ]:
            if not isinstance(piece, cls):
                raise TypeError(
                    f"{kind} must be a {cls.__name__} piece (manifold_nets.observer), got "
                    f"{type(piece).__name__}."
                )
        self.group = group
        self.measurement = measurement.bind(group)
        self.update = (GroupUpdate() if update is None else update).bind(group)
        self.prior = prior.bind(group, self.measurement)
        self.features = nn.ModuleList([f.bind(group, self.measurement) for f in features])
        self.head = head.bind(group, self.measurement)
        self.scales = nn.ModuleList([s.bind(group, self.measurement) for s in scales])
        if self.head.needs_prediction and not self.prior.predicts:
            raise ValueError(
                f"the {self.head.name} head subtracts the core's output at the measurement the "
                "prediction expects, but the observer has no prior: then that output is the "
                "motion itself, and centring takes it away. Give a prior (the system's, a "
                "kinematic one) or use the plain head."
            )
        self.core = self._core(core)
        self._view = self.measurement.deferred_view if reads_as_one(self) else self.measurement.view
        self._timed, self._compiled_step = [self.head, *self.scales], None

    def _core(self, core: RecurrentCore | None) -> RecurrentCore:
        width = sum(f.width for f in self.features)
        out = self.head.output_size(self.group.tangent_dim, self.measurement.innovation_dim)
        if core is None or (callable(core) and not isinstance(core, nn.Module)):
            core = (GRUCore if core is None else core)(width, out)  # a core made here starts
            self.head.reset(core)  # where the head says (an untrained observer holds still)
        if not isinstance(core, RecurrentCore):
            raise TypeError(f"core must be a RecurrentCore, got {type(core).__name__}.")
        if core.input_size != width or core.output_size != out:
            parts = " + ".join(f"{f.name} {f.width}" for f in self.features)
            raise ValueError(
                f"core maps {core.input_size} -> {core.output_size}, but the observer needs "
                f"{width} ({parts}) -> {out} (the {self.head.name} head's output)."
            )
        return core

    # ------------------------------------------------------------------ description

    @property
    def measurement_dim(self) -> int:
        return self.measurement.dim

    @property
    def input_dim(self) -> int:
        return self.measurement.input_dim

    @property
    def state_dtype(self) -> torch.dtype:
        return self.update.state_dtype

    @property
    def net_dtype(self) -> torch.dtype:
        return next(self.core.parameters()).dtype

    @property
    def device(self) -> torch.device:
        return next(self.core.parameters()).device

    def pieces(self) -> dict[str, nn.Module]:
        """Every piece by its place: ``measurement``, ``prior``, ``features.<i>``, ``head``,
        ``scales.<i>``."""
        out = {"measurement": self.measurement, "prior": self.prior, "head": self.head}
        out.update({f"features.{i}": f for i, f in enumerate(self.features)})
        out.update({f"scales.{i}": s for i, s in enumerate(self.scales)})
        return out

    def signature(self) -> dict:
        """What a checkpoint must match to load into this observer (JSON-able)."""
        return {
            "group": repr(self.group),
            "update": self.update.signature(),
            "measurement": self.measurement.signature(),
            "prior": self.prior.signature(),
            "features": [f.signature() for f in self.features],
            "head": self.head.signature(),
            "scales": [s.signature() for s in self.scales],
            "core": self.core.signature(),
        }

    def extra_repr(self) -> str:
        return f"group={self.group!r}, update={list(self.update.rules)}"

    # ------------------------------------------------------------------ the loop

    def schedule_at(self, k: torch.Tensor) -> list[torch.Tensor | None]:
        """The timed pieces' values (the head's, then each scale's) at the step counts ``k``
        (float64, any shape), computed in float64 and cast to the network dtype; ``None`` for a
        piece without a schedule. The one schedule computation of every code path."""
        values = [piece.schedule(k) for piece in self._timed]
        return [s if s is None else s.to(device=self.device, dtype=self.net_dtype) for s in values]

    def schedule(self, k0: int, count: int) -> list[tuple]:
        """:meth:`schedule_at` for the ``count`` steps from ``x_{k0}`` on, one tuple per step."""
        k = torch.arange(k0, k0 + count, dtype=torch.float64)
        values = self.schedule_at(k)
        return list(zip(*([None] * count if v is None else v.unbind(0) for v in values)))

    @property
    def uses_step_count(self) -> bool:
        """Whether a piece depends on the step count (the exported step then carries it)."""
        return any(v is not None for v in self.schedule_at(torch.zeros(1, dtype=torch.float64)))

    def step_unchecked(self, x, hidden, yu, ys, measured, timed):
        """One step on checked tensors: ``x`` ``(B, numel)`` state dtype, ``yu`` ``(B, l + m)``
        network dtype, ``ys`` the same in the state dtype, ``measured`` the measured elements,
        ``timed`` the step's :meth:`schedule` entry. Returns ``(x_{k+1}, hidden)``."""
        x = self.prior(x, yu, ys)
        view = self._view(x, yu, measured)  # (measurement.view, or deferred: features.reads_as_one)
        v, hidden = self.head(self.core, self._features, view, hidden, timed[0])
        for scale, d in zip(self.scales, timed[1:]):
            v = scale(v, d)
        return self.update(x, v), hidden  # the update casts v to the state dtype

    def _features(self, view) -> torch.Tensor:
        return view.cat_features(self.features)  # cat(f(view) for f in self.features)

    def init_state(self, batch: int, device=None, estimate=None) -> ObserverState:
        """The start: the identity (or ``estimate``, measured) and the core's initial state."""
        if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
            raise ValueError(f"batch must be a positive integer, got {batch!r}.")
        device = self.device if device is None else device
        x = self.group.identity((batch,), dtype=self.state_dtype, device=device) if estimate is None \
            else estimate.to(device=device, dtype=self.state_dtype)  # fmt: skip
        return ObserverState(x, self.core.initial_hidden(batch, device=device))

    def step(self, state: ObserverState, y: torch.Tensor, u: torch.Tensor | None = None):
        """One online step: ``y`` ``(B, l)`` is ``y_{k+1}``, ``u`` ``(B, m)`` is ``u_k``.
        Returns the new :class:`ObserverState`; its ``estimate`` is ``xhat_{k+1}``."""
        yu, ys = check_step_args(self, state, y, u)
        x = state.estimate.reshape(yu.shape[0], self.update.numel).to(self.state_dtype)
        x, hidden = self.step_unchecked(
            x, state.hidden, yu, ys, self.measurement.elements(ys), self.schedule(state.steps, 1)[0]
        )
        return ObserverState(x.view(x.shape[0], *self.group.element_shape), hidden, state.steps + 1)

    def forward(self, measurements, inputs=None, state: ObserverState | None = None,
                return_state: bool = False):
        """Rolls the observer over whole sequences (module docstring for the shapes); ``state``
        where to start (default the identity), ``return_state`` also returns the final state."""
        run = self.rollout(measurements, inputs, state)
        return (run.estimates, run.final) if return_state else run.estimates

    def _steps(self, x, hidden, inputs, keep_hidden: bool):
        """The rollout's loop over ``inputs`` (``(yu, ys, measured, timed)`` per step): the
        estimates ``x_0 .. x_T``, the hidden states kept and the last."""
        compiled = self._compiled_step is not None and torch.is_grad_enabled()
        step, xs, hs = self._compiled_step if compiled else self.step_unchecked, [x], [hidden]
        for yu_k, ys_k, m_k, t_k in inputs:
            x, hidden = step(x, hidden, yu_k, ys_k, m_k, t_k)
            xs.append(x)
            if keep_hidden:
                hs.append(hidden)
        return xs, hs, hidden

    def rollout(self, measurements, inputs=None, state: ObserverState | None = None,
                keep_hidden: bool = False) -> Rollout:
        """:meth:`forward`'s rollout as a :class:`Rollout`; ``keep_hidden`` also keeps the
        core's state after every step (what a covariance readout reads)."""
        yu, ys = check_sequences(self, measurements, inputs)  # (T, N, l + m)
        n, steps = yu.shape[1], yu.shape[0]
        state = self.init_state(n, device=yu.device) if state is None else check_start(self, state, n)
        x, hidden = state.estimate.reshape(n, self.update.numel).to(self.state_dtype), state.hidden
        measured = list(zip(*(m.unbind(0) for m in self.measurement.elements(ys)))) or [()] * steps
        # unbind: one backward node for all the steps' slices (indexing would add one per step)
        per_step = zip(yu.unbind(0), ys.unbind(0), measured, self.schedule(state.steps, steps))
        loop = lean_steps if runs_lean(self) else ResidualObserver._steps  # (.fused)
        xs, hs, hidden = loop(self, x, hidden, per_step, keep_hidden)
        est = torch.stack(xs, dim=1).unflatten(-1, self.group.element_shape)
        final = ObserverState(xs[-1].view(n, *est.shape[2:]), hidden, state.steps + steps)
        kept = tuple(torch.stack(h, dim=1) for h in zip(*hs)) if keep_hidden else None
        return Rollout(est, final, kept)

    def compile_step(self, **options) -> ResidualObserver:
        """Compiles the step with ``torch.compile`` for rollouts that record gradients (training);
        ``options`` go to ``torch.compile`` (default ``dynamic=False``). Returns ``self``."""
        self._compiled_step = compiled(self.step_unchecked, **options)  # (.compiling)
        return self

    def online_step_module(self) -> nn.Module:
        """The online step as a check-free module for ``torch.export`` (:class:`~manifold_nets.
        deploy.OnlineStep`; parameters shared)."""
        from ..deploy import OnlineStep

        return OnlineStep(self)
