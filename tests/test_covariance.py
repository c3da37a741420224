"""The learned covariance: its Cholesky parameterisation, its likelihood, the calibrated
observer's rollout, online and exported steps (one computation), and its training."""

from __future__ import annotations

import inspect
import math
from functools import partial

import pytest
import torch

from groups import SO3, Euclidean, Product
from manifold_nets.cores import GRUCore
from manifold_nets.covariance_training import Sequences, fit_covariance, mean_nll
from manifold_nets.observer import (
    CalibratedObserver,
    CovarianceReadout,
    Measurement,
    ResidualObserver,
)
from manifold_nets.observer.covariance import gaussian_nll, input_width
from observer_checks import assert_covariances_close, assert_step_covariances_follow

GROUP = Product(SO3(), Euclidean(3), names=("R", "p"))


def _observer(seed=0):
    torch.manual_seed(seed)
    measurement = Measurement(12, factors={"R": [0, 9], "p": [9, 12]})
    obs = ResidualObserver(GROUP, measurement, core=partial(GRUCore, hidden_size=8, num_layers=2))
    with torch.no_grad():  # a moving observer: the zero-started output layer set at random
        obs.core.head.weight.normal_(0, 0.1)
    return obs


@pytest.mark.parametrize("structure", ["diagonal", "factor", "joint"])
def test_the_factor_has_the_structure_s_pattern_and_its_log_determinant(structure):
    r = CovarianceReadout(GROUP, 16, structure, memory=4)
    with torch.no_grad():
        for p in r.parameters():
            p.normal_()
    L, log_diag = r.log_scale(torch.randn(3, 5, 16))
    assert L.shape == (3, 5, 6, 6) and L.dtype == torch.float64
    assert torch.equal(L.triu(1), torch.zeros_like(L))
    off_block = L[..., 3:, :3]
    if structure == "joint":
        assert off_block.abs().sum() > 0
    else:
        assert torch.equal(off_block, torch.zeros_like(off_block))
    if structure == "diagonal":
        assert torch.equal(L, torch.diag_embed(torch.diagonal(L, dim1=-2, dim2=-1)))
    torch.testing.assert_close(torch.logdet(L @ L.mT), 2 * log_diag.sum(-1), rtol=1e-5, atol=1e-9)


def test_the_likelihood_is_the_gaussian_s():
    r = CovarianceReadout(GROUP, 16, "joint", memory=0)
    with torch.no_grad():
        for p in r.parameters():
            p.normal_(0, 0.3)
    L, log_diag = r.log_scale(torch.randn(4, 2, 16))
    e = torch.randn(4, 2, 6, dtype=torch.float64)
    mvn = torch.distributions.MultivariateNormal(torch.zeros(6, dtype=torch.float64), scale_tril=L)
    want = -mvn.log_prob(e) - 3 * math.log(2 * math.pi)
    torch.testing.assert_close(gaussian_nll(e, L, log_diag), want)


def test_set_scale_starts_every_covariance_at_the_given_diagonal():
    r = CovarianceReadout(GROUP, 16, "factor", memory=4)
    std = torch.arange(1, 7, dtype=torch.float64) / 10
    r.set_scale(std)
    L, _ = r.log_scale(torch.randn(2, 3, 16))
    torch.testing.assert_close(r.covariance(L), torch.diag(std**2).expand(2, 3, 6, 6).float().double())
    torch.testing.assert_close(r.covariance(r.initial_cholesky()), torch.diag(std**2).float().double())


def _measurements(n, t, seed=5):
    """Noisy embedded elements of the group: what a sensor of R and p gives."""
    gen = torch.Generator().manual_seed(seed)
    x = GROUP.random((n, t), generator=gen, dtype=torch.float64)
    return GROUP.embed(x)


@pytest.mark.parametrize("clock", [(), (2.0, 5.0)])
@pytest.mark.parametrize("source", ["residual", "residual_size", "hidden", "readings"])
def test_rollout_online_and_exported_steps_give_the_same_estimates_and_covariances(source, clock):
    obs = _observer()
    r = CovarianceReadout(GROUP, input_width(obs, source), "factor", memory=4, source=source,
                          clock=clock)
    with torch.no_grad():
        for p in r.parameters():
            p.normal_(0, 0.3)
    cal = CalibratedObserver(obs, r)
    y = _measurements(3, 6)
    with torch.no_grad():
        est, cov = cal(y)
        assert torch.equal(est, obs(y))  # the readout does not move the estimate
        assert cov.shape == (3, 7, 6, 6)
        torch.testing.assert_close(cov[:, 0], r.covariance(r.initial_cholesky((3,))))
        state = cal.init_state(3)
        step = cal.online_step_module()
        flat = step.initial_state(3)
        for k in range(6):
            state, P = cal.step(state, y[:, k])
            *flat, P_exp = step(*flat, y[:, k])
            torch.testing.assert_close(state.observer.estimate, est[:, k + 1], rtol=0, atol=1e-12)
            assert_covariances_close(P, cov[:, k + 1])
            assert_covariances_close(P_exp, cov[:, k + 1])
            torch.testing.assert_close(flat[0], est[:, k + 1].reshape(3, -1), rtol=0, atol=1e-12)


def test_a_size_readout_reads_the_residuals_and_the_log_of_each_factor_s_squared_size(tmp_path):
    from manifold_nets.covariance_training import load_readout, save_readout
    from manifold_nets.observer.covariance import readout_inputs

    obs = _observer()
    assert input_width(obs, "residual_size") == input_width(obs, "residual") + 2
    y = _measurements(2, 5)
    with torch.no_grad():
        run = obs.rollout(y, keep_hidden=True)
        x = run.estimates[:, 1:].flatten(2)
        plain = readout_inputs(obs, "residual", x, y, None, None)
        sized = readout_inputs(obs, "residual_size", x, y, None, None)
    assert sized.shape == (2, 5, 8) and torch.equal(sized[..., :6], plain)
    # R's residual is the rotation vector from the estimate to the measurement: its angle
    r_hat = x[..., :9].reshape(2, 5, 3, 3).double()
    r_meas = y[..., :9].reshape(2, 5, 3, 3)
    cos = ((r_hat.mT @ r_meas).diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    angle = torch.arccos(cos.clamp(-1, 1))
    torch.testing.assert_close(sized[..., 6], (angle.square() + 1e-12).log().float(), atol=1e-4, rtol=1e-4)
    p_res = (y[..., 9:] - x[..., 9:12].double()).square().sum(-1)
    torch.testing.assert_close(sized[..., 7], (p_res + 1e-12).log().float(), atol=1e-4, rtol=1e-4)
    r = CovarianceReadout(GROUP, 8, "factor", memory=3, source="residual_size")
    save_readout(tmp_path / "s.pt", r, observer="test")
    with torch.no_grad():
        torch.testing.assert_close(load_readout(tmp_path / "s.pt", obs)(y)[1],
                                   CalibratedObserver(obs, r)(y)[1], rtol=0, atol=0)


def test_sequences_read_for_another_source_are_refused_with_the_fix():
    from manifold_nets.covariance_training import factor_nees, readout_sequences
    from manifold_nets.observer.covariance import SOURCES

    from manifold_nets.trajectory_dataset import TrajectoryDataset

    obs = _observer()
    gen = torch.Generator().manual_seed(3)
    states = GROUP.random((2, 6), generator=gen, dtype=torch.float64)
    data = TrajectoryDataset(states, _measurements(2, 5), torch.zeros(2, 5, 0), {})
    plain = readout_sequences(obs, data, "residual")
    sized = CovarianceReadout(GROUP, input_width(obs, "residual_size"), memory=2, source="residual_size")
    with pytest.raises(ValueError, match=r"reads 8 numbers a step, the sequences give 6: .*'residual_size'"):
        fit_covariance(sized, plain, plain, epochs=1)
    with pytest.raises(ValueError, match="reads 8 numbers"):
        factor_nees(sized, plain)
    assert set(SOURCES) == {"residual", "residual_size", "hidden", "readings"}


def test_a_readout_of_another_width_or_source_is_refused():
    obs = _observer()
    with pytest.raises(ValueError, match="reads 99 numbers"):
        CalibratedObserver(obs, CovarianceReadout(GROUP, 99))
    plain = ResidualObserver(GROUP, 12, core=partial(GRUCore, hidden_size=8, num_layers=1))
    with pytest.raises(ValueError, match="names no measured factor; use source='hidden'"):
        CalibratedObserver(plain, CovarianceReadout(GROUP, 6))
    CalibratedObserver(plain, CovarianceReadout(GROUP, 8, source="hidden"))


@pytest.mark.parametrize(
    "bad", [{"structure": "full"}, {"memory": -1}, {"memory": 1.5}, {"source": "innovation"}]
)
def test_bad_settings_are_refused(bad):
    with pytest.raises(ValueError, match="covariance"):
        CovarianceReadout(GROUP, 16, **bad)


def test_fitting_learns_a_noise_level_the_features_carry():
    """Sequences at two noise levels whose features say which: the fitted readout's standard
    deviations land on each level's, where the starting one (one diagonal for all) cannot."""
    gen = torch.Generator().manual_seed(4)
    n, t, levels = 64, 40, torch.tensor([0.02, 0.5])
    which = torch.arange(n) % 2
    sd = levels[which].double()
    feats = torch.zeros(n, t, 2)
    feats[torch.arange(n), :, which] = 1.0
    errors = torch.randn(n, t, 6, generator=gen, dtype=torch.float64) * sd[:, None, None]
    known = torch.ones(n, t, dtype=torch.bool)
    data = Sequences(feats, errors, known)
    r = CovarianceReadout(GROUP, 2, "diagonal", memory=0)
    history = fit_covariance(r, data, data, epochs=60, lr=3e-2, batch_size=8, show_progress=False)
    assert history[-1]["val_nll"] < history[0]["val_nll"] - 1.0
    assert mean_nll(r, data) == pytest.approx(min(h["val_nll"] for h in history))
    L, _ = r.log_scale(feats[:2])
    got = torch.diagonal(L, dim1=-2, dim2=-1)[:, -1].mean(-1)
    torch.testing.assert_close(got, levels.double(), rtol=0.15, atol=0)


def test_a_saved_readout_loads_back_and_a_foreign_one_is_refused(tmp_path):
    from manifold_nets.checkpoint import CheckpointError
    from manifold_nets.covariance_training import load_readout, save_readout

    obs = _observer()
    r = CovarianceReadout(GROUP, input_width(obs, "residual"), "joint", memory=3)
    with torch.no_grad():
        for p in r.parameters():
            p.normal_()
    save_readout(tmp_path / "c.pt", r, observer="test")
    cal = load_readout(tmp_path / "c.pt", obs)
    y = _measurements(2, 4)
    with torch.no_grad():
        torch.testing.assert_close(cal(y)[1], CalibratedObserver(obs, r)(y)[1], rtol=0, atol=0)
    other = ResidualObserver(Product(SO3(), names=("R",)), Measurement(9, factors={"R": [0, 9]}))
    with pytest.raises(CheckpointError, match="does not fit this observer.*group"):
        load_readout(tmp_path / "c.pt", other)
    (tmp_path / "bad.pt").write_bytes(b"not a file torch wrote")
    with pytest.raises(CheckpointError, match="bad.pt is not a loadable readout"):
        load_readout(tmp_path / "bad.pt", obs)
    with pytest.raises(CheckpointError, match="no covariance readout"):
        load_readout(tmp_path / "none.pt", obs)
    torch.save({"format": "manifold_nets.covariance/1", "signature": r.signature(),
                "model": {**r.state_dict(), "out.weight": torch.zeros(2, 2)}}, tmp_path / "w.pt")
    with pytest.raises(CheckpointError, match="w.pt.*out.weight"):
        load_readout(tmp_path / "w.pt", obs)


def test_the_calibrated_step_exports_with_torch_export_and_gives_the_same_covariance(clock=()):
    obs = _observer()
    r = CovarianceReadout(GROUP, input_width(obs, "residual"), "factor", memory=4, clock=clock)
    with torch.no_grad():
        for p in r.parameters():
            p.normal_(0, 0.3)
    step = CalibratedObserver(obs, r).online_step_module().eval()
    y = _measurements(2, 3)
    args = (*step.initial_state(2), y[:, 0])
    program = torch.export.export(step, args)
    flat_eager, flat_exported = step.initial_state(2), step.initial_state(2)
    with torch.no_grad():
        for k in range(3):
            *flat_eager, P = step(*flat_eager, y[:, k])
            *flat_exported, P_exp = program.module()(*flat_exported, y[:, k])
            assert_covariances_close(P_exp, P)
            torch.testing.assert_close(flat_exported[0], flat_eager[0], rtol=0, atol=1e-12)


def test_broad_calibration_cuts_sequences_into_windows_without_losing_a_known_step():
    from manifold_nets_examples.broad.calibration import _windows

    feats = torch.arange(2 * 7, dtype=torch.float32).reshape(2, 7, 1)
    errors = torch.arange(2 * 7 * 3, dtype=torch.float64).reshape(2, 7, 3)
    known = torch.ones(2, 7, dtype=torch.bool)
    known[1, 4:] = False  # the second sequence's last window holds no known step
    out = _windows(Sequences(feats, errors, known), 3)
    assert out.features.shape == (5, 3, 1) and out.known.sum() == known.sum()
    torch.testing.assert_close(out.errors[out.known], errors[known])
    assert not out.known[2, 1:].any()  # the first sequence's padded tail


def test_exporting_the_calibrated_step_leaves_the_piece_classes_as_they_were():
    """torch.export's tracer once patched the measurement's class (its __init__ became the
    tracer's proxy's) when a module was reachable twice; every later config build failed."""
    from manifold_nets.observer.piece import PIECES

    test_the_calibrated_step_exports_with_torch_export_and_gives_the_same_covariance()
    patched = [k for k, c in PIECES.items() if "AttrProxy" in c.__init__.__qualname__]
    assert patched == []
    assert "dim" in inspect.signature(Measurement.__init__).parameters


def test_the_exported_step_of_a_readout_with_a_clock_counts_its_steps():
    test_the_calibrated_step_exports_with_torch_export_and_gives_the_same_covariance(clock=(3.0,))


def test_a_clock_reads_the_steps_from_the_start_and_changes_the_covariance():
    """The clock's inputs are exp(-k / tau) at the observer's steps k = start + 1 ..; a readout
    started later (a window, a resumed state) reads the later steps, and the clock matters."""
    r = CovarianceReadout(GROUP, 16, "factor", memory=4, clock=(2.0, 7.0))
    with torch.no_grad():
        for p in r.parameters():
            p.normal_(0, 0.3)
    c = r.clock_inputs(torch.tensor([0, 3]), 4)
    k = torch.tensor([[1, 2, 3, 4], [4, 5, 6, 7]], dtype=torch.float64)
    torch.testing.assert_close(c, torch.exp(-k[..., None] / torch.tensor([2.0, 7.0]).double()).float())
    z = torch.randn(2, 6, 16)
    whole, _ = r.log_scale(z)
    later, _ = r.log_scale(z[:, 3:], torch.tensor([3, 3]))
    assert not torch.allclose(whole[:, 3:], later)  # another memory, another clock
    plain = CovarianceReadout(GROUP, 16, "factor", memory=4)
    assert r.gru.input_size == plain.gru.input_size + 2
    assert "clock" in r.signature() and "clock" not in plain.signature()


@pytest.mark.parametrize("clock", [[0.0], [-1.0], [float("nan")], list(range(1, 10)), "10", [True]])
def test_a_bad_clock_is_refused_with_the_fix(clock):
    with pytest.raises(ValueError, match="clock must be a list of at most 8 positive time constants"):
        CovarianceReadout(GROUP, 16, "factor", memory=4, clock=clock)


def test_a_readout_with_a_clock_saves_and_loads(tmp_path):
    from manifold_nets.checkpoint import CheckpointError
    from manifold_nets.covariance_training import load_readout, save_readout

    obs = _observer()
    r = CovarianceReadout(GROUP, input_width(obs, "residual"), "factor", memory=4, clock=(5.0, 50.0))
    with torch.no_grad():
        for p in r.parameters():
            p.normal_(0, 0.3)
    save_readout(tmp_path / "c.pt", r, "test")
    cal = load_readout(tmp_path / "c.pt", obs)
    assert cal.readout.clock == (5.0, 50.0)
    y = _measurements(2, 5)
    with torch.no_grad():
        torch.testing.assert_close(cal(y)[1], CalibratedObserver(obs, r)(y)[1], rtol=0, atol=0)
    payload = torch.load(tmp_path / "c.pt", weights_only=True)
    payload["signature"]["clock"] = [-5.0, 50.0]
    torch.save(payload, tmp_path / "bad.pt")
    with pytest.raises(CheckpointError, match="does not fit this observer"):
        load_readout(tmp_path / "bad.pt", obs)


def test_windows_carry_the_steps_they_start_after():
    from manifold_nets_examples.broad.calibration import _windows

    feats = torch.zeros(2, 7, 1)
    seqs = Sequences(feats, torch.zeros(2, 7, 3, dtype=torch.float64), torch.ones(2, 7, dtype=torch.bool))
    out = _windows(seqs, 3)
    assert out.start.tolist() == [0, 3, 6, 0, 3, 6]
    assert Sequences.cat([out.select(torch.tensor([1])), out]).starts.tolist() == [3, 0, 3, 6, 0, 3, 6]
    assert seqs.select(torch.tensor([1])).starts.tolist() == [0]  # whole sequences start at 0


@pytest.mark.parametrize("structure", ["diagonal", "factor", "joint"])
def test_rescale_multiplies_each_factor_s_block(structure):
    r = CovarianceReadout(GROUP, 16, structure, memory=4)
    with torch.no_grad():
        for p in r.parameters():
            p.normal_(0, 0.3)
    z = torch.randn(2, 5, 16)
    before = r.covariance(r.log_scale(z)[0])
    start = r.covariance(r.initial_cholesky())
    scales = {"R": 2.0, "p": 2.0} if structure == "joint" else {"R": 4.0, "p": 0.25}
    r.rescale(scales)
    after = r.covariance(r.log_scale(z)[0])
    for name, s in scales.items():
        sl = GROUP.tangent_slice(name)
        torch.testing.assert_close(after[..., sl, sl], s * before[..., sl, sl], rtol=1e-5, atol=0)
        torch.testing.assert_close(r.covariance(r.initial_cholesky())[sl, sl], s * start[sl, sl],
                                   rtol=1e-5, atol=0)
    if structure == "joint":
        torch.testing.assert_close(after, 2.0 * before, rtol=1e-5, atol=0)
        with pytest.raises(ValueError, match="give every factor the same scale"):
            r.rescale({"R": 2.0, "p": 3.0})
    for bad in ({"q": 2.0}, {"R": 0.0}, {"R": float("inf")}, {"R": True}):
        with pytest.raises(ValueError, match="positive finite scales"):
            r.rescale(bad)


def test_scaling_to_held_out_sequences_makes_each_factor_s_mean_nees_one():
    from manifold_nets.covariance_training import factor_nees, scale_to_heldout

    gen = torch.Generator().manual_seed(3)
    r = CovarianceReadout(GROUP, 16, "factor", memory=4)
    r.set_scale(torch.ones(6))  # P = I at every step, whatever the random initial weights
    errors = torch.randn(6, 20, 6, generator=gen, dtype=torch.float64) * torch.tensor([0.1] * 3 + [2.0] * 3).double()
    known = torch.ones(6, 20, dtype=torch.bool)
    known[:, :3] = False
    seqs = Sequences(torch.randn(6, 20, 16, generator=gen), errors, known)
    before = factor_nees(r, seqs)
    assert before["R"] < 0.1 and before["p"] > 3  # P = I: R's errors small, p's large
    scales = scale_to_heldout(r, seqs)
    assert scales == pytest.approx(before)
    assert factor_nees(r, seqs) == pytest.approx({"R": 1.0, "p": 1.0}, rel=1e-5)


def test_a_clock_reads_the_observer_s_own_step_count_in_the_exported_step():
    """An observer whose pieces count steps (a step decay) carries ``steps`` in its exported
    state already: the readout's clock reads it, no second counter."""
    from manifold_nets.observer import StepDecay

    torch.manual_seed(0)
    obs = ResidualObserver(GROUP, Measurement(12, factors={"R": [0, 9], "p": [9, 12]}),
                           core=partial(GRUCore, hidden_size=8, num_layers=2),
                           scales=[StepDecay({"p": 3})])
    with torch.no_grad():
        obs.core.head.weight.normal_(0, 0.1)
    r = CovarianceReadout(GROUP, input_width(obs, "residual"), "factor", memory=4, clock=(2.0,))
    with torch.no_grad():
        for p in r.parameters():
            p.normal_(0, 0.3)
    cal = CalibratedObserver(obs, r)
    step = cal.online_step_module()
    plain = obs.online_step_module()
    assert plain.clock and len(step.initial_state(2)) == len(plain.initial_state(2)) + 1  # + memory
    y = _measurements(2, 6)
    with torch.no_grad():
        _, cov = cal(y)
    assert_step_covariances_follow(step, step.initial_state(2), y, cov)
