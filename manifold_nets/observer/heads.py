"""Heads: how the core's step becomes the tangent vector ``v_k``.

A head runs the core on the step's features and reads ``v`` off its output:
``forward(core, features, view, hidden, c) -> (v, hidden)``, with ``features(view)`` the core's
input ``z`` and ``c`` the head's schedule value for the step (or ``None``).

* :class:`PlainHead`: ``v = T(z)``, the paper's.
* :class:`GainHead`: the core outputs an offset ``a`` and a gain ``K`` (``tangent_dim`` x the
  innovation's width) and ``v = a + K nu`` (``offset=False``: ``v = K nu``), a Kalman-type
  update whose gain the network computes.
* :class:`CentredHead`: ``v = T(z) - c_k T(z^0)``, less what the core outputs had each measured
  factor been measured exactly at its prediction (``z^0``: innovations zero). At ``c = 1`` a zero
  innovation moves nothing but the prior, as in every filter's update. ``ramp=K`` raises ``c``
  over the first ``K`` steps, ``c_k = c min(1, k / K)``; ``factors={name: c_f}`` centres some
  factors' components by their own ``c_f``. It wraps a plain or a gain head (``inner``) and
  adds no weight; the core runs on twice the batch.

Every head starts where an untrained observer cannot run away (:meth:`Head.reset`): with a
:class:`~manifold_nets.cores.GRUCore`, the plain head's output layer starts at zero (the
untrained observer holds still, or follows its prior), the gain head's ``K`` starts at zero.
"""

from __future__ import annotations

import torch

from .piece import Piece, check_factor, check_int, check_number

__all__ = ["Head", "PlainHead", "GainHead", "CentredHead"]


class Head(Piece):
    """See the module docstring."""

    kind = "head"
    #: Whether the head needs a prior that predicts the measurement (the observer checks it).
    needs_prediction = False

    def output_size(self, tangent_dim: int, innovation_dim: int) -> int:  # noqa: ARG002
        """How many numbers the core outputs per step."""
        return tangent_dim

    def reset(self, core) -> None:
        """Sets the core's output layer where this head starts (``core.zero_output``)."""
        zero = getattr(core, "zero_output", None)
        if callable(zero):
            zero(0)

    def read(self, out: torch.Tensor, view) -> torch.Tensor:  # noqa: ARG002
        """``v`` from the core's output ``(B, output_size)``."""
        return out

    def forward(self, core, features, view, hidden, c=None):
        out, hidden = core.step(features(view), hidden)
        return self.read(out, view), hidden


class PlainHead(Head):
    """``v = T(z)``."""

    name = "plain"


class GainHead(Head):
    """``v = a + K nu`` (``offset=True``) or ``v = K nu``; needs measured factors."""

    name = "gain"

    def __init__(self, offset: bool = True):
        super().__init__()
        if not isinstance(offset, bool):
            raise ValueError(f"gain head: offset must be true or false, got {offset!r}.")
        self.offset = offset

    def settings(self):
        return {} if self.offset else {"offset": False}

    def bind(self, group, measurement):
        if not measurement.factors:
            raise ValueError(
                "the gain head multiplies a learned gain with the innovation, but the measurement "
                "names no measured factor; give its factors ({R: [0, 9], p: [9, 12]}) or use the "
                "plain head."
            )
        self.n, self.width = group.tangent_dim, measurement.innovation_dim
        return self

    def output_size(self, tangent_dim, innovation_dim):
        return tangent_dim * (int(self.offset) + innovation_dim)

    def reset(self, core):
        zero = getattr(core, "zero_output", None)
        if callable(zero):
            zero(self.n if self.offset else 0)

    def read(self, out, view):
        n, a = self.n, self.n if self.offset else 0
        nu = view.nu[0] if len(view.nu) == 1 else torch.cat(view.nu, dim=-1)
        kv = (out[:, a:].unflatten(-1, (n, self.width)) @ nu.unsqueeze(-1)).squeeze(-1)
        return out[:, :n] + kv if self.offset else kv

    def widen(self, state, prefix, old):
        """From a plain head (with the same core): the offset rows kept, ``K`` zero."""
        if old is not None and old.get("type") == self.name:
            return state
        if not self.offset:
            raise ValueError("a plain head's weights widen only into a gain head with its offset.")
        out = dict(state)
        for key in ("core.head.weight", "core.head.bias"):
            w = state[key]
            if w.shape[0] != self.n:
                raise ValueError(f"{key} has {w.shape[0]} rows, expected {self.n}.")
            k = torch.zeros((self.n * self.width, *w.shape[1:]), dtype=w.dtype, device=w.device)
            out[key] = torch.cat([w, k])
        return out


class CentredHead(Head):
    """``v = inner(T(z)) - c_k T(z^0)``; see the module docstring.

    Args:
        c: the centring in ``[0, 1]``.
        ramp: ``K`` (steps, >= 0): ``c_k = c min(1, k / K)``; 0: ``c`` from the first step.
        factors: ``{factor name: c_f}``, each in ``[0, 1]``: those factors' components are
            centred by ``c_f`` instead (ramped alike).
        inner: the head whose ``v`` is centred (default plain; a gain head with its offset).
    """

    name, needs_prediction = "centred", True

    def __init__(self, c: float, ramp: int = 0, factors: dict | None = None, inner: Head | None = None):
        super().__init__()
        self.c = check_number("centred head: c", c, 0.0, 1.0)
        if not self.c:
            raise ValueError("centred head: c = 0 centres nothing; use the plain head.")
        self.ramp = check_int("centred head: ramp", ramp, 0, " (steps)")
        self.factors = {
            str(n): check_number(f"centred head: factors[{n!r}]", v, 0.0, 1.0)
            for n, v in dict(factors or {}).items()
        }
        self.inner = PlainHead() if inner is None else inner
        if isinstance(self.inner, CentredHead) or not isinstance(self.inner, Head):
            raise ValueError("centred head: inner must be a plain or a gain head.")
        if isinstance(self.inner, GainHead) and not self.inner.offset:
            raise ValueError(
                "centred head: a gain head without offset (v = K nu) is already zero at zero "
                "innovation; centring it changes nothing. Use it alone."
            )

    def settings(self):
        out = {"c": self.c}
        if self.ramp:
            out["ramp"] = self.ramp
        if self.factors:
            out["factors"] = dict(self.factors)
        if not isinstance(self.inner, PlainHead):
            out["inner"] = self.inner.signature()
        return out

    def bind(self, group, measurement):
        self.inner.bind(group, measurement)
        if not measurement.factors:
            raise ValueError(
                "the centred head subtracts the core's output at zero innovation, but the "
                "measurement names no measured factor; give its factors ({R: [0, 9], p: [9, 12]})."
            )
        scale = None
        if self.factors:
            scale = [1.0] * group.tangent_dim
            for n, cf in self.factors.items():
                check_factor("centred head: factors", group, n)
                cols = group.tangent_slice(n)
                scale[cols] = [cf / self.c] * (cols.stop - cols.start)
        self._scale, self.n = scale, group.tangent_dim  # a list, so no change of dtype rounds it
        return self

    def output_size(self, tangent_dim, innovation_dim):
        return self.inner.output_size(tangent_dim, innovation_dim)

    def reset(self, core):
        self.inner.reset(core)

    def schedule(self, k):
        """``c_k`` ``(*k.shape, 1)``."""
        if not self.ramp:
            return k.new_full((*k.shape, 1), self.c)
        return self.c * (k / self.ramp).clamp(max=1.0)[..., None]

    def forward(self, core, features, view, hidden, c=None):
        z, z0 = features(view), features(view.exact())
        b = z.shape[0]
        out, hidden = core.step(torch.cat((z, z0)), tuple(torch.cat((h, h)) for h in hidden))
        v = self.inner.read(out[:b], view)
        at_zero = out[b:, : self.n]
        if self._scale is not None:
            at_zero = at_zero * at_zero.new_tensor(self._scale)
        return v - c * at_zero, tuple(h[:b] for h in hidden)

    def widen(self, state, prefix, old):
        """From any head: the inner head's widening (the centring adds no weight)."""
        inner_old = old
        if old is not None and old.get("type") == self.name:
            inner_old = old.get("inner", {"type": "plain"})
        return self.inner.widen(state, prefix + "inner.", inner_old)
