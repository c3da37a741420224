"""``mn-apply``: a trained observer over a dataset file. Its destination is checked before any
work (:func:`manifold_nets.destination.check_destination`), non-finite estimates are an error
that writes nothing, and it runs on one torch thread unless asked."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

from manifold_nets.checkpoint import load_checkpoint, save_checkpoint
from manifold_nets.cli import apply
from manifold_nets.data import save_dataset
from manifold_nets.destination import check_destination
from manifold_nets.plugins import zoo_path


@pytest.fixture
def data_file(tmp_path):
    from manifold_nets_examples.rigid_body import RigidBody

    ds = RigidBody().simulate(2, 20, 0.1, torch.Generator().manual_seed(0))
    save_dataset(ds, tmp_path / "data.npz")
    return tmp_path / "data.npz"


def test_the_estimates_land_in_a_npz_file(tmp_path, data_file):
    out = apply.run(["zoo:rigid_body/paper", str(data_file), "--out", str(tmp_path / "e.npz"),
                     "--no-progress"])
    est = np.load(out)["estimates"]
    assert est.shape == (2, 21, 18) and np.isfinite(est).all()


def _unwritable() -> Path:
    """A folder no one can create a file in, root included (a read-only /sys)."""
    try:
        with tempfile.TemporaryFile(dir="/sys"):
            pass
    except OSError:
        return Path("/sys")
    pytest.skip("/sys takes files here: no unwritable folder to test with")


@pytest.mark.parametrize("bad, needle", [
    ("e.csv", "the name must end in .npz"), ("folder", "is a folder"),
    ("file.txt/e.npz", "file.txt is a file, so nothing can be created under it"),
    ("UNWRITABLE", "cannot write in /sys (PermissionError"),
])
def test_a_bad_destination_is_refused_before_any_work(
    tmp_path, data_file, bad, needle, capsys, monkeypatch
):
    (tmp_path / "folder").mkdir()
    (tmp_path / "file.txt").write_text("x")
    out = _unwritable() / "e.npz" if bad == "UNWRITABLE" else tmp_path / bad
    monkeypatch.setattr(apply, "load_observer", lambda *_: pytest.fail("work started"))
    with pytest.raises(SystemExit):
        apply.run(["zoo:rigid_body/paper", str(data_file), "--out", str(out)])
    err = capsys.readouterr().err
    assert f"--out {out}: " in err and needle in err, err


def test_the_destination_check_creates_nothing(tmp_path):
    out = check_destination(tmp_path / "a" / "b" / "e.npz", suffixes=(".npz",))
    assert out == tmp_path / "a" / "b" / "e.npz" and list(tmp_path.iterdir()) == []
    assert check_destination(tmp_path / "run", folder=True) == tmp_path / "run"
    (tmp_path / "f").write_text("x")
    with pytest.raises(ValueError, match=r"^--out .*f: is a file, not a folder"):
        check_destination(tmp_path / "f", folder=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]


def test_nan_weights_are_an_error_and_nothing_is_written(tmp_path, data_file):
    folder = zoo_path("rigid_body/paper")
    ckpt = load_checkpoint(folder / "checkpoints" / "best.pt")
    ckpt["model"]["core.head.bias"][0] = float("nan")
    save_checkpoint(tmp_path / "nan.pt", {k: v for k, v in ckpt.items() if k != "format"})
    out = tmp_path / "e.npz"
    with pytest.raises(ValueError, match="non-finite estimates.*nothing was written"):
        apply.run([str(tmp_path / "nan.pt"), str(data_file), "--out", str(out), "--no-progress"])
    assert not out.exists()
    # the console script says so in one line, exit status 1, no traceback
    with pytest.raises(SystemExit) as info:
        apply.main([str(tmp_path / "nan.pt"), str(data_file), "--out", str(out), "--no-progress"])
    assert str(info.value).startswith(f"error: {tmp_path / 'nan.pt'} gave non-finite estimates")
    assert not out.exists()


def test_mn_apply_runs_on_one_thread_unless_asked(tmp_path, data_file, monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        apply.run(["zoo:rigid_body/paper", str(data_file), "--out", str(tmp_path / "e.npz"),
                   "--no-progress"])
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize("bad", ["int64", "complex", "sparse", "meta"])
def test_a_weight_of_another_kind_is_refused_naming_the_file_and_tensor(tmp_path, bad):
    from manifold_nets import load_observer
    from manifold_nets.checkpoint import CheckpointError

    ckpt = load_checkpoint(zoo_path("rigid_body/paper") / "checkpoints" / "best.pt")
    w = ckpt["model"]["core.head.bias"]
    ckpt["model"]["core.head.bias"] = {
        "int64": lambda: w.to(torch.int64), "complex": lambda: w.to(torch.complex64),
        "sparse": lambda: w.to_sparse(), "meta": lambda: w.to("meta"),
    }[bad]()
    path = tmp_path / "bad.pt"
    torch.save(ckpt, path)
    with pytest.raises(CheckpointError, match=r"bad.pt.*core.head.bias"):
        load_observer(path)


def test_a_start_off_the_group_or_not_finite_is_refused():
    from manifold_nets import load_observer

    observer, system, _ = load_observer("zoo:rigid_body/paper")
    y = torch.zeros(2, 5, 18, dtype=torch.float64)
    state = observer.init_state(2)
    off = state._replace(estimate=state.estimate * 2)
    with pytest.raises(ValueError, match="off the group"):
        observer(y, state=off)
    nan = state._replace(estimate=state.estimate.clone().fill_(float("nan")))
    with pytest.raises(ValueError, match="NaN or Inf"):
        observer(y, state=nan)


@pytest.mark.parametrize("key, value, match", [
    ("hidden_size", 20000, "outside 1 .. 16384"), ("num_layers", 20000, "outside 1 .. 64"),
    ("hidden_size", "one more", "the checkpoint's core has"),
])
def test_a_config_asking_for_a_huge_or_other_model_is_refused_before_building(
    tmp_path, key, value, match
):
    import shutil

    import yaml

    from manifold_nets import load_observer
    from manifold_nets.loading import ArtefactError

    folder = tmp_path / "run"
    shutil.copytree(zoo_path("rigid_body/paper"), folder)
    cfg = yaml.safe_load((folder / "config.yaml").read_text())
    cfg["model"][key] = cfg["model"][key] + 1 if value == "one more" else value
    (folder / "config.yaml").write_text(yaml.safe_dump(cfg))
    with pytest.raises(ArtefactError, match=match):
        load_observer(folder)


def test_an_observer_trained_behind_a_prefilter_reads_raw_readings_through_it(tmp_path):
    # zoo:broad/attitude reads the gyroscope less its bias at rest and a low-passed
    # accelerometer: mn-apply runs its system's filter on the file's readings, or skips it when
    # --preprocessed says the file went through it (tests/test_broad_prefilter_piece.py has the
    # equality of the two paths)
    from manifold_nets_examples.broad.simulator import BroadSimulator

    assert BroadSimulator().preprocessing is None  # the raw 9-D readings
    ds = BroadSimulator(rest_bias=True, acc_lowpass=1.0).simulate(
        2, 16, 0.0, torch.Generator().manual_seed(0)
    )
    save_dataset(ds, tmp_path / "imu.npz")
    args = ["zoo:broad/attitude", str(tmp_path / "imu.npz"), "--no-progress"]
    raw = np.load(apply.run([*args, "--out", str(tmp_path / "raw.npz")]))
    assert "readings_filter" in str(raw["meta"])
    est = np.load(apply.run([*args, "--out", str(tmp_path / "q.npz"), "--preprocessed"]))
    assert est["estimates"].shape == raw["estimates"].shape == (2, 17, 3, 3)
    assert np.isfinite(raw["estimates"]).all()
    assert not np.allclose(est["estimates"], raw["estimates"])  # the filter did something


def test_a_system_that_names_a_preprocessing_without_a_filter_is_refused(tmp_path, monkeypatch):
    from manifold_nets_examples.broad.simulator import BroadSimulator

    monkeypatch.setattr(BroadSimulator, "readings_filter", lambda self: None)
    ds = BroadSimulator().simulate(1, 8, 0.0, torch.Generator().manual_seed(0))
    save_dataset(ds, tmp_path / "imu.npz")
    args = ["zoo:broad/attitude", str(tmp_path / "imu.npz"), "--out", str(tmp_path / "q.npz"),
            "--no-progress"]
    with pytest.raises(ValueError, match="gyroscope less its bias estimated at rest.*"
                       "no readings_filter.*--preprocessed"):
        apply.run(args)
    assert not (tmp_path / "q.npz").exists()
    assert np.load(apply.run([*args, "--preprocessed"]))["estimates"].shape == (1, 9, 3, 3)
