"""The learned observer for BROAD: its shape, where it starts, how it is augmented and applied.

The observer is :class:`manifold_nets.ResidualObserver` on ``SO(3)`` (the orientation only: the
gyro bias is not in the state, the recurrent core carries what it needs of it) reading the
layout of :mod:`.data` and :mod:`.simulator`: ``y_{k+1} = (acc / G0, mag / M0)`` (6) and
``u_k = gyr`` (3, rad/s). On top of the paper's observer it uses three of the framework's pieces
(:mod:`manifold_nets.observer`), because at 285.7 Hz the paper's form would have the network
re-learn integration to 1e-4 rad per step:

* the kinematic prior, ``prior: {type: kinematic, velocities: {x: [6, 9]}}``: ``R^- = R exp(dt
  gyr)``; the network outputs the correction only (its head starts at zero, so the untrained
  observer is dead reckoning);
* the rotated feature, ``{type: rotated, vectors: {x: [[0, 3], [3, 6]]}}``: the core also reads
  ``R^- acc`` and ``R^- mag``, the readings in the world frame, where their error against "up"
  and "north" is linear;
* optionally (``broad.train --tilt-tau 3``) the complementary prior after the kinematic one,
  ``{type: complementary, factor: x, vector: [0, 3], tau: 3.0, inner: <the kinematic prior>}``:
  ``R^-`` turned by ``dt / tau`` of the angle between ``R^- acc`` and "up" (Mahony's explicit
  complementary correction), so the network learns what a fixed tilt correction misses rather
  than the whole correction;
* optionally (``--heading-only 1``) the projection scale ``{type: projection, factors: {x:
  [[0, 0, 1]]}}``: the world-frame correction is a turn about "up", so the network moves the
  heading only and the tilt is the complementary prior's;
* optionally (``--heading-tau 10``) a second complementary prior after those, turning about
  "up" only towards magnetic north, ``{type: complementary, factor: x, vector: [3, 6], tau:
  10.0, reference: [0, 1, 0], about: [0, 0, 1], inner: ...}``, a heading correction that cannot
  tilt the estimate; ``--heading-gate 1`` gates it on the field's strength and dip
  (:func:`field_gate`), so a nearby magnet does not turn it;
* an output scale, ``scales: [{type: output, scale: 0.01}]``: corrections are ~1e-3 rad per
  step, so the head's output is scaled down (the optimiser's steps on its weights stay in
  proportion);
* ``updates = {x: left}`` (``x``: the one factor of a group that is not a product): the
  correction is a world-frame rotation, ``R = exp(v) R^-``.

:func:`measured_start` starts an estimate from the first accelerometer and magnetometer sample
(TRIAD); :class:`RandomMounting` is the augmentation "the sensor mounted differently": one
random rotation ``Q`` per sequence applied to the gyroscope, accelerometer and magnetometer
readings together, and the reference orientation rotated to match (``R' = R Q^T``), which
leaves the world-frame readings ``R y`` unchanged and the body-frame ones turned.
"""

from __future__ import annotations

import math

import torch

from groups import SO3
from manifold_nets.builders import build_observer
from manifold_nets.config import ModelConfig
from manifold_nets.data import TrajectoryDataset
from manifold_nets.observer import EnsembleObserver, ResidualObserver

from .data import M0
from .simulator import BroadSimulator

__all__ = [
    "model_config",
    "make_observer",
    "measured_start",
    "near_truth_start",
    "RandomMounting",
    "RandomHeading",
    "estimate_rotations",
    "tilt",
    "tilt_start",
    "without_magnetometer",
]

_SO3 = SO3()


def model_config(
    hidden_size: int = 64, num_layers: int = 2, output_scale: float = 0.01, tilt_tau: float = 0.0,
    heading_only: bool = False, heading_tau: float = 0.0, heading_gate: dict | None = None,
) -> ModelConfig:
    """The BROAD observer's model config (see the module docstring); ``tilt_tau > 0`` (seconds)
    adds the complementary prior's tilt correction towards the accelerometer after the
    gyroscope's step; ``heading_only`` projects the core's correction onto "up" (a turn about
    the vertical: it moves the heading only); ``heading_tau > 0`` (seconds) adds, after those,
    the complementary prior's heading correction towards magnetic north (a turn about "up"),
    ``heading_gate`` its gate (:func:`field_gate`)."""
    prior = {"type": "kinematic", "velocities": {"x": [6, 9]}}  # the gyroscope, integrated
    if tilt_tau > 0:
        prior = {"type": "complementary", "factor": "x", "vector": [0, 3], "tau": tilt_tau,
                 "inner": prior}  # fmt: skip
    if heading_tau > 0:
        prior = {"type": "complementary", "factor": "x", "vector": [3, 6], "tau": heading_tau,
                 "reference": [0.0, 1.0, 0.0], "about": [0.0, 0.0, 1.0], "inner": prior}
        if heading_gate is not None:
            prior["gate"] = dict(heading_gate)
    return ModelConfig(
        hidden_size=hidden_size,
        num_layers=num_layers,
        updates={"x": "left"},
        prior=prior,
        features=[
            "embedding", "readings", {"type": "rotated", "vectors": {"x": [[0, 3], [3, 6]]}},
        ],
        scales=([{"type": "projection", "factors": {"x": [[0.0, 0.0, 1.0]]}}] if heading_only
                else []) + [{"type": "output", "scale": output_scale}],
    )


def field_gate(system: BroadSimulator, norm_tol: float = 0.1, dip_tol: float = 10.0) -> dict:
    """The heading correction's gate: the magnetometer trusted where its field strength is within
    ``norm_tol`` of the system's and its dip within ``dip_tol`` degrees (VQF's default
    thresholds), in the observer's units (``mag / M0``)."""
    return {"norm": system.magnetic_strength / M0, "norm_tol": norm_tol,
            "elevation": -system.magnetic_dip_deg, "elevation_tol": dip_tol}


def make_observer(system: BroadSimulator, model: ModelConfig, seed: int = 0) -> ResidualObserver:
    """The observer of ``model`` for ``system``'s layout; its head starts at zero (the untrained
    observer integrates the gyroscope and corrects nothing)."""
    torch.manual_seed(seed)
    return build_observer(
        system.group, system.measurement_dim, system.input_dim, model, dt=system.dt,
        system=system,
    )


def measured_start(system: BroadSimulator):
    """``batch -> (B, 3, 3)``: TRIAD of the batch's first measurement (the attitude from the
    first accelerometer and magnetometer sample), the ``start`` of :func:`manifold_nets.fit`."""

    def start(batch: TrajectoryDataset) -> torch.Tensor:
        return system.state_from_measurement(batch.measurements[:, 0])

    return start


def tilt(acc: torch.Tensor) -> torch.Tensor:
    """``(*batch, 3) -> (*batch, 3, 3)``: the smallest rotation that turns the accelerometer's
    direction to "up" (``R a / |a| = e_z``): the attitude a 6-D filter can know from one sample,
    its heading arbitrary (that of the shortest turn). Upside down (``a`` within 1e-6 of
    ``-e_z``) it turns by pi about the body's x axis."""
    a = acc.to(torch.float64)
    a = a / a.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    up = torch.zeros_like(a)
    up[..., 2] = 1.0
    axis = torch.linalg.cross(a, up)
    s, c = axis.norm(dim=-1, keepdim=True), a[..., 2:3]
    flipped = (s < 1e-6) & (c < 0)
    safe = torch.where(s < 1e-12, torch.ones_like(s), s)  # "double where": no 0/0 anywhere
    turn = axis / safe * torch.atan2(s, c)
    turn = torch.where(flipped, torch.tensor([math.pi, 0.0, 0.0], dtype=a.dtype), turn)
    return _SO3.exp(turn).to(acc.dtype)


def without_magnetometer(data: TrajectoryDataset) -> TrajectoryDataset:
    """``data`` with the magnetometer columns of ``y`` (3:6) set to zero: what a 6-D observer
    (gyroscope and accelerometer only) is trained and run on. A constant input carries no
    information, so the 9-D observer's shape serves the 6-D one unchanged."""
    y = data.measurements.clone()
    y[..., 3:6] = 0.0
    return TrajectoryDataset(data.states, y, data.inputs, data.meta, data.mask)


def tilt_start(system: BroadSimulator):
    """``batch -> (B, 3, 3)``: :func:`tilt` of the batch's first accelerometer reading, the
    6-D counterpart of :func:`measured_start` (``system``: for the same signature)."""

    def start(batch: TrajectoryDataset) -> torch.Tensor:
        return tilt(batch.measurements[:, 0, :3])

    return start


def near_truth_start(system: BroadSimulator, angle_std: float = 0.05, magnetometer: bool = True):
    """``batch -> (B, 3, 3)``: the true first state turned by a random rotation of
    ``N(0, angle_std^2)`` per axis (radians), or TRIAD where the reference is missing.

    For training windows cut from inside a trial: there the deployed observer has long
    converged, to a few degrees, so a window that starts from TRIAD of one sample in motion (off
    by up to ~20 deg through the linear acceleration) would teach it to converge rather than to
    track. The perturbation is a function of the batch (seeded by its first states), so the
    validation loss of a model is the same at every epoch. Without the ``magnetometer`` the
    fallback is :func:`tilt_start`."""
    triad = measured_start(system) if magnetometer else tilt_start(system)

    def start(batch: TrajectoryDataset) -> torch.Tensor:
        x0 = batch.states[:, 0]
        seed = int(torch.sum(torch.abs(x0.detach().double())).item() * 1e6) % (2**31)
        gen = torch.Generator().manual_seed(seed)
        turn = angle_std * torch.randn(len(batch), 3, generator=gen, dtype=torch.float64)
        out = x0 @ _SO3.exp(turn).to(x0)
        if batch.mask is not None and not bool(batch.mask[:, 0].all()):
            out = torch.where(batch.mask[:, 0, None, None], out, triad(batch).to(out))
        return out

    return start


class RandomMounting:
    """The augmentation of the module docstring: per sequence a rotation ``Q`` (Haar-uniform, or
    within ``max_angle`` radians of the identity), readings ``Q v``, reference ``R Q^T``."""

    def __init__(self, max_angle: float = math.pi):
        if not 0 < max_angle <= math.pi:
            raise ValueError(f"max_angle must be in (0, pi] radians, got {max_angle!r}.")
        self.max_angle = float(max_angle)

    def rotations(self, n: int, generator: torch.Generator) -> torch.Tensor:
        if self.max_angle >= math.pi:
            return _SO3.random((n,), generator=generator, dtype=torch.float64)
        axis = torch.randn(n, 3, generator=generator, dtype=torch.float64)
        axis = axis / axis.norm(dim=-1, keepdim=True)
        angle = self.max_angle * torch.rand(n, 1, generator=generator, dtype=torch.float64)
        return _SO3.exp(axis * angle)

    def __call__(self, batch: TrajectoryDataset, generator: torch.Generator) -> TrajectoryDataset:
        Q = self.rotations(len(batch), generator).to(batch.states)
        Qm = Q[:, None].to(batch.measurements.dtype)
        y = batch.measurements.unflatten(-1, (2, 3))  # acc, mag
        y = (Qm[:, :, None] @ y[..., None])[..., 0].flatten(-2)
        u = (Qm @ batch.inputs[..., None])[..., 0]
        states = batch.states @ Q[:, None].transpose(-1, -2)
        return TrajectoryDataset(states, y, u, batch.meta, batch.mask)


class RandomHeading:
    """The augmentation for a 6-D observer: the world turned about "up" by a uniform random
    angle per sequence, ``R' = R_z(psi) R``. The readings (body frame) are unchanged: without a
    magnetometer nothing tells one heading from another, and the observer, which reads its own
    estimate, must not learn the lab's headings."""

    def __call__(self, batch: TrajectoryDataset, generator: torch.Generator) -> TrajectoryDataset:
        psi = 2 * math.pi * torch.rand(len(batch), 1, generator=generator, dtype=torch.float64)
        turn = torch.cat((torch.zeros(len(batch), 2, dtype=torch.float64), psi), -1)
        Rz = _SO3.exp(turn).to(batch.states)
        states = Rz[:, None] @ batch.states
        return TrajectoryDataset(states, batch.measurements, batch.inputs, batch.meta, batch.mask)


@torch.inference_mode()
def estimate_rotations(
    observer: ResidualObserver | EnsembleObserver, system: BroadSimulator, data: TrajectoryDataset,
    magnetometer: bool = True,
) -> torch.Tensor:
    """The observer over whole sequences from their first sample: ``(N, T+1, 3, 3)`` float64.

    Estimate 0 is TRIAD of the first measurement (the readings one observer step later), then
    one estimate per step. Without the ``magnetometer``: its columns zeroed
    (:func:`without_magnetometer`) and started from :func:`tilt`."""
    observer.eval()
    if not magnetometer:
        data = without_magnetometer(data)
    first = measured_start(system) if magnetometer else tilt_start(system)
    x0 = first(data).to(device=observer.device, dtype=observer.state_dtype)
    state = observer.init_state(len(x0), x0.device, estimate=x0)  # every member's, for an ensemble
    est = observer(data.measurements, data.inputs, state=state)
    return est.cpu().to(torch.float64)
