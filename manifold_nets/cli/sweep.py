"""Gathers the results of a hydra multirun of the train command into one table.

::

    python -m manifold_nets.cli.train -m experiment=default seed=0,1,2 'eval.sigmas=[0.1],[0.3]'
    python -m manifold_nets.cli.sweep multirun/default/<run id>

Every job folder under the given folder that holds ``results/metrics.json`` contributes its
table rows (one per sigma), prefixed by the job's command-line overrides (from
``.hydra/overrides.yaml``), its seed and its folder. Written next to the jobs:

* ``sweep.csv`` / ``sweep.md``: every row of every job;
* ``sweep_summary.csv`` / ``sweep_summary.md``: when some jobs differ only in their seed, the
  mean and standard deviation over the seeds of every metric, per sigma and remaining
  overrides.

The Markdown of both is printed too.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from manifold_nets.reporting import markdown_table, write_table
from manifold_nets.results import collect, summarize

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m manifold_nets.cli.sweep",
        description="Gather a multirun's results into one table.",
    )
    ap.add_argument("folder", help="the multirun folder (multirun/<name>/<run id>)")
    args = ap.parse_args(argv)
    try:
        rows = collect(args.folder)
    except FileNotFoundError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    root = Path(args.folder)
    written = write_table(rows, root / "sweep", title=f"sweep {root}")
    print(markdown_table(rows))
    if len({r.get("seed") for r in rows}) > 1:
        summary = summarize(rows)
        title = f"sweep {root}: mean and std over seeds"
        written += write_table(summary, root / "sweep_summary", title=title)
        print(markdown_table(summary))
    print("wrote " + ", ".join(map(str, written)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
