"""The level scale of a readout's covariance: its basis, what it does to ``P``, one computation in
the rollout, the online and the exported step, its fit, and its file."""

from __future__ import annotations

import copy
import math
from functools import partial

import pytest
import torch

from groups import SO3, Euclidean, Product
from manifold_nets.checkpoint import CheckpointError
from manifold_nets.cores import GRUCore
from manifold_nets.covariance_training import (
    LevelSteps,
    Sequences,
    factor_nees,
    fit_level_scale,
    level_steps,
    load_readout,
    save_readout,
)
from manifold_nets.observer import (
    CalibratedObserver,
    CovarianceReadout,
    LevelScale,
    Measurement,
    ResidualObserver,
    StepDecay,
)
from manifold_nets.observer.covariance import input_width
from observer_checks import assert_covariances_close, assert_step_covariances_follow

GROUP = Product(SO3(), Euclidean(3), names=("R", "p"))


def _observer(scales=()):
    torch.manual_seed(0)
    obs = ResidualObserver(GROUP, Measurement(12, factors={"R": [0, 9], "p": [9, 12]}),
                           core=partial(GRUCore, hidden_size=8, num_layers=2), scales=list(scales))
    with torch.no_grad():
        obs.core.head.weight.normal_(0, 0.1)
    return obs


def _readout(obs, clock=()):
    r = CovarianceReadout(GROUP, input_width(obs, "residual"), "factor", memory=4, clock=clock)
    with torch.no_grad():
        for p in r.parameters():
            p.normal_(0, 0.3)
    return r


def _scale(seed=0, knots=4, clock=(3.0, 20.0), tau=5.0, first=1):
    gen = torch.Generator().manual_seed(seed)
    at = torch.sort(torch.randn(2, knots, generator=gen, dtype=torch.float64) * 2, dim=1).values
    w = 0.3 * torch.randn(2, knots, 1 + len(clock), generator=gen, dtype=torch.float64)
    return LevelScale(GROUP, at, w, clock, tau, first)


def _measurements(n, t, seed=1):
    x = GROUP.random((n, t), generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return GROUP.embed(x)


def test_the_hats_interpolate_between_the_knots_and_hold_beyond_them():
    s = _scale(knots=4)
    at = s.knots  # (2, 4)
    mid = 0.25 * at[:, 1] + 0.75 * at[:, 2]
    lbar = torch.stack([at[:, 0] - 5, at[:, 1], mid, at[:, 3] + 5])  # (4, F): below, on, between, above
    hats = s.basis(lbar, torch.full((4,), 1e9))[..., 0]  # the clock's constant term: (4, F, K)
    torch.testing.assert_close(hats.sum(-1), torch.ones(4, 2, dtype=torch.float64))  # a partition of 1
    eye = torch.eye(4, dtype=torch.float64)
    torch.testing.assert_close(hats[0], eye[[0, 0]])  # held at the first knot
    torch.testing.assert_close(hats[1], eye[[1, 1]])
    torch.testing.assert_close(hats[2], torch.tensor([[0, 0.25, 0.75, 0]] * 2, dtype=torch.float64))
    torch.testing.assert_close(hats[3], eye[[3, 3]])



def test_one_factor_s_basis_is_its_slice_of_the_whole_bit_for_bit():
    """The fit builds one factor's basis at a time (the whole one of millions of steps does not
    fit in memory); it must be that factor's slice of :meth:`LevelScale.basis` exactly, so the
    fitted weights are the same to the bit."""
    from manifold_nets.observer.level_scale import hat_clock_basis

    s = _scale(knots=5)
    gen = torch.Generator().manual_seed(3)
    lbar = torch.randn(300, 2, generator=gen, dtype=torch.float64) * 3
    k = torch.randint(1, 2000, (300,), generator=gen).double()
    whole = s.basis(lbar, k)
    for f in range(2):
        one = hat_clock_basis(s.knots[f:f + 1], s.taus, s.first, lbar[:, f:f + 1], k)[:, 0]
        assert torch.equal(one, whole[:, f])

def test_it_scales_each_factor_s_block_by_exp_u_and_reads_the_block_s_level():
    obs = _observer()
    r = _readout(obs)
    y = _measurements(3, 7)
    u = {"R": 0.4, "p": -0.7}
    w = torch.zeros(2, 3, 1, dtype=torch.float64)
    w[0], w[1] = u["R"], u["p"]  # the same at every knot: u_f whatever the level
    scale = LevelScale(GROUP, torch.tensor([[-9.0, 0.0, 9.0]] * 2), w, (), 4.0)
    with torch.no_grad():
        _, plain = CalibratedObserver(obs, r)(y)
        _, scaled = CalibratedObserver(obs, r, scale)(y)
    torch.testing.assert_close(scaled[:, 0], plain[:, 0], rtol=0, atol=0)  # the start's is kept
    for name, s in (("R", slice(0, 3)), ("p", slice(3, 6))):
        torch.testing.assert_close(scaled[:, 1:, s, s], math.exp(u[name]) * plain[:, 1:, s, s])
        want = torch.logdet(plain[:, 1:, s, s]) / 3  # a block-diagonal L: log det P_ff / d
        got = scale.level(torch.linalg.cholesky(plain[:, 1:]))[..., ["R", "p"].index(name)]
        torch.testing.assert_close(got, want)


def test_zero_weights_leave_the_covariance_as_it_was():
    obs = _observer()
    r = _readout(obs, clock=(2.0,))
    scale = LevelScale(GROUP, torch.tensor([[0.0, 1.0]] * 2), torch.zeros(2, 2, 2), (5.0,), 3.0)
    y = _measurements(2, 5)
    with torch.no_grad():
        torch.testing.assert_close(CalibratedObserver(obs, r, scale)(y)[1],
                                   CalibratedObserver(obs, r)(y)[1], rtol=1e-12, atol=0)


@pytest.mark.parametrize("counted", [False, True])
@pytest.mark.parametrize("clock", [(), (2.0,)])
def test_rollout_online_and_exported_steps_give_the_same_scaled_covariances(clock, counted):
    """One computation in three places: the averaged level carried as state (``level``), the
    step read from the observer's own count where it keeps one (a step decay), else from
    ``clock_steps``."""
    obs = _observer([StepDecay({"p": 3})] if counted else [])
    cal = CalibratedObserver(obs, _readout(obs, clock), _scale(first=2))
    step = cal.online_step_module()
    names = step.state_names()
    assert names[names.index("memory") + 1] == "level"
    assert ("clock_steps" in names) == (not counted)
    y = _measurements(3, 6)
    program = torch.export.export(step, (*step.initial_state(3), y[:, 0]))
    with torch.no_grad():
        est, cov = cal(y)
        state, flat, flat_x = cal.init_state(3), step.initial_state(3), step.initial_state(3)
        for k in range(6):
            state, P = cal.step(state, y[:, k])
            *flat, P_exp = step(*flat, y[:, k])
            *flat_x, P_prog = program.module()(*flat_x, y[:, k])
            for got in (P, P_exp, P_prog):
                assert_covariances_close(got, cov[:, k + 1])
            torch.testing.assert_close(state.observer.estimate, est[:, k + 1], rtol=0, atol=1e-12)


def test_export_observer_writes_the_scaled_step_and_its_description(tmp_path):
    from manifold_nets import export_observer
    from manifold_nets.deploy import load_exported_step

    obs = _observer()
    scale = _scale()
    cal = CalibratedObserver(obs, _readout(obs, (2.0,)), scale).eval()
    export_observer(cal, tmp_path / "cal.pt2")
    loaded = load_exported_step(tmp_path / "cal.pt2")
    assert loaded.meta["inputs"][-4:] == ["memory", "level", "clock_steps", "y"]
    assert loaded.meta["level_scale"] == scale.signature()
    y = _measurements(2, 5)
    with torch.no_grad():
        _, cov = cal(y)
    assert_step_covariances_follow(loaded, loaded.initial_state(2), y, cov)


def _two_levels(n=40, t=60, off=1.5, seed=5):
    """A memoryless diagonal readout whose features say which of two groups a sequence is in: it
    reports standard deviations 0.1 and 1.0, and the second group's errors are ``off`` times
    larger in variance than it says."""
    r = CovarianceReadout(GROUP, 2, "diagonal", memory=0)
    with torch.no_grad():
        r.out.weight.zero_()
        r.out.weight[:, 0], r.out.weight[:, 1] = math.log(0.1), 0.0
        r.out.bias.zero_()
    which = torch.arange(n) % 2
    feats = torch.zeros(n, t, 2)
    feats[torch.arange(n), :, which] = 1.0
    sd = torch.where(which == 0, 0.1, math.sqrt(off)).double()
    gen = torch.Generator().manual_seed(seed)
    errors = torch.randn(n, t, 6, generator=gen, dtype=torch.float64) * sd[:, None, None]
    return r, Sequences(feats, errors, torch.ones(n, t, dtype=torch.bool)), which


def test_fitting_removes_a_miscalibration_that_depends_on_the_level():
    """At its minimum the scaled NEES averages 1 on every basis function: with two knots at the
    two groups' levels and no smoothing, each group's mean NEES is 1 exactly, where one constant
    scale (the held-out scale) can only make their average 1."""
    r, seqs, which = _two_levels()
    before = {g: factor_nees(r, seqs.select(torch.nonzero(which == g).squeeze(1))) for g in (0, 1)}
    assert before[0]["R"] == pytest.approx(1.0, abs=0.15)
    assert before[1]["R"] == pytest.approx(1.5, abs=0.2)
    scale = fit_level_scale(r, seqs, knots=2, tau=1.0, clock=(), ridge=0.0)
    torch.testing.assert_close(scale.knots, torch.tensor([[2 * math.log(0.1), 0.0]] * 2,
                                                         dtype=torch.float64))
    for g in (0, 1):
        after = factor_nees(r, seqs.select(torch.nonzero(which == g).squeeze(1)), level_scale=scale)
        assert after == pytest.approx({"R": 1.0, "p": 1.0}, abs=1e-6)


def test_a_fit_over_steps_reduced_a_part_at_a_time_is_the_fit_over_the_whole_bit_for_bit():
    """The held-out sequences rolled out and reduced part by part (parts on the batch's
    boundaries, as the rigid-body command reduces one noise level at a time) give the same
    steps, the same fitted weights and knots, and each part's mean NEES as the readout reads it."""
    r, seqs, which = _two_levels(n=40, t=60)
    whole = fit_level_scale(r, seqs, knots=3, tau=4.0, clock=(10.0,), thin=3, batch_size=10)
    parts = [level_steps(r, seqs.select(torch.arange(a, a + 20)), 4.0, batch_size=10)
             for a in (0, 20)]
    steps = LevelSteps.cat(parts)
    assert torch.equal(steps.q, level_steps(r, seqs, 4.0, batch_size=10).q)
    streamed = fit_level_scale(r, steps, knots=3, tau=4.0, clock=(10.0,), thin=3)
    assert torch.equal(streamed.weights, whole.weights) and torch.equal(streamed.knots, whole.knots)
    for a, part in zip((0, 20), parts):
        got = part.nees(whole)
        want = factor_nees(r, seqs.select(torch.arange(a, a + 20)), level_scale=whole)
        torch.testing.assert_close(got, torch.tensor([want["R"], want["p"]], dtype=torch.float64))
    with pytest.raises(ValueError, match="averaged over tau=4, not 5"):
        fit_level_scale(r, steps, knots=3, tau=5.0, clock=(10.0,))
    with pytest.raises(ValueError, match="same tau"):
        LevelSteps.cat([parts[0], level_steps(r, seqs, 5.0)])


def test_a_level_scale_saves_with_its_readout_and_a_bad_one_is_refused(tmp_path):
    obs = _observer()
    r, scale = _readout(obs, (2.0,)), _scale()
    save_readout(tmp_path / "c.pt", r, "test", scale)
    cal = load_readout(tmp_path / "c.pt", obs)
    assert isinstance(cal.level_scale, LevelScale) and cal.level_scale.signature() == scale.signature()
    y = _measurements(2, 5)
    with torch.no_grad():
        torch.testing.assert_close(cal(y)[1], CalibratedObserver(obs, r, scale)(y)[1], rtol=0, atol=0)
    save_readout(tmp_path / "plain.pt", r, "test")
    assert load_readout(tmp_path / "plain.pt", obs).level_scale is None
    good = torch.load(tmp_path / "c.pt", weights_only=True)
    bad = {
        "unsigned": {"knots": scale.knots, "weights": scale.weights},
        "nan": {**good["level_scale"], "weights": scale.weights * float("nan")},
        "order": {**good["level_scale"], "knots": scale.knots.flip(1)},
        "shape": {**good["level_scale"], "weights": scale.weights[:1]},
        "first": {**good["level_scale"], "signature": {**scale.signature(), "first": -3}},
        "code": {**good["level_scale"], "signature": "os.system('x')"},
    }
    for name, entry in bad.items():
        torch.save({**good, "level_scale": entry}, tmp_path / f"{name}.pt")
        with pytest.raises(CheckpointError, match=f"{name}.pt.*level scale"):
            load_readout(tmp_path / f"{name}.pt", obs)


@pytest.mark.parametrize("bad, match", [
    ({"knots": torch.tensor([[0.0, 1.0]])}, "one row per factor"),
    ({"knots": torch.arange(600.0).repeat(2, 1)}, "K <= 256"),
    ({"knots": torch.tensor([[1.0, 0.0]] * 2)}, "increase strictly"),
    ({"weights": torch.zeros(2, 2, 3)}, "weights must be"),
    ({"weights": torch.full((2, 2, 2), float("inf"))}, "finite"),
    ({"tau": 0.5}, "tau must be"),
    ({"first": -1}, "first must be"),
    ({"clock": (-1.0,)}, "clock"),
])
def test_bad_settings_are_refused_with_what_is_wrong(bad, match):
    args = {"knots": torch.tensor([[0.0, 1.0]] * 2), "weights": torch.zeros(2, 2, 2),
            "clock": (5.0,), "tau": 3.0, "first": 1} | bad
    with pytest.raises(ValueError, match=match):
        LevelScale(GROUP, **args)


def test_the_fit_and_the_calibrated_observer_refuse_what_they_cannot_use():
    r, seqs, _ = _two_levels(n=4, t=10)
    with pytest.raises(ValueError, match="too few"):
        fit_level_scale(r, seqs, knots=8)
    with pytest.raises(ValueError, match="knots must be an integer >= 2"):
        fit_level_scale(r, seqs, knots=1)
    flat = CovarianceReadout(GROUP, 2, "diagonal", memory=0)
    with torch.no_grad():
        flat.out.weight.zero_()  # one level at every step
    with pytest.raises(ValueError, match="hardly varies"):
        fit_level_scale(flat, _two_levels(n=40, t=60)[1], knots=2, tau=1.0, clock=())
    obs = _observer()
    other = LevelScale(Product(SO3(), names=("R",)), torch.tensor([[0.0, 1.0]]),
                       torch.zeros(1, 2, 1), (), 2.0)
    with pytest.raises(ValueError, match="LevelScale of the readout's group"):
        CalibratedObserver(obs, _readout(obs), other)


def test_the_rigid_body_command_writes_readouts_with_a_level_scale(tmp_path):
    """The example command, tiny: a readout file per case that loads back with its level scale,
    and the held-out ANEES before and after."""
    import json

    from manifold_nets_examples.rigid_body.level_scale import main, zoo_readout

    main(["--out", str(tmp_path), "--cases", "nominal", "--sigmas", "0.1", "0.5", "--heldout", "3"])
    cal, _ = zoo_readout("nominal")
    loaded = load_readout(tmp_path / "nominal_covariance.pt", cal.observer)
    assert isinstance(loaded.level_scale, LevelScale) and loaded.level_scale.first == 10
    for name, value in cal.readout.state_dict().items():  # the readout itself is the zoo's
        assert torch.equal(loaded.readout.state_dict()[name], value)
    report = json.loads((tmp_path / "level_scale.json").read_text())
    assert set(report["cases"]["nominal"]) == {"0.1", "0.5"}
    assert set(report["cases"]["nominal"]["0.1"]["R"]) == {"before", "after"}


def test_the_rigid_body_command_fits_another_readout_given_by_folder(tmp_path):
    """``--readouts DIR``: the level scale is fitted to ``DIR/<case>_covariance.pt`` (here the
    zoo's readout with one weight changed), and that readout, not the zoo's, is what it writes."""
    from manifold_nets.covariance_training import save_readout
    from manifold_nets_examples.rigid_body.level_scale import main, zoo_readout

    cal, _ = zoo_readout("nominal")
    other = copy.deepcopy(cal.readout)
    name, weight = next(iter(other.state_dict().items()))
    with torch.no_grad():
        weight.add_(0.01)
    (tmp_path / "in").mkdir()
    save_readout(tmp_path / "in" / "nominal_covariance.pt", other, "zoo:rigid_body/nominal")
    main(["--out", str(tmp_path / "out"), "--cases", "nominal", "--sigmas", "0.1", "0.5",
          "--heldout", "3", "--readouts", str(tmp_path / "in")])
    loaded = load_readout(tmp_path / "out" / "nominal_covariance.pt", cal.observer)
    assert isinstance(loaded.level_scale, LevelScale)
    assert torch.equal(loaded.readout.state_dict()[name], other.state_dict()[name])
    assert not torch.equal(loaded.readout.state_dict()[name], cal.readout.state_dict()[name])


def test_the_rigid_body_command_reads_the_held_out_sequences_as_the_given_readout_does(tmp_path):
    """A readout of another source (the residuals and their log size: 8 numbers a step, not 6)
    gets its level scale fitted on its own inputs."""
    from manifold_nets.covariance_training import save_readout
    from manifold_nets.observer import CovarianceReadout
    from manifold_nets.observer.covariance import input_width
    from manifold_nets_examples.rigid_body.level_scale import main, zoo_readout

    cal, _ = zoo_readout("nominal")
    torch.manual_seed(0)
    sized = CovarianceReadout(cal.observer.group, input_width(cal.observer, "residual_size"),
                              "factor", memory=4, source="residual_size")
    (tmp_path / "in").mkdir()
    save_readout(tmp_path / "in" / "nominal_covariance.pt", sized, "zoo:rigid_body/nominal")
    main(["--out", str(tmp_path / "out"), "--cases", "nominal", "--sigmas", "0.1", "0.5",
          "--heldout", "3", "--readouts", str(tmp_path / "in")])
    loaded = load_readout(tmp_path / "out" / "nominal_covariance.pt", cal.observer)
    assert loaded.readout.source == "residual_size" and loaded.readout.width == 8
    assert isinstance(loaded.level_scale, LevelScale)
