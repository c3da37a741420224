"""A readout that reads context: side information beside what the observer reads, given with each
step. Rollout, online and exported steps agree; a fit learns a noise level only the context
carries; it saves and loads; a missing or misshapen context is refused with the shape needed."""

from __future__ import annotations

import pytest
import torch

from groups import SO3
from manifold_nets.checkpoint import CheckpointError
from manifold_nets.covariance_training import (
    Sequences, fit_covariance, load_readout, mean_nll, readout_sequences, save_readout,
)
from manifold_nets.data import TrajectoryDataset
from manifold_nets.observer import (
    CalibratedObserver, CovarianceReadout, EnsembleObserver, ResidualObserver,
)
from observer_checks import assert_covariances_close, noisy_walk, randomise_head

GROUP = SO3()


def _observer(seed: int = 0) -> ResidualObserver:
    torch.manual_seed(seed)
    obs = ResidualObserver(GROUP, 9).eval()
    randomise_head(obs, seed=seed, scale=0.3)
    return obs


def _readout(context: int = 2, memory: int = 4) -> CovarianceReadout:
    r = CovarianceReadout(GROUP, 9, "factor", memory=memory, source="readings", context=context)
    with torch.no_grad():
        for p in r.parameters():
            p.normal_(0, 0.3)
    return r


def _walk(n: int, t: int, noise: torch.Tensor, seed: int = 0):
    """States ``(n, t+1, 3, 3)``, measurements ``(n, t, 9)`` with per-sequence noise ``(n,)``."""
    return noisy_walk(GROUP, n, t, step=0.05, noise=noise, seed=seed)


@pytest.mark.parametrize("ensemble", [False, True])
def test_rollout_online_and_exported_steps_read_the_same_context(ensemble):
    obs = EnsembleObserver([_observer(0), _observer(1)]) if ensemble else _observer()
    cal = CalibratedObserver(obs, _readout())
    _, y = _walk(3, 6, torch.full((3,), 0.1))
    c = torch.randn(3, 6, 2, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        est, cov = cal(y, context=c)
        _, other = cal(y, context=c + 1.0)
        assert (other[:, 1:] - cov[:, 1:]).abs().amax() > 1e-3  # the context is read
        torch.testing.assert_close(other[:, 0], cov[:, 0], rtol=0, atol=0)  # the start's is not
        state, step = cal.init_state(3), cal.online_step_module()
        flat = step.initial_state(3)
        for k in range(6):
            state, P = cal.step(state, y[:, k], context=c[:, k])
            *flat, P_exp = step(*flat, y[:, k], c[:, k])
            torch.testing.assert_close(state.observer.estimate, est[:, k + 1], rtol=0, atol=1e-12)
            assert_covariances_close(P, cov[:, k + 1])
            assert_covariances_close(P_exp, cov[:, k + 1])


def test_a_fit_learns_a_noise_level_only_the_context_carries(tmp_path):
    """Half the sequences err ten times more; the readings do not say which, the context (the
    level's log) does: the context readout's NLL is lower by about log 10 per component, and it
    saves and loads to the same covariances."""
    n, t = 48, 30
    level = torch.where(torch.arange(n) % 2 == 0, 0.02, 0.2)
    states, y = _walk(n, t, torch.full((n,), 0.05), seed=2)
    data = TrajectoryDataset(states, y, torch.zeros(n, t, 0), {})
    obs = _observer()
    context = level.log()[:, None, None].expand(n, t, 1).float()
    seqs = readout_sequences(obs, data, "readings", context=context)
    without = readout_sequences(obs, data, "readings")
    torch.testing.assert_close(seqs.features[..., :9], without.features, rtol=0, atol=0)
    torch.testing.assert_close(seqs.features[..., 9:], context, rtol=0, atol=0)
    torch.testing.assert_close(seqs.errors, without.errors, rtol=0, atol=0)
    g = torch.Generator().manual_seed(3)  # errors whose size only the context tells
    errors = torch.randn(n, t, 3, generator=g, dtype=torch.float64) * level.double()[:, None, None]
    fitted = {}
    for name, feats, c in (("context", seqs.features, 1), ("readings", without.features, 0)):
        data_c = Sequences(feats, errors, seqs.known)
        torch.manual_seed(0)
        r = CovarianceReadout(GROUP, 9, "diagonal", memory=0, source="readings", context=c)
        fit_covariance(r, data_c, data_c, epochs=40, lr=3e-2, batch_size=8, show_progress=False)
        fitted[name] = (r, mean_nll(r, data_c))
    assert fitted["context"][1] < fitted["readings"][1] - 1.0  # the exact fits: 2.4 nats a step apart
    r = fitted["context"][0]
    save_readout(tmp_path / "c.pt", r)
    loaded = load_readout(tmp_path / "c.pt", obs)
    with torch.no_grad():
        torch.testing.assert_close(loaded(y, context=context)[1],
                                   CalibratedObserver(obs, r)(y, context=context)[1], rtol=0, atol=0)


def test_a_missing_or_misshapen_context_is_refused_with_the_shape_needed(tmp_path):
    obs = _observer()
    _, y = _walk(2, 4, torch.full((2,), 0.1))
    cal = CalibratedObserver(obs, _readout(context=2))
    with pytest.raises(ValueError, match=r"reads 2 numbers of context per step: give context of "
                                         r"shape \(2, 4, 2\), got none"):
        cal(y)
    with pytest.raises(ValueError, match=r"shape \(2, 2\), got \(2, 3\)"):
        cal.step(cal.init_state(2), y[:, 0], context=torch.zeros(2, 3))
    plain = CalibratedObserver(obs, _readout(context=0))
    with pytest.raises(ValueError, match="reads no context"):
        plain(y, context=torch.zeros(2, 4, 2))
    with pytest.raises(ValueError, match="context must be an integer"):
        CovarianceReadout(GROUP, 9, source="readings", context=-1)
    states, _ = _walk(2, 4, torch.full((2,), 0.1))
    data = TrajectoryDataset(states, y, torch.zeros(2, 4, 0), {})
    with pytest.raises(ValueError, match=r"context must be \(2, 4, C\)"):
        readout_sequences(obs, data, "readings", context=torch.zeros(2, 3, 1))
    # a file whose readout asks for an absurd context is refused before anything is built
    r = _readout(context=2)
    torch.save({"format": "manifold_nets.covariance/1",
                "signature": {**r.signature(), "context": 10**9}, "model": r.state_dict()},
               tmp_path / "big.pt")
    with pytest.raises(CheckpointError, match="does not fit this observer"):
        load_readout(tmp_path / "big.pt", obs)
