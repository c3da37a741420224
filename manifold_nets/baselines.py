"""Model-free baselines for any system: the raw measurement and dead reckoning.

Every estimator here (and :class:`manifold_nets.ekf.ErrorStateEKF`, the rigid body's
complementary filter) has the same small interface, :class:`Estimator`: a ``name``, the
``group`` of its estimates and ``estimate(data) -> (N, T+1, *element_shape)``, estimates
``xhat_0 .. xhat_T`` aligned with ``data.states`` like the learned observer's rollout, so that
``System.metrics`` and the evaluation tables read them unchanged.

What a :class:`~manifold_nets.system.System` must provide:

* :class:`RawMeasurement`: ``state_from_measurement(y)``, the state read off ``y`` (measured
  factors as they are, the unmeasured ones at the identity). ``xhat_0 = e`` (no measurement
  at ``k = 0``), ``xhat_k = state_from_measurement(y_k)``.
* :class:`DeadReckoning`: ``state_from_measurement`` for the start and
  ``drive_from_measurement(y, u)``, the drive as read (for the rigid body the biased velocity
  readings); ``xhat_0 = e``, ``xhat_1 = state_from_measurement(y_1)``, then
  ``xhat_{k+1} = step(xhat_k, drive_from_measurement(y_{k+1}, u_k))``, the system's own
  dynamics. (No oracle start from the true ``x_0``: it would carry true values of factors,
  such as the rigid body's biases, that dead reckoning never uses.)
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

import torch

from groups import LieGroup

from .data import TrajectoryDataset

__all__ = ["DeadReckoning", "Estimator", "RawMeasurement", "make_estimator"]


@runtime_checkable
class Estimator(Protocol):
    """A state estimator run over whole datasets."""

    name: str
    group: LieGroup

    def estimate(self, data: TrajectoryDataset) -> torch.Tensor:
        """``(N, T+1, *group.element_shape)``: ``xhat_0 .. xhat_T``."""
        ...


def _check_data(system, data: TrajectoryDataset, who: str) -> None:
    if not isinstance(data, TrajectoryDataset):
        raise TypeError(f"{who}.estimate needs a TrajectoryDataset, got {type(data).__name__}.")
    if data.measurements.shape[-1] != system.measurement_dim:
        raise ValueError(
            f"{who}: the data has measurements of size {data.measurements.shape[-1]}, "
            f"{type(system).__name__} measures {system.measurement_dim}: data from another system?"
        )


class RawMeasurement:
    """The state read off each measurement: ``xhat_k = state_from_measurement(y_k)``, ``xhat_0 = e``."""

    name = "raw"

    def __init__(self, system):
        self.system = system
        self.group = system.group

    def __repr__(self) -> str:
        return f"RawMeasurement({type(self.system).__name__})"

    def estimate(self, data: TrajectoryDataset) -> torch.Tensor:
        _check_data(self.system, data, "RawMeasurement")
        y = data.measurements
        x = self.system.state_from_measurement(y)  # (N, T, *element_shape)
        x0 = self.group.identity((len(data), 1), dtype=y.dtype, device=y.device)
        return torch.cat((x0, x), dim=1)


class DeadReckoning:
    """Integrates the drive as read with the system's ``step``; see the module docstring."""

    name = "dead_reckoning"

    def __init__(self, system):
        self.system = system
        self.group = system.group

    def __repr__(self) -> str:
        return f"DeadReckoning({type(self.system).__name__})"

    def estimate(self, data: TrajectoryDataset) -> torch.Tensor:
        _check_data(self.system, data, "DeadReckoning")
        s, y, u = self.system, data.measurements, data.inputs
        n, t = y.shape[:2]
        est = y.new_empty(n, t + 1, *self.group.element_shape)
        est[:, 0] = self.group.identity((n,), dtype=y.dtype, device=y.device)
        est[:, 1] = s.state_from_measurement(y[:, 0])
        for k in range(1, t):
            est[:, k + 1] = s.step(est[:, k], s.drive_from_measurement(y[:, k], u[:, k]))
        return est


def _takes_sigma(factory: Callable[..., Any]) -> bool:
    try:
        params = inspect.signature(factory).parameters.values()
    except (TypeError, ValueError):  # no signature (a builtin): call it without sigma
        return False
    return any(p.name == "sigma" or p.kind is p.VAR_KEYWORD for p in params)


def make_estimator(
    system, method: str | Callable[..., Any], sigma: float, **params: Any
) -> Estimator:
    """The estimator ``method`` of ``system`` for data of noise level ``sigma``.

    ``method`` is a name of ``system.estimators()`` (``raw``, ``dead_reckoning``, ``ekf``, ...)
    or a factory; the factory is called as ``factory(system, sigma=sigma, **params)``, without
    ``sigma`` when it takes none (a model-free baseline). The result must be an
    :class:`Estimator` on the system's group.
    """
    if isinstance(method, str):
        table = system.estimators()
        if method not in table:
            raise ValueError(
                f"method={method!r}: {type(system).__name__} has no estimator of that name; it "
                f"has {sorted(table)} (System.estimators()), besides the learned observer "
                "(learned, untrained). Or set method.target to the dotted path of a factory "
                "(system, sigma=..., **params) -> Estimator."
            )
        factory = table[method]
    else:
        factory = method
    try:
        est = factory(system, sigma=sigma, **params) if _takes_sigma(factory) else factory(
            system, **params
        )
    except TypeError as err:
        raise TypeError(f"method {method!r} with params {params}: {err}") from None
    if not isinstance(est, Estimator):
        raise TypeError(
            f"method {method!r} made a {type(est).__name__}, not an Estimator (name, group, "
            "estimate(data))."
        )
    if tuple(est.group.element_shape) != tuple(system.group.element_shape):
        raise ValueError(
            f"method {method!r} estimates elements of shape {tuple(est.group.element_shape)}, "
            f"the system's states are {tuple(system.group.element_shape)}."
        )
    return est
