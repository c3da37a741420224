"""What the evaluation adds to the learned observer: a covariance readout (``eval.covariance``)
and a lock-out guard (``eval.lock_out``). Their checks run before any work; the estimator they
make is what :mod:`manifold_nets.cli.tasks` evaluates."""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path

from omegaconf import DictConfig

from manifold_nets.builders import LEARNED_METHODS, build_observer
from manifold_nets.evaluation import CalibratedEstimator, ObserverEstimator

from .common import absolute

__all__ = ["check_covariance", "check_guarded_model", "check_lock_out", "covariance_file",
           "learned_estimator"]


def covariance_file(cfg: DictConfig) -> Path:
    """``eval.covariance`` as a file: a path; a zoo entry, its ``covariance.pt``; or another of
    an entry's readouts by its file name, ``zoo:rigid_body/nominal/covariance_sensor.pt``."""
    text = str(cfg.eval.covariance)
    if not text.startswith("zoo:"):
        return Path(absolute(text))
    from manifold_nets.plugins import locate

    entry, name = text, "covariance.pt"
    if text.count("/") >= 2:  # <package>/<entry>/<file>
        entry, _, name = text.rpartition("/")
        if not re.fullmatch(r"covariance[A-Za-z0-9_-]*\.pt", name):
            raise ValueError(
                f"eval.covariance={text!r}: {name!r} is not a readout's file name; an entry's "
                "readouts are covariance.pt or covariance_<system>.pt (see the entry's card.md)."
            )
    return locate(entry) / name


def check_covariance(cfg: DictConfig) -> None:
    if not cfg.eval.covariance:
        return
    if not cfg.eval.calibration:
        raise ValueError(
            f"eval.covariance={cfg.eval.covariance!r} is scored only with eval.calibration=true; "
            "set it (or drop eval.covariance)."
        )
    if cfg.method.name != "learned" or cfg.method.target:
        raise ValueError(
            f"eval.covariance is a readout of the learned observer's errors; method="
            f"{cfg.method.name!r} has its own covariance or none (drop eval.covariance)."
        )
    path = covariance_file(cfg)
    if not path.is_file():
        raise ValueError(
            f"eval.covariance={cfg.eval.covariance!r}: no covariance readout at {path}; give a "
            "covariance.pt (docs/calibration.md) or a zoo entry that ships one."
        )


def check_lock_out(cfg: DictConfig) -> None:
    """``eval.lock_out``: ``{tau, floor}`` (``null`` or ``{}``: no guard), for the learned
    observer."""
    guard = cfg.eval.get("lock_out")
    if not guard:
        return
    if cfg.method.name not in LEARNED_METHODS or cfg.method.target:
        raise ValueError(
            f"eval.lock_out guards the learned observer; method={cfg.method.name!r} is another "
            "estimator (drop eval.lock_out)."
        )
    if not isinstance(guard, Mapping) or not set(guard) <= {"tau", "floor"}:
        raise ValueError(
            f"eval.lock_out={guard!r} must be a mapping of tau and floor, e.g. "
            "eval.lock_out='{tau: 20, floor: 0.1}' (null for no guard)."
        )
    from manifold_nets.observer import LockOutGuard

    LockOutGuard.check_settings(**guard)


def check_guarded_model(cfg: DictConfig, system, model_cfg) -> None:
    """The observer ``eval.lock_out`` guards (built from ``model_cfg``: cheap, and before the run
    folder gets anything) has a robust measurement."""
    from manifold_nets.observer import LockOutGuard

    model = build_observer(system.group, system.measurement_dim, system.input_dim, model_cfg,
                           dt=getattr(system, "dt", None), system=system)
    try:
        LockOutGuard(model, **cfg.eval.lock_out)
    except ValueError as err:
        raise ValueError(f"eval.lock_out: {err}") from None


def learned_estimator(cfg: DictConfig, model, label: str, metrics: dict) -> ObserverEstimator:
    """The learned observer as the evaluation's estimator: behind its guard (``eval.lock_out``)
    and with its readout (``eval.covariance``) when the config names them; both recorded in
    ``metrics``."""
    guarded = model
    if cfg.eval.get("lock_out"):
        from manifold_nets.observer import LockOutGuard

        guarded = LockOutGuard(model, **cfg.eval.lock_out)
        metrics["lock_out"] = guarded.settings()
    est = ObserverEstimator(guarded, label, cfg.train.eval_batch_size, cfg.eval.progress)
    if cfg.eval.covariance:
        from manifold_nets.covariance_training import load_readout
        from manifold_nets.observer import CalibratedObserver

        path = covariance_file(cfg)
        cal = load_readout(path, model)
        cal = CalibratedObserver(guarded, cal.readout, cal.level_scale)
        est = CalibratedEstimator(cal, label, cfg.train.eval_batch_size, cfg.eval.progress)
        metrics["covariance"] = str(path)
    return est
