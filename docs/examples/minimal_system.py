"""The smallest complete system: a turntable on SO(2), seen as a noisy unit vector.

The complete code of the tutorial ``docs/add_your_own_system.md``. It lives outside the library
(nothing in ``groups`` or ``manifold_nets`` changes): one :class:`manifold_nets.system.System`
subclass, then a dataset made, checked, cached and read back. ``tests/test_minimal_system_doc.py``
runs this file and checks that the tutorial's code blocks are verbatim excerpts of it.

The state is the turntable's angle ``theta`` as a rotation ``R = R(theta)`` in SO(2), a
``(2, 2)`` matrix. It turns at a rate ``omega_k ~ U[-1, 1]`` rad/s held over each step of
``dt = 0.1`` s, and a sensor reports a marker's direction ``R e_1 = (cos theta, sin theta)`` and
the rate, each with Gaussian noise::

    R_{k+1} = R_k exp(omega_k dt),        y_{k+1} = (cos theta_{k+1}, sin theta_{k+1}, omega_k) + n

Run it with ``python docs/examples/minimal_system.py``.
"""

from __future__ import annotations

import functools
import tempfile

import torch

from groups import SO2
from manifold_nets import (
    DatasetConfig,
    GRUCore,
    ResidualObserver,
    System,
    TrainSettings,
    evaluate,
    fit,
    load_or_generate,
    make_dataset,
)
from manifold_nets.testing import check_system


class Turntable(System):
    """A turntable on SO(2): its angle, seen as a noisy unit vector, and a noisy rate reading."""

    name = "turntable"   # file names and metadata
    measurement_dim = 3  # y = (cos theta, sin theta, omega) + noise
    input_dim = 0        # no control input: the rate reading is part of y
    drive_dim = 1        # w_k = omega_k, the true rate held over the step k -> k+1
    noise_dim = 3        # n ~ N(0, sigma^2 I_3), drawn by System.simulate

    def __init__(self, dt: float = 0.1, rate_range: float = 1.0):
        if not dt > 0 or not rate_range >= 0:
            raise ValueError(f"Turntable needs dt > 0 and rate_range >= 0, got {dt}, {rate_range}.")
        self.dt = float(dt)
        self.rate_range = float(rate_range)
        self.group = SO2()

    def config(self) -> dict:
        """Everything that changes the data: the dataset cache hashes it."""
        return {"dt": self.dt, "rate_range": self.rate_range}

    def sample_initial_state(self, num_sequences, generator):
        """``(N, 2, 2)``: a uniform random angle."""
        return self.group.random((num_sequences,), generator=generator, dtype=torch.float64)

    def sample_drive(self, num_sequences, length, generator):
        """``(N, T, 1)``: ``omega_k ~ U[-rate_range, rate_range]``."""
        u = torch.rand(num_sequences, length, 1, generator=generator, dtype=torch.float64)
        return (2 * u - 1) * self.rate_range

    def step(self, x, drive, dt=None):
        """``R_{k+1} = R_k exp(omega_k dt)``: exact for a rate held over the step."""
        dt = self.dt if dt is None else dt
        return x @ self.group.exp(drive * dt)

    def observe(self, x, drive):
        """The noise-free ``(cos theta, sin theta, omega)``; the noise is added to it."""
        marker = x[..., :, 0]  # R e_1 = (cos theta, sin theta)
        batch = torch.broadcast_shapes(marker.shape[:-1], drive.shape[:-1])
        return torch.cat((marker.expand(*batch, 2), drive.expand(*batch, 1)), dim=-1)


def main() -> None:
    system = Turntable()

    # one dataset in memory: 64 sequences of 50 steps at noise sigma 0.1, split 48/16
    data = make_dataset(system, num_sequences=64, length=50, sigma=0.1, seed=0,
                        splits={"train": 0.75, "val": 0.25})
    data.validate(system.group)  # finite, and every state on SO(2) (raises otherwise)
    print("states", tuple(data.states.shape), "measurements", tuple(data.measurements.shape),
          "inputs", tuple(data.inputs.shape))

    # the contract every system keeps (one call in your own test): raises naming what is broken
    check_system(system)

    # the measurement is the model: noise-free, y_{k+1} is the direction of R_{k+1}
    clean = make_dataset(system, num_sequences=64, length=50, sigma=0.0, seed=0)
    R1 = clean.states[:, 1:]
    assert torch.equal(clean.measurements[..., :2], R1[..., :, 0])

    # the raw baseline: the angle read off the noisy direction
    angle = torch.atan2(data.measurements[..., 1], data.measurements[..., 0])
    error = system.group.distance(SO2().exp(angle[..., None]), data.states[:, 1:])
    print(f"raw angle error at sigma 0.1: {error.mean():.4f} rad")

    # cached files, as `python -m manifold_nets.cli.generate` writes them
    with tempfile.TemporaryDirectory() as cache:
        config = DatasetConfig(num_sequences=100, length=20, sigma=0.1, cache_dir=cache,
                               progress=False)
        parts = load_or_generate(system, config)  # {"train", "val", "test"}
        again = load_or_generate(system, config)  # read back from the cache, validated
        assert torch.equal(parts["train"].states, again["train"].states)
        print("splits", {name: len(part) for name, part in parts.items()})

    # the generic observer on SO(2) (training for real: docs/observer.md, docs/examples_systems.md)
    torch.manual_seed(0)
    core = functools.partial(GRUCore, hidden_size=32, num_layers=1)  # the paper's: 512 x 2
    observer = ResidualObserver(system.group, system.measurement_dim, core)
    with tempfile.TemporaryDirectory() as out:
        settings = TrainSettings(epochs=5, batch_size=16, lr=3e-3, grad_clip=1.0, progress=False)
        fit(observer, data.split("train"), data.split("val"), settings, out_dir=out)
    result = evaluate(observer, data.split("val"), system, skip=10)
    # 48 sequences and 5 epochs teach it little: this shows the calls, not a result
    print(f"observer after 5 epochs: ||Rhat - R||_F = {result.row['x est']:.3f}, membership "
          f"error {result.row['membership max']:.1e}")

    # the same system built from a config, as hydra does from configs/system/turntable.yaml
    from hydra.utils import instantiate

    built = instantiate({"_target_": f"{__name__}.Turntable", "dt": 0.05})
    assert isinstance(built, Turntable) and built.config() == {"dt": 0.05, "rate_range": 1.0}
    print("Turntable works")


if __name__ == "__main__":
    main()
