"""``LieGroup.mean``, the barycentre: against scipy's rotation mean, the arithmetic mean, per factor
on a product, over any batch dimension, its refusals. (The axiom suite's ``mean`` property checks
the barycentre condition and equivariance on every shipped group: test_group_axioms.)"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from groups import SE3, SO3, Euclidean, Product

DTYPES = [torch.float32, torch.float64]


def _cluster(group, k: int, batch: tuple, spread: float, dtype, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    centre = group.random(batch, generator=g, dtype=dtype)
    v = spread * torch.randn(k, *batch, group.tangent_dim, generator=g, dtype=dtype)
    return group.rplus(centre.unsqueeze(0), v)


@pytest.mark.parametrize("dtype", DTYPES)
def test_two_rotations_give_scipys_mean(dtype):
    """Of two rotations the geodesic and the chordal mean are one: the midpoint."""
    xs = _cluster(SO3(), 2, (5,), 0.4, dtype)
    got = SO3().mean(xs, 0).double().numpy()
    for b in range(5):
        want = Rotation.from_matrix(xs[:, b].double().numpy()).mean().as_matrix()
        np.testing.assert_allclose(got[b], want, atol=1e-12 if dtype == torch.float64 else 2e-6)


def test_three_rotations_near_scipys_chordal_mean():
    """Three rotations 0.05 rad apart: the geodesic mean differs from scipy's chordal one by
    the third order of the spread, not more."""
    xs = _cluster(SO3(), 3, (20,), 0.05, torch.float64)
    m = SO3().mean(xs, 0)
    for b in range(20):
        want = torch.from_numpy(Rotation.from_matrix(xs[:, b].numpy()).mean().as_matrix())
        gap = SO3().distance(m[b], want)
        assert 0 < gap < 0.05**3, gap


@pytest.mark.parametrize("dtype", DTYPES)
def test_vector_space_mean_is_the_arithmetic_mean(dtype):
    x = torch.randn(4, 2, 3, dtype=dtype)
    torch.testing.assert_close(Euclidean(3).mean(x, 0), x.mean(0))


def test_product_mean_is_the_factors_means():
    G = Product(SO3(), Euclidean(3))
    xs = _cluster(G, 3, (4,), 0.1, torch.float64)
    m = G.mean(xs, 0)
    r = xs[..., G.element_slice(0)].reshape(3, 4, 3, 3)
    torch.testing.assert_close(m[..., G.element_slice(0)].reshape(4, 3, 3), SO3().mean(r, 0))
    torch.testing.assert_close(m[..., G.element_slice(1)], xs[..., G.element_slice(1)].mean(0))


@pytest.mark.parametrize("dim", [1, -1])
def test_any_batch_dimension(dim):
    """``dim`` counts batch dimensions only; the mean over the second equals it slice by slice."""
    xs = _cluster(SE3(), 3, (2,), 0.05, torch.float64).transpose(0, 1)  # (2, 3, 4, 4)
    m = SE3().mean(xs, dim)
    assert m.shape == (2, 4, 4)
    for b in range(2):
        torch.testing.assert_close(m[b], SE3().mean(xs[b], 0))


def test_wider_spreads_need_more_iterations():
    """At 0.5 rad per axis the default four iterations leave a residual of 1e-4; sixteen reach
    float64's precision."""
    G = SO3()
    xs = _cluster(G, 3, (50,), 0.5, torch.float64)

    def residual(it):
        return G.rminus(xs, G.mean(xs, 0, iterations=it).unsqueeze(0)).mean(0).norm(dim=-1).max()

    assert residual(1) > residual(4) > 1e-6 > residual(8) > residual(16)
    assert residual(16) < 1e-14


def test_gradients_flow():
    xs = _cluster(SO3(), 3, (2,), 0.1, torch.float64).requires_grad_(True)
    SO3().embed(SO3().mean(xs, 0)).sum().backward()
    assert torch.isfinite(xs.grad).all() and xs.grad.abs().sum() > 0


@pytest.mark.parametrize("kwargs, match", [
    ({"iterations": 0}, "iterations must be an int >= 1"),
    ({"iterations": True}, "iterations must be an int >= 1"),
    ({"iterations": 2.0}, "iterations must be an int >= 1"),
    ({"dim": 1}, "dim must name one of the 1 batch dimensions"),
    ({"dim": -2}, "dim must name one of the 1 batch dimensions"),
])  # fmt: skip
def test_refusals(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SO3().mean(SO3().identity((3,)), **kwargs)


def test_refuses_a_single_element_and_an_empty_stack():
    with pytest.raises(ValueError, match="0 batch dimensions"):
        SO3().mean(SO3().identity())
    with pytest.raises(ValueError, match="no elements along dim 0"):
        SO3().mean(SO3().identity((0,)))
