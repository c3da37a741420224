"""``python -m manifold_nets.cli.evaluate``: a trained observer or a baseline on the inference sets.

The evaluation task of every run: per sigma of ``eval.sigmas`` the inference set (generated or
read from the cache), the estimates of the method, the paper's metrics, one table row and one
figure. Written into ``<run folder>/results/``: ``table.csv``, ``table.md``, ``metrics.json``,
``curves.json`` and ``errors_sigma<s>.png`` per sigma::

    python -m manifold_nets.cli.evaluate experiment=default eval.checkpoint=outputs/default/<id>
    python -m manifold_nets.cli.evaluate experiment=paper_cpu method=ekf
    python -m manifold_nets.cli.evaluate -m experiment=default eval.checkpoint=<run> \
        'eval.sigmas=[0.1],[0.2],[0.3]'

The train command calls :func:`evaluate` after training; this command evaluates without
training (``method=learned`` then needs ``eval.checkpoint``).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from manifold_nets.atomic import write_text_atomic
from manifold_nets.baselines import make_estimator
from manifold_nets.builders import build_estimator_factory
from manifold_nets.checkpoint import load_weights
from manifold_nets.datasets import inference_data
from manifold_nets.evaluation import ObserverEstimator, evaluate as evaluate_estimator
from manifold_nets.observer import ResidualObserver
from manifold_nets.reporting import plot_errors, write_table

from . import CONFIG_PATH

__all__ = ["absolute", "check_sigmas", "evaluate", "json_safe", "main", "to_json"]

log = logging.getLogger(__name__)


def absolute(path: str) -> str:
    """``path`` from the folder the command was launched in (hydra may have moved the cwd); a zoo
    entry (``zoo:...``) as it is."""
    if str(path).startswith("zoo:"):
        return str(path)
    try:
        from hydra.utils import to_absolute_path

        return to_absolute_path(path)
    except ValueError:  # hydra not initialised (tests, plain Python)
        return str(Path(path).absolute())


def json_safe(value: Any) -> Any:
    """``value`` with every float that is not finite (an undefined metric: the measurement
    error at k = 0, a reduction against a measurement error of 0) replaced by ``None``."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


def to_json(value: Any, **kwargs) -> str:
    """Valid JSON always (``allow_nan=False``): undefined values are written as ``null``."""
    return json.dumps(json_safe(value), allow_nan=False, default=str, **kwargs)


def check_sigmas(sigmas: Sequence[float]) -> list[float]:
    """The noise levels as floats; ``ValueError`` unless each is finite and ``>= 0``."""
    out = [float(s) for s in sigmas]
    for s in out:
        if not (math.isfinite(s) and s >= 0):
            raise ValueError(f"eval.sigmas must be finite and >= 0, got {s!r}.")
    if not out:
        raise ValueError("eval.sigmas is empty; name at least one noise level, e.g. [0.1].")
    return out


def _estimator(cfg: DictConfig, system, model: ResidualObserver | None, metrics: dict):
    """A function ``sigma -> Estimator`` for the run's method (checked before any work)."""
    label = metrics["method"]
    if model is not None:
        if cfg.eval.checkpoint:
            path, ckpt = load_weights(model, absolute(cfg.eval.checkpoint), model.device)
            metrics.update(
                checkpoint=str(path),
                best_epoch=ckpt["epoch"],
                best_val_loss=ckpt.get("best", {}).get("val_loss"),
            )
            log.info("evaluating %s (epoch %s)", path, ckpt["epoch"])
        est = ObserverEstimator(model, label, cfg.train.eval_batch_size, cfg.eval.progress)
        return lambda sigma: est
    factory = build_estimator_factory(system, cfg.method)
    metrics["method_params"] = dict(cfg.method.params)

    def make(sigma: float):
        est = make_estimator(system, factory, sigma, **dict(cfg.method.params))
        if isinstance(getattr(est, "progress", None), bool):  # a filter's bar over its steps
            est.progress = bool(cfg.eval.progress)
        metrics.setdefault("estimators", {})[f"{sigma:g}"] = repr(est)
        return est

    return make


def evaluate(
    cfg: DictConfig,
    system,
    out_dir: str | Path,
    model: ResidualObserver | None = None,
    info: dict[str, Any] | None = None,
) -> dict:
    """The evaluation task: every sigma's row and figure, then the tables and ``metrics.json``.

    ``model`` is the observer (trained, or to load ``eval.checkpoint`` into) for the learned
    methods, ``None`` for a baseline; ``info`` is what training recorded. Returns the metrics.
    """
    out_dir, res_dir = Path(out_dir), Path(out_dir) / "results"
    meth = cfg.method
    # rows are labelled by method; a trained observer by its experiment (paper_cpu, ...)
    label = meth.label or (cfg.name if meth.name == "learned" and not meth.target else meth.name)
    metrics: dict[str, Any] = {
        "name": cfg.name,
        "method": label,
        "seed": int(cfg.seed),
        "skip_steps": int(cfg.eval.skip_steps),
        "out_dir": str(out_dir),
        **(info or {}),
    }
    estimator = _estimator(cfg, system, model, metrics)
    what = cfg.name if label == cfg.name else f"{cfg.name}, method {label}"
    dataset = OmegaConf.to_object(cfg.dataset)
    rows, curves = [], {}
    for sigma in check_sigmas(cfg.eval.sigmas):
        data = inference_data(
            system, dataset, cfg.eval, sigma, cache_dir=absolute(dataset.cache_dir)
        )
        r = evaluate_estimator(estimator(sigma), data, system, skip=cfg.eval.skip_steps)
        r.row = {
            "sigma": sigma,
            "method": label,
            **{k: v for k, v in r.row.items() if k != "sigma"},
            "seconds": r.seconds,
            "us/step": 1e6 * r.seconds / (len(data) * data.length),
        }
        rows.append(r.row)
        curves[f"{sigma:g}"] = {k: v.tolist() for k, v in r.curves.items()}
        if cfg.eval.plots:
            title = f"{what}: sigma = {sigma:g}, {len(data)} x {data.length} steps"
            plot_errors(r, res_dir / f"errors_sigma{sigma:g}.png", title=title)
        shown = {k: (float(f"{v:.4g}") if isinstance(v, float) else v) for k, v in r.row.items()}
        log.info("sigma %g: %s", sigma, shown)
    _, md_path = write_table(rows, res_dir / "table", title=f"{what} (seed {cfg.seed})")
    metrics["table"] = rows
    write_text_atomic(res_dir / "metrics.json", to_json(metrics, indent=1) + "\n")
    write_text_atomic(res_dir / "curves.json", to_json(curves) + "\n")
    log.info("results in %s\n%s", res_dir, md_path.read_text())
    return metrics


def _hydra_main(cfg: DictConfig) -> float | None:
    """Evaluates and returns the run's objective (``objective=``, e.g. ``'R est'``) to a sweeper."""
    from hydra.core.hydra_config import HydraConfig

    from .train import run, say_where_on_failure, sweeper_reads_the_objective

    if cfg.method.name == "learned" and not cfg.method.target and not cfg.eval.checkpoint:
        raise ValueError(
            "the evaluate command does not train: give eval.checkpoint=<run folder or .pt> for "
            "method=learned, or pick a baseline (method=ekf, raw, ...); to train, use "
            "manifold_nets.cli.train."
        )
    required = sweeper_reads_the_objective(cfg)
    out_dir = HydraConfig.get().runtime.output_dir
    with say_where_on_failure(out_dir):
        return run(cfg, out_dir, objective_required=required)["objective"]


def main() -> None:
    """The command-line entry (configs from the package ``manifold_nets_configs``, primary config ``train.yaml``)."""
    import hydra

    hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="train")(_hydra_main)()


if __name__ == "__main__":
    main()
