"""The axiom suite of ``groups.testing`` over every group the library ships, plus pinned edge cases.

One test per group x dtype x batch shape x property, so a failure names all four in its id
(``test_axiom[SE3()-float32-(3, 1, 2)-log_exp]``). The deterministic adversarial grid (every angle
of Theseus' list with every translation magnitude) runs once per group and dtype, with the
``()`` batch shape. Inapplicable combinations (``matrix_exp`` on a group that is not a
:class:`~groups.MatrixLieGroup`, ``gradcheck`` in float32) are not generated at all.
"""

from __future__ import annotations

import math

import hypothesis
import pytest
import torch
from hypothesis import strategies as st

from groups import SE2, SE3, SE23, SO2, SO3, Euclidean, LieGroup, MatrixLieGroup, Product
from groups.testing import (
    BATCH_SHAPES,
    CHECKS,
    TOLERANCES,
    batch_shapes,
    check_group,
    elements,
    tangent_vectors,
)

SHIPPED: list[LieGroup] = [
    SO2(),
    SO3(),
    SE2(),
    SE3(),
    SE23(),
    Euclidean(3),
    Product(SO3(), Euclidean(3), Euclidean(3), Euclidean(3)),  # the paper's group
    Product(SE3(), Euclidean(2)),
]
DTYPES = (torch.float32, torch.float64)


def _dtype_id(dtype: torch.dtype) -> str:
    return str(dtype).removeprefix("torch.")


def _axiom_params() -> list:
    params = []
    for group in SHIPPED:
        for dtype in DTYPES:
            for bs in BATCH_SHAPES:
                for prop in CHECKS:
                    matrix_only = prop in ("matrix_exp", "matrix_compose")
                    if matrix_only and not isinstance(group, MatrixLieGroup):
                        continue
                    if prop == "gradcheck" and dtype != torch.float64:
                        continue
                    ids = f"{group!r}-{_dtype_id(dtype)}-{bs}-{prop}"
                    params.append(pytest.param(group, dtype, bs, prop, id=ids))
    return params


@pytest.mark.parametrize("group, dtype, batch_shape, prop", _axiom_params())
def test_axiom(group: LieGroup, dtype: torch.dtype, batch_shape: tuple, prop: str, device) -> None:
    result = CHECKS[prop](
        group, dtype=dtype, batch_shape=batch_shape, grid=batch_shape == (), device=device
    )
    assert not result.skipped, result.skipped
    assert result.worst_ratio <= 1.0, str(result)


def test_check_group_is_one_call_over_everything() -> None:
    """The public entry point runs every property for every dtype and batch shape."""
    G = Product(SO3(), Euclidean(3), Euclidean(3), Euclidean(3))
    results = check_group(G, max_examples=2)
    seen = {(r.prop, r.dtype, r.batch_shape) for r in results}
    assert seen == {(p, d, bs) for p in CHECKS for d in DTYPES for bs in BATCH_SHAPES}
    assert all(r.worst_ratio <= 1.0 for r in results)
    assert {r.prop for r in results if r.skipped} == {"matrix_exp", "matrix_compose", "gradcheck"}


# ---------------------------------------------------------------------------------- strategies


@pytest.mark.parametrize("group", SHIPPED, ids=repr)
@hypothesis.settings(max_examples=8, deadline=None)
@hypothesis.given(data=st.data())
def test_random_batch_shapes(group: LieGroup, data) -> None:
    """Every operation keeps any batch shape drawn by ``batch_shapes()``."""
    bs = data.draw(batch_shapes(), label="batch shape")
    dtype = data.draw(st.sampled_from(DTYPES), label="dtype")
    x = data.draw(elements(group, batch_shape=bs, dtype=dtype), label="x")
    v = data.draw(tangent_vectors(group, batch_shape=bs, dtype=dtype), label="v")
    k, el = group.tangent_dim, tuple(group.element_shape)
    assert x.shape == (*bs, *el) and v.shape == (*bs, k)
    assert group.exp(v).shape == (*bs, *el)
    assert group.log(x).shape == (*bs, k)
    assert group.rplus(x, v).shape == (*bs, *el)
    assert group.embed(x).shape == (*bs, group.embedding_dim)
    assert group.adjoint(x).shape == (*bs, k, k)
    assert group.membership_error(x).shape == bs
    assert float(group.membership_error(group.rplus(x, v)).max()) <= TOLERANCES[dtype].member


def test_tangent_vectors_reach_the_adversarial_cases() -> None:
    """The strategy produces an angle of exactly pi, and a tiny rotation with a huge translation."""
    settings = hypothesis.settings(max_examples=500, database=None)
    v = hypothesis.find(
        tangent_vectors(SO3(), dtype=torch.float64),
        lambda v: abs(float(v.norm()) - math.pi) < 1e-15,
        settings=settings,
    )
    assert abs(float(v.norm()) - math.pi) < 1e-15
    v = hypothesis.find(
        tangent_vectors(SE3(), dtype=torch.float64),
        lambda v: 0 < float(v[3:].norm()) < 1e-2 and float(v[:3].norm()) > 100,
        settings=settings,
    )
    assert float(v[3:].norm()) < 1e-2 and float(v[:3].norm()) > 100


# ---------------------------------------------------------------------------------- SO(3) pinned


def _rotation_by_pi(axis: torch.Tensor) -> torch.Tensor:
    """``2 n n^T - I``: the rotation by exactly pi about the unit vector ``n``."""
    n = axis / axis.norm()
    return 2.0 * torch.outer(n, n) - torch.eye(3, dtype=axis.dtype)


PI_AXES = [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (1.0, 1.0, 0.0), (0.3, -0.5, 0.8)]


@pytest.mark.parametrize("dtype", DTYPES, ids=_dtype_id)
@pytest.mark.parametrize("axis", PI_AXES, ids=str)
def test_so3_log_at_exactly_pi(dtype: torch.dtype, axis: tuple) -> None:
    G = SO3()
    R = _rotation_by_pi(torch.tensor(axis, dtype=torch.float64)).to(dtype)
    w = G.log(R)
    eps = torch.finfo(dtype).eps
    assert abs(float(w.double().norm()) - math.pi) <= 10 * eps
    n = torch.tensor(axis, dtype=torch.float64)
    n = n / n.norm()
    assert abs(abs(float(w.double() @ n)) - math.pi) <= 10 * eps  # along the axis, either sign
    assert float((G.exp(w) - R).abs().max()) <= 10 * eps


@pytest.mark.parametrize("dtype", DTYPES, ids=_dtype_id)
@pytest.mark.parametrize(
    "v",
    [(0.0, 0.0, 0.0), (math.pi, 0.0, 0.0), (0.0, 0.0, -math.pi), (1.0, 2.0, 2.0)],
    ids=["zero", "pi-x", "minus-pi-z", "pi-oblique"],
)
def test_so3_gradients_finite_at_zero_and_pi(dtype: torch.dtype, v: tuple) -> None:
    G = SO3()
    t = torch.tensor(v, dtype=torch.float64)
    if t.norm() > 0:
        t = t / t.norm() * math.pi
    for fn in (lambda v_: G.exp(v_).sum(), lambda v_: G.log(G.exp(v_)).sum()):
        vr = t.to(dtype).requires_grad_(True)
        (g,) = torch.autograd.grad(fn(vr), vr)
        assert torch.isfinite(g).all(), g
    # and the gradient of log with respect to the matrix entries, at R exactly
    R = G.exp(t.to(dtype)).detach().requires_grad_(True)
    (g,) = torch.autograd.grad(G.log(R).sum(), R)
    assert torch.isfinite(g).all(), g
