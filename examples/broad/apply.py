"""Apply a trained BROAD observer to any BROAD-format ``.mat`` file; write its quaternions.

::

    python -m manifold_nets_examples.broad.apply zoo:broad/attitude trial.mat --out q.csv

``trial.mat`` needs only ``imu_gyr``, ``imu_acc``, ``imu_mag`` and ``sampling_rate`` as
BROAD's files hold them: a recording of one's own IMU has no optical reference. Where the file
has ``opt_quat`` (and ``movement``), the benchmark's RMSE over its movement samples (every
sample with a reference when ``movement`` is absent) is printed. The file is read as
:func:`.data.read_trial` reads any trial from outside (its header checked before any data, at
most :data:`.data.MAX_SAMPLES` samples). The observer is a run folder of :mod:`.train` or a
checkpoint, loaded by :func:`manifold_nets.load_observer`, which executes nothing a file names.

Writes one row per sample, ``w, x, y, z`` (the IMU's orientation in East-North-Up), as ``.npy``
(float64, ``(T, 4)``) or ``.csv`` (a header line, then the rows), atomically: an interrupted run
leaves no half file. ``--out`` is checked before any work (its ending, not a folder, no file in
its path, a folder that takes a new file); estimates that are NaN or Inf are an error and
nothing is written. Errors end the command with ``error: ...`` and exit status 1.
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import numpy as np

from manifold_nets import load_observer
from manifold_nets.atomic import atomic_open
from manifold_nets.destination import check_destination
from manifold_nets.threads import use_threads

from . import simulator  # noqa: F401  (registers BroadSimulator for load_observer)
from .data import read_trial
from .evaluate import decimation, observer_quaternions
from .metric import rmse

__all__ = ["apply_observer", "write_quaternions"]

FORMATS = (".npy", ".csv")


def write_quaternions(path: Path, quats: np.ndarray) -> None:
    """``quats`` ``(T, 4)`` to ``path`` (``.npy`` or ``.csv``), written atomically."""
    path = check_destination(path, suffixes=FORMATS)
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
    Returns ``{"quaternions": (T, 4), "rmse": {...} or None, "scored": samples scored,
    "movement_in_file": bool}``."""
    if out is not None:  # before any work
        out = check_destination(out, suffixes=FORMATS)
    trial = read_trial(mat_file, reference=False)
    observer, system, _ = load_observer(observer_path)
    decimation(system, trial.rate)  # the observer's step must be whole samples
    quats = observer_quaternions(observer, system, [trial], source=str(observer_path))[0]
    if out is not None:
        write_quaternions(out, quats)
    scored = int((trial.known & trial.movement).sum())
    return {
        "quaternions": quats,
        "rmse": rmse(quats, trial.quat, trial.movement) if scored else None,
        "scored": scored,
        "movement_in_file": trial.movement_in_file,
    }


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("observer", help="a run folder of broad.train, or its checkpoint")
    p.add_argument("mat_file", help="a BROAD-format .mat recording")
    p.add_argument("--out", required=True, help="where the quaternions go (.npy or .csv)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads (default: one, or OMP_NUM_THREADS)")
    args = p.parse_args(argv)
    try:
        use_threads(args.threads)
        res = apply_observer(args.observer, args.mat_file, Path(args.out))
    except (ValueError, OSError) as err:
        raise SystemExit(f"error: {err}") from None
    print(f"{len(res['quaternions'])} quaternions (w, x, y, z) -> {args.out}")
    if res["rmse"] is None:
        print("no reference in the file (opt_quat, movement): nothing scored")
        return
    r = res["rmse"]
    over = ("movement samples with a reference" if res["movement_in_file"]
            else "samples with a reference (the file has no movement)")  # fmt: skip
    print(f"RMSE over the {res['scored']} {over}: total {r['total']:.3f} deg, heading "
          f"{r['heading']:.3f} deg, inclination {r['inclination']:.3f} deg")


if __name__ == "__main__":
    main()
