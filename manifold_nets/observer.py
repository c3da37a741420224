"""The residual-on-algebra observer (the paper's Section 2 and Algorithm 1), generic over any group.

Per step ``k`` a recurrent *core* reads ``(embed(xhat_k), y_{k+1}, u_k)`` and outputs a tangent
vector ``v_k`` (``group.tangent_dim``); the estimate moves by a group update, so it never leaves
the group::

    xhat_0     = e                          (the identity)
    v_k        = T(embed(xhat_k), y_{k+1}, u_k)
    xhat_{k+1} = xhat_k · exp(v_k)          ("residual", the paper's update)

The update is chosen per factor of a :class:`groups.Product` (a non-product group is one factor):

* ``"residual"``: ``x_f <- x_f · exp(v_f)`` (``rplus``; for ``R^n`` this is ``x_f + v_f``);
* ``"absolute"``: ``x_f <- exp(v_f)``, the factor is set to the prediction (for ``R^n`` this is
  ``x_f = v_f``: the paper's biases ``b = gamma``).

Shapes: measurements ``(N, T, measurement_dim)`` with ``measurements[:, k] = y_{k+1}``, inputs
``(N, T, input_dim)`` with ``inputs[:, k] = u_k`` (``None`` when ``input_dim == 0``); the rollout
returns the estimates ``(N, T+1, *group.element_shape)``, ``xhat_0 .. xhat_T``.

The group state has its own dtype (``state_dtype``, float64 by default), separate from the
network's (its parameters' dtype, float32 by default): the network reads ``embed(xhat)`` cast
to its dtype and its output is cast to the state dtype before the update, so the estimate stays
on the group to rounding of the state dtype (~1e-14 after 1000 steps in float64).

Speed: the rollout is the hot loop of training, evaluation and online use. Inputs are checked
once before the loop; inside it each step is a handful of fused kernels (``torch.gru_cell`` per
layer, a ``Linear``, the group update on precomputed factor slices) and no validation.
Consecutive ``R^n`` factors with the same rule are merged into one slice.

Optional innovation input (an extension; off by default, the paper's inputs are
``(embed(xhat), y, u)``): when a measurement holds the embedding of some factors directly (the
rigid body's ``y`` starts with ``vec R^m`` and ``p^m``), ``innovation={"R": (0, 9), "p": (9, 12)}``
names those factors and where they sit in ``y``; the core then also reads, per factor, the
tangent vector ``rminus(m_f, xhat_f) = log(xhat_f^-1 · m_f)`` from the estimate to the measured
factor ``m_f = unembed(y[a:b])``: the innovation of a classical observer, which turns the
nonlinear comparison of two embedded elements into an input the network can use linearly.

Optional relative-only factors (an extension; needs the innovation of those factors):
``relative_only=["p"]`` leaves the absolute estimate and measurement of the factor ``p`` out of
the core's input; the core sees the factor only through its innovation ``p^m - phat``. For the
rigid body, whose motion does not depend on where it is, the observer is then invariant to
translations of the whole trajectory, so it does not leave the range of positions it was
trained on when it runs longer than the training sequences.

The core is replaceable: any :class:`RecurrentCore` (``initial_hidden`` and ``step``) works;
:class:`GRUCore` is the paper's (GRU 36 -> 512, GRU 512 -> 512, Linear 512 -> 12 for the rigid
body, sizes and layer count configurable).
"""

from __future__ import annotations

import abc
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import nn

from groups import Euclidean, LieGroup, Product

__all__ = [
    "UPDATE_RULES",
    "core_input_size",
    "RecurrentCore",
    "GRUCore",
    "ObserverState",
    "ResidualObserver",
    "factor_names",
]

#: The per-factor update rules.
UPDATE_RULES = ("residual", "absolute")

Hidden = tuple[torch.Tensor, ...]


def factor_names(group: LieGroup) -> tuple[str, ...]:
    """Names of the factors of ``group``: a Product's ``names`` (``factor0``, ... when unnamed),
    or ``("x",)`` for a group that is not a product (the keys of ``System.metrics``)."""
    if isinstance(group, Product):
        return (
            tuple(group.names)
            if group.names
            else tuple(f"factor{i}" for i in range(len(group.factors)))
        )
    return ("x",)


# ---------------------------------------------------------------------- cores


class RecurrentCore(nn.Module, abc.ABC):
    """A recurrent map ``(input (B, input_size), hidden) -> (output (B, output_size), hidden)``.

    The observer's input is ``cat(embed(xhat_k), y_{k+1}, u_k)`` and its output ``v_k``.
    ``hidden`` is a tuple of tensors whose first dimension is the batch. Subclass it to replace
    the paper's GRU stack; ``signature()`` identifies the architecture in checkpoints.
    """

    input_size: int
    output_size: int

    @abc.abstractmethod
    def initial_hidden(
        self, batch: int, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> Hidden:
        """The hidden state before the first step (zeros for a GRU)."""

    @abc.abstractmethod
    def step(self, inp: torch.Tensor, hidden: Hidden) -> tuple[torch.Tensor, Hidden]:
        """One step; no validation (the observer checks its inputs once, before the loop)."""

    def signature(self) -> dict:
        """What must match for a checkpoint of this core to load: type and sizes."""
        return {
            "type": type(self).__name__,
            "input_size": self.input_size,
            "output_size": self.output_size,
        }


class GRUCore(RecurrentCore):
    """A stack of GRU layers and a linear head (the paper's Table): ``input -> H -> ... -> output``.

    Parameters live in a ``torch.nn.GRU`` (same names, same initialisation, so an open-loop
    ``nn.GRU`` run over the same inputs gives the same hidden states) and an ``nn.Linear``;
    a step calls ``torch.gru_cell`` once per layer.
    """

    def __init__(
        self, input_size: int, output_size: int, hidden_size: int = 512, num_layers: int = 2
    ):
        super().__init__()
        for name, val in (
            ("input_size", input_size),
            ("output_size", output_size),
            ("hidden_size", hidden_size),
            ("num_layers", num_layers),
        ):
            if isinstance(val, bool) or not isinstance(val, int) or val < 1:
                raise ValueError(f"GRUCore: {name} must be a positive integer, got {val!r}.")
        self.input_size = input_size
        self.output_size = output_size
        self.hidden_size = hidden_size
        self.num_layers = num_layers
        self.gru = nn.GRU(input_size, hidden_size, num_layers)
        self.head = nn.Linear(hidden_size, output_size)

    def initial_hidden(self, batch, device=None, dtype=None) -> Hidden:
        w = self.head.weight
        shape = (batch, self.hidden_size)
        return tuple(
            torch.zeros(
                shape,
                device=w.device if device is None else device,
                dtype=w.dtype if dtype is None else dtype,
            )
            for _ in range(self.num_layers)
        )

    def _layers(self) -> list[tuple[torch.Tensor, ...]]:
        g = self.gru
        return [
            (
                getattr(g, f"weight_ih_l{i}"),
                getattr(g, f"weight_hh_l{i}"),
                getattr(g, f"bias_ih_l{i}"),
                getattr(g, f"bias_hh_l{i}"),
            )
            for i in range(self.num_layers)
        ]

    def step(self, inp: torch.Tensor, hidden: Hidden) -> tuple[torch.Tensor, Hidden]:
        out = []
        h = inp
        for (w_ih, w_hh, b_ih, b_hh), h_prev in zip(self._layers(), hidden):
            h = torch.gru_cell(h, h_prev, w_ih, w_hh, b_ih, b_hh)
            out.append(h)
        return self.head(h), tuple(out)

    def signature(self) -> dict:
        return {
            **super().signature(),
            "hidden_size": self.hidden_size,
            "num_layers": self.num_layers,
        }


# ---------------------------------------------------------------------- the group update


@dataclass(frozen=True)
class _Block:
    """One run of the flat state updated the same way (a factor, or merged ``R^n`` factors)."""

    factor: LieGroup | None  # None: a merged run of R^n factors
    element: slice  # in the flat element
    tangent: slice
    rule: str


def _parse_rules(group: LieGroup, update: str | Mapping | Sequence | None) -> tuple[str, ...]:
    """One rule per factor from a rule, a ``{name or index: rule}`` mapping or a sequence."""
    names = factor_names(group)
    n = len(names)
    if update is None:
        rules = ["residual"] * n
    elif isinstance(update, str):
        rules = [update] * n
    elif isinstance(update, Mapping):
        rules = ["residual"] * n
        for key, rule in update.items():
            if isinstance(key, str) and key in names:
                i = names.index(key)
            elif isinstance(key, int) or (isinstance(key, str) and key.lstrip("-").isdigit()):
                i = int(key)
                if not -n <= i < n:
                    raise ValueError(f"update: {group!r} has {n} factor(s), no factor {i}.")
            else:
                raise ValueError(
                    f"update names a factor {key!r} that {group!r} does not have; its factors "
                    f"are {list(names)} (or indices 0..{n - 1})."
                )
            rules[i] = rule
    else:
        rules = list(update)
        if len(rules) != n:
            raise ValueError(
                f"update gives {len(rules)} rule(s) for the {n} factor(s) {list(names)}."
            )
    for name, rule in zip(names, rules):
        if rule not in UPDATE_RULES:
            raise ValueError(
                f"update rule {rule!r} for factor {name!r} is not one of {UPDATE_RULES} "
                "(residual: x·exp(v); absolute: x = exp(v), for R^n x = v)."
            )
    return tuple(rules)


def _blocks(group: LieGroup, rules: Sequence[str]) -> list[_Block]:
    factors = group.factors if isinstance(group, Product) else (group,)
    blocks: list[_Block] = []
    el = tan = 0
    for f, rule in zip(factors, rules):
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


def _factor(group: LieGroup, name: str) -> LieGroup:
    if isinstance(group, Product):
        return group.factors[factor_names(group).index(name)]
    return group


def _element_slice(group: LieGroup, name: str) -> slice:
    if isinstance(group, Product):
        return group.element_slice(factor_names(group).index(name))
    return slice(0, math.prod(group.element_shape))


def _embed_is_flatten(group: LieGroup) -> bool:
    """Whether ``embed`` of every factor is its flattened element (SO(3), R^n; not SE(3)).

    Checked once, exactly, on two random elements in float64; the rollout then feeds the flat
    state to the core without slicing and concatenating the factors' embeddings every step.
    """
    factors = group.factors if isinstance(group, Product) else (group,)
    gen = torch.Generator().manual_seed(0)
    for f in factors:
        if isinstance(f, Euclidean):
            continue
        if f.embedding_dim != math.prod(f.element_shape):
            return False
        x = f.random((2,), generator=gen, dtype=torch.float64)
        if not torch.equal(f.embed(x), x.flatten(1)):
            return False
    return True


def _parse_innovation(group, measurement_dim, innovation) -> dict[str, tuple[int, int]]:
    """``{factor name: (start, stop)}`` checked against the group and the measurement size."""
    if not innovation:
        return {}
    names = factor_names(group)
    out = {}
    for name, span in dict(innovation).items():
        if name not in names:
            raise ValueError(
                f"innovation names a factor {name!r} that {group!r} does not have; its factors "
                f"are {list(names)}."
            )
        f = _factor(group, name)
        try:
            a, b = (int(i) for i in span)
        except (TypeError, ValueError):
            raise ValueError(
                f"innovation[{name!r}] must be (start, stop) in y, got {span!r}."
            ) from None
        if not (0 <= a < b <= measurement_dim and b - a == f.embedding_dim):
            raise ValueError(
                f"innovation[{name!r}] = ({a}, {b}) must be a span of y (size {measurement_dim}) "
                f"of the factor's embedding_dim = {f.embedding_dim} entries."
            )
        out[name] = (a, b)
    return out


def _parse_relative(group, innovation, relative_only) -> tuple[str, ...]:
    """The relative-only factor names, each checked to have an innovation span."""
    names = tuple(relative_only or ())
    for name in names:
        if name not in factor_names(group):
            raise ValueError(
                f"relative_only names a factor {name!r} that {group!r} does not have; its "
                f"factors are {list(factor_names(group))}."
            )
        if name not in innovation:
            raise ValueError(
                f"relative_only factor {name!r} has no innovation span: the core would not see "
                "it at all. Add it to innovation ({name: [start, stop]} in y) or drop it."
            )
    return names


def _kept_columns(group, context_dim, innovation, relative) -> tuple:
    """Index tensors of the embedding and (y, u) columns the core reads (``None``: all)."""
    if not relative:
        return None, None
    emb = torch.ones(group.embedding_dim, dtype=torch.bool)
    ctx = torch.ones(context_dim, dtype=torch.bool)
    for name in relative:
        if isinstance(group, Product):
            emb[group.embedding_slice(factor_names(group).index(name))] = False
        else:
            emb[:] = False
        a, b = innovation[name]
        ctx[a:b] = False
    return emb.nonzero().flatten(), ctx.nonzero().flatten()


def core_input_size(
    group: LieGroup,
    measurement_dim: int,
    input_dim: int = 0,
    innovation: Mapping[str, Sequence[int]] | None = None,
    relative_only: Sequence[str] = (),
) -> int:
    """The size of what the core reads per step: ``embed(xhat)``, ``y`` and ``u`` (less the
    relative-only columns) and the innovation's tangent vectors. Checks the arguments."""
    innov = _parse_innovation(group, measurement_dim, innovation)
    relative = _parse_relative(group, innov, relative_only)
    emb, ctx = _kept_columns(group, measurement_dim + input_dim, innov, relative)
    return (
        (group.embedding_dim if emb is None else len(emb))
        + (measurement_dim + input_dim if ctx is None else len(ctx))
        + sum(_factor(group, name).tangent_dim for name in innov)
    )


# ---------------------------------------------------------------------- the observer


class ObserverState(NamedTuple):
    """The online state: the estimate ``(B, *element_shape)`` and the core's hidden state."""

    estimate: torch.Tensor
    hidden: Hidden


class ResidualObserver(nn.Module):
    """The paper's observer on ``group``; see the module docstring.

    Args:
        group: the state's group (any :class:`groups.LieGroup`).
        measurement_dim: size ``l`` of a measurement ``y``.
        input_dim: size ``m`` of an input ``u`` (0: no input).
        core: a :class:`RecurrentCore` with ``input_size = embedding_dim + l + m`` (plus the
            innovation's tangent dimensions) and
            ``output_size = tangent_dim``; default a :class:`GRUCore` of ``hidden_size`` x
            ``num_layers``.
        update: ``"residual"`` / ``"absolute"`` for every factor, or a mapping ``{factor name or
            index: rule}`` (unnamed factors default to residual), or one rule per factor.
        innovation: ``{factor name: (start, stop)}``: ``y[..., start:stop]`` is the embedding
            of that factor, measured; the core also reads ``rminus(m_f, xhat_f)`` per factor
            (see the module docstring). ``None`` (default): the paper's inputs.
        relative_only: factor names (each with an ``innovation`` span) whose absolute estimate
            and measurement the core does not read (see the module docstring).
        state_dtype: dtype of the group state (float64 default); the network keeps its own.
    """

    def __init__(
        self,
        group: LieGroup,
        measurement_dim: int,
        input_dim: int = 0,
        core: RecurrentCore | None = None,
        *,
        hidden_size: int = 512,
        num_layers: int = 2,
        update: str | Mapping | Sequence | None = None,
        innovation: Mapping[str, Sequence[int]] | None = None,
        relative_only: Sequence[str] = (),
        state_dtype: torch.dtype = torch.float64,
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
        self.group = group
        self.measurement_dim = measurement_dim
        self.input_dim = input_dim
        self.state_dtype = state_dtype
        self.rules = _parse_rules(group, update)
        self._blocks = _blocks(group, self.rules)
        self._embed_is_flat = _embed_is_flatten(group)
        self._numel = math.prod(group.element_shape)
        self.innovation = _parse_innovation(group, measurement_dim, innovation)
        self._innov = [
            (_factor(group, name), _element_slice(group, name), slice(a, b))
            for name, (a, b) in self.innovation.items()
        ]
        innov_dim = sum(f.tangent_dim for f, _, _ in self._innov)
        self.relative_only = _parse_relative(group, self.innovation, relative_only)
        keep_embedding, keep_context = _kept_columns(
            group, measurement_dim + input_dim, self.innovation, self.relative_only
        )
        # column indices of embed(x) and of (y, u) that the core reads; None: all of them
        self.register_buffer("_keep_embedding", keep_embedding, persistent=False)
        self.register_buffer("_keep_context", keep_context, persistent=False)
        in_size = core_input_size(
            group, measurement_dim, input_dim, self.innovation, self.relative_only
        )
        if core is None:
            core = GRUCore(in_size, group.tangent_dim, hidden_size, num_layers)
        if not isinstance(core, RecurrentCore):
            raise TypeError(f"core must be a RecurrentCore, got {type(core).__name__}.")
        if core.input_size != in_size or core.output_size != group.tangent_dim:
            raise ValueError(
                f"core maps {core.input_size} -> {core.output_size}, but the observer needs "
                f"{in_size} (embedding_dim + measurement_dim + input_dim + innovation's tangent "
                f"dims = {group.embedding_dim} + {measurement_dim} + {input_dim} + {innov_dim}"
                + (f", less relative_only {list(self.relative_only)}" if self.relative_only else "")
                + f") -> tangent_dim = {group.tangent_dim}."
            )
        self.core = core
        self._compiled_step = None

    def compile_step(self, **options) -> ResidualObserver:
        """Compiles the per-step function with ``torch.compile`` for the rollouts that record
        gradients (training); rollouts without gradients (evaluation, online use) stay eager.

        The step is a few dozen small kernels (the core's cells, the group update, the
        innovation's log); compiled, they fuse, and the backward pass with them. Measured on 2
        CPU cores, 1 thread, 2x128 on the rigid body: 1.22x faster at batch 256 (1.42x with
        innovation inputs), 1.36x at batch 64 (1.77x with innovation inputs), after about 45 s
        of compilation (once per batch shape); the losses equal the eager ones to six digits
        (``benchmarks/results/observer.md``). Needs a C++
        compiler on the CPU. ``options`` go to ``torch.compile`` (default ``dynamic=False``).
        Returns ``self``.
        """
        self._compiled_step = torch.compile(self._step, **{"dynamic": False, **options})
        return self

    # ------------------------------------------------------------------ description

    @property
    def net_dtype(self) -> torch.dtype:
        return next(self.core.parameters()).dtype

    @property
    def device(self) -> torch.device:
        return next(self.core.parameters()).device

    def signature(self) -> dict:
        """What a checkpoint must match to load into this observer (JSON-able)."""
        sig = {
            "group": repr(self.group),
            "measurement_dim": self.measurement_dim,
            "input_dim": self.input_dim,
            "update": list(self.rules),
            "innovation": {k: list(v) for k, v in self.innovation.items()},
            "core": self.core.signature(),
        }
        if self.relative_only:  # only when used: older checkpoints keep matching
            sig["relative_only"] = list(self.relative_only)
        return sig

    def extra_repr(self) -> str:
        return (
            f"group={self.group!r}, measurement_dim={self.measurement_dim}, "
            f"input_dim={self.input_dim}, update={list(self.rules)}, "
            f"state_dtype={self.state_dtype}"
        )

    # ------------------------------------------------------------------ the hot path (unchecked)

    def _embed(self, x: torch.Tensor) -> torch.Tensor:
        """``embed`` of a flat state ``(B, numel)`` -> ``(B, embedding_dim)``."""
        if self._embed_is_flat:  # e.g. SO(3) x R^n: the flat element is its embedding
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

    def _step(self, x: torch.Tensor, hidden: Hidden, context: torch.Tensor, measured=()):
        """One unchecked step.

        ``x``: the flat state ``(B, numel)`` in the state dtype; ``context``: ``(B, l + m)`` in the
        network dtype (less the relative-only columns); ``measured``: the step's measured factor
        elements (innovation only).
        """
        net = context.dtype
        e = self._embed(x)
        if self._keep_embedding is not None:
            e = e.index_select(-1, self._keep_embedding)
        parts = [e.to(net), context]
        for (f, xs, _), m in zip(self._innov, measured):
            parts.append(f.rminus(m, x[:, xs].unflatten(-1, f.element_shape)).to(net))
        v, hidden = self.core.step(torch.cat(parts, dim=-1), hidden)
        return self._update(x, v.to(x.dtype)), hidden

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
        if not bool(torch.isfinite(context).all()):
            raise ValueError("measurements/inputs hold NaN or Inf; the observer needs finite data.")
        if self._keep_context is not None:
            context = context.index_select(-1, self._keep_context)
        return context.transpose(0, 1).contiguous()

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
        )
        return ObserverState(x.view(x.shape[0], *self.group.element_shape), hidden)

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
        step = self._step
        if self._compiled_step is not None and torch.is_grad_enabled():
            step = self._compiled_step
        for c, m in zip(steps, measured):
            x, hidden = step(x, hidden, c, m)
            xs.append(x)
        est = torch.stack(xs, dim=1).unflatten(-1, self.group.element_shape)
        if return_state:
            return est, ObserverState(x.view(n, *self.group.element_shape), hidden)
        return est
