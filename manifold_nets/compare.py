"""Methods side by side: gathers evaluated runs into one comparison per noise level.

Every ``python -m manifold_nets.train`` run, whatever its ``method=`` (the learned observer, an
ablation, a baseline, a classical filter), writes the same ``results/metrics.json`` (one row per
sigma) and ``results/curves.json`` (mean error against the step). This command reads any number
of run folders (or folders holding many, such as a multirun) and writes into ``--out``:

* ``comparison.csv`` / ``comparison.md``: per sigma, one row per method (mean errors of every
  metric over the steps ``k >= skip``, the distance from the group, wall time per
  sequence-step), and rows ``<method> / <reference>`` with the ratio of each trained observer's
  errors to the reference method's (``--reference``, default ``ekf``; below 1: better);
* ``comparison_vs_sigma.png``: each metric against sigma, one line per method (log scale);
* ``comparison_sigma<s>.png``: each metric against the step at that sigma, one line per method.

::

    python -m manifold_nets.train -m experiment=default method=raw,dead_reckoning,ekf,untrained
    python -m manifold_nets.train experiment=default
    python -m manifold_nets.compare multirun/default/<id> outputs/default/<id> --out results/cmp

Runs must have been evaluated on the same inference sets (same ``eval`` settings): the command
checks that every row of one sigma has the same number of sequences and steps.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path

import torch

from .evaluation import markdown_table, write_table

__all__ = ["collect_runs", "comparison_rows", "main", "plot_comparison", "plot_vs_sigma"]

_NOT_METRICS = {"sigma", "method", "sequences", "steps", "seconds"}


def collect_runs(paths: Sequence[str | Path]) -> list[dict]:
    """``[{"dir", "metrics", "curves", "label"}]`` for every ``results/metrics.json`` under
    ``paths``; the label is the run's method, made distinct where several share one."""
    runs = []
    for root in map(Path, paths):
        if not root.exists():
            raise FileNotFoundError(f"{root} does not exist; pass run folders or multirun folders.")
        found = sorted(root.rglob("results/metrics.json"), key=str)
        if (root / "results" / "metrics.json").is_file():
            found = [root / "results" / "metrics.json"]
        if not found:
            raise FileNotFoundError(
                f"no results/metrics.json under {root}: did the run finish? (it is written last)"
            )
        for path in found:
            metrics = json.loads(path.read_text())
            cpath = path.with_name("curves.json")
            curves = json.loads(cpath.read_text()) if cpath.is_file() else {}
            runs.append({"dir": str(path.parent.parent), "metrics": metrics, "curves": curves})
    return _name_runs(runs)


def _label(run: dict) -> str:
    return run.get("label") or str(run["metrics"].get("method") or "learned")


def _name_runs(runs: list[dict]) -> list[dict]:
    """Gives each run a distinct ``label``: its method, with `` seed <s>`` added where runs of
    one method differ in seed (a seed sweep), and `` #<i>`` where even that repeats."""
    base = [str(r["metrics"].get("method") or "learned") for r in runs]
    labels = list(base)
    for i, run in enumerate(runs):
        if base.count(base[i]) > 1 and "seed" in run["metrics"]:
            labels[i] = f"{base[i]} seed {run['metrics']['seed']}"
    seeded = list(labels)
    for i, label in enumerate(seeded):
        if seeded.count(label) > 1:
            labels[i] = f"{label} #{seeded[: i + 1].count(label)}"
    for run, label in zip(runs, labels):
        run["label"] = label
    return runs


def _metric_names(rows: Sequence[dict]) -> list[str]:
    names: list[str] = []
    for r in rows:
        for k in r:
            if k.endswith(" est") and k[:-4] not in names:
                names.append(k[:-4])
    return names


def comparison_rows(runs: Sequence[dict], reference: str = "ekf") -> list[dict]:
    """The comparison table (module docstring), sorted by sigma, methods in the order given."""
    by_sigma: dict[float, list[tuple[dict, dict]]] = {}
    for run in runs:
        for row in run["metrics"].get("table", []):
            by_sigma.setdefault(float(row["sigma"]), []).append((run, row))
    out: list[dict] = []
    for sigma in sorted(by_sigma):
        pairs = by_sigma[sigma]
        sizes = {(r.get("sequences"), r.get("steps")) for _, r in pairs}
        if len(sizes) > 1:
            raise ValueError(
                f"sigma {sigma:g}: the runs were evaluated on sets of different sizes "
                f"{sorted(sizes, key=str)} (sequences, steps); evaluate them with the same eval.*."
            )
        names = _metric_names([r for _, r in pairs])
        block = []
        for run, r in pairs:
            row = {"sigma": sigma, "method": _label(run)}
            row.update({n: r.get(f"{n} est", math.nan) for n in names})
            row["membership mean"] = r.get("membership mean", math.nan)
            row["membership max"] = r.get("membership max", math.nan)
            if "us/step" in r:
                row["us/step"] = r["us/step"]
            row["trained"] = "checkpoint" in run["metrics"]
            block.append(row)
        if not any(b["method"] == "raw" for b in block):  # the raw measurement as a reference row
            r0 = pairs[0][1]
            meas = {n: r0[f"{n} meas"] for n in names if f"{n} meas" in r0}
            if meas:
                block.insert(0, {"sigma": sigma, "method": "measurement", **meas, "trained": False})
        ref = next((b for b in block if b["method"] == reference), None)
        ratios = []
        if ref is not None:
            for b in block:
                if b["trained"] and b is not ref:
                    q = {"sigma": sigma, "method": f"{b['method']} / {reference}"}
                    for n in names:
                        if isinstance(ref.get(n), float) and ref[n] > 0:
                            q[n] = b[n] / ref[n]
                    ratios.append(q)
        for b in block:
            b.pop("trained")
        out += block + ratios
    return out


def plot_vs_sigma(rows: Sequence[dict], path: str | Path, title: str | None = None) -> Path:
    """Each metric against sigma, one line per method (log scale); ratio rows are left out."""
    rows = [r for r in rows if " / " not in r["method"]]
    metrics = [c for c in _columns(rows) if c not in _NOT_METRICS and c != "us/step"]
    methods = list(dict.fromkeys(r["method"] for r in rows))
    fig, axes = _panels(len(metrics), height=3.2)
    for metric, ax in zip(metrics, axes):
        for j, method in enumerate(methods):
            pts = [
                (r["sigma"], r[metric])
                for r in rows
                if r["method"] == method
                and isinstance(r.get(metric), float)
                and math.isfinite(r[metric])
                and r[metric] > 0
            ]
            if pts:
                xs, ys = zip(*sorted(pts))
                ax.plot(xs, ys, marker="o", ms=3, lw=1.2, color=f"C{j % 10}", label=method)
        ax.set_yscale("log")
        ax.set_title(metric)
        ax.set_xlabel("sigma")
        ax.set_ylabel("mean error" if not metric.startswith("membership") else "distance")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def plot_comparison(
    curves: dict[str, dict[str, Sequence[float]]],
    skip: int,
    path: str | Path,
    title: str | None = None,
) -> Path:
    """Mean error against the step, one panel per metric, one line per method (PNG, Agg).

    ``curves`` is ``{method: {metric: (T+1,) mean over sequences}}`` (NaN where undefined);
    a method far above the others (4x the median of the panel) gets the axis clipped so the
    others stay readable.
    """
    metrics: list[str] = []
    for c in curves.values():
        metrics += [m for m in c if m not in metrics]
    fig, axes = _panels(len(metrics), height=3.0)
    for metric, ax in zip(metrics, axes):
        tops = []
        for j, (method, c) in enumerate(curves.items()):
            if metric in c:
                v = c[metric]
                if not isinstance(v, torch.Tensor):
                    v = torch.tensor([math.nan if a is None else a for a in v])
                y = v.double()[skip:]
                ax.plot(
                    torch.arange(skip, skip + len(y)), y, lw=1.0, color=f"C{j % 10}", label=method
                )
                tops.append(float(y.nan_to_num(0.0).max()))
        tops.sort()
        mid = tops[len(tops) // 2] if tops else 0.0
        if metric == "membership":
            ax.set_yscale("log")
            ax.set_title("distance from the group")
            ax.set_ylabel("distance")
        elif mid > 0 and tops[-1] > 4 * mid:  # one method far off: keep the others readable
            ax.set_ylim(0, 2 * mid)
            ax.set_title(f"{metric} (axis clipped)")
        else:
            ax.set_ylim(bottom=0)
            ax.set_title(metric)
        ax.set_xlabel("step k")
        if metric != "membership":
            ax.set_ylabel("mean error")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def _panels(n: int, height: float):
    """A figure (Agg canvas, no display) with ``n`` panels in two columns, and the axes."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    cols = 2 if n > 1 else 1
    nrows = math.ceil(n / cols)
    fig = Figure(figsize=(5.0 * cols, height * nrows), layout="constrained")
    FigureCanvasAgg(fig)
    return fig, [fig.add_subplot(nrows, cols, i + 1) for i in range(n)]


def _columns(rows: Sequence[dict]) -> list[str]:
    cols: list[str] = []
    for r in rows:
        cols += [c for c in r if c not in cols]
    return cols


def _save(fig, path: str | Path) -> Path:
    from .atomic import atomic_open

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=110)
    return path


def _step_curves(runs: Sequence[dict], sigma: float) -> tuple[dict, int]:
    """``{method: {metric: curve}}`` of the estimates at ``sigma`` and the runs' skip."""
    out: dict[str, dict] = {}
    skip = 10
    for run in runs:
        c = run["curves"].get(f"{sigma:g}")
        if not c:
            continue
        out[_label(run)] = {
            k.removesuffix(" est"): v
            for k, v in c.items()
            if not k.endswith(" meas")
        }
        skip = int(run["metrics"].get("skip_steps", skip))
    return out, skip


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m manifold_nets.compare",
        description="Gather evaluated runs (any method=) into one comparison per sigma.",
    )
    ap.add_argument("folders", nargs="+", help="run folders, or folders holding several runs")
    ap.add_argument("--out", required=True, help="folder for comparison.{csv,md} and the figures")
    ap.add_argument("--reference", default="ekf", help="method the trained observers are divided by")
    ap.add_argument("--title", default=None, help="title of the table and figures")
    ap.add_argument("--skip", type=int, default=None, help="first step drawn in the step figures")
    args = ap.parse_args(argv)
    try:
        runs = collect_runs(args.folders)
        rows = comparison_rows(runs, args.reference)
    except (FileNotFoundError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    out = Path(args.out)
    title = args.title or "comparison"
    write_table(rows, out / "comparison", title=title)
    plot_vs_sigma(rows, out / "comparison_vs_sigma.png", title=title)
    skip = args.skip
    for sigma in sorted({r["sigma"] for r in rows}):
        curves, default_skip = _step_curves(runs, sigma)
        if curves:
            plot_comparison(
                curves,
                default_skip if skip is None else skip,
                out / f"comparison_sigma{sigma:g}.png",
                title=f"{title}: sigma = {sigma:g}",
            )
    print(markdown_table(rows))
    print(f"wrote {out / 'comparison.csv'}, {out / 'comparison.md'} and figures in {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
