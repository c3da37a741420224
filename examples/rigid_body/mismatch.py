"""The paper's rigid body with a wrong model: the data break what a model-based filter assumes.

:class:`MismatchedRigidBody` simulates the same motion as :class:`~.system.RigidBody` and
measures it with the errors real sensors have and the nominal model leaves out. Its ``step``,
``observe``, ``apply_noise`` and ``measurement_residual`` stay the nominal ones, so a filter built
on it (``method=ekf``) is the EKF with the nominal model; only :meth:`simulate` draws the truth:

* ``scale_factor``, ``misalignment``: per sequence, each velocity sensor (gyro, velocity) reads
  ``M_i w_i + b_i + noise`` with ``M_i = exp([a_i]x) (I + diag(s_i))``,
  ``s_i ~ N(0, scale_factor^2 I_3)``, ``a_i ~ N(0, misalignment^2 I_3)`` (rad);
* ``bias_walk``: the biases drift, ``b_{k+1} = b_k + bias_walk sqrt(dt) e_k``, ``e_k ~ N(0, I_6)``
  (units per sqrt(s)); the states carry the drifting biases, which is what the metrics compare;
* ``noise_dof``: Student-t measurement noise with that many degrees of freedom (an integer >= 3,
  scaled to variance ``sigma^2``; 0: Gaussian);
* ``outlier_prob``, ``outlier_scale``: each 3-vector of noise (w1 .. w4) at each step is, with
  probability ``outlier_prob``, ``outlier_scale`` times larger;
* ``noise_correlation``: every noise component is an AR(1) process over the steps,
  ``n_k = rho n_{k-1} + sqrt(1 - rho^2) e_k`` (stationary, variance ``sigma^2``).

With every parameter at 0 (the defaults) the data are the nominal rigid body's, bit for bit.
Draws, in this order from the one generator: the initial states and the drives (as the nominal
system), the sensor errors ``s``, ``a`` (when nonzero), the bias walk (when nonzero), then the
noise (only when ``sigma > 0``): so the states and the sensor errors are the same at every sigma,
as :func:`manifold_nets.datasets.noise_level_mixture` requires.
"""

from __future__ import annotations

import math

import torch

from groups import SO3
from manifold_nets.data import TrajectoryDataset
from manifold_nets.system import check_number, check_simulate_args

from .system import RigidBody

__all__ = ["MismatchedRigidBody"]

_DTYPE = torch.float64
_SO3 = SO3()
_WHO = "MismatchedRigidBody"


class MismatchedRigidBody(RigidBody):
    """The rigid body whose sensors break the nominal model; see the module docstring.

    Keyword arguments besides the mismatch are :class:`~.system.RigidBody`'s.
    """

    name = "rigid_body_mismatch"

    def __init__(
        self,
        *,
        scale_factor: float = 0.0,
        misalignment: float = 0.0,
        bias_walk: float = 0.0,
        noise_dof: int = 0,
        outlier_prob: float = 0.0,
        outlier_scale: float = 10.0,
        noise_correlation: float = 0.0,
        **nominal,
    ):
        super().__init__(**nominal)
        self.scale_factor = check_number(_WHO, "scale_factor", scale_factor)
        self.misalignment = check_number(_WHO, "misalignment", misalignment)
        self.bias_walk = check_number(_WHO, "bias_walk", bias_walk)
        if self.scale_factor > 0.25 or self.misalignment > 0.25:
            raise ValueError(
                f"{_WHO}: scale_factor={scale_factor!r} and misalignment={misalignment!r} are "
                "standard deviations of small sensor errors and must be <= 0.25 (25 %, 0.25 rad)."
            )
        if isinstance(noise_dof, bool) or not isinstance(noise_dof, int) or noise_dof in (1, 2) \
                or noise_dof < 0:
            raise ValueError(
                f"{_WHO}: noise_dof must be 0 (Gaussian noise) or an integer >= 3 (Student-t "
                f"with finite variance), got {noise_dof!r}."
            )
        self.noise_dof = noise_dof
        self.outlier_prob = check_number(_WHO, "outlier_prob", outlier_prob)
        if not self.outlier_prob < 1:
            raise ValueError(f"{_WHO}: outlier_prob must be in [0, 1), got {outlier_prob!r}.")
        self.outlier_scale = check_number(_WHO, "outlier_scale", outlier_scale)
        if self.outlier_scale < 1:
            raise ValueError(
                f"{_WHO}: outlier_scale must be >= 1 (an outlier is larger), got {outlier_scale!r}."
            )
        self.noise_correlation = check_number(_WHO, "noise_correlation", noise_correlation)
        if not self.noise_correlation < 1:
            raise ValueError(
                f"{_WHO}: noise_correlation is an AR(1) coefficient and must be in [0, 1), got "
                f"{noise_correlation!r}."
            )

    def config(self) -> dict:
        return {
            **super().config(),
            "scale_factor": self.scale_factor,
            "misalignment": self.misalignment,
            "bias_walk": self.bias_walk,
            "noise_dof": self.noise_dof,
            "outlier_prob": self.outlier_prob,
            "outlier_scale": self.outlier_scale,
            "noise_correlation": self.noise_correlation,
        }

    def estimators(self) -> dict:
        """:class:`~.system.RigidBody`'s, and on the paper's group ``ekf_ar1``
        (:class:`~.correlated_noise.CorrelatedNoiseEKF`): the EKF told the noise's true AR(1)
        law (``noise_correlation``), the oracle row of the correlated-noise mismatch."""
        out = super().estimators()
        if self.pose_group == "so3_r3":
            from .correlated_noise import CorrelatedNoiseEKF

            out["ekf_ar1"] = CorrelatedNoiseEKF
        return out

    # ------------------------------------------------------------------ the truth

    def sensor_matrices(self, num_sequences: int, generator: torch.Generator) -> torch.Tensor:
        """``(N, 2, 3, 3)``: ``M_i = exp([a_i]x) (I + diag(s_i))`` for the gyro (0) and the
        velocity sensor (1); ``s`` drawn before ``a``, each only when its parameter is > 0."""
        n = num_sequences
        s = torch.zeros(n, 2, 3, dtype=_DTYPE)
        a = torch.zeros(n, 2, 3, dtype=_DTYPE)
        if self.scale_factor > 0:
            s = torch.randn(n, 2, 3, generator=generator, dtype=_DTYPE) * self.scale_factor
        if self.misalignment > 0:
            a = torch.randn(n, 2, 3, generator=generator, dtype=_DTYPE) * self.misalignment
        return _SO3.exp(a) * (1.0 + s).unsqueeze(-2)  # exp([a]x) @ diag(1 + s)

    def sample_noise(
        self, num_sequences: int, length: int, sigma: float, generator: torch.Generator
    ) -> torch.Tensor:
        """``(N, T, 12)`` measurement noise ``(w1, w2, w3, w4)`` of the configured law, times
        ``sigma`` (variance ``sigma^2`` per component, whatever the law)."""
        n, t = num_sequences, length
        e = torch.randn(n, t, 12, generator=generator, dtype=_DTYPE)
        if self.noise_dof:
            nu = self.noise_dof
            chi2 = torch.randn(n, t, 12, nu, generator=generator, dtype=_DTYPE).square().sum(-1)
            e = e / (chi2 / nu).sqrt() * math.sqrt((nu - 2) / nu)  # Student-t, unit variance
        if self.outlier_prob > 0:
            hit = torch.rand(n, t, 4, generator=generator, dtype=_DTYPE) < self.outlier_prob
            e = torch.where(hit.repeat_interleave(3, dim=-1), e * self.outlier_scale, e)
        rho = self.noise_correlation
        if rho > 0:
            keep = math.sqrt(1.0 - rho * rho)
            for k in range(1, t):  # n_k = rho n_{k-1} + sqrt(1 - rho^2) e_k, n_0 = e_0
                e[:, k].mul_(keep).add_(e[:, k - 1], alpha=rho)
        return e.mul_(sigma)

    def simulate(
        self,
        num_sequences: int,
        length: int,
        sigma: float,
        generator: torch.Generator,
        *,
        show_progress: bool = False,
    ) -> TrajectoryDataset:
        """The nominal motion measured by the mismatched sensors; see the module docstring for
        the laws and the order of the draws. Everything is float64."""
        n, t, sigma = check_simulate_args(num_sequences, length, sigma, generator)
        x0 = self.sample_initial_state(n, generator)
        drive = self.sample_drive(n, t, generator)
        sensed = drive
        if self.scale_factor > 0 or self.misalignment > 0:
            M = self.sensor_matrices(n, generator)  # (N, 2, 3, 3)
            w = drive.unflatten(-1, (2, 3)).unsqueeze(-1)  # (N, T, 2, 3, 1)
            sensed = (M.unsqueeze(1) @ w).squeeze(-1).flatten(-2)
        states = self.rollout(x0, drive, show_progress=show_progress)
        if self.bias_walk > 0:
            steps = torch.randn(n, t, 6, generator=generator, dtype=_DTYPE)
            states[:, 1:, -6:] += steps.mul_(self.bias_walk * math.sqrt(self.dt)).cumsum(1)
        noise = self.sample_noise(n, t, sigma, generator) if sigma > 0 else None
        measurements = self.measure(states[:, 1:], sensed, noise)
        return self.trajectory_dataset(states, measurements, drive, sigma)
