"""An optional TensorBoard log of a run: losses and learning rate per epoch, evaluation metrics.

The training loop knows nothing of TensorBoard: :func:`manifold_nets.training.fit` calls an
``on_epoch(row)`` callback, and the train command (``train.tensorboard=true``) hands it
:meth:`TensorBoardLog.on_epoch`, writing into ``<run folder>/tensorboard/``::

    tensorboard --logdir outputs/            # every run, side by side

Tags: ``loss/train``, ``loss/val``, ``loss/best_val``, ``lr`` and ``epoch_seconds`` per epoch
(step: the epoch, 0 the starting model); ``loss/test`` and one ``eval/sigma<s>/<column>`` per
metric column of the results table (spaces as ``_``, ``us/step`` as ``us_per_step``) at the
evaluated model's epoch. Needs the ``tensorboard`` package: ``pip install
'manifold_nets[logging]'`` (:func:`check_tensorboard` says so before any work).
"""

from __future__ import annotations

import importlib.util
import math
import os
from collections.abc import Iterable, Mapping

__all__ = ["EPOCH_TAGS", "TensorBoardLog", "check_tensorboard", "eval_tag"]

#: ``{key of a fit log row: TensorBoard tag}``.
EPOCH_TAGS = {
    "train_loss": "loss/train",
    "val_loss": "loss/val",
    "best_val_loss": "loss/best_val",
    "lr": "lr",
    "seconds": "epoch_seconds",
}
_NOT_METRICS = ("sigma", "method", "sequences", "steps")


def check_tensorboard(setting: str = "train.tensorboard=true") -> None:
    """Raises ``ImportError`` naming the extra to install unless ``tensorboard`` is importable."""
    if importlib.util.find_spec("tensorboard") is None:
        raise ImportError(
            f"{setting} writes TensorBoard files and needs the tensorboard package: "
            "pip install 'manifold_nets[logging]' (or pip install tensorboard)."
        )


def eval_tag(sigma: float, column: str) -> str:
    """The tag of a results-table column at ``sigma``: ``eval/sigma0.1/R_est``."""
    return f"eval/sigma{float(sigma):g}/" + column.replace("/", "_per_").replace(" ", "_")


class TensorBoardLog:
    """A ``torch.utils.tensorboard.SummaryWriter`` into ``log_dir`` fed with a run's rows."""

    def __init__(self, log_dir: str | os.PathLike):
        check_tensorboard()
        from torch.utils.tensorboard import SummaryWriter

        self.log_dir = log_dir
        self.writer = SummaryWriter(log_dir=str(log_dir))

    def on_epoch(self, row: Mapping) -> None:
        """One epoch's row of :func:`~manifold_nets.training.fit` (``epoch``, losses, ``lr``...)."""
        step = int(row["epoch"])
        for key, tag in EPOCH_TAGS.items():
            if row.get(key) is not None:
                self.writer.add_scalar(tag, float(row[key]), step)
        self.writer.flush()

    def results(self, rows: Iterable[Mapping], step: int = 0, test_loss: float | None = None):
        """The evaluation's table rows (one per sigma) and the test loss, at ``step``."""
        if test_loss is not None:
            self.writer.add_scalar("loss/test", float(test_loss), step)
        for row in rows:
            for column, value in row.items():
                if column in _NOT_METRICS or not isinstance(value, (int, float)):
                    continue
                if math.isfinite(value):
                    self.writer.add_scalar(eval_tag(row["sigma"], column), float(value), step)
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()
