"""What an error-state EKF needs of a system: the :class:`FilterModel` interface (drive,
dynamics, measurement, noise, prior, optional analytic Jacobians), the plain model of a
:class:`~manifold_nets.system.System` and the model of a system whose biased readings drive its
prediction.

The filter that runs these models, and its equations: :mod:`manifold_nets.ekf`.
"""

from __future__ import annotations

import abc
import math

import torch

from groups import LieGroup

__all__ = [
    "BiasedReadingsFilterModel",
    "FilterModel",
    "SystemFilterModel",
    "check_noise_level",
]


def check_noise_level(owner: str, sigma: object) -> float:
    """``sigma`` as a float, or a ValueError unless it is finite and ``> 0``.

    A model-based filter is told the noise level of its data; it sets the filter's measurement
    (and, where readings drive the prediction, process) noise, and with ``sigma = 0`` the
    innovation covariance is singular.
    """
    if isinstance(sigma, bool) or not isinstance(sigma, (int, float)) or not 0 < sigma < math.inf:
        raise ValueError(
            f"{owner} needs the noise level sigma > 0 (its measurement and process noise; with "
            f"noise-free data the innovation covariance is singular: use the raw measurement), "
            f"got {sigma!r}."
        )
    return float(sigma)


class FilterModel(abc.ABC):
    """What an error-state EKF needs of a system: drive, dynamics, measurement and noise.

    A subclass sets ``group``, ``measurement_dim`` (size of the raw ``y``), ``input_dim``,
    ``process_noise_dim`` and ``measurement_noise_dim``, and writes :meth:`drive`, :meth:`step`,
    :meth:`measure`, :meth:`process_noise_cov`, :meth:`measurement_noise_cov` and
    :meth:`initial_state`. ``step`` and ``measure`` should be the system's own (declared once,
    serving simulator and filter). Everything must be differentiable in ``x`` and the noises
    (autograd Jacobians), and batched over leading dimensions.
    """

    group: LieGroup
    measurement_dim: int
    input_dim: int = 0
    process_noise_dim: int
    measurement_noise_dim: int
    #: ``slice(a, b)`` where the analytic ``H`` is the rows ``a .. b-1`` of the identity (the
    #: update measures that part of the error state as it is: a pose sensor): the analytic
    #: filter then takes ``P H^T``, ``H P H^T`` and ``K H`` by selection, not as products, and
    #: ignores the ``H`` of :meth:`linearize_measurement`. ``None`` (default): a general ``H``.
    measured_states: slice | None = None

    @abc.abstractmethod
    def drive(
        self, x: torch.Tensor, y: torch.Tensor, u: torch.Tensor, noise: torch.Tensor | None = None
    ) -> torch.Tensor:
        """The drive ``w_k`` ``(*batch, drive_dim)`` from the estimate ``x_k``, ``y_{k+1}``,
        ``u_k``.

        ``noise`` ``(*batch, process_noise_dim)`` is the error of that reconstruction: the true
        drive is ``drive(x_true, y, u, q_true)``. ``None`` means zero.
        """

    @abc.abstractmethod
    def step(self, x: torch.Tensor, drive: torch.Tensor) -> torch.Tensor:
        """``x_{k+1}`` from ``x_k`` and the drive (the system's dynamics)."""

    @abc.abstractmethod
    def measure(
        self, x: torch.Tensor, drive: torch.Tensor, noise: torch.Tensor | None = None
    ) -> torch.Tensor:
        """The predicted measurement the update compares with :meth:`observation`."""

    def observation(self, y: torch.Tensor) -> torch.Tensor:
        """What the update compares with :meth:`measure`, from the raw ``y``. Default: ``y``."""
        return y

    def residual(self, z: torch.Tensor, z_hat: torch.Tensor) -> torch.Tensor:
        """The innovation ``(*batch, d)``. Default: the plain difference ``z - z_hat``."""
        return z - z_hat

    @abc.abstractmethod
    def process_noise_cov(self, dtype: torch.dtype, device=None) -> torch.Tensor:
        """``Q`` ``(process_noise_dim, process_noise_dim)``, the covariance of the drive's error."""

    @abc.abstractmethod
    def measurement_noise_cov(self, dtype: torch.dtype, device=None) -> torch.Tensor:
        """``R_n`` ``(measurement_noise_dim, measurement_noise_dim)``."""

    @abc.abstractmethod
    def initial_state(
        self, batch: int, dtype: torch.dtype, device=None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The prior ``(xhat_0 (batch, *element_shape), P_0 (batch, n, n))``."""

    def state_noise_cov(self, dtype: torch.dtype, device=None) -> torch.Tensor | None:
        """``Q_e`` ``(n, n)`` (or ``(B, n, n)``), noise added to the error state over a step
        besides ``G Q G^T``: the random walk of a bias the model lets drift. Default ``None``:
        none (a constant bias)."""
        return None

    def measured_slice(self) -> slice | None:
        """:attr:`measured_states` as ``slice(start, stop)`` in the tangent space, checked."""
        sel, n = self.measured_states, self.group.tangent_dim
        if sel is not None and (not isinstance(sel, slice) or sel.step not in (None, 1)
                                or len(range(n)[sel]) == 0):  # fmt: skip
            raise ValueError(f"measured_states must be a non-empty slice or None, got {sel!r}.")
        return None if sel is None else slice(*sel.indices(n)[:2])

    # optional analytic Jacobians (jacobians="analytic")

    def process_jacobians(
        self, x: torch.Tensor, y: torch.Tensor, u: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(F (*batch, n, n), G (*batch, n, process_noise_dim))`` at ``e = 0, q = 0``."""
        raise NotImplementedError(
            f"{type(self).__name__} has no analytic process Jacobians; use jacobians='autograd' "
            f"or write process_jacobians(x, y, u) -> (F, G)."
        )

    def measurement_jacobians(
        self, x: torch.Tensor, drive: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(H (*batch, d, n), M (*batch, d, measurement_noise_dim))`` at ``e = 0, r = 0``."""
        raise NotImplementedError(
            f"{type(self).__name__} has no analytic measurement Jacobians; use "
            f"jacobians='autograd' or write measurement_jacobians(x, drive) -> (H, M)."
        )

    def reset_jacobian(self, x: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
        """``d/de rminus(x·exp(delta + e), x·exp(delta))`` at 0, ``(*batch, n, n)``. Optional."""
        raise NotImplementedError

    # the analytic filter's calls: one per stage of a step, so that a model can share the work
    # (an exp and its Jacobians) and keep the number of operations small

    def linearize_step(
        self, x: torch.Tensor, y: torch.Tensor, u: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(xhat^-, w, F, G)``: the prediction, the drive and :meth:`process_jacobians`.

        Default: :meth:`drive`, :meth:`step` and :meth:`process_jacobians`; a model overrides it
        to compute them in one pass (tested equal to them). ``F`` and ``G`` may be ``(n, n)``,
        ``(n, q)`` when they do not depend on the batch.
        """
        w = self.drive(x, y, u)
        F, G = self.process_jacobians(x, y, u)
        return self.step(x, w), w, F, G

    def linearize_measurement(
        self, x: torch.Tensor, drive: torch.Tensor, y: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """``(nu, H, M)``: the innovation ``residual(observation(y), measure(x, drive))``
        ``(*batch, d)`` and :meth:`measurement_jacobians`; ``M = None`` stands for the identity
        (the update's noise enters the residual as it is), ``H`` may be ``(d, n)``.

        Default: :meth:`measure`, :meth:`residual` and :meth:`measurement_jacobians`.
        """
        nu = self.residual(self.observation(y), self.measure(x, drive))
        H, M = self.measurement_jacobians(x, drive)
        return nu, H, M

    def linearize_reset(
        self, x: torch.Tensor, delta: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``(x·exp(delta), J)`` with ``J`` :meth:`reset_jacobian`, or ``None`` where the model
        has none (the filter then takes it by autograd). Default: ``group.rplus`` and
        :meth:`reset_jacobian`."""
        try:
            J = self.reset_jacobian(x, delta)
        except NotImplementedError:
            J = None
        return self.group.rplus(x, delta), J


class SystemFilterModel(FilterModel):
    """The plain filter model of a :class:`~manifold_nets.system.System`.

    ``drive = system.drive_from_measurement(y, u) + q`` with ``q ~ N(0, drive_noise_std^2 I)``,
    ``step = system.step``, ``measure = system.measure`` with the system's noise
    ``N(0, sigma^2 I_noise_dim)``, ``residual = system.measurement_residual``, and the prior
    ``xhat_0 = e``, ``P_0 = initial_std^2 I``. Right for a system whose drive is a known input
    and whose measurement is all update (a linear system, a pose sensor); a system whose state
    enters the drive (biases) or whose measurement carries the drive (velocity readings used
    for prediction) writes its own :class:`FilterModel` (see
    ``examples/rigid_body/filter_model.py``).
    """

    def __init__(
        self, system, sigma: float, drive_noise_std: float = 0.0, initial_std: float = 1.0
    ):
        sigma = check_noise_level("SystemFilterModel", sigma)
        if not drive_noise_std >= 0 or not initial_std > 0:
            raise ValueError(
                f"drive_noise_std must be >= 0 and initial_std > 0, got {drive_noise_std!r}, "
                f"{initial_std!r}."
            )
        self.system = system
        self.group = system.group
        self.measurement_dim = system.measurement_dim
        self.input_dim = system.input_dim
        self.process_noise_dim = system.drive_dim
        self.measurement_noise_dim = system.noise_dim
        self.sigma, self.drive_noise_std, self.initial_std = sigma, drive_noise_std, initial_std

    def drive(self, x, y, u, noise=None):
        w = self.system.drive_from_measurement(y, u)
        return w if noise is None else w + noise

    def step(self, x, drive):
        return self.system.step(x, drive)

    def measure(self, x, drive, noise=None):
        return self.system.measure(x, drive, noise)

    def residual(self, z, z_hat):
        return self.system.measurement_residual(z, z_hat)

    def process_noise_cov(self, dtype, device=None):
        return self.drive_noise_std**2 * torch.eye(
            self.process_noise_dim, dtype=dtype, device=device
        )

    def measurement_noise_cov(self, dtype, device=None):
        return self.sigma**2 * torch.eye(self.measurement_noise_dim, dtype=dtype, device=device)

    def initial_state(self, batch, dtype, device=None):
        n = self.group.tangent_dim
        x0 = self.group.identity((batch,), dtype=dtype, device=device)
        P0 = self.initial_std**2 * torch.eye(n, dtype=dtype, device=device).expand(batch, n, n)
        return x0, P0.clone()


class BiasedReadingsFilterModel(FilterModel):
    """The filter model of a system whose readings drive its prediction, biased by a state.

    An IMU's gyro, a vehicle's odometry: the motion over ``k -> k+1`` is known only through
    readings in ``y_{k+1}`` whose biases are part of the state. The filter uses the readings
    for the prediction and the rest of ``y`` for the update::

        drive     w = system.drive_from_measurement(y, u) - bias(x) - q   q: the readings' noise
        step      system.step(x, w)
        measure   system.measure(x, w, (r, 0)): the update's noise r; the readings' is q already
        residual  system.measurement_residual(z, z_hat)[..., :measurement_noise_dim]

    The layout this assumes: the update's entries come first in ``system.measure``'s noise and
    in its residual, the readings' after them (true of the rigid body, the AHRS and the planar
    vehicle). Counting the readings in the update too would use their noise twice.

    A subclass sets ``system_type`` (checked in the constructor), ``process_noise_dim`` (the
    readings' noise), ``measurement_noise_dim`` (the update's), writes :meth:`bias`, the two
    covariances and the prior. ``sigma`` is the data's noise level (checked, > 0).
    """

    system_type: type = object

    def __init__(self, system, sigma: float):
        who = type(self).__name__
        if not isinstance(system, self.system_type):
            want = self.system_type.__name__
            article = "an" if want[0] in "AEIOU" else "a"
            raise TypeError(f"{who} needs {article} {want}, got {type(system).__name__}.")
        self.system = system
        self.sigma = check_noise_level(who, sigma)
        self.group = system.group
        self.measurement_dim = system.measurement_dim
        self.input_dim = system.input_dim

    @abc.abstractmethod
    def bias(self, x: torch.Tensor) -> torch.Tensor:
        """The readings' biases ``(*batch, process_noise_dim)`` held in the state ``x``."""

    def drive(self, x, y, u, noise=None):
        w = self.system.drive_from_measurement(y, u) - self.bias(x)
        return w if noise is None else w - noise

    def step(self, x, drive):
        return self.system.step(x, drive)

    def measure(self, x, drive, noise=None):
        if noise is not None:  # the update's noise only: the readings' is the process noise
            pad = self.system.noise_dim - noise.shape[-1]
            noise = torch.cat((noise, noise.new_zeros(*noise.shape[:-1], pad)), dim=-1)
        return self.system.measure(x, drive, noise)

    def residual(self, z, z_hat):
        return self.system.measurement_residual(z, z_hat)[..., : self.measurement_noise_dim]
