"""The learned observer next to the vehicle's EKF, dead reckoning and the raw fixes.

    python -m manifold_nets_examples.planar.compare outputs/planar/<id> [--sigmas 0.1] [--length N]

The comparison itself is generic (:func:`manifold_nets_examples.attitude.compare.compare_run`);
this module only names the vehicle's classical estimators. Writes ``results/compare.{csv,md}`` and
``results/compare_sigma<s>.png`` into the run folder.
"""

from __future__ import annotations

from manifold_nets_examples.attitude.compare import main

__all__ = ["planar_estimators"]


def planar_estimators(system, sigma: float) -> list:
    """The vehicle's classical estimators: its EKF and dead reckoning of the biased odometry."""
    from manifold_nets.baselines import DeadReckoning

    from .filters import PlanarEKF

    return [PlanarEKF(system, sigma), DeadReckoning(system)]


if __name__ == "__main__":
    main(planar_estimators)
