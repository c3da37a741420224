"""The training settings checked, and the learning rate: its schedule over the epochs and the
optimizer's parameter groups (``param_lr``: some parameters at their own rate).

Used by :func:`manifold_nets.training_loop.fit`; :mod:`manifold_nets.training` describes the
protocol.
"""

from __future__ import annotations

import math

import torch

from .config import TrainSettings
from .losses import check_loss_weights
from .training_losses import LOSSES

__all__ = ["SCHEDULES", "check_schedule", "check_settings", "learning_rate", "param_groups"]

SCHEDULES = ("constant", "cosine")


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


#: The largest noise level a setting may ask for (the measurements' units; the rigid body's
#: readings are of order 1).
MAX_SIGMA = 1e3


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
        ("threads", "one thread, or OMP_NUM_THREADS when set"),
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
    limit = settings.time_limit
    if limit is not None and (
        isinstance(limit, bool) or not isinstance(limit, (int, float))
        or not (math.isfinite(limit) and limit > 0)
    ):
        raise ValueError(
            f"time_limit must be a number of minutes > 0 or None (null: all epochs), got "
            f"{limit!r}."
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
    _check_regularisation(settings)
    if settings.loss not in LOSSES:
        raise ValueError(
            f"loss={settings.loss!r} is not a training loss; choose one of {', '.join(LOSSES)}."
        )
    check_loss_weights(settings.loss_weights)
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


def _check_regularisation(settings: TrainSettings) -> None:
    """``weight_decay`` and the training noise (``noise.*``): finite and in range."""
    wd = settings.weight_decay
    if isinstance(wd, bool) or not isinstance(wd, (int, float)) or not (
        math.isfinite(wd) and wd >= 0
    ):
        raise ValueError(f"weight_decay must be a finite number >= 0 (AdamW's), got {wd!r}.")
    noise = settings.noise
    lo, hi = noise.sigma_min, noise.sigma_max
    for name, val in (("noise.sigma_min", lo), ("noise.sigma_max", hi)):
        if isinstance(val, bool) or not isinstance(val, (int, float)) or not (
            math.isfinite(val) and 0 <= val <= MAX_SIGMA
        ):
            raise ValueError(f"{name} must be a number in [0, {MAX_SIGMA:g}], got {val!r}.")
    if hi and lo > hi:
        raise ValueError(f"noise.sigma_min={lo} is above noise.sigma_max={hi}.")
    for level in noise.levels:
        if isinstance(level, bool) or not isinstance(level, (int, float)) or not (
            math.isfinite(level) and 0 <= level <= MAX_SIGMA
        ):
            raise ValueError(
                f"noise.levels must hold numbers in [0, {MAX_SIGMA:g}], got {level!r}."
            )


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
    (``model.named_parameters()``) starts with a key of ``param_lr``, or has it as a part of its
    dotted path (``robust`` names ``prior.robust.*`` and ``measurement.robust.*``: every learned
    robust weight), train at its learning rate,
    the rest at ``lr``; first the rest, then one group per key. Each group's ``lr_scale`` is its
    rate over ``lr``, so a schedule scales every group alike.

    Raises ``ValueError`` for a key that names no parameter, or a parameter two keys name."""
    named = list(model.named_parameters())
    param_lr = dict(param_lr or {})
    owner: dict[str, str] = {}
    for prefix in param_lr:
        hits = [name for name, _ in named
                if name.startswith(prefix) or f".{prefix}." in f".{name}"]
        if not hits:
            tops = sorted({name.split(".")[0] for name, _ in named})
            raise ValueError(
                f"param_lr[{prefix!r}] names no parameter of the model; a key is the start of "
                f"parameter names, e.g. one of the model's parts {tops}."
            )
        for name in hits:
            if name in owner:
                raise ValueError(
                    f"param_lr: the parameter {name!r} is named by both {owner[name]!r} and "
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

