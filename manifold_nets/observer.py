"""The residual-on-algebra observer (the paper's Section 2 and Algorithm 1), generic over any group.

Per step ``k`` a recurrent *core* reads ``(embed(xhat_k), y_{k+1}, u_k)`` and outputs a tangent
vector ``v_k`` (``group.tangent_dim``); the estimate moves by a group update, so it never leaves
the group::

    xhat_0     = e                          (the identity)
    v_k        = T(embed(xhat_k), y_{k+1}, u_k)
    xhat_{k+1} = xhat_k · exp(v_k)          ("residual", the paper's update)

The update is chosen per factor (``group.factor_names``; a non-product group is its one factor
``x``), as ``update={name: rule}``:

* ``"residual"``: ``x_f <- x_f · exp(v_f)`` (``rplus``; for ``R^n`` this is ``x_f + v_f``);
* ``"absolute"``: ``x_f <- exp(v_f)``, the factor is set to the prediction (for ``R^n`` this is
  ``x_f = v_f``: the paper's biases ``b = gamma``);
* ``"left"``: ``x_f <- exp(v_f) · x_f``, a correction in the world frame (an extension; for
  ``R^n`` the same as ``residual``). With world-frame inputs (``ObserverInputs.rotated``) the
  correction the core must output is then linear in what it reads.

With a kinematic prior (``ObserverInputs.propagate``) the named factors first move by their
measured velocity, ``x_f^- = x_f · exp(dt · u_f)``, and the core reads and corrects that
prediction: ``xhat_{k+1} = xhat_k^- · exp(v_k)`` (or ``exp(v_k) · xhat_k^-`` for ``left``).
A *model prior* (``prior``, e.g. a system's :meth:`~manifold_nets.system.System.predict`) does the
same with the whole nominal model, ``xhat_k^- = prior(xhat_k, y_{k+1}, u_k)`` (for the rigid body
the step with the bias-corrected readings): the core then learns what a filter's update adds to
the model's prediction, not the prediction. With ``prior_drive`` (a system's
:meth:`~manifold_nets.system.System.compensated_drive`, and ``inputs.prior_drive`` its width) the
core also reads the drive that prediction integrated, so a reading the motion cannot produce (an
outlier) is a plain input.

*Learned robust weights* (:class:`~manifold_nets.robust.RobustWeights`, M-estimator weight
functions learned per channel, the identity when new) pull implausible values in before they
move anything. ``robust_drive``: the prior steps with the drive ``d_i <- w_i(|d_i|) d_i``,
component by component (``prior_step(x, d)``, a system's ``step``, with ``prior_drive`` the
drive; the prior must be ``prior_step(x, prior_drive(x, y, u))``, as the default
:meth:`~manifold_nets.system.System.predict` is). ``robust_innovation``: each innovation factor's
innovation ``nu_f <- w_f(||nu_f||) nu_f``, and the measurement the core reads with it,
``m_f <- xhat_f^- exp(nu_f)``. The core reads the drive as it was given (``inputs.prior_drive``).

A *gain head* (``gain=True``, needs innovation inputs) makes the core's output a Kalman-type
update: the core outputs an offset ``a_k`` and a gain matrix ``K_k`` (``tangent_dim`` x the
innovation's width) and ``v_k = a_k + K_k nu_k`` with ``nu_k`` the innovation it reads
(``ObserverInputs.innovation``). What a filter does with the innovation (a gain that shrinks as
the estimate converges; a bias corrected in proportion to the attitude innovation) is then
linear in what the core computes, where a plain head must produce ``K nu`` through its
nonlinearities.

A *centred* update (``centering=c``, ``0 < c <= 1``, needs innovation inputs and a prediction:
a ``prior`` or ``inputs.propagate``) subtracts what the core would output had the measurement been
exactly the prediction::

    v_k = T(z_k) - c T(z_k^0)

``z_k^0`` is ``z_k`` with each innovation factor's measured columns replaced by the embedding of
its prediction and its innovation by zero; both read the same hidden state, and the hidden
state moves on with ``z_k``. At ``c = 1`` a zero innovation moves nothing but the prior, as in
every filter's update: with exact readings the truth is a fixed point whatever the network
remembers. A ``c`` below 1 keeps part of the offset a trained observer relies on (its weights
load unchanged at any ``c``). The core runs on twice the batch. ``centering_ramp=K`` raises
``c`` linearly over the first ``K`` steps (``c_k = c min(1, k / K)``), so the start-up stays
uncentred; :attr:`ObserverState.steps` counts the steps (the same count drives the clock inputs,
``ObserverInputs.clock``: the core reads ``tau / (tau + k)``). ``centering_factors={name: c_f}``
sets another ``c`` for some factors (their tangent components), ramped alike: on the rigid body a
bias left 15 % uncentred keeps a floor under its error, where the attitude needs the offset.

``step_decay={name: K_f}`` scales those factors' tangent components of ``v_k`` by
``d_k = min(1, K_f / k)``: after ``K_f`` steps their step size falls like ``1 / k``, as a Kalman
filter's gain on a constant does (a stochastic-approximation step size). It is meant for factors
that the system keeps constant or nearly so, such as the rigid body's biases, whose error then
keeps falling where a constant learned gain settles at a floor. The same step count drives it.

Shapes: measurements ``(N, T, measurement_dim)`` with ``measurements[:, k] = y_{k+1}``, inputs
``(N, T, input_dim)`` with ``inputs[:, k] = u_k`` (``None`` when ``input_dim == 0``); the rollout
returns the estimates ``(N, T+1, *group.element_shape)``, ``xhat_0 .. xhat_T``.

The group state has its own dtype (``state_dtype``, float64 by default), separate from the
network's (its parameters' dtype, float32 by default): the network reads ``embed(xhat)`` cast
to its dtype and its output is cast to the state dtype before the update, so the estimate stays
on the group to the rounding of the state dtype.

The rollout is the hot loop of training, evaluation and online use: inputs are checked once
before the loop; inside it each step is the core's step, the group update on precomputed factor
slices (consecutive ``R^n`` factors with the same rule merged into one) and no validation.

What the core reads besides ``(embed(xhat), y, u)`` (innovation terms, relative-only factors) is
an :class:`~manifold_nets.inputs.ObserverInputs`; the core is any
:class:`~manifold_nets.cores.RecurrentCore` (default the paper's :class:`~manifold_nets.cores.GRUCore`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import nn

from groups import Euclidean, LieGroup

from .cores import GRUCore, Hidden, RecurrentCore
from .inputs import ObserverInputs
from .robust import RobustWeights, safe_norm

__all__ = ["UPDATE_RULES", "ObserverState", "ResidualObserver", "core_output_size"]

#: The per-factor update rules.
UPDATE_RULES = ("residual", "absolute", "left")


# ---------------------------------------------------------------------- the group update


@dataclass(frozen=True)
class _Block:
    """One run of the flat state updated the same way (a factor, or merged ``R^n`` factors)."""

    factor: LieGroup | None  # None: a merged run of R^n factors
    element: slice  # in the flat element
    tangent: slice
    rule: str


def _parse_rules(group: LieGroup, update: Mapping[str, str] | None) -> tuple[str, ...]:
    """One rule per factor from ``{factor name: rule}``; factors not named are ``residual``."""
    names = group.factor_names
    update = dict(update or {})
    unknown = [k for k in update if k not in names]
    if unknown:
        raise ValueError(
            f"update names factors {unknown} that {group!r} does not have; its factors are "
            f"{list(names)}."
        )
    rules = tuple(update.get(name, "residual") for name in names)
    for name, rule in zip(names, rules):
        if rule not in UPDATE_RULES:
            raise ValueError(
                f"update rule {rule!r} for factor {name!r} is not one of {UPDATE_RULES} "
                "(residual: x·exp(v); absolute: x = exp(v), for R^n x = v; left: exp(v)·x)."
            )
    return rules


def _blocks(group: LieGroup, rules: tuple[str, ...]) -> list[_Block]:
    blocks: list[_Block] = []
    el = tan = 0
    for f, rule in zip(group.factors, rules):
        numel, tdim = math.prod(f.element_shape), f.tangent_dim
        vector = isinstance(f, Euclidean)
        prev = blocks[-1] if blocks else None
        if vector and prev is not None and prev.factor is None and prev.rule == rule:
            blocks[-1] = _Block(
                None,
                slice(prev.element.start, el + numel),
                slice(prev.tangent.start, tan + tdim),
                rule,
            )
        else:
            blocks.append(
                _Block(None if vector else f, slice(el, el + numel), slice(tan, tan + tdim), rule)
            )
        el += numel
        tan += tdim
    return blocks


def core_output_size(
    group: LieGroup, inputs: ObserverInputs, gain: bool = False, offset: bool = True
) -> int:
    """How many numbers the core outputs per step: ``group.tangent_dim``, or with the gain head
    ``tangent_dim * (1 + innovation width)`` (the offset ``a``, then ``K`` row by row), without
    the offset ``tangent_dim * innovation width``."""
    n = group.tangent_dim
    return n * (int(offset) + inputs.innovation_dim(group)) if gain else n


# ---------------------------------------------------------------------- the observer


def _check_factor(group: LieGroup, name: str, what: str) -> None:
    """Raises ``ValueError`` unless ``group`` has a factor ``name`` (``what`` names the setting)."""
    if name not in group.factor_names:
        raise ValueError(
            f"{what} names a factor {name!r} that {group!r} does not have; "
            f"its factors are {list(group.factor_names)}."
        )


def _check_output_scale(output_scale: float) -> float:
    if (
        isinstance(output_scale, bool) or not isinstance(output_scale, (int, float))
        or not 0 < output_scale < math.inf
    ):
        raise ValueError(
            f"ResidualObserver: output_scale must be a positive number, got {output_scale!r}."
        )
    return float(output_scale)


class ObserverState(NamedTuple):
    """The online state: the estimate ``(B, *element_shape)``, the core's hidden state, and the
    number of steps taken from the start (the clock of the centring ramp, ``centering_ramp``,
    and of the clock inputs, ``ObserverInputs.clock``; one count for the whole batch)."""

    estimate: torch.Tensor
    hidden: Hidden
    steps: int = 0


class ResidualObserver(nn.Module):
    """The paper's observer on ``group``; see the module docstring.

    Args:
        group: the state's group (any :class:`groups.LieGroup`).
        measurement_dim: size ``l`` of a measurement ``y``.
        input_dim: size ``m`` of an input ``u`` (0: no input).
        core: a :class:`~manifold_nets.cores.RecurrentCore` mapping
            ``inputs.core_input_size(group, l, m)`` (``embedding_dim + l + m`` for the paper's
            inputs) to ``tangent_dim``; default a :class:`~manifold_nets.cores.GRUCore` of
            ``hidden_size`` x ``num_layers`` (512 x 2, the paper's).
        update: ``{factor name: "residual" | "absolute"}``; factors not named are residual.
        inputs: what the core reads besides the paper's inputs
            (:class:`~manifold_nets.inputs.ObserverInputs`; default none).
        state_dtype: dtype of the group state (float64 default); the network keeps its own.
        output_scale: the core's output times this is the tangent vector ``v`` (default 1). For
            corrections much smaller than 1 (a correction of 1e-3 rad per step of a 35 Hz
            filter), a small scale keeps the optimiser's steps on the weights in proportion.
        hidden_size, num_layers: sizes of the default GRU core (only without ``core``).
        prior: the model prior, ``prior(x (B, *element_shape), y (B, l), u (B, m) | None) -> x^-``
            in the state dtype (a system's ``predict``; differentiable in ``x``); ``None``: none.
            A checkpoint's signature records that there is one (``prior_name``), not what it is.
        prior_name: what the signature calls the prior (default ``"system"``: ``System.predict``).
        prior_drive: with ``inputs.prior_drive`` (its width), the drive the prior integrates,
            ``prior_drive(x, y, u) -> (B, inputs.prior_drive)`` in the state dtype (a system's
            ``compensated_drive``), which the core also reads, last; ``None``: none.
        gain: the gain head: the core outputs ``(a, K)``, ``tangent_dim * (1 + innovation
            width)`` numbers, and ``v = a + K nu`` (see the module docstring; needs
            ``inputs.innovation``). :func:`core_output_size` says how wide the core's output is.
        offset: with the gain head, ``False`` drops the offset: ``v = K nu``, so a zero
            innovation moves nothing but the prior (the truth, measured exactly, is a fixed
            point).
            With a :class:`~manifold_nets.cores.GRUCore` the head's rows of ``K`` start at zero;
            a core of your own should start its ``K`` small too.
        centering: ``c`` in ``[0, 1]``: ``v = T(z) - c T(z^0)``, the core's output less ``c``
            times what it outputs when each innovation factor is measured exactly where it is
            predicted (see the module docstring; needs ``inputs.innovation``; default 0, none).
            It adds no weight: ``train.init_from`` starts it from any other ``c``.
        centering_ramp: ``K``, an integer >= 0: the centring ramps in over the first ``K`` steps,
            ``c_k = c min(1, k / K)`` at the step from ``x_k`` (default 0: ``c`` from the
            first step). The start-up, where the network pulls large errors in through its
            memory, stays uncentred; ``ObserverState.steps`` is its clock.
        centering_factors: ``{factor name: c_f}``, each in ``[0, 1]``: those factors' tangent
            components are centred by ``c_f`` instead of ``centering`` (ramped alike; needs
            ``centering`` > 0; default none). It adds no weight either.
        step_decay: ``{factor name: K_f}``, each an integer >= 1: those factors' tangent
            components of ``v_k`` are scaled by ``min(1, K_f / k)`` at the step from ``x_k``
            (default none). It adds no weight.
        prior_step: with ``robust_drive``, the step the prior takes with a drive,
            ``prior_step(x, d (B, drive width)) -> x^-`` (a system's ``step``), so that
            ``prior(x, y, u) == prior_step(x, prior_drive(x, y, u))``.
        robust_drive: a :class:`~manifold_nets.robust.RobustWeights` of one channel per drive
            component: the prior steps with ``w_i(|d_i|) d_i`` (needs ``prior``,
            ``prior_step`` and ``prior_drive``; default ``None``, none).
        robust_innovation: a :class:`~manifold_nets.robust.RobustWeights` of one channel per
            innovation factor (``inputs.innovation``, in its order): the core reads
            ``w_f(||nu_f||) nu_f`` and the measurement that innovation implies (default
            ``None``, none).
    """

    def __init__(
        self,
        group: LieGroup,
        measurement_dim: int,
        input_dim: int = 0,
        core: RecurrentCore | None = None,
        *,
        update: Mapping[str, str] | None = None,
        inputs: ObserverInputs | None = None,
        state_dtype: torch.dtype = torch.float64,
        hidden_size: int | None = None,
        num_layers: int | None = None,
        output_scale: float = 1.0,
        prior: Callable[..., torch.Tensor] | None = None,
        prior_name: str = "system",
        prior_drive: Callable[..., torch.Tensor] | None = None,
        gain: bool = False,
        offset: bool = True,
        centering: float = 0.0,
        centering_ramp: int = 0,
        centering_factors: Mapping[str, float] | None = None,
        step_decay: Mapping[str, int] | None = None,
        prior_step: Callable[..., torch.Tensor] | None = None,
        robust_drive: RobustWeights | None = None,
        robust_innovation: RobustWeights | None = None,
    ):
        super().__init__()
        if not isinstance(group, LieGroup):
            raise TypeError(f"group must be a groups.LieGroup, got {type(group).__name__}.")
        for name, val, low in (
            ("measurement_dim", measurement_dim, 1),
            ("input_dim", input_dim, 0),
        ):
            if isinstance(val, bool) or not isinstance(val, int) or val < low:
                raise ValueError(
                    f"ResidualObserver: {name} must be an integer >= {low}, got {val!r}."
                )
        if state_dtype not in (torch.float32, torch.float64):
            raise TypeError(
                f"state_dtype must be torch.float32 or torch.float64, got {state_dtype}."
            )
        self.output_scale = _check_output_scale(output_scale)
        inputs = ObserverInputs() if inputs is None else inputs
        if not isinstance(inputs, ObserverInputs):
            raise TypeError(f"inputs must be an ObserverInputs, got {type(inputs).__name__}.")
        self.group = group
        self.measurement_dim = measurement_dim
        self.input_dim = input_dim
        self.state_dtype = state_dtype
        self.inputs = inputs.check(group, measurement_dim)
        self.prior, self.prior_drive = self._check_prior(prior, prior_drive)
        self.prior_name = str(prior_name) if prior is not None else None
        form = self._check_form(gain, offset, centering, centering_ramp)
        self.gain, self.offset, self.centering, self.centering_ramp = form
        self.centering_factors = self._check_centering_factors(group, centering_factors)
        self.step_decay = self._check_step_decay(group, step_decay)
        self.prior_step = prior_step
        self.robust_drive, self.robust_innovation = self._check_robust(
            robust_drive, robust_innovation
        )
        self._innov_dim = self.inputs.innovation_dim(group)
        self.rules = _parse_rules(group, update)
        self._blocks = _blocks(group, self.rules)
        self._numel = math.prod(group.element_shape)
        self._innov = [
            (group.factor(name), group.element_slice(name), slice(a, b))
            for name, (a, b) in inputs.innovation.items()
        ]
        keep_embedding, keep_context = inputs.kept_columns(group, measurement_dim + input_dim)
        # column indices of embed(x) and of (y, u) that the core reads; None: all of them
        self.register_buffer("_keep_embedding", keep_embedding, persistent=False)
        self.register_buffer("_keep_context", keep_context, persistent=False)
        self.core = self._check_core(core, hidden_size, num_layers)  # checks the inputs
        if gain and isinstance(self.core, GRUCore):
            self._zero_gain(self.core)
        self._setup_extras(group, self.inputs)
        self._compiled_step = None

    def _check_prior(self, prior, drive) -> tuple:
        """``prior`` and ``prior_drive``, checked against each other and the inputs."""
        for name, fn, what in (("prior", prior, "x^- such as system.predict"),
                               ("prior_drive", drive, "drive such as system.compensated_drive")):
            if fn is not None and not callable(fn):
                raise TypeError(
                    f"{name} must be a callable (x, y, u) -> {what}, got {type(fn).__name__}."
                )
        if prior is not None and self.inputs.propagate:
            raise ValueError(
                "prior and inputs.propagate are two kinematic priors; use one (prior: the whole "
                "nominal model, e.g. system.predict; propagate: a factor moved by a measured rate)."
            )
        if (self.inputs.prior_drive and drive is None) or (drive is not None and prior is None):
            raise ValueError(
                "the core reads the prior's drive with a model prior, inputs.prior_drive (its "
                "width) and prior_drive (the callable, e.g. system.compensated_drive) together; "
                f"got prior={'set' if prior is not None else None}, inputs.prior_drive="
                f"{self.inputs.prior_drive}, prior_drive={'set' if drive is not None else None}."
            )
        return prior, drive

    def _check_robust(self, drive_map, innovation_map) -> tuple:
        """``robust_drive`` and ``robust_innovation``, checked against the prior and the inputs."""
        for name, m in (("robust_drive", drive_map), ("robust_innovation", innovation_map)):
            if m is not None and not isinstance(m, RobustWeights):
                raise TypeError(
                    f"{name} must be a manifold_nets.robust.RobustWeights, got {type(m).__name__}."
                )
        if drive_map is not None and (
            self.prior is None or self.prior_drive is None or not callable(self.prior_step)
        ):
            raise ValueError(
                "robust_drive weighs the drive the model prior steps with, so it needs the prior "
                "(prior=system.predict), its drive (prior_drive=system.compensated_drive) and "
                "its step (prior_step=system.step); got "
                f"prior={'set' if self.prior is not None else None}, prior_drive="
                f"{'set' if self.prior_drive is not None else None}, prior_step="
                f"{'set' if self.prior_step is not None else None}."
            )
        if drive_map is None and self.prior_step is not None:
            raise ValueError(
                "prior_step is the step robust_drive's weighted drive is taken with; without "
                "robust_drive leave it out (the prior steps itself)."
            )
        n = len(self.inputs.innovation)
        if innovation_map is not None and innovation_map.channels != n:
            raise ValueError(
                f"robust_innovation has {innovation_map.channels} channels, but the observer reads "
                f"{n} innovation factors ({list(self.inputs.innovation)}): one weight function "
                "per factor"
                + ("; give inputs.innovation or drop robust_innovation." if not n else ".")
            )
        return drive_map, innovation_map

    def _check_gain(self, gain: bool, offset: bool) -> tuple[bool, bool]:
        if not isinstance(gain, bool):
            raise TypeError(f"gain must be True or False, got {gain!r}.")
        if not isinstance(offset, bool) or (not offset and not gain):
            raise ValueError(
                f"offset={offset!r}: offset=False (v = K nu, no offset) is a form of the gain "
                "head; it needs gain=True."
            )
        if gain and not self.inputs.innovation:
            raise ValueError(
                "gain=True multiplies a learned gain with the innovation, but the observer reads "
                "none; give inputs.innovation ({factor: (start, stop)} in y, model.innovation) or "
                "drop the gain."
            )
        return gain, offset

    def _check_form(
        self, gain: bool, offset: bool, centering: float, ramp: int
    ) -> tuple[bool, bool, float, int]:
        """The update's form (gain head, its offset, centering and its ramp), checked against
        each other and the inputs."""
        self.gain, self.offset = self._check_gain(gain, offset)
        self.centering = self._check_centering(centering)
        return self.gain, self.offset, self.centering, self._check_ramp(ramp)

    def _check_centering(self, centering: float) -> float:
        if (
            isinstance(centering, bool) or not isinstance(centering, (int, float))
            or not 0 <= centering <= 1
        ):
            raise ValueError(
                f"ResidualObserver: centering must be a number in [0, 1], got {centering!r}."
            )
        if centering and not self.inputs.innovation:
            raise ValueError(
                "centering subtracts the core's output at zero innovation, but the observer reads "
                "none; give inputs.innovation ({factor: (start, stop)} in y, model.innovation) "
                "or set centering to 0."
            )
        if centering and self.prior is None and not self.inputs.propagate:
            raise ValueError(
                "centering subtracts the core's output at the measurement its prediction expects, "
                "but the observer has no prediction (no prior, no inputs.propagate): then that "
                "output is the motion itself, and centring takes it away. Give a prior (e.g. "
                "prior=system.predict) or set centering to 0."
            )
        if centering and self.gain and not self.offset:
            raise ValueError(
                "centering with the gain head and no offset (v = K nu) changes nothing: that "
                "update is already zero at zero innovation; set centering to 0."
            )
        return float(centering)

    def _check_centering_factors(self, group: LieGroup, factors) -> dict[str, float]:
        """``centering_factors`` checked; sets ``_centering_scale``, the per-component ``c_f / c``
        as floats (``None`` without per-factor values; a plain list, not a buffer, so that no
        change of dtype rounds it)."""
        factors = dict(factors or {})
        for name, c in factors.items():
            _check_factor(group, name, "centering_factors")
            if isinstance(c, bool) or not isinstance(c, (int, float)) or not 0 <= c <= 1:
                raise ValueError(
                    f"centering_factors[{name!r}] must be a number in [0, 1], got {c!r}."
                )
        if factors and not self.centering:
            raise ValueError(
                f"centering_factors={factors} centres some factors otherwise, but centering is 0; "
                "set centering (0 < c <= 1), the value of the other factors."
            )
        scale = None
        if factors:
            scale = [1.0] * group.tangent_dim
            for name, c in factors.items():
                cols = group.tangent_slice(name)
                scale[cols] = [float(c) / self.centering] * (cols.stop - cols.start)
        self._centering_scale = scale
        return {name: float(c) for name, c in factors.items()}

    def _check_ramp(self, ramp: int) -> int:
        if isinstance(ramp, bool) or not isinstance(ramp, int) or ramp < 0:
            raise ValueError(
                f"ResidualObserver: centering_ramp must be an integer >= 0 (steps), got {ramp!r}."
            )
        if ramp and not self.centering:
            raise ValueError(
                f"centering_ramp={ramp} ramps in the centred update, but centering is 0; set "
                "centering (0 < c <= 1) or the ramp to 0."
            )
        return ramp

    def _check_step_decay(self, group: LieGroup, decay) -> dict[str, int]:
        """``step_decay`` checked; sets ``_decay_columns``, ``(tangent slice, K_f)`` per factor."""
        decay = dict(decay or {})
        for name, k in decay.items():
            _check_factor(group, name, "step_decay")
            if isinstance(k, bool) or not isinstance(k, int) or k < 1:
                raise ValueError(
                    f"step_decay[{name!r}] must be an integer >= 1 (the steps before the factor's "
                    f"step size starts to fall like K / k), got {k!r}."
                )
        self._decay_columns = [(group.tangent_slice(n), k) for n, k in decay.items()]
        return decay

    def decay_at(self, k: torch.Tensor) -> torch.Tensor | None:
        """``d_k``, the scale of each tangent component of the step from ``x_k``, ``(*k.shape,
        tangent_dim)`` in ``k``'s dtype: ``min(1, K_f / k)`` on the ``step_decay`` factors, 1
        elsewhere; ``None`` without ``step_decay``. ``k``: a floating tensor of step counts."""
        if not self._decay_columns:
            return None
        d = k.new_ones((*k.shape, self.group.tangent_dim))
        for cols, big_k in self._decay_columns:
            d[..., cols] = (big_k / k.clamp(min=1)).clamp(max=1.0)[..., None]
        return d

    def centering_at(self, k):
        """``c_k``, the centring of the step from ``x_k`` (``k`` steps taken): ``centering``,
        ramped in over the first ``centering_ramp`` steps. ``k`` an integer, or with a ramp a
        floating tensor of step counts (then ``c_k`` is a tensor of its shape)."""
        ramp = self.centering_ramp
        if not ramp:
            return self.centering
        if isinstance(k, torch.Tensor):
            return self.centering * (k / ramp).clamp(max=1.0)
        return self.centering * min(1.0, k / ramp)

    def _zero_gain(self, core: GRUCore) -> None:
        """``K`` starts at zero: the untrained observer is the prior plus a bounded offset, not a
        random feedback of the innovation (which can make the estimate run away)."""
        first = self.group.tangent_dim if self.offset else 0
        with torch.no_grad():
            core.head.weight[first:].zero_()
            core.head.bias[first:].zero_()

    def _setup_extras(self, group: LieGroup, inputs: ObserverInputs) -> None:
        """The raw ``(y, u)`` columns appended to the context for the kinematic prior and the
        rotated vectors, and where each factor finds its own among them."""
        extra = inputs.extra_columns()
        self._num_extra = len(extra)
        cols = torch.tensor(extra, dtype=torch.long) if extra else None
        self.register_buffer("_extra_columns", cols, persistent=False)
        self._propagate, at = [], 0
        for name, (a, b) in inputs.propagate.items():
            f = group.factor(name)
            self._propagate.append((f, group.element_slice(name), slice(at, at + b - a)))
            at += b - a
        self._rotated = []
        for name, spans in inputs.rotated.items():
            self._rotated.append((group.element_slice(name), slice(at, at + 3 * len(spans))))
            at += 3 * len(spans)
        self._dt = inputs.dt
        # where each innovation factor's measured columns sit in the core's context, for the
        # centred update (None: read only through its innovation); only whole relative-only
        # spans leave the context, so a kept span stays one block
        kept = None if self._keep_context is None else self._keep_context.tolist()
        self._measured_in_context = [
            None if name in inputs.relative_only
            else slice(a, b) if kept is None
            else slice(kept.index(a), kept.index(a) + b - a)
            for name, (a, b) in inputs.innovation.items()
        ]
        # innovation_frame: (position in the innovation list, the rotation factor's slice of x)
        names = list(inputs.innovation)
        self._frames = [
            (names.index(vec), group.element_slice(rot))
            for vec, rot in inputs.innovation_frame.items()
        ]

    def _context(self, full: torch.Tensor) -> torch.Tensor:
        """The core's context from the whole ``(..., l + m)`` ``(y, u)``: the kept columns, then
        the raw columns of the kinematic prior and the rotated vectors (``_step`` splits them)."""
        context = full
        if self._keep_context is not None:
            context = full.index_select(-1, self._keep_context)
        if self._extra_columns is not None:
            context = torch.cat((context, full.index_select(-1, self._extra_columns)), dim=-1)
        return context

    def _check_core(self, core, hidden_size, num_layers) -> RecurrentCore:
        """``core``, or the default GRU core, checked against the sizes the observer needs."""
        in_size = self.inputs.core_input_size(self.group, self.measurement_dim, self.input_dim)
        out_size = core_output_size(self.group, self.inputs, self.gain, self.offset)
        if core is None:
            return GRUCore(in_size, out_size, hidden_size or 512, num_layers or 2)
        if not isinstance(core, RecurrentCore):
            raise TypeError(f"core must be a RecurrentCore, got {type(core).__name__}.")
        if hidden_size is not None or num_layers is not None:
            raise ValueError(
                "hidden_size and num_layers size the default GRU core; with a core of your own, "
                "size the core itself."
            )
        if core.input_size != in_size or core.output_size != out_size:
            relative = self.inputs.relative_only
            raise ValueError(
                f"core maps {core.input_size} -> {core.output_size}, but the observer needs "
                f"{in_size} (embedding_dim + measurement_dim + input_dim + innovation's tangent "
                f"dims = {self.group.embedding_dim} + {self.measurement_dim} + {self.input_dim} "
                f"+ {self.inputs.innovation_dim(self.group)}"
                + (f", less relative_only {list(relative)}" if relative else "")
                + f") -> {out_size}"
                + (
                    f" (the gain head: tangent_dim x ({int(self.offset)} + innovation width) = "
                    f"{self.group.tangent_dim} x {int(self.offset) + self._innov_dim})."
                    if self.gain
                    else " = tangent_dim."
                )
            )
        return core

    def compile_step(self, **options) -> ResidualObserver:
        """Compiles the per-step function with ``torch.compile`` for the rollouts that record
        gradients (training); rollouts without gradients (evaluation, online use) stay eager.

        The step is a few dozen small kernels (the core's cells, the group update, the
        innovation's log); compiled, they fuse, and the backward pass with them
        (``benchmarks/results/observer.md`` has the speed-ups). Compilation takes tens of
        seconds, once per batch shape, and needs a C++ compiler on the CPU. ``options`` go to
        ``torch.compile`` (default ``dynamic=False``). Returns ``self``.
        """
        self._compiled_step = torch.compile(self._step, **{"dynamic": False, **options})
        return self

    def online_step_module(self) -> nn.Module:
        """This observer's online step as a check-free module,
        ``forward(x, *hidden, y[, u]) -> (x, *hidden)`` on flat tensors, for ``torch.export``,
        ``torch.compile`` or ONNX (:class:`manifold_nets.deploy.OnlineStep`; parameters shared).
        """
        from .deploy import OnlineStep

        return OnlineStep(self)

    # ------------------------------------------------------------------ description

    @property
    def net_dtype(self) -> torch.dtype:
        return next(self.core.parameters()).dtype

    @property
    def device(self) -> torch.device:
        return next(self.core.parameters()).device

    def signature(self) -> dict:
        """What a checkpoint must match to load into this observer (JSON-able)."""
        return {
            "group": repr(self.group),
            "measurement_dim": self.measurement_dim,
            "input_dim": self.input_dim,
            "update": list(self.rules),
            **self.inputs.signature(),
            "core": self.core.signature(),
            # absent at 1: the signature of older checkpoints
            **({"output_scale": self.output_scale} if self.output_scale != 1.0 else {}),
            **({"prior": self.prior_name} if self.prior is not None else {}),
            **({"gain": True} if self.gain else {}),
            **({"offset": False} if not self.offset else {}),
            **({"centering": self.centering} if self.centering else {}),
            **({"centering_ramp": self.centering_ramp} if self.centering_ramp else {}),
            **({"centering_factors": self.centering_factors} if self.centering_factors else {}),
            **({"step_decay": self.step_decay} if self.step_decay else {}),
            **{
                name: m.signature()
                for name, m in (
                    ("robust_drive", self.robust_drive),
                    ("robust_innovation", self.robust_innovation),
                )
                if m is not None
            },
        }

    def state_with_robust(
        self, state: dict, signature: dict, where: str = "checkpoint"
    ) -> tuple[dict, dict]:
        """A ``state_dict`` and signature for this observer from one of the same observer without
        some of its learned robust weights (``robust_drive``, ``robust_innovation``): each
        missing map starts new, the identity, so this observer starts out computing what that one
        does (``train.init_from``).

        Raises :class:`~manifold_nets.checkpoint.CheckpointError` when the checkpoint has a map
        this observer lacks, or one of another shape."""
        from .checkpoint import CheckpointError

        out, sig = dict(state), dict(signature)
        for name in ("robust_drive", "robust_innovation"):
            mine, theirs = getattr(self, name), signature.get(name)
            if theirs is None and mine is not None:
                new = RobustWeights(**mine.signature()).to(mine.amplitude)  # its dtype, device
                out.update({f"{name}.{k}": v for k, v in new.state_dict().items()})
                sig[name] = mine.signature()
            elif theirs is not None and (mine is None or theirs != mine.signature()):
                raise CheckpointError(
                    f"{where}: the checkpoint's {name} {theirs} does not fit this observer's "
                    f"({mine.signature() if mine is not None else None}); model.{name} must "
                    "match, or be off in the checkpoint (then it starts as the identity)."
                )
        return out, sig

    def state_with_gain(self, state: dict, signature: dict, where: str = "checkpoint") -> dict:
        """A ``state_dict`` for this gain-head observer from one of the same observer without the
        gain head (``state`` and its ``signature``): the same weights, the head's offset rows
        rescaled by that observer's ``output_scale`` over this one's, the rows of ``K`` zero, so
        this observer starts out computing exactly what that one does (``train.init_from``).

        Raises :class:`~manifold_nets.checkpoint.CheckpointError` when the two differ in more
        than the gain head and the output scale, or this observer has no gain head or no
        :class:`~manifold_nets.cores.GRUCore`."""
        from .checkpoint import CheckpointError, check_signature

        own = self.signature()
        if (
            not self.gain or not self.offset or not isinstance(self.core, GRUCore)
            or signature.get("gain")
        ):
            raise CheckpointError(
                f"{where}: a plain observer's weights widen only into an observer with the gain "
                "head, its offset and a GRU core (model.gain=true, model.gain_offset=true, "
                "model.core=gru)."
            )

        def plain(sig: dict) -> dict:
            sig = {k: v for k, v in sig.items() if k not in ("gain", "output_scale")}
            return {**sig, "core": {**sig.get("core", {}), "output_size": None}}

        check_signature(plain(signature), plain(own), where=where)
        n, ratio = self.group.tangent_dim, float(signature.get("output_scale", 1.0))
        ratio /= self.output_scale
        out = dict(state)
        for name in ("core.head.weight", "core.head.bias"):
            old = state[name]
            if old.shape[0] != n:
                raise CheckpointError(f"{where}: {name} has {old.shape[0]} rows, expected {n}.")
            gain = torch.zeros((self.core.output_size - n, *old.shape[1:]), dtype=old.dtype)
            out[name] = torch.cat([old * ratio, gain.to(old.device)])
        return out

    def state_with_inputs(
        self, state: dict, signature: dict, where: str = "checkpoint"
    ) -> tuple[dict, dict]:
        """A ``state_dict`` and signature for this observer from one of the same observer without
        some of the inputs the core reads last (``inputs.appended()``: clock inputs, the framed
        innovation, then the prior's drive): the first GRU layer's input weights get a zero column per missing
        input, so this observer starts out computing exactly what that one does
        (``train.init_from``). The other differences (the gain head, the centring) are left to
        the caller's checks.

        Raises :class:`~manifold_nets.checkpoint.CheckpointError` when nothing is missing, when
        what is missing is not the last of those inputs, or without a
        :class:`~manifold_nets.cores.GRUCore`."""
        from .checkpoint import CheckpointError

        appended = self.inputs.appended()
        missing = [entry for entry in appended if not signature.get(entry[0])]
        if (
            not missing or appended[len(appended) - len(missing):] != missing
            or not isinstance(self.core, GRUCore)
        ):
            raise CheckpointError(
                f"{where}: an observer's weights widen to clock inputs (model.clock), a framed "
                "innovation (model.innovation_frame) or the prior's drive (model.prior_drive) "
                "only into an observer with them and a GRU core (model.core=gru), from one "
                "without the last of them, in that order (clock, innovation_frame, prior_drive)."
            )
        name = "core.gru.weight_ih_l0"
        old = state.get(name)
        core = dict(signature.get("core", {}))
        if old is None or old.dim() != 2 or old.shape[1] != core.get("input_size"):
            raise CheckpointError(f"{where}: no first GRU layer of the checkpoint's input size.")
        n = sum(width for _, _, width in missing)
        zeros = torch.zeros((old.shape[0], n), dtype=old.dtype, device=old.device)
        state = {**state, name: torch.cat([old, zeros], dim=1)}
        core["input_size"] = old.shape[1] + n
        return state, {**signature, "core": core, **{key: value for key, value, _ in missing}}

    def extra_repr(self) -> str:
        return (
            f"group={self.group!r}, measurement_dim={self.measurement_dim}, "
            f"input_dim={self.input_dim}, update={list(self.rules)}, "
            f"state_dtype={self.state_dtype}"
        )

    # ------------------------------------------------------------------ the hot path (unchecked)

    def _embed(self, x: torch.Tensor) -> torch.Tensor:
        """``embed`` of a flat state ``(B, numel)`` -> ``(B, embedding_dim)``."""
        if self.group.embedding_is_flat:  # e.g. SO(3) x R^n: the flat element is its embedding
            return x
        parts = []
        for b in self._blocks:
            xf = x[:, b.element]
            if b.factor is not None:
                xf = b.factor.embed(xf.unflatten(-1, b.factor.element_shape))
            parts.append(xf)
        return parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1)

    def _update(self, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """The per-factor update of a flat state ``(B, numel)`` by ``v`` ``(B, tangent_dim)``."""
        parts = []
        for b in self._blocks:
            vf = v[:, b.tangent]
            if b.factor is None:
                new = vf if b.rule == "absolute" else x[:, b.element] + vf
            else:
                shape = b.factor.element_shape
                if b.rule == "absolute":
                    new = b.factor.exp(vf)
                elif b.rule == "left":
                    new = b.factor.compose(b.factor.exp(vf), x[:, b.element].unflatten(-1, shape))
                else:
                    new = b.factor.rplus(x[:, b.element].unflatten(-1, shape), vf)
                new = new.flatten(-len(shape)) if len(shape) > 1 else new
            parts.append(new)
        return parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1)

    def _measured(self, y: torch.Tensor) -> list[torch.Tensor]:
        """The measured factor elements ``(..., *factor.element_shape)`` in the state dtype, read
        from the measurements ``(..., measurement_dim)`` as given (not rounded to the network's)."""
        y = y.to(device=self.device, dtype=self.state_dtype)
        return [f.unembed(y[..., ys]) for f, _, ys in self._innov]

    def _readings(self, y: torch.Tensor, u: torch.Tensor | None) -> torch.Tensor | None:
        """``(y, u)`` ``(..., l + m)`` in the state dtype, as given, for the model prior; ``None``
        without one."""
        if self.prior is None:
            return None
        parts = [y] if u is None or not self.input_dim else [y, u]
        return torch.cat([p.to(device=self.device, dtype=self.state_dtype) for p in parts], -1)

    def _step(
        self, x: torch.Tensor, hidden: Hidden, context: torch.Tensor, measured=(), readings=None,
        centering=None, clock=None, decay=None,
    ):
        """One unchecked step.

        ``x``: the flat state ``(B, numel)`` in the state dtype; ``context``: ``(B, l + m)`` in the
        network dtype (less the relative-only columns); ``measured``: the step's measured factor
        elements (innovation only); ``readings``: the step's ``(y, u)`` ``(B, l + m)`` in the
        state dtype (model prior only); ``centering``: the step's ``c_k`` (a number or a 0-d
        tensor; default ``self.centering``; read only when the observer is centred); ``clock``:
        the step's clock features ``(len(inputs.clock),)`` or ``(B, len(inputs.clock))`` in the
        network dtype (clock inputs only); ``decay``: the step's ``d_k`` ``(tangent_dim,)`` or
        ``(B, tangent_dim)`` in the network dtype (``step_decay`` only).
        """
        net = context.dtype
        drive = []
        if self.prior is not None:
            x, drive = self._prior(x, readings, net)
        extra = None
        if self._num_extra:
            context, extra = context[:, : -self._num_extra], context[:, -self._num_extra :]
            x = self._predict(x, extra)
        e = self._embed(x)
        if self._keep_embedding is not None:
            e = e.index_select(-1, self._keep_embedding)
        innovation = [
            f.rminus(m, x[:, xs].unflatten(-1, f.element_shape))
            for (f, xs, _), m in zip(self._innov, measured)
        ]
        if self.robust_innovation is not None:
            innovation, context = self._robust_innovation(x, innovation, context)
        innovation = [nu.to(net) for nu in innovation]
        e = e.to(net)
        rotated = []
        for xs, cols in self._rotated:  # world-frame vectors R v of body-frame v
            R = x[:, xs].unflatten(-1, (3, 3)).to(net)
            vecs = extra[:, cols].unflatten(-1, (-1, 3))
            rotated.append((vecs @ R.transpose(-1, -2)).flatten(-2))
        tail = rotated if clock is None else [*rotated, clock.expand(x.shape[0], -1)]
        framed = [  # Rhat^T nu, as the row nu^T Rhat
            (innovation[i].unsqueeze(-2) @ x[:, rs].unflatten(-1, (3, 3)).to(net)).squeeze(-2)
            for i, rs in self._frames
        ]
        inp = torch.cat([e, context, *innovation, *tail, *framed, *drive], dim=-1)
        if self.centering:  # v = T(z) - c T(z^0): one core step on both, the hidden state from z
            b = inp.shape[0]
            zero = [torch.zeros_like(i) for i in innovation]
            zero_framed = [torch.zeros_like(f) for f in framed]
            z0 = torch.cat(
                [e, self._measured_at(x, context), *zero, *tail, *zero_framed, *drive], dim=-1
            )
            out, hidden = self.core.step(
                torch.cat((inp, z0)), tuple(torch.cat((h, h)) for h in hidden)
            )
            hidden = tuple(h[:b] for h in hidden)
            v = out[:b]
        else:
            v, hidden = self.core.step(inp, hidden)
        if self.gain:  # v = a + K nu, or K nu
            n, a = self.group.tangent_dim, self.group.tangent_dim if self.offset else 0
            nu = innovation[0] if len(innovation) == 1 else torch.cat(innovation, dim=-1)
            gain = v[:, a:].unflatten(-1, (n, self._innov_dim))
            kv = (gain @ nu.unsqueeze(-1)).squeeze(-1)
            v = v[:, :n] + kv if self.offset else kv
        if self.centering:  # at z^0 the innovation is zero: the gain head's K nu drops out
            c = self.centering if centering is None else centering
            at_zero = out[b:, : self.group.tangent_dim]
            if self._centering_scale is not None:  # c_f per factor
                at_zero = at_zero * at_zero.new_tensor(self._centering_scale)
            v = v - c * at_zero
        if decay is not None:
            v = v * decay
        if self.output_scale != 1.0:
            v = v * self.output_scale
        return self._update(x, v.to(x.dtype)), hidden

    def _prior(
        self, x: torch.Tensor, readings: torch.Tensor, net: torch.dtype
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """The model prior's ``x^-`` ``(B, numel)`` from the flat ``x_k``, with ``robust_drive``
        the step with the weighted drive, and the drive the core reads (``[]`` or one ``(B,
        width)`` in the network dtype ``net``)."""
        y = readings[:, : self.measurement_dim]
        u = readings[:, self.measurement_dim :] if self.input_dim else None
        x = x.unflatten(-1, self.group.element_shape)
        d = None if self.prior_drive is None else self.prior_drive(x, y, u)  # from x_k
        drive = [d.to(net)] if self.inputs.prior_drive else []  # the drive as given
        if self.robust_drive is None:
            return self.prior(x, y, u).flatten(1), drive
        w = self.robust_drive(d.abs().to(net)).to(d.dtype)  # d_i <- w_i(|d_i|) d_i
        return self.prior_step(x, w * d).flatten(1), drive

    def _robust_innovation(
        self, x: torch.Tensor, innovation: list[torch.Tensor], context: torch.Tensor
    ) -> tuple[list[torch.Tensor], torch.Tensor]:
        """``nu_f <- w_f(||nu_f||) nu_f`` for each innovation factor (state dtype), and in the
        context each measured factor's columns set to the measurement that implies,
        ``xhat_f^- exp(nu_f)``."""
        norms = torch.stack([safe_norm(nu) for nu in innovation], dim=-1)
        w = self.robust_innovation(norms.to(context.dtype)).to(norms.dtype)
        innovation = [nu * w[:, i : i + 1] for i, nu in enumerate(innovation)]
        if any(cols is not None for cols in self._measured_in_context):
            context = context.clone()
            for (f, xs, _), nu, cols in zip(self._innov, innovation, self._measured_in_context):
                if cols is not None:
                    m = f.rplus(x[:, xs].unflatten(-1, f.element_shape), nu)
                    context[:, cols] = f.embed(m).reshape(x.shape[0], -1).to(context.dtype)
        return innovation, context

    def _clocks(self, k0: int, count: int) -> torch.Tensor | list[None]:
        """The clock features of the ``count`` steps from ``x_{k0}`` on, ``(count,
        len(inputs.clock))`` in the network dtype; without clock inputs, ``None`` per step."""
        if not self.inputs.clock:
            return [None] * count
        k = torch.arange(k0, k0 + count, dtype=self.net_dtype, device=self.device)
        return self.inputs.clock_features(k)

    def _decays(self, k0: int, count: int) -> torch.Tensor | list[None]:
        """``d_k`` of the ``count`` steps from ``x_{k0}`` on, ``(count, tangent_dim)`` in the
        network dtype; without ``step_decay``, ``None`` per step."""
        if not self._decay_columns:
            return [None] * count
        k = torch.arange(k0, k0 + count, dtype=torch.float64, device=self.device)
        return self.decay_at(k).to(self.net_dtype)

    def _measured_at(self, x: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        """``context`` with each innovation factor's measured columns set to the embedding of
        its prediction in ``x``: the context of ``z^0``, the measurement exactly predicted."""
        context = context.clone()
        for (f, xs, _), cols in zip(self._innov, self._measured_in_context):
            if cols is not None:
                pred = f.embed(x[:, xs].unflatten(-1, f.element_shape))
                context[:, cols] = pred.reshape(x.shape[0], -1).to(context.dtype)
        return context

    def _predict(self, x: torch.Tensor, extra: torch.Tensor) -> torch.Tensor:
        """The kinematic prior: each ``propagate`` factor moved by ``dt`` times its velocity."""
        if not self._propagate:
            return x
        x = x.clone()
        for f, xs, cols in self._propagate:
            w = extra[:, cols].to(x.dtype) * self._dt
            shape = f.element_shape
            if isinstance(f, Euclidean):
                x[:, xs] = x[:, xs] + w
            else:
                new = f.rplus(x[:, xs].unflatten(-1, shape), w)
                x[:, xs] = new.flatten(-len(shape)) if len(shape) > 1 else new
        return x

    # ------------------------------------------------------------------ checks

    def _check_sequences(self, measurements, inputs) -> torch.Tensor:
        """Validates once, returns the time-major context ``(T, N, l + m)`` in the network dtype."""
        if not isinstance(measurements, torch.Tensor) or not measurements.is_floating_point():
            raise TypeError(
                "measurements must be a floating-point torch.Tensor "
                f"(N, T, {self.measurement_dim}), "
                f"got {type(measurements).__name__}"
                + (
                    f" of dtype {measurements.dtype}"
                    if isinstance(measurements, torch.Tensor)
                    else ""
                )
                + "."
            )
        if measurements.dim() != 3 or measurements.shape[-1] != self.measurement_dim:
            raise ValueError(
                f"measurements must have shape (N, T, measurement_dim={self.measurement_dim}), got "
                f"{tuple(measurements.shape)}; is this data from the system the observer was "
                "built for?"
            )
        n, t = measurements.shape[:2]
        if t < 1 or n < 1:
            raise ValueError(
                "measurements must hold at least one sequence of one step, got "
                f"{tuple(measurements.shape)}."
            )
        parts = [measurements]
        if inputs is None:
            if self.input_dim:
                raise ValueError(
                    f"this observer reads inputs u of size {self.input_dim}; pass inputs "
                    f"(N, T, {self.input_dim})."
                )
        else:
            if not isinstance(inputs, torch.Tensor) or not inputs.is_floating_point():
                raise TypeError(
                    f"inputs must be a floating-point torch.Tensor (N, T, {self.input_dim})."
                )
            if tuple(inputs.shape) != (n, t, self.input_dim):
                raise ValueError(
                    f"inputs must have shape (N, T, input_dim) = ({n}, {t}, {self.input_dim}) "
                    "to match "
                    f"the measurements, got {tuple(inputs.shape)}."
                )
            if self.input_dim:
                parts.append(inputs)
        dev, net = self.device, self.net_dtype
        context = torch.cat([p.to(device=dev, dtype=net) for p in parts], dim=-1)
        # a data-dependent branch: checked in eager use, left out of a traced graph
        # (torch.compile, torch.export), which cannot branch on values
        if not torch.compiler.is_compiling() and not bool(torch.isfinite(context).all()):
            raise ValueError("measurements/inputs hold NaN or Inf; the observer needs finite data.")
        return self._context(context).transpose(0, 1).contiguous()

    # ------------------------------------------------------------------ public API

    def init_state(self, batch: int, device=None) -> ObserverState:
        """The state before the first step: the identity and the core's initial hidden state."""
        if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
            raise ValueError(f"batch must be a positive integer, got {batch!r}.")
        device = self.device if device is None else device
        x = self.group.identity((batch,), dtype=self.state_dtype, device=device)
        return ObserverState(x, self.core.initial_hidden(batch, device=device))

    def step(
        self, state: ObserverState, y: torch.Tensor, u: torch.Tensor | None = None
    ) -> ObserverState:
        """One online step: ``y`` ``(B, measurement_dim)`` is ``y_{k+1}``, ``u`` ``(B, input_dim)``
        is ``u_k``.

        Returns the new state; its ``estimate`` is ``xhat_{k+1}`` ``(B, *element_shape)``.
        """
        if not isinstance(y, torch.Tensor) or y.dim() != 2:
            raise ValueError(
                f"y must be a tensor (B, measurement_dim={self.measurement_dim}), got "
                f"{tuple(y.shape) if isinstance(y, torch.Tensor) else type(y).__name__}."
            )
        context = self._check_sequences(y[:, None], None if u is None else u[:, None])[0]
        x = state.estimate
        if x.shape[0] != context.shape[0]:
            raise ValueError(
                f"the state holds a batch of {x.shape[0]}, y a batch of {context.shape[0]}."
            )
        x, hidden = self._step(
            x.reshape(x.shape[0], self._numel).to(self.state_dtype),
            state.hidden,
            context,
            self._measured(y),
            self._readings(y, u),
            self.centering_at(state.steps),
            self._clocks(state.steps, 1)[0],
            self._decays(state.steps, 1)[0],
        )
        shape = self.group.element_shape
        return ObserverState(x.view(x.shape[0], *shape), hidden, state.steps + 1)

    def forward(
        self,
        measurements: torch.Tensor,
        inputs: torch.Tensor | None = None,
        state: ObserverState | None = None,
        return_state: bool = False,
    ):
        """Rolls the observer over whole sequences.

        Args:
            measurements: ``(N, T, measurement_dim)``, ``measurements[:, k] = y_{k+1}``.
            inputs: ``(N, T, input_dim)`` (``u_k``) or ``None`` when ``input_dim == 0``.
            state: where to start (default ``init_state(N)``: the identity, zero hidden state).
            return_state: also return the final :class:`ObserverState` (to continue online).

        Returns:
            The estimates ``(N, T+1, *element_shape)`` in the state dtype, ``[:, 0]`` the start.
        """
        context = self._check_sequences(measurements, inputs)  # (T, N, l + m)
        n = context.shape[1]
        if state is None:
            state = self.init_state(n, device=context.device)
        elif tuple(state.estimate.shape) != (n, *self.group.element_shape):
            raise ValueError(
                f"state.estimate has shape {tuple(state.estimate.shape)}, expected "
                f"{(n, *self.group.element_shape)} for {n} sequences."
            )
        x = state.estimate.reshape(n, self._numel).to(self.state_dtype)
        hidden = state.hidden
        xs = [x]
        # unbind: one backward node for all the steps' slices (indexing would add one per step)
        steps = context.unbind(0)
        if self._innov:
            measured = list(
                zip(*(m.unbind(0) for m in self._measured(measurements.transpose(0, 1))))
            )
        else:
            measured = [()] * len(steps)
        readings = self._readings(measurements, inputs)
        readings = [None] * len(steps) if readings is None else readings.transpose(0, 1).unbind(0)
        step = self._step
        if self._compiled_step is not None and torch.is_grad_enabled():
            step = self._compiled_step
        k0 = state.steps
        ramp = ()  # c_k of the steps inside the ramp, as 0-d tensors: one compiled graph for all
        if k0 < self.centering_ramp:
            ks = torch.arange(k0, min(k0 + len(steps), self.centering_ramp), dtype=torch.float64)
            ramp = self.centering_at(ks).to(context).unbind(0)
        clocks, decays = self._clocks(k0, len(steps)), self._decays(k0, len(steps))
        for i, (c, m, r) in enumerate(zip(steps, measured, readings)):
            ci = ramp[i] if i < len(ramp) else None
            x, hidden = step(x, hidden, c, m, r, ci, clocks[i], decays[i])
            xs.append(x)
        est = torch.stack(xs, dim=1).unflatten(-1, self.group.element_shape)
        if return_state:
            shape = self.group.element_shape
            return est, ObserverState(x.view(n, *shape), hidden, k0 + len(steps))
        return est
