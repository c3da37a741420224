"""The group update: how the estimate moves by the tangent vector ``v``, factor by factor.

``GroupUpdate(rules={name: rule}, state_dtype=torch.float64)``: each factor of the state's group
(``group.factor_names``; a non-product group is its one factor ``x``) moves by its rule:

* ``"residual"``: ``x_f <- x_f · exp(v_f)`` (``rplus``; for ``R^n`` this is ``x_f + v_f``), the paper's;
* ``"absolute"``: ``x_f <- exp(v_f)`` (for ``R^n`` ``x_f = v_f``: the paper's biases ``b = gamma``);
* ``"left"``: ``x_f <- exp(v_f) · x_f``, a correction in the world frame.

The state is a flat tensor ``(B, numel)`` in ``state_dtype``; consecutive ``R^n`` factors with one
rule are merged into one block, so the update is a few slices and one ``cat``.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass

import torch

from groups import Euclidean, LieGroup
from groups.so3_kernels import records

from .fused import fusable_update, fused_update

__all__ = ["UPDATE_RULES", "GroupUpdate"]

#: The per-factor update rules.
UPDATE_RULES = ("residual", "absolute", "left")


@dataclass(frozen=True)
class _Block:
    """One run of the flat state updated the same way (a factor, or merged ``R^n`` factors)."""

    factor: LieGroup | None  # None: a merged run of R^n factors
    element: slice
    tangent: slice
    rule: str


def _absolute_vector(x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return v


def _flat(factor: LieGroup, t: torch.Tensor) -> torch.Tensor:
    return t.flatten(-len(factor.element_shape)) if len(factor.element_shape) > 1 else t


def _residual(factor: LieGroup, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return _flat(factor, factor.rplus(x.unflatten(-1, factor.element_shape), v))


def _absolute(factor: LieGroup, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return _flat(factor, factor.exp(v))


def _left(factor: LieGroup, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return _flat(factor, factor.compose(factor.exp(v), x.unflatten(-1, factor.element_shape)))


def _move(factor: LieGroup | None, rule: str):
    """``(x_f (B, numel_f), v_f (B, tangent_dim_f)) -> x_f'`` of one block (``None``: R^n)."""
    if factor is None:
        return _absolute_vector if rule == "absolute" else torch.add
    return functools.partial({"residual": _residual, "absolute": _absolute, "left": _left}[rule],
                             factor)


class GroupUpdate:
    """The per-factor update rules and the state's dtype; :meth:`bind` fixes the group.

    Args:
        rules: ``{factor name: "residual" | "absolute" | "left"}``; factors not named are residual.
        state_dtype: dtype of the estimate (``torch.float64`` keeps it on the group to ~1e-14).
    """

    def __init__(self, rules: Mapping[str, str] | None = None, state_dtype=torch.float64):
        if state_dtype not in (torch.float32, torch.float64):
            raise TypeError(
                f"state_dtype must be torch.float32 or torch.float64, got {state_dtype}."
            )
        self.named, self.state_dtype = dict(rules or {}), state_dtype
        for name, rule in self.named.items():
            if rule not in UPDATE_RULES:
                raise ValueError(
                    f"update rule {rule!r} for factor {name!r} is not one of {UPDATE_RULES} "
                    "(residual: x·exp(v); absolute: x = exp(v), for R^n x = v; left: exp(v)·x)."
                )

    def bind(self, group: LieGroup) -> GroupUpdate:
        """Checks the rules against ``group`` and lays out its blocks. Returns ``self``."""
        names = group.factor_names
        unknown = [k for k in self.named if k not in names]
        if unknown:
            raise ValueError(
                f"update names factors {unknown} that {group!r} does not have; its factors are "
                f"{list(names)}."
            )
        self.group, self.numel = group, math.prod(group.element_shape)
        self.rules = tuple(self.named.get(name, "residual") for name in names)
        self.blocks: list[_Block] = []
        el = tan = 0
        for f, rule in zip(group.factors, self.rules):
            numel, tdim, prev = math.prod(f.element_shape), f.tangent_dim, self.blocks[-1:]
            if isinstance(f, Euclidean) and prev and prev[0].factor is None and prev[0].rule == rule:
                start = prev[0]
                self.blocks[-1] = _Block(
                    None, slice(start.element.start, el + numel),
                    slice(start.tangent.start, tan + tdim), rule,
                )
            else:
                vec = isinstance(f, Euclidean)
                self.blocks.append(
                    _Block(None if vec else f, slice(el, el + numel), slice(tan, tan + tdim), rule)
                )
            el, tan = el + numel, tan + tdim
        self._sizes = tuple([b.element.stop - b.element.start for b in self.blocks]), tuple(
            [b.tangent.stop - b.tangent.start for b in self.blocks]
        )
        self._moves = [_move(b.factor, b.rule) for b in self.blocks]  # chosen once, not per step
        self._fused = fusable_update(self)
        return self

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        """``embed`` of a flat state ``(B, numel)`` -> ``(B, embedding_dim)``."""
        if self.group.embedding_is_flat:  # e.g. SO(3) x R^n: the flat element is its embedding
            return x
        parts = []
        for b in self.blocks:
            xf = x[:, b.element]
            if b.factor is not None:
                xf = b.factor.embed(xf.unflatten(-1, b.factor.element_shape))
            parts.append(xf)
        return parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1)

    def __call__(self, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """The flat state ``(B, numel)`` moved by ``v`` ``(B, tangent_dim)`` (any dtype: cast to
        the state's), factor by factor: one autograd node for SO(3) and R^n factors while
        autograd records (:mod:`.fused`)."""
        if self._fused and records(x, v):
            return fused_update(self, x, v)
        return self.generic(x, v.to(x.dtype))

    def generic(self, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """:meth:`__call__` for any factors, with the factors' own operations."""
        if len(self._moves) == 1:
            return self._moves[0](x, v)
        # split: one backward node for all the blocks (a slice each would add one per block)
        xs, vs = x.split(self._sizes[0], dim=-1), v.split(self._sizes[1], dim=-1)
        return torch.cat([move(xf, vf) for move, xf, vf in zip(self._moves, xs, vs)], dim=-1)

    def signature(self) -> list[str]:
        return list(self.rules)
