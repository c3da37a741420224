"""Runs that start from a checkpoint, through the config: resume, fine-tuning (``train.init_from``),
``train.epochs=0``, and training on a mixture of noise levels."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import manifold_nets.config  # noqa: F401  (registers the schema)
from manifold_nets.checkpoint import CheckpointError
from manifold_nets.cli.train import run

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def _compose(*overrides: str):
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose("train", overrides=list(overrides))


def _tiny(cache: Path, *more: str) -> list[str]:
    """The tiny run of experiment=default (``configs/debug/tiny.yaml``), its data in ``cache``."""
    return ["experiment=default", "debug=tiny", f"dataset.cache_dir={cache}", *more]


def test_resume_through_the_config(tmp_path):
    cache = tmp_path / "data"
    run(_compose(*_tiny(cache, "train.epochs=1")), tmp_path / "first")
    m = run(
        _compose(*_tiny(cache, "train.epochs=2", f"train.resume={tmp_path / 'first'}")),
        tmp_path / "second",
    )
    log = json.loads((tmp_path / "second" / "log.json").read_text())
    assert [r["epoch"] for r in log] == [0, 1, 2]
    assert m["best_epoch"] in (0, 1, 2)
    ckpt = torch.load(tmp_path / "second" / "checkpoints" / "last.pt", weights_only=True)
    assert ckpt["epoch"] == 2 and ckpt["config"]["train"]["epochs"] == 2
    # other data: refused before any work (the best model would be chosen across two sets)
    for change in ("dataset.seed=3", "dataset.sigma=0.2"):
        with pytest.raises(ValueError, match=r"continues a run on its own data.*"
                                             + change.split("=")[0].replace(".", r"\.")):
            run(_compose(*_tiny(cache, "train.epochs=3", change,
                                f"train.resume={tmp_path / 'second'}")), tmp_path / "third")
        assert not (tmp_path / "third").exists()


def test_init_from_fine_tunes_a_trained_model_on_other_data(tmp_path):
    cache = tmp_path / "data"
    first = run(_compose(*_tiny(cache, "train.epochs=2")), tmp_path / "first")
    # the run starts from the first run's best weights, with a fresh optimizer and epochs
    m = run(
        _compose(*_tiny(cache, "train.lr=1e-4", f"train.init_from={tmp_path / 'first'}")),
        tmp_path / "tuned",
    )
    assert m["init_from"] == str(tmp_path / "first" / "checkpoints" / "best.pt")
    log = json.loads((tmp_path / "tuned" / "log.json").read_text())
    assert [r["epoch"] for r in log] == [0, 1] and log[1]["lr"] == 1e-4
    # epoch 0 (before any step) is the first run's best model on the same validation set (a
    # trained one: a model freshly built with the same seed would score the untrained loss)
    assert first["best_epoch"] > 0
    assert log[0]["val_loss"] == pytest.approx(first["best_val_loss"], rel=1e-6)
    # and on other data (longer sequences: what fine-tuning is for)
    run(
        _compose(*_tiny(cache, "dataset.length=12", f"train.init_from={tmp_path / 'first'}")),
        tmp_path / "longer",
    )
    with pytest.raises(CheckpointError, match="hidden_size"):  # another model
        run(
            _compose(*_tiny(cache, "model.hidden_size=6", f"train.init_from={tmp_path / 'first'}")),
            tmp_path / "other",
        )
    with pytest.raises(ValueError, match="set only one"):
        run(
            _compose(
                *_tiny(cache, f"train.init_from={tmp_path / 'first'}", f"train.resume={tmp_path}")
            ),
            tmp_path / "both",
        )
    assert not (tmp_path / "both" / "checkpoints").exists()


def test_zero_epochs_from_init_from_evaluate_its_weights_under_this_runs_config(tmp_path):
    """``train.epochs=0``: a trained model's weights, evaluated as they are under a weight-free
    setting of this run (here the step-size decay) and saved with this run's config."""
    cache = tmp_path / "data"
    run(_compose(*_tiny(cache)), tmp_path / "first")
    decay = "++model.scales=[{type:step_decay,factors:{b_v:3}}]"
    m = run(
        _compose(*_tiny(cache, "train.epochs=0", decay, f"train.init_from={tmp_path / 'first'}")),
        tmp_path / "as_is",
    )
    log = json.loads((tmp_path / "as_is" / "log.json").read_text())
    assert [r["epoch"] for r in log] == [0] and m["best_epoch"] == 0
    assert not (tmp_path / "as_is" / "checkpoints" / "last.pt").exists()
    first, as_is = (
        torch.load(tmp_path / d / "checkpoints" / "best.pt", weights_only=True)
        for d in ("first", "as_is")
    )
    assert as_is["config"]["model"]["scales"] == [{"type": "step_decay", "factors": {"b_v": 3}}]
    assert not first["config"]["model"]["scales"]
    for name, w in first["model"].items():
        assert torch.equal(as_is["model"][name], w), name
    # the decay acts: the same weights evaluate otherwise than the first run's
    row = m["table"][0]
    first_row = json.loads((tmp_path / "first" / "results" / "metrics.json").read_text())["table"][0]
    assert row["b_v est"] != first_row["b_v est"]
    # the saved folder is a checkpoint of the decayed observer: eval.checkpoint loads it as is
    again = run(_compose(*_tiny(cache, f"eval.checkpoint={tmp_path / 'as_is'}")), tmp_path / "again")
    assert again["table"][0]["b_v est"] == row["b_v est"]


def test_noise_levels_mix_measurements_per_sequence(tmp_path):
    from hydra.utils import instantiate

    from manifold_nets.datasets import training_data

    def data(*overrides):
        cfg = _compose(*_tiny(tmp_path / "data", *overrides))
        return training_data(
            instantiate(cfg.system),
            OmegaConf.to_object(cfg.dataset),
            noise_levels=list(cfg.train.noise.levels),
        )

    mixed = data("train.noise.levels=[0.0,0.3]")
    clean = data("dataset.sigma=0.0")
    noisy = data("dataset.sigma=0.3")
    for name in ("train", "val", "test"):
        m, c, n = mixed[name], clean[name], noisy[name]
        assert torch.equal(m.states, c.states)
        is_clean = (m.measurements == c.measurements).flatten(1).all(1)
        is_noisy = (m.measurements == n.measurements).flatten(1).all(1)
        assert bool((is_clean ^ is_noisy).all())  # every sequence from exactly one level
    assert 0 < int(is_clean.sum()) < len(is_clean) or len(is_clean) < 4
    assert mixed["train"].meta["noise_levels"] == [0.0, 0.3]
