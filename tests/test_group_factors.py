"""The factors view over every shipped group: names, positions, slices and ``embedding_is_flat``.

* A non-product group is its single factor ``"x"``, whose slices are the whole element, tangent
  vector and embedding.
* A Product's element, tangent and embedding slices tile the flat tensors in factor order, and
  ``split``, ``split_tangent``, ``split_embedding``, ``get`` and ``embed`` agree with them; an
  unnamed Product's factors are ``factor0``, ``factor1``, ...; a nested Product is one factor of
  the outer one.
* ``index`` takes a name, an index or a negative index; a bad key raises KeyError/IndexError
  naming the factors there are.
* ``embedding_is_flat`` is true exactly for SO2, SO3, Euclidean and products of only those.
"""

from __future__ import annotations

import math
import re

import pytest
import torch

from groups import SE2, SE3, SE23, SO2, SO3, Euclidean, LieGroup, Product

SINGLE: list[LieGroup] = [SO2(), SO3(), SE2(), SE3(), SE23(), Euclidean(3)]
NESTED = Product(Product(SO3(), Euclidean(3), names=("R", "p")), SE2(), Euclidean(2))
PRODUCTS: list[Product] = [
    Product(SO3(), Euclidean(3), Euclidean(3), Euclidean(3), names=("R", "p", "b_w", "b_v")),
    Product(SE3(), Euclidean(2)),  # unnamed
    Product(SO2(), SE23(), Euclidean(1), names=("heading", "state", "bias")),
    NESTED,
]
ALL: list[LieGroup] = [*SINGLE, *PRODUCTS]


def _numel(group: LieGroup) -> int:
    return math.prod(group.element_shape)


# ---------------------------------------------------------------------------------- one factor


@pytest.mark.parametrize("group", SINGLE, ids=repr)
def test_a_non_product_group_is_its_single_factor_x(group: LieGroup) -> None:
    assert group.factors == (group,)
    assert group.factor_names == ("x",)
    for key in ("x", 0, -1):
        assert group.index(key) == 0
        assert group.factor(key) is group
    assert group.element_slice("x") == slice(0, _numel(group))
    assert group.tangent_slice("x") == slice(0, group.tangent_dim)
    assert group.embedding_slice("x") == slice(0, group.embedding_dim)


# ---------------------------------------------------------------------------------- products


def _tile(slices: list[slice], sizes: list[int], total: int) -> None:
    """``slices`` are contiguous, in order, of the given sizes, and cover ``[0, total)``."""
    start = 0
    for s, n in zip(slices, sizes, strict=True):
        assert s == slice(start, start + n), (slices, sizes)
        start += n
    assert start == total


@pytest.mark.parametrize("group", PRODUCTS, ids=repr)
def test_product_slices_tile_in_factor_order(group: Product) -> None:
    keys = range(len(group.factors))
    _tile([group.element_slice(i) for i in keys], [_numel(f) for f in group.factors],
          _numel(group))
    _tile([group.tangent_slice(i) for i in keys], [f.tangent_dim for f in group.factors],
          group.tangent_dim)
    _tile([group.embedding_slice(i) for i in keys], [f.embedding_dim for f in group.factors],
          group.embedding_dim)
    for i, name in enumerate(group.factor_names):  # by name, the same slices
        assert group.element_slice(name) == group.element_slice(i)
        assert group.tangent_slice(name) == group.tangent_slice(i)
        assert group.embedding_slice(name) == group.embedding_slice(i)


@pytest.mark.parametrize("group", PRODUCTS, ids=repr)
def test_split_and_embed_agree_with_the_slices(group: Product) -> None:
    gen = torch.Generator().manual_seed(0)
    x = group.random((2, 3), generator=gen, dtype=torch.float64)
    v = torch.randn(2, 3, group.tangent_dim, generator=gen, dtype=torch.float64)
    z = group.embed(x)
    parts = group.split(x)
    for i, (f, name) in enumerate(zip(group.factors, group.factor_names, strict=True)):
        el = x[..., group.element_slice(name)]
        assert torch.equal(parts[i].reshape(2, 3, -1), el)
        assert torch.equal(group.get(x, name), parts[i])
        assert torch.equal(group.split_tangent(v)[i], v[..., group.tangent_slice(name)])
        assert torch.equal(group.split_embedding(z)[i], z[..., group.embedding_slice(name)])
        assert torch.equal(f.embed(parts[i]), z[..., group.embedding_slice(name)])


def test_names_unnamed_and_nested() -> None:
    assert PRODUCTS[0].factor_names == ("R", "p", "b_w", "b_v")
    assert Product(SE3(), Euclidean(2)).factor_names == ("factor0", "factor1")
    assert NESTED.factor_names == ("factor0", "factor1", "factor2")
    inner = NESTED.factor(0)
    assert inner == Product(SO3(), Euclidean(3), names=("R", "p"))
    assert inner.factor_names == ("R", "p")
    assert NESTED.element_slice(0) == slice(0, 12)
    assert NESTED.tangent_slice("factor1") == slice(6, 9)
    assert NESTED.embedding_slice(-1) == slice(12 + 6, 12 + 6 + 2)


# ---------------------------------------------------------------------------------- index


@pytest.mark.parametrize("group", ALL, ids=repr)
def test_index_by_name_index_and_negative_index(group: LieGroup) -> None:
    k = len(group.factors)
    assert len(group.factor_names) == k
    for i, name in enumerate(group.factor_names):
        assert group.index(name) == i
        assert group.index(i) == i
        assert group.index(i - k) == i
        assert group.factor(name) is group.factors[i]
        assert group.factor(i - k) is group.factors[i]


@pytest.mark.parametrize("group", ALL, ids=repr)
def test_a_bad_key_names_the_factors(group: LieGroup) -> None:
    names = list(group.factor_names)
    k = len(names)
    with pytest.raises(KeyError, match=re.escape(str(names))):
        group.index("no_such_factor")
    for bad in (k, -k - 1, 1.0, True, None):
        with pytest.raises(IndexError, match=re.escape(str(names))):
            group.index(bad)  # type: ignore[arg-type]
    for method in (group.factor, group.element_slice, group.tangent_slice, group.embedding_slice):
        with pytest.raises(KeyError, match="no_such_factor"):
            method("no_such_factor")
        with pytest.raises(IndexError):
            method(k)


# ---------------------------------------------------------------------------------- flat


FLAT = [
    SO2(),
    SO3(),
    Euclidean(1),
    Euclidean(3),
    Product(SO3(), Euclidean(3), Euclidean(3), Euclidean(3)),
    Product(SO2(), Euclidean(2), names=("theta", "p")),
    Product(Product(SO2(), Euclidean(2)), SO3()),
]
NOT_FLAT = [
    SE2(),
    SE3(),
    SE23(),
    Product(SE3(), Euclidean(2)),
    Product(SO3(), SE2()),
    Product(Product(SO2(), SE3()), Euclidean(3)),
]


@pytest.mark.parametrize("group", FLAT + NOT_FLAT, ids=repr)
def test_embedding_is_flat_exactly_for_so2_so3_euclidean_and_their_products(
    group: LieGroup,
) -> None:
    assert group.embedding_is_flat == any(group is g for g in FLAT)
    x = group.random((4,), generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    flat = x.reshape(4, _numel(group))
    if group.embedding_is_flat:
        assert group.embedding_dim == _numel(group)
        assert torch.equal(group.embed(x), flat)
    else:
        assert group.embedding_dim != _numel(group) or not torch.equal(group.embed(x), flat)
