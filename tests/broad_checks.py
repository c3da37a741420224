"""Shared test helpers for the BROAD commands: a split file over copies of the committed excerpt
(tests/fixtures/broad/, 2000 samples of trial 01, CC-BY-4.0, see ATTRIBUTION.md)."""

from __future__ import annotations

import shutil
from pathlib import Path

import yaml

FIXTURE = Path(__file__).parent / "fixtures" / "broad" / "excerpt.mat"


def tiny_split(folder: Path) -> tuple[Path, Path]:
    """The excerpt copied as trials ``tr``, ``va`` and ``te`` into ``folder/mat`` and a split file
    ``folder/trials.yaml`` naming one each for training, validation and test: ``(data, split)``."""
    data = folder / "mat"
    data.mkdir()
    for name in ("tr", "va", "te"):
        shutil.copyfile(FIXTURE, data / f"{name}.mat")
    split = folder / "trials.yaml"
    split.write_text(yaml.safe_dump({"data_dir": str(data),
                                     "splits": {"train": ["tr"], "val": ["va"], "test": ["te"]}}))
    return data, split
