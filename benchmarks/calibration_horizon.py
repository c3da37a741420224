"""How the rigid-body readouts hold beyond the 1000 steps they were fitted on.

Each case's zoo observer and readout (or ``--readouts DIR``'s ``<case>_covariance.pt``, as
``calibration_in_band.py`` takes them) on ``--sequences`` fresh sequences of ``--length`` steps per
noise level (seed ``--seed`` at every level, as the calibration command draws its evaluation
sets): the ANEES of ``R`` and ``p`` (``NEES / 3`` averaged over the sequences, then over the
steps) in each span of steps ``--spans`` (``k >= 10``)::

    python benchmarks/calibration_horizon.py --write benchmarks/results/calibration_horizon

About a minute a case on one thread.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from manifold_nets.atomic import write_text_atomic
from manifold_nets.calibration import nees, tangent_errors
from manifold_nets.threads import use_threads
from manifold_nets_examples.rigid_body.calibration import CASES, SKIP, _sim
from manifold_nets_examples.rigid_body.level_scale import zoo_readout

FACTORS = ("R", "p")


@torch.no_grad()
def spans_anees(cal, system, n: int, length: int, sigma: float, seed: int,
                spans: list[int]) -> dict[str, list[float]]:
    """Per factor, the ANEES over each span ``[spans[j], spans[j + 1])`` of steps."""
    data, g = _sim(system, n, length, sigma, seed), system.group
    est, cov = cal(data.measurements)
    xi = tangent_errors(g, est, data.states)
    out = {}
    for f in FACTORS:
        s = g.tangent_slice(f)
        q = (nees(xi[..., s], cov[..., s, s].double()) / (s.stop - s.start)).mean(0)  # (T + 1,)
        out[f] = [float(q[a:b].mean()) for a, b in zip(spans[:-1], spans[1:])]
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", nargs="+", default=["nominal"], choices=list(CASES))
    p.add_argument("--sigmas", nargs="+", type=float, default=[0.1, 0.3, 0.5])
    p.add_argument("--sequences", type=int, default=100, help="sequences per noise level")
    p.add_argument("--length", type=int, default=3000, help="steps per sequence")
    p.add_argument("--spans", nargs="+", type=int, default=[SKIP, 1000, 2000, 3001],
                   help="the edges of the spans of steps, the last past the end")
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--readouts", type=Path, default=None,
                   help="a folder of <case>_covariance.pt scored in place of the zoo's readouts")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--write", type=Path, default=None, help="also write PATH.md and PATH.json")
    args = p.parse_args(argv)
    if sorted(args.spans) != args.spans or args.spans[0] < SKIP or len(args.spans) < 2:
        raise SystemExit(f"--spans must be at least two increasing steps from {SKIP} on, "
                         f"got {args.spans}.")
    use_threads(args.threads)
    command = "python benchmarks/calibration_horizon.py " + " ".join(
        argv if argv is not None else sys.argv[1:])
    labels = [f"{a}-{min(b, args.length + 1) - 1}" for a, b in zip(args.spans[:-1], args.spans[1:])]
    results = {"command": command, "spans": labels, "cases": {}}
    for case in args.cases:
        cal, system = zoo_readout(case, args.readouts)
        cal.eval()
        results["cases"][case] = {
            str(sigma): spans_anees(cal, system, args.sequences, args.length, sigma, args.seed,
                                    args.spans)
            for sigma in args.sigmas}
        print(case, json.dumps(results["cases"][case]), flush=True)
    lines = ["# The readouts' ANEES beyond the steps they were fitted on", "", f"`{command}`", "",
             f"{args.sequences} sequences of {args.length} steps per sigma (seed {args.seed}); "
             "ANEES of R / p in each span of steps.", "",
             "| case | sigma | " + " | ".join(f"steps {s}" for s in labels) + " |",
             "|" + " --- |" * (2 + len(labels))]
    for case, rows in results["cases"].items():
        for sigma, r in rows.items():
            lines.append(f"| {case} | {sigma} | " + " | ".join(
                f"{a:.3f} / {b:.3f}" for a, b in zip(r["R"], r["p"])) + " |")
    text = "\n".join(lines + [""])
    if args.write is not None:  # each file whole or not at all
        write_text_atomic(args.write.with_suffix(".json"), json.dumps(results, indent=1))
        write_text_atomic(args.write.with_suffix(".md"), text)
    print(text)


if __name__ == "__main__":
    sys.exit(main())
