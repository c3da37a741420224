"""How far to trust the BROAD observer's attitude: a covariance readout fitted on real trials.

::

    python -m manifold_nets_examples.broad.calibration --out outputs/broad_calibration
    python -m manifold_nets_examples.broad.calibration --sources readings --epochs 2 --out /tmp/bc

The observer (``--observer``: a run folder or an ensemble folder; default the zoo's
``broad/attitude``, an ensemble of three) stays frozen; it measures no group factor (it reads
the IMU), so the readout reads either the IMU readings of each step (``readings``; the only
source of an ensemble, whose members have no one core) or one observer's hidden state
(``hidden``). For each ``--sources`` a readout
(per-factor blocks, a 32-wide memory) is fitted to the attitude errors ``Log(Rhat^T R_ref)`` on
the training trials (``--fit val``: the validation trials, which the observer was not trained on;
cut into windows of ``--window`` observer steps; the reference's unknown samples left out), the
one of lowest NLL on the other split is kept. ``--fit cv`` fits a ``readings`` readout to
errors no observer made on its own training trials: each cross-validation fold's run
(``--cv-runs``, one per ``--folds`` split file, as ``broad.crossval`` takes them; repeated
for more seeds) on that fold's held-out trials, every training and validation trial once a
seed; the readings do not depend on the observer, so the readout then serves ``--observer``
(the run of fold 1 when that is the fixed split's); with no trial left to choose an epoch on,
the epoch of lowest NLL on the fitted errors is kept. ``--conformal 1`` then scales the
readout so that held-out errors fall inside its 3-sigma ellipsoid at the Gaussian share
(:func:`manifold_nets.covariance_training.scale_to_share`): the other split's errors, or with
``--fit cv`` each fold's errors under a readout fitted to the other folds' (cross-conformal;
the report then also gives each of those trials' share inside the scaled 3-sigma ellipsoid).
On the test
trials (never used to fit or choose) each trial's time-averaged NEES / 3 and the share of its
errors inside the 1, 2 and 3 sigma ellipsoids (Gaussian: 19.9 / 73.9 / 97.1 %) are reported, at
the observer's steps where the reference is known and the IMU moves (the benchmark's samples).
Writes ``OUT/broad_calibration.md``, ``.json`` and the readout ``OUT/covariance.pt``.
"""

from __future__ import annotations

import argparse
import sys
import json
from pathlib import Path

import numpy as np
import torch

from manifold_nets import load_observer
from manifold_nets.atomic import write_text_atomic
from manifold_nets.calibration import SIGMAS, gaussian_share, nees, tangent_errors
from manifold_nets.covariance_training import (
    Sequences,
    fit_covariance,
    mean_nll,
    readout_sequences,
    save_readout,
    scale_to_share,
    step_nees,
)
from manifold_nets.observer import (
    CalibratedObserver, CovarianceReadout, EnsembleObserver,
)
from manifold_nets.observer.covariance import input_width
from manifold_nets.plugins import locate
from manifold_nets.threads import use_threads

from . import simulator  # noqa: F401  (registers BroadSimulator for load_observer)
from .data import read_trials, split_trials
from .evaluate import decimation, input_settings, readings_batch
from .learning import measured_start, tilt_start, without_magnetometer
from .rate import decimate

__all__ = ["main", "estimate_with_covariance", "observer_readings", "step_context", "block_spread"]


def observer_readings(trials, system, moving: bool = False):
    """The trials as the observer of ``system`` reads them (pre-filtered, without the
    magnetometer where it was trained so: :func:`.evaluate.input_settings`), decimated to its
    steps."""
    batch, _ = readings_batch(trials, system)
    k = decimation(system, trials[0].rate)
    data = decimate(batch, k, 1.0 / trials[0].rate)
    if not input_settings(system)["magnetometer"]:
        data = without_magnetometer(data)
    if moving:  # the benchmark's samples: reference known and the IMU moving
        length = data.length
        move = [np.r_[t.movement, np.zeros(max(0, length * k + 1 - len(t.movement)))][: length * k + 1 : k]
                for t in trials]
        data.mask = data.mask & torch.as_tensor(np.stack(move) > 0)
    return data


#: What ``--context 1`` gives a readout: per observer step, the logs of how far the raw
#: accelerometer (m/s^2) and gyroscope (rad/s) samples of the step's block spread.
CONTEXT = ("log acc block spread", "log gyr block spread")


def block_spread(trial, k: int) -> np.ndarray:
    """``(J, 2)`` float32 for the ``J = (T - 1) // k`` observer steps of ``trial``: step ``j``
    covers samples ``jk + 1 .. (j + 1) k`` (:func:`.rate.decimate`); the logs of the norms of
    the raw accelerometer's and gyroscope's per-axis standard deviations over them. A vibration
    shows here (phone vibration: 6-8 m/s^2 against 0.3-3.7 in every other BROAD trial, median
    over the steps) and nowhere in what the observer reads (the accelerometer low-passed, the
    gyroscope integrated over the step)."""
    j = (len(trial) - 1) // k
    out = []
    for raw, floor in ((trial.acc, 1e-3), (trial.gyr, 1e-4)):
        blocks = np.asarray(raw[1 : j * k + 1], dtype=np.float64).reshape(j, k, 3)
        out.append(np.log(np.linalg.norm(blocks.std(axis=1), axis=-1) + floor))
    return np.stack(out, -1).astype(np.float32)


def step_context(trials, system, length: int) -> torch.Tensor:
    """``(N, length, 2)``: :func:`block_spread` of each trial at ``system``'s decimation, padded
    with zeros to ``length`` steps (padded steps are masked out)."""
    k = decimation(system, trials[0].rate)
    out = torch.zeros(len(trials), length, len(CONTEXT))
    for i, t in enumerate(trials):
        c = torch.from_numpy(block_spread(t, k))[:length]
        out[i, : len(c)] = c
    return out


def _start(system):
    """Where a whole trial starts: TRIAD of its first sample, or its tilt for a 6-D observer."""
    return measured_start(system) if input_settings(system)["magnetometer"] else tilt_start(system)


def _read(trials, system, context: bool, moving: bool = False):
    """``(data, context or None)``: :func:`observer_readings` of ``trials`` and, when asked,
    their :func:`step_context` over its steps."""
    data = observer_readings(trials, system, moving)
    return data, step_context(trials, system, data.length) if context else None


def estimate_with_covariance(trials, folder=None, readout=None):
    """The observer of ``folder`` (default: the zoo's ``broad/attitude``) and its covariance
    readout (default: ``covariance.pt`` in the folder) on BROAD ``trials`` read as it was
    trained (:func:`observer_readings`, with :func:`step_context` for a readout that reads it),
    from TRIAD of each trial's first sample: ``(estimates (N, J+1, 3, 3), covariances (N, J+1,
    3, 3), data)`` at the observer's ``J`` steps (every ``k``-th sample), ``data`` their
    :class:`~manifold_nets.data.TrajectoryDataset` (the reference, its mask)."""
    from manifold_nets.covariance_training import load_readout

    folder = locate(folder or "zoo:broad/attitude")
    observer, system, _ = load_observer(folder)
    calibrated = load_readout(folder / "covariance.pt" if readout is None else readout, observer)
    data, context = _read(trials, system, bool(calibrated.readout.context))
    state = observer.init_state(len(data), estimate=_start(system)(data))
    with torch.no_grad():
        est, cov = calibrated.eval()(data.measurements, data.inputs, state=state, context=context)
    return est, cov, data


def _windows(seqs: Sequences, window: int) -> Sequences:
    """Sequences cut into windows of ``window`` steps (the last padded with unknown steps), each
    with the steps it starts after (a readout's clock reads them)."""
    n, t = seqs.known.shape
    pad = (-t) % window
    def cut(x, fill):
        x = torch.cat([x, x.new_full((n, pad, *x.shape[2:]), fill)], 1) if pad else x
        return x.reshape(n * ((t + pad) // window), window, *x.shape[2:])
    windows = (t + pad) // window
    start = (seqs.starts.reshape(n, 1) + window * torch.arange(windows)).reshape(-1)
    out = Sequences(cut(seqs.features, 0.0), cut(seqs.errors, 0.0), cut(seqs.known, False), start)
    keep = out.known.any(1)
    return out.select(keep.nonzero().squeeze(-1))


def _cross_fitted(args, observer) -> list[tuple[int, str, Sequences]]:
    """``--fit cv``'s sequences: each fold's run on the fold's held-out trials (``readings``),
    every seed's, as ``(fold index, trial, sequences)`` in ``--cv-runs``' order."""
    from .crossval import fold_trials

    folds = [f for f in args.folds.split(",") if f]
    sets = [[Path(r) for r in item.split(",") if r] for item in args.cv_runs]
    try:
        data_dir, held = fold_trials(folds)
        if any(len(runs) != len(folds) for runs in sets):
            raise ValueError(f"--cv-runs: one run per fold ({len(folds)}) each time, got "
                             f"{[len(runs) for runs in sets]}.")
        return [(k, name, seqs) for runs in sets
                for k, (run, names, fold) in enumerate(zip(runs, held, folds))
                for name, seqs in _fold_sequences(args, observer, run, names, fold, data_dir)]
    except (ValueError, OSError) as err:
        raise SystemExit(f"error: {err}") from None


def _fold_sequences(args, observer, run, names, fold, data_dir) -> list[tuple[str, Sequences]]:
    """One fold's run on its held-out trials (one batch), each trial's in windows (the folds'
    trials differ in length)."""
    from .crossval import check_run_fold

    check_run_fold(run, names, fold)
    obs, system, _ = load_observer(run)
    if input_width(obs, "readings") != input_width(observer, "readings"):
        raise ValueError(f"--cv-runs {run}: reads {input_width(obs, 'readings')} numbers "
                         f"a step, --observer {input_width(observer, 'readings')}.")
    data, context = _read(read_trials(args.data_dir or data_dir, names), system, args.context)
    seqs = readout_sequences(obs, data, "readings", skip=1, start=_start(system), context=context)
    return [(name, _windows(seqs.select(torch.tensor([i])), args.window))
            for i, name in enumerate(names)]


def _sequences_of(args, observer, system, trials, start):
    """``source -> Sequences`` of ``trials`` (a function: each source reads them afresh)."""
    data, context = _read(trials, system, args.context)
    return lambda source: readout_sequences(observer, data, source, skip=1, start=start,
                                            context=context)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True)
    p.add_argument("--observer", default=None,
                   help="a run folder or an ensemble folder (default: the zoo's broad/attitude)")
    p.add_argument("--sources", nargs="+", default=None, choices=["readings", "hidden"],
                   help="what the readout reads (default: readings and hidden for one "
                   "observer, readings for an ensemble)")
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--window", type=int, default=400, help="observer steps per training window")
    p.add_argument("--fit", default="train", choices=["train", "val", "cv"],
                   help="the trials the readout is fitted to (the other split picks the source); "
                        "cv: each fold's held-out trials as its run estimates them")
    p.add_argument("--folds", default=None, help="--fit cv: the folds' split files, comma-separated")
    p.add_argument("--cv-runs", action="append", default=[],
                   help="--fit cv: one run folder per fold, comma-separated, in --folds' order; "
                        "again for another seed's runs (their errors are all fitted)")
    p.add_argument("--conformal", type=int, choices=(0, 1), default=0,
                   help="1: scale the readout so that held-out errors fall inside its 3-sigma "
                        "ellipsoid at the Gaussian share, 97.1 %% (the other split's; with "
                        "--fit cv each fold's errors under a readout fitted to the other folds')")
    p.add_argument("--context", type=int, choices=(0, 1), default=0,
                   help="1: the readout also reads how far each step's raw samples spread "
                        "(block_spread: the accelerometer's and the gyroscope's)")
    p.add_argument("--seed", type=int, default=0,
                   help="the readouts' initial weights and batch order")
    p.add_argument("--data-dir", default=None)
    p.add_argument("--threads", type=int, default=None)
    return p


def _fit(train: Sequences, val: Sequences, observer, source: str, args):
    torch.manual_seed(args.seed)  # the readout's initial weights (torch seeds itself at random)
    readout = CovarianceReadout(observer.group, input_width(observer, source), "factor", 32, source,
                                context=len(CONTEXT) if args.context else 0)
    history = fit_covariance(readout, _windows(train, args.window), val, epochs=args.epochs,
                             lr=3e-3, batch_size=4, seed=args.seed)
    return readout, history


def _cross_conformal(parts, observer, args) -> tuple[dict, float, dict]:
    """Each fold's errors' NEES under a readout fitted to the other folds' errors, their mean
    NLL (over all the folds' known steps) under those readouts, and each trial's NEES."""
    q, per_trial, total, count = {}, {}, 0.0, 0
    for k in sorted({k for k, _, _ in parts}):
        rest = Sequences.cat([seqs for j, _, seqs in parts if j != k])
        readout, _ = _fit(rest, rest, observer, "readings", args)
        mine = [(trial, seqs) for j, trial, seqs in parts if j == k]
        held = Sequences.cat([seqs for _, seqs in mine])
        sizes = [int(seqs.known.sum()) for _, seqs in mine]  # its known steps, trial by trial
        for name, values in step_nees(readout, held).items():
            q.setdefault(name, []).append(values)
            for (trial, _), part in zip(mine, values.split(sizes)):
                per_trial.setdefault(trial, {}).setdefault(name, []).append(part)
        steps = int(held.known.sum())
        total, count = total + mean_nll(readout, held) * steps, count + steps
    cat = lambda d: {name: torch.cat(v) for name, v in d.items()}  # noqa: E731
    return cat(q), total / count, {trial: cat(d) for trial, d in per_trial.items()}


def _held_out_shares(per_trial: dict, scales: dict) -> dict:
    """Each cross-validation trial's share of its held-out errors inside the 3-sigma ellipsoid
    (NEES <= 9) of the scaled readouts (a NEES ``q`` under ``P`` is ``q / s`` under ``s P``), per
    factor, and its number of steps."""
    return {trial: {name: {"in_3sigma": float((v / scales[name] <= 9.0).double().mean()),
                           "steps": len(v)} for name, v in q.items() if name in scales}
            for trial, q in per_trial.items()}


def main(argv=None) -> None:
    args = _parser().parse_args(argv)
    use_threads(args.threads)
    if args.fit == "cv" and (args.sources not in (None, ["readings"]) or not args.folds
                             or not args.cv_runs):
        raise SystemExit("error: --fit cv takes --sources readings (each fold's observer has a "
                         "hidden state of its own), --folds and --cv-runs.")
    if args.conformal and args.fit == "cv" and len([f for f in args.folds.split(",") if f]) < 2:
        raise SystemExit("error: --conformal with --fit cv reads each fold's errors under a "
                         "readout fitted to the other folds': give two folds or more.")
    data_dir, split = split_trials(None)
    data_dir = args.data_dir or data_dir
    if args.observer is None:
        args.observer = "zoo:broad/attitude"
    observer, system, _ = load_observer(args.observer)
    ensemble = isinstance(observer, EnsembleObserver)
    if args.sources is None:
        args.sources = ["readings"] if ensemble or args.fit == "cv" else ["readings", "hidden"]
    if ensemble and "hidden" in args.sources:
        raise SystemExit(
            f"error: --observer {args.observer} is an ensemble of {len(observer.members)} "
            "observers, whose members have no one core to read: use --sources readings, or give "
            "one member's run folder (members/<name> inside it) for a hidden-state readout."
        )
    start = _start(system)
    if args.fit == "cv":  # the training and validation trials come through the folds' runs
        parts = _cross_fitted(args, observer)
        cv = Sequences.cat([seqs for _, _, seqs in parts])
    else:
        cv, data = None, {s: _sequences_of(args, observer, system, read_trials(data_dir, split[s]),
                                           start) for s in ("train", "val")}  # fmt: skip
    test_trials = read_trials(data_dir, split["test"])
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    fits, held, best = {}, {}, None
    for source in args.sources:
        other = "val" if args.fit == "train" else "train"
        train, val = (cv, cv) if cv is not None else (data[args.fit](source), data[other](source))
        readout, history = _fit(train, val, observer, source, args)
        fits[source], held[source] = {"val_nll": mean_nll(readout, val), "history": history}, val
        print(source, "validation NLL", fits[source]["val_nll"], flush=True)
        if best is None or fits[source]["val_nll"] < fits[best[0]]["val_nll"]:
            best = (source, readout)
    source, readout = best
    test, context = _read(test_trials, system, args.context, moving=True)
    result = {"observer": args.observer, "source": source, "fits": fits,
              **_scored(observer, readout, test, test_trials, start, context)}
    if args.conformal:
        before = result
        if cv is not None:
            q, result["cross_fitted_nll"], per_trial = _cross_conformal(parts, observer, args)
            scales = scale_to_share(readout, q)
            result["cross_fitted_trials"] = _held_out_shares(per_trial, scales)
        else:
            scales = scale_to_share(readout, held[source])
        result = {**result, "scales": scales, "unscaled": {"trials": before["trials"],
                  "mean": before["mean"]}, **_scored(observer, readout, test, test_trials, start, context)}
    save_readout(out / "covariance.pt", readout, args.observer)
    write_text_atomic(out / "broad_calibration.json", json.dumps(result, indent=1))
    text = _report(result, args, argv)
    write_text_atomic(out / "broad_calibration.md", text)
    print(text)


def _scored(observer, readout, test, test_trials, start, context=None) -> dict:
    """Each test trial's NEES / 3 and shares inside 1, 2, 3 sigma, and their means."""
    cal = CalibratedObserver(observer, readout).eval()
    state = observer.init_state(len(test), estimate=start(test))
    with torch.no_grad():
        est, cov = cal(test.measurements, test.inputs, state=state, context=context)
    xi = tangent_errors(observer.group, est, test.states)
    q = nees(xi[:, 1:], cov[:, 1:])  # (N, T): d = 3
    rows = {}
    for i, t in enumerate(test_trials):
        known = test.mask[i, 1:]
        qi = q[i][known]
        rows[t.name] = {"nees/3": float(qi.mean() / 3), "steps": int(known.sum()),
                        **{f"in_{s}sigma": float((qi <= s * s).double().mean()) for s in SIGMAS}}
    mean = {k: float(np.mean([r[k] for r in rows.values()])) for k in next(iter(rows.values()))}
    return {"trials": rows, "mean": mean,
            "gaussian": {f"in_{s}sigma": gaussian_share(s, 3) for s in SIGMAS}}


def _report(result: dict, args, argv) -> str:
    fits, source = result["fits"], result["source"]
    lines = ["# BROAD: calibration of the learned attitude covariance on the test trials", "",
             f"Observer `{args.observer}`, readout source `{source}`"
             + (" with the context (`block_spread`)" if args.context else "") + " (validation NLL: "
             + ", ".join(
                 f"{s} {f['val_nll']:.3f}" for s, f in fits.items()) + ")."]
    if "scales" in result:
        lines += ["", "Scaled to hold the Gaussian 3-sigma share on held-out errors (conformal): "
                  "P x " + ", ".join(f"{v:.3f} ({k})" for k, v in result["scales"].items()) + "."]
    if "cross_fitted_nll" in result:
        lines += ["", "Held-out NLL, each fold's errors under a readout fitted to the other folds': "
                  f"{result['cross_fitted_nll']:.3f}."]
    if "cross_fitted_trials" in result:
        shares = result["cross_fitted_trials"]
        lines += ["", "Each cross-validation trial's held-out errors (under the readout fitted "
                  "without its fold) inside the scaled 3-sigma ellipsoid: " + ", ".join(
                      f"{t[:2]} {100 * r['in_3sigma']:.1f} %" for t, f in shares.items()
                      for r in f.values()) + "."]
    lines += ["", "| trial | steps | NEES / 3 | in 1 sigma | in 2 sigma | in 3 sigma |",
              "|---|---|---|---|---|---|"]
    rows = [*result["trials"].items(), ("mean over trials", result["mean"])]
    if "unscaled" in result:
        rows.append(("mean over trials, unscaled", result["unscaled"]["mean"]))
    for name, r in rows:
        lines.append(f"| {name} | {r['steps']:.0f} | {r['nees/3']:.3f} | {100 * r['in_1sigma']:.1f} % | "
                     f"{100 * r['in_2sigma']:.1f} % | {100 * r['in_3sigma']:.1f} % |")
    lines += ["| Gaussian | | 1 | 19.9 % | 73.9 % | 97.1 % |", "",
              "Command: `python -m manifold_nets_examples.broad.calibration " + " ".join(
                  argv if argv is not None else sys.argv[1:]) + "`", ""]
    return "\n".join(lines)

if __name__ == "__main__":
    main()
