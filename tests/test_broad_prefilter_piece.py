"""BROAD's pre-filters as the library's readings-filter piece (``broad.imu_prefilter``): equal to
the numpy ones (``OnlinePrefilter`` sample by sample, ``prefiltered``/``prefilter_dataset`` in
batch), its step equal to its sequence method, in chunks too, built by the system from its config,
and run by ``mn-apply`` and the exported step of ``zoo:broad/attitude`` on raw readings. On the
committed excerpt (tests/fixtures/broad/, 2000 samples of trial 01, CC-BY-4.0) with a rest put
in front (the excerpt itself is in motion throughout)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from manifold_nets import load_observer
from manifold_nets.cli import apply
from manifold_nets.data import save_dataset
from manifold_nets.observer import FilteredObserver, with_readings_filter
from manifold_nets_examples.broad.data import G0, M0, read_trial, trials_to_dataset
from manifold_nets_examples.broad.imu_prefilter import ImuPrefilter
from manifold_nets_examples.broad.prefilter import OnlinePrefilter, prefilter_dataset, prefiltered
from manifold_nets_examples.broad.rate import decimate
from manifold_nets_examples.broad.simulator import BroadSimulator

FIXTURE = Path(__file__).parent / "fixtures" / "broad" / "excerpt.mat"
SETTINGS = [(0.0, True, 1), (0.5, False, 1), (0.5, True, 1), (0.5, True, 2), (3.0, False, 2)]
#: m/s^2: VQF's second-order filter at 3 s has poles within 2e-3 of 1 at 285.7 Hz, which
#: amplifies the different roundings of the scan, lfilter and the loop a thousandfold
ACC_TOL = {1: 1e-9, 2: 1e-7}


@pytest.fixture(scope="module")
def trial():
    t = read_trial(FIXTURE)
    gyr, acc = t.gyr.copy(), t.acc.copy()
    gyr[:800], acc[:800] = [0.004, -0.002, 0.003], [0.0, 0.0, 9.81]  # a rest, then the excerpt
    return dataclasses.replace(t, gyr=gyr, acc=acc)


def _readings(trial):
    y = torch.from_numpy(np.concatenate((trial.acc / G0, trial.mag / M0), 1))[None]
    return y, torch.from_numpy(trial.gyr)[None]


@pytest.mark.parametrize("tau,rest,order", SETTINGS)
def test_the_piece_is_the_online_and_the_batch_prefilter(trial, tau, rest, order):
    y, u = _readings(trial)
    yf, uf, _ = ImuPrefilter(trial.rate, tau, rest, order=order)(y, u)
    want = prefiltered(trial, tau, rest, order)
    np.testing.assert_allclose(uf[0].numpy(), want.gyr, rtol=0, atol=1e-12)
    np.testing.assert_allclose(yf[0, :, :3].numpy() * G0, want.acc, rtol=0, atol=ACC_TOL[order])
    assert torch.equal(yf[..., 3:], y[..., 3:])  # the magnetometer as it is
    online = OnlinePrefilter(trial.rate, tau, rest, order=order)
    got = [online.update(g, a) for g, a in zip(trial.gyr, trial.acc)]
    np.testing.assert_allclose(uf[0].numpy(), [g for g, _ in got], rtol=0, atol=1e-12)
    np.testing.assert_allclose(yf[0, :, :3].numpy() * G0, [a for _, a in got], rtol=0,
                               atol=ACC_TOL[order])
    if rest:
        assert (trial.gyr[-1] - uf[0, -1].numpy() != 0).all()  # a bias was found and removed


@pytest.mark.parametrize("order", [1, 2])
def test_the_piece_is_prefilter_dataset_on_a_dataset(trial, order):
    ds = trials_to_dataset([trial])
    want = prefilter_dataset(ds, 1 / trial.rate, 0.5, rest=True, order=order)
    yf, uf, _ = ImuPrefilter(trial.rate, 0.5, rest=True, order=order)(ds.measurements, ds.inputs)
    torch.testing.assert_close(yf, want.measurements, rtol=0, atol=ACC_TOL[order] / G0)
    torch.testing.assert_close(uf, want.inputs, rtol=0, atol=1e-12)


@pytest.mark.parametrize("tau,rest,order", SETTINGS)
def test_the_step_is_the_sequence_and_chunks_carry_the_state(trial, tau, rest, order):
    y, u = _readings(trial)
    f = ImuPrefilter(trial.rate, tau, rest, order=order)
    yf, uf, last = f(y[:, :1200], u[:, :1200])
    state, ys, us = f.init_state(1), [], []
    for k in range(1200):
        state, a, b = f.step(state, y[:, k], u[:, k])
        ys.append(a)
        us.append(b)
    tol = 1e-12 if order == 1 else ACC_TOL[order] / G0  # in y's units (g)
    torch.testing.assert_close(torch.stack(ys, 1), yf, rtol=0, atol=tol)
    torch.testing.assert_close(torch.stack(us, 1), uf, rtol=0, atol=1e-15)
    for a, b in zip(state, last):
        torch.testing.assert_close(a, b, rtol=0, atol=tol)
    whole, _, _ = f(y, u)
    state, parts = f.init_state(1), []
    for k in range(0, y.shape[1], 333):  # chunks that split the window and the rest
        part, _, state = f(y[:, k : k + 333], u[:, k : k + 333], state)
        parts.append(part)
    torch.testing.assert_close(torch.cat(parts, 1), whole, rtol=0, atol=tol)


def test_strided_readings_float32_and_a_batch(trial):
    y, u = _readings(trial)
    f = ImuPrefilter(trial.rate, 0.5, rest=True)
    want, want_u, _ = f(y, u)
    both = torch.cat((y, u), -1).expand(2, -1, -1).transpose(0, 1).contiguous().transpose(0, 1)
    yy, uu = both[..., :6], both[..., 6:]
    assert not yy.is_contiguous()
    got, got_u, _ = f(yy, uu, f.init_state(2))
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[0])
    got32, got32_u, state = f(y.float(), u.float(), f.init_state(1, torch.float32))
    assert got32.dtype == got32_u.dtype == torch.float32 and all(s.dtype == torch.float32 for s in state)
    torch.testing.assert_close(got32.double(), want, rtol=0, atol=1e-4)
    torch.testing.assert_close(got32_u.double(), want_u, rtol=0, atol=1e-6)


def test_bad_readings_are_refused_with_the_fix(trial):
    y, u = _readings(trial)
    f = ImuPrefilter(trial.rate, 0.5, rest=True)
    with pytest.raises(ValueError, match=r"y \(N, T, 6\).*got \(1, 2000, 9\).*all of their columns"):
        f(torch.cat((y, u), -1), u)
    with pytest.raises(ValueError, match=r"inputs u .*\(3,\) beside y, got \(1, 2000, 2\)"):
        f(y, u[..., :2])
    with pytest.raises(ValueError, match="tau must be a finite number >= 0"):
        ImuPrefilter(trial.rate, float("nan"))
    with pytest.raises(ValueError, match=r"order must be 1 \(first order\) or 2"):
        ImuPrefilter(trial.rate, 0.5, order=3)


def test_the_system_builds_its_filter_from_its_config():
    assert BroadSimulator().readings_filter() is None  # the raw 9-D readings
    s = BroadSimulator(dt=0.028, rest_bias=True, acc_lowpass=1.0, magnetometer=False)
    f = s.readings_filter()
    assert isinstance(f, ImuPrefilter)
    assert (f.rate, f.tau, f.rest, f.magnetometer, f.n) == (1 / 0.028, 1.0, True, False, 54)
    y = torch.randn(1, 5, 6, dtype=torch.float64)
    assert not f(y, torch.zeros(1, 5, 3, dtype=torch.float64))[0][..., 3:].any()  # 6-D: no mag
    with pytest.raises(ValueError, match="more than 100000.*1 / the system's dt"):
        BroadSimulator(dt=1e-6, rest_bias=True).readings_filter()
    s2 = BroadSimulator(dt=0.028, acc_lowpass=3.0, acc_lowpass_order=2)
    assert s2.readings_filter().order == 2 and s2.config()["acc_lowpass_order"] == 2
    assert "acc_lowpass_order" not in s.config()  # the default stays out of older configs
    assert BroadSimulator(**s2.config()).readings_filter().signature() == \
        s2.readings_filter().signature()
    with pytest.raises(ValueError, match="acc_lowpass_order 2 .* acc_lowpass is 0"):
        BroadSimulator(acc_lowpass_order=2)
    with pytest.raises(ValueError, match="acc_lowpass_order must be 1 .* or 2"):
        BroadSimulator(acc_lowpass=1.0, acc_lowpass_order=3)


@pytest.fixture(scope="module")
def zoo_data(trial, tmp_path_factory):
    """The excerpt at the zoo observer's rate (every 8th sample), raw and pre-filtered."""
    observer, system, _ = load_observer("zoo:broad/attitude")
    k = round(system.dt * trial.rate)
    raw = decimate(trials_to_dataset([trial]), k, 1 / trial.rate)
    folder = tmp_path_factory.mktemp("zoo")
    save_dataset(raw, folder / "raw.npz")
    pre = prefilter_dataset(raw, system.dt, system.acc_lowpass, rest=system.rest_bias,
                            order=system.acc_lowpass_order)
    save_dataset(pre, folder / "pre.npz")
    return observer, system, raw, folder


def test_mn_apply_on_raw_readings_is_the_old_path_on_prefiltered_ones(zoo_data):
    _, _, raw, folder = zoo_data
    args = ["zoo:broad/attitude", "--no-progress", "--chunk", "97"]
    got = np.load(apply.run([*args, str(folder / "raw.npz"), "--out", str(folder / "a.npz")]))
    want = np.load(apply.run([*args, str(folder / "pre.npz"), "--out", str(folder / "b.npz"),
                              "--preprocessed"]))["estimates"]
    assert got["estimates"].shape == want.shape == (1, raw.length + 1, 3, 3)
    np.testing.assert_allclose(got["estimates"], want, rtol=0, atol=1e-6)


def test_the_exported_zoo_step_on_raw_readings_is_the_filtered_rollout(zoo_data, tmp_path):
    from manifold_nets import export_observer
    from manifold_nets.deploy import load_exported_step

    observer, system, raw, _ = zoo_data
    filtered = with_readings_filter(observer, system)
    assert isinstance(filtered, FilteredObserver)
    assert isinstance(load_observer("zoo:broad/attitude").filtered(), FilteredObserver)
    assert load_observer("zoo:rigid_body/nominal").filtered().__class__.__name__ == "ResidualObserver"
    y, u = raw.measurements[:, :80], raw.inputs[:, :80]
    with torch.no_grad():
        want = filtered(y, u)
    export_observer(filtered, tmp_path / "step.pt2", batch=1)
    step = load_exported_step(tmp_path / "step.pt2")
    assert step.meta["readings_filter"]["tau"] == system.acc_lowpass == 2.5
    assert step.meta["readings_filter"]["order"] == 2  # VQF's second-order low-pass
    state = step.initial_state()
    with torch.no_grad():
        for j in range(y.shape[1]):
            state = step(*state, y[:, j], u[:, j])
            np.testing.assert_allclose(state[0].numpy(), want[:, j + 1].flatten(1).numpy(),
                                       rtol=0, atol=1e-6)
    assert state[-1].shape == (1, 3, 2)  # its state, two numbers per axis (lowpass_state)

