"""The trial split of the BROAD experiments: which trials train, validate and test.

``configs/broad/trials.yaml`` (installed as ``manifold_nets_configs/broad/trials.yaml``) names
the trials, without ``.mat``, under ``train``, ``val`` and ``test``; a file of the same form can
replace it. The test trials are never used for training or model selection.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import yaml

__all__ = ["SPLITS", "default_split_file", "load_split"]

SPLITS = ("train", "val", "test")


def default_split_file() -> Path:
    return Path(str(resources.files("manifold_nets_configs") / "broad" / "trials.yaml"))


def load_split(path: str | Path | None = None) -> dict[str, list[str]]:
    """``{train: [...], val: [...], test: [...]}`` trial names from ``path`` (default the shipped
    split), checked: plain YAML, three lists of names, no trial in two splits."""
    path = Path(path) if path is not None else default_split_file()
    try:
        raw = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        raise ValueError(f"cannot read the trial split {path}: {err}") from None
    if not isinstance(raw, dict) or any(not isinstance(raw.get(s), list) for s in SPLITS):
        raise ValueError(
            f"{path} must map each of {list(SPLITS)} to a list of trial names "
            "(e.g. train: [01_undisturbed_slow_rotation_A, ...])."
        )
    split = {s: [str(n).removesuffix(".mat") for n in raw[s]] for s in SPLITS}
    seen: dict[str, str] = {}
    for s, names in split.items():
        for name in names:
            if name in seen:
                raise ValueError(
                    f"{path}: trial {name!r} is in both {seen[name]!r} and {s!r}; a test trial "
                    "must never be trained or validated on."
                )
            seen[name] = s
    return split
