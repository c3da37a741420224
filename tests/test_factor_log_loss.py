"""``train.loss: factor_log_mse``: each sequence's log MSE per factor of a product group, so that a
factor tracked to a small error in its own units (the rigid body's biases) weighs as much as the
others; for a group that is not a product it is ``log_mse``."""

from __future__ import annotations

import functools
import json
import math

import pytest
import torch

from groups import SE3, SO3, Euclidean, Product
from manifold_nets import GRUCore, TrainSettings
from manifold_nets.losses import (
    LOG_MSE_EPS,
    embedding_factor_log_mse,
    embedding_log_mse,
    embedding_mse,
    factor_sequence_mse,
    sequence_mse,
)
from manifold_nets.observer import ResidualObserver
from manifold_nets.training import LOSSES, check_settings, fit, validation_loss
from tests.observer_checks import run_tiny, so3_walk

P = Product(SO3(), Euclidean(3), Euclidean(2))


def rollout(group, n=4, t=6, seed=0, dtype=torch.float64, scales=None):
    g = torch.Generator().manual_seed(seed)
    states = group.random((n, t + 1), generator=g, dtype=dtype)
    tangent = 0.3 * torch.randn(n, t + 1, group.tangent_dim, generator=g, dtype=dtype)
    if scales is not None:
        tangent = tangent * torch.as_tensor(scales, dtype=dtype)
    return group.compose(states, group.exp(tangent)), states


def by_hand(group, est, states, skip=1):
    """The mean over sequences of the mean over factors of log(factor MSE + eps), in a loop."""
    per_seq = []
    for i in range(len(est)):
        logs = []
        for f in range(len(group.factor_names)):
            cols = group.embedding_slice(f)
            d = group.embed(est[i, skip:])[..., cols] - group.embed(states[i, skip:])[..., cols]
            logs.append(torch.log((d * d).mean() + LOG_MSE_EPS))
        per_seq.append(torch.stack(logs).mean())
    return torch.stack(per_seq).mean()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("skip", [1, 3])
def test_factor_log_mse_is_the_mean_of_each_sequences_and_factors_log_mse(dtype, skip):
    est, states = rollout(P, dtype=dtype)
    got = embedding_factor_log_mse(P, est, states, skip=skip)
    assert got.dtype == dtype
    torch.testing.assert_close(got, by_hand(P, est, states, skip))
    per, count = factor_sequence_mse(P, est, states, skip=skip)
    assert per.shape == (4, 3) and count.tolist() == [7 - skip] * 4
    # L_i is the factors' MSEs weighted by their embedding dimensions (9, 3, 2)
    dims = torch.tensor([9.0, 3.0, 2.0], dtype=dtype)
    whole, _ = sequence_mse(P, est, states, skip=skip)
    torch.testing.assert_close(whole, (per * dims).sum(-1) / dims.sum())


@pytest.mark.parametrize("group", [SO3(), SE3()], ids=repr)
def test_for_a_group_that_is_not_a_product_it_is_log_mse(group):
    est, states = rollout(group)
    assert group.factor_names == ("x",)
    torch.testing.assert_close(
        embedding_factor_log_mse(group, est, states), embedding_log_mse(group, est, states),
        rtol=1e-12, atol=0,
    )


def test_every_factor_weighs_alike_whatever_its_units():
    """Doubling the error of a factor tracked 100x closer than the others raises the loss by
    log 4 / F, as doubling the attitude's does; under log_mse it hardly moves the loss."""
    est, states = rollout(P, n=1, t=8, scales=[0.2, 0.2, 0.2, 0.005, 0.005, 0.005, 1, 1])
    tangent = P.log(P.compose(P.inverse(states), est))
    doubled = {}
    for name, cols in (("small", slice(3, 6)), ("large", slice(0, 3))):
        t2 = tangent.clone()
        t2[..., cols] *= 2
        doubled[name] = P.compose(states, P.exp(t2))
    base_f, base_l = embedding_factor_log_mse(P, est, states), embedding_log_mse(P, est, states)
    d_small = embedding_factor_log_mse(P, doubled["small"], states) - base_f
    d_large = embedding_factor_log_mse(P, doubled["large"], states) - base_f
    a = float(factor_sequence_mse(P, est, states)[0][0, 1])  # Euclidean: exactly, with eps
    assert float(d_small) == pytest.approx(
        math.log((4 * a + LOG_MSE_EPS) / (a + LOG_MSE_EPS)) / 3, rel=1e-9
    )
    assert a > 100 * LOG_MSE_EPS
    assert float(d_large) == pytest.approx(math.log(4) / 3, rel=0.02)  # up to the curvature
    assert float(embedding_log_mse(P, doubled["small"], states) - base_l) < 1e-3


def test_the_mask_leaves_steps_and_whole_sequences_out():
    est, states = rollout(P, n=3)
    mask = torch.ones(3, 7, dtype=torch.bool)
    mask[0, 2:5] = False
    mask[2] = False
    other = states.clone()
    other[0, 2:5] = P.random((3,), dtype=torch.float64)
    other[2] = P.random((7,), dtype=torch.float64)
    got = embedding_factor_log_mse(P, est, states, mask=mask)
    torch.testing.assert_close(got, embedding_factor_log_mse(P, est, other, mask=mask))
    first = by_hand(P, est[0:1, [0, 1, 5, 6]], states[0:1, [0, 1, 5, 6]])
    second = by_hand(P, est[1:2], states[1:2])
    torch.testing.assert_close(got, (first + second) / 2)
    nothing = torch.zeros_like(mask)
    assert float(embedding_factor_log_mse(P, est, states, mask=nothing)) == 0.0


def test_an_exact_factor_keeps_the_loss_and_its_gradient_finite():
    est, states = rollout(P, n=2, t=4, scales=[1, 1, 1, 0, 0, 0, 1, 1])
    tangent = torch.zeros(2, 5, P.tangent_dim, dtype=torch.float64, requires_grad=True)
    loss = embedding_factor_log_mse(P, P.compose(est, P.exp(tangent)), states)
    loss.backward()
    assert math.isfinite(loss.item()) and bool(torch.isfinite(tangent.grad).all())
    assert factor_sequence_mse(P, est, states)[0][:, 1].abs().max() < 1e-20


def test_it_is_a_training_loss():
    assert set(LOSSES) == {"mse", "log_mse", "factor_log_mse"}
    check_settings(TrainSettings(loss="factor_log_mse"))


@pytest.mark.parametrize("tbptt", [None, 4])
def test_fit_trains_and_validates_on_the_factor_log_loss(tmp_path, tbptt):
    train, val = so3_walk(12, 12, 1), so3_walk(6, 12, 2)
    torch.manual_seed(0)
    model = ResidualObserver(SO3(), 9, functools.partial(GRUCore, hidden_size=8, num_layers=1))
    before = validation_loss(model, val, loss="factor_log_mse")
    assert before == pytest.approx(validation_loss(model, val, loss="log_mse"), rel=1e-6)
    settings = TrainSettings(
        epochs=3, batch_size=4, lr=1e-2, progress=False, loss="factor_log_mse", tbptt=tbptt
    )
    res = fit(model, train, val, settings, out_dir=tmp_path)
    assert res.history[0]["val_loss"] == before
    assert res.best_val_loss < before


def test_the_train_command_trains_the_rigid_body_on_it(tmp_path):
    """On SO(3) x R^3 x R^3 x R^3 the validation loss is the per-factor one: its epoch-0 value
    differs from log_mse's for the same starting model, and the test loss is still ``L``."""
    runs = {}
    for loss in ("factor_log_mse", "log_mse"):
        cfg = run_tiny("paper_cpu_prior", tmp_path, tmp_path / loss, f"train.loss={loss}")
        assert cfg.train.loss == loss
        log = json.loads((tmp_path / loss / "log.json").read_text())
        metrics = json.loads((tmp_path / loss / "results" / "metrics.json").read_text())
        runs[loss] = (log, metrics)
    v_factor, v_log = (runs[k][0][0]["val_loss"] for k in ("factor_log_mse", "log_mse"))
    assert math.isfinite(v_factor) and v_factor != pytest.approx(v_log, rel=1e-3)
    assert runs["factor_log_mse"][0][-1]["epoch"] >= 1
    test_loss = runs["factor_log_mse"][1]["test_loss"]
    assert test_loss > 0 and math.isfinite(test_loss)


def test_l_is_unchanged_by_the_refactoring():
    """``embedding_mse`` still sums each step's squared error over the coordinates first."""
    est, states = rollout(P, n=3)
    sq = ((P.embed(est[:, 1:]) - P.embed(states[:, 1:])) ** 2).sum(-1)
    assert embedding_mse(P, est, states) == (sq.sum(-1) / (6 * P.embedding_dim)).mean()
