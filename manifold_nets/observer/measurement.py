"""What the observer reads: the measurement ``y``, the input ``u``, and the factors ``y`` measures.

:class:`Measurement` describes the data: ``dim`` (``l``, the size of ``y``), ``input_dim``
(``m``) and ``factors = {name: (start, stop)}``, the spans of ``y`` holding a factor's embedding
directly (the rigid body's ``y`` starts with ``vec R^m`` and ``p^m``). For each measured factor
the step forms the *innovation* ``nu_f = log(xhat_f^-1 m_f)`` from the prediction to the measured
element, which features (:class:`~manifold_nets.observer.features.Innovation`) and heads (the
gain, the centring) read.

:class:`RobustMeasurement` adds learned robust weights (an M-estimator's weight function per
measured factor, :class:`~manifold_nets.observer.robust.RobustWeights`, the identity when new):
``nu_f <- w_f(||nu_f||) nu_f``, and the measured columns of ``y`` the features read become the
measurement that innovation implies, ``xhat_f exp(nu_f)``: a learned gate on implausible
measurements.

Per step the measurement makes the :class:`StepView` every feature and head reads.
"""

from __future__ import annotations

from collections.abc import Mapping
import torch

from groups.so3_kernels import records

from .fused import fusable_innovations, fused_features, fused_innovations, gradient_layout
from .piece import Piece, check_factor, check_int, check_number, check_spans
from .robust import MAX_SIZE, RobustWeights, safe_norm

__all__ = ["DeferredView", "Measurement", "RobustMeasurement", "StepView"]


class StepView:
    """What one step's features and heads read.

    ``x``: the prediction ``x^-`` ``(B, numel)`` in the state dtype; ``yu``: ``(y, u)``
    ``(B, l + m)`` in the network dtype (measured columns as the core reads them); ``nu``: the
    innovations ``(B, tangent_dim_f)`` per measured factor, in the network dtype; ``nu_flat``
    (when the measurement made them at once) the same concatenated, ``(B, innovation_dim)``.
    Given ``nu_flat`` and ``nu=None``, ``nu`` is split from it when first read (the paper's
    head and the innovation feature read ``nu_flat`` only: no split, no autograd node).
    """

    __slots__ = ("x", "yu", "_nu", "measurement", "nu_flat")

    def __init__(self, x: torch.Tensor, yu: torch.Tensor, nu: list[torch.Tensor] | None,
                 measurement: Measurement, nu_flat: torch.Tensor | None = None):
        self.x, self.yu, self._nu, self.measurement, self.nu_flat = x, yu, nu, measurement, nu_flat

    @property
    def nu(self) -> list[torch.Tensor]:
        if self._nu is None:
            self._nu = list(self.nu_flat.split(self.measurement._widths, dim=-1))
        return self._nu

    def cat_features(self, features) -> torch.Tensor:
        """The core's input ``z = cat(f(self) for f in features)``."""
        return torch.cat([f(self) for f in features], dim=-1)

    def exact(self) -> StepView:
        """The view had each measured factor been measured exactly at its prediction: the
        innovations zero and the measured columns the prediction's embedding."""
        m = self.measurement
        yu = self.yu.clone()
        for (f, xs, ys) in m.spans:
            yu[:, ys] = f.embed(self.x[:, xs].unflatten(-1, f.element_shape)).reshape(
                self.x.shape[0], -1
            ).to(yu.dtype)
        return StepView(self.x, yu, [torch.zeros_like(nu) for nu in self.nu], m)


class DeferredView(StepView):
    """A :class:`StepView` whose innovations are made when first read (by
    :meth:`Measurement.view`), for an observer whose features are the paper's embedding and
    readings and the innovation feature, over a fusable measurement, and whose head reads
    nothing else (:func:`~manifold_nets.observer.features.reads_as_one`): its
    :meth:`cat_features` makes them all as one autograd node
    (:func:`~manifold_nets.observer.fused.fused_features`), the same values."""

    __slots__ = ("_measured", "_made")

    def __init__(self, x, yu, measurement, measured):  # (nu_flat is a property here)
        self.x, self.yu, self.measurement, self._measured, self._made = (
            x, yu, measurement, measured, None)

    def _view(self) -> StepView:
        if self._made is None:
            self._made = self.measurement.view(self.x, self.yu, self._measured)
        return self._made

    @property
    def nu(self) -> list[torch.Tensor]:
        return self._view().nu

    @property
    def nu_flat(self) -> torch.Tensor | None:
        return self._view().nu_flat

    def cat_features(self, features) -> torch.Tensor:
        # (not while torch.compile traces: dynamo refuses one tensor given twice to a Function)
        if (self._made is None and self.measurement._fused and records(self.x)
                and not torch.compiler.is_compiling()):
            return fused_features(self.measurement, self.x, self.yu, self._measured)
        self._view()  # the innovations first, as Measurement.view makes them
        return super().cat_features(features)


class Measurement(Piece):
    """The measurement's size, the input's size and the factors ``y`` measures directly.

    Args:
        dim: ``l``, the size of a measurement ``y`` (>= 1).
        input_dim: ``m``, the size of an input ``u`` (0: none).
        factors: ``{factor name: (start, stop)}``, ``y[start:stop]`` that factor's embedding.
    """

    kind, name = "measurement", "measurement"

    def __init__(self, dim: int, input_dim: int = 0, factors: Mapping[str, tuple] | None = None):
        super().__init__()
        self.dim = check_int("Measurement: dim", dim, 1)
        self.input_dim = check_int("Measurement: input_dim", input_dim, 0)
        self.factors = check_spans("measurement factors", factors, "y")

    def bind(self, group, measurement=None) -> Measurement:
        for fname, (a, b) in self.factors.items():
            check_factor("measurement factors", group, fname)
            dim = group.factor(fname).embedding_dim
            if not (0 <= a < b <= self.dim and b - a == dim):
                raise ValueError(
                    f"measurement factors[{fname!r}] = ({a}, {b}) must be a span of y (size "
                    f"{self.dim}) of the factor's embedding_dim = {dim} entries."
                )
        self.group = group
        self.spans = [
            (group.factor(n), group.element_slice(n), slice(a, b))
            for n, (a, b) in self.factors.items()
        ]
        self.innovation_dim = sum(group.factor(n).tangent_dim for n in self.factors)
        self._widths = [f.tangent_dim for f, _, _ in self.spans]
        self._fused = fusable_innovations(self)
        self._layout = gradient_layout(self) if self._fused else ()
        return self

    def settings(self) -> dict:
        return {"dim": self.dim, "input_dim": self.input_dim,
                "factors": {k: list(v) for k, v in self.factors.items()}}

    def elements(self, ys: torch.Tensor) -> list[torch.Tensor]:
        """The measured factor elements ``(..., *element_shape)`` from ``(y, u)`` ``(..., l + m)``
        in the state dtype, as given."""
        return [f.unembed(ys[..., s]) for f, _, s in self.spans]

    def innovations(self, x: torch.Tensor, measured) -> list[torch.Tensor]:
        """``log(xhat_f^-1 m_f)`` per measured factor, in the state dtype."""
        return [
            f.rminus(m, x[:, xs].unflatten(-1, f.element_shape))
            for (f, xs, _), m in zip(self.spans, measured)
        ]

    def deferred_view(self, x: torch.Tensor, yu: torch.Tensor, measured) -> StepView:
        """:meth:`view`, its innovations made when first read (:class:`DeferredView`)."""
        return DeferredView(x, yu, self, measured)

    def view(self, x: torch.Tensor, yu: torch.Tensor, measured) -> StepView:
        """The step's view at the prediction ``x`` (flat, state dtype) of ``(y, u)`` ``yu``
        (network dtype) and the measured elements ``measured`` (state dtype)."""
        if self._fused and records(x):  # one autograd node for them all (.fused)
            flat = fused_innovations(self, x, measured, yu.dtype)
            return StepView(x, yu, None, self, flat)  # nu split when read
        nu = self.innovations(x, measured)
        return StepView(x, yu, [n.to(yu.dtype) for n in nu], self)


class RobustMeasurement(Measurement):
    """A :class:`Measurement` whose innovations pass learned robust weights (module docstring).

    Args:
        dim, input_dim, factors: as :class:`Measurement` (at least one factor).
        width: steps of each learned weight function (>= 1).
        span: where the steps start, evenly over ``[0, span]`` (> 0).
    """

    name = "robust"

    def __init__(self, dim, input_dim=0, factors=None, width: int = 16, span: float = 4.0):
        super().__init__(dim, input_dim, factors)
        if not self.factors:
            raise ValueError(
                "a robust measurement weighs the innovations of the measured factors, but it "
                "names none; give factors ({R: [0, 9], p: [9, 12]}) or use a plain measurement."
            )
        width = check_int("robust measurement: width", width, 1, high=MAX_SIZE)
        span = check_number("robust measurement: span", span, 1e-12, 1e12)
        self.robust = RobustWeights(len(self.factors), width, span)

    def settings(self) -> dict:
        return {**super().settings(), "width": self.robust.width, "span": self.robust.span}

    def view(self, x, yu, measured) -> StepView:
        nu = self.innovations(x, measured)
        norms = torch.stack([safe_norm(n) for n in nu], dim=-1)
        w = self.robust(norms.to(yu.dtype)).to(norms.dtype)
        nu = [n * w[:, i : i + 1] for i, n in enumerate(nu)]
        yu = yu.clone()
        for (f, xs, ys), n in zip(self.spans, nu):
            m = f.rplus(x[:, xs].unflatten(-1, f.element_shape), n)
            yu[:, ys] = f.embed(m).reshape(x.shape[0], -1).to(yu.dtype)
        return StepView(x, yu, [n.to(yu.dtype) for n in nu], self)

    def widen(self, state: dict, prefix: str, old: dict | None) -> dict:
        """From a plain measurement of the same factors: the weights start as the identity."""
        if old is not None and old.get("type") == "robust":
            return state
        new = RobustWeights(self.robust.channels, self.robust.width, self.robust.span)
        new = new.to(self.robust.amplitude)
        return {**state, **{f"{prefix}robust.{k}": v for k, v in new.state_dict().items()}}
