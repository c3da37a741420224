"""Training the observer: BPTT through the whole rollout, AdamW, best-validation model, resume.

:func:`fit` runs the paper's protocol (Algorithm 1): every batch is rolled out from the
identity over its whole length, the loss is the embedding MSE ``L`` of
:mod:`manifold_nets.losses`, gradients flow back through every step and group update, and
AdamW (lr 3e-4, weight decay 0.1 by default) updates the weights. After every epoch the
validation loss is computed; the model with the smallest one is kept (``best.pt``).

The learning rate is constant (the paper names no schedule) or, with ``schedule="cosine"``,
follows :func:`learning_rate`: a half cosine, one value per epoch, from ``lr`` in the first epoch
down towards ``lr_min`` (a function of the epoch alone, so a resumed run gets the same rates).

Files written in ``out_dir``:

* ``checkpoints/last.pt`` after every epoch: weights, optimizer, epoch, the generator states,
  the best validation loss and the history: everything to resume (``resume=``) exactly as if
  the run had not been interrupted;
* ``checkpoints/best.pt`` whenever the validation loss improves (epoch 0 is the starting
  model, so a best checkpoint exists from the start);
* ``log.csv`` and ``log.json``: one row per epoch (train loss, validation loss, best, time).

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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from .atomic import write_text_atomic
from .checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from .data import TrajectoryDataset
from .losses import embedding_mse
from .observer import ResidualObserver

__all__ = [
    "FitResult",
    "TrainingDiverged",
    "check_schedule",
    "fit",
    "learning_rate",
    "resolve_checkpoint",
    "validation_loss",
]

log = logging.getLogger(__name__)

SCHEDULES = ("constant", "cosine")

_LOG_FIELDS = ("epoch", "train_loss", "val_loss", "best_val_loss", "best_epoch", "lr", "seconds")


def check_schedule(schedule: str, lr: float, lr_min: float = 0.0) -> None:
    """Raises ``ValueError`` naming the setting unless the learning-rate settings are usable."""
    if schedule not in SCHEDULES:
        raise ValueError(
            f"train.schedule={schedule!r} is not a schedule; choose one of {', '.join(SCHEDULES)}."
        )
    if not (math.isfinite(lr) and lr > 0):
        raise ValueError(f"train.lr must be a positive number, got {lr!r}.")
    if not (math.isfinite(lr_min) and 0.0 <= lr_min <= lr):
        raise ValueError(
            f"train.lr_min must satisfy 0 <= lr_min <= train.lr = {lr}, got {lr_min!r}; it is "
            "where the cosine schedule's learning rate ends."
        )


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


def resolve_checkpoint(path: str | os.PathLike, name: str = "last.pt") -> Path:
    """A checkpoint file from a file path or a run folder (``<dir>/checkpoints/<name>``)."""
    p = Path(path)
    if p.is_dir():
        for cand in (p / "checkpoints" / name, p / name):
            if cand.is_file():
                return cand
        raise CheckpointError(f"no {name} in the run folder {p} (looked in {p}/checkpoints/).")
    return p


def _write_logs(out_dir: Path, history: list[dict]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=_LOG_FIELDS, extrasaction="ignore")
    w.writeheader()
    w.writerows(history)
    write_text_atomic(out_dir / "log.csv", buf.getvalue())
    write_text_atomic(out_dir / "log.json", json.dumps(history, indent=1) + "\n")


def _batches(data: TrajectoryDataset, idx: torch.Tensor):
    inputs = data.inputs[idx] if data.inputs.shape[-1] else None
    return data.measurements[idx], inputs, data.states[idx]


@torch.no_grad()
def validation_loss(
    model: ResidualObserver, data: TrajectoryDataset, batch_size: int = 500
) -> float:
    """The embedding MSE ``L`` of ``model`` on ``data``, averaged over all its sequences."""
    was = model.training
    model.eval()
    total = 0.0
    n = len(data)
    for s in range(0, n, batch_size):
        idx = torch.arange(s, min(n, s + batch_size))
        y, u, x = _batches(data, idx)
        est = model(y, u)
        total += float(embedding_mse(model.group, est, x.to(est))) * len(idx)
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
    )


def _noisy(system, y: torch.Tensor, sigma_min: float, sigma_max: float, gen: torch.Generator):
    """Noise of a per-sequence sigma ~ U[sigma_min, sigma_max] applied to clean measurements."""
    n, t = y.shape[:2]
    sigma = torch.empty(n, dtype=torch.float64).uniform_(sigma_min, sigma_max, generator=gen)
    noise = torch.randn(n, t, system.noise_dim, generator=gen, dtype=torch.float64)
    noise.mul_(sigma[:, None, None])
    return system.apply_noise(y.to(torch.float64).cpu(), noise).to(y)


def fit(
    model: ResidualObserver,
    train_data: TrajectoryDataset,
    val_data: TrajectoryDataset,
    *,
    out_dir: str | os.PathLike,
    epochs: int,
    batch_size: int = 256,
    lr: float = 3e-4,
    weight_decay: float = 0.1,
    schedule: str = "constant",
    lr_min: float = 0.0,
    grad_clip: float | None = None,
    max_batches: int | None = None,
    eval_batch_size: int = 500,
    seed: int = 0,
    noise_sigma: tuple[float, float] = (0.0, 0.0),
    system: Any = None,
    config: dict | None = None,
    resume: str | os.PathLike | None = None,
    progress: bool = True,
) -> FitResult:
    """Trains ``model`` in place (it ends with the *last* epoch's weights; load ``best.pt`` for
    the best) and returns a :class:`FitResult`. See the module docstring for the files.

    ``noise_sigma = (lo, hi)`` with ``hi > 0`` adds measurement noise of a per-sequence
    ``sigma ~ U[lo, hi]`` to every training batch through ``system.apply_noise(measurements,
    noise)`` (noise ``(N, T, system.noise_dim)``, already scaled); validation stays as given.
    ``schedule`` (``constant`` or ``cosine``, down to ``lr_min``) sets each epoch's learning
    rate through :func:`learning_rate`. ``config`` (plain data) is stored in the checkpoints.
    ``resume`` is a ``last.pt`` (or a run folder holding one) of the same model; training
    continues after its epoch.
    """
    for name, val in (
        ("epochs", epochs),
        ("batch_size", batch_size),
        ("eval_batch_size", eval_batch_size),
    ):
        if (
            isinstance(val, bool)
            or not isinstance(val, int)
            or val < (0 if name == "epochs" else 1)
        ):
            raise ValueError(f"{name} must be a positive integer, got {val!r}.")
    check_schedule(schedule, lr, lr_min)
    lo, hi = (float(s) for s in noise_sigma)
    if not 0.0 <= lo <= hi:
        raise ValueError(f"noise sigma range must satisfy 0 <= min <= max, got ({lo}, {hi}).")
    if hi > 0 and not callable(getattr(system, "apply_noise", None)):
        raise ValueError(
            "noise-augmented training needs a system with apply_noise(measurements, noise) and "
            f"noise_dim; got {type(system).__name__}. Use train.noise.sigma_max=0 (the paper's "
            "noise-free protocol) or give the system that method."
        )
    out_dir = Path(out_dir)
    ckpt_dir = out_dir / "checkpoints"
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    best_path, last_path = ckpt_dir / "best.pt", ckpt_dir / "last.pt"
    device = model.device
    train = _prepare(train_data, model, device, "training")
    val = _prepare(val_data, model, device, "validation")
    config = {} if config is None else config
    signature = model.signature()

    gen = torch.Generator().manual_seed(int(seed))
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=weight_decay)
    history: list[dict] = []
    best = {"epoch": 0, "val_loss": math.inf}
    start = 1
    if resume is not None:
        path = resolve_checkpoint(resume)
        ckpt = load_checkpoint(path, expected_signature=signature, map_location=device)
        if "optimizer" not in ckpt or "rng" not in ckpt:
            raise CheckpointError(f"{path} holds no optimizer/RNG state: resume from a last.pt.")
        model.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        gen.set_state(ckpt["rng"]["generator"])
        torch.set_rng_state(ckpt["rng"]["torch"])
        history = list(ckpt.get("history", []))
        best = dict(ckpt["best"])
        start = int(ckpt["epoch"]) + 1
        if Path(path).resolve() != last_path.resolve():  # resuming into a new folder
            src_best = Path(path).parent / "best.pt"
            if src_best.is_file():
                b = load_checkpoint(src_best, expected_signature=signature)
                save_checkpoint(best_path, b)
        log.info(
            "resumed from %s after epoch %d (best val %.4g at epoch %d)",
            path,
            start - 1,
            best["val_loss"],
            best["epoch"],
        )

    def payload(epoch: int, full: bool) -> dict:
        p = {
            "model": model.state_dict(),
            "signature": signature,
            "config": config,
            "epoch": epoch,
            "best": dict(best),
        }
        if full:
            p.update(
                optimizer=opt.state_dict(),
                history=history,
                rng={"generator": gen.get_state(), "torch": torch.get_rng_state()},
            )
        return p

    def diverged(what: str, value: float, epoch: int, batch: int | None = None) -> TrainingDiverged:
        where = f"epoch {epoch}" + (f", batch {batch}" if batch is not None else "")
        kept = (
            f"the best checkpoint (epoch {best['epoch']}, val loss {best['val_loss']:.4g}) is "
            f"kept at {best_path}"
            if best_path.is_file()
            else "no checkpoint was written yet"
        )
        return TrainingDiverged(
            f"the {what} became {value} at {where}; training stopped. {kept}. Try a smaller "
            "train.lr, gradient clipping (train.grad_clip=1.0) or a float64 network "
            "(model.net_dtype=float64)."
        )

    if start == 1:
        v0 = validation_loss(model, val, eval_batch_size)
        if not math.isfinite(v0):
            raise diverged("validation loss of the starting model", v0, 0)
        best = {"epoch": 0, "val_loss": v0}
        history.append(
            {
                "epoch": 0,
                "train_loss": None,
                "val_loss": v0,
                "best_val_loss": v0,
                "best_epoch": 0,
                "lr": lr,
                "seconds": 0.0,
            }
        )
        save_checkpoint(best_path, payload(0, full=False))
        _write_logs(out_dir, history)
        log.info("epoch 0 (before any step): val loss %.5g", v0)

    n = len(train)
    model.train()
    for epoch in range(start, epochs + 1):
        t0 = time.perf_counter()
        rate = learning_rate(epoch, epochs=epochs, lr=lr, schedule=schedule, lr_min=lr_min)
        for group in opt.param_groups:
            group["lr"] = rate
        perm = torch.randperm(n, generator=gen)
        batches = list(perm.split(batch_size))
        if max_batches is not None:
            batches = batches[:max_batches]
        running, count = 0.0, 0
        bar = tqdm(
            batches,
            desc=f"epoch {epoch}/{epochs}",
            leave=False,
            dynamic_ncols=True,
            disable=None if progress else True,
        )
        for b, idx in enumerate(bar, 1):
            y, u, x = _batches(train, idx.to(train.measurements.device))
            if hi > 0:
                y = _noisy(system, y, lo, hi, gen)
            loss = embedding_mse(model.group, model(y, u), x)
            value = loss.item()
            if not math.isfinite(value):
                bar.close()
                raise diverged("training loss", value, epoch, b)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if grad_clip is not None:
                torch.nn.utils.clip_grad_norm_(model.parameters(), grad_clip)
            opt.step()
            running += value * len(idx)
            count += len(idx)
            bar.set_postfix(loss=f"{running / count:.4g}")
        bar.close()
        train_loss = running / max(count, 1)
        val_loss = validation_loss(model, val, eval_batch_size)
        if not math.isfinite(val_loss):
            raise diverged("validation loss", val_loss, epoch)
        if val_loss < best["val_loss"]:
            best = {"epoch": epoch, "val_loss": val_loss}
            save_checkpoint(best_path, payload(epoch, full=False))
        row = {
            "epoch": epoch,
            "train_loss": train_loss,
            "val_loss": val_loss,
            "best_val_loss": best["val_loss"],
            "best_epoch": best["epoch"],
            "lr": opt.param_groups[0]["lr"],
            "seconds": time.perf_counter() - t0,
        }
        history.append(row)
        save_checkpoint(last_path, payload(epoch, full=True))
        _write_logs(out_dir, history)
        log.info(
            "epoch %d/%d: train loss %.5g, val loss %.5g (best %.5g at epoch %d), %.1f s",
            epoch,
            epochs,
            train_loss,
            val_loss,
            best["val_loss"],
            best["epoch"],
            row["seconds"],
        )
    return FitResult(
        best["epoch"],
        best["val_loss"],
        history,
        best_path,
        last_path if last_path.is_file() else None,
    )
