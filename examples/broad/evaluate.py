"""A trained BROAD observer on whole trials: its quaternions, and the benchmark's metric of them.

::

    python -m manifold_nets_examples.broad.evaluate runs/broad --splits val,test

Every trial is estimated from its first sample (TRIAD of the first accelerometer and
magnetometer reading, then the observer at every sample), all trials of a split in one batch
(shorter ones padded at the end: the observer is causal, so padding never changes an earlier
estimate). Writes ``results/learned_<split>.json`` (per trial and mean total, heading and
inclination RMSE in degrees) and ``results/learned_<split>_quaternions.npz`` (one array per
trial, ``(T, 4)`` w, x, y, z) for the comparison (:mod:`.compare`), each atomically (a failed
write leaves the previous file whole). Everything is checked before the first estimate: the
split names, that the results folder can be written, that every trial has samples to score
(``movement`` with a reference). Non-finite estimates are an error naming the trial, raised
before that split's files are written.
"""

from __future__ import annotations

import argparse
import io
import json
import logging
import time
from pathlib import Path

import numpy as np
import torch

from manifold_nets import load_observer
from manifold_nets.atomic import atomic_open, write_text_atomic
from manifold_nets.data import TrajectoryDataset, collate_trajectories
from manifold_nets.destination import check_destination
from manifold_nets.threads import use_threads

from . import simulator  # noqa: F401  (registers BroadSimulator for load_observer)
from .data import BroadFormatError, Trial, read_trials, split_trials, trials_to_dataset
from .learning import estimate_rotations
from .metric import matrix_to_quat, rmse
from .prefilter import prefiltered
from .rate import decimate, upsample

__all__ = [
    "pad_trials", "readings_batch", "quaternions_from", "observer_quaternions", "check_scored",
    "chosen_splits", "evaluate_run", "input_settings",
]

log = logging.getLogger("broad.evaluate")


def pad_trials(trials: list[Trial]) -> tuple[TrajectoryDataset, list[int]]:
    """Whole trials as one batch, padded to the longest (last reading repeated, reference masked);
    returns the batch and each trial's number of samples."""
    parts = [trials_to_dataset([t]) for t in trials]
    steps = max(p.length for p in parts)
    padded = []
    for p in parts:
        extra = steps - p.length
        y = torch.cat((p.measurements, p.measurements[:, -1:].expand(1, extra, -1)), 1)
        u = torch.cat((p.inputs, p.inputs[:, -1:].expand(1, extra, -1)), 1)
        s = torch.cat((p.states, p.states[:, -1:].expand(1, extra, 3, 3)), 1)
        mask = torch.cat((p.mask, torch.zeros(1, extra, dtype=torch.bool)), 1)
        padded.append(TrajectoryDataset(s, y, u, p.meta, mask))
    batch = collate_trajectories(padded)
    batch.meta = {"trials": [t.name for t in trials]}
    return batch, [p.length + 1 for p in parts]


def decimation(system, rate: float) -> int:
    """The number of samples per observer step: ``system.dt`` in samples at ``rate`` Hz."""
    k = round(system.dt * rate)
    if k < 1 or abs(k - system.dt * rate) > 1e-3 * k:
        raise ValueError(
            f"the observer steps every {system.dt:.6g} s, which is not a whole number of samples "
            f"at {rate:.6g} Hz; resample the recording to a rate it divides."
        )
    return k


def readings_batch(trials: list[Trial], system) -> tuple[TrajectoryDataset, list[int]]:
    """The trials as the observer of ``system`` reads them at full rate (pre-filtered by
    :mod:`.prefilter` as :func:`input_settings` says), padded into one batch
    (:func:`pad_trials`: the batch and each trial's number of samples)."""
    reads = input_settings(system)
    return pad_trials([prefiltered(t, reads["acc_lowpass"], reads["rest_bias"],
                                   reads["acc_lowpass_order"]) for t in trials])


def quaternions_from(
    estimates: torch.Tensor, batch: TrajectoryDataset, lengths: list[int], trials: list[Trial],
    k: int, source: str = "the observer",
) -> list[np.ndarray]:
    """Per trial ``(T_i, 4)`` quaternions, one per sample, from the observer's ``estimates``
    ``(N, J+1, 3, 3)`` at every ``k``-th sample of :func:`readings_batch`'s ``batch``: between
    them the gyroscope integrated from the last estimate (:func:`.rate.upsample`).

    ``ValueError`` naming ``source`` and the trial where an estimate is NaN or Inf (NaN
    weights, a diverging observer): a file of NaN quaternions is never the answer."""
    R = estimates.to(torch.float64)
    R = upsample(R, batch.inputs.to(R), 1.0 / trials[0].rate, k)
    q = matrix_to_quat(R.numpy())
    out = [q[i, :n] for i, n in enumerate(lengths)]
    for t, qt in zip(trials, out):
        bad = np.flatnonzero(~np.isfinite(qt).all(axis=1))
        if bad.size:
            raise ValueError(
                f"{source} gave non-finite estimates on {t.name} at {bad.size} of {len(qt)} "
                f"samples (first {bad[0]}): NaN or Inf weights, or a diverging observer; "
                "nothing was written."
            )
    return out


def observer_quaternions(
    observer, system, trials: list[Trial], source: str = "the observer"
) -> list[np.ndarray]:
    """The observer's quaternions ``(T_i, 4)`` per trial, one per sample
    (:func:`quaternions_from`), reading the trials as the system says (:func:`readings_batch`):
    a 6-D observer reads no magnetometer and starts from the tilt."""
    batch, lengths = readings_batch(trials, system)
    k = decimation(system, trials[0].rate)
    R = estimate_rotations(observer, system, decimate(batch, k, 1.0 / trials[0].rate),
                           input_settings(system)["magnetometer"])
    return quaternions_from(R, batch, lengths, trials, k, source)


def check_scored(trials: list[Trial], what: str) -> None:
    """``BroadFormatError`` naming each trial of ``trials`` (``what``: where they come from) that
    has no sample to score (``movement`` with a known reference): checked before any work."""
    empty = [t.name for t in trials if not (t.movement & t.known).any()]
    if empty:
        raise BroadFormatError(
            f"{what}: trial(s) {empty} have no sample with movement == 1 and a known reference, "
            "so they cannot be scored; take them out of the split."
        )


def chosen_splits(names, split: dict, option: str) -> list[str]:
    """``names`` (a comma-separated string or a list) checked against the split file's
    splits: ``BroadFormatError`` naming ``option`` unless it names at least one, all known."""
    chosen = [n for n in (names.split(",") if isinstance(names, str) else names) if n]
    unknown = [n for n in chosen if n not in split]
    if not chosen or unknown:
        raise BroadFormatError(
            f"{option} {','.join(chosen) or repr(names)}: "
            f"{'unknown split(s) ' + str(unknown) if unknown else 'names no split'}; the split "
            f"file has {sorted(split)} (e.g. {option} {','.join(sorted(split)[:2])})."
        )
    return chosen


def _save_npz(path: Path, arrays: dict) -> None:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    with atomic_open(path, "wb") as f:
        f.write(buf.getvalue())


def input_settings(system) -> dict:
    """How the observer of ``system`` reads a recording (its config's ``magnetometer``,
    ``acc_lowpass``, ``acc_lowpass_order`` and ``rest_bias``; a system without them, such as one
    loaded from an older run, reads the raw 9-D readings)."""
    return {"magnetometer": bool(getattr(system, "magnetometer", True)),
            "acc_lowpass": float(getattr(system, "acc_lowpass", 0.0)),
            "acc_lowpass_order": int(getattr(system, "acc_lowpass_order", 1)),
            "rest_bias": bool(getattr(system, "rest_bias", False))}


def evaluate_run(
    run: str | Path, data_dir=None, split_file=None, splits=("val", "test")
) -> dict:
    """Evaluates the run's observer on whole trials of ``splits``; returns ``{split: rows}``."""
    run = Path(run)
    default_dir, split = split_trials(split_file)
    splits = chosen_splits(splits, split, "--splits")
    out = check_destination(run / "results", folder=True, option="results folder")
    observer, system, _ = load_observer(run)
    data_dir = data_dir or default_dir
    every = {name: read_trials(data_dir, split[name]) for name in splits}
    for name, trials in every.items():
        check_scored(trials, f"split {name!r}")
    results = {}
    for name, trials in every.items():
        t0 = time.perf_counter()
        quats = observer_quaternions(observer, system, trials, source=str(run))
        seconds = time.perf_counter() - t0
        rows = {t.name: rmse(q, t.quat, t.movement) for t, q in zip(trials, quats)}
        mean = {k: float(np.mean([r[k] for r in rows.values()])) for k in next(iter(rows.values()))}
        results[name] = {"trials": rows, "mean": mean, "seconds": seconds}
        write_text_atomic(out / f"learned_{name}.json", json.dumps(results[name], indent=1) + "\n")
        _save_npz(out / f"learned_{name}_quaternions.npz", {t.name: q for t, q in zip(trials, quats)})
        log.info("%s: mean total %.3f deg, heading %.3f, inclination %.3f (%d trials, %.0f s)",
                 name, mean["total"], mean["heading"], mean["inclination"], len(trials), seconds)
    return results


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="a run folder of broad.train")
    p.add_argument("--data-dir", default=None, help="default: the split file's data_dir")
    p.add_argument("--split", default=None, help="trials yaml (default configs/broad/trials.yaml)")
    p.add_argument("--splits", default="val,test")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads (default: one, or OMP_NUM_THREADS)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s] %(message)s")
    try:
        use_threads(args.threads)
        evaluate_run(args.run, args.data_dir, args.split, args.splits)
    except (ValueError, OSError) as err:
        raise SystemExit(f"error: {err}") from None


if __name__ == "__main__":
    main()
