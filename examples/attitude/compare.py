"""The learned observer next to classical estimators, on the same inference sets, for any system.

    python -m manifold_nets_examples.attitude.compare outputs/attitude/<run id>  # the AHRS
    python -m manifold_nets_examples.planar.compare outputs/planar/<run id>      # the vehicle
    python -m manifold_nets_examples.attitude.compare <run> --sigmas 0.3 --length 500 --tag long

A training run folder (``python -m manifold_nets.cli.train``) holds its resolved ``config.yaml`` and
``checkpoints/best.pt``. :func:`compare_run` rebuilds the system and the observer from them,
loads (or generates) the run's inference sets (``eval.*`` of the config; overridable), and runs
on each, over the same sequences:

* ``learned``: the observer's rollout from the identity;
* the system's estimators (for the AHRS and the vehicle: the error-state EKF with the true model
  and noise level, and dead reckoning of the biased readings);
* ``measurement``: the raw baseline, ``system.measurement_errors`` (TRIAD; the fix and the
  course over ground).

It writes, next to the run's own table, ``results/compare.csv`` and ``compare.md``: the mean of
every metric over the steps ``k >= eval.skip_steps`` per method, and a row ``learned / ekf`` with
the ratio of the learned observer's error to the EKF's (below 1: the observer is better); and
``results/compare_sigma<s>.png``, the mean error against the step per metric and method
(``compare_<tag>...`` with ``--tag``, so that other inference sets do not overwrite them).

Only library pieces of ``manifold_nets`` are used (``load_observer``, ``inference_data``,
``rollout``), no command; the estimators follow
``manifold_nets.baselines.Estimator``.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from omegaconf import OmegaConf

from manifold_nets.datasets import inference_data
from manifold_nets.evaluation import rollout
from manifold_nets.loading import load_observer
from manifold_nets.reporting import plot_comparison, write_table
from manifold_nets.threads import use_threads

# the shipped systems, registered so that their run folders load (load_observer looks the
# config's system up among the imported System subclasses)
from ..planar import system as _planar  # noqa: F401
from ..rigid_body import system as _rigid_body  # noqa: F401
from . import system as _attitude  # noqa: F401

__all__ = ["compare_run", "load_run", "main"]

#: ``estimators(system, sigma) -> [Estimator, ...]`` (each with ``name`` and ``estimate(data)``).
EstimatorFactory = Callable[[object, float], Sequence[object]]


def load_run(run_dir: str | Path):
    """``(config, system, observer)`` of a training run folder; the observer holds the best
    validation weights (its signature is checked against the config's model).

    Through :func:`manifold_nets.load_observer`: the system is one of the shipped ones (imported
    above) or one the caller imported, never a class the folder's config would have imported."""
    run_dir = Path(run_dir)
    if not (run_dir / "config.yaml").is_file():
        raise FileNotFoundError(
            f"{run_dir} has no config.yaml: not a run folder of the train command."
        )
    model, system, cfg = load_observer(run_dir)
    return cfg, system, model


def _mean_curve(err: torch.Tensor, length: int) -> torch.Tensor:
    """``(N, T')`` errors to the ``(T+1,)`` mean over sequences, NaN where undefined (k = 0)."""
    err = err.double()
    if err.shape[1] < length:
        pad = err.new_full((err.shape[0], length - err.shape[1]), math.nan)
        err = torch.cat((pad, err), dim=1)
    return err.mean(0)


def compare_run(
    run_dir: str | Path,
    estimators: EstimatorFactory,
    sigmas: Sequence[float] | None = None,
    num_sequences: int | None = None,
    length: int | None = None,
    plots: bool = True,
    tag: str = "",
) -> list[dict]:
    """Runs the comparison (module docstring) and writes it into ``<run_dir>/results``.

    ``sigmas``, ``num_sequences``, ``length`` override the run's ``eval`` settings (the sets are
    cached like the run's own). ``tag`` names the files ``compare_<tag>``. Returns the rows.
    """
    cfg, system, model = load_run(run_dir)
    if sigmas is not None:
        cfg.eval.sigmas = [float(s) for s in sigmas]
    if num_sequences is not None:
        cfg.eval.num_sequences = int(num_sequences)
    if length is not None:
        cfg.eval.length = int(length)
    levels = list(cfg.eval.sigmas)
    dataset = OmegaConf.to_object(cfg.dataset)
    skip = int(cfg.eval.skip_steps)
    rows: list[dict] = []
    out = Path(run_dir) / "results"
    stem = f"compare_{tag}" if tag else "compare"
    for sigma in levels:
        data = inference_data(
            system, dataset, cfg.eval, float(sigma), cache_dir=Path(dataset.cache_dir).absolute()
        )
        t = data.length
        curves: dict[str, dict[str, torch.Tensor]] = {}
        methods = [("learned", rollout(model, data).double())]
        for est in estimators(system, float(sigma)):
            methods.append((est.name, est.estimate(data)))
        for name, est in methods:
            system.group.check_member(est.to(torch.float64), atol=1e-9)
            curves[name] = {k: _mean_curve(v, t + 1) for k, v in system.metrics(est, data).items()}
        curves["measurement"] = {
            k: _mean_curve(v, t + 1) for k, v in system.measurement_errors(data).items()
        }
        block = []
        for name, c in curves.items():
            row = {"sigma": float(sigma), "method": name}
            row.update({k: float(v[max(skip, 1):].nanmean()) for k, v in c.items()})
            block.append(row)
        by = {r["method"]: r for r in block}
        if "ekf" in by:
            ratio = {"sigma": float(sigma), "method": "learned / ekf"}
            for k, v in by["learned"].items():
                if k not in ("sigma", "method") and by["ekf"].get(k):
                    ratio[k] = v / by["ekf"][k]
            block.append(ratio)
        rows += block
        if plots:
            plot_comparison(curves, skip, out / f"{stem}_sigma{float(sigma):g}.png",
                            title=f"{cfg.name}: sigma = {float(sigma):g}, {len(data)} x {t} steps")
    title = f"{cfg.name}: learned observer and baselines, {len(data)} x {data.length} steps"
    write_table(rows, out / stem, title=title)
    return rows


def main(estimators: EstimatorFactory, argv: Sequence[str] | None = None) -> list[dict]:
    """The command line of :func:`compare_run` (``run_dir [--sigmas ...] [--num-sequences N]
    [--length T] [--tag NAME] [--no-plots]``); prints the Markdown table."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dir", help="a run folder of the train command")
    p.add_argument("--sigmas", type=float, nargs="+", default=None)
    p.add_argument("--num-sequences", type=int, default=None)
    p.add_argument("--length", type=int, default=None)
    p.add_argument("--tag", default="", help="write compare_<tag>.* instead of compare.*")
    p.add_argument("--no-plots", action="store_true")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads (default: one, or OMP_NUM_THREADS)")
    a = p.parse_args(argv)
    use_threads(a.threads)
    rows = compare_run(a.run_dir, estimators, a.sigmas, a.num_sequences, a.length,
                       plots=not a.no_plots, tag=a.tag)
    stem = f"compare_{a.tag}" if a.tag else "compare"
    print((Path(a.run_dir) / "results" / f"{stem}.md").read_text())
    return rows


def attitude_estimators(system, sigma: float) -> list:
    """The AHRS's classical estimators: its EKF and dead reckoning of the biased gyro."""
    from manifold_nets.baselines import DeadReckoning

    from .filters import AttitudeEKF

    return [AttitudeEKF(system, sigma), DeadReckoning(system)]


if __name__ == "__main__":
    main(attitude_estimators)
