"""Data augmentation for training: batch transforms handed to :func:`manifold_nets.training.fit`.

A batch transform maps a training batch's measurements ``(B, T, l)`` and the run's
``torch.Generator`` to new measurements; :func:`~manifold_nets.training.fit` applies it to every
training batch (never to validation data), so augmentation draws fresh randomness every epoch,
reproducibly from the run's seed.
"""

from __future__ import annotations

import torch

__all__ = ["MeasurementNoise"]


class MeasurementNoise:
    """Measurement noise of a per-sequence ``sigma ~ U[sigma_min, sigma_max]``, applied through the
    system's noise model: ``system.apply_noise(y, noise)`` with ``noise`` ``(B, T, noise_dim)``
    drawn from ``N(0, sigma^2 I)``.

    Meant for noise-free training data (the noise is added on top of what the batch holds).
    """

    def __init__(self, system, sigma_min: float, sigma_max: float):
        lo, hi = float(sigma_min), float(sigma_max)
        if not 0.0 <= lo <= hi:
            raise ValueError(
                f"the noise sigma range must satisfy 0 <= sigma_min <= sigma_max, got ({lo}, {hi})."
            )
        if not callable(getattr(system, "apply_noise", None)):
            raise ValueError(
                "measurement-noise augmentation needs a system with apply_noise(measurements, "
                f"noise) and noise_dim; {type(system).__name__} has none."
            )
        try:  # a system that cannot apply noise says so now, not at the first noisy batch
            system.apply_noise(
                torch.zeros(1, 1, system.measurement_dim, dtype=torch.float64),
                torch.zeros(1, 1, system.noise_dim, dtype=torch.float64),
            )
        except NotImplementedError as err:
            raise ValueError(
                f"measurement-noise augmentation needs {type(system).__name__}.apply_noise: {err}"
            ) from None
        self.system, self.sigma_min, self.sigma_max = system, lo, hi

    def __repr__(self) -> str:
        return f"MeasurementNoise(sigma ~ U[{self.sigma_min:g}, {self.sigma_max:g}])"

    def __call__(self, y: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        n, t = y.shape[:2]
        sigma = torch.empty(n, dtype=torch.float64).uniform_(
            self.sigma_min, self.sigma_max, generator=generator
        )
        noise = torch.randn(n, t, self.system.noise_dim, generator=generator, dtype=torch.float64)
        noise.mul_(sigma[:, None, None])
        return self.system.apply_noise(y.to(torch.float64).cpu(), noise).to(y)
