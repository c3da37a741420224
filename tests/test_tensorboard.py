"""``train.tensorboard=true``: the run writes TensorBoard event files with the expected tags."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from manifold_nets import tensorboard_log
from manifold_nets.cli.train import run
from manifold_nets.tensorboard_log import EPOCH_TAGS, eval_tag

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def _tiny(tmp_path: Path, *more: str):
    cache = f"dataset.cache_dir={tmp_path / 'data'}"
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose(
            "train",
            overrides=["experiment=default", "debug=tiny", cache, "eval.plots=false", *more],
        )


def test_a_tiny_run_writes_losses_learning_rate_and_metrics(tmp_path):
    if importlib.util.find_spec("tensorboard") is None:
        pytest.skip("tensorboard is not installed: pip install 'manifold_nets[logging]'")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    m = run(_tiny(tmp_path, "train.tensorboard=true", "train.epochs=2"), tmp_path / "run")
    board = tmp_path / "run" / "tensorboard"
    assert list(board.glob("events.out.tfevents.*"))
    acc = EventAccumulator(str(board))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    per_epoch = set(EPOCH_TAGS.values())
    evals = {eval_tag(0.1, c) for c in ("R est", "R meas", "R reduction %", "membership max")}
    assert per_epoch | evals | {"loss/test", "eval/sigma0.1/us_per_step"} <= tags, tags
    assert [e.step for e in acc.Scalars("loss/val")] == [0, 1, 2]
    assert [e.step for e in acc.Scalars("loss/train")] == [1, 2]  # none before any step
    assert acc.Scalars("loss/best_val")[-1].value == pytest.approx(m["best_val_loss"], rel=1e-6)
    (r_est,) = acc.Scalars(eval_tag(0.1, "R est"))
    assert r_est.step == m["best_epoch"] and r_est.value == pytest.approx(m["table"][0]["R est"])


def test_without_tensorboard_the_flag_fails_before_any_work(tmp_path, monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(
        tensorboard_log.importlib.util, "find_spec",
        lambda name, *a: None if name == "tensorboard" else real(name, *a),
    )  # fmt: skip
    with pytest.raises(ImportError, match=r"pip install 'manifold_nets\[logging\]'"):
        run(_tiny(tmp_path, "train.tensorboard=true"), tmp_path / "run")
    assert not (tmp_path / "run").exists() and not (tmp_path / "data").exists()
