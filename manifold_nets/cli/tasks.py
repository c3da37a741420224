"""The commands' tasks: training, evaluation, and a whole run (train if needed, then evaluate).

:func:`run` does the work of one composed config (what the train and evaluate commands and the
tests call); :func:`train` is the training task alone, :func:`evaluate` the evaluation task:
per sigma of ``eval.sigmas`` the inference set (generated or read from the cache), the method's
estimates, the paper's metrics, one table row and one figure, written into
``<run folder>/results/`` (``table.csv``, ``table.md``, ``metrics.json``, ``curves.json``,
``errors_sigma<s>.png``).

``eval.checkpoint`` (a run folder, a checkpoint or a zoo entry ``zoo:rigid_body/nominal``) is
evaluated as the observer its own config describes: the command's ``model`` settings do not
apply to it. ``train.init_from`` starts the command's ``model`` from a checkpoint's weights
(widened when the model has more pieces: :func:`manifold_nets.checkpoint.load_weights`).
"""

from __future__ import annotations

import logging
import time
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from manifold_nets.atomic import write_text_atomic
from manifold_nets.augmentation import MeasurementNoise
from manifold_nets.baselines import make_estimator
from manifold_nets.builders import (
    LEARNED_METHODS,
    build_estimator_factory,
    build_observer,
    build_system,
    resolve_device,
)
from manifold_nets.checkpoint import load_checkpoint, load_weights, resolve_checkpoint
from manifold_nets.config import MethodConfig, ModelConfig
from manifold_nets.datasets import inference_data, training_data
from manifold_nets.evaluation import evaluate as evaluate_estimator
from manifold_nets.objective import objective_value, parse_objective
from manifold_nets.observer import ResidualObserver
from manifold_nets.reporting import plot_errors, write_table
from manifold_nets.streaming import SimulatedStream
from manifold_nets.tensorboard_log import TensorBoardLog, check_tensorboard
from manifold_nets.training import EpochCallback, check_settings, fit, validation_loss
from manifold_nets.training_settings import param_groups

from .common import absolute, check_config, check_sigmas, to_json
from .learned_extras import check_covariance, check_guarded_model, check_lock_out, learned_estimator

__all__ = ["evaluate", "run", "train"]

log = logging.getLogger(__name__)


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
            "(e.g. under another centring, model.head, or step decay, model.scales, which add no "
            "weight); give train.init_from=<run folder or checkpoint>, or set train.epochs >= 1."
        )
    e = cfg.eval
    for key, value, low in (("eval.length", e.length, 1), ("eval.num_sequences", e.num_sequences, 1),
                            ("eval.seed", e.seed, 0), ("eval.skip_steps", e.skip_steps, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value < 2**63:
            raise ValueError(f"{key} must be an integer >= {low}, got {value!r}.")
    from manifold_nets.datasets import MAX_STEPS

    for key, n, length in (("dataset", cfg.dataset.num_sequences, cfg.dataset.length),
                           ("eval", e.num_sequences, e.length)):
        if n * length > MAX_STEPS:
            raise ValueError(
                f"{key}.num_sequences x {key}.length = {n} x {length} is more than "
                f"{MAX_STEPS:.0e} steps; ask for fewer or shorter sequences."
            )
    if e.skip_steps >= e.length:
        raise ValueError(
            f"eval.skip_steps={e.skip_steps} leaves no step of eval.length={e.length} to "
            "evaluate; use eval.skip_steps < eval.length."
        )
    if _trains(cfg) and not cfg.data_file and cfg.train.skip_steps > cfg.dataset.length:
        raise ValueError(
            f"train.skip_steps={cfg.train.skip_steps} is longer than a training sequence "
            f"(dataset.length={cfg.dataset.length}): no step would be in the loss."
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
    check_covariance(cfg)
    check_lock_out(cfg)
    if cfg.method.name == "untrained" and cfg.eval.checkpoint:
        raise ValueError(
            "method=untrained evaluates the observer at its initialisation; it cannot load "
            f"eval.checkpoint={cfg.eval.checkpoint!r} (use method=learned for that)."
        )


def _check_lock_out_model(cfg: DictConfig, system) -> None:
    """:func:`check_guarded_model` of the observer the run evaluates (``eval.checkpoint``'s own
    model config, else the command's)."""
    if cfg.eval.get("lock_out"):
        learned = cfg.method.name == "learned" and cfg.eval.checkpoint
        check_guarded_model(cfg, system,
                            _checkpoint_model(cfg.eval.checkpoint) if learned else cfg.model)


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
    _check_lock_out_model(cfg, system)
    if _trains(cfg) and cfg.train.param_lr:  # an unknown name: refused before the run folder
        model = build_observer(system.group, system.measurement_dim, system.input_dim, cfg.model,
                               dt=getattr(system, "dt", None), system=system)
        try:
            param_groups(model, float(cfg.train.lr), dict(cfg.train.param_lr))
        except ValueError as err:
            raise ValueError(f"train.{err}") from None
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    resolved = OmegaConf.to_container(cfg, resolve=True)
    write_text_atomic(out_dir / "config.yaml", OmegaConf.to_yaml(resolved))
    from manifold_nets.threads import use_threads  # one rule for every command's threads

    use_threads(None if cfg.train.threads is None else int(cfg.train.threads))
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
            path = resolve_checkpoint(absolute(cfg.train.resume), name="last.pt")
            _same_data(cfg, load_checkpoint(path)["config"], path)


#: What decides a run's data: resuming on other data would pick the best model by comparing
#: validation losses of two different sets.
_DATA_KEYS = ("dataset.num_sequences", "dataset.length", "dataset.sigma", "dataset.seed",
              "dataset.splits", "data_file", "train.noise", "train.stream", "system")


def _same_data(cfg: DictConfig, old: dict, path) -> None:
    """Refuses ``train.resume`` of a run whose data this config would change."""
    now = OmegaConf.to_container(cfg, resolve=True)
    diff = []
    for key in _DATA_KEYS:
        a, b = old, now
        for part in key.split("."):
            a = a.get(part) if isinstance(a, dict) else None
            b = b.get(part) if isinstance(b, dict) else None
        if a != b:
            diff.append(f"{key}: the run's {a!r:.80}, now {b!r:.80}")
    if diff:
        raise ValueError(
            f"train.resume={str(path)!r} continues a run on its own data, but this config "
            f"changes it ({'; '.join(diff)}); its best model would be chosen between validation "
            "losses of two different sets. Resume with the run's data settings, or start a new "
            "run from its weights: train.init_from=<the run>."
        )


def _checkpoint_model(where: str) -> DictConfig:
    """The model config a checkpoint was written with (its ``config.model``), checked against
    the schema; the observer ``eval.checkpoint`` names is built from it, not from the command's
    ``model``."""
    from manifold_nets.loading import ArtefactError, _check_plain, check_sizes

    path = resolve_checkpoint(absolute(where), name="best.pt")
    ckpt = load_checkpoint(path)
    raw = ckpt["config"].get("model")
    if not isinstance(raw, dict):
        raise ArtefactError(f"{path} holds no model config; it cannot be evaluated by itself.")
    _check_plain(raw, f"{path}: model")
    try:
        model = OmegaConf.merge(OmegaConf.structured(ModelConfig), raw)
    except Exception as err:  # omegaconf's validation errors
        msg = str(err).splitlines()[0]
        raise ArtefactError(f"{path}: its model config does not fit the schema: {msg}.") from None
    check_sizes(model, ckpt["signature"], str(path))  # before anything is built
    log.info("eval.checkpoint=%s: the observer its own config describes", where)
    return model


def _train_and_evaluate(
    cfg: DictConfig, out_dir: Path, board: TensorBoardLog | None, system, device: torch.device
) -> dict:
    """The observer (for the learned methods), training, the evaluation."""
    model, info = None, {}
    if cfg.method.name in LEARNED_METHODS and not cfg.method.target:
        torch.manual_seed(int(cfg.seed))
        model_cfg = cfg.model
        if cfg.eval.checkpoint and cfg.method.name == "learned":
            model_cfg = _checkpoint_model(cfg.eval.checkpoint)
        with warnings.catch_warnings():
            if model_cfg is not cfg.model:  # a file's first-format keys are the reader's business
                warnings.simplefilter("ignore", FutureWarning)
            model = build_observer(
                system.group, system.measurement_dim, system.input_dim, model_cfg,
                dt=getattr(system, "dt", None), system=system, import_core=model_cfg is cfg.model,
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


def _estimator(cfg: DictConfig, system, model: ResidualObserver | None, metrics: dict):
    """A function ``sigma -> Estimator`` for the run's method (checked before any work)."""
    label = metrics["label"]  # the experiment's name, for a trained observer
    if model is not None:
        if cfg.eval.checkpoint:
            path, ckpt = load_weights(model, absolute(cfg.eval.checkpoint), model.device)
            metrics.update(
                checkpoint=str(path),
                best_epoch=ckpt["epoch"],
                best_val_loss=ckpt.get("best", {}).get("val_loss"),
            )
            log.info("evaluating %s (epoch %s)", path, ckpt["epoch"])
        est = learned_estimator(cfg, model, label, metrics)
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
    # the rows say the method (learned, ekf, ...); the comparison command labels a trained
    # observer by its experiment (paper_cpu, ...), so that observers of two experiments stay apart
    method = meth.label or meth.name
    learned = meth.name == "learned" and not meth.target
    metrics: dict[str, Any] = {
        "name": cfg.name,
        "method": method,
        "label": meth.label or (cfg.name if learned else meth.name),
        "seed": int(cfg.seed),
        "skip_steps": int(cfg.eval.skip_steps),
        "out_dir": str(out_dir),
        **(info or {}),
    }
    estimator = _estimator(cfg, system, model, metrics)
    what = cfg.name if learned and not meth.label else f"{cfg.name}, method {method}"
    dataset = OmegaConf.to_object(cfg.dataset)
    rows, curves, reference_rows = [], {}, []
    for name in cfg.eval.baselines:
        build_estimator_factory(system, MethodConfig(name=name))  # an unknown one: refused now
    for sigma in check_sigmas(cfg.eval.sigmas):
        data = inference_data(
            system, dataset, cfg.eval, sigma, cache_dir=absolute(dataset.cache_dir)
        )
        r = evaluate_estimator(estimator(sigma), data, system, skip=cfg.eval.skip_steps,
                               calibration=cfg.eval.calibration)
        r.row = {
            "sigma": sigma,
            "method": method,
            **{k: v for k, v in r.row.items() if k != "sigma"},
            "seconds": r.seconds,
            "us/step": 1e6 * r.seconds / (len(data) * data.length),
        }
        rows.append(r.row)
        for name in cfg.eval.baselines:  # the references, on the same set
            try:
                est = make_estimator(
                    system, build_estimator_factory(system, MethodConfig(name=name)), sigma
                )
            except ValueError as err:  # e.g. a filter at sigma 0: no row, and why
                log.info("eval.baselines: no %s row at sigma %g (%s)", name, sigma, err)
                continue
            b = evaluate_estimator(est, data, system, skip=cfg.eval.skip_steps,
                                   calibration=cfg.eval.calibration)
            reference_rows.append({"sigma": sigma, "method": name,
                                   **{k: v for k, v in b.row.items() if k != "sigma"},
                                   "seconds": b.seconds,
                                   "us/step": 1e6 * b.seconds / (len(data) * data.length)})
        curves[f"{sigma:g}"] = {k: v.tolist() for k, v in r.curves.items()}
        if cfg.eval.plots:
            title = f"{what}: sigma = {sigma:g}, {len(data)} x {data.length} steps"
            plot_errors(r, res_dir / f"errors_sigma{sigma:g}.png", title=title, group=system.group)
        shown = {k: (float(f"{v:.4g}") if isinstance(v, float) else v) for k, v in r.row.items()}
        log.info("sigma %g: %s", sigma, shown)
    shown = sorted(rows + reference_rows, key=lambda row: row["sigma"])  # stable: method first
    _, md_path = write_table(shown, res_dir / "table", title=f"{what} (seed {cfg.seed})")
    metrics["table"] = rows
    if reference_rows:
        metrics["references"] = reference_rows
    write_text_atomic(res_dir / "metrics.json", to_json(metrics, indent=1) + "\n")
    write_text_atomic(res_dir / "curves.json", to_json(curves) + "\n")
    log.info("results in %s\n%s", res_dir, md_path.read_text())
    return metrics
