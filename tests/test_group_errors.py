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
from pathlib import Path

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


# ------------------------------------------------------------------ bad arguments


@pytest.mark.parametrize("group", SHIPPED, ids=ids)
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16], ids=["float16", "bfloat16"])
def test_half_precision_is_refused_naming_the_supported_dtypes(group: LieGroup, dtype) -> None:
    """Message: ``SO3.exp expects a tensor of dtype float32 or float64 (the only supported
    dtypes), got torch.float16; convert it first, e.g. with .float() or .double().``"""
    v = torch.zeros(2, group.tangent_dim, dtype=dtype)
    x = group.identity((2,)).to(dtype)
    msg = rf"\.\w+ expects a tensor of dtype float32 or float64 .*got {dtype}"
    for call in (
        lambda: group.exp(v),
        lambda: group.log(x),
        lambda: group.compose(x, x),
        lambda: group.check_member(x),
    ):
        with pytest.raises(TypeError, match=msg):
            call()


@pytest.mark.parametrize("group", SHIPPED, ids=ids)
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16], ids=["float16", "bfloat16"])
def test_identity_and_random_refuse_half_precision(group: LieGroup, dtype) -> None:
    """Message: ``SO3.random expects dtype float32 or float64 (the only
    supported dtypes), got torch.float16; ask for torch.float32 or torch.float64 and convert the
    result afterwards if you need another dtype.``"""
    for where, call in (
        ("identity", lambda: group.identity((2,), dtype=dtype)),
        ("random", lambda: group.random((2,), dtype=dtype)),
    ):
        with pytest.raises(
            TypeError,
            match=rf"^{re.escape(group.name)}\.{where} expects dtype float32 or float64 \(the "
            rf"only supported dtypes\), got {dtype}; ask for torch.float32 or torch.float64",
        ):
            call()
    assert group.identity((2,), dtype=torch.float64).dtype == torch.float64


@pytest.mark.parametrize("group", SHIPPED, ids=ids)
def test_compose_and_between_name_both_batch_shapes(group: LieGroup) -> None:
    """Message: ``SO3.compose: the batch shapes of x (2,) and y (3,) do not broadcast (x has
    shape (2, 3, 3), y (3, 3, 3)); batch dimensions must be equal or 1, ...``"""
    x, y = group.identity((2,)), group.identity((3,))
    for where, call in (("compose", group.compose), ("between", group.between)):
        with pytest.raises(
            ValueError,
            match=rf"\.{where}: the batch shapes of x \(2,\) and y \(3,\) do not broadcast",
        ):
            call(x, y)
    assert group.compose(group.identity((2, 1)), y).shape[:2] == (2, 3)  # broadcasting still works


@pytest.mark.parametrize("group", SHIPPED, ids=ids)
def test_compose_and_between_name_both_dtypes(group: LieGroup) -> None:
    """Message: ``SO3.compose expects x and y of one dtype, got x torch.float32 and y
    torch.float64; convert one first, e.g. y.to(x.dtype).`` (Euclidean used to promote.)"""
    x, y = group.identity((2,)), group.identity((2,), dtype=torch.float64)
    for where, call in (("compose", group.compose), ("between", group.between)):
        with pytest.raises(
            TypeError,
            match=rf"\.{where} expects x and y of one dtype, got x torch.float32 and y torch.float64",
        ):
            call(x, y)


@pytest.mark.parametrize("atol", [-1, -1e-9, math.nan, math.inf, "1e-3", True])
def test_check_member_validates_atol(atol) -> None:
    """Message: ``SO3.check_member: atol must be a finite number >= 0, got -1; pass e.g.
    atol=1e-5, or None for the default (1e-4 in float32, 1e-9 in float64).``"""
    for call in (
        lambda: SO3().check_member(torch.eye(3), atol=atol),
        lambda: SO3().from_embedding(torch.eye(3).flatten(), atol=atol),
    ):
        with pytest.raises(ValueError, match=r"atol must be a finite number >= 0, got "):
            call()
    SO3().check_member(torch.eye(3), atol=0)  # 0 is a valid (strict) tolerance


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["float32", "float64"])
def test_so3_exp_domain_is_documented_and_kept(dtype: torch.dtype) -> None:
    """NaN in, NaN out; below the documented bound sqrt(finfo.max) the rotation by |v|, at and
    above it (the squared angle overflows) a whole number of turns, the identity (issue #36).

    The docstring says: ``NaN in any entry of v gives NaN in its matrix (NaN in, NaN out, never
    an error). An angle whose square overflows, |v| >= sqrt(finfo(dtype).max) ... is taken as a
    whole number of turns``."""
    G = SO3()
    doc = " ".join(G.exp.__doc__.split())
    assert "NaN in, NaN out" in doc and "sqrt(finfo(dtype).max)" in doc
    assert "whole number of turns" in doc
    bound = G.exp_max_norm(dtype)
    assert bound == pytest.approx(1.8e19 if dtype == torch.float32 else 1.3e154, rel=0.05)
    assert "SO3.exp" in (Path(__file__).parents[1] / "docs" / "groups.md").read_text()
    axis = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8]], dtype=dtype)
    inside = G.exp(0.999 * bound * axis)
    assert bool(torch.isfinite(inside).all())
    G.check_member(inside, atol=1e-4)
    eye = torch.eye(3, dtype=dtype).expand(2, 3, 3)
    assert torch.equal(G.exp(1.001 * bound * axis), eye)
    v = torch.tensor([[math.nan, 0.0, 0.0], [0.1, 0.2, 0.3]], dtype=dtype)
    R = G.exp(v)
    assert bool(torch.isnan(R[0]).all()) and bool(torch.isfinite(R[1]).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["float32", "float64"])
def test_log_of_a_reflection_is_documented_and_refused_at_the_door(dtype: torch.dtype) -> None:
    """Message: ``SO3: 1 of 1 element(s) are not on the group (largest membership error 2 >
    atol 0.0001). The worst has det -1 (a reflection: log and exp are undefined for it). ...``"""
    reflection = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=dtype))
    doc = " ".join(SO3.log.__doc__.split())
    assert "undefined" in doc and "from_embedding" in doc and "check_member" in doc
    with pytest.raises(GroupMembershipError, match=r"The worst has det -1 \(a reflection"):
        SO3().from_embedding(reflection.flatten())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("batch", [(), (3,)])
def test_the_generic_adjoint_keeps_the_dtype_and_matches_the_closed_forms(dtype, batch):
    """The base class's adjoint (forward-mode autograd) for a subclass without a closed form:
    with batch shape () a 0-dim tensor's scalar arithmetic once promoted float32 to float64
    under forward AD (SE(3)'s exp then failed on a matrix product of mixed dtypes)."""
    from groups import SE2, SE3, SO2, SO3
    from groups.base import LieGroup

    tol = 2e-6 if dtype == torch.float32 else 1e-12
    for G in (SO2(), SO3(), SE2(), SE3()):
        x = G.random(batch, generator=torch.Generator().manual_seed(0), dtype=dtype)
        generic = LieGroup.adjoint(G, x)
        assert generic.dtype == dtype and generic.shape == (*batch, G.tangent_dim, G.tangent_dim)
        assert float((generic - G.adjoint(x)).abs().max()) < tol, G
