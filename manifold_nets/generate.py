"""Datasets from a config: make them, cache them by a hash of the config, and the hydra command.

Plain Python (no hydra needed)::

    from examples.rigid_body import RigidBody
    from manifold_nets.generate import DatasetConfig, load_or_generate, make_dataset

    ds = make_dataset(RigidBody(), num_sequences=100, length=50, sigma=0.1, seed=0)
    parts = load_or_generate(RigidBody(), DatasetConfig(num_sequences=2000, length=50))
    parts["train"], parts["val"], parts["test"]          # TrajectoryDataset each

From the command line (configs in ``configs/generate.yaml``, ``configs/system/``,
``configs/dataset/``)::

    python -m manifold_nets.generate system=rigid_body dataset=paper_train
    python -m manifold_nets.generate dataset=paper_inference dataset.sigma=0.3
    python -m manifold_nets.generate -m dataset=paper_inference dataset.sigma=0.1,0.2,0.3,0.4,0.5

One :class:`DatasetConfig` describes one file (``num_sequences`` x ``length`` at ``sigma`` from
``seed``, cut into contiguous ``splits``) and, optionally, a second ``inference`` file. A file
is named by the system, sizes and a hash of everything that determines its contents (the
system's ``config()``, sizes, sigma, seed, splits, format version): the same config reuses the
file, a changed one writes a new file. ``DatasetConfig`` is a structured config registered in
hydra's ConfigStore as ``dataset/dataset_schema``, so a misspelt key fails when composing.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

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
from .system import System

__all__ = [
    "DatasetConfig",
    "InferenceConfig",
    "make_dataset",
    "load_or_generate",
    "dataset_path",
    "register_configs",
]

log = logging.getLogger(__name__)

INFERENCE = "inference"
DEFAULT_SPLITS = {"train": 0.8, "val": 0.1, "test": 0.1}


@dataclass
class InferenceConfig:
    """A second, noisy file of long sequences for evaluation (the paper's inference set)."""

    num_sequences: int = 100
    length: int = 200
    sigma: float = 0.1
    seed: int = 1


@dataclass
class DatasetConfig:
    """One dataset file (and optionally an inference file); the schema of ``configs/dataset/``."""

    #: A label for logs; not part of the cache key.
    name: str = "custom"
    num_sequences: int = 2000
    length: int = 50
    #: Standard deviation of every measurement noise component (0: noise-free).
    sigma: float = 0.0
    seed: int = 0
    #: Fractions of the sequences, in order, as contiguous ranges; must sum to 1.
    #: ``None`` means ``{train: 0.8, val: 0.1, test: 0.1}``. (A command-line dict override merges
    #: into the existing one: drop a split with ``~dataset.splits.test``.)
    splits: Optional[dict[str, float]] = None
    inference: Optional[InferenceConfig] = None
    #: Where the files go; relative paths are taken from the directory the command ran in.
    cache_dir: str = "data"
    #: Write the files again even when a cached file exists.
    regenerate: bool = False
    #: Show a progress bar (only on a terminal).
    progress: bool = True


def _as_config(cfg: Any) -> DatasetConfig:
    if isinstance(cfg, DatasetConfig):
        return cfg
    from omegaconf import DictConfig, OmegaConf

    if isinstance(cfg, (dict, DictConfig)):
        merged = OmegaConf.merge(OmegaConf.structured(DatasetConfig), cfg)
        return OmegaConf.to_object(merged)  # type: ignore[return-value]
    raise TypeError(f"expected a DatasetConfig, dict or DictConfig, got {type(cfg).__name__}.")


def _files(cfg: DatasetConfig) -> list[dict]:
    """The per-file requests of a config, validated; raises before any work."""
    splits = dict(DEFAULT_SPLITS if cfg.splits is None else cfg.splits)
    if cfg.inference is not None and INFERENCE in splits:
        raise DatasetError(
            f"a split may not be called {INFERENCE!r} when the config also has an inference file."
        )
    files = [
        dict(num_sequences=cfg.num_sequences, length=cfg.length, sigma=cfg.sigma,
             seed=cfg.seed, splits=splits)
    ]
    if cfg.inference is not None:
        inf = cfg.inference
        files.append(
            dict(num_sequences=inf.num_sequences, length=inf.length, sigma=inf.sigma,
                 seed=inf.seed, splits={INFERENCE: 1.0})
        )
    for f in files:
        _check_request(**f)
    return files


def _check_request(num_sequences, length, sigma, seed, splits) -> None:
    check_positive_int("num_sequences", num_sequences)
    check_positive_int("length", length)
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
    if not isinstance(system, System):
        raise TypeError(
            f"system must be a manifold_nets.system.System, got {type(system).__name__}."
        )
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
    system: System, cfg: DatasetConfig | dict | Any, cache_dir: str | Path | None = None
) -> dict[str, TrajectoryDataset]:
    """The datasets of ``cfg`` by split name, read from the cache or generated and cached.

    Returns ``{split: TrajectoryDataset}`` for the main file's splits (``train``, ``val``,
    ``test`` by default) plus ``inference`` when ``cfg.inference`` is set. ``cache_dir``
    overrides ``cfg.cache_dir``. A cached file is validated on load (format version, NaN/Inf,
    states on ``system.group``, config hash); ``cfg.regenerate`` rewrites it. All of ``cfg`` is
    checked before any work.
    """
    cfg = _as_config(cfg)
    if not isinstance(system, System):
        raise TypeError(
            f"system must be a manifold_nets.system.System, got {type(system).__name__}."
        )
    root = Path(cfg.cache_dir if cache_dir is None else cache_dir)
    out: dict[str, TrajectoryDataset] = {}
    for request in _files(cfg):
        path = dataset_path(system, root, **request)
        expected = _hash(_request_config(system, **request))
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
            ds = make_dataset(system, **request, show_progress=cfg.progress)
            made = time.perf_counter() - start
            ds.validate(system.group, where=str(path))
            save_dataset(ds, path)
            log.info(
                "generated %s (%d x %d, sigma=%g) in %.2f s, total %.2f s",
                path, request["num_sequences"], request["length"], request["sigma"], made,
                time.perf_counter() - start,
            )
        ds.meta["path"] = str(path)
        for name, part in ds.splits().items():
            out[name] = part
    return out


def register_configs() -> None:
    """Registers :class:`DatasetConfig` as ``dataset/dataset_schema`` in hydra's ConfigStore.

    ``configs/dataset/*.yaml`` start with ``defaults: [dataset_schema, _self_]``; call this (or
    import this module) before composing a config that uses them.
    """
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(group="dataset", name="dataset_schema", node=DatasetConfig)


register_configs()


def _main(cfg) -> None:
    from hydra.utils import instantiate, to_absolute_path
    from omegaconf import OmegaConf

    dcfg = _as_config(cfg.dataset)
    _files(dcfg)  # every check before the system is built or any work is done
    system = instantiate(cfg.system)
    parts = load_or_generate(system, dcfg, cache_dir=to_absolute_path(dcfg.cache_dir))
    for name, ds in parts.items():
        print(
            f"{name:>10}: {len(ds):6d} x {ds.length:5d} sigma={ds.meta['sigma']:g} "
            f"seed={ds.meta['seed']} <- {ds.meta['path']}"
        )
    log.debug("config:\n%s", OmegaConf.to_yaml(cfg))


def main() -> None:
    """``python -m manifold_nets.generate [overrides]`` (hydra; config root ``configs/``)."""
    import hydra

    hydra.main(version_base="1.3", config_path="../configs", config_name="generate")(_main)()


if __name__ == "__main__":
    main()
