"""Resource bombs in a run folder's config: each is refused quickly with an ``ArtefactError``
naming the file, never expanded, walked or allowed to crash the reader."""

from __future__ import annotations

import shutil
import time

import pytest
import torch

from manifold_nets import load_observer
from manifold_nets.checkpoint import load_checkpoint, save_checkpoint
from manifold_nets.loading import ArtefactError
from manifold_nets.plugins import zoo_path


@pytest.fixture
def run(tmp_path):
    folder = tmp_path / "run"
    shutil.copytree(zoo_path("rigid_body/paper"), folder)
    return folder


def _laughs(levels=9) -> str:
    lines = ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for i in range(1, levels):
        refs = ", ".join([f"*a{i - 1}"] * 9)
        lines.append(f"a{i}: &a{i} [{refs}]")
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("name, text, match", [
    ("billion laughs", _laughs(), "alias"),
    ("deep nesting", "x: " + "[" * 5000 + "]" * 5000 + "\n", "deeper than"),
    ("a 5000-digit integer", "x: " + "9" * 5000 + "\n", "plain YAML"),
    ("a 4000-digit integer", "x: " + "9" * 4000 + "\n", "bits"),
])
def test_a_yaml_bomb_is_refused_quickly(run, name, text, match):
    (run / "config.yaml").write_text((run / "config.yaml").read_text() + text)
    t0 = time.perf_counter()
    with pytest.raises(ArtefactError, match=match):
        load_observer(run)
    assert time.perf_counter() - t0 < 5, name


def test_a_config_that_is_not_utf8_is_refused(run):
    (run / "config.yaml").write_bytes(b"system: \xff\xfe\n")
    with pytest.raises(ArtefactError, match="not UTF-8"):
        load_observer(run)


def test_a_checkpoint_config_shared_two_to_the_forty_ways_is_refused_quickly(run, tmp_path):
    ckpt = load_checkpoint(run / "checkpoints" / "best.pt")
    node: list = ["x"]
    for _ in range(20):
        node = [node] * 4  # 4^20 = 2^40 paths, 21 objects, 21 levels
    config = dict(ckpt["config"], bomb=node)
    save_checkpoint(tmp_path / "bomb.pt", {**{k: v for k, v in ckpt.items() if k != "format"},
                                            "config": config})
    t0 = time.perf_counter()
    with pytest.raises(ArtefactError, match="more than 100000 nodes"):
        load_observer(tmp_path / "bomb.pt")
    assert time.perf_counter() - t0 < 5
    assert torch.is_tensor(ckpt["model"]["core.head.bias"])  # the original is untouched
