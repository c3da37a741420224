"""The observer's fused group arithmetic (``manifold_nets/observer/fused.py``): the update and the
innovations of an SO(3) x R^n state as one autograd node each, with the values, gradients and
second derivatives of the generic path (and of autograd through the formulas)."""

from __future__ import annotations

import pytest
import torch

from groups import SE3, Euclidean, Product
from groups import so3_kernels
from manifold_nets.losses import embedding_mse
from manifold_nets.observer import GroupUpdate, Measurement, ResidualObserver
from manifold_nets.observer import measurement as measurement_module
from manifold_nets.observer import update as update_module
from tests.observer_checks import rigid_readings, rigid_short
from manifold_nets.observer.features import Embedding, Innovation, Readings

RIGID = rigid_short()


def _observer(net_dtype=torch.float32, rules=None, seed=0):
    torch.manual_seed(seed)
    obs = ResidualObserver(
        RIGID, Measurement(18, factors={"R": (0, 9), "p": (9, 12)}),
        update=GroupUpdate(rules or {"bw": "absolute", "bv": "absolute"}),
        features=[Embedding(), Readings(), Innovation()],
    ).to(net_dtype)
    obs.core.head.reset_parameters()  # the untrained head is zero: let the estimate move
    return obs


_data = rigid_readings


def _grads(obs, y, x, fused, create_graph=False):
    obs.update._fused = obs.measurement._fused = fused
    loss = embedding_mse(RIGID, obs(y), x)
    return loss, torch.autograd.grad(loss, list(obs.parameters()), create_graph=create_graph)


@pytest.mark.parametrize("net_dtype", [torch.float32, torch.float64])
def test_the_fused_step_gives_the_generic_losses_and_gradients(net_dtype):
    obs, (y, x) = _observer(net_dtype), _data()
    assert obs.update._fused and obs.measurement._fused
    loss, grads = _grads(obs, y, x, True)
    loss0, grads0 = _grads(obs, y, x, False)
    assert torch.equal(loss, loss0)
    tol = 1e-12 if net_dtype == torch.float64 else 1e-6
    for a, b in zip(grads, grads0):
        torch.testing.assert_close(a, b, rtol=tol, atol=tol)
    with torch.no_grad():
        assert torch.equal(obs(y), obs(y))


def test_a_second_derivative_through_the_fused_step_is_the_formula_s(monkeypatch):
    """A Hessian-vector product of the loss: the fused nodes differentiate the generic path (whose
    network output v depends on the estimate x: the partial derivatives of each formula only)."""
    obs, (y, x) = _observer(torch.float64), _data(n=3, t=3)
    params = list(obs.parameters())

    def hvp(fused):
        _, g = _grads(obs, y, x, fused, create_graph=True)
        return torch.autograd.grad(sum((gi * gi).sum() for gi in g), params[-1])[0]

    fused = hvp(True)
    for module in (so3_kernels, update_module, measurement_module):  # autograd through formulas
        monkeypatch.setattr(module, "records", lambda *t: False)
    torch.testing.assert_close(fused, hvp(False), rtol=1e-10, atol=1e-12)


def test_only_so3_and_vector_factors_with_residual_rotations_fuse():
    assert not _observer(rules={"R": "left"}).update._fused
    assert not _observer(rules={"R": "absolute"}).update._fused
    se3 = ResidualObserver(Product(SE3(), Euclidean(3)), Measurement(15, factors={"factor0": (0, 12)}))
    assert not se3.update._fused and not se3.measurement._fused
