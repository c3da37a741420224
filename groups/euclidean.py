"""R^n as a Lie group under addition: the vector factors of a product group (positions, biases).

Elements, tangent vectors and embeddings are all ``(*batch, n)``; ``exp`` and ``log`` are the
identity and ``compose`` is ``+``.
"""

from __future__ import annotations

import torch

from .base import LieGroup

__all__ = ["Euclidean"]


class Euclidean(LieGroup):
    """The additive group ``R^n``."""

    embedding_is_flat = True

    def __init__(self, n: int):
        if not isinstance(n, int) or n < 1:
            raise ValueError(f"Euclidean(n) needs a positive integer n, got {n!r}.")
        self.n = n
        self.element_shape = (n,)
        self.tangent_dim = n
        self.embedding_dim = n

    def __repr__(self) -> str:
        return f"Euclidean({self.n})"

    def identity(self, batch_shape=(), dtype=torch.float32, device=None) -> torch.Tensor:
        self.check_dtype(dtype, "identity")
        return torch.zeros(*batch_shape, self.n, dtype=dtype, device=device)

    def compose(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        self.check_pair(x, y, "compose")
        return x + y

    def inverse(self, x: torch.Tensor) -> torch.Tensor:
        self.check_element(x, "inverse")
        return -x

    def exp(self, v: torch.Tensor) -> torch.Tensor:
        self.check_tangent(v, "exp")
        return v.clone()

    def log(self, x: torch.Tensor) -> torch.Tensor:
        self.check_element(x, "log")
        return x.clone()

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        self.check_element(x, "embed")
        return x

    def unembed(self, z: torch.Tensor) -> torch.Tensor:
        self.check_shape(z, (self.n,), "unembed", "an embedded element")
        return z

    def membership_error(self, x: torch.Tensor) -> torch.Tensor:
        """0 for every finite vector (NaN where the input is not finite)."""
        self.check_element(x, "membership_error")
        return (x - x).abs().sum(-1)

    def rplus(self, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        self.check_element(x, "rplus")
        self.check_tangent(v, "rplus")
        return x + v

    def rminus(self, y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``y - x``."""
        self.check_pair(x, y, "rminus")
        return y - x

    def adjoint(self, x: torch.Tensor) -> torch.Tensor:
        """The identity: R^n is abelian."""
        self.check_element(x, "adjoint")
        eye = torch.eye(self.n, dtype=x.dtype, device=x.device)
        return eye.expand(*x.shape[:-1], self.n, self.n)
