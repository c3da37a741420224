"""The BROAD reader: the fixture excerpt reads, hostile files fail with messages naming the fix,
and ``trials_to_dataset`` aligns states, measurements, inputs and the mask as documented."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.io
import torch

from manifold_nets_examples.broad.data import (
    G0,
    M0,
    BroadFormatError,
    quat_to_matrix,
    read_trial,
    read_trials,
    trials_to_dataset,
)

FIXTURE = Path(__file__).parent / "fixtures" / "broad" / "excerpt.mat"


def _raw() -> dict:
    raw = scipy.io.loadmat(str(FIXTURE), squeeze_me=True)
    return {k: v for k, v in raw.items() if not k.startswith("__")}


def _write(tmp_path, raw, name="bad.mat") -> Path:
    path = tmp_path / name
    scipy.io.savemat(str(path), raw)
    return path


def test_fixture_reads_with_its_gap_and_movement():
    t = read_trial(FIXTURE)
    assert t.name == "excerpt" and len(t) == 2000
    assert t.rate == pytest.approx(285.714, abs=1e-3)
    for a in (t.gyr, t.acc, t.mag):
        assert a.shape == (2000, 3) and a.dtype == np.float64
    assert t.quat.shape == (2000, 4) and t.movement.dtype == bool
    assert 0 < (~t.known).sum() < 100 and np.isnan(t.quat[~t.known]).all()
    assert np.allclose(np.linalg.norm(t.quat[t.known], axis=1), 1.0, atol=1e-12)
    assert t.movement.any()


def _expect(tmp_path, raw, *needles):
    with pytest.raises(BroadFormatError) as info:
        read_trial(_write(tmp_path, raw))
    msg = str(info.value)
    assert "bad.mat" in msg
    for needle in needles:
        assert needle in msg, msg
    return msg


def test_missing_key(tmp_path):
    raw = _raw()
    del raw["imu_acc"]
    _expect(tmp_path, raw, "'imu_acc' is missing", "original BROAD trial file")


def test_missing_magnetometer_names_the_6d_observer_which_needs_none(tmp_path):
    raw = _raw()
    del raw["imu_mag"]
    _expect(tmp_path, raw, "'imu_mag' is missing", "zoo:broad/attitude_6d")
    scipy.io.savemat(str(tmp_path / "six.mat"), raw)
    trial = read_trial(tmp_path / "six.mat", magnetometer=False)
    assert np.array_equal(trial.mag, np.zeros((len(trial), 3)))
    assert np.array_equal(trial.acc, read_trial(FIXTURE).acc)


def test_wrong_shape(tmp_path):
    raw = _raw()
    raw["imu_acc"] = raw["imu_acc"][:, :2]
    _expect(tmp_path, raw, "'imu_acc' has shape (2000, 2), expected (T, 3)")


def test_inconsistent_length(tmp_path):
    raw = _raw()
    raw["movement"] = raw["movement"][:-5]
    _expect(tmp_path, raw, "'movement' has 1995 samples but imu_gyr has 2000")


def test_nan_gyro(tmp_path):
    raw = _raw()
    raw["imu_gyr"][17, 1] = np.nan
    _expect(tmp_path, raw, "'imu_gyr' (rad/s) holds NaN/Inf in 1 sample(s), first 17", "finite")


def test_object_array_is_refused(tmp_path):
    raw = _raw()
    cell = np.empty(2, dtype=object)
    cell[0], cell[1] = "print('hi')", np.zeros(3)
    raw["imu_gyr"] = cell
    _expect(tmp_path, raw, "'imu_gyr' is not a numeric array", "object, struct, cell")


def test_string_rate_is_refused(tmp_path):
    raw = _raw()
    raw["sampling_rate"] = "fast"
    _expect(tmp_path, raw, "'sampling_rate' is not a numeric array")


def test_bad_rate(tmp_path):
    raw = _raw()
    raw["sampling_rate"] = -1.0
    _expect(tmp_path, raw, "'sampling_rate' is -1.0, not one positive finite number")


def test_non_unit_quaternion(tmp_path):
    raw = _raw()
    raw["opt_quat"][5] *= 1.01
    _expect(tmp_path, raw, "'opt_quat' has 1 row(s) that are not unit quaternions", "sample 5")


def test_slightly_off_quaternion_is_normalised(tmp_path):
    raw = _raw()
    raw["opt_quat"][5] *= 1.0005
    t = read_trial(_write(tmp_path, raw))
    assert np.linalg.norm(t.quat[5]) == pytest.approx(1.0, abs=1e-12)


def test_movement_not_binary(tmp_path):
    raw = _raw()
    raw["movement"] = raw["movement"].astype(float)
    raw["movement"][3] = 2.0
    _expect(tmp_path, raw, "'movement' holds values other than 0 and 1")


def test_not_a_mat_file(tmp_path):
    path = tmp_path / "bad.mat"
    path.write_bytes(b"import os; os.system('echo pwned')")
    with pytest.raises(BroadFormatError, match="not a readable Matlab v5 file"):
        read_trial(path)


def test_read_trials_names_missing_files(tmp_path):
    _write(tmp_path, _raw(), "a.mat")
    assert [t.name for t in read_trials(tmp_path, ["a.mat"])] == ["a"]
    with pytest.raises(BroadFormatError, match=r"missing trial file\(s\) \['b.mat'\]"):
        read_trials(tmp_path, ["a", "b"])


def test_whole_trial_alignment():
    t = read_trial(FIXTURE)
    d = trials_to_dataset([t])
    assert d.states.shape == (1, 2000, 3, 3)
    assert d.measurements.shape == (1, 1999, 6) and d.inputs.shape == (1, 1999, 3)
    assert d.meta == {"system": "broad", "trials": ["excerpt"], "starts": [0], "rate": t.rate}
    k = 100
    assert torch.allclose(d.measurements[0, k, :3], torch.from_numpy(t.acc[k + 1] / G0))
    assert torch.allclose(d.measurements[0, k, 3:], torch.from_numpy(t.mag[k + 1] / M0))
    assert torch.equal(d.inputs[0, k], torch.from_numpy(t.gyr[k + 1]))
    mask = d.mask[0].numpy()
    assert np.array_equal(mask, t.known)
    known = np.flatnonzero(t.known)[3]
    assert np.allclose(d.states[0, known].numpy(), quat_to_matrix(t.quat[known]))
    missing = np.flatnonzero(~t.known)[0]
    assert torch.equal(d.states[0, missing], torch.eye(3, dtype=torch.float64))


def test_windows_and_strides():
    t = read_trial(FIXTURE)
    d = trials_to_dataset([t, t], window=500, stride=250)
    starts = [0, 250, 500, 750, 1000, 1250]  # start + 500 <= 1999
    assert d.meta["starts"] == starts * 2 and d.meta["trials"] == ["excerpt"] * 12
    assert d.states.shape == (12, 501, 3, 3) and d.measurements.shape == (12, 500, 6)
    assert d.mask.shape == (12, 501)
    s = 750
    assert torch.equal(d.inputs[3, 0], torch.from_numpy(t.gyr[s + 1]))
    assert np.array_equal(d.mask[3].numpy(), t.known[s : s + 501])
    assert trials_to_dataset([t], window=500).meta["starts"] == [0, 500, 1000]


def test_dataset_errors():
    t = read_trial(FIXTURE)
    short = read_trial(FIXTURE)
    for f in ("gyr", "acc", "mag", "quat", "movement"):
        setattr(short, f, getattr(short, f)[:100])
    with pytest.raises(BroadFormatError, match="different lengths"):
        trials_to_dataset([t, short])
    with pytest.raises(BroadFormatError, match="longer than every trial"):
        trials_to_dataset([short], window=100)
    with pytest.raises(BroadFormatError, match="window must be a positive integer"):
        trials_to_dataset([t], window=0)


def test_split_config_names_23_disjoint_trials():
    from manifold_nets_examples.broad.data import split_trials

    data_dir, splits = split_trials()
    assert data_dir == "../shared/broad/data_mat"
    assert [len(splits[k]) for k in ("train", "val", "test")] == [11, 4, 8]
    names = [n for v in splits.values() for n in v]
    assert len(set(names)) == 23 and all(not n.endswith(".mat") for n in names)
    assert [n[:2] for n in splits["test"]] == ["02", "05", "07", "11", "16", "27", "29", "33"]
