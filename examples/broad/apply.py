"""Apply a trained BROAD observer to any BROAD-format ``.mat`` file; write its quaternions.

::

    python -m manifold_nets_examples.broad.apply zoo:broad/attitude trial.mat --out q.csv
    python -m manifold_nets_examples.broad.apply zoo:broad/attitude trial.mat --out q.csv \
        --covariance p.npz              # and the covariance of each step's attitude error
    python -m manifold_nets_examples.broad.apply zoo:broad/attitude_6d trial.mat --out q.csv \
        --heading-from zoo:broad/attitude   # the 6-D inclination under the 9-D heading

``trial.mat`` needs only ``imu_gyr``, ``imu_acc``, ``imu_mag`` and ``sampling_rate`` as
BROAD's files hold them (a 6-D observer's, no ``imu_mag``): a recording of one's own IMU has no
optical reference. Where the file
has ``opt_quat`` (and ``movement``), the benchmark's RMSE over its movement samples (every
sample with a reference when ``movement`` is absent) is printed: for a 6-D observer
(``zoo:broad/attitude_6d``, trained with ``--magnetometer 0``), which reads no magnetometer and
whose heading is therefore free, the inclination alone. The file is read as
:func:`.data.read_trial` reads any trial from outside (its header checked before any data, at
most :data:`.data.MAX_SAMPLES` samples). The observer is a run folder of :mod:`.train` or a
checkpoint, loaded by :func:`manifold_nets.load_observer`, which executes nothing a file names.

Writes one row per sample, ``w, x, y, z`` (the IMU's orientation in East-North-Up), as ``.npy``
(float64, ``(T, 4)``) or ``.csv`` (a header line, then the rows), atomically: an interrupted run
leaves no half file. ``--out`` is checked before any work (its ending, not a folder, no file in
its path, a folder that takes a new file); estimates that are NaN or Inf are an error and
nothing is written. Errors end the command with ``error: ...`` and exit status 1.

``--covariance P.npz`` also writes the covariance of the attitude error at each observer step
(:func:`.calibration.estimate_with_covariance`; the readout ``--readout``, by default
``covariance.pt`` in the observer's folder, as the zoo entry ships it): ``covariance``
``(J+1, 3, 3)`` (float64, of ``Log(R_est^T R)``, radians squared) and ``sample`` ``(J+1,)``, the
sample each belongs to (every ``k``-th; between them the quaternions are the gyroscope's
integration from the last step). One rollout of the observer with its readout gives the
quaternions and the covariances (the readout reads the run, it does not change it).

``--heading-from OBSERVER9`` joins a 6-D observer's inclination (the first argument) with a 9-D
observer's heading, as VQF joins its 6-D estimate and its heading correction
(:func:`.six_d.cascade`): a magnetic disturbance then cannot tilt the estimate. With the zoo's
two BROAD entries it is the lowest inclination on BROAD's test trials (``docs/real_data.md``).
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
from .evaluate import (
    decimation,
    input_settings,
    observer_quaternions,
    quaternions_from,
    readings_batch,
)
from .metric import rmse

__all__ = ["apply_observer", "write_quaternions", "write_covariances"]

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


def write_covariances(path: Path, covariance: np.ndarray, sample: np.ndarray) -> None:
    """``covariance`` ``(J+1, 3, 3)`` and ``sample`` ``(J+1,)`` to the ``.npz`` ``path``,
    atomically."""
    path = check_destination(path, suffixes=(".npz",), option="--covariance")
    buf = io.BytesIO()
    np.savez(buf, covariance=np.ascontiguousarray(covariance, dtype=np.float64),
             sample=np.ascontiguousarray(sample, dtype=np.int64))
    with atomic_open(path, "wb") as f:
        f.write(buf.getvalue())


def _readout_of(observer_path, readout) -> tuple[Path, Path]:
    """The observer's folder and its readout (``readout``, or ``covariance.pt`` in the folder)."""
    from manifold_nets.plugins import locate

    folder = locate(observer_path)
    if readout is None and not (folder / "covariance.pt").is_file():
        raise ValueError(f"--covariance: {folder} holds no covariance.pt; give --readout (one "
                         "that broad.calibration wrote) or an observer folder that ships one.")
    return folder, Path(readout) if readout is not None else folder / "covariance.pt"


def _heading_observer(heading_from, reads_mag: bool, observer_path):
    """The 9-D observer of ``--heading-from``, checked against the first (which must be 6-D)."""
    if reads_mag:
        raise ValueError(f"--heading-from joins a 6-D observer's inclination with a 9-D "
                         f"observer's heading, but {observer_path} reads a magnetometer; give "
                         "a 6-D one first (zoo:broad/attitude_6d).")
    loaded = load_observer(heading_from)
    if not input_settings(loaded.system)["magnetometer"]:
        raise ValueError(f"--heading-from {heading_from} reads no magnetometer, so it has no "
                         "heading to give; give a 9-D observer (zoo:broad/attitude).")
    return loaded


def apply_observer(observer_path, mat_file, out: Path | None = None,
                   covariance: Path | None = None, readout=None, heading_from=None) -> dict:
    """Estimates ``mat_file`` with the observer at ``observer_path``; writes ``out`` when given,
    and the covariances to ``covariance`` (module docstring). With ``heading_from`` (a 9-D
    observer; ``observer_path`` then a 6-D one) the estimate is the cascade of the first's
    inclination and the second's heading (:func:`.six_d.cascade`). Returns ``{"quaternions":
    (T, 4), "rmse": {...} or None, "scored": samples scored, "movement_in_file": bool,
    "magnetometer": whether the estimate reads one}`` (and ``"covariance"``, ``"sample"`` when
    asked)."""
    if out is not None:  # before any work
        out = check_destination(out, suffixes=FORMATS)
    if covariance is not None and heading_from is not None:
        raise ValueError("--covariance is one observer's; leave out --heading-from or "
                         "--covariance.")
    if covariance is not None:
        covariance = check_destination(covariance, suffixes=(".npz",), option="--covariance")
        folder, readout = _readout_of(observer_path, readout)
    observer, system, _ = load_observer(observer_path)
    reads_mag = input_settings(system)["magnetometer"]
    if covariance is not None and not reads_mag:
        raise ValueError(f"--covariance: {observer_path} is a 6-D observer, whose heading is free; "
                         "a covariance of the 3-D attitude error cannot describe it, and no "
                         "readout is fitted for one. Leave out --covariance.")
    nine = None if heading_from is None else _heading_observer(heading_from, reads_mag,
                                                                observer_path)
    with_heading = reads_mag or nine is not None  # the estimate's heading means something
    trial = read_trial(mat_file, reference=False, magnetometer=with_heading)
    k = decimation(system, trial.rate)  # the observer's step must be whole samples
    extra = {}
    if covariance is None:
        quats = observer_quaternions(observer, system, [trial], source=str(observer_path))[0]
        if nine is not None:
            from .six_d import cascade

            q9 = observer_quaternions(nine.observer, nine.system, [trial], str(heading_from))[0]
            quats = cascade(quats, q9)
    else:  # one rollout gives both: the readout reads the observer's run, it does not move it
        from .calibration import estimate_with_covariance

        est, cov, _ = estimate_with_covariance([trial], folder, readout)
        batch, lengths = readings_batch([trial], system)
        quats = quaternions_from(est, batch, lengths, [trial], k, str(observer_path))[0]
        cov = cov[0].numpy()
        if not np.isfinite(cov).all():
            raise ValueError(f"the covariance of {observer_path} on {mat_file} is not finite; "
                             "nothing written.")
        extra = {"covariance": cov, "sample": np.arange(len(cov)) * k, "step": k}
    if out is not None:
        write_quaternions(out, quats)
    if covariance is not None:
        write_covariances(covariance, extra["covariance"], extra["sample"])
    scored = int((trial.known & trial.movement).sum())
    return {
        "quaternions": quats,
        "rmse": rmse(quats, trial.quat, trial.movement) if scored else None,
        "scored": scored,
        "movement_in_file": trial.movement_in_file,
        "magnetometer": with_heading,
        **extra,
    }


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("observer", help="a run folder of broad.train, or its checkpoint")
    p.add_argument("mat_file", help="a BROAD-format .mat recording")
    p.add_argument("--out", required=True, help="where the quaternions go (.npy or .csv)")
    p.add_argument("--covariance", default=None,
                   help="also write each step's attitude covariance here (.npz)")
    p.add_argument("--readout", default=None,
                   help="the covariance readout (default: covariance.pt in the observer's folder)")
    p.add_argument("--heading-from", default=None, metavar="OBSERVER9",
                   help="a 9-D observer whose heading joins the (6-D) observer's inclination "
                        "(zoo:broad/attitude_6d with zoo:broad/attitude: the lowest inclination "
                        "with a magnetometer, docs/real_data.md)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads (default: one, or OMP_NUM_THREADS)")
    args = p.parse_args(argv)
    try:
        use_threads(args.threads)
        res = apply_observer(args.observer, args.mat_file, Path(args.out),
                             None if args.covariance is None else Path(args.covariance), args.readout,
                             args.heading_from)
    except (ValueError, OSError) as err:
        raise SystemExit(f"error: {err}") from None
    print(f"{len(res['quaternions'])} quaternions (w, x, y, z) -> {args.out}")
    if "covariance" in res:
        print(f"{len(res['covariance'])} covariances (every {res['step']} samples) -> "
              f"{args.covariance}")
    if res["rmse"] is None:
        print("no reference in the file (opt_quat, movement): nothing scored")
        return
    r = res["rmse"]
    over = ("movement samples with a reference" if res["movement_in_file"]
            else "samples with a reference (the file has no movement)")  # fmt: skip
    if not res["magnetometer"]:
        print(f"RMSE over the {res['scored']} {over}: inclination {r['inclination']:.3f} deg (a "
              "6-D observer reads no magnetometer: its heading is free and not scored)")
        return
    print(f"RMSE over the {res['scored']} {over}: total {r['total']:.3f} deg, heading "
          f"{r['heading']:.3f} deg, inclination {r['inclination']:.3f} deg")


if __name__ == "__main__":
    main()
