"""The objective of a run: the one number a hydra sweeper (Optuna) optimises.

The train and evaluate commands return it from their hydra entry, named by the config key
``objective`` (:class:`~manifold_nets.config.RunConfig`):

=============================  ===============================================================
``best_val_loss`` (default)    the validation loss of the best epoch (a training run; a run that
                               evaluates ``eval.checkpoint`` reads it from the checkpoint)
``test_loss``                  the best model's loss on the test split (a training run with
                               ``eval.test_split=true``)
``<column>``                   a metric column of the results table, averaged over the
                               evaluated sigmas: ``R est``, ``p meas``, ``R reduction %``,
                               ``membership max``, ``seconds``, ``us/step``
``<column>@<sigma>``           the column at one evaluated sigma: ``R est@0.1``
=============================  ===============================================================

:func:`parse_objective` checks the syntax (and the sigma against the evaluated ones) before any
work; the table's columns are known only after the evaluation, so :func:`objective_value`
checks the column then, naming the columns there are. A missing value or a NaN fails: a
sweeper must never optimise a number that is not one. Errors, estimate and measurement
columns, losses and times are minimised; ``reduction %`` is maximised
(:attr:`Objective.minimize`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

__all__ = ["LOSSES", "Objective", "objective_value", "parse_objective"]

#: The objectives that are losses of the training task, not table columns.
LOSSES = ("best_val_loss", "test_loss")

#: The metric columns of a results table, by form (``manifold_nets.evaluation.evaluate`` and
#: the evaluation command write them): per factor (``<name> est``, ...) or whole-run.
_SUFFIXES = (" est", " meas", " reduction %")
_WHOLE = ("membership mean", "membership max", "seconds", "us/step")

CHOICES = (
    "best_val_loss (default), test_loss, or a metric column of the results table averaged over "
    "the sigmas ('<factor> est', '<factor> meas', '<factor> reduction %', 'membership mean', "
    "'membership max', 'seconds', 'us/step'; e.g. 'R est'), or at one evaluated sigma with "
    "'<column>@<sigma>' (e.g. 'R est@0.1')"
)


@dataclass(frozen=True)
class Objective:
    """A parsed objective: a loss (``column is None``) or a table column, at ``sigma`` or the
    mean over the sigmas."""

    name: str
    column: str | None = None
    sigma: float | None = None

    @property
    def is_loss(self) -> bool:
        return self.column is None

    @property
    def minimize(self) -> bool:
        """Whether smaller is better (everything but a ``reduction %``)."""
        return self.is_loss or not self.column.endswith(" reduction %")


def _fail(name: str, why: str) -> ValueError:
    return ValueError(f"objective={name!r} {why}; choose {CHOICES}.")


def parse_objective(name: str, sigmas: Sequence[float] | None = None) -> Objective:
    """``name`` parsed, or a ``ValueError`` listing the choices; no work needed.

    With ``sigmas`` (the evaluated noise levels), ``<column>@<sigma>`` must name one of them.
    """
    if not isinstance(name, str) or not name.strip():
        raise _fail(str(name), "names nothing")
    text = name.strip()
    if text in LOSSES:
        return Objective(text)
    column, sigma = text, None
    if "@" in text:
        column, _, at = text.rpartition("@")
        column = column.strip()
        if column in LOSSES:
            raise _fail(name, f"asks for {column} at one sigma; the losses have no sigma")
        try:
            sigma = float(at)
        except ValueError:
            raise _fail(name, f"has {at!r} after '@', not a noise level") from None
        if not (math.isfinite(sigma) and sigma >= 0):
            raise _fail(name, f"has sigma {sigma!r} after '@'; a noise level is finite and >= 0")
        if sigmas is not None and not any(math.isclose(sigma, float(s)) for s in sigmas):
            listed = ", ".join(f"{float(s):g}" for s in sigmas)
            raise ValueError(
                f"objective={name!r} asks for sigma {sigma:g}, which is not evaluated "
                f"(eval.sigmas: {listed}); name one of them or drop '@{at}' for the mean."
            )
    if not (column in _WHOLE or (column.endswith(_SUFFIXES) and column not in _SUFFIXES)):
        raise _fail(name, "is not a loss or a metric column")
    return Objective(text, column, sigma)


def objective_value(objective: Objective | str, metrics: Mapping) -> float:
    """The objective's value in a run's ``metrics`` (what the commands return and write to
    ``results/metrics.json``: the training losses and the ``table`` rows, one per sigma).

    Raises ``ValueError`` naming what is missing (the loss, the column, the sigma) or when the
    value is not a finite number.
    """
    obj = parse_objective(objective) if isinstance(objective, str) else objective
    if obj.is_loss:
        value = metrics.get(obj.name)
        if value is None:
            raise ValueError(
                f"objective={obj.name!r}: this run has no {obj.name} ({_why_no_loss(obj.name)}); "
                f"choose a metric column instead, e.g. objective='R est' ({CHOICES})."
            )
        value = float(value)
    else:
        value = _column_mean(obj, list(metrics.get("table") or []))
    if not math.isfinite(value):
        raise ValueError(
            f"objective={obj.name!r} is {value} in this run: a sweeper cannot optimise it "
            "(a measurement error of 0 makes 'reduction %' NaN; a diverged estimator Inf)."
        )
    return value


def _why_no_loss(name: str) -> str:
    if name == "best_val_loss":
        return "it is recorded by training (method=learned) or read from eval.checkpoint"
    return "it is recorded by training with eval.test_split=true on data with a test split"


def _column_mean(obj: Objective, rows: list[Mapping]) -> float:
    if not rows:
        raise ValueError(f"objective={obj.name!r}: the run has no results table.")
    if obj.column not in rows[0]:
        columns = [k for k, v in rows[0].items() if isinstance(v, (int, float)) and k != "sigma"]
        raise ValueError(
            f"objective={obj.name!r}: the results table has no column {obj.column!r}; its "
            f"metric columns: {', '.join(repr(c) for c in columns)}."
        )
    if obj.sigma is not None:
        rows = [r for r in rows if math.isclose(float(r["sigma"]), obj.sigma)]
        if not rows:
            raise ValueError(
                f"objective={obj.name!r}: no row of the table has sigma {obj.sigma:g}."
            )
    values = [r.get(obj.column) for r in rows]
    if any(v is None for v in values):
        return math.nan
    return math.fsum(float(v) for v in values) / len(values)
