"""The 6-D path on BROAD and its pieces: the tilt start, the random heading, the observer without
a magnetometer, the accelerometer pre-filter, the heading cascade, the 6-D reference rows and the
``broad.six_d`` command, on the committed excerpt (tests/fixtures/broad/, 2000 samples of trial
01, CC-BY-4.0, see ATTRIBUTION.md) and on constructed cases."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from groups import SO3
from manifold_nets_examples.broad import six_d
from manifold_nets_examples.broad import train as train_cmd
from manifold_nets_examples.broad.data import read_trial, trials_to_dataset
from manifold_nets_examples.broad.evaluate import input_settings
from manifold_nets_examples.broad.learning import RandomHeading, tilt, without_magnetometer
from manifold_nets_examples.broad.metric import errors, matrix_to_quat, quat_multiply, rmse
from manifold_nets_examples.broad.prefilter import (
    butterworth2,
    OnlinePrefilter,
    lowpass_acc,
    prefilter_dataset,
    rest_bias,
    strapdown,
)
from tests.broad_checks import tiny_split

FIXTURE = Path(__file__).parent / "fixtures" / "broad" / "excerpt.mat"
G = SO3()
DT = 1 / 285.714


@pytest.fixture(scope="module")
def trial():
    return read_trial(FIXTURE)


def test_tilt_turns_the_accelerometer_to_up_by_the_shortest_turn():
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(200, 3, generator=gen, dtype=torch.float64) * 4
    a = torch.cat((a, torch.tensor([[0, 0, 9.81], [0, 0, -9.81], [1e-9, 0, -1.0]]).double()))
    R = tilt(a)
    G.check_member(R)
    up = (R @ (a / a.norm(dim=-1, keepdim=True))[..., None])[..., 0]
    assert torch.allclose(up, torch.tensor([0.0, 0, 1]).double().expand_as(up), atol=1e-9)
    # the shortest turn: its angle is the angle between the reading and up
    want = torch.acos((a[:, 2] / a.norm(dim=-1)).clamp(-1, 1))
    assert torch.allclose(G.distance(R, torch.eye(3).double()), want, atol=1e-6)


def test_random_heading_turns_the_world_about_up_and_nothing_else(trial):
    ds = trials_to_dataset([trial], window=200, stride=300)
    out = RandomHeading()(ds, torch.Generator().manual_seed(1))
    assert torch.equal(out.measurements, ds.measurements) and torch.equal(out.inputs, ds.inputs)
    G.check_member(out.states)
    # "up" in the body frame, R^T e_z, is the same: the inclination cannot tell them apart
    assert torch.allclose(out.states[..., 2, :], ds.states[..., 2, :], atol=1e-12)
    turn = out.states[:, 0] @ ds.states[:, 0].transpose(-1, -2)
    assert float(G.distance(turn, torch.eye(3).double()).std()) > 0.3  # headings differ
    q, q0 = (matrix_to_quat(s[:, 1:].numpy()) for s in (out.states, ds.states))
    moving = np.ones(q.shape[1], dtype=bool)
    for a, b in zip(q, q0):
        assert rmse(a, b, moving)["inclination"] < 1e-6


def test_the_6d_observer_reads_no_magnetometer(trial):
    ds = trials_to_dataset([trial], window=100, stride=100)
    out = without_magnetometer(ds)
    assert torch.equal(out.measurements[..., :3], ds.measurements[..., :3])
    assert not out.measurements[..., 3:].any() and ds.measurements[..., 3:].abs().min() >= 0
    assert torch.equal(out.states, ds.states)


def test_the_prefilter_is_exact_for_gravity_alone_and_smooths_linear_acceleration():
    rng = np.random.default_rng(0)
    T = 6000
    gyr = np.cumsum(rng.normal(0, 0.05, (T, 3)), 0)  # a smooth, turning motion
    Q = strapdown(gyr, DT)
    R_loop, loop = np.eye(3), []
    for w in gyr[:50]:
        R_loop = R_loop @ G.exp(torch.from_numpy(w * DT)).numpy()
        loop.append(R_loop)
    np.testing.assert_allclose(Q[:50], np.array(loop), atol=1e-12)
    R0 = G.exp(torch.tensor([0.3, -0.2, 0.1]).double()).numpy()
    world = np.einsum("ij,tjk->tik", R0, Q)  # body to world
    gravity = np.einsum("tji,j->ti", world, [0.0, 0.0, 9.81])
    np.testing.assert_allclose(lowpass_acc(gyr, gravity, 1 / DT, 1.0), gravity, atol=1e-9)
    # linear acceleration of zero mean (1 Hz, 3 m/s^2 in the world frame)
    t = np.arange(T) * DT
    lin_w = 3.0 * np.stack((np.sin(2 * np.pi * t), np.cos(2 * np.pi * t), 0 * t), 1)
    acc = gravity + np.einsum("tji,tj->ti", world, lin_w)
    out = lowpass_acc(gyr, acc, 1 / DT, 1.0)
    settled = slice(3 * 286, None)
    raw_err = np.linalg.norm(acc - gravity, axis=1)[settled].mean()
    err = np.linalg.norm(out - gravity, axis=1)[settled].mean()
    assert err < 0.2 * raw_err
    assert np.array_equal(lowpass_acc(gyr, acc, 1 / DT, 0.0), acc)
    with pytest.raises(ValueError, match="time constant"):
        lowpass_acc(gyr, acc, 1 / DT, -1.0)


def test_the_second_order_low_pass_is_vqf_s_butterworth_filter_in_the_strapdown_frame():
    """``order=2``: gain 1 at rest and ``1 / sqrt(2)`` at VQF's cutoff ``sqrt(2) / (2 pi tau)``
    Hz; with no turn, the textbook difference equation run sample by sample from rest on the
    first reading; gravity alone passes unchanged while the body turns; linear acceleration of
    zero mean is attenuated more than by the first-order filter of the same ``tau``."""
    rate, tau = 1 / DT, 2.5
    b, a = butterworth2(rate, tau)
    assert a[0] == 1.0
    fc = math.sqrt(2.0) / (2 * math.pi * tau)
    for f, gain in ((0.0, 1.0), (fc, 1 / math.sqrt(2.0))):
        z = np.exp(-2j * math.pi * f / rate)
        h = (b[0] + b[1] * z + b[2] * z * z) / (a[0] + a[1] * z + a[2] * z * z)
        assert abs(abs(h) - gain) < 1e-9
    rng = np.random.default_rng(3)
    acc = 9.81 * np.array([0.1, -0.2, 1.0]) + rng.normal(0, 1.0, (3000, 3))
    out = lowpass_acc(np.zeros((3000, 3)), acc, rate, tau, order=2)
    x, y = [acc[0], acc[0]], [acc[0], acc[0]]  # at rest on the first reading
    for t in range(3000):
        y.append(b[0] * acc[t] + b[1] * x[-1] + b[2] * x[-2] - a[1] * y[-1] - a[2] * y[-2])
        x.append(acc[t])
    np.testing.assert_allclose(out, np.array(y[2:]), rtol=0, atol=1e-9)
    T = 6000
    gyr = np.cumsum(rng.normal(0, 0.05, (T, 3)), 0)
    world = np.einsum("ij,tjk->tik", G.exp(torch.tensor([0.3, -0.2, 0.1]).double()).numpy(),
                      strapdown(gyr, DT))  # fmt: skip
    gravity = np.einsum("tji,j->ti", world, [0.0, 0.0, 9.81])
    np.testing.assert_allclose(lowpass_acc(gyr, gravity, rate, tau, order=2), gravity, atol=1e-9)
    t = np.arange(T) * DT
    lin_w = 3.0 * np.stack((np.sin(2 * np.pi * t), np.cos(2 * np.pi * t), 0 * t), 1)
    moving = gravity + np.einsum("tji,tj->ti", world, lin_w)
    settled = slice(round(4 * tau * rate), None)
    err = {k: np.linalg.norm(lowpass_acc(gyr, moving, rate, tau, order=k) - gravity,
                             axis=1)[settled].mean() for k in (1, 2)}  # fmt: skip
    assert err[2] < 0.5 * err[1]
    with pytest.raises(ValueError, match="order must be 1 .* or 2"):
        lowpass_acc(gyr, moving, rate, tau, order=3)


def test_the_rest_bias_is_the_gyroscope_at_rest_and_ignores_a_slow_steady_turn():
    rng = np.random.default_rng(1)
    rate, n = 285.714, 6000
    bias = np.array([0.004, -0.002, 0.003])
    gyr = bias + rng.normal(0, 0.002, (n, 3))
    acc = np.array([0, 0, 9.81]) + rng.normal(0, 0.07, (n, 3))
    gyr[3000:4000] += [0, 0, 0.05]  # a steady turn of 2.9 deg/s about up: not a rest
    gyr[4000:] += rng.normal(0, 1.0, (2000, 3))  # motion
    acc[4000:] += rng.normal(0, 2.0, (2000, 3))
    b = rest_bias(gyr, acc, rate)
    assert not b[:427].any()  # before the first full window of 1.5 s: no estimate
    np.testing.assert_allclose(b[1000], bias, atol=3e-4)
    np.testing.assert_allclose(b[-1], bias, atol=3e-4)  # the turn and the motion left it
    # only the windows at the turn's start, mostly rest, enter the average: 0.02 deg/s at most
    assert np.abs(b[3000:] - b[3000]).max() < 5e-4
    causal = rest_bias(gyr[:2000], acc[:2000], rate)
    np.testing.assert_array_equal(causal, b[:2000])  # the future never changes the past


def test_the_prefilter_of_a_dataset_matches_that_of_its_trial(trial):
    from manifold_nets_examples.broad.prefilter import prefiltered

    import dataclasses

    # the excerpt is in motion throughout (no rest, no bias): its first 800 samples made a rest
    assert not rest_bias(trial.gyr, trial.acc, trial.rate).any()
    gyr, acc = trial.gyr.copy(), trial.acc.copy()
    gyr[:800], acc[:800] = [0.004, -0.002, 0.003], [0.0, 0.0, 9.81]
    trial = dataclasses.replace(trial, gyr=gyr, acc=acc)
    ds = trials_to_dataset([trial])
    out = prefilter_dataset(ds, 1 / trial.rate, 0.1, rest=True)
    want = trials_to_dataset([prefiltered(trial, 0.1, rest=True)])
    # the dataset pairs sample k+1's readings; its first sample's pair is absent, so the
    # filters start one sample apart and agree once that start has decayed (exp(-21))
    late = slice(600, None)
    torch.testing.assert_close(out.measurements[:, late], want.measurements[:, late],
                               atol=1e-6, rtol=0)  # fmt: skip
    torch.testing.assert_close(out.inputs[:, late], want.inputs[:, late], atol=1e-5, rtol=0)
    torch.testing.assert_close(ds.inputs[0, -1] - out.inputs[0, -1],
                               torch.tensor([0.004, -0.002, 0.003]).to(ds.inputs))
    assert torch.equal(out.measurements[..., 3:], ds.measurements[..., 3:])


def test_the_online_prefilter_gives_the_batch_results_sample_by_sample(trial):
    import dataclasses

    from manifold_nets_examples.broad.prefilter import prefiltered

    gyr, acc = trial.gyr.copy(), trial.acc.copy()
    gyr[:800], acc[:800] = [0.004, -0.002, 0.003], [0.0, 0.0, 9.81]  # a rest, then the excerpt
    trial = dataclasses.replace(trial, gyr=gyr, acc=acc)
    for tau, rest in ((0.0, True), (0.5, False), (0.5, True)):
        want = prefiltered(trial, tau, rest)
        f = OnlinePrefilter(trial.rate, tau, rest)
        got = [f.update(g, a) for g, a in zip(trial.gyr, trial.acc)]
        np.testing.assert_allclose(np.array([g for g, _ in got]), want.gyr, atol=1e-12)
        np.testing.assert_allclose(np.array([a for _, a in got]), want.acc, atol=1e-9)


def _turn_about_up(q: np.ndarray, angle: np.ndarray) -> np.ndarray:
    qz = np.stack((np.cos(angle / 2), 0 * angle, 0 * angle, np.sin(angle / 2)), 1)
    return quat_multiply(qz, q)


def test_the_cascade_keeps_the_6d_inclination_and_takes_the_9d_heading(trial):
    q_ref = trial.quat[trial.known][:500]
    rng = np.random.default_rng(0)
    tilt_err = G.exp(torch.from_numpy(rng.normal(0, 0.02, (500, 3)))).numpy()
    q6 = _turn_about_up(quat_multiply(matrix_to_quat(tilt_err), q_ref), rng.uniform(-3, 3, 500))
    q9 = _turn_about_up(q_ref, rng.normal(0, 0.05, 500))  # right tilt, small heading error
    q = six_d.cascade(q6, q9)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1, atol=1e-12)
    e, e6, e9 = (errors(x, q_ref) for x in (q, q6, q9))
    np.testing.assert_allclose(e["inclination"], e6["inclination"], atol=1e-7)
    assert np.abs(e["heading"]).max() < np.abs(e9["heading"]).max() + 0.05
    assert np.abs(e6["heading"]).max() > 1.0  # the 6-D heading was arbitrary
    np.testing.assert_allclose(np.abs(six_d.cascade(q9, q9)), np.abs(q9), atol=1e-12)


def test_the_6d_ensemble_averages_inclinations_whatever_the_headings(trial):
    from manifold_nets_examples.broad.seeds import ensemble

    q_ref = trial.quat[trial.known][:500]
    rng = np.random.default_rng(4)
    tilt = G.exp(torch.from_numpy(rng.normal(0, 0.02, (500, 3)) * [1, 1, 0])).numpy()
    back = np.transpose(tilt, (0, 2, 1))  # the opposite tilt about the same horizontal axis
    a = _turn_about_up(quat_multiply(matrix_to_quat(tilt), q_ref), rng.uniform(-3, 3, 500))
    b = _turn_about_up(quat_multiply(matrix_to_quat(back), q_ref), rng.uniform(-3, 3, 500))
    got = six_d.tilt_ensemble([a, b])
    e_a, e = (np.abs(errors(x, q_ref)["inclination"]) for x in (a, got))
    assert e_a.mean() > 0.01 and e.max() < 1e-3 * e_a.max()  # radians: the tilts cancel
    np.testing.assert_allclose(errors(got, a)["heading"], 0, atol=1e-6)  # the first's heading
    assert np.abs(errors(ensemble([a, b]), q_ref)["inclination"]).max() > 0.02  # unaligned: no


def test_the_6d_reference_rows_track_the_excerpt(trial):
    pytest.importorskip("vqf")
    from manifold_nets_examples.broad.reference import riann_6d, vqf_6d

    q = vqf_6d([trial])[0]
    assert q.shape == (len(trial), 4)
    assert rmse(q, trial.quat, trial.movement)["inclination"] < 3.0
    pytest.importorskip("riann")
    q = riann_6d([trial])[0]
    assert q.shape == (len(trial), 4) and np.isfinite(q).all()
    assert rmse(q, trial.quat, trial.movement)["inclination"] < 5.0


@pytest.fixture(scope="module")
def six_d_runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("broad6")
    _, split = tiny_split(tmp)
    common = ["--split", str(split), "--hidden-size", "8", "--num-layers", "1", "--decimation",
              "4", "--pretrain-sequences", "4", "--pretrain-length", "16", "--pretrain-epochs",
              "1", "--window", "32", "--stride", "64", "--finetune-epochs", "1", "--batch-size",
              "4", "--mounting", "0"]  # fmt: skip
    train_cmd.main([*common, "--out", str(tmp / "r6"), "--magnetometer", "0",
                    "--acc-lowpass", "0.5", "--acc-lowpass-order", "2", "--rest-bias", "1",
                    "--tilt-tau", "1.5", "--loss-weights", "0,0,0,0,0,0,1,1,1"])  # fmt: skip
    train_cmd.main([*common, "--out", str(tmp / "r9")])
    return tmp, split


def test_a_6d_run_records_what_it_reads_and_is_scored_on_whole_trials(six_d_runs):
    tmp, _ = six_d_runs
    from manifold_nets import load_observer

    # the run's system config says how its observer reads, so its files alone suffice
    assert input_settings(load_observer(tmp / "r6")[1]) == {
        "magnetometer": False, "acc_lowpass": 0.5, "acc_lowpass_order": 2, "rest_bias": True}
    assert input_settings(load_observer(tmp / "r9")[1]) == {
        "magnetometer": True, "acc_lowpass": 0.0, "acc_lowpass_order": 1, "rest_bias": False}
    system6 = yaml.safe_load((tmp / "r6" / "config.yaml").read_text())["system"]
    assert system6["rest_bias"] and system6["acc_lowpass_order"] == 2
    # a system config without the keys (an older run, the first zoo entry) reads the raw 9-D
    assert input_settings(object()) == {"magnetometer": True, "acc_lowpass": 0.0,
                                        "acc_lowpass_order": 1, "rest_bias": False}
    res = json.loads((tmp / "r6" / "results" / "learned_test.json").read_text())
    assert math.isfinite(res["mean"]["inclination"])
    # trained on the inclination alone (the loss's third row of R), recorded with the command
    command = json.loads((tmp / "r6" / "command.json").read_text())
    assert command["loss_weights"] == [0.0] * 6 + [1.0] * 3
    assert json.loads((tmp / "r9" / "command.json").read_text())["loss_weights"] is None
    prior = load_observer(tmp / "r6")[0].signature()["prior"]
    assert (prior["type"], prior["tau"], prior["inner"]["type"]) == ("complementary", 1.5,
                                                                     "kinematic")  # fmt: skip


def test_a_run_from_an_observer_without_the_tilt_correction_adds_it(six_d_runs, trial):
    """``--init-from`` an observer trained without ``--tilt-tau``: the new run's observer is the
    old one's weights behind the tilt correction (untrained here: its own checkpoint is written,
    not the old one's file), and it levels a tilted estimate the old one leaves; with
    ``--heading-only 1`` its tilt is the correction's alone, ``t <- t - (dt / tau) sin t``."""
    from manifold_nets import load_observer

    tmp, split = six_d_runs
    train_cmd.main(["--split", str(split), "--out", str(tmp / "r9t"), "--init-from",
                    str(tmp / "r9"), "--hidden-size", "8", "--num-layers", "1", "--decimation",
                    "4", "--pretrain-epochs", "0", "--finetune-epochs", "0", "--tilt-tau", "0.5",
                    "--eval-splits", "test", "--heading-only", "1"])  # fmt: skip
    old, system, _ = load_observer(tmp / "r9")
    new, _, _ = load_observer(tmp / "r9t")
    assert new.signature()["prior"]["type"] == "complementary"
    assert new.signature()["scales"][0] == {"type": "projection", "factors": {"x": [[0, 0, 1]]}}
    for (k, a), b in zip(old.state_dict().items(), new.state_dict().values()):
        assert torch.equal(a, b), k
    y = torch.zeros(1, 40, 6, dtype=torch.float64)
    y[..., 2], y[..., 4] = 1.0, 1.0  # at rest: up, and a field to the north
    tilted = SO3().exp(torch.tensor([[0.2, 0.0, 0.0]], dtype=torch.float64))
    tilts = []
    for obs in (old.double(), new.double()):
        start = obs.init_state(1)._replace(estimate=tilted)
        with torch.no_grad():
            R = obs(y, torch.zeros(1, 40, 3, dtype=torch.float64), start)[0, -1]
        tilts.append(torch.arccos(R[2, 2]).item())
    assert tilts[1] < 0.2 * math.exp(-40 * system.dt / 0.5) * 1.5 < tilts[0]
    t = 0.2
    for _ in range(40):
        t -= system.dt / 0.5 * math.sin(t)
    assert tilts[1] == pytest.approx(t, abs=1e-9)


def test_a_run_with_the_gated_heading_correction_turns_only_the_heading(six_d_runs):
    """``--heading-tau`` (and ``--heading-gate 1``) from an observer without it: the weights
    carry over, the prior is the heading correction after the tilt correction, gated by the
    system's field; held still with a heading error and the field undisturbed, the estimate's
    heading error shrinks by ``(dt / tau) sin`` of itself and its tilt stays; with the field 30 %
    too strong nothing turns it."""
    from manifold_nets import load_observer
    from manifold_nets_examples.broad.learning import field_gate

    tmp, split = six_d_runs
    train_cmd.main(["--split", str(split), "--out", str(tmp / "r9h"), "--init-from",
                    str(tmp / "r9"), "--hidden-size", "8", "--num-layers", "1", "--decimation",
                    "4", "--pretrain-epochs", "0", "--finetune-epochs", "0", "--tilt-tau", "0.5",
                    "--heading-tau", "0.25", "--heading-gate", "1", "--heading-only", "1",
                    "--eval-splits", "test"])  # fmt: skip
    old, _, _ = load_observer(tmp / "r9")
    new, system, _ = load_observer(tmp / "r9h")
    prior = new.signature()["prior"]
    assert (prior["vector"], prior["tau"], prior["about"]) == ([3, 6], 0.25, [0.0, 0.0, 1.0])
    assert prior["gate"] == field_gate(system) and prior["inner"]["tau"] == 0.5
    for (k, a), b in zip(old.state_dict().items(), new.state_dict().values()):
        assert torch.equal(a, b), k
    new = new.double()
    new.core.head.weight.data.zero_()  # the priors alone (the core's heading-only turn is its own)
    new.core.head.bias.data.zero_()
    dip = math.radians(system.magnetic_dip_deg)
    strength = system.magnetic_strength / 44.0
    e, steps = 0.3, 30
    for scale, turned in ((1.0, True), (1.3, False)):
        y = torch.zeros(1, steps, 6, dtype=torch.float64)
        y[..., 2] = 1.0
        y[..., 4], y[..., 5] = scale * strength * math.cos(dip), -scale * strength * math.sin(dip)
        start = new.init_state(1)._replace(
            estimate=SO3().exp(torch.tensor([[0.0, 0.0, e]], dtype=torch.float64)))
        with torch.no_grad():
            R = new(y, torch.zeros(1, steps, 3, dtype=torch.float64), start)[0, -1]
        assert R[2, 2] == pytest.approx(1.0, abs=1e-12)  # no tilt
        t = e
        for _ in range(steps if turned else 0):
            t -= system.dt / 0.25 * math.sin(t)
        assert math.atan2(R[1, 0], R[0, 0]) == pytest.approx(t, abs=1e-9)


def test_the_six_d_command_writes_the_rows_and_the_cascade(six_d_runs):
    pytest.importorskip("vqf")
    tmp, split = six_d_runs
    out = tmp / "table"
    r6, r9 = str(tmp / "r6"), str(tmp / "r9")
    six_d.main(["--split", "test", "--config", str(split), "--out", str(out),
                "--learned", f"six={r6},{r6}", "--cascade", f"both={r6}+{r9}",
                "--ensemble"])  # fmt: skip
    metrics = json.loads((out / "metrics.json").read_text())
    rows = metrics["inclination"]
    assert {"vqf_6d", "vqf_9d", "six"} <= set(rows)
    assert rows["six"]["std_over_runs"] == 0.0  # the same run twice
    assert math.isclose(rows["six"]["mean"], rows[f"six [{r6}]"]["mean"])
    assert math.isclose(rows["six (ensemble of 2)"]["mean"], rows["six"]["mean"], rel_tol=1e-9)
    both = {r["trial"]: r for r in metrics["cascades"] if r["method"] == "both"}
    assert math.isclose(both["te"]["inclination"], rows["six"]["te"], rel_tol=1e-9)
    assert "### 6-D" in (out / "table.md").read_text()
    with pytest.raises(SystemExit, match="LABEL=RUN6"):
        six_d.main(["--out", str(out), "--cascade", f"x={r6}"])
    with pytest.raises(SystemExit, match="broad/attitude_6d"):  # the installed entries, listed
        six_d.main(["--out", str(out), "--learned", "x=zoo:broad/nope"])


def test_the_six_d_command_scores_the_6d_zoo_entry(six_d_runs):
    pytest.importorskip("vqf")
    tmp, split = six_d_runs
    six_d.main(["--split", "test", "--config", str(split), "--out", str(tmp / "zoo6"),
                "--learned", "entry=zoo:broad/attitude_6d"])  # fmt: skip
    rows = json.loads((tmp / "zoo6" / "metrics.json").read_text())["inclination"]
    assert 0 < rows["entry"]["mean"] < 3.0  # degrees on the excerpt (2.49 measured)


def test_the_seed_ensemble_is_the_mean_rotation_whatever_the_signs():
    from manifold_nets_examples.broad.seeds import ensemble

    rng = np.random.default_rng(2)
    mid = matrix_to_quat(G.random((50,), generator=torch.Generator().manual_seed(3),
                                  dtype=torch.float64).numpy())  # fmt: skip
    turn = matrix_to_quat(G.exp(torch.from_numpy(rng.normal(0, 0.05, (50, 3)))).numpy())
    back = turn * np.array([1, -1, -1, -1])  # the inverse turn
    a, b = quat_multiply(turn, mid), -quat_multiply(back, mid)  # b with the other sign
    got = ensemble([a, b])
    assert np.abs(errors(got, mid)["total"]).max() < 1e-12
    np.testing.assert_allclose(ensemble([a, -a]), a, atol=1e-15)


def test_the_seeds_command_gives_mean_spread_and_ensemble(six_d_runs):
    pytest.importorskip("vqf")
    from manifold_nets_examples.broad import seeds

    tmp, split = six_d_runs
    r9, r6 = str(tmp / "r9"), str(tmp / "r6")
    out = tmp / "seeds"
    seeds.main(["--split", "test", "--config", str(split), "--out", str(out),
                "--runs", f"a={r9},{r9}", "--runs", f"b={r6}", "--ensemble"])  # fmt: skip
    rows = json.loads((out / "metrics.json").read_text())
    assert set(rows) == {"vqf", "a", "a (ensemble of 2)", "b"}
    assert rows["a"]["std"]["total"] == 0.0 and rows["b"]["std"]["total"] is None
    assert math.isclose(rows["a (ensemble of 2)"]["mean"]["total"], rows["a"]["mean"]["total"],
                        rel_tol=1e-9)  # fmt: skip
    stored = json.loads((tmp / "r9" / "results" / "learned_test.json").read_text())
    assert math.isclose(rows["a"]["mean"]["inclination"], stored["mean"]["inclination"],
                        rel_tol=1e-9)  # fmt: skip
    with pytest.raises(SystemExit, match="no such run"):
        seeds.main(["--out", str(out), "--runs", f"c={tmp / 'nowhere'}"])
