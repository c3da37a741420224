"""Bad input gets a clear error that names the problem and the fix, for every shipped group.

* wrong trailing shape -> ValueError naming the expected shape ``(*batch, ...)``;
* an integer tensor -> TypeError asking for floating point;
* NaN, a non-member matrix, a reflection (det -1) -> :class:`groups.GroupMembershipError`;
* malformed ``Product`` / ``Euclidean`` constructions and factor look-ups;
* misuse of ``groups.testing.check_group``.
"""

from __future__ import annotations

import math
import re

import pytest
import torch

from groups import (
    SE2,
    SE3,
    SE23,
    SO2,
    SO3,
    Euclidean,
    GroupMembershipError,
    LieGroup,
    Product,
)
from groups.testing import check_group

SHIPPED: list[LieGroup] = [
    SO2(),
    SO3(),
    SE2(),
    SE3(),
    SE23(),
    Euclidean(3),
    Product(SO3(), Euclidean(3), Euclidean(3), Euclidean(3)),
    Product(SE3(), Euclidean(2)),
]
ids = [repr(g) for g in SHIPPED]


def _shape_text(trailing) -> str:
    return "(" + ", ".join(["*batch", *map(str, trailing)]) + ")"


def _wrong(trailing: tuple[int, ...]) -> tuple[int, ...]:
    """A trailing shape one longer in its last dimension."""
    return (2, *trailing[:-1], trailing[-1] + 1)


@pytest.mark.parametrize("group", SHIPPED, ids=ids)
def test_wrong_trailing_shape_names_the_expected_shape(group: LieGroup) -> None:
    el, k, n = tuple(group.element_shape), group.tangent_dim, group.embedding_dim
    x = group.identity((2,))
    bad_v = torch.zeros(_wrong((k,)))
    bad_x = torch.zeros(_wrong(el))
    bad_z = torch.zeros(_wrong((n,)))
    cases = [
        (lambda: group.exp(bad_v), (k,)),
        (lambda: group.rplus(x, bad_v), (k,)),
        (lambda: group.log(bad_x), el),
        (lambda: group.compose(x, bad_x), el),
        (lambda: group.inverse(bad_x), el),
        (lambda: group.embed(bad_x), el),
        (lambda: group.check_member(bad_x), el),
        (lambda: group.from_embedding(bad_z), (n,)),
    ]
    for call, trailing in cases:
        with pytest.raises(ValueError, match=re.escape(_shape_text(trailing))):
            call()


@pytest.mark.parametrize("group", SHIPPED, ids=ids)
def test_integer_dtype_asks_for_floating_point(group: LieGroup) -> None:
    v = torch.zeros(2, group.tangent_dim, dtype=torch.int64)
    x = torch.zeros(2, *group.element_shape, dtype=torch.int32)
    for call in (lambda: group.exp(v), lambda: group.log(x), lambda: group.embed(x)):
        with pytest.raises(TypeError, match="float"):
            call()


@pytest.mark.parametrize("group", SHIPPED, ids=ids)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["float32", "float64"])
def test_nan_is_not_a_member(group: LieGroup, dtype: torch.dtype) -> None:
    x = group.identity((3,), dtype=dtype)
    x[1].view(-1)[0] = math.nan
    with pytest.raises(GroupMembershipError, match="NaN"):
        group.check_member(x)
    z = group.embed(group.identity((3,), dtype=dtype)).clone()
    z[2, -1] = math.inf
    with pytest.raises(GroupMembershipError, match="Inf"):
        group.from_embedding(z)


@pytest.mark.parametrize(
    "group", [g for g in SHIPPED if g.embedding_dim > g.tangent_dim], ids=repr
)
def test_from_embedding_rejects_points_off_the_group(group: LieGroup) -> None:
    gen = torch.Generator().manual_seed(0)
    z = group.embed(group.random((4,), generator=gen, dtype=torch.float64))
    assert torch.equal(group.embed(group.from_embedding(z)), z)  # on the group: accepted
    off = z + 0.1 * torch.randn(z.shape, generator=gen, dtype=torch.float64)
    with pytest.raises(GroupMembershipError, match="not on the group"):
        group.from_embedding(off)
    # a large enough atol accepts rounded data on purpose
    slightly_off = z + 1e-7
    with pytest.raises(GroupMembershipError):
        group.from_embedding(slightly_off)
    group.from_embedding(slightly_off, atol=1e-5)


def test_non_member_matrix_to_so3_from_embedding() -> None:
    z = torch.arange(9.0)  # vec of [[0, 1, 2], [3, 4, 5], [6, 7, 8]]
    with pytest.raises(GroupMembershipError, match="not on the group"):
        SO3().from_embedding(z)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["float32", "float64"])
def test_reflection_is_rejected(dtype: torch.dtype) -> None:
    """Orthogonal with det -1: ``R R^T = I`` holds, only the determinant tells."""
    reflection = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=dtype))
    assert float(SO3().membership_error(reflection)) >= 1.9  # |det - 1| = 2
    with pytest.raises(GroupMembershipError, match="det"):
        SO3().check_member(reflection)
    with pytest.raises(GroupMembershipError):
        SO2().check_member(torch.diag(torch.tensor([1.0, -1.0], dtype=dtype)))
    pose = torch.eye(4, dtype=dtype)
    pose[:3, :3] = reflection
    with pytest.raises(GroupMembershipError):
        SE3().check_member(pose)


def test_product_construction_errors() -> None:
    with pytest.raises(ValueError, match="at least one factor"):
        Product()
    with pytest.raises(TypeError, match="LieGroup"):
        Product(SO3(), 3)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="one distinct name per factor"):
        Product(SO3(), Euclidean(3), names=("R",))
    with pytest.raises(ValueError, match="one distinct name per factor"):
        Product(SO3(), Euclidean(3), names=("R", "R"))
    G = Product(SO3(), Euclidean(3), names=("R", "p"))
    with pytest.raises(KeyError, match="no factor named 'q'"):
        G.factor("q")
    with pytest.raises(IndexError, match="2 factors"):
        G.factor(2)
    with pytest.raises(ValueError, match="needs 2 parts"):
        G.join([torch.eye(3)])
    with pytest.raises(ValueError, match=re.escape("(*batch, 3, 3)")):
        G.join([torch.eye(4), torch.zeros(3)])


@pytest.mark.parametrize("n", [0, -1, 2.5, "3", None])
def test_euclidean_needs_a_positive_integer(n) -> None:
    with pytest.raises(ValueError, match="positive integer"):
        Euclidean(n)  # type: ignore[arg-type]


def test_check_group_misuse() -> None:
    with pytest.raises(ValueError, match="unknown checks"):
        check_group(SO3(), checks=["exp_log", "commutativity"])
    with pytest.raises(TypeError, match="LieGroup"):
        check_group("SO3")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="tolerances"):
        check_group(SO3(), dtypes=(torch.float16,), checks=["exp_log"])
