"""``broad.crossval``: k-fold cross-validation over trials, on two copies of the committed excerpt
(tests/fixtures/broad/, CC-BY-4.0) as two folds, tiny runs trained per fold."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import yaml

from manifold_nets_examples.broad import crossval
from manifold_nets_examples.broad import train as train_cmd
from manifold_nets_examples.broad.data import read_trial
from manifold_nets_examples.broad.metric import rmse
from manifold_nets_examples.broad.seeds import ensemble
from tests.broad_checks import FIXTURE


def _fold(folder, name, train, held):
    path = folder / f"{name}.yaml"
    path.write_text(yaml.safe_dump({"data_dir": str(folder / "mat"),
                                    "splits": {"train": train, "val": held, "test": held}}))
    return str(path)


@pytest.fixture(scope="module")
def folds(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("cv")
    (tmp / "mat").mkdir()
    for name in ("a", "b"):
        shutil.copyfile(FIXTURE, tmp / "mat" / f"{name}.mat")
    f1, f2 = _fold(tmp, "f1", ["b"], ["a"]), _fold(tmp, "f2", ["a"], ["b"])
    common = ["--hidden-size", "8", "--num-layers", "1", "--decimation", "4",
              "--pretrain-sequences", "0", "--window", "32", "--stride", "64",
              "--finetune-epochs", "1", "--batch-size", "4", "--mounting", "0",
              "--eval-splits", "val"]  # fmt: skip
    for seed in (0, 1):
        for k, f in ((1, f1), (2, f2)):
            train_cmd.main([*common, "--split", f, "--seed", str(seed),
                            "--out", str(tmp / f"r{k}_s{seed}")])  # fmt: skip
    # a fold-2 run whose estimates differ from fold 1's even untrained (a tilt correction)
    train_cmd.main([*common, "--split", f2, "--tilt-tau", "1.5", "--out", str(tmp / "r2_tilt")])
    return tmp, f1, f2


def test_each_trial_is_scored_by_the_run_that_did_not_train_on_it(folds):
    pytest.importorskip("vqf")
    tmp, f1, f2 = folds
    out = tmp / "table"
    crossval.main(["--out", str(out), "--folds", f"{f1},{f2}",
                   "--runs", f"c={tmp / 'r1_s0'},{tmp / 'r2_s0'}",
                   "--runs", f"c={tmp / 'r1_s1'},{tmp / 'r2_s1'}", "--ensemble"])  # fmt: skip
    got = json.loads((out / "metrics.json").read_text())
    assert got["chosen"] == "c" and set(got["rows"]) == {"vqf", "c", "c (ensemble of 2)"}
    # the ensemble row: each trial's two seeds (their stored estimates) averaged, then scored
    ens = got["rows"]["c (ensemble of 2)"]
    for k, name in ((1, "a"), (2, "b")):
        qs = []
        for seed in (0, 1):
            with np.load(tmp / f"r{k}_s{seed}" / "results" / "learned_val_quaternions.npz") as z:
                qs.append(z[name])
        trial = read_trial(tmp / "mat" / f"{name}.mat")
        want = rmse(ensemble(qs), trial.quat, trial.movement)["total"]
        assert math.isclose(ens["trials"][name], want, rel_tol=1e-12)
    row = got["rows"]["c"]
    # each seed's figure: the mean over both folds of what train stored for its held-out trial
    for seed, figures in enumerate(row["per_seed"]):
        stored = [json.loads((tmp / f"r{k}_s{seed}" / "results" / "learned_val.json").read_text())
                  for k in (1, 2)]  # fmt: skip
        for m in ("total", "heading", "inclination"):
            assert math.isclose(figures[m], np.mean([s["mean"][m] for s in stored]), rel_tol=1e-9)
    totals = [f["total"] for f in row["per_seed"]]
    assert math.isclose(row["mean"]["total"], np.mean(totals), rel_tol=1e-12)
    assert math.isclose(row["std"]["total"], np.std(totals, ddof=1), rel_tol=1e-9)
    assert row["folds"] == [row["trials"]["a"], row["trials"]["b"]]
    assert "lowest mean total (the selection rule): **c**" in (out / "table.md").read_text().lower()


def test_runs_out_of_fold_order_overlapping_folds_and_leaks_are_refused(folds):
    tmp, f1, f2 = folds
    out = str(tmp / "refused")
    swapped = f"c={tmp / 'r2_s0'},{tmp / 'r1_s0'}"
    with pytest.raises(SystemExit, match="in the order of --folds"):
        crossval.main(["--out", out, "--folds", f"{f1},{f2}", "--runs", swapped])
    with pytest.raises(SystemExit, match="overlap"):
        crossval.main(["--out", out, "--folds", f"{f1},{f1}", "--runs", swapped])
    leak = _fold(tmp, "leak", ["a", "b"], ["a"])
    with pytest.raises(SystemExit, match="trains on held-out"):
        crossval.main(["--out", out, "--folds", f"{leak},{f2}", "--runs", swapped])
    with pytest.raises(SystemExit, match="one run per fold"):
        crossval.main(["--out", out, "--folds", f"{f1},{f2}", "--runs", f"c={tmp / 'r1_s0'}"])
    with pytest.raises(SystemExit, match="no such run"):
        crossval.main(["--out", out, "--folds", f"{f1},{f2}",
                       "--runs", f"c={tmp / 'r1_s0'},{tmp / 'nowhere'}"])  # fmt: skip
    # the run records the trials it read: its fold is known wherever the split file went
    moved = tmp / "moved"
    shutil.copytree(tmp / "r2_s0", moved)
    assert yaml.safe_load((moved / "split.yaml").read_text())["splits"]["val"] == ["b"]
    (moved / "command.json").write_text(json.dumps({"split": str(tmp / "gone.yaml")}))
    crossval.check_run_fold(moved, ["b"], f2)
    with pytest.raises(ValueError, match="in the order of --folds"):
        crossval.check_run_fold(moved, ["a"], f1)
    # a run without split.yaml (made before it was recorded) is checked by its command.json
    hostile = tmp / "hostile"
    shutil.copytree(tmp / "r2_s0", hostile)
    (hostile / "split.yaml").unlink()
    crossval.check_run_fold(hostile, ["b"], f2)
    (hostile / "command.json").write_text(json.dumps({"split": "/dev/zero"}))
    with pytest.raises(SystemExit, match="/dev/zero is not a file"):
        crossval.main(["--out", out, "--folds", f"{f1},{f2}",
                       "--runs", f"c={tmp / 'r1_s0'},{hostile}"])  # fmt: skip
    (hostile / "command.json").write_text(" " * (2 << 20))
    with pytest.raises(SystemExit, match="over 1048576 bytes"):
        crossval.main(["--out", out, "--folds", f"{f1},{f2}",
                       "--runs", f"c={tmp / 'r1_s0'},{hostile}"])  # fmt: skip
    assert not (tmp / "refused").exists()  # nothing written by a refused call


def test_the_cross_fitted_calibration_reads_each_trial_through_the_run_that_did_not_train_on_it(
    folds,
):
    import argparse

    import torch

    from manifold_nets import load_observer
    from manifold_nets.covariance_training import Sequences, readout_sequences
    from manifold_nets_examples.broad.calibration import _cross_fitted, observer_readings, _windows
    from manifold_nets_examples.broad.data import read_trials
    from manifold_nets_examples.broad.learning import measured_start

    tmp, f1, f2 = folds
    runs = (tmp / "r1_s0", tmp / "r2_tilt")
    observer = load_observer(runs[0]).observer
    args = argparse.Namespace(folds=f"{f1},{f2}", cv_runs=[",".join(map(str, runs))], window=16,
                              data_dir=None, context=0)  # fmt: skip
    parts = _cross_fitted(args, observer)
    assert [(k, trial) for k, trial, _ in parts] == [(0, "a"), (1, "b")]
    got = Sequences.cat([seqs for _, _, seqs in parts])

    def through(run, name):
        obs, system, _ = load_observer(run)
        data = observer_readings(read_trials(tmp / "mat", [name]), system)
        return _windows(readout_sequences(obs, data, "readings", skip=1,
                                          start=measured_start(system)), 16)  # fmt: skip

    # by hand: fold 1's run on trial a, fold 2's on trial b, each cut into windows
    want = [through(runs[0], "a"), through(runs[1], "b")]
    assert torch.equal(got.errors, torch.cat([w.errors for w in want]))
    assert torch.equal(got.features, torch.cat([w.features for w in want]))
    assert got.errors.shape[1] == 16 and got.known.sum() == sum(w.known.sum() for w in want)
    # fold 2's errors are its own run's, not fold 1's run's on the same trial
    assert not torch.equal(through(runs[0], "b").errors, want[1].errors)
    twice = _cross_fitted(argparse.Namespace(**{**vars(args), "cv_runs": args.cv_runs * 2}),
                          observer)  # fmt: skip
    assert [k for k, _, _ in twice] == [0, 1, 0, 1]  # in --cv-runs' order, as fitted
    assert torch.equal(Sequences.cat([s for _, _, s in twice]).errors, torch.cat([got.errors] * 2))
    swapped = argparse.Namespace(**{**vars(args), "cv_runs": [f"{runs[1]},{runs[0]}"]})
    with pytest.raises(SystemExit, match="in the order of --folds"):
        _cross_fitted(swapped, observer)


def test_the_cross_conformal_scale_reads_each_folds_errors_under_a_readout_fitted_without_them(
    folds,
):
    import argparse

    import torch

    from manifold_nets import load_observer
    from manifold_nets.covariance_training import Sequences, mean_nll, step_nees
    from manifold_nets.calibration import conformal_scale
    from manifold_nets_examples.broad.calibration import (
        _cross_conformal, _cross_fitted, _fit, _held_out_shares,
    )

    tmp, f1, f2 = folds
    runs = (tmp / "r1_s0", tmp / "r2_tilt")
    observer = load_observer(runs[0]).observer
    args = argparse.Namespace(folds=f"{f1},{f2}", cv_runs=[",".join(map(str, runs))] * 2,
                              window=16, data_dir=None, epochs=2, seed=5, context=0)  # fmt: skip
    parts = _cross_fitted(args, observer)
    got, nll, per_trial = _cross_conformal(parts, observer, args)
    torch.manual_seed(123)  # the fits seed themselves: the global state does not matter
    want, total, count = [], 0.0, 0
    for k in (0, 1):  # by hand: fitted to the other fold's errors (both seeds'), read on fold k
        rest = Sequences.cat([s for j, _, s in parts if j != k])
        readout, _ = _fit(rest, rest, observer, "readings", args)
        held = Sequences.cat([s for j, _, s in parts if j == k])
        want.append(step_nees(readout, held)["x"])
        total, count = total + mean_nll(readout, held) * int(held.known.sum()), count + int(held.known.sum())
    assert set(got) == {"x"} and torch.equal(got["x"], torch.cat(want))
    assert nll == pytest.approx(total / count, rel=1e-12)  # the held-out NLL, step-weighted
    assert len(got["x"]) == int(Sequences.cat([s for _, _, s in parts]).known.sum())
    # each trial's own NEES: fold k's trial is k's held-out one, both seeds' in --cv-runs' order
    assert set(per_trial) == {"a", "b"}
    for k, trial in ((0, "a"), (1, "b")):
        torch.testing.assert_close(per_trial[trial]["x"], want[k], rtol=0, atol=0)
    # each trial's share inside the scaled 3-sigma ellipsoid; weighted by steps, the pooled one
    scale = conformal_scale(got["x"], 3)
    shares = _held_out_shares(per_trial, {"x": scale})
    for k, trial in ((0, "a"), (1, "b")):
        assert shares[trial]["x"] == {"in_3sigma": float((want[k] <= 9 * scale).double().mean()),
                                      "steps": len(want[k])}
    pooled = sum(r["x"]["in_3sigma"] * r["x"]["steps"] for r in shares.values()) / len(got["x"])
    assert pooled == pytest.approx(float((got["x"] <= 9 * scale).double().mean()), abs=1e-12)
    assert 0.9 < pooled < 1  # the conformal scale holds the Gaussian share of the pooled errors


def test_the_cross_fitted_calibration_refuses_a_hidden_state_source(tmp_path):
    from manifold_nets_examples.broad import calibration

    with pytest.raises(SystemExit, match="--fit cv takes --sources readings"):
        calibration.main(["--fit", "cv", "--sources", "readings", "hidden", "--out",
                          str(tmp_path / "c"), "--folds", "a.yaml", "--cv-runs", "r"])  # fmt: skip
    with pytest.raises(SystemExit, match="give two folds or more"):
        calibration.main(["--fit", "cv", "--sources", "readings", "--conformal", "1", "--out",
                          str(tmp_path / "c"), "--folds", "a.yaml", "--cv-runs", "r"])  # fmt: skip
    assert not (tmp_path / "c").exists()


def test_an_ensemble_folder_is_checked_member_by_member(folds):
    """An ensemble folder (members/<name>/, each a run folder) is of a fold when every member
    is; one member of another fold, or a hostile folder, is refused naming it."""
    tmp, f1, f2 = folds
    ens = tmp / "ens_f2"
    for name in ("s0", "s1"):
        shutil.copytree(tmp / "r2_s0", ens / "members" / name)
    crossval.check_run_fold(ens, ["b"], f2)
    with pytest.raises(ValueError, match="s0.*in the order of --folds"):
        crossval.check_run_fold(ens, ["a"], f1)
    shutil.copytree(tmp / "r1_s0", ens / "members" / "s2")  # a member of fold 1
    with pytest.raises(ValueError, match="s2.*not fold"):
        crossval.check_run_fold(ens, ["b"], f2)
    (ens / "config.yaml").write_text("name: x\n")
    with pytest.raises(ValueError, match="both a config.yaml and members/"):
        crossval.check_run_fold(ens, ["b"], f2)
