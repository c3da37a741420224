"""Where along a run a readout's level is off: each span of steps' ANEES and share in band.

``calibration_in_band.py``'s *oracle level x time* divides a step's ANEES by its own mean over
six spans of steps (10-20, 20-50, 50-100, 100-200, 200-500, 500-1000); this prints those means,
and the share of each span's steps inside the 95 % band, for the zoo's readouts as shipped (with
their level scales). A span off alike on independent sets is a profile along the run that the
level scale does not follow, not a set's noise; off on the level scale's own fitting sequences
too (``--seed 6000 + i`` for the level ``CONTINUUM[i]`` of
``manifold_nets_examples.rigid_body.level_scale``, ``--test 400``: the zoo's fitting set of that
level), it is one its basis cannot follow even where it was fitted. ``--pooled`` adds a row
per factor of the sequences of all the given levels together: over the levels the readouts were
fitted on (``--continuum``), the mixture they learnt, which a readout that cannot yet tell the
levels apart can match while each level alone is off::

    python benchmarks/calibration_profile.py --cases nominal correlated --sigmas 0.1 \\
        --write benchmarks/results/calibration_profile            # the scored sets, seeds 8000 + i
    python benchmarks/calibration_profile.py --cases nominal --sigmas 0.1 --seed 6002 --test 400
    python benchmarks/calibration_profile.py --cases nominal correlated outliers --continuum \\
        --pooled --test 200 --seed 20000 --write benchmarks/results/calibration_profile_continuum

"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the scorer beside this file
from calibration_in_band import SPANS, _in_band, add_set_arguments, write_results, zoo_cells  # noqa: E402

from manifold_nets.threads import use_threads  # noqa: E402
from manifold_nets_examples.rigid_body.calibration import SKIP  # noqa: E402
from manifold_nets_examples.rigid_body.level_scale import CONTINUUM  # noqa: E402


def profile(q: np.ndarray) -> dict:
    """Per span of steps: the ANEES and the share in band of ``q`` ``(sequences, steps)``
    (``NEES / d`` from step ``SKIP`` on)."""
    a, n = q.mean(0), len(q)
    k = np.arange(len(a)) + SKIP
    spans = {}
    for lo, hi in zip(SPANS[:-1], SPANS[1:]):
        at = (k >= lo) & (k < hi)
        spans[f"{lo}-{min(hi, 1000)}"] = {"anees": float(a[at].mean()), "in band": _in_band(a[at], n)}
    return {"anees": float(a.mean()), "in band": _in_band(a, n), "spans": spans}


def _markdown(results: dict) -> str:
    spans = [f"{lo}-{min(hi, 1000)}" for lo, hi in zip(SPANS[:-1], SPANS[1:])]
    lines = ["# Where along a run the readouts' level is off", "", f"`{results['command']}`", "",
             f"The zoo's readouts as shipped (with their level scales); sequences of seeds "
             f"{results['seed']} + i, {results['test']} per noise level. Each span of steps: its "
             "ANEES (its share of steps in the 95 % band)"
             + ("; sigma *pooled*: the sequences of all the levels above together (the band is "
                "then that of their number)." if results.get("pooled") else "."), "",
             "| case | factor | sigma | all steps | " + " | ".join(spans) + " |",
             "|" + " --- |" * (4 + len(spans))]
    for case, rows in results["cases"].items():
        for key, r in rows.items():
            f, sigma = key.split()
            cells = [f"{s['anees']:.3f} ({100 * s['in band']:.0f} %)" for s in r["spans"].values()]
            lines.append(f"| {case} | {f} | {sigma} | {r['anees']:.3f} ({100 * r['in band']:.0f} %) | "
                         + " | ".join(cells) + " |")
    return "\n".join(lines + [""])


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_set_arguments(p)
    p.add_argument("--continuum", action="store_true",
                   help="score the 28 levels the readouts were fitted on (in place of --sigmas)")
    p.add_argument("--pooled", action="store_true",
                   help="also a row per factor of all the levels' sequences together")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--write", type=Path, default=None, help="also write PATH.md and PATH.json")
    args = p.parse_args(argv)
    use_threads(args.threads)
    if args.continuum:
        args.sigmas = list(CONTINUUM)
    command = "python benchmarks/calibration_profile.py " + " ".join(
        argv if argv is not None else sys.argv[1:])
    seen: dict[str, list[np.ndarray]] = {}

    def measure(q: np.ndarray, factor: str) -> dict:
        if args.pooled:
            seen.setdefault(factor, []).append(q)
        return profile(q)

    cases = {}
    for case in args.cases:  # one case at a time, so that pooling holds one case's sequences
        cases |= zoo_cells(argparse.Namespace(**{**vars(args), "cases": [case]}), measure)
        for factor, qs in seen.items():
            cases[case][f"{factor} pooled"] = profile(np.concatenate(qs))
        seen.clear()
    results = {"command": command, "seed": args.seed, "test": args.test, "pooled": args.pooled,
               "cases": cases}
    write_results(args.write, results, _markdown(results))


if __name__ == "__main__":
    sys.exit(main())
