"""Gathers the results of a hydra multirun of ``manifold_nets.train`` into one table.

::

    python -m manifold_nets.train -m experiment=default seed=0,1,2 eval.sigma=0.1,0.3
    python -m manifold_nets.sweep multirun/default/<run id>

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
import json
import math
import statistics
import sys
from pathlib import Path

from .evaluation import markdown_table, write_table

__all__ = ["collect", "summarize", "main"]


def _overrides(job: Path) -> dict[str, str]:
    path = job / ".hydra" / "overrides.yaml"
    if not path.is_file():
        return {}
    from omegaconf import OmegaConf

    out = {}
    for item in OmegaConf.to_container(OmegaConf.load(path)) or []:
        key, _, value = str(item).partition("=")
        out[key.lstrip("+~")] = value
    return out


def collect(root: str | Path) -> list[dict]:
    """One row per (job, sigma) for every ``results/metrics.json`` under ``root``."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(
            f"{root} is not a folder; pass a multirun folder (multirun/<name>/<id>)."
        )
    rows = []
    for metrics_path in sorted(root.rglob("results/metrics.json"), key=lambda p: str(p)):
        job = metrics_path.parent.parent
        metrics = json.loads(metrics_path.read_text())
        over = {k: v for k, v in _overrides(job).items() if k != "seed"}
        base = {"job": str(job.relative_to(root)) or ".", **over, "seed": metrics.get("seed")}
        for key in ("best_epoch", "best_val_loss", "test_loss"):
            if metrics.get(key) is not None:
                base[key] = metrics[key]
        for r in metrics.get("table", []):
            rows.append({**base, **r})
    if not rows:
        raise FileNotFoundError(
            f"no results/metrics.json under {root}: did the jobs finish? (a job writes it last)"
        )
    return rows


_KEYS = ("job", "seed", "best_epoch", "best_val_loss", "test_loss", "sequences", "steps", "seconds")


def summarize(rows: list[dict]) -> list[dict]:
    """Mean and std over seeds of every numeric metric, grouped by everything else that is set."""
    metric_cols = [
        c
        for c in rows[0]
        if c not in _KEYS and isinstance(rows[0][c], (int, float)) and c != "sigma"
    ]
    group_cols = [
        c for c in {c for r in rows for c in r} if c not in metric_cols and c not in _KEYS
    ]
    group_cols.sort(key=lambda c: (c != "sigma", c))
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault(tuple(str(r.get(c, "")) for c in group_cols), []).append(r)
    out = []
    for members in groups.values():
        row = {c: members[0].get(c, "") for c in group_cols}
        row["seeds"] = len(members)
        for c in metric_cols:
            vals = [
                float(m[c])
                for m in members
                if isinstance(m.get(c), (int, float)) and not math.isnan(float(m[c]))
            ]
            if vals:
                row[f"{c} mean"] = statistics.fmean(vals)
                row[f"{c} std"] = statistics.stdev(vals) if len(vals) > 1 else 0.0
        out.append(row)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m manifold_nets.sweep",
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
    write_table(rows, root / "sweep", title=f"sweep {root}")
    print(markdown_table(rows))
    if len({r.get("seed") for r in rows}) > 1:
        summary = summarize(rows)
        write_table(summary, root / "sweep_summary", title=f"sweep {root}: mean and std over seeds")
        print(markdown_table(summary))
    print(f"wrote {root / 'sweep.csv'} and {root / 'sweep.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
