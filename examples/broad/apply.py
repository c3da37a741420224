"""Apply a trained BROAD observer to any BROAD-format ``.mat`` file; write its quaternions.

::

    python -m manifold_nets_examples.broad.apply zoo:broad/attitude trial.mat --out q.csv

``trial.mat`` needs ``imu_gyr``, ``imu_acc``, ``imu_mag`` and ``sampling_rate`` as BROAD's files
hold them (``opt_quat`` and ``movement`` are optional: without a reference nothing is scored);
the observer is a run folder of :mod:`.train` or a checkpoint, loaded by
:func:`manifold_nets.load_observer`, which executes nothing a file names. Writes one row per
sample, ``w, x, y, z`` (the IMU's orientation in East-North-Up), as ``.npy`` (float64, ``(T, 4)``)
or ``.csv`` (a header line, then the rows), atomically: an interrupted run leaves no half file.
With a reference in the file the benchmark's RMSE over its movement samples is printed.
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import numpy as np

from manifold_nets import load_observer
from manifold_nets.atomic import atomic_open

from . import simulator  # noqa: F401  (registers BroadSimulator for load_observer)
from .data import read_trial
from .evaluate import decimation, observer_quaternions
from .metric import rmse

__all__ = ["apply_observer", "write_quaternions"]

FORMATS = (".npy", ".csv")


def write_quaternions(path: Path, quats: np.ndarray) -> None:
    """``quats`` ``(T, 4)`` to ``path`` (``.npy`` or ``.csv``), written atomically."""
    if path.suffix not in FORMATS:
        raise ValueError(f"--out must end in {' or '.join(FORMATS)}, got {path.name!r}.")
    if path.suffix == ".npy":
        buf = io.BytesIO()
        np.save(buf, np.ascontiguousarray(quats, dtype=np.float64), allow_pickle=False)
        data = buf.getvalue()
    else:
        buf = io.StringIO()
        np.savetxt(buf, quats, delimiter=",", header="w,x,y,z", comments="", fmt="%.17g")
        data = buf.getvalue().encode()
    with atomic_open(path, "wb") as f:
        f.write(data)


def apply_observer(observer_path, mat_file, out: Path | None = None) -> dict:
    """Estimates ``mat_file`` with the observer at ``observer_path``; writes ``out`` when given.
    Returns ``{"quaternions": (T, 4), "rmse": {...} or None}``."""
    if out is not None and Path(out).suffix not in FORMATS:  # before any work
        raise ValueError(f"--out must end in {' or '.join(FORMATS)}, got {Path(out).name!r}.")
    trial = read_trial(mat_file)
    observer, system, _ = load_observer(observer_path)
    decimation(system, trial.rate)  # the observer's step must be whole samples
    quats = observer_quaternions(observer, system, [trial])[0]
    if out is not None:
        write_quaternions(Path(out), quats)
    scored = bool(np.isfinite(trial.quat).all(axis=1).any() and trial.movement.any())
    return {"quaternions": quats, "rmse": rmse(quats, trial.quat, trial.movement) if scored else None}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("observer", help="a run folder of broad.train, or its checkpoint")
    p.add_argument("mat_file", help="a BROAD-format .mat recording")
    p.add_argument("--out", required=True, help="where the quaternions go (.npy or .csv)")
    args = p.parse_args(argv)
    try:
        res = apply_observer(args.observer, args.mat_file, Path(args.out))
    except (ValueError, FileNotFoundError) as err:
        raise SystemExit(f"error: {err}") from None
    print(f"{len(res['quaternions'])} quaternions (w, x, y, z) -> {args.out}")
    if res["rmse"] is not None:
        r = res["rmse"]
        print(f"RMSE over the movement samples: total {r['total']:.3f} deg, heading "
              f"{r['heading']:.3f} deg, inclination {r['inclination']:.3f} deg")


if __name__ == "__main__":
    main()
