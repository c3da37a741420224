"""The datasets of a run: simulated from a config and cached by hash, mixed, or read from a file.

:mod:`manifold_nets.data` is the dataset type and its file format; this module makes and finds
the datasets a run needs::

    from manifold_nets import DatasetConfig, load_or_generate, make_dataset
    from manifold_nets_examples.rigid_body import RigidBody

    ds = make_dataset(RigidBody(), num_sequences=100, length=50, sigma=0.1, seed=0)
    parts = load_or_generate(RigidBody(), DatasetConfig(num_sequences=2000, length=50))
    parts["train"], parts["val"], parts["test"]          # TrajectoryDataset each

A :class:`~manifold_nets.config.DatasetConfig` describes one file (``num_sequences`` x
``length`` at ``sigma`` from ``seed``, cut into contiguous ``splits``). A file is named by the
system, sizes and a hash of everything that determines its contents (the system's
``config()``, sizes, sigma, seed, splits, format version): the same config reuses the file, a
changed one writes a new file. The check and the generation hold a lock on ``<file>.lock``
(:func:`~manifold_nets.atomic.file_lock`), so parallel jobs of a sweep that need the same file
make it once: the first generates it, the others wait and read it.

For training and evaluation: :func:`training_data` (the ``train``/``val`` splits from the cache,
a file, or a mixture of noise levels, one per sequence: :func:`noise_level_mixture`) and
:func:`inference_data` (the noisy evaluation set of one sigma).
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from .data import (
    FORMAT_VERSION,
    DatasetError,
    TrajectoryDataset,
    check_positive_int,
    check_sigma,
    load_dataset,
    save_dataset,
    split_ranges,
)
from .atomic import file_lock
from .config import DatasetConfig, EvalConfig
from .system import System

__all__ = [
    "make_dataset",
    "dataset_path",
    "load_or_generate",
    "training_data",
    "noise_level_mixture",
    "inference_data",
]

log = logging.getLogger(__name__)

INFERENCE = "inference"
DEFAULT_SPLITS = {"train": 0.8, "val": 0.1, "test": 0.1}


def _as_config(cfg: Any) -> DatasetConfig:
    if isinstance(cfg, DatasetConfig):
        return cfg
    from omegaconf import DictConfig, OmegaConf

    if isinstance(cfg, (dict, DictConfig)):
        merged = OmegaConf.merge(OmegaConf.structured(DatasetConfig), cfg)
        return OmegaConf.to_object(merged)  # type: ignore[return-value]
    raise TypeError(f"expected a DatasetConfig, dict or DictConfig, got {type(cfg).__name__}.")


def _request(cfg: DatasetConfig) -> dict:
    """The file request of a config, validated; raises before any work."""
    splits = dict(DEFAULT_SPLITS if cfg.splits is None else cfg.splits)
    request = dict(
        num_sequences=cfg.num_sequences,
        length=cfg.length,
        sigma=cfg.sigma,
        seed=cfg.seed,
        splits=splits,
    )
    _check_request(**request)
    return request


#: The most steps one dataset may hold (``num_sequences * length``): 2e7 steps of the rigid
#: body are 2.9 GB of float64 states; the paper's largest set holds 2e6.
MAX_STEPS = 20_000_000


def _check_request(num_sequences, length, sigma, seed, splits) -> None:
    check_positive_int("num_sequences", num_sequences)
    check_positive_int("length", length)
    if num_sequences * length > MAX_STEPS:
        raise DatasetError(
            f"num_sequences x length = {num_sequences} x {length} is more than {MAX_STEPS:.0e} "
            "steps (manifold_nets.datasets.MAX_STEPS); ask for fewer or shorter sequences (or "
            "stream them: train.stream=true draws fresh ones every epoch)."
        )
    check_sigma(sigma)
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**63:
        raise DatasetError(f"seed must be an integer in [0, 2**63), got {seed!r}.")
    split_ranges(num_sequences, splits)


def _request_config(system: System, num_sequences, length, sigma, seed, splits) -> dict:
    """Everything that determines a file's contents (hashed for the cache key)."""
    return {
        "format_version": FORMAT_VERSION,
        "system": {
            "name": system.name,
            "target": f"{type(system).__module__}.{type(system).__qualname__}",
            "config": system.config(),
        },
        "num_sequences": int(num_sequences),
        "length": int(length),
        "sigma": float(sigma),
        "seed": int(seed),
        "splits": {k: float(v) for k, v in splits.items()},
    }


def _hash(config: dict) -> str:
    text = json.dumps(config, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()


def make_dataset(
    system: System,
    num_sequences: int,
    length: int,
    sigma: float = 0.0,
    seed: int = 0,
    splits: dict[str, float] | None = None,
    show_progress: bool = False,
) -> TrajectoryDataset:
    """Simulates one dataset from ``seed`` (no cache, no file); same arguments, same bytes.

    ``splits`` (default: everything in one split ``all``) are recorded in ``meta['splits']`` as
    contiguous ``[start, stop]`` ranges; ``ds.split("train")`` returns one. ``meta`` also holds
    the seed, the resolved ``config`` and its ``config_hash``.
    """
    _check_system(system)
    splits = {"all": 1.0} if splits is None else dict(splits)
    _check_request(num_sequences, length, sigma, seed, splits)
    config = _request_config(system, num_sequences, length, sigma, seed, splits)
    generator = torch.Generator().manual_seed(int(seed))
    ds = system.simulate(num_sequences, length, sigma, generator, show_progress=show_progress)
    ds.meta.update(
        seed=int(seed),
        splits=split_ranges(num_sequences, splits),
        config=config,
        config_hash=_hash(config),
        torch_version=torch.__version__,
    )
    return ds


def dataset_path(
    system: System, cache_dir: str | Path, num_sequences, length, sigma, seed, splits
) -> Path:
    """The cache file of a request: ``<cache_dir>/<system>_<N>x<T>_sigma<s>_seed<k>_<hash>.npz``."""
    config = _request_config(system, num_sequences, length, sigma, seed, splits)
    tag = f"{system.name}_{num_sequences}x{length}_sigma{float(sigma):g}_seed{seed}"
    return Path(cache_dir) / f"{tag}_{_hash(config)[:12]}.npz"


def load_or_generate(
    system: System,
    cfg: DatasetConfig | dict | Any,
    cache_dir: str | Path | None = None,
    *,
    cache: bool = True,
) -> dict[str, TrajectoryDataset]:
    """The splits of ``cfg``'s file by name, read from the cache or generated and cached.

    Returns ``{split: TrajectoryDataset}`` (``train``, ``val``, ``test`` by default).
    ``cache_dir`` overrides ``cfg.cache_dir``. A cached file is validated on load (format
    version, NaN/Inf, states on ``system.group``, config hash); ``cfg.regenerate`` rewrites it.
    With ``cache=False`` a cached file is still read, but a missing one is generated in memory
    and not written (the same data: the file's name and contents depend only on ``cfg``).
    All of ``cfg`` is checked before any work.
    """
    cfg = _as_config(cfg)
    _check_system(system)
    request = _request(cfg)
    path = dataset_path(system, Path(cfg.cache_dir if cache_dir is None else cache_dir), **request)
    expected = _hash(_request_config(system, **request))
    if not cache and not (path.exists() and not cfg.regenerate):
        ds, made = _generate(system, cfg, request, path)
        log.info("generated %d x %d at sigma %g in memory (not cached) in %.2f s",
                 request["num_sequences"], request["length"], request["sigma"], made)
        return ds.splits()
    with file_lock(path):  # parallel jobs wanting this file: one generates, the others read it
        ds = _read_or_make(system, cfg, request, path, expected)
    ds.meta["path"] = str(path)
    return ds.splits()


def _read_or_make(system: System, cfg: DatasetConfig, request: dict, path: Path, expected: str):
    """The dataset of ``path`` if cached (and of the expected config), else made and written."""
    if path.exists() and not cfg.regenerate:
        ds = load_dataset(path, group=system.group)
        if ds.meta.get("config_hash") != expected:
            found = str(ds.meta.get("config_hash"))[:12]
            raise DatasetError(
                f"{path} was made from another config (hash {found}..., expected "
                f"{expected[:12]}...); delete it or set regenerate=true."
            )
        log.info("reusing %s", path)
    else:
        start = time.perf_counter()
        ds, made = _generate(system, cfg, request, path)
        save_dataset(ds, path)
        log.info(
            "generated %s (%d x %d, sigma=%g) in %.2f s, total %.2f s",
            path, request["num_sequences"], request["length"], request["sigma"], made,
            time.perf_counter() - start,
        )
    return ds


def _generate(system: System, cfg: DatasetConfig, request: dict, path: Path):
    """The dataset of ``request`` simulated and checked (for ``path``, not written), and the
    seconds the simulation took."""
    start = time.perf_counter()
    ds = make_dataset(system, **request, show_progress=cfg.progress)
    made = time.perf_counter() - start
    _check_generated(system, ds, path)
    ds.validate(system.group, where=f"the data generated for {path}")
    return ds, made


def _check_generated(system: System, ds: TrajectoryDataset, path: Path) -> None:
    """Raises :class:`DatasetError` naming the system when its simulation made NaN or Inf
    (before anything is written: the file at ``path`` is not to blame, the parameters are)."""
    for name in ("states", "measurements", "inputs"):
        t = getattr(ds, name)
        finite = torch.isfinite(t)
        if not bool(finite.all()):
            seq = int((~finite).flatten(1).any(1).nonzero()[0, 0])
            raise DatasetError(
                f"the system {system!r} generated non-finite values (NaN/Inf) in its {name} "
                f"({int((~finite).sum())} of them; the first in sequence {seq}); nothing was "
                f"written to {path}. Check the system's parameters (system.* in the config): a "
                "step length or a range too large overflows the simulation."
            )


def training_data(
    system: System,
    dataset: DatasetConfig,
    *,
    data_file: str | Path | None = None,
    noise_levels: Sequence[float] = (),
    cache_dir: str | Path | None = None,
    cache: bool = True,
) -> dict[str, TrajectoryDataset]:
    """The splits to train on (at least ``train`` and ``val``): read from ``data_file`` (a file
    of :func:`~manifold_nets.data.save_dataset`), a :func:`noise_level_mixture` of ``dataset``
    at ``noise_levels``, or ``dataset`` itself from the cache (``cache=False``: a missing file is
    generated in memory, not written; :func:`load_or_generate`)."""
    if data_file is not None:
        if noise_levels:
            raise ValueError(
                "noise_levels generates the data per level; it cannot be used with a data_file."
            )
        path = Path(data_file)
        if not path.is_file():
            raise FileNotFoundError(
                f"data_file={str(data_file)!r}: no dataset at {path}. Generate one (or drop "
                "data_file to generate from the dataset config)."
            )
        parts = load_dataset(path, group=system.group).splits()
    elif noise_levels:
        parts = noise_level_mixture(system, dataset, noise_levels, cache_dir=cache_dir, cache=cache)
    else:
        parts = load_or_generate(system, dataset, cache_dir=cache_dir, cache=cache)
    missing = [s for s in ("train", "val") if s not in parts]
    if missing:
        raise DatasetError(
            f"training needs 'train' and 'val' splits; the data has {sorted(parts)}. Set the "
            "splits, e.g. {train: 0.8, val: 0.1, test: 0.1}."
        )
    return parts


def noise_level_mixture(
    system: System,
    dataset: DatasetConfig,
    levels: Sequence[float],
    cache_dir: str | Path | None = None,
    cache: bool = True,
) -> dict[str, TrajectoryDataset]:
    """Every split of ``dataset`` with each sequence's measurements taken from one noise level of
    ``levels``, drawn at random (seeded by ``dataset.seed``).

    The data are generated (or read from the cache) once per level with the same seed, so the
    trajectories agree and only the measurement noise differs (``cache``: as for
    :func:`load_or_generate`).
    """
    levels = [float(s) for s in levels]
    gen = torch.Generator().manual_seed(int(dataset.seed))
    choice: dict[str, torch.Tensor] = {}
    out: dict[str, TrajectoryDataset] = {}
    for i, sigma in enumerate(levels):
        parts = load_or_generate(
            system, replace(dataset, sigma=sigma), cache_dir=cache_dir, cache=cache
        )
        for name, part in parts.items():
            if name not in choice:
                choice[name] = torch.randint(len(levels), (len(part),), generator=gen)
                meta = {**part.meta, "sigma": None, "noise_levels": levels}
                out[name] = TrajectoryDataset(
                    part.states, part.measurements.clone(), part.inputs, meta
                )
            elif not torch.equal(out[name].states, part.states):
                raise DatasetError(
                    f"the {name} split at sigma {sigma} has other trajectories than at sigma "
                    f"{levels[0]}; the system must draw its noise after the trajectories."
                )
            pick = choice[name] == i
            out[name].measurements[pick] = part.measurements[pick]
    log.info("training data: noise levels %s, one per sequence", levels)
    return out


def inference_data(
    system: System,
    dataset: DatasetConfig,
    evaluation: EvalConfig,
    sigma: float,
    cache_dir: str | Path | None = None,
) -> TrajectoryDataset:
    """The inference set at ``sigma``: ``evaluation.num_sequences`` x ``evaluation.length`` from
    ``evaluation.seed`` (``dataset`` gives the cache folder and the progress setting)."""
    cfg = replace(
        dataset,
        name="inference",
        num_sequences=evaluation.num_sequences,
        length=evaluation.length,
        sigma=float(sigma),
        seed=evaluation.seed,
        splits={INFERENCE: 1.0},
        regenerate=False,
    )
    return load_or_generate(system, cfg, cache_dir=cache_dir)[INFERENCE]


def _check_system(system) -> None:
    if not isinstance(system, System):
        raise TypeError(
            f"system must be a manifold_nets.System, got {type(system).__name__}."
        )
