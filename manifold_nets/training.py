"""Training the observer: BPTT through the whole rollout, AdamW, best-validation model, resume.

:func:`fit` runs the paper's protocol (Algorithm 1): every batch is rolled out from the
identity over its whole length, the loss is the embedding MSE ``L`` of
:mod:`manifold_nets.losses`, gradients flow back through every step and group update, and
AdamW (lr 3e-4, weight decay 0.1 by default) updates the weights. After every epoch the
validation loss is computed; the model with the smallest one is kept (``best.pt``).

The learning rate is constant (the paper names no schedule) or, with ``schedule="cosine"``,
follows :func:`learning_rate`: a half cosine, one value per epoch, from ``lr`` in the first epoch
down towards ``lr_min`` (a function of the epoch alone, so a resumed run gets the same rates).
``param_lr`` gives some parameters their own rate (:func:`param_groups`), scaled by the same
schedule: new parts of a fine-tuned model (say learned robust weights) move in a few hundred
steps what the rest, at a small rate, would not.

Files written in ``out_dir``:

* ``checkpoints/last.pt`` after every epoch: weights, optimizer, epoch, the generator states,
  the best validation loss and the history: everything to resume (``resume=``) exactly as if
  the run had not been interrupted;
* ``checkpoints/best.pt`` whenever the validation loss improves (epoch 0 is the starting
  model, so a best checkpoint exists from the start; with ``epochs=0`` it is all there is: a
  model whose weights came from elsewhere, validated and saved with this run's ``config``);
* ``log.csv`` and ``log.json``: one row per epoch (train loss, validation loss, best, time).

``on_epoch(row)``, when given, is called with a copy of every new row (epoch 0 included; a
resumed run continues from its next epoch): the hook for loggers (the train command's
TensorBoard writer, :mod:`manifold_nets.tensorboard_log`) and early looks, without the loop
knowing any of them.

Training data: a fixed :class:`~manifold_nets.data.TrajectoryDataset`, or a stream (a
:class:`~manifold_nets.streaming.SimulatedStream`, or any
:class:`~manifold_nets.streaming.DataStream`: ``epoch(int) -> TrajectoryDataset``) from which
every epoch ``e`` draws ``train_data.epoch(e)``, fresh simulated sequences; the batch order,
augmentation, transform, ``tbptt``, ``max_batches`` and resume are the same either way (a stream
gives the same data for the same epoch, so a resumed run sees what the uninterrupted one saw).
Validation stays on the fixed ``val_data``.

Settings come as one :class:`~manifold_nets.config.TrainSettings` (the ``train`` group of the
config schema). Data augmentation is a batch transform handed to :func:`fit`
(:class:`~manifold_nets.augmentation.MeasurementNoise` adds measurement noise of a random
sigma per sequence through the system's noise model); validation data stay as given.

A NaN or Inf loss stops training with :class:`TrainingDiverged`, naming the epoch and batch,
and leaves ``best.pt`` and ``last.pt`` (the last good epoch) in place.

Randomness: the batch order and the training noise come from one ``torch.Generator`` seeded
with ``seed``; the model's initialisation is the caller's (seed torch before building it).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tqdm.auto import tqdm

from .atomic import write_text_atomic
from .checkpoint import (
    CheckpointError,
    load_checkpoint,
    load_state,
    resolve_checkpoint,
    save_checkpoint,
)
from .config import TrainSettings
from .data import TrajectoryDataset
from .losses import embedding_factor_log_mse, embedding_log_mse, embedding_mse
from .observer import ObserverState, ResidualObserver
from .streaming import DataStream

__all__ = [
    "BatchAugment",
    "BatchTransform",
    "StartFn",
    "batch_loss",
    "initial_state",
    "EpochCallback",
    "FitResult",
    "TrainingDiverged",
    "check_schedule",
    "check_settings",
    "fit",
    "learning_rate",
    "validation_loss",
]

#: A batch transform: ``(measurements (B, T, l), generator) -> measurements``, applied to every
#: training batch before the rollout (e.g. :class:`~manifold_nets.augmentation.MeasurementNoise`).
BatchTransform = Callable[[torch.Tensor, torch.Generator], torch.Tensor]

#: A whole-batch transform: ``(batch, generator) -> batch`` (:class:`TrajectoryDataset`), e.g. a
#: random sensor mounting that rotates the readings and the true states together.
BatchAugment = Callable[[TrajectoryDataset, torch.Generator], TrajectoryDataset]

#: Where rollouts start: ``batch -> (B, *element_shape)`` initial estimates.
StartFn = Callable[[TrajectoryDataset], torch.Tensor]

#: A per-epoch callback: called with each log row (``epoch``, ``train_loss`` (``None`` for
#: epoch 0), ``val_loss``, ``best_val_loss``, ``best_epoch``, ``lr``, ``seconds``).
EpochCallback = Callable[[dict], None]

log = logging.getLogger(__name__)

SCHEDULES = ("constant", "cosine")

#: The training losses (``train.loss``), each ``(group, estimates, states, mask=) -> scalar``:
#: ``mse`` the paper's ``L``, ``log_mse`` the mean of each sequence's ``log L_i`` (every
#: sequence's relative error weighs alike, whatever its noise level), ``factor_log_mse`` the mean
#: of each sequence's ``log L_if`` over the factors too (every factor's relative error weighs
#: alike; :mod:`~manifold_nets.losses`).
LOSSES = {
    "mse": embedding_mse, "log_mse": embedding_log_mse, "factor_log_mse": embedding_factor_log_mse
}

_LOG_FIELDS = ("epoch", "train_loss", "val_loss", "best_val_loss", "best_epoch", "lr", "seconds")


def check_schedule(schedule: str, lr: float, lr_min: float = 0.0) -> None:
    """Raises ``ValueError`` naming the setting unless the learning-rate settings are usable."""
    if schedule not in SCHEDULES:
        raise ValueError(
            f"schedule={schedule!r} is not a schedule; choose one of {', '.join(SCHEDULES)}."
        )
    if not (math.isfinite(lr) and lr > 0):
        raise ValueError(f"lr must be a positive number, got {lr!r}.")
    if not (math.isfinite(lr_min) and 0.0 <= lr_min <= lr):
        raise ValueError(
            f"lr_min must satisfy 0 <= lr_min <= lr = {lr}, got {lr_min!r}; it is where the "
            "cosine schedule's learning rate ends."
        )


def check_settings(settings: TrainSettings) -> TrainSettings:
    """Raises ``ValueError`` naming the setting unless ``settings`` can train; returns them.

    Every message starts with the name of the setting (``lr must ...``)."""
    if not isinstance(settings, TrainSettings):
        raise TypeError(
            f"settings must be a manifold_nets.TrainSettings, got {type(settings).__name__}."
        )
    if not _is_int(settings.epochs) or settings.epochs < 0:
        raise ValueError(
            f"epochs must be an integer >= 0 (0: no step, the starting model is kept), got "
            f"{settings.epochs!r}."
        )
    for name in ("batch_size", "eval_batch_size"):
        val = getattr(settings, name)
        if not _is_int(val) or val < 1:
            raise ValueError(f"{name} must be an integer >= 1, got {val!r}.")
    for name, none in (
        ("max_batches", "the whole training split"),
        ("tbptt", "backpropagation through the whole rollout"),
        ("threads", "torch's default"),
    ):
        val = getattr(settings, name)
        if val is not None and (not _is_int(val) or val < 1):
            raise ValueError(f"{name} must be an integer >= 1 or None (null: {none}), got {val!r}.")
    clip = settings.grad_clip
    if clip is not None and (
        isinstance(clip, bool)
        or not isinstance(clip, (int, float))
        or not (math.isfinite(clip) and clip > 0)
    ):
        raise ValueError(
            f"grad_clip must be > 0 or None (null: no clipping), got {clip!r}; it is the largest "
            "norm the gradient is clipped to (a negative one would ascend, zero would freeze the "
            "model), e.g. 1.0."
        )
    check_schedule(settings.schedule, float(settings.lr), float(settings.lr_min))
    for prefix, rate in dict(settings.param_lr or {}).items():
        if not isinstance(prefix, str) or not prefix:
            raise ValueError(f"param_lr: each key must be a parameter-name prefix, got {prefix!r}.")
        if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not (
            math.isfinite(rate) and rate > 0
        ):
            raise ValueError(
                f"param_lr[{prefix!r}] must be a positive learning rate, got {rate!r}."
            )
    if settings.loss not in LOSSES:
        raise ValueError(
            f"loss={settings.loss!r} is not a training loss; choose one of {', '.join(LOSSES)}."
        )
    skip = settings.skip_steps
    if not _is_int(skip) or skip < 1:
        raise ValueError(
            f"skip_steps must be an integer >= 1 (1: only the fixed start x_0 is left out of the "
            f"loss), got {skip!r}."
        )
    if settings.tbptt is not None and skip > settings.tbptt:
        raise ValueError(
            f"skip_steps={skip} is longer than a truncated-BPTT piece (tbptt={settings.tbptt}): "
            "the first piece would have no step in the loss; use skip_steps <= tbptt."
        )
    return settings


def _is_int(val) -> bool:
    return isinstance(val, int) and not isinstance(val, bool)


def learning_rate(
    epoch: int, *, epochs: int, lr: float, schedule: str = "constant", lr_min: float = 0.0
) -> float:
    """The learning rate of ``epoch`` (1 .. ``epochs``) under ``schedule``.

    ``constant``: ``lr`` throughout. ``cosine``: ``lr_min + (lr - lr_min) (1 + cos(pi (epoch -
    1) / epochs)) / 2``: ``lr`` in the first epoch, falling along a half cosine that would reach
    ``lr_min`` after the last (so no epoch is spent at ``lr_min = 0``).
    """
    check_schedule(schedule, lr, lr_min)
    if schedule == "constant":
        return float(lr)
    frac = (epoch - 1) / epochs
    return float(lr_min + (lr - lr_min) * 0.5 * (1.0 + math.cos(math.pi * frac)))


def param_groups(model: torch.nn.Module, lr: float, param_lr: dict | None) -> list[dict]:
    """The optimizer's parameter groups: the parameters whose name
    (``model.named_parameters()``) starts with a key of ``param_lr`` train at its learning rate,
    the rest at ``lr``; first the rest, then one group per key. Each group's ``lr_scale`` is its
    rate over ``lr``, so a schedule scales every group alike.

    Raises ``ValueError`` for a key that names no parameter, or a parameter two keys name."""
    named = list(model.named_parameters())
    param_lr = dict(param_lr or {})
    owner: dict[str, str] = {}
    for prefix in param_lr:
        hits = [name for name, _ in named if name.startswith(prefix)]
        if not hits:
            tops = sorted({name.split(".")[0] for name, _ in named})
            raise ValueError(
                f"param_lr[{prefix!r}] names no parameter of the model; a key is the start of "
                f"parameter names, e.g. one of the model's parts {tops}."
            )
        for name in hits:
            if name in owner:
                raise ValueError(
                    f"param_lr: the parameter {name!r} starts with both {owner[name]!r} and "
                    f"{prefix!r}; give each parameter one learning rate."
                )
            owner[name] = prefix
    groups = [{"params": [p for name, p in named if name not in owner], "lr_scale": 1.0}]
    for prefix, rate in param_lr.items():
        groups.append({
            "params": [p for name, p in named if owner.get(name) == prefix],
            "lr": float(rate),
            "lr_scale": float(rate) / float(lr),
        })
    return groups


class TrainingDiverged(FloatingPointError):
    """The training or validation loss became NaN or Inf."""


@dataclass
class FitResult:
    """What :func:`fit` leaves behind."""

    best_epoch: int
    best_val_loss: float
    history: list[dict] = field(default_factory=list)
    best_path: Path | None = None
    last_path: Path | None = None


def _write_logs(out_dir: Path, history: list[dict]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=_LOG_FIELDS, extrasaction="ignore")
    w.writeheader()
    w.writerows(history)
    write_text_atomic(out_dir / "log.csv", buf.getvalue())
    write_text_atomic(out_dir / "log.json", json.dumps(history, indent=1) + "\n")


def batch_loss(
    model: ResidualObserver,
    batch: TrajectoryDataset,
    start: StartFn | None = None,
    loss: str = "mse",
    skip: int = 1,
) -> torch.Tensor:
    """The loss (:data:`LOSSES`; default the embedding MSE ``L``) of ``model`` rolled out over
    ``batch`` (its steps ``k < skip`` and those whose true state is unknown, ``batch.mask``
    False, left out), started at ``start(batch)`` or the identity."""
    inputs = batch.inputs if batch.inputs.shape[-1] else None
    est = model(batch.measurements, inputs, state=initial_state(model, batch, start))
    return LOSSES[loss](model.group, est, batch.states.to(est), skip=skip, mask=batch.mask)


def initial_state(
    model: ResidualObserver, batch: TrajectoryDataset, start: StartFn | None = None
) -> ObserverState | None:
    """Where ``batch``'s rollout starts: ``start(batch)`` and the core's initial hidden state, or
    ``None`` (the observer's own start, the identity) without ``start``."""
    if start is None:
        return None
    x0 = start(batch).to(device=model.device, dtype=model.state_dtype)
    return ObserverState(x0, model.core.initial_hidden(len(batch), device=model.device))


def _chunks(batch: TrajectoryDataset, length: int):
    """``batch`` cut along time into pieces of ``length`` steps; piece ``i`` holds states
    ``x_{iL} .. x_{(i+1)L}`` (the first is where the previous piece ended)."""
    for a in range(0, batch.length, length):
        b = min(a + length, batch.length)
        mask = None if batch.mask is None else batch.mask[:, a : b + 1]
        yield TrajectoryDataset(
            batch.states[:, a : b + 1], batch.measurements[:, a:b], batch.inputs[:, a:b],
            batch.meta, mask,
        )


@torch.no_grad()
def validation_loss(
    model: ResidualObserver,
    data: TrajectoryDataset,
    batch_size: int = 500,
    start: StartFn | None = None,
    loss: str = "mse",
    skip: int = 1,
) -> float:
    """The loss (:data:`LOSSES`; default the embedding MSE ``L``) of ``model`` on ``data``,
    averaged over all its sequences (steps ``k < skip`` left out)."""
    was = model.training
    model.eval()
    total = 0.0
    n = len(data)
    for s in range(0, n, batch_size):
        idx = torch.arange(s, min(n, s + batch_size))
        total += float(batch_loss(model, data[idx], start, loss, skip)) * len(idx)
    model.train(was)
    return total / n


def _prepare(
    data: TrajectoryDataset, model: ResidualObserver, device, name: str
) -> TrajectoryDataset:
    """``data`` checked against the model and moved to the device (states in the state dtype)."""
    if not isinstance(data, TrajectoryDataset):
        raise TypeError(f"{name} data must be a TrajectoryDataset, got {type(data).__name__}.")
    g = model.group
    if tuple(data.states.shape[2:]) != tuple(g.element_shape):
        raise ValueError(
            f"{name} data has states of element shape {tuple(data.states.shape[2:])}, but the "
            f"observer's group {g!r} has {tuple(g.element_shape)}: data from another system?"
        )
    if (
        data.measurements.shape[-1] != model.measurement_dim
        or data.inputs.shape[-1] != model.input_dim
    ):
        raise ValueError(
            f"{name} data has measurements of size {data.measurements.shape[-1]} and inputs of "
            f"size {data.inputs.shape[-1]}; the observer expects {model.measurement_dim} and "
            f"{model.input_dim}: data from another system?"
        )
    return TrajectoryDataset(
        data.states.to(device=device, dtype=model.state_dtype),
        data.measurements.to(device=device),
        data.inputs.to(device=device),
        data.meta,
        None if data.mask is None else data.mask.to(device=device),
    )


def fit(
    model: ResidualObserver,
    train_data: TrajectoryDataset | DataStream,
    val_data: TrajectoryDataset,
    settings: TrainSettings,
    *,
    out_dir: str | os.PathLike,
    seed: int = 0,
    transform: BatchTransform | None = None,
    config: dict | None = None,
    on_epoch: EpochCallback | None = None,
    augment: BatchAugment | None = None,
    start: StartFn | None = None,
) -> FitResult:
    """Trains ``model`` in place (it ends with the *last* epoch's weights; load ``best.pt`` for
    the best) and returns a :class:`FitResult`. See the module docstring for the files.

    ``train_data``: a :class:`TrajectoryDataset`, or a stream (``train_data.epoch(e)`` is the
    data of epoch ``e``, e.g. :class:`~manifold_nets.streaming.SimulatedStream`), drawn afresh
    every epoch. ``val_data`` is fixed.

    ``settings`` (:class:`~manifold_nets.config.TrainSettings`): ``epochs``, ``batch_size``,
    ``lr``, ``weight_decay``, ``schedule`` and ``lr_min`` (each epoch's rate from
    :func:`learning_rate`), ``grad_clip``, ``max_batches``, ``eval_batch_size``, ``progress``,
    and ``resume``: a ``last.pt`` (or a run folder holding one) of the same model, training then
    continues after its epoch. ``transform`` is applied to every training batch's measurements
    with the run's generator (seeded by ``seed``, like the batch order). ``config`` (plain data)
    is stored in the checkpoints. ``on_epoch`` is called with each new log row.

    ``augment(batch, generator) -> batch`` transforms a whole training batch (states,
    measurements, inputs, mask together: e.g. the sensor mounted differently), before
    ``transform``. ``start(batch) -> (B, *element_shape)`` is where every rollout (training and
    validation) starts, e.g. an attitude from the first measurement; default the identity (the
    paper's). Steps whose true state is unknown (``data.mask``) are left out of the loss.
    """
    check_settings(settings)
    stream = _stream(train_data, settings)
    trainer = _Trainer(model, settings, Path(out_dir), seed, config or {})
    trainer.on_epoch = on_epoch
    trainer.augment, trainer.start_fn = augment, start
    train = None if stream is not None else _prepare(train_data, model, trainer.device, "training")
    val = _prepare(val_data, model, trainer.device, "validation")
    first = 1 if settings.resume is None else trainer.resume(settings.resume)
    if stream is not None and first <= settings.epochs:  # checked before epoch 0's files
        train = _prepare(stream.epoch(first), model, trainer.device, "training")
    if first == 1:
        trainer.start(val)
    model.train()
    for epoch in range(first, settings.epochs + 1):
        if stream is not None and epoch > first:
            train = _prepare(stream.epoch(epoch), model, trainer.device, "training")
        trainer.epoch(epoch, train, val, transform)
    return trainer.result()


def _stream(train_data, settings: TrainSettings) -> DataStream | None:
    """``train_data`` when it is a stream (it has ``epoch``), ``None`` for a fixed dataset."""
    if isinstance(train_data, TrajectoryDataset):
        if settings.stream:
            raise ValueError(
                "stream=True, but train_data is a fixed TrajectoryDataset: pass a stream "
                "(manifold_nets.streaming.SimulatedStream(system, ...)) as train_data, or set "
                "stream=False."
            )
        return None
    if not callable(getattr(train_data, "epoch", None)):
        raise TypeError(
            "training data must be a TrajectoryDataset or a stream with epoch(int) -> "
            f"TrajectoryDataset (e.g. manifold_nets.streaming.SimulatedStream), got "
            f"{type(train_data).__name__}."
        )
    return train_data


class _Trainer:
    """The state of one :func:`fit`: optimizer, generator, history, best, checkpoint files."""

    def __init__(self, model, settings: TrainSettings, out_dir: Path, seed: int, config: dict):
        self.model, self.settings, self.out_dir, self.config = model, settings, out_dir, config
        ckpt_dir = out_dir / "checkpoints"
        ckpt_dir.mkdir(parents=True, exist_ok=True)
        self.best_path, self.last_path = ckpt_dir / "best.pt", ckpt_dir / "last.pt"
        self.device = model.device
        self.signature = model.signature()
        self.gen = torch.Generator().manual_seed(int(seed))
        self.opt = torch.optim.AdamW(
            param_groups(model, settings.lr, settings.param_lr),
            lr=settings.lr, weight_decay=settings.weight_decay,
        )
        self.history: list[dict] = []
        self.best = {"epoch": 0, "val_loss": math.inf}
        self.on_epoch: EpochCallback | None = None
        self.augment: BatchAugment | None = None
        self.start_fn: StartFn | None = None

    def tell(self, row: dict) -> None:
        """Hands a new log row to ``on_epoch`` (a copy: the history stays the trainer's)."""
        if self.on_epoch is not None:
            self.on_epoch(dict(row))

    def payload(self, epoch: int, full: bool) -> dict:
        """What a checkpoint holds: ``best.pt`` the weights, ``last.pt`` all to resume."""
        p = {
            "model": self.model.state_dict(),
            "signature": self.signature,
            "config": self.config,
            "epoch": epoch,
            "best": dict(self.best),
        }
        if full:
            p.update(
                optimizer=self.opt.state_dict(),
                history=self.history,
                rng={"generator": self.gen.get_state(), "torch": torch.get_rng_state()},
            )
        return p

    def resume(self, where: str | os.PathLike) -> int:
        """Restores everything from ``where``'s ``last.pt``; returns the next epoch."""
        path = resolve_checkpoint(where)
        ckpt = load_checkpoint(path, expected_signature=self.signature, map_location=self.device)
        if "optimizer" not in ckpt or "rng" not in ckpt or "best" not in ckpt:
            raise CheckpointError(
                f"{path} holds no optimizer/RNG/best state: resume from a last.pt."
            )
        for name in ("generator", "torch"):  # tried on a scratch generator: nothing changes yet
            try:
                torch.Generator().set_state(ckpt["rng"][name].cpu())
            except RuntimeError as err:
                raise CheckpointError(
                    f"{path}: the field 'rng.{name}' is not a generator state ({err}). The file "
                    "is damaged; resume from another last.pt, or start afresh."
                ) from None
        load_state(self.model, ckpt, path)
        try:
            self.opt.load_state_dict(ckpt["optimizer"])
        except (ValueError, KeyError, TypeError, RuntimeError) as err:
            raise CheckpointError(
                f"{path}: the field 'optimizer' does not fit this model's optimizer "
                f"({type(err).__name__}: {str(err)[:300]}). The file is damaged; resume from "
                "another last.pt, or start afresh."
            ) from None
        self.gen.set_state(ckpt["rng"]["generator"].cpu())
        torch.set_rng_state(ckpt["rng"]["torch"].cpu())
        self.history = list(ckpt.get("history", []))
        self.best = dict(ckpt["best"])
        if Path(path).resolve() != self.last_path.resolve():  # resuming into a new folder
            src_best = Path(path).parent / "best.pt"
            if src_best.is_file():
                b = load_checkpoint(src_best, expected_signature=self.signature)
                save_checkpoint(self.best_path, b)
        log.info(
            "resumed from %s after epoch %d (best val %.4g at epoch %d)",
            path, ckpt["epoch"], self.best["val_loss"], self.best["epoch"],
        )
        return int(ckpt["epoch"]) + 1

    def diverged(self, what: str, value: float, epoch: int, batch: int | None = None):
        where = f"epoch {epoch}" + (f", batch {batch}" if batch is not None else "")
        kept = (
            f"the best checkpoint (epoch {self.best['epoch']}, val loss "
            f"{self.best['val_loss']:.4g}) is kept at {self.best_path}"
            if self.best_path.is_file()
            else "no checkpoint was written yet"
        )
        return TrainingDiverged(
            f"the {what} became {value} at {where}; training stopped. {kept}. Try a smaller "
            "learning rate (lr), gradient clipping (grad_clip=1.0) or a float64 network "
            "(net_dtype float64)."
        )

    def start(self, val: TrajectoryDataset) -> None:
        """Epoch 0: the starting model's validation loss, its ``best.pt`` and log row."""
        s = self.settings
        v0 = validation_loss(
            self.model, val, s.eval_batch_size, self.start_fn, s.loss, s.skip_steps
        )
        if not math.isfinite(v0):
            raise self.diverged("validation loss of the starting model", v0, 0)
        self.best = {"epoch": 0, "val_loss": v0}
        self.history.append(
            {"epoch": 0, "train_loss": None, "val_loss": v0, "best_val_loss": v0,
             "best_epoch": 0, "lr": self.settings.lr, "seconds": 0.0}
        )
        save_checkpoint(self.best_path, self.payload(0, full=False))
        _write_logs(self.out_dir, self.history)
        self.tell(self.history[-1])
        log.info("epoch 0 (before any step): val loss %.5g", v0)

    def epoch(self, epoch: int, train, val, transform: BatchTransform | None) -> None:
        """One pass over the training split, then validation, checkpoints and the log row."""
        s, t0 = self.settings, time.perf_counter()
        rate = learning_rate(
            epoch, epochs=s.epochs, lr=s.lr, schedule=s.schedule, lr_min=s.lr_min
        )
        for group in self.opt.param_groups:  # each group's own lr on the same schedule
            group["lr"] = rate * group.get("lr_scale", 1.0)
        batches = list(torch.randperm(len(train), generator=self.gen).split(s.batch_size))
        if s.max_batches is not None:
            batches = batches[: s.max_batches]
        train_loss = self.train_batches(epoch, train, batches, transform)
        val_loss = validation_loss(
            self.model, val, s.eval_batch_size, self.start_fn, s.loss, s.skip_steps
        )
        if not math.isfinite(val_loss):
            raise self.diverged("validation loss", val_loss, epoch)
        if val_loss < self.best["val_loss"]:
            self.best = {"epoch": epoch, "val_loss": val_loss}
            save_checkpoint(self.best_path, self.payload(epoch, full=False))
        row = {
            "epoch": epoch,
            "train_loss": train_loss,
            "val_loss": val_loss,
            "best_val_loss": self.best["val_loss"],
            "best_epoch": self.best["epoch"],
            "lr": self.opt.param_groups[0]["lr"],
            "seconds": time.perf_counter() - t0,
        }
        self.history.append(row)
        save_checkpoint(self.last_path, self.payload(epoch, full=True))
        _write_logs(self.out_dir, self.history)
        self.tell(row)
        log.info(
            "epoch %d/%d: train loss %.5g, val loss %.5g (best %.5g at epoch %d), %.1f s",
            epoch, s.epochs, train_loss, val_loss, self.best["val_loss"], self.best["epoch"],
            row["seconds"],
        )

    def train_batches(self, epoch, train, batches, transform) -> float:
        """BPTT and an optimizer step per batch; returns the epoch's mean training loss."""
        model, s = self.model, self.settings
        running, count = 0.0, 0
        bar = tqdm(
            batches,
            desc=f"epoch {epoch}/{s.epochs}",
            leave=False,
            dynamic_ncols=True,
            disable=None if s.progress else True,
        )
        for b, idx in enumerate(bar, 1):
            batch = train[idx.to(train.measurements.device)]
            if self.augment is not None:
                batch = self.augment(batch, self.gen)
            if transform is not None:
                batch.measurements = transform(batch.measurements, self.gen)
            if s.tbptt is None:
                value = self.optimise(
                    batch_loss(model, batch, self.start_fn, s.loss, s.skip_steps)
                )
            else:
                value = self.truncated(batch)
            if not math.isfinite(value):
                bar.close()
                raise self.diverged("training loss", value, epoch, b)
            running += value * len(idx)
            count += len(idx)
            bar.set_postfix(loss=f"{running / count:.4g}")
        bar.close()
        return running / max(count, 1)

    def optimise(self, loss: torch.Tensor) -> float:
        """One optimizer step on ``loss`` (skipped when it is not finite); returns its value."""
        value = loss.item()
        if not math.isfinite(value):
            return value
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        if self.settings.grad_clip is not None:
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.settings.grad_clip)
        self.opt.step()
        return value

    def truncated(self, batch: TrajectoryDataset) -> float:
        """Truncated BPTT: an optimizer step per ``tbptt`` steps of the rollout, the estimate and
        the hidden state carried (detached) into the next piece; returns the mean loss."""
        model = self.model
        state = initial_state(model, batch, self.start_fn)
        if state is None:
            state = model.init_state(len(batch))
        total, length = 0.0, batch.length
        for i, piece in enumerate(_chunks(batch, self.settings.tbptt)):
            inputs = piece.inputs if piece.inputs.shape[-1] else None
            est, state = model(piece.measurements, inputs, state=state, return_state=True)
            skip = self.settings.skip_steps if i == 0 else 1  # a later piece's x_0 was counted
            loss = LOSSES[self.settings.loss](
                model.group, est, piece.states.to(est), skip=skip, mask=piece.mask
            )
            value = self.optimise(loss)
            if not math.isfinite(value):
                return value
            total += value * (piece.length / length)  # one piece: its value, to the last bit
            state = state._replace(
                estimate=state.estimate.detach(), hidden=tuple(h.detach() for h in state.hidden)
            )
        return total

    def result(self) -> FitResult:
        last = self.last_path if self.last_path.is_file() else None
        return FitResult(
            self.best["epoch"], self.best["val_loss"], self.history, self.best_path, last
        )
