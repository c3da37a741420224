"""What a system is: a discrete-time system on a Lie group, and its simulation into a dataset.

A :class:`System` is the paper's ``x_{k+1} = f(x_k, u_k, mu)``, ``y_k = h(x_k, nu)`` written so
that both a simulator and a filter can use it::

    x_{k+1} = step(x_k, w_k)                  the dynamics over one step of length dt
    y_{k+1} = measure(x_{k+1}, w_k, nu_{k+1})  the measurement model, nu ~ N(0, sigma^2 I)
    u_k     = inputs(w_k)                     the part of w_k an observer is given as input

``w_k`` is the *drive*: everything that moves the state over the step ``k -> k+1`` (for the
rigid body the true body velocities ``(Omega_k, v_k)``; for a controlled system its control
input). The drive of step ``k`` may enter the measurement ``y_{k+1}`` (a velocity sensor reads
the velocity applied over that step). The noise ``nu`` is an explicit argument, so ``measure(x,
w)`` is the noise-free model ``h(x, w, 0)`` and its derivatives in ``x`` and ``nu`` are what an
(error-state) Kalman filter needs.

The measurement is written in two parts, and :meth:`System.measure` is derived from them once::

    observe(x, w)               the noise-free model h(x, w, 0), (*batch, measurement_dim)
    apply_noise(y, nu)          how the noise enters a noise-free measurement y
    measure(x, w, nu)         = apply_noise(observe(x, w), nu);  measure(x, w) = observe(x, w)

``apply_noise`` is also what noise-augmented training applies to noise-free data. The base class
makes it additive, ``y + nu``, when ``noise_dim == measurement_dim``; a system whose noise is
scaled per sensor or enters on a group (a rotation ``R exp([w]x)``) writes its own.

A subclass writes ``sample_initial_state``, ``sample_drive``, ``step``, ``observe`` and ``config``
(and ``apply_noise`` unless the noise is additive), and sets ``group``, ``measurement_dim``,
``input_dim``, ``drive_dim``, ``noise_dim``, ``dt`` and ``name``. A system whose noisy
measurement is not a function of the noise-free one may override ``measure`` instead of writing
``observe``; it then has no ``apply_noise`` unless it writes one. :meth:`System.simulate` draws,
in this order from one ``torch.Generator``, the initial states, the drives and the noise, rolls
the dynamics out and measures, in float64. ``manifold_nets.testing.check_system(system)`` checks
a subclass against this contract.

Optional hooks for classical filters and baselines (:mod:`manifold_nets.ekf`,
:mod:`manifold_nets.baselines`): ``measurement_residual`` (how a measurement is compared with a
predicted one; default the plain difference), ``state_from_measurement`` (the raw-measurement
baseline), ``drive_from_measurement`` (the drive as read, for dead reckoning) and ``predict``
(the nominal prediction from an estimate and the readings; the learned observer's model prior).
:meth:`System.estimators` names the classical estimators a system offers, which hydra's
``method=<name>`` selects.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import torch

from groups import LieGroup

from .data import TrajectoryDataset, check_positive_int, check_sigma
from .losses import factor_errors
from .progress import progress
from .registry import Registry

if TYPE_CHECKING:
    from .observer.readings_filter import ReadingsFilter

__all__ = ["SYSTEMS", "System", "check_last_dim", "check_number", "check_simulate_args"]

#: Every imported :class:`System` subclass by ``module.qualname``: what a run folder's
#: ``system._target_`` may name (:mod:`manifold_nets.registry`).
SYSTEMS = Registry("System", "manifold_nets.System", plugins="manifold_nets.systems")

_DTYPE = torch.float64
_MEASURE_CHUNK = 1 << 17  # (sequence, step) pairs measured at once: small temporaries are faster


def check_last_dim(owner: str, t: torch.Tensor, size: int, what: str) -> None:
    """Raises a ValueError naming ``owner`` unless ``t`` is a tensor of shape ``(*batch, size)``.

    For system authors: validate the arguments of ``step``/``measure`` with one line.
    """
    if not isinstance(t, torch.Tensor) or t.dim() < 1 or t.shape[-1] != size:
        shape = tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
        raise ValueError(f"{owner} expects the {what} of shape (*batch, {size}), got {shape}.")


def check_number(owner: str, name: str, value: object, positive: bool = False) -> float:
    """``value`` as a float, or a ValueError unless it is finite and ``>= 0`` (``> 0`` if
    ``positive``). For system authors validating their constructor's parameters."""
    ok = not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)
    if not ok or value < 0 or (positive and value == 0):
        rel = "> 0" if positive else ">= 0"
        raise ValueError(f"{owner}: {name} must be a finite number {rel}, got {value!r}.")
    return float(value)


def check_simulate_args(
    num_sequences: int, length: int, sigma: float, generator: torch.Generator
) -> tuple[int, int, float]:
    """``(num_sequences, length, sigma)`` checked for :meth:`System.simulate` (a
    ``DatasetError`` or ``TypeError`` naming the argument); for a subclass that writes its own
    ``simulate``."""
    n = check_positive_int("num_sequences", num_sequences)
    t = check_positive_int("length", length)
    sigma = check_sigma(sigma)
    if not isinstance(generator, torch.Generator):
        raise TypeError(
            f"generator must be a torch.Generator (e.g. torch.Generator().manual_seed(0)), "
            f"got {type(generator).__name__}."
        )
    return n, t, sigma


class System(abc.ABC):
    """Abstract discrete-time system on a Lie group; see the module docstring."""

    #: The state's group; states are ``(*batch, *group.element_shape)``.
    group: LieGroup
    #: Size ``l`` of a measurement ``y``.
    measurement_dim: int
    #: Size ``m`` of the observer's input ``u`` (0 allowed).
    input_dim: int = 0
    #: Size of the drive ``w`` that moves the state over a step.
    drive_dim: int
    #: Size of the measurement noise vector ``nu``, drawn from ``N(0, sigma^2 I)``.
    noise_dim: int
    #: Step length in seconds.
    dt: float
    #: Short name, used in file names and metadata.
    name: str
    #: What a recording's readings go through before this system's observer reads them, when
    #: more than the data file holds (a pre-filter the observer was trained behind), in words;
    #: ``None``: the readings as they are. :meth:`readings_filter` is the filter itself; a
    #: system that names one here but gives none is refused by the commands that feed a data
    #: file's readings (``mn-apply``) unless they are told the file went through it.
    preprocessing: str | None = None

    # ------------------------------------------------------------------ what a subclass writes

    @abc.abstractmethod
    def config(self) -> dict:
        """The parameters that determine the simulated data, as a JSON-able dict.

        The dataset cache hashes it: anything that changes the data must be in it.
        """

    @abc.abstractmethod
    def sample_initial_state(self, num_sequences: int, generator: torch.Generator) -> torch.Tensor:
        """Random initial states ``x_0``, float64, ``(num_sequences, *group.element_shape)``."""

    @abc.abstractmethod
    def sample_drive(
        self, num_sequences: int, length: int, generator: torch.Generator
    ) -> torch.Tensor:
        """Random drives ``w_0 .. w_{T-1}``, float64, ``(num_sequences, length, drive_dim)``."""

    @abc.abstractmethod
    def step(self, x: torch.Tensor, drive: torch.Tensor, dt: float | None = None) -> torch.Tensor:
        """``x_{k+1}`` from ``x_k`` ``(*batch, *element_shape)``, ``w_k`` ``(*batch, drive_dim)``.

        ``dt`` defaults to ``self.dt``.
        """

    @abc.abstractmethod
    def observe(self, x: torch.Tensor, drive: torch.Tensor) -> torch.Tensor:
        """The noise-free measurement ``h(x, w, 0)``, ``(*batch, measurement_dim)``.

        ``x`` ``(*batch, *element_shape)`` is the state the measurement is taken at
        (``x_{k+1}``), ``drive`` ``(*batch, drive_dim)`` the drive of the step that led there
        (``w_k``); batch dimensions broadcast, the dtype of ``x`` is kept. Differentiable.
        """

    def apply_noise(self, measurements: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Noise-free measurements ``(*batch, measurement_dim)`` with ``noise``
        ``(*batch, noise_dim)`` (already times sigma) applied, ``(*batch, measurement_dim)``.

        ``measure(x, w, noise)`` is ``apply_noise(observe(x, w), noise)``; noise-augmented
        training calls it on noise-free data. Default: additive, ``measurements + noise``, when
        ``noise_dim == measurement_dim``. Write it for any other noise (per-sensor scales, a
        rotation perturbed on its group); it must be plain differentiable torch and give the
        measurements back for zero noise.
        """
        who = type(self).__name__
        if type(self).measure is not System.measure:
            raise NotImplementedError(
                f"{who} overrides measure(x, drive, noise) itself, so the base class cannot know "
                f"how noise enters a noise-free measurement: write apply_noise(measurements, "
                f"noise) (or write observe(x, drive) and apply_noise instead of measure)."
            )
        if self.noise_dim != self.measurement_dim:
            raise NotImplementedError(
                f"{who}: noise_dim={self.noise_dim} differs from measurement_dim="
                f"{self.measurement_dim}, so the noise is not simply added: write "
                f"apply_noise(measurements, noise) to say how the noise enters a noise-free "
                f"measurement."
            )
        check_last_dim(who, noise, self.noise_dim, "noise")
        return measurements + noise

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        SYSTEMS.add(cls)  # a file may name it once its module is imported, never before
        # a subclass that writes measure itself (the older form) gets observe from it
        if "measure" in cls.__dict__ and getattr(cls.observe, "__isabstractmethod__", False):
            cls.observe = _observe_by_measure

    # ------------------------------------------------------------------ derived, overridable

    def measure(
        self, x: torch.Tensor, drive: torch.Tensor, noise: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``y = h(x, w, nu)``, ``(*batch, measurement_dim)``: ``observe(x, drive)``, then
        ``apply_noise(..., noise)`` unless ``noise`` is ``None``.

        ``x`` is the state the measurement is taken at (``x_{k+1}``), ``drive`` the drive of the
        step that led there (``w_k``), ``noise`` ``(*batch, noise_dim)`` or ``None`` for none.
        """
        y = self.observe(x, drive)
        return y if noise is None else self.apply_noise(y, noise)

    # ------------------------------------------------------------------ derived, overridable

    def inputs(self, drive: torch.Tensor) -> torch.Tensor:
        """The observer's inputs ``u_k`` ``(*batch, input_dim)`` from the drive ``w_k``.

        Default: nothing when ``input_dim == 0``, the drive itself when it is all known input.
        """
        if self.input_dim == 0:
            return drive.new_zeros(*drive.shape[:-1], 0)
        if self.input_dim == self.drive_dim:
            return drive
        raise NotImplementedError(
            f"{type(self).__name__}: input_dim={self.input_dim} differs from drive_dim="
            f"{self.drive_dim}; override inputs(drive) to say which part of the drive is input."
        )

    def rollout(
        self, x0: torch.Tensor, drive: torch.Tensor, show_progress: bool = False
    ) -> torch.Tensor:
        """States ``x_0 .. x_T``, ``(N, T+1, *element_shape)``, from ``x0`` and the drives.

        The default loops :meth:`step` over time, vectorised over the sequences. Override it for
        a faster (e.g. closed-form, precomputed) rollout; it must agree with :meth:`step`.
        """
        n, t = drive.shape[:2]
        states = x0.new_empty(n, t + 1, *self.group.element_shape)
        states[:, 0] = x0
        for k in progress(range(t), desc=f"{self.name} steps", enabled=show_progress):
            states[:, k + 1] = self.step(states[:, k], drive[:, k])
        return states

    def simulate(
        self,
        num_sequences: int,
        length: int,
        sigma: float,
        generator: torch.Generator,
        *,
        show_progress: bool = False,
    ) -> TrajectoryDataset:
        """``num_sequences`` trajectories of ``length`` steps with measurement noise ``sigma``.

        Draws, in this order from ``generator``: the initial states, the drives, then (only when
        ``sigma > 0``) the noise ``(N, T, noise_dim)`` times ``sigma``. Everything is float64.
        The states do not depend on ``sigma``: the same generator seed gives the same
        trajectories at every noise level. Bad arguments raise before any work.
        """
        n, t, sigma = check_simulate_args(num_sequences, length, sigma, generator)
        x0 = self.sample_initial_state(n, generator)
        drive = self.sample_drive(n, t, generator)
        noise = None
        if sigma > 0:
            noise = torch.randn(n, t, self.noise_dim, generator=generator, dtype=_DTYPE)
            noise.mul_(sigma)
        states = self.rollout(x0, drive, show_progress=show_progress)
        want = (n, t + 1, *self.group.element_shape)
        if tuple(states.shape) != want or states.dtype != _DTYPE:
            raise ValueError(
                f"{type(self).__name__}.rollout returned {tuple(states.shape)} {states.dtype}; "
                f"expected {want} float64."
            )
        rows = max(1, _MEASURE_CHUNK // t)
        if rows >= n:  # one call: no copy
            measurements = self.measure(states[:, 1:], drive, noise)
        else:  # in chunks of sequences: small temporaries, no fresh pages to fault in
            measurements = torch.empty(n, t, self.measurement_dim, dtype=_DTYPE)
            for s in range(0, n, rows):
                e = min(n, s + rows)
                nz = None if noise is None else noise[s:e]
                measurements[s:e] = self.measure(states[s:e, 1:], drive[s:e], nz)
        if tuple(measurements.shape) != (n, t, self.measurement_dim):
            raise ValueError(
                f"{type(self).__name__}.measure returned {tuple(measurements.shape)}; expected "
                f"{(n, t, self.measurement_dim)} (N, T, measurement_dim)."
            )
        return self.trajectory_dataset(states, measurements, drive, sigma)

    def trajectory_dataset(
        self, states: torch.Tensor, measurements: torch.Tensor, drive: torch.Tensor, sigma: float
    ) -> TrajectoryDataset:
        """The dataset :meth:`simulate` returns, from its arrays: states ``(N, T+1, ...)``,
        measurements ``(N, T, l)``, drives ``(N, T, drive_dim)`` (the inputs are
        ``inputs(drive)``) and the meta every simulated dataset carries. For a subclass that
        writes its own ``simulate`` (draws the data another way) and returns what the base does."""
        meta = {
            "system": self.name,
            "system_target": f"{type(self).__module__}.{type(self).__qualname__}",
            "system_config": self.config(),
            "group": repr(self.group),
            "dt": float(self.dt),
            "sigma": float(sigma),
            "measurement_dim": self.measurement_dim,
            "input_dim": self.input_dim,
        }
        return TrajectoryDataset(states, measurements, self.inputs(drive), meta)

    def readings_filter(self) -> ReadingsFilter | None:
        """The causal pre-filter of the readings this system's observer was trained behind, as a
        :class:`~manifold_nets.observer.readings_filter.ReadingsFilter` built by the system's own
        code from its config's plain numbers (never from a name in a file), or ``None`` (the
        default: the readings as they are). ``mn-apply`` and the exported step of
        :func:`manifold_nets.observer.filtered.with_readings_filter` run it before the observer."""
        return None

    # ------------------------------------------------------------------ evaluation hooks

    def metrics(self, estimates: torch.Tensor, data: TrajectoryDataset) -> dict[str, torch.Tensor]:
        """Per-factor embedding errors ``||pi(xhat) - pi(x)||``, each ``(N, T')``.

        ``estimates`` is ``(N, T+1, *element_shape)`` (compared with ``x_0 .. x_T``) or
        ``(N, T, *element_shape)`` (compared with ``x_1 .. x_T``). The keys are the group's
        ``factor_names`` (a Product's names, ``factor0``, ... when unnamed; ``x`` for a group
        that is not a product): :func:`manifold_nets.losses.factor_errors`. For SO(3) as
        rotation matrices this is the Frobenius norm ``||Rhat - R||_F`` of the paper's table.
        """
        states = data.states.to(dtype=estimates.dtype, device=estimates.device)
        if estimates.shape[1] == states.shape[1] - 1:
            states = states[:, 1:]
        if estimates.shape != states.shape:
            short = (len(data), data.length, *data.states.shape[2:])
            raise ValueError(
                f"estimates must be (N, T+1, ...) or (N, T, ...) = {tuple(data.states.shape)} "
                f"or {short}; got {tuple(estimates.shape)}."
            )
        return factor_errors(self.group, estimates, states)

    # ------------------------------------------------------------------ hooks for classical filters

    def measurement_residual(self, y: torch.Tensor, y_hat: torch.Tensor) -> torch.Tensor:
        """The innovation of a measurement ``y`` against a predicted one ``y_hat``, ``(*batch, d)``.

        A Kalman filter linearises this, not ``y - y_hat``, so that a measurement with a group
        part (a measured rotation) is compared on the group. The residual must behave like a
        ``minus``: ``residual(y_hat, y_hat) = 0`` and, near ``y_hat``, first order in the
        measurement noise. Default: the plain difference ``y - y_hat`` in ``R^l`` (``d = l``).
        """
        return y - y_hat

    def state_from_measurement(self, y: torch.Tensor) -> torch.Tensor:
        """The state read off a measurement, ``(*batch, measurement_dim) -> (*batch, *element_shape)``.

        The raw-measurement baseline (:mod:`manifold_nets.baselines`): the measured factors taken
        as they are, the unmeasured ones at the identity. Optional; a system whose measurement
        holds (part of) the state overrides it.
        """
        raise NotImplementedError(
            f"{type(self).__name__} does not say how to read a state off a measurement: override "
            f"state_from_measurement(y) (the measured factors, the others at the identity) to use "
            f"the raw-measurement or dead-reckoning baselines."
        )

    def drive_from_measurement(self, y: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The drive ``w_k`` as read, ``(*batch, drive_dim)``, from ``y_{k+1}`` and ``u_k``.

        What a filter knows of the motion over the step ``k -> k+1`` without a state estimate
        (for the rigid body: the biased velocity readings). Dead reckoning steps with it.
        Default: the input itself when the drive is all known input (``input_dim == drive_dim``).
        """
        if self.input_dim == self.drive_dim:
            return u
        raise NotImplementedError(
            f"{type(self).__name__}: the drive (drive_dim={self.drive_dim}) is not the input "
            f"(input_dim={self.input_dim}); override drive_from_measurement(y, u) to say how the "
            f"drive is read from the measurement and input (e.g. velocity readings in y)."
        )

    def compensated_drive(
        self, x: torch.Tensor, y: torch.Tensor, u: torch.Tensor | None
    ) -> torch.Tensor:
        """The drive the prediction integrates, ``(*batch, drive_dim)``: the readings of
        ``y_{k+1}``, ``u_k`` compensated by the estimate ``x_k``.

        Default: :meth:`drive_from_measurement`, the drive as read. A system whose readings
        carry biases held in the state subtracts the estimate's (the rigid body:
        ``(Omega^m - bhat_Omega, v^m - bhat_v)``); it must stay differentiable in ``x``. The
        learned observer's core reads it with ``model.prior_drive=true``.
        """
        return self.drive_from_measurement(y, u)

    def predict(self, x: torch.Tensor, y: torch.Tensor, u: torch.Tensor | None) -> torch.Tensor:
        """The nominal model's prediction ``x_{k+1}^-`` from an estimate ``x_k`` and the step's
        readings ``y_{k+1}``, ``u_k``: what a filter's predict step computes.

        ``x`` ``(*batch, *element_shape)``, ``y`` ``(*batch, measurement_dim)``, ``u``
        ``(*batch, input_dim)`` or ``None``; returns ``(*batch, *element_shape)``. The learned
        observer's model prior (``model.prior=system``) moves its estimate by this before the
        network's correction. Default: ``step(x, compensated_drive(x, y, u))``, the step on the
        readings less what the estimate says of their errors (for a system without such states,
        dead reckoning on the drive as read). It must stay differentiable in ``x`` (the
        observer is trained through it).
        """
        return self.step(x, self.compensated_drive(x, y, u))

    def estimators(self) -> dict[str, Callable[..., Any]]:
        """The classical estimators of this system by name: ``{name: factory}``.

        A factory is called as ``factory(system, sigma=sigma, **params)`` (``sigma`` only when it
        takes one: the noise level of the data, which a model-based filter is told) and returns a
        :class:`manifold_nets.baselines.Estimator`. ``python -m manifold_nets.cli.train method=<name>``
        evaluates it in place of the learned observer. Default: ``raw`` and ``dead_reckoning``
        (:mod:`manifold_nets.baselines`; they need ``state_from_measurement`` and
        ``drive_from_measurement``). A system with filters of its own adds them (the rigid body:
        ``ekf``, ``complementary``).
        """
        from .baselines import DeadReckoning, RawMeasurement

        return {"raw": RawMeasurement, "dead_reckoning": DeadReckoning}

    def measurement_errors(self, data: TrajectoryDataset) -> dict[str, torch.Tensor]:
        """Errors of the raw measurements against the true states, ``{name: (N, T)}``.

        The baseline an observer must beat (the paper's ``R^m`` and ``p^m`` columns). Default:
        none; a system whose measurement contains state factors overrides it.
        """
        return {}

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.config().items())
        return f"{type(self).__name__}({args})"


def _observe_by_measure(self: System, x: torch.Tensor, drive: torch.Tensor) -> torch.Tensor:
    """The noise-free measurement ``measure(x, drive)`` of a system that writes ``measure``."""
    return self.measure(x, drive)
