"""Methods side by side: gathers evaluated runs into one comparison per noise level.

Every run of the train or evaluate command, whatever its ``method=`` (the learned observer, an
ablation, a baseline, a classical filter), writes the same ``results/metrics.json`` (one row per
sigma) and ``results/curves.json`` (mean error against the step). This command reads any number
of run folders (or folders holding many, such as a multirun) and writes into ``--out``:

* ``comparison.csv`` / ``comparison.md``: per sigma, one row per method (a baseline by its
  method, ``ekf``; a trained observer by its experiment, ``paper_cpu``, where its own table says
  ``learned``; mean errors of every metric over the steps ``k >= skip``, the distance from the group, wall time per
  sequence-step), and rows ``<method> / <reference>`` with the ratio of each trained observer's
  errors to the reference method's (``--reference``, default ``ekf``; below 1: better);
* ``comparison_vs_sigma.png``: each metric against sigma, one line per method (log scale);
* ``comparison_sigma<s>.png``: each metric against the step at that sigma, one line per method;
* with ``--horizon 100 1000``: ``horizon.csv`` / ``horizon.md``, each method's error at those
  steps (mean over +-10 steps) and the ratio of the last to the first: whether an observer's
  error grows past the length it was trained on.

::

    python -m manifold_nets.cli.train -m experiment=default method=raw,dead_reckoning,ekf,untrained
    python -m manifold_nets.cli.train experiment=default
    python -m manifold_nets.cli.compare multirun/default/<id> outputs/default/<id> --out results/cmp

Runs must have been evaluated on the same inference sets (same ``eval`` settings): the command
checks that every row of one sigma has the same number of sequences and steps.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from manifold_nets.reporting import markdown_table, plot_comparison, plot_vs_sigma, write_table
from manifold_nets.results import collect_runs, comparison_rows, horizon_rows, step_curves

__all__ = ["main"]


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m manifold_nets.cli.compare",
        description="Gather evaluated runs (any method=) into one comparison per sigma.",
    )
    ap.add_argument("folders", nargs="+", help="run folders, or folders holding several runs")
    ap.add_argument("--out", required=True, help="folder for comparison.{csv,md} and the figures")
    ap.add_argument("--reference", default="ekf", help="method the trained observers are divided by")
    ap.add_argument("--title", default=None, help="title of the table and figures")
    ap.add_argument("--skip", type=int, default=None, help="first step drawn in the step figures")
    ap.add_argument(
        "--horizon", type=int, nargs="+", default=None, metavar="STEP",
        help="also tabulate each method's error at these steps (e.g. 100 1000) in horizon.md",
    )
    args = ap.parse_args(argv)
    try:
        runs = collect_runs(args.folders)
        rows = comparison_rows(runs, args.reference)
        horizon = horizon_rows(runs, args.horizon) if args.horizon else None
    except (FileNotFoundError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    out = Path(args.out)
    title = args.title or "comparison"
    write_table(rows, out / "comparison", title=title)
    plot_vs_sigma(rows, out / "comparison_vs_sigma.png", title=title)
    skip = args.skip
    for sigma in sorted({r["sigma"] for r in rows}):
        curves, default_skip = step_curves(runs, sigma)
        if curves:
            plot_comparison(
                curves,
                default_skip if skip is None else skip,
                out / f"comparison_sigma{sigma:g}.png",
                title=f"{title}: sigma = {sigma:g}",
            )
    if horizon:
        write_table(horizon, out / "horizon", title=f"{title}: error at steps {args.horizon}")
        print(markdown_table(horizon))
    print(markdown_table(rows))
    print(f"wrote {out / 'comparison.csv'}, {out / 'comparison.md'} and figures in {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
