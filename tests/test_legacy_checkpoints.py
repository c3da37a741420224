"""Checkpoints of the first format (flat ``model.*`` keys, ``manifold_nets.checkpoint/1``) still
load: into the observer built from their config (the flat keys translated into pieces), checked
against the first format's signature, with the robust weights renamed; their estimates are the
ones recorded when they were written (tests/fixtures/legacy/make_legacy.py)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from manifold_nets import load_observer
from manifold_nets.builders import build_observer, model_blocks
from manifold_nets.checkpoint import CheckpointError, load_weights
from manifold_nets.config import ModelConfig
from manifold_nets.loading import build_system_safely

LEGACY = Path(__file__).parent / "fixtures" / "legacy"


#: The steps compared: gain_decay's fixture (random weights) is unstable, its estimates growing
#: tenfold every ten steps and a last-bit difference tenfold every five: beyond step 25 the
#: rollouts of two CPUs part (measured: 2.6e-6 of (1 + |x|) at step 25, 70 % at step 60).
STEPS = {"all_pieces": 60, "gain_decay": 25}


@pytest.mark.parametrize("name", ["all_pieces", "gain_decay"])
def test_a_first_format_checkpoint_loads_and_reproduces_its_estimates(name):
    """On the CPU that recorded them the estimates were reproduced to 1e-10; another CPU's float32
    arithmetic moves them by up to 4.8e-6 of (1 + |x|) (AMD EPYC), so: within 1e-5 of that."""
    observer, _, _ = load_observer(LEGACY / name)
    ref = np.load(LEGACY / name / "reference.npz")
    with torch.no_grad():
        est = observer(torch.from_numpy(ref["measurements"])).flatten(2)
    n = STEPS[name] + 1
    np.testing.assert_allclose(est.numpy()[:, :n], ref["rollout"][:, :n], rtol=1e-5, atol=1e-5)


def test_a_first_format_checkpoint_refuses_another_observer():
    raw = yaml.safe_load((LEGACY / "all_pieces" / "config.yaml").read_text())
    system = build_system_safely(raw["system"])
    model = ModelConfig(hidden_size=8, measurement={"factors": {"R": [0, 9], "p": [9, 12]}},
                        prior={"type": "system"})
    obs = build_observer(system.group, 18, 0, model, system=system)
    with pytest.raises(CheckpointError, match="another model"):
        load_weights(obs, LEGACY / "all_pieces")


def test_flat_keys_translate_into_blocks_with_a_warning_that_shows_them():
    raw = yaml.safe_load((LEGACY / "all_pieces" / "config.yaml").read_text())["model"]
    with pytest.warns(FutureWarning, match="type: centred"):
        blocks = model_blocks(raw)
    assert blocks["head"] == {"type": "centred", "c": 0.85, "ramp": 50,
                              "factors": {"b_omega": 0.97, "b_v": 0.99}}
    assert [f["type"] for f in blocks["features"]] == [
        "embedding", "readings", "innovation", "framed_innovation"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert model_blocks({"hidden_size": 8})["features"] == [
            {"type": "embedding"}, {"type": "readings"}]


@pytest.mark.parametrize("key,value", [("clock", [10.0]), ("prior_drive", True)])
def test_a_removed_option_is_refused_with_the_reason(key, value):
    with pytest.raises(ValueError, match=f"model.{key} was removed"):
        model_blocks({key: value})


def test_flat_keys_and_blocks_together_are_refused():
    with pytest.raises(ValueError, match=r"model.centering -> model.head=\{type: centred"):
        model_blocks({"centering": 0.5, "head": {"type": "plain"}})
