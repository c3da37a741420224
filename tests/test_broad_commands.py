"""The BROAD commands against careless and hostile input: a recording without a reference is
estimated; a file's header is checked before any data is read (and no variable expands beyond
what its header claims); destinations and arguments are checked before any work; readings
beyond float32, folders and FIFOs are named; non-finite estimates write nothing; results are
written atomically; and every command sets torch's threads by one rule."""

from __future__ import annotations

import ast
import errno
import io
import os
import shutil
import signal
import struct
import subprocess
import sys
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pytest
import scipy.io
import torch
import yaml

from manifold_nets.checkpoint import load_checkpoint, save_checkpoint
from manifold_nets.loading import ensemble_members
from manifold_nets.plugins import zoo_path
from manifold_nets.threads import use_threads
from manifold_nets_examples.broad import apply as apply_cmd
from manifold_nets_examples.broad import compare as compare_cmd
from manifold_nets_examples.broad import evaluate as evaluate_cmd
from manifold_nets_examples.broad import train as train_cmd
from manifold_nets_examples.broad.data import (
    MAX_SAMPLES,
    BroadFormatError,
    read_trial,
)
from manifold_nets_examples.broad.metric import rmse

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "tests" / "fixtures" / "broad" / "excerpt.mat"
IMU = ("imu_gyr", "imu_acc", "imu_mag", "sampling_rate")


def _member() -> Path:
    """One observer of the zoo's BROAD ensemble (a run folder: its first member)."""
    return ensemble_members(zoo_path("broad/attitude"))[0]


def _raw() -> dict:
    raw = scipy.io.loadmat(str(FIXTURE), squeeze_me=True)
    return {k: v for k, v in raw.items() if not k.startswith("__")}


def _save(path: Path, raw: dict) -> Path:
    scipy.io.savemat(str(path), raw)
    return path


def _no_work(monkeypatch):
    """Makes every step that does work fail the test if it is reached."""
    def work(*_, **__):
        raise AssertionError("the command started its work before refusing")

    for module, name in ((apply_cmd, "read_trial"), (apply_cmd, "load_observer"),
                         (train_cmd, "fit"), (train_cmd, "read_trials"),
                         (evaluate_cmd, "load_observer"), (compare_cmd, "read_trials")):
        monkeypatch.setattr(module, name, work)


# -- 1. a recording without a reference -------------------------------------------------------


def test_apply_estimates_a_recording_without_reference(tmp_path, capsys):
    own = _save(tmp_path / "own.mat", {k: v for k, v in _raw().items() if k in IMU})
    apply_cmd.main(["zoo:broad/attitude", str(own), "--out", str(tmp_path / "own.npy")])
    printed = capsys.readouterr().out
    assert "2000 quaternions" in printed and "nothing scored" in printed
    apply_cmd.main(["zoo:broad/attitude", str(FIXTURE), "--out", str(tmp_path / "full.npy")])
    # the same IMU readings give the same estimates: the reference only adds the score
    assert np.array_equal(np.load(tmp_path / "own.npy"), np.load(tmp_path / "full.npy"))


def test_apply_with_the_6d_entry_reads_no_magnetometer_and_scores_the_inclination(tmp_path, capsys):
    raw = _raw()
    apply_cmd.main(["zoo:broad/attitude_6d", str(FIXTURE), "--out", str(tmp_path / "q.npy")])
    printed = capsys.readouterr().out
    assert "inclination" in printed and "heading is free and not scored" in printed
    assert "total" not in printed
    scrambled = {**raw, "imu_mag": np.random.default_rng(0).normal(0, 50, raw["imu_mag"].shape)}
    apply_cmd.main(["zoo:broad/attitude_6d", str(_save(tmp_path / "m.mat", scrambled)),
                    "--out", str(tmp_path / "m.npy")])  # fmt: skip
    assert np.array_equal(np.load(tmp_path / "q.npy"), np.load(tmp_path / "m.npy"))
    no_mag = _save(tmp_path / "n.mat", {k: v for k, v in raw.items() if k != "imu_mag"})
    apply_cmd.main(["zoo:broad/attitude_6d", str(no_mag), "--out", str(tmp_path / "n.npy")])
    assert np.array_equal(np.load(tmp_path / "q.npy"), np.load(tmp_path / "n.npy"))
    broken = _save(tmp_path / "b.mat", {**raw, "imu_mag": np.full(raw["imu_mag"].shape, np.nan)})
    apply_cmd.main(["zoo:broad/attitude_6d", str(broken), "--out", str(tmp_path / "b.npy")])
    assert np.array_equal(np.load(tmp_path / "q.npy"), np.load(tmp_path / "b.npy"))  # never read
    with pytest.raises(SystemExit, match="imu_mag.*is missing.*zoo:broad/attitude_6d"):  # 9-D
        apply_cmd.main(["zoo:broad/attitude", str(no_mag), "--out", str(tmp_path / "n9.npy")])
    assert not (tmp_path / "n9.npy").exists()
    apply_cmd.main(["zoo:broad/attitude", str(FIXTURE), "--out", str(tmp_path / "q9.npy")])
    apply_cmd.main(["zoo:broad/attitude", str(tmp_path / "m.mat"), "--out", str(tmp_path / "m9.npy")])
    assert not np.allclose(np.load(tmp_path / "q9.npy"), np.load(tmp_path / "m9.npy"))  # 9-D reads it
    with pytest.raises(SystemExit, match="6-D observer, whose heading is free"):  # any readout
        apply_cmd.main(["zoo:broad/attitude_6d", str(FIXTURE), "--out", str(tmp_path / "c.npy"),
                        "--covariance", str(tmp_path / "c.npz"), "--readout",
                        str(zoo_path("broad/attitude") / "covariance.pt")])  # fmt: skip
    assert not (tmp_path / "c.npy").exists() and not (tmp_path / "c.npz").exists()
    got = rmse(np.load(tmp_path / "q.npy"), read_trial(FIXTURE).quat, read_trial(FIXTURE).movement)
    assert got["inclination"] < 3.0  # degrees (2.49 measured), 7 s from a tilt start on trial 01


def test_apply_joins_the_6d_inclination_with_a_9d_heading(tmp_path, capsys):
    from manifold_nets_examples.broad.metric import errors
    from manifold_nets_examples.broad.six_d import cascade

    q = {}
    for name, extra in (("six", []), ("nine", []), ("both", ["--heading-from", "zoo:broad/attitude"])):
        entry = "zoo:broad/attitude" if name == "nine" else "zoo:broad/attitude_6d"
        apply_cmd.main([entry, str(FIXTURE), "--out", str(tmp_path / f"{name}.npy"), *extra])
        q[name] = np.load(tmp_path / f"{name}.npy")
    assert "total" in capsys.readouterr().out.splitlines()[-1]  # the cascade is scored in full
    np.testing.assert_array_equal(q["both"], cascade(q["six"], q["nine"]))
    e = {k: errors(v, read_trial(FIXTURE).quat) for k, v in q.items()}
    np.testing.assert_allclose(e["both"]["inclination"], e["six"]["inclination"], atol=1e-7)
    for bad, match in (
        (["zoo:broad/attitude", "--heading-from", "zoo:broad/attitude"], "reads a magnetometer"),
        (["zoo:broad/attitude_6d", "--heading-from", "zoo:broad/attitude_6d"], "no heading"),
        (["zoo:broad/attitude_6d", "--heading-from", "zoo:broad/attitude", "--covariance",
          str(tmp_path / "p.npz")], "--covariance is one observer's"),
    ):
        with pytest.raises(SystemExit, match=match):
            apply_cmd.main([bad[0], str(FIXTURE), "--out", str(tmp_path / "x.npy"), *bad[1:]])
        assert not (tmp_path / "x.npy").exists() and not (tmp_path / "p.npz").exists()


def test_apply_writes_the_covariance_of_each_step_when_asked(tmp_path, capsys):
    """--covariance: the zoo entry's readout at every observer step, the sample each belongs to,
    the quaternions unchanged; what estimate_with_covariance gives in Python."""
    from manifold_nets_examples.broad.calibration import estimate_with_covariance

    own = _save(tmp_path / "own.mat", {k: v for k, v in _raw().items() if k in IMU})
    apply_cmd.main(["zoo:broad/attitude", str(own), "--out", str(tmp_path / "q.npy"),
                    "--covariance", str(tmp_path / "p.npz")])
    assert "250 covariances (every 8 samples)" in capsys.readouterr().out
    with np.load(tmp_path / "p.npz", allow_pickle=False) as f:
        cov, sample = f["covariance"], f["sample"]
    assert cov.shape == (250, 3, 3) and np.array_equal(sample, np.arange(250) * 8)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    _, want, _ = estimate_with_covariance([read_trial(own, reference=False)])
    np.testing.assert_array_equal(cov, want[0].numpy())
    apply_cmd.main(["zoo:broad/attitude", str(own), "--out", str(tmp_path / "plain.npy")])
    assert np.array_equal(np.load(tmp_path / "q.npy"), np.load(tmp_path / "plain.npy"))


def test_apply_refuses_a_covariance_it_cannot_write_or_read_before_any_work(tmp_path, monkeypatch):
    (tmp_path / "run").mkdir()
    _no_work(monkeypatch)
    with pytest.raises(SystemExit, match=r"--covariance .*p\.npy: .*end in \.npz"):
        apply_cmd.main(["zoo:broad/attitude", str(FIXTURE), "--out", str(tmp_path / "q.npy"),
                        "--covariance", str(tmp_path / "p.npy")])
    with pytest.raises(SystemExit, match="holds no covariance.pt; give --readout"):
        apply_cmd.main([str(tmp_path / "run"), str(FIXTURE), "--out", str(tmp_path / "q.npy"),
                        "--covariance", str(tmp_path / "p.npz")])
    assert not (tmp_path / "q.npy").exists() and not (tmp_path / "p.npz").exists()


def test_without_movement_every_sample_with_a_reference_is_scored(tmp_path, capsys):
    raw = _raw()
    del raw["movement"]
    path = _save(tmp_path / "nomove.mat", raw)
    res = apply_cmd.apply_observer("zoo:broad/attitude", path)
    trial = read_trial(FIXTURE)
    assert res["scored"] == int(trial.known.sum()) and not res["movement_in_file"]
    assert res["rmse"] == rmse(res["quaternions"], trial.quat, np.ones(len(trial), bool))
    apply_cmd.main(["zoo:broad/attitude", str(path), "--out", str(tmp_path / "q.csv")])
    assert "samples with a reference (the file has no movement)" in capsys.readouterr().out


def test_training_and_evaluation_still_need_the_reference(tmp_path):
    own = _save(tmp_path / "own.mat", {k: v for k, v in _raw().items() if k in IMU})
    with pytest.raises(BroadFormatError, match=r"own.mat: field 'opt_quat' is missing"):
        read_trial(own)


# -- 2. the header before the data -------------------------------------------------------------


def _elements(raw: dict) -> tuple[bytes, dict[str, bytes]]:
    """The 128-byte header and each variable's uncompressed element of ``savemat(raw)``."""
    buf = io.BytesIO()
    scipy.io.savemat(buf, raw, do_compression=False)
    data, pos, out = buf.getvalue(), 128, {}
    for name in raw:
        _, n = struct.unpack("<II", data[pos:pos + 8])
        out[name] = data[pos:pos + 8 + n]
        pos += 8 + n
    return data[:128], out


def _compressed(element: bytes) -> bytes:
    packed = zlib.compress(element)
    return struct.pack("<II", 15, len(packed)) + packed


def _claiming(element: bytes, rows: int) -> bytes:
    """``element`` (a (10, 3) double) with a header that claims ``rows`` rows."""
    dims = struct.pack("<II", 5, 8) + struct.pack("<ii", 10, 3)
    assert element.count(dims) == 1
    return element.replace(dims, struct.pack("<II", 5, 8) + struct.pack("<ii", rows, 3))


def _holding(element: bytes, rows: int) -> bytes:
    """``element`` (a (10, 3) double) holding ``rows`` x 3 zeros (compressed) behind its header."""
    data_tag = struct.pack("<II", 9, 240)
    head = bytearray(element[: element.index(data_tag)])
    n = rows * 3 * 8
    struct.pack_into("<I", head, 4, len(head) - 8 + 8 + n)
    packer = zlib.compressobj()
    packed = packer.compress(bytes(head) + struct.pack("<II", 9, n))
    block = bytes(1 << 20)
    for start in range(0, n, len(block)):
        packed += packer.compress(block[: min(len(block), n - start)])
    packed += packer.flush()
    return struct.pack("<II", 15, len(packed)) + packed


def _hostile(tmp_path, gyr: bytes, extra: bytes = b"") -> Path:
    """The fixture with ``gyr`` as the (raw, top-level) element of imu_gyr."""
    raw = _raw()
    raw["imu_gyr"] = np.zeros((10, 3))
    head, el = _elements(raw)
    path = tmp_path / "hostile.mat"
    path.write_bytes(head + b"".join(gyr if k == "imu_gyr" else _compressed(v)
                                     for k, v in el.items()) + extra)  # fmt: skip
    return path


def _peak(fn) -> int:
    tracemalloc.start()
    try:
        fn()
    except Exception:  # noqa: BLE001 - the caller checks the error separately
        pass
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak


def test_a_header_claiming_5e7_samples_is_refused_before_any_data(tmp_path):
    head, el = _elements({"imu_gyr": np.zeros((10, 3))})
    path = _hostile(tmp_path, _compressed(_claiming(el["imu_gyr"], 50_000_000)))
    assert path.stat().st_size < 2**20
    assert scipy.io.whosmat(str(path))[0] == ("imu_gyr", (50_000_000, 3), "double")
    with pytest.raises(BroadFormatError) as info:
        read_trial(path)
    assert str(info.value) == (
        f"{path}: field 'imu_gyr' claims shape (50000000, 3) (150000000 values), more than this "
        f"reader's limit of MAX_SAMPLES = {MAX_SAMPLES} samples x 3; split the recording into "
        f"files of at most {MAX_SAMPLES} samples."
    )
    assert _peak(lambda: read_trial(path)) < 2**20


def test_a_variable_holding_more_than_its_header_claims_is_never_expanded(tmp_path):
    _, el = _elements({"imu_gyr": np.zeros((10, 3))})
    path = _hostile(tmp_path, _holding(el["imu_gyr"], 1_000_000))  # 24 MB behind (10, 3)
    with pytest.raises(BroadFormatError, match=r"hostile.mat: variable 'imu_gyr' holds more "
                                               r"data than its header's shape and class allow"):
        read_trial(path)
    assert _peak(lambda: read_trial(path)) < 2**20
    # the control: scipy on its own expands all of it before it finds the mismatch
    assert _peak(lambda: scipy.io.loadmat(str(path))) > 24_000_000


def test_an_uncompressed_variable_larger_than_its_header_is_refused(tmp_path):
    raw = _raw()
    raw["imu_gyr"] = np.zeros((10, 3))
    head, el = _elements(raw)
    big = _elements({"imu_gyr": np.zeros((1000, 3))})[1]["imu_gyr"]
    gyr = big.replace(struct.pack("<ii", 1000, 3), struct.pack("<ii", 10, 3), 1)
    path = tmp_path / "bad.mat"
    path.write_bytes(head + b"".join(gyr if k == "imu_gyr" else v for k, v in el.items()))
    with pytest.raises(BroadFormatError, match=r"variable 'imu_gyr' takes 24\d\d\d bytes, more "
                                               r"than its header's shape and class allow"):
        read_trial(path)


def test_variables_the_reader_does_not_need_are_skipped_unread(tmp_path):
    raw = _raw()
    raw["junk"] = np.zeros((10, 3))
    head, el = _elements(raw)
    path = tmp_path / "junk.mat"
    path.write_bytes(head + b"".join(_holding(v, 1_000_000) if k == "junk" else _compressed(v)
                                     for k, v in el.items()))  # fmt: skip
    assert len(read_trial(path)) == 2000
    assert _peak(lambda: read_trial(path)) < 8 * 2**20  # the trial itself: 2000 x 17 doubles


@pytest.mark.parametrize("field, value, needle", [
    ("sampling_rate", np.full(5, 285.714), "'sampling_rate' has shape (1, 5), not one number"),
    ("imu_acc", np.array(["a string"]), "'imu_acc' is not a numeric array (got a Matlab char"),
])
def test_the_header_refuses_wrong_kinds_before_reading(tmp_path, field, value, needle):
    raw = _raw()
    raw[field] = value
    with pytest.raises(BroadFormatError) as info:
        read_trial(_save(tmp_path / "bad.mat", raw))
    assert needle in str(info.value)


def test_a_v4_file_is_refused_naming_the_fix(tmp_path):
    path = tmp_path / "v4.mat"
    scipy.io.savemat(str(path), {k: np.atleast_2d(v) for k, v in _raw().items() if k in IMU},
                     format="4")
    with pytest.raises(BroadFormatError, match=r"v4.mat: not a readable Matlab v5 file .*save -v7"):
        read_trial(path)


# -- 3. destinations before the work -----------------------------------------------------------


def _unwritable() -> Path:
    """A folder no one can create a file in, root included (a read-only /sys)."""
    try:
        with __import__("tempfile").TemporaryFile(dir="/sys"):
            pass
    except OSError:
        return Path("/sys")
    pytest.skip("/sys takes files here: no unwritable folder to test with")


@pytest.mark.parametrize("bad, needle", [
    ("folder", "is a folder; give the path of a file in it"),
    ("file.txt/q.npy", "file.txt is a file, so nothing can be created under it"),
    ("file.txt/sub/q.npy", "file.txt is a file, so nothing can be created under it"),
    ("q.txt", "the name must end in .npy or .csv"),
    ("UNWRITABLE", "cannot write in /sys (PermissionError"),
])
def test_apply_checks_its_destination_before_any_work(tmp_path, monkeypatch, bad, needle):
    (tmp_path / "folder").mkdir()
    (tmp_path / "file.txt").write_text("x")
    out = _unwritable() / "q.npy" if bad == "UNWRITABLE" else tmp_path / bad
    _no_work(monkeypatch)
    with pytest.raises(SystemExit) as info:
        apply_cmd.main(["zoo:broad/attitude", str(FIXTURE), "--out", str(out)])
    assert str(info.value).startswith(f"error: --out {out}: ") and needle in str(info.value)
    assert (tmp_path / "file.txt").read_text() == "x"


# -- 4. readings beyond float32, folders and FIFOs ---------------------------------------------


def test_a_finite_reading_beyond_float32_is_named(tmp_path):
    raw = _raw()
    raw["imu_acc"][7, 2] = 1e300
    path = _save(tmp_path / "big.mat", raw)
    with pytest.raises(BroadFormatError) as info:
        read_trial(path)
    msg = str(info.value)
    assert msg.startswith(f"{path}: field 'imu_acc' (m/s^2) holds readings beyond +-1e+06 in 1 "
                          "sample(s), first 7")
    assert "float32" in msg and "fix or cut those samples" in msg


@pytest.mark.parametrize("kind", ["folder", "fifo"])
def test_a_folder_or_fifo_given_as_the_trial_is_named(tmp_path, kind, monkeypatch):
    path = tmp_path / "trial.mat"
    path.mkdir() if kind == "folder" else os.mkfifo(path)
    signal.signal(signal.SIGALRM, lambda *_: pytest.fail("the reader blocked on the FIFO"))
    signal.alarm(20)
    try:
        with pytest.raises(SystemExit) as info:
            apply_cmd.main(["zoo:broad/attitude", str(path), "--out", str(tmp_path / "q.npy")])
    finally:
        signal.alarm(0)
    msg = str(info.value)
    assert msg == (f"error: {path}: is a folder, not a .mat file; give the path of a .mat file."
                   if kind == "folder" else f"error: {path}: is not a regular file (a FIFO, "
                   "socket or device); give the path of a .mat file on disk.")  # fmt: skip
    assert "--data-dir" not in msg and "no such file" not in msg


def test_a_missing_trial_names_no_option_the_command_lacks(tmp_path):
    with pytest.raises(SystemExit, match=r"^error: .*nope.mat: no such file; check the path.$"):
        apply_cmd.main(["zoo:broad/attitude", str(tmp_path / "nope.mat"), "--out",
                        str(tmp_path / "q.npy")])


# -- 5. non-finite estimates -------------------------------------------------------------------


@pytest.fixture
def nan_run(tmp_path) -> Path:
    run = tmp_path / "nan_run"
    shutil.copytree(_member(), run)
    ckpt = load_checkpoint(run / "checkpoints" / "best.pt")
    name = next(k for k, v in ckpt["model"].items() if v.is_floating_point())
    ckpt["model"][name] = torch.full_like(ckpt["model"][name], float("nan"))
    save_checkpoint(run / "checkpoints" / "best.pt", {k: v for k, v in ckpt.items()
                                                     if k != "format"})  # fmt: skip
    return run


def test_nan_weights_are_an_error_and_the_old_file_stays(tmp_path, nan_run):
    out = tmp_path / "q.npy"
    out.write_bytes(b"the user's earlier result")
    with pytest.raises(SystemExit) as info:
        apply_cmd.main([str(nan_run), str(FIXTURE), "--out", str(out)])
    assert str(info.value).startswith(f"error: {nan_run} gave non-finite estimates on excerpt")
    assert "nothing was written" in str(info.value)
    assert out.read_bytes() == b"the user's earlier result"


# -- 6. atomic results, every argument before the work -----------------------------------------


def _split(tmp_path, movement=True) -> tuple[Path, Path]:
    data = tmp_path / "data"
    data.mkdir()
    raw = _raw()
    for name in ("tr", "va"):
        _save(data / f"{name}.mat", raw)
    if not movement:
        raw["movement"] = np.zeros_like(raw["movement"])
    _save(data / "te.mat", raw)
    split = tmp_path / "trials.yaml"
    split.write_text(yaml.safe_dump({"data_dir": str(data),
                                     "splits": {"train": ["tr"], "val": ["va"], "test": ["te"]}}))
    return data, split


def _fail_fsync_of(name: str, monkeypatch) -> None:
    """A full disk for the atomic writes of files called ``name``: fsync fails with ENOSPC."""
    import manifold_nets.atomic as atomic

    real = os.fsync

    def fsync(fd):
        if f".{name}." in os.readlink(f"/proc/self/fd/{fd}"):
            raise OSError(errno.ENOSPC, "No space left on device")
        real(fd)

    monkeypatch.setattr(atomic.os, "fsync", fsync)


def test_evaluate_keeps_the_good_results_when_the_disk_is_full(tmp_path, monkeypatch):
    data, split = _split(tmp_path)
    run = tmp_path / "run"
    shutil.copytree(_member(), run)
    evaluate_cmd.evaluate_run(run, data, split, ["test"])
    npz = run / "results" / "learned_test_quaternions.npz"
    good = npz.read_bytes()
    assert np.load(npz)["te"].shape == (2000, 4)
    _fail_fsync_of(npz.name, monkeypatch)
    with pytest.raises(SystemExit, match="error: .*No space left on device"):
        evaluate_cmd.main([str(run), "--data-dir", str(data), "--split", str(split),
                           "--splits", "test"])
    assert npz.read_bytes() == good
    assert sorted(p.name for p in npz.parent.iterdir()) == [
        "learned_test.json", "learned_test_quaternions.npz"]


def test_train_copies_best_pt_atomically(tmp_path, monkeypatch):
    _, split = _split(tmp_path)
    out = tmp_path / "run"
    _fail_fsync_of("best.pt", monkeypatch)
    with pytest.raises(SystemExit, match="error: .*No space left on device"):
        train_cmd.main(["--split", str(split), "--out", str(out), "--init-from",
                        str(_member()), "--pretrain-epochs", "0", "--finetune-epochs", "0"])
    assert not (out / "checkpoints" / "best.pt").exists()
    assert list((out / "checkpoints").iterdir()) == []


@pytest.mark.parametrize("args, needle", [
    (["--eval-splits", ""], "--eval-splits '': names no split; the split file has"),
    (["--eval-splits", "val,nope"], "--eval-splits val,nope: unknown split(s) ['nope']"),
    (["--window", "0"], "--window must be an integer >= 1, got 0."),
    (["--stride", "0"], "--stride must be an integer >= 1, got 0."),
    (["--mounting", "7"], "--mounting must be an angle in [0, pi] radians"),
    (["--tilt-tau", "-1"], "--tilt-tau must be a finite number >= 0 (seconds; 0: no tilt"),
    (["--tilt-tau", "0.01"], "tau = 0.01 s is shorter than the step dt = 0.028 s"),
    (["--acc-lowpass-order", "2"], "--acc-lowpass-order 2 is the order of the accelerometer's "
     "low-pass, and --acc-lowpass is 0"),
    (["--heading-only", "1"], "--heading-only 1 leaves the tilt to --tilt-tau's correction"),
    (["--heading-tau", "inf"], "--heading-tau must be a finite number >= 0 (seconds; 0: no"),
    (["--heading-gate", "1"], "--heading-gate 1 gates the heading correction, and --heading-tau"),
    (["--heading-tau", "9", "--magnetometer", "0"], "--heading-tau corrects the heading from the "
     "magnetometer, and --magnetometer is 0"),
    (["--lr", "nan"], "--lr must be a finite number > 0, got nan."),
    (["--loss-weights", "1,1,1"], "--loss-weights '1,1,1': loss_weights has 3 numbers; the "
     "group's embedding has 9"),
    (["--loss-weights", "0,0,0,0,0,0,1,1,x"], "--loss-weights '0,0,0,0,0,0,1,1,x': could not "
     "convert string to float"),
    (["--loss-weights", "0,0,0,0,0,0,0,0,0"], "must be finite numbers >= 0, not all 0"),
    (["--pretrain-sequences", "1"], "--pretrain-sequences must be 0 (no pre-training) or >= 2"),
    (["--window", "1000", "--decimation", "8"], "--window 1000 x --decimation 8 = 8000 samples: "
     "window=8000 is longer than every trial"),
    (["--init-from", "nowhere"], "--init-from nowhere: no checkpoint at nowhere"),
    (["MOVEMENT"], "--eval-splits test: trial(s) ['te'] have no sample with movement == 1"),
])
def test_train_checks_every_argument_before_any_work(tmp_path, monkeypatch, args, needle):
    _, split = _split(tmp_path, movement=args != ["MOVEMENT"])
    args = [] if args == ["MOVEMENT"] else args
    monkeypatch.setattr(train_cmd, "fit", lambda *a, **k: pytest.fail("training started"))
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as info:
        train_cmd.main(["--split", str(split), "--out", str(out), "--pretrain-sequences", "8",
                        "--pretrain-length", "16", "--window", "32", *args])
    assert str(info.value).startswith("error: ") and needle in str(info.value), info.value
    assert not out.exists()


@pytest.mark.parametrize("command, args, needle", [
    (evaluate_cmd, ["RUN", "--splits", "nope"], "--splits nope: unknown split(s) ['nope']"),
    (evaluate_cmd, ["RUN", "--splits", ""], "--splits '': names no split"),
    (compare_cmd, ["--out", "OUT", "--split", "nope"], "--split 'nope': unknown or no split"),
    (compare_cmd, ["--out", "OUT", "--methods", "vqf,kalman"], "--methods 'vqf,kalman': choose"),
    (compare_cmd, ["--out", "FILE"], "--out FILE: is a file, not a folder"),
    (compare_cmd, ["--out", "OUT", "--tuned", "FILE"], "--tuned FILE: cannot be read as JSON"),
])
def test_evaluate_and_compare_check_their_arguments_before_any_work(
    tmp_path, monkeypatch, command, args, needle
):
    _, split = _split(tmp_path)
    (tmp_path / "file").write_text("not json")
    places = {"RUN": str(tmp_path / "run"), "OUT": str(tmp_path / "out"),
              "FILE": str(tmp_path / "file")}  # fmt: skip
    _no_work(monkeypatch)
    flag = "--split" if command is evaluate_cmd else "--config"
    with pytest.raises(SystemExit) as info:
        command.main([places.get(a, a) for a in args] + [flag, str(split)])
    needle = needle.replace("FILE", places["FILE"])
    assert str(info.value).startswith("error: ") and needle in str(info.value), info.value
    assert not (tmp_path / "out").exists() and not (tmp_path / "run").exists()


# -- threads: one rule for every command -------------------------------------------------------


@pytest.fixture
def restore_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_use_threads_follows_its_rule(monkeypatch, restore_threads):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    torch.set_num_threads(2)
    assert use_threads() == 1 and torch.get_num_threads() == 1
    assert use_threads(3) == 3 and torch.get_num_threads() == 3
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    torch.set_num_threads(2)  # what torch read from OMP_NUM_THREADS at import
    assert use_threads() == 2 and torch.get_num_threads() == 2
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ValueError, match="threads must be an integer >= 1 or None"):
            use_threads(bad)


def test_broad_apply_runs_on_one_thread_unless_asked(tmp_path, monkeypatch, restore_threads):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    torch.set_num_threads(2)
    apply_cmd.main(["zoo:broad/attitude", str(FIXTURE), "--out", str(tmp_path / "q.npy")])
    assert torch.get_num_threads() == 1
    apply_cmd.main(["zoo:broad/attitude", str(FIXTURE), "--out", str(tmp_path / "q.npy"),
                    "--threads", "2"])
    assert torch.get_num_threads() == 2


def _calls(path: Path, name: str) -> bool:
    return any(isinstance(n, ast.Call) and name in ast.unparse(n.func)
               for n in ast.walk(ast.parse(path.read_text())))


def test_every_command_sets_its_threads_through_use_threads():
    commands = [ROOT / "manifold_nets" / "cli" / f for f in ("apply.py", "tasks.py", "generate.py")]
    commands += [p for p in (ROOT / "examples").rglob("*.py")
                 if "def main(" in p.read_text() and "import main" not in p.read_text()]
    assert len(commands) >= 7, commands
    assert [p.name for p in commands if not _calls(p, "use_threads")] == []
    others = [p.relative_to(ROOT).as_posix() for folder in ("manifold_nets", "examples")
              for p in (ROOT / folder).rglob("*.py") if _calls(p, "set_num_threads")]
    # the library's rule, and the EKF's block that runs on one thread and restores the count
    assert set(others) <= {"examples/broad/filters.py", "manifold_nets/threads.py"}, others


def _damaged_variants(rng) -> list[bytes]:
    """The fixture cut short, and (compressed and not) with 4 bytes overwritten: anywhere, and
    in the first 64 bytes of a variable (its tag, flags, dimensions, name, data tag)."""
    good = FIXTURE.read_bytes()
    plain, pos, starts = _plain_fixture(), 128, []
    while pos < len(plain):
        starts.append(pos)
        pos += 8 + struct.unpack("<II", plain[pos:pos + 8])[1]
    out = [good[:n] for n in (0, 100, 128, 131, 136, 200, 1000, len(good) // 2, len(good) - 1)]
    for source, places in ((good, rng.integers(0, len(good), 40)),
                           (plain, rng.choice(starts, 300) + rng.integers(0, 64, 300))):
        for at in places:
            bad = bytearray(source)
            bad[at : at + 4] = rng.integers(0, 256, 4, dtype=np.uint8).tobytes()
            out.append(bytes(bad))
    return out


def _plain_fixture() -> bytes:
    buf = io.BytesIO()
    scipy.io.savemat(buf, _raw(), do_compression=False)
    return buf.getvalue()


def test_damaged_files_are_refused_as_format_errors_never_anything_else(tmp_path):
    """Each damaged file either reads or is a BroadFormatError naming it: no struct.error,
    zlib.error, and no crash of scipy's parser (which an unknown data type segfaults)."""
    refused = 0
    for i, data in enumerate(_damaged_variants(np.random.default_rng(0))):
        path = tmp_path / f"damaged{i}.mat"
        path.write_bytes(data)
        try:
            read_trial(path)
        except BroadFormatError as err:
            assert str(err).startswith(f"{path}: "), err
            refused += 1
    assert refused >= 250  # of 349: most damage is found (some bytes are padding)


def test_an_unknown_data_type_is_refused_not_a_crash(tmp_path):
    """scipy.io.loadmat segfaults on this file (sampling_rate's data tagged as type 203)."""
    plain = bytearray(_plain_fixture())
    tag = struct.pack("<II", 9, 8) + struct.pack("<d", _raw()["sampling_rate"])
    assert plain.count(tag) == 1
    plain[plain.index(tag)] = 203
    path = tmp_path / "crash.mat"
    path.write_bytes(bytes(plain))
    code = ("from manifold_nets_examples.broad.data import read_trial, BroadFormatError\n"
            f"try:\n    read_trial({str(path)!r})\nexcept BroadFormatError as err:\n"
            "    print(err)")  # fmt: skip
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == (f"{path}: variable 'sampling_rate' is damaged (its real part "
                                   "has no numeric data); re-export the file.")
