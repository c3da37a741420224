"""Read BROAD trials (``.mat`` files from outside: checked, never trusted) into datasets.

A trial file (Matlab v5) holds, for ``T`` samples at ``sampling_rate`` Hz (285.714 Hz in BROAD):

* ``imu_gyr`` ``(T, 3)`` rad/s, ``imu_acc`` ``(T, 3)`` m/s^2, ``imu_mag`` ``(T, 3)`` uT, in the
  IMU's frame;
* ``opt_quat`` ``(T, 4)`` the IMU's orientation (w, x, y, z) in East-North-Up,
  ``v_world = R(q) v_body``, NaN rows where the optical reference is missing;
* ``movement`` ``(T,)`` 0/1, the samples that count for the error metric.

:func:`read_trial` reads the file's header first (:mod:`.matfile`: names, shapes and classes,
no data) and refuses a field that is missing, not numeric, or larger than :data:`MAX_SAMPLES`
samples before any data is read; then it reads only these fields, each decompressed at most to
the size its header claims, and checks every value (shapes, one ``T``, IMU readings finite and
within :data:`MAX_READING`, a positive finite rate, unit quaternions to 1e-3, a 0/1 movement).
Each refusal is a :class:`BroadFormatError` naming the file, the field and the fix. Only numeric
arrays are accepted: object, struct, cell and function arrays are refused, nothing from a file
is executed. With ``reference=False`` (a recording of one's own IMU, for :mod:`.apply`)
``opt_quat`` and ``movement`` may be absent: the trial then has no reference (NaN rows), or
without ``movement`` every sample with a reference counts. With ``magnetometer=False`` (for a 6-D
observer, which reads none) ``imu_mag`` is neither needed nor read: the trial's ``mag`` is zeros.

:func:`trials_to_dataset` makes a :class:`~manifold_nets.data.TrajectoryDataset` on
``SO3()``: for samples ``0..T-1`` the states are ``x_k = R(quat_k)`` ``(N, L+1, 3, 3)``,
``measurements[:, k] = (acc_{k+1} / G0, mag_{k+1} / M0)`` ``(N, L, 6)`` and
``inputs[:, k] = gyr_{k+1}`` ``(N, L, 3)`` rad/s (the rate over the step ``k -> k+1``: each
sample's gyro reading is integrated into that sample's estimate, as VQF does). Where the
reference is missing the state is the identity (a placeholder) and the mask is False.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from manifold_nets.data import TrajectoryDataset

from .matfile import NUMERIC_CLASSES, MatFileError, check_regular_file, read_variables, variables

__all__ = [
    "G0",
    "M0",
    "MAX_READING",
    "MAX_SAMPLES",
    "BroadFormatError",
    "Trial",
    "read_trial",
    "read_trials",
    "trials_to_dataset",
    "quat_to_matrix",
    "split_trials",
]

#: Units fed to learning: ``acc / G0`` (about 1 at rest) and ``mag / M0`` (about 1: the field
#: magnitude in these recordings is about 44 uT); the gyro stays in rad/s.
G0 = 9.81
M0 = 44.0

#: The most samples one trial file may hold: 16 times BROAD's longest trial (60,861 samples,
#: 3.5 min at 285.7 Hz), 58 min at that rate; ``broad.apply`` on a file of this length peaked
#: at 1.06 GB resident. A field whose header claims more is refused before any of it is read.
MAX_SAMPLES = 1_000_000

#: The largest magnitude an IMU reading may have, in its unit (rad/s, m/s^2, uT): far beyond any
#: IMU's range (BROAD's largest: 25 rad/s, 155 m/s^2, 86 uT), far inside float32's (the
#: observer's) 3.4e38 even squared, where a finite 1e300 would become Inf.
MAX_READING = 1e6

_VECTORS = {"imu_gyr": "rad/s", "imu_acc": "m/s^2", "imu_mag": "uT"}
_WIDTHS = {"imu_gyr": 3, "imu_acc": 3, "imu_mag": 3, "opt_quat": 4, "movement": 1,
           "sampling_rate": None}  # fmt: skip
_REFERENCE = ("opt_quat", "movement")
#: The fix a missing field's error names, where it is not the default one (an original file).
_MISSING_FIX = {"imu_mag": "store the magnetometer's readings (uT), or, for an IMU without one, "
                           "use a 6-D observer (zoo:broad/attitude_6d, or one trained with "
                           "--magnetometer 0), which reads none"}
_QUAT_TOL = 1e-3


class BroadFormatError(ValueError):
    """A BROAD trial file (or a request for trials) is malformed; the message names the fix."""


@dataclass(eq=False)
class Trial:
    """One BROAD recording of ``T`` samples (numpy float64; see the module docstring).

    ``gyr``, ``acc``, ``mag`` ``(T, 3)``; ``quat`` ``(T, 4)`` unit (w, x, y, z) or NaN rows;
    ``movement`` ``(T,)`` bool; ``rate`` in Hz; ``movement_in_file``: False where the file had no
    ``movement`` (read with ``reference=False``) and every sample counts.
    """

    name: str
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    quat: np.ndarray
    movement: np.ndarray
    rate: float
    movement_in_file: bool = True

    def __len__(self) -> int:
        return len(self.gyr)

    @property
    def known(self) -> np.ndarray:
        """``(T,)`` bool: where the reference orientation is known (not NaN)."""
        return np.isfinite(self.quat).all(axis=1)


def _fail(path, field: str, problem: str, fix: str) -> BroadFormatError:
    return BroadFormatError(f"{path}: field {field!r} {problem}; {fix}.")


def _not_numeric(path, field: str, what: str) -> BroadFormatError:
    return _fail(
        path, field, f"is not a numeric array (got {what}: an object, struct, cell, string or "
        "function value)", "the BROAD format stores it as a real numeric matrix; re-export the trial",
    )


def _check_header(path, header: dict, fields) -> None:
    """Each of ``fields`` is in ``header``, numeric, and no larger than :data:`MAX_SAMPLES`
    samples (the rate: one number), judged from the header alone: nothing is read yet."""
    for field in fields:
        if field not in header:
            raise _fail(
                path, field, f"is missing (the file has {sorted(header)[:20]}"
                f"{' and more' if len(header) > 20 else ''})",
                _MISSING_FIX.get(field, "use an original BROAD trial file from "
                                 "https://github.com/dlaidig/broad (data_mat/), or store the field"),
            )
        shape, cls = header[field].shape, header[field].cls
        if cls not in NUMERIC_CLASSES:
            raise _not_numeric(path, field, f"a Matlab {cls} array")
        values, width = math.prod(shape), _WIDTHS[field]
        if width is None and values != 1:
            raise _fail(path, field, f"has shape {shape}, not one number",
                        "store the sampling frequency in Hz (285.714 in BROAD)")
        if width is not None and values > MAX_SAMPLES * width:
            raise _fail(
                path, field, f"claims shape {shape} ({values} values), more than this reader's "
                f"limit of MAX_SAMPLES = {MAX_SAMPLES} samples x {width}",
                f"split the recording into files of at most {MAX_SAMPLES} samples",
            )


def _numeric(path, raw: dict, field: str) -> np.ndarray:
    """``raw[field]`` as a float64 array, refusing anything but a plain numeric array."""
    value = raw[field]
    arr = np.asarray(value) if isinstance(value, (int, float, np.number)) else value
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "biuf":
        kind = getattr(getattr(arr, "dtype", None), "kind", type(arr).__name__)
        raise _not_numeric(path, field, f"{type(value).__name__} of kind {kind!r}")
    return arr.astype(np.float64)


def _shaped(path, arr: np.ndarray, field: str, width: int | None) -> np.ndarray:
    want = "(T,)" if width is None else f"(T, {width})"
    ok = arr.ndim == 1 if width is None else arr.ndim == 2 and arr.shape[1] == width
    if not ok or len(arr) < 2:
        raise _fail(
            path, field, f"has shape {arr.shape}, expected {want} with T >= 2 samples",
            "store one row per sample",
        )
    return arr


def _check_quat(path, quat: np.ndarray) -> np.ndarray:
    """Unit quaternions to 1e-3 (then normalised); a row with any NaN becomes all NaN."""
    missing = np.isnan(quat).any(axis=1)
    if np.isinf(quat).any():
        raise _fail(path, "opt_quat", "holds Inf values", "mark missing samples with NaN rows")
    norm = np.linalg.norm(np.where(missing[:, None], 1.0, quat), axis=1)
    norm[missing] = 1.0
    bad = np.flatnonzero(np.abs(norm - 1.0) > _QUAT_TOL)
    if bad.size:
        raise _fail(
            path, "opt_quat", f"has {bad.size} row(s) that are not unit quaternions (first: "
            f"sample {bad[0]}, norm {norm[bad[0]]:.6g}; tolerance {_QUAT_TOL})",
            "store unit quaternions (w, x, y, z), NaN rows where the reference is missing",
        )
    out = quat / norm[:, None]
    out[missing] = np.nan
    return out


def _check_rate(path, raw: dict) -> float:
    rate = _numeric(path, raw, "sampling_rate")
    if rate.size != 1 or not math.isfinite(float(rate.reshape(-1)[0])) or rate.reshape(-1)[0] <= 0:
        raise _fail(
            path, "sampling_rate", f"is {rate.tolist()!r}, not one positive finite number",
            "store the sampling frequency in Hz (285.714 in BROAD)",
        )
    return float(rate.reshape(-1)[0])


def _load(path: Path, reference: bool, magnetometer: bool = True) -> dict:
    """The fields of a trial that ``path`` holds, their header checked before any is read."""
    try:
        check_regular_file(path)
        header = variables(path)
        vectors = [f for f in _VECTORS if magnetometer or f != "imu_mag"]
        fields = [*vectors, "sampling_rate"] + [f for f in _REFERENCE if reference or f in header]
        _check_header(path, header, fields)
        return read_variables(path, header, fields)
    except MatFileError as err:
        raise BroadFormatError(str(err)) from None


def _check_readings(path, arrays: dict) -> None:
    for field, unit in _VECTORS.items():
        arr = arrays[field]
        bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
        if bad.size:
            raise _fail(
                path, field, f"({unit}) holds NaN/Inf in {bad.size} sample(s), first {bad[0]}",
                "IMU readings must be finite; cut the trial or fill the gap before using it",
            )
        big = np.flatnonzero((np.abs(arr) > MAX_READING).any(axis=1))
        if big.size:
            raise _fail(
                path, field, f"({unit}) holds readings beyond +-{MAX_READING:g} in {big.size} "
                f"sample(s), first {big[0]} ({arr[big[0]].tolist()}): no IMU measures that, and "
                "the observer computes in float32",
                "the recording is damaged or in other units; fix or cut those samples",
            )


def read_trial(path: str | Path, reference: bool = True, magnetometer: bool = True) -> Trial:
    """The checked :class:`Trial` in ``path``; :class:`BroadFormatError` if anything is off.

    ``reference=False``: ``opt_quat`` and ``movement`` may be missing (where present they are
    checked as always); ``magnetometer=False``: ``imu_mag`` is not read, ``mag`` is zeros (see
    the module docstring)."""
    path = Path(path)
    raw = _load(path, reference, magnetometer)
    arrays = {f: _shaped(path, _numeric(path, raw, f), f, 3) for f in _VECTORS if f in raw}
    t = len(arrays["imu_gyr"])
    arrays.setdefault("imu_mag", np.zeros((t, 3)))
    quat = (_shaped(path, _numeric(path, raw, "opt_quat"), "opt_quat", 4) if "opt_quat" in raw
            else np.full((t, 4), np.nan))  # fmt: skip
    movement = (_shaped(path, _numeric(path, raw, "movement"), "movement", None)
                if "movement" in raw else np.ones(t))  # fmt: skip
    rate = _check_rate(path, raw)
    for field, arr in [*arrays.items(), ("opt_quat", quat), ("movement", movement)]:
        if len(arr) != t:
            raise _fail(
                path, field, f"has {len(arr)} samples but imu_gyr has {t}",
                "every per-sample field must have the same number of rows T",
            )
    _check_readings(path, arrays)
    if not np.isin(movement, (0.0, 1.0)).all():
        raise _fail(path, "movement", "holds values other than 0 and 1", "store a 0/1 mask")
    return Trial(
        name=path.stem, gyr=arrays["imu_gyr"], acc=arrays["imu_acc"], mag=arrays["imu_mag"],
        quat=_check_quat(path, quat), movement=movement.astype(bool), rate=rate,
        movement_in_file="movement" in raw,
    )


def read_trials(data_dir: str | Path, names) -> list[Trial]:
    """The trials ``names`` (file stems: ``01_undisturbed_slow_rotation_A``) in ``data_dir``."""
    data_dir = Path(data_dir)
    names = [str(n).removesuffix(".mat") for n in names]
    missing = [n for n in names if not (data_dir / f"{n}.mat").exists()]
    if missing:
        raise BroadFormatError(
            f"{data_dir}: missing trial file(s) {[m + '.mat' for m in missing]}; download the "
            "BROAD trials (data_mat/*.mat, https://github.com/dlaidig/broad) into that folder or "
            "pass the right data directory."
        )
    return [read_trial(data_dir / f"{n}.mat") for n in names]


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of unit quaternions ``(..., 4)`` (w, x, y, z)."""
    q = np.asarray(q, dtype=np.float64)
    w, x, y, z = np.moveaxis(q, -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def _sequence(trial: Trial, start: int, steps: int):
    """``(states (L+1, 3, 3), measurements (L, 6), inputs (L, 3), mask (L+1,))`` from ``start``."""
    sl = slice(start, start + steps + 1)
    quat = trial.quat[sl]
    known = np.isfinite(quat).all(axis=1)
    states = quat_to_matrix(np.where(known[:, None], quat, [1.0, 0.0, 0.0, 0.0]))
    nxt = slice(start + 1, start + steps + 1)
    meas = np.concatenate((trial.acc[nxt] / G0, trial.mag[nxt] / M0), axis=1)
    return states, meas, trial.gyr[nxt], known


def _windows(trials: list[Trial], window: int | None, stride: int | None):
    """``[(trial index, start)]`` and the number of steps ``L`` per sequence."""
    if window is None:
        lengths = {len(t) for t in trials}
        if len(lengths) != 1:
            raise BroadFormatError(
                f"whole trials of different lengths ({sorted(lengths)} samples) cannot share "
                "one dataset; pass window=L (windows of L steps) or one trial per call: "
                "[trials_to_dataset([t]) for t in trials]."
            )
        return [(i, 0) for i in range(len(trials))], lengths.pop() - 1
    for name, v in (("window", window), ("stride", stride)):
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
            raise BroadFormatError(f"{name} must be a positive integer or None, got {v!r}.")
    stride = window if stride is None else stride
    out = [(i, s) for i, t in enumerate(trials) for s in range(0, len(t) - window, stride)]
    if not out:
        raise BroadFormatError(
            f"window={window} is longer than every trial (samples {[len(t) for t in trials]}); "
            "use a shorter window."
        )
    return out, window


def trials_to_dataset(
    trials: list[Trial], window: int | None = None, stride: int | None = None
) -> TrajectoryDataset:
    """A dataset of ``trials``; see the module docstring for the layout.

    ``window=None``: one sequence per trial, ``L = T - 1`` steps (the trials must all have the
    same length ``T``; otherwise call once per trial). ``window=L``: sequences of ``L`` steps
    (``L + 1`` samples) starting every ``stride`` samples (default ``L``: no overlap).
    ``meta = {"system": "broad", "trials": [name per sequence], "starts": [first sample per
    sequence], "rate": Hz}``. The mask ``(N, L+1)`` (True where the reference is known) is the
    dataset's ``mask`` field.
    """
    if not trials:
        raise BroadFormatError("trials_to_dataset needs at least one trial.")
    rates = {t.rate for t in trials}
    if len(rates) != 1:
        raise BroadFormatError(f"the trials have different sampling rates {sorted(rates)} Hz.")
    spans, steps = _windows(list(trials), window, stride)
    parts = [_sequence(trials[i], s, steps) for i, s in spans]
    states, meas, inputs, mask = (
        torch.from_numpy(np.stack([p[j] for p in parts])) for j in range(4)
    )
    meta = {
        "system": "broad",
        "trials": [trials[i].name for i, _ in spans],
        "starts": [int(s) for _, s in spans],
        "rate": rates.pop(),
    }
    return TrajectoryDataset(states, meas, inputs, meta, mask=mask)


def split_trials(config: str | Path | None = None) -> tuple[str, dict[str, list[str]]]:
    """``(data_dir, {"train": [...], "val": [...], "test": [...]})`` from the split file.

    ``config`` defaults to the shipped ``configs/broad/trials.yaml`` (package
    ``manifold_nets_configs``); names are file stems without ``.mat``.
    """
    import importlib.resources

    import yaml

    if config is None:
        text = importlib.resources.files("manifold_nets_configs").joinpath(
            "broad/trials.yaml"
        ).read_text()
    else:
        text = Path(config).read_text()
    cfg = yaml.safe_load(text)
    splits = cfg.get("splits") if isinstance(cfg, dict) else None
    if not isinstance(splits, dict) or not all(isinstance(v, list) for v in splits.values()):
        raise BroadFormatError(
            f"{config or 'configs/broad/trials.yaml'}: expected 'splits: {{name: [trial, ...]}}'."
        )
    return str(cfg.get("data_dir", "../shared/broad/data_mat")), {
        k: [str(n).removesuffix(".mat") for n in v] for k, v in splits.items()
    }
