"""Calibration of the rigid-body zoo readouts (and the nominal EKF) on the paper's inference sets.

Runs ``mn-evaluate`` once per case: the case's zoo observer with the readout the zoo ships for
the case's system (the sensor errors: the nominal entry's ``covariance_sensor.pt``), or
``--covariance-dir``'s ``<case>_covariance.pt`` (what ``manifold_nets_examples.rigid_body.
calibration`` writes; a case without one there, its observer's: ``manifold_nets_examples.
rigid_body.calibration.readout_file``), ``eval.calibration=true``, on the experiment's
inference sets (1000 sequences of 1000 steps per sigma, seed 1), the EKF beside it unless
``--no-ekf``; then gathers the ANEES, the share of steps in the 95 % band and the share inside 3
sigma of R and p into one table::

    python benchmarks/calibration_paper_sets.py --out outputs/calibration_paper_sets \\
        --write benchmarks/results/calibration_paper_sets

About 2 minutes a case on one thread without the EKF, 5 with it.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

#: case -> (experiment, zoo entry); the sensor errors are scored with the nominal entry
CASES = {
    "nominal": ("paper_cpu_prior", "nominal"),
    "sensor": ("mismatch_sensor", "nominal"),
    "outliers": ("mismatch_outliers", "outliers"),
    "correlated": ("mismatch_correlated", "correlated"),
    "bias_walk": ("mismatch_bias_walk", "bias_walk"),
}
FIELDS = ("ANEES", "in band %", "in 3 sigma %")


def _readout(case: str, covariance_dir: Path | None) -> str:
    """``eval.covariance`` for the case: the file ``readout_file`` picks, the zoo's by name."""
    from manifold_nets_examples.rigid_body.calibration import readout_file

    path = readout_file(case, covariance_dir)
    if covariance_dir is not None:
        return str(path)
    entry = f"zoo:rigid_body/{CASES[case][1]}"
    return entry if path.name == "covariance.pt" else f"{entry}/{path.name}"


def _command(case: str, out: Path, covariance_dir: Path | None, ekf: bool) -> list[str]:
    experiment, entry = CASES[case]
    readout = _readout(case, covariance_dir)
    return ["mn-evaluate", f"experiment={experiment}", f"eval.checkpoint=zoo:rigid_body/{entry}",
            f"eval.covariance={readout}", "eval.calibration=true",
            "eval.baselines=[ekf]" if ekf else "eval.baselines=[]", "eval.test_split=false",
            "eval.plots=false", f"hydra.run.dir={out / case}"]


def _rows(run: Path) -> list[dict]:
    rows = []
    for path in sorted((run / "results").glob("**/metrics.json")):
        metrics = json.loads(path.read_text())
        rows += metrics["table"] + metrics.get("references", [])  # the baselines' rows
    return rows


def _markdown(results: dict, commands: dict) -> str:
    lines = ["# Calibration on the paper's sets: the zoo readouts and the nominal EKF, 1000 x 1000 per sigma",
             "", "One command per case (`python benchmarks/calibration_paper_sets.py` runs them):", "",
             "```bash", *(" ".join(c) for c in commands.values()), "```", ""]
    for case, rows in results.items():
        lines += [f"## {case}", "", "| sigma | estimator | " + " | ".join(
            f"{f} {k}" for f in ("R", "p") for k in FIELDS) + " |", "|" + " --- |" * 8]
        for r in sorted(rows, key=lambda r: (r["sigma"], r["method"] != "learned")):
            cells = [f"{r[f'{f} ANEES']:.3f} | {r[f'{f} in band %']:.0f} % | {r[f'{f} in 3 sigma %']:.1f} %"
                     for f in ("R", "p")]
            lines.append(f"| {r['sigma']} | {r['method']} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="the folder the evaluation runs go to")
    p.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    p.add_argument("--covariance-dir", type=Path, default=None,
                   help="score <case>_covariance.pt from this folder instead of the zoo's")
    p.add_argument("--no-ekf", action="store_true", help="the learned observer only")
    p.add_argument("--write", type=Path, default=None, help="also write PATH.md and PATH.json")
    p.add_argument("--gather-only", action="store_true",
                   help="do not evaluate: gather the tables of the runs already in --out")
    args = p.parse_args(argv)
    results, commands = {}, {}
    for case in args.cases:
        commands[case] = _command(case, args.out, args.covariance_dir, not args.no_ekf)
        print(" ".join(commands[case]), flush=True)
        if not args.gather_only:
            subprocess.run(commands[case], check=True, stdout=subprocess.DEVNULL)
        results[case] = _rows(args.out / case)
        for r in results[case]:
            print(case, r["sigma"], r["method"], {k: r[k] for k in r if "ANEES" in k or "band" in k},
                  flush=True)
    text = _markdown(results, commands)
    if args.write is not None:
        args.write.with_suffix(".md").write_text(text)
        args.write.with_suffix(".json").write_text(json.dumps(results, indent=1))
    print(text)


if __name__ == "__main__":
    sys.exit(main())
