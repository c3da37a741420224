"""The direct product ``G_1 x ... x G_k`` of any groups, e.g. the paper's SO(3) x R^3 x R^3 x R^3.

An element is the concatenation of the factors' *flattened* elements, ``(*batch, sum numel_i)``;
tangent vectors and embeddings are the concatenations of the factors'. Everything acts factor by
factor. Factors are reachable by index or by name (``names=("R", "p", ...)``), and
``split``/``join`` convert between the flat tensor and the list of factor elements.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from .base import LieGroup

__all__ = ["Product"]


def _offsets(sizes: Sequence[int]) -> list[slice]:
    out, start = [], 0
    for s in sizes:
        out.append(slice(start, start + s))
        start += s
    return out


def _cat(parts: Sequence[torch.Tensor]) -> torch.Tensor:
    """``torch.cat`` on the last dimension after broadcasting the batch dimensions."""
    batch = torch.broadcast_shapes(*(p.shape[:-1] for p in parts))
    return torch.cat([p.expand(*batch, p.shape[-1]) for p in parts], dim=-1)


class Product(LieGroup):
    """Direct product of ``factors`` (each a :class:`LieGroup`), optionally named."""

    def __init__(self, *factors: LieGroup, names: Sequence[str] | None = None):
        if not factors:
            raise ValueError("Product needs at least one factor, e.g. Product(SO3(), Euclidean(3)).")
        for f in factors:
            if not isinstance(f, LieGroup):
                raise TypeError(f"Product factors must be LieGroup instances, got {f!r}.")
        if names is not None:
            names = tuple(names)
            if len(names) != len(factors) or len(set(names)) != len(names):
                raise ValueError(
                    f"Product got {len(factors)} factors but names {names!r}; give one distinct "
                    "name per factor."
                )
        self._factors = tuple(factors)
        self.names = names
        self._numel = [math.prod(f.element_shape) for f in factors]
        self._el = _offsets(self._numel)
        self._tan = _offsets([f.tangent_dim for f in factors])
        self._emb = _offsets([f.embedding_dim for f in factors])
        self.element_shape = (sum(self._numel),)
        self.tangent_dim = sum(f.tangent_dim for f in factors)
        self.embedding_dim = sum(f.embedding_dim for f in factors)
        self.embedding_is_flat = all(f.embedding_is_flat for f in factors)
        self.angle_slices = tuple(
            slice(t.start + a.start, t.start + a.stop)
            for f, t in zip(self.factors, self._tan)
            for a in f.angle_slices
        )

    def __repr__(self) -> str:
        inner = ", ".join(map(repr, self.factors))
        return f"Product({inner}" + (f", names={self.names!r})" if self.names else ")")

    # ------------------------------------------------------------------ the factors view

    @property
    def factors(self) -> tuple[LieGroup, ...]:  # type: ignore[override]
        return self._factors

    @property
    def factor_names(self) -> tuple[str, ...]:  # type: ignore[override]
        return self.names or tuple(f"factor{i}" for i in range(len(self._factors)))

    def tangent_slice(self, key: int | str) -> slice:
        return self._tan[self.index(key)]

    def embedding_slice(self, key: int | str) -> slice:
        return self._emb[self.index(key)]

    def element_slice(self, key: int | str) -> slice:
        return self._el[self.index(key)]

    def split(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The factor elements of ``x``, each ``(*batch, *factor.element_shape)``."""
        self.check_element(x, "split")
        return [x[..., s].unflatten(-1, f.element_shape) for f, s in zip(self.factors, self._el)]

    def join(self, parts: Sequence[torch.Tensor]) -> torch.Tensor:
        """Inverse of :meth:`split`; batch dimensions of the parts broadcast."""
        if len(parts) != len(self.factors):
            raise ValueError(f"{self!r}.join needs {len(self.factors)} parts, got {len(parts)}.")
        flat = []
        for f, p in zip(self.factors, parts):
            f.check_element(p, "join")
            flat.append(p.flatten(p.dim() - len(f.element_shape)) if f.element_shape else p)
        return _cat(flat)

    def get(self, x: torch.Tensor, key: int | str) -> torch.Tensor:
        """Factor ``key`` of the element ``x``."""
        i = self.index(key)
        self.check_element(x, "get")
        return x[..., self._el[i]].unflatten(-1, self.factors[i].element_shape)

    def split_tangent(self, v: torch.Tensor) -> list[torch.Tensor]:
        self.check_tangent(v, "split_tangent")
        return [v[..., s] for s in self._tan]

    def split_embedding(self, z: torch.Tensor) -> list[torch.Tensor]:
        self.check_shape(z, (self.embedding_dim,), "split_embedding", "an embedded element")
        return [z[..., s] for s in self._emb]

    # ------------------------------------------------------------------ minimum API

    def identity(self, batch_shape=(), dtype=torch.float32, device=None) -> torch.Tensor:
        self.check_dtype(dtype, "identity")
        return self.join([f.identity(batch_shape, dtype, device) for f in self.factors])

    def compose(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        self.check_pair(x, y, "compose")
        return self.join([f.compose(a, b) for f, a, b in zip(self.factors, self.split(x), self.split(y))])

    def inverse(self, x: torch.Tensor) -> torch.Tensor:
        return self.join([f.inverse(a) for f, a in zip(self.factors, self.split(x))])

    def exp(self, v: torch.Tensor) -> torch.Tensor:
        return self.join([f.exp(a) for f, a in zip(self.factors, self.split_tangent(v))])

    def log(self, x: torch.Tensor) -> torch.Tensor:
        return _cat([f.log(a) for f, a in zip(self.factors, self.split(x))])

    def rplus(self, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        parts = zip(self.factors, self.split(x), self.split_tangent(v))
        return self.join([f.rplus(a, b) for f, a, b in parts])

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        return _cat([f.embed(a) for f, a in zip(self.factors, self.split(x))])

    def unembed(self, z: torch.Tensor) -> torch.Tensor:
        return self.join([f.unembed(a) for f, a in zip(self.factors, self.split_embedding(z))])

    def membership_error(self, x: torch.Tensor) -> torch.Tensor:
        """The largest membership error over the factors."""
        errs = [f.membership_error(a) for f, a in zip(self.factors, self.split(x))]
        return torch.stack(torch.broadcast_tensors(*errs), dim=-1).amax(dim=-1)

    def adjoint(self, x: torch.Tensor) -> torch.Tensor:
        """Block-diagonal in the factors' adjoints."""
        blocks = [f.adjoint(a) for f, a in zip(self.factors, self.split(x))]
        batch = torch.broadcast_shapes(*(b.shape[:-2] for b in blocks))
        out = x.new_zeros(*batch, self.tangent_dim, self.tangent_dim)
        for s, b in zip(self._tan, blocks):
            out[..., s, s] = b
        return out

    def random(self, batch_shape=(), generator=None, dtype=torch.float32, device=None):
        self.check_dtype(dtype, "random")
        return self.join([f.random(batch_shape, generator, dtype, device) for f in self.factors])
