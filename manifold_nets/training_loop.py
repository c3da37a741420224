"""The training loop: :func:`fit` and the state of one run (optimizer, generator, history, best,
checkpoint files, resume), the log files it writes and the check that the loss has not diverged.

:mod:`manifold_nets.training` describes the protocol, the files written and the settings; the
loss of a batch is in :mod:`manifold_nets.training_losses`, the checks of the settings and the
learning-rate schedule in :mod:`manifold_nets.training_settings`.
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
from .graphed_step import GraphedStep, check_graphable
from .observer import ResidualObserver
from .losses import check_loss_weights
from .streaming import DataStream
from .training_losses import (
    LOSSES,
    StartFn,
    _chunks,
    batch_loss,
    initial_state,
    validation_loss,
)
from .training_settings import check_settings, learning_rate, param_groups

__all__ = [
    "BatchAugment",
    "BatchTransform",
    "EXPLODED",
    "EpochCallback",
    "FitResult",
    "TrainingDiverged",
    "exploded",
    "fit",
]

#: A batch transform: ``(measurements (B, T, l), generator) -> measurements``, applied to every
#: training batch before the rollout (e.g. :class:`~manifold_nets.augmentation.MeasurementNoise`).
BatchTransform = Callable[[torch.Tensor, torch.Generator], torch.Tensor]

#: A whole-batch transform: ``(batch, generator) -> batch`` (:class:`TrajectoryDataset`), e.g. a
#: random sensor mounting that rotates the readings and the true states together.
BatchAugment = Callable[[TrajectoryDataset, torch.Generator], TrajectoryDataset]

#: A per-epoch callback: called with each log row (``epoch``, ``train_loss`` (``None`` for
#: epoch 0), ``val_loss``, ``best_val_loss``, ``best_epoch``, ``lr``, ``seconds``).
EpochCallback = Callable[[dict], None]

# the logger of manifold_nets.training, where this loop was written: its name is what log
# settings and filters select
log = logging.getLogger("manifold_nets.training")

_LOG_FIELDS = ("epoch", "train_loss", "val_loss", "best_val_loss", "best_epoch", "lr", "seconds")


class TrainingDiverged(FloatingPointError):
    """The training or validation loss became NaN or Inf, or exploded
    (:mod:`manifold_nets.training`)."""


#: A starting validation loss above this: the untrained observer's steps grow without bound.
EXPLODED = 1e12


def exploded(value: float, start: float) -> bool:
    """Whether a finite training or validation ``value`` has exploded against the starting
    model's validation loss ``start``: above ``max(1e4 |start|, 1e6)``."""
    return value > max(1e4 * abs(start), 1e6)


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
    the best) and returns a :class:`FitResult`. See :mod:`manifold_nets.training` for the
    files.

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
    check_loss_weights(settings.loss_weights, model.group.embedding_dim)
    if settings.cuda_graph:
        check_graphable(model.device, settings.tbptt, start)
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
    began = time.monotonic()
    for epoch in range(first, settings.epochs + 1):
        if stream is not None and epoch > first:
            train = _prepare(stream.epoch(epoch), model, trainer.device, "training")
        start_epoch = time.monotonic()
        trainer.epoch(epoch, train, val, transform)
        now = time.monotonic()
        if epoch < settings.epochs and _out_of_time(settings, now - began, now - start_epoch):
            log.info("train.time_limit (%.3g min): stopped after epoch %d of %d",
                     settings.time_limit, epoch, settings.epochs)
            break
    return trainer.result()


def _out_of_time(settings: TrainSettings, spent: float, last: float) -> bool:
    """Whether another epoch as long as the ``last`` would end past ``settings.time_limit``."""
    return settings.time_limit is not None and spent + last > 60.0 * settings.time_limit


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
            lr=settings.lr, weight_decay=settings.weight_decay, capturable=settings.cuda_graph,
        )
        self.graphed = GraphedStep(model, self.opt, settings, self.optimise)
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
        happened = f"became {value}"
        if math.isfinite(value) and self.history:
            limit = max(1e4 * abs(self.history[0]["val_loss"]), 1e6)
            happened = f"exploded without going NaN ({value:.4g}, over {limit:.3g})"
        elif math.isfinite(value):
            happened = (
                f"is {value:.4g}, over {EXPLODED:g}: the untrained observer's steps grow without "
                "bound (start its head at zero: let the observer make its core; or add an "
                "output scale)"
            )
        return TrainingDiverged(
            f"the {what} {happened} at {where}; training stopped. {kept}. Try a smaller "
            "learning rate (lr), gradient clipping (grad_clip=1.0) or a float64 network "
            "(net_dtype float64)."
        )

    def start(self, val: TrajectoryDataset) -> None:
        """Epoch 0: the starting model's validation loss, its ``best.pt`` and log row."""
        s = self.settings
        v0 = validation_loss(
            self.model, val, s.eval_batch_size, self.start_fn, s.loss, s.skip_steps,
            s.loss_weights,
        )
        if not math.isfinite(v0) or v0 > EXPLODED:
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
            self.model, val, s.eval_batch_size, self.start_fn, s.loss, s.skip_steps,
            s.loss_weights,
        )
        if not math.isfinite(val_loss) or exploded(val_loss, self.history[0]["val_loss"]):
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
            if s.cuda_graph:
                value = self.graphed(batch)
            elif s.tbptt is None:
                value = self.optimise(
                    batch_loss(model, batch, self.start_fn, s.loss, s.skip_steps, s.loss_weights)
                )
            else:
                value = self.truncated(batch)
            if not math.isfinite(value) or exploded(value, self.history[0]["val_loss"]):
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
                model.group, est, piece.states.to(est), skip=skip, mask=piece.mask,
                weights=self.settings.loss_weights,
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
