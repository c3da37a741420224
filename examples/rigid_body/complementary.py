"""The rigid body's complementary filter (Mahony, Hamel and Pflimlin's, with bias estimation,
plus its position analogue): :class:`ComplementaryFilter`, its gains and their grid search,
:func:`tune_complementary_gains`.

The filter's equations: :mod:`manifold_nets_examples.rigid_body.filters`.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import asdict, dataclass

import torch

from groups import SO3
from groups.so3 import unskew
from manifold_nets.data import TrajectoryDataset
from manifold_nets.ekf import check_noise_level

from .filter_support import _check_system, _repeat
from .system import RigidBody

__all__ = ["ComplementaryFilter", "ComplementaryGains", "tune_complementary_gains"]

_SO3 = SO3()
# the logger of the module this was split from (filters), the name log settings select
log = logging.getLogger(__name__.rpartition(".")[0] + ".filters")


@dataclass(frozen=True)
class ComplementaryGains:
    """Continuous-time gains: attitude ``k_P``, gyro bias ``k_I``, position ``k_p``, velocity
    bias ``k_b`` (each step applies ``gain * dt``). Defaults: the grid search's choice at
    sigma = 0.3, dt = 0.1; tune them for other settings (:func:`tune_complementary_gains`)."""

    k_P: float = 4.0
    k_I: float = 16.0
    k_p: float = 2.0
    k_b: float = 4.0


class ComplementaryFilter:
    """Mahony's passive complementary filter with bias estimation, plus its position analogue.

    Starts from the first measurement: ``xhat_0 = e`` (nothing known), ``xhat_1 = (R^m_1,
    p^m_1, 0, 0)``, then filters. Gains may be tensors ``(N,)`` (one set per sequence), which is
    how :func:`tune_complementary_gains` runs a whole grid in one batch.
    """

    name = "complementary"

    def __init__(self, system: RigidBody, gains: ComplementaryGains | None = None):
        _check_system(system, "ComplementaryFilter")
        self.system = system
        self.group = system.group
        self.gains = gains or ComplementaryGains()

    @classmethod
    def tuned(cls, system: RigidBody, sigma: float, **search) -> ComplementaryFilter:
        """The filter with its gains chosen for ``sigma`` by :func:`tune_complementary_gains`
        (keyword arguments go to the search); what ``method=complementary`` runs."""
        gains, _ = tune_complementary_gains(
            system, check_noise_level("ComplementaryFilter.tuned", sigma), **search
        )
        log.info("complementary filter, sigma %g: gains %s", sigma, gains)
        return cls(system, gains)

    def filter(self, measurements: torch.Tensor, gains: dict | None = None) -> torch.Tensor:
        """Estimates ``(N, T+1, 18)`` from ``measurements`` ``(N, T, 18)``.

        ``gains`` maps ``k_P``, ``k_I``, ``k_p``, ``k_b`` to floats or ``(N,)`` tensors
        (default: ``self.gains``).
        """
        if measurements.dim() != 3 or measurements.shape[-1] != 18:
            raise ValueError(f"measurements must be (N, T, 18), got {tuple(measurements.shape)}.")
        n, t = measurements.shape[:2]
        dt = self.system.dt
        g = asdict(self.gains) if gains is None else gains

        def col(name):
            k = torch.as_tensor(g[name], dtype=measurements.dtype, device=measurements.device)
            return (k * dt).reshape(-1, 1) if k.dim() else k * dt

        aP, aI, ap, ab = col("k_P"), col("k_I"), col("k_p"), col("k_b")
        est = measurements.new_empty(n, t + 1, 18)
        est[:, 0] = self.group.identity((n,), dtype=measurements.dtype, device=measurements.device)
        x = self.system.state_from_measurement(measurements[:, 0])
        est[:, 1] = x
        for k in range(1, t):
            y = measurements[:, k]
            b = x[:, 12:]
            xm = self.system.step(x, y[:, 12:] - b)  # predict with bias-corrected readings
            Rm_ = xm[:, :9].unflatten(-1, (3, 3))
            Ry = y[:, :9].unflatten(-1, (3, 3))
            omega = unskew(Rm_.transpose(-1, -2) @ Ry)  # vex(P_a(Rhat^T R^m))
            R = Rm_ @ _SO3.exp(aP * omega)
            e = y[:, 9:12] - xm[:, 9:12]
            p = xm[:, 9:12] + ap * e
            b_omega = b[:, :3] - aI * omega
            b_v = b[:, 3:] - ab * (Rm_.transpose(-1, -2) @ e.unsqueeze(-1)).squeeze(-1)
            x = torch.cat((R.flatten(-2), p, b_omega, b_v), dim=-1)
            est[:, k + 1] = x
        return est

    def __repr__(self) -> str:
        g = self.gains
        return f"ComplementaryFilter(k_P={g.k_P:g}, k_I={g.k_I:g}, k_p={g.k_p:g}, k_b={g.k_b:g})"

    def estimate(self, data: TrajectoryDataset) -> torch.Tensor:
        """Estimates ``(N, T+1, 18)`` on ``data`` with ``self.gains``."""
        return self.filter(data.measurements)


#: Gains in 1/s; with dt = 0.1 a step applies at most ``10 * dt = 1`` of the correction. The
#: biases (up to 10 rad/s, 10 m/s) need large integral gains to be learnt in a few seconds.
_DEFAULT_GRID = {
    "k_P": (1.0, 2.0, 4.0, 6.0, 8.0, 10.0),
    "k_I": (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0),
    "k_p": (1.0, 2.0, 4.0, 6.0, 8.0, 10.0),
    "k_b": (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0),
}


def tune_complementary_gains(
    system: RigidBody,
    sigma: float,
    grid: dict | None = None,
    num_sequences: int = 32,
    length: int = 500,
    seed: int = 10_000,
    skip: int = 10,
) -> tuple[ComplementaryGains, dict]:
    """Grid search of the complementary filter's gains on a simulated validation set.

    Simulates ``num_sequences x length`` at ``sigma`` from ``seed`` (keep it apart from the
    inference sets' seeds), then picks ``(k_P, k_I)`` minimising the mean ``||Rhat - R||_F`` and,
    with those, ``(k_p, k_b)`` minimising the mean ``||phat - p||``, over steps ``>= skip``
    (the attitude does not depend on the position gains). Each grid runs as one batch.
    Returns the gains and ``{"attitude": {(k_P, k_I): err}, "position": {(k_p, k_b): err}}``.
    """
    grid = {**_DEFAULT_GRID, **(grid or {})}
    data = system.simulate(num_sequences, length, sigma, torch.Generator().manual_seed(seed))
    cf = ComplementaryFilter(system)
    base = asdict(ComplementaryGains())
    scores: dict = {}
    best = dict(base)
    for part, (a, b), factor in (
        ("attitude", ("k_P", "k_I"), "R"),
        ("position", ("k_p", "k_b"), "p"),
    ):
        combos = list(itertools.product(grid[a], grid[b]))
        reps = len(combos)
        y = data.measurements.repeat(reps, 1, 1)
        gains = {k: float(v) for k, v in best.items()}
        gains[a] = torch.tensor([c[0] for c in combos]).repeat_interleave(num_sequences)
        gains[b] = torch.tensor([c[1] for c in combos]).repeat_interleave(num_sequences)
        est = cf.filter(y, gains)
        err = system.metrics(est, _repeat(data, reps))[factor]
        mean = err[:, skip:].mean(1).reshape(reps, num_sequences).mean(1)
        scores[part] = {c: float(m) for c, m in zip(combos, mean)}
        i = int(mean.argmin())
        best[a], best[b] = combos[i]
    return ComplementaryGains(**best), scores
