"""Datasets from configs: hydra composition and overrides, the cache keyed by the config hash,
validation before work, and the command ``python -m manifold_nets.cli.generate``."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from hydra.utils import instantiate
from omegaconf import OmegaConf

from manifold_nets_examples.rigid_body import RigidBody
from groups import SO3
from manifold_nets import datasets as gen_mod
from manifold_nets.system import System
from manifold_nets.data import DatasetError, load_dataset
from manifold_nets.config import DatasetConfig
from manifold_nets.datasets import dataset_path, load_or_generate

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = str(ROOT / "configs")


def composed(*overrides: str):
    with initialize_config_dir(config_dir=CONFIGS, version_base="1.3"):
        return compose("generate", overrides=list(overrides))


def tiny(tmp_path, **kw) -> DatasetConfig:
    base = dict(num_sequences=10, length=4, sigma=0.0, seed=0, cache_dir=str(tmp_path))
    return DatasetConfig(**(base | {"progress": False} | kw))


def test_paper_configs_compose():
    cfg = composed("system=rigid_body", "dataset=paper_train")
    d = cfg.dataset
    assert (d.num_sequences, d.length, d.sigma) == (20000, 100, 0.0)
    assert dict(d.splits) == {"train": 0.8, "val": 0.1, "test": 0.1}
    cfg = composed("dataset=paper_inference", "dataset.sigma=0.3")
    assert (cfg.dataset.num_sequences, cfg.dataset.length, cfg.dataset.sigma) == (1000, 1000, 0.3)
    assert dict(cfg.dataset.splits) == {"inference": 1.0}
    cfg = composed()  # defaults: the rigid body and the small dataset
    assert cfg.dataset.name == "small" and "inference" not in cfg.dataset
    system = instantiate(cfg.system)
    assert isinstance(system, RigidBody) and system.dt == 0.1 and system.integrator == "exact"
    assert isinstance(OmegaConf.to_object(cfg.dataset), DatasetConfig)


def test_overrides_from_the_command_line():
    cfg = composed(
        "dataset.num_sequences=50", "dataset.length=7", "system.dt=0.05",
        "system.integrator=rk45", "dataset.sigma=0.4", "~dataset.splits.test",
        "dataset.splits.train=0.9",
    )
    assert (cfg.dataset.num_sequences, cfg.dataset.length, cfg.system.dt) == (50, 7, 0.05)
    assert cfg.dataset.sigma == 0.4
    assert dict(cfg.dataset.splits) == {"train": 0.9, "val": 0.1}
    assert instantiate(cfg.system).integrator == "rk45"


@pytest.mark.parametrize(
    "override", ["dataset.sigmaa=0.3", "dataset.num_sequences=abc", "dataset.inference.length=3",
                 "dataset.seed=0.5", "system.dtt=0.2"]
)
def test_typos_and_wrong_types_fail_when_composing(override):
    with pytest.raises(ConfigCompositionException):
        composed(override)


def test_cache_reuses_the_file_and_regenerates_on_change(tmp_path, monkeypatch):
    body = RigidBody()
    cfg = tiny(tmp_path)
    parts = load_or_generate(body, cfg)
    assert list(parts) == ["train", "val", "test"]
    assert [len(parts[k]) for k in parts] == [8, 1, 1]
    files = sorted(tmp_path.glob("*.npz"))
    assert len(files) == 1
    stamps = {f: f.stat().st_mtime_ns for f in files}

    def boom(*a, **k):
        raise AssertionError("regenerated although the cache holds the file")

    monkeypatch.setattr(gen_mod, "make_dataset", boom)
    again = load_or_generate(body, cfg)
    assert all(again[k] == parts[k] for k in parts)
    assert {f: f.stat().st_mtime_ns for f in files} == stamps
    monkeypatch.undo()
    load_or_generate(body, tiny(tmp_path, sigma=0.1))  # changed config: a new file
    load_or_generate(RigidBody(dt=0.15), tiny(tmp_path))  # changed system: a new file
    assert len(list(tmp_path.glob("*.npz"))) == 3
    assert not list(tmp_path.glob(".*tmp"))


def test_without_cache_the_same_data_is_made_in_memory_and_a_cached_file_still_read(
    tmp_path, monkeypatch
):
    """``cache=False`` (a streamed run's validation data): nothing is written, the data are the
    cached ones bit for bit, and a file already there is read, not remade."""
    body = RigidBody()
    fresh = load_or_generate(body, tiny(tmp_path / "a"), cache=False)
    assert not (tmp_path / "a").exists() or not list((tmp_path / "a").iterdir())
    cached = load_or_generate(body, tiny(tmp_path / "b"))
    assert all(torch.equal(fresh[k].measurements, cached[k].measurements) for k in cached)
    assert all(torch.equal(fresh[k].states, cached[k].states) for k in cached)

    def boom(*a, **k):
        raise AssertionError("regenerated although the cache holds the file")

    monkeypatch.setattr(gen_mod, "make_dataset", boom)
    again = load_or_generate(body, tiny(tmp_path / "b"), cache=False)
    assert all(again[k] == cached[k] for k in cached)


def test_regenerate_rewrites_and_hash_mismatch_is_refused(tmp_path):
    body = RigidBody()
    cfg = tiny(tmp_path)
    load_or_generate(body, cfg)
    (path,) = tmp_path.glob("*.npz")
    path.write_bytes(b"garbage")
    with pytest.raises(DatasetError, match="delete it"):
        load_or_generate(body, cfg)
    load_or_generate(body, tiny(tmp_path, regenerate=True))
    assert load_dataset(path).meta["config_hash"]
    other = dataset_path(body, tmp_path, 10, 4, 0.5, 0, {"train": 0.8, "val": 0.1, "test": 0.1})
    path.rename(other)  # a file under another config's name
    with pytest.raises(DatasetError, match="another config"):
        load_or_generate(body, tiny(tmp_path, sigma=0.5))


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(sigma=-0.2), "sigma"),
        (dict(num_sequences=0), "num_sequences"),
        (dict(length=-5), "length"),
        (dict(splits={"train": 0.7, "val": 0.1}), "sum to"),
    ],
)
def test_bad_configs_fail_before_any_work(tmp_path, kw, match):
    with pytest.raises(DatasetError, match=match):
        load_or_generate(RigidBody(), tiny(tmp_path, **kw))
    assert not list(tmp_path.iterdir())


def test_plain_dict_config(tmp_path):
    parts = load_or_generate(RigidBody(), {"num_sequences": 4, "length": 3, "splits": {"all": 1.0},
                                           "cache_dir": str(tmp_path), "progress": False})
    assert list(parts) == ["all"] and len(parts["all"]) == 4
    with pytest.raises(Exception, match="sigmaa"):
        load_or_generate(RigidBody(), {"sigmaa": 0.1, "cache_dir": str(tmp_path)})


def test_command_line(tmp_path):
    """``python -m manifold_nets.cli.generate`` from another directory: files land in its data/."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    args = [
        sys.executable, "-m", "manifold_nets.cli.generate", "dataset.num_sequences=10",
        "dataset.length=4", f"hydra.run.dir={tmp_path / 'run'}",
    ]
    out = subprocess.run(args, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    files = sorted((tmp_path / "data").glob("rigid_body_*.npz"))
    assert len(files) == 1 and "train" in out.stdout
    # the same config in this process gives the same bytes
    cfg = tiny(tmp_path / "here")
    load_or_generate(RigidBody(), cfg)
    here = sorted((tmp_path / "here").glob("*.npz"))
    assert [f.name for f in here] == [f.name for f in files]

    def digest(p):
        return hashlib.sha256(p.read_bytes()).hexdigest()

    assert [digest(f) for f in here] == [digest(f) for f in files]


def test_command_checks_the_config_before_any_work(tmp_path):
    from manifold_nets.cli.generate import generate

    cfg = composed("dataset.sigma=-1", f"dataset.cache_dir={tmp_path}")
    with pytest.raises(DatasetError, match="sigma"):
        generate(cfg)
    assert not list(tmp_path.iterdir())


def test_loaded_data_feed_float32_training(tmp_path):
    parts = load_or_generate(RigidBody(), tiny(tmp_path))
    train = parts["train"].to(torch.float32)
    assert train.states.dtype == torch.float32 and train.meta["split"] == "train"


class SpinningTop(System):
    """Another system, defined outside the library: a rotation driven by a known input rate."""

    name = "spinning_top"
    measurement_dim = 9
    input_dim = drive_dim = 3
    noise_dim = 3
    dt = 0.05

    def __init__(self):
        self.group = SO3()

    def config(self):
        return {"dt": self.dt}

    def sample_initial_state(self, num_sequences, generator):
        return self.group.random((num_sequences,), generator=generator, dtype=torch.float64)

    def sample_drive(self, num_sequences, length, generator):
        return torch.randn(num_sequences, length, 3, generator=generator, dtype=torch.float64)

    def step(self, x, drive, dt=None):
        return self.group.rplus(x, drive * (self.dt if dt is None else dt))

    def measure(self, x, drive, noise=None):
        y = x if noise is None else self.group.rplus(x, noise)
        return self.group.embed(y)


def test_any_system_plugs_into_the_same_machinery(tmp_path):
    top = SpinningTop()
    parts = load_or_generate(top, tiny(tmp_path, sigma=0.1))
    train = parts["train"]
    assert train.states.shape == (8, 5, 3, 3) and train.inputs.shape == (8, 4, 3)
    assert train.meta["system"] == "spinning_top"
    top.group.check_member(train.states)
    # the default rollout loops step; the default inputs are the drive
    rebuilt = train.states[:, 0]
    for k in range(4):
        rebuilt = top.step(rebuilt, train.inputs[:, k])
    torch.testing.assert_close(rebuilt, train.states[:, -1])
    errors = top.metrics(train.states, train)
    assert set(errors) == {"x"} and float(errors["x"].max()) == 0.0
    (path,) = [p for p in tmp_path.glob("spinning_top_*.npz")]
    assert load_dataset(path, group=top.group).meta["config"]["system"]["target"].endswith(
        "SpinningTop"
    )
