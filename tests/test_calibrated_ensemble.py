"""A covariance for an ensemble (or a filtered observer): a readout of the readings alone serves
any observer; its rollout, online and exported steps are one computation; its fit, save and load;
the readouts that need one core are refused with the way that works."""

from __future__ import annotations

from functools import partial

import pytest
import torch

from groups import SO3, Euclidean, Product
from manifold_nets.checkpoint import CheckpointError
from manifold_nets.cores import GRUCore
from manifold_nets.covariance_training import (
    fit_covariance, load_readout, readout_sequences, save_readout,
)
from manifold_nets.data import TrajectoryDataset
from manifold_nets.observer import (
    CalibratedObserver, CovarianceReadout, EnsembleObserver, Measurement, ResidualObserver,
)
from manifold_nets.observer.covariance import input_width, steps_taken
from observer_checks import assert_covariances_close, noisy_walk

GROUP = Product(SO3(), Euclidean(3), names=("R", "p"))


def _member(seed: int) -> ResidualObserver:
    torch.manual_seed(seed)
    measurement = Measurement(12, factors={"R": [0, 9], "p": [9, 12]})
    obs = ResidualObserver(GROUP, measurement, core=partial(GRUCore, hidden_size=8, num_layers=2))
    with torch.no_grad():  # a moving observer: the zero-started output layer set at random
        obs.core.head.weight.normal_(0, 0.1)
    return obs.eval()


def _ensemble(k: int = 3) -> EnsembleObserver:
    return EnsembleObserver([_member(s) for s in range(k)])


def _walk(n: int, t: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """States ``(n, t+1, 4, 4)`` of a random walk and noisy measurements ``(n, t, 12)``."""
    return noisy_walk(GROUP, n, t, step=0.1, noise=0.05, seed=seed)


def _readout(clock=()) -> CovarianceReadout:
    r = CovarianceReadout(GROUP, 12, "factor", memory=4, source="readings", clock=clock)
    with torch.no_grad():
        for p in r.parameters():
            p.normal_(0, 0.3)
    return r


@pytest.mark.parametrize("clock", [(), (2.0, 5.0)])
def test_rollout_online_and_exported_steps_of_a_calibrated_ensemble_agree(clock):
    ens = _ensemble()
    cal = CalibratedObserver(ens, _readout(clock))
    _, y = _walk(3, 6)
    with torch.no_grad():
        est, cov = cal(y)
        torch.testing.assert_close(est, ens(y), rtol=0, atol=0)  # the estimate is the ensemble's
        assert cov.shape == (3, 7, 6, 6)
        # the covariance reads the readings alone: a readout on one member gives the same P
        _, cov_one = CalibratedObserver(ens.members[0], cal.readout)(y)
        torch.testing.assert_close(cov, cov_one, rtol=0, atol=0)
        state, step = cal.init_state(3), cal.online_step_module()
        flat = step.initial_state(3)
        for k in range(6):
            state, P = cal.step(state, y[:, k])
            *flat, P_exp = step(*flat, y[:, k])
            assert steps_taken(state.observer) == k + 1
            torch.testing.assert_close(state.observer.estimate, est[:, k + 1], rtol=0, atol=1e-12)
            assert_covariances_close(P, cov[:, k + 1])
            assert_covariances_close(P_exp, cov[:, k + 1])
            torch.testing.assert_close(flat[0], est[:, k + 1].reshape(3, -1), rtol=0, atol=1e-12)


def test_a_calibrated_ensemble_starts_where_it_is_told_and_goes_on_from_a_state():
    ens = _ensemble(2)
    cal = CalibratedObserver(ens, _readout((3.0,)))
    states, y = _walk(2, 8, seed=1)
    with torch.no_grad():
        state = cal.init_state(2, estimate=states[:, 0])
        assert all(torch.equal(s.estimate, states[:, 0]) for s in state.observer.members)
        est, cov = cal(y, state=state.observer)
        # in two pieces: the second from the first's final state (the clock reads its steps)
        _, mid = ens(y[:, :5], state=state.observer, return_state=True)
        second, cov2 = cal(y[:, 5:], state=mid)
    torch.testing.assert_close(second[:, 1:], est[:, 6:], rtol=0, atol=1e-12)
    # the readout's memory starts fresh at a given state, but its clock goes on from step 5
    fresh = CovarianceReadout.covariance(cal.readout.cholesky(
        cal.inputs(None, y[:, 5:], None, None), cal.readout.initial_memory(2), 5)[0])
    torch.testing.assert_close(cov2[:, 1:], fresh, rtol=0, atol=0)


def test_fitting_to_an_ensemble_s_errors_and_saving_and_loading_it(tmp_path):
    ens = _ensemble(2)
    states, y = _walk(16, 20, seed=2)
    data = TrajectoryDataset(states, y, torch.zeros(16, 20, 0), {})
    seqs = readout_sequences(ens, data, "readings")
    with torch.no_grad():
        want = GROUP.rminus(states, ens(y))[:, 1:]  # Log(xhat^-1 x), the ensemble's errors
    torch.testing.assert_close(seqs.errors, want, rtol=0, atol=1e-12)
    torch.testing.assert_close(seqs.features, y.float(), rtol=0, atol=0)
    r = CovarianceReadout(GROUP, input_width(ens, "readings"), "factor", memory=4, source="readings")
    history = fit_covariance(r, seqs, seqs, epochs=3, batch_size=4, show_progress=False)
    assert history[-1]["val_nll"] < history[0]["val_nll"]
    save_readout(tmp_path / "c.pt", r, observer="ensemble")
    cal = load_readout(tmp_path / "c.pt", ens)
    with torch.no_grad():
        torch.testing.assert_close(cal(y)[1], CalibratedObserver(ens, r)(y)[1], rtol=0, atol=0)
    # a readout of one member's core does not fit the ensemble
    hidden = CovarianceReadout(GROUP, input_width(ens.members[0], "hidden"), source="hidden")
    save_readout(tmp_path / "h.pt", hidden)
    with pytest.raises(CheckpointError, match="does not fit this observer.*width"):
        load_readout(tmp_path / "h.pt", ens)


def test_readouts_that_read_one_core_are_refused_for_an_ensemble():
    ens = _ensemble(2)
    for source in ("hidden", "residual"):
        r = CovarianceReadout(GROUP, 8, source=source)
        with pytest.raises(TypeError, match="source 'readings' serves any observer"):
            CalibratedObserver(ens, r)
    states, y = _walk(2, 3)
    data = TrajectoryDataset(states, y, torch.zeros(2, 3, 0), {})
    with pytest.raises(ValueError, match="reads source='readings', got 'hidden'"):
        readout_sequences(ens, data, "hidden")
    with pytest.raises(TypeError, match="got a Linear"):
        CalibratedObserver(torch.nn.Linear(2, 2), _readout())


def test_a_filtered_observer_with_a_context_readout_rolls_out_steps_and_exports_alike():
    """The BROAD member behind its pre-filter (its readings raw, the filter inside), a readout
    of the raw readings and two numbers of context: rollout, online step and exported step."""
    from manifold_nets import load_observer
    from manifold_nets.loading import ensemble_members
    from manifold_nets.plugins import zoo_path

    filtered = load_observer(ensemble_members(zoo_path("broad/attitude"))[0]).filtered()
    r = CovarianceReadout(filtered.group, input_width(filtered, "readings"), memory=4,
                          source="readings", context=2)
    with torch.no_grad():
        for p in r.parameters():
            p.normal_(0, 0.1)
    cal = CalibratedObserver(filtered, r)
    g = torch.Generator().manual_seed(6)
    y = torch.randn(2, 12, filtered.measurement_dim, generator=g, dtype=torch.float64)
    u = torch.randn(2, 12, filtered.input_dim, generator=g, dtype=torch.float64)
    c = torch.randn(2, 12, 2, generator=g)
    with torch.no_grad():
        est, cov = cal(y, u, context=c)
        torch.testing.assert_close(est, filtered(y, u), rtol=0, atol=0)
        state, step = cal.init_state(2), cal.online_step_module()
        flat = step.initial_state(2)
        for k in range(12):
            state, P = cal.step(state, y[:, k], u[:, k], context=c[:, k])
            *flat, P_exp = step(*flat, y[:, k], u[:, k], c[:, k])
            assert steps_taken(state.observer) == k + 1
            assert_covariances_close(P, cov[:, k + 1])
            assert_covariances_close(P_exp, cov[:, k + 1])
            torch.testing.assert_close(flat[0], est[:, k + 1].reshape(2, -1), rtol=0, atol=1e-10)


@pytest.mark.parametrize("batch", [None, 1])
def test_export_observer_writes_a_calibrated_ensemble_s_step_with_its_covariance(tmp_path, batch):
    """export_observer takes a CalibratedObserver: the saved program, loaded back, steps as the
    eager step (estimate, every state tensor, P), from the description's initial state; the
    description names the readout's memory, clock and context inputs and holds its signature."""
    from manifold_nets import export_observer
    from manifold_nets.deploy import load_exported_step

    ens = _ensemble(2)
    r = CovarianceReadout(GROUP, 12, "factor", memory=4, source="readings", clock=(3.0,),
                          context=2)
    with torch.no_grad():
        for p in r.parameters():
            p.normal_(0, 0.3)
    cal = CalibratedObserver(ens, r).eval()
    program = export_observer(cal, tmp_path / "cal.pt2", batch=batch)
    # no size read from data (a boolean mask's count once was: an unbacked symbol u0, checked
    # at run time and warned about on loading)
    assert not [s for s in program.range_constraints if str(s).startswith("u")]
    loaded = load_exported_step(tmp_path / "cal.pt2")
    meta = loaded.meta
    assert meta["inputs"][-4:] == ["memory", "clock_steps", "y", "context"]
    assert meta["inputs"][0] == "x" and meta["covariance_readout"] == r.signature()
    step = cal.online_step_module()
    n = 1 if batch == 1 else 3
    flat, got = step.initial_state(n), loaded.initial_state(n)
    for a, b in zip(flat, got):
        torch.testing.assert_close(b, a, rtol=0, atol=0)
    _, y = _walk(n, 6, seed=3)
    c = torch.randn(n, 6, 2, generator=torch.Generator().manual_seed(4))
    with torch.no_grad():
        est, cov = cal(y, context=c)
        for k in range(6):
            *flat, P = step(*flat, y[:, k], c[:, k])
            *got, P_exp = loaded(*got, y[:, k], c[:, k])
            assert_covariances_close(P_exp, P)
            assert_covariances_close(P_exp, cov[:, k + 1])
            for a, b in zip(flat, got):
                torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-6)
            torch.testing.assert_close(got[0], est[:, k + 1].reshape(n, -1), rtol=0, atol=1e-6)
