"""The axioms of a group with a matrix form: ``exp`` against the matrix exponential and
``compose`` against the matrix product (:mod:`~groups.testing.properties` lists them with the
others in ``PROPERTIES``)."""

from __future__ import annotations

import math

import torch

from ..base import MatrixLieGroup
from .comparison import Case, magnitude

__all__ = ["matrix_exp", "matrix_compose"]


def _matrix_exp_reference(a: torch.Tensor) -> torch.Tensor:
    """``torch.linalg.matrix_exp`` of ``(*batch, d, d)``, always called on a batch of >= 2.

    torch's unbatched path (a single matrix) picks a degree-8 Taylor polynomial with a wrong
    coefficient for norms around 0.01-0.1 (errors up to 2e-10 in float64, 5e-5 in float32 in
    torch 2.13; pytorch/pytorch#196592). Padding the batch with a zero matrix takes the accurate
    batched path.
    """
    d = a.shape[-1]
    flat = a.reshape(-1, d, d)
    padded = torch.cat((flat, flat.new_zeros(1, d, d)))
    return torch.linalg.matrix_exp(padded)[:-1].reshape(a.shape)


def matrix_exp(c: Case, data) -> None:
    """``exp(v)`` against ``matrix_exp(hat(v))`` in float64, ``vee(hat(v)) = v``; matrix groups."""
    G = c.group
    if not isinstance(G, MatrixLieGroup):
        c.result.skipped = "not a MatrixLieGroup"
        return
    v = c.v(data, "v")
    ref = _matrix_exp_reference(G.hat(v.double()))
    c.shape("hat(v)", G.hat(v), G.element_shape)
    c.close_elements(f"exp(v) in {c.dtype} == matrix_exp(hat(v)) in float64", G.exp(v), ref,
            inputs={"v": v})
    c.close_tangent("vee(hat(v)) == v", G.vee(G.hat(v)), v, inputs={"v": v})


def matrix_compose(c: Case, data) -> None:
    """``compose(x, y)`` is the matrix product where the group has a matrix form: a
    :class:`~groups.MatrixLieGroup`'s elements, or an embedding that is one
    (``embedding_is_matrix``). Without one the suite cannot tell ``compose`` from its opposite
    (``compose(y, x)`` is a valid group too, and the generic adjoint follows it): skipped."""
    G = c.group
    if isinstance(G, MatrixLieGroup):
        def as_matrix(x):
            return x
    elif getattr(G, "embedding_is_matrix", False):
        d = math.isqrt(G.embedding_dim)

        def as_matrix(x):
            return G.embed(x).unflatten(-1, (d, d))
    else:
        c.result.skipped = "no matrix form (embedding_is_matrix is False)"
        return
    x, y = c.x(data, "x"), c.x(data, "y")
    mx, my = as_matrix(x), as_matrix(y)
    c.close("matrix(compose(x, y)) == matrix(x) @ matrix(y)", as_matrix(G.compose(x, y)),
            mx @ my, trailing=2, scale=magnitude(mx, 2) * magnitude(my, 2),
            inputs={"x": x, "y": y})
