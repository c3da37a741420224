"""The planar vehicle on SE(2) x R x R (or SO(2) x R^2 x R x R): config, dataset, group
membership, the exact unicycle step against an ODE solver, the laws, the measurement model and
its noise law, baselines, metrics, and the two layouts' agreement. The generic contract (same
seed -> same data, rollout against step, shapes, dtypes, batches, gradients, the noise rule) is
checked in tests/test_system_contract.py."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from scipy.integrate import solve_ivp

from manifold_nets_examples.planar import Planar
from manifold_nets_examples.planar.filters import PlanarEKF
from manifold_nets_examples.planar.system import course_over_ground
from groups import SE2, SO2
from manifold_nets.data import load_dataset
from manifold_nets import DatasetConfig, load_or_generate, make_dataset

F64 = torch.float64
CONFIGS = str(Path(__file__).resolve().parents[1] / "configs")


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


LAYOUTS = pytest.mark.parametrize("pose_group", ["se2", "so2_r2"])


def pose(system: Planar, x: torch.Tensor) -> torch.Tensor:
    """The homogeneous ``(*batch, 3, 3)`` pose of states in either layout."""
    T = torch.zeros(*x.shape[:-1], 3, 3, dtype=x.dtype)
    T[..., :2, :2] = system.rotation(x)
    T[..., :2, 2] = system.position(x)
    T[..., 2, 2] = 1.0
    return T


def twists_from_states(system: Planar, states: torch.Tensor) -> torch.Tensor:
    """``log(T_k^-1 T_{k+1}) / dt = (v, lateral, omega)``, the held body twist of each step."""
    T = pose(system, states)
    return SE2().log(SE2().between(T[:, :-1], T[:, 1:])) / system.dt


def test_config_composes_and_generates_a_tiny_dataset(tmp_path):
    with initialize_config_dir(config_dir=CONFIGS, version_base="1.3"):
        cfg = compose("generate", overrides=["system=planar", "dataset=planar_small"])
    system = instantiate(cfg.system)
    assert isinstance(system, Planar)
    assert system.config() == Planar().config()  # the yaml restates the defaults
    assert cfg.dataset.name == "planar_small"
    dcfg = DatasetConfig(**dict(cfg.dataset))
    dcfg.num_sequences, dcfg.length, dcfg.cache_dir, dcfg.progress = 10, 6, str(tmp_path), False
    parts = load_or_generate(system, dcfg)
    train = parts["train"]
    assert train.states.shape == (8, 7, 11) and train.measurements.shape == (8, 6, 4)
    assert parts["val"].inputs.shape == (1, 6, 0)
    ds = load_dataset(parts["test"].meta["path"], group=system.group)
    assert ds.meta["system"] == "planar"


@LAYOUTS
def test_every_state_is_on_the_group_after_2000_steps(pose_group):
    system = Planar(pose_group=pose_group)
    ds = system.simulate(8, 2000, 0.0, gen(1))
    assert ds.states.shape == (8, 2001, 11 if pose_group == "se2" else 8)
    system.group.check_member(ds.states, atol=1e-12)
    assert torch.equal(ds.states[:, :, -2:], ds.states[:, :1, -2:].expand(-1, 2001, -1))


def test_both_layouts_embed_the_same_states_and_measure_the_same():
    se2, so2_r2 = Planar(), Planar(pose_group="so2_r2")
    assert se2.config() == Planar().config() and so2_r2.config()["pose_group"] == "so2_r2"
    a, b = se2.simulate(6, 40, 0.1, gen(14)), so2_r2.simulate(6, 40, 0.1, gen(14))
    torch.testing.assert_close(se2.group.embed(a.states), so2_r2.group.embed(b.states),
                               rtol=0, atol=1e-12)
    torch.testing.assert_close(a.measurements, b.measurements, rtol=0, atol=1e-12)
    # the observer's update differs: body-frame translation on SE(2), world-frame on R^2
    v = torch.tensor([1.0, 0.0, 0.0, 0.0, 0.0], dtype=F64)  # the first tangent component
    moved_se2 = se2.position(se2.group.rplus(a.states[:, 5], v))
    moved_r2 = so2_r2.group.rplus(b.states[:, 5], torch.tensor([0.0, 1, 0, 0, 0], dtype=F64))
    torch.testing.assert_close(moved_se2 - se2.position(a.states[:, 5]),
                               se2.rotation(a.states[:, 5])[..., :, 0])
    torch.testing.assert_close(so2_r2.position(moved_r2) - so2_r2.position(b.states[:, 5]),
                               torch.tensor([1.0, 0.0], dtype=F64).expand(6, 2))


@LAYOUTS
def test_step_matches_an_ode_solver_and_is_a_unicycle(pose_group):
    system = Planar(dt=0.2, pose_group=pose_group)
    ds = system.simulate(3, 12, 0.0, gen(2))
    twist = twists_from_states(system, ds.states)
    # a unicycle never slides sideways, and the twists are the drive the simulator drew
    assert twist[..., 1].abs().max() < 1e-12
    g = gen(2)
    system.sample_initial_state(3, g)
    drive = system.sample_drive(3, 12, g)
    torch.testing.assert_close(twist[..., [0, 2]], drive, rtol=0, atol=1e-12)
    for i in range(3):
        x0 = ds.states[i, 0]
        z = np.array([*system.position(x0).tolist(), float(system.heading(x0))])
        for k in range(12):
            v, w = drive[i, k].tolist()
            sol = solve_ivp(lambda _t, z, v=v, w=w: [v * math.cos(z[2]), v * math.sin(z[2]), w],
                            (0, system.dt), z, method="DOP853", rtol=1e-12, atol=1e-12)
            z = sol.y[:, -1]
            x1 = ds.states[i, k + 1]
            assert np.abs(z[:2] - system.position(x1).numpy()).max() < 1e-9
            d = z[2] - float(system.heading(x1))
            assert abs(math.atan2(math.sin(d), math.cos(d))) < 1e-9


@LAYOUTS
def test_step_overrides_dt_and_checks_the_drive(pose_group):
    # dtypes and batches: tests/test_system_contract.py
    system = Planar(pose_group=pose_group)
    x = system.sample_initial_state(4, gen(3))
    w = torch.randn(4, 2, generator=gen(4), dtype=F64)
    two = system.step(system.step(x, w, dt=0.05), w, dt=0.05)
    torch.testing.assert_close(two, system.step(x, w), rtol=0, atol=1e-13)
    with pytest.raises(ValueError, match=r"\(\*batch, 2\)"):
        system.step(x, w[:, :1])


@LAYOUTS
def test_measurement_without_noise_is_the_model(pose_group):
    system = Planar(pose_group=pose_group)
    ds = system.simulate(16, 30, 0.0, gen(5))
    x1, y = ds.states[:, 1:], ds.measurements
    assert torch.equal(y[..., :2], system.position(x1))  # the position of x_{k+1}
    twist = twists_from_states(system, ds.states)
    torch.testing.assert_close(y[..., 2:], twist[..., [0, 2]] + x1[..., -2:], rtol=0, atol=1e-10)


def test_noise_law_and_per_sensor_scales():
    system = Planar(gps_noise=3.0, speed_noise=0.5, turn_rate_noise=1.0)
    sigma = 0.2
    res = (system.simulate(400, 50, sigma, gen(6)).measurements
           - system.simulate(400, 50, 0.0, gen(6)).measurements).reshape(-1, 4)
    scale = torch.tensor([3.0, 3.0, 0.5, 1.0], dtype=F64)
    assert (res.std(0) / (sigma * scale) - 1).abs().max() < 0.03
    assert (res.mean(0) / (sigma * scale)).abs().max() < 0.03
    assert (torch.corrcoef(res.T) - torch.eye(4, dtype=F64)).abs().max() < 0.04
    x = system.sample_initial_state(5, gen(7))
    w, nu = torch.randn(5, 2, dtype=F64), torch.randn(5, 4, dtype=F64)
    torch.testing.assert_close(system.measure(x, w, nu) - system.measure(x, w), nu * scale)


def test_initial_state_drive_and_bias_laws():
    system = Planar(position_range=3.0, speed_min=0.4, speed_max=1.2, speed_bias_range=0.3,
                    turn_rate_bias_range=0.05)
    x0 = system.sample_initial_state(4000, gen(8))
    system.group.check_member(x0)
    p, th = system.position(x0), system.heading(x0)
    assert p.abs().max() <= 3.0 and (p.var(0) / 9 - 1 / 3).abs().max() < 0.03
    assert (th.var() / math.pi**2 - 1 / 3).abs() < 0.03  # uniform heading
    assert x0[:, 9].abs().max() <= 0.3 and x0[:, 10].abs().max() <= 0.05
    w = system.sample_drive(4000, 40, gen(9))
    # v = v_mean exp(s): always forward; E[log v] = E[log v_mean] = (b ln b - a ln a)/(b - a) - 1
    assert float(w[..., 0].min()) > 0
    lo, hi = 0.4, 1.2
    expected = (hi * math.log(hi) - lo * math.log(lo)) / (hi - lo) - 1
    assert abs(float(w[..., 0].log().mean()) - expected) < 0.02
    # per sequence, log v varies about log v_mean with the stated rms (0.2)
    spread = (w[..., 0].log() - w[..., 0].log().mean(1, keepdim=True)).pow(2).mean().sqrt()
    assert 0.1 < float(spread) < 0.2
    assert abs(float(w[..., 1].pow(2).mean().sqrt()) - 0.5) < 0.03
    assert (w[:, 1:] - w[:, :-1]).abs().mean() < 0.05  # smooth, not white


def test_baselines_gps_and_course_over_ground():
    system = Planar()
    clean = system.simulate(20, 40, 0.0, gen(10))
    err = system.measurement_errors(clean)
    assert err["position_m"].abs().max() == 0
    # noise-free, the chord lags the heading by half a step's turn: |omega| dt / 2
    twist = twists_from_states(system, clean.states)
    lag = (twist[..., 2].abs() * system.dt / 2 * 180 / math.pi)
    assert (err["heading_deg"][:, 1:] - lag[:, 1:]).abs().max() < 1e-6
    noisy = system.simulate(200, 40, 0.1, gen(10))
    err = system.measurement_errors(noisy)
    assert abs(float(err["position_m"].mean()) - 0.1 * math.sqrt(math.pi / 2)) < 0.005  # Rayleigh
    assert float(err["heading_deg"].mean()) > 20  # the heading is hard to read off the fixes
    fixes = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]], dtype=F64)
    expected = torch.tensor([[0.0, 0.0, math.pi / 2]], dtype=F64)
    torch.testing.assert_close(course_over_ground(fixes), expected)


@LAYOUTS
def test_metrics_position_and_wrapped_heading(pose_group):
    system = Planar(pose_group=pose_group)
    data = system.simulate(3, 8, 0.0, gen(11))
    exact = system.metrics(data.states, data)
    factors = {"pose"} if pose_group == "se2" else {"R", "p"}
    assert set(exact) == factors | {"b_v", "b_omega", "position_m", "heading_deg"}
    assert all(float(v.abs().max()) < 1e-6 for v in exact.values())
    # turn by 179 deg twice: the heading errors wrap to 2 deg, not 358
    turn = SO2().exp(torch.tensor([math.radians(179.0)], dtype=F64))
    R = system.rotation(data.states) @ turn @ turn
    shift = torch.tensor([0.3, -0.4], dtype=F64)
    est = system.join(R, system.position(data.states) + shift, data.states[..., -2:])
    m = system.metrics(est, data)
    torch.testing.assert_close(m["heading_deg"], torch.full((3, 9), 2.0, dtype=F64))
    torch.testing.assert_close(m["position_m"], torch.full((3, 9), 0.5, dtype=F64))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"speed_min": 2.0, "speed_max": 1.0}, "speed_min <= speed_max"),
        ({"speed_min": 0.0}, "speed_min"),
        ({"freq_max": 5.0}, "Nyquist"),
        ({"dt": -0.1}, "dt"),
        ({"gps_noise": math.nan}, "gps_noise"),
        ({"num_terms": 1.5}, "num_terms"),
        ({"pose_group": "se3"}, "pose_group"),
    ],
)
def test_bad_parameters_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Planar(**kwargs)


@LAYOUTS
def test_filter_hooks_read_the_state_and_the_drive_off_the_measurement(pose_group):
    system = Planar(pose_group=pose_group)
    data = system.simulate(4, 25, 0.0, gen(13))
    x0 = system.state_from_measurement(data.measurements)
    system.group.check_member(x0)
    assert torch.equal(system.position(x0), system.position(data.states[:, 1:]))
    assert torch.equal(system.heading(x0), torch.zeros(4, 25, dtype=F64))
    x = data.states[:, 0]
    for k in range(25):
        w = system.drive_from_measurement(data.measurements[:, k], data.inputs[:, k]) - x[:, -2:]
        x = system.step(x, w)
        torch.testing.assert_close(x, data.states[:, k + 1], rtol=0, atol=1e-12)


@LAYOUTS
def test_ekf_is_consistent_stays_on_the_group_and_beats_the_raw_fixes(pose_group):
    system = Planar(pose_group=pose_group)
    data = make_dataset(system, 12, 60, sigma=0.1, seed=5)
    ekf = PlanarEKF(system, 0.1)
    est = ekf.estimate(data)
    assert est.shape == data.states.shape
    system.group.check_member(est, atol=1e-12)
    x5, P5 = ekf.model.fixes_prior(data.measurements[:, :5])
    nis = ekf.ekf.filter(data.measurements[:, 5:], x0=x5, P0=P5).nis
    assert 1.5 < float(nis[:, 10:].mean()) < 2.5  # 2 degrees of freedom: the model is right
    ours, raw = system.metrics(est, data), system.measurement_errors(data)
    assert ours["position_m"][:, 10:].mean() < 0.6 * raw["position_m"][:, 10:].mean()
    assert ours["heading_deg"][:, 10:].mean() < 0.2 * raw["heading_deg"][:, 10:].mean()
    with pytest.raises(ValueError, match="init_steps"):
        PlanarEKF(system, 0.1, init_steps=1)


def test_experiment_trains_a_few_steps_evaluates_and_compares(tmp_path):
    from manifold_nets_examples.attitude.compare import compare_run, load_run
    from manifold_nets_examples.planar.compare import planar_estimators
    from manifold_nets.evaluation import rollout
    from manifold_nets.cli.train import run

    tiny = [
        "experiment=planar", "debug=tiny", f"dataset.cache_dir={tmp_path / 'data'}",
        "eval.plots=false",
    ]
    with initialize_config_dir(config_dir=CONFIGS, version_base="1.3"):
        cfg = compose("train", overrides=tiny)
    assert cfg.system.pose_group == "so2_r2"
    assert OmegaConf.to_container(cfg.model.measurement) == {"factors": {"p": [0, 2]}}
    (row,) = run(cfg, tmp_path / "run")["table"]
    assert {"p est", "position_m est", "position_m meas", "heading_deg est"} <= set(row)
    assert row["membership max"] < 1e-12
    _, system, model = load_run(tmp_path / "run")
    data = system.simulate(3, 20, 0.1, gen(15))
    system.group.check_member(rollout(model, data), atol=1e-12)  # the estimates stay on the group
    rows = compare_run(tmp_path / "run", planar_estimators, plots=False)
    assert {r["method"] for r in rows} == {
        "learned", "ekf", "dead_reckoning", "measurement", "learned / ekf"}


def test_a_step_that_can_turn_by_pi_is_refused_naming_the_parameters():
    """(Once accepted, silent garbage.) Message: ``Planar: one step can turn by
    up to (4 * turn_rate_rms + turn_rate_bias_range) * dt = (4 * 10 + 0.1) * 0.1 = 4.01 rad,
    which must be < pi ...; Use a smaller dt, turn_rate_rms or turn_rate_bias_range (dt <
    0.07834 s for these values).``"""
    with pytest.raises(
        ValueError,
        match=r"^Planar: one step can turn by up to \(4 \* turn_rate_rms \+ "
        r"turn_rate_bias_range\) \* dt = \(4 \* 10 \+ 0\.1\) \* 0\.1 = 4\.01 rad, which must be "
        r"< pi .* Use a smaller dt, turn_rate_rms or turn_rate_bias_range \(dt < 0\.07834 s for "
        r"these values\)\.$",
    ):
        Planar(turn_rate_rms=10.0)
    with pytest.raises(ValueError, match=r"\(4 \* 0\.5 \+ 0\.1\) \* 2 = 4\.2 rad"):
        Planar(dt=2.0, freq_max=0.2)
    with pytest.raises(ValueError, match=r"\(4 \* 0\.5 \+ 40\) \* 0\.1 = 4\.2 rad"):
        Planar(turn_rate_bias_range=40.0)
    Planar(turn_rate_rms=7.0)  # (28 + 0.1) * 0.1 = 2.81 rad: accepted
