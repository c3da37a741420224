"""The model zoo (examples/*/zoo/): a few plain-named trained observers, each with a card.

Each entry loads by name (``zoo:rigid_body/nominal``) without an import by hand and without
executing anything its files name, and reproduces the outputs recorded before the observer was
rebuilt from pieces (``tests/fixtures/zoo_reference.npz``, by
``tests/fixtures/record_zoo_reference.py``; ``rigid_body/paper`` when it entered the zoo): its
rollout within 1e-5 (on the CPU that recorded them it reproduced them to 1e-10; another CPU's
float32 arithmetic moves them by up to 2e-6), and its online and exported
steps this machine's rollout to 1e-10 (the old exported step computed the centring ramp in
float32 and was up to 1.7e-6 off the rollout; today all three share one schedule). On fresh
data of its own system each entry beats the raw measurement.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from manifold_nets import load_observer
from manifold_nets.checkpoint import FORMAT, load_checkpoint
from manifold_nets.loading import ensemble_members
from manifold_nets.plugins import zoo_entries, zoo_path

ROOT = Path(__file__).parents[1]
FIXTURES = Path(__file__).parent / "fixtures"
ENTRIES = [
    "rigid_body/paper", "rigid_body/nominal", "rigid_body/outliers", "rigid_body/correlated",
    "rigid_body/bias_walk", "broad/attitude", "broad/attitude_6d",
]


#: The rigid-body readouts the zoo ships: case (its system) -> the entry and the file. The nominal
#: observer serves the sensor errors too, with a readout fitted on that system's errors.
COVARIANCES = {
    "nominal": ("rigid_body/nominal", "covariance.pt"),
    "sensor": ("rigid_body/nominal", "covariance_sensor.pt"),
    "outliers": ("rigid_body/outliers", "covariance.pt"),
    "correlated": ("rigid_body/correlated", "covariance.pt"),
    "bias_walk": ("rigid_body/bias_walk", "covariance.pt"),
}


def test_the_zoo_is_these_entries_and_at_most_nine_checkpoints_ship():
    assert zoo_entries() == sorted(ENTRIES)
    # what a checkout holds (tests/ keeps its own small fixtures), never a run's outputs: the
    # entries' checkpoints and their covariance readouts, nothing else
    folders = ["examples", "manifold_nets", "groups", "configs", "docs", "benchmarks"]
    shipped = [p for f in folders for p in (ROOT / f).rglob("*.pt")]
    checkpoints = [p for p in shipped if p.parent.name == "checkpoints"]
    readouts = sorted(p for p in shipped if p.name.startswith("covariance"))
    assert len(checkpoints) <= 9, checkpoints
    assert readouts == sorted([zoo_path(e) / f for e, f in COVARIANCES.values()]
                              + [zoo_path("broad/attitude") / "covariance.pt"])
    assert len(shipped) == len(checkpoints) + len(readouts), shipped


#: Entries that are ensembles (``members/<name>/``, each a run folder), with their member count.
ENSEMBLES = {"broad/attitude": 3}


@pytest.mark.parametrize("name", ENTRIES)
def test_an_entry_has_a_card_a_small_checkpoint_of_today_s_format(name):
    folder = zoo_path(name)
    card = (folder / "card.md").read_text()
    assert f"zoo:{name}" in card  # the command that evaluates it
    runs = ensemble_members(folder) or [folder]
    assert len(runs) == ENSEMBLES.get(name, 1)
    for run in runs:
        ckpt_file = run / "checkpoints" / "best.pt"
        assert ckpt_file.stat().st_size < 5 * 2**20
        assert load_checkpoint(ckpt_file)["format"] == FORMAT


@pytest.mark.parametrize("name", list(ENSEMBLES))
def test_an_ensemble_entry_loads_as_its_members(name):
    from manifold_nets.observer import EnsembleObserver

    loaded = load_observer(f"zoo:{name}")
    assert isinstance(loaded.observer, EnsembleObserver)
    for member, run in zip(loaded.observer.members, ensemble_members(zoo_path(name))):
        alone = load_observer(run).observer.state_dict()
        assert all(torch.equal(t, alone[k]) for k, t in member.state_dict().items())


@pytest.mark.parametrize("name", ENTRIES)
def test_an_entry_reproduces_its_recorded_outputs(name):
    sys.path.insert(0, str(FIXTURES))
    try:
        from record_zoo_reference import outputs
    finally:
        sys.path.remove(str(FIXTURES))
    reference = np.load(FIXTURES / "zoo_reference.npz")
    observer, system, _ = load_observer(f"zoo:{name}")
    out = outputs(observer, system)
    # The record was made on one CPU. On another, vectorised float64 kernels (sin, exp, ...) may
    # round the last bit differently and float32 ones (the network) more: measured on an AMD EPYC
    # against the record, the data 3.3e-16, the estimates 1.3e-6 to 2.0e-6 (rigid body, 80 closed-
    # loop steps of a float32 network) and 9.4e-10 (broad/attitude). So: the data to 1e-13, the
    # rollout to the record within 1e-5, and the online and exported steps to this machine's
    # rollout within 1e-10 (the three code paths agree to the last digits on any machine).
    np.testing.assert_allclose(out["measurements"], reference[f"{name}:measurements"], rtol=0,
                               atol=1e-13)
    np.testing.assert_allclose(out["rollout"], reference[f"{name}:rollout"], rtol=0, atol=1e-5,
                               err_msg=f"{name}: rollout")
    for key in ("online", "exported"):
        np.testing.assert_allclose(out[key], out["rollout"], rtol=0, atol=1e-10,
                                   err_msg=f"{name}: {key}")


@pytest.mark.parametrize("name", [e for e in ENTRIES if e.startswith("rigid_body/")])
def test_a_rigid_body_entry_beats_the_raw_measurement_on_its_own_system(name):
    observer, system, _ = load_observer(f"zoo:{name}")
    data = system.simulate(32, 150, 0.4, torch.Generator().manual_seed(123))
    with torch.no_grad():
        est = observer(data.measurements)
    errors, raw = system.metrics(est, data), system.measurement_errors(data)
    for factor in ("R", "p"):
        learned, measured = float(errors[factor][:, 10:].mean()), float(raw[factor][:, 10:].mean())
        assert learned < 0.85 * measured, (name, factor, learned, measured)


def test_an_unknown_entry_is_refused_with_the_list():
    with pytest.raises(ValueError, match="rigid_body/nominal"):
        load_observer("zoo:rigid_body/nope")
    with pytest.raises(ValueError, match="not an installed zoo entry"):
        load_observer("zoo:rigid_body/../zoo/nominal")


def test_a_run_of_an_example_system_loads_with_no_import_by_hand():
    """In a fresh interpreter, by path (not by zoo name, which imports its package): the
    registry finds the example system through the installed entry points."""
    import subprocess

    folder = ROOT / "examples" / "rigid_body" / "zoo" / "bias_walk"
    code = (
        "import sys\n"
        "from manifold_nets import load_observer\n"
        "assert 'manifold_nets_examples.rigid_body' not in sys.modules\n"
        f"obs, system, _ = load_observer({str(folder)!r})\n"
        "print(type(system).__name__)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "MismatchedRigidBody"  # the bias walk's true system


@pytest.mark.parametrize("case", COVARIANCES)
def test_an_entry_s_covariance_loads_and_is_calibrated_on_fresh_data(case):
    """The readout of each system (docs/calibration.md: the residuals and their log size, with a
    level scale), the one the calibration commands pick for it, on 40 fresh sequences of that
    system at sigma 0.3: its ANEES of R and p near 1 (0.91-1.14 on these 40 x 150; 0.980-1.012
    on 100 x 1000, benchmarks/results/calibration.md), where a readout that did not follow the
    noise would be off by the noise level's spread (0.1-0.5: 25x in variance)."""
    from manifold_nets.calibration import calibration, tangent_errors
    from manifold_nets.covariance_training import load_readout
    from manifold_nets_examples.rigid_body.calibration import CASES, _system, readout_file

    name, file = COVARIANCES[case]
    path = zoo_path(name) / file
    assert readout_file(case) == path and CASES[case][0] == name
    observer, system = _system(*CASES[case][:2])
    calibrated = load_readout(path, observer)
    assert calibrated.readout.source == "residual_size" and calibrated.level_scale is not None
    assert path.stat().st_size < 2**20
    assert file in (zoo_path(name) / "card.md").read_text()
    data = system.simulate(40, 150, 0.3, torch.Generator().manual_seed(321))
    with torch.no_grad():
        est, cov = calibrated(data.measurements)
        assert torch.equal(est, observer(data.measurements))  # the point estimate is the entry's
    xi = tangent_errors(system.group, est[:, 10:], data.states[:, 10:])
    out = calibration(system.group, xi, cov[:, 10:])
    for factor in ("R", "p"):
        assert 0.75 < out[factor].anees < 1.33, (case, factor, out[factor].anees)


def test_the_broad_entry_s_covariance_widens_under_a_vibration():
    """broad/attitude's readout (the ensemble's, docs/calibration.md) on the committed excerpt:
    the ensemble's estimates unchanged, a covariance at every step, and a wider one when the
    same recording is shaken (the raw accelerometer shaken within each step, the observer's
    low-passed readings moved a little)."""
    import dataclasses

    from manifold_nets_examples.broad.calibration import estimate_with_covariance
    from manifold_nets_examples.broad.data import read_trial

    trial = read_trial(FIXTURES / "broad" / "excerpt.mat")
    observer, _, _ = load_observer("zoo:broad/attitude")
    assert (zoo_path("broad/attitude") / "covariance.pt").stat().st_size < 2**20
    assert "covariance.pt" in (zoo_path("broad/attitude") / "card.md").read_text()
    est, cov, data = estimate_with_covariance([trial])
    with torch.no_grad():
        start = observer.init_state(1, estimate=est[:, 0])
        torch.testing.assert_close(est, observer(data.measurements, data.inputs, state=start),
                                   rtol=0, atol=0)
    assert cov.shape == (1, data.length + 1, 3, 3) and torch.isfinite(cov).all()
    assert torch.linalg.eigvalsh(cov).min() > 0
    shaken = trial.acc.copy()
    shaken[1::2] += 5.0  # +-2.5 m/s^2 about the mean at every other sample
    _, cov_shaken, _ = estimate_with_covariance([dataclasses.replace(trial, acc=shaken)])
    trace = torch.diagonal(cov, dim1=-2, dim2=-1).sum(-1)[0, 50:]
    trace_shaken = torch.diagonal(cov_shaken, dim1=-2, dim2=-1).sum(-1)[0, 50:]
    # measured: 1.155, and 1.155 with the context (the raw samples' spread) held at the unshaken
    # recording's: this readout widens through the readings, its context barely moves it
    # (docs/calibration.md, On real data)
    assert float(np.median((trace_shaken / trace).numpy())) > 1.1


def test_the_6d_entry_behind_its_filter_ignores_the_magnetometer_columns():
    """broad/attitude_6d's deployed form (``.filtered()``, what ``export_observer`` exports)
    takes six columns of ``y`` and zeroes the magnetometer's: anything there gives the same
    estimates, bit for bit; the accelerometer's columns do move them."""
    filtered = load_observer("zoo:broad/attitude_6d").filtered()
    g = torch.Generator().manual_seed(0)
    y = torch.randn(2, 40, 6, generator=g, dtype=torch.float64) * 0.1
    y[..., 2] += 1.0
    u = torch.randn(2, 40, 3, generator=g, dtype=torch.float64) * 0.1
    other_mag, other_acc = y.clone(), y.clone()
    other_mag[..., 3:] = torch.randn(2, 40, 3, generator=g, dtype=torch.float64)
    other_acc[..., :3] += 0.2
    with torch.no_grad():
        base = filtered(y, u)
        assert torch.equal(filtered(other_mag, u), base)
        assert not torch.allclose(filtered(other_acc, u), base)
