"""The learned BROAD observer on the committed excerpt: the rate change, the augmentation, the
measured start, a tiny training run through the command, and the apply command.

The excerpt (tests/fixtures/broad/, 2000 samples of trial 01, CC-BY-4.0, see ATTRIBUTION.md)
stands in for the recordings, so these run without ../shared.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from groups import SO3
from manifold_nets import load_observer
from manifold_nets_examples.broad import apply as apply_cmd
from manifold_nets_examples.broad import train as train_cmd
from manifold_nets_examples.broad.data import read_trial, trials_to_dataset
from manifold_nets_examples.broad.evaluate import observer_quaternions
from manifold_nets_examples.broad.learning import RandomMounting, measured_start
from manifold_nets_examples.broad.metric import errors, quat_to_matrix
from manifold_nets_examples.broad.rate import decimate, upsample
from manifold_nets_examples.broad.simulator import BROAD_DT, BroadSimulator
from tests.broad_checks import tiny_split

FIXTURE = Path(__file__).parent / "fixtures" / "broad" / "excerpt.mat"
G = SO3()


@pytest.fixture(scope="module")
def trial():
    return read_trial(FIXTURE)


def _integrate(R0, rates, dt):
    out = [R0]
    for i in range(rates.shape[1]):
        out.append(out[-1] @ G.exp(rates[:, i] * dt))
    return torch.stack(out, 1)


def test_decimated_rates_integrate_exactly_like_the_full_rate_gyroscope(trial):
    ds = trials_to_dataset([trial])
    k = 8
    dec = decimate(ds, k, BROAD_DT)
    j = ds.length // k
    assert dec.states.shape == (1, j + 1, 3, 3) and dec.inputs.shape == (1, j, 3)
    assert torch.equal(dec.states, ds.states[:, : j * k + 1 : k])
    assert torch.equal(dec.measurements[:, 0], ds.measurements[:, k - 1])  # y at sample k
    assert torch.equal(dec.mask, ds.mask[:, : j * k + 1 : k])
    full = _integrate(ds.states[:, 0], ds.inputs, BROAD_DT)
    coarse = _integrate(ds.states[:, 0], dec.inputs, k * BROAD_DT)
    assert torch.allclose(coarse, full[:, : j * k + 1 : k], atol=1e-10)
    # and back: every sample from the last coarse estimate and the gyro in between
    assert torch.allclose(upsample(coarse, ds.inputs, BROAD_DT, k), full, atol=1e-10)
    assert decimate(ds, 1, BROAD_DT) is ds
    with pytest.raises(ValueError, match="decimation factor k must be a positive integer"):
        decimate(ds, 0, BROAD_DT)


def test_random_mounting_turns_the_body_frame_and_keeps_the_world_frame(trial):
    ds = trials_to_dataset([trial], window=200, stride=300)
    out = RandomMounting()(ds, torch.Generator().manual_seed(0))
    R, Rm = ds.states[:, 1:], out.states[:, 1:]
    for a in (slice(0, 3), slice(3, 6)):  # acc and mag in the world frame: unchanged
        world = (R @ ds.measurements[..., a, None])[..., 0]
        assert torch.allclose((Rm @ out.measurements[..., a, None])[..., 0], world, atol=1e-12)
    # the gyro turns with the body: the mounted states integrate the mounted rates
    Q = (out.states[:, :1].transpose(-1, -2) @ ds.states[:, :1])  # R' = R Q^T -> Q = R'^T R
    assert torch.allclose((Q @ ds.inputs[..., None])[..., 0], out.inputs, atol=1e-12)
    G.check_member(out.states)
    assert torch.equal(out.mask, ds.mask)
    small = RandomMounting(max_angle=0.1)(ds, torch.Generator().manual_seed(0))
    angle = G.distance(small.states[:, 0], ds.states[:, 0])
    assert float(angle.max()) <= 0.1 + 1e-9


def test_the_measured_start_is_near_the_reference(trial):
    ds = trials_to_dataset([trial], window=100, stride=100)
    R0 = measured_start(BroadSimulator())(ds)
    known = ds.mask[:, 0]
    deg = G.distance(R0[known], ds.states[known, 0]) * 180 / math.pi
    # TRIAD from one sample of a hand-moved IMU: its linear acceleration tilts "up" by degrees
    assert float(deg.median()) < 10.0 and float(deg.max()) < 25.0


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("broad")
    _, split = tiny_split(tmp)
    train_cmd.main([
        "--split", str(split), "--out", str(tmp / "run"), "--hidden-size", "8",
        "--num-layers", "1", "--decimation", "4", "--pretrain-sequences", "8",
        "--pretrain-length", "16", "--pretrain-epochs", "1", "--window", "32", "--stride", "64",
        "--finetune-epochs", "2", "--batch-size", "4",
    ])
    return tmp / "run"


def test_a_tiny_run_trains_both_stages_and_evaluates_whole_trials(tiny_run):
    for stage in ("pretrain", "finetune"):
        assert (tiny_run / stage / "checkpoints" / "best.pt").is_file()
    results = yaml.safe_load((tiny_run / "results" / "learned_test.json").read_text())
    assert set(results["trials"]) == {"te"}
    for key in ("total", "heading", "inclination"):
        assert math.isfinite(results["mean"][key]) and results["mean"][key] >= 0
    q = np.load(tiny_run / "results" / "learned_test_quaternions.npz")["te"]
    assert q.shape == (2000, 4)
    observer, system, _ = load_observer(tiny_run)
    assert observer.signature()["prior"]["velocities"] == {"x": [6, 9]}
    assert math.isclose(system.dt, 4 * BROAD_DT)


def test_a_second_run_into_the_same_folder_is_refused(tiny_run):
    with pytest.raises(SystemExit, match="already holds a trained observer"):
        train_cmd.main(["--out", str(tiny_run), "--pretrain-epochs", "1"])


def test_apply_writes_one_unit_quaternion_per_sample(tiny_run, tmp_path, trial, capsys):
    apply_cmd.main([str(tiny_run), str(FIXTURE), "--out", str(tmp_path / "q.csv")])
    printed = capsys.readouterr().out
    assert "2000 quaternions (w, x, y, z)" in printed
    assert "movement samples with a reference: total" in printed
    rows = np.loadtxt(tmp_path / "q.csv", delimiter=",", skiprows=1)
    assert (tmp_path / "q.csv").read_text().startswith("w,x,y,z\n")
    assert rows.shape == (2000, 4) and np.allclose(np.linalg.norm(rows, axis=1), 1)
    apply_cmd.main([str(tiny_run), str(FIXTURE), "--out", str(tmp_path / "q.npy")])
    q = np.load(tmp_path / "q.npy", allow_pickle=False)
    assert np.allclose(q, rows)
    observer, system, _ = load_observer(tiny_run)
    assert np.allclose(q, observer_quaternions(observer, system, [trial])[0])
    # the first estimate is the measured start: near the reference
    assert np.degrees(errors(q[:1], trial.quat[:1])["total"][0]) < 25
    assert np.allclose(quat_to_matrix(q[:1])[0] @ quat_to_matrix(q[:1])[0].T, np.eye(3))


def test_apply_refuses_a_bad_output_name_before_any_work(tiny_run, tmp_path):
    with pytest.raises(SystemExit, match=r"error: --out .*q\.txt: the name must end in \.npy or \.csv"):
        apply_cmd.main([str(tiny_run), str(FIXTURE), "--out", str(tmp_path / "q.txt")])
    assert not (tmp_path / "q.txt").exists()


def test_the_compare_command_puts_the_learned_row_beside_the_filters(tiny_run, tmp_path):
    from manifold_nets_examples.broad import compare

    data, split = tiny_split(tmp_path)
    tuned = Path(__file__).parents[1] / "benchmarks" / "results" / "broad_tuned.json"
    compare.main([
        "--data-dir", str(data), "--config", str(split), "--out", str(tmp_path / "cmp"),
        "--split", "test", "--methods", "vqf", "--tuned", str(tuned),
        "--learned", f"learned={tiny_run}", "--learned", "shipped=zoo:broad/attitude",
    ])
    table = (tmp_path / "cmp" / "table.md").read_text()
    assert "| learned |" in table and "| vqf |" in table and "| shipped |" in table
    assert (tmp_path / "cmp" / "figures" / "te.png").is_file()
    with pytest.raises(SystemExit, match="--learned takes LABEL=RUN"):
        compare.main(["--out", str(tmp_path / "x"), "--learned", str(tiny_run)])
    with pytest.raises(SystemExit, match="label 'vqf' is taken"):
        compare.main(["--out", str(tmp_path / "x"), "--learned", f"vqf={tiny_run}"])
    with pytest.raises(SystemExit, match="--learned x=zoo:broad/nope: zoo:broad/nope is not an "
                                         "installed zoo entry; the entries are"):
        compare.main(["--out", str(tmp_path / "x"), "--learned", "x=zoo:broad/nope"])


def test_the_shipped_observer_loads_and_tracks_the_excerpt(trial, tmp_path):
    """The zoo's broad/attitude (docs/real_data.md): loads without executing anything, and on
    the excerpt (from a training trial, started mid-motion from TRIAD) stays within degrees."""
    shipped = Path(__file__).parents[1] / "examples" / "broad" / "zoo" / "attitude"
    res = apply_cmd.apply_observer(shipped, FIXTURE, tmp_path / "q.npy")
    assert res["quaternions"].shape == (2000, 4)
    assert res["rmse"]["total"] < 10.0, res["rmse"]
    observer, system, _ = load_observer(shipped)
    assert [m["core"]["hidden_size"] for m in observer.signature()["ensemble"]] == [64] * 3
    for member in (shipped / "members").iterdir():
        assert (member / "checkpoints" / "best.pt").stat().st_size < 5 * 2**20
