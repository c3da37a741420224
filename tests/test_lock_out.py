"""The lock-out guard: when it re-acquires a factor and what it sets it to, that a guard that never
fires changes nothing, one computation in the rollout, the online and the exported step, a readout
behind it, and the settings it refuses."""

from __future__ import annotations

from functools import partial

import pytest
import torch

from groups import SO3, Euclidean, Product
from manifold_nets.cores import GRUCore
from manifold_nets.observer import (
    CalibratedObserver,
    CovarianceReadout,
    GuardedState,
    LockOutGuard,
    Measurement,
    ResidualObserver,
    RobustMeasurement,
    StepDecay,
)
from manifold_nets.observer.covariance import input_width
from observer_checks import assert_covariances_close, randomise_head

GROUP = Product(SO3(), Euclidean(3), names=("R", "p"))
FACTORS = {"R": [0, 9], "p": [9, 12]}


def _observer(shut_beyond: float | None = 2.0, scales=(), head_seed: int | None = None):
    """An observer with a robust measurement whose weights are 2 below ``shut_beyond`` and 0
    beyond it (``None``: the identity, 1 everywhere); it holds still unless ``head_seed`` gives
    its output layer random weights."""
    torch.manual_seed(0)
    obs = ResidualObserver(GROUP, RobustMeasurement(12, factors=FACTORS, width=2),
                           core=partial(GRUCore, hidden_size=8), scales=list(scales))
    if shut_beyond is not None:
        with torch.no_grad():
            obs.measurement.robust.amplitude.fill_(-0.5)
            obs.measurement.robust.knots.fill_(shut_beyond)
            obs.measurement.robust.log_width.fill_(-5.0)
    if head_seed is not None:
        randomise_head(obs, head_seed, scale=0.3)
    return obs


def _readings(n: int, t: int, offset=(0.0, 0.0, 0.0), seed: int = 1, noise: float = 0.05):
    """Readings ``(n, t, 12)``: rotations near the identity and positions near ``offset``."""
    g = torch.Generator().manual_seed(seed)
    r = SO3().exp(noise * torch.randn(n, t, 3, generator=g, dtype=torch.float64))
    p = torch.tensor(offset, dtype=torch.float64) + noise * torch.randn(n, t, 3, generator=g,
                                                                         dtype=torch.float64)
    return torch.cat([r.flatten(-2), p], -1)


def test_a_locked_out_factor_is_set_to_its_measurement_when_its_average_weight_falls_below_the_floor():
    """Still at the identity and measured 5 m away, ``p`` gets weight 0 at every step: its
    average falls 1 -> 0.75 -> 0.5625 -> 0.42 (tau 4) and crosses 0.5 after the third step, where
    ``p`` becomes that step's measurement and its average starts again at 1. ``R`` (measured
    where it is) keeps weight 2 and is never touched; the unguarded observer stays lost."""
    obs = _observer()
    y = _readings(1, 8, offset=(5.0, 0.0, 0.0), noise=0.0)
    guard = LockOutGuard(obs, tau=4.0, floor=0.5)
    with torch.no_grad():
        run = guard.rollout(y)
        plain = obs(y)
    p = GROUP.element_slice("p")
    est = run.estimates.flatten(2)
    assert run.resets[0].nonzero().tolist() == [[2, 1]]  # after step 3, factor p
    torch.testing.assert_close(est[0, :3, p], torch.zeros(3, 3, dtype=torch.float64))
    torch.testing.assert_close(est[0, 3:, p], y[0, 2:, 9:12])
    # each average moves from 1 toward the weight 2: R over 8 steps, p over the 5 after its reset
    torch.testing.assert_close(run.final.average[0],
                               2.0 - 0.75 ** torch.tensor([8.0, 5.0], dtype=torch.float64))
    assert float(plain.flatten(2)[0, -1, p].abs().max()) == 0.0


def test_a_rotation_re_acquired_from_a_noisy_embedding_is_a_rotation():
    """``xhat exp(log(xhat^-1 m))``, not the reading itself: a measured ``vec R`` with noise on
    its nine entries is no rotation, and the state must stay on the group."""
    obs = _observer(shut_beyond=1.0)
    g = torch.Generator().manual_seed(4)
    turn = SO3().exp(torch.tensor([2.0, 0.0, 0.0], dtype=torch.float64))
    y = torch.zeros(1, 5, 12, dtype=torch.float64)
    y[..., :9] = turn.flatten() + 0.05 * torch.randn(1, 5, 9, generator=g, dtype=torch.float64)
    with torch.no_grad():
        run = LockOutGuard(obs, tau=2.0, floor=0.4).rollout(y)
    assert run.resets[0].nonzero().tolist() == [[1, 0]]  # after step 2, factor R
    rotations = run.estimates[0, :, :9].reshape(-1, 3, 3)
    assert float(SO3().membership_error(rotations).max()) < 1e-12
    assert float(SO3().rminus(turn, rotations[2]).norm()) < 0.15  # near the reading


@pytest.mark.parametrize("offset", [0.0, 50.0])
def test_a_guard_that_never_fires_changes_nothing_to_the_last_bit(offset):
    """With identity weights (1 everywhere, above the floor 0.1) nothing is reset, however far
    the measurements, and the estimates are the observer's own, bit for bit."""
    obs = _observer(shut_beyond=None, head_seed=3)
    y = _readings(4, 12, offset=(offset, 0.0, 0.0))
    with torch.no_grad():
        run = LockOutGuard(obs).rollout(y)
        assert not bool(run.resets.any())
        assert torch.equal(run.estimates, obs(y))


def _locking(n=4, t=14):
    """A moving observer that locks out on half of its sequences (their positions 5 m off)."""
    obs = _observer(head_seed=3)
    y = _readings(n, t)
    y[: n // 2, :, 9:12] += 5.0
    return obs, y


def test_rollout_online_and_exported_steps_agree_and_the_state_carries_over():
    obs, y = _locking()
    guard = LockOutGuard(obs, tau=3.0, floor=0.3).eval()
    step = guard.online_step_module()
    assert step.state_names()[-1] == "lock_out_average"
    program = torch.export.export(step, (*step.initial_state(4), y[:, 0]))
    with torch.no_grad():
        run = guard.rollout(y)
        assert bool(run.resets[:2].any()) and not bool(run.resets[2:].any())
        state, flat, flat_x = guard.init_state(4), step.initial_state(4), step.initial_state(4)
        for k in range(y.shape[1]):
            state = guard.step(state, y[:, k])
            flat = step(*flat, y[:, k])
            flat_x = program.module()(*flat_x, y[:, k])
            want = run.estimates[:, k + 1]
            torch.testing.assert_close(state.estimate, want, rtol=0, atol=1e-12)
            for got in (flat, flat_x):
                torch.testing.assert_close(got[0], want.flatten(1), rtol=0, atol=1e-10)
                torch.testing.assert_close(got[-1], state.average, rtol=0, atol=1e-10)
        head, mid = guard(y[:, :6], return_state=True)
        assert isinstance(mid, GuardedState) and mid.steps == 6
        tail = guard(y[:, 6:], state=mid)
    torch.testing.assert_close(torch.cat([head, tail[:, 1:]], 1), run.estimates, rtol=0, atol=0)


@pytest.mark.parametrize("counted", [False, True])
def test_a_readout_reads_the_guarded_estimates_in_the_rollout_the_online_and_the_exported_step(
        tmp_path, counted):
    """The readout's residuals are formed at the guarded estimates; the exported step carries the
    guard's average before the readout's memory and finds the observer's own step count by name
    (a step decay counts steps)."""
    from manifold_nets import export_observer
    from manifold_nets.deploy import load_exported_step

    obs, y = _locking()
    if counted:
        obs = _observer(head_seed=3, scales=[StepDecay({"p": 3})])
    guard = LockOutGuard(obs, tau=3.0, floor=0.3)
    readout = CovarianceReadout(GROUP, input_width(obs, "residual"), "factor", memory=4,
                                clock=(2.0,))
    with torch.no_grad():
        for p in readout.parameters():
            p.normal_(0, 0.3)
    cal = CalibratedObserver(guard, readout).eval()
    with torch.no_grad():
        est, cov = cal(y)
        torch.testing.assert_close(est, guard(y), rtol=0, atol=0)
        state = cal.init_state(4)
        for k in range(y.shape[1]):
            state, P = cal.step(state, y[:, k])
            assert_covariances_close(P, cov[:, k + 1])
    export_observer(cal, tmp_path / "cal.pt2")
    loaded = load_exported_step(tmp_path / "cal.pt2")
    inputs = loaded.meta["inputs"]
    assert inputs.index("lock_out_average") + 1 == inputs.index("memory")
    assert loaded.meta["lock_out"] == {"tau": 3.0, "floor": 0.3}
    flat = loaded.initial_state(4)
    with torch.no_grad():
        for k in range(y.shape[1]):
            *flat, P = loaded(*flat, y[:, k])
            assert_covariances_close(P, cov[:, k + 1])
        torch.testing.assert_close(flat[0], est[:, -1].flatten(1), rtol=0, atol=1e-10)


def test_what_the_guard_refuses():
    plain = ResidualObserver(GROUP, Measurement(12, factors=FACTORS),
                             core=partial(GRUCore, hidden_size=4))
    with pytest.raises(ValueError, match="model.measurement=\\{type: robust"):
        LockOutGuard(plain)
    with pytest.raises(TypeError, match="ResidualObserver"):
        LockOutGuard(torch.nn.Linear(2, 2))
    obs = _observer()
    for kw in ({"tau": 0.5}, {"tau": float("inf")}, {"floor": 0.0}, {"floor": -1.0},
               {"floor": float("nan")}, {"tau": True}, {"floor": "0.1"}):
        with pytest.raises(ValueError, match="LockOutGuard: (tau|floor)"):
            LockOutGuard(obs, **kw)
    guard = LockOutGuard(obs)
    y = _readings(2, 3)
    with pytest.raises(TypeError, match="GuardedState"):
        guard(y, state=obs.init_state(2))
    bad = GuardedState(obs.init_state(2), torch.ones(2, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="state.average has shape"):
        guard(y, state=bad)
    assert guard.signature()["lock_out"] == {"tau": 20.0, "floor": 0.1}


def _evaluate(tmp_path, name: str, *more: str):
    """The evaluate command's run (in process) of the zoo's outliers observer with its readout on
    3 short sequences; its metrics."""
    import json
    from pathlib import Path

    from hydra import compose, initialize_config_dir

    from manifold_nets.cli.evaluate import run

    root = Path(__file__).resolve().parents[1]
    overrides = ["experiment=mismatch_outliers", "eval.checkpoint=zoo:rigid_body/outliers",
                 "eval.covariance=zoo:rigid_body/outliers", "eval.calibration=true",
                 "eval.sigmas=[0.3]", "eval.num_sequences=3", "eval.length=30",
                 "eval.plots=false", "eval.test_split=false", "eval.progress=false",
                 f"dataset.cache_dir={tmp_path / 'data'}", *more]
    with initialize_config_dir(config_dir=str(root / "configs"), version_base="1.3"):
        cfg = compose("train", overrides=overrides)
    run(cfg, tmp_path / name)
    return json.loads((tmp_path / name / "results" / "metrics.json").read_text())


def test_the_evaluate_command_guards_the_observer_it_is_told_to_and_refuses_what_cannot_lock_out(
        tmp_path):
    """``eval.lock_out`` wraps the learned observer (and its readout) in the guard; on sequences
    where it never fires the table is the unguarded one. An observer with a plain measurement, a
    baseline and malformed settings are refused before the run folder gets anything."""
    plain = _evaluate(tmp_path, "plain")
    guarded = _evaluate(tmp_path, "guarded", "eval.lock_out={tau: 20, floor: 0.1}")
    assert guarded["lock_out"] == {"tau": 20.0, "floor": 0.1} and "lock_out" not in plain
    for key in ("R est", "p est", "R ANEES", "p ANEES"):
        assert guarded["table"][0][key] == plain["table"][0][key], key
    for more, match in [
        (["eval.checkpoint=zoo:rigid_body/bias_walk", "eval.covariance=null",
          "eval.calibration=false"], "cannot lock out"),
        (["method=ekf", "eval.checkpoint=null", "eval.covariance=null"], "guards the learned"),
        (["eval.covariance=null"], "LockOutGuard: floor"),
    ]:
        lock = "{tau: 20, floor: 0}" if match.startswith("LockOutGuard") else "{tau: 20}"
        with pytest.raises(ValueError, match=match):
            _evaluate(tmp_path, "refused", f"eval.lock_out={lock}", *more)
        assert not (tmp_path / "refused").exists()
    with pytest.raises(ValueError, match="mapping of tau and floor"):
        _evaluate(tmp_path, "refused", "eval.lock_out={gamma: 1}")
