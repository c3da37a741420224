"""``train.loss_weights``: one weight per embedding coordinate in the training and validation loss.
SO(3)'s third embedding row is ``R^T e_z``: weighted alone, the loss scores the inclination and
leaves the heading free (an attitude observer without a magnetometer)."""

from __future__ import annotations

import functools

import pytest
import torch

from groups import SE3, SO3, Euclidean, Product
from manifold_nets import GRUCore, TrainSettings
from manifold_nets.losses import (
    check_loss_weights,
    embedding_factor_log_mse,
    embedding_log_mse,
    embedding_mse,
)
from manifold_nets.observer import ResidualObserver
from manifold_nets.training import check_settings, fit, validation_loss
from tests.observer_checks import so3_walk

G = SO3()
UP = [0.0] * 6 + [1.0] * 3
LOSS_FNS = [embedding_mse, embedding_log_mse, embedding_factor_log_mse]
GROUPS = [SO3(), SE3(), Product(SO3(), Euclidean(3), Euclidean(2))]


def rollout(group, n=4, t=6, seed=0, dtype=torch.float64, scale=0.3):
    g = torch.Generator().manual_seed(seed)
    states = group.random((n, t + 1), generator=g, dtype=dtype)
    noise = scale * torch.randn(n, t + 1, group.tangent_dim, generator=g, dtype=dtype)
    return group.compose(states, group.exp(noise)), states


@pytest.mark.parametrize("group", GROUPS, ids=repr)
@pytest.mark.parametrize("fn", LOSS_FNS, ids=lambda f: f.__name__)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_weights_of_one_are_the_unweighted_loss_to_the_last_bit(group, fn, dtype):
    est, states = rollout(group, dtype=dtype)
    mask = torch.ones(est.shape[:2], dtype=torch.bool)
    mask[1, 2:5] = False
    ones = [1.0] * group.embedding_dim
    for m in (None, mask):
        got = fn(group, est, states, mask=m, weights=ones)
        assert torch.equal(got, fn(group, est, states, mask=m))


@pytest.mark.parametrize("group", GROUPS, ids=repr)
def test_the_weighted_mse_is_the_weighted_mean_of_the_squared_embedding_errors(group):
    est, states = rollout(group, seed=3)
    g = torch.Generator().manual_seed(4)
    w = torch.rand(group.embedding_dim, generator=g, dtype=torch.float64) * 3
    diff = group.embed(est[:, 1:]) - group.embed(states[:, 1:])
    by_hand = (diff * diff * w).sum(-1).mean() / group.embedding_dim
    torch.testing.assert_close(embedding_mse(group, est, states, weights=w.tolist()), by_hand)
    # the mask keeps its steps out whatever the weights
    mask = torch.ones(est.shape[:2], dtype=torch.bool)
    mask[0] = False
    by_hand = (diff[1:] * diff[1:] * w).sum(-1).mean() / group.embedding_dim
    got = embedding_mse(group, est, states, mask=mask, weights=w.tolist())
    torch.testing.assert_close(got, by_hand)


def _turned(states, angle, axis):
    """``states`` turned in the world frame by ``angle`` about ``axis``."""
    v = torch.zeros(*states.shape[:-2], 3, dtype=states.dtype)
    v[..., axis] = angle
    return G.compose(G.exp(v), states)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_third_row_alone_scores_the_tilt_and_leaves_the_heading_free(dtype):
    g = torch.Generator().manual_seed(5)
    states = G.random((3, 8), generator=g, dtype=dtype)
    heading = torch.linspace(-3.0, 3.0, 8, dtype=dtype).expand(3, 8)
    turned = _turned(states, heading, 2)  # about world "up": a heading error only
    assert float(embedding_mse(G, turned, states)) > 0.1
    assert float(embedding_mse(G, turned, states, weights=UP)) < 1e-12
    tilted = _turned(states, torch.full((3, 8), 0.05, dtype=dtype), 0)  # 0.05 rad of tilt
    # a small tilt by phi: the third row moves by |phi| in two entries' worth, 2 phi^2 / 9 per
    # coordinate of the unweighted loss, phi^2 / 9 of the third row's
    up = float(embedding_mse(G, tilted, states, weights=UP))
    assert up == pytest.approx(0.05**2 / 9, rel=1e-3)
    assert float(embedding_mse(G, tilted, states)) == pytest.approx(2 * 0.05**2 / 9, rel=1e-3)


def test_the_gradient_reaches_only_the_weighted_coordinates():
    est, states = rollout(G, seed=6)
    est = est.clone().requires_grad_(True)
    embedding_mse(G, est, states, weights=UP).backward()
    assert torch.count_nonzero(est.grad[..., :2, :]) == 0
    assert torch.count_nonzero(est.grad[:, 1:, 2, :]) > 0


@pytest.mark.parametrize(
    "weights, message",
    [
        ([1.0] * 8, "has 8 numbers; the group's embedding has 9 coordinates"),
        ([-1.0] + [1.0] * 8, "finite numbers >= 0, not all 0"),
        ([float("nan")] + [1.0] * 8, "finite numbers >= 0, not all 0"),
        ([0.0] * 9, "finite numbers >= 0, not all 0"),
        ([True] * 9, "finite numbers >= 0, not all 0"),
        ("111111111", "must be a list of numbers"),
        ([], "finite numbers >= 0, not all 0"),
    ],
)
def test_bad_weights_are_refused_naming_the_fix(weights, message):
    with pytest.raises(ValueError, match=message):
        check_loss_weights(weights, 9)
    est, states = rollout(G)
    with pytest.raises(ValueError, match=message):
        embedding_mse(G, est, states, weights=weights)


def test_the_settings_check_the_weights_and_fit_their_number_before_any_work(tmp_path):
    check_settings(TrainSettings(loss_weights=UP))
    with pytest.raises(ValueError, match="finite numbers >= 0"):
        check_settings(TrainSettings(loss_weights=[0.0] * 9))
    model = ResidualObserver(G, 9, functools.partial(GRUCore, hidden_size=8, num_layers=1))
    with pytest.raises(ValueError, match="has 3 numbers; the group's embedding has 9"):
        fit(model, so3_walk(4, 6, 1), so3_walk(2, 6, 2),
            TrainSettings(epochs=1, progress=False, loss_weights=[1.0, 1.0, 1.0]), out_dir=tmp_path)
    assert not (tmp_path / "checkpoints" / "best.pt").exists()


@pytest.mark.parametrize("tbptt", [None, 4])
def test_fit_trains_and_picks_best_on_the_weighted_loss(tmp_path, tbptt):
    train, val = so3_walk(12, 12, 1), so3_walk(6, 12, 2)
    torch.manual_seed(0)
    model = ResidualObserver(G, 9, functools.partial(GRUCore, hidden_size=8, num_layers=1))
    before = validation_loss(model, val, weights=UP)
    assert before != validation_loss(model, val)
    res = fit(
        model, train, val,
        TrainSettings(epochs=3, batch_size=4, lr=1e-2, progress=False, loss_weights=UP,
                      tbptt=tbptt),
        out_dir=tmp_path,
    )
    assert res.history[0]["val_loss"] == before  # best.pt is picked on the weighted loss
    assert res.best_val_loss < before
    assert res.history[-1]["val_loss"] == pytest.approx(validation_loss(model, val, weights=UP))


def test_the_train_command_takes_the_weights_from_the_config(tmp_path):
    """``train.loss_weights`` through hydra: the rigid body's 18 coordinates (R's 9, then the three
    vectors'); a list of another length is refused naming the embedding's size."""
    from tests.observer_checks import run_tiny

    weights = [0.0] * 9 + [1.0] * 9  # the vectors only
    cfg = run_tiny("paper_cpu_prior", tmp_path, tmp_path / "run",
                   f"train.loss_weights=[{','.join(map(str, weights))}]")
    assert list(cfg.train.loss_weights) == weights
    assert (tmp_path / "run" / "checkpoints" / "best.pt").exists()
    with pytest.raises(ValueError, match="has 3 numbers; the group's embedding has 18"):
        run_tiny("paper_cpu_prior", tmp_path, tmp_path / "bad", "train.loss_weights=[1,1,1]")
    assert not (tmp_path / "bad" / "checkpoints" / "best.pt").exists()
