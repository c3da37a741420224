"""``python -m manifold_nets.train``: data -> training -> the paper's table and figure, by hydra.

One command generates (or reuses from the cache) the datasets of the configured system, trains
the residual observer, keeps the best-validation model, evaluates it on a noisy inference set
per sigma and writes everything into its own run folder::

    python -m manifold_nets.train experiment=default              # small: minutes on 2 CPU cores
    python -m manifold_nets.train experiment=paper_rigid_body     # the paper's sizes
    python -m manifold_nets.train -m experiment=default seed=0,1,2
    python -m manifold_nets.train -m experiment=default eval.checkpoint=<run>/checkpoints/best.pt \
        eval.sigma=0.1,0.2,0.3,0.4,0.5
    python -m manifold_nets.sweep multirun/default/<run id>     # one table for a sweep
    python -m manifold_nets.train experiment=default method=ekf  # a baseline, same evaluation
    python -m manifold_nets.compare outputs/default multirun/...  # methods side by side

``method=`` (``configs/method/``) picks what produces the estimates: ``learned`` (default: train
the observer, or evaluate ``eval.checkpoint``), ``untrained`` (the observer at its seeded
initialisation), or a classical estimator of the system (``System.estimators()``: ``raw``,
``dead_reckoning``, ``ekf``, ``complementary``, ...; no training). Every method goes through
the same inference sets, metrics, table and figures.

A run folder (``outputs/<name>/<date_time_pid>/``, or ``multirun/<name>/<date_time_pid>/<job>/``)
holds ``config.yaml`` (resolved), ``log.csv``/``log.json`` (per epoch), ``checkpoints/best.pt``
and ``last.pt``, and ``results/``: ``table.csv``, ``table.md``, ``metrics.json`` and one
``errors_sigma<s>.png`` per sigma. Interrupted? Resume with ``train.resume=<run folder>``.

:func:`run` does the work from a composed config and is what tests call; :func:`build_observer`
turns a ``model`` config into a :class:`~manifold_nets.observer.ResidualObserver`.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Any

# OpenMP threads that spin while they wait make torch 10-50x slower as soon as another process
# shares the cores (measured on 2 busy cores: 3 s instead of 0.13 s for a small training batch).
# Sleeping waits cost a wake-up per parallel region instead. Only effective when this module
# imports torch first (the command line); an OMP_WAIT_POLICY set by the user wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch
from omegaconf import DictConfig, OmegaConf

from . import train_config  # noqa: F401  (registers the schema and the run-id resolver)
from .atomic import write_text_atomic
from .baselines import make_estimator
from .checkpoint import load_checkpoint
from .data import DatasetError, TrajectoryDataset, load_dataset
from .evaluation import ObserverEstimator, evaluate, plot_errors, write_table
from .generate import DatasetConfig, load_or_generate
from .observer import GRUCore, RecurrentCore, ResidualObserver, core_input_size, factor_names
from .relax import relax
from .train_config import DTYPES, RunConfig
from .training import check_schedule, fit, resolve_checkpoint, validation_loss

__all__ = ["LEARNED_METHODS", "build_observer", "check_config", "main", "resolve_device", "run"]

#: The methods that are the residual observer (``method.name``); any other is an estimator.
LEARNED_METHODS = ("learned", "untrained")

log = logging.getLogger(__name__)


def _dtype(name: str, key: str) -> torch.dtype:
    if name not in DTYPES:
        raise ValueError(f"{key} must be one of {DTYPES}, got {name!r}.")
    return getattr(torch, name)


def build_observer(group, measurement_dim: int, input_dim: int, mcfg: Any) -> ResidualObserver:
    """The observer of a ``model`` config (:class:`~manifold_nets.train_config.ModelConfig`).

    ``group`` is the system's; ``model.relax`` takes factors off it (:func:`~manifold_nets.relax.relax`).
    """
    group = relax(group, list(mcfg.relax))
    innovation = {k: list(v) for k, v in dict(mcfg.innovation).items()}
    in_size = core_input_size(
        group, measurement_dim, input_dim, innovation, list(mcfg.relative_only)
    )
    if mcfg.core == "gru":
        core = GRUCore(in_size, group.tangent_dim, mcfg.hidden_size, mcfg.num_layers)
    else:
        from hydra.utils import get_class

        try:
            cls = get_class(mcfg.core)
        except Exception as err:
            raise ValueError(
                f"model.core must be 'gru' or the dotted path of a RecurrentCore subclass; "
                f"{mcfg.core!r} could not be imported ({err})."
            ) from None
        if not (isinstance(cls, type) and issubclass(cls, RecurrentCore)):
            raise ValueError(f"model.core={mcfg.core!r} is not a RecurrentCore subclass.")
        core = cls(
            in_size, group.tangent_dim, hidden_size=mcfg.hidden_size, num_layers=mcfg.num_layers
        )
    rules = dict(mcfg.updates)
    update = {name: rules.pop(name, mcfg.default_update) for name in factor_names(group)}
    if rules:
        raise ValueError(
            f"model.updates names factors {sorted(rules)} that the group {group!r} does not have; "
            f"its factors: {list(factor_names(group))}."
        )
    model = ResidualObserver(
        group,
        measurement_dim,
        input_dim,
        core,
        update=update,
        innovation=innovation,
        relative_only=list(mcfg.relative_only),
        state_dtype=_dtype(mcfg.state_dtype, "model.state_dtype"),
    )
    return model.to(_dtype(mcfg.net_dtype, "model.net_dtype"))


def _method_factory(system, meth: Any):
    """The estimator factory of a non-learned ``method`` config (checked before any work)."""
    if meth.target:
        from hydra.utils import get_object

        try:
            return get_object(meth.target)
        except Exception as err:
            raise ValueError(
                f"method.target={meth.target!r} could not be imported ({err}); give the dotted "
                "path of a factory (system, sigma=..., **params) -> Estimator."
            ) from None
    table = system.estimators()
    if meth.name not in table:
        raise ValueError(
            f"method={meth.name!r}: {type(system).__name__} has no estimator of that name; the "
            f"methods are {list(LEARNED_METHODS)} (the observer) and {sorted(table)} "
            "(System.estimators()); or set method.target to the dotted path of a factory."
        )
    return table[meth.name]


def resolve_device(name: str) -> torch.device:
    """``cpu``, ``cuda[:i]`` or ``auto``; a clear error when CUDA is asked for but missing."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(
            f"train.device={name!r} but CUDA is not available here; use train.device=cpu."
        )
    return dev


def _check_system(system) -> None:
    for attr in ("group", "measurement_dim", "input_dim"):
        if not hasattr(system, attr):
            raise TypeError(
                f"the configured system {type(system).__name__} has no {attr!r}; a system must be "
                "a manifold_nets.system.System (configs/system/<name>.yaml with a _target_)."
            )


def _dataset_config(cfg: DictConfig, **changes) -> DatasetConfig:
    d = OmegaConf.to_object(cfg.dataset)
    for k, v in changes.items():
        setattr(d, k, v)
    return d


def _abs(path: str) -> str:
    try:
        from hydra.utils import to_absolute_path

        return to_absolute_path(path)
    except ValueError:  # hydra not initialised (tests, plain Python)
        return str(Path(path).absolute())


def load_training_data(system, cfg: DictConfig) -> dict[str, TrajectoryDataset]:
    """The ``train``/``val`` (and ``test``) splits: read from ``data_file`` or made from ``dataset``."""
    if cfg.get("data_file"):
        path = Path(_abs(cfg.data_file))
        if not path.is_file():
            raise FileNotFoundError(
                f"data_file={cfg.data_file!r}: no dataset at {path}. Generate one with "
                "`python -m manifold_nets.generate ...` (or drop data_file to generate from "
                "`dataset`)."
            )
        parts = load_dataset(path, group=system.group).splits()
    elif cfg.train.noise.levels:
        parts = _noise_level_mixture(system, cfg)
    else:
        dcfg = _dataset_config(cfg, inference=None)
        parts = load_or_generate(system, dcfg, cache_dir=_abs(dcfg.cache_dir))
    missing = [s for s in ("train", "val") if s not in parts]
    if missing:
        raise DatasetError(
            f"training needs 'train' and 'val' splits; the data has {sorted(parts)}. Set "
            "dataset.splits, e.g. {train: 0.8, val: 0.1, test: 0.1}."
        )
    return parts


def _noise_level_mixture(system, cfg: DictConfig) -> dict[str, TrajectoryDataset]:
    """Every split with each sequence's measurements taken from one noise level drawn at random.

    The data are generated (or read from the cache) once per level of ``train.noise.levels``
    with the same seed, so the trajectories agree and only the measurement noise differs.
    """
    levels = [float(s) for s in cfg.train.noise.levels]
    if cfg.get("data_file"):
        raise ValueError(
            "train.noise.levels generates the data per level; it cannot be used with data_file."
        )
    base = _dataset_config(cfg, inference=None)
    gen = torch.Generator().manual_seed(int(base.seed))
    choice: dict[str, torch.Tensor] = {}
    out: dict[str, TrajectoryDataset] = {}
    for i, sigma in enumerate(levels):
        dcfg = _dataset_config(cfg, inference=None, sigma=sigma)
        parts = load_or_generate(system, dcfg, cache_dir=_abs(dcfg.cache_dir))
        for name, part in parts.items():
            if name not in choice:
                choice[name] = torch.randint(len(levels), (len(part),), generator=gen)
                meta = {**part.meta, "sigma": None, "noise_levels": levels}
                out[name] = TrajectoryDataset(
                    part.states, part.measurements.clone(), part.inputs, meta
                )
            elif not torch.equal(out[name].states, part.states):
                raise DatasetError(
                    f"the {name} split at sigma {sigma} has other trajectories than at sigma "
                    f"{levels[0]}; the system must draw its noise after the trajectories."
                )
            pick = choice[name] == i
            out[name].measurements[pick] = part.measurements[pick]
    log.info("training data: noise levels %s, one per sequence", levels)
    return out


def load_inference_data(system, cfg: DictConfig, sigma: float) -> TrajectoryDataset:
    """The inference set at ``sigma``: ``eval.num_sequences`` x ``eval.length`` from ``eval.seed``."""
    e = cfg.eval
    dcfg = _dataset_config(
        cfg,
        name="inference",
        num_sequences=e.num_sequences,
        length=e.length,
        sigma=float(sigma),
        seed=e.seed,
        splits={"inference": 1.0},
        inference=None,
        regenerate=False,
    )
    return load_or_generate(system, dcfg, cache_dir=_abs(dcfg.cache_dir))["inference"]


def _sigmas(cfg: DictConfig) -> list[float]:
    sigmas = (
        [float(cfg.eval.sigma)]
        if cfg.eval.sigma is not None
        else [float(s) for s in cfg.eval.sigmas]
    )
    for s in sigmas:
        if not (math.isfinite(s) and s >= 0):
            raise ValueError(f"eval sigmas must be finite and >= 0, got {s!r}.")
    return sigmas


def _load_weights(model: ResidualObserver, where: str, device) -> tuple[Path, dict]:
    """Loads the weights of ``where`` (a checkpoint, or a run folder: its ``best.pt``) into
    ``model``, checking it is the same model; returns the file and the checkpoint."""
    path = resolve_checkpoint(_abs(where), name="best.pt")
    ckpt = load_checkpoint(path, expected_signature=model.signature(), map_location=device)
    model.load_state_dict(ckpt["model"])
    return path, ckpt


def check_config(cfg: DictConfig) -> None:
    """Raises ``ValueError`` unless ``cfg`` fits :class:`~manifold_nets.train_config.RunConfig`.

    Composing already checks overrides; this also catches keys appended with ``+``.
    """
    try:
        OmegaConf.merge(OmegaConf.structured(RunConfig), OmegaConf.to_container(cfg))
    except Exception as err:  # omegaconf's ConfigKeyError / ValidationError
        msg = str(err).splitlines()[0]
        raise ValueError(
            f"the config does not fit the schema: {msg} (not in the schema "
            "manifold_nets/train_config.py; check the spelling)."
        ) from None


def run(cfg: DictConfig, out_dir: str | Path) -> dict:
    """Runs one experiment into ``out_dir`` (see the module docstring); returns the metrics."""
    check_config(cfg)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    resolved = OmegaConf.to_container(cfg, resolve=True)
    write_text_atomic(out_dir / "config.yaml", OmegaConf.to_yaml(resolved))
    sigmas = _sigmas(cfg)  # every check that needs no work, first
    check_schedule(cfg.train.schedule, float(cfg.train.lr), float(cfg.train.lr_min))
    if cfg.train.init_from and cfg.train.resume:
        raise ValueError(
            f"train.init_from={cfg.train.init_from!r} and train.resume={cfg.train.resume!r}: "
            "resume continues a run (its weights, optimizer and epoch), init_from starts a new "
            "one from a model's weights; set only one."
        )
    if cfg.train.threads is not None:
        torch.set_num_threads(int(cfg.train.threads))
    device = resolve_device(cfg.train.device)

    from hydra.utils import instantiate

    system = instantiate(cfg.system)
    _check_system(system)
    meth = cfg.method
    # rows are labelled by method; a trained observer by its experiment (paper_cpu, ...)
    label = meth.label or (cfg.name if meth.name == "learned" and not meth.target else meth.name)
    learned = meth.name in LEARNED_METHODS and not meth.target
    metrics: dict[str, Any] = {
        "name": cfg.name,
        "method": label,
        "seed": int(cfg.seed),
        "skip_steps": int(cfg.eval.skip_steps),
        "out_dir": str(out_dir),
    }
    if not learned:
        factory = _method_factory(system, meth)  # fails before any work for an unknown method
        metrics["method_params"] = dict(meth.params)
    elif meth.name == "untrained" and cfg.eval.checkpoint:
        raise ValueError(
            "method=untrained evaluates the observer at its initialisation; it cannot load "
            f"eval.checkpoint={cfg.eval.checkpoint!r} (use method=learned for that)."
        )
    model = None
    if learned:
        torch.manual_seed(int(cfg.seed))
        model = build_observer(
            system.group, system.measurement_dim, system.input_dim, cfg.model
        ).to(device)
        log.info(
            "observer: %s, %d parameters",
            model.signature(),
            sum(p.numel() for p in model.parameters()),
        )
    if learned and cfg.eval.checkpoint:
        path, ckpt = _load_weights(model, cfg.eval.checkpoint, device)
        metrics.update(
            checkpoint=str(path),
            best_epoch=ckpt["epoch"],
            best_val_loss=ckpt.get("best", {}).get("val_loss"),
        )
        log.info("evaluating %s (epoch %s)", path, ckpt["epoch"])
    elif meth.name == "learned" and learned:
        t = cfg.train
        if t.init_from:
            path, ckpt = _load_weights(model, t.init_from, device)
            metrics["init_from"] = str(path)
            log.info("starting from the weights of %s (epoch %s)", path, ckpt["epoch"])
        parts = load_training_data(system, cfg)
        if t.compile:
            model.compile_step()
            log.info("the observer's step is compiled (torch.compile): the first batch waits")
        t0 = time.perf_counter()
        result = fit(
            model,
            parts["train"],
            parts["val"],
            out_dir=out_dir,
            epochs=t.epochs,
            batch_size=t.batch_size,
            lr=t.lr,
            weight_decay=t.weight_decay,
            schedule=t.schedule,
            lr_min=t.lr_min,
            grad_clip=t.grad_clip,
            max_batches=t.max_batches,
            eval_batch_size=t.eval_batch_size,
            seed=int(cfg.seed),
            noise_sigma=(t.noise.sigma_min, t.noise.sigma_max),
            system=system,
            config=resolved,
            resume=_abs(t.resume) if t.resume else None,
            progress=t.progress,
        )
        best = load_checkpoint(
            result.best_path, expected_signature=model.signature(), map_location=device
        )
        model.load_state_dict(best["model"])
        metrics.update(
            best_epoch=result.best_epoch,
            best_val_loss=result.best_val_loss,
            train_seconds=time.perf_counter() - t0,
            checkpoint=str(result.best_path),
        )
        if cfg.eval.test_split and "test" in parts:
            metrics["test_loss"] = validation_loss(
                model.to(device), parts["test"], t.eval_batch_size
            )
            log.info(
                "test loss of the best model (epoch %d): %.5g",
                result.best_epoch,
                metrics["test_loss"],
            )

    res_dir = out_dir / "results"
    what = cfg.name if label == cfg.name else f"{cfg.name}, method {label}"
    rows, curves = [], {}
    for sigma in sigmas:
        data = load_inference_data(system, cfg, sigma)
        if learned:
            est = ObserverEstimator(model, label, cfg.train.eval_batch_size)
        else:
            est = make_estimator(system, factory, sigma, **dict(meth.params))
            metrics.setdefault("estimators", {})[f"{sigma:g}"] = repr(est)
        r = evaluate(est, data, system, skip=cfg.eval.skip_steps)
        r.row = {
            "sigma": sigma,
            "method": label,
            **{k: v for k, v in r.row.items() if k != "sigma"},
            "seconds": r.seconds,
            "us/step": 1e6 * r.seconds / (len(data) * data.length),
        }
        rows.append(r.row)
        curves[f"{sigma:g}"] = {
            k: [None if math.isnan(x) else x for x in v.tolist()] for k, v in r.curves.items()
        }
        if cfg.eval.plots:
            plot_errors(
                r,
                res_dir / f"errors_sigma{sigma:g}.png",
                title=f"{what}: sigma = {sigma:g}, {len(data)} x {data.length} steps",
            )
        log.info(
            "sigma %g: %s",
            sigma,
            {k: (float(f"{v:.4g}") if isinstance(v, float) else v) for k, v in r.row.items()},
        )
    _, md_path = write_table(rows, res_dir / "table", title=f"{what} (seed {cfg.seed})")
    metrics["table"] = rows
    write_text_atomic(res_dir / "metrics.json", json.dumps(metrics, indent=1, default=str) + "\n")
    write_text_atomic(res_dir / "curves.json", json.dumps(curves) + "\n")
    log.info("results in %s\n%s", res_dir, md_path.read_text())
    return metrics


def _hydra_main(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    run(cfg, HydraConfig.get().runtime.output_dir)


def main() -> None:
    """The command-line entry (config root ``configs/``, primary config ``train.yaml``)."""
    import hydra

    hydra.main(version_base="1.3", config_path="../configs", config_name="train")(_hydra_main)()


if __name__ == "__main__":
    main()
