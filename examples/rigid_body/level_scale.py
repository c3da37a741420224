"""A level scale for each rigid-body zoo readout, fitted on held-out sequences of its own system.

::

    python -m manifold_nets_examples.rigid_body.level_scale --out outputs/level_scale
    python benchmarks/calibration_paper_sets.py --covariance-dir outputs/level_scale --no-ekf \\
        --out outputs/calibration_paper_sets_level_scale

For each case of :data:`manifold_nets_examples.rigid_body.calibration.CASES` (by default nominal,
outliers, AR(1) noise, bias walk; ``--cases sensor`` the sensor errors' own readout) the zoo
observer and the readout that scores the case (the zoo's, or ``--readouts``'; which file:
:func:`~manifold_nets_examples.rigid_body.calibration.readout_file`) are rolled out over
``--heldout`` fresh sequences of 1000 steps per noise level (seeds 6000 + i: neither the
readout's training, validation and scale sequences, 1000-3027, nor the paper's sets, seed 1; by
default 100 at each of 28 levels 0.06, 0.08, ..., 0.60, the levels the zoo's readouts are fitted
on: fitted on the paper's five levels alone it learns each level's correction and does harm
between them, and a range that ends at 0.1 or 0.5 pulls that end toward the middle,
``docs/calibration.md``), and a :class:`~manifold_nets.observer.LevelScale` is
fitted to its errors there (:func:`manifold_nets.covariance_training.fit_level_scale`: ``--knots``
points of the readout's level averaged over ``--tau`` steps, times the readout's clock; steps
``k >= 10``) on the case's own system. ``--readouts DIR`` fits the level scales of other readouts
of the same observers (``DIR/<case>_covariance.pt``, written by
``python -m manifold_nets_examples.rigid_body.calibration --out DIR``) in place of the zoo's. ``OUT/<case>_covariance.pt`` is the readout with its level scale
(:func:`~manifold_nets.covariance_training.load_readout` reads it back), ``OUT/level_scale.json``
the held-out ANEES of ``R`` and ``p`` before and after, per noise level.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from manifold_nets.atomic import write_text_atomic
from manifold_nets.covariance_training import (
    LevelSteps,
    fit_level_scale,
    level_steps,
    load_readout,
    readout_sequences,
    save_readout,
)
from manifold_nets.threads import use_threads

from .calibration import CASES, SKIP, _sim, _system, readout_file

__all__ = ["main", "zoo_readout", "CONTINUUM"]

#: The noise levels the level scales (and the zoo's readouts) are fitted on by default: a
#: continuum past both ends of the paper's range (0.06 ... 0.60), so that neither 0.1 nor 0.5 is
#: the fitted range's edge.
CONTINUUM = tuple(round(0.06 + 0.02 * i, 2) for i in range(28))


def zoo_readout(case: str, readouts: Path | None = None):
    """The zoo observer of ``case`` with its shipped readout (a ``CalibratedObserver``), or with
    ``readouts``' in its place (which file: :func:`~manifold_nets_examples.rigid_body.calibration.
    readout_file`), and the system it is scored on."""
    entry, overrides, _ = CASES[case]
    observer, system = _system(entry, overrides)
    return load_readout(readout_file(case, readouts), observer), system


def _held_out(observer, readout, system, n: int, sigmas, tau: float) -> list[LevelSteps]:
    """Each noise level's ``n`` held-out sequences (seeds 6000 + i), rolled out and reduced to
    their steps one level at a time: memory grows with the steps, not with the sequences."""
    return [level_steps(readout, readout_sequences(observer, _sim(system, n, 1000, s, 6000 + i),
                                                   readout.source, skip=SKIP), tau)
            for i, s in enumerate(sigmas)]


def _fit_case(case: str, args, out: Path) -> dict:
    """Fit and save one case's level scale."""
    cal, system = zoo_readout(case, args.readouts)
    held = _held_out(cal.observer, cal.readout, system, args.heldout, args.sigmas, args.tau)
    scale = fit_level_scale(cal.readout, LevelSteps.cat(held), args.knots, args.tau,
                            thin=args.thin)
    save_readout(out / f"{case}_covariance.pt", cal.readout, f"zoo:{CASES[case][0]}", scale)
    rows = {}
    for sigma, steps in zip(args.sigmas, held):
        before, after = steps.nees(), steps.nees(scale)
        rows[str(sigma)] = {f: {"before": round(float(before[i]), 4), "after": round(float(after[i]), 4)}
                            for i, f in enumerate(cal.readout.group.factor_names) if f in ("R", "p")}
        print(case, sigma, json.dumps(rows[str(sigma)]), flush=True)
    return rows


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="the folder <case>_covariance.pt goes to")
    p.add_argument("--cases", nargs="+", default=["nominal", "outliers", "correlated", "bias_walk"],
                   choices=list(CASES), help="sensor: the sensor-error system's own readout "
                   "(the zoo's covariance_sensor.pt, or --readouts' sensor_covariance.pt)")
    p.add_argument("--sigmas", nargs="+", type=float, default=list(CONTINUUM))
    p.add_argument("--heldout", type=int, default=100, help="sequences per noise level")
    p.add_argument("--knots", type=int, default=8)
    p.add_argument("--tau", type=float, default=100.0, help="steps the level is averaged over")
    p.add_argument("--thin", type=int, default=3, help="fit on every THIN-th known step")
    p.add_argument("--readouts", type=Path, default=None,
                   help="a folder of <case>_covariance.pt (the calibration command's) to fit the "
                        "level scales of, in place of the zoo's readouts")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    use_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = {"command": "python -m manifold_nets_examples.rigid_body.level_scale "
              + " ".join(argv if argv is not None else sys.argv[1:]), "cases": {}}
    for case in args.cases:
        report["cases"][case] = _fit_case(case, args, out)
        write_text_atomic(out / "level_scale.json", json.dumps(report, indent=1))
    print(f"-> {out}")


if __name__ == "__main__":
    main()
