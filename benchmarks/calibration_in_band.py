"""Why the rigid-body readouts' ANEES falls outside its 95 % band at many steps, and how much a
level recalibration fitted on held-out sequences would win back.

With 1000 sequences a step's ANEES must lie within 0.950-1.051 (the chi-square band of 3000
degrees of freedom), so the readout's level has to be right to about 1.5 % at every step. For each
case of ``manifold_nets_examples.rigid_body.calibration`` (its zoo observer and readout, as the
paper's sets score them) this simulates fresh sequences of 1000 steps per noise level, reads every
step's ``NEES / 3`` of ``R`` and ``p`` and the readout's level (``log det P_f / 3``), and reports
per noise level:

* **as shipped**: the ANEES and the share of steps whose ANEES is inside the band (the readout
  with the level scale its file holds, as the zoo's do; with ``--level-scale``, the readout
  alone);
* **ceiling**: the share expected if the level were exactly 1 at every step, given how much the
  errors' NEES spreads over sequences at each step (a spread wider than the chi-square's
  lowers it; ``calibration_spread.py`` tells what widens it);
* **oracle level**, **oracle level x time**: the share after dividing by the set's own mean (per
  noise level), or by its own mean in six spans of steps (10-20, 20-50, 50-100, 100-200,
  200-500, 500-1000): upper bounds fitted on the scored set itself, to tell the level's share of
  the misses from the time profile's;
* **level scale**: the same with the readout's :class:`~manifold_nets.observer.LevelScale` from
  ``--level-scale DIR`` (``DIR/<case>_covariance.pt`` of the case whose readout is scored,
  :func:`~manifold_nets_examples.rigid_body.calibration.readout_case`; written by
  ``python -m manifold_nets_examples.rigid_body.level_scale --out DIR``: fitted on other
  sequences per noise level, seeds 6000 + i), applied to the same rollout in place of the
  readout's own.

``--readouts DIR`` scores other readouts in place of the zoo's (``DIR/<case>_covariance.pt``,
written by ``python -m manifold_nets_examples.rigid_body.calibration --out DIR``; a case without
a file of its own there, its observer's), in every column.

The scored sequences are seeds 8000 + i (``--test`` per noise level), neither the paper's sets
(seed 1) nor the readouts' and level scales' own (1000-3027, 6000-6027)::

    python benchmarks/calibration_in_band.py --write outputs/in_band          # the zoo's, as shipped
    python -m manifold_nets_examples.rigid_body.level_scale --out outputs/level_scale_five \
        --cases nominal sensor outliers correlated bias_walk \
        --sigmas 0.1 0.2 0.3 0.4 0.5 --heldout 400       # another level scale of the zoo's readouts
    python benchmarks/calibration_in_band.py --level-scale outputs/level_scale_five \
        --write outputs/in_band_five                       # the readouts alone, and with it

About 5 minutes a case on one thread.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.stats import chi2, norm

from manifold_nets.calibration import nees, tangent_errors
from manifold_nets.observer import CalibratedObserver, CovarianceReadout
from manifold_nets.threads import use_threads
from manifold_nets.covariance_training import load_readout
from manifold_nets_examples.rigid_body.calibration import CASES, SIGMAS, SKIP, _sim, readout_case
from manifold_nets_examples.rigid_body.level_scale import zoo_readout

FACTORS = ("R", "p")
SPANS = (10, 20, 50, 100, 200, 500, 1001)


@torch.no_grad()
def _read(cal, scale, system, n: int, sigma: float, seed: int) -> dict[str, np.ndarray]:
    """Per factor: ``NEES / d`` ``(n, T + 1)`` under the readout's covariance, and under it with
    the level scale ``scale`` (``"<f> scaled"``; none without one)."""
    data, g = _sim(system, n, 1000, sigma, seed), system.group
    parts: dict[str, list] = {}
    for b in range(0, n, 100):
        est, cov = cal(data.measurements[b:b + 100])
        xi = tangent_errors(g, est, data.states[b:b + 100])
        covs = {"": cov}
        if scale is not None:  # the same rollout's Cholesky factors, scaled
            chol = torch.linalg.cholesky(cov)
            later, _ = scale(chol[:, 1:], scale.initial(chol[:, 0]), 0)
            covs[" scaled"] = CovarianceReadout.covariance(torch.cat([chol[:, :1], later], 1))
        for f in FACTORS:
            s = g.tangent_slice(f)
            for tag, c in covs.items():
                parts.setdefault(f + tag, []).append(
                    (nees(xi[..., s], c[..., s, s].double()) / (s.stop - s.start)).numpy())
    return {k: np.concatenate(v) for k, v in parts.items()}


def _in_band(anees_k: np.ndarray, n: int, d: int = 3) -> float:
    lo, hi = chi2.ppf([0.025, 0.975], n * d) / (n * d)
    return float(np.mean((anees_k >= lo) & (anees_k <= hi)))


def _ceiling(q: np.ndarray, d: int = 3) -> float:
    n = len(q)
    lo, hi = chi2.ppf([0.025, 0.975], n * d) / (n * d)
    sd = np.sqrt(q.var(0) / n)
    return float(np.mean(norm.cdf((hi - 1) / sd) - norm.cdf((lo - 1) / sd)))


def _by_span(anees_k: np.ndarray) -> np.ndarray:
    k, out = np.arange(len(anees_k)) + SKIP, np.empty_like(anees_k)
    for a, b in zip(SPANS[:-1], SPANS[1:]):
        span = (k >= a) & (k < b)
        out[span] = anees_k[span].mean()
    return out


def _level_scale_file(case: str, args) -> Path:
    """``--level-scale``'s file for the case: fitted over the readout that scores it, the case's
    own or its observer's."""
    return args.level_scale / f"{readout_case(case, args.readouts)}_covariance.pt"


def _case(case: str, args) -> dict:
    cal, system = zoo_readout(case, args.readouts)  # --readouts: in the zoo's place
    scale = None
    if args.level_scale is not None:  # set against the readout alone: its own level scale aside
        cal = CalibratedObserver(cal.observer, cal.readout)
        path = _level_scale_file(case, args)
        scale = load_readout(path, cal.observer).level_scale
        if scale is None:
            raise SystemExit(f"{path} has no level scale; write one with "
                             "python -m manifold_nets_examples.rigid_body.level_scale.")
    cal.eval()
    rows = {}
    for i, sigma in enumerate(args.sigmas):
        r = _read(cal, scale, system, args.test, sigma, args.seed + i)
        for f in FACTORS:
            q = r[f][:, SKIP:]
            a = q.mean(0)
            row = {"anees": float(a.mean()), "in band": _in_band(a, len(q)), "ceiling": _ceiling(q),
                   "oracle level": _in_band(a / a.mean(), len(q)),
                   "oracle level x time": _in_band(a / _by_span(a), len(q))}
            if scale is not None:
                a_s = r[f + " scaled"][:, SKIP:].mean(0)
                row |= {"level scale anees": float(a_s.mean()), "level scale": _in_band(a_s, len(q))}
            rows[f"{f} {sigma}"] = row
            print(case, f, sigma, json.dumps({k: round(v, 4) for k, v in row.items()}), flush=True)
    return rows


def _markdown(results: dict, command: str) -> str:
    lines = ["# Where the readouts' steps leave the 95 % band, and what a level recalibration wins back",
             "", f"`{command}`", "",
             f"Share of steps whose ANEES is inside the band (fresh sequences, seeds {results['seed']} + i; "
             f"{results['test']} per noise level). "
             "The oracles are fitted on the scored set itself: upper bounds, not estimators.", "",
             "| case | factor | sigma | ANEES | in band | ceiling | oracle level | oracle level x time "
             "| level scale: ANEES | in band |", "|" + " --- |" * 10]
    for case, rows in results["cases"].items():
        for key, r in rows.items():
            f, sigma = key.split()
            lines.append(
                f"| {case} | {f} | {sigma} | {r['anees']:.3f} | {100 * r['in band']:.0f} % | "
                f"{100 * r['ceiling']:.0f} % | {100 * r['oracle level']:.0f} % | "
                f"{100 * r['oracle level x time']:.0f} % | "
                + (f"{r['level scale anees']:.3f} | {100 * r['level scale']:.0f} % |"
                   if "level scale" in r else "- | - |"))
    return "\n".join(lines + [""])


def write_results(path: Path | None, results: dict, text: str) -> None:
    """``text`` printed, and with ``results`` written to ``path``.md and ``path``.json (when given)."""
    if path is not None:
        path.with_suffix(".json").write_text(json.dumps(results, indent=1))
        path.with_suffix(".md").write_text(text)
    print(text)


def add_set_arguments(p: argparse.ArgumentParser) -> None:
    """The options that choose the scored sets: ``--cases``, ``--sigmas``, ``--test``, ``--seed``."""
    p.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    p.add_argument("--sigmas", nargs="+", type=float, default=list(SIGMAS))
    p.add_argument("--test", type=int, default=1000, help="sequences per noise level scored")
    p.add_argument("--seed", type=int, default=8000, help="the scored sets' seeds: SEED + i")


def zoo_cells(args, measure) -> dict:
    """``{case: {"<factor> <sigma>": measure(q, factor)}}`` over the sets ``add_set_arguments``
    chose, the zoo's readouts as shipped (with their level scales), ``q`` their ``NEES / d``
    ``(sequences, steps from SKIP)``: what ``calibration_spread.py`` and
    ``calibration_profile.py`` tabulate."""
    cases = {}
    for case in args.cases:
        cal, system = zoo_readout(case)
        cal.eval()
        rows = {}
        for i, sigma in enumerate(args.sigmas):
            r = _read(cal, None, system, args.test, sigma, args.seed + i)
            for f in FACTORS:
                rows[f"{f} {sigma}"] = measure(r[f][:, SKIP:], f)
                print(case, f, sigma, json.dumps(rows[f"{f} {sigma}"]), flush=True)
        cases[case] = rows
    return cases


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_set_arguments(p)
    p.add_argument("--level-scale", type=Path, default=None,
                   help="a folder of <case>_covariance.pt with level scales to score beside")
    p.add_argument("--readouts", type=Path, default=None,
                   help="a folder of <case>_covariance.pt scored in place of the zoo's readouts")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--write", type=Path, default=None, help="also write PATH.md and PATH.json")
    args = p.parse_args(argv)
    use_threads(args.threads)
    files = [_level_scale_file(c, args) for c in args.cases] if args.level_scale else []
    missing = [str(f) for f in files if not f.is_file()]
    if missing:  # before any case is scored
        raise SystemExit(f"--level-scale: no {', '.join(missing)}; fit them with python -m "
                         "manifold_nets_examples.rigid_body.level_scale --out DIR --cases ... "
                         "(the sensor errors' own readout: --cases sensor).")
    command = "python benchmarks/calibration_in_band.py " + " ".join(
        argv if argv is not None else sys.argv[1:])
    results = {"command": command, "seed": args.seed, "test": args.test,
               "cases": {c: _case(c, args) for c in args.cases}}
    write_results(args.write, results, _markdown(results, command))


if __name__ == "__main__":
    sys.exit(main())
