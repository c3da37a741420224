"""Training data simulated afresh every epoch: a :class:`SimulatedStream` of a system.

A simulator makes millions of steps per second, so training on one fixed dataset is a choice,
not a necessity. A :class:`SimulatedStream` hands :func:`manifold_nets.training.fit` a new
:class:`~manifold_nets.data.TrajectoryDataset` for every epoch::

    from manifold_nets.streaming import SimulatedStream

    stream = SimulatedStream(RigidBody(), num_sequences=1600, length=50, noise_levels=[0.0, 0.3])
    fit(model, stream, val_data, settings, out_dir="run")   # val_data stays fixed

Epoch ``e``'s data come from a ``torch.Generator`` seeded by :func:`stream_seed` ``(seed, e)``
alone, so the same epoch always gives the same data (a resumed run sees exactly what the
uninterrupted run saw) and different epochs give different data. The noise is the system's own
(:meth:`~manifold_nets.system.System.simulate` at each sigma), never a Gaussian laid on top.

:class:`DataStream` is what ``fit`` accepts besides a fixed dataset: any object with
``epoch(int) -> TrajectoryDataset``.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import torch

from .data import DatasetError, TrajectoryDataset, check_positive_int, check_sigma
from .system import System

__all__ = ["DataStream", "SimulatedStream", "stream_seed"]


@runtime_checkable
class DataStream(Protocol):
    """Training data by epoch: ``epoch(e)`` is the :class:`TrajectoryDataset` of epoch ``e``
    (1, 2, ... in :func:`~manifold_nets.training.fit`); the same ``e`` must give the same data,
    or a resumed run differs from an uninterrupted one."""

    def epoch(self, epoch: int) -> TrajectoryDataset: ...


def stream_seed(seed: int, epoch: int) -> int:
    """The generator seed of ``epoch`` of the stream ``seed``: the first 63 bits of
    ``sha256("stream/{seed}/{epoch}")`` (independent streams for nearby seeds and epochs)."""
    digest = hashlib.sha256(f"stream/{int(seed)}/{int(epoch)}".encode()).digest()
    return int.from_bytes(digest[:8], "big") >> 1


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


class SimulatedStream:
    """``num_sequences`` fresh sequences of ``length`` steps of ``system`` every epoch.

    ``epoch(e)`` returns a dataset with states ``(num_sequences, length + 1, *element_shape)``,
    measurements ``(num_sequences, length, measurement_dim)`` and inputs
    ``(num_sequences, length, input_dim)``, float64, simulated with
    ``system.simulate(..., generator)`` from a generator seeded by :func:`stream_seed`
    ``(seed, e)``.

    Noise: without ``noise_levels`` every sequence has measurement noise ``sigma``. With
    ``noise_levels`` (a list of sigmas; ``sigma`` is then not used) the sequences are split as
    evenly as possible across the levels (the first ``num_sequences % len(levels)`` levels get
    one more), each level's share is simulated at its sigma with the system's noise model, one
    after the other from the same generator, and the concatenation is shuffled by a permutation
    drawn from it last (with one level nothing is shuffled: ``noise_levels=[s]`` gives the data
    of ``sigma=s``). Every level needs at least one sequence.

    ``meta`` of an epoch's dataset: the system's (:meth:`System.simulate`), with ``sigma``
    (``None`` with levels), ``noise_levels`` (a list, empty without levels), ``stream_seed``
    (``seed``), ``epoch`` and ``generator_seed``.
    """

    def __init__(
        self,
        system: System,
        num_sequences: int,
        length: int,
        *,
        sigma: float = 0.0,
        noise_levels: Sequence[float] = (),
        seed: int = 0,
    ):
        if not isinstance(system, System):
            raise TypeError(
                f"SimulatedStream: system must be a manifold_nets.System (it simulates the "
                f"sequences), got {type(system).__name__}."
            )
        try:
            self.num_sequences = check_positive_int("num_sequences", num_sequences)
            self.length = check_positive_int("length", length)
            self.sigma = check_sigma(sigma)
        except DatasetError as err:  # it names the parameter and what it must be
            raise ValueError(f"SimulatedStream: {err}") from None
        self.noise_levels = _check_levels(noise_levels, self.num_sequences)
        if not _is_int(seed):
            raise ValueError(f"SimulatedStream: seed must be an integer, e.g. 0; got {seed!r}.")
        self.system, self.seed = system, seed

    def level_sizes(self) -> list[int]:
        """How many sequences each noise level gets (empty without levels)."""
        n, k = self.num_sequences, len(self.noise_levels)
        return [n // k + (i < n % k) for i in range(k)]

    def epoch(self, epoch: int) -> TrajectoryDataset:
        """The sequences of ``epoch`` (an integer >= 0); the same ``epoch`` gives the same data."""
        if not _is_int(epoch) or epoch < 0:
            raise ValueError(f"epoch must be an integer >= 0 (fit counts from 1), got {epoch!r}.")
        gen_seed = stream_seed(self.seed, epoch)
        gen = torch.Generator().manual_seed(gen_seed)
        n, t = self.num_sequences, self.length
        if not self.noise_levels:
            data = self.system.simulate(n, t, self.sigma, gen)
            sigma = self.sigma
        else:
            parts = [
                self.system.simulate(k, t, s, gen)
                for s, k in zip(self.noise_levels, self.level_sizes())
            ]
            data = TrajectoryDataset(
                torch.cat([p.states for p in parts]),
                torch.cat([p.measurements for p in parts]),
                torch.cat([p.inputs for p in parts]),
                parts[0].meta,
            )
            if len(parts) > 1:
                data = data[torch.randperm(n, generator=gen)]
            sigma = None
        data.meta = {
            **data.meta, "sigma": sigma, "noise_levels": list(self.noise_levels),
            "stream_seed": self.seed, "epoch": epoch, "generator_seed": gen_seed,
        }
        return data

    def __repr__(self) -> str:
        noise = (
            f"noise_levels={list(self.noise_levels)}" if self.noise_levels
            else f"sigma={self.sigma}"
        )
        return (
            f"SimulatedStream({self.system!r}, num_sequences={self.num_sequences}, "
            f"length={self.length}, {noise}, seed={self.seed})"
        )


def _check_levels(levels: Sequence[float], num_sequences: int) -> tuple[float, ...]:
    """``levels`` as floats, or a ``ValueError`` naming the bad one and the fix."""
    if isinstance(levels, (str, bytes)) or not isinstance(levels, Sequence):
        raise ValueError(
            f"SimulatedStream: noise_levels must be a list of sigmas, e.g. [0.0, 0.1, 0.3] (empty: "
            f"every sequence at sigma), got {levels!r}."
        )
    out = []
    for i, s in enumerate(levels):
        try:
            out.append(check_sigma(s))
        except DatasetError as err:
            raise ValueError(f"SimulatedStream: noise_levels[{i}] = {s!r}: {err}") from None
    if len(out) > num_sequences:
        raise ValueError(
            f"SimulatedStream: num_sequences={num_sequences} is fewer than the {len(out)} "
            "noise_levels, and every level needs at least one sequence; use more sequences or "
            "fewer levels."
        )
    return tuple(out)
