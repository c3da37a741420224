"""``train.loss: log_mse``: each sequence's log embedding MSE, so that the sequences at low noise
weigh as much as the noisy ones (the paper's ``L`` is dominated by the noisiest)."""

from __future__ import annotations

import functools
import json
import math

import pytest
import torch

from groups import SO3
from manifold_nets import GRUCore, TrainSettings
from manifold_nets.losses import LOG_MSE_EPS, embedding_log_mse, embedding_mse, sequence_mse
from manifold_nets.observer import ResidualObserver
from manifold_nets.training import LOSSES, check_settings, fit, validation_loss
from tests.observer_checks import run_tiny, so3_walk

G = SO3()


def rollout(n=5, t=7, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    states = G.random((n, t + 1), generator=g, dtype=dtype)
    est = G.compose(states, G.exp(0.3 * torch.randn(n, t + 1, 3, generator=g, dtype=dtype)))
    return est, states


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_log_mse_is_the_mean_of_each_sequences_log_mse(dtype):
    est, states = rollout(dtype=dtype)
    by_hand = torch.stack(
        [torch.log(embedding_mse(G, est[i : i + 1], states[i : i + 1]) + LOG_MSE_EPS)
         for i in range(len(est))]
    ).mean()
    got = embedding_log_mse(G, est, states)
    assert got.dtype == dtype
    torch.testing.assert_close(got, by_hand)
    per_seq, count = sequence_mse(G, est, states)
    assert count.tolist() == [7] * 5
    torch.testing.assert_close(per_seq.mean(), embedding_mse(G, est, states))


def test_every_sequence_weighs_alike_whatever_its_error():
    """Doubling the error of the sequence with the smallest error or of the one with the largest
    raises the loss by the same log 4 / N; under ``L`` the largest decides."""
    est, states = rollout(n=4, t=6)
    tangent = G.log(G.compose(G.inverse(states), est))
    tangent[0] *= 0.01  # one sequence nearly exact, the others 30x further off
    tangent[1:] *= 0.3
    base = G.compose(states, G.exp(tangent))
    small, large = base.clone(), base.clone()
    small[0] = G.compose(states[0], G.exp(2 * tangent[0]))
    large[3] = G.compose(states[3], G.exp(2 * tangent[3]))
    d_small = embedding_log_mse(G, small, states) - embedding_log_mse(G, base, states)
    d_large = embedding_log_mse(G, large, states) - embedding_log_mse(G, base, states)
    # log of the MSE's ratio: ~log 4 for a small rotation, equal for both up to the curvature
    assert float(d_small) == pytest.approx(math.log(4) / 4, rel=1e-2)
    assert float(d_large) == pytest.approx(float(d_small), rel=0.02)
    m_small = embedding_mse(G, small, states) - embedding_mse(G, base, states)
    m_large = embedding_mse(G, large, states) - embedding_mse(G, base, states)
    assert float(m_large) > 100 * float(m_small)


def test_the_mask_leaves_steps_and_whole_sequences_out():
    est, states = rollout(n=3, t=6)
    mask = torch.ones(3, 7, dtype=torch.bool)
    mask[0, 2:5] = False
    mask[2] = False  # no known state at all: left out of the mean
    other = states.clone()
    other[0, 2:5] = G.random((3,), dtype=torch.float64)
    other[2] = G.random((7,), dtype=torch.float64)
    a = embedding_log_mse(G, est, states, mask=mask)
    torch.testing.assert_close(a, embedding_log_mse(G, est, other, mask=mask))
    keep = [1, 5, 6]
    first = embedding_mse(G, est[0:1, keep], states[0:1, keep], skip=0)
    second = embedding_mse(G, est[1:2], states[1:2])
    by_hand = (torch.log(first + LOG_MSE_EPS) + torch.log(second + LOG_MSE_EPS)) / 2
    torch.testing.assert_close(a, by_hand)
    nothing = torch.zeros_like(mask)
    assert float(embedding_log_mse(G, est, states, mask=nothing)) == 0.0
    # the masked L is unchanged by the per-sequence refactoring: the mean over all kept steps
    sq = ((G.embed(est) - G.embed(states)) ** 2).sum(-1)
    kept = mask.clone()
    kept[:, 0] = False
    torch.testing.assert_close(embedding_mse(G, est, states, mask=mask), sq[kept].mean() / 9)


def test_an_exact_sequence_keeps_the_loss_and_its_gradient_finite():
    est, states = rollout(n=2, t=4)
    est = est.clone()
    est[0] = states[0]
    tangent = torch.zeros(2, 5, 3, dtype=torch.float64, requires_grad=True)
    loss = embedding_log_mse(G, G.compose(est, G.exp(tangent)), states)
    loss.backward()
    assert math.isfinite(loss.item()) and bool(torch.isfinite(tangent.grad).all())
    other = float(embedding_mse(G, est[1:], states[1:]))
    assert loss.item() == pytest.approx((math.log(LOG_MSE_EPS) + math.log(other + LOG_MSE_EPS)) / 2)


def test_an_unknown_loss_is_refused_naming_the_choices():
    assert {"mse", "log_mse"} <= set(LOSSES)
    check_settings(TrainSettings(loss="log_mse"))
    with pytest.raises(ValueError, match="loss='l1' is not a training loss; choose one of mse, "):
        check_settings(TrainSettings(loss="l1"))


@pytest.mark.parametrize("tbptt", [None, 4])
def test_fit_trains_and_validates_on_the_log_loss(tmp_path, tbptt):
    train, val = so3_walk(12, 12, 1), so3_walk(6, 12, 2)
    torch.manual_seed(0)
    model = ResidualObserver(G, 9, functools.partial(GRUCore, hidden_size=8, num_layers=1))
    before = validation_loss(model, val, loss="log_mse")
    res = fit(
        model, train, val,
        TrainSettings(epochs=3, batch_size=4, lr=1e-2, progress=False, loss="log_mse", tbptt=tbptt),
        out_dir=tmp_path,
    )
    assert res.history[0]["val_loss"] == before  # best.pt is picked on the log loss
    assert res.best_val_loss < before
    last = res.history[-1]
    assert last["val_loss"] == pytest.approx(validation_loss(model, val, loss="log_mse"))
    assert all(row["val_loss"] < 0 for row in res.history)  # logs of MSEs below 1


def _train_command(tmp_path, loss):
    cfg = run_tiny("paper_cpu_prior", tmp_path, tmp_path / loss, f"train.loss={loss}")
    assert cfg.train.loss == loss
    log = json.loads((tmp_path / loss / "log.json").read_text())
    metrics = json.loads((tmp_path / loss / "results" / "metrics.json").read_text())
    return log, metrics


def test_the_train_command_trains_on_log_mse_and_reports_the_papers_test_loss(tmp_path):
    log_rows, log_metrics = _train_command(tmp_path, "log_mse")
    mse_rows, _ = _train_command(tmp_path, "mse")
    # the same starting model, validated on the mean of logs and on L: Jensen, strictly
    v_log, v_mse = log_rows[0]["val_loss"], mse_rows[0]["val_loss"]
    assert math.exp(v_log) < v_mse
    assert log_rows[-1]["epoch"] == mse_rows[-1]["epoch"] >= 1
    assert log_metrics["test_loss"] > 0 and math.isfinite(log_metrics["test_loss"])
