"""Why a cell's ceiling is low: how widely ``NEES / d`` spreads over the sequences at a step.

``calibration_in_band.py``'s *ceiling* is the share of steps whose ANEES would fall inside the
95 % band if the level were exactly 1 at every step; it is set by the variance over the
sequences of each step's ``q = NEES / d``. Errors that are Gaussian under their covariance give
``var q = 2 / d`` (0.667 for a 3-D factor) and a ceiling near 95 %. A larger variance comes
either from a few huge values (an outlier the covariance did not widen for) or from the body of
the distribution (the covariance right on average but too narrow for some sequences and too wide
for others at the same step, or errors not Gaussian in shape). This tells the two apart: per
factor and noise level, the median over steps of ``var q``, the same with ``q`` capped at
``--cap`` (huge values cut), the share of values the cap cuts, and the ceiling before and after
the cap. A level scale can move neither: only a covariance that follows each sequence more
closely can.

The zoo's readouts as shipped (with their level scales), fresh sequences of 1000 steps, seeds
SEED + i, the same as ``calibration_in_band.py``'s::

    python benchmarks/calibration_spread.py --sigmas 0.1 \\
        --write benchmarks/results/calibration_spread        # about 1 minute a case on one thread
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the scorer beside this file
from calibration_in_band import _ceiling, _in_band, add_set_arguments, write_results, zoo_cells  # noqa: E402

from manifold_nets.threads import use_threads  # noqa: E402


def spread(q: np.ndarray, cap: float, d: int = 3) -> dict[str, float]:
    """The spread of ``q`` ``(sequences, steps)`` (``NEES / d`` per sequence and step)."""
    if cap <= 0:
        raise ValueError(f"spread: cap must be > 0, got {cap!r}.")
    capped = np.minimum(q, cap)
    a = q.mean(0)
    return {"anees": float(a.mean()), "in band": _in_band(a, len(q), d),
            "var q": float(np.median(q.var(0))), "var q capped": float(np.median(capped.var(0))),
            "cut": float(np.mean(q > cap)), "ceiling": _ceiling(q, d),
            "ceiling capped": _ceiling(capped, d)}


def _markdown(results: dict) -> str:
    lines = ["# How widely NEES / d spreads over the sequences at a step", "",
             f"`{results['command']}`", "",
             f"The zoo's readouts as shipped; fresh sequences, seeds {results['seed']} + i, "
             f"{results['test']} per noise level. `var q`: the median over steps of the variance "
             "over sequences of q = NEES / 3 (Gaussian errors under their covariance: 0.667); "
             f"capped: q cut at {results['cap']:g} first.", "",
             "| case | factor | sigma | ANEES | in band | var q | var q capped | share cut | ceiling "
             "| ceiling capped |", "|" + " --- |" * 10]
    for case, rows in results["cases"].items():
        for key, r in rows.items():
            f, sigma = key.split()
            lines.append(f"| {case} | {f} | {sigma} | {r['anees']:.3f} | {100 * r['in band']:.1f} % | "
                         f"{r['var q']:.3f} | {r['var q capped']:.3f} | {100 * r['cut']:.3f} % | "
                         f"{100 * r['ceiling']:.1f} % | {100 * r['ceiling capped']:.1f} % |")
    return "\n".join(lines + [""])


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_set_arguments(p)
    p.add_argument("--cap", type=float, default=10.0, help="where q is cut for the capped columns")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--write", type=Path, default=None, help="also write PATH.md and PATH.json")
    args = p.parse_args(argv)
    if args.cap <= 0:
        p.error(f"--cap must be > 0, got {args.cap:g}.")
    use_threads(args.threads)
    command = "python benchmarks/calibration_spread.py " + " ".join(
        argv if argv is not None else sys.argv[1:])
    results = {"command": command, "seed": args.seed, "test": args.test, "cap": args.cap,
               "cases": zoo_cells(args, lambda q, _: spread(q, args.cap))}
    write_results(args.write, results, _markdown(results))


if __name__ == "__main__":
    sys.exit(main())
