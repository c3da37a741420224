"""``python -m manifold_nets.cli.train``: data -> training -> the paper's table and figure, by hydra.

One command generates (or reuses from the cache) the datasets of the configured system, trains
the residual observer, keeps the best-validation model, evaluates it on a noisy inference set
per sigma and writes everything into its own run folder::

    python -m manifold_nets.cli.train experiment=default            # small: minutes on a CPU
    python -m manifold_nets.cli.train experiment=default debug=tiny # seconds: a smoke test
    python -m manifold_nets.cli.train experiment=paper_rigid_body   # the paper's sizes
    python -m manifold_nets.cli.train -m experiment=default seed=0,1,2
    python -m manifold_nets.cli.train experiment=default method=ekf # a baseline, same evaluation

``method=`` (``configs/method/``) picks what produces the estimates: ``learned`` (default: train
the observer, or evaluate ``eval.checkpoint``), ``untrained`` (the observer at its seeded
initialisation), or a classical estimator of the system (``System.estimators()``). Every method
goes through the same evaluation (:mod:`manifold_nets.cli.evaluate`).

A run folder (``outputs/<name>/<date_time_pid>/``, or ``multirun/<name>/<date_time_pid>/<job>/``)
holds ``config.yaml`` (resolved), ``log.csv``/``log.json`` (per epoch), ``checkpoints/best.pt``
and ``last.pt``, ``results/`` (see the evaluation command), and with ``train.tensorboard=true``
``tensorboard/`` (losses, learning rate, metrics: :mod:`manifold_nets.tensorboard_log`).
Interrupted? Resume with ``train.resume=<run folder>``.

The hydra entry returns the run's objective (``objective=``: ``best_val_loss`` by default,
``test_loss``, or a table column such as ``'R est'`` or ``'R est@0.1'``; see
:mod:`manifold_nets.objective`) as a float, which hydra's Optuna sweeper optimises::

    python -m manifold_nets.cli.train -m hydra/sweeper=optuna hydra.sweeper.n_trials=20 \
        experiment=default 'train.lr=interval(1e-4,1e-2)'

A run with no loss to return (a baseline under the default objective) returns ``None``, unless
a sweeper that reads the value runs it: then it fails before any work. docs/sweeps.md has the
launchers (joblib, submitit) and the search.

:func:`run` does the work of one composed config (what tests call); :func:`train` is the
training task alone.
"""

from __future__ import annotations

import logging
import time
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from manifold_nets.atomic import write_text_atomic
from manifold_nets.augmentation import MeasurementNoise
from manifold_nets.builders import (
    LEARNED_METHODS,
    build_estimator_factory,
    build_observer,
    build_system,
    resolve_device,
)
from manifold_nets.checkpoint import load_checkpoint, load_weights, resolve_checkpoint
from manifold_nets.config import RunConfig
from manifold_nets.datasets import training_data
from manifold_nets.objective import objective_value, parse_objective
from manifold_nets.streaming import SimulatedStream
from manifold_nets.tensorboard_log import TensorBoardLog, check_tensorboard
from manifold_nets.training import EpochCallback, check_settings, fit, validation_loss

from . import CONFIG_PATH
from .evaluate import absolute, check_sigmas, evaluate

__all__ = [
    "check_config",
    "main",
    "run",
    "say_where_on_failure",
    "sweeper_reads_the_objective",
    "train",
]

log = logging.getLogger(__name__)


def check_config(cfg: DictConfig) -> None:
    """Raises ``ValueError`` unless ``cfg`` fits :class:`~manifold_nets.config.RunConfig`.

    Composing already checks overrides; this also catches keys appended with ``+``.
    """
    try:
        OmegaConf.merge(OmegaConf.structured(RunConfig), OmegaConf.to_container(cfg))
    except Exception as err:  # omegaconf's ConfigKeyError / ValidationError
        msg = str(err).splitlines()[0]
        raise ValueError(
            f"the config does not fit the schema: {msg} (not in the schema "
            "manifold_nets/config.py; check the spelling)."
        ) from None


def _check_before_work(cfg: DictConfig, objective_required: bool = False) -> None:
    """Every check that needs no work: the schema, the sigmas, the objective, the training
    settings."""
    check_config(cfg)
    check_sigmas(cfg.eval.sigmas)
    if cfg.train.tensorboard:
        check_tensorboard()
    objective = parse_objective(cfg.objective, cfg.eval.sigmas)
    missing = _no_loss_to_return(cfg) if objective.is_loss else None
    if objective_required and missing:
        raise ValueError(
            f"objective={cfg.objective!r}: the sweeper needs a value, but {missing}; choose a "
            "metric column of the results table instead, e.g. objective='R est' (docs/sweeps.md)."
        )
    try:
        check_settings(OmegaConf.to_object(cfg.train))
    except ValueError as err:  # the library names its parameter first: name the config key
        raise ValueError(f"train.{err}") from None
    if cfg.train.epochs == 0 and not cfg.train.init_from and _trains(cfg):
        raise ValueError(
            "train.epochs=0 trains nothing: it evaluates train.init_from's weights as they are "
            "(e.g. under another model.centering_factors or model.step_decay, which add no "
            "weight); give train.init_from=<run folder or checkpoint>, or set train.epochs >= 1."
        )
    if cfg.train.init_from and cfg.train.resume:
        raise ValueError(
            f"train.init_from={cfg.train.init_from!r} and train.resume={cfg.train.resume!r}: "
            "resume continues a run (its weights, optimizer and epoch), init_from starts a new "
            "one from a model's weights; set only one."
        )
    if cfg.train.stream and cfg.data_file:
        raise ValueError(
            f"train.stream=true simulates fresh training sequences every epoch, but "
            f"data_file={cfg.data_file!r} is a file, which has no simulator; set "
            "train.stream=false to train on the file, or drop data_file to simulate."
        )
    if cfg.method.name == "untrained" and cfg.eval.checkpoint:
        raise ValueError(
            "method=untrained evaluates the observer at its initialisation; it cannot load "
            f"eval.checkpoint={cfg.eval.checkpoint!r} (use method=learned for that)."
        )


def _trains(cfg: DictConfig) -> bool:
    """Whether the run trains an observer (a learned method without ``eval.checkpoint``)."""
    return cfg.method.name == "learned" and not cfg.method.target and not cfg.eval.checkpoint


def _no_loss_to_return(cfg: DictConfig) -> str | None:
    """Why the run will have no ``cfg.objective`` loss to return (``None``: it will have one)."""
    learned = cfg.method.name == "learned" and not cfg.method.target
    if not learned:
        return f"method={cfg.method.name} does not train, so it has no {cfg.objective}"
    if cfg.objective == "test_loss" and cfg.eval.checkpoint:
        return "a run that evaluates eval.checkpoint does not train, so it has no test_loss"
    if cfg.objective == "test_loss" and not cfg.eval.test_split:
        return "eval.test_split=false: the test loss is not computed"
    return None


def train(
    cfg: DictConfig, system, model, out_dir: Path, on_epoch: EpochCallback | None = None
) -> dict[str, Any]:
    """The training task: data, fit, the best weights back into ``model``, the test loss.

    Returns what the run's ``metrics.json`` records of it; ``on_epoch`` goes to ``fit``.
    """
    t, info = cfg.train, {}
    if t.init_from:
        path, ckpt = load_weights(model, absolute(t.init_from), model.device, widen=True)
        info["init_from"] = str(path)
        log.info("starting from the weights of %s (epoch %s)", path, ckpt["epoch"])
    dataset = OmegaConf.to_object(cfg.dataset)
    parts = training_data(
        system,
        dataset,
        data_file=absolute(cfg.data_file) if cfg.data_file else None,
        noise_levels=list(t.noise.levels),
        cache_dir=absolute(dataset.cache_dir),
        cache=not t.stream,  # a stream trains on fresh data: only val/test are used, not cached
    )
    if t.compile:
        model.compile_step()
        log.info("the observer's step is compiled (torch.compile): the first batch waits")
    settings = OmegaConf.to_object(t)
    if settings.resume:
        settings = replace(settings, resume=absolute(settings.resume))
    noise = None
    if t.noise.sigma_max > 0:
        noise = MeasurementNoise(system, t.noise.sigma_min, t.noise.sigma_max)
    train_data = parts["train"]
    if t.stream:
        train_data = SimulatedStream(
            system, len(parts["train"]), cfg.dataset.length, sigma=cfg.dataset.sigma,
            noise_levels=list(t.noise.levels), seed=int(cfg.dataset.seed),
        )
        del parts["train"]  # not trained on: free its memory
        log.info("training data: fresh every epoch (train.stream=true), %r", train_data)
    t0 = time.perf_counter()
    result = fit(
        model, train_data, parts["val"], settings, out_dir=out_dir, seed=int(cfg.seed),
        transform=noise, config=OmegaConf.to_container(cfg, resolve=True), on_epoch=on_epoch,
    )
    load_weights(model, result.best_path, model.device)
    info.update(
        best_epoch=result.best_epoch,
        best_val_loss=result.best_val_loss,
        train_seconds=time.perf_counter() - t0,
        checkpoint=str(result.best_path),
    )
    if cfg.eval.test_split and "test" in parts:
        info["test_loss"] = validation_loss(model, parts["test"], t.eval_batch_size)
        log.info("test loss of the best model (epoch %d): %.5g", result.best_epoch,
                 info["test_loss"])
    return info


def run(cfg: DictConfig, out_dir: str | Path, *, objective_required: bool = False) -> dict:
    """Runs one experiment into ``out_dir``: training (when the method learns and no
    ``eval.checkpoint`` is given), then the evaluation. Returns the metrics, with
    ``metrics["objective"]`` the value of ``cfg.objective`` (``None`` when the run has no such
    loss and ``objective_required`` is false; with it true that fails before any work)."""
    _check_before_work(cfg, objective_required)
    # the device and the system are checked (the system's constructor checks its parameters)
    # before the run folder gets anything: a run refused here leaves no config.yaml behind
    device = resolve_device(cfg.train.device)
    system = build_system(cfg.system)
    if cfg.method.name not in LEARNED_METHODS or cfg.method.target:
        build_estimator_factory(system, cfg.method)  # an unknown method: refused now
    _check_checkpoints(cfg)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    resolved = OmegaConf.to_container(cfg, resolve=True)
    write_text_atomic(out_dir / "config.yaml", OmegaConf.to_yaml(resolved))
    if cfg.train.threads is not None:  # checked (>= 1) by check_settings
        torch.set_num_threads(int(cfg.train.threads))
    board = TensorBoardLog(out_dir / "tensorboard") if cfg.train.tensorboard else None
    try:
        metrics = _train_and_evaluate(cfg, out_dir, board, system, device)
    finally:
        if board is not None:
            board.close()
    metrics["objective"] = None
    if not (parse_objective(cfg.objective).is_loss and _no_loss_to_return(cfg)):
        metrics["objective"] = objective_value(cfg.objective, metrics)
        log.info("objective %s = %.6g", cfg.objective, metrics["objective"])
    return metrics


def _check_checkpoints(cfg: DictConfig) -> None:
    """Reads ``eval.checkpoint``, ``train.init_from`` and ``train.resume`` once before the run
    folder gets anything, so a typo'd path or an unreadable file is refused
    (``CheckpointError`` naming the file) and leaves no half-made run folder; whether it fits
    the model is checked when it is loaded into the observer."""
    if cfg.method.name not in LEARNED_METHODS or cfg.method.target:
        return
    if cfg.eval.checkpoint:
        load_checkpoint(resolve_checkpoint(absolute(cfg.eval.checkpoint), name="best.pt"))
    elif cfg.method.name == "learned":
        if cfg.train.init_from:
            load_checkpoint(resolve_checkpoint(absolute(cfg.train.init_from), name="best.pt"))
        if cfg.train.resume:
            load_checkpoint(resolve_checkpoint(absolute(cfg.train.resume), name="last.pt"))


def _train_and_evaluate(
    cfg: DictConfig, out_dir: Path, board: TensorBoardLog | None, system, device: torch.device
) -> dict:
    """The observer (for the learned methods), training, the evaluation."""
    model, info = None, {}
    if cfg.method.name in LEARNED_METHODS and not cfg.method.target:
        torch.manual_seed(int(cfg.seed))
        model = build_observer(
            system.group, system.measurement_dim, system.input_dim, cfg.model,
            dt=getattr(system, "dt", None), system=system,
        ).to(device)
        n_params = sum(p.numel() for p in model.parameters())
        log.info("observer: %s, %d parameters", model.signature(), n_params)
        if cfg.method.name == "learned" and not cfg.eval.checkpoint:
            on_epoch = board.on_epoch if board is not None else None
            info = train(cfg, system, model, out_dir, on_epoch=on_epoch)
    metrics = evaluate(cfg, system, out_dir, model=model, info=info)
    if board is not None:
        step = int(metrics.get("best_epoch") or 0)
        board.results(metrics["table"], step=step, test_loss=metrics.get("test_loss"))
        log.info("TensorBoard files in %s", board.log_dir)
    return metrics


def sweeper_reads_the_objective(cfg: DictConfig) -> bool:
    """Whether this hydra job runs under a sweeper that reads its return value (Optuna, ...):
    a multirun whose sweeper is not hydra's basic one, which ignores the value. Warns when the
    sweeper's ``direction`` goes against the objective (minimising a ``reduction %``)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    hc = HydraConfig.get()
    target = str(OmegaConf.select(hc, "sweeper._target_", default="") or "")
    direction = OmegaConf.select(hc, "sweeper.direction", default=None)
    direction = getattr(direction, "name", direction)  # the Optuna sweeper's enum, or a str
    if isinstance(direction, str) and direction in ("minimize", "maximize"):
        minimize = parse_objective(cfg.objective).minimize
        if (direction == "minimize") != minimize:
            log.warning(
                "the sweeper will %s objective=%r, which is better %s: set "
                "hydra.sweeper.direction=%s", direction,
                cfg.objective, "smaller" if minimize else "larger",
                "minimize" if minimize else "maximize",
            )
    return hc.mode == RunMode.MULTIRUN and not target.endswith(".BasicSweeper")


def _hydra_main(cfg: DictConfig) -> float | None:
    from hydra.core.hydra_config import HydraConfig

    required = sweeper_reads_the_objective(cfg)
    out_dir = HydraConfig.get().runtime.output_dir
    with say_where_on_failure(out_dir):
        metrics = run(cfg, out_dir, objective_required=required)
    return metrics["objective"]


@contextmanager
def say_where_on_failure(out_dir: str | Path):
    """Logs the run folder when the run fails: hydra made it (its ``.hydra/`` and log) before
    the run could check anything, so a refused run leaves it behind; this says where."""
    try:
        yield
    except Exception:
        log.error("the run failed; its folder (hydra's files, and what the run wrote): %s", out_dir)
        raise


def main() -> None:
    """The command-line entry (configs from the package ``manifold_nets_configs``, primary config ``train.yaml``)."""
    import hydra

    hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="train")(_hydra_main)()


if __name__ == "__main__":
    main()
