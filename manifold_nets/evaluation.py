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
* the wall time of the estimation, ``seconds``;
* with ``calibration=True``, for an estimator that also gives covariances
  (``estimate_with_covariance(data) -> (estimates, covariances)``: the project's EKF, a learned
  observer with a covariance readout), per factor the ANEES and the share of errors inside the
  3-sigma ellipsoid (:mod:`manifold_nets.calibration`; steps without a finite covariance, such as
  a filter's before its start, left out).

:func:`write_table` writes rows as CSV and Markdown; :func:`plot_errors` draws the paper's
figure (mean error against time per factor, estimate and measurement, and the distance from
the group on a log scale) as a PNG with matplotlib's Agg canvas (no display needed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from .data import TrajectoryDataset
from .losses import factor_errors
from .observer import ResidualObserver
from .progress import progress_bar

__all__ = [
    "EstimatesNotFinite",
    "EvalResult",
    "ObserverEstimator",
    "CalibratedEstimator",
    "rollout",
    "evaluate",
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
    model: ResidualObserver,
    data: TrajectoryDataset,
    batch_size: int = 500,
    show_progress: bool = False,
) -> torch.Tensor:
    """The observer's estimates ``(N, T+1, *element_shape)`` on the CPU, in chunks of sequences.

    ``show_progress``: a bar of the sequences done (on a terminal, when it takes over a second).
    """
    if data.measurements.shape[-1] != model.measurement_dim:
        raise ValueError(
            f"the data has measurements of size {data.measurements.shape[-1]}, the observer "
            f"reads {model.measurement_dim}: data from another system?"
        )
    was = model.training
    model.eval()
    out = []
    bar = progress_bar(
        len(data), desc="evaluation", unit="seq", enabled=show_progress, delay=1.0
    )
    with torch.inference_mode():
        for s in range(0, len(data), batch_size):
            y = data.measurements[s : s + batch_size]
            u = data.inputs[s : s + batch_size] if model.input_dim else None
            out.append(model(y, u).cpu())
            bar.update(len(y))
    bar.close()
    model.train(was)
    return torch.cat(out)


class ObserverEstimator:
    """The learned observer as an :class:`~manifold_nets.baselines.Estimator`: its rollout from
    the identity over whole datasets, in chunks of ``batch_size`` sequences (``progress``: a bar
    of the sequences done, on a terminal, for long evaluations)."""

    def __init__(
        self,
        model: ResidualObserver,
        name: str = "learned",
        batch_size: int = 500,
        progress: bool = True,
    ):
        self.model, self.name, self.batch_size = model, name, batch_size
        self.group = model.group
        self.progress = progress

    def estimate(self, data: TrajectoryDataset) -> torch.Tensor:
        return rollout(self.model, data, self.batch_size, show_progress=self.progress)


class CalibratedEstimator(ObserverEstimator):
    """A learned observer with a covariance readout
    (:class:`~manifold_nets.observer.CalibratedObserver`): the observer's estimates, and with
    :meth:`estimate_with_covariance` its covariances too."""

    def __init__(self, calibrated, name: str = "learned", batch_size: int = 500,
                 progress: bool = True):
        super().__init__(calibrated.observer, name, batch_size, progress)
        self.calibrated = calibrated

    @torch.no_grad()
    def estimate_with_covariance(self, data: TrajectoryDataset):
        was = self.calibrated.training
        self.calibrated.eval()
        est, cov = [], []
        try:
            for s in range(0, len(data), self.batch_size):
                part = data[torch.arange(s, min(len(data), s + self.batch_size))]
                inputs = part.inputs if part.inputs.shape[-1] else None
                e, c = self.calibrated(part.measurements, inputs)
                est.append(e)
                cov.append(c)
        finally:
            self.calibrated.train(was)
        return torch.cat(est), torch.cat(cov)


def _calibration_columns(group, est, cov, states, skip: int) -> dict[str, float]:
    """Per factor: ``<f> ANEES``, ``<f> in band %`` (the steps whose ANEES over the sequences is
    inside its chi-square 95 % band for that many sequences) and ``<f> in 3 sigma %`` over the
    steps ``>= skip`` whose covariance is finite."""
    from .calibration import calibration, tangent_errors

    est, cov, states = est[:, skip:], cov[:, skip:].double(), states[:, skip:]
    known = torch.isfinite(cov).flatten(2).all(-1)
    safe = torch.where(known[..., None, None], cov, torch.eye(cov.shape[-1], dtype=cov.dtype))
    xi = tangent_errors(group, est, states)
    out = {}
    for name, c in calibration(group, xi, safe, known).items():
        out[f"{name} ANEES"] = c.anees
        out[f"{name} in band %"] = 100.0 * c.in_band
        out[f"{name} in 3 sigma %"] = 100.0 * c.shares[3]
    return out


def _estimate(method, data, estimates, calibration: bool):
    """``(estimates, covariances or None, seconds)``: given estimates (0 s), or the method's,
    with its covariances when ``calibration`` and it gives them."""
    import time

    if estimates is not None:
        return estimates, None, 0.0
    t0 = time.perf_counter()
    if calibration and callable(getattr(method, "estimate_with_covariance", None)):
        est, cov = method.estimate_with_covariance(data)
    else:
        est, cov = method.estimate(data), None
    return est, cov, time.perf_counter() - t0


def _pad_front(t: torch.Tensor, length: int) -> torch.Tensor:
    """``(N, T)`` aligned with ``k = 1..T`` -> ``(N, T+1)`` with NaN at ``k = 0``."""
    if t.shape[1] == length:
        return t
    return torch.cat([t.new_full((t.shape[0], length - t.shape[1]), math.nan), t], dim=1)


class EstimatesNotFinite(FloatingPointError):
    """An estimator returned NaN or Inf estimates (NaN weights, a diverged filter)."""


def _check_finite(name: str, est: torch.Tensor) -> None:
    """Raises :class:`EstimatesNotFinite` naming the method and the first bad sequence."""
    finite = torch.isfinite(est).reshape(*est.shape[:2], -1).all(-1)  # (N, T+1)
    if bool(finite.all()):
        return
    bad = ~finite.all(1)
    seq = int(bad.nonzero()[0, 0])
    step = int((~finite[seq]).nonzero()[0, 0])
    raise EstimatesNotFinite(
        f"{name}: the estimates are not finite (NaN/Inf) in {int(bad.sum())} of {len(bad)} "
        f"sequences, the first in sequence {seq} from step {step} on; no metric is computed from "
        "them. A checkpoint with NaN weights (a diverged training), or an estimator that "
        "diverged: check the method's weights or parameters."
    )


def evaluate(
    method,
    data: TrajectoryDataset,
    system=None,
    *,
    skip: int = 10,
    batch_size: int = 500,
    estimates: torch.Tensor | None = None,
    calibration: bool = False,
) -> EvalResult:
    """The table row and curves of ``method`` on ``data`` (see the module docstring).

    ``method`` is a :class:`~manifold_nets.observer.ResidualObserver` (rolled out in chunks of
    ``batch_size`` sequences) or any :class:`~manifold_nets.baselines.Estimator`. ``system`` (a
    :class:`manifold_nets.system.System`) supplies ``metrics``, ``measurement_errors`` and the
    group the estimates should lie on; without one the per-factor errors are computed from the
    estimator's group and there is no measurement column. ``estimates`` skips the estimation
    when already computed (``seconds`` is then 0). NaN/Inf estimates: :class:`EstimatesNotFinite`.
    ``calibration``: also score the covariances of an estimator that gives them.
    """
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
    est, cov, seconds = _estimate(method, data, estimates, calibration)
    expected = (n, t + 1, *method.group.element_shape)
    if tuple(est.shape) != expected:
        raise ValueError(
            f"{method.name}: estimates of shape {tuple(est.shape)}, expected {expected} "
            "(x_0 .. x_T of every sequence)."
        )
    _check_finite(method.name, est)
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
    if cov is not None:
        row.update(_calibration_columns(group, est, cov, states, skip))
    row["sequences"] = n
    row["steps"] = t
    return EvalResult(row, curves, skip, seconds)
