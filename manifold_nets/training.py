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
and leaves ``best.pt`` and ``last.pt`` (the last good epoch) in place; so does a loss that
explodes without going NaN: above ``EXPLODED`` (1e12) before any step, or during training above
``max(1e4 |v_0|, 1e6)``, ``v_0`` the starting model's validation loss.

Randomness: the batch order and the training noise come from one ``torch.Generator`` seeded
with ``seed``; the model's initialisation is the caller's (seed torch before building it).

The code is in three modules, gathered here: :mod:`manifold_nets.training_loop` (:func:`fit`, the
run's state, checkpoints, logs, divergence), :mod:`manifold_nets.training_losses` (the loss of a
batch, the validation loss, the pieces of truncated BPTT) and
:mod:`manifold_nets.training_settings` (the checks of the settings, the learning-rate schedule
and the parameter groups).
"""

from __future__ import annotations

from .training_loop import (  # noqa: F401  (_-names: importable here as they always were)
    EXPLODED,
    BatchAugment,
    BatchTransform,
    EpochCallback,
    FitResult,
    TrainingDiverged,
    _LOG_FIELDS,
    _prepare,
    _stream,
    _Trainer,
    _write_logs,
    exploded,
    fit,
    log,
)
from .training_losses import (  # noqa: F401
    LOSSES,
    StartFn,
    _chunks,
    batch_loss,
    initial_state,
    validation_loss,
)
from .training_settings import (  # noqa: F401
    SCHEDULES,
    _is_int,
    check_schedule,
    check_settings,
    learning_rate,
    param_groups,
)

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
    "EXPLODED",
    "LOSSES",
    "SCHEDULES",
    "exploded",
    "param_groups",
]
