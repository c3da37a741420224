"""Tables and figures of results: Markdown/CSV tables, the paper's error figure, comparisons.

* :func:`write_table` / :func:`markdown_table`: rows (dicts) as CSV (full precision) and
  Markdown (rounded for reading);
* :func:`plot_errors`: the paper's figure for one evaluation (mean error against the step per
  factor, estimate and measurement, and the distance from the group on a log scale), each axis
  naming its norm (:func:`metric_label`: ``||R_est - R|| (Frobenius)`` for a rotation matrix);
* :func:`plot_comparison` and :func:`plot_vs_sigma`: several methods against the step, or
  against the noise level.

Figures are PNGs drawn on matplotlib's Agg canvas (no display needed); every file is written
atomically.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch

from .atomic import atomic_open, write_text_atomic

__all__ = [
    "markdown_table", "write_table", "metric_label", "plot_errors", "plot_comparison",
    "plot_vs_sigma",
]

_NOT_METRICS = {"sigma", "method", "sequences", "steps", "seconds"}


def _fmt(v) -> str:
    if isinstance(v, float):
        if math.isnan(v):
            return ""
        if v != 0 and (abs(v) < 1e-3 or abs(v) >= 1e5):
            return f"{v:.1e}"
        return f"{v:.4g}" if abs(v) < 100 else f"{v:.2f}"
    return str(v)


def _columns(rows: Sequence[Mapping]) -> list[str]:
    cols: list[str] = []
    for r in rows:
        cols += [c for c in r if c not in cols]
    return cols


def markdown_table(rows: Sequence[Mapping], columns: Sequence[str] | None = None) -> str:
    """Rows (dicts) as a Markdown table; floats rounded for reading (the CSV keeps them all)."""
    cols = list(columns) if columns is not None else _columns(rows)
    lines = ["| " + " | ".join(cols) + " |", "|" + "|".join("---:" for _ in cols) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(_fmt(r.get(c, "")) for c in cols) + " |")
    return "\n".join(lines) + "\n"


def write_table(
    rows: Sequence[Mapping], stem: str | Path, title: str | None = None
) -> tuple[Path, Path]:
    """Writes ``<stem>.csv`` (full precision) and ``<stem>.md``; returns both paths."""
    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    cols = _columns(rows)
    csv_path, md_path = stem.with_suffix(".csv"), stem.with_suffix(".md")
    with atomic_open(csv_path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols)
        w.writeheader()
        w.writerows(rows)
    md = (f"# {title}\n\n" if title else "") + markdown_table(rows, cols)
    write_text_atomic(md_path, md)
    return csv_path, md_path


def metric_label(name: str, group=None) -> str:
    """The y-axis label of metric ``name``: the norm it is.

    A factor of ``group`` (a name of ``group.factor_names``) is measured by the default
    ``System.metrics``, ``||pi_f(xhat) - pi_f(x)||``: the Frobenius norm of the difference for a
    matrix element (a rotation ``R``), the vector norm for a flat vector element, the norm of
    the embeddings' difference otherwise. Any other name (a system's own metric, named with its
    unit, such as ``attitude_deg``) is shown as it is.
    """
    if group is None or name not in group.factor_names:
        return f"mean {name}"
    factor = group.factor(name)
    if len(factor.element_shape) == 2:
        return f"mean ||{name}_est - {name}|| (Frobenius)"
    if factor.embedding_is_flat:
        return f"mean ||{name}_est - {name}||"
    return f"mean ||pi({name}_est) - pi({name})||"


def plot_errors(result, path: str | Path, title: str | None = None, group=None) -> Path:
    """The paper's figure: mean error against the step per factor (estimate and measurement) and
    the distance of the estimate from the group (log scale), from step ``skip`` on. ``group``
    (the system's) names each factor's norm on its axis (:func:`metric_label`)."""
    names = [k[: -len(" est")] for k in result.curves if k.endswith(" est")]
    fig, axes = _panels(len(names) + 1, height=3.0)
    start = result.skip
    for name, ax in zip(names, axes):
        est = result.curves[f"{name} est"][start:]
        k = torch.arange(start, start + len(est))
        lines = [est]
        if f"{name} meas" in result.curves:
            lines.insert(0, result.curves[f"{name} meas"][start:])
            ax.plot(k, lines[0], color="C1", lw=0.8, label="measurement")
        ax.plot(k, est, color="C0", lw=1.0, label="estimate")
        ax.set_title(f"error in {name}")
        ax.set_ylabel(metric_label(name, group))
        top = float(torch.cat(lines).double().nan_to_num(0.0, 0.0, 0.0).max())
        ax.set_ylim(0, 1.08 * top if top > 0 else None)  # a flat line stays inside the frame
    ax = axes[-1]
    c = result.curves["membership"][start:]
    k = torch.arange(start, start + len(c))
    ax.set_title("distance of the estimate from the group")
    ax.set_ylabel("membership error")
    if bool((c == 0).all()):  # exactly on the group: nothing to draw on a log scale
        ax.plot(k, c, color="C2", label="estimate")
        ax.text(0.5, 0.5, "0 at every step", transform=ax.transAxes, ha="center")
    else:
        ax.semilogy(k, c.clamp_min(1e-300), color="C2", label="estimate")
    for ax in axes:
        ax.set_xlabel("step k")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


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
        if ax.get_lines():  # a metric no method has a value of: an empty panel, no legend
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
    """A figure (Agg canvas, no display) with ``n`` panels in two columns, and the axes; with
    an odd ``n`` the last panel spans the last row, so that no panel is left empty."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    cols = 2 if n > 1 else 1
    nrows = math.ceil(n / cols)
    fig = Figure(figsize=(5.0 * cols, height * nrows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = [fig.add_subplot(nrows, cols, i + 1) for i in range(n - 1)]
    last = (n, nrows * cols) if n % cols else n  # (first, last) cell: the whole last row
    return fig, [*axes, fig.add_subplot(nrows, cols, last)]


def _save(fig, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format=path.suffix.lstrip(".") or "png", dpi=110)
    return path
