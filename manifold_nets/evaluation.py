"""Evaluation on noisy inference sets: the paper's table (per sigma) and figure, for any system.

For one inference set (``N`` sequences of ``T`` steps at noise ``sigma``) :func:`evaluate` runs
an estimator over it (the observer's rollout from the identity, or any
:class:`~manifold_nets.baselines.Estimator`: a baseline, a classical filter) and reports, over
the steps ``k = skip .. T`` (the paper skips the first 10):

* per factor, the mean error of the estimate, ``||pi_f(xhat_k) - pi_f(x_k)||`` (the Frobenius
  norm of the embedding difference; ``||Rhat - R||_F`` for SO(3)), from ``system.metrics``
  (the hook may add named metrics of its own);
* per measured factor, the mean error of the raw measurement (``system.measurement_errors``,
  e.g. ``||R^m - R||_F``) and the reduction ``100 (1 - est / meas)`` %;
* the distance of the estimate from the group, ``group.membership_error`` of the *system's*
  group when a system is given (for SO(3) ``max(||R R^T - I||_F, |det R - 1|)``), mean and
  max: an estimator that works off the group (the unconstrained ablation) shows it here;
* the wall time of the estimation, ``seconds``.

:func:`write_table` writes rows as CSV and Markdown; :func:`plot_errors` draws the paper's
figure (mean error against time per factor, estimate and measurement, and the distance from
the group on a log scale) as a PNG with matplotlib's Agg canvas (no display needed).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch

from groups import LieGroup, Product

from .atomic import atomic_open, write_text_atomic
from .data import TrajectoryDataset
from .observer import ResidualObserver, factor_names

__all__ = [
    "EvalResult",
    "ObserverEstimator",
    "rollout",
    "factor_errors",
    "evaluate",
    "write_table",
    "markdown_table",
    "plot_errors",
]


@dataclass
class EvalResult:
    """Summary row and per-step mean curves of one evaluation."""

    row: dict[str, float]
    #: ``{"<name> est" | "<name> meas" | "membership": (T+1,) mean over sequences}``, NaN where
    #: undefined (the measurement at k = 0).
    curves: dict[str, torch.Tensor] = field(default_factory=dict)
    skip: int = 10
    seconds: float = 0.0


def rollout(
    model: ResidualObserver, data: TrajectoryDataset, batch_size: int = 500
) -> torch.Tensor:
    """The observer's estimates ``(N, T+1, *element_shape)`` on the CPU, in chunks of sequences."""
    if data.measurements.shape[-1] != model.measurement_dim:
        raise ValueError(
            f"the data has measurements of size {data.measurements.shape[-1]}, the observer "
            f"reads {model.measurement_dim}: data from another system?"
        )
    was = model.training
    model.eval()
    out = []
    with torch.inference_mode():
        for s in range(0, len(data), batch_size):
            y = data.measurements[s : s + batch_size]
            u = data.inputs[s : s + batch_size] if model.input_dim else None
            out.append(model(y, u).cpu())
    model.train(was)
    return torch.cat(out)


class ObserverEstimator:
    """The learned observer as an :class:`~manifold_nets.baselines.Estimator`: its rollout from
    the identity over whole datasets, in chunks of ``batch_size`` sequences."""

    def __init__(self, model: ResidualObserver, name: str = "learned", batch_size: int = 500):
        self.model, self.name, self.batch_size = model, name, batch_size
        self.group = model.group

    def estimate(self, data: TrajectoryDataset) -> torch.Tensor:
        return rollout(self.model, data, self.batch_size)


def factor_errors(
    group: LieGroup, estimates: torch.Tensor, states: torch.Tensor
) -> dict[str, torch.Tensor]:
    """``{factor name: ||pi_f(xhat) - pi_f(x)|| (*batch,)}`` (the default of ``System.metrics``)."""
    diff = group.embed(estimates) - group.embed(states.to(estimates))
    if isinstance(group, Product):
        return {
            name: torch.linalg.vector_norm(diff[..., group.embedding_slice(i)], dim=-1)
            for i, name in enumerate(factor_names(group))
        }
    return {"x": torch.linalg.vector_norm(diff, dim=-1)}


def _pad_front(t: torch.Tensor, length: int) -> torch.Tensor:
    """``(N, T)`` aligned with ``k = 1..T`` -> ``(N, T+1)`` with NaN at ``k = 0``."""
    if t.shape[1] == length:
        return t
    return torch.cat([t.new_full((t.shape[0], length - t.shape[1]), math.nan), t], dim=1)


def evaluate(
    method,
    data: TrajectoryDataset,
    system=None,
    *,
    skip: int = 10,
    batch_size: int = 500,
    estimates: torch.Tensor | None = None,
) -> EvalResult:
    """The table row and curves of ``method`` on ``data`` (see the module docstring).

    ``method`` is a :class:`~manifold_nets.observer.ResidualObserver` (rolled out in chunks of
    ``batch_size`` sequences) or any :class:`~manifold_nets.baselines.Estimator`. ``system`` (a
    :class:`manifold_nets.system.System`) supplies ``metrics``, ``measurement_errors`` and the
    group the estimates should lie on; without one the per-factor errors are computed from the
    estimator's group and there is no measurement column. ``estimates`` skips the estimation
    when already computed (``seconds`` is then 0).
    """
    import time

    from .baselines import Estimator

    if isinstance(method, ResidualObserver):
        method = ObserverEstimator(method, batch_size=batch_size)
    if not isinstance(method, Estimator):
        raise TypeError(
            f"evaluate needs a ResidualObserver or an Estimator (name, group, estimate(data)), "
            f"got {type(method).__name__}."
        )
    n, t = len(data), data.length
    if not 0 <= skip < t:
        raise ValueError(f"skip={skip} must be in [0, T) for sequences of T={t} steps.")
    t0 = time.perf_counter()
    est = method.estimate(data) if estimates is None else estimates
    seconds = time.perf_counter() - t0 if estimates is None else 0.0
    expected = (n, t + 1, *method.group.element_shape)
    if tuple(est.shape) != expected:
        raise ValueError(
            f"{method.name}: estimates of shape {tuple(est.shape)}, expected {expected} "
            "(x_0 .. x_T of every sequence)."
        )
    group = system.group if system is not None else method.group
    states = data.states.to(est.dtype)
    if system is not None and callable(getattr(system, "metrics", None)):
        est_err = dict(system.metrics(est, data))
    else:
        est_err = factor_errors(group, est, states)
    meas_err = {}
    if system is not None and callable(getattr(system, "measurement_errors", None)):
        meas_err = dict(system.measurement_errors(data))
    member = group.membership_error(est)  # (N, T+1)

    curves: dict[str, torch.Tensor] = {}
    row: dict[str, float] = {"sigma": float(data.meta.get("sigma", math.nan))}
    for name, err in est_err.items():
        err = _pad_front(err.double(), t + 1)
        curves[f"{name} est"] = err.mean(0)
        row[f"{name} est"] = float(err[:, skip:].mean())
        if name in meas_err:
            m = _pad_front(meas_err[name].double(), t + 1)
            curves[f"{name} meas"] = m.mean(0)
            row[f"{name} meas"] = float(m[:, max(skip, 1) :].mean())
            meas = row[f"{name} meas"]
            row[f"{name} reduction %"] = (
                100.0 * (1.0 - row[f"{name} est"] / meas) if meas > 0 else math.nan
            )
    for name, m in meas_err.items():  # measured quantities that are not estimated factors
        if name not in est_err:
            m = _pad_front(m.double(), t + 1)
            curves[f"{name} meas"] = m.mean(0)
            row[f"{name} meas"] = float(m[:, max(skip, 1) :].mean())
    member = member.double()
    curves["membership"] = member.mean(0)
    row["membership mean"] = float(member[:, skip:].mean())
    row["membership max"] = float(member[:, skip:].max())
    row["sequences"] = n
    row["steps"] = t
    return EvalResult(row, curves, skip, seconds)


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


def plot_errors(result: EvalResult, path: str | Path, title: str | None = None) -> Path:
    """The paper's figure: mean error against the step per factor (estimate and measurement) and
    the distance of the estimate from the group (log scale), from step ``skip`` on."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    names = [k[: -len(" est")] for k in result.curves if k.endswith(" est")]
    panels = names + ["membership"]
    cols = 2 if len(panels) > 1 else 1
    rows = math.ceil(len(panels) / cols)
    fig = Figure(figsize=(5.0 * cols, 3.0 * rows), layout="constrained")
    FigureCanvasAgg(fig)
    start = result.skip
    for i, name in enumerate(panels):
        ax = fig.add_subplot(rows, cols, i + 1)
        if name == "membership":
            c = result.curves["membership"][start:].clamp_min(1e-300)
            k = torch.arange(start, start + len(c))
            ax.semilogy(k, c, color="C2", label="estimate")
            ax.set_title("distance of the estimate from the group")
            ax.set_ylabel("membership error")
        else:
            est = result.curves[f"{name} est"][start:]
            k = torch.arange(start, start + len(est))
            if f"{name} meas" in result.curves:
                ax.plot(
                    k,
                    result.curves[f"{name} meas"][start:],
                    color="C1",
                    lw=0.8,
                    label="measurement",
                )
            ax.plot(k, est, color="C0", lw=1.0, label="estimate")
            ax.set_title(f"error in {name}")
            ax.set_ylabel("mean error")
            ax.set_ylim(bottom=0)
        ax.set_xlabel("step k")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    path = Path(path)
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format=path.suffix.lstrip(".") or "png", dpi=110)
    return path
