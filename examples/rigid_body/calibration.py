"""How far to trust the learned observer's covariance, beside the EKF's: the paper's rigid body at
every noise level and under each model mismatch.

::

    python -m manifold_nets_examples.rigid_body.calibration --out outputs/calibration
    python -m manifold_nets_examples.rigid_body.calibration --cases nominal --sigmas 0.1 0.5 \\
        --train 20 --eval 20 --length 100 --epochs 2 --heldout 5 --out /tmp/cal   # a quick look

For each case (a zoo observer and the system it is scored on):

1. a :class:`~manifold_nets.observer.CovarianceReadout` (per-factor blocks, reading the residuals
   of the measured pose, with ``--source residual_size`` also the log of each factor's squared
   residual, and a clock of the step, ``--clock`` time constants; a 32-wide memory) is
   fitted to the frozen observer's errors on ``--train`` sequences of ``--length`` steps per
   noise level of the case's own system (seeds 1000 + i; ``--train / 4`` more, seeds 2000 + i,
   pick the epoch: :func:`manifold_nets.covariance_training.fit_covariance`), each factor's
   scale then set on ``--heldout`` fresh sequences per noise level (seeds 3000 + i;
   :func:`~manifold_nets.covariance_training.scale_to_heldout`), and written to
   ``OUT/<case>_covariance.pt`` (:func:`~manifold_nets.covariance_training.load_readout` reads
   it back);
2. on ``--eval`` fresh sequences per noise level (seed 7), the learned observer's and the nominal
   EKF's calibration (:mod:`manifold_nets.calibration`) over the steps ``k >= 10``: ANEES per
   factor, the share of steps whose ANEES is inside its 95 % band, the share of errors inside the
   3-sigma ellipsoid; the EKF is the one that knows the nominal model and sigma (started at step
   5 from the first measurements, as in every table of the project).

Writes ``OUT/calibration.md`` (the tables), ``OUT/calibration.json`` and
``OUT/calibration_<case>.png`` (one sequence's attitude and position errors with the +-3 sigma
bands of both, at sigma 0.3). The sensor-error case is scored with the nominal observer (one zoo
entry serves both) and a readout fitted on the sensor-error system's own errors. ``--readouts
DIR`` skips step 1 and scores ``DIR/<case>_covariance.pt`` as they are, each with its level scale
when the file holds one (e.g. the zoo's, or readouts fitted one case a process); a case without a
file of its own there (the sensor errors) is scored with its observer's, ``nominal_covariance.pt``
(:func:`readout_file`).
"""

from __future__ import annotations

import argparse
import sys
import json
from pathlib import Path

import torch

from manifold_nets import load_observer
from manifold_nets.atomic import atomic_open, write_text_atomic
from manifold_nets.calibration import calibration, tangent_errors
from manifold_nets.covariance_training import (
    Sequences,
    fit_covariance,
    load_readout,
    readout_sequences,
    save_readout,
    scale_to_heldout,
)
from manifold_nets.observer import CalibratedObserver, CovarianceReadout
from manifold_nets.observer.covariance import input_width
from manifold_nets.plugins import zoo_path
from manifold_nets.threads import use_threads

from .ekf_estimator import RigidBodyEKF
from .mismatch import MismatchedRigidBody

__all__ = ["CASES", "main", "readout_case", "readout_file"]

#: case -> (zoo entry, system overrides of MismatchedRigidBody, the case of the entry's observer:
#: whose readout scores the case where there is none of its own)
CASES = {
    "nominal": ("rigid_body/nominal", None, "nominal"),
    "sensor": ("rigid_body/nominal", {"scale_factor": 0.1, "misalignment": 0.05}, "nominal"),
    "outliers": ("rigid_body/outliers", None, "outliers"),
    "correlated": ("rigid_body/correlated", None, "correlated"),
    "bias_walk": ("rigid_body/bias_walk", None, "bias_walk"),
}
SIGMAS = (0.1, 0.2, 0.3, 0.4, 0.5)
SKIP = 10
#: The readouts' clock (time constants in steps): the errors' spread changes with the step while
#: the biases converge and after, which a readout of the residuals alone cannot tell.
CLOCK = (10.0, 50.0, 250.0, 1000.0)


def _readout_path(case: str, readout_case: str, folder: Path | None) -> Path:
    if folder is None:  # the zoo entry: covariance.pt is its observer's own case's
        entry, _, observer_case = CASES[case]
        name = "covariance.pt" if readout_case == observer_case else f"covariance_{readout_case}.pt"
        return zoo_path(entry) / name
    return Path(folder) / f"{readout_case}_covariance.pt"


def readout_case(case: str, folder: Path | None = None) -> str:
    """The case whose readout scores ``case``: the case itself where ``folder`` (without one, the
    zoo entry) holds a readout of its own, else its observer's case (the sensor errors: nominal)."""
    return case if _readout_path(case, case, folder).is_file() else CASES[case][2]


def readout_file(case: str, folder: Path | None = None) -> Path:
    """The file of the readout that scores ``case`` (:func:`readout_case`):
    ``folder/<case>_covariance.pt``, or without a folder the zoo entry's ``covariance_<case>.pt``
    (``covariance.pt`` for the entry's own case)."""
    return _readout_path(case, readout_case(case, folder), folder)


def _system(entry: str, overrides: dict | None):
    observer, system, _ = load_observer(f"zoo:{entry}")
    if overrides:
        system = MismatchedRigidBody(**{**system.config(), **overrides})
    return observer, system


def _sim(system, n: int, length: int, sigma: float, seed: int):
    return system.simulate(n, length, sigma, torch.Generator().manual_seed(seed))


def _sequences(observer, system, args, n: int, seed: int) -> Sequences:
    return Sequences.cat([
        readout_sequences(observer, _sim(system, n, args.length, s, seed + i), args.source,
                          skip=SKIP)
        for i, s in enumerate(args.sigmas)
    ])


def _fit(observer, system, args) -> tuple[CovarianceReadout, dict]:
    train = _sequences(observer, system, args, args.train, 1000)
    val = _sequences(observer, system, args, max(2, args.train // 4), 2000)
    width = input_width(observer, args.source)
    torch.manual_seed(args.seed)  # the readout's initial weights
    readout = CovarianceReadout(observer.group, width, "factor", memory=args.memory,
                                source=args.source, clock=tuple(args.clock))
    history = fit_covariance(readout, train, val, epochs=args.epochs, lr=args.lr,
                             batch_size=args.batch_size)
    scales = None
    if args.heldout:  # fresh sequences: neither fitted nor used to pick the epoch
        scales = scale_to_heldout(readout, _sequences(observer, system, args, args.heldout, 3000))
    return readout, {"epochs": history, "heldout_scales": scales}


def _row(group, est, cov, states) -> dict:
    xi = tangent_errors(group, est[:, SKIP:], states[:, SKIP:])
    out = calibration(group, xi, cov[:, SKIP:])
    return {name: {k: round(v, 4) for k, v in c.row().items()} for name, c in out.items()}


def _figure(path: Path, group, data, learned, ekf, sigma: float) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 6))
    FigureCanvasAgg(fig)
    t = torch.arange(data.length + 1)[SKIP:].numpy()
    for row, name in enumerate(("R", "p")):
        s = group.tangent_slice(name)
        for col, (label, (est, cov)) in enumerate((("learned", learned), ("EKF", ekf))):
            ax = fig.add_subplot(2, 2, 2 * row + col + 1)
            xi = tangent_errors(group, est[0, SKIP:], data.states[0, SKIP:])[:, s]
            sd = torch.diagonal(cov[0, SKIP:, s, s], dim1=-2, dim2=-1).sqrt()
            for j in range(xi.shape[-1]):
                ax.plot(t, xi[:, j].numpy(), lw=0.7, label=f"{name}[{j}]")
                ax.fill_between(t, -3 * sd[:, j].numpy(), 3 * sd[:, j].numpy(), alpha=0.12)
            ax.set_title(f"{label}: {name} error and its +-3 sigma band (sigma {sigma:g})")
            ax.set_xlabel("step k")
            ax.set_ylabel("rad" if name == "R" else "m")
            ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=110)


def _table(results: dict) -> str:
    lines = ["# Calibration of the learned observer's covariance and the nominal EKF's", ""]
    for case, per_sigma in results["cases"].items():
        lines += [f"## {case}", "", "| sigma | estimator | " + " | ".join(
            f"{f} ANEES | {f} in band | {f} in 3 sigma" for f in ("R", "p")) + " |",
            "|" + " --- |" * 8]
        for sigma, rows in per_sigma.items():
            for est_name in ("learned", "ekf"):
                r = rows[est_name]
                cells = [
                    f"{r[f]['anees']:.3f} | {100 * r[f]['in_band']:.0f} % | {100 * r[f]['in_3sigma']:.1f} %"
                    for f in ("R", "p")
                ]
                lines.append(f"| {sigma} | {est_name} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += ["Command: `" + results["command"] + "`", ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="the folder the tables, figures and readouts go to")
    p.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    p.add_argument("--sigmas", nargs="+", type=float, default=list(SIGMAS))
    p.add_argument("--train", type=int, default=200, help="training sequences per noise level")
    p.add_argument("--eval", type=int, default=100, help="evaluation sequences per noise level")
    p.add_argument("--length", type=int, default=1000, help="steps per sequence")
    p.add_argument("--clock", nargs="*", type=float, default=list(CLOCK),
                   help="the readout's clock: time constants in steps (none: no clock)")
    p.add_argument("--epochs", type=int, default=20)
    p.add_argument("--lr", type=float, default=3e-3)
    p.add_argument("--batch-size", type=int, default=16, help="sequences per update")
    p.add_argument("--heldout", type=int, default=40,
                   help="fresh sequences per noise level each factor's scale is set on (0: none)")
    p.add_argument("--memory", type=int, default=32)
    p.add_argument("--source", default="residual", choices=("residual", "residual_size"),
                   help="what the readout reads: the measured pose's residuals, or those and "
                        "the log of each factor's squared residual")
    p.add_argument("--seed", type=int, default=0, help="the readouts' initial weights")
    p.add_argument("--readouts", type=Path, default=None,
                   help="a folder of <case>_covariance.pt to score as they are, in place of "
                        "fitting (its readouts must fit the cases' zoo observers)")
    p.add_argument("--threads", type=int, default=None)
    args = p.parse_args(argv)
    use_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {"command": "python -m manifold_nets_examples.rigid_body.calibration "
               + " ".join(argv if argv is not None else sys.argv[1:]),
               "cases": {}, "history": {}}
    for case in args.cases:
        entry, overrides, _ = CASES[case]
        observer, system = _system(entry, overrides)
        if args.readouts is not None:  # scored as they are: nothing fitted, nothing written
            path = readout_file(case, args.readouts)
            loaded = load_readout(path, observer)  # the readout with its level scale, if any
            results["history"][case] = {"loaded": str(path)}
            print(case, "scored with", path, flush=True)
        else:  # fitted on the case's own system
            readout, results["history"][case] = _fit(observer, system, args)
            save_readout(out / f"{case}_covariance.pt", readout, f"zoo:{entry}")
            loaded = load_readout(out / f"{case}_covariance.pt", observer)
        cal = CalibratedObserver(observer, loaded.readout, loaded.level_scale).eval()
        results["cases"][case] = {}
        for sigma in args.sigmas:
            data = _sim(system, args.eval, args.length, sigma, 7)
            with torch.no_grad():
                learned = cal(data.measurements)
                ekf = RigidBodyEKF(system, sigma).estimate_with_covariance(data)
            results["cases"][case][str(sigma)] = {
                "learned": _row(system.group, *learned, data.states),
                "ekf": _row(system.group, *ekf, data.states),
            }
            if sigma == 0.3:
                _figure(out / f"calibration_{case}.png", system.group, data, learned, ekf, sigma)
            print(case, sigma, json.dumps(results["cases"][case][str(sigma)]))
        write_text_atomic(out / "calibration.json", json.dumps(results, indent=1))
        write_text_atomic(out / "calibration.md", _table(results))
    print(f"-> {out / 'calibration.md'}")


if __name__ == "__main__":
    main()
